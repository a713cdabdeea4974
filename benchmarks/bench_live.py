"""The servo loop with the marionette running, per physics mode: lateness, missed ticks, trips, freshness, latency.

Run:  python benchmarks/bench_live.py [--seconds 60] [--repeats 1] [--modes thread,process,shm,shm-nort]
                                      [--json FILE]

The simulated device follows the ``hanging`` scene's main bar (tabulated beforehand, so a
read costs what a real device's does, not a spline evaluation); the marionette (optimised
kernels) runs

* ``thread``: in the servo loop's worker thread (same process, shares the GIL);
* ``process``: in a child process, one pipe round trip per tick;
* ``shm``: in a child process over shared memory, servo thread and child pinned to the first
  two CPUs, both asking for SCHED_FIFO 10 (the default of ``dmarionette live``);
* ``shm-nort``: the same without real-time priority (what a user without the right gets);
* ``thread-2dev``: as ``thread``, with two simulated devices, one on ``main`` and one on
  ``hand`` (both read and written every tick by the one servo loop; not in the default list).

Per run: tick lateness p50/p99/max (tick start minus deadline), missed ticks (deadlines
skipped), watchdog trips, the fraction of ticks run that wrote a force computed for them
(fresh; the rest held the last one), string steps run per 1 kHz deadline (missed deadlines
count against it), and the device-to-force latency (device read to the force written,
p50/p99). With ``--repeats`` > 1 each figure is the median over
the runs (modes interleaved, so load drifts hit all alike), with the range. The load average
(1 min) is printed before each run. Targets (issue 5): p99 lateness <= 0.5 ms and no watchdog
trips, on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.live.run import run_live  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

MODES = {"thread": {"physics": "thread"}, "process": {"physics": "process"},
         "shm": {"physics": "shm"}, "shm-nort": {"physics": "shm", "realtime": False},
         "thread-2dev": {"physics": "thread", "device": ["simulated", "simulated"], "bar": ["main", "hand"]}}
COLUMNS = [("lateness_p50_us", "p50 [us]"), ("lateness_p99_us", "p99 [us]"), ("lateness_max_us", "max [us]"),
           ("missed", "missed"), ("watchdog_trips", "trips"), ("fresh_percent", "fresh [%]"),
           ("steps_percent", "steps/deadlines [%]"),
           ("latency_p50_us", "dev->force p50 [us]"), ("latency_p99_us", "dev->force p99 [us]")]


def run_once(model: MarionetteModel, mode: str, seconds: float) -> dict:
    load = os.getloadavg()[0]
    before = os.times()
    stats, summary = run_live(model, duration=seconds, force_scale=0.3, **MODES[mode])
    after = os.times()
    servo_cpu = (after.user + after.system) - (before.user + before.system)
    latency = summary.get("device_to_force_us", {"p50": float("nan"), "p99": float("nan")})
    return {"mode": mode, "load_1min": load, "ticks": stats.tick_count,
            "lateness_p50_us": stats.lateness_p50 * 1e6, "lateness_p99_us": stats.lateness_p99 * 1e6,
            "lateness_max_us": stats.lateness_max * 1e6, "missed": stats.missed_ticks,
            "watchdog_trips": stats.watchdog_trips, "fresh_percent": 100.0 * stats.fresh_fraction,
            "latency_p50_us": latency["p50"], "latency_p99_us": latency["p99"],
            "string_steps": summary["string_steps"],
            # CPU time of this process (servo thread, and the physics in thread mode) and of the
            # shared-memory physics process (which includes its start-up), per second of run [%].
            "servo_process_cpu_percent": 100.0 * servo_cpu / seconds,
            "physics_process_cpu_percent": 100.0 * summary.get("physics_cpu_seconds", float("nan")) / seconds,
            "steps_percent": 100.0 * summary["string_steps"] / (seconds * model.scene.string_hz),
            "notes": list(stats.notes)}


def table(runs: list[dict], modes: list[str]) -> str:
    lines = ["| mode | runs | load (1 min) | " + " | ".join(h for _, h in COLUMNS) + " |",
             "| --- | --- | --- | " + " | ".join("---" for _ in COLUMNS) + " |"]
    for mode in modes:
        rows = [r for r in runs if r["mode"] == mode]
        loads = [r["load_1min"] for r in rows]
        cells = []
        for key, _ in COLUMNS:
            values = np.array([r[key] for r in rows], dtype=float)
            median = float(np.median(values))
            digits = 1 if key.endswith("percent") else 0
            text = f"{median:.{digits}f}"
            if len(values) > 1:
                text += f" ({values.min():.{digits}f}-{values.max():.{digits}f})"
            cells.append(text)
        lines.append(f"| {mode} | {len(rows)} | {min(loads):.1f}-{max(loads):.1f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="seconds per run (default 60)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per mode (default 1)")
    parser.add_argument("--modes", default="thread,process,shm,shm-nort",
                        help=f"comma-separated, from {', '.join(MODES)}")
    parser.add_argument("--own-process", action="store_true", help="older spelling of --modes process")
    parser.add_argument("--json", default=None, help="also write every run to this JSON file")
    args = parser.parse_args()
    modes = ["process"] if args.own_process else [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        parser.error(f"--modes: got {unknown}; expected some of {', '.join(MODES)}")
    model = MarionetteModel(dm.load_scene("hanging"), optimization_level=2)
    runs = []
    for k in range(args.repeats):
        for mode in modes:
            run = run_once(model, mode, args.seconds)
            runs.append(run)
            print(f"[{k + 1}/{args.repeats}] {mode}: load {run['load_1min']:.2f}; p99 {run['lateness_p99_us']:.0f} us, "
                  f"missed {run['missed']}, trips {run['watchdog_trips']}, fresh {run['fresh_percent']:.1f} %, "
                  f"latency p50 {run['latency_p50_us']:.0f} us; "
                  f"CPU this process {run['servo_process_cpu_percent']:.0f} %, "
                  f"physics process {run['physics_process_cpu_percent']:.0f} %; {'; '.join(run['notes'])}", flush=True)
    print(f"\n# Live servo loop — {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; "
          f"'hanging', simulated device, {args.seconds:g} s per run, medians (range)\n")
    print(table(runs, modes))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f, indent=2)


if __name__ == "__main__":
    main()
