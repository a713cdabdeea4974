"""Levenberg-Marquardt for small problems with expensive residuals (NumPy, no JIT).

Each step solves the damped normal equations with Marquardt's scaling,
``(J^T J + lam D) dx = -J^T r`` with ``D = diag(J^T J)`` (floored), raises ``lam`` until
the step fits the trust region ``|dx|_inf <= max_step``, evaluates the trial point
and accepts it when the cost ``0.5 |r|^2`` drops and the caller's ``feasible`` test passes;
``lam`` follows Nielsen's update (Madsen, Nielsen & Tingleff, "Methods for non-linear least
squares problems", 2004, sec. 3.2). The solver stops when the caller's ``done`` says the
answer is right, at a stationary point (``|J^T r|_inf <= gtol (1 + cost)``), when an accepted
step changed every ``x`` by less than ``step_tol`` (and every residual by less than
``residual_tol``: the caller's "converged"),
when steps no longer change ``x`` or the cost (``xtol``, ``ftol``), or when the step or time
budget runs out; :class:`LMResult` says which, in ``status``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

__all__ = ["LMResult", "levenberg_marquardt"]

# Marquardt's scaling D = diag(J^T J), floored at this fraction of its largest entry: a
# coordinate that barely moves the residuals (only a weak regulariser pulls on it) is damped
# like the others instead of taking huge, cheap steps.
DIAGONAL_FLOOR = 1e-2
STATUSES = ("done", "stationary", "small_step", "no_progress", "max_steps", "max_seconds")


@dataclasses.dataclass
class LMResult:
    """What a Levenberg-Marquardt run did.

    Attributes:
        x: the last accepted point ``(n,)``; residuals: its residuals ``(m,)``; cost: ``0.5 |r|^2``.
        jacobian: the Jacobian at ``x`` ``(m, n)`` (the last one computed).
        status: ``"done"`` (the caller's test passed), ``"stationary"`` (gradient ~ 0),
            ``"small_step"`` (a step within ``step_tol``), ``"no_progress"`` (steps stopped changing
            x or the cost), ``"max_steps"``, ``"max_seconds"``.
        steps: iterations run (Jacobians computed); history: one dict per iteration.
    """

    x: np.ndarray
    residuals: np.ndarray
    cost: float
    jacobian: np.ndarray
    status: str
    steps: int
    history: list[dict]


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray],
                        jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray], x0: np.ndarray, *,
                        max_steps: int = 50, deadline: float | None = None,
                        done: Callable[[np.ndarray, np.ndarray], bool] | None = None,
                        feasible: Callable[[np.ndarray], bool] | None = None,
                        gtol: float = 1e-10, xtol: float = 1e-10, ftol: float = 1e-12,
                        lam0: float = 1e-3, max_step: float | None = None,
                        secant_rows: int = 0, exact_rows: Callable[[np.ndarray], np.ndarray] | None = None,
                        stall_steps: int | None = None, stall_rtol: float = 1e-2,
                        step_tol: float | Callable[[np.ndarray], np.ndarray] | None = None,
                        residual_tol: float | None = None,
                        on_step: Callable[[dict], None] | None = None) -> LMResult:
    """Minimises ``0.5 |r(x)|^2``.

    Args:
        residuals: ``x (n,) -> r (m,)``; may return non-finite values (the trial is rejected).
        jacobian: ``(x, r(x)) -> J (m, n)`` (the expensive, exact one).
        x0: the start ``(n,)``.
        max_steps: iterations (trial points) at most.
        deadline: ``time.perf_counter()`` value after which no new step starts.
        done: ``(x, r) -> bool``, checked at every accepted point (and the start).
        feasible: ``x -> bool``, called after ``residuals(x)`` on each trial point; an
            infeasible trial is rejected like a cost increase.
        gtol, xtol, ftol: stationarity, step and cost-change tolerances (see the module).
        lam0: initial damping (times ``D``).
        max_step: the largest ``|dx|_inf`` of a trial step (``lam`` grows until it fits), or None.
        secant_rows: with ``k > 0``, the first ``k`` rows of ``J`` are not recomputed after each
            step but updated from it (Broyden's rank-one secant update, as in the secant
            version of L-M of Madsen, Nielsen & Tingleff, sec. 3.4), and the other rows come
            from ``exact_rows(x)``; ``jacobian`` is called again only when two trials in a row
            fail, or before the run would stop at a stationary point or for lack of progress.
        exact_rows: ``x -> J[k:]`` (cheap), with ``secant_rows``.
        stall_steps: with ``N``, the run stops as ``"no_progress"`` when the last ``N`` accepted
            steps lowered the cost by less than ``stall_rtol`` of it (after a fresh Jacobian,
            with ``secant_rows``): a crawl along a valley that would eat the whole budget.
        step_tol: with ``t`` (a number, or ``J -> (n,)`` tolerances per coordinate, evaluated on
            each fresh Jacobian), the run stops as ``"small_step"`` after an accepted step that
            changed every ``x_i`` by at most ``t_i`` and every residual by at most
            ``residual_tol`` (when given): a Cauchy test, as optimistix's; with ``secant_rows``
            the step must have been taken with a fresh Jacobian.
        on_step: receives each iteration's history entry.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    r = np.asarray(residuals(x), dtype=np.float64)
    if not np.all(np.isfinite(r)):
        raise ValueError("levenberg_marquardt: the residuals at the start are not finite")
    cost = 0.5 * float(r @ r)
    history = []
    start = time.perf_counter()
    if done is not None and done(x, r):
        return LMResult(x, r, cost, np.zeros((len(r), len(x))), "done", 0, history)
    jac, fresh, jacobians = np.asarray(jacobian(x, r), dtype=np.float64), True, 1
    lam, nu, failures = lam0, 2.0, 0
    status = "max_steps"

    def tolerance():
        return None if step_tol is None else (step_tol(jac) if callable(step_tol) else step_tol)

    tol = tolerance()

    def refresh():
        nonlocal jac, fresh, jacobians, failures, costs, tol
        jac, fresh, failures = np.asarray(jacobian(x, r), dtype=np.float64), True, 0
        jacobians += 1
        costs = [cost]
        tol = tolerance()

    step = 0
    costs = [cost]  # at the accepted points since the last fresh Jacobian
    while step < max_steps:
        if deadline is not None and time.perf_counter() >= deadline:
            status = "max_seconds"
            break
        grad = jac.T @ r
        if np.max(np.abs(grad), initial=0.0) <= gtol * (1.0 + cost):
            if not fresh:
                refresh()
                continue
            status = "stationary"
            break
        jtj = jac.T @ jac
        diag = np.maximum(np.diag(jtj), DIAGONAL_FLOOR * max(np.max(np.diag(jtj)), 1e-300))
        while True:
            try:
                dx = np.linalg.solve(jtj + lam * np.diag(diag), -grad)
            except np.linalg.LinAlgError:
                lam, nu = lam * nu, nu * 2.0
                continue
            if max_step is not None and np.max(np.abs(dx), initial=0.0) > max_step:
                lam, nu = lam * nu, nu * 2.0  # a trust region: more damping until the step fits
                continue
            break
        step += 1
        trial = x + dx
        r_trial = np.asarray(residuals(trial), dtype=np.float64)
        finite = bool(np.all(np.isfinite(r_trial)))
        ok = finite and (feasible is None or feasible(trial))
        cost_trial = 0.5 * float(r_trial @ r_trial) if ok else np.inf
        predicted = -(grad @ dx) - 0.5 * dx @ jtj @ dx
        rho = (cost - cost_trial) / predicted if predicted > 0 else -1.0
        was_fresh = fresh  # the Jacobian this step was taken with
        if secant_rows and finite:
            k = secant_rows
            jac[:k] += np.outer(r_trial[:k] - r[:k] - jac[:k] @ dx, dx) / float(dx @ dx)
            fresh = False
        accepted = ok and cost_trial < cost and rho > 0
        if accepted:
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu, failures = 2.0, 0
            small_x = np.linalg.norm(dx) <= xtol * (np.linalg.norm(x) + xtol)
            small_f = cost - cost_trial <= ftol * cost
            cauchy = tol is not None and bool(np.all(np.abs(dx) <= tol)) and \
                (residual_tol is None or np.max(np.abs(r_trial - r), initial=0.0) <= residual_tol)
            taken_fresh = was_fresh or not secant_rows
            x, r, cost = trial, r_trial, cost_trial
        else:
            lam, nu, failures = lam * nu, nu * 2.0, failures + 1
        entry = {"step": step, "cost": cost, "grad_inf": float(np.max(np.abs(grad))), "lambda": float(lam),
                 "accepted": bool(accepted), "jacobians": jacobians, "elapsed": time.perf_counter() - start}
        history.append(entry)
        if on_step is not None:
            on_step(entry)
        if accepted:
            costs.append(cost)
            if done is not None and done(x, r):
                status = "done"
                break
            if cauchy:
                if taken_fresh:
                    status = "small_step"
                    break
                refresh()
                continue
            if stall_steps and len(costs) > stall_steps and costs[-1 - stall_steps] - cost < stall_rtol * cost:
                if len(costs) == stall_steps + 1 or not secant_rows:  # the window began with a fresh J
                    status = "no_progress"
                    break
                refresh()
                continue
            if small_x or small_f:
                if fresh or not secant_rows:
                    status = "no_progress"
                    break
                refresh()
                continue
            if secant_rows:
                if exact_rows is not None:
                    jac[secant_rows:] = exact_rows(x)
            else:
                refresh()
        elif lam > 1e16:
            if fresh or not secant_rows:
                status = "no_progress"
                break
            lam, nu = lam0, 2.0
            refresh()
        elif secant_rows and failures >= 2 and not fresh:
            refresh()
    return LMResult(x, r, cost, jac, status, len(history), history)
