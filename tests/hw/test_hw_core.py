"""Device interface, simulated and replay devices, eq. 3 mapping, force safety filter."""

import ast
import pathlib

import numpy as np
import pytest

from dmarionette.hw.device import (
    DeviceDisconnectedError,
    HapticDeviceError,
    HapticDeviceSpec,
    HapticSample,
)
from dmarionette.hw.mapping import DeviceMapping, rigid_transform, scale_transform
from dmarionette.hw.safety import ForceSafetyFilter, SafetyConfig, clamp_force
from dmarionette.hw.simulated import DEFAULT_SIMULATED_SPEC, HapticDeviceReplay, HapticDeviceSimulated

HW = pathlib.Path(__file__).resolve().parents[2] / "dmarionette" / "hw"


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_hw_imports_neither_kernels_nor_warp():
    for path in HW.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [("." * node.level) + (node.module or "")]
            for n in names:
                assert "warp" not in n.split(".") and "kernels" not in n, f"{path.name} imports {n}"
                # Outside hw/, only the NumPy-only rotations leaf.
                assert n.split(".")[0] != "dmarionette" or n == "dmarionette.rotations", f"{path.name} imports {n}"


def test_sample_orientation_round_trips_through_its_rotation_matrix():
    """Samples hold (w, x, y, z); ``make`` takes either form, ``rotation`` gives the matrix."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        r = HapticSample.make(0.0, np.zeros(3), q).rotation
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(HapticSample.make(0.0, np.zeros(3), r).orientation, q, atol=1e-12)
    turn = HapticSample.make(0.0, np.zeros(3), [np.cos(0.3), 0, 0, np.sin(0.3)])
    np.testing.assert_allclose(turn.rotation, rot_z(0.6), atol=1e-12)


def test_spec_validation_names_the_problem():
    with pytest.raises(ValueError, match="max_continuous_force"):
        HapticDeviceSpec("x", 1.0, 2.0, (-1, -1, -1), (1, 1, 1))
    with pytest.raises(ValueError, match="workspace_min must be below"):
        HapticDeviceSpec("x", 1.0, 0.5, (1, -1, -1), (1, 1, 1))


def test_simulated_device_follows_trajectory_and_records_forces():
    clock = FakeClock()
    traj = lambda t: (np.array([t, 2 * t, 0.0]), rot_z(t), 1)  # noqa: E731
    dev = HapticDeviceSimulated(traj, clock=clock)
    with pytest.raises(HapticDeviceError, match="not open"):
        dev.read()
    with dev:
        clock.t += 0.25
        s = dev.read()
        assert s.time == pytest.approx(0.25)
        np.testing.assert_allclose(s.position, [0.25, 0.5, 0.0])
        np.testing.assert_allclose(s.rotation, rot_z(0.25), atol=1e-12)
        assert s.buttons == 1
        dev.write_force([1.0, 0.0, -0.5])
        with pytest.raises(ValueError, match=r"shape \(3,\)"):
            dev.write_force([1.0, 2.0])
    times, forces = dev.force_log()
    np.testing.assert_allclose(times, [0.25, 0.25])
    np.testing.assert_allclose(forces, [[1.0, 0.0, -0.5], [0.0, 0.0, 0.0]])  # close writes zero
    assert dev.close_count == 1 and not dev.is_open


def test_simulated_device_set_pose_and_disconnect():
    dev = HapticDeviceSimulated(clock=FakeClock())
    dev.open()
    np.testing.assert_allclose(dev.read().position, DEFAULT_SIMULATED_SPEC.workspace_center)
    dev.set_pose([0.01, 0.02, 0.03], np.array([0.0, 1.0, 0.0, 0.0]), buttons=3)
    s = dev.read()
    np.testing.assert_allclose(s.position, [0.01, 0.02, 0.03])
    np.testing.assert_allclose(s.orientation, [0, 1, 0, 0])
    assert s.buttons == 3
    dev.simulate_disconnect()
    with pytest.raises(DeviceDisconnectedError):
        dev.read()
    with pytest.raises(DeviceDisconnectedError):
        dev.write_force(np.zeros(3))
    dev.close()  # never raises on a lost device
    assert not dev.is_open


def test_replay_plays_samples_at_their_timestamps():
    clock = FakeClock()
    times = np.array([10.0, 10.1, 10.3])
    pos = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float) * 0.01
    rots = np.stack([rot_z(a) for a in (0.0, 0.1, 0.2)])
    dev = HapticDeviceReplay(times, pos, rots, buttons=[0, 1, 2], clock=clock)
    dev.open()
    got = []
    for dt in (0.0, 0.05, 0.1 + 1e-9, 0.29, 0.3 + 1e-9, 5.0):
        clock.t = 100.0 + dt
        s = dev.read()
        got.append((s.time, s.position[0], s.buttons))
    np.testing.assert_allclose(got, [(0.0, 0.0, 0), (0.0, 0.0, 0), (0.1, 0.01, 1), (0.1, 0.01, 1),
                                     (0.3, 0.02, 2), (0.3, 0.02, 2)], atol=1e-12)
    assert dev.finished
    np.testing.assert_allclose(dev.read().rotation, rot_z(0.2), atol=1e-12)
    with pytest.raises(ValueError, match="strictly increasing"):
        HapticDeviceReplay([0.0, 0.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"positions must have shape \(2, 3\)"):
        HapticDeviceReplay([0.0, 1.0], np.zeros((3, 3)))


def test_replay_loops():
    clock = FakeClock()
    dev = HapticDeviceReplay([0.0, 0.5], [[0, 0, 0], [1, 0, 0]], loop=True, clock=clock)
    dev.open()
    clock.t += 1.2  # period 1.0 s (duration 0.5 + one sample step)
    s = dev.read()
    assert s.time == pytest.approx(1.0) and s.position[0] == 0.0 and not dev.finished


def test_mapping_eq3_known_values():
    # W: 90 deg about z, then translate (1, 2, 3); S: scale 10.
    m = DeviceMapping(scale_transform(10.0), rigid_transform(rot_z(np.pi / 2), [1.0, 2.0, 3.0]))
    p = np.array([0.1, 0.0, 0.0])
    # W p = (0, 0.1, 0) + (1, 2, 3) = (1, 2.1, 3); S of that = (10, 21, 30).
    np.testing.assert_allclose(m.position_to_world(p), [10.0, 21.0, 30.0], atol=1e-12)
    np.testing.assert_allclose(m.matrix @ np.r_[p, 1.0], [10.0, 21.0, 30.0, 1.0], atol=1e-12)
    # Force: through W's rotation only, not scaled: world +y is device +x.
    np.testing.assert_allclose(m.force_to_device([0.0, 2.0, 0.0]), [2.0, 0.0, 0.0], atol=1e-12)
    # Stiffness: world 100 N/m felt as 1000 N/m (one device metre is ten world metres).
    assert m.stiffness_to_device(100.0) == pytest.approx(1000.0)


def test_mapping_round_trips_and_anisotropic_stiffness():
    rng = np.random.default_rng(1)
    q = rng.normal(size=4)
    m = DeviceMapping.make(scale=[2.0, 3.0, 0.5], rotation=q / np.linalg.norm(q), translation=[0.1, -0.2, 0.3])
    pts = rng.normal(size=(10, 3))
    np.testing.assert_allclose(m.position_to_device(m.position_to_world(pts)), pts, atol=1e-12)
    f = rng.normal(size=(10, 3))
    np.testing.assert_allclose(m.force_to_world(m.force_to_device(f)), f, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(m.force_to_device(f), axis=1), np.linalg.norm(f, axis=1))
    # Stiffness matrix agrees with a finite displacement: F_dev = -K_dev d.
    k_world = 50.0
    d = np.array([1e-3, -2e-3, 0.5e-3])
    p0 = np.array([0.01, 0.02, 0.03])
    f_world = -k_world * (m.position_to_world(p0 + d) - m.position_to_world(p0))
    np.testing.assert_allclose(m.force_to_device(f_world), -m.stiffness_to_device(k_world) @ d, atol=1e-12)
    # Orientation: W's rotation composes, scale does not act.
    s = HapticSample.make(0.0, p0, rot_z(0.3))
    _, q_world = m.sample_to_world(s)
    np.testing.assert_allclose(HapticSample.make(0.0, p0, q_world).rotation, m.rotation @ rot_z(0.3), atol=1e-12)


def test_mapping_refuses_non_rigid_w_and_bad_scale():
    with pytest.raises(ValueError, match="must be rigid"):
        DeviceMapping(np.eye(4), np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="must be diagonal"):
        DeviceMapping(np.ones((4, 4)), np.eye(4))
    with pytest.raises(ValueError, match="> 0"):
        scale_transform(-1.0)


def test_clamp_keeps_direction_and_zeroes_nonfinite():
    f = clamp_force([3.0, 4.0, 0.0], 2.5)
    np.testing.assert_allclose(f, [1.5, 2.0, 0.0])
    np.testing.assert_allclose(clamp_force([0.1, 0.2, 0.3], 2.5), [0.1, 0.2, 0.3])
    for bad in ([np.nan, 0, 0], [np.inf, 1, 1], [0, -np.inf, 0]):
        np.testing.assert_array_equal(clamp_force(bad, 2.5), np.zeros(3))


def test_safety_filter_ramp_clamp_nonfinite():
    spec = DEFAULT_SIMULATED_SPEC
    filt = ForceSafetyFilter(spec, SafetyConfig(ramp_time=0.5, continuous_time_constant=0.0))
    np.testing.assert_allclose(filt([1.0, 0, 0], 0.0), 0.0)  # ramp starts at zero
    np.testing.assert_allclose(filt([1.0, 0, 0], 0.25), [0.5, 0, 0])  # smoothstep(0.5) = 0.5
    np.testing.assert_allclose(filt([1.0, 0, 0], 0.5), [1.0, 0, 0])
    big = filt([0.0, 30.0, 40.0], 1.0)
    np.testing.assert_allclose(big, np.array([0.0, 3.0, 4.0]) / 5.0 * spec.max_force)
    assert filt.clamp_count == 1
    np.testing.assert_array_equal(filt([np.nan, 1.0, 1.0], 1.0), np.zeros(3))
    assert filt.nonfinite_count == 1
    ramp = [ForceSafetyFilter(spec, SafetyConfig(ramp_time=1.0)).ramp_factor(t) for t in np.linspace(0, 1, 11)]
    assert np.all(np.diff(ramp) > 0) and ramp[0] == 0.0 and ramp[-1] == 1.0
    with pytest.raises(ValueError, match="outside"):
        ForceSafetyFilter(spec, SafetyConfig(max_force=10.0))
    with pytest.raises(ValueError, match="within 5 ms"):
        SafetyConfig(watchdog_timeout=0.01)


def test_safety_filter_continuous_limit():
    spec = DEFAULT_SIMULATED_SPEC  # 3.3 N peak, 0.88 N continuous
    filt = ForceSafetyFilter(spec, SafetyConfig(ramp_time=0.0, continuous_time_constant=0.5))
    mags = [np.linalg.norm(filt([3.0, 0, 0], i * 1e-3)) for i in range(5000)]
    assert mags[1] == pytest.approx(3.0)  # a short peak is allowed
    assert mags[-1] == pytest.approx(spec.max_continuous_force, rel=1e-6)  # held: continuous rating
    assert max(mags) <= spec.max_force


def test_mapping_wraps_a_world_step_for_the_device():
    m = DeviceMapping.make(scale=10.0, rotation=rot_z(np.pi / 2), translation=[0.0, 1.0, 0.0])
    seen = []

    def world_step(sample, t):
        seen.append(sample)
        return np.array([0.0, 3.0, 0.0])  # world +y

    f = m.wrap(world_step)(HapticSample.make(0.5, [0.1, 0.0, 0.0], rot_z(0.2), buttons=4), 0.5)
    np.testing.assert_allclose(f, [3.0, 0.0, 0.0], atol=1e-12)  # world +y is device +x
    s = seen[0]
    np.testing.assert_allclose(s.position, [0.0, 11.0, 0.0], atol=1e-12)  # S (W p) = 10 * (0, 1.1, 0)
    np.testing.assert_allclose(s.rotation, rot_z(np.pi / 2 + 0.2), atol=1e-12)
    assert s.time == 0.5 and s.buttons == 4
