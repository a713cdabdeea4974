"""Novint Falcon: kinematics round trips, packet codec, and the device end to end against a
virtual FTDI/Falcon behind a pyusb backend (tests/support/hw_fakes/virtual_falcon.py)."""

import time

import numpy as np
import pytest

from dmarionette.hw.device import DeviceDisconnectedError, HapticDeviceError
from dmarionette.hw.falcon import (
    FIRMWARE_ENV,
    FTDI,
    FalconPacketReader,
    HapticDeviceFalcon,
    decode_status_packet,
    encode_command_packet,
)
from dmarionette.hw.falcon_kinematics import FalconKinematics, FalconKinematicsError
from dmarionette.hw.safety import SafetyConfig
from dmarionette.hw.servo import run_servo_loop
usb = pytest.importorskip("usb", reason="pyusb is needed for the virtual Falcon backend")
from tests.support.hw_fakes.virtual_falcon import (VirtualFalcon, VirtualFalconBackend, reference_leg_angles,
                                                   reference_ticks)

FIRMWARE = bytes(range(256)) * 3 + b"\x01\x02\x03"  # a made-up "firmware" (the real one is never bundled)
ORIGIN = np.array([0.0, 0.0, 0.11])


def workspace_points(n, seed=0):
    rng = np.random.default_rng(seed)
    return ORIGIN + rng.uniform(-0.04, 0.04, size=(n, 3))


def test_ik_matches_an_independent_form_and_fk_inverts_it():
    k = FalconKinematics()
    for p in workspace_points(200):
        theta = k.leg_angles(p)
        np.testing.assert_allclose(theta, reference_leg_angles(p), atol=1e-10)
        np.testing.assert_allclose(k.constraints(p, theta), 0.0, atol=1e-15)
        np.testing.assert_allclose(k.position(theta, guess=ORIGIN), p, atol=1e-9)


def test_fk_from_encoder_ticks_is_within_quantisation():
    k = FalconKinematics()
    for p in workspace_points(50, seed=1):
        q = k.position(k.angles_from_encoders(reference_ticks(p)))
        assert np.linalg.norm(q - p) < 2e-4  # one tick is ~0.036 degrees of thigh, ~0.05 mm
    np.testing.assert_array_equal(k.encoders_from_angles(k.angles_from_encoders([-5, 0, 700])), [-5, 0, 700])


def test_jacobian_and_torques_by_virtual_work():
    k = FalconKinematics()
    p = np.array([0.01, -0.02, 0.12])
    h = 1e-6
    jfd = np.stack([(reference_leg_angles(p + dp) - reference_leg_angles(p - dp)) / (2 * h) for dp in np.eye(3) * h],
                   axis=1)
    np.testing.assert_allclose(k.jacobian(p), jfd, rtol=1e-6, atol=1e-6)
    force = np.array([1.0, -2.0, 0.5])
    tau = k.joint_torques(p, force)
    dp = np.array([1e-6, 2e-6, -1e-6])  # the same work done in joint and in Cartesian space
    assert tau @ (k.jacobian(p) @ dp) == pytest.approx(force @ dp, rel=1e-9)


def test_unreachable_position_is_refused():
    with pytest.raises(FalconKinematicsError, match="outside the workspace"):
        FalconKinematics().leg_angles([0.0, 0.0, 0.5])


def test_packet_codec_round_trip():
    pkt = encode_command_packet([-1, 300, -32768], leds=0x8, homing=True)
    assert len(pkt) == 16 and pkt[:1] == b"<" and pkt[-1:] == b">"
    assert all(0x41 <= b <= 0x50 for b in pkt[1:15])
    assert pkt[13] == 0x41 + 0x9
    # A status packet (same nibble scheme): encoders -1, 300, -32768, homed 0b101, buttons 0b0010.
    status = b"<" + pkt[1:13] + bytes([0x41 + 0x52, 0x41]) + b">"
    enc, homed, buttons = decode_status_packet(status)
    np.testing.assert_array_equal(enc, [-1, 300, -32768])
    assert homed == 0b101 and buttons == 0b0010
    reader = FalconPacketReader()
    assert reader.feed(b"xx" + status[:7]) == []
    got = reader.feed(status[7:] + status[:3])
    assert len(got) == 1 and reader.malformed == 2
    assert len(reader.feed(status[3:])) == 1


def open_falcon(vf, tmp_path, **kwargs):
    fw = tmp_path / "novint.bin"
    fw.write_bytes(FIRMWARE)
    kwargs.setdefault("firmware_path", fw)
    return HapticDeviceFalcon(backend=VirtualFalconBackend([vf]), **kwargs)


def test_firmware_handshake_upload_homing_read_write_close(tmp_path):
    vf = VirtualFalcon(firmware=FIRMWARE)
    dev = open_falcon(vf, tmp_path, force_timeout=0.1)
    dev.open()
    try:
        assert dev.firmware_loaded_now and bytes(vf.received_firmware) == FIRMWARE and vf.mode == "running"
        assert not vf.kernel_driver and vf.claimed  # ftdi_sio detached, interface claimed
        log = vf.ctrl_log
        # FTDI set-up, then the boot-loader settings, in libnifalcon's order.
        assert log[:2] == [(FTDI.RESET, FTDI.RESET_SIO), (FTDI.SET_BITMODE, FTDI.BITMODE_RESET)]
        boot = log.index((FTDI.SET_BAUD_RATE, FTDI.BAUD_BOOT))
        assert log[boot - 1] == (FTDI.SET_LATENCY_TIMER, 16)
        assert log[boot + 1:boot + 6] == [(FTDI.SET_DATA, 8), (FTDI.SET_FLOW_CTRL, 0), (FTDI.MODEM_CTRL, FTDI.RTS_LOW),
                                          (FTDI.MODEM_CTRL, FTDI.DTR_LOW), (FTDI.MODEM_CTRL, FTDI.DTR_HIGH)]
        assert (FTDI.SET_BAUD_RATE, FTDI.BAUD_UPLOAD) in log and vf.latency == 1 and vf.baud == FTDI.BAUD_NORMAL
        # Homing ran (homing bit sent, all three flags back) and the LED went green.
        assert vf.homed == 7 and vf.homing_packets >= vf.home_after
        time.sleep(0.02)
        assert vf.commands[-1][1] == 0x2
        # Positions: encoder ticks -> kinematics -> metres, origin at ORIGIN.
        for p in (np.array([0.0, 0.0, 0.11]), np.array([0.02, -0.01, 0.13]), np.array([-0.03, 0.02, 0.09])):
            vf.position = p
            time.sleep(0.02)
            s = dev.read()
            assert np.linalg.norm(s.position - (p - ORIGIN)) < 2e-4
            np.testing.assert_array_equal(s.orientation, [1, 0, 0, 0])
        vf.buttons = 0b0101
        time.sleep(0.02)
        assert dev.read().buttons == 0b0101
        # Force -> motor commands: -10000 * tau with J^T tau = F (tau checked by virtual work above),
        # at the position the device last read.
        at = dev.read().position + ORIGIN
        force = np.array([1.0, 2.0, -1.5])
        n0 = len(vf.commands)
        dev.write_force(force)
        time.sleep(0.01)
        expected = np.rint(-10000.0 * dev.kinematics.joint_torques(at, force)).astype(int)
        np.testing.assert_array_equal(dev.motor_commands, expected)
        assert any(np.array_equal(c[0], expected) for c in vf.commands[n0:])
        assert np.abs(expected).max() > 100
    finally:
        dev.close()
    np.testing.assert_array_equal(vf.commands[-1][0], [0, 0, 0])  # motors off
    assert not vf.claimed and not dev.is_open


def test_firmware_already_running_is_not_reloaded(tmp_path):
    vf = VirtualFalcon(firmware_running=True)
    with HapticDeviceFalcon(backend=VirtualFalconBackend([vf]), home=False) as dev:
        assert not dev.firmware_loaded_now and len(vf.received_firmware) == 0
        assert dev.read().position.shape == (3,)


def test_stale_force_goes_to_zero_in_the_io_thread(tmp_path):
    vf = VirtualFalcon(firmware_running=True)
    with HapticDeviceFalcon(backend=VirtualFalconBackend([vf]), home=False, force_timeout=0.005) as dev:
        dev.read()
        dev.write_force([0.0, 3.0, 0.0])
        time.sleep(0.05)
        nonzero = [i for i, c in enumerate(vf.commands) if np.any(c[0] != 0)]
        assert nonzero and np.all(vf.commands[-1][0] == 0)


def test_missing_firmware_file_messages(tmp_path, monkeypatch):
    monkeypatch.delenv(FIRMWARE_ENV, raising=False)
    vf = VirtualFalcon(firmware=FIRMWARE)
    with pytest.raises(HapticDeviceError) as e:
        HapticDeviceFalcon(backend=VirtualFalconBackend([vf])).open()
    msg = str(e.value)
    assert "no firmware running" in msg and FIRMWARE_ENV in msg and "novint.bin" in msg and "none is bundled" in msg
    assert not vf.claimed  # released after the failed open
    with pytest.raises(HapticDeviceError, match=r"firmware file .*nope\.bin not found"):
        HapticDeviceFalcon(tmp_path / "nope.bin", backend=VirtualFalconBackend([VirtualFalcon()])).open()


def test_wrong_firmware_is_detected(tmp_path):
    vf = VirtualFalcon(firmware=b"something else")
    with pytest.raises(HapticDeviceError, match="does not answer packets"):
        open_falcon(vf, tmp_path).open()


def test_no_device_and_permission_messages(tmp_path):
    with pytest.raises(HapticDeviceError) as e:
        HapticDeviceFalcon(backend=VirtualFalconBackend([])).open()
    assert "no Novint Falcon found" in str(e.value) and "0x0403" in str(e.value) and "0xcb48" in str(e.value)
    with pytest.raises(HapticDeviceError) as e:
        open_falcon(VirtualFalcon(firmware=FIRMWARE, permission_denied=True), tmp_path).open()
    assert "permission denied" in str(e.value) and "udev" in str(e.value) and 'ATTRS{idProduct}=="cb48"' in str(e.value)


def test_homing_timeout_says_what_to_do(tmp_path):
    vf = VirtualFalcon(firmware_running=True, home_after=10**9)
    with pytest.raises(HapticDeviceError, match="pull the grip all the way out"):
        HapticDeviceFalcon(backend=VirtualFalconBackend([vf]), homing_timeout=0.1).open()


def test_unplug_is_a_disconnect_and_the_servo_loop_stops(tmp_path):
    vf = VirtualFalcon(firmware_running=True)
    dev = HapticDeviceFalcon(backend=VirtualFalconBackend([vf]))

    def step(sample, t):
        if t > 0.05:
            vf.unplugged = True
        return -50.0 * sample.position

    with pytest.raises(DeviceDisconnectedError, match="unplugged"):
        run_servo_loop(dev, step, duration=2.0, safety=SafetyConfig(ramp_time=0.0))
    assert not dev.is_open


def test_real_pyusb_without_a_falcon_says_so():
    # The real libusb backend (or its absence): either way a clear error, never a crash.
    with pytest.raises(HapticDeviceError, match="no Novint Falcon found|no USB backend"):
        HapticDeviceFalcon().open()


def test_unplug_mid_run_motors_off_and_a_replugged_falcon_starts_at_zero():
    """Unplugged while pushing: a clear error, the loop stops, no command reaches the device after,
    and a re-plugged Falcon gets zero motor commands (the stale force is not resumed)."""
    from dmarionette.hw.servo import ServoLoop

    vf = VirtualFalcon(firmware_running=True)
    vf.position = np.array([0.02, 0.0, 0.11])
    dev = HapticDeviceFalcon(backend=VirtualFalconBackend([vf]))
    unplugged_at = []

    def step(sample, t):
        if t > 0.15 and not unplugged_at:
            unplugged_at.append(len(vf.commands))
            vf.unplugged = True
        return -50.0 * sample.position  # pushes: ~1 N

    loop = ServoLoop(dev, step, safety=SafetyConfig(ramp_time=0.0, continuous_time_constant=0.0))
    with pytest.raises(DeviceDisconnectedError, match="Falcon: USB I/O failed.*unplugged or powered off"):
        loop.run(duration=3.0)
    assert loop.statistics.stop_reason == "disconnected" and loop.statistics.duration < 1.0
    assert not dev.is_open
    assert any(np.any(motor != 0) for motor, _, _ in vf.commands[:unplugged_at[0]])  # it was pushing
    sent = len(vf.commands)
    time.sleep(0.05)
    assert len(vf.commands) == sent  # nothing is sent to an unplugged device any more
    vf.unplugged = False  # plugged back in: a new session starts from zero force
    with HapticDeviceFalcon(backend=VirtualFalconBackend([vf]), home=False) as again:
        time.sleep(0.03)
        again.read()
    assert len(vf.commands) > sent and all(np.all(motor == 0) for motor, _, _ in vf.commands[sent:])
