"""Novint Falcon over USB (pyusb), after the open libnifalcon protocol.

The Falcon is an FTDI FT232 USB-serial chip (vendor 0x0403, product 0xCB48) in front of a
microcontroller whose firmware is lost at every power cycle. Opening it:

1. find and claim the FTDI interface (detaching the ``ftdi_sio`` kernel driver);
2. FTDI set-up by vendor control requests (reset/purge, latency timer, baud rate, line
   properties, flow control, bit mode, modem lines);
3. if no firmware answers, the firmware-load handshake: at 9600 baud with DTR pulsed,
   send ``0a 43 0d`` until the boot loader answers ``0a 44 2c 0d``; then DTR low, the
   fast load rate, send ``A`` and expect ``A`` back; then stream the firmware file in
   chunks of at most 62 bytes, each echoed back and compared. The firmware file is the
   user's (Novint's ``novint.bin`` from the Novint drivers, or a libnifalcon test
   firmware); it is never bundled here;
4. normal mode (latency 1 ms, fast baud rate), then packets of the Novint SDK firmware:
   16 bytes ``'<' 14 nibbles '>'``, each nibble sent as ``0x41 + value``. Out: three
   signed 16-bit motor commands (4 nibbles each, low nibble first), then one nibble of
   LED bits and the homing-mode bit. In: three signed 16-bit encoder counts, then one
   byte whose high nibble holds the per-axis homing flags and low nibble the grip
   buttons. Every FTDI bulk-in transfer starts with two modem-status bytes;
5. homing: send packets with the homing bit set while the user pulls the grip fully
   out and pushes it in, until all three homing flags are set.

An I/O thread exchanges packets continuously; ``read`` turns the latest encoder counts
into a position with :class:`~dmarionette.hw.falcon_kinematics.FalconKinematics`, and
``write_force`` turns a force into motor commands through the Jacobian. A force not
refreshed within ``force_timeout`` is replaced by zero in the I/O thread.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any, final

import numpy as np

from .device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError
from .device import HapticDeviceSpec, HapticSample, as_force
from .falcon_kinematics import FalconKinematics, FalconKinematicsError

__all__ = ["FALCON_PRODUCT_ID", "FALCON_VENDOR_ID", "FTDI", "FalconPacketReader", "HapticDeviceFalcon",
           "encode_command_packet", "decode_status_packet"]

FALCON_VENDOR_ID = 0x0403
FALCON_PRODUCT_ID = 0xCB48
EP_OUT = 0x02
EP_IN = 0x81
FIRMWARE_ENV = "FALCON_FIRMWARE"


class FTDI:
    """FTDI vendor requests (libftdi's SIO_* names) and the values the Falcon needs."""

    REQUEST_TYPE_OUT = 0x40  # vendor request, host to device
    RESET, MODEM_CTRL, SET_FLOW_CTRL, SET_BAUD_RATE, SET_DATA = 0x00, 0x01, 0x02, 0x03, 0x04
    SET_LATENCY_TIMER, SET_BITMODE = 0x09, 0x0B
    RESET_SIO, PURGE_RX, PURGE_TX = 0, 1, 2
    DTR_LOW, DTR_HIGH = 0x0100, 0x0101  # (mask << 8) | value
    RTS_LOW, RTS_HIGH = 0x0200, 0x0202
    FLOW_NONE = 0x0000
    DATA_8N1 = 0x0008  # 8 data bits, no parity, 1 stop bit
    BITMODE_RESET = 0x0000  # plain serial (UART) mode
    # Baud-rate divisor words (as libnifalcon sends them): 9600 baud for the boot loader,
    # about 140 kbaud for the firmware upload, and the fast rate of normal operation.
    BAUD_BOOT, BAUD_UPLOAD, BAUD_NORMAL = 0x4138, 0x0015, 0x0002


BOOT_PROBE = bytes([0x0A, 0x43, 0x0D])
BOOT_REPLY = bytes([0x0A, 0x44, 0x2C, 0x0D])
LED_GREEN, LED_BLUE, LED_RED = 0x2, 0x4, 0x8
HOMING_BIT = 0x1
ALL_HOMED = 0x7
UPLOAD_CHUNK = 62  # 64-byte full-speed packets minus the FTDI's two status bytes


def encode_command_packet(motor: Any, leds: int = 0, homing: bool = False) -> bytes:
    """Host -> Falcon packet of the Novint SDK firmware.

    Args:
        motor: Three signed 16-bit motor commands, shape (3,).
        leds: LED bits (LED_GREEN | LED_BLUE | LED_RED).
        homing: Set the homing-mode bit.

    Returns:
        16 bytes: ``'<'``, 14 nibbles as ``0x41 + nibble``, ``'>'``.
    """
    nibbles = []
    for m in np.asarray(motor).astype(np.int64).reshape(3):
        word = int(np.clip(m, -32768, 32767)) & 0xFFFF
        nibbles += [(word >> shift) & 0xF for shift in (0, 4, 8, 12)]
    nibbles.append((leds & 0xE) | (HOMING_BIT if homing else 0))
    nibbles.append(0)
    return b"<" + bytes(0x41 + n for n in nibbles) + b">"


def decode_status_packet(packet: bytes) -> tuple[np.ndarray, int, int]:
    """Falcon -> host packet: ``(encoder ticks (3,) int, homing flags (3 bits), grip buttons (4 bits))``."""
    if len(packet) != 16 or packet[0] != ord("<") or packet[15] != ord(">"):
        raise ValueError(f"not a Falcon status packet: {packet!r}")
    n = [(b - 0x41) & 0xF for b in packet[1:13]]
    enc = []
    for i in range(3):
        word = n[4 * i] | n[4 * i + 1] << 4 | n[4 * i + 2] << 8 | n[4 * i + 3] << 12
        enc.append(word - 0x10000 if word & 0x8000 else word)
    status = (packet[13] - 0x41) & 0xFF
    return np.array(enc, dtype=int), (status >> 4) & 0x7, status & 0xF


class FalconPacketReader:
    """Reassembles 16-byte status packets from FTDI bulk-in transfers (status bytes removed)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.malformed = 0
        """Bytes dropped while looking for a packet start."""

    def feed(self, data: bytes) -> list[tuple[np.ndarray, int, int]]:
        """Adds payload bytes; returns the packets completed, decoded."""
        self._buf += data
        out = []
        while True:
            start = self._buf.find(b"<")
            if start < 0:
                self.malformed += len(self._buf)
                self._buf.clear()
                return out
            if start:
                self.malformed += start
                del self._buf[:start]
            if len(self._buf) < 16:
                return out
            packet = bytes(self._buf[:16])
            if packet[15] == ord(">"):
                out.append(decode_status_packet(packet))
                del self._buf[:16]
            else:
                self.malformed += 1
                del self._buf[:1]


def _usb() -> Any:
    try:
        import usb.core
        import usb.util
    except ImportError as e:
        raise HapticDeviceError("Falcon: pyusb is not installed (pip install pyusb, plus the libusb-1.0 system "
                                "library)") from e
    return usb


@final
class HapticDeviceFalcon(AbstractHapticDevice):
    """A Novint Falcon through pyusb and the Novint SDK firmware protocol.

    Args:
        firmware_path: The firmware file to load when the device has none (after each power
            cycle); None reads ``$FALCON_FIRMWARE``. Never bundled: take ``novint.bin`` from
            Novint's driver package or a firmware from the libnifalcon distribution.
        backend: A pyusb backend (``usb.backend.IBackend``); None lets pyusb pick libusb.
        home: Require homing at ``open`` (pull the grip out and push it in).
        homing_timeout: How long ``open`` waits for homing [s].
        origin: Position [m] in libnifalcon's frame that becomes the sample origin.
        force_timeout: The I/O thread sends zero when ``write_force`` was not called for
            this long [s].
        io_period: Packet exchange period [s].
        torque_to_command: Motor command per N m of thigh torque (libnifalcon's empirical
            10000; not calibrated here).
        index: Which Falcon, when several are plugged in.
    """

    def __init__(self, firmware_path: str | os.PathLike[str] | None = None, *, backend: Any = None,
                 home: bool = True, homing_timeout: float = 30.0, origin: Any = (0.0, 0.0, 0.11),
                 force_timeout: float = 0.005, io_period: float = 0.001, torque_to_command: float = 10000.0,
                 index: int = 0) -> None:
        self._firmware_path = firmware_path
        self._backend = backend
        self._home = home
        self._homing_timeout = float(homing_timeout)
        self._origin = np.asarray(origin, dtype=float).reshape(3)
        self._force_timeout = float(force_timeout)
        self._io_period = float(io_period)
        self._torque_to_command = float(torque_to_command)
        self._index = index
        self.kinematics = FalconKinematics()
        self._dev: Any = None
        self._lock = threading.Lock()
        self._motor = np.zeros(3, dtype=int)
        self._motor_time = 0.0
        self._leds = LED_RED
        self._homing = False
        self._encoders: np.ndarray | None = None
        self._homed = 0
        self._buttons = 0
        self._status_time = 0.0
        self._error: HapticDeviceError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reader = FalconPacketReader()
        self._t0 = 0.0
        self._last_position = np.zeros(3)
        self.firmware_loaded_now = False
        """True when ``open`` had to load the firmware (False: it was already running)."""
        self.packet_count = 0
        """Status packets received since open."""
        self._spec = HapticDeviceSpec(
            name="Novint Falcon", max_force=8.9, max_continuous_force=4.0,
            workspace_min=(-0.05, -0.05, -0.05), workspace_max=(0.05, 0.05, 0.05),
            native_length_unit="encoder ticks (3 motors), through the delta kinematics to m",
            native_axes="libnifalcon frame: x right, y up, z towards the user; shifted by origin")

    # -- USB and FTDI ----------------------------------------------------------------------

    @property
    def spec(self) -> HapticDeviceSpec:
        return self._spec

    @property
    def is_open(self) -> bool:
        return self._dev is not None

    def _ctrl(self, request: int, value: int) -> None:
        self._dev.ctrl_transfer(FTDI.REQUEST_TYPE_OUT, request, value, 0, None, 1000)

    def _write(self, data: bytes) -> None:
        self._dev.write(EP_OUT, data, 1000)

    def _read(self, size: int = 64, timeout: int = 1000) -> bytes:
        """One bulk-in transfer without its two FTDI status bytes."""
        return bytes(self._dev.read(EP_IN, size, timeout))[2:]

    def _find(self) -> Any:
        usb = _usb()
        try:
            found = list(usb.core.find(find_all=True, idVendor=FALCON_VENDOR_ID, idProduct=FALCON_PRODUCT_ID,
                                       backend=self._backend))
        except usb.core.NoBackendError as e:
            raise HapticDeviceError("Falcon: pyusb found no USB backend; install the libusb-1.0 library "
                                    "(e.g. apt install libusb-1.0-0)") from e
        if len(found) <= self._index:
            raise HapticDeviceError(
                f"Falcon: no Novint Falcon found (looked for USB vendor 0x{FALCON_VENDOR_ID:04x}, product "
                f"0x{FALCON_PRODUCT_ID:04x}, index {self._index}; found {len(found)}). Plug it in and power it "
                "(the power brick, not only USB); check with lsusb.")
        return found[self._index]

    def _claim(self, dev: Any) -> None:
        usb = _usb()
        try:
            try:
                if dev.is_kernel_driver_active(0):
                    dev.detach_kernel_driver(0)  # ftdi_sio binds the Falcon as a serial port
            except NotImplementedError:
                pass
            dev.set_configuration()
            usb.util.claim_interface(dev, 0)
        except usb.core.USBError as e:
            if getattr(e, "errno", None) in (13, 1) or "Access denied" in str(e):
                raise HapticDeviceError(
                    f"Falcon: permission denied opening the USB device ({e}). Add a udev rule, e.g. "
                    "/etc/udev/rules.d/99-novint-falcon.rules with the line SUBSYSTEM==\"usb\", "
                    "ATTRS{idVendor}==\"0403\", ATTRS{idProduct}==\"cb48\", MODE=\"0660\", TAG+=\"uaccess\", "
                    "then udevadm control --reload && udevadm trigger, and re-plug (see docs/hardware.md).") from e
            raise HapticDeviceError(f"Falcon: could not claim the USB interface ({e}); is another program "
                                    "(a libnifalcon tool, a driver) using it?") from e

    def _ftdi_setup(self) -> None:
        self._ctrl(FTDI.RESET, FTDI.RESET_SIO)
        self._ctrl(FTDI.SET_BITMODE, FTDI.BITMODE_RESET)
        self._ctrl(FTDI.RESET, FTDI.PURGE_RX)
        self._ctrl(FTDI.RESET, FTDI.PURGE_TX)

    def _normal_mode(self) -> None:
        self._ctrl(FTDI.SET_LATENCY_TIMER, 1)
        self._ctrl(FTDI.SET_BAUD_RATE, FTDI.BAUD_NORMAL)
        self._ctrl(FTDI.RESET, FTDI.PURGE_RX)
        self._ctrl(FTDI.RESET, FTDI.PURGE_TX)

    def _firmware_running(self, tries: int = 20) -> bool:
        """Sends command packets; True when a status packet comes back."""
        reader = FalconPacketReader()
        for _ in range(tries):
            self._write(encode_command_packet(np.zeros(3), LED_RED))
            try:
                if reader.feed(self._read(64, 50)):
                    return True
            except _usb().core.USBTimeoutError:
                pass
        return False

    def _firmware_bytes(self) -> bytes:
        path = self._firmware_path or os.environ.get(FIRMWARE_ENV)
        if not path:
            raise HapticDeviceError(
                "Falcon: the device has no firmware running (it is lost at every power cycle) and no firmware file "
                f"was given. Pass firmware_path=... or set {FIRMWARE_ENV}=/path/to/novint.bin (from Novint's "
                "driver package, or a firmware from the libnifalcon distribution); none is bundled here.")
        if not os.path.isfile(path):
            raise HapticDeviceError(f"Falcon: firmware file {path} not found (from firmware_path or "
                                    f"{FIRMWARE_ENV}); give the path of novint.bin or a libnifalcon firmware file.")
        with open(path, "rb") as fh:
            data = fh.read()
        if not data:
            raise HapticDeviceError(f"Falcon: firmware file {path} is empty")
        return data

    def _load_firmware(self, firmware: bytes) -> None:
        """The boot-loader handshake, then the upload with echo check (see module docstring)."""
        usb = _usb()
        for request, value in ((FTDI.RESET, FTDI.PURGE_RX), (FTDI.RESET, FTDI.PURGE_TX),
                               (FTDI.SET_LATENCY_TIMER, 16), (FTDI.SET_BAUD_RATE, FTDI.BAUD_BOOT),
                               (FTDI.SET_DATA, FTDI.DATA_8N1), (FTDI.SET_FLOW_CTRL, FTDI.FLOW_NONE),
                               (FTDI.MODEM_CTRL, FTDI.RTS_LOW), (FTDI.MODEM_CTRL, FTDI.DTR_LOW),
                               (FTDI.MODEM_CTRL, FTDI.DTR_HIGH)):
            self._ctrl(request, value)
        for _ in range(100):
            self._write(BOOT_PROBE)
            try:
                reply = self._read(512, 100)
            except usb.core.USBTimeoutError:
                continue
            if reply.lstrip(b"\x00") == BOOT_REPLY:
                break
        else:
            raise HapticDeviceError("Falcon: the boot loader did not answer the firmware-load handshake "
                                    f"(sent {BOOT_PROBE.hex(' ')}, expected {BOOT_REPLY.hex(' ')}); power-cycle the "
                                    "Falcon (unplug the power brick) and try again")
        self._ctrl(FTDI.MODEM_CTRL, FTDI.DTR_LOW)
        self._ctrl(FTDI.SET_BAUD_RATE, FTDI.BAUD_UPLOAD)
        self._write(b"A")
        if self._read(3, 1000) != b"A":
            raise HapticDeviceError("Falcon: the boot loader did not acknowledge the upload ('A'); power-cycle it")
        for at in range(0, len(firmware), UPLOAD_CHUNK):
            chunk = firmware[at:at + UPLOAD_CHUNK]
            self._write(chunk)
            echo = b""
            while len(echo) < len(chunk):
                echo += self._read(len(chunk) + 2, 1000)
            if echo != chunk:
                raise HapticDeviceError(f"Falcon: firmware upload echo mismatch at byte {at} (is the file a Falcon "
                                        "firmware? a bad cable?)")

    # -- open / close ----------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            return
        dev = self._find()
        self._claim(dev)
        self._dev = dev
        try:
            self._ftdi_setup()
            self._normal_mode()
            self.firmware_loaded_now = False
            if not self._firmware_running():
                firmware = self._firmware_bytes()
                self._load_firmware(firmware)
                self._normal_mode()
                self.firmware_loaded_now = True
                if not self._firmware_running():
                    raise HapticDeviceError("Falcon: firmware uploaded but the device does not answer packets; is "
                                            "it the Novint SDK firmware (novint.bin)?")
            self._error = None
            self._stop.clear()
            self._t0 = time.perf_counter()
            self._motor_time = self._t0
            self._thread = threading.Thread(target=self._io_loop, name="dmarionette-falcon-io", daemon=True)
            self._thread.start()
            self._wait(lambda: self._encoders is not None, 1.0, "Falcon: no status packet within 1 s of start")
            if self._home:
                self.home(self._homing_timeout)
        except BaseException:
            self._release()
            raise

    def _wait(self, cond: Any, timeout: float, message: str) -> None:
        end = time.perf_counter() + timeout
        while not cond():
            if self._error is not None:
                raise self._error
            if time.perf_counter() > end:
                raise HapticDeviceError(message)
            time.sleep(0.001)

    def home(self, timeout: float = 30.0) -> None:
        """Homing: red LED and the homing bit until all three axes report homed, then green.

        Move the grip all the way out, then push it in, while this runs.
        """
        with self._lock:
            self._homing, self._leds = True, LED_RED
        self._wait(lambda: self._homed == ALL_HOMED, timeout,
                   f"Falcon: not homed within {timeout:g} s; pull the grip all the way out and push it back in "
                   "while homing runs")
        with self._lock:
            self._leds = LED_GREEN

    def close(self) -> None:
        if self._dev is None:
            return
        with self._lock:
            self._motor = np.zeros(3, dtype=int)
            self._motor_time = time.perf_counter()
        if self._thread is not None and self._error is None:
            time.sleep(max(3 * self._io_period, 0.003))  # let the zero command go out
        self._release()

    def _release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        dev, self._dev = self._dev, None
        if dev is None:
            return
        usb = _usb()
        try:
            if self._error is None:
                dev.write(EP_OUT, encode_command_packet(np.zeros(3), 0), 100)
        except usb.core.USBError:
            pass
        try:
            usb.util.release_interface(dev, 0)
            usb.util.dispose_resources(dev)
        except usb.core.USBError:
            pass
        self._encoders = None

    # -- I/O thread --------------------------------------------------------------------------

    def _io_loop(self) -> None:
        usb = _usb()
        next_t = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            with self._lock:
                stale = self._force_timeout > 0.0 and now - self._motor_time > self._force_timeout
                motor = np.zeros(3, dtype=int) if stale else self._motor
                packet = encode_command_packet(motor, self._leds, self._homing)
            try:
                self._dev.write(EP_OUT, packet, 100)
                data = bytes(self._dev.read(EP_IN, 64, 100))[2:]
            except usb.core.USBTimeoutError:
                continue
            except usb.core.USBError as e:
                self._error = DeviceDisconnectedError(f"Falcon: USB I/O failed ({e}); was it unplugged or powered off?")
                return
            for enc, homed, buttons in self._reader.feed(data):
                with self._lock:
                    self._encoders, self._homed, self._buttons = enc, homed, buttons
                    self._status_time = time.perf_counter()
                self.packet_count += 1
            next_t += self._io_period
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.perf_counter()

    # -- samples and forces ------------------------------------------------------------------

    def _check(self, what: str) -> None:
        if self._error is not None:
            raise self._error
        if self._dev is None:
            raise HapticDeviceError(f"HapticDeviceFalcon.{what}: device is not open; call open() first")

    def read(self) -> HapticSample:
        self._check("read")
        with self._lock:
            enc, buttons, t = self._encoders, self._buttons, self._status_time
        assert enc is not None
        try:
            native = self.kinematics.position(self.kinematics.angles_from_encoders(enc))
        except FalconKinematicsError:
            native = self._last_position + self._origin  # keep the last good one (e.g. before homing)
        self._last_position = native - self._origin
        return HapticSample(t - self._t0, self._last_position.copy(), np.array([1.0, 0.0, 0.0, 0.0]), buttons)

    def write_force(self, force: Any) -> None:
        self._check("write_force")
        f = as_force(force)
        if np.any(f != 0.0):
            tau = self.kinematics.joint_torques(self._last_position + self._origin, f)
            motor = np.clip(np.rint(-self._torque_to_command * tau), -32767, 32767).astype(int)
        else:
            motor = np.zeros(3, dtype=int)
        with self._lock:
            self._motor = motor
            self._motor_time = time.perf_counter()

    @property
    def motor_commands(self) -> np.ndarray:
        """The motor commands the I/O thread is sending, shape (3,)."""
        with self._lock:
            return self._motor.copy()
