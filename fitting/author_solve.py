"""The keyframe solve: Levenberg-Marquardt on the keyframe residuals, hard device limits,
continuation over keyframes, and an honest verdict per keyframe.

- **Variables.** ``z``, the authored knots through :class:`fitting.knot_bounds.BoundedKnots`:
  every bar path stays inside the device workspace by construction.
- **Residuals.** Per keyframe target ``w k (x - x*)`` (``w`` the point or joint weight of
  ``[weights]``, ``k`` the keyframe's own ``weight``), then the smoothness residuals.
- **Jacobian.** Forward differences of whole rollouts (``n + 1`` forward rollouts for ``n``
  knot coordinates) for the keyframe rows; the smoothness rows (a function of the knots
  only) by JAX forward mode, exactly. Measured against the reverse-mode Jacobian
  (``benchmarks/bench_author.py --jacobians``): forward differences are cheaper (one forward
  rollout per coordinate against one backward pass, 4-5 forward rollouts' worth, per residual)
  and agree with it to the rounding of the step (see docs/authoring.md).
- **Device force.** A hard limit too: a trial point whose replay would send a device more
  than its peak force is rejected like a cost increase (the start must be feasible; if the
  scene's own start already exceeds it, no trial may exceed the start's peak, and the
  result says the limit is not met).
- **Continuation.** Keyframes are switched on in time order: stage ``k`` fits keyframes
  ``1..k`` from where stage ``k - 1`` ended.
- **Stalls at contacts.** Where a hard contact starts or ends between ``z`` and a probe
  ``FD_STEP`` away, the rollout jumps and that difference is no slope (the ball kick: the end
  pose jumped by 1 mm and 0.8 deg for 50 nm of a knot), so every trial step fails. A stage that
  stalls short of half the tolerances goes on with differences over ``FD_STEP_COARSE``, which
  span such jumps.
- **The best point seen.** Every point a stage evaluates (not the probes) is kept with its
  errors; where the solve's own point misses a target, an evaluated point that reaches every
  target (a trial of another stage, a per-target solve's step) is the result instead.
- **Verdict.** A keyframe is *reached* when every target is within the position and angle
  tolerances. Targets the reachability pre-check (:mod:`fitting.reachability`) rules out are
  left out from the start. When the solve ends with targets missed, each missed target is
  solved alone from there, the farthest first (with a budget of ``max_steps`` more steps, and
  ``max_steps`` again for the final solve without the unreachable ones): if
  it is reached alone, it conflicts with the others; if that solve stops at a
  stationary point, stalls short of it or crawls through its whole budget, it is *unreachable*: such targets are left out and all
  the keyframes solved again without them, so they cannot degrade the others. Conflicts alone
  (nothing unreachable) are solved once more, in time order: keyframe 1 from there, then each
  next keyframe moving only the knot coordinates that cannot move the earlier ones (the bar
  motion up to them does not depend on these: causality), so an earlier keyframe, once reached,
  stays reached. What is still missed: *not converged*.
- **Restart.** When the result misses a target the pre-check does not rule out (not converged, or
  unreachable by the analysis above, which only shows that no small change helps from where the
  solve stopped), the whole solve and its analysis run again from the other start (the
  quasi-static warm start, :mod:`fitting.quasi_static`, after the scene's own bar motion; the
  scene's after the warm start), with budgets of their own; with the secant Jacobian (the default)
  and still a miss, once more from there with forward-difference Jacobians. The result that misses
  fewer targets (then: by less relative to its tolerance) is kept, and a note says which. A target
  the analysis calls unreachable that some evaluated point reached is *not converged* instead. A
  local solve can stop in another basin than a bar motion that reaches every target: on the lead's
  random references, with the main bar's depth knots pressed on the workspace bound on the side
  away from the reference's (docs/authoring.md, "When the solve misses"). A solve that reaches every
  target never restarts, so its result is unchanged.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import numpy as np

from .knot_bounds import BoundedKnots
from .least_squares import LMResult, levenberg_marquardt

jax.config.update("jax_enable_x64", True)

__all__ = ["EXIT_CODES", "KeyframeSolve", "KeyframeVerdict", "solve_keyframes"]

#: The exit codes of ``dmarionette author`` (docs/authoring.md).
EXIT_CODES = {"reached": 0, "not_converged": 3, "unreachable": 4, "limit_exceeded": 5}
MAX_STEP = 0.5  # the largest change of one coordinate of z in a step (2.5 cm, 0.05 rad, a bound's half)
STALL_STEPS = 10  # a stage stops when 10 accepted steps lower the cost by less than STALL_RTOL of it
STALL_RTOL = 0.03


def _crawled(result) -> bool:
    """Whether a solve that used up its step budget crawled: over all its steps it lowered the cost
    by less than the stall rule allows per ``STALL_STEPS`` (``STALL_RTOL`` of it per 10 steps, on
    average). The stall rule looks at windows of accepted steps, which a solve that keeps having
    trials rejected may never fill before its budget ends; on average the two say the same."""
    if result.status != "max_steps" or len(result.history) < STALL_STEPS:
        return False
    first, last = result.history[0]["cost"], result.cost
    return first - last < STALL_RTOL * last * len(result.history) / STALL_STEPS
REST = "end at rest"  # the target name of [author] end_at_rest (the last keyframe's)
WARM_BLENDS = (1.0, 0.5, 0.25)  # how far towards the quasi-static warm start the solve may start (force limit)
FD_STEP = 1e-6  # forward-difference step in z (about 5e-8 m or 1e-7 rad of a knot)
FD_STEP_COARSE = 1e-3  # after a stall: about 5e-5 m or 1e-4 rad of a knot


@dataclasses.dataclass
class KeyframeVerdict:
    """One keyframe's outcome.

    Attributes:
        index: the keyframe's position in the file (0-based); t: its time [s].
        status: ``"reached"``, ``"unreachable"`` or ``"not_converged"``.
        errors: target name -> error (position [m], joint: largest axis error [deg]).
        best: for an unreachable keyframe, target name -> the smallest error any solve reached.
        reasons: plain sentences, one per missed target or limiting cause.
        units: target name -> ``"m"`` or ``"deg"``.
    """

    index: int
    t: float
    status: str
    errors: dict
    best: dict
    reasons: list[str]
    units: dict


@dataclasses.dataclass
class KeyframeSolve:
    """The result of :func:`solve_keyframes`."""

    y: dict
    z: np.ndarray
    verdicts: list[KeyframeVerdict]
    status: str
    exit_code: int
    history: list[dict]
    lm_status: list[str]
    messages: list[str]
    peak_force: dict
    seconds: float
    warm_start: dict | None = None  # the quasi-static warm start (QuasiStaticStart.summary()), if run

    @property
    def converged(self) -> bool:
        return self.status == "reached"


class KeyframeResiduals:
    """Residuals and Jacobians of an :class:`fitting.author.AuthoringProblem` in ``z``."""

    def __init__(self, problem, fd_step: float = FD_STEP, position_tolerance: float | None = None,
                 angle_tolerance: float | None = None):
        self.problem = problem
        spec = problem.spec
        self.tolerance = {"m": spec.position_tolerance if position_tolerance is None else position_tolerance,
                          "deg": spec.angle_tolerance if angle_tolerance is None else angle_tolerance,
                          "m/s": spec.rest_tolerance}
        objective = problem.objective
        self.spec = spec = problem.spec
        self.bounds = BoundedKnots(problem.param, objective.boxes if objective.limits is not None else None)
        self.fd_step = fd_step
        self.columns = None  # the coordinates of z the Jacobian is computed for (None: all; the others 0)
        param = problem.param
        self._y = jax.jit(self.bounds.y)
        smooth = lambda z: spec.weights.smoothness * param.acceleration_residuals(self.bounds.y(z))  # noqa: E731
        self._smooth_and_jac = jax.jit(lambda z: (smooth(z), jax.jacfwd(smooth)(z)))
        # Every keyframe residual entry: its keyframe, its target's name and kind, its weight.
        kf, names, kinds, weights = [], [], [], []
        for kind, size in (("point", 3), ("body", 3), ("joint", 1), ("orientation", 3)):
            for k, pose in enumerate(spec.keyframes):
                table = {"point": pose.points, "body": pose.bodies, "joint": pose.joints,
                         "orientation": pose.orientations}[kind]
                for name, value in table.items():
                    count = size if kind != "joint" else len(value)
                    kf += [k] * count
                    names += [name] * count
                    kinds += [kind] * count
                    weights += [spec.weights.point if kind in ("point", "body") else spec.weights.joint] * count
        if spec.end_at_rest:  # every body's end velocity, a target of the last keyframe
            count = 3 * len(problem.model.puppet.body_names)
            kf += [len(spec.keyframes) - 1] * count
            names += [REST] * count
            kinds += ["rest"] * count
            weights += [spec.weights.rest] * count
        self.entry_keyframe = np.array(kf, dtype=np.int64)
        self.entry_name = names
        self.entry_kind = np.array(kinds)
        self.entry_weight = np.array(weights, dtype=np.float64)
        self.keyframe_weight = np.array([pose.weight for pose in spec.keyframes], dtype=np.float64)
        self.active = np.ones(len(spec.keyframes))
        self.entry_mask = np.ones(len(kf))  # 0: a target left out (unreachable by the pre-check)
        self._cache: dict[bytes, dict] = {}

    # ---------------------------------------------------------------- rollouts
    def outputs(self, z) -> dict[str, np.ndarray]:
        """The rollout's outputs at ``z`` (the last few are cached)."""
        z = np.asarray(z, dtype=np.float64)
        key = z.tobytes()
        if key in self._cache:
            return self._cache[key]
        outputs = self._rollout(z)
        if len(self._cache) >= 4:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = outputs
        return outputs

    def _rollout(self, z: np.ndarray) -> dict[str, np.ndarray]:
        return self.problem.forward(self._y(z))

    def errors(self, outputs) -> np.ndarray:
        """Unweighted keyframe errors, one per entry [m] or [rad]."""
        key = self.problem.objective.keyframe_residuals(outputs)
        parts = [np.asarray(key[kind]).ravel() for kind in ("point", "body", "joint", "orientation")]
        if self.spec.end_at_rest:
            parts.append(np.asarray(self.problem.objective.end_velocity(outputs)).ravel())
        return np.concatenate(parts)

    def row_weights(self) -> np.ndarray:
        return self.entry_weight * self.entry_mask * (self.keyframe_weight * self.active)[self.entry_keyframe]

    def residuals(self, z) -> np.ndarray:
        """Weighted keyframe residuals of the active keyframes, then the smoothness residuals."""
        smooth = np.asarray(self._smooth_and_jac(z)[0])
        return np.concatenate([self.row_weights() * self.errors(self.outputs(z)), smooth])

    def smoothness_jacobian(self, z) -> np.ndarray:
        """The smoothness rows of the Jacobian (exact, JAX forward mode)."""
        return np.asarray(self._smooth_and_jac(np.asarray(z, dtype=np.float64))[1])

    def jacobian(self, z, r) -> np.ndarray:
        """Forward differences of the keyframe rows (``n`` rollouts); exact smoothness rows."""
        z = np.asarray(z, dtype=np.float64)
        count = len(self.entry_keyframe)
        base = self.errors(self.outputs(z))
        jac = np.zeros((len(r), len(z)))
        weights = self.row_weights()
        for j in range(len(z)) if self.columns is None else self.columns:
            trial = z.copy()
            trial[j] += self.fd_step
            jac[:count, j] = weights * (self.errors(self._rollout(trial)) - base) / self.fd_step
        jac[count:] = np.asarray(self._smooth_and_jac(z)[1])
        return jac

    def error_jacobian(self, z) -> np.ndarray:
        """Unweighted keyframe errors' Jacobian in ``z`` (forward differences)."""
        saved = self.active
        self.active = np.ones_like(saved)
        try:
            r = self.residuals(z)
            jac = self.jacobian(z, r)[:len(self.entry_keyframe)]
        finally:
            self.active = saved
        weights = self.entry_weight * self.keyframe_weight[self.entry_keyframe]
        return jac / np.where(weights > 0, weights, 1.0)[:, None]

    def later_columns(self, z, keyframe: int) -> np.ndarray:
        """The coordinates of ``z`` that cannot move ``keyframe``: the bar motion up to one puppet step
        after its time does not depend on them (exactly: the spline's Jacobian there is zero), so by
        causality nor does the puppet's pose at the keyframe."""
        jac = jax.jacfwd(lambda zz: self.problem.param.rollout_inputs(self.bounds.y(zz)))(
            np.asarray(z, dtype=np.float64))
        sub = int(round(self.problem.model.puppet_dt / self.problem.model.string_dt))
        last = (int(self.problem.objective.steps[keyframe]) + 1) * sub  # string steps up to here feed the keyframe
        moved = np.zeros(len(z), dtype=bool)
        for value in jac.values():
            value = np.asarray(value)[:last + 1]
            moved |= np.abs(value.reshape(-1, len(z))).max(axis=0) > 0.0
        return np.nonzero(~moved)[0]

    def peak_force(self, z) -> dict[str, float]:
        """Per authored bar: the largest force the device would be sent over the motion [N]."""
        outputs = self.outputs(z)
        field = "bar_reaction" if self.spec.feedback == "reaction" else "bar_feedback"
        return {a["name"]: float(self.spec.force_scale * np.linalg.norm(outputs[field][:, a["index"]], axis=-1).max())
                for a in self.problem.param.authored}

    # ---------------------------------------------------------------- verdicts
    def target_errors(self, z) -> list[dict]:
        """Per keyframe: target name -> error (position [m]; joint: largest axis error [deg])."""
        errors = self.errors(self.outputs(z))
        out = [dict() for _ in self.spec.keyframes]
        i = 0
        while i < len(errors):
            k, name, kind = self.entry_keyframe[i], self.entry_name[i], self.entry_kind[i]
            if kind == "joint":
                j = i
                while j < len(errors) and self.entry_keyframe[j] == k and self.entry_name[j] == name \
                        and self.entry_kind[j] == "joint":
                    j += 1
                out[k][name] = float(np.degrees(np.abs(errors[i:j]).max()))
                i = j
            elif kind == "rest":
                speeds = np.linalg.norm(errors[i:].reshape(-1, 3), axis=1)
                out[k][REST] = float(speeds.max())
                i = len(errors)
            elif kind == "orientation":
                half = min(float(np.linalg.norm(errors[i:i + 3])) / 2.0, 1.0)  # |2 v| = 2 sin(angle / 2)
                out[k][f"{name} (orientation)"] = float(np.degrees(2.0 * np.arcsin(half)))
                i += 3
            else:
                label = name if kind == "point" else f"{name} (body)"
                out[k][label] = float(np.linalg.norm(errors[i:i + 3]))
                i += 3
        return out

    def leave_out(self, keyframe: int, label: str) -> None:
        """Leaves target ``label`` (a :meth:`target_errors` name) of ``keyframe`` out of the fit."""
        name, kind = label, None
        for suffix in ("body", "orientation"):
            if label.endswith(f" ({suffix})"):
                name, kind = label[:-len(suffix) - 3], suffix
        for i in range(len(self.entry_name)):
            if self.entry_keyframe[i] == keyframe and self.entry_name[i] == name and (
                    self.entry_kind[i] == kind if kind else self.entry_kind[i] in ("point", "joint")):
                self.entry_mask[i] = 0.0

    def target_mask(self, keyframe: int, label: str) -> np.ndarray:
        """1 on the entries of target ``label`` of ``keyframe``, 0 elsewhere."""
        saved = self.entry_mask
        self.entry_mask = np.ones_like(saved)
        self.leave_out(keyframe, label)
        mask = 1.0 - self.entry_mask
        self.entry_mask = saved
        return mask

    def reached(self, errors: dict, skip: frozenset = frozenset(), scale: float = 1.0) -> bool:
        """Whether every target of ``errors`` (but ``skip``) is within ``scale`` x its tolerance."""
        return all(v <= scale * self.tolerance[self.unit(n)] for n, v in errors.items() if n not in skip)

    def unit(self, label: str) -> str:
        """The unit of a :meth:`target_errors` name: ``"m"``, ``"deg"`` (joints, orientations), ``"m/s"``."""
        if label == REST:
            return "m/s"
        if label.endswith(" (orientation)") or any(
                self.entry_name[i] == label and self.entry_kind[i] == "joint" for i in range(len(self.entry_name))):
            return "deg"
        return "m"


def solve_keyframes(problem, *, max_steps: int, max_seconds: float | None = None, continuation: bool = False,
                    position_tolerance: float = 1e-3, angle_tolerance: float = 0.5,
                    say: Callable[[str], None] = lambda line: None, z0: np.ndarray | None = None,
                    secant: bool = True, warm_start: str = "scene") -> KeyframeSolve:
    """Levenberg-Marquardt on the keyframes of ``problem`` with hard device limits and a verdict.

    Args:
        problem: an :class:`fitting.author.AuthoringProblem`.
        max_steps: solver iterations (trial points) at most, over all stages.
        max_seconds: wall-time budget [s] of the solve (None: no limit).
        continuation: switch keyframes on in time order (else all at once).
        position_tolerance: [m], angle_tolerance: [deg]: a keyframe is reached within them.
        say: receives progress lines.
        z0: start (default: the scene's own bar motion, or the quasi-static warm start).
        secant: update the keyframe rows of the Jacobian by Broyden's secant formula between
            forward-difference Jacobians (one rollout a step instead of ``n + 1``; see
            :func:`fitting.least_squares.levenberg_marquardt`).
        warm_start: ``"scene"`` (start from the scene's own bar motion) or ``"quasi_static"``
            (:mod:`fitting.quasi_static`: the knots from each keyframe's quasi-static pose, used when
            it lowers the cost and respects the force limit; else the scene's, and a message says why).
    """
    started = time.perf_counter()
    deadline = None if max_seconds is None else started + max_seconds
    res = KeyframeResiduals(problem, position_tolerance=position_tolerance, angle_tolerance=angle_tolerance)
    spec = problem.spec
    count = len(spec.keyframes)
    z = res.bounds.z0() if z0 is None else np.asarray(z0, dtype=np.float64)
    limit = None if problem.objective.limits is None else problem.objective.limits["max_force"]
    start_peak = res.peak_force(z)
    allowed = {name: max(limit, peak) for name, peak in start_peak.items()} if limit is not None else None
    messages = []
    from .reachability import unreachable_targets

    prechecked = unreachable_targets(problem)
    skip = [set() for _ in range(count)]
    for reach in prechecked:
        res.leave_out(reach.keyframe, reach.name)
        skip[reach.keyframe].add(reach.name)
    skip = [frozenset(v) for v in skip]
    if prechecked:
        say("unreachable targets, left out of the fit: " + "; ".join(
            f"keyframe {r.keyframe + 1} {r.sentence()}" for r in prechecked))
    if allowed is not None:
        for name, peak in start_peak.items():
            if peak > limit:
                messages.append(f"bar {name}: the scene's own start already sends the device {peak:.3g} N, above "
                                f"its {limit:.3g} N limit (lower [author] force_scale, now {spec.force_scale:g}); "
                                "no step may raise it further")

    def feasible(zt) -> bool:
        return allowed is None or all(p <= allowed[n] for n, p in res.peak_force(zt).items())

    def quasi_static_z(z_scene: np.ndarray, better: bool = True, warm=None):
        """The quasi-static warm start (:mod:`fitting.quasi_static`), or (when it would send a device more than
        its peak force) the first of the blends z + a (z_warm - z), a = 1/2, 1/4, that does not: a smaller move
        pulls less. ``better``: only where it lowers the cost of ``z_scene``; ``warm``: the warm start if already
        found. Returns (the start or None, the warm start, a line saying which)."""
        from .quasi_static import quasi_static_start

        warm = warm if warm is not None else quasi_static_start(problem, res, deadline=deadline, say=say)
        cost_scene = 0.5 * float(np.sum(res.residuals(z_scene) ** 2))
        use, line = None, ""
        for a in WARM_BLENDS:
            trial = warm.z if a == 1.0 else z_scene + a * (warm.z - z_scene)
            cost = 0.5 * float(np.sum(res.residuals(trial) ** 2))
            if better and not cost < cost_scene:
                line = line or f"cost {cost:.4g}: no better"
                break
            if feasible(trial):
                use = trial
                line = f"cost {cost:.4g}" + ("" if a == 1.0 else f" (the knots {a:g} of the way from the scene's "
                                                                  "to the warm start's: all the way sends a device "
                                                                  "more than its peak force)")
                break
            line = line or "it sends a device more than its peak force"
        line = (f"quasi-static warm start ({warm.seconds:.1f} s): " + line + f", against {cost_scene:.4g} from the "
                "scene's own bar motion; " + ("starting from it" if use is not None else "NOT used"))
        return use, warm, line

    warm = None
    if warm_start == "quasi_static" and z0 is None:
        use, warm, line = quasi_static_z(z)
        say(line)
        messages.append(line)
        if use is not None:
            z = use

    history: list[dict] = []
    lm_status: list[str] = []
    steps_left = [max_steps]

    def record(stage: str):
        def on_step(entry):
            counts = problem.counter() if hasattr(problem, "counter") else {}
            history.append({**entry, "step": len(history), "stage": stage, "loss": entry["cost"],
                            "grad_norm": entry["grad_inf"], "terms": {}, **counts})
            say(f"{len(history) - 1:5d} {stage:>18s} cost {entry['cost']:11.4e} |J^T r| {entry['grad_inf']:10.3e} "
                f"lambda {entry['lambda']:9.2e} Jacobians {entry['jacobians']:3d} {entry['elapsed']:7.1f}s")
        return on_step

    # Every point a stage evaluated (not the forward-difference probes), with its errors on every keyframe:
    # the result is the best of them by the verdict's measure, which need not be where the stage stopped.
    seen: list[tuple[np.ndarray, list[dict], str]] = []

    def shortfall(errors: list[dict], skipped: list | None = None) -> tuple[int, float]:
        """A point's distance from the verdict: (targets missed, the largest error / its tolerance), the
        targets ``skipped`` (default: those left out so far) not counted."""
        skipped = skip if skipped is None else skipped
        ratios = [v / res.tolerance[res.unit(n)] for k in range(count) for n, v in errors[k].items()
                  if n not in skipped[k]]
        return sum(ratio > 1.0 for ratio in ratios), max(ratios, default=0.0)

    def best_seen(z_now: np.ndarray, label: str) -> np.ndarray:
        """``z_now``, or an evaluated point that reaches every target (not left out) where ``z_now`` does not
        (the one with the smallest largest error / tolerance). A point that misses fewer targets but
        by more is not taken: the solve's own point is then the least-squares compromise."""
        best = min(((shortfall(e), i) for i, (_, e, _) in enumerate(seen) if shortfall(e)[0] == 0), default=None)
        if best is None or shortfall(res.target_errors(z_now))[0] == 0:
            return z_now
        z_best, _, where = seen[best[1]]
        lm_status.append(f"{label}: kept the point of {where}, which reaches every target (the largest error "
                         f"{best[0][1]:.3g} x its tolerance)")
        say(lm_status[-1])
        return z_best

    def residuals(zt: np.ndarray) -> np.ndarray:
        r = res.residuals(zt)
        if np.all(np.isfinite(r)) and feasible(zt):
            seen.append((np.array(zt, dtype=np.float64), res.target_errors(zt), f"{stage_now[0]} step {len(history)}"))
        return r

    stage_now = ["start"]
    prefix = [""]  # the stages of a restart are named after its start

    def run(stage: str, active: np.ndarray, z_start: np.ndarray, target: tuple[int, str] | None = None,
            columns: np.ndarray | None = None) -> LMResult:
        """One LM stage on the ``active`` keyframes (or on the single ``target``), moving the
        coordinates ``columns`` of ``z`` (default: all)."""
        stage = prefix[0] + stage
        stage_now[0] = stage
        res.active = active.astype(np.float64)
        on = [k for k in range(count) if active[k] > 0]
        saved_mask = res.entry_mask.copy()
        if target is not None:
            res.entry_mask = saved_mask * res.target_mask(*target)

        def done(zt, rt):
            errors = res.target_errors(zt)
            if target is not None:
                return res.reached({target[1]: errors[target[0]][target[1]]}, scale=0.5)
            return all(res.reached(errors[k], skip[k], scale=0.5) for k in on)

        cols = np.arange(len(z_start)) if columns is None else np.asarray(columns)

        def embed(x):
            full = np.array(z_start, dtype=np.float64)
            full[cols] = x
            return full

        res.columns = cols
        result = levenberg_marquardt(lambda x: residuals(embed(x)), lambda x, r: res.jacobian(embed(x), r)[:, cols],
                                     np.asarray(z_start, dtype=np.float64)[cols], max_steps=max(steps_left[0], 0),
                                     deadline=deadline, done=lambda x, r: done(embed(x), r),
                                     feasible=lambda x: feasible(embed(x)), max_step=MAX_STEP,
                                     secant_rows=len(res.entry_keyframe) if secant else 0,
                                     exact_rows=lambda x: res.smoothness_jacobian(embed(x))[:, cols],
                                     stall_steps=STALL_STEPS, stall_rtol=STALL_RTOL, on_step=record(stage))
        result.x = embed(result.x)
        res.columns = None
        steps_left[0] -= result.steps
        res.entry_mask = saved_mask
        lm_status.append(f"{stage}: {result.status} after {result.steps} steps")
        return result

    z_start = z
    ones = np.ones(count)
    res.active = ones
    r0 = res.residuals(z)
    history.append({"step": 0, "stage": "start", "cost": 0.5 * float(r0 @ r0), "loss": 0.5 * float(r0 @ r0),
                    "grad_norm": float("nan"), "terms": {}, "elapsed": 0.0,
                    **(problem.counter() if hasattr(problem, "counter") else {})})
    say(f"{'step':>5s} {'stage':>18s} (Levenberg-Marquardt; a forward-difference Jacobian costs "
        f"{res.bounds.size} rollouts{', updated by secant steps in between' if secant else ''})")

    def attempt(z: np.ndarray) -> dict:
        """The solve from ``z`` and the analysis of what it misses; returns the point and what the verdict
        needs of it."""
        nonlocal skip
        steps_left[0] = max_steps
        result = None
        if continuation and count > 1:
            for k in range(1, count):
                active = np.where(np.arange(count) < k, 1.0, 0.0)
                result = run(f"keyframes 1-{k}", active, z)
                z = result.x
                if steps_left[0] <= 0 or result.status == "max_seconds":
                    break
        if steps_left[0] > 0 and (result is None or result.status != "max_seconds"):
            result = run("all keyframes", ones, z)
            z = result.x
            errors = res.target_errors(z)
            if result.status in ("stationary", "no_progress") and steps_left[0] > 0 and not all(
                    res.reached(errors[k], skip[k], scale=0.5) for k in range(count)):
                # Stuck short of its goal (half the tolerances): where a hard contact starts or ends between
                # z and a probe 1e-6 away, the rollout jumps (measured on examples/keyframes_ball_kick.toml:
                # 1 mm and 0.8 deg at the end for 50 nm of a knot) and that difference over 1e-6 is no slope.
                # Go on with differences over a step that spans such jumps; the better point is kept.
                res.fd_step = FD_STEP_COARSE
                result = run("coarse differences", ones, z)
                res.fd_step = FD_STEP
                z = best_seen(result.x, "after coarse differences")
        final_status = result.status if result is not None else "max_steps"

        z = best_seen(z, "after the solve")

        # ---- the verdict
        errors = res.target_errors(z)
        missed = [k for k in range(count) if not res.reached(errors[k], skip[k])]
        best = [dict() for _ in range(count)]
        found: dict[tuple[int, str], str] = {}  # (keyframe, target) -> why it is unreachable
        conflict: list[int] = []
        # The analysis of missed keyframes has a budget of its own (max_steps again, and the time left).
        steps_left[0] = max_steps
        if missed and final_status != "max_seconds":
            z_all = z
            # every missed target, the farthest (relative to its tolerance) first, solved alone from here
            targets = sorted(((k, n) for k in missed for n, v in errors[k].items()
                              if n not in skip[k] and v > res.tolerance[res.unit(n)]),
                             key=lambda kn: -errors[kn[0]][kn[1]] / res.tolerance[res.unit(kn[1])])
            for k, name in targets:
                if steps_left[0] <= 0 or (deadline is not None and time.perf_counter() >= deadline):
                    break
                alone = run(f"{name} @ {k + 1} alone", np.where(np.arange(count) == k, 1.0, 0.0), z_all,
                            target=(k, name))
                best[k][name] = res.target_errors(alone.x)[k][name]
                if res.reached({name: best[k][name]}):
                    conflict.append((k, name))
                elif alone.status in ("stationary", "no_progress") or _crawled(alone):
                    found[(k, name)] = (
                        "it stopped at a stationary point (no small change of the bars brings it closer)"
                        if alone.status == "stationary" else
                        f"it stalled ({STALL_STEPS} steps lowered the cost by less than {STALL_RTOL:.0%}): out of "
                        "reach within the device limits as far as this solver can tell")
            if conflict and not found:
                # Targets each reached alone but not together: the keyframes in time order, each stage moving
                # only the coordinates that cannot move the earlier keyframes (by causality: the bar motion up
                # to them does not depend on these), so what an earlier stage reached stays reached.
                z_order = z_all
                for k in range(count):
                    columns = None if k == 0 else res.later_columns(z_order, k - 1)
                    if steps_left[0] <= 0 or (columns is not None and len(columns) == 0) or (
                            deadline is not None and time.perf_counter() >= deadline):
                        break
                    z_order = run(f"keyframe {k + 1} in time order", np.where(np.arange(count) <= k, 1.0, 0.0),
                                  z_order, columns=columns).x
            # a solve for one target may have passed by a better point
            z_seen = best_seen(z_all, "after the analysis")
            if found and shortfall(res.target_errors(z_seen))[0] > 0:
                steps_left[0] = max_steps  # the final solve without them has a budget of its own too
                for k, name in found:
                    res.leave_out(k, name)
                skip = [frozenset(skip[k] | {n for (j, n) in found if j == k}) for k in range(count)]
                again = run("without unreachable", ones, z_all)
                z = best_seen(again.x, "without unreachable")
                final_status = again.status
            else:
                z, found = z_seen, {}
            errors = res.target_errors(z)
        return {"z": z, "found": found, "conflict": conflict, "best": best, "final_status": final_status,
                "skip": skip, "mask": res.entry_mask.copy()}

    skip_first, mask_first = skip, res.entry_mask.copy()  # the pre-check's leave-outs only
    restart = {}  # where the solve restarted: {"restart_kept": whether the result is a restart's}
    outcome = attempt(z)
    missed_first = shortfall(res.target_errors(outcome["z"]), skip_first)
    if missed_first[0] > 0 and outcome["final_status"] != "max_seconds" and (
            deadline is None or time.perf_counter() < deadline):
        # The restart (docs/authoring.md, "When the solve misses"): targets missed that the pre-check does not
        # rule out, and a local solve from one start can stop in the wrong basin (measured: the main bar's
        # depth knots pressed on the workspace bound on the side away from a reference that reaches every
        # target). The whole solve and its analysis again, from the other start: the quasi-static warm start
        # after the scene's, the scene's after the warm start (with the secant Jacobian and still a miss, again
        # with forward-difference Jacobians). The one that misses fewer targets (then: by less) is the result.
        # A solve that reaches every target never gets here: its result is unchanged.
        skip, res.entry_mask, res.active = skip_first, mask_first.copy(), ones
        from_scene = np.array_equal(z_start, res.bounds.z0())
        first = ("the scene's own bar motion" if from_scene else "the quasi-static warm start" if warm is not None
                 else "the given start")
        if from_scene:
            other, warm, line = quasi_static_z(z_start, better=False, warm=warm)
            name = "the quasi-static warm start"
        else:
            other, line, name = res.bounds.z0(), "", "the scene's own bar motion"
        if other is not None:
            # From there with the file's Jacobian, then (if that misses too and it was the secant one) with
            # forward-difference Jacobians every step: measured, each reaches random references the other misses.
            tries = [(name, secant)] + ([(f"{name} with forward-difference Jacobians", False)] if secant else [])
            kept, best_missed, notes, given = "the first result", missed_first, [], secant
            for number, (label, secant) in enumerate(tries, start=1):
                if deadline is not None and time.perf_counter() >= deadline:
                    break
                skip, res.entry_mask, res.active = skip_first, mask_first.copy(), ones
                prefix[0] = "restart: " if number == 1 else f"restart {number}: "
                again = attempt(other)
                prefix[0] = ""
                missed_again = shortfall(res.target_errors(again["z"]), skip_first)
                notes.append(f"again from {label}: misses {missed_again[0]} ({missed_again[1]:.3g} x)")
                if missed_again < best_missed:
                    outcome, best_missed, kept = again, missed_again, label
                if missed_again[0] == 0:
                    break
            secant = given
            restart["restart_kept"] = kept != "the first result"
            # (no seconds in the note: a run's messages are the same on every machine; they are in warm_start)
            line = (f"the solve from {first} missed {missed_first[0]} targets (the largest error {missed_first[1]:.3g} "
                    "x its tolerance); " + "; ".join(notes) + f"; kept: {kept}")
        else:
            line = (f"the solve from {first} missed {missed_first[0]} targets; no restart from {name}: it sends a "
                    "device more than its peak force (also 1/2 and 1/4 of the way there)")
        say(line)
        messages.append(line)
        skip, res.entry_mask = outcome["skip"], outcome["mask"]
    z, found, conflict, best = outcome["z"], outcome["found"], outcome["conflict"], outcome["best"]
    final_status = outcome["final_status"]
    # A target the analysis calls unreachable (a solve for it alone stopped short) that some evaluated point
    # reached (a stage of another start, a solve for another target) is not unreachable: not converged.
    refuted = {}
    for k, name in list(found):
        near = min((e[k][name] for _, e, _ in seen if name in e[k]), default=np.inf)
        if near <= res.tolerance[res.unit(name)]:
            refuted[(k, name)] = near
            del found[(k, name)]
            skip = [frozenset(skip[j] - {name}) if j == k else skip[j] for j in range(count)]
    errors = res.target_errors(z)
    res.active = ones
    peak = res.peak_force(z)
    verdicts = []
    jac = None
    sentences = {(r.keyframe, r.name): r.sentence() + "; left out of the fit" for r in prechecked}
    unit_text = {"deg": lambda v: f"{v:.3g} deg", "m/s": lambda v: f"{v:.3g} m/s (a body's speed)",
                 "m": lambda v: f"{v * 1000:.3g} mm" if v < 1 else f"{v:.3g} m"}
    for k, pose in enumerate(spec.keyframes):
        ok = res.reached(errors[k], skip[k])
        status = "reached" if ok and not skip[k] else "unreachable" if ok else "not_converged"
        reasons = []
        for name, value in errors[k].items():
            unit = unit_text[res.unit(name)]
            if (k, name) in sentences:
                reasons.append(sentences[(k, name)])
            elif (k, name) in found:
                reasons.append(f"{name}: {unit(value)} from the target; a solve for this target alone came no "
                               f"nearer than {unit(best[k][name])}, where {found[(k, name)]}; left out of the "
                               "final fit")
            elif (k, name) in refuted:
                reasons.append(f"{name}: {unit(value)} from the target; a solve for this target alone stopped "
                               f"short, but a point evaluated on the way reached it ({unit(refuted[(k, name)])}, "
                               "not together with the other targets): not unreachable; left out of the final fit")
            elif value > res.tolerance[res.unit(name)]:
                line = f"{name}: {unit(value)} from the target"
                if (k, name) in conflict:
                    line += (f"; a solve for this target alone reaches it ({unit(best[k][name])}), but not together "
                             "with the other targets")
                else:
                    line += f"; the solve stopped before reaching it ({final_status})"
                reasons.append(line)
        verdicts.append(KeyframeVerdict(index=k, t=pose.t, status=status, errors=errors[k], best=best[k],
                                        reasons=reasons,
                                        units={n: res.unit(n) for n in errors[k]}))
        if not ok and jac is None:
            jac = res.error_jacobian(z)
    saturated = res.bounds.saturation(z)
    labels = res.bounds.names()
    flat = np.concatenate([v.ravel() for v in saturated.values()]) if saturated else np.zeros(0)
    at_bound = [i for i in range(len(flat)) if np.isfinite(flat[i]) and flat[i] > 0.99]
    if jac is None:
        jac = res.error_jacobian(z)
    if at_bound and any(v.status != "reached" for v in verdicts):
        # The cost's slope along each bounded knot value: value = start + a sin z, so
        # d cost / d value has the sign of (J^T r)_z cos z; the targets pull the knot out of the
        # box when lowering the cost means moving the value past the bound (the side of sin z).
        weights = res.entry_weight * res.entry_mask * res.keyframe_weight[res.entry_keyframe]
        slope = (jac * weights[:, None]).T @ (weights * res.errors(res.outputs(z)))
        pulled = [labels[i] for i in at_bound if -np.sign(slope[i] * np.cos(z[i])) == np.sign(np.sin(z[i]))]
        if pulled:
            messages.append("the device workspace limits the motion: these knot coordinates are on its bound and "
                            "the targets pull them further out: " + ", ".join(pulled))
        rest = [labels[i] for i in at_bound if labels[i] not in pulled]
        if rest:
            messages.append("knot coordinates at the device workspace bound: " + ", ".join(rest))
    column = np.linalg.norm(jac, axis=0)
    idle = [labels[i] for i in range(len(column)) if column[i] <= 1e-9 * max(column.max(), 1e-300)]
    if idle:
        messages.append("bar coordinates with no effect on any target: " + ", ".join(idle))
    over = {n: p for n, p in peak.items() if limit is not None and p > limit}
    binding = {n: p for n, p in peak.items() if limit is not None and limit >= p >= 0.999 * limit}
    if binding and any(v.status != "reached" for v in verdicts):
        messages.append("the device force limit binds: " + ", ".join(
            f"bar {n} sends {p:.4g} N of the {limit:g} N allowed" for n, p in binding.items())
            + " (no step may raise it; the missed targets may need more force)")
    if any(v.status == "not_converged" for v in verdicts):
        status = "not_converged"
    elif any(v.status == "unreachable" for v in verdicts):
        status = "unreachable"
    elif over:
        status = "limit_exceeded"
    else:
        status = "reached"
    if over:
        messages.append("device force above the limit: " + ", ".join(f"{n} {p:.3g} N > {limit:g} N"
                                                                       for n, p in over.items()))
    y = {k: np.asarray(v) for k, v in res._y(z).items()}
    return KeyframeSolve(y=y, z=z, verdicts=verdicts, status=status, exit_code=EXIT_CODES[status], history=history,
                         lm_status=lm_status, messages=messages, peak_force=peak,
                         seconds=time.perf_counter() - started,
                         warm_start=None if warm is None else {**warm.summary(), "used": bool(not np.array_equal(
                             z_start, res.bounds.z0())), **restart})
