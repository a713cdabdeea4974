"""Physics in its own process, exchanging samples and forces with the servo loop through shared memory.

Why: in one process the physics (~100 µs of Warp launches and numpy per tick) and the servo
thread's deadline spin compete for Python's interpreter lock; through a pipe every tick
costs two process wake-ups (~160 µs on the 2-core development VM). Here the two processes
share one small block (:mod:`multiprocessing.shared_memory`) and nobody is woken up:

* the **servo process** (the caller: device I/O, safety filter, watchdog) writes a request
  (loop time, the device sample, the last force actually sent) and then its sequence number;
  it spins on the answer's sequence number for at most the loop's compute budget;
* the **physics process** (spawned: its own interpreter, lock and Warp runtime) spins on the
  request's sequence number near the time the next one is due, sleeps in between, computes,
  writes the force and then the answer's sequence number.

Each side writes payload first and sequence number last, and a side only writes when the
other is not reading (strict ping-pong: a new request only after the last one was answered).
That is enough on x86-64, whose stores become visible in program order (TSO); CPUs with a
weaker memory model (ARM) would need a fence that Python does not offer, so
:class:`SharedMemoryPhysics` refuses to start there.

Block layout (float64 words; request, answer and control on separate cache lines):

====  =====================================================================
0     request sequence number
1     loop time t [s]
2     sample time [s]
3-5   sample position [m] (device frame)
6-9   sample orientation (w, x, y, z)
10    buttons
11-13 the force last written to the device [N] (device frame)
14    1 when 11-13 hold a force
16    answer sequence number (equals 0 when the answer to that request is there)
17-19 force [N] (device frame)
20    the physics' compute time for it [s]
21    when the physics picked the request up (``time.perf_counter``, CLOCK_MONOTONIC, the
      same clock in both processes) [s]
32    stop (set by the servo process)
33    error (set by the physics process after it sent the text through the pipe)
====  =====================================================================

The pipe carries only start-up (``("ready", info)`` / ``("error", text)``), a physics error's
text and the final summary. This module imports no simulator code: what runs in the child is
built there by a picklable ``factory()`` (see :class:`SharedMemoryPhysics`).
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import os
import platform
import signal
import time
import traceback
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from .device import HapticSample
from .servo import PhysicsLink, pin_to_cpu, request_fifo

__all__ = ["PhysicsProcessError", "SharedMemoryPhysics", "SpringPhysics"]

_WORDS = 64
_REQ, _T, _STIME, _POS, _QUAT, _BUTTONS, _LAST, _HAS_LAST = 0, 1, 2, 3, 6, 10, 11, 14
_ANS, _FORCE, _COMPUTE, _PICKED = 16, 17, 20, 21
_STOP, _ERROR = 32, 33
_IDLE_AFTER = 0.02  # [s] without a request: the parent is not ticking, poll at a relaxed rate
_IDLE_POLL = 0.0005  # [s]
_LATE_SPIN = 0.0005  # [s] past the due time a request is still spun for
_LATE_POLL = 0.0001  # [s] then polled at this interval


class PhysicsProcessError(RuntimeError):
    """The physics process failed: it raised (its traceback is in the message) or it died."""


class SpringPhysics:
    """A virtual spring to a point, ``F = -k (P - centre)``: checks a device and the link without a simulation.

    Args:
        stiffness: Spring constant [N/m].
        centre: Rest point [m], shape (3,), device frame.
    """

    def __init__(self, stiffness: float = 100.0, centre: Any = (0.0, 0.0, 0.0)) -> None:
        self.stiffness = float(stiffness)
        self.centre = np.asarray(centre, dtype=float).reshape(3)

    def __call__(self) -> SpringPhysics:  # its own factory: picklable, built in the child
        return self

    def step(self, sample: HapticSample, t: float) -> np.ndarray:
        return -self.stiffness * (sample.position - self.centre)


def _physics_main(conn, shm_name: str, factory, period: float, spin_margin: float, cpu: int | None,
                  priority: int | None) -> None:
    """The child: builds the physics, then answers requests until told to stop."""
    try:
        # Spawned children share the parent's resource tracker, so attaching registers nothing new
        # and the parent's unlink is the only one.
        shm = shared_memory.SharedMemory(name=shm_name)
        block = np.ndarray((_WORDS,), dtype=np.float64, buffer=shm.buf)
        physics = factory()
    except BaseException as error:  # noqa: BLE001 - reported to the parent, which raises it with context
        conn.send(("error", f"{type(error).__name__}: {error}"))
        return
    # Scheduling only now: building the physics (compiling kernels) should not run at FIFO priority.
    notes = []
    if cpu is not None:
        notes.append(pin_to_cpu("physics process", cpu))
    if priority is not None:
        notes.append(request_fifo("physics process", priority)[1])
    gc.freeze()  # the physics' objects out of the collector's view: no long full collections while serving
    force_sent = getattr(physics, "force_sent", None)
    conn.send(("ready", {"pid": os.getpid(), "notes": notes, **getattr(physics, "info", {})}))
    summary: dict[str, Any] = {}
    try:
        last = 0.0
        parent = os.getppid()
        arrived = time.perf_counter()
        clock = time.perf_counter
        while True:
            seq = block[_REQ]
            if seq != last:
                start = clock()
                arrived = start
                if force_sent is not None and block[_HAS_LAST]:
                    force_sent(block[_LAST:_LAST + 3].copy())
                sample = HapticSample(float(block[_STIME]), block[_POS:_POS + 3].copy(),
                                      block[_QUAT:_QUAT + 4].copy(), int(block[_BUTTONS]))
                force = np.asarray(physics.step(sample, float(block[_T])), dtype=np.float64).reshape(3)
                block[_FORCE:_FORCE + 3] = force
                block[_COMPUTE] = clock() - start
                block[_PICKED] = start
                block[_ANS] = seq  # last: the parent reads the force only after this
                last = seq
                continue
            if block[_STOP]:
                break
            now = clock()
            due = arrived + period
            if now < due - spin_margin:  # sleep until shortly before the next request is due
                time.sleep(due - spin_margin - now)
            elif now < due + _LATE_SPIN:
                pass  # spin
            elif now - arrived > _IDLE_AFTER:
                if os.getppid() != parent:  # the servo process is gone (killed): nobody to answer
                    break
                time.sleep(_IDLE_POLL)
            else:
                # The servo is late: poll, but give the CPU up in between. Spinning here could keep a
                # thread of the servo process off this CPU, e.g. one the servo thread hands the GIL to.
                time.sleep(_LATE_POLL)
    except BaseException:  # noqa: BLE001 - the text goes to the parent, which raises it
        conn.send(("error", traceback.format_exc()))
        block[_ERROR] = 1.0
    finally:
        close = getattr(physics, "close", None)
        try:
            if close is not None:
                summary = close() or {}
        finally:
            conn.send(("summary", summary))
            del block
            shm.close()


class SharedMemoryPhysics(PhysicsLink):
    """A :class:`~dmarionette.hw.servo.PhysicsLink` to physics in a spawned process, through shared memory.

    Args:
        factory: Picklable callable, called once in the child, returning the physics: an object
            with ``step(sample, t) -> force [N] (3,)`` (device frame, like a servo step), and
            optionally ``force_sent(force)`` (called with the force last written to the device
            before each step), ``close() -> dict`` (a summary, returned by :meth:`close`) and
            ``info`` (a dict sent back at start, in :attr:`info`).
        rate_hz: The servo loop's rate [Hz]; the child wakes up shortly before each request.
        spin_margin: The child sleeps until this long before the next request is due, then spins [s].
        cpu: Pin the physics process to this CPU; None leaves it.
        realtime_priority: SCHED_FIFO priority for the physics process; None leaves it. Refusal
            is not an error: :attr:`notes` says so.
        start_timeout: Seconds to wait for the child to build the physics (compiling kernels).

    Raises:
        PhysicsProcessError: The child could not build the physics (its error in the message),
            or did not report within ``start_timeout``.
        RuntimeError: Not an x86-64 machine (see the module docstring).
    """

    def __init__(self, factory, *, rate_hz: float = 1000.0, spin_margin: float = 0.0003, cpu: int | None = None,
                 realtime_priority: int | None = None, start_timeout: float = 300.0) -> None:
        if platform.machine().lower() not in ("x86_64", "amd64"):
            raise RuntimeError(f"SharedMemoryPhysics relies on x86-64 store ordering; this is {platform.machine()}. "
                               "Use the worker thread or the pipe process instead.")
        self._shm = shared_memory.SharedMemory(create=True, size=_WORDS * 8)
        self._block = np.ndarray((_WORDS,), dtype=np.float64, buffer=self._shm.buf)
        self._block[:] = 0.0
        self._seq = 0
        self._taken = 0
        self._error: BaseException | None = None
        self._closed = False
        self.submitted_at = 0.0
        self.last_force: np.ndarray | None = None
        """Set by the caller to the force last written to the device; sent with the next request."""
        self.summary: dict[str, Any] = {}
        self.compute_times: list[float] = []
        """Per answer taken, the physics' compute time [s] as the child measured it."""
        self.pickup_delays: list[float] = []
        """Per answer taken, from the request's submission to the child picking it up [s]."""
        context = mp.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_physics_main, name="dmarionette-physics", daemon=True,
                                        args=(child, self._shm.name, factory, 1.0 / rate_hz, spin_margin, cpu,
                                              realtime_priority))
        self._process.start()
        child.close()
        try:
            if not self._conn.poll(start_timeout):
                raise PhysicsProcessError(f"the physics process did not start within {start_timeout} s")
            kind, info = self._conn.recv()
            if kind == "error":
                raise PhysicsProcessError(f"the physics process could not start: {info}")
        except BaseException:
            self._shutdown()
            raise
        self.info = info
        self.pid = info["pid"]
        self.notes = ("physics: own process, shared memory",) + tuple(info["notes"])

    @property
    def busy(self) -> bool:
        """A request is unanswered."""
        return self._block[_ANS] != self._seq

    @property
    def error(self) -> BaseException | None:
        """What the physics raised (its traceback in the message), once it has."""
        if self._error is None and self._block[_ERROR]:
            text = "(no message)"
            while self._conn.poll(0.1):
                kind, value = self._conn.recv()
                if kind == "error":
                    text = value
                    break
            self._error = PhysicsProcessError(f"the physics process raised:\n{text}")
        return self._error

    def submit(self, sample: HapticSample, t: float) -> None:
        b = self._block
        b[_T] = t
        b[_STIME] = sample.time
        b[_POS:_POS + 3] = sample.position
        b[_QUAT:_QUAT + 4] = sample.orientation
        b[_BUTTONS] = sample.buttons
        if self.last_force is not None:
            b[_LAST:_LAST + 3] = self.last_force
            b[_HAS_LAST] = 1.0
        self._seq += 1
        self.submitted_at = time.perf_counter()
        b[_REQ] = self._seq  # last: the child reads the request only after this

    def wait(self, timeout: float) -> None:
        """Spins until the answer is there, the child reports an error, or ``timeout`` [s] passed."""
        b, seq = self._block, self._seq
        end = time.perf_counter() + timeout
        while b[_ANS] != seq and not b[_ERROR] and time.perf_counter() < end:
            pass

    def take(self) -> np.ndarray | None:
        if self._taken == self._seq or self._block[_ANS] != self._seq:
            return None
        self._taken = self._seq
        self.compute_times.append(float(self._block[_COMPUTE]))
        self.pickup_delays.append(float(self._block[_PICKED]) - self.submitted_at)
        return self._block[_FORCE:_FORCE + 3].copy()

    def failure(self) -> BaseException | None:
        """A :class:`PhysicsProcessError` when the child has exited, else None."""
        if self._process.is_alive():
            return None
        code = self._process.exitcode
        how = (f"killed by {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}")
        return PhysicsProcessError(f"the physics process (pid {self.pid}) died ({how}); the force was zeroed "
                                   "and the motors turned off")

    def close(self, timeout: float = 30.0) -> dict[str, Any]:
        """Stops the child (after its ``close()``, e.g. a recording, is done); returns its summary."""
        if self._process.is_alive():
            self._block[_STOP] = 1.0
            end = time.monotonic() + timeout
            while time.monotonic() < end and self._conn.poll(max(end - time.monotonic(), 0.0)):
                try:
                    kind, value = self._conn.recv()
                except EOFError:
                    break
                if kind == "summary":
                    self.summary = value
                    break
        self._shutdown()
        return self.summary

    def _shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._process.join(5.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(5.0)
        self._conn.close()
        del self._block
        self._shm.close()
        self._shm.unlink()
