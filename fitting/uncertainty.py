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

**Unidentifiable directions.** With ``J = U S V^T``, a direction ``v_i`` of the log-constants is
unidentifiable when the data barely see it: ``s_i < 1e-4 s_max`` (``cond(J^T J) >= 1e8``,
numerically null) or its standard error ``sigma / s_i`` exceeds 1 in log space (the data fix
that combination to no better than a factor ``e``; ``sigma^2`` the pooled residual variance,
1 with known noise). The covariance is then taken on the identifiable directions only
(pseudo-inverse), and every constant with a component above 0.1 on an unidentifiable
direction gets an infinite standard error: its interval is unbounded.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

__all__ = ["GaussNewtonUncertainty", "gauss_newton_uncertainty"]

#: A direction whose singular value of ``J`` is below this fraction of the largest is null.
NULL_RATIO = 1e-4
#: A direction whose standard error in log space exceeds this is not determined by the data.
LOG_ERROR_LIMIT = 1.0
#: A constant with a component above this on an unidentifiable direction is unidentifiable.
COMPONENT_LIMIT = 0.1


@dataclasses.dataclass
class GaussNewtonUncertainty:
    """The Gauss-Newton covariance at an optimum.

    Attributes:
        covariance: of the log-parameters (and linear ones, ``linear``), ``(n, n)``.
        standard_error: of the constants themselves (delta method), ``(n,)``.
        relative_error: ``se(c) / c`` = the log-parameters' standard errors, ``(n,)``.
        correlation: ``(n, n)``.
        condition_number: of ``J^T J`` (2-norm); large means poorly identified combinations
            (``inf`` when singular).
        noise_variance: ``s_c^2`` per target (1 when the noise scales are known).
        residual_count: ``m``; parameter_count: ``n``.
        singular_values: of ``J``, largest first, ``(n,)``.
        directions: the right singular vectors, one per row, ``(n, n)``.
        direction_error: standard error along each direction in log space, ``(n,)``.
        unidentifiable_directions: indices of the unidentifiable directions (module doc).
        identifiable: per constant, False when it has an infinite standard error, ``(n,)``.
    """

    covariance: np.ndarray
    standard_error: np.ndarray
    relative_error: np.ndarray
    correlation: np.ndarray
    condition_number: float
    noise_variance: dict[str, float]
    residual_count: int
    parameter_count: int
    singular_values: np.ndarray
    directions: np.ndarray
    direction_error: np.ndarray
    unidentifiable_directions: list[int]
    identifiable: np.ndarray


def gauss_newton_uncertainty(jacobian: np.ndarray, residuals: np.ndarray, values: np.ndarray,
                             targets: Mapping[str, np.ndarray] | None = None, *,
                             known_noise: bool = False, known: tuple[str, ...] = (),
                             linear: np.ndarray | None = None) -> GaussNewtonUncertainty:
    """Covariance and standard errors from the Jacobian at the optimum.

    Args:
        jacobian: ``dr/dtheta`` at the optimum, ``(m, n)`` (``theta`` = log-constants).
        residuals: ``r`` at the optimum, ``(m,)`` (scaled by the noise scales).
        values: the fitted constants ``exp(theta)``, ``(n,)``.
        targets: target name -> the indices of its rows (default: one target, every row).
        known_noise: the noise scales were the true standard deviations (``s_c = 1``).
        known: targets whose rows have unit variance whatever ``known_noise`` (a prior's rows).
        linear: per parameter, 0 where ``theta`` is a log-constant, else the unit ``u`` of a
            parameter fitted as such (a delay, ``value = u theta``): its standard error is ``u``
            times that of ``theta``, its relative error that over ``|value|``.

    Returns:
        The covariance on the identifiable directions; unidentifiable constants get infinite
        standard errors (module doc). Fewer residuals than parameters: every constant is
        unidentifiable.

    Raises:
        ValueError: shapes that do not match, or non-finite entries.
    """
    jacobian = np.asarray(jacobian, dtype=np.float64)
    residuals = np.asarray(residuals, dtype=np.float64)
    m, n = jacobian.shape
    if residuals.shape != (m,):
        raise ValueError(f"residuals: got shape {residuals.shape}; expected ({m},) like the Jacobian's rows")
    if not (np.all(np.isfinite(jacobian)) and np.all(np.isfinite(residuals))):
        raise ValueError("the Jacobian or the residuals at the optimum hold non-finite values")
    targets = {"all": np.arange(m)} if targets is None else {k: np.asarray(v) for k, v in targets.items()}
    # V is (n, n) either way; U stays (m, min(m, n)) (a full U would be m x m: 38 GiB on the benchmark).
    _, singular, directions = np.linalg.svd(jacobian, full_matrices=m < n)
    singular = np.concatenate([singular, np.zeros(n - len(singular))])
    condition = float((singular[0] / singular[-1]) ** 2) if singular[-1] > 0 else float("inf")
    dof = m - n
    pooled = 1.0 if known_noise else (float(residuals @ residuals / dof) if dof > 0 else float("inf"))
    with np.errstate(divide="ignore"):
        direction_error = np.where(singular > 0, np.sqrt(pooled) / np.where(singular > 0, singular, 1.0), np.inf)
    weak = (singular <= NULL_RATIO * singular[0]) | ~(direction_error <= LOG_ERROR_LIMIT) | (dof <= 0)
    kept = directions[~weak]
    a_pinv = kept.T @ np.diag(1.0 / singular[~weak] ** 2) @ kept if len(kept) else np.zeros((n, n))
    b = np.zeros((n, n))
    variance = {}
    for name, rows in targets.items():
        r = residuals[rows]
        if known_noise or name in known:
            s2 = 1.0
        else:
            share = len(rows) - n * len(rows) / m
            s2 = float(r @ r / share) if share > 0 else float("inf")
        variance[name] = s2
        j = jacobian[rows]
        b += (s2 if np.isfinite(s2) else 0.0) * (j.T @ j)
    covariance = a_pinv @ b @ a_pinv
    covariance = 0.5 * (covariance + covariance.T)
    identifiable = ~np.any(np.abs(directions[weak]) > COMPONENT_LIMIT, axis=0) if weak.any() else np.ones(n, bool)
    relative = np.where(identifiable, np.sqrt(np.clip(np.diag(covariance), 0.0, None)), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        correlation = covariance / np.outer(relative, relative)
    correlation[~np.isfinite(correlation)] = np.nan
    values = np.asarray(values, dtype=np.float64)
    unit = np.zeros(n) if linear is None else np.asarray(linear, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):  # 0 * inf where unused: discarded by where
        standard_error = np.where(unit > 0, unit * relative, values * relative)
        relative = np.where(unit > 0, standard_error / np.abs(values), relative)
    return GaussNewtonUncertainty(covariance=covariance, standard_error=standard_error,
                                  relative_error=relative, correlation=correlation, condition_number=condition,
                                  noise_variance=variance, residual_count=m, parameter_count=n,
                                  singular_values=singular, directions=directions, direction_error=direction_error,
                                  unidentifiable_directions=[int(i) for i in np.nonzero(weak)[0]],
                                  identifiable=identifiable)
