"""Calibration: fit string constants (eq. 2 ``k``, ``k_d`` per string, optionally ``k_s``) to a
recorded session (docs/calibration.md).

The parameters are the logarithms of the constants (so they stay positive), one per string
or one shared by every string. The residuals are ``(simulated - recorded) / noise scale``
for the chosen targets: body centres at the puppet rate and/or the exact reaction of the
strings on each bar at the string rate (:mod:`fitting.calibration_data`). The rollout is
:class:`dmarionette.grad.engine.MarionetteGradient`, whose gradients come from Warp's tape
(reverse mode only), exposed to JAX by :func:`fitting.rollout.marionette_rollout`.

Solvers (measured costs in docs/calibration.md):

- ``"lm-fd"`` (default): Levenberg-Marquardt (``optimistix.LevenbergMarquardt``) on every
  residual, with the Jacobian from forward sensitivities by one-sided differences of the
  rollout (``n + 1`` forward rollouts per linearisation for ``n`` parameters, whatever the
  number of residuals). It enters optimistix as a function with a custom JVP ``J v``
  (forward mode, optimistix's default ``jac="fwd"``).
- ``"lm-bwd"``: Levenberg-Marquardt with the reverse-mode Jacobian (``jac="bwd"``: one
  backward pass of the rollout per residual), on a subsample of the residuals
  (``rows``, spread evenly over time and the targets).
- ``"bfgs"``: BFGS (``optimistix.BFGS``) on the scalar loss ``0.5 |r|^2`` over every residual,
  with its reverse-mode gradient (one forward and one backward pass per evaluation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from .calibration_data import CalibrationData
from .synthetic_session import SPEC_FIELDS

__all__ = ["SOLVERS", "CalibrationProblem", "Parameter", "parse_bounds", "parse_parameters", "parse_priors"]

SOLVERS = ("lm-fd", "lm-bwd", "bfgs")
#: Input field of the rollout engine for each constant.
ENGINE_FIELDS = {"k": "tie_stiffness", "k_d": "tie_damping", "k_s": "string_stiffness"}
_FD_STEP = 1e-5  # central-difference step in log space (truncation ~1e-10, round-off ~1e-11 relative)
_FD_STEP_ONE_SIDED = 1e-6  # one-sided step (truncation ~1e-6 relative, round-off ~1e-10)


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One fitted constant: ``name`` (``k``, ``k_d``, ``k_s``) of the strings ``strings``
    (indices; one parameter shared by them when ``shared``, else one per string)."""

    name: str
    shared: bool
    strings: tuple[int, ...]

    def labels(self, string_names: Sequence[str]) -> list[str]:
        if self.shared:
            return [f"{self.name}[shared]"]
        return [f"{self.name}[{string_names[i]}]" for i in self.strings]

    @property
    def size(self) -> int:
        return 1 if self.shared else len(self.strings)


def parse_parameters(text: str | Sequence[str], data: CalibrationData,
                     freeze: str | Sequence[str] | None = None) -> list[Parameter]:
    """Parses ``"k,k_d"`` or ``"k,k_d,k_s:shared"``: constants fitted per string, or shared.

    ``k`` and ``k_d`` (eq. 2) apply to the strings tied to a body point; ``k_s`` (the whole
    string's stiffness) to every string. ``freeze`` lists per-string constants held at their
    start values, by label: ``"k[head],k_d[hand_left]"``.

    Raises:
        ValueError: an unknown constant, an unknown suffix, a constant named twice, or a frozen
            label that is not a fitted per-string constant.
    """
    params = _parse_parameters(text, data)
    frozen = [s.strip() for s in (freeze.split(",") if isinstance(freeze, str) else (freeze or ())) if s.strip()]
    names = [s.name for s in data.scene.strings]
    for label in frozen:
        name, _, rest = label.partition("[")
        string = rest.rstrip("]")
        match = [p for p in params if p.name == name and not p.shared]
        if not rest.endswith("]") or not match or string not in names or names.index(string) not in match[0].strings:
            fitted = [lab for p in params if not p.shared for lab in p.labels(names)]
            raise ValueError(f"--freeze: got {label!r}; expected labels of fitted per-string constants, some of "
                             f"{fitted}")
        index = params.index(match[0])
        params[index] = Parameter(name, False, tuple(i for i in match[0].strings if i != names.index(string)))
    params = [p for p in params if p.strings]
    if not params:
        raise ValueError(f"--freeze {freeze!r}: every fitted constant is frozen; nothing to fit")
    return params


def parse_bounds(text: str | Mapping[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]]:
    """Parses ``"k=100:1000,k_d=0.5:10"``: lower and upper bounds per constant name, in its unit.

    Raises:
        ValueError: an unknown constant, a malformed entry, bounds not ``0 < low < high``.
    """
    items = _parse_pairs(text, "--bounds", ":", "NAME=LOW:HIGH, e.g. 'k=100:1000,k_d=0.5:10'")
    for name, (low, high) in items.items():
        if name not in ENGINE_FIELDS:
            raise ValueError(f"--bounds: unknown constant {name!r}; expected some of {sorted(ENGINE_FIELDS)}")
        if not (np.isfinite(low) and np.isfinite(high) and 0 < low < high):
            raise ValueError(f"--bounds {name}: got {low}:{high}; expected 0 < LOW < HIGH")
    return items


def _parse_pairs(text, flag: str, separator: str, expected: str) -> dict[str, tuple[float, float]]:
    """``"NAME=A<sep>B,..."`` (or a mapping) as ``{name: (A, B)}``; a ``ValueError`` naming ``flag``."""
    if text is None:
        return {}
    if isinstance(text, Mapping):
        return {k: (float(v[0]), float(v[1])) for k, v in text.items()}
    items = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        name, eq, value = part.partition("=")
        first, sep, second = value.partition(separator)
        try:
            items[name.strip()] = (float(first), float(second))
        except ValueError:
            sep = ""
        if not eq or not sep:
            raise ValueError(f"{flag}: got {part!r} in {text!r}; expected {expected}") from None
    return items


def _parse_parameters(text: str | Sequence[str], data: CalibrationData) -> list[Parameter]:
    items = [s.strip() for s in (text.split(",") if isinstance(text, str) else text) if s.strip()]
    if not items:
        raise ValueError(f"--params: got {text!r}; expected a comma-separated list of {sorted(ENGINE_FIELDS)}, "
                         "each optionally ':shared' (e.g. 'k,k_d' or 'k,k_d,k_s:shared')")
    tied = tuple(i for i, p in enumerate(data.scene.string_body_points) if p is not None)
    params, seen = [], set()
    for item in items:
        name, _, mode = item.partition(":")
        if name not in ENGINE_FIELDS:
            raise ValueError(f"--params: unknown constant {name!r} in {text!r}; expected some of "
                             f"{sorted(ENGINE_FIELDS)} (k, k_d: eq. 2 tie stiffness and damping; k_s: string "
                             "stiffness)")
        if mode not in ("", "shared", "per-string"):
            raise ValueError(f"--params: {item!r}: expected '{name}', '{name}:shared' or '{name}:per-string'")
        if name in seen:
            raise ValueError(f"--params: {name!r} named twice in {text!r}")
        seen.add(name)
        strings = tied if name in ("k", "k_d") else tuple(range(len(data.scene.strings)))
        if not strings:
            raise ValueError(f"{data.path}: no string is tied to a body point, so {name!r} has no effect")
        params.append(Parameter(name, mode == "shared", strings))
    return params


def parse_priors(text: str | Mapping[str, tuple[float, float]] | None) -> dict[str, tuple[float, float]]:
    """Parses ``"k=300±100,k_d=3+-1"``: a Gaussian prior (mean, standard deviation, in the
    constant's unit) per constant name, for every string's constant of that name.

    Raises:
        ValueError: an unknown constant, a malformed entry, a non-positive mean or deviation.
    """
    if isinstance(text, str):
        text = text.replace("+-", "±")
    items = _parse_pairs(text, "--prior", "±", "NAME=MEAN±SD (or MEAN+-SD), e.g. 'k=300±100,k_d=3+-1'")
    for name, (mean, sd) in items.items():
        if name not in ENGINE_FIELDS:
            raise ValueError(f"--prior: unknown constant {name!r}; expected some of {sorted(ENGINE_FIELDS)}")
        if not (np.isfinite(mean) and mean > 0 and np.isfinite(sd) and sd > 0):
            raise ValueError(f"--prior {name}: got mean {mean} and deviation {sd}; expected positive finite numbers")
    return items


class CalibrationProblem:
    """The residuals of a session as a function of the log-constants, and their Jacobians.

    Args:
        data: the session's inputs and targets.
        params: the fitted constants (:func:`parse_parameters`).
        start: start values by constant name: a scalar or one value per string ``(S,)``
            (default: the constants the session's scene has).
        noise_position: noise scale of a body-centre coordinate [m] (divides its residuals).
        noise_force: noise scale of a reaction component [N].
        optimization_level: Warp optimisation of the puppet kernels (0 compiles fast).
        checkpoint_steps: puppet steps per taped segment of the gradient engine.
        priors: Gaussian priors ``{name: (mean, sd)}`` (:func:`parse_priors`): one residual row
            ``(c - mean) / sd`` per fitted constant of that name, after the data's rows.
        bounds: ``{name: (low, high)}`` (:func:`parse_bounds`): the solver keeps the constants
            inside (``log_bounds``); the start must lie inside.
        window_steps: multiple shooting (:mod:`fitting.calibration_windows`): puppet steps per
            window, each started from the recorded puppet state; None: one rollout over the
            whole session (single shooting). Needs ``joint_q`` in ``/puppet/state`` at every
            frame; the forward-only residuals (:meth:`host_residuals`, :meth:`fd_jacobian`)
            use the windows, the reverse-mode ones (:meth:`jax_residuals`) do not.
        delay: the targets lag the bar inputs by this many seconds (:mod:`fitting.calibration_delay`:
            the inputs are shifted); with ``fit_delay`` its start value.
        fit_delay: fit the delay too: one more parameter, ``"delay"``, after the constants, in
            milliseconds in ``theta`` (:data:`fitting.calibration_delay.DELAY_UNIT`; not a logarithm),
            inside ``[-MAX_DELAY, MAX_DELAY]``. Forward-only residuals.
        fit_initial_state: refine the start state of every window but the first in the full-session
            stage (:mod:`fitting.calibration_initial_state`): ``2 qd_count`` unknowns per window,
            after the constants and the delay, added by :meth:`use_windows`; ``noise_joint``: the
            recorded ``joint_q``'s noise, their prior (rad, m).
    """

    def __init__(self, data: CalibrationData, params: Sequence[Parameter], *,
                 start: Mapping[str, float | Sequence[float]] | None = None, noise_position: float = 1e-3,
                 noise_force: float = 1e-2, optimization_level: int = 2, checkpoint_steps: int | None = None,
                 window_steps: int | None = None, priors: Mapping[str, tuple[float, float]] | None = None,
                 bounds: Mapping[str, tuple[float, float]] | None = None, delay: float = 0.0,
                 fit_delay: bool = False, fit_initial_state: bool = False, noise_joint: float = 1e-3):
        from dmarionette.marionette.solver import MarionetteModel
        from dmarionette.grad.engine import MarionetteGradient

        for label, value in (("noise_position", noise_position), ("noise_force", noise_force)):
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"{label}: got {value}; expected a positive noise scale")
        self.data = data
        self.params = list(params)
        self.noise = {"bodies": float(noise_position), "feedback": float(noise_force)}
        self._optimization_level = optimization_level
        try:
            self.model = MarionetteModel(data.scene, optimization_level=optimization_level, requires_grad=True)
        except ValueError as error:
            raise ValueError(f"{data.path}: the session's scene cannot be simulated for calibration: {error}") \
                from None
        self.engine = MarionetteGradient(self.model, data.puppet_steps, checkpoint_steps=checkpoint_steps)
        self.counts = {"forward": 0, "backward": 0}
        self.on_forward: Callable[[int], None] | None = None
        self._wrap_engine()
        base = self.engine.scene_inputs()
        base.top_q, base.bar_q, base.bar_qd = data.top_q, data.bar_q, data.bar_qd
        self.base = base
        self.string_names = [s.name for s in data.scene.strings]
        self.labels = [label for p in self.params for label in p.labels(self.string_names)]
        self.theta_start = self._start_theta(start or {})
        for name, values in (start or {}).items():  # every string's, the frozen ones included
            field = ENGINE_FIELDS[name]
            setattr(self.base, field, np.broadcast_to(np.asarray(values, float), (len(data.scene.strings),)).copy())
        self._rows_of = self._target_layout()
        self.priors = parse_priors(priors)
        unknown = sorted(set(self.priors) - {p.name for p in self.params})
        if unknown:
            raise ValueError(f"--prior: {unknown} not fitted (fitted: {[p.name for p in self.params]})")
        offset, self._prior_index = 0, []
        for p in self.params:
            if p.name in self.priors:
                self._prior_index += list(range(offset, offset + p.size))
            offset += p.size
        self._prior_mean = np.array([self.priors[self._name_of(i)][0] for i in self._prior_index])
        self._prior_sd = np.array([self.priors[self._name_of(i)][1] for i in self._prior_index])
        self.bounds = parse_bounds(bounds)
        unknown = sorted(set(self.bounds) - {p.name for p in self.params})
        if unknown:
            raise ValueError(f"--bounds: {unknown} not fitted (fitted: {[p.name for p in self.params]})")
        names = [self._name_of(i) for i in range(len(self.theta_start))]
        self.log_bounds = (np.array([np.log(self.bounds[n][0]) if n in self.bounds else -np.inf for n in names]),
                           np.array([np.log(self.bounds[n][1]) if n in self.bounds else np.inf for n in names]))
        outside = [(label, float(np.exp(t)))
                   for label, t, lo, hi in zip(self.labels, self.theta_start, *self.log_bounds) if not lo <= t <= hi]
        if outside:
            raise ValueError(f"--bounds: start values {outside} lie outside their bounds {self.bounds}; give "
                             "--start values inside")
        self.constant_count = len(self.theta_start)  # the log-constants; then the linear unknowns
        self._set_delay(delay, fit_delay)
        self.data_residual_count = self.residual_count
        self.residual_count += len(self._prior_index)
        self.windows = None
        self.active_rows = None
        self.row_weights: np.ndarray | None = None
        self.fit_initial_state, self.noise_joint = bool(fit_initial_state), float(noise_joint)
        self.initial_state = None
        self.use_windows(window_steps)

    #: ``row_weights``: None, or a factor per returned residual row of :meth:`host_residuals` (IRLS:
    #: the square roots of the Huber weights, :mod:`fitting.calibration_robust`); the forward-only
    #: residuals and Jacobians are then of the weighted rows.

    def _set_delay(self, delay: float, fit_delay: bool) -> None:
        """The recording delay: known (``delay``), or fitted from it (one more, linear, parameter)."""
        from .calibration_delay import DELAY_UNIT, MAX_DELAY, delayed

        if not (np.isfinite(delay) and abs(delay) <= MAX_DELAY):
            raise ValueError(f"--delay: got {delay!r} s; expected a delay of the targets behind the bar inputs "
                             f"within +-{MAX_DELAY:g} s")
        self.delay = float(delay)
        self.delay_index = None
        self._recorded_inputs = (self.base.top_q, self.base.bar_q, self.base.bar_qd)
        if not fit_delay:  # a known delay: the inputs shifted once, for every solver
            self.base.top_q, self.base.bar_q, self.base.bar_qd = (delayed(x, self.delay, self.data.string_dt)
                                                                  for x in self._recorded_inputs)
        else:
            self.delay_index = len(self.theta_start)
            self.labels = [*self.labels, "delay"]
            self.theta_start = np.append(self.theta_start, self.delay / DELAY_UNIT)
            self.log_bounds = (np.append(self.log_bounds[0], -MAX_DELAY / DELAY_UNIT),
                               np.append(self.log_bounds[1], MAX_DELAY / DELAY_UNIT))

    def delay_of(self, theta) -> float:
        """The delay [s] at ``theta``: fitted, or the known one."""
        from .calibration_delay import DELAY_UNIT

        return self.delay if self.delay_index is None else float(theta[self.delay_index]) * DELAY_UNIT

    def inputs_at(self, theta: np.ndarray):
        """The rollout's inputs at ``theta``: the constants, and the bar inputs delayed (if any)."""
        from .calibration_delay import delayed

        inputs = dataclasses.replace(self.base, **self.constants(theta))
        if self.delay_index is None:
            return inputs  # self.base holds the known delay's inputs
        top_q, bar_q, bar_qd = (delayed(x, self.delay_of(theta), self.data.string_dt) for x in self._recorded_inputs)
        return dataclasses.replace(inputs, top_q=top_q, bar_q=bar_q, bar_qd=bar_qd)

    def linear(self) -> np.ndarray:
        """Per parameter, 0 where ``theta`` is a log-constant, else the unit of ``theta`` (the delay:
        its value is ``DELAY_UNIT * theta``) ``(n,)``."""
        from .calibration_delay import DELAY_UNIT

        unit = np.where(np.arange(len(self.theta_start)) >= self.constant_count, DELAY_UNIT, 0.0)
        if self.initial_state is not None:
            unit[self.initial_state.offset:] = self.initial_state.units()
        return unit

    def _name_of(self, index: int) -> str:
        offset = 0
        for p in self.params:
            if offset <= index < offset + p.size:
                return p.name
            offset += p.size
        raise IndexError(index)

    def prior_residuals(self, theta):
        """``(exp(theta_i) - mean_i) / sd_i`` for the constants with a prior, ``(priors,)`` (numpy or JAX)."""
        xp = _array_module(theta)
        index = np.array(self._prior_index, dtype=int)
        return (xp.exp(theta[index]) - self._prior_mean) / self._prior_sd

    def prior_slice(self) -> tuple[int, int]:
        """Residual index range of the prior rows (empty without priors)."""
        return self.data_residual_count, self.residual_count

    def use_windows(self, window_steps: int | None, prefix_steps: int | None = None) -> None:
        """Multiple shooting with ``window_steps`` puppet steps per window from now on (None: one
        rollout over the session); the model and its compiled kernels are kept. ``prefix_steps``:
        only the first puppet steps of the session (windows over them; the forward-only residuals
        and Jacobians then hold only their rows, ``active_rows``, and the prior's). Clears
        ``row_weights``."""
        self.active_rows = None
        self.row_weights = None
        self._drop_initial_state()
        if window_steps is None:
            if self.fit_initial_state:
                raise ValueError("--fit-initial-state refines the start states of the shooting windows, taken from "
                                 "the recording; one rollout (--window 0) starts from the scene's rest state only: "
                                 "use windows (the default)")
            self.windows = None
            return
        if prefix_steps is not None and prefix_steps < self.data.puppet_steps:
            rows = []
            for target, (a, _) in self._rows_of.items():
                d = self.data
                per_step = 3 * (len(d.bodies) if target == "bodies" else len(d.bars) * d.substeps)
                rows.append(np.arange(a, a + prefix_steps * per_step))
            rows.append(np.arange(*self.prior_slice()))
            self.active_rows = np.concatenate(rows)
        else:
            prefix_steps = None
        from .calibration_windows import WindowedRollout, recorded_joint_q

        joint_q = recorded_joint_q(self.data)
        if joint_q is None:
            raise ValueError(f"{self.data.path}: multiple shooting (windows) starts each window from the recorded "
                             "puppet state, but channel /puppet/state does not hold 'joint_q' at every puppet "
                             "frame; calibrate with one rollout (windows off) instead")
        self.windows = WindowedRollout(self.model, self.data, joint_q, int(window_steps), puppet_steps=prefix_steps)
        if self.fit_initial_state and prefix_steps is None:
            self._add_initial_state()

    def _add_initial_state(self) -> None:
        """The start states of the windows but the first as unknowns (after the other parameters)."""
        from .calibration_initial_state import InitialStateUnknowns

        d = self.data
        per_step = {"bodies": 3 * len(d.bodies), "feedback": 3 * len(d.bars)}
        unknowns = InitialStateUnknowns(self.windows.windows, self.model.puppet.topology.qd_count, self.noise_joint,
                                        d.puppet_dt, len(self.theta_start), self._rows_of, per_step, d.substeps,
                                        self.residual_count)
        self.initial_state = unknowns
        self.labels = [*self.labels, *unknowns.labels()]
        self.theta_start = np.concatenate([self.theta_start, np.zeros(unknowns.count)])
        self.log_bounds = tuple(np.concatenate([b, np.full(unknowns.count, sign * np.inf)])
                                for b, sign in zip(self.log_bounds, (-1.0, 1.0)))
        self.residual_count += unknowns.count

    def _drop_initial_state(self) -> None:
        unknowns, self.initial_state = getattr(self, "initial_state", None), None
        if unknowns is None:
            return
        keep = unknowns.offset
        self.labels, self.theta_start = self.labels[:keep], self.theta_start[:keep]
        self.log_bounds = tuple(b[:keep] for b in self.log_bounds)
        self.residual_count -= unknowns.count

    # ------------------------------------------------------------------ parameters
    def _wrap_engine(self) -> None:
        forward, backward = self.engine.forward, self.engine.backward

        def counted_forward(inputs):
            self.counts["forward"] += 1
            if self.on_forward is not None:
                self.on_forward(self.counts["forward"])
            return forward(inputs)

        def counted_backward(cotangents):
            self.counts["backward"] += 1
            return backward(cotangents)

        self.engine.forward, self.engine.backward = counted_forward, counted_backward

    def _start_theta(self, start: Mapping[str, float | Sequence[float]]) -> np.ndarray:
        unknown = sorted(set(start) - {p.name for p in self.params})
        if unknown:
            raise ValueError(f"start values for {unknown}, which are not fitted (fitted: "
                             f"{[p.name for p in self.params]})")
        theta = []
        for p in self.params:
            scene_values = np.array([getattr(s, SPEC_FIELDS[p.name]) for s in self.data.scene.strings], float)
            values = np.broadcast_to(np.asarray(start.get(p.name, scene_values), float), (len(scene_values),))
            chosen = values[list(p.strings)]
            if not np.all(np.isfinite(chosen) & (chosen > 0.0)):
                raise ValueError(f"start value of {p.name}: got {chosen.tolist()}; expected positive numbers")
            theta.append(np.log([np.exp(np.mean(np.log(chosen)))] if p.shared else chosen))
        return np.concatenate(theta)

    def constants(self, theta) -> dict[str, np.ndarray]:
        """The engine's per-string constant arrays ``(S,)`` for log-parameters ``theta`` (numpy or JAX)."""
        xp = _array_module(theta)
        out, offset = {}, 0
        for p in self.params:
            field = ENGINE_FIELDS[p.name]
            values = xp.asarray(getattr(self.base, field), dtype=xp.float64)
            block = xp.exp(theta[offset:offset + p.size])
            index = np.array(p.strings)
            block = xp.broadcast_to(block, (len(index),))
            values = values.at[index].set(block) if xp is not np else _set(values, index, block)
            out[field] = values
            offset += p.size
        return out

    def values(self, theta) -> np.ndarray:
        """The fitted constants themselves, ``exp(theta)`` [N/m or N s/m], and the linear unknowns
        (the delay [s]) as they are."""
        theta, unit = np.asarray(theta, dtype=np.float64), self.linear()
        return np.where(unit > 0, unit * theta, np.exp(np.where(unit > 0, 0.0, theta)))

    # ------------------------------------------------------------------ residuals
    def _target_layout(self) -> dict[str, tuple[int, int]]:
        """Where each target's residuals sit in the residual vector: name -> (start, stop)."""
        d, layout, offset = self.data, {}, 0
        names = self.model.puppet.body_names
        missing = [b for b in d.bodies if b not in names]
        if missing and d.body_pos is not None:
            raise ValueError(f"{d.path}: bodies {missing} of the session are not in the simulated puppet {names}")
        self._body_index = np.array([names.index(b) for b in d.bodies]) if d.body_pos is not None else None
        if d.body_pos is not None:
            size = d.puppet_steps * len(d.bodies) * 3
            layout["bodies"] = (offset, offset + size)
            offset += size
        if d.bar_reaction is not None:
            size = d.step_count * len(d.bars) * 3
            layout["feedback"] = (offset, offset + size)
            offset += size
        self.residual_count = offset
        return layout

    def residuals_from_outputs(self, outputs: Mapping[str, object]):
        """Scaled residuals from rollout outputs (a dict of arrays, numpy or JAX), ``(m,)``."""
        d = self.data
        xp = _array_module(outputs["body_pos"])
        parts = []
        if d.body_pos is not None:
            simulated = outputs["body_pos"][1:, self._body_index]
            parts.append(((simulated - d.body_pos[1:]) / self.noise["bodies"]).reshape(-1))
        if d.bar_reaction is not None:
            simulated = outputs["bar_reaction"][:, :len(d.bars)]
            parts.append(((simulated - d.bar_reaction) / self.noise["feedback"]).reshape(-1))
        return xp.concatenate(parts)

    def host_residuals(self, theta: np.ndarray) -> np.ndarray:
        """Residuals ``(m,)`` at ``theta`` from one forward rollout (numpy, no JAX)."""
        inputs = self.inputs_at(np.asarray(theta, np.float64))
        if self.windows is None:
            outputs = dataclasses.asdict(self.engine.forward(inputs))
        else:
            self.counts["forward"] += 1  # one pass over every window: one rollout of the session
            if self.on_forward is not None:
                self.on_forward(self.counts["forward"])
            refine = None if self.initial_state is None else self.initial_state.refine(np.asarray(theta, np.float64))
            outputs = self.windows.forward(inputs, refine)
        return self._residuals_at(theta, outputs)

    def _residuals_at(self, theta: np.ndarray, outputs: dict) -> np.ndarray:
        """What :meth:`host_residuals` returns, from the rollout's ``outputs`` at ``theta``."""
        data = np.asarray(self.residuals_from_outputs(outputs))
        parts = [data]
        if self._prior_index:
            parts.append(self.prior_residuals(np.asarray(theta, np.float64)))
        if self.initial_state is not None:
            parts.append(self.initial_state.prior_rows(theta))
        full = np.concatenate(parts) if len(parts) > 1 else data
        out = full if self.active_rows is None else full[self.active_rows]
        return out if self.row_weights is None else out * self.row_weights

    def residuals_at(self, points: Sequence[np.ndarray]) -> list[np.ndarray]:
        """:meth:`host_residuals` at each of ``points`` (log-constants ``(n,)`` each), their rollouts run
        together as the worlds of one batched marionette (one launch per pass for all of them: the
        per-launch and per-window Python costs are paid once; each world's numbers are bit for bit its
        own rollout's); the finite differences' rollouts (a stacked problem runs its sessions' in
        parallel)."""
        thetas = [np.asarray(t, np.float64) for t in points]
        if len(thetas) == 1:
            return [self.host_residuals(thetas[0])]
        runner = self._batched(len(thetas))
        inputs = [self.inputs_at(t) for t in thetas]
        self.counts["forward"] += len(thetas)
        if self.on_forward is not None:
            self.on_forward(self.counts["forward"])
        if self.windows is None:
            outputs = [dataclasses.asdict(out) for out in runner.forward(inputs)]
        else:
            refine = None if self.initial_state is None else [self.initial_state.refine(t) for t in thetas]
            outputs = runner.forward(inputs, refine)
        return [self._residuals_at(t, out) for t, out in zip(thetas, outputs)]

    def _batched(self, worlds: int):
        """The batched rollout of ``worlds`` worlds for the current windows (built once per count and
        window layout; the batched model compiles nothing new: its kernels are the one-world model's)."""
        from dmarionette.grad.engine import MarionetteGradient
        from dmarionette.marionette.solver import MarionetteModel

        layout = None if self.windows is None else (self.windows.window_steps, self.windows.puppet_steps)
        key = (worlds, layout)
        cache = self.__dict__.setdefault("_batched_runners", {})
        if key not in cache:
            cache.clear()  # one batched model at a time: they hold W times the one-world arrays
            model = MarionetteModel(self.data.scene, world_count=worlds, optimization_level=self._optimization_level,
                                    requires_grad=True)
            if self.windows is None:
                cache[key] = MarionetteGradient(model, self.data.puppet_steps,
                                                checkpoint_steps=self.engine.checkpoint_steps)
            else:
                from .calibration_windows import WindowedRollout

                cache[key] = WindowedRollout(model, self.data, self.windows.joint_q, self.windows.window_steps,
                                             puppet_steps=self.windows.puppet_steps)
        return cache[key]

    def fd_jacobian(self, theta: np.ndarray, *, central: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Residuals ``(m,)`` and their Jacobian ``(m, n)`` from forward rollouts alone (the
        forward sensitivities by finite differences in log space, every residual at once), the
        ``n + 1`` (``2 n + 1``) rollouts run together as the worlds of one batched marionette
        (:meth:`residuals_at`).

        ``central``: ``(r(t + h e_j) - r(t - h e_j)) / 2h`` with ``h = 1e-5`` (``2 n + 1``
        rollouts; truncation ~1e-10, round-off ~1e-11 relative); else one-sided
        ``(r(t + h e_j) - r(t)) / h`` with ``h = 1e-6`` (``n + 1`` rollouts; error ~1e-6
        relative, which moves the Gauss-Newton steps, not the optimum they converge to).
        """
        theta = np.asarray(theta, np.float64)
        step = _FD_STEP if central else _FD_STEP_ONE_SIDED
        # The initial states' block by colouring (calibration_initial_state), the rest batched as worlds.
        columns = len(theta) if self.initial_state is None else self.initial_state.offset
        points = [theta]
        for j in range(columns):
            for sign in ((1.0, -1.0) if central else (1.0,)):
                moved = theta.copy()
                moved[j] += sign * step
                points.append(moved)
        values = self.residuals_at(points)  # [r(theta), r(up_0), (r(down_0)), r(up_1), ...]
        value = values[0]
        jacobian = np.empty((len(value), len(theta)))
        if self.initial_state is not None:
            jacobian[:, columns:] = self.initial_state.colored_columns(self.host_residuals, theta, value, step, central)
        for j in range(columns):
            if central:
                jacobian[:, j] = (values[1 + 2 * j] - values[2 + 2 * j]) / (2 * step)
            else:
                jacobian[:, j] = (values[1 + j] - value) / step
        return value, jacobian

    def jax_residuals(self) -> tuple[Callable, dict]:
        """``(r, base)``: ``r(theta, base)`` in JAX through the reverse-mode rollout wrapper
        (custom VJP), and ``base``, the rollout's fixed inputs (bars, initial state) as JAX
        arrays. Pass ``base`` as the solver's ``args`` so that, under ``jit``, it is traced
        like ``theta`` rather than closed over."""
        import jax.numpy as jnp

        from .rollout import marionette_rollout

        rollout = marionette_rollout(self.engine)
        base = {f.name: jnp.asarray(getattr(self.base, f.name)) for f in dataclasses.fields(self.base)}

        def residuals(theta, base):
            outputs = rollout({**base, **self.constants(theta)})
            data = self.residuals_from_outputs(outputs)
            return jnp.concatenate([data, self.prior_residuals(theta)]) if self._prior_index else data

        return residuals, base

    def subsample_rows(self, rows: int) -> np.ndarray:
        """About ``rows`` residual indices spread evenly over time for each target (in proportion
        to its size), every coordinate of a chosen frame or step kept together."""
        d = self.data
        picked = []
        total = self.residual_count
        for target, (a, b) in self._rows_of.items():
            per = 3 * (len(d.bodies) if target == "bodies" else len(d.bars))
            times = (b - a) // per
            want = max(1, round(rows * (b - a) / total / per))
            chosen = np.unique(np.linspace(0, times - 1, min(want, times)).round().astype(int))
            picked.append((a + chosen[:, None] * per + np.arange(per)[None, :]).reshape(-1))
        picked.append(np.arange(*self.prior_slice()))  # the prior rows, always
        return np.concatenate(picked)

    def target_slices(self) -> dict[str, tuple[int, int]]:
        """Residual index range of each target: ``{"bodies": (a, b), "feedback": (a, b)}``."""
        return dict(self._rows_of)


def _array_module(value):
    if isinstance(value, np.ndarray) or np.isscalar(value):
        return np
    import jax.numpy as jnp

    return jnp


def _set(values: np.ndarray, index: np.ndarray, block: np.ndarray) -> np.ndarray:
    values = np.array(values, dtype=np.float64)
    values[index] = block
    return values
