"""The live marionette in its own process: through a pipe (``--physics process``) or shared memory (``--physics shm``).

Shared memory: :class:`LivePhysicsFactory` builds the marionette in the child that
:class:`dmarionette.hw.shm_link.SharedMemoryPhysics` spawns; the rest of this module is the
pipe version.

In one process the physics (Warp launches, numpy) and the servo thread's deadline spin
compete for Python's interpreter lock, and the physics misses deadlines. Here the physics
runs in a child process (``spawn``: a fresh interpreter with its own lock and Warp runtime);
the servo loop's physics call sends the device sample through a pipe and blocks on the
answer, which releases the lock while the child computes.

Measured on the 2-core development VM: a pipe round trip alone costs ~160 µs (p50; process
wake-ups are expensive there), so with ~100 µs of physics this mode kept *fewer* deadlines
than the worker thread (926-1112 vs 1408-1969 string steps in 2 s over four runs each) and
is not the default. The shared-memory mode (``--physics shm``, :mod:`dmarionette.hw.shm_link`)
has no wake-ups and is the default where real-time priority is allowed (docs/hardware.md).

Both children work in the device frame: they map each device sample to the world with the
driven bar's mapping (eq. 3), step the marionette and return the force through ``W``'s
rotation, and they record the device samples and the forces sent as the device gave and got
them (device frame, as the worker-thread mode does and ``docs/session.md`` says).

Messages (pickled tuples): parent -> child ``(sample time, position (3,), orientation
quaternion (4,), buttons, t, last force sent (3,))``, the device's sample as it read it
(device frame, its own clock) and the loop time, or ``None`` to stop; child -> parent the device-frame
force ``(3,)``, or at the end a summary dict; on start the child answers ``("ready", info)`` or
``("error", text)``.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import time
from typing import Any

import numpy as np

__all__ = ["LivePhysicsFactory", "PhysicsProcess"]


@dataclasses.dataclass(frozen=True)
class LivePhysicsFactory:
    """Builds the live marionette in the shared-memory physics process (picklable: sent to the child).

    The child works in the device frame: it maps each sample to the world with ``mapping``
    (eq. 3), steps the marionette and returns the force through ``W``'s rotation, so the
    servo process only reads, filters and writes. It also writes the recording, with the
    device samples and the forces actually sent in the device frame (as the worker-thread
    mode does).

    Attributes:
        scene_ref: A built-in scene name or a scene file path (the child loads it).
        bar, duration, feedback, force_scale: As for :func:`dmarionette.live.run.make_physics_step`.
        mapping: Device-to-world mapping of the driven bar.
        optimization_level: Puppet kernel optimisation (compiled kernels are cached on disk).
        record_path: Write the session (MCAP) from the child, or None.
    """

    scene_ref: str
    bar: str
    duration: float
    mapping: Any
    feedback: str = "reaction"
    force_scale: float = 1.0
    optimization_level: int = 2
    record_path: str | None = None

    def __call__(self) -> _LivePhysics:
        return _LivePhysics(self)


class _LivePhysics:
    """The child's physics object for :class:`~dmarionette.hw.shm_link.SharedMemoryPhysics`."""

    def __init__(self, f: LivePhysicsFactory) -> None:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        from dmarionette.live.run import LiveMarionette, make_physics_step
        from dmarionette.marionette.solver import MarionetteModel
        from dmarionette.scene.scene import load_scene

        scene = load_scene(f.scene_ref)
        self.model = MarionetteModel(scene, optimization_level=f.optimization_level)
        self.live = LiveMarionette(self.model)
        self.bar = f.bar
        self.writer = None
        if f.record_path is not None:
            from pathlib import Path

            from dmarionette.io.session import SessionWriter

            self.writer = SessionWriter(f.record_path, scene, Path(scene.source).read_text())
        world_step = make_physics_step(self.live, f.bar, f.duration, feedback=f.feedback, force_scale=f.force_scale,
                                       on_tick=_recorder(self.writer, self.model, self.live, f.bar)
                                       if self.writer else None)
        self._step = f.mapping.wrap(world_step)
        self.info = {"substeps": self.model.substeps, "string_dt": self.model.string_dt}

    def force_sent(self, force: np.ndarray) -> None:
        if self.writer is not None:
            self.writer.write_force(self.bar, self.live.time, force)

    def step(self, sample, t: float) -> np.ndarray:
        if self.writer is not None:
            self.writer.write_device_sample(self.bar, sample, t=self.live.time)
        return self._step(sample, t)

    def close(self) -> dict[str, Any]:
        if self.writer is not None:
            self.writer.close()
        live = self.live
        return {"string_steps": live.tick, "puppet_steps": live.tick // self.model.substeps,
                "simulated_seconds": round(live.time, 4), "physics_cpu_seconds": round(time.process_time(), 3)}


def _physics_main(conn, scene_ref: str, bar: str, duration: float, mapping, feedback: str, force_scale: float,
                  optimization_level: int, record_path: str | None) -> None:
    """The child: builds the live marionette, then answers one device-frame force per device-frame sample."""
    try:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        from dmarionette.hw.device import HapticSample
        from dmarionette.live.run import LiveMarionette, make_physics_step
        from dmarionette.marionette.solver import MarionetteModel
        from dmarionette.scene.scene import load_scene

        scene = load_scene(scene_ref)
        model = MarionetteModel(scene, optimization_level=optimization_level)
        live = LiveMarionette(model)
        writer = None
        if record_path is not None:
            from pathlib import Path

            from dmarionette.io.session import SessionWriter

            writer = SessionWriter(record_path, scene, Path(scene.source).read_text())
        step = mapping.wrap(make_physics_step(live, bar, duration, feedback=feedback, force_scale=force_scale,
                                              on_tick=_recorder(writer, model, live, bar) if writer else None))
        # Kernels compile and graphs are captured above, before the parent's loop starts.
    except Exception as error:  # reported to the parent, which raises it with context
        conn.send(("error", f"{type(error).__name__}: {error}"))
        return
    conn.send(("ready", {"substeps": model.substeps, "string_dt": model.string_dt}))
    try:
        while True:
            message = conn.recv()
            if message is None:
                break
            sample_time, position, orientation, buttons, t, last_force = message
            if writer is not None and last_force is not None:
                writer.write_force(bar, live.time, last_force)
            sample = HapticSample(sample_time, position, orientation, buttons)  # as the device gave it
            if writer is not None:
                writer.write_device_sample(bar, sample, t=live.time)
            conn.send(np.asarray(step(sample, t), dtype=np.float64))
    finally:
        if writer is not None:
            writer.close()
        conn.send({"string_steps": live.tick, "puppet_steps": live.tick // model.substeps,
                   "simulated_seconds": round(live.time, 4)})


def _recorder(writer, model, live, bar):
    from dmarionette.live.run import _record_tick

    return lambda tick, poses: _record_tick(writer, model, live, tick, poses)


class PhysicsProcess:
    """The live marionette in a child process; ``step(sample_device, t) -> force_device``.

    Args:
        scene_ref: a built-in scene name or a scene file path (the child loads it).
        bar, duration, feedback, force_scale: as for :func:`dmarionette.live.run.make_physics_step`.
        mapping: the driven bar's device-to-world mapping (a
            :class:`~dmarionette.hw.DeviceMapping`); the child maps samples and forces with it.
        optimization_level: puppet kernel optimisation (compiled kernels are cached on disk).
        record_path: write the session (MCAP) from the child, or None.
        start_timeout: seconds to wait for the child to build the model.
    """

    def __init__(self, scene_ref: str, bar: str, duration: float, mapping, *, feedback: str = "reaction",
                 force_scale: float = 1.0, optimization_level: int = 2, record_path: str | None = None,
                 start_timeout: float = 300.0):
        context = mp.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_physics_main, name="dmarionette-physics", daemon=True,
            args=(child, scene_ref, bar, duration, mapping, feedback, force_scale, optimization_level, record_path))
        self._process.start()
        if not self._conn.poll(start_timeout):
            self._process.kill()
            raise RuntimeError(f"the physics process did not start within {start_timeout} s")
        kind, info = self._conn.recv()
        if kind == "error":
            self._process.join(5.0)
            raise RuntimeError(f"the physics process could not start: {info}")
        self.info = info
        self.pid = self._process.pid
        self.last_force: np.ndarray | None = None
        self.summary: dict[str, Any] = {}

    def step(self, sample, t: float) -> np.ndarray:
        """Sends a device-frame sample, returns the device-frame force (blocks without holding the GIL)."""
        self._conn.send((float(sample.time), np.asarray(sample.position, dtype=np.float64),
                         np.asarray(sample.orientation, dtype=np.float64), int(sample.buttons), float(t),
                         self.last_force))
        return self._conn.recv()

    def close(self) -> dict[str, Any]:
        """Stops the child; returns its summary (steps run)."""
        if self._process.is_alive():
            self._conn.send(None)
            if self._conn.poll(30.0):
                self.summary = self._conn.recv()
            self._process.join(30.0)
        if self._process.is_alive():
            self._process.kill()
        return self.summary
