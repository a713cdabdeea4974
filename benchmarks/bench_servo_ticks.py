"""How well the 1 kHz servo loop keeps time, with and without a busy Python thread.

Runs :class:`dmarionette.hw.ServoLoop` on the simulated device (a spring towards the
workspace centre as the physics) for a few seconds in each of these set-ups and prints
the tick statistics:

1. idle: the loop alone in this process;
2. busy thread, GIL switch interval left at Python's default (5 ms);
3. busy thread, the loop's lowered switch interval (0.2 ms, the default of ServoLoop);
4. busy thread in this process, the loop in a separate process (multiprocessing, spawn);
5. busy thread, 0.2 ms switch interval, servo thread under SCHED_FIFO (when allowed).

The busy thread is a pure-Python loop (it holds the GIL between forced switches), the
kind of work a viewer, a recorder or a 30 Hz puppet step in Python would be.

    .venv/bin/python benchmarks/bench_servo_ticks.py [--duration 3]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import threading

import numpy as np

from dmarionette.hw import HapticDeviceSimulated, SafetyConfig, ServoLoop, ServoStatistics


def spring(sample, t):
    return -100.0 * sample.position  # N, towards the device origin


def circle(t):
    return np.array([0.03 * np.cos(2.0 * t), 0.02 * np.sin(2.0 * t), 0.0])


def run_loop(duration: float, switch_interval: float | None, realtime: int | None = None) -> ServoStatistics:
    loop = ServoLoop(HapticDeviceSimulated(circle), spring, safety=SafetyConfig(ramp_time=0.2),
                     switch_interval=switch_interval, realtime_priority=realtime)
    return loop.run(duration)


def _child(duration: float, queue) -> None:
    queue.put(run_loop(duration, 0.0002))


class BusyThread:
    """A thread that spins in pure Python until stopped."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self.iterations = 0
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            sum(range(2000))
            self.iterations += 1

    def __enter__(self) -> BusyThread:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def report(name: str, s: ServoStatistics, extra: str = "") -> None:
    late = s.lateness
    over = [int(np.sum(late > x)) for x in (0.0005, 0.001, 0.005)]
    print(f"{name:<44} ticks {s.tick_count:5d}  p50 {s.lateness_p50 * 1e6:7.1f} us  p99 {s.lateness_p99 * 1e6:7.1f} us"
          f"  max {s.lateness_max * 1e6:8.1f} us  >0.5ms {over[0]:4d}  >1ms {over[1]:4d}  >5ms {over[2]:3d}"
          f"  missed {s.missed_ticks:4d}  stale {s.stale_ticks:4d}  trips {s.watchdog_trips}{extra}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per set-up")
    args = parser.parse_args(argv)
    d = args.duration
    print(f"Python {platform.python_version()}, {os.cpu_count()} CPUs, {platform.platform()}; {d:g} s per set-up; "
          "lateness = tick start minus its deadline")
    report("1. idle, loop in a thread", run_loop(d, 0.0002))
    with BusyThread() as busy:
        s = run_loop(d, None)
    report("2. busy thread, switch interval 5 ms", s, f"  (busy iterations {busy.iterations})")
    with BusyThread() as busy:
        s = run_loop(d, 0.0002)
    report("3. busy thread, switch interval 0.2 ms", s, f"  (busy iterations {busy.iterations})")
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    with BusyThread() as busy:
        child = ctx.Process(target=_child, args=(d, queue))
        child.start()
        s = queue.get()
        child.join()
    report("4. busy thread here, loop in another process", s, f"  (busy iterations {busy.iterations})")
    with BusyThread() as busy:
        s = run_loop(d, 0.0002, realtime=10)
    report("5. busy thread, 0.2 ms, SCHED_FIFO" + ("" if s.realtime else " (refused)"), s,
           f"  (busy iterations {busy.iterations})")


if __name__ == "__main__":
    main()
