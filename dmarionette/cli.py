"""The ``dmarionette`` command line.

``dmarionette simulate SCENE`` runs a scene headless and writes its trajectory, a
summary and a picture; ``dmarionette demo`` does the same for the default scene;
``dmarionette scenes`` lists the built-in scenes. ``--help`` on every command.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["main"]


def _add_simulate_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds (default: the scene's [scene] duration)")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: out/<scene name>)")
    parser.add_argument("--precision", choices=["float64", "float32"], default=None,
                        help="float type of the kernels (default: the scene's [solver] precision)")
    parser.add_argument("--no-picture", action="store_true", help="skip the PNG picture")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmarionette",
        description="A differentiable simulator of a string marionette (NVIDIA Warp).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    simulate = sub.add_parser(
        "simulate", help="run a scene headless and write its trajectory, summary and picture",
        description="Run a scene headless. Writes OUT/trajectory.npz (docs/trajectory.md), "
                    "OUT/summary.json and OUT/strings.png, and prints the summary.",
    )
    simulate.add_argument("scene", help="a built-in scene name (see 'dmarionette scenes') or a TOML file")
    _add_simulate_options(simulate)
    demo = sub.add_parser("demo", help="simulate the built-in default scene ('hanging')",
                          description="Same as 'dmarionette simulate hanging'.")
    _add_simulate_options(demo)
    sub.add_parser("scenes", help="list the built-in scenes", description="List the built-in scenes.")
    return parser


def _run_simulate(scene_name: str, args: argparse.Namespace) -> int:
    import dataclasses

    from .scene import load_scene
    from .simulate import simulate_strings
    from .trajectory_file import summarize, write_trajectory

    scene = load_scene(scene_name)
    if args.precision is not None:
        scene = dataclasses.replace(scene, precision=args.precision)
    out = args.out if args.out is not None else Path("out") / scene.name
    trajectory = simulate_strings(scene, args.duration, progress=not args.quiet)
    files = {"trajectory": str(write_trajectory(out / "trajectory.npz", trajectory, scene))}
    if not args.no_picture:
        from .render_strings import render_string_picture

        files["picture"] = str(render_string_picture(out / "strings.png", trajectory, title=scene.description,
                                                     ground_height=scene.ground_height))
    summary = summarize(trajectory, scene)
    summary["files"] = files
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    if not summary["all_finite"]:
        print("error: the simulation produced a non-finite value", file=sys.stderr)
        return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``dmarionette`` command."""
    args = _parser().parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # before Warp starts: stdout carries the JSON summary, not Warp's banner
    from .scene_fields import SceneError

    try:
        if args.command == "scenes":
            from .scene import builtin_scenes, load_scene

            for name in builtin_scenes():
                print(f"{name:12s} {load_scene(name).description}")
            return 0
        if args.command == "demo":
            from .scene import DEFAULT_SCENE

            return _run_simulate(DEFAULT_SCENE, args)
        return _run_simulate(args.scene, args)
    except (SceneError, ValueError, RuntimeError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
