"""HapticDeviceSpaceMouse through a fake HID transport fed with report bytes.

The report bytes below follow the layouts public drivers document (report ID first,
little-endian int16); they were written by hand, not captured from a device.
"""

import struct

import numpy as np
import pytest

from dmarionette.hw.device import DeviceDisconnectedError, HapticDeviceError
from dmarionette.hw.safety import SafetyConfig
from dmarionette.hw.servo import run_servo_loop
from dmarionette.hw.spacemouse import HapticDeviceSpaceMouse, SpaceMouseReportParser

# SpaceNavigator-style split reports: x=+175 (half right), y=-350 (full away from the user),
# z=+350 (full down); rotation rz=+350 about HID z; buttons 0b10.
SPLIT_TRANSLATION = bytes.fromhex("01 af00 a2fe 5e01")
SPLIT_ROTATION = bytes.fromhex("02 0000 0000 5e01")
BUTTONS = bytes.fromhex("03 02")
# Single-report model: the same six values in one 13-byte report.
SINGLE = bytes.fromhex("01 af00 a2fe 5e01 0000 0000 5e01")
ZERO_SPLIT = [bytes.fromhex("01 000000000000"), bytes.fromhex("02 000000000000")]


class FakeTransport:
    """Queue of report bytes; ``read`` pops one (or returns b"" when empty)."""

    def __init__(self, reports=()):
        self.reports = list(reports)
        self.closed = False
        self.unplugged = False

    def push(self, *reports):
        self.reports.extend(reports)

    def read(self, max_length, timeout_ms=0):
        if self.unplugged:
            raise OSError("read error")
        return list(self.reports.pop(0)[:max_length]) if self.reports else []

    def close(self):
        self.closed = True


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_parser_split_and_single_layouts_agree():
    a, b = SpaceMouseReportParser(), SpaceMouseReportParser()
    for r in (SPLIT_TRANSLATION, SPLIT_ROTATION, BUTTONS):
        a.feed(r)
    for r in (SINGLE, BUTTONS):
        b.feed(r)
    assert a.layout == "split" and b.layout == "single"
    for p in (a, b):
        np.testing.assert_array_equal(p.translation, [175, -350, 350])
        np.testing.assert_array_equal(p.rotation, [0, 0, 350])
        assert p.buttons == 2
    a.feed(bytes.fromhex("17 64"))  # battery report: ignored
    assert a.ignored == 1
    assert struct.unpack("<h", SPLIT_TRANSLATION[3:5])[0] == -350


@pytest.mark.parametrize("reports", [[SPLIT_TRANSLATION, SPLIT_ROTATION, BUTTONS], [SINGLE, BUTTONS]])
def test_integrates_velocity_into_pose_in_sample_axes(reports):
    clock = FakeClock()
    t = FakeTransport()
    dev = HapticDeviceSpaceMouse(t, max_speed=0.1, max_angular_speed=1.0, clock=clock,
                                 workspace_min=(-1, -1, -1), workspace_max=(1, 1, 1))
    with dev:
        s0 = dev.read()
        np.testing.assert_allclose(s0.position, 0.0)
        t.push(*reports)
        dev.read()  # reports take effect from now on
        clock.t += 0.5
        s = dev.read()
        # HID (x, y, z) = (0.5, -1, +1) of full scale -> sample (x, y, z) = (0.5, -1 (down), -1 (away)).
        np.testing.assert_allclose(s.position, 0.1 * 0.5 * np.array([0.5, -1.0, -1.0]), atol=1e-12)
        # Rotation about HID +z (down) at 1 rad/s for 0.5 s = -0.5 rad about sample +y.
        c, sn = np.cos(-0.5), np.sin(-0.5)
        np.testing.assert_allclose(s.rotation, [[c, 0, sn], [0, 1, 0], [-sn, 0, c]], atol=1e-12)
        assert s.buttons == 2 and s.time == pytest.approx(0.5)
        t.push(*ZERO_SPLIT)  # cap released: the pose stays
        dev.read()
        clock.t += 1.0
        np.testing.assert_allclose(dev.read().position, s.position, atol=1e-12)
    assert t.closed


def test_deadzone_and_workspace_clamp():
    clock = FakeClock()
    t = FakeTransport([bytes.fromhex("01 0300 fdff 0300")])  # +-3 counts: drift at rest
    dev = HapticDeviceSpaceMouse(t, clock=clock)
    dev.open()
    dev.read()
    clock.t += 10.0
    np.testing.assert_allclose(dev.read().position, 0.0)
    t.push(SPLIT_TRANSLATION)
    dev.read()
    clock.t += 100.0
    np.testing.assert_allclose(dev.read().position, [0.1, -0.1, -0.1])  # held at the box


def test_force_is_ignored_or_refused():
    dev = HapticDeviceSpaceMouse(FakeTransport())
    dev.open()
    assert dev.spec.max_force == 0.0 and dev.spec.output_dof == 0
    dev.write_force([1.0, 0.0, 0.0])  # ignored
    strict = HapticDeviceSpaceMouse(FakeTransport(), refuse_force=True)
    strict.open()
    strict.write_force(np.zeros(3))  # motors-off zero is fine
    with pytest.raises(HapticDeviceError, match="no motors"):
        strict.write_force([1.0, 0.0, 0.0])


def test_servo_loop_with_a_spacemouse_sends_only_zero():
    t = FakeTransport([SPLIT_TRANSLATION])
    dev = HapticDeviceSpaceMouse(t, refuse_force=True)
    stats = run_servo_loop(dev, lambda s, tt: [1.0, 2.0, 3.0], duration=0.05, safety=SafetyConfig(ramp_time=0.0))
    assert stats.stop_reason == "duration" and stats.clamped_forces > 0 and t.closed


def test_unplugged_is_a_disconnect():
    t = FakeTransport()
    dev = HapticDeviceSpaceMouse(t)
    dev.open()
    t.unplugged = True
    with pytest.raises(DeviceDisconnectedError, match="unplugged"):
        dev.read()


class FakeHid:
    def __init__(self, devices, open_error=None):
        self.devices, self.open_error = devices, open_error

    def enumerate(self):
        return self.devices

    def device(self):
        outer = self

        class Dev(FakeTransport):
            def open_path(self, path):
                if outer.open_error:
                    raise OSError(outer.open_error)

        return Dev()


def test_open_errors_say_what_was_looked_for_and_how_to_fix():
    with pytest.raises(HapticDeviceError) as e:
        other = {"vendor_id": 0x1234, "product_id": 1, "path": b"/dev/hidraw0"}
        HapticDeviceSpaceMouse(hid_api=FakeHid([other])).open()
    assert "no 3Dconnexion device" in str(e.value) and "256f:c635" in str(e.value) and "046d:c626" in str(e.value)
    info = {"vendor_id": 0x256F, "product_id": 0xC635, "path": b"/dev/hidraw3"}
    with pytest.raises(HapticDeviceError) as e:
        HapticDeviceSpaceMouse(hid_api=FakeHid([info], open_error="open failed")).open()
    msg = str(e.value)
    assert "SpaceMouse Compact" in msg and "/dev/hidraw3" in msg and "open failed" in msg
    assert "udev" in msg and 'ATTRS{idVendor}=="256f"' in msg
    dev = HapticDeviceSpaceMouse(hid_api=FakeHid([info]))
    dev.open()
    assert dev.model == "SpaceMouse Compact" and dev.is_open


def test_real_hidapi_module_is_the_right_one():
    hid = pytest.importorskip("hid")
    assert hasattr(hid, "device") and hasattr(hid, "enumerate")
    # No SpaceMouse here: enumeration works and open reports it cleanly.
    with pytest.raises(HapticDeviceError, match="no 3Dconnexion device|HID enumeration failed"):
        HapticDeviceSpaceMouse().open()


def test_unplugged_mid_run_stops_the_servo_loop():
    import threading

    from dmarionette.hw.servo import ServoLoop

    t = FakeTransport([SPLIT_TRANSLATION] * 10)
    dev = HapticDeviceSpaceMouse(t, refuse_force=True)
    loop = ServoLoop(dev, lambda s, tt: [0.0, 0.0, 0.0], safety=SafetyConfig(ramp_time=0.0))
    timer = threading.Timer(0.1, lambda: setattr(t, "unplugged", True))
    timer.start()
    with pytest.raises(DeviceDisconnectedError, match="unplugged"):
        loop.run(duration=3.0)
    timer.join()
    assert loop.statistics.stop_reason == "disconnected" and loop.statistics.duration < 1.0
    assert t.closed and not dev.is_open
