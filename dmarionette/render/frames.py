"""A strip of marionette frames side by side (one PNG): a motion at a glance, for the docs.

The puppet, strings and bars are drawn as in :func:`dmarionette.render.marionette.render_marionette_animation`
(the same polylines and colours: strings taut dark, slack orange), seen from one side, every
panel on the same scale and extent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .marionette import bar_polyline, body_polyline, draw_chair, frame_extent
from .pyplot import headless_pyplot

__all__ = ["render_marionette_frames"]


def render_marionette_frames(path: str | Path, trajectory, times, *, title: str = "", axis: int = 2,
                             ground_height: float = 0.0, chair=None, ball_radius: float | None = None,
                             dpi: int = 100) -> Path:
    """Writes the frames nearest ``times`` [s], side by side, as a PNG; returns its path.

    Args:
        path: the ``.png`` to write.
        trajectory: a :class:`dmarionette.marionette.rollout.MarionetteTrajectory`.
        times: the times to show [s] (each drawn at the nearest frame).
        title: the heading above the strip.
        axis: the horizontal axis of the view: 0 (x, seen from the front) or 2 (z, from the side).
        ground_height: the ground plane's height [m]; chair: ``(centre, half_extents)`` or None;
        ball_radius: the ball's radius [m] when the scene has one (the last body), or None.
        dpi: pixels per inch (each panel is 2.4 x 4 inches).
    """
    plt = headless_pyplot()

    path = Path(path)
    if path.suffix != ".png":
        raise ValueError(f"frames file {str(path)!r}: expected a .png suffix")
    path.parent.mkdir(parents=True, exist_ok=True)
    frame_time = np.asarray(trajectory.frame_time)
    frames = [int(np.argmin(np.abs(frame_time - t))) for t in times]
    lo, hi = frame_extent(trajectory, chair=chair, ball_radius=ball_radius)
    lo[1] = min(lo[1], ground_height - 0.03)
    fig, axes = plt.subplots(1, len(frames), figsize=(2.4 * len(frames), 4.0), dpi=dpi, sharey=True)
    axes = np.atleast_1d(axes)
    for ax, f in zip(axes, frames):
        ax.set_xlim(lo[axis], hi[axis])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.axhspan(lo[1] - 1.0, ground_height, color="0.85", zorder=0)
        draw_chair(ax, chair, axis)
        step = min(len(trajectory.string_taut) - 1, max(0, f * trajectory.frame_steps - 1))
        for s in range(len(trajectory.string_names)):
            a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
            taut = trajectory.string_taut[step, s] or f == 0
            ax.plot(trajectory.particle_q[f, a:b, axis], trajectory.particle_q[f, a:b, 1], lw=0.9,
                    color="0.15" if taut else "darkorange")
        body = body_polyline(trajectory, f)
        ax.plot(body[:, axis], body[:, 1], color="steelblue", lw=1.0)
        bars = bar_polyline(trajectory, f)
        ax.plot(bars[:, axis], bars[:, 1], color="saddlebrown", lw=4, solid_capstyle="butt")
        if ball_radius is not None:
            centre = trajectory.body_pos[f, -1]
            ax.add_patch(plt.Circle((centre[axis], centre[1]), ball_radius, color="crimson", alpha=0.6))
        ax.set_title(f"t = {frame_time[f]:.2f} s", fontsize=9)
        ax.set_xlabel(f"{'xyz'[axis]} [m] ({'front' if axis == 0 else 'side'})", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("y [m]", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
