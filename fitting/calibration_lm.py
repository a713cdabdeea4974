"""The ``lm-fd`` calibration solver: Levenberg-Marquardt on forward rollouts alone, with secant
updates of a batched finite-difference Jacobian (docs/calibration.md, "Solvers").

The residuals of a session are ~10^5 rows in ~10 constants, and each evaluation is a rollout of
the session. A forward-difference Jacobian costs ``n + 1`` rollouts (run together as the worlds of
one batched marionette, :meth:`fitting.calibrate.CalibrationProblem.fd_jacobian`). Recomputing it
at every step (optimistix's ``LevenbergMarquardt`` with ``jac="fwd"``, the solver before) made
each step cost ``n + 2`` rollouts, 13 or 14 for 12 constants. Here (:func:`fitting.least_squares.
levenberg_marquardt` with ``secant_rows``) the Jacobian is computed once and then updated from
each step by Broyden's rank-one secant update (every row, the prior's too), so a step costs one
rollout; a fresh Jacobian is computed when two trials in a row fail, and before the run may stop.

Convergence is a Cauchy test on the solver variable ``u = (theta - theta_start) / STEP_UNIT``
(one unit is a 1 % change of a constant): a step taken with a fresh Jacobian moved every constant
by less than :data:`STEP_FRACTION` of its standard error under the given noise scales (from that
Jacobian, ``(J^T J)^-1``), and by no less than ``atol`` nor more than 1 % of itself. The test the
optimistix solver used, every constant by less than ``atol`` (1e-5 of itself) and every residual
by less than a thousandth of its noise, asked for precision that no data supports: its last
steps moved the constants by hundredths of their standard errors at 13 rollouts each. Bounds
(``--bounds``) by projection, as before: outside them a constant stays at its bound.
"""

from __future__ import annotations

import time

import numpy as np

from .least_squares import levenberg_marquardt

__all__ = ["fit_lm_fd"]

#: Steps (trial points) of the secant solver per step budget of the solver it replaced: it takes
#: about as many steps but each costs one rollout, not n + 2 (``--max-steps`` keeps its meaning:
#: Jacobians, roughly).
SECANT_STEPS_PER_STEP = 4
#: Converged: a step taken with a fresh Jacobian moved every constant by less than this fraction of
#: its standard error (under the noise scales given; the residuals are scaled by them).
STEP_FRACTION = 0.1


def fit_lm_fd(problem, theta_start: np.ndarray, *, max_steps: int, atol: float, step_unit: float) -> dict:
    """Minimises ``0.5 |r(theta)|^2`` from ``theta_start`` with forward rollouts only; returns the
    dict :func:`fitting.calibration_fit.fit_problem` returns (``theta``, ``steps``, ``converged``,
    ``message``, ``rows``, ``forward_passes``, ``backward_passes``, ``seconds``)."""
    before = dict(problem.counts)
    start = time.perf_counter()
    theta0 = np.asarray(theta_start, dtype=np.float64)
    low, high = (np.asarray(b, dtype=np.float64) for b in getattr(problem, "log_bounds", (-np.inf, np.inf)))
    low, high = np.broadcast_to(low, theta0.shape), np.broadcast_to(high, theta0.shape)

    def theta_of(u):
        return np.clip(theta0 + step_unit * u, low, high)

    rows = []  # the residual count, from the first evaluation

    def residuals(u):
        # A trial whose constants overflow (a long step along a flat direction: theta > ~709) is
        # not simulated: non-finite residuals make the solver reject it and shrink its step.
        theta = theta_of(u)
        with np.errstate(over="ignore"):
            finite = bool(np.all(np.isfinite(np.exp(theta))))
        if not finite and rows:
            return np.full(rows[0], np.nan)
        r = problem.host_residuals(theta)
        rows[:] = [len(r)]
        return r

    def jacobian(u, r):
        theta = theta_of(u)
        _, jac = problem.fd_jacobian(theta, central=False)
        jac = jac * step_unit
        free = (theta0 + step_unit * u > low) & (theta0 + step_unit * u < high)
        jac[:, ~free] = 0.0  # held at a bound by the projection: no derivative
        return jac

    def step_tolerance(jac):
        # A tenth of each constant's standard error under the given noise (the residuals are scaled
        # by it), in u units; never below atol (the old test) nor above one unit (1 %).
        jtj = jac.T @ jac
        try:
            sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(jtj, rcond=1e-12, hermitian=True)), 0.0, None))
        except np.linalg.LinAlgError:
            sd = np.zeros(len(jtj))
        return np.clip(STEP_FRACTION * sd, atol, 1.0)

    count = problem.residual_count if problem.active_rows is None else len(problem.active_rows)
    result = levenberg_marquardt(residuals, jacobian, np.zeros_like(theta0),
                                 max_steps=int(max_steps) * SECANT_STEPS_PER_STEP, step_tol=step_tolerance,
                                 xtol=0.0, ftol=0.0, gtol=0.0, secant_rows=count)
    converged = result.status in ("small_step", "stationary")
    message = "converged" if converged else {
        "no_progress": "not converged: the steps stopped lowering the cost before they became small",
        "max_steps": "not converged: the step budget ran out",
    }.get(result.status, f"not converged: {result.status}")
    return {"theta": theta_of(result.x), "steps": result.steps, "converged": converged, "message": message,
            "rows": None, "forward_passes": problem.counts["forward"] - before["forward"],
            "backward_passes": problem.counts["backward"] - before["backward"],
            "seconds": time.perf_counter() - start}
