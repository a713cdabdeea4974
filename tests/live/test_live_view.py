"""The live view: snapshots published by the physics, the browser view (viser) fed by them, a
drag in the browser moving the simulated device and then the bar, colours, headless mode, and
a clean shutdown. The browser side is a real websocket client (tests/support/live_view_client.py)
speaking viser's protocol on 127.0.0.1 with an ephemeral port."""

import json
import socket
import threading
import time

import numpy as np
import pytest
import warp as wp

from dmarionette.hw import HapticDeviceSimulated, HapticSample
from dmarionette.live.run import LiveMarionette, make_physics_step, run_live
from dmarionette.live.setup import make_device
from dmarionette.live.view import (
    SLACK_RGB,
    TAUT_RGB,
    LiveSnapshot,
    LiveViewGeometry,
    LiveViewPublisher,
    SnapshotBuffer,
    string_colors,
)

viser = pytest.importorskip("viser")
from dmarionette.live.view_viser import LiveViewServer  # noqa: E402
from tests.support.live_view_client import ViewClient  # noqa: E402
from viser import _messages as vm  # noqa: E402

wp.config.log_level = wp.LOG_WARNING


def _stop_session(out: dict, thread) -> tuple:
    """Stops a session run in ``thread`` (its ``on_start`` put ``stop`` in ``out``); its result."""
    out["stop"]()
    thread.join(timeout=120)
    assert not thread.is_alive()
    if "error" in out:
        raise out["error"]
    return out["result"]


def _wait(condition, timeout: float, what: str) -> None:
    end = time.perf_counter() + timeout
    while not condition():
        if time.perf_counter() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)


def test_string_colours_are_those_of_the_offline_animation():
    """Taut dark, slack orange: the same colours render_marionette draws ("0.15", "darkorange")."""
    from matplotlib.colors import to_rgb

    np.testing.assert_array_equal(np.round(255 * np.array(to_rgb("0.15"))).astype(int), TAUT_RGB)
    np.testing.assert_array_equal(np.round(255 * np.array(to_rgb("darkorange"))).astype(int), SLACK_RGB)
    np.testing.assert_array_equal(string_colors(np.array([1, 0, 3, 0])),
                                  [TAUT_RGB, SLACK_RGB, TAUT_RGB, SLACK_RGB])
    np.testing.assert_array_equal(string_colors(np.array([True, False])), [TAUT_RGB, SLACK_RGB])


def test_snapshots_hold_the_state_of_the_tick_they_were_taken_after(model):
    """Published after every tick (rate far above the tick rate), each snapshot's string tops
    sit exactly on their bar's attach points at that tick's bar pose, so the particles are those
    of the latest string step (across the solver's spare states and the puppet-step boundary),
    and the taut flags are that tick's."""
    live = LiveMarionette(model)
    buffer = SnapshotBuffer()
    publisher = LiveViewPublisher(buffer, rate_hz=1e9)
    geometry = LiveViewGeometry.from_model(model, "main")
    steps = 2 * model.substeps + 3
    times = model.string_dt * np.arange(1, steps + 1)
    position, _, rotation = model.scene.bars[0].trajectory.pose(times)
    taut_seen = []
    step = make_physics_step(live, "main", steps * model.string_dt, view=publisher,
                             on_tick=lambda tick, poses: taut_seen.append(tick.string_taut))
    names = list(geometry.string_names)
    for k in range(steps):
        step(HapticSample.make(time=times[k], position=position[k], orientation=rotation[k]), times[k])
        snap = buffer.latest()
        assert snap.sequence == k + 1 == buffer.published
        np.testing.assert_allclose(snap.bar_pos[0], position[k], rtol=0, atol=0)
        np.testing.assert_allclose(snap.bar_rot[0], rotation[k], rtol=0, atol=1e-15)
        for b, bar in enumerate(model.scene.bars):
            for s_name, local in bar.attach.items():
                top = snap.particle_q[geometry.string_start[names.index(s_name)]]
                np.testing.assert_allclose(top, snap.bar_pos[b] + snap.bar_rot[b] @ np.array(local), rtol=0,
                                           atol=1e-12)
        np.testing.assert_array_equal(snap.string_taut, taut_seen[k])
        if (k + 1) % model.substeps == 0:  # at a puppet step boundary: the marionette's own state
            np.testing.assert_array_equal(snap.particle_q, live.state.strings.particle_q.numpy())
    # Bodies: the current state's kinematics, converted from Warp's (x, y, z, w).
    np.testing.assert_array_equal(snap.body_pos, live.state.puppet.body_pos.numpy()[0])
    np.testing.assert_array_equal(snap.body_wxyz[:, 0], live.state.puppet.body_rot.numpy()[0][:, 3])
    np.testing.assert_allclose(np.linalg.norm(snap.body_wxyz, axis=1), 1.0, atol=1e-12)


def _synthetic_snapshot(geometry: LiveViewGeometry, taut, sequence: int = 1) -> LiveSnapshot:
    rng = np.random.default_rng(sequence)
    n_p, n_b, n_bar = int(geometry.string_start[-1]), len(geometry.body_names), len(geometry.bar_names)
    q = rng.normal(size=(n_b, 4))
    return LiveSnapshot(sequence=sequence, t=0.1 * sequence, wall_time=time.perf_counter(),
                        particle_q=rng.normal(size=(n_p, 3)), body_pos=rng.normal(size=(n_b, 3)),
                        body_wxyz=q / np.linalg.norm(q, axis=1, keepdims=True),
                        bar_pos=rng.normal(size=(n_bar, 3)), bar_rot=np.tile(np.eye(3), (n_bar, 1, 1)),
                        string_taut=np.array(taut), bar_reaction=rng.normal(size=(n_bar, 3)),
                        force_sent=rng.normal(size=3))


def test_browser_receives_each_snapshot_with_taut_and_slack_colours(model):
    """What a browser receives for a snapshot: string segments, their colours per string
    (taut/slack), box and sphere poses, bars and arrows, equal to the snapshot (float32)."""
    geometry = LiveViewGeometry.from_model(model, "main")
    taut = [1, 0, 1, 0, 0, 1]
    with LiveViewServer(geometry, host="127.0.0.1", port=0) as view:
        client = ViewClient(view.url)
        try:
            _wait(lambda: client.updates("/strings", "points"), 10, "the scene to reach the client")
            snap = _synthetic_snapshot(geometry, taut)
            view.buffer.publish(snap)
            _wait(lambda: view.frames_sent == 1, 10, "the view to send the snapshot")
            _wait(lambda: len(client.updates("/strings", "colors")) >= 2, 10, "the colours")
            segments = geometry.string_segments()
            points = np.asarray(client.updates("/strings", "points")[-1][1]).reshape(-1, 2, 3)
            np.testing.assert_array_equal(points, snap.particle_q[segments].astype(np.float32))
            colors = np.asarray(client.updates("/strings", "colors")[-1][1]).reshape(-1, 2, 3)
            expected = np.array([TAUT_RGB if taut[s] else SLACK_RGB for s in geometry.string_of_segment()])
            np.testing.assert_array_equal(colors[:, 0], expected)
            np.testing.assert_array_equal(colors[:, 1], expected)
            boxes = [i for i, (shape, _) in enumerate(geometry.body_shape) if shape == "box"]
            got = np.asarray(client.updates("/puppet/boxes", "batched_positions")[-1][1]).reshape(-1, 3)
            np.testing.assert_array_equal(got, snap.body_pos[boxes].astype(np.float32))
            got = np.asarray(client.updates("/puppet/boxes", "batched_wxyzs")[-1][1]).reshape(-1, 4)
            np.testing.assert_array_equal(got, snap.body_wxyz[boxes].astype(np.float32))
            arrows = np.asarray(client.updates("/forces", "points")[-1][1]).reshape(-1, 2, 3)
            np.testing.assert_allclose(arrows[0, 1] - arrows[0, 0], view.arrow_scale * snap.bar_reaction[0],
                                       atol=1e-6)
            np.testing.assert_allclose(arrows[-1, 1] - arrows[-1, 0], view.arrow_scale * snap.force_sent,
                                       atol=1e-6)
            bars = np.asarray(client.updates("/bars", "points")[-1][1]).reshape(-1, 2, 3)
            np.testing.assert_allclose(bars[0, 1], snap.bar_pos[0] + geometry.bar_attach[0][0], atol=1e-6)
        finally:
            client.close()


def test_headless_picture_colours_strings_by_taut_flag(model, tmp_path):
    """The headless picture draws taut strings dark and slack ones orange: the same frame with
    every string taut has no slack-coloured pixels and many taut-coloured ones, and the other
    way round."""
    from matplotlib.image import imread

    from dmarionette.live.view import render_live_snapshot

    geometry = LiveViewGeometry.from_model(model, "main")
    live = LiveMarionette(model)
    publisher = LiveViewPublisher(SnapshotBuffer(), rate_hz=1e9)
    step = make_physics_step(live, "main", 0.01, view=publisher)
    bar = model.scene.bars[0].trajectory
    position, _, rotation = bar.pose(np.array([model.string_dt]))
    step(HapticSample.make(time=0.0, position=position[0], orientation=rotation[0]), 0.0)
    snap = publisher.buffer.latest()
    counts = {}
    for name, taut in (("taut", np.ones(6, int)), ("slack", np.zeros(6, int))):
        frame = LiveSnapshot(**{**snap.__dict__, "string_taut": taut})
        image = imread(render_live_snapshot(tmp_path / f"{name}.png", geometry, frame))[:, :, :3] * 255
        counts[name] = {c: int(np.all(np.abs(image - np.array(rgb)) < 20, axis=2).sum())
                        for c, rgb in (("taut", TAUT_RGB), ("slack", SLACK_RGB))}
    assert counts["taut"]["slack"] == 0 and counts["slack"]["slack"] > 500, counts
    assert counts["taut"]["taut"] > counts["slack"]["taut"] + 500, counts


def test_live_session_in_the_browser_view_with_a_drag_and_a_clean_shutdown(model):
    """The servo loop with the simulated device and the browser view, until the test stops it:

    - the view sends snapshots (counted: several; the rate it keeps is measured in
      benchmarks/bench_live_view.py, not asserted), and what the browser last received equals
      the last snapshot published;
    - a drag of the gizmo, sent by the websocket client as a browser sends it, moves the
      simulated device (its reads reach the dragged pose, device frame = world - bar start),
      then the bar and its string tops follow;
    - at the end the motors are off (last force written is zero, the device closed once), and
      closing the view stops its thread and its server (the port refuses connections).
    """
    rate = 40.0
    geometry = LiveViewGeometry.from_model(model, "main")
    start = np.array(model.scene.bars[0].trajectory.positions[0], dtype=np.float64)
    device = make_device("simulated", model.scene, "main", trajectory_offset=start)
    assert isinstance(device, HapticDeviceSimulated)
    view = LiveViewServer(geometry, host="127.0.0.1", port=0, rate_hz=rate)
    client = ViewClient(view.url)
    out = {}

    def session():  # runs until stopped below: a busy machine cannot end it before the drag
        try:
            out["result"] = run_live(model, device=device, duration=600.0, view=view,
                                     on_start=lambda info: out.setdefault("stop", info["stop"]))
        except BaseException as error:  # re-raised below
            out["error"] = error

    thread = threading.Thread(target=session)
    try:
        _wait(lambda: client.updates("/strings", "points"), 10, "the scene to reach the client")
        thread.start()
        _wait(lambda: view.frames_sent >= 5, 120, "the first snapshots")
        gizmo = "/drag/main"
        _wait(lambda: client.poses(gizmo, "position") and client.poses(gizmo, "wxyz"), 10, "the gizmo pose")
        assert not device.dragged
        target, q0 = client.drag(gizmo, [0.05, -0.03, 0.02], steps=5, pause=0.02)
        # The device follows the drag (first-order lag of 30 ms, position and orientation alike:
        # each converges geometrically from its own start, so each is waited for to its own tolerance)...
        _wait(lambda: device.last_read is not None and
              np.linalg.norm(device.last_read.position - (target - start)) < 1e-6 and
              np.max(np.abs(device.last_read.orientation - q0)) < 1e-9, 5, "the device to reach the drag")
        assert device.dragged
        # ... and the bar follows the device.
        _wait(lambda: np.linalg.norm(view.buffer.latest().bar_pos[0] - target) < 1e-6, 10, "the bar to follow")
        stats, summary = _stop_session(out, thread)
        last = view.buffer.latest()
        assert last.dragged
        names = list(geometry.string_names)
        for s_name, local in model.scene.bars[0].attach.items():
            np.testing.assert_allclose(last.particle_q[geometry.string_start[names.index(s_name)]],
                                       last.bar_pos[0] + last.bar_rot[0] @ np.array(local), atol=1e-12)
        # Update counts, not rates (the loop may fall behind on a loaded machine; never a timing assert).
        minimum = 5
        assert summary["view_snapshots"] == view.buffer.published >= minimum
        _wait(lambda: view.last_sent is last, 10, "the view to send the last snapshot")
        assert view.frames_sent >= minimum
        segments = geometry.string_segments()
        expected = last.particle_q[segments].astype(np.float32)
        _wait(lambda: np.array_equal(np.asarray(client.updates("/strings", "points")[-1][1]).reshape(-1, 2, 3),
                                     expected), 10, "the browser to show the last snapshot")
        # viser sends a slow client only the newest value of a property: received <= sent.
        assert len(client.updates("/strings", "points")) >= minimum // 2
        boxes = [i for i, (shape, _) in enumerate(geometry.body_shape) if shape == "box"]
        got = np.asarray(client.updates("/puppet/boxes", "batched_positions")[-1][1]).reshape(-1, 3)
        np.testing.assert_array_equal(got, last.body_pos[boxes].astype(np.float32))
        arrival = [t for t, _ in client.updates("/strings", "points")[1:]]
        print(f"view: {view.frames_sent} frames sent, {len(arrival)} received, "
              f"{(len(arrival) - 1) / (arrival[-1] - arrival[0]):.1f} Hz at the client; {stats.summary()}")
    finally:
        if "stop" in out:
            out["stop"]()
        view.close()
        thread.join(timeout=120)
    # Clean shutdown: motors off, server stopped.
    times, forces = device.force_log()
    np.testing.assert_array_equal(forces[-1], np.zeros(3))
    # The arrow's force is one the device was sent (the mapping's rotation is the identity here).
    assert any(np.array_equal(last.force_sent, f) for f in forces[:-1])
    assert device.close_count == 1 and not device.is_open
    assert stats.stop_reason == "stopped"
    assert not view.is_running
    _wait(lambda: client.closed.is_set(), 10, "the client to see the server close")
    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", view.port)) != 0
    client.close()


def test_cli_browser_view_and_headless_snapshot(tmp_path, capsys, monkeypatch):
    """`live --view browser --view-port 0` serves on loopback and says where; `--snapshot` writes a
    picture of the last frame without a browser; with a view `--physics auto` is `thread`, and
    `--own-process` or `--physics shm|process` are refused before the model is built."""
    from matplotlib.image import imread

    from dmarionette.cli import main

    assert main(["live", "--duration", "0.5", "--fast-compile", "--view", "browser", "--view-port", "0"]) == 0
    captured = capsys.readouterr()
    assert "live view: http://127.0.0.1:" in captured.err
    summary = json.loads(captured.out[captured.out.index("{"):])
    assert summary["view_snapshots"] >= 2  # a count, not a rate (benchmarks/bench_live_view.py measures that)

    picture = tmp_path / "last.png"
    assert main(["live", "--duration", "0.3", "--fast-compile", "--snapshot", str(picture)]) == 0
    summary = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    assert summary["snapshot"] == str(picture) and summary["view_snapshots"] >= 1
    assert summary["physics_mode"] == "thread"  # auto, with a view
    image = imread(picture)[:, :, :3]
    assert image.shape[0] > 300 and image.shape[1] > 600

    import dmarionette.marionette.solver

    def no_model(*_args, **_kwargs):
        raise AssertionError("the model was built before the physics mode was checked")

    monkeypatch.setattr(dmarionette.marionette.solver, "MarionetteModel", no_model)
    assert main(["live", "--duration", "0.3", "--view", "browser", "--own-process"]) == 2
    assert "drop --own-process" in capsys.readouterr().err
    for mode in ("shm", "process"):
        assert main(["live", "--duration", "0.3", "--snapshot", str(picture), "--physics", mode]) == 2
        err = capsys.readouterr().err
        assert f"--physics {mode}: a live view" in err and "needs the physics in this process" in err
    monkeypatch.undo()
    assert main(["live", "--duration", "0.3", "--snapshot", str(tmp_path / "x.jpg")]) == 2
    assert "expected a .png file name" in capsys.readouterr().err


def test_dragged_simulated_device_follows_with_a_first_order_lag():
    """From the first drag the device leaves its trajectory, starting where it was last read (no
    jump), and approaches the dragged pose as ``e(t) = e(0) exp(-t / drag_lag)`` (exact for any
    read times, since each read multiplies the error by ``exp(-dt / drag_lag)``); orientation too."""
    clock = {"t": 0.0}
    lag = 0.03
    device = HapticDeviceSimulated(trajectory=lambda t: np.array([0.1 * t, 0.0, 0.0]), clock=lambda: clock["t"],
                                   drag_lag=lag)
    device.open()
    clock["t"] = 0.5
    grabbed = device.read().position
    np.testing.assert_allclose(grabbed, [0.05, 0.0, 0.0])
    target = np.array([0.02, -0.01, 0.03])
    turn = np.array([np.cos(0.3), 0.0, np.sin(0.3), 0.0])  # 0.6 rad about y
    device.drag_to(target, turn)
    assert device.dragged
    np.testing.assert_array_equal(device.read().position, grabbed)  # no jump when grabbed
    reads = np.cumsum(np.random.default_rng(0).uniform(0.0005, 0.003, size=60))
    for dt_total in reads:
        clock["t"] = 0.5 + dt_total
        sample = device.read()
    expected = target + (grabbed - target) * np.exp(-reads[-1] / lag)
    np.testing.assert_allclose(sample.position, expected, rtol=0, atol=1e-15)
    assert abs(np.linalg.norm(sample.position - target) / np.linalg.norm(grabbed - target)
               - np.exp(-reads[-1] / lag)) < 1e-12
    clock["t"] += 1.0
    sample = device.read()
    np.testing.assert_allclose(sample.position, target, atol=1e-12)
    np.testing.assert_allclose(sample.orientation, turn, atol=1e-12)
    assert device.last_read is sample
    with pytest.raises(ValueError, match="finite position"):
        device.drag_to([np.nan, 0.0, 0.0])
    np.testing.assert_allclose(device.read().position, target, atol=1e-12)  # the target is kept
    with pytest.raises(ValueError, match="drag_lag"):
        HapticDeviceSimulated(drag_lag=-1.0)


def test_no_drag_handle_for_a_device_the_view_cannot_move(model):
    """With a replay device the gizmo stays hidden and a drag sent anyway moves nothing."""
    from dmarionette.hw import HapticDeviceReplay

    geometry = LiveViewGeometry.from_model(model, "main")
    times = np.linspace(0.0, 1.0, 11)
    positions = np.stack([0.01 * times, np.zeros_like(times), np.zeros_like(times)], axis=1)
    device = HapticDeviceReplay(times, positions)
    with LiveViewServer(geometry, host="127.0.0.1", port=0) as view:
        client = ViewClient(view.url)
        try:
            _wait(lambda: client.updates("/strings", "points"), 10, "the scene to reach the client")
            stop = {}
            session = threading.Thread(target=run_live, args=(model,), kwargs={
                "device": device, "duration": 600.0, "view": view,
                "on_start": lambda info: stop.setdefault("stop", info["stop"])})  # stopped below
            session.start()
            _wait(lambda: view.frames_sent >= 2, 120, "the first snapshots")
            assert not view.drag_handles_visible[0]
            client.send(vm.TransformControlsUpdateMessage(name="/drag/main", wxyz=(1.0, 0.0, 0.0, 0.0),
                                                          position=(0.3, 0.3, 0.3)))
            seen = view.frames_sent
            _wait(lambda: view.frames_sent >= seen + 2, 120, "snapshots after the drag")
            stop["stop"]()
            session.join(timeout=120)
            last = view.buffer.latest()
            assert not last.dragged
            assert np.linalg.norm(last.bar_pos[0] - np.array([0.3, 0.3, 0.3])) > 0.5
        finally:
            client.close()
    assert not device.is_open


def test_two_devices_each_get_their_own_drag_handle_and_force_arrow(model):
    from dmarionette.rotations import matrix_to_quat, to_wxyz

    """Two simulated devices, one per bar (the hand's with workspace scale 2): each bar has its own
    gizmo (``/drag/main``, ``/drag/hand``); dragging one moves that device only, through its own
    mapping (device position = (target - bar start) / S), and its bar follows; the snapshots and
    the browser's arrows carry each device's own force sent, on its own bar.

    The session runs until the test stops it (``on_start``'s ``stop``), so a busy machine only
    makes it slower, never too short for the drags."""
    bars, scales = ["main", "hand"], [1.0, 2.0]
    idx = [model.bar_names.index(b) for b in bars]
    geometry = LiveViewGeometry.from_model(model, bars)
    assert geometry.device_bars == tuple(idx) and geometry.driven_bar == idx[0]
    starts = [np.array(model.scene.bars[i].trajectory.positions[0], dtype=np.float64) for i in idx]
    devices = [make_device("simulated", model.scene, b, trajectory_offset=p, workspace_scale=s)
               for b, p, s in zip(bars, starts, scales)]
    view = LiveViewServer(geometry, host="127.0.0.1", port=0, rate_hz=40.0)
    client = ViewClient(view.url)
    out, started = {}, threading.Event()

    def on_start(info):
        out["stop"] = info["stop"]
        started.set()

    def session():
        try:
            out["result"] = run_live(model, device=devices, bar=bars, workspace_scale=scales, duration=600.0,
                                     view=view, on_start=on_start)
        except BaseException as error:  # re-raised below
            out["error"] = error
            started.set()

    thread = threading.Thread(target=session)
    try:
        _wait(lambda: client.updates("/strings", "points"), 10, "the scene to reach the client")
        thread.start()
        assert started.wait(120) and "error" not in out, out.get("error")
        _wait(lambda: view.frames_sent >= 2, 60, "the first snapshots")
        assert all(view.drag_handles_visible)
        targets = {}
        for k in (1, 0):  # the hand first: the main device must not move with it
            gizmo = f"/drag/{bars[k]}"
            _wait(lambda: client.poses(gizmo, "position"), 10, f"{gizmo}'s position")
            p0 = np.array(client.poses(gizmo, "position")[-1][1])
            # (viser sends an orientation only when it changes: the hand's stays the identity)
            q0 = tuple(float(x) for x in to_wxyz(matrix_to_quat(view.last_sent.bar_rot[idx[k]])))
            # On its own bar (which may have moved on a little since; the bars are 0.16 m apart).
            assert np.linalg.norm(p0 - view.last_sent.bar_pos[idx[k]]) < 0.01
            targets[k] = p0 + np.array([0.04, -0.02, 0.03]) * (k + 1)
            client.send(vm.TransformControlsDragStartMessage(name=gizmo))
            client.send(vm.TransformControlsUpdateMessage(name=gizmo, wxyz=q0, position=tuple(map(float, targets[k]))))
            client.send(vm.TransformControlsDragEndMessage(name=gizmo))
            expected = (targets[k] - starts[k]) / scales[k]
            _wait(lambda: devices[k].last_read is not None and
                  np.linalg.norm(devices[k].last_read.position - expected) < 1e-6, 30, f"device {k} to follow")
            if k == 1:
                assert devices[1].dragged and not devices[0].dragged
            _wait(lambda: np.linalg.norm(view.buffer.latest().bar_pos[idx[k]] - targets[k]) < 1e-6, 30,
                  f"bar {bars[k]} to follow")
        assert devices[0].dragged
        stats, summary = _stop_session(out, thread)
        assert stats.stop_reason == "stopped" and summary["bar"] == bars
        last = view.buffer.latest()
        assert last.dragged and last.forces_sent().shape == (2, 3)
        for k in (0, 1):  # each row is a force that device was sent (the mappings do not rotate)
            np.testing.assert_allclose(last.bar_pos[idx[k]], targets[k], atol=1e-6)
            sent = devices[k].force_log()[1]
            assert any(np.array_equal(last.forces_sent()[k], f) for f in sent), k
        if np.any(last.forces_sent()):
            assert not np.array_equal(last.forces_sent()[0], last.forces_sent()[1])
        else:  # zero to both: only the watchdog may do that (a loaded machine stalled the physics)
            assert stats.watchdog_trips > 0
        # Over the session each device got its own forces, not a copy of the other's.
        logs = [d.force_log()[1] for d in devices]
        n = min(len(x) for x in logs)
        assert any(np.any(logs[0][i]) and not np.array_equal(logs[0][i], logs[1][i]) for i in range(n))
        # The browser's arrows: a reaction per bar, then each device's force sent, on its own bar.
        _wait(lambda: view.last_sent is last, 10, "the view to send the last snapshot")
        n_bar = len(geometry.bar_names)

        def arrows_shown():
            updates = client.updates("/forces", "points")
            if not updates:
                return False
            arrows = np.asarray(updates[-1][1]).reshape(-1, 2, 3)
            return arrows.shape[0] == n_bar + 2 and np.allclose(
                arrows[n_bar:, 1] - arrows[n_bar:, 0], view.arrow_scale * last.forces_sent(), atol=1e-6) \
                and np.allclose(arrows[n_bar:, 0], last.bar_pos[idx], atol=1e-6)

        _wait(arrows_shown, 10, "the browser to show both force-sent arrows")
    finally:
        if "stop" in out:
            out["stop"]()
        view.close()
        thread.join(timeout=120)
        client.close()
    for device in devices:
        assert not device.is_open and device.close_count == 1
        np.testing.assert_array_equal(device.force_log()[1][-1], np.zeros(3))
