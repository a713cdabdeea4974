"""Chunks of launches captured once as a Warp graph and replayed (CPU graph capture, Warp >= 1.19;
a CUDA graph on a GPU): the one place where a rollout, the gradient engine, the tape and the live
loop turn many steps into one native call.

Two pieces, used together or apart:

- :func:`ping_pong` runs ``count`` steps alternating between two states and leaves the last
  one in the first state (one copy when ``count`` is odd), so that a captured chunk starts
  and ends in the same arrays and can be replayed;
- :class:`CapturedChunk` captures a callable's launches as a graph after one eager warm-up
  pass (which loads every module: Warp cannot compile while capturing) and replays them, or
  runs them one by one when capture is off (same numbers, slower).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import warp as wp

__all__ = ["AssignableState", "CapturedChunk", "ping_pong"]


class AssignableState(Protocol):
    def assign(self, other: Any) -> None: ...


def ping_pong(step: Callable[[int, Any, Any], None], state: AssignableState, spare: AssignableState,
              count: int) -> None:
    """Runs ``step(k, state_in, state_out)`` for ``k = 0 .. count-1`` between ``state`` and
    ``spare`` (``state -> spare -> state ...``); the result ends in ``state``."""
    pair = (state, spare)
    for k in range(count):
        step(k, pair[k % 2], pair[(k + 1) % 2])
    if count % 2 == 1:
        state.assign(spare)


class CapturedChunk:
    """The launches of ``launch()`` as one replayable graph.

    Args:
        launch: issues the chunk's launches (and nothing that must run on the host each time).
        device: the Warp device the launches run on.
        capture: capture a graph (default); False runs ``launch()`` at every :meth:`run`.
        warm_up: called once before capture to load every module (default: ``launch`` itself,
            eagerly; pass your own when an eager chunk would change state the caller keeps).
    """

    def __init__(self, launch: Callable[[], None], device, *, capture: bool = True,
                 warm_up: Callable[[], None] | None = None):
        self.launch = launch
        self.device = wp.get_device(device)
        self.graph = None
        if capture:
            (warm_up or launch)()
            with wp.ScopedCapture(device=self.device) as captured:
                launch()
            self.graph = captured.graph

    def run(self) -> None:
        """Replays the captured launches (or issues them, without capture)."""
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            self.launch()
