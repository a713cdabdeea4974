"""A virtual Novint Falcon behind a pyusb backend, for tests.

``VirtualFalcon`` emulates the FTDI chip (vendor control requests, two modem-status bytes
in front of every bulk-in transfer), the boot loader's firmware-load handshake and the
Novint SDK firmware's 16-byte nibble packets, with homing. Its encoder counts come from
its own inverse kinematics (the tangent-half-angle form of the leg constraint), written
here independently of ``dmarionette.hw.falcon_kinematics``.
"""

from __future__ import annotations

import math
import threading
import types

import numpy as np
import usb.backend
import usb.core

FTDI_VID, FALCON_PID = 0x0403, 0xCB48
BOOT_PROBE, BOOT_REPLY = bytes([0x0A, 0x43, 0x0D]), bytes([0x0A, 0x44, 0x2C, 0x0D])
MODEM_STATUS = bytes([0x31, 0x60])

# Geometry (m, rad), as in libnifalcon's FalconGeometry.h.
A, B, C, D, E, F, R, S = 0.060, 0.1025, 0.01443, 0.01125, 0.01125, -0.025, 0.0400, -0.02309
PHI = [math.pi / 2 + math.pi / 12, -math.pi / 6 + math.pi / 12, -5 * math.pi / 6 + math.pi / 12]
RAD_PER_TICK = 2 * math.pi / 1280 * (14.25 / 110.0)
THETA0 = math.radians(35.0)


def reference_leg_angles(p):
    """Thigh angles by the tangent-half-angle quadratic of each leg's closure equation."""
    out = []
    for phi in PHI:
        u = math.cos(phi) * p[0] + math.sin(phi) * p[1] - R
        v = -math.sin(phi) * p[0] + math.cos(phi) * p[1] - S
        w = p[2]
        k = D + E + B * math.sin(math.acos((v + F) / B))
        base = (u + C) ** 2 + w * w + A * A - k * k
        q0, q1, q2 = base - 2 * A * (u + C), -4 * A * w, base + 2 * A * (u + C)
        t = (-q1 - math.sqrt(q1 * q1 - 4 * q0 * q2)) / (2 * q2)
        out.append(2 * math.atan(t))
    return np.array(out)


def reference_ticks(p):
    return np.rint((reference_leg_angles(p) - THETA0) / RAD_PER_TICK).astype(int)


def _nibbles(word):
    word &= 0xFFFF
    return [(word >> s) & 0xF for s in (0, 4, 8, 12)]


class VirtualFalcon:
    """The device: FTDI state, boot loader, firmware and mechanics."""

    def __init__(self, firmware=None, firmware_running=False, home_after=20, permission_denied=False):
        self.lock = threading.Lock()
        self.expected_firmware = firmware
        self.mode = "running" if firmware_running else "boot"
        self.home_after = home_after
        self.permission_denied = permission_denied
        self.position = np.array([0.0, 0.0, 0.11])
        self.buttons = 0
        self.unplugged = False
        self.ctrl_log = []
        self.baud = None
        self.dtr = self.rts = 0
        self.dtr_pulsed = False
        self.latency = None
        self.out = bytearray()
        self.inbuf = bytearray()
        self.received_firmware = bytearray()
        self.commands = []  # (motor (3,), leds, homing)
        self.homing_packets = 0
        self.homed = 0
        self.kernel_driver = True
        self.claimed = False

    def _check(self):
        if self.unplugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", errno=19)

    def control(self, request, value):
        self._check()
        with self.lock:
            self.ctrl_log.append((request, value))
            if request == 0 and value == 1:
                self.out.clear()
            elif request == 3:
                self.baud = value
                if value == 0x0002 and self.mode == "upload":
                    ok = self.expected_firmware is not None and bytes(self.received_firmware) == self.expected_firmware
                    self.mode = "running" if ok else "dead"
            elif request == 1:
                mask, bits = value >> 8, value & 0xFF
                if mask & 1:
                    new = bits & 1
                    if self.dtr == 0 and new == 1:
                        self.dtr_pulsed = True
                    self.dtr = new
                if mask & 2:
                    self.rts = (bits >> 1) & 1
            elif request == 9:
                self.latency = value

    def host_write(self, data):
        self._check()
        with self.lock:
            if self.mode == "boot":
                if self.baud == 0x4138 and data == BOOT_PROBE and self.dtr_pulsed:
                    self.out += BOOT_REPLY
                elif self.baud == 0x0015 and data == b"A":
                    self.mode = "upload"
                    self.out += b"A"
            elif self.mode == "upload":
                self.received_firmware += data
                self.out += data
            elif self.mode == "running":
                self.inbuf += data
                while len(self.inbuf) >= 16:
                    packet, self.inbuf = bytes(self.inbuf[:16]), self.inbuf[16:]
                    self._command(packet)
        return len(data)

    def _command(self, packet):
        assert packet[0] == ord("<") and packet[15] == ord(">"), packet
        n = [b - 0x41 for b in packet[1:15]]
        motor = []
        for i in range(3):
            word = n[4 * i] | n[4 * i + 1] << 4 | n[4 * i + 2] << 8 | n[4 * i + 3] << 12
            motor.append(word - 0x10000 if word & 0x8000 else word)
        homing = bool(n[12] & 1)
        self.commands.append((np.array(motor), n[12] & 0xE, homing))
        if homing:
            self.homing_packets += 1
            if self.homing_packets >= self.home_after:
                self.homed = 7
        ticks = reference_ticks(self.position) + (0 if self.homed == 7 else 777)  # unhomed: offset counts
        nib = sum((_nibbles(int(t)) for t in ticks), [])
        status = (self.homed << 4) | self.buttons
        self.out += b"<" + bytes(0x41 + x for x in nib) + bytes([0x41 + status, 0x41]) + b">"

    def host_read(self, size):
        self._check()
        with self.lock:
            n = max(size - 2, 0)
            chunk, self.out = bytes(self.out[:n]), self.out[n:]
        return MODEM_STATUS + chunk


def _ns(**kw):
    kw.setdefault("extra_descriptors", [])
    return types.SimpleNamespace(**kw)


class VirtualFalconBackend(usb.backend.IBackend):
    """pyusb backend that shows the given virtual Falcons (and one unrelated device)."""

    def __init__(self, falcons):
        self.falcons = list(falcons)
        self.other = object()

    def enumerate_devices(self):
        yield self.other
        yield from self.falcons

    def get_device_descriptor(self, dev):
        vid, pid = (FTDI_VID, FALCON_PID) if dev is not self.other else (0x1D6B, 0x0002)
        index = self.falcons.index(dev) + 2 if dev is not self.other else 1
        return _ns(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
                   bDeviceProtocol=0, bMaxPacketSize0=8, idVendor=vid, idProduct=pid, bcdDevice=0x0600,
                   iManufacturer=0, iProduct=0, iSerialNumber=0, bNumConfigurations=1, address=index, bus=1,
                   port_number=index, port_numbers=(index,), speed=2)

    def get_configuration_descriptor(self, dev, config):
        return _ns(bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1, bConfigurationValue=1,
                   iConfiguration=0, bmAttributes=0x80, bMaxPower=45)

    def get_interface_descriptor(self, dev, intf, alt, config):
        return _ns(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=2,
                   bInterfaceClass=0xFF, bInterfaceSubClass=0xFF, bInterfaceProtocol=0xFF, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        address = (0x81, 0x02)[ep]
        return _ns(bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=2, wMaxPacketSize=64,
                   bInterval=0, bRefresh=0, bSynchAddress=0)

    def open_device(self, dev):
        if getattr(dev, "permission_denied", False):
            raise usb.core.USBError("Access denied (insufficient permissions)", errno=13)
        return dev

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        dev_handle._check()

    def get_configuration(self, dev_handle):
        return 1

    def claim_interface(self, dev_handle, intf):
        dev_handle._check()
        if dev_handle.kernel_driver:
            raise usb.core.USBError("Resource busy", errno=16)
        dev_handle.claimed = True

    def release_interface(self, dev_handle, intf):
        dev_handle.claimed = False

    def is_kernel_driver_active(self, dev_handle, intf):
        return dev_handle.kernel_driver

    def detach_kernel_driver(self, dev_handle, intf):
        dev_handle.kernel_driver = False

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        assert ep == 0x02
        return dev_handle.host_write(bytes(data))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        assert ep == 0x81
        data = dev_handle.host_read(len(buff))
        buff[: len(data)] = type(buff)(buff.typecode, data)
        return len(data)

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        assert bmRequestType == 0x40
        dev_handle.control(bRequest, wValue)
        return 0
