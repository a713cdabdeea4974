"""Are a fit's residuals white in time? A noise-scale-free test of "the fit explains the data"
(docs/calibration.md, "Honest results").

The reduced chi-squared (:mod:`fitting.calibration_verdict`) compares the residuals with the noise
scales the user gave, which are often known only roughly, so its limit (2) leaves room: a wrong
basin whose residuals are 1.3x the noise passes it (issue #14: chi^2 1.70 with one rollout on the
``roll_yaw`` session, 36.8 standard errors off). This test needs no noise scale. A simulation
that explains the data leaves the measurement noise, white in time; a wrong one leaves slow,
structured errors (a drift, a phase error of the swing) on top of it, correlated from one sample
to the next.

**The statistic.** For each residual channel ``c`` (one body coordinate, one force component), its
series in the recording's time order ``r_1 .. r_T`` (scaled residuals; the scale cancels) has the
lag-1 autocorrelation ``rho_c = sum_t r_t r_(t+1) / sum_t r_t^2`` (no mean removed). For
independent, symmetric noise ``E[rho_c] = 0`` exactly (flip the sign of one sample), and for
Gaussian noise ``Var[rho_c] = (T - 1) / (T (T + 2))`` exactly (``r_t^2 / sum r^2`` is
Dirichlet(1/2, ..., 1/2); about ``1 / T``). Pooled over the ``C`` channels of a target,

    z = sum_c rho_c / sqrt(sum_c (T_c - 1) / (T_c (T_c + 2)))

is standard normal under white noise independent across channels (central limit over ``C T``
products). A structured residual ``s`` (slow, so its own lag-1 autocorrelation is near 1) on
noise of variance ``sigma^2`` gives ``rho ~ |s|^2 / (|s|^2 + T sigma^2)``: the share of the
residual that is structure, e.g. 0.4 at chi^2 1.7, which is ``0.4 sqrt(C T)`` standard
deviations (13 for 36 body coordinates over 30 frames).

**The threshold** :data:`Z_LIMIT` = 4, one-sided (only positive correlation is structure): a
white-noise target exceeds it with probability ``1 - Phi(4) = 3.2e-5``. The fit itself moves the
residuals off white noise by projecting out the ``n`` directions of the Jacobian; those are smooth
in time, so it lowers ``sum r_t r_(t+1)`` by about ``n`` noise variances (``z`` by about
``n / sqrt(m_c)``, e.g. -0.3): conservative. Channels with fewer than :data:`MIN_SAMPLES` samples
(or all zero) are skipped; a target with none is not tested.

**Assumptions**: the measurement noise is white at the recording rate and independent between
channels. Noise correlated between the three coordinates of a marker inflates ``Var z`` by up to
3x (``z`` limit then about 2.3 standard deviations); noise filtered in time (a force sensor's
low-pass) is itself correlated and is reported as structure.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["MIN_SAMPLES", "Z_LIMIT", "lag1_whiteness"]

#: One-sided limit on the pooled z (standard normal under white noise): false alarm 3.2e-5 per target.
Z_LIMIT = 4.0
#: A channel needs at least this many samples in time to be tested.
MIN_SAMPLES = 4


def lag1_whiteness(series: Sequence[np.ndarray]) -> dict | None:
    """The pooled lag-1 autocorrelation test of one target's residuals.

    Args:
        series: one array ``(T, C)`` per session: the scaled residuals in time order (rows), one
            column per channel (a body coordinate, a force component).

    Returns:
        ``lag1`` (the mean ``rho_c``), ``z`` (module doc), ``channels`` (tested), ``samples`` (their
        total count), ``structured`` (``z > Z_LIMIT``); or None when no channel can be tested.
    """
    rho, variance, samples = [], [], 0
    for block in series:
        block = np.asarray(block, dtype=np.float64)
        if block.ndim != 2 or block.shape[0] < MIN_SAMPLES:
            continue
        t = block.shape[0]
        power = np.sum(block * block, axis=0)
        tested = power > 0.0
        lagged = np.sum(block[1:] * block[:-1], axis=0)
        rho.extend((lagged[tested] / power[tested]).tolist())
        variance.extend([(t - 1) / (t * (t + 2))] * int(tested.sum()))
        samples += t * int(tested.sum())
    if not rho:
        return None
    z = float(np.sum(rho) / np.sqrt(np.sum(variance)))
    return {"lag1": float(np.mean(rho)), "z": z, "channels": len(rho), "samples": samples,
            "structured": bool(z > Z_LIMIT)}
