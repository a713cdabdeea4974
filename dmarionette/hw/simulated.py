"""Devices that need no hardware: a simulated device and a replay of recorded samples."""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable
from typing import Any, final

import numpy as np

from .device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError
from .device import HapticDeviceSpec, HapticSample, as_force

__all__ = ["DEFAULT_SIMULATED_SPEC", "HapticDeviceReplay", "HapticDeviceSimulated"]

# Limits of a PHANToM Omni (SensAble data sheet: 3.3 N peak, 0.88 N continuous,
# 160 x 120 x 70 mm usable workspace), so the simulated device behaves like the paper's.
DEFAULT_SIMULATED_SPEC = HapticDeviceSpec(
    name="simulated (Omni-like limits)",
    max_force=3.3,
    max_continuous_force=0.88,
    workspace_min=(-0.08, -0.06, -0.035),
    workspace_max=(0.08, 0.06, 0.035),
    native_length_unit="m",
)

Trajectory = Callable[[float], Any]
"""A scripted pose: ``t [s] -> position (3,)`` or ``-> (position (3,), orientation)`` or
``-> (position, orientation, buttons)``; orientation a quaternion (w, x, y, z) or a 3x3 matrix."""


class _ForceLog:
    """Thread-safe record of the forces written: times [s] (device clock) and forces [N]."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._times: list[float] = []
        self._forces: list[np.ndarray] = []

    def append(self, t: float, force: np.ndarray) -> None:
        with self._lock:
            self._times.append(t)
            self._forces.append(force.copy())

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            times = np.array(self._times, dtype=float)
            forces = np.array(self._forces, dtype=float).reshape(-1, 3)
        return times, forces


class _RecordingDevice(AbstractHapticDevice):
    """Shared plumbing of the hardware-free devices: clock, open/close, force log, disconnect."""

    def __init__(self, spec: HapticDeviceSpec, clock: Callable[[], float]) -> None:
        self._spec = spec
        self._clock = clock
        self._t0 = 0.0
        self._open = False
        self._disconnected = False
        self._log = _ForceLog()
        self.close_count = 0
        """How many times ``close`` ran on an open device."""

    @property
    def spec(self) -> HapticDeviceSpec:
        return self._spec

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        if self._disconnected:
            raise DeviceDisconnectedError(f"{type(self).__name__}: the device was disconnected "
                                          "(simulate_disconnect); make a new one")
        self._t0 = self._clock()
        self._open = True

    def close(self) -> None:
        if not self._open:
            return
        if not self._disconnected:
            self._log.append(self.time(), np.zeros(3))  # motors off
        self._open = False
        self.close_count += 1

    def time(self) -> float:
        """Seconds since ``open`` on this device's clock [s]."""
        return self._clock() - self._t0

    def simulate_disconnect(self) -> None:
        """Makes every later ``read``/``write_force`` raise :class:`DeviceDisconnectedError`."""
        self._disconnected = True

    def write_force(self, force: Any) -> None:
        self._check("write_force")
        self._log.append(self.time(), as_force(force))

    def force_log(self) -> tuple[np.ndarray, np.ndarray]:
        """Everything written so far, including the zero written by ``close``.

        Returns:
            ``(times, forces)``: write times on the device clock [s], shape (n,), and
            forces [N], shape (n, 3).
        """
        return self._log.arrays()

    def _check(self, what: str) -> None:
        if self._disconnected:
            raise DeviceDisconnectedError(f"{type(self).__name__}.{what}: device disconnected")
        if not self._open:
            raise HapticDeviceError(f"{type(self).__name__}.{what}: device is not open; call open() "
                                    "first or use it as a context manager")


@final
class HapticDeviceSimulated(_RecordingDevice):
    """A device that follows a scripted trajectory or a pose set by hand, and records forces.

    A live view may also *drag* it (:meth:`drag_to`): from the first drag on, ``read`` follows
    the dragged pose instead of the trajectory.

    Args:
        trajectory: Optional callable ``t [s] -> pose`` (see :data:`Trajectory`); when None
            the pose is whatever :meth:`set_pose` last set (initially the workspace centre).
        spec: Limits and workspace; defaults to Omni-like limits.
        clock: Monotonic clock [s]; ``time.perf_counter`` by default. Tests may inject one.
        drag_lag: Time constant [s] of the first-order lag with which a dragged device moves
            to the dragged pose (0: it jumps there).
    """

    def __init__(self, trajectory: Trajectory | None = None, spec: HapticDeviceSpec = DEFAULT_SIMULATED_SPEC,
                 clock: Callable[[], float] = time.perf_counter, drag_lag: float = 0.03) -> None:
        super().__init__(spec, clock)
        if not (np.isfinite(drag_lag) and drag_lag >= 0.0):
            raise ValueError(f"HapticDeviceSimulated: drag_lag must be a finite time >= 0 [s], got {drag_lag}")
        self._trajectory = trajectory
        self._pose = HapticSample.make(0.0, spec.workspace_center)
        self._drag_lag = float(drag_lag)
        self._drag_target: HapticSample | None = None  # set by any thread, read by the reader
        self._dragged: HapticSample | None = None  # where the dragged device is (reader's thread only)
        self._last: HapticSample | None = None  # the last sample read (reader's thread only)

    @property
    def last_read(self) -> HapticSample | None:
        """The last sample ``read`` returned (None before the first); safe to look at from any
        thread (samples are never modified after they are made)."""
        return self._last

    @property
    def dragged(self) -> bool:
        """True once :meth:`drag_to` was called: ``read`` follows the drag, not the trajectory."""
        return self._drag_target is not None

    def drag_to(self, position: Any, orientation: Any = None) -> None:
        """Moves the device by hand (a mouse drag in the live view), from any thread.

        From the first call on, ``read`` reports a pose that approaches the latest dragged pose
        with a first-order lag of ``drag_lag`` (a mouse sends poses at 30-60 Hz; without the lag
        the string tops would jump several millimetres in one 1 ms tick at each mouse event),
        starting from the last pose read, so the bar does not jump when it is grabbed. The pose
        is then held where the drag leaves it. Thread-safe: the new target replaces the old one
        in one reference assignment, which a concurrent ``read`` sees whole or not at all.

        Args:
            position: Dragged position [m], shape (3,), device frame.
            orientation: Quaternion (w, x, y, z) or rotation matrix (3, 3); None for identity.

        Raises:
            ValueError: A non-finite pose (the device keeps its previous target).
        """
        target = HapticSample.make(0.0, position, orientation)
        if not (np.all(np.isfinite(target.position)) and np.all(np.isfinite(target.orientation))):
            got = None if orientation is None else np.asarray(orientation).tolist()
            raise ValueError("HapticDeviceSimulated.drag_to: need a finite position [m] and orientation; got "
                             f"{np.asarray(position).tolist()}, {got}")
        self._drag_target = target

    def set_pose(self, position: Any, orientation: Any = None, buttons: int = 0) -> None:
        """Sets the pose reported by ``read`` (used when there is no trajectory).

        Args:
            position: Position [m], shape (3,), device frame.
            orientation: Quaternion (w, x, y, z) or rotation matrix (3, 3); None for identity.
            buttons: Button bitmask.
        """
        self._pose = HapticSample.make(0.0, position, orientation, buttons)

    def read(self) -> HapticSample:
        self._check("read")
        t = self.time()
        target = self._drag_target
        if target is not None:
            sample = self._follow_drag(t, target)
        elif self._trajectory is None:
            p = self._pose
            sample = HapticSample(t, p.position.copy(), p.orientation.copy(), p.buttons)
        else:
            pose = self._trajectory(t)
            sample = HapticSample.make(t, *pose) if isinstance(pose, tuple) else HapticSample.make(t, pose)
        self._last = sample
        return sample

    def _follow_drag(self, t: float, target: HapticSample) -> HapticSample:
        """One lag step towards the dragged pose (position linearly, orientation by nlerp)."""
        previous = self._dragged or self._last or self._pose
        dt = max(t - previous.time, 0.0) if self._dragged is not None else 0.0
        a = 1.0 if self._drag_lag == 0.0 else 1.0 - np.exp(-dt / self._drag_lag)
        q_to = target.orientation if np.dot(target.orientation, previous.orientation) >= 0.0 else -target.orientation
        q = previous.orientation + a * (q_to - previous.orientation)
        position = previous.position + a * (target.position - previous.position)
        self._dragged = HapticSample(t, position, q / np.linalg.norm(q), previous.buttons)
        return HapticSample(t, position.copy(), self._dragged.orientation.copy(), previous.buttons)


@final
class HapticDeviceReplay(_RecordingDevice):
    """Plays back recorded samples at their timestamps (zero-order hold between them).

    Sample ``i`` is reported from ``times[i] - times[0]`` seconds after ``open`` until the
    next one is due; after the last, the last is held (``finished`` turns True) or, with
    ``loop=True``, playback restarts. Forces written are recorded, not played anywhere.

    Args:
        times: Recording times [s], shape (n,), strictly increasing.
        positions: Positions [m], shape (n, 3), device frame.
        orientations: Quaternions (w, x, y, z), shape (n, 4), or rotation matrices,
            shape (n, 3, 3); None for identity.
        buttons: Button bitmasks, shape (n,); None for zeros.
        spec: Limits of the device that was recorded.
        loop: Restart from the first sample after the last.
        clock: Monotonic clock [s].
    """

    def __init__(self, times: Any, positions: Any, orientations: Any = None, buttons: Any = None,
                 spec: HapticDeviceSpec = DEFAULT_SIMULATED_SPEC, loop: bool = False,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        super().__init__(spec, clock)
        t = np.asarray(times, dtype=float).reshape(-1)
        n = t.shape[0]
        if n == 0 or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0.0):
            raise ValueError("HapticDeviceReplay: times must be a non-empty, finite, strictly increasing "
                             f"array [s]; got {n} values")
        p = np.asarray(positions, dtype=float)
        if p.shape != (n, 3):
            raise ValueError(f"HapticDeviceReplay: positions must have shape ({n}, 3), got {p.shape}")
        o = None if orientations is None else np.asarray(orientations, dtype=float)
        if o is not None and o.shape not in ((n, 4), (n, 3, 3)):
            raise ValueError(f"HapticDeviceReplay: orientations must have shape ({n}, 4) or ({n}, 3, 3), "
                             f"got {o.shape}")
        b = np.zeros(n, dtype=np.int64) if buttons is None else np.asarray(buttons).astype(np.int64)
        if b.shape != (n,):
            raise ValueError(f"HapticDeviceReplay: buttons must have shape ({n},), got {b.shape}")
        self._times = (t - t[0]).tolist()
        self._samples = [HapticSample.make(self._times[i], p[i], None if o is None else o[i], int(b[i]))
                         for i in range(n)]
        self._loop = loop
        self.finished = False
        """True once the last sample is being held (never with ``loop=True``)."""

    @property
    def duration(self) -> float:
        """Length of the recording [s]."""
        return self._times[-1]

    def read(self) -> HapticSample:
        self._check("read")
        t = self.time()
        offset = 0.0
        if self._loop and self.duration > 0.0:
            period = self.duration + (self._times[1] if len(self._times) > 1 else 0.0)
            offset = period * np.floor(t / period)
        i = max(bisect.bisect_right(self._times, t - offset) - 1, 0)
        self.finished = not self._loop and i == len(self._times) - 1
        s = self._samples[i]
        # The timestamp is the recorded one (relative to the first sample), not the read time.
        return HapticSample(s.time + offset, s.position.copy(), s.orientation.copy(), s.buttons)
