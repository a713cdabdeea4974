"""Reading a recorded session (docs/session.md) as the inputs and targets of a calibration.

**Inputs** are the control bars over the session, at every string step: the string tops
``top_q (T, S, 3)``, bar centres ``bar_q (T, B, 3)`` and velocities ``bar_qd (T, B, 3)``. They
come from the recorded bar poses (``/bar/BAR/pose``, at t = k h): each string's top is its
attach point (``bar_attach`` in the metadata) moved by the bar's pose, ``x + R(angles) a``.
A bar without recorded poses may instead be driven by its device samples
(``/device/BAR/sample``) mapped by ``P' = S W P`` (eq. 3): that needs the mapping, a
``"device_mapping"`` metadata record (``bar``, ``scale`` and ``device_to_world``, 4x4 each,
see :func:`device_mapping_record`) or the ``"live"`` record that ``dmarionette live`` writes
(its ``devices``, each with ``bar``, ``S`` and ``W``); the live loop uses the sample read at t = (k - 1) h for
the string step ending at t = k h, and so does this reader.

**Targets**, as chosen: the recorded body centres at the puppet rate (``/puppet/state``
``body_pos``, frames f = 1 .. P at t = f H) and/or the exact reaction of the strings on each
bar at the string rate (``/bar/BAR/feedback`` ``reaction``, steps k = 1 .. T). eq. 4 (the
``eq4`` field) is not used as a target: it reads the bar's velocity, which a session does not
record (it is differentiated from the poses), so it does not test the strings alone.

A session is refused (``ValueError`` naming the file, the channel and what was expected) when
it lacks a needed channel, when a channel has a gap (a string step or puppet frame with no
message) or a non-finite value, or when it is too short for one puppet step.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dmarionette.scene.scene import Scene
from dmarionette.io.session import Session, read_session, scene_for_replay
from dmarionette.rotations import euler_to_matrix, from_wxyz, normalize_quat, quat_to_matrix

__all__ = ["TARGETS", "CalibrationData", "device_mapping_record", "read_calibration_data"]

#: Target choices: recorded body centres, the exact bar reaction, or both.
TARGETS = ("bodies", "feedback", "both")
_TIME_TOLERANCE = 1e-6  # a message is "at" step k when |t - k h| < 1e-6 h


@dataclasses.dataclass
class CalibrationData:
    """A session read for calibration.

    Attributes:
        path: the session file.
        session: the session as read (all channels).
        scene: the scene to simulate: the embedded scene with the recorded constants and rates
            (:func:`dmarionette.io.session.scene_for_replay`; bars follow the recorded poses).
        string_dt, puppet_dt: [s]; ``substeps`` string steps per puppet step.
        puppet_steps: ``P``, whole puppet steps covered; ``T = P * substeps`` string steps.
        step_time: end time of each string step [s], ``(T,)``.
        frame_time: puppet frame times [s], ``(P + 1,)`` (frame 0 is the start state).
        top_q: string tops at each step's end [m], ``(T, S, 3)``.
        bar_q, bar_qd: bar centres [m] and velocities [m/s], ``(T, B, 3)``.
        input_source: per bar, ``"bar poses"`` or ``"device poses"``.
        body_pos: recorded body centres [m], ``(P + 1, bodies, 3)`` (row 0 NaN when the session
            has no state at t = 0), or ``None`` when bodies are not a target.
        bar_reaction: recorded exact reaction per bar [N], ``(T, B, 3)``, or ``None``.
        targets: which of ``"bodies"``, ``"feedback"`` are targets.
        strings, bodies, bars: names, in the session's order.
    """

    path: Path
    session: Session
    scene: Scene
    string_dt: float
    puppet_dt: float
    substeps: int
    puppet_steps: int
    step_time: np.ndarray
    frame_time: np.ndarray
    top_q: np.ndarray
    bar_q: np.ndarray
    bar_qd: np.ndarray
    input_source: dict[str, str]
    body_pos: np.ndarray | None
    bar_reaction: np.ndarray | None
    targets: tuple[str, ...]
    strings: list[str]
    bodies: list[str]
    bars: list[str]

    @property
    def step_count(self) -> int:
        """``T``, string steps."""
        return len(self.step_time)


def device_mapping_record(bar: str, mapping) -> dict:
    """The ``"device_mapping"`` metadata record this reader understands, for
    ``SessionWriter.write_metadata("device_mapping", ...)``.

    Args:
        bar: the bar the device drives.
        mapping: a :class:`dmarionette.hw.DeviceMapping` (``S`` and ``W``).
    """
    return {"bar": bar, "scale": np.asarray(mapping.scale).tolist(),
            "device_to_world": np.asarray(mapping.device_to_world).tolist()}


def _grid_rows(path: Path, topic: str, t: np.ndarray, dt: float, first: int, last: int,
               what: str) -> np.ndarray:
    """Row index of the message at each grid time ``k dt``, ``k = first .. last``; refuses gaps."""
    k = np.rint(t / dt)
    on_grid = np.abs(t - k * dt) < _TIME_TOLERANCE * dt
    rows = np.full(last - first + 1, -1, dtype=np.int64)
    inside = on_grid & (k >= first) & (k <= last)
    rows[(k[inside] - first).astype(np.int64)] = np.nonzero(inside)[0]
    missing = np.nonzero(rows < 0)[0]
    if len(missing):
        k0 = first + missing[0]
        before = t[t < k0 * dt - _TIME_TOLERANCE * dt]
        after = t[t > k0 * dt + _TIME_TOLERANCE * dt]
        around = (f"between t = {before.max():.6g} s and " if len(before) else "before ") + \
                 (f"t = {after.min():.6g} s" if len(after) else "the end")
        raise ValueError(f"{path}: channel {topic} has a gap: no message at t = {k0 * dt:.6g} s ({around}; "
                         f"{len(missing)} of the {len(rows)} expected times missing); calibration expects "
                         f"{what}, one every {dt:.6g} s from t = {first * dt:.6g} s to {last * dt:.6g} s")
    return rows


def _finite(path: Path, topic: str, field: str, t: np.ndarray, values: np.ndarray) -> None:
    bad = ~np.all(np.isfinite(values.reshape(len(values), -1)), axis=1)
    if bad.any():
        raise ValueError(f"{path}: channel {topic} field {field!r} has a non-finite value at t = "
                         f"{t[np.argmax(bad)]:.6g} s ({int(bad.sum())} messages); expected finite numbers")


def _bar_from_poses(session: Session, bar: str, times: np.ndarray, dt: float, steps: int):
    """Bar centres ``(T, 3)``, rotations ``(T, 3, 3)`` at the string steps, from ``/bar/BAR/pose``."""
    topic = f"/bar/{bar}/pose"
    channel = session.channels[topic]
    rows = _grid_rows(session.path, topic, channel["t"], dt, 1, steps, "a bar pose at the end of every string step")
    position, rotation = channel["position"][rows], channel["rotation"][rows]
    _finite(session.path, topic, "position", channel["t"][rows], position)
    _finite(session.path, topic, "rotation", channel["t"][rows], rotation)
    return position, euler_to_matrix(rotation)


def _device_mapping(session: Session, bar: str):
    """``(record name, S, W)`` of the device that drove ``bar``, or ``(None, None, None)``: from a
    ``"device_mapping"`` record, or from the ``"live"`` record ``dmarionette live`` writes (one
    entry per device, with its bar, ``S`` and ``W``)."""
    record = session.extra_metadata.get("device_mapping")
    if isinstance(record, dict) and record.get("bar") == bar and {"scale", "device_to_world"} <= set(record):
        return "device_mapping", record["scale"], record["device_to_world"]
    live = session.extra_metadata.get("live")
    devices = live.get("devices") if isinstance(live, dict) else None
    for device in devices if isinstance(devices, list) else []:
        if isinstance(device, dict) and device.get("bar") == bar and {"S", "W"} <= set(device):
            return "live", device["S"], device["W"]
    return None, None, None


def _bar_from_device(session: Session, bar: str, dt: float, steps: int):
    """Bar centres and rotations at the string steps from the device samples through ``S W``."""
    from dmarionette.hw.mapping import DeviceMapping

    path, topic = session.path, f"/device/{bar}/sample"
    name, scale, device_to_world = _device_mapping(session, bar)
    if name is None:
        raise ValueError(f"{path}: calibration needs the pose of bar {bar!r} at every string step: channel "
                         f"/bar/{bar}/pose is absent, and its device samples ({topic}) cannot stand in without "
                         f"the mapping P' = S W P (a 'device_mapping' metadata record with bar = {bar!r}, "
                         f"'scale' and 'device_to_world', or the 'live' record that dmarionette live writes); "
                         f"metadata records found: {sorted(session.extra_metadata)}")
    try:
        mapping = DeviceMapping(np.asarray(scale, dtype=float), np.asarray(device_to_world, dtype=float))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: metadata record {name!r}, bar {bar!r}: {error}; expected 4x4 matrices S and W "
                         "(DeviceMapping)") from None
    channel = session.channels[topic]
    # The sample read at t = (k - 1) h drives the string step that ends at t = k h (live.py).
    rows = _grid_rows(path, topic, channel["t"], dt, 0, steps - 1, "a device sample at the start of every "
                      "string step (recorded with the simulated time)")
    _finite(path, topic, "position", channel["t"][rows], channel["position"][rows])
    _finite(path, topic, "orientation", channel["t"][rows], channel["orientation"][rows])
    position = mapping.position_to_world(channel["position"][rows])
    device_rotation = [quat_to_matrix(from_wxyz(normalize_quat(q))) for q in channel["orientation"][rows]]
    rotation = np.stack([mapping.rotation_to_world(r) for r in device_rotation])
    return position, rotation


def _bar_inputs(session: Session, scene: Scene, steps: int):
    """``top_q (T, S, 3)``, ``bar_q``, ``bar_qd (T, B, 3)`` and each bar's input source."""
    dt = 1.0 / session.string_hz
    times = dt * np.arange(1, steps + 1)
    names = [s.name for s in scene.strings]
    attach = session.metadata.get("bar_attach") or {b.name: dict(b.attach) for b in scene.bars}
    tops = scene.top_positions(np.array([s.top for s in scene.strings]), times)  # strings on no bar
    bar_q = np.zeros((steps, max(len(scene.bars), 1), 3))
    bar_qd = np.zeros_like(bar_q)
    sources = {}
    for b, bar in enumerate(scene.bars):
        has_poses = len(session.channels.get(f"/bar/{bar.name}/pose", {}).get("t", ())) > 0
        has_device = len(session.channels.get(f"/device/{bar.name}/sample", {}).get("t", ())) > 0
        if has_poses:
            position, rotation = _bar_from_poses(session, bar.name, times, dt, steps)
            sources[bar.name] = "bar poses"
        elif has_device:
            position, rotation = _bar_from_device(session, bar.name, dt, steps)
            sources[bar.name] = "device poses"
        else:
            _refuse_missing_bar(session, bar.name)
        carried = [i for i, n in enumerate(names) if n in bar.attach]
        local = np.array([attach[bar.name][names[i]] for i in carried], dtype=np.float64).reshape(-1, 3)
        tops[:, carried] = position[:, None, :] + np.einsum("tij,sj->tsi", rotation, local)
        bar_q[:, b] = position
        # The bar's velocity (eq. 4's proxy velocity only): central differences, as in replay.
        previous = np.concatenate([position[:1], position[:-1]])
        following = np.concatenate([position[1:], position[-1:]])
        span = np.full(steps, 2 * dt)
        span[0] = span[-1] = dt
        bar_qd[:, b] = (following - previous) / span[:, None] if steps > 1 else 0.0
    return tops, bar_q, bar_qd, sources


def _refuse_missing_bar(session: Session, bar: str) -> None:
    raise ValueError(f"{session.path}: calibration needs the pose of bar {bar!r} at every string step as an "
                     f"input: neither /bar/{bar}/pose nor /device/{bar}/sample is in this session (it has "
                     f"{sorted(session.channels)})")


def _last_time(session: Session, scene: Scene) -> float:
    """The last time every bar's input is known at [s]."""
    ends = []
    for bar in scene.bars:
        pose = session.channels.get(f"/bar/{bar.name}/pose", {}).get("t", ())
        sample = session.channels.get(f"/device/{bar.name}/sample", {}).get("t", ())
        if len(pose):
            ends.append(float(np.max(pose)))
        elif len(sample):
            ends.append(float(np.max(sample)) + 1.0 / session.string_hz)
        else:
            _refuse_missing_bar(session, bar.name)
    return min(ends) if ends else 0.0


def read_calibration_data(path: str | Path, targets: str = "bodies", *, duration: float | None = None,
                          session: Session | None = None) -> CalibrationData:
    """Reads a session's inputs and targets for calibration.

    Args:
        path: the ``.mcap`` session (a cut-off file is read up to its last complete record).
        targets: ``"bodies"`` (recorded body centres), ``"feedback"`` (the exact reaction per
            bar) or ``"both"``.
        duration: use only the first ``duration`` seconds [s] (default: the whole session).
        session: the session already read (else it is read from ``path``).

    Returns:
        The inputs and targets over whole puppet steps.

    Raises:
        ValueError: not a session; its scene has no puppet or no bars; a needed channel is
            absent, has a gap or a non-finite value; too short for one puppet step.
    """
    if targets not in TARGETS:
        raise ValueError(f"targets: got {targets!r}; expected one of {list(TARGETS)}")
    wanted = ("bodies", "feedback") if targets == "both" else (targets,)
    session = read_session(path) if session is None else session
    path = session.path
    scene = session.scene
    if scene.puppet is None or not scene.bars:
        raise ValueError(f"{path}: the session's scene {scene.name!r} has no [puppet] or no [bars]: calibration "
                         "fits the strings of a marionette driven by its bars")
    if "bodies" in wanted:
        session.require(["/puppet/state"], "calibration against body poses (--targets bodies)")
    if "feedback" in wanted:
        session.require([f"/bar/{b.name}/feedback" for b in scene.bars],
                        "calibration against the feedback forces (--targets feedback)")
    scene = scene_for_replay_or_device(session)
    string_dt = 1.0 / session.string_hz
    substeps = max(1, round(session.string_hz / session.puppet_hz))
    puppet_dt = substeps * string_dt
    end = _last_time(session, scene)
    if "bodies" in wanted:
        end = min(end, float(np.max(session.channels["/puppet/state"]["t"])))
    if duration is not None:
        if not duration > 0.0:
            raise ValueError(f"duration: got {duration}; expected a positive number of seconds")
        end = min(end, float(duration))
    puppet_steps = int(np.floor(end / puppet_dt + 1e-9))
    if puppet_steps < 1:
        raise ValueError(f"{path}: the session's inputs and targets end at t = {end:.6g} s, before the first "
                         f"puppet step ends (t = {puppet_dt:.6g} s): nothing to calibrate against")
    steps = puppet_steps * substeps
    top_q, bar_q, bar_qd, sources = _bar_inputs(session, scene, steps)
    body_pos = bar_reaction = None
    if "bodies" in wanted:
        topic, channel = "/puppet/state", session.channels["/puppet/state"]
        rows = _grid_rows(path, topic, channel["t"], puppet_dt, 1, puppet_steps,
                          "a puppet state at the end of every puppet step")
        _finite(path, topic, "body_pos", channel["t"][rows], channel["body_pos"][rows])
        bodies = len(session.bodies)
        if channel["body_pos"].ndim != 3 or channel["body_pos"].shape[1:] != (bodies, 3):
            raise ValueError(f"{path}: channel {topic} field 'body_pos' has shape {channel['body_pos'].shape[1:]}"
                             f" per message; expected ({bodies}, 3) (the metadata's {bodies} bodies)")
        body_pos = np.full((puppet_steps + 1, bodies, 3), np.nan)
        body_pos[1:] = channel["body_pos"][rows]
        first = np.nonzero(np.abs(channel["t"]) < _TIME_TOLERANCE * puppet_dt)[0]
        if len(first):
            body_pos[0] = channel["body_pos"][first[0]]
    if "feedback" in wanted:
        bar_reaction = np.zeros((steps, len(scene.bars), 3))
        for b, bar in enumerate(scene.bars):
            topic = f"/bar/{bar.name}/feedback"
            channel = session.channels[topic]
            rows = _grid_rows(path, topic, channel["t"], string_dt, 1, steps,
                              "the bar's feedback at the end of every string step")
            _finite(path, topic, "reaction", channel["t"][rows], channel["reaction"][rows])
            bar_reaction[:, b] = channel["reaction"][rows]
    return CalibrationData(
        path=path, session=session, scene=scene, string_dt=string_dt, puppet_dt=puppet_dt, substeps=substeps,
        puppet_steps=puppet_steps, step_time=string_dt * np.arange(1, steps + 1),
        frame_time=puppet_dt * np.arange(puppet_steps + 1), top_q=top_q, bar_q=bar_q, bar_qd=bar_qd,
        input_source=sources, body_pos=body_pos, bar_reaction=bar_reaction, targets=tuple(wanted),
        strings=session.strings, bodies=session.bodies, bars=session.bars)


def scene_for_replay_or_device(session: Session) -> Scene:
    """:func:`scene_for_replay` when every bar has recorded poses; else the same with the
    device-driven bars left on the scene's own trajectory (their inputs come from the device
    samples; the scene's trajectory only places the strings' tops at t = 0)."""
    scene = session.scene
    missing = [b.name for b in scene.bars if len(session.channels.get(f"/bar/{b.name}/pose", {}).get("t", ())) == 0]
    if not missing:
        return scene_for_replay(session)
    stand_in = {topic: channel for topic, channel in session.channels.items()}
    for bar in missing:  # a one-pose stand-in so scene_for_replay can place the tops; replaced below
        trajectory = next(b.trajectory for b in scene.bars if b.name == bar)
        stand_in[f"/bar/{bar}/pose"] = {"t": np.array([0.0]), "position": trajectory.positions[:1],
                                        "rotation": trajectory.rotations[:1]}
    return scene_for_replay(dataclasses.replace(session, channels=stand_in))

