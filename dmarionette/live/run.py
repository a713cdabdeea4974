"""Live puppetry: the marionette stepped one string step per servo tick (paper §3-4).

:class:`LiveMarionette` advances the marionette by one string step per call, running the
puppet every ``n`` calls: the passes of one puppet step are captured as ``n`` Warp graphs,
one per string-step index, so a tick costs one graph replay and a little host work.

:func:`make_physics_step` turns a haptic device's samples into a bar's pose: the device tip sits
at the bar's centre (paper §3.1) and is mapped to the world by ``P' = S W P`` (eq. 3,
:class:`dmarionette.hw.mapping.DeviceMapping`); the force sent back is the driven bar's
feedback, through ``W``'s rotation only, then the servo loop's safety filter.

Several devices may drive several bars (the paper's two Omnis, one per bar): each has its
own mapping (its origin at its bar's start), feels its own bar's force and has its own
safety filter, all in the same servo ticks (:class:`dmarionette.hw.ServoLoop` with a sequence
of devices); this runs in the ``"thread"`` physics mode.

:func:`run_live` runs a session; the pieces it is set up from (devices by name, their
mappings, the physics mode) are in :mod:`dmarionette.live.setup`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Callable, Sequence

import numpy as np
import warp as wp

from dmarionette.hw.device import AbstractHapticDevice
from dmarionette.live.setup import (DEFAULT_PHYSICS, PHYSICS_MODES, SIMULATED_TABLE_HZ, RecordingDevice, bar_mapping,
                         fifo_allowed, make_device, resolve_physics)
from dmarionette.live.view import scripted_rotations
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette, bar_inputs

# The session set-up (devices, mappings, physics modes) lives in dmarionette.live.setup; its
# public names are re-exported here, where callers have always found them.
__all__ = ["DEFAULT_PHYSICS", "PHYSICS_MODES", "SIMULATED_TABLE_HZ", "LiveMarionette", "LiveTick", "bar_mapping",
           "fifo_allowed", "make_device", "make_physics_step", "resolve_physics", "run_live"]



@dataclasses.dataclass
class LiveTick:
    """What one tick produced (world frame)."""

    t: float
    bar_feedback: np.ndarray  # eq. 4 per bar [N], (B, 3)
    bar_reaction: np.ndarray  # exact reaction per bar [N], (B, 3)
    string_taut: np.ndarray  # (S,)
    puppet_stepped: bool  # True on the tick that completed a puppet step


class LiveMarionette:
    """Steps a marionette one string step at a time.

    Args:
        model: the marionette (its scene's bars give the poses of bars no device drives).
    """

    def __init__(self, model: MarionetteModel):
        self.model = model
        self.solver = SolverMarionette(model)
        self.state = model.state()
        self._next = model.state()
        self.control = model.control()
        self.tick = 0
        # One eager puppet step loads every module; then start again from rest.
        self.solver.step(self.state, self._next, self.control)
        self.state = model.state()
        self._next.assign(self.state)
        self._graphs = [self._capture(j) for j in range(model.substeps)]
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        self._top_q = self.control.top_q.numpy()  # host views of the control buffers (CPU)
        self._bar_q = self.control.bar_q.numpy()
        self._bar_qd = self.control.bar_qd.numpy()
        self._feedback = self._next.bar_feedback.numpy()
        self._reaction = self._next.bar_reaction.numpy()
        self._taut = self._next.string_taut.numpy()
        # Where the latest string state is after string step j of a puppet step: the solver's
        # two spare string states in turn, and the step's output (then assigned to self.state)
        # after the last one (see SolverMarionette.step_string).
        self._particle_after = [self.solver.string_state_after(self.state, j).particle_q.numpy()
                                for j in range(n)]
        assert self._top_q.shape == (n, s, 3) and self._bar_q.shape == (n, b, 3)

    def reset(self) -> None:
        """Back to the scene's rest state at time 0 (the captured graphs are kept)."""
        self.state.assign(self.model.state())
        self._next.assign(self.state)
        self.tick = 0

    def _capture(self, j: int):
        n = self.model.substeps
        with wp.ScopedCapture(device=self.model.device) as capture:
            if j == 0:
                self.model.puppet_solver.eval_kinematics(self.state.puppet)  # body poses, for the view
                self.solver.begin_step(self.state, self._next)
            self.solver.step_string(self.state, self._next, self.control, j)
            if j == n - 1:
                self.solver.end_step(self.state, self._next)
                self.state.assign(self._next)
        return capture.graph

    @property
    def time(self) -> float:
        """Simulated time [s] after the ticks run so far."""
        return self.tick * self.model.string_dt

    def latest_particle_q(self) -> np.ndarray:
        """Host view of the string particles after the latest tick [m], ``(P, 3)`` float64 (do not
        keep it: the next ticks overwrite it). Float32 strings give a float64 copy instead."""
        return np.asarray(self._particle_after[(self.tick - 1) % self.model.substeps], dtype=np.float64)

    def latest_string_taut(self) -> np.ndarray:
        """Host view of the taut flags after the latest tick, ``(S,)``."""
        return self._taut[(self.tick - 1) % self.model.substeps]

    def advance(self, tops: np.ndarray, bar_q: np.ndarray, bar_qd: np.ndarray) -> LiveTick:
        """One string step with the string tops ``(S, 3)`` and bar centres/velocities ``(B, 3)`` at its end."""
        j = self.tick % self.model.substeps
        self._top_q[j] = tops
        if self.model.bar_count:
            self._bar_q[j] = bar_q
            self._bar_qd[j] = bar_qd
        wp.capture_launch(self._graphs[j])
        self.tick += 1
        return LiveTick(t=self.time, bar_feedback=self._feedback[j].copy(), bar_reaction=self._reaction[j].copy(),
                        string_taut=self._taut[j].copy(), puppet_stepped=j == self.model.substeps - 1)


def make_physics_step(live: LiveMarionette, driven_bar: str | Sequence[str], duration: float, *,
                      feedback: str = "reaction", force_scale: float = 1.0,
                      on_tick: Callable[[LiveTick, dict], None] | None = None, view=None):
    """A world-frame physics callback for the servo loop: the device (or devices) drive bars.

    Args:
        live: the marionette stepped per tick.
        driven_bar: the bar whose centre follows the (mapped) device tip; or a sequence of
            distinct bars, one per device, in the servo loop's device order. Other bars follow
            the scene's trajectories.
        duration: how long the session may run [s]; the scripted bars' inputs are evaluated
            for it beforehand (a spline evaluation per tick would cost a large part of a tick).
        feedback: ``"reaction"`` (the strings' pull on the bar) or ``"eq4"`` (the paper's eq. 4 as
            printed, which spans the whole string length and is large).
        force_scale: multiplies the force before it leaves (the safety filter clamps after).
        on_tick: called each tick with the tick and every bar's pose at its end,
            ``{bar: (position (3,), rotation (3,) XYZ deg)}``.
        view: a :class:`dmarionette.live.view.LiveViewPublisher` given a snapshot whenever one
            is due (a clock read per tick otherwise), or None.

    Returns:
        For one bar (a name): ``step(sample_world, t) -> force_world (3,)`` (wrap with
        ``DeviceMapping.wrap``). For a sequence: ``step(samples_world, t) -> forces_world
        (n, 3)``, row ``i`` the force on bar ``i`` (wrap with ``DeviceMapping.wrap_many``).
    """
    model = live.model
    names = [s.name for s in model.scene.strings]
    bars = model.scene.bars
    several = not isinstance(driven_bar, str)
    driven_names = list(driven_bar) if several else [driven_bar]
    for name in driven_names:
        if name not in model.bar_names:
            raise ValueError(f"driven bar: got {name!r}; expected one of {model.bar_names}")
    if not driven_names or len(set(driven_names)) != len(driven_names):
        raise ValueError(f"driven bars: got {driven_names}; expected distinct bars, one per device")
    if feedback not in ("reaction", "eq4"):
        raise ValueError(f"feedback: got {feedback!r}; expected 'reaction' or 'eq4'")
    driven = [model.bar_names.index(name) for name in driven_names]
    carried = [[i for i, n in enumerate(names) if n in bar.attach] for bar in bars]
    local = [np.array([bar.attach[names[i]] for i in idx]).reshape(-1, 3) for bar, idx in zip(bars, carried)]
    previous: list[np.ndarray | None] = [None] * len(driven)
    ticks = int(np.ceil(duration / model.string_dt)) + 2
    tick_times = model.string_dt * np.arange(1, ticks + 1)  # the end of each string step
    scripted = bar_inputs(model, tick_times)
    scripted_angles = [bar.trajectory.angles(tick_times) for bar in bars]

    def step_all(samples, _t: float) -> np.ndarray:
        k = min(live.tick, ticks - 1)  # past the planned duration the scripted bars hold still
        tops, bar_q, bar_qd = scripted[0][k].copy(), scripted[1][k].copy(), scripted[2][k].copy()
        rotations = []
        for i, (b, sample) in enumerate(zip(driven, samples, strict=True)):
            position = np.asarray(sample.position, dtype=np.float64)
            velocity = np.zeros(3) if previous[i] is None else (position - previous[i]) / model.string_dt
            previous[i] = position
            rotation = sample.rotation
            rotations.append(rotation)
            bar_q[b], bar_qd[b] = position, velocity
            tops[carried[b]] = position + local[b] @ rotation.T
        tick = live.advance(tops, bar_q, bar_qd)
        if on_tick is not None:
            poses = {name: (bar_q[b], scripted_angles[b][k]) for b, name in enumerate(model.bar_names)}
            for b, rotation in zip(driven, rotations):
                poses[model.bar_names[b]] = (bar_q[b], _matrix_to_euler_deg(rotation))
            on_tick(tick, poses)
        if view is not None and view.due():
            all_rotations = scripted_rotations(scripted_angles, k)
            for b, rotation in zip(driven, rotations):
                all_rotations[b] = rotation
            view.publish(live, bar_q, all_rotations, tick.bar_reaction)
        force = tick.bar_reaction[driven] if feedback == "reaction" else tick.bar_feedback[driven]
        return force_scale * force

    if several:
        return step_all

    def step(sample, t: float) -> np.ndarray:
        return step_all((sample,), t)[0]

    return step


def _matrix_to_euler_deg(r: np.ndarray) -> np.ndarray:
    """XYZ Euler angles [deg] of ``R = Rz Ry Rx`` (inverse of :func:`euler_to_matrix`)."""
    ry = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    rx = np.arctan2(r[2, 1], r[2, 2])
    rz = np.arctan2(r[1, 0], r[0, 0])
    return np.degrees([rx, ry, rz])




def run_live(model: MarionetteModel, *, device: str | AbstractHapticDevice | Sequence = "simulated",
             bar: str | Sequence[str] = "main", duration: float = 10.0, record=None, feedback: str = "reaction",
             force_scale: float = 1.0, workspace_scale: float | Sequence[float] = 1.0, process: bool = False,
             optimization_level: int = 2, session=None, physics: str | None = None, realtime: bool = True,
             on_start: Callable[[dict], None] | None = None, view=None, **servo_options):
    """Live puppetry: a device drives ``bar`` through the 1 kHz servo loop (paper §3).

    The device tip maps to the bar's centre with ``P' = S W P``: ``S`` the uniform
    ``workspace_scale``, ``W`` a translation (by the bar's start divided by ``S``) putting the
    device origin at the bar's start. A device displacement ``d`` moves the bar by ``S d``, so a
    world stiffness ``k`` is felt as ``S k`` (:meth:`~dmarionette.hw.DeviceMapping.stiffness_to_device`;
    the force itself is not scaled). Where the marionette runs is ``physics`` (:data:`~dmarionette.live.setup.PHYSICS_MODES` or ``"auto"``;
    :data:`~dmarionette.live.setup.DEFAULT_PHYSICS` when None, ``"process"`` when ``process=True``, the older spelling):

    * ``"thread"``: ``model`` itself, in the servo loop's worker thread;
    * ``"process"``: a child process over a pipe (:mod:`dmarionette.live.process`);
    * ``"auto"``: ``"thread"`` with a ``view`` or several devices; otherwise ``"shm"`` where
      SCHED_FIFO is allowed (and ``realtime``), else ``"thread"``;
    * ``"shm"``: a child process over shared memory (:mod:`dmarionette.hw.shm_link`); with
      ``realtime`` the servo thread and the child ask for SCHED_FIFO priority 10 (refusal is
      noted in the statistics, not an error) and, when it is allowed and there are two or
      more usable CPUs, are pinned to the first two.

    The child processes build the model from the scene's file with ``optimization_level``.
    ``record``: an MCAP file path for the session, or None. ``on_start``: called just before
    the servo loop starts, with ``{"physics": mode, "physics_pid": pid, "stop": callable}`` (the pid
    of the process that steps the marionette and writes the recording; ``stop()``, from any thread,
    ends the session after the current tick, as the end of ``duration`` would). ``servo_options`` go to
    :class:`dmarionette.hw.ServoLoop`.
    ``device``: a name (:func:`~dmarionette.live.setup.make_device`) or a device object (its frame: the world shifted to
    the bar's start, as for ``simulated``).

    Several devices: ``device`` a list (names or objects) and ``bar`` a list of as many distinct
    bars, device ``i`` driving bar ``i`` (the paper's two Omnis); ``workspace_scale`` one for all
    or a list, one per device. Each device has its own mapping ``P' = S_i W_i P`` (origin at its
    bar's start), feels its own bar's force through ``W_i``'s rotation and has its own safety
    filter; one servo loop reads and writes all of them each tick, and every way out turns
    every device's motors off. Physics ``"thread"`` only (``"auto"`` is ``"thread"``).

    ``view``: a :class:`~dmarionette.live.view.AbstractLiveView` (the browser view
    :class:`dmarionette.live.view_viser.LiveViewServer`, or
    :class:`~dmarionette.live.view.LiveViewHeadless`), or None. It gets snapshots at its rate
    from the physics thread, so it needs ``physics`` ``"thread"`` (or ``"auto"``, which then is
    ``"thread"``); ``"process"`` or ``"shm"`` with a view raise ValueError before anything is
    built. Each device that is a :class:`~dmarionette.hw.HapticDeviceSimulated` gets a
    ``drag(position, rotation)`` (world frame, through its own mapping) that moves it
    (:meth:`~dmarionette.hw.HapticDeviceSimulated.drag_to`): ``view.connect_device(drag)`` for one
    device, ``view.connect_devices([drag or None per device])`` for several (the view's geometry
    then names the devices' bars, ``LiveViewGeometry.from_model(model, bars)``); the snapshots
    carry every device's force sent (world frame), one row per device.

    Returns:
        ``(servo statistics, summary dict)``. With several devices the summary's ``device``,
        ``bar``, ``workspace_scale``, ``peak_force_sent_N`` and ``max_force_N`` are lists, one
        entry per device.
    """

    from dmarionette.hw import DeviceMapping, ServoLoop

    several = isinstance(device, (list, tuple))
    devices = list(device) if several else [device]
    bars = [bar] if isinstance(bar, str) else list(bar)
    scales = (list(workspace_scale) if isinstance(workspace_scale, (list, tuple, np.ndarray))
              else [workspace_scale] * len(bars))
    if len(devices) != len(bars) or not bars:
        raise ValueError(f"--device/--bar: got {len(devices)} device(s) {devices} and {len(bars)} bar(s) {bars}; "
                         "expected one bar per device")
    if len(scales) != len(bars):
        raise ValueError(f"--workspace-scale: got {len(scales)} values {scales} for {len(bars)} devices; expected "
                         "one for all or one per device")
    if len(set(bars)) != len(bars):
        raise ValueError(f"--bar: got {bars}; expected a different bar for each device")
    mode = resolve_physics(physics, process=process, realtime=realtime, view=view is not None, devices=len(devices))

    scene = model.scene
    for name in bars:
        if name not in model.bar_names:
            raise ValueError(f"--bar: got {name!r}; expected one of {model.bar_names}")
    starts = [np.array(scene.bars[model.bar_names.index(name)].trajectory.positions[0], dtype=np.float64)
              for name in bars]
    mappings = [bar_mapping(model, name, scale) for name, scale in zip(bars, scales)]
    haptics, device_names = [], []
    for name, bar_name, start, scale in zip(devices, bars, starts, scales):
        if isinstance(name, AbstractHapticDevice):
            haptics.append(name)
            device_names.append(type(name).__name__)
        else:
            haptics.append(make_device(name, scene, bar_name, trajectory_offset=start, session=session,
                                       duration=duration, workspace_scale=float(scale)))
            device_names.append(name)
    bar, mapping, haptic, start = bars[0], mappings[0], haptics[0], starts[0]  # the single-device modes
    peaks = [0.0] * len(haptics)
    publisher = None
    if view is not None:
        from dmarionette.hw import HapticDeviceSimulated
        from dmarionette.live.view import LiveViewPublisher

        publisher = LiveViewPublisher(view.buffer, view.rate_hz, force_to_world=[m.force_to_world for m in mappings]
                                      if several else mapping.force_to_world)

        def make_drag(h: AbstractHapticDevice, m) -> Callable[[np.ndarray, np.ndarray], None] | None:
            if not isinstance(h, HapticDeviceSimulated):
                return None

            def drag(position_world, rotation_world) -> None:  # the view's pose, through this device's mapping
                h.drag_to(m.position_to_device(position_world), m.rotation.T @ rotation_world)
                publisher.dragged = True

            return drag

        drags = [make_drag(h, m) for h, m in zip(haptics, mappings)]
        if several:
            view.connect_devices(drags)
        else:
            view.connect_device(drags[0])
    if mode == "shm":
        from dmarionette.hw.shm_link import SharedMemoryPhysics
        from dmarionette.live.process import LivePhysicsFactory

        priority = 10 if realtime else None
        # Pinned only with real-time priority: a pinned thread at normal priority cannot move away
        # from a busy CPU, and measured far worse on a loaded machine than an unpinned one.
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        pin = len(cpus) >= 2 and realtime and fifo_allowed()
        servo_cpu, physics_cpu = (cpus[0], cpus[1]) if pin else (None, None)
        servo_options.setdefault("cpu", servo_cpu)
        servo_options.setdefault("realtime_priority", priority)
        factory = LivePhysicsFactory(scene.source, bar, duration, mapping, feedback=feedback, force_scale=force_scale,
                                     optimization_level=optimization_level,
                                     record_path=None if record is None else str(record))
        physics_link = SharedMemoryPhysics(factory, rate_hz=scene.string_hz, cpu=physics_cpu,
                                           realtime_priority=priority)

        def on_device(kind: str, value) -> None:
            if kind == "force":
                physics_link.last_force = value  # the child records what was actually sent
                peaks[0] = max(peaks[0], float(np.linalg.norm(value)))

        device_step = physics_link
        handlers = [on_device]
    elif mode == "process":
        from dmarionette.live.process import PhysicsProcess

        physics = PhysicsProcess(scene.source, bar, duration, mapping, feedback=feedback, force_scale=force_scale,
                                 optimization_level=optimization_level,
                                 record_path=None if record is None else str(record))

        def on_device(kind: str, value) -> None:
            if kind == "force":
                physics.last_force = value  # the child records what was actually sent
                peaks[0] = max(peaks[0], float(np.linalg.norm(value)))

        device_step = physics.step  # device frame both ways: the child maps (and records device samples)
        handlers = [on_device]
    else:
        live = LiveMarionette(model)
        writer = None
        if record is not None:
            from pathlib import Path

            from dmarionette.io.session import SessionWriter

            writer = SessionWriter(record, scene, Path(scene.source).read_text())
            writer.write_metadata("live", {
                "devices": [{"bar": b, "device": n, "workspace_scale": float(s), "S": m.scale.tolist(),
                             "W": m.device_to_world.tolist(), "max_force_N": h.spec.max_force,
                             "max_continuous_force_N": h.spec.max_continuous_force}
                            for b, n, s, m, h in zip(bars, device_names, scales, mappings, haptics)],
                "feedback": feedback, "force_scale": float(force_scale)})
        lock = threading.Lock()

        def make_handler(i: int) -> Callable[[str, object], None]:
            def on_device(kind: str, value) -> None:
                if kind == "force":
                    peaks[i] = max(peaks[i], float(np.linalg.norm(value)))
                    if publisher is not None:
                        publisher.set_force_sent(i, value)
                if writer is not None:
                    with lock:
                        if kind == "sample":
                            writer.write_device_sample(bars[i], value, t=live.time)
                        else:
                            writer.write_force(bars[i], live.time, value)

            return on_device

        handlers = [make_handler(i) for i in range(len(haptics))]

        def on_tick(tick: LiveTick, poses: dict) -> None:
            with lock:
                _record_tick(writer, model, live, tick, poses)

        world_step = make_physics_step(live, bars if several else bar, duration, feedback=feedback,
                                       force_scale=force_scale, on_tick=on_tick if writer is not None else None,
                                       view=publisher)
        device_step = DeviceMapping.wrap_many(mappings, world_step) if several else mapping.wrap(world_step)
    proxies = [RecordingDevice(h, handler, label=f"device {i} ({n}, bar {b!r})" if several else None)
               for i, (h, handler, n, b) in enumerate(zip(haptics, handlers, device_names, bars))]
    try:
        loop = ServoLoop(proxies if several else proxies[0], device_step, rate_hz=scene.string_hz, **servo_options)
        if on_start is not None:
            pid = {"shm": lambda: physics_link.pid, "process": lambda: physics.pid}.get(mode, os.getpid)()
            on_start({"physics": mode, "physics_pid": pid, "stop": loop.request_stop})
        stats = loop.run(duration)
    finally:
        for h in haptics:  # ServoLoop.run closed them (motors off); again in case it never started
            h.close()
        if mode == "shm":
            steps = physics_link.close()
        elif mode == "process":
            steps = physics.close()
        else:
            if writer is not None:
                writer.close()
            steps = {"string_steps": live.tick, "puppet_steps": live.tick // model.substeps,
                     "simulated_seconds": round(live.time, 4)}
    names = {"thread": "servo worker thread", "process": "own process", "shm": "own process, shared memory"}
    peak = [round(p, 4) for p in peaks]
    limit = [h.spec.max_force for h in haptics]
    summary = {"device": device_names if several else device_names[0], "bar": bars if several else bar,
               "physics": names[mode], "physics_mode": mode, **steps,
               "peak_force_sent_N": peak if several else peak[0], "max_force_N": limit if several else limit[0]}
    if several:
        summary["workspace_scale"] = [float(s) for s in scales]
    if view is not None:
        summary["view_snapshots"] = view.buffer.published
    latencies = [x for p in proxies for x in p.latencies]
    if latencies:
        latency = np.array(latencies) * 1e6
        summary["device_to_force_us"] = {"p50": round(float(np.median(latency)), 1),
                                         "p99": round(float(np.percentile(latency, 99)), 1),
                                         "max": round(float(latency.max()), 1)}
    return stats, summary


def _record_tick(writer, model: MarionetteModel, live: LiveMarionette, tick: LiveTick, poses: dict) -> None:
    """Writes one tick of a live session: every bar's pose and feedback, taut flags, puppet state."""
    for b, name in enumerate(model.bar_names):
        writer.write_feedback(name, tick.t, tick.bar_feedback[b], tick.bar_reaction[b])
        writer.write_bar_pose(name, tick.t, *poses[name])
    writer.write_taut(tick.t, tick.string_taut)
    if tick.puppet_stepped:
        model.puppet_solver.eval_kinematics(live.state.puppet)
        writer.write_puppet_state(tick.t, live.state.puppet.joint_q.numpy()[0].copy(),
                                  live.state.puppet.body_pos.numpy()[0].copy(),
                                  live.state.puppet.body_rot.numpy()[0].copy())
