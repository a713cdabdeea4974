"""Frames of a marionette scene side by side, as one PNG (side view, the simulator's replay).

    python tools/frames_strip.py SCENE OUT.png [--times 0 0.5 1 1.5 2.5 4]

Draws with ``dmarionette.render.frames.render_marionette_frames`` (strings, bodies, bars, the
chair, the ball and the ground) at the given times. The README's pictures of the paper's scenes:
``python tools/frames_strip.py chair docs/img/chair_authored.png`` and
``python tools/frames_strip.py ball docs/img/ball_authored.png --times 0 0.4 0.66 1.3 2.0 2.5``.
"""

from __future__ import annotations

import argparse


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", help="a built-in scene name or a scene TOML file")
    parser.add_argument("out", help="the PNG to write")
    parser.add_argument("--times", type=float, nargs="+", default=[0.0, 0.5, 1.0, 1.5, 2.5, 4.0])
    args = parser.parse_args(argv)

    from dmarionette.marionette.rollout import simulate_marionette
    from dmarionette.marionette.solver import MarionetteModel
    from dmarionette.render.frames import render_marionette_frames
    from dmarionette.scene.scene import load_scene

    scene = load_scene(args.scene)
    trajectory = simulate_marionette(MarionetteModel(scene), max(max(args.times), 0.1), progress=False)
    print(render_marionette_frames(args.out, trajectory, args.times, title=f"{scene.name}: {scene.description}",
                                   ground_height=scene.ground_height, chair=scene.chair,
                                   ball_radius=scene.ball.radius if scene.ball is not None else None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
