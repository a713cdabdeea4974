"""The servo loop's link to the marionette, one factory per physics mode (:data:`PHYSICS_LINKS`).

Each factory sets the marionette up where its mode runs it and returns a :class:`LiveLink`:

* :func:`thread_link`: in this process (:class:`~dmarionette.live.setup.LivePhysics`), stepped
  in the servo loop's worker thread; it records the session and feeds a live view;
* :func:`process_link`: in a child process over a pipe (:class:`~dmarionette.live.process.PhysicsProcess`);
* :func:`shm_link`: in a child process over shared memory
  (:class:`~dmarionette.hw.shm_link.SharedMemoryPhysics`), with real-time priority and pinned
  CPUs where allowed.

The child processes record the session themselves, so those links only pass on the force
actually sent (with the next sample).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dmarionette.hw.shm_link import SharedMemoryPhysics
from dmarionette.live.process import LivePhysicsFactory, PhysicsProcess
from dmarionette.live.setup import LiveDevices, LivePhysics, fifo_allowed
from dmarionette.live.view import LiveViewPublisher
from dmarionette.marionette.solver import MarionetteModel

__all__ = ["PHYSICS_LINKS", "LiveLink", "LiveOptions", "process_link", "shm_link", "thread_link"]


@dataclasses.dataclass(frozen=True)
class LiveOptions:
    """What a session asks of its physics, whatever the mode (as :func:`dmarionette.live.run.run_live` takes them).

    Attributes:
        duration: How long the session may run [s].
        feedback: ``"reaction"`` or ``"eq4"``.
        force_scale: Multiplies the force before it leaves (the safety filter clamps after).
        record: The MCAP file to record the session to, or None.
        optimization_level: Puppet kernel optimisation of the child processes' models.
        realtime: Whether real-time priority (and pinning) may be asked for.
    """

    duration: float
    feedback: str = "reaction"
    force_scale: float = 1.0
    record: str | Path | None = None
    optimization_level: int = 2
    realtime: bool = True


@dataclasses.dataclass
class LiveLink:
    """How the servo loop reaches the marionette in one physics mode.

    Attributes:
        step: The servo loop's physics: a device-frame step callable or a
            :class:`~dmarionette.hw.PhysicsLink`.
        on_device: ``on_device(i, kind, value)``: device ``i`` read a sample (``kind``
            ``"sample"``) or was sent a force (``"force"``, after the safety filter).
        pid: The process that steps the marionette and writes the recording.
        close: Stops the physics and ends the recording; returns the steps run.
        servo_defaults: Servo loop options this mode sets unless the caller does.
    """

    step: Any
    on_device: Callable[[int, str, Any], None]
    pid: int
    close: Callable[[], dict[str, Any]]
    servo_defaults: dict[str, Any] = dataclasses.field(default_factory=dict)


def thread_link(model: MarionetteModel, devices: LiveDevices, options: LiveOptions,
                view: LiveViewPublisher | None) -> LiveLink:
    """``model`` itself, stepped in the servo loop's worker thread (any number of devices, a view)."""
    physics = LivePhysics(model, devices.bar, devices.mapping, options.duration, feedback=options.feedback,
                          force_scale=options.force_scale, record=options.record,
                          live_metadata=_live_metadata(devices, options), view=view)

    def on_device(i: int, kind: str, value) -> None:
        if kind == "force" and view is not None:
            view.set_force_sent(i, value)
        physics.record_device(i, kind, value)

    return LiveLink(physics.step, on_device, os.getpid(), physics.close)


def _live_metadata(devices: LiveDevices, options: LiveOptions) -> dict[str, Any] | None:
    """The recording's ``"live"`` record (``docs/session.md``), whichever process writes it; None
    when nothing is recorded."""
    if options.record is None:
        return None
    return {"devices": devices.metadata(), "feedback": options.feedback, "force_scale": float(options.force_scale)}


def _record_path(options: LiveOptions) -> str | None:
    return None if options.record is None else str(options.record)


def _send_force_with_next_sample(link) -> Callable[[int, str, Any], None]:
    """``on_device`` of a child-process link: the child records the force actually sent."""

    def on_device(i: int, kind: str, value) -> None:
        if kind == "force":
            link.last_force = value

    return on_device


def process_link(model: MarionetteModel, devices: LiveDevices, options: LiveOptions,
                 view: LiveViewPublisher | None) -> LiveLink:
    """A child process over a pipe; device frame both ways (the child maps and records)."""
    physics = PhysicsProcess(model.scene.source, devices.bars[0], options.duration, devices.mappings[0],
                             feedback=options.feedback, force_scale=options.force_scale,
                             optimization_level=options.optimization_level, record_path=_record_path(options),
                             live_metadata=_live_metadata(devices, options))
    return LiveLink(physics.step, _send_force_with_next_sample(physics), physics.pid, physics.close)


def shm_link(model: MarionetteModel, devices: LiveDevices, options: LiveOptions,
             view: LiveViewPublisher | None) -> LiveLink:
    """A child process over shared memory; with ``realtime`` both sides ask for SCHED_FIFO 10 and,
    where that is allowed and two CPUs are usable, are pinned to the first two."""
    priority = 10 if options.realtime else None
    # Pinned only with real-time priority: a pinned thread at normal priority cannot move away
    # from a busy CPU, and measured far worse on a loaded machine than an unpinned one.
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    pin = len(cpus) >= 2 and options.realtime and fifo_allowed()
    servo_cpu, physics_cpu = (cpus[0], cpus[1]) if pin else (None, None)
    factory = LivePhysicsFactory(model.scene.source, devices.bars[0], options.duration, devices.mappings[0],
                                 feedback=options.feedback, force_scale=options.force_scale,
                                 optimization_level=options.optimization_level, record_path=_record_path(options),
                                 live_metadata=_live_metadata(devices, options))
    link = SharedMemoryPhysics(factory, rate_hz=model.scene.string_hz, cpu=physics_cpu,
                               realtime_priority=priority)
    return LiveLink(link, _send_force_with_next_sample(link), link.pid, link.close,
                    servo_defaults={"cpu": servo_cpu, "realtime_priority": priority})


PHYSICS_LINKS: dict[str, Callable[[MarionetteModel, LiveDevices, LiveOptions, LiveViewPublisher | None], LiveLink]]
PHYSICS_LINKS = {"thread": thread_link, "process": process_link, "shm": shm_link}
"""The link factory of each physics mode (:data:`~dmarionette.live.setup.PHYSICS_MODES`)."""
