"""Sessions and the simulator: record a simulated run, replay a recorded session.

:func:`record_simulation` writes what a live session would hold, from a simulated run (no
device channels): it is the reference example of the format. :func:`replay_session`
rebuilds the scene from a session's metadata, drives its bars with the recorded bar
poses, re-simulates and says how far the re-simulated bodies are from the recorded ones.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.marionette.solver import MarionetteModel
from dmarionette.marionette.rollout import MarionetteTrajectory, simulate_marionette
from dmarionette.scene.bars import BarTrajectory
from dmarionette.scene.scene import Scene
from dmarionette.io.session.read import Session, read_session, session_bar_trajectories
from dmarionette.io.session.write import SessionWriter

__all__ = ["record_simulation", "replay_session", "scene_for_replay", "write_simulated_run"]


def write_simulated_run(writer: SessionWriter, trajectory: MarionetteTrajectory, bars, *, feedback: bool,
                        delay: float = 0.0, body_pos: np.ndarray | None = None,
                        bar_feedback: np.ndarray | None = None, bar_reaction: np.ndarray | None = None) -> None:
    """Writes a simulated run into an open session as a live run records it: every bar's pose at
    t = 0 and after every step of ``trajectory.step_time``, the bars' feedback (with ``feedback``)
    and the taut flags after every step, the puppet state at every frame.

    Args:
        writer: the open session.
        trajectory: the run (simulated with one frame per puppet step).
        bars: the scene's bars (``Scene.bars``); each pose from its spline at ``t + delay``.
        feedback: write the bars' feedback channels.
        delay: the recorded bar poses lead the rest by this many seconds (0: none).
        body_pos, bar_feedback, bar_reaction: written instead of the trajectory's own when given
            (e.g. with measurement noise added), same shapes.
    """
    body_pos = trajectory.body_pos if body_pos is None else body_pos
    bar_feedback = trajectory.bar_feedback if bar_feedback is None else bar_feedback
    bar_reaction = trajectory.bar_reaction if bar_reaction is None else bar_reaction
    times = np.concatenate([[0.0], trajectory.step_time])
    poses = [(bar.name, bar.trajectory.pose(times + delay)[0], bar.trajectory.angles(times + delay)) for bar in bars]
    steps = trajectory.frame_steps  # string steps per recorded puppet state (one puppet step)
    for k, t in enumerate(times):
        t = float(t)
        for name, position, angles in poses:
            writer.write_bar_pose(name, t, position[k], angles[k])
        if k > 0:
            if feedback:
                for b, name in enumerate(trajectory.bar_names):
                    writer.write_feedback(name, t, bar_feedback[k - 1, b], bar_reaction[k - 1, b])
            writer.write_taut(t, trajectory.string_taut[k - 1])
        if k % steps == 0:
            f = k // steps
            writer.write_puppet_state(float(trajectory.frame_time[f]), trajectory.joint_q[f], body_pos[f],
                                      trajectory.body_rot[f])


def record_simulation(model: MarionetteModel, duration: float, path: str | Path, *,
                      scene_text: str | None = None, flush_seconds: float = 1.0,
                      progress: bool = False) -> tuple[MarionetteTrajectory, Path]:
    """Simulates ``duration`` seconds of ``model`` and writes the session a live run would.

    Written: bar poses at t = 0 and after every string step (from the scene's bar
    trajectories), feedback and taut flags after every string step, and the puppet state
    at t = 0 and after every puppet step. No device channels (there is no device).

    Args:
        model: the marionette (its scene says the rates and the bars' motion).
        duration: simulated seconds (rounded up to whole puppet steps).
        path: the ``.mcap`` file to write.
        scene_text: the scene's TOML text; by default read from ``model.scene.source``.
        flush_seconds: see :class:`SessionWriter`.
        progress: show a progress bar while simulating.

    Returns:
        The simulated trajectory and the path written.
    """
    scene = model.scene
    if scene_text is None:
        source = Path(scene.source)
        if not source.is_file():
            raise ValueError(f"record_simulation: the scene's source {scene.source!r} is not a file; "
                             "pass scene_text= (the scene's TOML text)")
        scene_text = source.read_text()
    trajectory = simulate_marionette(model, duration, progress=progress, frame_hz=1.0 / model.puppet_dt)
    path = Path(path)
    with SessionWriter(path, scene, scene_text, flush_seconds=flush_seconds, recorder="simulation") as writer:
        write_simulated_run(writer, trajectory, scene.bars,
                            feedback=scene.body_effects["feedback"] and model.bar_count > 0)
    return trajectory, path


@dataclasses.dataclass(frozen=True)
class DeviceBarTrajectory(BarTrajectory):
    """A device-driven bar's recorded poses, with the velocity the live step gave it: the
    backward difference of consecutive recorded positions over the string step (eq. 4's bar
    velocity proxy). The spline's own derivative differs, so a replay's feedback channel would
    not match the recorded one. At a time between recorded poses the spline's derivative.

    Attributes:
        step: the string step [s] the live session divided by.
    """

    step: float = 1e-3

    def pose(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        position, velocity, rotation = super().pose(times)
        t = np.asarray(self.times)
        query = np.asarray(times, dtype=np.float64)
        k = np.clip(np.searchsorted(t, query), 0, len(t) - 1)
        k = np.where((k > 0) & (np.abs(t[k - 1] - query) < np.abs(t[k] - query)), k - 1, k)
        at_pose = np.abs(t[k] - query) < 1e-9  # a recorded time (up to rounding)
        p = np.asarray(self.positions, dtype=np.float64)
        difference = np.where((k > 0)[:, None], (p[k] - p[np.maximum(k - 1, 0)]) / self.step, 0.0)
        velocity[at_pose] = difference[at_pose]
        return position, velocity, rotation


def _replay_trajectory(session: Session, bar, recorded: BarTrajectory, driven: set[str]) -> BarTrajectory:
    """What drives ``bar`` in a replay: a device-driven bar its recorded poses with the live step's
    velocity; a bar whose scene trajectory is exactly its recorded poses (a scripted bar, or a
    simulated session) that trajectory, so that its velocity is the one simulated; otherwise the
    spline through its recorded poses."""
    if bar.name in driven:
        return DeviceBarTrajectory(recorded.times, recorded.positions, recorded.rotations, step=1.0 / session.string_hz)
    position, _, _ = bar.trajectory.pose(recorded.times)
    if np.array_equal(position, recorded.positions) and np.array_equal(bar.trajectory.angles(recorded.times),
                                                                       recorded.rotations):
        return bar.trajectory
    return recorded


def _as_field(value: Any) -> Any:
    return tuple(_as_field(v) for v in value) if isinstance(value, list) else value


def scene_for_replay(session: Session) -> Scene:
    """The session's scene with its recorded constants and rates, its bars driven by the
    recorded bar poses, and the strings on a bar starting from the first recorded pose.

    Raises:
        ValueError: the session lacks a bar's ``/bar/BAR/pose`` channel, or its metadata
            does not match its scene (different strings).
    """
    scene = session.scene if session.scene is not None else read_session(session.path).scene
    if scene.puppet is None:
        raise ValueError(f"{session.path}: the session's scene has no [puppet]; replay needs a marionette")
    session.require([f"/bar/{bar.name}/pose" for bar in scene.bars], "replay")
    constants = session.metadata["constants"]
    recorded = constants.get("strings", {})
    names = [s.name for s in scene.strings]
    if sorted(recorded) != sorted(names):
        raise ValueError(f"{session.path}: the metadata's strings {sorted(recorded)} differ from the embedded "
                         f"scene's {sorted(names)}")
    fields = {f.name for f in dataclasses.fields(type(scene.strings[0]))}
    strings = [dataclasses.replace(s, **{k: _as_field(v) for k, v in recorded[s.name].items() if k in fields})
               for s in scene.strings]
    trajectories = session_bar_trajectories(session)
    driven = {device.get("bar") for device in session.extra_metadata.get("live", {}).get("devices", ())}
    bars = tuple(dataclasses.replace(bar, trajectory=_replay_trajectory(session, bar, trajectories[bar.name], driven))
                 for bar in scene.bars)
    for bar in bars:  # a string on a bar starts at its attach point at the first recorded pose
        for i, spec in enumerate(strings):
            if spec.name in bar.attach:
                top = bar.attach_points(bar.trajectory.times[:1], [spec.name])[0, 0]
                strings[i] = dataclasses.replace(spec, top=tuple(float(v) for v in top))
    changes = dict(strings=tuple(strings), bars=bars, string_hz=session.string_hz, puppet_hz=session.puppet_hz)
    if "feedback" in constants:
        changes.update(feedback_stiffness=float(constants["feedback"]["stiffness"]),
                       feedback_damping=float(constants["feedback"]["damping"]))
    if "contact" in constants:
        changes["contact"] = dict(constants["contact"])
    if "world" in constants:
        changes.update(gravity=tuple(constants["world"]["gravity"]),
                       ground_height=float(constants["world"]["ground_height"]))
    if "initial_pose" in constants:
        changes["initial_pose"] = {k: tuple(v) for k, v in constants["initial_pose"].items()}
    return dataclasses.replace(scene, **changes)


def _at(times: np.ndarray, sim_times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (sampled at ``sim_times``) at ``times``, any trailing shape: the sample itself where
    a time is one of ``sim_times`` up to rounding (1e-9 s; the two sides add up step times
    differently), linearly interpolated elsewhere (interpolating between two samples at a
    time off by rounding would itself add a rounding-level gap)."""
    flat = values.reshape(len(sim_times), -1)
    out = np.stack([np.interp(times, sim_times, flat[:, j]) for j in range(flat.shape[1])], axis=1)
    nearest = np.clip(np.searchsorted(sim_times, times), 1, max(len(sim_times) - 1, 1))
    nearest = np.where(np.abs(sim_times[nearest - 1] - times) <= np.abs(sim_times[nearest] - times), nearest - 1, nearest) \
        if len(sim_times) > 1 else np.zeros(len(times), dtype=int)
    same = np.abs(sim_times[nearest] - times) < 1e-9
    out[same] = flat[nearest[same]]
    return out.reshape((len(times),) + values.shape[1:])


def replay_session(path: str | Path, *, optimization_level: int = 2, progress: bool = False,
                   device=None, require_puppet_state: bool = True) -> tuple[MarionetteTrajectory, dict[str, Any]]:
    """Re-simulates a recorded session from its recorded bar poses.

    Args:
        path: the session file (a cut-off file replays up to its last complete record).
        optimization_level: Warp optimisation of the puppet kernels (0 compiles fast).
        progress: show a progress bar.
        device: the Warp device (``None``: Warp's default).
        require_puppet_state: refuse a session without ``/puppet/state`` messages (there is
            nothing to compare the replay with); with ``False`` it is re-simulated and the
            report's ``notes`` say that nothing was compared.

    Returns:
        The re-simulated trajectory (frames at the puppet rate), and a report (JSON-ready):
        ``duration`` [s], ``frames_compared``, ``rms_body_gap`` and ``max_body_gap`` [m]
        (distance between recorded and re-simulated body centres at the recorded puppet
        times; ``None`` without ``/puppet/state``), per body ``rms_body_gap_per_body``,
        ``rms_feedback_gap`` [N] (recorded vs re-simulated eq. 4, when recorded),
        ``wall_seconds``, ``truncated``, ``notes`` (lines worth showing: cut off, bar poses
        ending before the recorded puppet states, nothing compared).

    Raises:
        ValueError: (a :class:`~dmarionette.io.session.read.SessionError`) not a session, a
            damaged one, or the channels replay needs (``/bar/BAR/pose`` for every bar, and
            ``/puppet/state`` unless ``require_puppet_state=False``) are missing.
    """
    start = time.perf_counter()
    session = read_session(path)
    scene = scene_for_replay(session)
    if require_puppet_state:
        session.require(["/puppet/state"], "replay (to compare the re-simulated puppet with the recorded one)")
    model = MarionetteModel(scene, optimization_level=optimization_level, device=device)
    if not scene.bars:
        raise ValueError(f"{session.path}: the session's scene has no [bars.*]: nothing drives a replay")
    puppet = session.channels.get("/puppet/state")
    ends = [session.channels[f"/bar/{b.name}/pose"]["t"].max() for b in scene.bars]
    if puppet is not None and len(puppet["t"]):
        ends.append(puppet["t"].max())
    end = float(max(ends))
    # Whole puppet steps, none past the last recorded pose (beyond it a bar would only be held).
    steps = int(np.floor(min(ends[:len(scene.bars)]) / model.puppet_dt + 1e-9))
    if steps < 1:
        raise ValueError(f"{session.path}: the recorded bar poses end at t = {end} s, before the first puppet "
                         f"step ({model.puppet_dt} s): nothing to replay")
    duration = (steps - 0.5) * model.puppet_dt
    trajectory = simulate_marionette(model, duration, progress=progress, frame_hz=1.0 / model.puppet_dt)
    notes = list(session.notes)
    if puppet is None or not len(puppet["t"]):
        notes.append("no /puppet/state messages: nothing to compare the replay with")
    elif puppet["t"].max() > trajectory.frame_time[-1] + model.puppet_dt + 1e-9:
        notes.append(f"the bar poses end at t = {min(ends[:len(scene.bars)]):.6g} s but the recorded puppet goes on "
                     f"to t = {puppet['t'].max():.6g} s: only the first {trajectory.frame_time[-1]:.6g} s are "
                     "replayed and compared")
    report: dict[str, Any] = {"path": str(session.path), "scene": scene.name, "duration": float(trajectory.frame_time[-1]),
                              "truncated": session.truncated, "frames_compared": 0, "rms_body_gap": None,
                              "max_body_gap": None, "rms_body_gap_per_body": None, "rms_feedback_gap": None,
                              "notes": notes}
    if puppet is not None and len(puppet["t"]):
        inside = puppet["t"] <= trajectory.frame_time[-1] + 1e-9
        t = puppet["t"][inside]
        recorded = puppet["body_pos"][inside]
        replayed = _at(t, trajectory.frame_time, trajectory.body_pos)
        gap = np.linalg.norm(recorded - replayed, axis=-1)  # (frames, bodies)
        report.update(frames_compared=int(len(t)), rms_body_gap=float(np.sqrt(np.mean(gap**2))),
                      max_body_gap=float(gap.max()),
                      rms_body_gap_per_body=dict(zip(session.bodies, np.sqrt(np.mean(gap**2, axis=0)).tolist())))
    gaps = []
    for b, name in enumerate(trajectory.bar_names):
        channel = session.channels.get(f"/bar/{name}/feedback")
        if channel is None or not len(channel["t"]):
            continue
        inside = (channel["t"] >= trajectory.step_time[0] - 1e-9) & (channel["t"] <= trajectory.step_time[-1] + 1e-9)
        replayed = _at(channel["t"][inside], trajectory.step_time, trajectory.bar_feedback[:, b])
        gaps.append(np.linalg.norm(channel["eq4"][inside] - replayed, axis=-1))
    if gaps:
        report["rms_feedback_gap"] = float(np.sqrt(np.mean(np.concatenate(gaps) ** 2)))
    report["wall_seconds"] = time.perf_counter() - start
    return trajectory, report
