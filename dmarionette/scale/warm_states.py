"""Work that keeps state between calls (a calibration session's model and compiled kernels), on Ray.

:class:`WarmStates` holds one state per item, built by ``build(item)`` where it runs, and calls
``fn(state, request)`` on every item's state at once (:meth:`WarmStates.map`), as often as the
caller likes; the states stay built (warm) between the calls. Where they live:

- ``ray="off"``: in this process; the items' calls one after another;
- ``ray="local"`` or a cluster address (:mod:`dmarionette.scale.ray_map`): on Ray actors, one per
  worker (``num_cpus=1``; at most one per CPU and one per item), item ``i`` on worker
  ``i % workers``; the workers run their items' calls in parallel, each worker its own items one
  after another.

A state is built on the first call that needs it (in the worker, so an error in ``build`` is
raised here as itself). A worker that dies is restarted by Ray and the call it held retried on it
(``max_restarts`` = ``max_task_retries`` = ``retries``); the restarted worker builds its states
again, so a request must carry everything that decides its answer (a state must not remember a
previous request's settings in a way that changes later answers). Past the retries,
:class:`dmarionette.scale.WorkerLostError`. An exception raised by ``build`` or ``fn`` is raised
here, as raised, and not retried.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

from .ray_map import DEFAULT_RETRIES, connect_ray, ray_error, shutdown_ray

__all__ = ["WarmStates"]


def _state_worker_class(retries: int):
    import ray

    @ray.remote(num_cpus=1, max_restarts=retries, max_task_retries=retries)
    class StateWorker:
        """One worker process holding the states of its items (built on first use, kept warm)."""

        def __init__(self, build: Callable[[Any], Any], setup: Callable[[], None] | None):
            self.build, self.items, self.states = build, None, {}
            if setup is not None:
                setup()

        def run(self, fn: Callable[[Any, Any], Any], items: list,
                requests: list[tuple[int, Any]]) -> list[tuple[int, Any]]:
            # items: [a reference to this worker's {index: item}], fetched once. It comes with every call, not to the
            # constructor: Ray cannot restart an actor whose constructor arguments lie in its object store (ray #53727)
            if self.items is None:
                self.items = ray.get(items[0])
            out = []
            for index, request in requests:
                if index not in self.states:
                    self.states[index] = self.build(self.items[index])
                out.append((index, fn(self.states[index], request)))
            return out

        def pid(self) -> int:
            return os.getpid()

    return StateWorker


class WarmStates:
    """One state per item, kept warm in this process or on Ray workers (see the module doc).

    Args:
        build: ``build(item) -> state`` (importable by reference for Ray: a module-level function
            or a ``functools.partial`` of one).
        items: what the states are built from (picklable for Ray).
        ray: ``"off"``, ``"local"`` or a cluster address.
        workers: Ray workers at most (default one per CPU of the cluster); never more than items.
        setup: run once per worker process when it starts (with ``"off"``: once, here).
        retries: restarts of a dead worker, and retries of the call it held.

    Use as a context manager (or call :meth:`close`): it kills its workers and shuts down a Ray
    connection it opened.

    Raises:
        MissingExtraError: ``ray`` is not ``"off"`` and Ray is not installed.
        ValueError: no Ray cluster answers at the address.
    """

    def __init__(self, build: Callable[[Any], Any], items: Sequence[Any], *, ray: str = "off",
                 workers: int | None = None, setup: Callable[[], None] | None = None,
                 retries: int = DEFAULT_RETRIES):
        if workers is not None and workers < 1:
            raise ValueError(f"workers: got {workers}; expected an integer >= 1")
        self.items, self.mode, self.retries = list(items), ray, retries
        self._build, self._states, self._actors, self._shares, self._started = build, {}, [], [], False
        self._refs: list = []
        if ray == "off":
            if self.items and setup is not None:
                setup()
            return
        self._started = connect_ray(ray, workers)
        import ray as ray_module

        cpus = int(ray_module.cluster_resources().get("CPU", 1))
        count = max(1, min(workers or cpus, cpus, len(self.items)))
        worker = _state_worker_class(retries)
        self._shares = [list(range(k, len(self.items), count)) for k in range(count)]
        self._refs = [ray_module.put({i: self.items[i] for i in share}) for share in self._shares]
        self._actors = [worker.remote(build, setup) for _ in self._refs]

    @property
    def worker_count(self) -> int:
        """Ray workers holding the states (0 in this process)."""
        return len(self._actors)

    def map(self, fn: Callable[[Any, Any], Any], requests: Sequence[Any]) -> list[Any]:
        """``[fn(state_i, requests[i]) for every item i]``, the workers in parallel.

        Args:
            fn: a function of a state and a request (importable by reference for Ray).
            requests: one per item, in the order of the items (picklable for Ray).

        Returns:
            The results, in the order of the items.
        """
        if len(requests) != len(self.items):
            raise ValueError(f"requests: got {len(requests)}; expected one per item ({len(self.items)})")
        if self.mode == "off":
            out = []
            for index, request in enumerate(requests):
                if index not in self._states:
                    self._states[index] = self._build(self.items[index])
                out.append(fn(self._states[index], request))
            return out
        import ray as ray_module
        from ray.exceptions import RayActorError, RayTaskError

        futures = [actor.run.remote(fn, [ref], [(i, requests[i]) for i in share])
                   for actor, ref, share in zip(self._actors, self._refs, self._shares)]
        results: list[Any] = [None] * len(self.items)
        try:
            for answers in ray_module.get(futures):
                for index, result in answers:
                    results[index] = result
        except (RayTaskError, RayActorError) as error:
            raise ray_error(error, self.retries) from None
        return results

    def pids(self) -> list[int]:
        """The workers' process ids (this process's with ``"off"``)."""
        if self.mode == "off":
            return [os.getpid()]
        import ray as ray_module

        return ray_module.get([actor.pid.remote() for actor in self._actors])

    def close(self) -> None:
        """Kills the workers, and shuts down the Ray connection this object opened."""
        self._states.clear()
        if not self._actors and not self._started:
            return
        import ray as ray_module

        for actor in self._actors:
            try:
                ray_module.kill(actor)
            except Exception:  # noqa: BLE001 - already gone with its cluster
                pass
        self._actors, self._refs = [], []
        if self._started:
            self._started = False
            shutdown_ray()

    def __enter__(self) -> WarmStates:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
