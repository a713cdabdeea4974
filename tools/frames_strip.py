"""Frames of a marionette scene side by side, as one PNG (side view, the simulator's replay).

    python tools/frames_strip.py SCENE OUT.png [--times 0 0.5 1 1.5 2.5 4]

Draws what ``dmarionette.render.marionette`` draws in its side view (strings, bodies, bars, the
chair and the ground) at the given times. Used for docs/img/chair_authored.png:
``python tools/frames_strip.py dmarionette/scene/builtin/chair.toml docs/img/chair_authored.png``.
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("out")
    parser.add_argument("--times", type=float, nargs="+", default=[0.0, 0.5, 1.0, 1.5, 2.5, 4.0])
    args = parser.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dmarionette.marionette.rollout import simulate_marionette
    from dmarionette.marionette.solver import MarionetteModel
    from dmarionette.render.marionette import _bar_polyline, _polyline, frame_extent
    from dmarionette.scene.scene import load_scene

    scene = load_scene(args.scene)
    trajectory = simulate_marionette(MarionetteModel(scene), max(args.times), progress=False)
    lo, hi = frame_extent(trajectory, chair=scene.chair)
    lo[1] = min(lo[1], scene.ground_height - 0.05)
    fig, axes = plt.subplots(1, len(args.times), figsize=(2.2 * len(args.times), 4.2), sharey=True)
    for ax, t in zip(np.atleast_1d(axes), args.times):
        f = int(np.argmin(np.abs(trajectory.frame_time - t)))
        ax.axhspan(lo[1] - 1.0, scene.ground_height, color="0.85", zorder=0)
        if scene.chair is not None:
            c, h = scene.chair
            ax.add_patch(plt.Rectangle((c[2] - h[2], c[1] - h[1]), 2 * h[2], 2 * h[1], color="tan", alpha=0.7))
        for s in range(len(trajectory.string_names)):
            a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
            ax.plot(trajectory.particle_q[f, a:b, 2], trajectory.particle_q[f, a:b, 1], color="0.15", lw=0.8)
        body, bar = _polyline(trajectory, f), _bar_polyline(trajectory, f)
        ax.plot(body[:, 2], body[:, 1], color="steelblue", lw=1.2)
        ax.plot(bar[:, 2], bar[:, 1], color="saddlebrown", lw=4, solid_capstyle="butt")
        ax.set_xlim(lo[2], hi[2])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(f"t = {trajectory.frame_time[f]:.2f} s", fontsize=9)
        ax.set_xlabel("z [m] (side)", fontsize=8)
        ax.tick_params(labelsize=7)
    np.atleast_1d(axes)[0].set_ylabel("y [m]")
    fig.suptitle(f"{scene.name}: {scene.description}", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
