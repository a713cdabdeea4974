"""What the motion exporters (BVH, glTF, USD) share: the checked body motion, quaternions, the puppet.

The exporters read a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (or any
object with the same ``frame_time``, ``body_pos``, ``body_rot``, ``body_names`` and
``body_shape`` attributes), or a trajectory file through :func:`read_marionette_trajectory`.
Quaternions are Warp's ``(x, y, z, w)``, body to world, as in the trajectory (and as in
glTF); body positions are the centres of mass [m], y up.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.rotations import matrix_to_quat, quat_to_matrix
from dmarionette.scene.puppet import PuppetDescription, load_puppet

__all__ = [
    "JOINT_GAP_TOLERANCE",
    "BodyMotion",
    "ExportError",
    "bar_tracks",
    "body_motion",
    "check_puppet_matches",
    "read_marionette_trajectory",
    "resolve_puppet",
    "string_tracks",
]

JOINT_GAP_TOLERANCE = 1e-6
"""Largest distance [m] allowed between a joint's anchor on the parent and on the child.

The puppet is simulated in reduced coordinates, so the two anchor points of a joint
coincide to rounding (measured ~1e-16 m); a larger gap means that the trajectory was not
made with the puppet description given to the exporter."""


class ExportError(ValueError):
    """A trajectory (or trajectory file) that cannot be exported as it is.

    The message names the file or object, the field, the value received and what was expected.
    """


@dataclasses.dataclass(frozen=True)
class BodyMotion:
    """The checked body motion of a trajectory, float64.

    Attributes:
        frame_time: [s], strictly increasing, shape ``(F,)``.
        body_pos: centres of mass, world [m], shape ``(F, B, 3)``.
        body_rot: unit quaternions ``(x, y, z, w)`` body to world, shape ``(F, B, 4)``.
        body_names: ``B`` names.
        body_shape: per body ``(shape, (sx, sy, sz))``: ``"box"`` with full extents [m] or
            ``"sphere"`` with ``(radius, 0, 0)``.
    """

    frame_time: np.ndarray
    body_pos: np.ndarray
    body_rot: np.ndarray
    body_names: list[str]
    body_shape: list[tuple[str, tuple[float, float, float]]]

    @property
    def frame_count(self) -> int:
        return len(self.frame_time)


def _field(trajectory: Any, name: str, where: str) -> Any:
    if isinstance(trajectory, dict):
        value = trajectory.get(name)
    else:
        value = getattr(trajectory, name, None)
    if value is None:
        raise ExportError(f"{where}: field '{name}': got nothing (missing); expected a marionette trajectory "
                          "(dmarionette.MarionetteTrajectory or a trajectory file of a scene with a puppet)")
    return value


def _array(trajectory: Any, name: str, where: str, shape: tuple) -> np.ndarray:
    value = _field(trajectory, name, where)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ExportError(f"{where}: field '{name}': got {type(value).__name__}; expected numbers") from None
    wanted = "(" + ", ".join(str(s) if s is not None else "?" for s in shape) + ")"
    if array.ndim != len(shape) or any(s is not None and a != s for a, s in zip(array.shape, shape)):
        raise ExportError(f"{where}: field '{name}': got shape {array.shape}; expected {wanted}")
    if not np.all(np.isfinite(array)):
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ExportError(f"{where}: field '{name}': got a non-finite value at index {tuple(int(i) for i in bad)}; "
                          "expected finite numbers (the simulation blew up?)")
    return array


def body_motion(trajectory: Any, where: str = "trajectory") -> BodyMotion:
    """Checks and returns the body motion of ``trajectory``.

    Args:
        trajectory: a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory`, or an
            object or dict with the same fields.
        where: names the trajectory in error messages (a file path).

    Raises:
        ExportError: a missing field, wrong shapes, non-finite values, times not strictly
            increasing, a quaternion far from unit length, an unknown body shape.
    """
    time = _array(trajectory, "frame_time", where, (None,))
    frames = len(time)
    if frames < 1:
        raise ExportError(f"{where}: field 'frame_time': got 0 frames; expected at least one")
    if frames > 1 and not np.all(np.diff(time) > 0.0):
        f = int(np.argmin(np.diff(time)))
        raise ExportError(f"{where}: field 'frame_time': got {time[f]} then {time[f + 1]} at frames {f}, {f + 1}; "
                          "expected strictly increasing times [s]")
    names = [str(n) for n in _field(trajectory, "body_names", where)]
    bodies = len(names)
    pos = _array(trajectory, "body_pos", where, (frames, bodies, 3))
    rot = _array(trajectory, "body_rot", where, (frames, bodies, 4))
    norm = np.linalg.norm(rot, axis=-1)
    if np.any(np.abs(norm - 1.0) > 1e-3):
        f, b = (int(i) for i in np.argwhere(np.abs(norm - 1.0) > 1e-3)[0])
        raise ExportError(f"{where}: field 'body_rot': got a quaternion of length {norm[f, b]:.6g} at frame {f}, "
                          f"body '{names[b]}'; expected unit quaternions (x, y, z, w)")
    rot = rot / norm[..., None]
    shapes = []
    raw_shapes = list(_field(trajectory, "body_shape", where))
    if len(raw_shapes) != bodies:
        raise ExportError(f"{where}: field 'body_shape': got {len(raw_shapes)} entries; expected one per body "
                          f"({bodies}: {names})")
    for b, entry in enumerate(raw_shapes):
        try:
            shape, size = entry
            size = tuple(float(s) for s in size)
        except (TypeError, ValueError):
            raise ExportError(f"{where}: field 'body_shape' of body '{names[b]}': got {entry!r}; expected "
                              "[shape, [sx, sy, sz]]") from None
        ok = len(size) == 3 and (
            (shape == "box" and all(s > 0.0 for s in size)) or (shape == "sphere" and size[0] > 0.0))
        if not ok:
            raise ExportError(f"{where}: field 'body_shape' of body '{names[b]}': got {entry!r}; expected "
                              "['box', [sx, sy, sz]] with extents > 0 [m] or ['sphere', [radius > 0, 0, 0]]")
        shapes.append((str(shape), size))
    return BodyMotion(time, pos, rot, names, shapes)


def resolve_puppet(trajectory: Any, puppet: PuppetDescription | None) -> PuppetDescription:
    """The puppet whose joint tree a trajectory was simulated with.

    The explicit ``puppet`` if given, else the trajectory's ``puppet`` attribute (set by
    :func:`read_marionette_trajectory` from the scene the file names), else the default
    marionette (``dmarionette/scene/builtin/puppet.toml``). :func:`check_puppet_matches` then
    verifies it against the motion.
    """
    if puppet is not None:
        return puppet
    own = trajectory.get("puppet") if isinstance(trajectory, dict) else getattr(trajectory, "puppet", None)
    return own if own is not None else load_puppet()


def check_puppet_matches(motion: BodyMotion, puppet: PuppetDescription, where: str) -> None:
    """Refuses a puppet description that does not describe the simulated bodies.

    The puppet's bodies must be the first bodies of the trajectory, in the same order
    (a free ball may follow), and every joint's two anchors (``anchor_parent`` on the
    parent, ``anchor_child`` on the child) must coincide in the world at every frame
    within :data:`JOINT_GAP_TOLERANCE`.

    Raises:
        ExportError: naming the first mismatch.
    """
    names = [b.name for b in puppet.bodies]
    if motion.body_names[: len(names)] != names:
        raise ExportError(f"{where}: field 'body_names': got {motion.body_names}; expected the bodies of puppet "
                          f"'{puppet.name}' first, in its order: {names} (pass the scene's puppet)")
    rot = quat_to_matrix(motion.body_rot)
    parents = puppet.parent_index()
    for b, joint in enumerate(puppet.joints, start=1):
        p = parents[b]
        on_parent = motion.body_pos[:, p] + rot[:, p] @ np.asarray(joint.anchor_parent)
        on_child = motion.body_pos[:, b] + rot[:, b] @ np.asarray(joint.anchor_child)
        gap = np.linalg.norm(on_parent - on_child, axis=-1)
        if gap.max() > JOINT_GAP_TOLERANCE:
            f = int(np.argmax(gap))
            raise ExportError(f"{where}: joint '{joint.name}' of puppet '{puppet.name}': its anchors are "
                              f"{gap[f]:.3g} m apart at frame {f}; expected them to coincide (<= "
                              f"{JOINT_GAP_TOLERANCE:g} m): the trajectory was simulated with another puppet "
                              "(pass the scene's puppet)")


def read_marionette_trajectory(path: str | Path):
    """Reads a marionette trajectory file (``dmarionette simulate``, docs/trajectory.md).

    Returns a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` with one extra
    attribute, ``puppet``: the puppet of the scene named by the file's ``scene_source``
    when that scene file still exists, else ``None`` (the exporters then use the default
    marionette and check that it fits). ``wall_seconds`` is not stored in the file: NaN.

    Raises:
        ExportError: the file is missing, not a NumPy archive, not a dmarionette
            trajectory, a strings-only trajectory, or lacks a field.
    """
    from dmarionette.marionette.rollout import MarionetteTrajectory

    from dmarionette.io.trajectory import (
        TrajectoryFileError,
        check_trajectory_arrays,
        read_npz_arrays,
        read_trajectory_metadata,
    )

    path = Path(path)
    try:
        arrays = read_npz_arrays(path)
        metadata = read_trajectory_metadata(arrays, str(path))
        if metadata.get("kind") != "marionette":
            raise ExportError(f"{path}: field 'metadata.kind': got {metadata.get('kind')!r}; expected 'marionette' "
                              "(this trajectory has strings only, no puppet motion to export)")
        check_trajectory_arrays(arrays, str(path), "marionette")
    except TrajectoryFileError as error:
        raise ExportError(str(error)) from None
    fields = [f.name for f in dataclasses.fields(MarionetteTrajectory)]
    stored = [n for n in fields if n not in ("body_shape", "string_dt", "puppet_dt", "frame_steps", "wall_seconds")]
    values = {n: arrays[n] for n in stored}
    for key in ("string_names", "body_names", "bar_names"):
        values[key] = [str(s) for s in values[key]]
    raw_shapes = metadata.get("body_shape")
    try:
        values["body_shape"] = [(str(s), tuple(float(v) for v in size)) for s, size in raw_shapes]
    except (TypeError, ValueError):
        raise ExportError(f"{path}: field 'metadata.body_shape': got {raw_shapes!r}; expected one [shape, [sx, sy, "
                          "sz]] per body") from None
    if len(values["body_shape"]) != len(values["body_names"]):
        raise ExportError(f"{path}: field 'metadata.body_shape': got {len(values['body_shape'])} entries; expected "
                          f"one per body ({len(values['body_names'])})")
    trajectory = MarionetteTrajectory(string_dt=float(metadata["string_dt"]), puppet_dt=float(metadata["puppet_dt"]),
                                      frame_steps=int(metadata["frame_steps"]), wall_seconds=float("nan"), **values)
    trajectory.puppet = _scene_puppet(metadata.get("scene_source"))
    return trajectory


def _scene_puppet(source: Any) -> PuppetDescription | None:
    if not isinstance(source, str) or not Path(source).is_file():
        return None
    from dmarionette.scene.scene import load_scene
    from dmarionette.scene.fields import SceneError

    try:
        return load_scene(source).puppet
    except SceneError:
        return None


def bar_tracks(trajectory: Any, frames: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, positions (F, 3), rotations (F, 4))`` of each control bar the trajectory has."""
    get = (lambda k: trajectory.get(k)) if isinstance(trajectory, dict) else (lambda k: getattr(trajectory, k, None))
    names, pos, rot = get("bar_names"), get("bar_pos"), get("bar_rot")
    if names is None or pos is None or rot is None or not len(names):
        return []
    pos, rot = np.asarray(pos, dtype=np.float64), np.asarray(rot, dtype=np.float64)
    if pos.shape[:2] != (frames, len(names)) or rot.shape[:2] != (frames, len(names)) or not (
            np.all(np.isfinite(pos)) and np.all(np.isfinite(rot))):
        return []
    return [(str(n), pos[:, b], matrix_to_quat(rot[:, b])) for b, n in enumerate(names)]


def string_tracks(trajectory: Any, frames: int, where: str) -> list[tuple[str, np.ndarray]] | None:
    """``(name, particle positions (F, n, 3))`` per string, or None when the trajectory has no strings."""
    get = (lambda k: trajectory.get(k)) if isinstance(trajectory, dict) else (lambda k: getattr(trajectory, k, None))
    q, start, names = get("particle_q"), get("string_start"), get("string_names")
    if q is None or start is None:
        return None
    q = np.asarray(q, dtype=np.float64)
    start = np.asarray(start).astype(np.int64)
    count = len(start) - 1
    names = [str(n) for n in names] if names is not None else [str(i) for i in range(count)]
    if q.ndim != 3 or q.shape[0] != frames or q.shape[2] != 3:
        raise ExportError(f"{where}: field 'particle_q': got shape {q.shape}; expected ({frames}, P, 3)")
    if count < 1 or start[0] != 0 or start[-1] != q.shape[1] or np.any(np.diff(start) < 2) or len(names) != count:
        raise ExportError(f"{where}: field 'string_start': got {start.tolist()}; expected increasing first-particle "
                          f"indices from 0 to {q.shape[1]}, at least 2 particles a string, one per string name")
    if not np.all(np.isfinite(q)):
        raise ExportError(f"{where}: field 'particle_q': got non-finite values; expected finite positions [m]")
    return [(names[s], q[:, start[s]:start[s + 1]]) for s in range(count)]
