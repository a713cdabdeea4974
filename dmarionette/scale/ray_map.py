"""Independent pieces of work across processes and machines with Ray (the optional ``scale`` extra).

:func:`imap_variants` runs ``fn(item)`` for every item and yields ``(index, result)`` as results
arrive; :func:`map_variants` returns them in order. Three places to run:

- ``ray="off"``: in this process, one item after another (no Ray needed);
- ``ray="local"``: an embedded Ray cluster on this machine, started here and shut down at the
  end: one worker per CPU (or ``workers``), loopback addresses only (Ray's services listen on
  127.0.0.1), no dashboard, no usage statistics, temporary files under ``/tmp/ray``;
- ``ray="ADDRESS"`` (``host:port`` or ``auto``): an existing Ray cluster; its nodes need
  dmarionette installed (the same version), as the functions are sent by reference.

If Ray is already initialised in this process (``ray.init`` called by the caller), that
connection is used whatever ``ray`` names (but ``"off"``) and left running.

Workers are Ray actors (``num_cpus=1``), one per worker, each reused for many items: ``setup()``
runs once when a worker starts (for the simulator: compile or load the Warp kernels, which then
stay loaded in the worker's process), and each item runs in a warm process. Items go to idle
workers through Ray's own ``ray.util.ActorPool``; nothing here schedules, queues or calls
remotely by itself. A worker that dies (its process killed, ``os._exit``, a lost node) is
restarted by Ray and the item it held is retried on it (``max_restarts`` / ``max_task_retries``
= ``retries``); past that, :class:`WorkerLostError`. An exception raised by ``fn`` itself is not
retried: it is raised here, as raised.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

__all__ = ["DEFAULT_RETRIES", "WorkerLostError", "check_ray_address", "connect_ray", "default_ray_mode",
           "imap_variants", "init_worker_warp", "map_variants", "ray_available", "ray_error", "ray_mode",
           "shutdown_ray", "start_local_ray"]

DEFAULT_RETRIES = 3
"""How many times a dead worker is restarted and its item retried before :class:`WorkerLostError`."""

RAY_TEMP_DIR = "/tmp/ray"
"""Where a local cluster keeps its session files, logs and sockets."""


class WorkerLostError(RuntimeError):
    """A Ray worker died more often than the retries allow; the results that arrived before stand."""


def ray_available() -> bool:
    """Whether Ray can be imported (the ``scale`` extra), without importing it."""
    from dmarionette.extras import missing_module

    return not missing_module("ray")


def default_ray_mode() -> str:
    """``"local"`` when Ray is installed, else ``"off"``."""
    return "local" if ray_available() else "off"


def _check_ray(mode: str) -> None:
    from dmarionette.extras import check_extras

    check_extras(f"--ray {mode}", ["scale"])


def _loopback_environment() -> None:
    """Set before Ray is first imported: its services bind the node's address, which is the loopback one
    only when Ray takes this machine for no cluster node (read once, at import); no usage statistics."""
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


def start_local_ray(workers: int | None = None) -> bool:
    """Starts an embedded local Ray cluster of ``workers`` CPUs (default: this machine's), on loopback.

    Returns:
        True if this call started it; False if Ray was already initialised here (left as it was).

    Raises:
        MissingExtraError: Ray is not installed (names the ``scale`` extra).
        RuntimeError: the cluster's services did not come up on a loopback address.
    """
    _check_ray("local")
    _loopback_environment()
    import ray

    if ray.is_initialized():
        return False
    cpus = workers if workers is not None else (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                                else os.cpu_count() or 1)
    with warnings.catch_warnings():
        # JAX, when imported, warns of every fork; Ray's services are started by fork + exec (no deadlock)
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        ray.init(num_cpus=cpus, include_dashboard=False, _node_ip_address="127.0.0.1", _temp_dir=RAY_TEMP_DIR,
                 log_to_driver=False, configure_logging=False)
    address = ray.get_runtime_context().gcs_address
    if not (address.startswith("127.") or address.startswith("localhost")):
        ray.shutdown()
        raise RuntimeError(f"the local Ray cluster came up at {address}, not on loopback: Ray was imported before "
                           "dmarionette.scale could keep it there; set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 in the "
                           "environment")
    return True


def connect_ray(mode: str, workers: int | None = None) -> bool:
    """Ray initialised for ``mode`` (``"local"`` or a cluster address), before any work is handed to it.

    Returns:
        True if this call started the local cluster or opened the connection (the caller then calls
        :func:`shutdown_ray`); False if Ray was already initialised here (left as it is).

    Raises:
        MissingExtraError: Ray is not installed (names the ``scale`` extra).
        ValueError: no Ray cluster answers at the address (names it).
    """
    if mode == "off":
        raise ValueError("connect_ray: mode 'off' runs in this process; expected 'local' or a cluster address")
    _check_ray(mode)
    if mode == "local":
        _loopback_environment()
    import ray

    if ray.is_initialized():
        return False
    if mode == "local":
        return start_local_ray(workers)
    check_ray_address(mode)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        ray.init(address=mode, log_to_driver=False, configure_logging=False)
    except (ConnectionError, ValueError, RuntimeError) as error:
        raise ValueError(f"--ray: got {mode!r}; could not connect to a Ray cluster there ({error}); expected "
                         "'local', 'off' or the address of a running cluster (host:port or auto)") from None
    return True


def shutdown_ray() -> None:
    """Shuts down this process's Ray connection (and the local cluster it started), if any."""
    from dmarionette.extras import missing_module

    if missing_module("ray"):
        return
    import ray

    if ray.is_initialized():
        _end_autoscaler_monitor()
        ray.shutdown()


AUTOSCALER_MONITOR = b"autoscaler/_private/monitor.py"
"""The script of Ray's autoscaler monitor, a process a local cluster's head starts (Ray 2.x)."""


def _end_autoscaler_monitor() -> None:
    """SIGKILLs the autoscaler monitor of the local cluster this process started (its child), before
    ``ray.shutdown``. Shutdown stops the GCS, then sends the monitor SIGTERM, which the monitor answers by
    reporting to the GCS, now gone: it waits out shutdown's 1 s grace and is killed anyway (measured: 1.0 s
    of a 1.6 s shutdown, ``benchmarks/bench_ray_interrupt.py``). A single-node local cluster has nothing to
    scale. Found by ``/proc`` (Linux; elsewhere nothing is done); Ray reaps it and skips it."""
    import signal

    me = str(os.getpid()).encode()
    try:
        entries = [e for e in os.listdir("/proc") if e.isdigit()]
    except OSError:
        return
    for entry in entries:
        try:
            with open(f"/proc/{entry}/stat", "rb") as stat:
                parent = stat.read().rsplit(b")", 1)[1].split()[1]
            if parent != me:
                continue
            with open(f"/proc/{entry}/cmdline", "rb") as cmdline:
                if AUTOSCALER_MONITOR not in cmdline.read():
                    continue
            os.kill(int(entry), signal.SIGKILL)
        except (OSError, IndexError):
            continue


def check_ray_address(mode: str, timeout: float = 5.0) -> None:
    """Refuses an address that is not ``host:port`` (or ``auto``), or where nothing accepts a TCP connection
    within ``timeout`` seconds (``ray.init`` would wait for it for ever).

    Raises:
        ValueError: naming the address and what was expected.
    """
    import socket

    if mode == "auto":
        return  # Ray finds the cluster this machine runs, or says there is none
    host, colon, port = mode.rpartition(":")
    expected = "'local', 'off' or the address of a running Ray cluster (host:port, or auto)"
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--ray: got {mode!r}; expected {expected}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as error:
        raise ValueError(f"--ray: got {mode!r}; nothing accepts a connection there "
                         f"({getattr(error, 'strerror', None) or error}); expected {expected}") from None


def ray_error(error: BaseException, retries: int) -> BaseException:
    """What to raise for an error Ray reported: the exception ``fn`` itself raised (a ``RayTaskError``'s
    cause, not retried), or :class:`WorkerLostError` for a worker that died more than ``retries`` times."""
    from ray.exceptions import RayTaskError

    if isinstance(error, RayTaskError):  # fn raised: its own exception, not a lost worker
        cause = getattr(error, "cause", None)
        return cause if isinstance(cause, BaseException) else RuntimeError(str(error))
    lines = str(error).strip().splitlines()  # Ray's own first line says why; the rest is actor details
    return WorkerLostError(f"a Ray worker died more than {retries} times (restarted and its item retried each "
                           f"time); the results that arrived before stand: {lines[0] if lines else type(error).__name__}")


def init_worker_warp() -> None:
    """Warp started in this process as the command line starts it (no banner, no CUDA-driver notice); a
    worker's ``setup``. Does nothing more once Warp runs."""
    import warp as wp

    from dmarionette.first_run import init_warp

    wp.config.log_level = wp.LOG_WARNING
    init_warp()


def ray_mode(text: str | None) -> str:
    """The mode a ``--ray`` value names: ``"off"``, ``"local"`` or a cluster address, which is checked
    here (:func:`check_ray_address`); None: :func:`default_ray_mode`.

    Raises:
        ValueError: a malformed address or one where nothing answers (names ``--ray``).
    """
    if text is None:
        return default_ray_mode()
    mode = text.strip()
    if mode not in ("off", "local"):
        check_ray_address(mode)
    return mode


def _worker_class(retries: int):
    import ray

    @ray.remote(num_cpus=1, max_restarts=retries, max_task_retries=retries)
    class VariantWorker:
        """One worker process: ``setup()`` once, then ``fn(item)`` per item (kept warm in between)."""

        def __init__(self, fn: Callable[[Any], Any], setup: Callable[[], None] | None):
            self.fn = fn
            if setup is not None:
                setup()

        def run(self, index: int, item: Any) -> tuple[int, Any]:
            return index, self.fn(item)

        def pid(self) -> int:
            return os.getpid()

    return VariantWorker


def imap_variants(fn: Callable[[Any], Any], items: Iterable[Any], *, ray: str = "off", workers: int | None = None,
                  setup: Callable[[], None] | None = None, retries: int = DEFAULT_RETRIES) -> Iterator[tuple[int, Any]]:
    """``(index, fn(item))`` for every item, as the results arrive (in order with ``ray="off"``).

    Args:
        fn: a function of one item (picklable by reference, i.e. defined at a module's top level,
            for Ray); it runs in a worker process with Ray.
        items: the work (picklable for Ray).
        ray: ``"off"``, ``"local"`` or a cluster address (see the module doc).
        workers: how many workers (default: one per CPU of the cluster); never more than items.
        setup: run once per worker before its first item (in this process with ``ray="off"``).
        retries: restarts of a dead worker, and retries of the item it held.

    Yields:
        ``(index, result)``, ``index`` the item's position in ``items``.

    Raises:
        MissingExtraError: ``ray`` is not ``"off"`` and Ray is not installed.
        WorkerLostError: a worker died more than ``retries`` times.
    """
    items = list(items)
    if workers is not None and workers < 1:
        raise ValueError(f"workers: got {workers}; expected an integer >= 1")
    if ray == "off":
        if items and setup is not None:
            setup()
        for index, item in enumerate(items):
            yield index, fn(item)
        return
    if not items:
        return
    started = connect_ray(ray, workers)
    import ray as ray_module
    from ray.exceptions import RayActorError, RayTaskError
    from ray.util import ActorPool

    actors: list = []
    try:
        cpus = int(ray_module.cluster_resources().get("CPU", 1))
        count = max(1, min(workers or cpus, cpus, len(items)))
        worker = _worker_class(retries)
        actors = [worker.remote(fn, setup) for _ in range(count)]
        pool = ActorPool(actors)
        for index, item in enumerate(items):
            pool.submit(lambda actor, job: actor.run.remote(*job), (index, item))
        while pool.has_next():
            try:
                yield pool.get_next_unordered()
            except (RayTaskError, RayActorError) as error:
                raise ray_error(error, retries) from None
    finally:
        for actor in actors:
            try:
                ray_module.kill(actor)
            except Exception:  # noqa: BLE001 - already gone with its cluster
                pass
        if started:
            shutdown_ray()


def map_variants(fn: Callable[[Any], Any], items: Sequence[Any], *, ray: str = "off", workers: int | None = None,
                 setup: Callable[[], None] | None = None, retries: int = DEFAULT_RETRIES,
                 on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """``[fn(item) for item in items]``, across Ray workers (see :func:`imap_variants` for the arguments).

    Args:
        on_result: called with ``(index, result)`` as each result arrives (to write it at once).

    Returns:
        The results, in the order of ``items``.
    """
    results: list[Any] = [None] * len(items)
    for index, result in imap_variants(fn, items, ray=ray, workers=workers, setup=setup, retries=retries):
        results[index] = result
        if on_result is not None:
            on_result(index, result)
    return results
