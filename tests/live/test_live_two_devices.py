"""Two devices drive the two bars (paper §3: two Omnis), each with its own mapping, force and limits."""

import json
import re

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmarionette.hw import DeviceMapping, HapticSample, SafetyConfig, ServoLoop
from dmarionette.hw.device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError, HapticDeviceSpec
from dmarionette.hw.simulated import HapticDeviceSimulated
from dmarionette.live.run import LiveMarionette, make_physics_step, run_live
from dmarionette.live.setup import bar_mapping, make_device
from dmarionette.marionette.rollout import simulate_marionette

wp.config.log_level = wp.LOG_WARNING

BARS = ["main", "hand"]
# Full force at once, and again at once after a watchdog trip (a loaded machine trips it).
NO_RAMP = SafetyConfig(ramp_time=0.0, continuous_time_constant=0.0, rearm_ramp_time=0.0)


def rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_two_devices_tick_by_tick_reproduce_the_offline_simulation(model):
    """Both bars driven by devices along the scene's own bar motion: 30 puppet steps equal the
    offline rollout, and each device gets its own bar's reaction through its own ``W`` rotation.

    The two mappings differ (scale 1 and no rotation; scale 2 and 30 deg about z with the origin
    at the bar's start), so a device fed the other bar's force, or a force not rotated back,
    would differ by ~0.1 N. The samples go device -> world through ``S W`` and back, which
    costs round-off only (~1e-16 m, times a string stiffness of ~1e3 N/m: ~1e-13 N); the puppet
    and the forces are compared at 1e-12 (measured: both bit-identical).
    """
    live = LiveMarionette(model)
    names = model.bar_names
    assert set(BARS) <= set(names)
    steps = 30 * model.substeps
    times = model.string_dt * np.arange(1, steps + 1)
    main_start = np.array(model.scene.bars[names.index("main")].trajectory.positions[0])
    hand_start = np.array(model.scene.bars[names.index("hand")].trajectory.positions[0])
    mappings = [DeviceMapping.make(1.0, translation=main_start),
                DeviceMapping.make(2.0, rotation=rot_z(np.pi / 6), translation=hand_start / 2.0)]
    np.testing.assert_allclose(mappings[1].position_to_world(np.zeros(3)), hand_start, atol=1e-15)
    poses = [model.scene.bars[names.index(b)].trajectory.pose(times) for b in BARS]
    step = DeviceMapping.wrap_many(mappings, make_physics_step(live, BARS, steps * model.string_dt))
    forces = np.zeros((steps, 2, 3))
    for k in range(steps):
        samples = tuple(HapticSample.make(times[k], m.position_to_device(p[0][k]), m.rotation.T @ p[2][k])
                        for m, p in zip(mappings, poses))
        forces[k] = step(samples, times[k])
    offline = simulate_marionette(model, 30 * model.puppet_dt - 1e-9, progress=False)
    assert offline.frame_time[-1] == pytest.approx(live.time)
    np.testing.assert_allclose(live.state.puppet.joint_q.numpy()[0], offline.joint_q[-1], rtol=0, atol=1e-12)
    for i, (bar, m) in enumerate(zip(BARS, mappings)):
        expected = m.force_to_device(offline.bar_reaction[:steps, names.index(bar)])
        np.testing.assert_allclose(forces[:, i], expected, rtol=0, atol=1e-12)
    # The two bars pull differently, and the hand device's force is turned by its W: a swap shows.
    assert np.abs(forces[:, 0] - forces[:, 1]).max() > 0.05
    assert np.abs(forces[:, 1] - offline.bar_reaction[:steps, names.index("hand")]).max() > 0.01


def test_device_stiffness_is_the_world_stiffness_times_the_workspace_scale(model):
    """With ``P' = S W P`` a device displacement ``u`` moves the bar by ``S u`` and the force comes
    back unscaled, so the stiffness felt at the device is ``S`` times the world one (issue #5 item 2).

    Measured on the marionette: each run starts from rest and holds the device for 10 ticks; the
    stiffness is the force difference over the displacement, per axis (3x3, central differences).
    The device origin must sit on the bar's start for any ``S`` (the rest run with ``S = 2``
    equals the one with ``S = 1``), and ``K_dev = S K_world`` =
    :meth:`DeviceMapping.stiffness_to_device`. ``S = 2`` is a power of two, so every scaling is
    exact in binary floating point and the identities hold bit for bit (measured: K_world has
    829.5 N/m vertically, 12.7 and 14.5 N/m across, after 10 ticks from rest).
    """
    live = LiveMarionette(model)
    s, u, ticks = 2.0, 1e-4, 10

    def force_after(mapping, position_device):
        live.reset()
        step = mapping.wrap(make_physics_step(live, "main", ticks * model.string_dt))
        for k in range(ticks):
            force = step(HapticSample.make(k * model.string_dt, position_device), 0.0)
        return force

    one, scaled = bar_mapping(model, "main", 1.0), bar_mapping(model, "main", s)
    start = np.array(model.scene.bars[0].trajectory.positions[0])
    np.testing.assert_array_equal(scaled.position_to_world(np.zeros(3)), start)
    rest_one, rest_scaled = force_after(one, np.zeros(3)), force_after(scaled, np.zeros(3))
    assert np.all(rest_one == force_after(one, np.zeros(3)))  # reset() gives the same run again
    np.testing.assert_array_equal(rest_scaled, rest_one)
    k_world, k_dev = np.zeros((3, 3)), np.zeros((3, 3))
    for axis in range(3):
        e = np.eye(3)[axis]
        # Same world displacements s u for both, so the ratio is exact up to round-off.
        k_world[:, axis] = -(force_after(one, s * u * e) - force_after(one, -s * u * e)) / (2 * s * u)
        k_dev[:, axis] = -(force_after(scaled, u * e) - force_after(scaled, -u * e)) / (2 * u)
    assert np.abs(k_world).max() > 1.0  # the strings do resist [N/m]
    np.testing.assert_array_equal(k_dev, scaled.stiffness_to_device(k_world))
    np.testing.assert_array_equal(k_dev, s * k_world)


def test_servo_loop_gives_each_device_its_own_row_and_limits():
    """One servo loop, two devices with different limits: each gets its own force row through its
    own safety filter (clamped to its own peak), a non-finite row zeroes both, and both end at 0."""
    weak = HapticDeviceSpec("weak", max_force=1.0, max_continuous_force=1.0, workspace_min=(-1, -1, -1),
                            workspace_max=(1, 1, 1))
    strong = HapticDeviceSpec("strong", max_force=3.3, max_continuous_force=3.3, workspace_min=(-1, -1, -1),
                              workspace_max=(1, 1, 1))
    a, b = HapticDeviceSimulated(spec=weak), HapticDeviceSimulated(spec=strong)
    calls = {"n": 0}

    def step(samples, t):
        assert len(samples) == 2 and all(isinstance(x, HapticSample) for x in samples)
        calls["n"] += 1
        if calls["n"] == 130:
            loop.request_stop()
        if 100 <= calls["n"] < 110:
            return [[np.nan, 0.0, 0.0], [0.0, -0.5, 0.0]]
        return [[5.0, 0.0, 0.0], [0.0, -0.5, 0.0]]

    loop = ServoLoop([a, b], step, safety=NO_RAMP)
    stats = loop.run(duration=10.0)  # stopped by the step after 130 answers
    assert stats.stop_reason == "stopped"
    assert not a.is_open and not b.is_open
    fa, fb = a.force_log()[1], b.force_log()[1]
    assert np.linalg.norm(fa, axis=1).max() <= 1.0 + 1e-12 and np.linalg.norm(fb, axis=1).max() <= 3.3 + 1e-12
    assert np.any(np.all(np.isclose(fa, [1.0, 0.0, 0.0], atol=1e-12), axis=1))  # 5 N clamped to weak's 1 N
    assert np.any(np.all(np.isclose(fb, [0.0, -0.5, 0.0], atol=1e-12), axis=1))  # within strong's limit
    assert not np.any(np.all(np.isclose(fb, [1.0, 0.0, 0.0]), axis=1))  # never the other device's row
    assert len(fa) == len(fb)  # the same ticks, and each device's own motors-off zero
    np.testing.assert_array_equal(fa[-1], 0.0)
    np.testing.assert_array_equal(fb[-1], 0.0)
    assert stats.watchdog_trips >= 1 and stats.nonfinite_forces >= 1
    zero_both = np.all(fa == 0.0, axis=1) & np.all(fb == 0.0, axis=1)
    assert zero_both[:-1].sum() >= 1  # a NaN for device a zeroed b as well (besides the final zero)
    assert "devices: 2" in stats.summary()
    with pytest.raises(ValueError, match="same device object was given twice"):
        ServoLoop([a, a], step)


def _spec(name, peak, continuous=None):
    return HapticDeviceSpec(name, max_force=peak, max_continuous_force=peak if continuous is None else continuous,
                            workspace_min=(-1, -1, -1), workspace_max=(1, 1, 1))


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
@given(peaks=st.tuples(st.floats(1e-3, 40.0), st.floats(1e-3, 40.0)),
       rows=st.lists(st.tuples(*[finite_or_not] * 6), min_size=1, max_size=30),
       ramp=st.sampled_from([0.0, 0.02]))
@settings(max_examples=10, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
def test_no_force_written_to_either_device_exceeds_its_own_limit(peaks, rows, ramp):
    """Property: whatever the physics answers (any floats, NaN and inf included), each device only
    ever gets a finite force within its own peak, and both end at zero."""
    a, b = HapticDeviceSimulated(spec=_spec("a", peaks[0])), HapticDeviceSimulated(spec=_spec("b", peaks[1]))
    calls = [0]
    answers = max(len(rows), 20)  # a number of answers, not of seconds: a busy machine cannot cut it short

    def step(samples, t):
        calls[0] += 1
        if calls[0] == answers:
            loop.request_stop()
        return np.array(rows[calls[0] % len(rows)]).reshape(2, 3)

    loop = ServoLoop([a, b], step, safety=SafetyConfig(ramp_time=ramp, continuous_time_constant=0.0,
                                                       rearm_ramp_time=0.01))
    with np.errstate(all="ignore"):
        stats = loop.run(duration=30.0)
    assert stats.stop_reason == "stopped" and stats.tick_count >= answers
    for device, peak in zip((a, b), peaks):
        written = device.force_log()[1]
        assert len(written) >= stats.tick_count and np.all(np.isfinite(written))
        assert np.all(np.linalg.norm(written, axis=1) <= peak * (1 + 1e-12))
        np.testing.assert_array_equal(written[-1], np.zeros(3))


class _Wrapping(AbstractHapticDevice):
    """Passes every call on to the wrapped device ``inner``; subclasses change one of them."""

    def __init__(self, device: AbstractHapticDevice):
        self.inner = device

    spec = property(lambda self: self.inner.spec)
    is_open = property(lambda self: self.inner.is_open)

    def open(self):
        self.inner.open()

    def close(self):
        self.inner.close()

    def read(self):
        return self.inner.read()

    def write_force(self, force):
        self.inner.write_force(force)


class _FailingWrite(_Wrapping):
    """Wraps a simulated device; ``write_force`` raises ``error`` from the ``after``-th call on."""

    def __init__(self, device: HapticDeviceSimulated, after: int, error: BaseException):
        super().__init__(device)
        self.after, self.error = after, error

    def write_force(self, force):
        self.after -= 1
        if self.after <= 0:
            raise self.error
        self.inner.write_force(force)


@pytest.mark.parametrize("how", ["physics error", "keyboard interrupt", "device error", "device bug"])
def test_both_motors_off_on_every_way_out(how):
    """A physics exception, Ctrl-C in the physics, or either device raising (a HapticDeviceError
    or any other exception): the error comes out of ``run`` and both devices end at zero, closed."""
    a = HapticDeviceSimulated(spec=_spec("a", 2.0))
    inner_b = HapticDeviceSimulated(spec=_spec("b", 2.0))
    errors = {"physics error": ValueError("physics broke"), "keyboard interrupt": KeyboardInterrupt(),
              "device error": HapticDeviceError("b: USB write failed"), "device bug": RuntimeError("b: bug")}
    error = errors[how]
    b = _FailingWrite(inner_b, 50, error) if how.startswith("device") else inner_b
    calls = [0]

    def step(samples, t):
        calls[0] += 1
        if not how.startswith("device") and calls[0] == 50:
            raise error
        return [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]]

    with pytest.raises(type(error)):
        ServoLoop([a, b], step, safety=NO_RAMP).run(duration=5.0)
    for device in (a, inner_b):
        assert not device.is_open and device.close_count == 1
        forces = device.force_log()[1]
        assert len(forces) >= 40 and np.all(forces[-1] == 0.0)
        assert np.abs(forces[:-1]).max() == pytest.approx(0.5)  # it did get its force before


class _UnpluggedAfter(_Wrapping):
    """A simulated device that is unplugged after ``reads`` reads (simulate_disconnect)."""

    def __init__(self, device: HapticDeviceSimulated, reads: int):
        super().__init__(device)
        self.reads = reads

    def read(self):
        self.reads -= 1
        if self.reads == 0:
            self.inner.simulate_disconnect()
        return self.inner.read()


def test_one_device_unplugged_mid_run_turns_both_motors_off(model):
    """The hand device goes away after 200 reads: run_live stops with an error naming it, the main
    device's last force is zero and both are closed."""
    start = np.array(model.scene.bars[1].trajectory.positions[0])
    main = make_device("simulated", model.scene, "main", trajectory_offset=np.array(
        model.scene.bars[0].trajectory.positions[0]), duration=2.0)
    hand = _UnpluggedAfter(make_device("simulated", model.scene, "hand", trajectory_offset=start, duration=2.0), 200)
    with pytest.raises(DeviceDisconnectedError, match=r"device 1 \(_UnpluggedAfter, bar 'hand'\): .*disconnected"):
        run_live(model, device=[main, hand], bar=BARS, duration=2.0, physics="thread")
    assert not main.is_open and not hand.is_open
    forces = main.force_log()[1]
    assert len(forces) >= 150 and np.all(forces[-1] == 0.0)
    assert main.close_count == 1


def test_two_devices_refuse_child_process_physics_and_mismatched_options(model):
    for mode in ("shm", "process"):
        with pytest.raises(ValueError, match=f"--physics {mode}: 2 devices run with the physics in the servo loop's "
                                             "worker thread only"):
            run_live(model, device=["simulated", "simulated"], bar=BARS, duration=0.1, physics=mode)
    with pytest.raises(ValueError, match=r"got 2 device\(s\) .* and 1 bar\(s\)"):
        run_live(model, device=["simulated", "simulated"], bar=["main"], duration=0.1)
    with pytest.raises(ValueError, match="expected a different bar for each device"):
        run_live(model, device=["simulated", "simulated"], bar=["main", "main"], duration=0.1)
    with pytest.raises(ValueError, match="--workspace-scale: got 3 values"):
        run_live(model, device=["simulated", "simulated"], bar=BARS, workspace_scale=[1, 2, 3], duration=0.1)


def test_two_device_session_records_both_and_replays(tmp_path, capsys, model):
    """`live --device sim --bar main --device sim --bar hand --record` records both devices (samples
    and forces sent, each within its limit); `replay` re-simulates it (every bar pose exact, the
    puppet exactly, as for one device, tests/live/test_live.py), and two `--device replay` play it back."""
    from dmarionette.cli import main
    from dmarionette.io.session import read_session, session_bar_trajectories

    session = tmp_path / "two.mcap"
    assert main(["live", "--device", "sim", "--bar", "main", "--device", "sim", "--bar", "hand",
                 "--workspace-scale", "1", "--workspace-scale", "2", "--duration", "1.0", "--record", str(session),
                 "--fast-compile"]) == 0
    stats_line, summary = capsys.readouterr().out.split("\n", 1)
    summary = json.loads(summary)
    trips = int(re.search(r"watchdog trips (\d+)", stats_line).group(1))
    assert summary["device"] == ["simulated", "simulated"] and summary["bar"] == BARS
    assert summary["physics_mode"] == "thread" and summary["workspace_scale"] == [1.0, 2.0]
    recorded = read_session(session)
    live_meta = recorded.extra_metadata["live"]["devices"]
    assert [d["bar"] for d in live_meta] == BARS and [d["workspace_scale"] for d in live_meta] == [1.0, 2.0]
    for bar in BARS:
        for kind in ("sample", "force"):
            assert len(recorded.channels[f"/device/{bar}/{kind}"]["t"]) > 100, (bar, kind)
        forces = np.linalg.norm(recorded.channels[f"/device/{bar}/force"]["force"], axis=1)
        assert forces.max() <= 3.3 + 1e-12
        # A bar's forces may be zero throughout only when the watchdog held them there (a loaded machine
        # stalls the physics past the watchdog; each trip ramps the forces in again over 0.2 s).
        assert forces.max() > 0.0 or trips > 0, (bar, stats_line)
    # Each bar pose driven by a device is one of that device's samples mapped to the world by the
    # recorded S W, which is the mapping run_live uses (origin at the bar's start).
    for bar, scale, meta in zip(BARS, (1.0, 2.0), live_meta):
        mapping = DeviceMapping(np.array(meta["S"]), np.array(meta["W"]))
        np.testing.assert_array_equal(mapping.matrix, bar_mapping(model, bar, scale).matrix)
        world = mapping.position_to_world(recorded.channels[f"/device/{bar}/sample"]["position"])
        channel = recorded.channels[f"/bar/{bar}/pose"]
        pose = channel["position"][channel["t"] > 0]  # at t = 0 the scene's start, before any sample
        gap = np.abs(pose[:, None, :] - world[None, :, :]).max(axis=2).min(axis=1)
        assert len(pose) > 100 and gap.max() < 1e-12, gap.max()

    assert main(["replay", str(session), "--fast-compile"]) == 0
    report = json.loads(capsys.readouterr().out)
    # Exactly the recorded puppet, as for one device (tests/live/test_live.py says why).
    assert report["frames_compared"] >= 3 and report["max_body_gap"] == 0.0 and report["rms_feedback_gap"] == 0.0, report
    trajectories = session_bar_trajectories(recorded)
    for bar in BARS:
        pose = recorded.channels[f"/bar/{bar}/pose"]
        np.testing.assert_array_equal(trajectories[bar].pose(pose["t"])[0], pose["position"])

    assert main(["live", "--device", "replay", "--bar", "main", "--device", "replay", "--bar", "hand",
                 "--workspace-scale", "1", "--workspace-scale", "2", "--session", str(session),
                 "--duration", "0.5", "--fast-compile"]) == 0
    summary = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    assert summary["device"] == ["replay", "replay"] and summary["string_steps"] > 0

    assert main(["live", "--device", "sim", "--device", "sim", "--duration", "0.1"]) == 2
    assert "give --bar once per device" in capsys.readouterr().err
    assert main(["live", "--device", "sim", "--bar", "main", "--device", "sim", "--bar", "hand",
                 "--physics", "shm", "--duration", "0.1"]) == 2
    assert "2 devices run with the physics in the servo loop's worker thread only" in capsys.readouterr().err
