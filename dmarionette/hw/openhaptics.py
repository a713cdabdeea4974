"""PHANToM Omni / Touch through the vendor's OpenHaptics HD library (ctypes).

The HD API runs a servo scheduler thread at 1 kHz inside ``libHD``; this binding schedules
one asynchronous callback that, every servo tick, reads the stylus transform and buttons
and sends the latest commanded force. ``read``/``write_force`` exchange data with that
callback under a lock. The callback also zeros a force that has not been refreshed for
``force_timeout`` (the Python servo loop stopped writing), so the motors never hold a
stale force even if Python stalls.

Constant values are those of the OpenHaptics 3.x headers ``HD/hdDefines.h`` and
``HD/hdScheduler.h`` (SensAble / 3D Systems); they are part of the vendor's binary
interface. Native units: millimetres, newtons; native axes: x right, y up, z towards the
user (the same axes as :class:`~dmarionette.hw.device.HapticSample`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
from typing import Any, final

import numpy as np

from dmarionette.rotations import matrix_to_quat, nearest_rotation, to_wxyz

from .device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError
from .device import HapticDeviceSpec, HapticSample, as_force

__all__ = ["HD", "HapticDeviceOpenHaptics", "find_hd_library"]

LIBRARY_ENV = "OPENHAPTICS_HD_LIBRARY"
# close(): the longest wait [s] for the servo loop to send the zero force before the scheduler stops.
CLOSE_ZERO_WAIT = 0.1


class HD:
    """OpenHaptics constants (values from ``HD/hdDefines.h`` and ``HD/hdScheduler.h``)."""

    DEFAULT_DEVICE = None  # HD_DEFAULT_DEVICE is NULL: the first configured device
    INVALID_HANDLE = 0xFFFFFFFF
    SUCCESS = 0x0000
    # Errors (hdDefines.h)
    INVALID_ENUM = 0x0100
    INVALID_VALUE = 0x0101
    INVALID_OPERATION = 0x0102
    BAD_HANDLE = 0x0104
    WARM_MOTORS = 0x0200
    EXCEEDED_MAX_FORCE = 0x0201
    EXCEEDED_MAX_FORCE_IMPULSE = 0x0202
    EXCEEDED_MAX_VELOCITY = 0x0203
    FORCE_ERROR = 0x0204
    DEVICE_FAULT = 0x0300
    DEVICE_ALREADY_INITIATED = 0x0301
    COMM_ERROR = 0x0302
    COMM_CONFIG_ERROR = 0x0303
    TIMER_ERROR = 0x0304
    ILLEGAL_BEGIN = 0x0400
    ILLEGAL_END = 0x0401
    FRAME_ERROR = 0x0402
    INVALID_PRIORITY = 0x0500
    SCHEDULER_FULL = 0x0501
    INVALID_LICENSE = 0x0600
    # Parameters (hdGet*/hdSet*)
    CURRENT_BUTTONS = 0x2000
    CURRENT_POSITION = 0x2050
    CURRENT_TRANSFORM = 0x2052
    USABLE_WORKSPACE_DIMENSIONS = 0x2551
    CALIBRATION_STYLE = 0x2555
    NOMINAL_MAX_FORCE = 0x2603
    NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
    CURRENT_FORCE = 0x2700
    DEVICE_MODEL_TYPE = 0x2501
    # Capabilities (hdEnable/hdDisable)
    FORCE_OUTPUT = 0x4000
    # Scheduler (hdScheduler.h)
    CALLBACK_DONE = 0
    CALLBACK_CONTINUE = 1
    MAX_SCHEDULER_PRIORITY = 0xFFFF  # USHRT_MAX
    MIN_SCHEDULER_PRIORITY = 0
    DEFAULT_SCHEDULER_PRIORITY = (0xFFFF + 0) // 2
    # Calibration
    CALIBRATION_OK = 0x5000
    CALIBRATION_NEEDS_UPDATE = 0x5001
    CALIBRATION_NEEDS_MANUAL_INPUT = 0x5002
    CALIBRATION_ENCODER_RESET = 1 << 0
    CALIBRATION_AUTO = 1 << 1
    CALIBRATION_INKWELL = 1 << 2


# Errors after which the device is gone, not merely unhappy.
_DISCONNECT_ERRORS = {HD.COMM_ERROR, HD.COMM_CONFIG_ERROR, HD.DEVICE_FAULT, HD.TIMER_ERROR}


class HDErrorInfo(ctypes.Structure):
    """``HDErrorInfo`` of hdDefines.h: error code, device-internal code, device handle."""

    _fields_ = [("errorCode", ctypes.c_uint), ("internalErrorCode", ctypes.c_int), ("hHD", ctypes.c_uint)]


HDSchedulerCallback = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)
"""``HDCallbackCode (HDCALLBACK *)(void *pUserData)``; HDCALLBACK is the C calling convention on Linux."""


def _declare(lib: ctypes.CDLL) -> None:
    """Argument and return types of the HD functions used here (hd.h, hdScheduler.h)."""
    c_uint, c_int, c_double, c_void_p = ctypes.c_uint, ctypes.c_int, ctypes.c_double, ctypes.c_void_p
    sigs = {
        "hdInitDevice": (c_uint, [ctypes.c_char_p]),
        "hdDisableDevice": (None, [c_uint]),
        "hdMakeCurrentDevice": (None, [c_uint]),
        "hdGetError": (HDErrorInfo, []),
        "hdGetErrorString": (ctypes.c_char_p, [c_uint]),
        "hdEnable": (None, [c_uint]),
        "hdDisable": (None, [c_uint]),
        "hdBeginFrame": (None, [c_uint]),
        "hdEndFrame": (None, [c_uint]),
        "hdGetDoublev": (None, [c_uint, ctypes.POINTER(c_double)]),
        "hdGetIntegerv": (None, [c_uint, ctypes.POINTER(c_int)]),
        "hdSetDoublev": (None, [c_uint, ctypes.POINTER(c_double)]),
        "hdScheduleAsynchronous": (ctypes.c_ulong, [HDSchedulerCallback, c_void_p, ctypes.c_ushort]),
        "hdUnschedule": (None, [ctypes.c_ulong]),
        "hdStartScheduler": (None, []),
        "hdStopScheduler": (None, []),
        "hdCheckCalibration": (c_uint, []),
        "hdUpdateCalibration": (None, [c_uint]),
    }
    missing = [name for name in sigs if not hasattr(lib, name)]
    if missing:
        raise HapticDeviceError(f"OpenHaptics: library {lib._name!r} lacks {', '.join(missing)}; is it the HD "
                                "library (libHD.so) of OpenHaptics 3.x? Point "
                                f"{LIBRARY_ENV} at the right file")
    for name, (restype, argtypes) in sigs.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes


def _error_text(lib: ctypes.CDLL, info: HDErrorInfo) -> str:
    """hdGetError's code and internal code, with hdGetErrorString's words."""
    text = lib.hdGetErrorString(info.errorCode)
    text = text.decode(errors="replace") if text else "no description"
    return f"HD error 0x{info.errorCode:04x} ({text}), internal code {info.internalErrorCode}"


def find_hd_library(path: str | os.PathLike[str] | None = None) -> str:
    """Locates the HD library: ``path``, else ``$OPENHAPTICS_HD_LIBRARY``, else ``find_library("HD")``.

    Raises:
        HapticDeviceError: Nothing found, with what was tried and how to fix it.
    """
    tried = []
    for origin, candidate in (("path argument", path), (LIBRARY_ENV, os.environ.get(LIBRARY_ENV))):
        if candidate:
            if os.path.isfile(candidate):
                return os.fspath(candidate)
            tried.append(f"{origin}: {candidate} (no such file)")
    found = ctypes.util.find_library("HD")
    if found:
        return found
    tried.append('ctypes.util.find_library("HD") (searched the linker paths for libHD.so: not found)')
    raise HapticDeviceError(
        "OpenHaptics HD library not found. Tried: " + "; ".join(tried) + ". Install OpenHaptics (3D Systems "
        "'OpenHaptics for Linux Developer Edition', plus the Touch device driver) and set "
        f"{LIBRARY_ENV}=/path/to/libHD.so, or pass library_path=..., or add its folder to LD_LIBRARY_PATH.")


@final
class HapticDeviceOpenHaptics(AbstractHapticDevice):
    """A PHANToM Omni / Touch (or any OpenHaptics device) through ``libHD``.

    Args:
        library_path: Path of ``libHD.so``; None searches ``$OPENHAPTICS_HD_LIBRARY`` then
            the linker paths.
        device_name: Configured device name (as in Touch Setup); None for HD_DEFAULT_DEVICE.
        force_timeout: The servo callback sends zero when ``write_force`` has not been called
            for this long [s]; 0 disables.
        calibrate: Check calibration at open and update it when the device says it can.
    """

    def __init__(self, library_path: str | os.PathLike[str] | None = None, device_name: str | None = None,
                 force_timeout: float = 0.005, calibrate: bool = True) -> None:
        self._library_path = library_path
        self._device_name = device_name
        self._force_timeout = float(force_timeout)
        self._calibrate = calibrate
        self._lib: ctypes.CDLL | None = None
        self._handle = HD.INVALID_HANDLE
        self._sched: int | None = None
        self._callback = HDSchedulerCallback(self._servo_tick)  # kept alive while scheduled
        self._lock = threading.Lock()
        self._transform = (ctypes.c_double * 16)()
        self._buttons = ctypes.c_int(0)
        self._force_buf = (ctypes.c_double * 3)()
        self._force = np.zeros(3)
        self._force_time = 0.0
        self._sample: HapticSample | None = None
        self._error: HapticDeviceError | None = None
        self._t0 = 0.0
        self._spec: HapticDeviceSpec | None = None
        self.calibration_status: int | None = None
        """Last ``hdCheckCalibration`` answer (HD.CALIBRATION_*), None before open."""
        self.tick_count = 0
        """Servo callbacks run since open."""

    # -- helpers ---------------------------------------------------------------------------

    def _error_text(self, info: HDErrorInfo) -> str:
        assert self._lib is not None
        return _error_text(self._lib, info)

    def _check(self, what: str, fix: str = "") -> None:
        assert self._lib is not None
        info = self._lib.hdGetError()
        if info.errorCode != HD.SUCCESS:
            cls = DeviceDisconnectedError if info.errorCode in _DISCONNECT_ERRORS else HapticDeviceError
            raise cls(f"OpenHaptics {what} failed: {self._error_text(info)}" + (f". {fix}" if fix else ""))

    def _get_doubles(self, param: int, count: int) -> np.ndarray:
        assert self._lib is not None
        buf = (ctypes.c_double * count)()
        self._lib.hdGetDoublev(param, buf)
        self._check(f"hdGetDoublev(0x{param:04x})")
        return np.array(buf[:], dtype=float)

    # -- AbstractHapticDevice --------------------------------------------------------------

    @property
    def spec(self) -> HapticDeviceSpec:
        if self._spec is None:
            raise HapticDeviceError("HapticDeviceOpenHaptics.spec: the limits are read from the device; open it first")
        return self._spec

    @property
    def is_open(self) -> bool:
        return self._sched is not None

    def open(self) -> None:
        if self.is_open:
            return
        path = find_hd_library(self._library_path)
        try:
            lib = ctypes.CDLL(path)
        except OSError as e:
            raise HapticDeviceError(f"OpenHaptics: could not load {path}: {e}. Check that its dependencies "
                                    "(the Touch driver libraries, libncurses) are on LD_LIBRARY_PATH") from e
        _declare(lib)
        self._lib = lib
        name = self._device_name.encode() if self._device_name else HD.DEFAULT_DEVICE
        handle = lib.hdInitDevice(name)
        info = lib.hdGetError()
        if handle == HD.INVALID_HANDLE or info.errorCode != HD.SUCCESS:
            self._lib = None
            raise HapticDeviceError(
                f"OpenHaptics: hdInitDevice({self._device_name or 'HD_DEFAULT_DEVICE'}) failed: "
                f"{_error_text(lib, info)}. Is the device plugged in and powered, configured with "
                "Touch Setup (the configuration file under ~/.3dsystems or /etc/openhaptics), and readable "
                "by you (serial/USB permissions: a udev rule for the Touch, see docs/hardware.md)?")
        self._handle = handle
        try:
            lib.hdMakeCurrentDevice(handle)
            max_force = float(self._get_doubles(HD.NOMINAL_MAX_FORCE, 1)[0])
            max_cont = float(self._get_doubles(HD.NOMINAL_MAX_CONTINUOUS_FORCE, 1)[0])
            ws = self._get_doubles(HD.USABLE_WORKSPACE_DIMENSIONS, 6) * 1e-3  # minX..minZ, maxX..maxZ [mm]
            self._spec = HapticDeviceSpec(
                name=f"OpenHaptics device {self._device_name or '(default)'}", max_force=max_force,
                max_continuous_force=min(max_cont, max_force), workspace_min=tuple(ws[:3]),
                workspace_max=tuple(ws[3:]), native_length_unit="mm (HD_CURRENT_TRANSFORM, column-major 4x4)",
                native_axes="x right, y up, z towards the user (as the sample frame)")
            if self._calibrate:
                self._calibration()
            lib.hdEnable(HD.FORCE_OUTPUT)
            self._check("hdEnable(HD_FORCE_OUTPUT)")
            self._t0 = time.perf_counter()
            self._force_time = self._t0
            self._sched = lib.hdScheduleAsynchronous(self._callback, None, HD.MAX_SCHEDULER_PRIORITY)
            self._check("hdScheduleAsynchronous")
            lib.hdStartScheduler()
            self._check("hdStartScheduler", "Another program may be using the device")
        except BaseException:
            self._shutdown()
            raise
        deadline = time.perf_counter() + 1.0
        while self._sample is None and self._error is None and time.perf_counter() < deadline:
            time.sleep(0.001)
        if self._sample is None:
            err = self._error
            self._shutdown()
            raise err or HapticDeviceError("OpenHaptics: the servo scheduler did not run the callback within 1 s")

    def _calibration(self) -> None:
        """hdCheckCalibration; hdUpdateCalibration with the best style the device supports."""
        assert self._lib is not None
        lib = self._lib
        status = lib.hdCheckCalibration()
        self._check("hdCheckCalibration")
        if status == HD.CALIBRATION_NEEDS_UPDATE:
            styles = ctypes.c_int(0)
            lib.hdGetIntegerv(HD.CALIBRATION_STYLE, ctypes.byref(styles))
            self._check("hdGetIntegerv(HD_CALIBRATION_STYLE)")
            for style in (HD.CALIBRATION_AUTO, HD.CALIBRATION_INKWELL, HD.CALIBRATION_ENCODER_RESET):
                if styles.value & style:
                    lib.hdUpdateCalibration(style)
                    self._check("hdUpdateCalibration")
                    break
            status = lib.hdCheckCalibration()
            self._check("hdCheckCalibration")
        self.calibration_status = status
        if status == HD.CALIBRATION_NEEDS_MANUAL_INPUT:
            raise HapticDeviceError("OpenHaptics: the device needs manual calibration: put the stylus in its "
                                    "inkwell (Touch / Omni) or run Touch Diagnostic, then open again")

    def _servo_tick(self, _user_data: Any) -> int:
        """The HD servo-loop callback (libHD's scheduler thread, 1 kHz)."""
        lib = self._lib
        if lib is None:
            return HD.CALLBACK_DONE
        try:
            lib.hdBeginFrame(self._handle)
            lib.hdGetDoublev(HD.CURRENT_TRANSFORM, self._transform)
            lib.hdGetIntegerv(HD.CURRENT_BUTTONS, ctypes.byref(self._buttons))
            now = time.perf_counter()
            with self._lock:
                stale = self._force_timeout > 0.0 and now - self._force_time > self._force_timeout
                f = (0.0, 0.0, 0.0) if stale else self._force
                self._force_buf[0], self._force_buf[1], self._force_buf[2] = f[0], f[1], f[2]
            lib.hdSetDoublev(HD.CURRENT_FORCE, self._force_buf)
            lib.hdEndFrame(self._handle)
            info = lib.hdGetError()
            if info.errorCode != HD.SUCCESS:
                cls = DeviceDisconnectedError if info.errorCode in _DISCONNECT_ERRORS else HapticDeviceError
                self._error = cls(f"OpenHaptics servo loop: {self._error_text(info)}")
                return HD.CALLBACK_DONE
            m = np.array(self._transform[:], dtype=float).reshape(4, 4).T  # column-major -> row-major
            sample = HapticSample(now - self._t0, m[:3, 3] * 1e-3, to_wxyz(matrix_to_quat(nearest_rotation(m[:3, :3]))),
                                  int(self._buttons.value))
            with self._lock:
                self._sample = sample
            self.tick_count += 1
            return HD.CALLBACK_CONTINUE
        except BaseException as e:  # noqa: BLE001 - never let an exception cross into C
            self._error = HapticDeviceError(f"OpenHaptics servo callback raised {e!r}")
            return HD.CALLBACK_DONE

    def read(self) -> HapticSample:
        if self._error is not None:
            raise self._error
        if not self.is_open or self._sample is None:
            raise HapticDeviceError("HapticDeviceOpenHaptics.read: device is not open; call open() first")
        with self._lock:
            return self._sample

    def write_force(self, force: Any) -> None:
        if self._error is not None:
            raise self._error
        if not self.is_open:
            raise HapticDeviceError("HapticDeviceOpenHaptics.write_force: device is not open; call open() first")
        f = as_force(force)
        with self._lock:
            self._force = f
            self._force_time = time.perf_counter()

    def close(self) -> None:
        if self._lib is None:
            return
        with self._lock:
            self._force = np.zeros(3)
            self._force_time = time.perf_counter()
            ticks = self.tick_count
        if self.is_open and self._error is None:
            # Let a whole servo tick send the zero (the one in flight may have read the old force):
            # two more ticks, or at most CLOSE_ZERO_WAIT s on a stalled machine, after which
            # hdDisable(HD_FORCE_OUTPUT) turns the motors off anyway. A fixed 3 ms sleep was not
            # always one tick under load.
            end = time.perf_counter() + CLOSE_ZERO_WAIT
            while self.tick_count < ticks + 2 and self._error is None and time.perf_counter() < end:
                time.sleep(0.0005)
        self._shutdown()

    def _shutdown(self) -> None:
        """hdStopScheduler, hdUnschedule, hdDisable(HD_FORCE_OUTPUT), hdDisableDevice; errors ignored."""
        lib = self._lib
        if lib is None:
            return
        lib.hdStopScheduler()
        if self._sched is not None:
            lib.hdUnschedule(self._sched)
            self._sched = None
        if self._handle != HD.INVALID_HANDLE:
            lib.hdDisable(HD.FORCE_OUTPUT)
            lib.hdDisableDevice(self._handle)
            self._handle = HD.INVALID_HANDLE
        for _ in range(64):  # drain the error stack
            if lib.hdGetError().errorCode == HD.SUCCESS:
                break
        self._lib = None
        self._sample = None
