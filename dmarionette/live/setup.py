"""Setting up a live session: devices by name, their mappings, where the physics runs.

:func:`make_device` opens a device by name (the simulated one follows a scene trajectory in
its own frame), :func:`bar_mapping` gives the mapping ``P' = S W P`` (paper eq. 3) of a
device driving a bar, :func:`resolve_physics` chooses (and checks) the physics mode before
anything is built, :func:`fifo_allowed` says whether SCHED_FIFO may be asked for, and
:class:`RecordingDevice` wraps a device so that what it reads and the forces actually sent
reach the recording. :func:`dmarionette.live.run.run_live` puts them together.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

import numpy as np

from dmarionette.hw.device import AbstractHapticDevice, HapticDeviceError, HapticDeviceSpec, HapticSample
from dmarionette.marionette.solver import MarionetteModel

__all__ = ["DEFAULT_PHYSICS", "PHYSICS_MODES", "SIMULATED_TABLE_HZ", "RecordingDevice", "bar_mapping",
           "fifo_allowed", "make_device", "resolve_physics"]


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
    from dmarionette import hw

    if name == "replay":
        from dmarionette.io.session import read_session

        recorded = read_session(session, load_scene=False)
        topic = f"/device/{bar}/sample"
        recorded.require([topic], "--device replay")
        channel = recorded.channels[topic]
        return hw.HapticDeviceReplay(channel["device_time"] if "device_time" in channel else channel["t"],
                                     channel["position"], channel["orientation"], channel["buttons"])
    if name == "simulated":
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

        return hw.HapticDeviceSimulated(trajectory=pose)
    if name == "openhaptics":
        return hw.HapticDeviceOpenHaptics()
    if name == "falcon":
        return hw.HapticDeviceFalcon()
    if name == "spacemouse":
        return hw.HapticDeviceSpaceMouse()
    raise ValueError(f"device: got {name!r}; expected one of simulated, replay, openhaptics, falcon, spacemouse")


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
    from dmarionette.hw import DeviceMapping

    if bar not in model.bar_names:
        raise ValueError(f"--bar: got {bar!r}; expected one of {model.bar_names}")
    if not (np.isfinite(workspace_scale) and workspace_scale > 0.0):
        raise ValueError(f"--workspace-scale: got {workspace_scale}; expected a finite number > 0")
    start = np.array(model.scene.bars[model.bar_names.index(bar)].trajectory.positions[0], dtype=np.float64)
    return DeviceMapping.make(float(workspace_scale), translation=start / float(workspace_scale))
