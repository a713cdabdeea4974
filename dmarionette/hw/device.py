"""The haptic-device interface: samples, specs and the abstract device.

A device reads a pose (position [m], orientation as a unit quaternion, buttons, a
timestamp [s]) and writes a force [N]. Nothing else: devices know no physics, and this
package never imports the simulator's kernels or Warp.

Frame convention of every sample (whatever the hardware's native frame): SI units, the
device's own frame with x to the user's right, y up, z towards the user (the OpenHaptics
convention). Each concrete device converts from its native units and axes, which its
:class:`HapticDeviceSpec` names. :mod:`dmarionette.hw.mapping` takes samples to the world.

Orientations of samples are quaternions ``(w, x, y, z)``, as session files and viser store
them; the rest of the project uses Warp's ``(x, y, z, w)``. The conversions are those of
:mod:`dmarionette.rotations` (``from_wxyz``/``to_wxyz`` at this boundary).
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any

import numpy as np

from dmarionette.rotations import from_wxyz, matrix_to_quat, nearest_rotation, normalize_quat, quat_to_matrix, to_wxyz

__all__ = [
    "AbstractHapticDevice",
    "DeviceDisconnectedError",
    "HapticDeviceError",
    "HapticDeviceSpec",
    "HapticSample",
]

IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


class HapticDeviceError(RuntimeError):
    """A device could not be opened or failed while running.

    The message says what was looked for, what was found, and how to fix it.
    """


class DeviceDisconnectedError(HapticDeviceError):
    """The device went away (unplugged, communication lost) while open."""


@dataclasses.dataclass(frozen=True)
class HapticSample:
    """One reading of a device, in the device frame (x right, y up, z towards the user).

    Attributes:
        time: Seconds since the device was opened [s].
        position: End-effector position [m], shape (3,).
        orientation: End-effector orientation, unit quaternion (w, x, y, z), shape (4,);
            identity for devices without orientation sensing (the Falcon).
        buttons: Button bitmask; bit i set while button i is pressed.
    """

    time: float
    position: np.ndarray
    orientation: np.ndarray
    buttons: int = 0

    @property
    def rotation(self) -> np.ndarray:
        """Orientation as a rotation matrix, shape (3, 3)."""
        return quat_to_matrix(from_wxyz(normalize_quat(self.orientation)))

    @staticmethod
    def make(time: float, position: Any, orientation: Any = None, buttons: int = 0) -> HapticSample:
        """Builds a sample from array-likes; ``orientation`` may be a quaternion or a 3x3 matrix.

        Args:
            time: Timestamp [s].
            position: Position [m], shape (3,).
            orientation: Quaternion (w, x, y, z), shape (4,), or rotation matrix, shape (3, 3);
                None for identity.
            buttons: Button bitmask.
        """
        p = np.asarray(position, dtype=float).reshape(3).copy()
        if orientation is None:
            q = IDENTITY_QUAT.copy()
        else:
            o = np.asarray(orientation, dtype=float)
            if o.shape == (3, 3):
                q = to_wxyz(matrix_to_quat(nearest_rotation(o)))
            elif o.shape == (4,):
                q = o / np.linalg.norm(o)
            else:
                raise ValueError(f"HapticSample.make: orientation must be a quaternion (4,) or a "
                                 f"rotation matrix (3, 3), got shape {o.shape}")
        return HapticSample(float(time), p, q, int(buttons))


@dataclasses.dataclass(frozen=True)
class HapticDeviceSpec:
    """What a device can do, and how its native readings relate to SI units.

    Attributes:
        name: Human-readable model name.
        max_force: Peak force the device may be sent [N]; 0 for input-only devices.
        max_continuous_force: Force the device can hold indefinitely [N] (motor heating).
        workspace_min: Lower corner of the usable workspace [m], shape (3,), device frame.
        workspace_max: Upper corner of the usable workspace [m], shape (3,), device frame.
        native_length_unit: Unit the hardware or vendor library reports positions in
            ("mm", "m", "encoder ticks", "HID counts").
        native_axes: How the native axes map to the sample frame (x right, y up, z towards
            the user), in words.
        output_dof: Number of force-output degrees of freedom (3 or 0).
    """

    name: str
    max_force: float
    max_continuous_force: float
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]
    native_length_unit: str = "m"
    native_axes: str = "x right, y up, z towards the user"
    output_dof: int = 3

    def __post_init__(self) -> None:
        if not (self.max_force >= 0.0 and self.max_continuous_force >= 0.0):
            raise ValueError(f"HapticDeviceSpec {self.name!r}: forces must be >= 0 N, got max_force="
                             f"{self.max_force}, max_continuous_force={self.max_continuous_force}")
        if self.max_continuous_force > self.max_force:
            raise ValueError(f"HapticDeviceSpec {self.name!r}: max_continuous_force "
                             f"({self.max_continuous_force} N) exceeds max_force ({self.max_force} N)")
        lo, hi = np.asarray(self.workspace_min, float), np.asarray(self.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or np.any(lo >= hi):
            raise ValueError(f"HapticDeviceSpec {self.name!r}: workspace_min must be below workspace_max "
                             f"on every axis, got {self.workspace_min} and {self.workspace_max}")

    @property
    def workspace_center(self) -> np.ndarray:
        """Centre of the workspace box [m], shape (3,)."""
        return 0.5 * (np.asarray(self.workspace_min, float) + np.asarray(self.workspace_max, float))


class AbstractHapticDevice(abc.ABC):
    """A haptic device: open, read poses, write forces, close.

    Concrete devices are final. Use as a context manager; ``close`` always switches the
    motors off first (zero force), and is safe to call twice.
    """

    @property
    @abc.abstractmethod
    def spec(self) -> HapticDeviceSpec:
        """Limits, workspace, native units and axes of this device."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """True between a successful ``open`` and ``close``."""

    @abc.abstractmethod
    def open(self) -> None:
        """Connects to the device; raises :class:`HapticDeviceError` saying how to fix a failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Sends zero force, then releases the device. Idempotent; never raises on a lost device."""

    @abc.abstractmethod
    def read(self) -> HapticSample:
        """Latest sample (position [m], orientation, buttons, time [s]) in the device frame.

        Raises:
            DeviceDisconnectedError: The device went away.
        """

    @abc.abstractmethod
    def write_force(self, force: Any) -> None:
        """Commands a force [N], shape (3,), device frame.

        The device does not clamp; :mod:`dmarionette.hw.safety` does, before this call.

        Raises:
            DeviceDisconnectedError: The device went away.
        """

    def __enter__(self) -> AbstractHapticDevice:
        if not self.is_open:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def as_force(force: Any) -> np.ndarray:
    """A force as a float array of shape (3,), with a clear error otherwise."""
    f = np.asarray(force, dtype=float)
    if f.shape != (3,):
        raise ValueError(f"write_force: need a force [N] of shape (3,), got shape {f.shape}")
    return f
