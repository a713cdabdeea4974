"""Setting up a live session: devices by name, their mappings, where the physics runs, the marionette.

:func:`make_device` opens a device by name (the simulated one follows a scene trajectory in
its own frame, :func:`simulated_pose`), :func:`bar_mapping` gives the mapping ``P' = S W P``
(paper eq. 3) of a device driving a bar, :func:`pair_devices` and :func:`open_devices` check
and open a session's devices (:class:`LiveDevices`), :func:`resolve_physics` chooses (and
checks) the physics mode before anything is built, :func:`fifo_allowed` says whether
SCHED_FIFO may be asked for, :func:`connect_view` lets a live view drag the simulated devices,
and :class:`RecordingDevice` wraps a device so that what it reads and the forces actually sent
reach the recording.

:class:`LivePhysics` is the one place where the marionette of a session is set up, whichever
process steps it: the per-tick marionette, its recording and its device-frame step.
:func:`dmarionette.live.run.run_live` puts them together.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette import hw
from dmarionette.hw.device import AbstractHapticDevice, HapticDeviceError, HapticDeviceSpec, HapticSample
from dmarionette.live.physics import LiveMarionette, LiveTick, make_physics_step
from dmarionette.live.record import open_session_writer, record_start, record_tick
from dmarionette.live.view import LiveViewPublisher
from dmarionette.marionette.solver import MarionetteModel

__all__ = ["DEFAULT_PHYSICS", "PHYSICS_MODES", "SIMULATED_TABLE_HZ", "LiveDevices", "LivePhysics", "RecordingDevice",
           "bar_mapping", "connect_view", "fifo_allowed", "make_device", "open_devices", "pair_devices",
           "resolve_physics", "simulated_pose"]


PHYSICS_MODES = ("thread", "process", "shm")
"""Where the marionette runs during live puppetry: the servo loop's worker thread, a child
process over a pipe, or a child process over shared memory (see ``docs/hardware.md``)."""
DEFAULT_PHYSICS = "auto"
"""Chosen by measurement (``benchmarks/bench_live.py``, docs/hardware.md "Live timing"): ``"auto"``
is ``"shm"`` where SCHED_FIFO is allowed (it kept 99.7-100 % of the ticks fresh under a load
average of 6 on 2 CPUs) and ``"thread"`` where it is not (there, ``"shm"`` without real-time
priority kept fewer ticks than the worker thread: 15-45 % against 55-68 %). With a live view
(or any ``view``) ``"auto"`` is ``"thread"``: the view reads the physics' snapshots in memory."""
SIMULATED_TABLE_HZ = 2000.0
"""Rate [Hz] at which :func:`make_device` tabulates the simulated device's trajectory."""

class RecordingDevice(AbstractHapticDevice):
    """A device that records what it reads and the forces actually sent (after the safety filter)."""

    def __init__(self, device: AbstractHapticDevice, record: Callable[[str, object], None], label: str | None = None):
        self._device = device
        self._record = record
        self._label = label  # with several devices: which one, put in front of its errors
        self._read_at: float | None = None
        self.latencies: list[float] = []  # read -> next force written [s]

    @property
    def spec(self) -> HapticDeviceSpec:
        return self._device.spec

    @property
    def is_open(self) -> bool:
        return self._device.is_open

    def open(self) -> None:
        self._device.open()

    def close(self) -> None:
        self._device.close()

    def read(self) -> HapticSample:
        self._read_at = time.perf_counter()
        try:
            sample = self._device.read()
        except HapticDeviceError as error:
            self._raise_labelled(error)
        self._record("sample", sample)
        return sample

    def write_force(self, force) -> None:
        try:
            self._device.write_force(force)
        except HapticDeviceError as error:
            self._raise_labelled(error)
        if self._read_at is not None:
            self.latencies.append(time.perf_counter() - self._read_at)
            self._read_at = None
        self._record("force", np.asarray(force, dtype=np.float64))


    def _raise_labelled(self, error: HapticDeviceError):
        """Re-raises ``error`` with the device's label in front (several devices: which one failed)."""
        labelled = None
        if self._label is not None:
            try:
                labelled = type(error)(f"{self._label}: {error}")
            except TypeError:  # an error class with another constructor: raised as it is
                labelled = None
        if labelled is None:
            raise error
        raise labelled from error


def fifo_allowed() -> bool:
    """Whether this process may use SCHED_FIFO: tried on the calling thread, then put back."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, policy, param)
        return True
    except (AttributeError, OSError):
        return False


def make_device(name: str, scene, bar: str, *, trajectory_offset: np.ndarray, session=None,
                duration: float | None = None, workspace_scale: float = 1.0) -> AbstractHapticDevice:
    """A device by name: ``simulated`` follows the scene's trajectory of ``bar`` (device frame =
    world frame shifted by ``trajectory_offset`` and divided by ``workspace_scale``, so that
    through ``P' = S W P`` with the device origin at ``trajectory_offset`` the bar moves as in
    the scene, whatever the scale); ``replay`` plays the device stream of the recorded
    ``session`` (an MCAP file); the others open real hardware.

    With ``duration`` [s] the simulated device's trajectory is tabulated beforehand at
    :data:`SIMULATED_TABLE_HZ` for ``duration`` + 1 s, positions interpolated linearly and the
    rotation taken from the table entry at or before the read, then held after the end. A
    spline evaluation per read costs ~160 µs (measured), which a real device's read does not,
    and which would otherwise count in the servo tick and the device-to-force latency.
    """
    if name == "replay":
        from dmarionette.io.session import read_session

        recorded = read_session(session, load_scene=False)
        topic = f"/device/{bar}/sample"
        recorded.require([topic], "--device replay")
        channel = recorded.channels[topic]
        return hw.HapticDeviceReplay(channel["device_time"] if "device_time" in channel else channel["t"],
                                     channel["position"], channel["orientation"], channel["buttons"])
    if name == "simulated":
        return hw.HapticDeviceSimulated(trajectory=simulated_pose(scene, bar, trajectory_offset=trajectory_offset,
                                                                  duration=duration, workspace_scale=workspace_scale))
    if name == "openhaptics":
        return hw.HapticDeviceOpenHaptics()
    if name == "falcon":
        return hw.HapticDeviceFalcon()
    if name == "spacemouse":
        return hw.HapticDeviceSpaceMouse()
    raise ValueError(f"device: got {name!r}; expected one of simulated, replay, openhaptics, falcon, spacemouse")


def simulated_pose(scene, bar: str, *, trajectory_offset: np.ndarray, duration: float | None = None,
                   workspace_scale: float = 1.0) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
    """The pose the ``simulated`` device of :func:`make_device` reads at time ``t``: ``pose(t) ->
    (position (3,) [m], rotation (3, 3))`` in its frame (the scene's trajectory of ``bar``, shifted
    by ``trajectory_offset`` and divided by ``workspace_scale``); tabulated for ``duration`` + 1 s
    when ``duration`` [s] is given (see :func:`make_device`)."""
    trajectory = scene.bars[[b.name for b in scene.bars].index(bar)].trajectory

    if duration is None:
        def pose(t: float):
            position, _, rotation = trajectory.pose(np.array([t]))
            return (position[0] - trajectory_offset) / workspace_scale, rotation[0]
    else:
        table_t = np.arange(int(np.ceil((duration + 1.0) * SIMULATED_TABLE_HZ)) + 1) / SIMULATED_TABLE_HZ
        table_p, _, table_r = trajectory.pose(table_t)
        table_p = (table_p - trajectory_offset) / workspace_scale
        last = len(table_t) - 1

        def pose(t: float):
            x = min(max(t * SIMULATED_TABLE_HZ, 0.0), float(last))
            i = min(int(x), last - 1)
            w = x - i
            return (1.0 - w) * table_p[i] + w * table_p[i + 1], table_r[i if w < 1.0 else i + 1]

    return pose


def resolve_physics(physics: str | None, *, process: bool = False, realtime: bool = True,
                    view: bool = False, devices: int = 1) -> str:
    """The physics mode a live session runs in (:data:`PHYSICS_MODES`), checked before anything is built.

    Args:
        physics: ``"auto"``, one of :data:`PHYSICS_MODES`, or None (:data:`DEFAULT_PHYSICS`, or
            ``"process"`` when ``process``).
        process: the older spelling of ``physics="process"`` (``--own-process``).
        realtime: whether real-time priority may be asked for (``"auto"`` picks ``"shm"`` only then).
        view: whether a live view (or a ``--snapshot``) reads the physics' snapshots: ``"auto"`` is
            then ``"thread"``, and ``"process"``/``"shm"`` are refused.
        devices: how many devices drive bars. With two or more, ``"auto"`` is ``"thread"`` and
            ``"process"``/``"shm"`` are refused: their child-process protocols carry one device's
            sample and force per tick (see docs/hardware.md "Two devices").

    Raises:
        ValueError: an unknown mode, or a child-process mode together with a view or several devices.
    """
    mode = physics if physics is not None else ("process" if process else DEFAULT_PHYSICS)
    if mode == "auto":
        if view or devices > 1:
            return "thread"
        return "shm" if realtime and fifo_allowed() else "thread"
    if mode not in PHYSICS_MODES:
        raise ValueError(f"--physics: got {mode!r}; expected auto or one of {', '.join(PHYSICS_MODES)}")
    if view and mode != "thread":
        spelled = "--own-process" if physics is None else f"--physics {mode}"
        raise ValueError(f"{spelled}: a live view (--view browser or --snapshot) needs the physics in this process "
                         f"(it reads the physics' snapshots in memory): drop {spelled} (auto and thread run it in "
                         f"the servo loop's worker thread), or drop the view")
    if devices > 1 and mode != "thread":
        spelled = "--own-process" if physics is None else f"--physics {mode}"
        raise ValueError(f"{spelled}: {devices} devices run with the physics in the servo loop's worker thread only "
                         f"(--physics thread or auto); the {mode} mode's child process exchanges one device's "
                         f"sample and force per tick")
    return mode


def bar_mapping(model: MarionetteModel, bar: str, workspace_scale: float = 1.0):
    """The mapping ``P' = S W P`` (eq. 3) of a device driving ``bar``: its origin at the bar's start.

    ``S`` is ``workspace_scale`` (uniform, > 0), ``W`` the translation by the bar's start divided
    by ``S`` (``W`` = the start itself would put the origin at ``S`` times the start). A device
    displacement ``d`` moves the bar by ``S d``; forces come back unscaled, so a world stiffness
    ``k`` is felt as ``S k`` (:meth:`~dmarionette.hw.DeviceMapping.stiffness_to_device`).

    Returns:
        a :class:`dmarionette.hw.DeviceMapping`.
    """
    if bar not in model.bar_names:
        raise ValueError(f"--bar: got {bar!r}; expected one of {model.bar_names}")
    if not (np.isfinite(workspace_scale) and workspace_scale > 0.0):
        raise ValueError(f"--workspace-scale: got {workspace_scale}; expected a finite number > 0")
    start = np.array(model.scene.bars[model.bar_names.index(bar)].trajectory.positions[0], dtype=np.float64)
    return hw.DeviceMapping.make(float(workspace_scale), translation=start / float(workspace_scale))


@dataclasses.dataclass
class LiveDevices:
    """A session's devices, each with the bar it drives and its mapping (lists in device order).

    Attributes:
        several: Whether the devices were given as a list (the summary's entries are then lists).
        bars: The bar each device drives (distinct).
        scales: Each device's workspace scale ``S``.
        mappings: Each device's mapping ``P' = S W P`` (:func:`bar_mapping`).
        haptics: The devices.
        names: Each device's name as the summary gives it (its class name for a device object).
    """

    several: bool
    bars: list[str]
    scales: list[float]
    mappings: list[hw.DeviceMapping]
    haptics: list[AbstractHapticDevice]
    names: list[str]

    @property
    def bar(self) -> str | list[str]:
        """The driven bar, or with several devices the list of them (as :func:`make_physics_step` takes it)."""
        return self.bars if self.several else self.bars[0]

    @property
    def mapping(self) -> hw.DeviceMapping | list[hw.DeviceMapping]:
        """The mapping, or with several devices the list of them (as :class:`LivePhysics` takes it)."""
        return self.mappings if self.several else self.mappings[0]

    def metadata(self) -> list[dict[str, Any]]:
        """The devices as a recording's ``"live"`` record lists them (``docs/session.md``)."""
        return [{"bar": b, "device": n, "workspace_scale": float(s), "S": m.scale.tolist(),
                 "W": m.device_to_world.tolist(), "max_force_N": h.spec.max_force,
                 "max_continuous_force_N": h.spec.max_continuous_force}
                for b, n, s, m, h in zip(self.bars, self.names, self.scales, self.mappings, self.haptics)]


def pair_devices(device: str | AbstractHapticDevice | Sequence, bar: str | Sequence[str],
                 workspace_scale: float | Sequence[float]) -> tuple[list, list[str], list[float]]:
    """The devices, the bars they drive and their workspace scales as lists, one entry per device.

    Raises:
        ValueError: Not one bar per device, not one scale for all or one per device, or a bar twice.
    """
    devices = list(device) if isinstance(device, (list, tuple)) else [device]
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
    return devices, bars, scales


def open_devices(model: MarionetteModel, devices: list, bars: list[str], scales: list[float], *, several: bool,
                 session=None, duration: float | None = None) -> LiveDevices:
    """The devices of a session (:func:`pair_devices`' lists), names made into devices (:func:`make_device`).

    Raises:
        ValueError: A bar the model does not have, or a workspace scale that is not > 0.
    """
    for name in bars:
        if name not in model.bar_names:
            raise ValueError(f"--bar: got {name!r}; expected one of {model.bar_names}")
    starts = [np.array(model.scene.bars[model.bar_names.index(name)].trajectory.positions[0], dtype=np.float64)
              for name in bars]
    mappings = [bar_mapping(model, name, scale) for name, scale in zip(bars, scales)]
    haptics, names = [], []
    for device, bar, start, scale in zip(devices, bars, starts, scales):
        if isinstance(device, AbstractHapticDevice):
            haptics.append(device)
            names.append(type(device).__name__)
        else:
            haptics.append(make_device(device, model.scene, bar, trajectory_offset=start, session=session,
                                       duration=duration, workspace_scale=float(scale)))
            names.append(device)
    return LiveDevices(several, bars, scales, mappings, haptics, names)


def connect_view(view, devices: LiveDevices) -> LiveViewPublisher:
    """The publisher of ``view``'s snapshots; each simulated device gets a drag from the view.

    Args:
        view: A :class:`~dmarionette.live.view.AbstractLiveView`.
        devices: The session's devices: each :class:`~dmarionette.hw.HapticDeviceSimulated` among
            them follows the view's drags of its bar (world frame, through its own mapping).
    """
    mappings = devices.mappings
    publisher = LiveViewPublisher(view.buffer, view.rate_hz, force_to_world=[m.force_to_world for m in mappings]
                                  if devices.several else mappings[0].force_to_world)

    def make_drag(h: AbstractHapticDevice, m) -> Callable[[np.ndarray, np.ndarray], None] | None:
        if not isinstance(h, hw.HapticDeviceSimulated):
            return None

        def drag(position_world, rotation_world) -> None:  # the view's pose, through this device's mapping
            h.drag_to(m.position_to_device(position_world), m.rotation.T @ rotation_world)
            publisher.dragged = True

        return drag

    drags = [make_drag(h, m) for h, m in zip(devices.haptics, mappings)]
    if devices.several:
        view.connect_devices(drags)
    else:
        view.connect_device(drags[0])
    return publisher


class LivePhysics:
    """The marionette of a live session, set up once for every physics mode: the per-tick
    marionette, the session's recording and the servo loop's device-frame step.

    Args:
        model: The marionette.
        bar: The driven bar, or a sequence of bars, one per device (as for :func:`make_physics_step`).
        mapping: The driven bar's mapping, or a sequence of them, one per device.
        duration: How long the session may run [s].
        feedback: ``"reaction"`` or ``"eq4"`` (:func:`make_physics_step`).
        force_scale: Multiplies the force before it leaves.
        record: The MCAP file to record the session to, or None.
        live_metadata: Written into the recording as its ``"live"`` record, or None.
        view: A :class:`~dmarionette.live.view.LiveViewPublisher` given snapshots, or None.

    Attributes:
        live: The per-tick marionette.
        step: The device-frame physics: ``step(sample, t) -> force (3,)`` for one bar,
            ``step(samples, t) -> forces (n, 3)`` for several.
    """

    def __init__(self, model: MarionetteModel, bar: str | Sequence[str], mapping, duration: float, *,
                 feedback: str = "reaction", force_scale: float = 1.0, record: str | Path | None = None,
                 live_metadata: dict[str, Any] | None = None, view: LiveViewPublisher | None = None) -> None:
        several = not isinstance(bar, str)
        self.live = LiveMarionette(model)
        self.bars = list(bar) if several else [bar]
        self.writer = None if record is None else open_session_writer(record, model.scene, live_metadata)
        if self.writer is not None:
            record_start(self.writer, self.live)
        self._lock = threading.Lock()  # the servo thread records devices, the physics thread ticks
        world_step = make_physics_step(self.live, bar, duration, feedback=feedback, force_scale=force_scale,
                                       on_tick=self._record_tick if self.writer is not None else None, view=view)
        self.step = hw.DeviceMapping.wrap_many(mapping, world_step) if several else mapping.wrap(world_step)

    def record_device(self, device: int, kind: str, value) -> None:
        """Records what device ``device`` read (``kind`` ``"sample"``, a :class:`~dmarionette.hw.HapticSample`)
        or was sent (``"force"``, device frame, after the safety filter), at the marionette's time."""
        if self.writer is None:
            return
        with self._lock:
            if kind == "sample":
                self.writer.write_device_sample(self.bars[device], value, t=self.live.time)
            else:
                self.writer.write_force(self.bars[device], self.live.time, value)

    def _record_tick(self, tick: LiveTick, poses: dict) -> None:
        with self._lock:
            record_tick(self.writer, self.live, tick, poses)

    def close(self) -> dict[str, float]:
        """Ends the recording; returns the steps run (:meth:`LiveMarionette.steps`)."""
        if self.writer is not None:
            self.writer.close()
        return self.live.steps()
