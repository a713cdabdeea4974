"""A recording delay between the bar inputs and the targets (docs/calibration.md, "Delay").

``dmarionette calibrate --fit-delay`` (or ``--delay S``, a known one) models recorded targets that
lag the recorded bar inputs by ``d`` seconds: ``measured(t) = simulated(t - d)`` (a motion-capture
system or a force sensor with latency, timestamps taken on receipt). The simulation is
time-invariant, so ``simulated(t - d)`` under the recorded inputs ``u`` is the simulation at
``t`` under the inputs delayed by ``d``, ``u(t - d)``. That is how it is done here: **the bar
inputs are shifted**, not the simulated trajectory interpolated, because

- the inputs are sampled at the string rate (1 kHz), where a cubic interpolation of the smooth
  bar motion is exact to ~1e-7 of a step's motion; the body targets are at the puppet rate
  (30 Hz), where interpolating the simulated bodies by a fraction of a 33 ms frame would err by
  more than the noise (``H^2 a / 8`` ~ 0.7 mm at 5 m/s^2);
- every comparison stays on the recording's own time grid, the body poses, the forces and the
  recorded puppet states the shooting windows start from (recorded with the same delay, so
  consistent with the delayed inputs).

Interpolation: cubic Hermite with Catmull-Rom tangents on the string steps (C1 in ``d``, so the
solver's finite-difference derivatives are smooth); before the first step the first input is held
(the bars at rest before the session: the assumption of the session's start state), after the
last one the last (``d < 0``, targets leading the inputs). ``d`` is fitted in milliseconds
(:data:`DELAY_UNIT`; not its logarithm: it may be 0 or negative), inside :data:`MAX_DELAY`. In
milliseconds its Jacobian column is of the size of the log-constants' (a 1 ms shift moves the
residuals about as much as a few % of a constant), so ``cond(J^T J)`` and the identifiability
test (a direction known to no better than 1 unit, :mod:`fitting.uncertainty`: here 1 ms) keep their
meaning; in seconds the column was 1000x larger (measured on the delay test: ``cond`` 8.9e6 in seconds,
4.9e3 in milliseconds, the same optimum).
"""

from __future__ import annotations

import numpy as np

__all__ = ["DELAY_UNIT", "MAX_DELAY", "delayed"]

#: The delay is fitted inside ``[-MAX_DELAY, MAX_DELAY]`` [s]: three puppet frames at 30 Hz, far
#: beyond a motion-capture or force-sensor latency (a few ms to tens of ms).
MAX_DELAY = 0.1
#: The delay's unit in the fitted vector [s]: milliseconds.
DELAY_UNIT = 1e-3


def delayed(samples: np.ndarray, delay: float, dt: float) -> np.ndarray:
    """A series sampled every ``dt`` [s] (rows; ``samples[k]`` at ``t_k = (k + 1) dt``) read ``delay``
    [s] later: row ``k`` is its value at ``t_k - delay`` (Catmull-Rom cubic; held at both ends).
    ``delay = 0`` returns the samples themselves."""
    samples = np.asarray(samples, dtype=np.float64)
    if delay == 0.0:
        return samples
    shift = delay / dt
    whole = int(np.floor(shift))
    f = 1.0 - (shift - whole)  # t_k - delay lies between samples k - whole - 1 and k - whole, at fraction f
    if f == 1.0:
        f, whole = 0.0, whole - 1  # exactly on a sample
    base = np.arange(len(samples)) - whole - 1
    weights = ((-f**3 + 2 * f**2 - f) / 2, (3 * f**3 - 5 * f**2 + 2) / 2, (-3 * f**3 + 4 * f**2 + f) / 2,
               (f**3 - f**2) / 2)
    out = np.zeros_like(samples)
    for offset, w in zip((-1, 0, 1, 2), weights):
        out += w * samples[np.clip(base + offset, 0, len(samples) - 1)]
    return out
