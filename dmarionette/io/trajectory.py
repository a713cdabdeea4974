"""The trajectory file (NumPy ``.npz``, documented in docs/trajectory.md) and its summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dmarionette.scene.scene import Scene
from dmarionette.strings.simulate import StringTrajectory

__all__ = ["FORMAT_VERSION", "NonFiniteTrajectoryError", "TrajectoryFileError", "check_trajectory_arrays",
           "check_trajectory_finite", "first_non_finite", "read_trajectory", "summarize", "write_trajectory"]

FORMAT_VERSION = 1


class TrajectoryFileError(ValueError):
    """A trajectory file (``.npz``) that cannot be read as one: the message names the file, the
    array (or metadata key), what was found and what was expected."""


class NonFiniteTrajectoryError(RuntimeError):
    """A simulated trajectory with a non-finite value, refused before it is written.

    Attributes:
        quantity: the array (``"particle_q"``, ``"tie_force"``, ...).
        index: the index of the first non-finite value.
        time: the simulated time [s] of that frame or step.
    """

    def __init__(self, quantity: str, index: tuple[int, ...], time: float | None, what: str):
        self.quantity, self.index, self.time = quantity, index, time
        when = f" at t = {time:.6g} s" if time is not None else ""
        super().__init__(f"{what}: the simulation produced a non-finite value: {quantity}{list(index)}{when} "
                         "(the first one; the run blew up, so nothing was written: check the scene's constants "
                         "and rates, see docs/scenes.md)")


# Arrays of a trajectory file: name -> (shape in symbols, dtype kind). F frames, T string steps,
# S strings, P particles, B bodies, K bars (at least 1), Q generalised coordinates, S1 = S + 1.
_STRING_ARRAYS = {
    "frame_time": (("F",), "f"), "particle_q": (("F", "P", 3), "f"), "top_q": (("F", "S", 3), "f"),
    "step_time": (("T",), "f"), "tie_force": (("T", "S", 3), "f"), "string_taut": (("T", "S"), "i"),
    "string_names": (("S",), "U"), "string_start": (("S1",), "i"), "string_rest_length": (("S",), "f"),
}
_MARIONETTE_ARRAYS = {
    **_STRING_ARRAYS, "joint_q": (("F", "Q"), "f"), "body_pos": (("F", "B", 3), "f"),
    "body_rot": (("F", "B", 4), "f"), "bar_pos": (("F", "K", 3), "f"), "bar_rot": (("F", "K", 3, 3), "f"),
    "bar_feedback": (("T", "K", 3), "f"), "bar_reaction": (("T", "K", 3), "f"), "body_names": (("B",), "U"),
    "bar_names": (("N",), "U"),
}
_FRAME_ARRAYS = ("particle_q", "top_q", "joint_q", "body_pos", "body_rot", "bar_pos", "bar_rot", "energy")
_STEP_ARRAYS = ("tie_force", "bar_feedback", "bar_reaction")


def check_trajectory_arrays(arrays: dict, where: str, kind: str = "strings", *,
                            allow_non_finite: bool = False) -> None:
    """Checks the arrays of a trajectory file: present, dtypes, shapes consistent with each other
    (frames, steps, strings, particles, bodies, bars), finite, times strictly increasing.

    Args:
        arrays: array name -> array (as ``np.load`` gives them).
        where: names the file in messages.
        kind: ``"strings"`` or ``"marionette"``.
        allow_non_finite: accept NaN or infinity in the float arrays.

    Raises:
        TrajectoryFileError: naming the file and the first array that is wrong.
    """
    spec = dict(_MARIONETTE_ARRAYS if kind == "marionette" else {**_STRING_ARRAYS, "energy": (("F",), "f")})
    missing = sorted(n for n in spec if n not in arrays)
    if missing:
        raise TrajectoryFileError(f"{where}: fields {missing}: got nothing (missing; the file has "
                                  f"{sorted(arrays)}); expected every array of docs/trajectory.md for a {kind} "
                                  "trajectory")
    sizes: dict[str, int] = {}
    source: dict[str, str] = {}  # symbol -> the array that set it
    for name, (shape, dtype) in spec.items():
        array = np.asarray(arrays[name])
        ok_kind = array.size == 0 or array.dtype.kind in ({"i", "u", "b"} if dtype == "i" else {"f"} if dtype == "f" else {"U"})
        if not ok_kind:
            what = {"i": "integers", "f": "floating-point numbers", "U": "strings"}[dtype]
            raise TrajectoryFileError(f"{where}: field '{name}': got dtype {array.dtype}; expected {what}")
        wanted = "(" + ", ".join(map(str, shape)) + ")"
        if array.ndim != len(shape):
            raise TrajectoryFileError(f"{where}: field '{name}': got shape {array.shape}; expected {wanted}")
        for axis, (symbol, size) in enumerate(zip(shape, array.shape)):
            if isinstance(symbol, int):
                expected = symbol
            elif symbol == "S1":
                expected = sizes["S"] + 1 if "S" in sizes else None
            else:
                expected = sizes.setdefault(symbol, size)
                source.setdefault(symbol, name)
            if expected is not None and size != expected:
                origin = source.get("S" if symbol == "S1" else symbol, "?")
                raise TrajectoryFileError(f"{where}: field '{name}': got shape {array.shape}; expected {wanted} "
                                          f"with {symbol} = {expected} (as field '{origin}' has it)")
        if dtype == "f" and not allow_non_finite and not np.all(np.isfinite(array)):
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
            raise TrajectoryFileError(f"{where}: field '{name}': got a non-finite value at index {list(bad)}; "
                                      "expected finite numbers")
    if sizes.get("F", 0) < 1 or sizes.get("S", 0) < 1:
        raise TrajectoryFileError(f"{where}: fields 'frame_time'/'string_names': got {sizes.get('F', 0)} frames "
                                  f"and {sizes.get('S', 0)} strings; expected at least one of each")
    start = np.asarray(arrays["string_start"])
    if start[0] != 0 or start[-1] != sizes["P"] or np.any(np.diff(start) < 2):
        raise TrajectoryFileError(f"{where}: field 'string_start': got {start.tolist()}; expected 0, then "
                                  f"increasing by at least 2 particles per string, up to the {sizes['P']} particles")
    if kind == "marionette" and sizes["N"] > sizes["K"]:
        raise TrajectoryFileError(f"{where}: field 'bar_names': got {sizes['N']} names; expected at most "
                                  f"{sizes['K']} (the bars of bar_pos)")
    for name in ("frame_time", "step_time"):
        t = np.asarray(arrays[name])
        if len(t) > 1 and not np.all(np.diff(t) > 0):
            k = int(np.argmin(np.diff(t)))
            raise TrajectoryFileError(f"{where}: field '{name}': got {t[k]} then {t[k + 1]} at {k}, {k + 1}; "
                                      "expected strictly increasing times [s]")


def first_non_finite(trajectory) -> tuple[str, tuple[int, ...], float | None] | None:
    """The earliest non-finite value of a trajectory: ``(array, index, time [s])``, or ``None``.

    Frame arrays and string-step arrays are compared by time, so the quantity named is the
    first to blow up (a step's tie force before the next frame's particles).
    """
    found = []
    for name in ("frame_time", "step_time", *_FRAME_ARRAYS, *_STEP_ARRAYS):
        value = getattr(trajectory, name, None)
        if value is None:
            continue
        array = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(array)):
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(array))[0])
            if name in ("frame_time", "step_time"):
                return name, bad, None
            times = trajectory.frame_time if name in _FRAME_ARRAYS else trajectory.step_time
            found.append((float(times[bad[0]]), name, bad))
    if not found:
        return None
    time, name, bad = min(found, key=lambda f: f[0])
    return name, bad, time


def check_trajectory_finite(trajectory, what: str = "trajectory") -> None:
    """Raises :class:`NonFiniteTrajectoryError` with the first non-finite quantity and its time.

    The CLI calls it (through the writers) before anything is written.
    """
    found = first_non_finite(trajectory)
    if found is not None:
        raise NonFiniteTrajectoryError(*found, what)


def _prepare_write(path, trajectory, scene: Scene, allow_non_finite: bool, *, effects: dict, kind: str | None = None,
                   **extra) -> tuple[Path, dict]:
    """What both writers do first: refuse a non-finite trajectory (unless allowed), make the
    folder, and the file's metadata (keys in the order docs/trajectory.md lists them)."""
    path = Path(path)
    if not allow_non_finite:
        check_trajectory_finite(trajectory, f"{scene.source}")
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {"format": "dmarionette-trajectory", "format_version": FORMAT_VERSION}
    if kind is not None:
        metadata["kind"] = kind
    metadata.update({"scene": scene.name, "scene_source": scene.source, "string_dt": trajectory.string_dt})
    if "puppet_dt" in extra:
        metadata["puppet_dt"] = extra.pop("puppet_dt")
    metadata.update({"frame_steps": trajectory.frame_steps, "precision": scene.precision,
                     "effects": {k: bool(v) for k, v in effects.items()}, **extra})
    if allow_non_finite:
        metadata["finite"] = first_non_finite(trajectory) is None
    return path, metadata


def write_trajectory(path: str | Path, trajectory: StringTrajectory, scene: Scene, *,
                     allow_non_finite: bool = False) -> Path:
    """Writes ``trajectory`` to ``path`` (``.npz``); every array is named as in docs/trajectory.md.

    Raises:
        NonFiniteTrajectoryError: the trajectory has a NaN or infinity (nothing is written),
            unless ``allow_non_finite`` (then the metadata says ``"finite": false``).
    """
    path, metadata = _prepare_write(path, trajectory, scene, allow_non_finite, effects=vars(scene.effects))
    np.savez_compressed(
        path,
        metadata=np.array(json.dumps(metadata)),
        frame_time=trajectory.frame_time,
        particle_q=trajectory.particle_q,
        top_q=trajectory.top_q,
        step_time=trajectory.step_time,
        tie_force=trajectory.tie_force,
        string_taut=trajectory.string_taut.astype(np.int8),
        string_names=np.array(trajectory.string_names),
        string_start=trajectory.string_start,
        string_rest_length=trajectory.string_rest_length,
        energy=trajectory.energy,
    )
    return path


def read_npz_arrays(path: str | Path) -> dict:
    """The arrays of a NumPy ``.npz`` file; :class:`TrajectoryFileError` naming the file when it
    is missing, not an archive, or damaged."""
    import zipfile
    import zlib

    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: no such file; expected a trajectory file (trajectory.npz from "
                                  "'dmarionette simulate')")
    if not zipfile.is_zipfile(path):
        raise TrajectoryFileError(f"{path}: not a NumPy .npz archive (not a zip file: {path.stat().st_size} bytes "
                                  "that do not start like one); expected a trajectory file from 'dmarionette "
                                  "simulate'")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, NotImplementedError, zlib.error) as error:
        raise TrajectoryFileError(f"{path}: cannot be read as a NumPy .npz archive ({type(error).__name__}: "
                                  f"{error}); expected a trajectory file from 'dmarionette simulate'") from None


def read_trajectory_metadata(arrays: dict, where: str) -> dict:
    """The decoded, checked ``metadata`` array of a trajectory file."""
    if "metadata" not in arrays:
        raise TrajectoryFileError(f"{where}: field 'metadata': got nothing (missing; the file has "
                                  f"{sorted(arrays)}); expected a dmarionette trajectory file")
    raw = arrays["metadata"]
    if raw.dtype.kind != "U" or raw.ndim != 0:
        raise TrajectoryFileError(f"{where}: field 'metadata': got dtype {raw.dtype}, shape {raw.shape}; expected "
                                  "one string of JSON")
    try:
        metadata = json.loads(str(raw))
    except json.JSONDecodeError as error:
        raise TrajectoryFileError(f"{where}: field 'metadata': not valid JSON ({error})") from None
    if not isinstance(metadata, dict) or metadata.get("format") != "dmarionette-trajectory":
        got = metadata.get("format") if isinstance(metadata, dict) else metadata
        raise TrajectoryFileError(f"{where}: field 'metadata.format': got {got!r}; expected 'dmarionette-trajectory' "
                                  "(not a dmarionette trajectory file)")
    version = metadata.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise TrajectoryFileError(f"{where}: field 'metadata.format_version': got {version!r}; expected an integer "
                                  f"from 1 to {FORMAT_VERSION}")
    keys = {"string_dt": "a step [s] > 0", "frame_steps": "an integer >= 1"}
    if metadata.get("kind") == "marionette":
        keys["puppet_dt"] = "a step [s] > 0"
    for key, what in keys.items():
        value = metadata.get(key)
        if key == "frame_steps":
            ok = isinstance(value, int) and not isinstance(value, bool) and value >= 1
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value) and value > 0
        if not ok:
            raise TrajectoryFileError(f"{where}: field 'metadata.{key}': got {value!r}; expected {what}")
    return metadata


def read_trajectory(path: str | Path, *, allow_non_finite: bool = False) -> dict:
    """Reads a trajectory file into a dict of arrays plus ``metadata`` (a dict).

    Raises:
        TrajectoryFileError: (a ``ValueError``) the file is missing, damaged, not a trajectory
            file, or an array is missing, of the wrong dtype or shape, inconsistent with the
            others, or not finite (unless ``allow_non_finite``).
    """
    out = read_npz_arrays(path)
    out["metadata"] = read_trajectory_metadata(out, str(path))
    check_trajectory_arrays(out, str(path), "marionette" if out["metadata"].get("kind") == "marionette"
                            else "strings", allow_non_finite=allow_non_finite)
    return out


def summarize(trajectory: StringTrajectory, scene: Scene) -> dict:
    """A short summary: timing, and per string its stretch, taut fraction and tie force."""
    simulated = float(trajectory.step_time[-1])
    q = trajectory.particle_q
    strings = {}
    for s, name in enumerate(trajectory.string_names):
        a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
        segments = np.linalg.norm(np.diff(q[:, a:b], axis=1), axis=2).sum(axis=1)
        length = trajectory.string_rest_length[s] * (b - a - 1)
        strings[name] = {
            "max_stretch_percent": round(float(100.0 * (segments.max() / length - 1.0)), 4),
            "taut_fraction": round(float(trajectory.string_taut[:, s].mean()), 4),
            "max_tie_force_N": round(float(np.linalg.norm(trajectory.tie_force[:, s], axis=1).max()), 6),
        }
    finite = bool(np.all(np.isfinite(q)) and np.all(np.isfinite(trajectory.tie_force)))
    return {
        "scene": scene.name,
        "simulated_seconds": round(simulated, 6),
        "string_steps": int(len(trajectory.step_time)),
        "string_dt": trajectory.string_dt,
        "wall_seconds": round(trajectory.wall_seconds, 4),
        "real_time_factor": round(simulated / trajectory.wall_seconds, 2) if trajectory.wall_seconds > 0 else None,
        "steps_per_second": round(len(trajectory.step_time) / trajectory.wall_seconds, 1)
        if trajectory.wall_seconds > 0 else None,
        "all_finite": finite,
        "energy_J": {"initial": float(trajectory.energy[0]), "final": float(trajectory.energy[-1])},
        "strings": strings,
    }


def write_marionette_trajectory(path: str | Path, trajectory, scene: Scene, *,
                                allow_non_finite: bool = False) -> Path:
    """Writes a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (docs/trajectory.md).

    Raises:
        NonFiniteTrajectoryError: as :func:`write_trajectory`.
    """
    path, metadata = _prepare_write(path, trajectory, scene, allow_non_finite,
                                    effects={**vars(scene.effects), **scene.body_effects}, kind="marionette",
                                    puppet_dt=trajectory.puppet_dt,
                                    body_shape=[[shape, list(size)] for shape, size in trajectory.body_shape])
    arrays = {name: getattr(trajectory, name) for name in (
        "frame_time", "particle_q", "joint_q", "body_pos", "body_rot", "bar_pos", "bar_rot", "top_q",
        "step_time", "tie_force", "bar_feedback", "bar_reaction", "string_start", "string_rest_length")}
    np.savez_compressed(path, metadata=np.array(json.dumps(metadata)),
                        string_taut=trajectory.string_taut.astype(np.int8),
                        string_names=np.array(trajectory.string_names), body_names=np.array(trajectory.body_names),
                        bar_names=np.array(trajectory.bar_names), **arrays)
    return path


def summarize_marionette(trajectory, scene: Scene) -> dict:
    """Timing, finiteness, and per string its taut fraction and largest tie force; per bar its feedback."""
    simulated = float(trajectory.step_time[-1])
    finite = all(bool(np.all(np.isfinite(getattr(trajectory, name))))
                 for name in ("particle_q", "body_pos", "tie_force", "bar_feedback", "bar_reaction"))
    pelvis = trajectory.body_pos[:, 0, 1]
    return {
        "scene": scene.name,
        "simulated_seconds": round(simulated, 6),
        "string_steps": int(len(trajectory.step_time)),
        "puppet_steps": int(round(simulated / trajectory.puppet_dt)),
        "string_dt": trajectory.string_dt,
        "puppet_dt": trajectory.puppet_dt,
        "wall_seconds": round(trajectory.wall_seconds, 4),
        "real_time_factor": round(simulated / trajectory.wall_seconds, 2) if trajectory.wall_seconds > 0 else None,
        "all_finite": finite,
        "torso_height_m": {"initial": round(float(pelvis[0]), 4), "final": round(float(pelvis[-1]), 4),
                           "max": round(float(pelvis.max()), 4)},
        "strings": {name: {"taut_fraction": round(float(trajectory.string_taut[:, s].mean()), 4),
                           "max_tie_force_N": round(float(np.linalg.norm(trajectory.tie_force[:, s], axis=1).max()), 4)}
                    for s, name in enumerate(trajectory.string_names)},
        "bars": {name: {"max_feedback_N": round(float(np.linalg.norm(trajectory.bar_feedback[:, b], axis=1).max()), 4),
                        "max_reaction_N": round(float(np.linalg.norm(trajectory.bar_reaction[:, b], axis=1).max()), 4)}
                 for b, name in enumerate(trajectory.bar_names)},
    }
