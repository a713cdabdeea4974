"""HapticDeviceOpenHaptics against a stand-in libHD compiled from tests/support/hw_fakes/fake_hd.c."""

import ctypes
import pathlib
import shutil
import subprocess
import time

import numpy as np
import pytest

from dmarionette.hw.device import DeviceDisconnectedError, HapticDeviceError
from dmarionette.hw.openhaptics import HD, LIBRARY_ENV, HapticDeviceOpenHaptics, find_hd_library
from dmarionette.hw.safety import SafetyConfig
from dmarionette.hw.servo import run_servo_loop

FAKE_SOURCE = pathlib.Path(__file__).resolve().parents[1] / "support" / "hw_fakes" / "fake_hd.c"


@pytest.fixture(scope="module")
def fake_lib_path(tmp_path_factory):
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not found: cannot build the stand-in libHD for the OpenHaptics tests")
    out = tmp_path_factory.mktemp("fake_hd") / "libHD.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-O2", "-pthread", "-Wall", "-Werror", str(FAKE_SOURCE),
                    "-o", str(out)], check=True)
    return str(out)


class Fake:
    """Test controls of the stand-in library (the same loaded copy the device uses)."""

    def __init__(self, path):
        self.lib = ctypes.CDLL(path)
        self.lib.fake_hd_force_log.restype = ctypes.c_long
        self.lib.fake_hd_callback_count.restype = ctypes.c_long
        self.lib.fake_hd_reset()

    def set_transform(self, rotation, position_mm):
        m = np.eye(4)
        m[:3, :3] = rotation
        m[:3, 3] = position_mm
        self.lib.fake_hd_set_transform((ctypes.c_double * 16)(*m.T.reshape(-1)))  # column-major

    def force_log(self):
        n = 65536
        t, f = (ctypes.c_double * n)(), (ctypes.c_double * (3 * n))()
        k = self.lib.fake_hd_force_log(t, f, n)
        return np.array(t[:k]), np.array(f[: 3 * k]).reshape(k, 3)

    def state(self):
        a, b, c = ctypes.c_int(), ctypes.c_int(), ctypes.c_int()
        n = self.lib.fake_hd_state(ctypes.byref(a), ctypes.byref(b), ctypes.byref(c))
        return dict(initialized=a.value, force_enabled=b.value, scheduler=c.value, callbacks=n)


@pytest.fixture
def fake(fake_lib_path):
    f = Fake(fake_lib_path)
    yield f
    f.lib.fake_hd_reset()


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def wait_for(cond, timeout=1.0):
    end = time.perf_counter() + timeout
    while not cond():
        if time.perf_counter() > end:
            raise AssertionError("condition not met in time")
        time.sleep(0.001)


def test_constants_match_openhaptics_headers():
    # Values of HD/hdDefines.h and HD/hdScheduler.h (OpenHaptics 3.x).
    assert (HD.CURRENT_BUTTONS, HD.CURRENT_TRANSFORM, HD.CURRENT_FORCE) == (0x2000, 0x2052, 0x2700)
    assert (HD.NOMINAL_MAX_FORCE, HD.NOMINAL_MAX_CONTINUOUS_FORCE, HD.FORCE_OUTPUT) == (0x2603, 0x2604, 0x4000)
    assert (HD.CALLBACK_DONE, HD.CALLBACK_CONTINUE, HD.INVALID_HANDLE) == (0, 1, 0xFFFFFFFF)
    assert (HD.CALIBRATION_OK, HD.CALIBRATION_NEEDS_UPDATE, HD.CALIBRATION_NEEDS_MANUAL_INPUT) == (
        0x5000, 0x5001, 0x5002)


def test_missing_library_names_env_var(monkeypatch, tmp_path):
    monkeypatch.setenv(LIBRARY_ENV, str(tmp_path / "nowhere" / "libHD.so"))
    monkeypatch.setattr("ctypes.util.find_library", lambda name: None)
    with pytest.raises(HapticDeviceError) as e:
        HapticDeviceOpenHaptics().open()
    msg = str(e.value)
    assert "HD library not found" in msg and LIBRARY_ENV in msg and "nowhere/libHD.so" in msg
    assert 'find_library("HD")' in msg and "OpenHaptics" in msg


def test_library_found_through_env_var(monkeypatch, fake_lib_path):
    monkeypatch.setenv(LIBRARY_ENV, fake_lib_path)
    assert find_hd_library() == fake_lib_path


def test_wrong_library_is_named(fake_lib_path, tmp_path):
    src = tmp_path / "other.c"
    src.write_text("int hdInitDevice(const char *n) { return 0; }\n")
    lib = tmp_path / "libother.so"
    subprocess.run([shutil.which("gcc"), "-shared", "-fPIC", str(src), "-o", str(lib)], check=True)
    with pytest.raises(HapticDeviceError, match="lacks hdDisableDevice.*OPENHAPTICS_HD_LIBRARY"):
        HapticDeviceOpenHaptics(lib).open()


def test_missing_device_error_has_code_and_advice(fake, fake_lib_path):
    fake.lib.fake_hd_set_init_failure(HD.COMM_ERROR)
    with pytest.raises(HapticDeviceError) as e:
        HapticDeviceOpenHaptics(fake_lib_path).open()
    msg = str(e.value)
    assert "hdInitDevice(HD_DEFAULT_DEVICE) failed" in msg and "0x0302" in msg
    assert "Communication error" in msg and "internal code -1" in msg
    assert "plugged in" in msg and "Touch Setup" in msg
    with pytest.raises(HapticDeviceError, match=r"hdInitDevice\(No Such Arm\).*Invalid device handle"):
        fake.lib.fake_hd_set_init_failure(HD.SUCCESS)
        HapticDeviceOpenHaptics(fake_lib_path, device_name="No Such Arm").open()


def test_open_read_write_close_end_to_end(fake, fake_lib_path):
    fake.set_transform(rot_x(0.4), [10.0, -20.0, 30.0])
    fake.lib.fake_hd_set_buttons(2)
    dev = HapticDeviceOpenHaptics(fake_lib_path, force_timeout=1.0)  # stale-force zeroing: tested below
    with dev:
        st = fake.state()
        assert st == dict(initialized=1, force_enabled=1, scheduler=1, callbacks=1)
        assert dev.spec.max_force == pytest.approx(3.3) and dev.spec.max_continuous_force == pytest.approx(0.88)
        np.testing.assert_allclose(dev.spec.workspace_min, [-0.08, -0.06, -0.035])
        s = dev.read()
        np.testing.assert_allclose(s.position, [0.010, -0.020, 0.030])  # mm -> m
        np.testing.assert_allclose(s.rotation, rot_x(0.4), atol=1e-12)
        assert s.buttons == 2 and s.time >= 0.0
        fake.set_transform(np.eye(3), [1.0, 2.0, 3.0])
        wait_for(lambda: abs(dev.read().position[0] - 0.001) < 1e-12)
        dev.write_force([0.5, -0.25, 1.0])
        wait_for(lambda: np.allclose(fake.force_log()[1][-1], [0.5, -0.25, 1.0]))
        n0 = fake.lib.fake_hd_callback_count()
        time.sleep(0.05)
        rate = (fake.lib.fake_hd_callback_count() - n0) / 0.05
        print(f"fake scheduler callback rate {rate:.0f} Hz")
        assert rate > 100  # it runs; ~1 kHz when the machine is idle (not asserted: timing)
    assert fake.state() == dict(initialized=0, force_enabled=0, scheduler=0, callbacks=0)
    _, forces = fake.force_log()
    np.testing.assert_array_equal(forces[-1], np.zeros(3))  # motors off before the device went away
    assert not dev.is_open


def test_stale_force_goes_to_zero_in_the_callback(fake, fake_lib_path):
    with HapticDeviceOpenHaptics(fake_lib_path, force_timeout=0.005) as dev:
        # Written every 1 ms until a callback has sent it (one write alone can go stale before
        # libHD's thread first runs on a loaded machine, and then 1.0 is never sent), then not.
        t_write = time.perf_counter()

        def written() -> bool:
            nonlocal t_write
            dev.write_force([1.0, 0.0, 0.0])
            t_write = time.perf_counter()
            time.sleep(0.001)
            return fake.force_log()[1][-1][0] == 1.0

        wait_for(written)
        time.sleep(0.05)  # nobody writes
        times, forces = fake.force_log()
        zero = times[(times > t_write) & np.all(forces == 0.0, axis=1)]
        # 5 ms timeout + one 1 ms tick on a quiet machine; the bound leaves room for a
        # loaded one (the callback needs the GIL from libHD's thread).
        print(f"stale force zeroed {(zero[0] - t_write) * 1e3:.1f} ms after the last write")
        assert len(zero) > 0 and zero[0] - t_write < 0.03


def test_injected_error_surfaces_as_disconnect(fake, fake_lib_path):
    dev = HapticDeviceOpenHaptics(fake_lib_path)
    dev.open()
    fake.lib.fake_hd_inject_error(HD.COMM_ERROR, 42)
    with pytest.raises(DeviceDisconnectedError, match=r"0x0302 \(Communication error\), internal code 42"):
        wait_for(lambda: dev.read() is None)
    dev.close()
    assert fake.state()["initialized"] == 0


def test_calibration_update_uses_supported_style(fake, fake_lib_path):
    fake.lib.fake_hd_set_calibration(HD.CALIBRATION_NEEDS_UPDATE, HD.CALIBRATION_INKWELL)
    with HapticDeviceOpenHaptics(fake_lib_path) as dev:
        assert dev.calibration_status == HD.CALIBRATION_OK
    style = ctypes.c_int()
    assert fake.lib.fake_hd_calibration_updates(ctypes.byref(style)) == 1 and style.value == HD.CALIBRATION_INKWELL
    fake.lib.fake_hd_set_calibration(HD.CALIBRATION_NEEDS_MANUAL_INPUT, 0)
    with pytest.raises(HapticDeviceError, match="inkwell"):
        HapticDeviceOpenHaptics(fake_lib_path).open()
    assert fake.state()["initialized"] == 0  # released after the failed open


def test_servo_loop_through_openhaptics(fake, fake_lib_path):
    fake.set_transform(np.eye(3), [0.0, 50.0, 0.0])
    dev = HapticDeviceOpenHaptics(fake_lib_path)
    k = 100.0  # N/m spring towards the origin

    stats = run_servo_loop(dev, lambda s, t: -k * s.position, duration=0.3,
                           safety=SafetyConfig(ramp_time=0.05, continuous_time_constant=0.0))
    print(stats.summary())
    _, forces = fake.force_log()
    # -k y = -5 N, clamped to the device's 3.3 N (reached unless a loaded machine made the
    # watchdog trip and ramp in again); then motors off at the end.
    assert -3.3 - 1e-9 <= forces[:, 1].min() < -1.0 and np.all(forces[:, [0, 2]] == 0.0)
    if stats.watchdog_trips == 0:
        assert forces[:, 1].min() == pytest.approx(-3.3)
    np.testing.assert_array_equal(forces[-1], np.zeros(3))
    assert stats.stop_reason == "duration" and not dev.is_open


def test_unplug_mid_run_stops_the_servo_loop_with_force_output_disabled(fake, fake_lib_path):
    """A communication error (the device unplugged) while the loop pushes: a clear error, the loop
    stops, and the library is left with force output disabled, the scheduler stopped."""
    import threading

    from dmarionette.hw.servo import ServoLoop

    fake.set_transform(np.eye(3), [0.0, 20.0, 0.0])
    dev = HapticDeviceOpenHaptics(fake_lib_path)
    loop = ServoLoop(dev, lambda s, t: -100.0 * s.position,
                     safety=SafetyConfig(ramp_time=0.0, continuous_time_constant=0.0))
    timer = threading.Timer(0.2, lambda: fake.lib.fake_hd_inject_error(HD.COMM_ERROR, 7))
    timer.start()
    with pytest.raises(DeviceDisconnectedError, match=r"0x0302 \(Communication error\)"):
        loop.run(duration=3.0)
    timer.join()
    assert loop.statistics.stop_reason == "disconnected" and loop.statistics.duration < 1.0
    _, forces = fake.force_log()
    assert forces[:, 1].min() < -1.0  # it was pushing (-2 N) before
    assert fake.state() == {"initialized": 0, "force_enabled": 0, "scheduler": 0, "callbacks": 0}
    assert not dev.is_open
