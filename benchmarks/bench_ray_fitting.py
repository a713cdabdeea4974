"""``calibrate`` over two sessions and ``author`` over two keyframes files: in this process against Ray.

Run:  python benchmarks/bench_ray_fitting.py [--session-seconds 1] [--max-steps 8] [--repeats 1]

- **calibrate**: two synthetic sessions (``sway`` and ``roll_yaw`` of ``fitting.synthetic_scenes``,
  ``--session-seconds`` each, the calibration test problem's true constants, 0.1 mm noise), fitted
  together by ``dmarionette calibrate a.mcap b.mcap --params k,k_d`` (12 constants, the default
  windows, ``--max-steps``), with ``--ray off`` and ``--ray local`` (2 workers, one session each).
  Reported: the command's wall time (with Ray: the cluster's start, the workers' start and kernel
  loads, and the shutdown are in it) and the fit's own time (calibration.json's solver and
  uncertainty seconds: the rollouts, where Ray runs the two sessions in parallel).
- **author**: two keyframes files of the ``hanging`` scene (a hand target 1.3 cm away, and one
  12 cm away that is not reached in ``--author-steps``), ``dmarionette author a.toml b.toml`` with
  ``--ray off`` and ``--ray local`` (2 workers, one file each), ``--no-animation --no-export``.

The modes are interleaved run by run; each run is a whole command as a user runs it (``main``),
and its numbers are checked equal across the modes. Medians over ``--repeats``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import tomli_w

from dmarionette.cli import main as dmarionette
from dmarionette.scene.scene import load_scene

TRUTH = {"k": [330.0, 280.0, 310.0, 260.0, 350.0, 240.0], "k_d": [3.4, 2.6, 3.1, 2.2, 3.8, 2.9]}


def record(folder: Path, motion: str, seconds: float, seed: int) -> Path:
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    text = motion_scene_text(motion, seconds)
    scene = folder / f"{motion}.toml"
    scene.write_text(text)
    _, path = record_synthetic_session(load_scene(scene), text, TRUTH, seconds, folder / f"{motion}.mcap",
                                       noise_position=1e-4, noise_force=1e-2, seed=seed)
    return path


def keyframes(folder: Path, name: str, target: list[float], steps: int) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(tomli_w.dumps({
        "author": {"scene": "hanging", "duration": 0.4, "particle_count": 6},
        "bars": {"hand": {"knots": [0.0, 0.4], "free": ["x", "z"]}},
        "keyframes": [{"t": 0.35, "points": {"hand_left": target}}],
        "weights": {"smoothness": 0.001}, "solver": {"max_steps": steps, "position_tolerance": 0.005}}))
    return path


def timed(argv: list[str]) -> tuple[float, int]:
    """The command's wall time [s] and exit code (its printed tables and JSON dropped)."""
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        code = dmarionette(argv)
    return time.perf_counter() - start, code


def comparable(summary: dict) -> dict:
    """calibration.json without its timings and where it ran."""
    drop = {"seconds", "total_seconds", "ray_workers", "files"}

    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if k not in drop}
        return [strip(x) for x in v] if isinstance(v, list) else v

    return strip(summary)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--session-seconds", type=float, default=1.0)
    parser.add_argument("--max-steps", type=int, default=8, help="calibrate's solver steps per stage at most")
    parser.add_argument("--author-steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench-ray-fitting-"))
    sessions = [record(folder, "sway", args.session_seconds, 21), record(folder, "roll_yaw", args.session_seconds, 22)]
    files = [keyframes(folder, "near", [0.11, 0.3437, 0.05], args.author_steps),
             keyframes(folder, "far", [0.1, 0.45, 0.1], args.author_steps)]
    quiet = ["--quiet"]
    load_before = os.getloadavg()[0]
    results: dict = {f"{what} {mode}": [] for what in ("calibrate", "author") for mode in ("off", "local")}
    fit_s: dict = {"off": [], "local": []}
    summaries: dict = {}
    for repeat in range(args.repeats):
        for mode in ("off", "local"):
            out = folder / f"cal_{mode}_{repeat}"
            wall, code = timed(["calibrate", *map(str, sessions), "--params", "k,k_d", "--start", "k=300,k_d=3",
                                "--noise-position", "1e-4", "--known-noise", "--max-steps", str(args.max_steps),
                                "--no-picture", "--ray", mode, "--out", str(out), *quiet])
            summary = json.loads((out / "calibration.json").read_text())
            summaries.setdefault("calibrate", []).append(comparable(summary))
            results[f"calibrate {mode}"].append(wall)
            fit_s[mode].append(summary["solver"]["seconds"] + summary["uncertainty"]["jacobian"]["seconds"])
            print(f"calibrate --ray {mode}: exit {code}, {wall:.1f} s", flush=True)
        for mode in ("off", "local"):
            out = folder / f"author_{mode}_{repeat}"
            wall, code = timed(["author", *map(str, files), "--ray", mode, "--out", str(out), "--no-animation",
                                "--no-export", *quiet])
            results[f"author {mode}"].append(wall)
            print(f"author --ray {mode}: exit {code}, {wall:.1f} s", flush=True)
    load_after = os.getloadavg()[0]
    same = all(s == summaries["calibrate"][0] for s in summaries["calibrate"])
    print(f"\n# calibrate (2 sessions of {args.session_seconds:g} s, 12 constants, --max-steps {args.max_steps}) and "
          f"author (2 files) ({platform.node()}, {os.cpu_count()} CPUs, load {load_before:.1f} before, "
          f"{load_after:.1f} after; medians of {args.repeats}); calibrate's numbers equal in every run: {same}\n")
    print("| command | --ray off [s] | --ray local, 2 workers [s] |")
    print("| --- | ---: | ---: |")
    for what in ("calibrate", "author"):
        print(f"| {what} (whole command) | {statistics.median(results[f'{what} off']):.1f} | "
              f"{statistics.median(results[f'{what} local']):.1f} |")
    print(f"| calibrate: the fit's rollouts and solver | {statistics.median(fit_s['off']):.1f} | "
          f"{statistics.median(fit_s['local']):.1f} |")
    print(json.dumps({"wall_s": results, "fit_s": fit_s, "load": [load_before, load_after]}))


if __name__ == "__main__":
    main()
