"""Live puppetry: :func:`run_live`, a session of the marionette driven by haptic devices (paper §3-4).

``run_live`` is a dispatcher: it pairs devices with bars and opens them
(:mod:`dmarionette.live.setup`), chooses the physics mode, lets the mode's factory
(:data:`dmarionette.live.links.PHYSICS_LINKS`) set the marionette up where it runs, runs the
servo loop (:class:`dmarionette.hw.ServoLoop`) over that link and sums the session up.

The per-tick marionette and the servo loop's physics callback are in
:mod:`dmarionette.live.physics`; the session set-up (devices, mappings, physics modes) in
:mod:`dmarionette.live.setup`. Their public names are re-exported here, where callers have
always found them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from dmarionette.hw import ServoLoop
from dmarionette.hw.device import AbstractHapticDevice
from dmarionette.live.links import PHYSICS_LINKS, LiveLink, LiveOptions
from dmarionette.live.physics import LiveMarionette, LiveTick, make_physics_step
from dmarionette.live.setup import (DEFAULT_PHYSICS, PHYSICS_MODES, SIMULATED_TABLE_HZ, LiveDevices, RecordingDevice,
                                    bar_mapping, connect_view, fifo_allowed, make_device, open_devices, pair_devices,
                                    resolve_physics)
from dmarionette.marionette.solver import MarionetteModel

__all__ = ["DEFAULT_PHYSICS", "PHYSICS_MODES", "SIMULATED_TABLE_HZ", "LiveMarionette", "LiveTick", "bar_mapping",
           "fifo_allowed", "make_device", "make_physics_step", "resolve_physics", "run_live"]

PHYSICS_NAMES = {"thread": "servo worker thread", "process": "own process", "shm": "own process, shared memory"}
"""How a session's summary names each physics mode (its ``"physics"`` entry)."""


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
    the force itself is not scaled). Where the marionette runs is ``physics``
    (:data:`~dmarionette.live.setup.PHYSICS_MODES` or ``"auto"``; :data:`~dmarionette.live.setup.DEFAULT_PHYSICS`
    when None, ``"process"`` when ``process=True``, the older spelling), each mode set up by its
    factory in :data:`dmarionette.live.links.PHYSICS_LINKS`:

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
    several = isinstance(device, (list, tuple))
    devices, bars, scales = pair_devices(device, bar, workspace_scale)
    mode = resolve_physics(physics, process=process, realtime=realtime, view=view is not None, devices=len(devices))
    opened = open_devices(model, devices, bars, scales, several=several, session=session, duration=duration)
    publisher = None if view is None else connect_view(view, opened)
    options = LiveOptions(duration, feedback=feedback, force_scale=force_scale, record=record,
                          optimization_level=optimization_level, realtime=realtime)
    link = PHYSICS_LINKS[mode](model, opened, options, publisher)
    for key, value in link.servo_defaults.items():
        servo_options.setdefault(key, value)
    peaks = [0.0] * len(opened.haptics)
    proxies = [RecordingDevice(h, _device_handler(link, peaks, i),
                               label=f"device {i} ({n}, bar {b!r})" if several else None)
               for i, (h, n, b) in enumerate(zip(opened.haptics, opened.names, opened.bars))]
    try:
        loop = ServoLoop(proxies if several else proxies[0], link.step, rate_hz=model.scene.string_hz,
                         **servo_options)
        if on_start is not None:
            on_start({"physics": mode, "physics_pid": link.pid, "stop": loop.request_stop})
        stats = loop.run(duration)
    finally:
        for h in opened.haptics:  # ServoLoop.run closed them (motors off); again in case it never started
            h.close()
        steps = link.close()
    return stats, _summary(opened, mode, steps, peaks, proxies, view)


def _device_handler(link: LiveLink, peaks: list[float], i: int) -> Callable[[str, object], None]:
    """What device ``i``'s :class:`RecordingDevice` calls: the peak force sent, then the link."""

    def on_device(kind: str, value) -> None:
        if kind == "force":
            peaks[i] = max(peaks[i], float(np.linalg.norm(value)))
        link.on_device(i, kind, value)

    return on_device


def _summary(devices: LiveDevices, mode: str, steps: dict, peaks: list[float], proxies: list[RecordingDevice],
             view) -> dict:
    """The session's summary: devices, bars, physics, steps run, forces, device-to-force latency."""
    several = devices.several
    peak = [round(p, 4) for p in peaks]
    limit = [h.spec.max_force for h in devices.haptics]
    summary = {"device": devices.names if several else devices.names[0], "bar": devices.bar,
               "physics": PHYSICS_NAMES[mode], "physics_mode": mode, **steps,
               "peak_force_sent_N": peak if several else peak[0], "max_force_N": limit if several else limit[0]}
    if several:
        summary["workspace_scale"] = [float(s) for s in devices.scales]
    if view is not None:
        summary["view_snapshots"] = view.buffer.published
    latencies = [x for p in proxies for x in p.latencies]
    if latencies:
        latency = np.array(latencies) * 1e6
        summary["device_to_force_us"] = {"p50": round(float(np.median(latency)), 1),
                                         "p99": round(float(np.percentile(latency, 99)), 1),
                                         "max": round(float(latency.max()), 1)}
    return summary
