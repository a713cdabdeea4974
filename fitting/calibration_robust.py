"""A robust loss for calibration: Huber's, by iteratively reweighted least squares
(docs/calibration.md, "Robust loss").

``--loss huber --huber-scale C`` replaces ``0.5 sum r_i^2`` (``r`` the residuals divided by the
noise scales) by ``sum rho(r_i)`` with Huber's ``rho(r) = r^2 / 2`` for ``|r| <= C`` and
``C |r| - C^2 / 2`` beyond: a residual more than ``C`` noise scales off (an outlier: a marker
swap, a dropped frame, a force spike) pulls with a constant force instead of one growing with
it. Its minimum is found by IRLS: with weights ``w_i = min(1, C / |r_i|)`` frozen at the current
constants, Levenberg-Marquardt minimises ``0.5 sum w_i r_i^2`` (the rows ``sqrt(w_i) r_i``,
:attr:`fitting.calibrate.CalibrationProblem.row_weights`); then the weights are recomputed, until
none changes by more than :data:`WEIGHT_TOL` (at most :data:`MAX_ROUNDS` rounds; else the fit
says it did not converge). The prior rows keep weight 1. The default ``C = 1.345`` keeps 95 %
of least squares' efficiency on Gaussian noise.

The uncertainty is then that of the weighted rows at the end (``sqrt(w_i) r_i``); the verdict's
reduced chi-squared is the robust one (:func:`fitting.calibration_verdict.judge_fit`,
``robust``): the plain residuals' scale from their median absolute value, which a few gross
outliers do not move (their weighted squares would: ``C |r_i|`` each). The RMS residuals printed
are the plain ones.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["DEFAULT_HUBER_SCALE", "LOSSES", "MAX_ROUNDS", "WEIGHT_TOL", "huber_weights", "irls_fit"]

LOSSES = ("l2", "huber")
DEFAULT_HUBER_SCALE = 1.345
WEIGHT_TOL = 1e-3
MAX_ROUNDS = 12


def huber_weights(residuals: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights of Huber's loss, ``min(1, scale / |r|)``, ``(m,)``, for scaled residuals ``(m,)``."""
    magnitude = np.abs(np.asarray(residuals, np.float64))
    return np.minimum(1.0, scale / np.maximum(magnitude, 1e-300))


def irls_fit(problem, fit: Callable[[np.ndarray], dict[str, Any]], theta: np.ndarray, scale: float) -> dict[str, Any]:
    """Huber's loss minimised by IRLS from ``theta``.

    Args:
        problem: a :class:`fitting.calibrate.CalibrationProblem` (or a stacked one) in its current
            shooting; its ``row_weights`` are set here and left at the final weights' roots.
        fit: runs the least-squares solver from a ``theta`` and returns
            :func:`fitting.calibration_fit.fit_problem`'s dict.
        theta: the start, log-constants ``(n,)``.
        scale: Huber's ``C`` in noise scales.

    Returns:
        The last round's result with ``steps``, ``forward_passes``, ``seconds`` summed over the
        rounds, ``rounds``, ``outliers`` (rows with weight below 1 at the end) and ``converged``
        false (with a message) when the weights did not settle within :data:`MAX_ROUNDS`.
    """
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"--huber-scale: got {scale}; expected a positive number of noise scales")
    a, b = problem.prior_slice()
    prior_rows = b - a
    previous, totals, result = None, {"steps": 0, "forward_passes": 0, "backward_passes": 0, "seconds": 0.0}, None
    settled = False
    for rounds in range(1, MAX_ROUNDS + 1):
        problem.row_weights = None
        weights = huber_weights(problem.host_residuals(theta), scale)
        if prior_rows:
            weights[len(weights) - prior_rows:] = 1.0
        if previous is not None and np.max(np.abs(weights - previous)) <= WEIGHT_TOL:
            settled = True
            break
        problem.row_weights = np.sqrt(weights)
        result = fit(theta)
        theta = result["theta"]
        for key in totals:
            totals[key] += result[key]
        previous = weights
    problem.row_weights = np.sqrt(weights)
    out = {**result, **totals, "theta": theta, "rounds": rounds, "outliers": int(np.sum(weights < 1.0))}
    if not settled:
        out["converged"] = False
        out["message"] = (f"not converged: the Huber weights still changed by {np.max(np.abs(weights - previous)):.3g}"
                          f" > {WEIGHT_TOL:g} after {MAX_ROUNDS} IRLS rounds")
    return out
