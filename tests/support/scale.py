"""What the Ray tests share: functions a worker runs (importable there by reference: Ray puts the
driver's working folder on its workers' path), and a watcher that SIGKILLs a worker mid-task."""

import os
import signal
import threading
import time
from pathlib import Path


def square_and_pid(x: int) -> tuple[int, int]:
    """``(x * x, the worker's pid)``."""
    return x * x, os.getpid()


def die_once(marker: str, x: int) -> tuple[int, int]:
    """Ends its process (as a crash does) the first time any worker calls it, then squares as above."""
    path = Path(marker)
    if not path.exists():
        path.write_text(str(os.getpid()))
        os._exit(1)
    return square_and_pid(x)


def always_die(x: int) -> int:
    os._exit(1)


def refuse_three(x: int) -> int:
    if x == 3:
        raise ValueError(f"item {x} is refused")
    return x


def _ppid(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return -1


def _title(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


class KillWorkerMidTask:
    """A thread that SIGKILLs the first of this process's Ray workers (a grandchild: driver -> raylet ->
    worker) seen running a task whose title starts with ``title``, within ``timeout`` seconds; the
    first ``skip`` tasks seen starting (polled every 10 ms) are let run. With ``times`` > 1 it goes on
    killing each task seen starting after that, ``times`` workers in all (``kills`` lists them)."""

    def __init__(self, title: bytes = b"ray::VariantWorker.run", timeout: float = 120.0, skip: int = 0,
                 times: int = 1):
        self.title = title
        self.timeout = timeout
        self.skip = skip
        self.times = times
        self.killed: int | None = None
        self.kills: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def _watch(self) -> None:
        me = os.getpid()
        end = time.monotonic() + self.timeout
        running: set[int] = set()  # workers seen running a task at the last poll
        started = 0
        while not self._stop.is_set() and time.monotonic() < end:
            now = set()
            for entry in Path("/proc").iterdir():
                if not entry.name.isdigit():
                    continue
                pid = int(entry.name)
                if _title(pid).startswith(self.title) and _ppid(_ppid(pid)) == me:
                    now.add(pid)
                    started += pid not in running
                    if started > self.skip and pid not in self.kills:
                        os.kill(pid, signal.SIGKILL)
                        self.killed = pid
                        self.kills.append(pid)
                        if len(self.kills) >= self.times:
                            return
            running = now
            time.sleep(0.01)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        return False


def without(value, keys: set):
    """``value`` (JSON: dicts, lists) with every dict entry named in ``keys`` removed, at any depth."""
    if isinstance(value, dict):
        return {k: without(v, keys) for k, v in value.items() if k not in keys}
    if isinstance(value, list):
        return [without(v, keys) for v in value]
    return value


def build_counter(item: int) -> dict:
    """A state for :class:`dmarionette.scale.WarmStates`: its item and the calls it has had."""
    if item < 0:
        raise ValueError(f"item {item} cannot be built")
    return {"item": item, "calls": 0}


def count_call(state: dict, request: int) -> tuple[int, int, int]:
    """``(item * request, calls of this state so far, the worker's pid)``."""
    state["calls"] += 1
    return state["item"] * request, state["calls"], os.getpid()
