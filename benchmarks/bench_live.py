"""The servo loop with the marionette running: tick lateness, missed ticks, device-to-force latency.

Run:  python benchmarks/bench_live.py [--seconds 60] [--own-process]

The simulated device follows the ``hanging`` scene's main bar; the marionette (optimised
kernels) runs in the servo loop's worker thread, or with ``--own-process`` in a child
process. Targets (issue 5): p99 lateness <= 0.5 ms and no watchdog trips, on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.live import run_live  # noqa: E402
from dmarionette.marionette import MarionetteModel  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--own-process", action="store_true")
    args = parser.parse_args()
    model = MarionetteModel(dm.load_scene("hanging"), optimization_level=2)
    stats, summary = run_live(model, duration=args.seconds, process=args.own_process, force_scale=0.3)
    print(f"# Live servo loop — {platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f}; 'hanging', simulated device, {args.seconds:g} s")
    print(stats.summary())
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
