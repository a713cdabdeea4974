"""The 1 kHz servo loop: read the device, ask the physics for a force, filter it, write it.

Threads (all in this process):

* the **servo thread** owns the clock and the device (or devices). Each tick it waits for its deadline
  (``time.sleep`` until ``spin_margin`` before it, then a busy-wait), reads a sample,
  hands it to the physics thread, waits for the answer at most ``compute_budget`` of a
  period, passes the force through :class:`~dmarionette.hw.safety.ForceSafetyFilter`
  and writes it. No answer in time: the last force is held; no fresh finite answer for
  ``watchdog_timeout``: zero is written (a watchdog trip) until the physics recovers,
  and then forces ramp in again.
* the **physics thread** calls the user's ``step(sample, t) -> force``. It is separate so
  that a physics callback that blocks or loops cannot hold the motors at a stale force.
  Instead of a ``step`` the loop takes a :class:`PhysicsLink`: the same request/answer
  protocol to physics elsewhere, e.g. another process over shared memory
  (:class:`dmarionette.hw.shm_link.SharedMemoryPhysics`), which the loop spins on instead of
  waiting on an event. A link whose physics is gone for good (a dead process) stops the
  loop, motors off.
* the **caller's thread** waits in :meth:`ServoLoop.run`, where Ctrl-C arrives.

Several devices (the paper's two Omnis, one per bar, both at 1 kHz in one haptic process):
give :class:`ServoLoop` a sequence of devices. Each tick reads every device, asks the physics
once with all samples, and writes each device its own row of the answer through its own
:class:`~dmarionette.hw.safety.ForceSafetyFilter` (its own limits and ramp). The physics is
one, so the watchdog is one: a stall or a non-finite value zeroes every device. Any way out
(one device unplugged or raising included) turns every device's motors off.

Motors off (zero force, then ``close``) on every way out: end of ``duration``,
:meth:`ServoLoop.request_stop`, an exception in the physics (re-raised from ``run``),
KeyboardInterrupt (re-raised after the motors are off) and a device disconnect
(:class:`~dmarionette.hw.device.DeviceDisconnectedError` re-raised).

The GIL: a CPU-bound Python thread keeps the GIL for up to ``sys.getswitchinterval()``
(5 ms by default) before the servo thread can run, which alone would break the 5 ms
stall guarantee. ``run`` therefore lowers the switch interval (``switch_interval``,
0.2 ms by default) for its duration and restores it after. It also freezes the garbage
collector's current objects (``gc.freeze``) for its duration, so a full collection over a
large model cannot stall a tick, and with ``cpu`` pins the servo thread and, while it waits,
the calling thread to that CPU. ``benchmarks/bench_servo_ticks.py``
measures what a busy thread does to the ticks, and what a separate process buys.
"""

from __future__ import annotations

import dataclasses
import gc
import os
import sys
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .device import AbstractHapticDevice, DeviceDisconnectedError, HapticDeviceError, HapticSample
from .safety import ForceSafetyFilter, SafetyConfig

__all__ = ["PhysicsLink", "PhysicsStep", "ServoLoop", "ServoStatistics", "run_servo_loop"]

PhysicsStep = Callable[[HapticSample, float], Any]
"""``step(sample, t) -> force``: ``sample`` the latest device reading (device frame, SI),
``t`` the loop time [s] since start; returns the force to render [N], shape (3,), device
frame (use :class:`~dmarionette.hw.mapping.DeviceMapping` to come from the world). With
several devices: ``step(samples, t) -> forces``, ``samples`` a tuple (one per device, in
order), ``forces`` shape (n, 3), row ``i`` in device ``i``'s frame
(:meth:`~dmarionette.hw.mapping.DeviceMapping.wrap_many`)."""


@dataclasses.dataclass(frozen=True)
class ServoStatistics:
    """How well the loop kept time.

    Attributes:
        rate_hz: Target tick rate [Hz].
        tick_count: Ticks run.
        duration: Wall time from first to last tick [s].
        lateness: Per tick, start of tick minus its deadline [s], shape (tick_count,).
        lateness_p50: Median lateness [s].
        lateness_p99: 99th percentile lateness [s].
        lateness_max: Largest lateness [s].
        missed_ticks: Deadlines skipped entirely because the loop was more than a period behind.
        stale_ticks: Ticks that wrote a held (not fresh) force because the physics had not
            answered within the compute budget.
        watchdog_trips: Times the watchdog switched to zero force (physics stalled or
            produced a non-finite value).
        nonfinite_forces: Non-finite forces the safety filter replaced by zero.
        clamped_forces: Forces the peak or continuous limit cut.
        stop_reason: "duration", "stopped", "physics error", "keyboard interrupt",
            "disconnected" or "error".
        realtime: True when the servo thread ran with the requested real-time priority.
        notes: How the loop and the physics were scheduled (priority, CPU, or why a request
            was refused), one phrase each; part of :meth:`summary`.
    """

    rate_hz: float
    tick_count: int
    duration: float
    lateness: np.ndarray
    lateness_p50: float
    lateness_p99: float
    lateness_max: float
    missed_ticks: int
    stale_ticks: int
    watchdog_trips: int
    nonfinite_forces: int
    clamped_forces: int
    stop_reason: str
    realtime: bool = False
    notes: tuple[str, ...] = ()

    @property
    def fresh_fraction(self) -> float:
        """Fraction of ticks that wrote a force computed for that tick (not a held one)."""
        return (self.tick_count - self.stale_ticks) / self.tick_count if self.tick_count else 0.0

    def summary(self) -> str:
        """One line of the figures that matter, lateness in microseconds, then the scheduling notes."""
        line = (f"{self.tick_count} ticks in {self.duration:.3f} s at {self.rate_hz:g} Hz target: lateness "
                f"p50 {self.lateness_p50 * 1e6:.0f} us, p99 {self.lateness_p99 * 1e6:.0f} us, "
                f"max {self.lateness_max * 1e6:.0f} us; missed {self.missed_ticks}, stale {self.stale_ticks} "
                f"(fresh {100.0 * self.fresh_fraction:.1f} %), watchdog trips {self.watchdog_trips}; "
                f"stop: {self.stop_reason}")
        return line + "".join(f"; {n}" for n in self.notes)


class PhysicsLink:
    """Where the servo loop sends a sample and later picks up the force: the interface.

    The loop calls, per tick: ``busy`` (is a request unanswered?), ``submit(sample, t)``
    when it is not, ``wait(timeout)`` (return as soon as an answer is there, or after
    ``timeout`` [s]), ``error`` (an exception the physics raised, re-raised by the loop),
    ``take()`` (the answer once, or None) and ``submitted_at`` (``time.perf_counter()`` of
    the unanswered request, for the watchdog). When a request is overdue it calls
    ``failure()``: an exception when the physics is gone for good (a dead process: the loop
    then stops, motors off), else None (a stall: zero force until it answers). ``notes``
    describe its scheduling for :class:`ServoStatistics`. The loop does not start or close
    a link it was given; a plain ``step`` callable is run on a thread (``_PhysicsWorker``).
    """

    busy: bool
    submitted_at: float
    error: BaseException | None
    notes: tuple[str, ...] = ()

    def submit(self, sample: HapticSample, t: float) -> None:
        raise NotImplementedError

    def wait(self, timeout: float) -> None:
        raise NotImplementedError

    def take(self) -> np.ndarray | None:
        raise NotImplementedError

    def failure(self) -> BaseException | None:
        return None


class _PhysicsWorker(PhysicsLink):
    """Runs ``step`` on its own daemon thread, one request at a time."""

    notes = ("physics: worker thread",)

    def __init__(self, step: PhysicsStep, shape: tuple[int, ...] = (3,)) -> None:
        self._step = step
        self._shape = shape
        self._cv = threading.Condition()
        self._request: tuple[HapticSample, float] | None = None
        self._stop = False
        self.busy = False
        self.submitted_at = 0.0
        self.done = threading.Event()
        self.result: np.ndarray | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="dmarionette-physics", daemon=True)
        self._thread.start()

    def submit(self, sample: HapticSample, t: float) -> None:
        with self._cv:
            self.busy = True
            self.submitted_at = time.perf_counter()
            self.done.clear()
            self._request = (sample, t)
            self._cv.notify()

    def wait(self, timeout: float) -> None:
        self.done.wait(timeout)

    def take(self) -> np.ndarray | None:
        """The answer, once; None when there is none."""
        if not self.done.is_set():
            return None
        self.done.clear()
        r, self.result = self.result, None
        return r

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout=0.05)  # a stuck step is left behind (daemon thread)

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._request is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                sample, t = self._request
                self._request = None
            try:
                force = np.asarray(self._step(sample, t), dtype=float).reshape(self._shape)
            except BaseException as e:  # noqa: BLE001 - KeyboardInterrupt included, re-raised by run()
                self.error = e
                self.busy = False
                self.done.set()
                return
            self.result = force
            self.busy = False
            self.done.set()


class ServoLoop:
    """The haptic servo loop around one device (or several) and one physics callback.

    Args:
        device: The device; opened by ``run`` if it is not open, always closed at the end.
            Or a sequence of distinct devices, all driven in the same ticks (see the module
            docstring): ``step`` then takes a tuple of samples and returns forces (n, 3).
        step: ``step(sample, t) -> force [N] (3,)``, see :data:`PhysicsStep`, run on a worker
            thread; or a started :class:`PhysicsLink` (e.g. physics in another process,
            :class:`dmarionette.hw.shm_link.SharedMemoryPhysics`), which the caller closes.
            A link serves one device only.
        rate_hz: Tick rate [Hz].
        safety: Ramp-in, limits and watchdog timeout.
        spin_margin: Sleep until this long before a deadline, then busy-wait [s].
        compute_budget: Fraction of a period the loop waits for the physics' answer.
        switch_interval: GIL switch interval during ``run`` [s]; None leaves it alone.
        realtime_priority: Run the servo thread under ``SCHED_FIFO`` with this priority
            (1-99, Linux; needs CAP_SYS_NICE or an ``rtprio`` limit); None (default) leaves
            the scheduling alone. When refused, a warning says so, the statistics' notes
            say so, and the loop runs anyway.
        cpu: Pin the servo thread to this CPU (Linux ``sched_setaffinity``); None leaves it.
    """

    def __init__(self, device: AbstractHapticDevice | Sequence[AbstractHapticDevice], step: PhysicsStep | PhysicsLink,
                 *, rate_hz: float = 1000.0,
                 safety: SafetyConfig = SafetyConfig(), spin_margin: float = 0.0005,
                 compute_budget: float = 0.6, switch_interval: float | None = 0.0002,
                 realtime_priority: int | None = None, cpu: int | None = None) -> None:
        if not rate_hz > 0.0:
            raise ValueError(f"ServoLoop: rate_hz must be > 0, got {rate_hz}")
        if not 0.0 < compute_budget < 1.0:
            raise ValueError(f"ServoLoop: compute_budget must be in (0, 1) of a period, got {compute_budget}")
        self.several = not isinstance(device, AbstractHapticDevice)
        self.devices: tuple[AbstractHapticDevice, ...] = tuple(device) if self.several else (device,)
        if not self.devices or not all(isinstance(d, AbstractHapticDevice) for d in self.devices):
            raise ValueError(f"ServoLoop: device must be a haptic device or a non-empty sequence of them; got "
                             f"{device!r}")
        if len({id(d) for d in self.devices}) != len(self.devices):
            raise ValueError("ServoLoop: the same device object was given twice; each device is read and written "
                             "once per tick")
        if self.several and isinstance(step, PhysicsLink):
            raise ValueError(f"ServoLoop: a PhysicsLink serves one device; got {len(self.devices)} devices (use a "
                             "step callable, run on the worker thread)")
        self.device = self.devices[0]
        self.step = step
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.safety = safety
        self.spin_margin = float(spin_margin)
        self.compute_budget = float(compute_budget)
        self.switch_interval = switch_interval
        self.realtime_priority = realtime_priority
        self.cpu = cpu
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._finished = threading.Event()
        self.statistics: ServoStatistics | None = None
        """Statistics of the last run, set when it ends (also when it raised)."""

    def request_stop(self) -> None:
        """Asks the loop to end after the current tick (thread-safe)."""
        self._stop.set()

    def run(self, duration: float | None = None) -> ServoStatistics:
        """Runs the loop until ``duration`` [s] passed or :meth:`request_stop`.

        Returns:
            The tick statistics (also kept on ``self.statistics``).

        Raises:
            KeyboardInterrupt: Ctrl-C, after the motors are off.
            DeviceDisconnectedError: The device went away (motors off as far as possible).
            BaseException: Whatever ``step`` raised, after the motors are off.
        """
        self._stop.clear()
        self._error = None
        try:
            for device in self.devices:
                if not device.is_open:
                    device.open()
        except BaseException:
            self._motors_off()  # the ones already opened
            raise
        # Everything alive now (a simulator's model is many objects) leaves the collector's view,
        # so a full collection triggered by the loop's own allocations costs microseconds, not
        # the ~10-20 ms seen as single late ticks; undone when the loop ends.
        gc.freeze()
        old_interval = sys.getswitchinterval()
        if self.switch_interval is not None:
            sys.setswitchinterval(self.switch_interval)
        self._finished.clear()
        caller_cpus = None
        if self.cpu is not None and hasattr(os, "sched_getaffinity"):
            # This (waiting) thread shares the servo thread's CPU: when the servo thread hands it the
            # GIL it must get to run at once, not wait behind a busy thread on another CPU.
            try:
                caller_cpus = os.sched_getaffinity(0)
                os.sched_setaffinity(0, {int(self.cpu)})
            except (OSError, ValueError):
                caller_cpus = None
        thread = threading.Thread(target=self._servo, args=(duration,), name="dmarionette-servo", daemon=True)
        try:
            thread.start()
            # Short waits on an Event (not Thread.join, whose state an interrupt can upset),
            # so Ctrl-C reaches this thread.
            while not self._finished.wait(0.02):
                pass
        except KeyboardInterrupt:
            self._stop.set()
            while not self._finished.wait(0.02):
                pass
            self._set_reason("keyboard interrupt")
            raise
        finally:
            sys.setswitchinterval(old_interval)
            gc.unfreeze()
            if caller_cpus is not None:
                os.sched_setaffinity(0, caller_cpus)
        if self._error is not None:
            raise self._error
        assert self.statistics is not None
        return self.statistics

    def _set_reason(self, reason: str) -> None:
        if self.statistics is not None:
            self.statistics = dataclasses.replace(self.statistics, stop_reason=reason)

    @staticmethod
    def _wait_until(deadline: float, spin_margin: float) -> None:
        remaining = deadline - time.perf_counter()
        if remaining > spin_margin:
            time.sleep(remaining - spin_margin)
        while time.perf_counter() < deadline:
            pass

    def _make_realtime(self) -> tuple[bool, list[str]]:
        """Pins the calling (servo) thread and asks for SCHED_FIFO, as configured.

        Returns:
            ``(realtime granted, notes for the statistics)``.
        """
        notes = []
        if self.cpu is not None:
            notes.append(pin_to_cpu("servo thread", self.cpu))
        if self.realtime_priority is None:
            return False, notes
        granted, note = request_fifo("servo thread", self.realtime_priority)
        notes.append(note)
        if not granted:
            warnings.warn(f"ServoLoop: {note}; running with normal scheduling. Grant it with an rtprio limit in "
                          "/etc/security/limits.conf or CAP_SYS_NICE.", RuntimeWarning, stacklevel=1)
        return granted, notes

    def _servo(self, duration: float | None) -> None:
        realtime, notes = self._make_realtime()
        devices, period, n = self.devices, self.period, len(self.devices)
        filters = [ForceSafetyFilter(d.spec, self.safety) for d in devices]
        own_worker = not isinstance(self.step, PhysicsLink)
        worker = _PhysicsWorker(self.step, (n, 3) if self.several else (3,)) if own_worker else self.step
        notes.extend(worker.notes)
        if self.several:
            notes.append(f"devices: {n}")
        lateness: list[float] = []
        missed = stale = trips = 0
        reason = "stopped"
        held = np.zeros((n, 3))
        zero = np.zeros(3)
        tripped = False
        t0 = time.perf_counter()
        k = 0
        try:
            while not self._stop.is_set():
                deadline = t0 + k * period
                self._wait_until(deadline, self.spin_margin)
                now = time.perf_counter()
                t = now - t0
                if duration is not None and t >= duration:
                    reason = "duration"
                    break
                lateness.append(now - deadline)
                samples = tuple(d.read() for d in devices)
                if not worker.busy:
                    worker.submit(samples if self.several else samples[0], t)
                wait_end = deadline + self.compute_budget * period
                if worker.busy:  # do not wait past the moment the watchdog must act
                    wait_end = min(wait_end, worker.submitted_at + self.safety.watchdog_timeout + 1e-5)
                worker.wait(max(wait_end - time.perf_counter(), 0.0))
                if worker.error is not None:
                    reason = "physics error"
                    self._error = worker.error
                    break
                fresh = worker.take()
                now = time.perf_counter()
                if fresh is not None:
                    held = fresh.reshape(n, 3)
                else:
                    stale += 1
                # Stalled: a request has waited too long (the servo's own lateness does not count).
                stalled = worker.busy and now - worker.submitted_at > self.safety.watchdog_timeout
                if stalled:
                    gone = worker.failure()
                    if gone is not None:  # e.g. the physics process died: zero now, then motors off
                        for d in devices:
                            d.write_force(zero)
                        trips += 1
                        reason, self._error = "physics error", gone
                        break
                finite = np.all(np.isfinite(held), axis=1)
                if stalled or not finite.all():  # one physics: a non-finite row zeroes every device
                    if not tripped:
                        trips += 1
                        tripped = True
                    forces = []
                    for i, filt in enumerate(filters):
                        if not finite[i]:
                            filt.nonfinite_count += 1
                        forces.append(filt(zero, now - t0))
                else:
                    if tripped:  # recovered after a trip: ramp in again
                        tripped = False
                        for filt in filters:
                            filt.rearm(now - t0)
                    forces = [filt(held[i], now - t0) for i, filt in enumerate(filters)]
                for d, force in zip(devices, forces):
                    d.write_force(force)
                k += 1
                behind = int((time.perf_counter() - t0) / period) - k
                if behind > 0:  # a whole period or more late: skip those deadlines
                    missed += behind
                    k += behind
        except DeviceDisconnectedError as e:
            reason, self._error = "disconnected", e
        except BaseException as e:  # noqa: BLE001 - motors off below, then re-raised by run()
            reason, self._error = "error", e
        finally:
            error = self._motors_off()
            if error is not None and self._error is None:
                reason, self._error = "error", error
            if own_worker:
                worker.stop()
            lat = np.asarray(lateness, dtype=float)
            pct = (lambda q: float(np.percentile(lat, q))) if lat.size else (lambda q: 0.0)
            self.statistics = ServoStatistics(
                rate_hz=self.rate_hz, tick_count=int(lat.size), duration=time.perf_counter() - t0,
                lateness=lat, lateness_p50=pct(50), lateness_p99=pct(99),
                lateness_max=float(lat.max()) if lat.size else 0.0, missed_ticks=missed, stale_ticks=stale,
                watchdog_trips=trips, nonfinite_forces=sum(f.nonfinite_count for f in filters),
                clamped_forces=sum(f.clamp_count for f in filters),
                stop_reason=reason, realtime=realtime, notes=tuple(notes))
            self._finished.set()

    def _motors_off(self) -> BaseException | None:
        """Zero force, then close, for every device, whatever any one of them does.

        A lost device may refuse the zero (:class:`HapticDeviceError`, ignored); close still
        runs, and the other devices are still zeroed and closed. Returns the first other
        exception a device raised here (the caller reports it), or None.
        """
        first: BaseException | None = None
        for device in self.devices:
            try:
                if device.is_open:
                    device.write_force(np.zeros(3))
            except HapticDeviceError:
                pass
            except Exception as e:  # noqa: BLE001 - the next devices must still go off
                first = first or e
            finally:
                try:
                    device.close()
                except Exception as e:  # noqa: BLE001 - likewise
                    first = first or e
        return first


def pin_to_cpu(who: str, cpu: int) -> str:
    """Pins the calling thread to ``cpu`` (Linux); returns a note saying what happened."""
    try:
        os.sched_setaffinity(0, {int(cpu)})  # 0: the calling thread
        return f"{who}: CPU {cpu}"
    except (AttributeError, OSError, ValueError) as e:
        return f"{who}: pinning to CPU {cpu} refused ({e})"


def request_fifo(who: str, priority: int) -> tuple[bool, str]:
    """Asks SCHED_FIFO ``priority`` for the calling thread; returns ``(granted, note)``."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))  # 0: the calling thread
        return True, f"{who}: SCHED_FIFO {priority}"
    except (AttributeError, OSError) as e:
        return False, f"{who}: SCHED_FIFO {priority} refused ({e}), normal scheduling"


def run_servo_loop(device: AbstractHapticDevice, step: PhysicsStep, duration: float | None = None,
                   **kwargs: Any) -> ServoStatistics:
    """Runs a :class:`ServoLoop` (``kwargs`` go to its constructor) for ``duration`` [s]."""
    return ServoLoop(device, step, **kwargs).run(duration)
