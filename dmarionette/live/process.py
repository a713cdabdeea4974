"""The live marionette in its own process: through a pipe (``--physics process``) or shared memory (``--physics shm``).

:class:`LivePhysicsFactory` builds the marionette in the child (:class:`ChildPhysics`, one
device, device frame): called, in the child that :class:`dmarionette.hw.shm_link.SharedMemoryPhysics`
spawns; through :meth:`LivePhysicsFactory.build`, in the one :class:`PhysicsProcess` spawns (the
pipe version, the rest of this module).

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

from dmarionette.hw.device import HapticSample
from dmarionette.live.setup import LivePhysics

__all__ = ["ChildPhysics", "LivePhysicsFactory", "PhysicsProcess"]


@dataclasses.dataclass(frozen=True)
class LivePhysicsFactory:
    """Builds the live marionette in a physics process (picklable: sent to the child).

    Called, it builds the physics object that :class:`dmarionette.hw.shm_link.SharedMemoryPhysics`
    runs in its child; :class:`PhysicsProcess` builds its child's with :meth:`build`. The child
    works in the device frame: it maps each sample to the world with ``mapping`` (eq. 3), steps
    the marionette and returns the force through ``W``'s rotation, so the servo process only
    reads, filters and writes. It also writes the recording, with the device samples and the
    forces actually sent in the device frame (as the worker-thread mode does).

    Attributes:
        scene_ref: A built-in scene name or a scene file path (the child loads it).
        bar, duration, feedback, force_scale: As for :func:`dmarionette.live.physics.make_physics_step`.
        mapping: Device-to-world mapping of the driven bar.
        optimization_level: Puppet kernel optimisation (compiled kernels are cached on disk).
        record_path: Write the session (MCAP) from the child, or None.
        live_metadata: The recording's ``"live"`` record (devices, mappings, feedback), or None.
    """

    scene_ref: str
    bar: str
    duration: float
    mapping: Any
    feedback: str = "reaction"
    force_scale: float = 1.0
    optimization_level: int = 2
    record_path: str | None = None
    live_metadata: dict[str, Any] | None = None

    def build(self) -> LivePhysics:
        """Loads the scene and sets the marionette up: kernels compile and graphs are captured
        here, before the parent's loop starts."""
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        from dmarionette.first_run import init_warp

        init_warp()  # this fresh interpreter's Warp, without the CUDA-driver notice on a CPU-only machine
        from dmarionette.marionette.solver import MarionetteModel
        from dmarionette.scene.scene import load_scene

        model = MarionetteModel(load_scene(self.scene_ref), optimization_level=self.optimization_level)
        return LivePhysics(model, self.bar, self.mapping, self.duration, feedback=self.feedback,
                           force_scale=self.force_scale, record=self.record_path, live_metadata=self.live_metadata)

    def __call__(self) -> _SharedMemoryChild:
        return _SharedMemoryChild(self.build())


class ChildPhysics:
    """One device's marionette in a physics process, device frame both ways; it records the
    samples as the device gave them and the forces as the device got them.

    Args:
        physics: The marionette, set up for one driven bar.
    """

    def __init__(self, physics: LivePhysics) -> None:
        self.physics = physics
        model = physics.live.model
        self.info = {"substeps": model.substeps, "string_dt": model.string_dt}

    def force_sent(self, force: np.ndarray) -> None:
        """Records the force last written to the device (after the safety filter)."""
        self.physics.record_device(0, "force", force)

    def step(self, sample: HapticSample, t: float) -> np.ndarray:
        """Records the sample, then steps the marionette: the device-frame force ``(3,)``."""
        self.physics.record_device(0, "sample", sample)
        return self.physics.step(sample, t)

    def close(self) -> dict[str, Any]:
        """Ends the recording; returns the steps run."""
        return self.physics.close()


class _SharedMemoryChild(ChildPhysics):
    """The shared-memory child's physics: its summary also gives the CPU time it used."""

    def close(self) -> dict[str, Any]:
        return {**super().close(), "physics_cpu_seconds": round(time.process_time(), 3)}


def _physics_main(conn, factory: LivePhysicsFactory) -> None:
    """The pipe child: builds the live marionette, then answers one device-frame force per device-frame sample."""
    try:
        physics = ChildPhysics(factory.build())
    except Exception as error:  # reported to the parent, which raises it with context
        conn.send(("error", f"{type(error).__name__}: {error}"))
        return
    conn.send(("ready", physics.info))
    try:
        while True:
            message = conn.recv()
            if message is None:
                break
            sample_time, position, orientation, buttons, t, last_force = message
            if last_force is not None:
                physics.force_sent(last_force)
            sample = HapticSample(sample_time, position, orientation, buttons)  # as the device gave it
            conn.send(np.asarray(physics.step(sample, t), dtype=np.float64))
    finally:
        conn.send(physics.close())


class PhysicsProcess:
    """The live marionette in a child process; ``step(sample_device, t) -> force_device``.

    Args:
        scene_ref: a built-in scene name or a scene file path (the child loads it).
        bar, duration, feedback, force_scale: as for :func:`dmarionette.live.physics.make_physics_step`.
        mapping: the driven bar's device-to-world mapping (a
            :class:`~dmarionette.hw.DeviceMapping`); the child maps samples and forces with it.
        optimization_level: puppet kernel optimisation (compiled kernels are cached on disk).
        record_path: write the session (MCAP) from the child, or None.
        live_metadata: the recording's ``"live"`` record, or None.
        start_timeout: seconds to wait for the child to build the model.
    """

    def __init__(self, scene_ref: str, bar: str, duration: float, mapping, *, feedback: str = "reaction",
                 force_scale: float = 1.0, optimization_level: int = 2, record_path: str | None = None,
                 live_metadata: dict[str, Any] | None = None, start_timeout: float = 300.0):
        context = mp.get_context("spawn")
        self._conn, child = context.Pipe()
        factory = LivePhysicsFactory(scene_ref, bar, duration, mapping, feedback=feedback, force_scale=force_scale,
                                     optimization_level=optimization_level, record_path=record_path,
                                     live_metadata=live_metadata)
        self._process = context.Process(target=_physics_main, name="dmarionette-physics", daemon=True,
                                        args=(child, factory))
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
