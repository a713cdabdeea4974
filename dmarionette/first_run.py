"""A first run that talks: Warp started without its CUDA-driver notice on CPU-only machines, and
a progress bar while the kernels compile.

- :func:`init_warp`: ``wp.init()`` with the one line Warp's native library prints on a machine
  without the NVIDIA driver ("Warp CUDA warning: Could not find or load the NVIDIA CUDA
  driver...") filtered out; anything else it prints (a too-old driver, a failed entry point) is
  passed on unchanged. Warp 1.19 has no setting for that line: it is an ``fprintf`` in
  ``native/cuda_util.cpp`` run by ``wp.init``, so it is caught at the file-descriptor level.
- :class:`CompileProgress`: a context manager that, once its block has run for
  ``after_s`` seconds (a cached run finishes before), shows a tqdm bar on stderr: seconds
  elapsed against the expected first-run time, how many Warp modules were compiled so far and
  the latest one's name (new entries of Warp's kernel cache), and the step in progress.
- :func:`load_kernels`: compiles (or loads from the cache) the Warp kernels an object holds,
  one module at a time, so that the compilation happens under the bar, not in the first step.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["CUDA_DRIVER_NOTICE", "FIRST_RUN_S", "CompileProgress", "build_marionette", "end_progress_lines",
           "load_string_kernels",
           "filter_native_stderr", "init_warp", "load_kernels", "versions"]

_SHOWN: set = set()  # the progress bars on screen now (their line is open until they close)


def end_progress_lines() -> None:
    """Ends the line of every progress bar on screen, so that a last message (Ctrl-C's, from
    another thread, before the process ends at once) starts on a line of its own."""
    for bar in list(_SHOWN):
        _SHOWN.discard(bar)
        bar.close()

CUDA_DRIVER_NOTICE = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver."
"""The start of the line Warp 1.19's native library prints on a machine without the NVIDIA driver."""


def init_warp() -> None:
    """``wp.init()`` without Warp's CUDA-driver notice on a CPU-only machine; other output passes."""
    import warp as wp

    filter_native_stderr(wp.init)


def filter_native_stderr(call: Callable[[], object]) -> None:
    """Runs ``call`` with file descriptor 2 captured, then writes what it printed to stderr without
    the lines that start with :data:`CUDA_DRIVER_NOTICE`."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no usable stderr descriptor (embedded interpreters): nothing to filter
        call()
        return
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            call()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode("utf-8", errors="replace")
    kept = [line for line in text.splitlines(keepends=True) if not line.startswith(CUDA_DRIVER_NOTICE)]
    if kept:
        sys.stderr.write("".join(kept))
        sys.stderr.flush()


def versions() -> str:
    """``dmarionette X (Warp Y)``: the installed package's version (its metadata) and Warp's."""
    from importlib import metadata

    try:
        own = metadata.version("dmarionette")
    except metadata.PackageNotFoundError:  # a source tree run with PYTHONPATH, not installed
        import tomllib

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        try:
            own = tomllib.loads(pyproject.read_text())["project"]["version"] + " (source tree, not installed)"
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            own = "unknown (not installed)"
    try:
        warp_version = metadata.version("warp-lang")
    except metadata.PackageNotFoundError:
        warp_version = "not installed"
    return f"dmarionette {own} (Warp {warp_version})"


_HASH = re.compile(r"_[0-9a-f]{7,}$")
_BUILDING = re.compile(r"_p\d+_t\d+$")  # Warp's temporary folder of a module being compiled


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _module_label(entry: str) -> str:
    """A kernel-cache entry's module name: ``wp_dmarionette.kernels.x_f800b57`` -> ``dmarionette.kernels.x``."""
    name = entry[3:] if entry.startswith("wp_") else entry
    name = name.split("__locals__")[-1]  # a kernel made by a factory: its own name
    while _HASH.search(name):
        name = _HASH.sub("", name)
    return name


class CompileProgress:
    """A progress bar on stderr while Warp compiles, shown only when the block takes a while.

    Args:
        what: what is compiled, for the bar's label (``"the marionette's kernels"``).
        expected_s: about how long the first run takes [s]: the bar's total (raised if passed).
        quiet: show nothing.
        after_s: show the bar once the block has run this long [s] (a cached run is faster).
        interval_s: seconds between updates.
        cache_dir: Warp's kernel cache, whose new entries are the modules compiled (default:
            ``wp.config.kernel_cache_dir`` once Warp is initialised).
        stream: where the bar goes (default ``sys.stderr``).
    """

    def __init__(self, what: str, expected_s: float, *, quiet: bool = False, after_s: float = 2.0,
                 interval_s: float = 1.0, cache_dir: str | Path | None = None, stream=None):
        self.what = what
        self.expected_s = float(expected_s)
        self.quiet = quiet
        self.after_s = after_s
        self.interval_s = interval_s
        self.cache_dir = cache_dir
        self.stream = stream
        self.step = ""
        self.shown = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._before: set[str] = set()
        self._bar = None

    def _entries(self) -> set[str]:
        try:
            return set(os.listdir(self.cache_dir)) if self.cache_dir is not None else set()
        except OSError:
            return set()

    def compiled(self) -> list[str]:
        """Module names of the kernel-cache entries that appeared since the block started."""
        new = [e for e in self._entries() - self._before if not _BUILDING.search(e)]
        new.sort(key=lambda e: _mtime(Path(self.cache_dir) / e))
        return list(dict.fromkeys(_module_label(e) for e in new))  # oldest first

    def __enter__(self) -> CompileProgress:
        if self.quiet:
            return self
        if self.cache_dir is None:
            import warp as wp

            self.cache_dir = wp.config.kernel_cache_dir
        self._before = self._entries()
        self._start = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="compile-progress", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        from tqdm import tqdm

        while not self._stop.wait(self.interval_s if self._bar is not None else min(self.interval_s, 0.2)):
            elapsed = time.monotonic() - self._start
            if elapsed < self.after_s:
                continue
            if self._bar is None:
                self.shown = True
                self._bar = tqdm(total=round(self.expected_s), unit="s", file=self.stream or sys.stderr,
                                 desc=f"compiling {self.what} (first run: ~{self.expected_s:.0f} s; then cached)",
                                 bar_format="{desc}: {bar:20} {n}/{total} s{postfix}", dynamic_ncols=True)
                _SHOWN.add(self._bar)
            self._update(elapsed)

    def _update(self, elapsed: float) -> None:
        compiled = self.compiled()
        latest = f", latest {compiled[-1]}" if compiled else ""
        step = f"; {self.step}" if self.step else ""
        if elapsed > self._bar.total:
            self._bar.total = round(elapsed) + 1
        self._bar.n = round(elapsed)
        self._bar.set_postfix_str(f"{len(compiled)} modules compiled{latest}{step}", refresh=False)
        self._bar.refresh()

    def __exit__(self, *exc) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        if self._bar is not None and self._bar in _SHOWN:
            _SHOWN.discard(self._bar)
            self._update(time.monotonic() - self._start)
            self._bar.close()


def _kernels(obj, seen: set[int], found: list, depth: int = 0) -> None:
    """Collects the ``wp.Kernel`` objects held by ``obj``'s attributes (dmarionette objects, containers)."""
    import warp as wp

    if id(obj) in seen or depth > 8:
        return
    seen.add(id(obj))
    if isinstance(obj, wp.Kernel):
        found.append(obj)
    elif isinstance(obj, dict):
        for value in obj.values():
            _kernels(value, seen, found, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for value in obj:
            _kernels(value, seen, found, depth + 1)
    elif hasattr(obj, "__dict__") and type(obj).__module__.startswith("dmarionette"):
        for value in vars(obj).values():
            _kernels(value, seen, found, depth + 1)


def load_kernels(obj, device, on_module: Callable[[int, int, str], None] | None = None) -> int:
    """Compiles or loads the Warp modules of the kernels ``obj`` holds, one at a time.

    Args:
        obj: an object whose attributes (recursively, within dmarionette's objects) hold kernels,
            e.g. a ``MarionetteModel``.
        device: the Warp device to load them on.
        on_module: called with ``(index, count, kernel name)`` before each module.

    Returns:
        The number of modules loaded.
    """
    import warp as wp

    found: list = []
    _kernels(obj, set(), found)
    modules = {}
    for kernel in found:
        modules.setdefault(id(kernel.module), (kernel.module, kernel.key.split("__locals__")[-1]))
    for index, (module, name) in enumerate(modules.values()):
        if on_module is not None:
            on_module(index, len(modules), name)
        wp.load_module(module, device=device)
    return len(modules)


FIRST_RUN_S = {0: 30.0, 1: 70.0, 2: 120.0}
"""About how long the first run compiles the marionette's kernels [s] by optimisation level. Measured
on a busy 2-core machine with an empty kernel cache: 126 s for ``MarionetteModel(hanging)`` at level 2
(the issue's fresh machine: ~85 s), 36 s for all 15 modules at level 0 (``--fast-compile``)."""


def build_marionette(scene, *, optimization_level: int = 2, quiet: bool = False):
    """``MarionetteModel(scene)`` with its kernels compiled (or loaded from the cache) under a progress bar.

    The puppet's generated kernels compile while the model is built; the string, coupling, feedback and
    contact kernels a ``SolverMarionette`` launches are then loaded one module at a time
    (``wp.load_module``; their factories are cached, so they are the kernels the simulation launches),
    so the first step compiles nothing.
    """
    from dmarionette.marionette.solver import MarionetteModel, SolverMarionette

    with CompileProgress("the marionette's Warp kernels", FIRST_RUN_S.get(optimization_level, 100.0),
                         quiet=quiet) as progress:
        progress.step = "the puppet's articulation kernels"
        model = MarionetteModel(scene, optimization_level=optimization_level)

        def on_module(index: int, count: int, name: str) -> None:
            progress.step = f"kernel {index + 1}/{count}: {name}"

        load_kernels(SolverMarionette(model), model.device, on_module)  # the solver holds the model too
    return model


def load_string_kernels(scene, *, quiet: bool = False) -> None:
    """Compiles (or loads from the cache) the kernels of ``scene``'s string solver under a progress
    bar, so that a strings-only simulation is not silent while they compile (its own bar follows)."""
    from dmarionette.strings.model import StringModel
    from dmarionette.strings.solver import SolverStringImplicit

    with CompileProgress("the string kernels", 15.0, quiet=quiet) as progress:
        solver = SolverStringImplicit(StringModel.from_scene(scene))

        def on_module(index: int, count: int, name: str) -> None:
            progress.step = f"kernel {index + 1}/{count}: {name}"

        load_kernels(solver, solver.model.device, on_module)
