"""Benchmark: rendering the marionette animation of a trajectory (issue 17 target: <= 5 s for the 10 s demo).

Renders ``TRAJECTORY`` (a ``trajectory.npz`` from ``dmarionette simulate``) at 15 fps as the CLI
does and prints the frame count, the wall time and
the process's CPU time (the wall time on a busy machine says less). ``--renderer FILE`` renders with another copy of
``dmarionette/render/marionette.py`` (e.g. an older one from ``git show``), to compare.

Usage::

    dmarionette demo --no-picture --out out/hanging
    python benchmarks/bench_render.py out/hanging/trajectory.npz /tmp/animation.gif
    git show be87cf4:dmarionette/render/marionette.py > /tmp/old_render.py
    python benchmarks/bench_render.py out/hanging/trajectory.npz /tmp/old.gif --renderer /tmp/old_render.py
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time

from dmarionette.io.export.common import read_marionette_trajectory
from dmarionette.scene.scene import load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trajectory")
    parser.add_argument("out", help="the animation to write (.gif or .mp4)")
    parser.add_argument("--scene", default="hanging", help="the trajectory's scene (default hanging)")
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--renderer", default=None, help="another copy of render/marionette.py")
    args = parser.parse_args()
    if args.renderer is None:
        import dmarionette.render.marionette as renderer
    else:
        spec = importlib.util.spec_from_file_location("renderer_under_test", args.renderer)
        renderer = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(renderer)
    trajectory = read_marionette_trajectory(args.trajectory)
    scene = load_scene(args.scene)
    every = max(1, round(1.0 / (args.fps * (trajectory.frame_time[1] - trajectory.frame_time[0]))))
    start, cpu = time.perf_counter(), time.process_time()
    path, frames = renderer.render_marionette_animation(
        args.out, trajectory, title=scene.description, ground_height=scene.ground_height, chair=scene.chair,
        ball_radius=scene.ball.radius if scene.ball is not None else None, every=every)
    print(json.dumps({"file": str(path), "frames": frames, "seconds": round(time.perf_counter() - start, 2),
                      "cpu_seconds": round(time.process_time() - cpu, 2)}))


if __name__ == "__main__":
    main()
