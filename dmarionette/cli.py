"""The ``dmarionette`` command line.

- ``dmarionette simulate SCENE``: run a scene headless; write its trajectory, summary, animation;
- ``dmarionette demo``: the same for the default scene (``hanging``);
- ``dmarionette scenes``: list the built-in scenes;
- ``dmarionette live [SCENE]``: live puppetry with a haptic device in the 1 kHz servo loop
  (``--view browser``: a 3D view in the browser, docs/live_view.md);
- ``dmarionette bench accuracy``: what accuracy costs in time;
- ``dmarionette export TRAJECTORY``: the puppet motion as BVH and glTF (docs/export.md);
- ``dmarionette sweep SCENE --set KEY=V1,V2,...``: a grid of scene variants, a summary row each,
  in this process or on Ray workers (docs/sweep.md);
- plug-in commands, from other packages: ``fitting`` adds ``dmarionette author KEYFRAMES`` (bar
  motions that reach keyframe poses, docs/authoring.md) and ``dmarionette calibrate SESSION``
  (string constants fitted to a recorded session, docs/calibration.md).

``--help`` on every command.

Plug-in commands. ``dmarionette`` never imports ``fitting`` (nor any other plug-in) by name: a
package declares its commands in the ``dmarionette.commands`` entry-point group, e.g. in its
pyproject.toml::

    [project.entry-points."dmarionette.commands"]
    author = "fitting.cli:add_author_command"

The entry's name is the command; its object is a function ``add(commands)`` that adds the
command's subparser to ``commands`` (what ``ArgumentParser.add_subparsers`` returned) and sets
the subparser's default ``handler``: a function ``handler(args) -> int`` that runs the command
and returns its exit code. A ``SceneError``, ``ValueError`` or ``RuntimeError`` it raises is
printed as ``error: ...`` and exits with 2, as for the built-in commands; a
``dmarionette.cli_checks.NonFiniteError`` exits with 1, and Ctrl-C with 130 (one line: what was
kept). ``args.outputs`` (a ``dmarionette.cli_checks.Outputs``) checks the command's output folders
and files before its work (``args.outputs.folder("--out", path)``) and removes what it created if
the command fails. Entries are loaded lazily: only the command a command line names (all of
them for the top-level help or an unknown command), so ``dmarionette simulate`` never imports
JAX. An entry that cannot be loaded (a missing extra) still appears as a command, which
explains the problem and exits 2.

Where the entries come from (``find_commands``): the installed packages' metadata
(``importlib.metadata``; ``pip install -e '.[dev]'`` writes it, as CI does), and, for a
source tree run without installing it (``PYTHONPATH=.``) or installed before a command was
added, the same table read from the tree's own pyproject.toml (the installed metadata wins
where both name a command). A plug-in cannot replace a built-in command. Where neither knows
any plug-in, the top-level help and an unknown command say how to install them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tomllib
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path

from .extras import check_command_extras
from .first_run import build_marionette, init_warp, load_string_kernels, versions
from .cli_checks import Outputs, PromptInterrupt, integer, number, optimization_level, refuse_empty_option_values

__all__ = ["COMMAND_GROUP", "find_commands", "main"]

COMMAND_GROUP = "dmarionette.commands"
"""The entry-point group in which packages declare their ``dmarionette`` commands."""

SOURCE_TREE = Path(__file__).resolve().parents[1]
"""The folder above this package: a source tree when it holds dmarionette's pyproject.toml."""

_NO_PLUGINS = (f"no plug-in commands were found (entry-point group {COMMAND_GROUP!r}); fitting's author and "
               "calibrate come with the installed package: pip install -e '.[fitting]' in the source tree, or "
               "pip install 'dmarionette[fitting]'")


def _add_simulate_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=number(0.0, low_open=True, unit="s"), default=None,
                        help="simulated seconds (default: the scene's [scene] duration)")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default: out/<scene name>)")
    parser.add_argument("--precision", choices=["float64", "float32"], default=None,
                        help="float type of the kernels (default: the scene's [solver] precision)")
    parser.add_argument("--no-picture", action="store_true", help="skip the picture / animation")
    parser.add_argument("--animation", choices=["gif", "mp4"], default="gif",
                        help="animation format for scenes with a puppet (default: gif)")
    parser.add_argument("--fps", type=number(0.1, 1000.0, unit="Hz"), default=15.0,
                        help="animation frames per second (default: 15)")
    parser.add_argument("--fast-compile", action="store_true",
                        help="compile the puppet kernels without optimisation: ~10 s instead of ~1 min on "
                             "the first run, slower to run")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or compile messages")


def _parser() -> tuple[argparse.ArgumentParser, argparse.Action]:
    """The parser of the built-in commands, and its subcommands (for the plug-ins to add to)."""
    parser = argparse.ArgumentParser(
        prog="dmarionette",
        description="A differentiable simulator of a string marionette (NVIDIA Warp).",
    )
    parser.add_argument("--version", action="version", version=versions())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    simulate = sub.add_parser(
        "simulate", help="run a scene headless and write its trajectory, summary and picture",
        description="Run a scene headless. Writes OUT/trajectory.npz (docs/trajectory.md), "
                    "OUT/summary.json and, for a marionette, OUT/animation.gif (or .mp4); for strings "
                    "alone, OUT/strings.png. Prints the summary.",
    )
    simulate.add_argument("scene", help="a built-in scene name (see 'dmarionette scenes') or a TOML file")
    _add_simulate_options(simulate)
    simulate.set_defaults(handler=lambda args: _run_simulate(args.scene, args))
    demo = sub.add_parser("demo", help="simulate the built-in default scene ('hanging': the marionette)",
                          description="Same as 'dmarionette simulate hanging'.")
    _add_simulate_options(demo)
    demo.set_defaults(handler=_run_demo)
    scenes = sub.add_parser("scenes", help="list the built-in scenes", description="List the built-in scenes.")
    scenes.set_defaults(handler=_run_scenes)
    live = sub.add_parser(
        "live", help="live puppetry: a haptic device drives a bar at 1 kHz and feels the strings",
        description="Live puppetry (paper §3): the device tip drives a control bar through P' = S W P, "
                    "the strings and feedback run at the scene's string rate in the servo loop, the puppet "
                    "at its own rate; forces are clamped, ramped in, and cut by a watchdog. Prints the "
                    "servo tick statistics at the end.")
    live.add_argument("scene", nargs="?", default="hanging", help="scene name or TOML file (default: hanging)")
    live.add_argument("--device", choices=["sim", "simulated", "replay", "openhaptics", "falcon", "spacemouse"],
                      action="append", default=None,
                      help="the haptic device (sim = simulated: follows the scene's bar motion; replay: plays "
                           "the device stream of --session; default simulated). Give it twice, with --bar twice, "
                           "for two devices, one per bar (the n-th --device drives the n-th --bar; physics thread "
                           "only; docs/hardware.md \"Two devices\")")
    live.add_argument("--session", type=Path, default=None, help="the recorded session --device replay plays")
    live.add_argument("--bar", action="append", default=None,
                      help="the bar the device drives (default: main); once per --device")
    live.add_argument("--duration", type=number(0.0, low_open=True, unit="s"), default=10.0,
                      help="seconds to run (default: 10)")
    live.add_argument("--record", type=Path, default=None, help="write the session to this MCAP file")
    live.add_argument("--feedback", choices=["reaction", "eq4"], default="reaction",
                      help="force sent: the strings' pull on the bar (default) or the paper's eq. 4 as printed")
    live.add_argument("--force-scale", type=number(0.0), default=0.3,
                      help="multiplies the feedback before the safety filter (default 0.3: the puppet's "
                           "~7 N weight becomes ~2 N, inside a PHANToM Omni's 3.3 N)")
    live.add_argument("--workspace-scale", type=number(0.0, low_open=True), action="append", default=None,
                      help="S of P' = S W P (default 1); once for all devices or once per --device")
    live.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    live.add_argument("--physics", choices=["auto", "thread", "process", "shm"], default=None,
                      help="where the marionette runs: the servo loop's worker thread, a child process over a "
                           "pipe, or a child process over shared memory with real-time priority where allowed; "
                           "auto (default): thread with --view browser or --snapshot (the view reads the "
                           "physics in this process) or with two devices; process and shm are refused there; "
                           "otherwise shm "
                           "where SCHED_FIFO is allowed, else thread (docs/hardware.md)")
    live.add_argument("--own-process", action="store_true", help="the same as --physics process (older spelling)")
    live.add_argument("--no-realtime", action="store_true",
                      help="with --physics shm: do not ask for SCHED_FIFO priority")
    live.add_argument("--view", choices=["none", "browser"], default="none",
                      help="none (default): no view, nothing but the servo loop; browser: a 3D view served on "
                           "http://HOST:PORT (viser; needs the 'view' extra): puppet, strings (dark taut, orange "
                           "slack), bars, force arrows; with the simulated device the driven bar can be dragged; "
                           "runs the physics in the servo loop's worker thread (docs/live_view.md)")
    live.add_argument("--view-port", type=integer(0, 65535), default=8080,
                      help="TCP port of the browser view (default 8080; 0: any free port; a taken port: the next)")
    live.add_argument("--view-host", default="127.0.0.1",
                      help="address the browser view listens on (default 127.0.0.1, this machine only)")
    live.add_argument("--view-hz", type=number(0.0, 1000.0, low_open=True, unit="Hz"), default=40.0,
                      help="view updates per second (default 40)")
    live.add_argument("--snapshot", type=Path, default=None,
                      help="write a picture (PNG) of the last frame here at the end; works with any --view "
                           "(and, like it, runs the physics in the worker thread)")
    live.set_defaults(handler=_run_live)
    info = sub.add_parser("info", help="summarise a recorded session (MCAP)",
                          description="Summarise a recorded session: duration, topics with counts and rates, "
                                      "scene, bars, whether the recording was cut off (docs/session.md).")
    info.add_argument("session", type=Path, help="the .mcap file")
    info.set_defaults(handler=_run_info)
    session = sub.add_parser("session", help="session file tools (index)", description="Session file tools.")
    session_index = session.add_subparsers(dest="session_command", required=True).add_parser(
        "index", help="rewrite a session chunked, indexed and zstd-compressed (after a crash; old sessions)",
        description="Rewrite a session file chunked, indexed and zstd-compressed, as a recording that closes "
                    "normally is; for a file left by a crash (everything up to its last complete record) or an "
                    "old session (the Foxglove channels are added from its bar poses and puppet states).")
    session_index.add_argument("session", type=Path, help="the .mcap file (rewritten in place unless --out)")
    session_index.add_argument("--out", type=Path, default=None, help="write the indexed file here instead")
    session_index.set_defaults(handler=_run_session_index)
    replay = sub.add_parser("replay", help="re-simulate a recorded session and compare",
                            description="Rebuild the session's scene from its metadata, drive its bars with the "
                                        "recorded bar poses, re-simulate, and report the gap between recorded "
                                        "and re-simulated body positions.")
    replay.add_argument("session", type=Path, help="the .mcap file")
    replay.add_argument("--out", type=Path, default=None, help="also write trajectory.npz and summary.json here")
    replay.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    replay.add_argument("--quiet", action="store_true", help="no progress bars or compile messages")
    replay.set_defaults(handler=_run_replay)
    bench = sub.add_parser("bench", help="measure what accuracy costs in time",
                           description="Benchmarks. 'accuracy': sweep particles per string, string step, "
                                       "puppet rate, float32/float64 strings, tension-only springs and contact "
                                       "model against a refined reference; writes "
                                       "OUT/accuracy.csv, accuracy.png (Pareto plot) and accuracy.md.")
    bench.add_argument("what", choices=["accuracy"], help="the benchmark to run")
    bench.add_argument("--grid", choices=["full", "reduced"], default="full",
                       help="full sweep (about 30 s on one core once its kernels are compiled; the first "
                            "run compiles them, minutes) or the reduced grid CI runs")
    bench.add_argument("--seconds", type=number(0.1, 60.0, unit="s"), default=3.0,
                       help="length of the scripted motion [s] (0.1 to 60; the full grid takes about 30 s at 3 s, "
                            "kernels compiled)")
    bench.add_argument("--repeats", type=integer(1, 100), default=3, help="timed runs per setting (median)")
    bench.add_argument("--out", type=Path, default=Path("out") / "bench", help="output folder")
    bench.add_argument("--fast-compile", action="store_true",
                       help="puppet kernels without optimisation (timings then mean less)")
    bench.set_defaults(handler=_run_bench)
    export = sub.add_parser("export", help="export the puppet motion of a trajectory to BVH and glTF",
                            description="Write the puppet motion of a marionette trajectory file (from 'dmarionette "
                                        "simulate') as OUT/motion.bvh (joint tree, metres, degrees) and/or OUT/motion.glb "
                                        "(binary glTF 2.0: body meshes and an animation), for Blender "
                                        "(docs/export.md). Prints the written files as JSON.")
    export.add_argument("trajectory", type=Path, help="the trajectory.npz file")
    export.add_argument("--format", choices=["bvh", "gltf", "usd", "all"], default="all",
                        help="what to write (default: all; USD, OUT/motion.usda, needs the usd extra and is "
                             "part of 'all' only when pxr imports)")
    export.add_argument("--out", type=Path, default=None,
                        help="output folder (default: the trajectory file's folder)")
    export.add_argument("--fps", type=number(0.0, 1000.0, low_open=True, unit="Hz"), default=None,
                        help="BVH frame rate (default: one BVH frame per trajectory frame)")
    export.add_argument("--scene", default=None,
                        help="the scene (name or TOML file) whose puppet the trajectory was simulated with "
                             "(default: the scene the file names, else the default marionette)")
    export.set_defaults(handler=_run_export)
    from .sweep.cli import add_sweep_command

    add_sweep_command(sub)  # dmarionette sweep SCENE --set KEY=V1,V2,... (docs/sweep.md)
    return parser, sub


def _run_session_index(args: argparse.Namespace) -> int:
    from .io.session.index import index_session

    print(json.dumps(index_session(args.session, args.out), indent=2))
    return 0


def _run_export(args: argparse.Namespace) -> int:
    from .io.export.bvh import export_bvh
    from .io.export.common import read_marionette_trajectory
    from .io.export.gltf import export_gltf

    trajectory = read_marionette_trajectory(args.trajectory)
    trajectory.source = str(args.trajectory)
    if args.scene is not None:
        from .scene.scene import load_scene

        scene = load_scene(args.scene)
        if scene.puppet is None:
            raise ValueError(f"{scene.source}: --scene: this scene has no [puppet]; expected the marionette's scene")
        trajectory.puppet = scene.puppet
    out = args.outputs.folder("--out", args.out if args.out is not None else args.trajectory.parent)
    files = {}
    if args.format in ("bvh", "all"):
        files["bvh"] = str(export_bvh(trajectory, out / "motion.bvh", fps=args.fps))
    if args.format in ("gltf", "all"):
        files["gltf"] = str(export_gltf(trajectory, out / "motion.glb"))
    if args.format in ("usd", "all"):
        from .io.export.usd import export_usd, usd_available

        if usd_available():
            files["usd"] = str(export_usd(trajectory, out / "motion.usda"))
        elif args.format == "usd":
            print(f"error: {usd_available.hint}", file=sys.stderr)
            return 2
        else:
            files["usd"] = f"skipped: {usd_available.hint}"
    print(json.dumps(files, indent=2))
    return 0


def _run_simulate(scene_name: str, args: argparse.Namespace) -> int:
    import dataclasses

    from .cli_checks import check_finite, check_trajectory_fits
    from .scene.limits import trajectory_bytes
    from .scene.scene import load_scene
    from .strings.simulate import simulate_strings
    from .io.trajectory import summarize, write_trajectory

    scene = load_scene(scene_name)
    if args.precision is not None:
        scene = dataclasses.replace(scene, precision=args.precision)
    duration = scene.duration if args.duration is None else args.duration
    check_trajectory_fits("--duration" if args.duration is not None else f"{scene.source}: [scene] duration",
                          duration, trajectory_bytes(scene, duration))
    out = args.outputs.folder("--out", args.out if args.out is not None else Path("out") / scene.name)
    if scene.puppet is not None:
        return _run_marionette(scene, out, args)
    load_string_kernels(scene, quiet=args.quiet)  # compiled under a progress bar, not silently in the first step
    trajectory = simulate_strings(scene, duration, progress=not args.quiet)
    check_finite(trajectory)
    files = {"trajectory": str(write_trajectory(out / "trajectory.npz", trajectory, scene))}
    if not args.no_picture:
        from .render.strings import render_string_picture

        files["picture"] = str(render_string_picture(out / "strings.png", trajectory, title=scene.description,
                                                     ground_height=scene.ground_height))
    return _write_summary(out, summarize(trajectory, scene), files)


def _run_marionette(scene, out: Path, args: argparse.Namespace) -> int:
    from .cli_checks import check_finite
    from .marionette.rollout import simulate_marionette
    from .io.trajectory import summarize_marionette, write_marionette_trajectory

    if not args.quiet:
        print("building the marionette (the first run compiles the puppet kernels)", file=sys.stderr)
    model = build_marionette(scene, optimization_level=optimization_level(args), quiet=args.quiet)
    duration = scene.duration if args.duration is None else args.duration
    trajectory = simulate_marionette(model, duration, progress=not args.quiet)
    check_finite(trajectory)
    files = {"trajectory": str(write_marionette_trajectory(out / "trajectory.npz", trajectory, scene))}
    if not args.no_picture:
        from .render.marionette import render_marionette_animation

        every = max(1, round(1.0 / (args.fps * (trajectory.frame_time[1] - trajectory.frame_time[0]))))
        path, frames = render_marionette_animation(
            out / f"animation.{args.animation}", trajectory, title=scene.description,
            ground_height=scene.ground_height, chair=scene.chair,
            ball_radius=scene.ball.radius if scene.ball is not None else None, every=every,
            progress=not args.quiet)
        files["animation"] = str(path)
        files["animation_frames"] = frames
    return _write_summary(out, summarize_marionette(trajectory, scene), files)


def _write_summary(out: Path, summary: dict, files: dict) -> int:
    """Writes OUT/summary.json (with the files written) and prints it; exit code 1 on a non-finite value."""
    summary["files"] = files
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    if not summary["all_finite"]:
        print("error: the simulation produced a non-finite value", file=sys.stderr)
        return 1
    return 0


def _run_replay(args: argparse.Namespace) -> int:
    from .cli_checks import check_finite
    from .io.session import read_session, replay_session

    out = args.outputs.folder("--out", args.out) if args.out is not None else None
    level = optimization_level(args)
    build_marionette(read_session(args.session).scene, optimization_level=level, quiet=args.quiet)  # compiles
    trajectory, report = replay_session(args.session, optimization_level=level, progress=not args.quiet)
    if out is not None:
        from .io.trajectory import summarize_marionette, write_marionette_trajectory

        check_finite(trajectory)
        scene = read_session(args.session).scene
        write_marionette_trajectory(out / "trajectory.npz", trajectory, scene)
        (out / "summary.json").write_text(json.dumps(summarize_marionette(trajectory, scene), indent=2) + "\n")
    print(json.dumps(report, indent=2, default=float))
    return 0


def _run_live(args: argparse.Namespace) -> int:
    from .live.run import resolve_physics, run_live
    from .scene.scene import load_scene

    scene = load_scene(args.scene)
    if scene.puppet is None or not scene.bars:
        raise ValueError(f"{scene.source}: live puppetry needs a scene with a [puppet] and [bars]")
    devices = ["simulated" if d == "sim" else d for d in (args.device or ["simulated"])]
    if args.bar is None and len(devices) > 1:
        raise ValueError(f"--device given {len(devices)} times: give --bar once per device (the n-th --device "
                         f"drives the n-th --bar); bars in {scene.source}: {[b.name for b in scene.bars]}")
    bars = args.bar or ["main"]
    if len(bars) != len(devices):
        raise ValueError(f"--bar given {len(bars)} times for {len(devices)} --device; expected one bar per device")
    for bar in bars:
        if bar not in [b.name for b in scene.bars]:
            raise ValueError(f"--bar: got {bar!r}; expected one of {[b.name for b in scene.bars]} ({scene.source})")
    if len(set(bars)) != len(bars):
        raise ValueError(f"--bar: got {bars}; expected a different bar for each device")
    scales = args.workspace_scale or [1.0]
    if len(scales) not in (1, len(devices)):
        raise ValueError(f"--workspace-scale given {len(scales)} times for {len(devices)} devices; expected once "
                         "for all or once per device")
    if "replay" in devices and args.session is None:
        raise ValueError("--device replay needs --session FILE (a recorded session)")
    if args.own_process and args.physics not in (None, "process"):
        raise ValueError(f"--own-process is --physics process; got it together with --physics {args.physics}")
    # Checked before anything compiles: a view reads the physics' snapshots in this process.
    resolve_physics(args.physics, process=args.own_process, realtime=not args.no_realtime,
                    view=args.view != "none" or args.snapshot is not None, devices=len(devices))
    if args.snapshot is not None and args.snapshot.suffix.lower() != ".png":
        raise ValueError(f"--snapshot: got {str(args.snapshot)!r}; expected a .png file name")
    from .cli_checks import check_host, check_trajectory_fits, live_input_bytes

    check_trajectory_fits("--duration", args.duration, live_input_bytes(scene, args.duration))
    if args.session is not None and not args.session.is_file():
        raise ValueError(f"--session: got {str(args.session)!r}; expected an existing session file (.mcap)")
    if args.view == "browser":
        check_host("--view-host", args.view_host)
    for flag, path in (("--record", args.record), ("--snapshot", args.snapshot)):
        if path is not None:
            args.outputs.file(flag, path)
    level = optimization_level(args)
    model = build_marionette(scene, optimization_level=level)  # compiles here; the child then loads the cache
    args.interrupt.disarm()  # from here devices open and the servo loop turns the motors off on Ctrl-C
    from .live.view import LiveViewGeometry, LiveViewHeadless, render_live_snapshot

    def on_start(info: dict) -> None:
        # CLOCK_MONOTONIC is the clock of the simulated device and of time.monotonic() in any process
        # (tests relate a recording's device times to the moment they kill this process by it).
        record = f"; recording to {args.record}" if args.record is not None else ""
        print(f"live: servo loop starting at CLOCK_MONOTONIC {time.monotonic():.6f} s; physics: {info['physics']} "
              f"(pid {info['physics_pid']}){record}", file=sys.stderr, flush=True)

    geometry = LiveViewGeometry.from_model(model, bars)  # every device's bar: a drag handle, a force-sent arrow
    view = None
    if args.view == "browser" and geometry is not None:
        from .live.view_viser import LiveViewServer

        view = LiveViewServer(geometry, host=args.view_host, port=args.view_port, rate_hz=args.view_hz)
        print(f"live view: {view.url}", file=sys.stderr, flush=True)
    elif args.snapshot is not None:
        view = LiveViewHeadless()
    try:
        several = len(devices) > 1
        stats, summary = run_live(model, device=devices if several else devices[0], bar=bars if several else bars[0],
                                  session=args.session, duration=args.duration,
                                  record=args.record, feedback=args.feedback, force_scale=args.force_scale,
                                  workspace_scale=scales if len(scales) > 1 else scales[0],
                                  process=args.own_process,
                                  physics=args.physics, realtime=not args.no_realtime, optimization_level=level,
                                  on_start=on_start, view=view)
    finally:
        if view is not None:
            view.close()
    if args.snapshot is not None and view.buffer.latest() is not None:
        summary["snapshot"] = str(render_live_snapshot(args.snapshot, geometry, view.buffer.latest(),
                                                       title=scene.description))
    print(stats.summary())
    if args.record is not None:
        summary["record"] = str(args.record)
    print(json.dumps(summary, indent=2))
    return 0


def _run_demo(args: argparse.Namespace) -> int:
    from .scene.scene import DEFAULT_SCENE

    return _run_simulate(DEFAULT_SCENE, args)


def _run_scenes(args: argparse.Namespace) -> int:
    from .scene.scene import builtin_scenes, load_scene

    names = builtin_scenes()
    width = max(len(name) for name in names)
    for name in names:
        print(f"{name:{width}s}  {load_scene(name).description}")
    return 0


def _run_info(args: argparse.Namespace) -> int:
    from .io.session import format_session_info, session_info

    print(format_session_info(session_info(args.session)))
    return 0


def _run_bench(args: argparse.Namespace) -> int:
    from .marionette.accuracy import run_sweep, write_outputs

    args.outputs.folder("--out", args.out)
    from .scene.scene import DEFAULT_SCENE, load_scene

    # The sweep's puppet kernels (one topology) compiled under a progress bar before its first row.
    build_marionette(load_scene(DEFAULT_SCENE), optimization_level=optimization_level(args))
    rows, summary = run_sweep(args.seconds, args.grid, optimization_level(args), args.repeats,
                              progress=lambda line: print(line, file=sys.stderr))
    files = write_outputs(rows, summary, args.out)
    print(files["table"].read_text())
    print(json.dumps({k: str(v) for k, v in files.items()}))
    return 0


def find_commands(*, installed: bool = True,
                  source_tree: Path | None = SOURCE_TREE) -> dict[str, metadata.EntryPoint]:
    """The plug-in commands, not loaded: command name -> entry point (see the module docstring).

    Args:
        installed: read the installed packages' metadata (``importlib.metadata``).
        source_tree: a folder whose pyproject.toml, when it is dmarionette's, declares entries too
            (default: the folder above this package); None: none.

    Returns:
        The entries of the ``dmarionette.commands`` group; the installed metadata's where both name
        a command.
    """
    found = {}
    if installed:
        found = {entry.name: entry for entry in metadata.entry_points(group=COMMAND_GROUP)}
    pyproject = source_tree / "pyproject.toml" if source_tree is not None else None
    if pyproject is not None and pyproject.is_file():
        project = tomllib.loads(pyproject.read_text()).get("project", {})
        if project.get("name") == "dmarionette":
            for name, value in project.get("entry-points", {}).get(COMMAND_GROUP, {}).items():
                found.setdefault(name, metadata.EntryPoint(name, value, COMMAND_GROUP))
    return found


def _add_plugin(sub, entry: metadata.EntryPoint) -> None:
    """Adds a plug-in command; one that cannot be loaded becomes a command that says why."""
    try:
        add = entry.load()
    except ImportError as error:
        message = (f"'dmarionette {entry.name}' is a plug-in command ({entry.value}, entry-point group "
                   f"{COMMAND_GROUP!r}) that could not be loaded: {error}; if a package is missing, install the "
                   "extra that brings it, e.g. pip install 'dmarionette[fitting]'")
        stub = sub.add_parser(entry.name, help=f"(not available: {error})", description=message)
        stub.add_argument("arguments", nargs=argparse.REMAINDER, help="not read")

        def unavailable(args: argparse.Namespace) -> int:
            raise RuntimeError(message)

        stub.set_defaults(handler=unavailable)
        return
    add(sub)


def main(argv: Sequence[str] | None = None, commands: Mapping[str, metadata.EntryPoint] | None = None) -> int:
    """Entry point of the ``dmarionette`` command.

    Args:
        argv: the arguments (default: ``sys.argv[1:]``).
        commands: the plug-in commands (default: ``find_commands()``).

    Returns:
        The exit code: 0 done, 1 a simulation produced a non-finite value (nothing written), 2 an error
        (printed; a flag, a file or an output path), 130 interrupted (Ctrl-C; one line says what was kept).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    parser, sub = _parser()
    builtin = set(sub.choices)
    plugins = find_commands() if commands is None else commands
    named = next((a for a in argv if not a.startswith("-")), None)  # the command: the first positional
    for name in sorted(plugins):
        if name not in builtin and (named == name or named not in builtin):  # load only what may be used
            _add_plugin(sub, plugins[name])
    if not plugins:
        parser.epilog = _NO_PLUGINS
        if named is not None and named not in builtin:
            parser.error(f"unknown command {named!r}; {_NO_PLUGINS}")
    refuse_empty_option_values(parser, argv)
    args = parser.parse_args(argv)
    args.outputs = Outputs()  # the handler checks its outputs with it before the work (cli_checks)
    # Ctrl-C stops within a second even inside a kernel compile (live disarms it before it opens the devices).
    args.interrupt = PromptInterrupt(args.outputs)
    try:
        with args.interrupt:
            return _run_handler(args)
    except KeyboardInterrupt:
        print(args.outputs.interrupted(), file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of the output went away (`dmarionette scenes | head -3`): stop quietly, with the
        # status of a command ended by SIGPIPE; what is still buffered goes nowhere, not to a second
        # error at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


def _run_handler(args: argparse.Namespace) -> int:
    """Runs the command; its errors printed (exit code 2; 1 for a non-finite result)."""
    from .cli_checks import NonFiniteError
    from .scene.fields import SceneError

    try:
        check_command_extras(args)  # a missing extra: one line, exit 2, before any work
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING  # before Warp starts: stdout carries the JSON summary, not Warp's banner
        init_warp()  # without the CUDA-driver notice on a CPU-only machine
        return args.handler(args)
    except NonFiniteError as error:
        args.outputs.discard()
        print(f"error: {error}", file=sys.stderr)
        return 1
    except (SceneError, ValueError, RuntimeError) as error:
        args.outputs.discard()
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
