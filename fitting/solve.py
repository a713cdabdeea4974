"""Driving optimistix solvers one step at a time, with progress and a convergence history.

The rollout is reverse-mode only (Warp's tape), so:

- **BFGS** (``optimistix.BFGS``) minimises the scalar loss; each step evaluates the loss at
  one trial point (one forward rollout) and, when the backtracking line search accepts it,
  its gradient (one backward pass, ``autodiff_mode = "bwd"``);
- **Levenberg-Marquardt / Gauss-Newton** (``optimistix.LevenbergMarquardt`` /
  ``GaussNewton``) fit the residual vector with a reverse-mode Jacobian
  (``options={"jac": "bwd"}``): one backward pass per residual, so they pay only when the
  residual vector is short (few keyframe targets and no per-step workspace/force terms).

The solvers are stepped from Python (optimistix's ``init``/``step``/``terminate``), which
lets every step print a progress line and be recorded.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

jax.config.update("jax_enable_x64", True)
# With asynchronous dispatch on the CPU, a process pinned to one core hung after the jitted
# solve, at the next eager call of the rollout's pure_callback (the main thread waiting on
# XLA's in-flight semaphore, every worker idle; cf. jax-ml/jax#25861). Dispatching inline
# avoids it; it must be set before JAX creates its CPU client.
jax.config.update("jax_cpu_enable_async_dispatch", False)

__all__ = ["SolveResult", "solve"]


@dataclasses.dataclass
class SolveResult:
    """What a solve did.

    Attributes:
        y: the best knots found (the last accepted point).
        history: one dict per solver step: ``step``, ``loss`` (at the last accepted point),
            ``terms`` (the loss's parts; for BFGS those of the accepted point before it, as
            optimistix hands the aux back one step late), ``grad_norm`` (BFGS), ``accepted`` (steps so far),
            ``elapsed`` [s], ``forward``/``backward`` (rollout passes so far).
        converged: whether the solver's own termination test was met (else max_steps ran out).
        result: optimistix's result message.
        seconds: wall time [s].
    """

    y: dict
    history: list[dict]
    converged: bool
    result: str
    seconds: float


def solve(objective, y0: dict, *, method: str = "bfgs", max_steps: int = 60, rtol: float = 1e-6,
          atol: float = 1e-8, progress: bool | Callable[[str], None] = True,
          counter: Callable[[], dict] | None = None, y_scale: dict | None = None,
          max_seconds: float | None = None) -> SolveResult:
    """Minimises ``objective`` (an :class:`AuthoringObjective`) from the knots ``y0``.

    Args:
        method: ``"bfgs"`` (scalar loss), ``"lm"`` or ``"gauss_newton"`` (residual vector).
        max_steps: solver steps at most (each one forward rollout, plus a backward one when
            a BFGS step is accepted, or one per residual for a least-squares Jacobian).
        rtol, atol: optimistix's Cauchy termination on the change of ``y`` and of the loss.
        progress: True prints one line per step to stderr; a callable receives the lines.
        counter: returns ``{"forward": n, "backward": m}`` rollout passes so far (for the history).
        y_scale: a typical change of each coordinate of ``y`` (same structure). The solver
            works on ``z = y / y_scale`` and on the loss divided by its value at ``y0``, so
            that BFGS's first steps (identity Hessian) are of about the right size; the
            history reports the loss unscaled.
        max_seconds: wall-time budget [s]: no step starts after it (None: no limit).
    """
    say = progress if callable(progress) else ((lambda line: print(line, file=sys.stderr, flush=True))
                                               if progress else (lambda line: None))
    scale = jax.tree.map(jnp.asarray, y_scale) if y_scale is not None else jax.tree.map(jnp.ones_like, y0)
    unscale = lambda z: jax.tree.map(lambda a, b: a * b, z, scale)  # noqa: E731
    loss0 = float(objective.loss(y0))
    if not (np.isfinite(loss0) and loss0 > 0.0):
        raise ValueError(f"the loss at the initial knots is {loss0}; expected a finite positive number")
    if method == "bfgs":
        solver = optx.BFGS(rtol=rtol, atol=atol)

        def fn(z, args):
            loss, terms = objective.loss_terms(unscale(z))
            return loss / loss0, terms

        options = {"autodiff_mode": "bwd"}
        f_struct = jax.ShapeDtypeStruct((), jnp.float64)
    elif method in ("lm", "gauss_newton"):
        solver = (optx.LevenbergMarquardt(rtol=rtol, atol=atol) if method == "lm"
                  else optx.GaussNewton(rtol=rtol, atol=atol))

        def fn(z, args):
            residuals = objective.residuals(unscale(z))
            return (jnp.concatenate([r.ravel() for r in residuals.values()]) / np.sqrt(loss0),
                    {k: 0.5 * jnp.sum(r**2) for k, r in residuals.items()})

        options = {"jac": "bwd"}
        f_struct = jax.eval_shape(lambda z: fn(z, None)[0], y0)
    else:
        raise ValueError(f"method: got {method!r}; expected 'bfgs', 'lm' or 'gauss_newton'")
    z0 = jax.tree.map(lambda a, b: a / b, y0, scale)
    aux_struct = jax.eval_shape(lambda z: fn(z, None)[1], z0)
    tags = frozenset()
    args = None
    state = solver.init(fn, z0, args, options, f_struct, aux_struct, tags)

    @eqx.filter_jit
    def step(y, state):
        y, state, aux = solver.step(fn, y, args, options, state, tags)
        done, result = solver.terminate(fn, y, args, options, state, tags)
        return y, state, aux, done, result

    z = z0
    history = []
    start = time.perf_counter()
    converged, result = False, optx.RESULTS.successful
    say(f"{'step':>5s} {'loss':>13s} {'|grad|':>11s} {'accepted':>8s} {'elapsed':>9s}")
    for i in range(max_steps + 1):
        z, state, aux, done, result = step(z, state)
        entry = {"step": i, "accepted": int(state.num_accepted_steps) if hasattr(state, "num_accepted_steps")
                 else i, "elapsed": time.perf_counter() - start}
        if method == "bfgs":
            entry["loss"] = float(state.f_info.f) * loss0
            grad = jax.tree.map(lambda g, s: g * loss0 / s, state.f_info.grad, scale)  # dL/dy
            entry["grad_norm"] = float(jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(grad))))
        else:
            entry["loss"] = float(sum(aux.values())) if aux else float("nan")
            entry["grad_norm"] = float("nan")
        entry["terms"] = {k: float(v) for k, v in aux.items()}
        if counter is not None:
            entry.update(counter())
        # Step 0 only evaluates the start point; its recorded values are those of y0.
        history.append(entry)
        say(f"{i:5d} {entry['loss']:13.6e} {entry['grad_norm']:11.4e} {entry['accepted']:8d} "
            f"{entry['elapsed']:8.1f}s")
        if bool(done) and i > 0:
            converged = result == optx.RESULTS.successful
            break
        if max_seconds is not None and time.perf_counter() - start >= max_seconds:
            break
    return SolveResult(y=unscale(z), history=history, converged=bool(converged),
                       result=str(optx.RESULTS[result]) if hasattr(optx.RESULTS, "__getitem__") else str(result),
                       seconds=time.perf_counter() - start)
