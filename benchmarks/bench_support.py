"""Helpers shared by the benchmark scripts (run as ``python benchmarks/bench_x.py``, so this
folder is on ``sys.path``)."""

from __future__ import annotations

import statistics
import time
from typing import Any

import warp as wp

__all__ = ["CLOCKS", "add_clock_flag", "capture_graph", "graph_cost", "median_spread", "time_forward_backward",
           "time_interleaved"]

CLOCKS = {"wall": time.perf_counter, "cpu": time.thread_time}
"""What ``--clock`` names: the wall clock, or the calling thread's CPU time (which leaves out the
time the thread waited for a core on a machine shared with other work)."""


def add_clock_flag(parser, help: str = "wall: wall-clock time (default); cpu: the thread's CPU time "
                                       "(shared machines)") -> None:
    """Adds ``--clock wall|cpu`` to ``parser``; ``CLOCKS[args.clock]`` is the clock it names."""
    parser.add_argument("--clock", choices=tuple(CLOCKS), default="wall", help=help)


def median_spread(times: list[float]) -> tuple[float, float]:
    """The median of ``times`` and their relative spread, ``(max - min) / median``."""
    median = statistics.median(times)
    return median, (max(times) - min(times)) / median


def capture_graph(fn, count: int, device=None):
    """A Warp graph of ``count`` calls of ``fn()`` on ``device`` (default: Warp's), captured after
    one call outside it (which loads the modules: no compiling while capturing)."""
    fn()
    with wp.ScopedCapture(device=device) as capture:
        for _ in range(count):
            fn()
    return capture.graph


def graph_cost(fn, count: int, repeats: int, least: bool = False, clock=time.thread_time, device=None) -> float:
    """Time [s] of one ``fn()`` replayed from a Warp graph of ``count`` calls (:func:`capture_graph`),
    over ``repeats`` replays: their median, or with ``least`` the least. ``clock``: the thread's CPU
    time (default) or another of :data:`CLOCKS`."""
    graph = capture_graph(fn, count, device)
    times = []
    for _ in range(repeats):
        start = clock()
        wp.capture_launch(graph)
        times.append(clock() - start)
    return (min(times) if least else statistics.median(times)) / count


def time_interleaved(calls, repeats: int) -> list[list[float]]:
    """Wall times [s] of ``repeats`` rounds of ``calls`` (functions of no arguments), called one after
    another in each round: one list of ``repeats`` times per call, in the order of ``calls``."""
    times = [[] for _ in calls]
    for _ in range(repeats):
        for call, out in zip(calls, times):
            start = time.perf_counter()
            call()
            out.append(time.perf_counter() - start)
    return times


def time_forward_backward(engine: Any, inputs: Any, cot: dict, repeats: int) -> tuple[list[float], list[float]]:
    """Wall times [s] of ``repeats`` alternating ``engine.forward(inputs)`` / ``engine.backward(cot)`` calls.

    Args:
        engine: A gradient engine with ``forward`` and ``backward`` (e.g. ``MarionetteGradient``),
            already warmed up (kernels compiled, graphs captured).
        inputs: What ``forward`` takes.
        cot: The output cotangents ``backward`` takes.
        repeats: Number of forward/backward pairs.

    Returns:
        ``(forward, backward)``: one time per repeat each.
    """
    forward, backward = time_interleaved([lambda: engine.forward(inputs), lambda: engine.backward(cot)], repeats)
    return forward, backward
