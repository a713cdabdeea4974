"""Running a calibration: the solver, the residuals before and after, the uncertainty.

:func:`calibrate_session` reads a session, fits the chosen constants with one of
:data:`fitting.calibrate.SOLVERS` and returns a :class:`CalibrationResult`;
:mod:`fitting.calibration_report` writes it out (table, JSON, plot, scene file).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .calibrate import ENGINE_FIELDS, SOLVERS, CalibrationProblem, parse_parameters
from .calibration_data import CalibrationData, read_calibration_data
from .calibration_verdict import Verdict, judge_fit
from .uncertainty import GaussNewtonUncertainty, gauss_newton_uncertainty

__all__ = ["DEFAULT_WINDOWS", "CalibrationResult", "calibrate_session", "fit_problem", "window_steps_for"]


@dataclasses.dataclass
class CalibrationResult:
    """What a calibration found.

    Attributes:
        data: the session's inputs and targets.
        labels: parameter labels, ``"k[head]"``, ``"k_s[shared]"``, ``(n,)``.
        start, fitted: the constants before and after [N/m, N s/m], ``(n,)``.
        uncertainty: the Gauss-Newton covariance and standard errors at the optimum.
        rms_before, rms_after: RMS residual per target in its unit (``"bodies"`` [m],
            ``"feedback"`` [N]).
        residuals_before, residuals_after: unscaled residual vectors per target (body
            ``(P, bodies, 3)`` [m], feedback ``(T, B, 3)`` [N]).
        solver: the solver's name; ``solver_steps``; ``converged``: the solver converged *and*
            the fit explains the data (``verdict``); ``message``.
        verdict: the honest assessment (:mod:`fitting.calibration_verdict`): reduced chi-squared
            per target, unidentifiable constants, warnings, the exit code.
        window_steps: puppet steps per multiple-shooting window (None: one rollout).
        priors: the Gaussian priors used, ``{name: (mean, sd)}``.
        string_constants: every string's value of each fitted constant name as simulated at the
            end (fitted, or held: frozen), ``{name: (S,)}``.
        jacobian: how the uncertainty's Jacobian was computed: ``method`` (``"fd"``: forward
            differences, ``"bwd"``: reverse mode), ``rows``, ``forward_passes``,
            ``backward_passes``, ``seconds``.
        cost: rollouts and seconds of the fit alone: ``forward_passes``, ``backward_passes``,
            ``seconds``; and of the whole run (``total_seconds``).
        noise: the noise scales used (``bodies`` [m], ``feedback`` [N]); ``known_noise``.
        validation: with ``validate``, the held-out end's residuals
            (:func:`fitting.calibration_validation.held_out_residuals`; ``data`` is then the part
            fitted), else None.
        sessions: with several sessions, one dict per session: ``session`` (its path),
            ``rms_before``, ``rms_after`` per target in its unit; else None.
        delay: the recording delay of the targets behind the bar inputs: ``seconds``, ``fitted``
            (``--fit-delay``) and its ``standard_error`` [s] (None when given).
        initial_state: with ``fit_initial_state``, the refined window starts
            (:func:`_initial_state_summary`), else None. ``labels``, ``start``, ``fitted`` and
            :meth:`table` hold the constants (and the delay) only; ``uncertainty`` every unknown.
        loss: ``name`` (``"l2"``, ``"huber"``); for Huber also ``scale`` (``C``), ``rounds``
            (IRLS rounds of the last stage), ``outliers`` (rows down-weighted at the end), ``rows``.
    """

    data: CalibrationData
    parameters: list
    labels: list[str]
    start: np.ndarray
    fitted: np.ndarray
    uncertainty: GaussNewtonUncertainty
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    residuals_before: dict[str, np.ndarray]
    residuals_after: dict[str, np.ndarray]
    solver: str
    solver_steps: int
    converged: bool
    message: str
    jacobian: dict[str, Any]
    cost: dict[str, Any]
    noise: dict[str, float]
    known_noise: bool
    theta: np.ndarray
    verdict: Verdict | None = None
    window_steps: int | None = None
    priors: dict = dataclasses.field(default_factory=dict)
    string_constants: dict = dataclasses.field(default_factory=dict)
    validation: dict | None = None
    sessions: list | None = None
    loss: dict = dataclasses.field(default_factory=lambda: {"name": "l2"})
    delay: dict = dataclasses.field(default_factory=lambda: {"seconds": 0.0, "fitted": False, "standard_error": None})
    initial_state: dict | None = None

    def table(self) -> list[dict[str, Any]]:
        """One row per constant: ``label``, ``start``, ``fitted``, ``standard_error``, ``relative_error``."""
        u = self.uncertainty
        return [{"label": label, "start": float(s), "fitted": float(f), "standard_error": float(e),
                 "relative_error": float(r)}
                for label, s, f, e, r in zip(self.labels, self.start, self.fitted, u.standard_error,
                                              u.relative_error)]


def _unscaled(problem: CalibrationProblem, residuals: np.ndarray) -> dict[str, np.ndarray]:
    d, out = problem.data, {}
    for target, (a, b) in problem.target_slices().items():
        shape = (d.puppet_steps, len(d.bodies), 3) if target == "bodies" else (d.step_count, len(d.bars), 3)
        out[target] = residuals[a:b].reshape(shape) * problem.noise[target]
    return out


def _time_series(problem: CalibrationProblem, residuals: np.ndarray) -> dict[str, list[np.ndarray]]:
    """Per target, the scaled residuals in the recording's time order, one ``(steps, channels)``
    array per session (the whiteness test of :func:`fitting.calibration_verdict.judge_fit`)."""
    def steps(d: CalibrationData, target: str) -> int:
        return d.puppet_steps if target == "bodies" else d.step_count

    if not hasattr(problem, "session_data"):
        return {t: [residuals[a:b].reshape(steps(problem.data, t), -1)]
                for t, (a, b) in problem.target_slices().items()}
    out: dict[str, list[np.ndarray]] = {}
    for data, rows in zip(problem.session_data, problem.session_rows()):
        for t, index in rows.items():
            out.setdefault(t, []).append(residuals[index].reshape(steps(data, t), -1))
    return out


def _initial_state_summary(states, theta: np.ndarray) -> dict[str, Any]:
    """The refined window starts: ``windows`` (their start times [s]), ``unknowns``, the priors
    ``sigma_q`` (rad, m) and ``sigma_qd`` (rad/s, m/s), and the corrections' RMS and largest size in
    prior deviations, positions ``dq`` and velocities ``dqd`` apart."""
    block = np.asarray(theta[states.offset:states.offset + states.count]).reshape(len(states.starts), 2, -1)
    return {"windows": [a * states.puppet_dt for a in states.starts], "unknowns": states.count,
            "sigma_q": states.sigma_q, "sigma_qd": states.sigma_qd,
            "rms_dq": float(np.sqrt(np.mean(block[:, 0] ** 2))), "rms_dqd": float(np.sqrt(np.mean(block[:, 1] ** 2))),
            "max_dq": float(np.abs(block[:, 0]).max()), "max_dqd": float(np.abs(block[:, 1]).max())}


def _rms(residuals: Mapping[str, np.ndarray]) -> dict[str, float]:
    """RMS over every coordinate of each target."""
    return {k: float(np.sqrt(np.mean(v**2))) for k, v in residuals.items()}


def _rms_over(problem, residuals: np.ndarray) -> dict[str, float]:
    """RMS per target in its unit over every session of a stacked problem."""
    return {t: float(np.sqrt(np.mean(residuals[index] ** 2)) * problem.noise[t])
            for t, index in problem.target_rows().items() if t != "prior"}


#: The solvers' variable is ``u = (theta - theta_start) / STEP_UNIT``: one unit is a 1 % change of a
#: constant, so one absolute tolerance can speak of constants and residuals alike (below).
STEP_UNIT = 1e-2


def fit_problem(problem: CalibrationProblem, *, solver: str = "lm-fd", max_steps: int = 50, rows: int = 96,
                atol: float = 1e-3, rtol: float = 0.0, theta_start: np.ndarray | None = None) -> dict[str, Any]:
    """Minimises ``0.5 |r|^2`` from ``theta_start`` (default ``problem.theta_start``); returns ``theta``, ``steps``,
    ``converged``, ``message``, ``rows`` (the residual indices the solver used, or None for
    all), ``forward_passes``, ``backward_passes``, ``seconds``.

    Termination is optimistix's Cauchy test on the solver variable ``u`` (:data:`STEP_UNIT`) and
    on what it minimises: a step must change every ``u`` by less than ``atol + rtol |u|`` and
    (least squares) every scaled residual by less than ``atol + rtol |r|``, or (BFGS) the
    loss by less than that. With ``atol = 1e-3``: every constant by less than 1e-5 of itself,
    every residual by less than a thousandth of its noise scale. (The test is per residual, so
    an absolute tolerance of 1e-6 on residuals of noise size 1 is never met: the solvers then
    ran to ``max_steps``, 28-60 steps where 4-6 had converged the loss.)
    """
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    jax.config.update("jax_enable_x64", True)
    if solver not in SOLVERS:
        raise ValueError(f"solver: got {solver!r}; expected one of {list(SOLVERS)}")
    if not (isinstance(max_steps, (int, np.integer)) and max_steps >= 1):
        raise ValueError(f"max_steps: got {max_steps!r}; expected an integer >= 1")
    before = dict(problem.counts)
    start = time.perf_counter()
    theta0 = jnp.asarray(problem.theta_start if theta_start is None else theta_start)
    u0 = jnp.zeros_like(theta0)

    low, high = (jnp.asarray(b) for b in getattr(problem, "log_bounds", (-np.inf, np.inf)))

    def theta_of(u):
        # Bounds (--bounds) by projection: outside them a constant stays at its bound (zero derivative).
        return jnp.clip(theta0 + STEP_UNIT * u, low, high)

    chosen = None
    if solver == "lm-fd":  # forward rollouts only: secant-updated, batched finite differences
        from .calibration_lm import fit_lm_fd

        return fit_lm_fd(problem, np.asarray(theta0), max_steps=max_steps, atol=atol, step_unit=STEP_UNIT)
    if solver == "lm-bwd":
        chosen = problem.subsample_rows(rows)
        full, base = problem.jax_residuals()
        index = jnp.asarray(chosen)

        def fn(u, args):
            return full(theta_of(u), args)[index]

        solution = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=rtol, atol=atol), u0, args=base,
                                      options={"jac": "bwd"}, max_steps=int(max_steps), throw=False)
    else:
        full, base = problem.jax_residuals()

        def loss(u, args):
            r = full(theta_of(u), args)
            return 0.5 * jnp.sum(r * r)

        # BFGS starts from the identity as its inverse Hessian, so its first trial step is the raw
        # gradient, ~1e4 units here (exp overflows). The loss is scaled so that its gradient at the
        # start has norm 1: a first trial step of 1 unit, 1 % in the constants.
        _, gradient = jax.value_and_grad(loss)(u0, base)
        scale = 1.0 / float(jnp.linalg.norm(gradient))

        def fn(u, args):
            return scale * loss(u, args)

        solution = optx.minimise(fn, optx.BFGS(rtol=rtol, atol=atol), u0, args=base, max_steps=int(max_steps),
                                 throw=False)
    theta = np.asarray(theta_of(solution.value), dtype=np.float64)
    converged = bool(solution.result == optx.RESULTS.successful)
    message = "converged" if converged else f"not converged: {optx.RESULTS[solution.result]}"
    return {"theta": theta, "steps": int(solution.stats["num_steps"]), "converged": converged, "message": message,
            "rows": chosen, "forward_passes": problem.counts["forward"] - before["forward"],
            "backward_passes": problem.counts["backward"] - before["backward"],
            "seconds": time.perf_counter() - start}


def jacobian_at(problem: CalibrationProblem, theta: np.ndarray, method: str,
                rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Residuals and Jacobian at ``theta`` (all rows, or ``rows``), by forward differences
    (``"fd"``: ``n + 1`` rollouts in one batch, step 1e-6 in log space, about 1e-6 relative error:
    a millionth of a standard error, far below the singular-value cut of the unidentifiable test,
    1e-4) or reverse mode (``"bwd"``: one backward pass per row); returns them with the cost."""
    before = dict(problem.counts)
    start = time.perf_counter()
    if method == "fd":
        residuals, jacobian = problem.fd_jacobian(theta, central=False)
        if rows is not None:
            residuals, jacobian = residuals[rows], jacobian[rows]
    elif method == "bwd":
        import jax
        import jax.numpy as jnp

        jax.config.update("jax_enable_x64", True)
        full, base = problem.jax_residuals()
        index = jnp.asarray(np.arange(problem.residual_count) if rows is None else rows)

        def fn(t):
            r = full(t, base)[index]
            return r, r

        jacobian, residuals = jax.jacrev(fn, has_aux=True)(jnp.asarray(theta))
        residuals, jacobian = np.asarray(residuals), np.asarray(jacobian)
    else:
        raise ValueError(f"jacobian: got {method!r}; expected 'fd' or 'bwd'")
    cost = {"method": method, "rows": int(len(residuals)),
            "forward_passes": problem.counts["forward"] - before["forward"],
            "backward_passes": problem.counts["backward"] - before["backward"],
            "seconds": time.perf_counter() - start}
    return residuals, jacobian, cost


#: Default multiple-shooting windows [s], one fit per entry, each from the previous one's result
#: (docs/calibration.md, "Windows": measured on five sessions).
DEFAULT_WINDOWS = (1.0 / 30.0, 1.0 / 3.0)
#: The solvers' absolute tolerance (:func:`fit_problem`) in the stages before the last: they only
#: need to bring the constants into the last stage's basin (1e-4 of each constant per step).
STAGE_ATOL = 1e-2
#: The stages before the last fit only the session's first seconds [s]: enough to find the basin,
#: and the shortest windows (most rollouts' overhead) then stay cheap on long sessions.
STAGE_SECONDS = 2.0
#: A constant (no ``--bounds``) whose log moved more than this from its start [log units: a factor
#: 1e4] ran off: along a direction the fit's windows hardly inform, the Levenberg-Marquardt steps
#: can carry it to 0 or infinity, where its derivative vanishes (``exp`` of the log underflows) and
#: no later stage can bring it back. Measured: a 1 s swaying session with ``k_d`` of one hand string
#: at 4.32 N s/m; the one-step windows ran it to 0, the 1/3 s windows kept it there (reduced chi^2
#: 1.04, exit 4); restarted, it is fitted (5.44 +- 0.53, chi^2 0.96, exit 0).
RUNAWAY_LOG = float(np.log(1e4))


def ran_off(problem, theta: np.ndarray) -> list[int]:
    """Indices of the unbounded constants of ``theta`` that moved more than :data:`RUNAWAY_LOG`
    from the problem's start (or to a non-finite value)."""
    low, high = (np.asarray(b, dtype=np.float64) for b in problem.log_bounds)
    start = np.asarray(problem.theta_start, dtype=np.float64)
    n = min(len(theta), len(start), len(low))
    moved = np.abs(np.asarray(theta[:n], dtype=np.float64) - start[:n])
    return [i for i in range(n) if np.isinf(low[i]) and np.isinf(high[i]) and not moved[i] <= RUNAWAY_LOG]


def restart_runaways(problem, theta: np.ndarray) -> tuple[np.ndarray, list[str], int]:
    """Between stages: the constants that ran off (:func:`ran_off`) back at their start, if that
    lowers the next stage's sum of squares (one rollout each way, on the windows in use); returns
    the next stage's start, the labels restarted (empty when ``theta`` is kept) and the rollouts
    run."""
    runaway = ran_off(problem, theta)
    if not runaway:
        return theta, [], 0
    restarted = np.array(theta, dtype=np.float64)
    restarted[runaway] = np.asarray(problem.theta_start, dtype=np.float64)[runaway]
    losses = [float(np.sum(np.square(problem.host_residuals(t)))) for t in (theta, restarted)]
    if not losses[1] < losses[0] and np.isfinite(losses[0]):
        return theta, [], 2
    return restarted, [problem.labels[i] for i in runaway], 2


def retry_runaways(problem, theta: np.ndarray, run_fit, judged: int) -> tuple[np.ndarray, dict | None, list[str], int]:
    """After the last stage: the constants among the first ``judged`` that ended run off
    (:func:`ran_off`) back at their start and the stage fitted again (``run_fit(theta_start)``); the
    lower sum of squares wins. Returns the theta kept, the retry's fit (None when none ran), the
    labels restarted and the two comparison rollouts' count."""
    runaway = [i for i in ran_off(problem, theta) if i < judged]
    if not runaway:
        return theta, None, [], 0
    start = np.array(theta, dtype=np.float64)
    start[runaway] = np.asarray(problem.theta_start, dtype=np.float64)[runaway]
    retry = run_fit(start)
    losses = [float(np.sum(np.square(problem.host_residuals(t)))) for t in (theta, retry["theta"])]
    kept = bool(losses[1] < losses[0] or not np.isfinite(losses[0]))
    return (retry["theta"] if kept else theta), {**retry, "kept": kept}, [problem.labels[i] for i in runaway], 2


def window_steps_for(data: CalibrationData, window: float | None, solver: str) -> int | None:
    """Puppet steps per window for ``window`` seconds (None or 0: one rollout)."""
    from .calibration_windows import recorded_joint_q

    if window is None or window == 0:
        return None
    if not (isinstance(window, (int, float, np.floating)) and window > 0):
        raise ValueError(f"window: got {window!r}; expected a positive number of seconds, or 0 for one rollout")
    if solver != "lm-fd":
        raise ValueError(f"window {window} s: multiple shooting runs with --solver lm-fd only (got {solver!r}); "
                         "use --window 0 with the reverse-mode solvers")
    if recorded_joint_q(data) is None:
        raise ValueError(f"{data.path}: multiple shooting (--window {window}) starts each window from the recorded "
                         "puppet state, but /puppet/state does not hold 'joint_q' at every puppet frame; use "
                         "--window 0 (one rollout over the whole session)")
    return max(1, int(round(window / data.puppet_dt)))


def _closing(fn):
    """``fn`` with a list ``_opened`` of what it opens (a stacked problem's Ray workers), closed when it
    returns or raises."""
    @functools.wraps(fn)
    def call(*args, **kwargs):
        opened: list = []
        try:
            return fn(*args, **kwargs, _opened=opened)
        finally:
            for problem in opened:
                problem.close()

    return call


@_closing
def calibrate_session(path: str | Path | Sequence[str | Path], *, targets: str = "bodies",
                      params: str | Sequence[str] = "k,k_d",
                      solver: str = "lm-fd", max_steps: int = 50, start: Mapping[str, Any] | None = None,
                      noise_position: float = 1e-3, noise_force: float = 1e-2, known_noise: bool = False,
                      duration: float | None = None, rows: int = 96, jacobian: str | None = None,
                      optimization_level: int = 2, checkpoint_steps: int | None = None,
                      progress=None, data: CalibrationData | None = None,
                      window: float | Sequence[float] | None = "default",
                      prior: str | Mapping[str, tuple[float, float]] | None = None,
                      bounds: str | Mapping[str, tuple[float, float]] | None = None,
                      freeze: str | Sequence[str] | None = None,
                      validate: float | None = None, loss: str = "l2",
                      huber_scale: float | None = None, delay: float = 0.0,
                      fit_delay: bool = False, fit_initial_state: bool = False,
                      noise_joint: float = 1e-3, ray: str = "off", workers: int | None = None,
                      _opened: list | None = None) -> CalibrationResult:
    """Fits string constants to a recorded session.

    Args:
        path: the ``.mcap`` session, or a list of sessions fitted together with one shared set of
            constants (:mod:`fitting.calibration_sessions`; same strings and rates, ``lm-fd``, no
            ``validate``): their residuals are stacked; ``data``, the residuals and the plot are
            then the first session's, ``rms_*`` over all, ``sessions`` per session.
        targets: ``"bodies"``, ``"feedback"`` or ``"both"`` (:func:`read_calibration_data`).
        params: the constants to fit (:func:`fitting.calibrate.parse_parameters`).
        solver: ``"lm-fd"``, ``"lm-bwd"`` or ``"bfgs"`` (module doc of :mod:`fitting.calibrate`).
        max_steps: solver steps at most.
        start: start values by constant (default: the session scene's constants).
        noise_position, noise_force: noise scales [m], [N] dividing the residuals.
        known_noise: the noise scales are the true standard deviations (else the residuals'
            variance per target is estimated at the optimum).
        duration: use only the first ``duration`` seconds.
        rows: residuals kept by ``lm-bwd`` (one backward pass each per solver step).
        jacobian: how the uncertainty's Jacobian is computed: ``"fd"`` or ``"bwd"`` (default:
            ``"bwd"`` on the solver's rows for ``lm-bwd``, else ``"fd"`` on every row).
        optimization_level: Warp optimisation of the puppet kernels.
        checkpoint_steps: puppet steps per taped segment.
        progress: called as ``progress(stage, forward_passes)`` while it runs (a progress display).
        data: the session already read (else read from ``path``).
        window: multiple shooting, seconds per window (:mod:`fitting.calibration_windows`), or a
            sequence of them: one fit per entry, each started from the previous one's result (a
            continuation from short windows, which find the basin, to longer ones, which pin
            the constants down); 0 or None: one rollout over the whole session. ``"default"``:
            :data:`DEFAULT_WINDOWS` with ``lm-fd`` when the session records ``joint_q``, else
            one rollout.
        prior: Gaussian priors per constant name, ``"k=300±100,k_d=3+-1"`` or ``{"k": (300, 100)}``
            (:func:`fitting.calibrate.parse_priors`): residual rows ``(c - mean) / sd``.
        bounds: per constant name, ``"k=100:1000"`` or ``{"k": (100, 1000)}``: the solver keeps the
            constants inside (projection); a constant that ends at a bound is warned about.
        freeze: per-string constants held at their start values, ``"k[head],k_d[back]"``.
        validate: hold out this fraction of the session's end (``0 < validate < 1``): fit on the
            rest, then simulate the whole session with the fitted constants and judge the
            held-out residuals (:mod:`fitting.calibration_validation`; a reduced chi-squared
            above 2 there is a warning and exit code 3).
        loss: ``"l2"`` (least squares) or ``"huber"`` (:mod:`fitting.calibration_robust`: IRLS,
            ``lm-fd`` only).
        huber_scale: Huber's ``C`` in noise scales (default 1.345; ``loss="huber"`` only).
        delay: the recorded targets lag the bar inputs by this many seconds
            (:mod:`fitting.calibration_delay`); with ``fit_delay`` the start value.
        fit_delay: fit the delay too (``lm-fd`` only): a parameter ``"delay"`` [s] after the
            constants, with its standard error; shared by several sessions.
        fit_initial_state: refine the start state of every shooting window but the first in the last
            stage (:mod:`fitting.calibration_initial_state`; ``lm-fd``, one session, windows), with
            the prior ``noise_joint`` (the recorded ``joint_q``'s noise, rad and m).
        ray: with several sessions, where their problems are kept and rolled out
            (:mod:`fitting.calibration_sessions`): ``"off"`` (this process), ``"local"`` or a Ray
            cluster address, a worker per session at most (``workers``: fewer); the same numbers
            in both. One session runs here whatever it says (Ray is not started).
        workers: Ray workers at most (default: one per CPU of the cluster).
    """
    total = time.perf_counter()
    paths = list(path) if isinstance(path, (list, tuple)) else [path]
    if not paths:
        raise ValueError("path: got no session; expected one .mcap session or more")
    data = read_calibration_data(paths[0], targets, duration=duration) if data is None else data
    others = [read_calibration_data(p, targets, duration=duration) for p in paths[1:]]
    if others:
        from .calibration_sessions import check_same_strings

        check_same_strings([data, *others])
        if solver != "lm-fd":
            raise ValueError(f"several sessions are fitted with --solver lm-fd only (got {solver!r})")
        if validate is not None:
            raise ValueError("--validate with several sessions: not supported; validate one session at a time")
    from .calibration_robust import DEFAULT_HUBER_SCALE, LOSSES, irls_fit

    if loss not in LOSSES:
        raise ValueError(f"--loss: got {loss!r}; expected one of {list(LOSSES)}")
    if loss != "huber" and huber_scale is not None:
        raise ValueError(f"--huber-scale {huber_scale} given with --loss {loss}; it needs --loss huber")
    if loss == "huber" and solver != "lm-fd":
        raise ValueError(f"--loss huber runs with --solver lm-fd only (got {solver!r})")
    huber_scale = DEFAULT_HUBER_SCALE if huber_scale is None else huber_scale
    if fit_initial_state and (solver != "lm-fd" or others):
        raise ValueError("--fit-initial-state runs with --solver lm-fd and one session only (got "
                         f"{solver!r}, {len(paths)} sessions)")
    if fit_delay and solver != "lm-fd":
        raise ValueError(f"--fit-delay runs with --solver lm-fd only (got {solver!r}); give a known --delay instead")
    whole = None
    if validate is not None:
        from .calibration_validation import split_for_validation

        whole, data = data, split_for_validation(data, validate, targets)
    parameters = parse_parameters(params, data, freeze)
    if isinstance(window, str) and window == "default":
        from .calibration_windows import recorded_joint_q

        usable = solver == "lm-fd" and recorded_joint_q(data) is not None
        window = DEFAULT_WINDOWS if usable else None
    windows = list(window) if isinstance(window, (list, tuple)) else [window]
    if not windows:
        raise ValueError("window: got an empty list; expected seconds per window, or 0 for one rollout")
    schedule = [window_steps_for(data, w, solver) for w in windows]
    if others:
        from .calibration_sessions import SessionSpec, StackedProblem

        problem = StackedProblem([SessionSpec(d, parameters, start, noise_position, noise_force, optimization_level,
                                              checkpoint_steps, schedule[-1], prior if i == 0 else None,
                                              bounds if i == 0 else None, delay, fit_delay)
                                  for i, d in enumerate([data, *others])], ray=ray, workers=workers)
        _opened.append(problem)  # closed (its Ray workers stopped) by _closing, also if this raises
    else:
        problem = CalibrationProblem(data, parameters, start=start, noise_position=noise_position,
                                     noise_force=noise_force, optimization_level=optimization_level,
                                     checkpoint_steps=checkpoint_steps, window_steps=schedule[-1], priors=prior,
                                     bounds=bounds, delay=delay, fit_delay=fit_delay,
                                     fit_initial_state=fit_initial_state, noise_joint=noise_joint)
    stage = {"name": "start"}
    if progress is not None:
        problem.on_forward = lambda count: progress(stage["name"], count)
    r0 = problem.host_residuals(problem.theta_start)  # as the last stage measures them
    theta, stages = problem.theta_start, []
    for index, steps in enumerate(schedule):
        stage["name"] = "fit" if len(schedule) == 1 else f"fit {index + 1}/{len(schedule)}"
        last = index == len(schedule) - 1
        prefix = None if last or steps is None else max(1, int(round(STAGE_SECONDS / data.puppet_dt)))
        problem.use_windows(steps, prefix)
        n = len(problem.theta_start)  # the initial states are unknowns of the last stage only, from 0
        theta = np.concatenate([theta[:n], np.zeros(max(0, n - len(theta)))])
        restarted, restart_rollouts = [], 0
        if index > 0:
            theta, restarted, restart_rollouts = restart_runaways(problem, theta)

        def run(theta_start, atol=1e-3 if last else STAGE_ATOL):
            return fit_problem(problem, solver=solver, max_steps=max_steps, rows=rows, theta_start=theta_start,
                               atol=atol)

        fit = irls_fit(problem, run, theta, huber_scale) if loss == "huber" else run(theta)
        theta = fit["theta"]
        stages.append({"window_steps": steps, "puppet_steps": min(prefix or data.puppet_steps, data.puppet_steps),
                       "steps": fit["steps"], "converged": fit["converged"], "message": fit["message"],
                       "forward_passes": fit["forward_passes"] + restart_rollouts, "seconds": fit["seconds"],
                       "restarted": restarted})
    states = getattr(problem, "initial_state", None)
    judged_count = len(problem.labels) if states is None else states.offset  # not the nuisance states
    theta, retry, restarted, restart_rollouts = retry_runaways(
        problem, theta, (lambda t: irls_fit(problem, run, t, huber_scale)) if loss == "huber" else run, judged_count)
    if retry is not None:
        stages.append({"window_steps": steps, "puppet_steps": data.puppet_steps, "steps": retry["steps"],
                       "converged": retry["converged"], "message": retry["message"],
                       "forward_passes": retry["forward_passes"] + restart_rollouts, "seconds": retry["seconds"],
                       "restarted": restarted, "retry": True, "kept": retry["kept"]})
        if retry["kept"]:
            fit = retry
    fit = {**fit, "steps": sum(st["steps"] for st in stages),
           "forward_passes": sum(st["forward_passes"] for st in stages),
           "backward_passes": fit["backward_passes"], "seconds": sum(st["seconds"] for st in stages)}
    stage["name"] = "uncertainty"
    method = jacobian or ("bwd" if solver == "lm-bwd" else "fd")
    used = fit["rows"] if solver == "lm-bwd" else None
    residuals, jac, jac_cost = jacobian_at(problem, theta, method, used)
    slices = problem.target_slices()
    all_slices = {**slices, "prior": problem.prior_slice()}
    if others:
        rows_of = problem.target_rows()
    elif used is None:
        rows_of = {t: np.arange(a, b) for t, (a, b) in all_slices.items() if b > a}
    else:
        rows_of = {t: np.nonzero((used >= a) & (used < b))[0] for t, (a, b) in all_slices.items() if b > a}
    uncertainty = gauss_newton_uncertainty(jac, residuals, problem.values(theta), rows_of, known_noise=known_noise,
                                           known=("prior",), linear=problem.linear())
    stage["name"] = "residuals"
    r1 = problem.host_residuals(theta)  # Huber: the weighted rows
    weights, problem.row_weights = problem.row_weights, None
    plain = r1 if weights is None else problem.host_residuals(theta)
    problem.row_weights = weights
    at_bound = [label for label, t, lo, hi in zip(problem.labels, theta, *problem.log_bounds)
                if np.isclose(t, lo, rtol=0, atol=1e-9) or np.isclose(t, hi, rtol=0, atol=1e-9)]
    # Huber: the plain residuals, their scale by the median (robust), not the weighted rows
    judged, judged_slices = problem.by_target(plain) if others else (plain, slices)
    runaway = {problem.labels[i]: (float(problem.values(problem.theta_start)[i]), float(problem.values(theta)[i]))
               for i in ran_off(problem, theta) if i < judged_count}
    verdict = judge_fit(judged, judged_slices, problem.noise, problem.labels, uncertainty, fit["converged"],
                        fit["message"], at_bound=at_bound, ran_off=runaway, robust=loss == "huber",
                        series=_time_series(problem, plain), nuisance=0 if states is None else states.count)
    shown = len(problem.labels) if states is None else states.offset  # the initial states: a summary only
    validation = None
    if whole is not None:
        from .calibration_validation import held_out_residuals, judge_validation

        stage["name"] = "validation"
        full = CalibrationProblem(whole, parameters, start=start, noise_position=noise_position,
                                  noise_force=noise_force, optimization_level=optimization_level,
                                  checkpoint_steps=checkpoint_steps, window_steps=schedule[-1], delay=delay,
                                  fit_delay=fit_delay)  # the held-out end from the recorded window starts
        if progress is not None:
            full.on_forward = lambda count: progress(stage["name"], count)
        validation = held_out_residuals(full, theta[:shown], data)
        judge_validation(verdict, validation, problem.noise)
    message = "converged" if verdict.converged else \
        ("solver converged, but the fit does not explain the data" if fit["converged"] else fit["message"])
    before, after = _unscaled(problem, r0), _unscaled(problem, plain)
    rms_before, rms_after, sessions = _rms(before), _rms(after), None
    if others:
        from .calibration_sessions import session_summaries

        sessions = session_summaries(problem, r0, plain)
        rms_before, rms_after = (_rms_over(problem, r) for r in (r0, plain))
    return CalibrationResult(
        data=data, parameters=parameters, labels=problem.labels[:shown],
        start=problem.values(problem.theta_start)[:shown], fitted=problem.values(theta)[:shown],
        uncertainty=uncertainty, rms_before=rms_before, rms_after=rms_after,
        residuals_before=before, residuals_after=after, solver=solver, solver_steps=fit["steps"],
        converged=verdict.converged, message=message, jacobian=jac_cost,
        cost={"forward_passes": fit["forward_passes"], "backward_passes": fit["backward_passes"],
              "seconds": fit["seconds"], "total_seconds": time.perf_counter() - total,
              "residual_count": problem.residual_count, "stages": stages,
              "ray_workers": problem.states.worker_count if others else 0},
        noise=dict(problem.noise), known_noise=known_noise, theta=theta, verdict=verdict,
        window_steps=schedule[-1], priors=dict(problem.priors),
        string_constants={p.name: problem.constants(theta)[ENGINE_FIELDS[p.name]].tolist() for p in parameters},
        validation=validation, sessions=sessions,
        delay={"seconds": problem.delay_of(theta), "fitted": problem.delay_index is not None,
               "standard_error": None if problem.delay_index is None else
               float(uncertainty.standard_error[problem.delay_index])},
        initial_state=None if states is None else _initial_state_summary(states, theta),
        loss={"name": loss} if loss == "l2" else
        {"name": loss, "scale": huber_scale, "rounds": fit["rounds"], "outliers": fit["outliers"],
         "rows": int(len(r1))})
