"""Several sessions fitted at once with one shared set of constants (docs/calibration.md,
"Several sessions").

``dmarionette calibrate a.mcap b.mcap ...`` stacks the residuals of every session into one vector
and fits one parameter vector to all of them: each session is its own
:class:`fitting.calibrate.CalibrationProblem` (its own recorded bars, targets, windows and
rollout), all with the same fitted constants. Every session must have the same strings (names,
order and the body points they are tied to), or the constants would not mean the same thing.

Where the sessions' rollouts run (``--ray``): each session's problem (its model, compiled kernels
and windows) is built once and kept warm by :class:`dmarionette.scale.WarmStates`, in this process
(``"off"``) or on Ray workers (``"local"``, a cluster address), a worker per session at most. A
residual vector, and the finite-difference Jacobian's ``n + 1`` (one-sided) or ``2 n + 1``
(central) rollouts, are asked of every session at once: on Ray the sessions run in parallel. The
Levenberg-Marquardt step, the stacking and the differences stay here. The numbers are the same in
both places: the same rollouts, run by the same code in another process (tested bit for bit).

Row layout of the stacked residuals: the first session's data rows, then the second's, ...,
then the prior rows (once, :meth:`CalibrationProblem.prior_residuals`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from .calibrate import CalibrationProblem, Parameter
from .calibration_data import CalibrationData

__all__ = ["SessionSpec", "SessionState", "StackedProblem", "build_session", "check_same_strings",
           "session_summaries"]


def check_same_strings(sessions: Sequence[CalibrationData]) -> None:
    """Refuses sessions whose strings differ from the first session's.

    Raises:
        ValueError: naming the file, what it has and what the first session has.
    """
    first = sessions[0]

    def strings(d: CalibrationData):
        return [(s.name, p) for s, p in zip(d.scene.strings, d.scene.string_body_points)]

    for d in sessions[1:]:
        if strings(d) != strings(first):
            raise ValueError(f"{d.path}: its strings (name, tied body point) are {strings(d)}; expected those of "
                             f"{first.path}, {strings(first)}: sessions fitted together share one constant per "
                             "string, so they must have the same strings")
        if (d.string_dt, d.substeps) != (first.string_dt, first.substeps):
            raise ValueError(f"{d.path}: string step {d.string_dt:.6g} s with {d.substeps} per puppet step; expected "
                             f"{first.string_dt:.6g} s and {first.substeps} as in {first.path}: sessions fitted "
                             "together must have the same rates")
        if d.targets != first.targets:
            raise ValueError(f"{d.path}: its targets are {list(d.targets)}; expected {list(first.targets)} as in "
                             f"{first.path}")


@dataclasses.dataclass(frozen=True)
class SessionSpec:
    """What builds one session's :class:`CalibrationProblem` (its arguments; picklable for Ray)."""

    data: CalibrationData
    params: Sequence[Parameter]
    start: Mapping | None = None
    noise_position: float = 1e-3
    noise_force: float = 1e-2
    optimization_level: int = 2
    checkpoint_steps: int | None = None
    window_steps: int | None = None
    priors: Mapping | None = None
    bounds: Mapping | None = None
    delay: float = 0.0
    fit_delay: bool = False


@dataclasses.dataclass
class SessionState:
    """A session's problem where it is kept, and the shooting it is in: ``windows`` =
    ``(window_steps, prefix_steps)`` of its last :meth:`CalibrationProblem.use_windows`."""

    problem: CalibrationProblem
    windows: tuple


def build_session(spec: SessionSpec) -> SessionState:
    """The session's problem (model, kernels), built where it will be kept."""
    problem = CalibrationProblem(spec.data, spec.params, start=spec.start, noise_position=spec.noise_position,
                                 noise_force=spec.noise_force, optimization_level=spec.optimization_level,
                                 checkpoint_steps=spec.checkpoint_steps, window_steps=spec.window_steps,
                                 priors=spec.priors, bounds=spec.bounds, delay=spec.delay, fit_delay=spec.fit_delay)
    return SessionState(problem, (spec.window_steps, None))


def session_header(state: SessionState, _request=None) -> dict:
    """What the stacking needs of a session's problem, without its model: parameters, start, bounds,
    priors, noise scales, the engine's fixed inputs (``base``) and the row layout."""
    p = state.problem
    return {"params": p.params, "labels": p.labels, "string_names": p.string_names, "theta_start": p.theta_start,
            "constant_count": p.constant_count, "delay_index": p.delay_index, "delay": p.delay,
            "log_bounds": p.log_bounds, "priors": p.priors, "bounds": p.bounds, "noise": p.noise, "base": p.base,
            "prior_index": p._prior_index, "prior_mean": p._prior_mean, "prior_sd": p._prior_sd,
            "data_residual_count": p.data_residual_count, "target_slices": p.target_slices(),
            "prior_slice": p.prior_slice()}


def _shoot(state: SessionState, windows: tuple) -> None:
    if tuple(windows) != state.windows:
        state.problem.use_windows(*windows)
        state.windows = tuple(windows)


def session_windows(state: SessionState, windows: tuple) -> int:
    """Puts the session in ``windows`` = ``(window_steps, prefix_steps)``; returns how many data rows its
    residuals then have (its active rows less its prior rows)."""
    _shoot(state, windows)
    p = state.problem
    a, b = p.prior_slice()
    return (p.residual_count if p.active_rows is None else len(p.active_rows)) - (b - a)


def session_residuals(state: SessionState, request: tuple) -> tuple[list[np.ndarray], int]:
    """``request`` = ``(windows, points)``: the session's residuals (its active data rows, no prior rows)
    at each of ``points``, and how many rollouts that took."""
    windows, points = request
    _shoot(state, windows)  # a restarted worker has lost the shooting: every request carries it
    p = state.problem
    before = p.counts["forward"]
    a, b = p.prior_slice()
    out = [r[:len(r) - (b - a)] for r in p.residuals_at(points)]  # the points' rollouts batched as worlds
    return out, p.counts["forward"] - before


class StackedProblem(CalibrationProblem):
    """The residuals of several sessions as one function of one parameter vector.

    It has :class:`CalibrationProblem`'s interface for the forward-only path (``lm-fd``:
    :meth:`host_residuals`, ``fd_jacobian``, ``residuals_at``, :meth:`use_windows`); the
    reverse-mode residuals (``jax_residuals``) are not stacked. Call :meth:`close` at the end
    (it stops the Ray workers).

    Args:
        specs: one per session, with the same parameters; the first holds the priors and bounds
            (the others none).
        ray: where the sessions' problems are kept and rolled out: ``"off"`` (this process),
            ``"local"`` or a Ray cluster address (module doc).
        workers: Ray workers at most (default one per CPU of the cluster, never more than sessions).
    """

    def __init__(self, specs: Sequence[SessionSpec], *, ray: str = "off",  # noqa: D107 - no base __init__
                 workers: int | None = None):
        from dmarionette.scale import WarmStates
        from dmarionette.scale.ray_map import init_worker_warp

        self.session_data = [spec.data for spec in specs]
        self.states = WarmStates(build_session, list(specs), ray=ray, workers=workers, setup=init_worker_warp)
        try:
            headers = self.states.map(session_header, [None] * len(specs))
        except BaseException:
            self.states.close()
            raise
        first = headers[0]
        self.data = specs[0].data
        self.params, self.labels, self.string_names = first["params"], first["labels"], first["string_names"]
        self.theta_start, self.log_bounds = first["theta_start"], first["log_bounds"]
        self.constant_count, self.delay_index, self.delay = first["constant_count"], first["delay_index"], first["delay"]
        self.initial_state = None  # not with several sessions (refused by calibrate_session)
        self.priors, self.bounds, self.noise = first["priors"], first["bounds"], first["noise"]
        self.base = first["base"]
        self._prior_index, self._prior_mean = first["prior_index"], first["prior_mean"]
        self._prior_sd = first["prior_sd"]
        self._slices = [h["target_slices"] for h in headers]
        self._session_counts = [0] * len(specs)
        self.on_forward = None
        counts = [h["data_residual_count"] for h in headers]
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.data_residual_count = int(self.offsets[-1])
        self.residual_count = self.data_residual_count + len(self._prior_index)
        self.active_rows = None
        self.row_weights = None
        self.windows = None
        self._shooting = (specs[0].window_steps, None)

    def close(self) -> None:
        """Stops the sessions' workers (and a Ray cluster this problem started)."""
        self.states.close()

    @property
    def counts(self) -> dict[str, int]:
        """Rollouts of every session, summed: ``forward``, ``backward`` (none: forward only)."""
        return {"forward": sum(self._session_counts), "backward": 0}

    def use_windows(self, window_steps: int | None, prefix_steps: int | None = None) -> None:
        """:meth:`CalibrationProblem.use_windows` on every session."""
        self._shooting = (window_steps, prefix_steps)
        rows = self.states.map(session_windows, [self._shooting] * len(self.session_data))
        self.row_weights = None
        partial = sum(rows) < self.data_residual_count
        self.active_rows = np.arange(sum(rows) + len(self._prior_index)) if partial else None

    def residuals_at(self, points: Sequence[np.ndarray]) -> list[np.ndarray]:
        """The stacked residuals at each of ``points``: every session's rollouts at once (in parallel on Ray)."""
        points = [np.asarray(theta, np.float64) for theta in points]
        answers = self.states.map(session_residuals, [(self._shooting, points)] * len(self.session_data))
        for index, (_, forwards) in enumerate(answers):
            self._session_counts[index] += forwards
        if self.on_forward is not None:
            self.on_forward(self.counts["forward"])
        out = []
        for k, theta in enumerate(points):
            parts = [vectors[k] for vectors, _ in answers]
            if self._prior_index:
                parts.append(self.prior_residuals(theta))
            stacked = np.concatenate(parts)
            out.append(stacked if self.row_weights is None else stacked * self.row_weights)
        return out

    def host_residuals(self, theta: np.ndarray) -> np.ndarray:
        """Every session's residuals (their active rows), then the prior rows, ``(m,)``."""
        return self.residuals_at([theta])[0]

    def session_rows(self) -> list[dict[str, np.ndarray]]:
        """Per session, each target's row indices in the stacked vector (all rows)."""
        return [{t: np.arange(a, b) + offset for t, (a, b) in slices.items()}
                for slices, offset in zip(self._slices, self.offsets[:-1])]

    def target_rows(self) -> dict[str, np.ndarray]:
        """Each target's row indices over every session, and ``prior``'s (when any)."""
        rows: dict[str, list] = {}
        for session in self.session_rows():
            for t, index in session.items():
                rows.setdefault(t, []).append(index)
        out = {t: np.concatenate(index) for t, index in rows.items()}
        if self._prior_index:
            out["prior"] = np.arange(self.data_residual_count, self.residual_count)
        return out

    def by_target(self, residuals: np.ndarray) -> tuple[np.ndarray, dict[str, tuple[int, int]]]:
        """The data rows reordered target by target, and each target's ``(start, stop)`` in it."""
        rows = {t: r for t, r in self.target_rows().items() if t != "prior"}
        slices, offset = {}, 0
        for t, index in rows.items():
            slices[t] = (offset, offset + len(index))
            offset += len(index)
        return np.concatenate([residuals[index] for index in rows.values()]), slices

    def prior_slice(self) -> tuple[int, int]:
        return self.data_residual_count, self.residual_count

    def target_slices(self) -> dict[str, tuple[int, int]]:
        """The first session's target slices (its rows come first)."""
        return dict(self._slices[0])


def session_summaries(problem: StackedProblem, before: np.ndarray, after: np.ndarray) -> list[dict]:
    """Per session: ``session`` (its path), ``rms_before`` and ``rms_after`` per target in its unit
    ([m], [N]) from the stacked scaled residuals ``before``, ``after`` ``(m,)``."""
    out = []
    for data, rows in zip(problem.session_data, problem.session_rows()):
        out.append({"session": str(data.path),
                    **{f"rms_{name}": {t: float(np.sqrt(np.mean(r[index] ** 2)) * problem.noise[t])
                                       for t, index in rows.items()}
                       for name, r in (("before", before), ("after", after))}})
    return out
