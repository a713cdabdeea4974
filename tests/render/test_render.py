"""The marionette animation (issue 17): exact GIF timing, framing, and the MP4 path."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from dmarionette.marionette.rollout import MarionetteTrajectory
from dmarionette.render.marionette import frame_extent, gif_delays_ms, render_marionette_animation


def _trajectory(frames: int = 31, frame_dt: float = 1.0 / 30.0, ball: bool = False) -> MarionetteTrajectory:
    """A small synthetic trajectory: a swaying box and head on two strings from one bar (and a ball)."""
    steps_per_frame = 4
    t = np.arange(frames) * frame_dt
    sway = 0.05 * np.sin(2 * np.pi * t)
    bodies = 3 if ball else 2
    body_pos = np.zeros((frames, bodies, 3))
    body_pos[:, 0] = np.stack([sway, 0.5 + 0 * t, 0 * t], 1)
    body_pos[:, 1] = np.stack([sway, 0.65 + 0 * t, 0 * t], 1)
    if ball:
        body_pos[:, 2] = np.stack([0 * t, 0.05 + 0 * t, 0.1 + 2.0 * t], 1)  # rolls 2 m away
    body_rot = np.tile([0.0, 0.0, 0.0, 1.0], (frames, bodies, 1))
    bar_pos = np.stack([sway, 1.2 + 0 * t, 0 * t], 1)[:, None]
    particles = np.linspace(0, 1, 5)[:, None]
    string = [bar_pos[:, 0][:, None] * (1 - particles) + body_pos[:, k][:, None] * particles for k in (0, 1)]
    steps = (frames - 1) * steps_per_frame + 1
    step_time = np.arange(steps) * frame_dt / steps_per_frame
    tension = np.stack([3.0 + np.sin(step_time), 1.0 + 0 * step_time], 1)
    shapes = [("box", (0.1, 0.2, 0.05)), ("sphere", (0.04,))] + ([("sphere", (0.05,))] if ball else [])
    return MarionetteTrajectory(
        frame_time=t, particle_q=np.concatenate(string, axis=1), joint_q=np.zeros((frames, 1)), body_pos=body_pos,
        body_rot=body_rot, bar_pos=bar_pos, bar_rot=np.tile(np.eye(3), (frames, 1, 1, 1)),
        top_q=np.zeros((frames, 2, 3)), step_time=step_time,
        tie_force=np.stack([0 * tension, tension, 0 * tension], 2), string_taut=np.ones((steps, 2), dtype=bool),
        bar_feedback=np.zeros((steps, 1, 3)), bar_reaction=np.stack([0 * step_time, tension.sum(1), 0 * step_time],
                                                                    1)[:, None],
        string_names=["back", "head"], string_start=np.array([0, 5, 10]), string_rest_length=np.array([0.2, 0.15]),
        body_names=["torso", "head"] + (["ball"] if ball else []), body_shape=shapes, bar_names=["main"],
        string_dt=frame_dt / steps_per_frame, puppet_dt=frame_dt, frame_steps=steps_per_frame, wall_seconds=0.0)


def _gif_durations(path) -> list[int]:
    image, durations = Image.open(path), []
    for k in range(image.n_frames):
        image.seek(k)
        durations.append(image.info["duration"])
    return durations


@pytest.mark.parametrize("fps", [15.0, 30.0, 24.0, 7.0])
def test_gif_delays_add_up_to_the_exact_time(fps):
    delays = gif_delays_ms(90, fps)
    assert all(d % 10 == 0 for d in delays)
    assert np.all(np.abs(np.cumsum(delays) - 1000.0 * np.arange(1, 91) / fps) <= 5.0 + 1e-9)


def test_the_gif_plays_in_simulated_time(tmp_path):
    trajectory = _trajectory(frames=31)  # 1 s at 30 frames/s
    path, count = render_marionette_animation(tmp_path / "a.gif", trajectory, title="test", every=2)
    assert count == 16
    durations = _gif_durations(path)
    assert len(durations) == 16
    assert set(durations) <= {60, 70}  # 15 fps: 66.7 ms in 10 ms units
    assert abs(sum(durations) - 16 * 1000.0 / 15.0) <= 5.0
    image = Image.open(path)
    first = np.asarray(image.convert("RGB"), dtype=float)
    image.seek(8)
    middle = np.asarray(image.convert("RGB"), dtype=float)
    assert first.std() > 10.0 and np.abs(first - middle).mean() > 0.01  # drawn, and it moves


def test_the_views_frame_the_puppet_bars_and_ball():
    lo, hi = frame_extent(_trajectory(), margin=0.0)
    assert lo[1] == pytest.approx(0.5 - 0.5 * np.linalg.norm([0.1, 0.2, 0.05])) and hi[1] == pytest.approx(1.2)
    assert hi[0] - lo[0] < 0.5 and hi[2] - lo[2] < 0.5  # a small puppet gets a small frame
    lo, hi = frame_extent(_trajectory(ball=True), ball_radius=0.05, margin=0.0, ball_reach=3.0)
    assert hi[2] == pytest.approx(0.1 + 2.0 + 0.05)  # the ball is in the picture
    puppet_hi = frame_extent(_trajectory(), margin=0.0)[1]
    lo, hi = frame_extent(_trajectory(ball=True), ball_radius=0.05, margin=0.0, ball_reach=0.5)
    assert hi[2] == pytest.approx(puppet_hi[2] + 0.5 + 0.05)  # kicked away: it leaves the picture
    lo, hi = frame_extent(_trajectory(), chair=((0.0, 0.2, -1.0), (0.2, 0.2, 0.2)), margin=0.1)
    assert lo[2] == pytest.approx(-1.3)


def test_a_ball_scene_renders(tmp_path):
    path, count = render_marionette_animation(tmp_path / "b.gif", _trajectory(ball=True), ball_radius=0.05,
                                              every=3)
    assert count == 11 and Image.open(path).n_frames == 11


def test_an_mp4_has_every_frame(tmp_path):
    import imageio.v2 as imageio

    path, count = render_marionette_animation(tmp_path / "a.mp4", _trajectory(frames=21), every=1)
    reader = imageio.get_reader(path)
    assert count == 21 and sum(1 for _ in reader) == 21
    assert reader.get_meta_data()["fps"] == pytest.approx(30.0, rel=0.01)


def test_a_wrong_suffix_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"expected a \.gif or \.mp4"):
        render_marionette_animation(tmp_path / "a.avi", _trajectory())
