"""3Dconnexion SpaceMouse over HID (hidapi): 6-DOF input, no force output.

The SpaceMouse is a velocity device: its cap reports a displacement (about +-350 counts
full scale) that this driver reads as a linear and angular velocity and integrates into
a pose, clamped to a workspace box. Report layouts (HID input reports, little-endian
int16 values, report ID first as hidraw delivers it):

* split-report models (SpaceNavigator, SpaceMouse Pro, Wireless, ...):
  report 1 = translation x, y, z (7 bytes), report 2 = rotation rx, ry, rz (7 bytes),
  report 3 = button bitmask (little-endian, 1 or more bytes);
* single-report models (newer firmware, e.g. SpaceMouse Compact/Enterprise on some
  firmware): report 1 = x, y, z, rx, ry, rz (13 bytes), report 3 = buttons.

The length of report 1 tells the two apart. Native HID axes: x right, y towards the user,
z down (3Dconnexion's HID convention as read by public drivers; not checked on hardware
here), converted by ``axes`` to the sample frame (x right, y up, z towards the user).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterable
from typing import Any, Protocol, final

import numpy as np

from dmarionette.rotations import matrix_to_quat, nearest_rotation, normalize_quat, quat_to_matrix, to_wxyz

from .device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError
from .device import HapticDeviceSpec, HapticSample, as_force

__all__ = ["KNOWN_SPACEMOUSE_IDS", "HapticDeviceSpaceMouse", "HidTransport", "SpaceMouseReportParser"]

KNOWN_SPACEMOUSE_IDS: dict[tuple[int, int], str] = {
    (0x046D, 0xC603): "SpaceMouse Plus XT", (0x046D, 0xC605): "CADman", (0x046D, 0xC606): "SpaceMouse Classic",
    (0x046D, 0xC621): "SpaceBall 5000", (0x046D, 0xC623): "SpaceTraveler", (0x046D, 0xC625): "SpacePilot",
    (0x046D, 0xC626): "SpaceNavigator", (0x046D, 0xC627): "SpaceExplorer",
    (0x046D, 0xC628): "SpaceNavigator for Notebooks", (0x046D, 0xC629): "SpacePilot Pro",
    (0x046D, 0xC62B): "SpaceMouse Pro", (0x256F, 0xC62E): "SpaceMouse Wireless (cable)",
    (0x256F, 0xC62F): "SpaceMouse Wireless (receiver)", (0x256F, 0xC631): "SpaceMouse Pro Wireless (cable)",
    (0x256F, 0xC632): "SpaceMouse Pro Wireless (receiver)", (0x256F, 0xC633): "SpaceMouse Enterprise",
    (0x256F, 0xC635): "SpaceMouse Compact", (0x256F, 0xC652): "Universal Receiver",
}
"""(USB vendor id, product id) -> model, as listed by public drivers (OCCT, spacenavd)."""

# HID (x right, y towards the user, z down) -> sample frame (x right, y up, z towards the user).
DEFAULT_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class HidTransport(Protocol):
    """What the driver needs from a HID connection (``hid.device`` fits)."""

    def read(self, max_length: int, timeout_ms: int = 0) -> Any:
        """One input report (report ID first) as bytes or a list of ints; empty when none is waiting."""

    def close(self) -> None:
        """Releases the device."""


class SpaceMouseReportParser:
    """Turns HID input reports into the latest raw axes and buttons.

    Attributes:
        translation: Raw x, y, z counts (HID axes), shape (3,).
        rotation: Raw rx, ry, rz counts (HID axes), shape (3,).
        buttons: Button bitmask.
        layout: "split", "single" or None before the first motion report.
    """

    def __init__(self) -> None:
        self.translation = np.zeros(3)
        self.rotation = np.zeros(3)
        self.buttons = 0
        self.layout: str | None = None
        self.ignored = 0
        """Reports of unknown ID or length (LED, battery, ...), skipped."""

    def feed(self, report: bytes) -> None:
        """Parses one report (report ID first)."""
        if not report:
            return
        rid, body = report[0], bytes(report[1:])
        if rid == 1 and len(body) >= 12:
            v = struct.unpack_from("<6h", body)
            self.translation, self.rotation = np.array(v[:3], float), np.array(v[3:], float)
            self.layout = "single"
        elif rid == 1 and len(body) >= 6:
            self.translation = np.array(struct.unpack_from("<3h", body), float)
            self.layout = "split"
        elif rid == 2 and len(body) >= 6:
            self.rotation = np.array(struct.unpack_from("<3h", body), float)
            self.layout = "split"
        elif rid == 3 and len(body) >= 1:
            self.buttons = int.from_bytes(body, "little")
        else:
            self.ignored += 1


def _hid_module() -> Any:
    try:
        import hid
    except ImportError as e:
        raise HapticDeviceError("SpaceMouse: the hidapi Python package is not installed (pip install hidapi; "
                                "it imports as 'hid'; the PyPI package named 'hid' is a different one)") from e
    if not hasattr(hid, "enumerate") or not hasattr(hid, "device"):
        raise HapticDeviceError(f"SpaceMouse: the 'hid' module at {getattr(hid, '__file__', '?')} is not hidapi "
                                "(no hid.device); uninstall the PyPI package 'hid' and install 'hidapi'")
    return hid


def _open_hid(hid_api: Any, ids: Iterable[tuple[int, int]]) -> tuple[HidTransport, str]:
    """Finds and opens the first matching HID device; errors say what was looked for."""
    ids = list(ids)
    try:
        devices = hid_api.enumerate()
    except Exception as e:  # noqa: BLE001 - hidapi raises plain OSError/IOError or its own types
        raise HapticDeviceError(f"SpaceMouse: HID enumeration failed ({e}); is the hidapi library usable here "
                                "(hidraw or libusb backend)?") from e
    found = [d for d in devices if (d.get("vendor_id"), d.get("product_id")) in ids]
    if not found:
        wanted = ", ".join(f"{v:04x}:{p:04x}" for v, p in ids)
        raise HapticDeviceError(f"SpaceMouse: no 3Dconnexion device among the HID devices (looked for vendor:product "
                                f"{wanted}). Plug it in (check with lsusb); for the wireless models pair the receiver.")
    info = found[0]
    vid, pid = info["vendor_id"], info["product_id"]
    dev = hid_api.device()
    try:
        if info.get("path"):
            dev.open_path(info["path"])
        else:
            dev.open(vid, pid)
    except (OSError, IOError) as e:
        path = info.get("path", b"")
        path = path.decode(errors="replace") if isinstance(path, bytes) else str(path)
        raise HapticDeviceError(
            f"SpaceMouse: found {KNOWN_SPACEMOUSE_IDS.get((vid, pid), 'a device')} ({vid:04x}:{pid:04x}) at {path} "
            f"but could not open it ({e}). Usually a permission problem: add a udev rule, e.g. "
            f"/etc/udev/rules.d/99-spacemouse.rules with the line KERNEL==\"hidraw*\", ATTRS{{idVendor}}=="
            f"\"{vid:04x}\", MODE=\"0660\", TAG+=\"uaccess\", then run udevadm control --reload && udevadm trigger "
            "and re-plug (see docs/hardware.md).") from e
    return dev, KNOWN_SPACEMOUSE_IDS.get((vid, pid), f"{vid:04x}:{pid:04x}")


@final
class HapticDeviceSpaceMouse(AbstractHapticDevice):
    """A 3Dconnexion SpaceMouse as a 6-DOF input device (integrated velocity), no force.

    Args:
        transport: An open :class:`HidTransport`; None opens the first known SpaceMouse
            through hidapi (``hid_api``, default the ``hid`` module) at ``open``.
        max_speed: Linear speed at full deflection [m/s].
        max_angular_speed: Angular speed at full deflection [rad/s].
        full_scale: Raw counts at full deflection (350 on the models public drivers measured).
        deadzone: Raw counts below which an axis reads zero (drift of the cap at rest).
        workspace_min: Lower corner of the box the integrated position stays in [m], (3,).
        workspace_max: Upper corner [m], (3,).
        axes: 3x3 matrix from HID axes to the sample frame (see module docstring).
        refuse_force: Raise on a non-zero ``write_force`` instead of ignoring it.
        clock: Monotonic clock [s].
        hid_api: Module with ``enumerate()`` and ``device()`` (hidapi); for tests.
        ids: (vendor, product) pairs to look for; the known SpaceMouse models by default.
    """

    def __init__(self, transport: HidTransport | None = None, *, max_speed: float = 0.1,
                 max_angular_speed: float = 1.0, full_scale: float = 350.0, deadzone: float = 4.0,
                 workspace_min: Any = (-0.1, -0.1, -0.1), workspace_max: Any = (0.1, 0.1, 0.1),
                 axes: Any = DEFAULT_AXES, refuse_force: bool = False,
                 clock: Callable[[], float] = time.perf_counter, hid_api: Any = None,
                 ids: Iterable[tuple[int, int]] = tuple(KNOWN_SPACEMOUSE_IDS)) -> None:
        self._given_transport = transport
        self._transport: HidTransport | None = None
        self._hid_api = hid_api
        self._ids = tuple(ids)
        self.max_speed, self.max_angular_speed = float(max_speed), float(max_angular_speed)
        self.full_scale, self.deadzone = float(full_scale), float(deadzone)
        self._axes = np.asarray(axes, dtype=float)
        proper = (self._axes.shape == (3, 3) and np.allclose(self._axes @ self._axes.T, np.eye(3))
                  and np.linalg.det(self._axes) > 0)
        if not proper:
            raise ValueError("HapticDeviceSpaceMouse: axes must be a proper rotation matrix (3, 3), got "
                             f"{self._axes.tolist()}")
        self._refuse_force = refuse_force
        self._clock = clock
        self._spec = HapticDeviceSpec(
            name="3Dconnexion SpaceMouse", max_force=0.0, max_continuous_force=0.0,
            workspace_min=tuple(np.asarray(workspace_min, float)),
            workspace_max=tuple(np.asarray(workspace_max, float)),
            native_length_unit="HID counts (about +-350 full scale), read as velocity",
            native_axes="HID x right, y towards the user, z down; axes= maps them to x right, y up, z to the user",
            output_dof=0)
        self.parser = SpaceMouseReportParser()
        self.model = ""
        self._pos = self._spec.workspace_center
        self._rot = np.eye(3)
        self._t0 = self._t_last = 0.0

    @property
    def spec(self) -> HapticDeviceSpec:
        return self._spec

    @property
    def is_open(self) -> bool:
        return self._transport is not None

    def open(self) -> None:
        if self.is_open:
            return
        if self._given_transport is not None:
            self._transport, self.model = self._given_transport, "injected transport"
        else:
            self._transport, self.model = _open_hid(self._hid_api or _hid_module(), self._ids)
        self._t0 = self._t_last = self._clock()
        self._pos = self._spec.workspace_center
        self._rot = np.eye(3)

    def close(self) -> None:
        if self._transport is None:
            return
        try:
            self._transport.close()
        except OSError:
            pass
        self._transport = None

    def recenter(self) -> None:
        """Puts the integrated pose back to the workspace centre and identity orientation."""
        self._pos, self._rot = self._spec.workspace_center, np.eye(3)

    def _scaled(self, raw: np.ndarray) -> np.ndarray:
        v = np.where(np.abs(raw) < self.deadzone, 0.0, raw) / self.full_scale
        return self._axes @ np.clip(v, -1.0, 1.0)

    def read(self) -> HapticSample:
        if self._transport is None:
            raise HapticDeviceError("HapticDeviceSpaceMouse.read: device is not open; call open() first")
        try:
            for _ in range(256):  # drain what is waiting
                report = self._transport.read(64, 0)
                if not report:
                    break
                self.parser.feed(bytes(report))
        except (OSError, ValueError) as e:
            raise DeviceDisconnectedError(f"SpaceMouse: HID read failed ({e}); was it unplugged?") from e
        now = self._clock()
        dt, self._t_last = max(now - self._t_last, 0.0), now
        v = self.max_speed * self._scaled(self.parser.translation)
        w = self.max_angular_speed * self._scaled(self.parser.rotation)
        lo, hi = np.asarray(self._spec.workspace_min), np.asarray(self._spec.workspace_max)
        self._pos = np.clip(self._pos + v * dt, lo, hi)
        angle = float(np.linalg.norm(w)) * dt
        if angle > 0.0:  # rotate about fixed (base) axes: R <- exp([w] dt) R
            axis = w / np.linalg.norm(w)
            dq = np.r_[np.sin(angle / 2) * axis, np.cos(angle / 2)]
            self._rot = quat_to_matrix(normalize_quat(dq)) @ self._rot
        return HapticSample(now - self._t0, self._pos.copy(), to_wxyz(matrix_to_quat(nearest_rotation(self._rot))),
                            self.parser.buttons)

    def write_force(self, force: Any) -> None:
        """No motors: a zero force is accepted, a non-zero one ignored (or refused with ``refuse_force``)."""
        f = as_force(force)
        if self._refuse_force and np.any(f != 0.0):
            raise HapticDeviceError("HapticDeviceSpaceMouse: a SpaceMouse has no motors (spec.max_force = 0); "
                                    f"refusing force {f.tolist()} N")
