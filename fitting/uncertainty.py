"""Uncertainty of fitted constants from the Gauss-Newton approximation.

At the optimum ``theta*`` of ``0.5 |r(theta)|^2`` (``r`` the residuals divided by their noise
scales, ``m`` of them, ``n`` parameters), the estimate's covariance is approximately

    cov(theta*) = A^-1 B A^-1,   A = J^T J,   B = sum_c s_c^2 J_c^T J_c

with ``J = dr/dtheta`` at the optimum and ``J_c`` its rows of target ``c`` (body centres,
feedback forces), whose scaled residuals have variance ``s_c^2``: ``1`` when the noise scales
given are the true ones (``known_noise``), else estimated from the residuals,
``s_c^2 = |r_c|^2 / (m_c - n m_c / m)`` (the ``n`` degrees of freedom the fit used, shared in
proportion). With a single target this is the familiar ``s^2 (J^T J)^-1``. The parameters are
logarithms, so the constants' standard errors follow by the delta method,
``se(c) = c se(theta)`` (first order; the relative error is ``se(theta)``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

__all__ = ["GaussNewtonUncertainty", "gauss_newton_uncertainty"]


@dataclasses.dataclass
class GaussNewtonUncertainty:
    """The Gauss-Newton covariance at an optimum.

    Attributes:
        covariance: of the log-parameters, ``(n, n)``.
        standard_error: of the constants themselves (delta method), ``(n,)``.
        relative_error: ``se(c) / c`` = the log-parameters' standard errors, ``(n,)``.
        correlation: ``(n, n)``.
        condition_number: of ``J^T J`` (2-norm); large means poorly identified combinations.
        noise_variance: ``s_c^2`` per target (1 when the noise scales are known).
        residual_count: ``m``; parameter_count: ``n``.
    """

    covariance: np.ndarray
    standard_error: np.ndarray
    relative_error: np.ndarray
    correlation: np.ndarray
    condition_number: float
    noise_variance: dict[str, float]
    residual_count: int
    parameter_count: int


def gauss_newton_uncertainty(jacobian: np.ndarray, residuals: np.ndarray, values: np.ndarray,
                             targets: Mapping[str, np.ndarray] | None = None, *,
                             known_noise: bool = False) -> GaussNewtonUncertainty:
    """Covariance and standard errors from the Jacobian at the optimum.

    Args:
        jacobian: ``dr/dtheta`` at the optimum, ``(m, n)`` (``theta`` = log-constants).
        residuals: ``r`` at the optimum, ``(m,)`` (scaled by the noise scales).
        values: the fitted constants ``exp(theta)``, ``(n,)``.
        targets: target name -> the indices of its rows (default: one target, every row).
        known_noise: the noise scales were the true standard deviations (``s_c = 1``).

    Raises:
        ValueError: fewer residuals than parameters, non-finite entries, or ``J^T J`` singular
            (a constant the data do not determine).
    """
    jacobian = np.asarray(jacobian, dtype=np.float64)
    residuals = np.asarray(residuals, dtype=np.float64)
    m, n = jacobian.shape
    if residuals.shape != (m,):
        raise ValueError(f"residuals: got shape {residuals.shape}; expected ({m},) like the Jacobian's rows")
    if m <= n:
        raise ValueError(f"{m} residuals for {n} parameters: the Gauss-Newton uncertainty needs more residuals "
                         "than parameters")
    if not (np.all(np.isfinite(jacobian)) and np.all(np.isfinite(residuals))):
        raise ValueError("the Jacobian or the residuals at the optimum hold non-finite values")
    targets = {"all": np.arange(m)} if targets is None else {k: np.asarray(v) for k, v in targets.items()}
    a = jacobian.T @ jacobian
    singular = np.linalg.svd(a, compute_uv=False)
    condition = float(singular[0] / singular[-1]) if singular[-1] > 0 else float("inf")
    if not condition < 1e14:
        raise ValueError(f"J^T J is singular (condition number {condition:.3g}): some combination of the "
                         "constants does not change the residuals; fit fewer constants or richer motion")
    a_inv = np.linalg.inv(a)
    b = np.zeros_like(a)
    variance = {}
    for name, rows in targets.items():
        r = residuals[rows]
        if known_noise:
            s2 = 1.0
        else:
            dof = len(rows) - n * len(rows) / m
            s2 = float(r @ r / dof)
        variance[name] = s2
        j = jacobian[rows]
        b += s2 * (j.T @ j)
    covariance = a_inv @ b @ a_inv
    covariance = 0.5 * (covariance + covariance.T)
    relative = np.sqrt(np.diag(covariance))
    correlation = covariance / np.outer(relative, relative)
    return GaussNewtonUncertainty(covariance=covariance, standard_error=np.asarray(values) * relative,
                                  relative_error=relative, correlation=correlation, condition_number=condition,
                                  noise_variance=variance, residual_count=m, parameter_count=n)
