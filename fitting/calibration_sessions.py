"""Several sessions fitted at once with one shared set of constants (docs/calibration.md,
"Several sessions").

``dmarionette calibrate a.mcap b.mcap ...`` stacks the residuals of every session into one vector
and fits one parameter vector to all of them: each session is its own
:class:`fitting.calibrate.CalibrationProblem` (its own recorded bars, targets, windows and
rollout), all with the same fitted constants. Every session must have the same strings (names,
order and the body points they are tied to), or the constants would not mean the same thing.

Row layout of the stacked residuals: the first session's data rows, then the second's, ...,
then the prior rows (once, :meth:`CalibrationProblem.prior_residuals`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .calibrate import CalibrationProblem
from .calibration_data import CalibrationData

__all__ = ["StackedProblem", "check_same_strings", "session_summaries"]


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


class StackedProblem(CalibrationProblem):
    """The residuals of several sessions as one function of one parameter vector.

    It has :class:`CalibrationProblem`'s interface for the forward-only path (``lm-fd``:
    :meth:`host_residuals`, ``fd_jacobian``, ``jax_fd_residuals``, :meth:`use_windows`); the
    reverse-mode residuals (``jax_residuals``) are not stacked.

    Args:
        problems: one problem per session, built with the same parameters; the first holds the
            priors and bounds (the others none).
    """

    def __init__(self, problems: Sequence[CalibrationProblem]):  # noqa: D107 - no base __init__: nothing to build
        first = problems[0]
        self.problems = list(problems)
        self.data = first.data
        self.params, self.labels, self.string_names = first.params, first.labels, first.string_names
        self.theta_start, self.log_bounds = first.theta_start, first.log_bounds
        self.constant_count, self.delay_index, self.delay = first.constant_count, first.delay_index, first.delay
        self.initial_state = None  # not with several sessions (refused by calibrate_session)
        self.priors, self.bounds, self.noise = first.priors, first.bounds, first.noise
        self.base, self._prior_index = first.base, first._prior_index
        self._prior_mean, self._prior_sd = first._prior_mean, first._prior_sd
        self.on_forward = None
        counts = [p.data_residual_count for p in self.problems]
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self.data_residual_count = int(self.offsets[-1])
        self.residual_count = self.data_residual_count + len(self._prior_index)
        self.active_rows = None
        self.row_weights = None
        self.windows = first.windows
        for p in self.problems:
            p.on_forward = self._forwarded

    def _forwarded(self, _count: int) -> None:
        if self.on_forward is not None:
            self.on_forward(self.counts["forward"])

    @property
    def counts(self) -> dict[str, int]:
        """Rollouts of every session, summed: ``forward``, ``backward``."""
        return {k: sum(p.counts[k] for p in self.problems) for k in ("forward", "backward")}

    def use_windows(self, window_steps: int | None, prefix_steps: int | None = None) -> None:
        """:meth:`CalibrationProblem.use_windows` on every session."""
        for p in self.problems:
            p.use_windows(window_steps, prefix_steps)
        self.windows = self.problems[0].windows
        partial = any(p.active_rows is not None for p in self.problems)
        self.row_weights = None
        self.active_rows = np.arange(len(self.host_residuals(self.theta_start))) if partial else None

    def host_residuals(self, theta: np.ndarray) -> np.ndarray:
        """Every session's residuals (their active rows), then the prior rows, ``(m,)``."""
        theta = np.asarray(theta, np.float64)
        parts = []
        for p in self.problems:
            r = p.host_residuals(theta)
            a, b = p.prior_slice()
            parts.append(r[:len(r) - (b - a)])
        if self._prior_index:
            parts.append(self.prior_residuals(theta))
        out = np.concatenate(parts)
        return out if self.row_weights is None else out * self.row_weights

    def session_rows(self) -> list[dict[str, np.ndarray]]:
        """Per session, each target's row indices in the stacked vector (all rows)."""
        return [{t: np.arange(a, b) + offset for t, (a, b) in p.target_slices().items()}
                for p, offset in zip(self.problems, self.offsets[:-1])]

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
        return self.problems[0].target_slices()


def session_summaries(problem: StackedProblem, before: np.ndarray, after: np.ndarray) -> list[dict]:
    """Per session: ``session`` (its path), ``rms_before`` and ``rms_after`` per target in its unit
    ([m], [N]) from the stacked scaled residuals ``before``, ``after`` ``(m,)``."""
    out = []
    for p, rows in zip(problem.problems, problem.session_rows()):
        out.append({"session": str(p.data.path),
                    **{f"rms_{name}": {t: float(np.sqrt(np.mean(r[index] ** 2)) * problem.noise[t])
                                       for t, index in rows.items()}
                       for name, r in (("before", before), ("after", after))}})
    return out
