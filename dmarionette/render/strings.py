"""A picture of a string trajectory: front and side views over time, and the strings' stretch."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dmarionette.strings.simulate import StringTrajectory
from dmarionette.render.pyplot import headless_pyplot

__all__ = ["render_string_picture"]


def render_string_picture(path: str | Path, trajectory: StringTrajectory, title: str = "", snapshots: int = 8,
                          ground_height: float = 0.0) -> Path:
    """Writes a PNG: front (x-y) and side (z-y) views at ``snapshots`` times, and stretch vs. time."""
    plt = headless_pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = trajectory.particle_q
    frames = np.linspace(0, len(q) - 1, min(snapshots, len(q))).round().astype(int)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2))
    colors = plt.get_cmap("tab10")
    for ax, (axis, label) in zip(axes[:2], ((0, "x [m] (front view)"), (2, "z [m] (side view)"))):
        for k, f in enumerate(frames):
            alpha = 0.25 + 0.75 * (k + 1) / len(frames)
            for s in range(len(trajectory.string_names)):
                a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
                ax.plot(q[f, a:b, axis], q[f, a:b, 1], color=colors(s), alpha=alpha, lw=1.2,
                        label=trajectory.string_names[s] if k == len(frames) - 1 else None)
                ax.plot(q[f, b - 1, axis], q[f, b - 1, 1], "o", color=colors(s), alpha=alpha, ms=4)
        ax.axhline(ground_height, color="0.4", lw=2)
        ax.set_xlabel(label)
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[0].set_title(f"{len(frames)} snapshots, t = 0 … {trajectory.frame_time[-1]:.2f} s (darker is later)")
    ax = axes[2]
    for s, name in enumerate(trajectory.string_names):
        a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
        length = np.linalg.norm(np.diff(q[:, a:b], axis=1), axis=2).sum(axis=1)
        rest = trajectory.string_rest_length[s] * (b - a - 1)
        ax.plot(trajectory.frame_time, 100.0 * (length / rest - 1.0), color=colors(s), label=name)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("stretch [% of rest length]")
    ax.set_title("string stretch")
    ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
