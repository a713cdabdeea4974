"""An animation of a marionette trajectory (GIF or MP4), rendered headless with matplotlib.

Front (x-y) and side (z-y) orthographic views: the puppet's boxes and head sphere, the
strings (taut dark, slack orange), the bars, the ground, the chair and the ball; a
third panel plots the feedback force on each bar up to the current time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dmarionette.marionette.rollout import MarionetteTrajectory
from dmarionette.rotations import quat_to_matrix

__all__ = ["render_marionette_animation"]

_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_BOX_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def _segments(trajectory: MarionetteTrajectory, f: int) -> list[np.ndarray]:
    """World-space line segments of the puppet's bodies at frame ``f``: box edges, sphere rings."""
    segments = []
    for b, (shape, size) in enumerate(trajectory.body_shape):
        rotation = quat_to_matrix(trajectory.body_rot[f, b])
        centre = trajectory.body_pos[f, b]
        if shape == "box":
            corners = centre + (_BOX_CORNERS * 0.5 * np.asarray(size)) @ rotation.T
            segments += [corners[[i, j]] for i, j in _BOX_EDGES]
        else:
            angle = np.linspace(0, 2 * np.pi, 25)
            r = size[0]
            for ring in (np.stack([np.cos(angle), np.sin(angle), 0 * angle], 1),
                         np.stack([0 * angle, np.sin(angle), np.cos(angle)], 1)):
                segments.append(centre + (r * ring) @ rotation.T)
    return segments


def render_marionette_animation(path: str | Path, trajectory: MarionetteTrajectory, *, title: str = "",
                                ground_height: float = 0.0, chair=None, ball_radius: float | None = None,
                                fps: float | None = None, every: int = 1) -> tuple[Path, int]:
    """Writes the animation (``.gif`` or ``.mp4`` by suffix); returns ``(path, frame count)``."""
    try:
        import imageio.v2 as imageio
        import matplotlib
    except ImportError:
        raise RuntimeError("animations need matplotlib and imageio: pip install 'dmarionette[viz]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = range(0, len(trajectory.frame_time), every)
    fps = fps or 1.0 / (trajectory.frame_time[1] - trajectory.frame_time[0]) / every
    everything = np.concatenate([trajectory.particle_q.reshape(-1, 3), trajectory.body_pos.reshape(-1, 3)])
    lo, hi = everything.min(axis=0) - 0.1, everything.max(axis=0) + 0.1
    lo[1] = min(lo[1], ground_height - 0.05)
    span = float(np.max(hi - lo))
    feedback_time = trajectory.step_time
    feedback = np.linalg.norm(trajectory.bar_feedback, axis=2)
    fig, axes = plt.subplots(1, 3, figsize=(13, 5), gridspec_kw={"width_ratios": [1, 1, 1.1]})
    # Artists are made once and updated per frame (much faster than redrawing the axes).
    views = []
    for ax, (axis, name) in zip(axes[:2], ((0, "x [m] (front)"), (2, "z [m] (side)"))):
        centre = 0.5 * (lo[axis] + hi[axis])
        ax.set_xlim(centre - span / 2, centre + span / 2)
        ax.set_ylim(lo[1], lo[1] + span)
        ax.set_aspect("equal")
        ax.axhspan(lo[1], ground_height, color="0.85")
        ax.set_xlabel(name)
        if chair is not None:
            c, h = chair
            ax.add_patch(plt.Rectangle((c[axis] - h[axis], c[1] - h[1]), 2 * h[axis], 2 * h[1], color="tan", alpha=0.7))
        strings = [ax.plot([], [], lw=0.9)[0] for _ in trajectory.string_names]
        bodies = [ax.plot([], [], color="steelblue", lw=1.0)[0] for _ in _segments(trajectory, 0)]
        bars = [ax.plot([], [], color="saddlebrown", lw=4)[0] for _ in trajectory.bar_names]
        ball = None
        if ball_radius is not None:
            ball = plt.Circle((0, 0), ball_radius, color="crimson", alpha=0.6)
            ax.add_patch(ball)
        views.append((axis, strings, bodies, bars, ball))
    ax = axes[2]
    curves = [ax.plot([], [], label=f"{name} bar")[0] for name in trajectory.bar_names]
    ax.set_xlim(0, feedback_time[-1])
    ax.set_ylim(0, max(1e-6, 1.05 * float(feedback.max())))
    ax.set_xlabel("time [s]")
    ax.set_ylabel("|feedback| eq. 4 [N]")
    if trajectory.bar_names:
        ax.legend(loc="upper right", fontsize=8)
    heading = fig.suptitle(title)
    fig.tight_layout()
    writer_options = {"fps": fps}
    if path.suffix == ".gif":
        writer_options = {"duration": 1000.0 / fps, "loop": 0}
    count = 0
    with imageio.get_writer(path, **writer_options) as writer:
        for f in frames:
            step = min(len(trajectory.string_taut) - 1, max(0, f * trajectory.frame_steps - 1))
            segments = _segments(trajectory, f)
            for axis, strings, bodies, bars, ball in views:
                for s, line in enumerate(strings):
                    a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
                    line.set_data(trajectory.particle_q[f, a:b, axis], trajectory.particle_q[f, a:b, 1])
                    line.set_color("0.15" if (trajectory.string_taut[step, s] or f == 0) else "darkorange")
                for line, segment in zip(bodies, segments):
                    line.set_data(segment[:, axis], segment[:, 1])
                for b, line in enumerate(bars):
                    ends = trajectory.bar_pos[f, b] + np.array([[-0.12, 0, 0], [0.12, 0, 0]]) @ trajectory.bar_rot[f, b].T
                    line.set_data(ends[:, axis], ends[:, 1])
                if ball is not None:
                    ball.center = (trajectory.body_pos[f, -1, axis], trajectory.body_pos[f, -1, 1])
            upto = int(np.searchsorted(feedback_time, trajectory.frame_time[f], side="right"))
            for b, curve in enumerate(curves):
                curve.set_data(feedback_time[:upto], feedback[:upto, b])
            heading.set_text(f"{title}   t = {trajectory.frame_time[f]:.2f} s")
            fig.canvas.draw()
            writer.append_data(np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy())
            count += 1
    plt.close(fig)
    return path, count
