"""Checks of the command line, made before any work: flag values, output paths, sizes, results.

- Flag types (argparse ``type=``): :func:`number` and :func:`integer` build a parser for one
  flag that refuses a non-number, NaN, an infinity or a value out of range with
  ``argparse.ArgumentTypeError`` naming the range (argparse names the flag and exits 2).
- Outputs (:class:`Outputs`): every folder or file a command writes is proven writable before
  the simulation or fit starts: a folder is created (with its parents) and a probe file
  written and removed in it; a file's folder likewise, and an existing file opened for
  writing. What exists already: **files the command writes are overwritten** (as a re-run
  expects), a path of the wrong kind is refused (a file where a folder is expected, a folder
  where a file is expected, a file in the middle of a path). Folders the command created are
  removed again (when still empty) if it stops with an error or Ctrl-C, so a refused run leaves
  nothing behind.
- Sizes (:func:`check_trajectory_fits`): the memory a rollout's trajectory takes, estimated
  from the scene's sizes before anything is allocated; a duration whose trajectory would not
  fit in this machine's memory is refused with the estimate.
- Results (:func:`first_non_finite`): the first non-finite quantity of a trajectory and the
  time it appeared, so that a command refuses to write a NaN result that would look valid.
- Ctrl-C (:meth:`Outputs.interrupted`): the one line a command prints when interrupted: what
  it kept, or that nothing was written.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["NonFiniteError", "Outputs", "PromptInterrupt", "check_finite", "check_host", "check_trajectory_fits",
           "format_bytes", "integer", "live_input_bytes", "number", "optimization_level", "refuse_empty_option_values",
           "start_values"]


def _range_text(low: float | None, high: float | None, low_open: bool, unit: str, kind: str) -> str:
    def show(x: float) -> str:
        return str(x) if isinstance(x, int) else f"{x:g}"

    parts = []
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {show(low)}")
    if high is not None:
        parts.append(f"<= {show(high)}")
    text = f"{kind} {' and '.join(parts)}" if parts else kind
    return f"{text} [{unit}]" if unit else text


def number(low: float | None = None, high: float | None = None, *, low_open: bool = False,
           unit: str = "") -> Callable[[str], float]:
    """An argparse ``type``: a finite float in ``[low, high]`` (``(low, high]`` with ``low_open``).

    Args:
        low, high: the bounds (None: none).
        low_open: exclude ``low`` itself (a strictly positive value for ``low=0``).
        unit: the unit, for the message (e.g. ``"s"``).
    """
    expected = _range_text(low, high, low_open, unit, "a finite number")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {expected}") from None
        if not math.isfinite(value) or (low is not None and (value <= low if low_open else value < low)) or (
                high is not None and value > high):
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {expected}")
        return value

    parse.__name__ = "number"
    return parse


def integer(low: int = 1, high: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``[low, high]`` (written as digits: ``1e3`` is refused)."""
    expected = _range_text(low, high, False, "", "an integer")

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {expected}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {expected}")
        return value

    parse.__name__ = "integer"
    return parse


def start_values(text: str) -> dict[str, float]:
    """An argparse ``type`` for ``--start``: ``NAME=VALUE,...`` with finite values."""
    values: dict[str, float] = {}
    if not text.strip():
        return values  # the default start
    for item in text.split(","):
        name, equals, value = item.partition("=")
        try:
            number_ = float(value)
        except ValueError:
            number_ = None
        if not equals or not name.strip() or number_ is None or not (math.isfinite(number_) and number_ > 0.0):
            raise argparse.ArgumentTypeError(f"{item!r}: expected NAME=VALUE with a finite value > 0 (the constants "
                                             "are positive), e.g. k=250,k_d=2.5")
        values[name.strip()] = number_
    return values


def add_ray_flags(parser: argparse.ArgumentParser, what: str, *, one_in_process: bool = False) -> None:
    """``--ray`` and ``--workers`` of a command that runs independent pieces of work on Ray
    (``dmarionette.scale.ray_map``; docs/sweep.md, "Ray"): ``what`` says what runs where;
    ``one_in_process``: the command runs a single piece in this process whatever ``--ray`` says."""
    single = "; a single one always runs in this process, without Ray" if one_in_process else ""
    parser.add_argument("--ray", default=None, metavar="local|off|ADDRESS",
                        help=f"{what}: local (the default when the 'scale' extra is installed: an embedded Ray "
                             "cluster on this machine, loopback only, one worker per core), off (this process, one "
                             "after another; the default without Ray), or the address of a running Ray cluster "
                             f"(host:port, or auto){single}")
    parser.add_argument("--workers", type=integer(1, 100_000), default=None,
                        help="Ray workers (default: one per CPU of the cluster)")


def optimization_level(args: argparse.Namespace) -> int:
    """The C++ optimisation level of the puppet kernels a command builds: 0 with ``--fast-compile``
    (seconds to compile, slower to run), else 2 (the library's default)."""
    return 0 if args.fast_compile else 2


def refuse_empty_option_values(parser: argparse.ArgumentParser, argv) -> None:
    """Refuses ``--flag=--``, which Python 3.11's argparse turns into ``[]`` without calling ``type``.

    (``--flag --`` is already refused: argparse reads the ``--`` as the end of the options.)
    """
    for arg in argv:
        name, equals, value = arg.partition("=")
        if name.startswith("--") and equals and value == "--":
            parser.error(f"argument {name}: got '--'; expected a value")


def check_host(flag: str, host: str) -> None:
    """Refuses an address the view could not listen on (one that does not resolve), before the work."""
    import socket

    try:
        socket.getaddrinfo(host, None)
    except (OSError, UnicodeError) as error:
        raise ValueError(f"{flag}: got {host!r}; expected an address of this machine (e.g. 127.0.0.1, 0.0.0.0 or "
                         f"localhost): {getattr(error, 'strerror', None) or error}") from None


# ----------------------------------------------------------------------------------- outputs


class Outputs:
    """The outputs of one command, checked before its work; undone or reported when it stops early.

    A handler calls :meth:`folder` or :meth:`file` for each output flag before it simulates or
    fits; ``dmarionette.cli.main`` gives every handler one (``args.outputs``), calls
    :meth:`discard` when the handler fails and prints :meth:`interrupted` on Ctrl-C.
    """

    def __init__(self) -> None:
        self._created: list[Path] = []  # folders this command created, parents first
        self._watched: list[Path] = []  # output folders and files
        self._started = time.time()

    def folder(self, flag: str, path: Path) -> Path:
        """Creates the output folder ``path`` (and its parents) and proves it writable.

        Raises:
            ValueError: naming ``flag``, the path and why it cannot be written.
        """
        path = Path(path)
        if path.exists() and not path.is_dir():
            raise ValueError(f"{flag}: {str(path)!r} is a file; expected a folder (or a path to create one at)")
        self._make_folder(flag, path)
        self._probe(flag, path)
        self._watched.append(path)
        return path

    def file(self, flag: str, path: Path) -> Path:
        """Proves that the output file ``path`` can be written (creating its folder if needed).

        An existing file is overwritten later by the command; nothing is written to it here.

        Raises:
            ValueError: naming ``flag``, the path and why it cannot be written.
        """
        path = Path(path)
        if path.is_dir():
            raise ValueError(f"{flag}: {str(path)!r} is a folder; expected a file name")
        parent = path.parent
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{flag}: {str(path)!r}: {str(parent)!r} is a file, not a folder")
        self._make_folder(flag, parent)
        if path.exists():
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_APPEND))
            except OSError as error:
                raise ValueError(f"{flag}: {str(path)!r} exists and cannot be written: "
                                 f"{error.strerror or error}") from None
        else:
            self._probe(flag, parent, what=str(path))
        self._watched.append(path)
        return path

    def _make_folder(self, flag: str, path: Path) -> None:
        missing = []
        above = path
        while not above.exists():
            missing.append(above)
            if above.parent == above:
                break
            above = above.parent
        if above.exists() and not above.is_dir():
            raise ValueError(f"{flag}: {str(path)!r}: {str(above)!r} is a file, not a folder")
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                continue
            except OSError as error:
                self.discard()
                raise ValueError(f"{flag}: cannot create the folder {str(folder)!r}: "
                                 f"{error.strerror or error}") from None
            self._created.append(folder)

    def _probe(self, flag: str, folder: Path, what: str | None = None) -> None:
        try:
            with tempfile.NamedTemporaryFile(dir=folder, prefix=".dmarionette-probe-"):
                pass
        except OSError as error:
            self.discard()
            target = f"{what!r} (in {str(folder)!r})" if what else f"{str(folder)!r}"
            raise ValueError(f"{flag}: cannot write {target}: {error.strerror or error}") from None

    def written(self) -> list[Path]:
        """The output files written since this command started."""
        found = []
        for path in self._watched:
            candidates = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
            for p in candidates:
                try:
                    if p.is_file() and p.stat().st_mtime >= self._started - 1.0:
                        found.append(p)
                except OSError:
                    continue
        return found

    def discard(self) -> None:
        """Removes the folders this command created that are still empty (deepest first)."""
        for folder in reversed(self._created):
            try:
                folder.rmdir()
            except OSError:
                pass
        self._created = [f for f in self._created if f.exists()]

    def interrupted(self) -> str:
        """The line to print on Ctrl-C (after :meth:`discard`)."""
        self.discard()
        kept = self.written()
        if not kept:
            return "interrupted; nothing written"
        return ("interrupted; kept what was written before the interrupt (a file being written may be incomplete): "
                + ", ".join(str(p) for p in kept))


# ------------------------------------------------------------------------------------- sizes


def format_bytes(count: float) -> str:
    """``7.28 TiB``-style text."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if count < 1024.0 or unit == "PiB":
            return f"{count:.3g} {unit}" if unit != "B" else f"{count:.0f} B"
        count /= 1024.0
    return f"{count:.3g} EiB"  # pragma: no cover


def live_input_bytes(scene, duration: float) -> float:
    """The memory [bytes] of the scripted bar inputs a live session evaluates up front (per 1 kHz tick)."""
    s, b = len(scene.strings), max(len(scene.bars), 1)
    return float(duration * scene.string_hz * 8 * (1 + s * 3 + b * (7 + 6 + 3)))


def check_trajectory_fits(flag: str, duration: float, size: float, limit: float | None = None) -> None:
    """Refuses a duration whose arrays (``size`` bytes, estimated) would not fit in memory.

    Raises:
        ValueError: naming ``flag`` (or the scene file's key), the estimate and the longest duration that fits.
    """
    from dmarionette.scene.limits import memory_budget_bytes

    limit = memory_budget_bytes() if limit is None else limit
    if not size <= limit:
        longest = duration * limit / size
        raise ValueError(f"{flag}: got {duration:g} s; the trajectory would take about {format_bytes(size)} in memory "
                         f"(estimated from the scene's sizes), more than the {format_bytes(limit)} allowed (half of this machine's memory); "
                         f"expected a duration of at most about {longest:.3g} s")


# ----------------------------------------------------------------------------------- results


class NonFiniteError(RuntimeError):
    """A simulation produced a non-finite value; nothing was written (``dmarionette`` exits 1)."""


def check_finite(trajectory) -> None:
    """Refuses a trajectory with a non-finite value before anything of it is written.

    Raises:
        NonFiniteError: naming the first non-finite quantity and the simulated time it appeared at.
    """
    from dmarionette.io.trajectory import first_non_finite

    found = first_non_finite(trajectory)
    if found is not None:
        name, index, at = found
        when = f" first at t = {at:.6g} s" if at is not None else ""
        raise NonFiniteError(f"the simulation produced a non-finite value: {name}{when} (index {list(index)}); "
                             "nothing written (a scene constant far outside the tested range diverges, "
                             "docs/scenes.md)")


class PromptInterrupt:
    """Ctrl-C that stops the command within ``grace`` seconds, even inside a long C call.

    Python raises ``KeyboardInterrupt`` only between bytecodes of the main thread, so a Ctrl-C
    during a kernel compile (tens of seconds in one call into the compiler) would wait for it.
    Inside this context the SIGINT handler's wake-up file (``signal.set_wakeup_fd``, written by
    the C-level handler whatever thread takes the signal) is read by a watcher thread: the usual
    ``KeyboardInterrupt`` still stops the command (its own cleanup runs), and if the command has
    not stopped ``grace`` seconds after the signal, the watcher prints ``outputs.interrupted()``
    and ends the process with exit code 130.

    ``live`` calls :meth:`disarm` once its kernels are compiled, before it opens the devices:
    from there its servo loop turns the motors off on ``KeyboardInterrupt`` and closes its
    physics processes, and must be left the time to. Does nothing outside
    the main thread, when SIGINT has a handler other than Python's default, or when a wake-up
    file is already set (an event loop's).
    """

    def __init__(self, outputs: Outputs, grace: float = 0.5):
        self.outputs = outputs
        self.grace = grace
        self._active = False
        self._armed = True

    def disarm(self) -> None:
        """From now on Ctrl-C only raises ``KeyboardInterrupt`` (the command's own cleanup takes its time)."""
        self._armed = False

    def __enter__(self) -> PromptInterrupt:
        import signal
        import socket
        import threading

        if (threading.current_thread() is not threading.main_thread()
                or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
            return self
        self._read, self._write = socket.socketpair()
        self._write.setblocking(False)
        self._read.settimeout(0.05)
        previous = signal.set_wakeup_fd(self._write.fileno(), warn_on_full_buffer=False)
        if previous != -1:  # someone else's: put it back, do nothing
            signal.set_wakeup_fd(previous)
            self._read.close()
            self._write.close()
            return self
        self._lock = threading.Lock()
        self._finished = threading.Event()
        self._active = True
        self._thread = threading.Thread(target=self._watch, name="dmarionette-interrupt", daemon=True)
        self._thread.start()
        return self

    def _watch(self) -> None:
        import signal
        import socket
        import sys

        while not self._finished.is_set():
            try:
                data = self._read.recv(64)
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            if signal.SIGINT not in data:
                continue
            if self._finished.wait(self.grace):
                return
            with self._lock:
                if self._finished.is_set():
                    return
                if not self._armed:
                    continue
                from dmarionette.first_run import end_progress_lines

                end_progress_lines()  # a compile's progress bar: its line ended first
                print(self.outputs.interrupted(), file=sys.stderr, flush=True)
                os._exit(130)

    def __exit__(self, *exc) -> None:
        if not self._active:
            return
        import signal

        with self._lock:
            self._finished.set()
        self._thread.join()
        signal.set_wakeup_fd(-1)
        self._read.close()
        self._write.close()
        self._active = False
