"""What the live view costs the servo loop: tick lateness and string steps with and without it.

Run:  python benchmarks/bench_live_view.py [--seconds 20] [--rounds 3] [--rate 40]

Modes, interleaved round by round (their order rotating) so that a change of machine load
hits all of them alike:

* ``none``: no view (``dmarionette live --view none``);
* ``server``: the browser view's server running and fed (``--view browser``), no browser connected;
* ``client``: the same with one websocket client connected that receives and decodes every
  frame as a browser would (tests/support/live_view_client.py, in this process, so its decoding counts
  in ``cpu_percent``; a real browser renders in its own process, which on a 2-core machine
  also takes CPU from the loop: not measured here).

Columns: tick lateness p50/p99/max [us], missed / stale ticks and watchdog trips per run,
string steps per second (1000 = every tick ran the physics), view frames sent and received
per second, this process's CPU time per wall second [% of one core; the servo thread's
busy-wait is part of it] and the view thread's wall time per frame in ``update`` [ms].

Also: the physics thread's cost of taking one snapshot (``LiveViewPublisher.publish``).
The simulated device follows the ``hanging`` scene's main bar; optimised kernels; the
physics in the servo loop's worker thread. Prints a markdown table (medians over rounds).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.live.run import LiveMarionette, run_live  # noqa: E402
from dmarionette.live.view import LiveViewGeometry, LiveViewPublisher, SnapshotBuffer  # noqa: E402
from dmarionette.live.view_viser import LiveViewServer  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support
from tests.support.live_view_client import ViewClient  # noqa: E402


def run_mode(model, mode: str, seconds: float, rate: float) -> dict:
    view = client = None
    if mode != "none":
        view = LiveViewServer(LiveViewGeometry.from_model(model, "main"), host="127.0.0.1", port=0, rate_hz=rate)
        if mode == "client":
            client = ViewClient(view.url)
    cpu = time.process_time()
    try:
        stats, summary = run_live(model, duration=seconds, force_scale=0.3, view=view)
    finally:
        cpu = time.process_time() - cpu
        if view is not None:
            view.close()
        received = len(client.updates("/strings", "points")) if client is not None else 0
        if client is not None:
            client.close()
    return {"p50_us": stats.lateness_p50 * 1e6, "p99_us": stats.lateness_p99 * 1e6, "max_us": stats.lateness_max * 1e6,
            "missed": stats.missed_ticks, "stale": stats.stale_ticks, "trips": stats.watchdog_trips,
            "steps_per_s": summary["string_steps"] / seconds,
            "frames_per_s": (view.frames_sent / seconds) if view is not None else 0.0,
            "received_per_s": received / seconds,
            "cpu_percent": 100.0 * cpu / seconds,
            "update_ms": (1e3 * view.update_seconds / max(view.frames_sent, 1)) if view is not None else 0.0}


def publish_cost(model, repeats: int = 2000) -> float:
    """Median wall time of one snapshot copy in the physics thread [s]."""
    live = LiveMarionette(model)
    n_bar = model.bar_count
    publisher = LiveViewPublisher(SnapshotBuffer(), rate_hz=1e9)
    zeros, rot = np.zeros((n_bar, 3)), np.tile(np.eye(3), (n_bar, 1, 1))
    live.tick = 1
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        publisher.publish(live, zeros, rot, zeros)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rate", type=float, default=40.0, help="view rate [Hz]")
    args = parser.parse_args()
    model = MarionetteModel(dm.load_scene("hanging"), optimization_level=2)
    modes = ["none", "server", "client"]
    rows: dict[str, list[dict]] = {m: [] for m in modes}
    loads = []
    for r in range(args.rounds):
        for mode in modes[r % 3:] + modes[:r % 3]:  # the order rotates, so no mode always runs first
            loads.append(os.getloadavg()[0])
            rows[mode].append(run_mode(model, mode, args.seconds, args.rate))
            print(f"round {r + 1} {mode}: {rows[mode][-1]}", file=sys.stderr, flush=True)
    print(f"# Live view cost — {platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{min(loads):.2f}-{max(loads):.2f}; 'hanging', simulated device, {args.seconds:g} s x {args.rounds} "
          f"rounds, view {args.rate:g} Hz; medians over rounds\n")
    keys = ["p50_us", "p99_us", "max_us", "missed", "stale", "trips", "steps_per_s", "frames_per_s", "received_per_s",
            "cpu_percent", "update_ms"]
    print("| view | " + " | ".join(keys) + " |")
    print("|" + "---|" * (len(keys) + 1))
    for mode in modes:
        med = {k: float(np.median([row[k] for row in rows[mode]])) for k in keys}
        cells = [f"{med[k]:.2f}" if k == "update_ms" else f"{med[k]:.0f}" for k in keys]
        print(f"| {mode} | " + " | ".join(cells) + " |")
    print(f"\none snapshot in the physics thread: {publish_cost(model) * 1e6:.1f} us (median)")


if __name__ == "__main__":
    main()
