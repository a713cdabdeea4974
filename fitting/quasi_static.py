"""The quasi-static warm start of the keyframe solve: per keyframe, the bar pose whose static
equilibrium puts the puppet closest to that keyframe's targets (issue 15 item 1; the idea of
Yamane et al.'s and the Tokyo Tech marionette work: control a marionette through its static
equilibria first, the dynamics second).

- **Which knot.** Keyframes are taken in time order. For each authored bar, the knot nearest
  the keyframe's time carries the pose (a later keyframe nearest the same knot poses it again).
- **The settle.** The motion up to that knot, then held: the bars follow the knots found so far
  (knots not posed by any keyframe linear in time between the posed ones; the first knot is the
  start pose), reach the pose ``P`` at its knot's time and stay there for ``HOLD_S`` (or until
  the keyframe's time, if that is later); the puppet's state at the end is taken as the static
  equilibrium for ``P``. It is the rollout of
  :mod:`fitting.author` itself (same marionette, particles, rates, contacts), for that
  shorter motion. Whether it really is at rest is checked (the largest body centre speed over
  the last puppet step, against ``REST_SPEED``) and reported; a pose that is not at rest is
  still a warm start, no more. The settle moves the bars with the motion's own timing: with
  contacts the equilibrium depends on the way there (in the chair, a fast lift stands the
  puppet up where a slow one leaves it seated).
- **The pose.** The free coordinates of the authored bars (as the keyframes file frees them),
  each position within the same bound as the main solve's knots (``start + a sin u``,
  :class:`fitting.knot_bounds.BoundedKnots`), so the pose is a knot value the main solve can
  take; the other coordinates keep the scene's knot values. Bars that are not authored follow
  the scene's motion (also during the hold: a deviation for scenes whose other bars move).
- **The solve.** First a global look, then a local one. The settle is cheap and the pose has few
  coordinates, so ``SAMPLES_PER_COORDINATE`` random poses per coordinate (uniform in the bounded
  variables, angles within ``ANGLE_RANGE_DEG``; a fixed seed: the same every run) and the current
  pose are settled, and the best is refined by Levenberg-Marquardt
  (:func:`fitting.least_squares.levenberg_marquardt`) on the keyframe's weighted residuals of the
  settled state (as the main solve weighs them), forward-difference Jacobians (one settle per
  coordinate, step ``FD_STEP``), ``MAX_STEPS`` trial points at most. The look is needed: with contacts the scene's
  own pose is a local minimum of the static map too (the chair: raising the bar a little lifts
  the knees and rocks the puppet back on the seat; standing needs the bar 15 cm up and pitched
  ~50-60 deg).
- **The start knots.** The posed knots as found; knots between posed ones linear in time; knots
  after the last posed one held at it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from .keyframes import BAR_DOFS, BarFreedom
from .knot_bounds import ANGLE_SCALE, POSITION_SCALE
from .least_squares import levenberg_marquardt

__all__ = ["QuasiStaticPose", "QuasiStaticStart", "HOLD_S", "REST_SPEED", "quasi_static_start"]

HOLD_S = 1.5         # [s] the pose is held this long before the settled state is read: enough for the chair
                     # (feet and seat damp it: 0.6-7 mm/s at the end), not for the free-hanging puppet,
                     # which is barely damped and still swings after 1.5 s (18 mm/s) and after 3 s
                     # (56 mm/s): it is printed "NOT at rest", and the pose fits a swinging snapshot
                     # (a known limitation; averaging over the swing would fix it, not done)
REST_SPEED = 0.01    # [m/s] the settled state is at rest when no body centre moves faster
MAX_STEPS = 12       # LM trial points per keyframe
SAMPLES_PER_COORDINATE = 16  # random poses settled per free coordinate before the LM refinement
ANGLE_RANGE_DEG = 90.0       # sampled bar angles within +-90 deg of the start's (a hand turns a bar that far)
UNBOUNDED_RANGE = 4.0        # sampled unbounded positions within +-4 units of z (20 cm) of the start's
SEED = 15
FD_STEP = 1e-6       # forward-difference step in u (as the main solve's)
MAX_STEP = 0.5       # the largest change of one coordinate of u in a step


@dataclasses.dataclass
class QuasiStaticPose:
    """One keyframe's quasi-static pose.

    Attributes:
        keyframe: the keyframe's index; t: its time [s].
        knots: authored bar name -> the time [s] of the knot that carries the pose.
        values: authored bar name -> ``(6,)`` the pose: position [m], XYZ Euler angles [deg].
        cost_start, cost_sampled, cost: ``0.5 |r|^2`` of the keyframe's weighted residuals at the
            settled state: from the pose before (the scene's, or an earlier keyframe's), the best
            sample, and after the LM refinement.
        errors: target name -> error of the settled state (position [m], joint and orientation [deg]).
        speed: the largest body centre speed at the end of the settle [m/s]; at_rest: ``speed <= REST_SPEED``.
        status: the LM run's status; settles: settle rollouts run; seconds: wall time.
    """

    keyframe: int
    t: float
    knots: dict
    values: dict
    cost_start: float
    cost_sampled: float
    cost: float
    errors: dict
    speed: float
    at_rest: bool
    status: str
    settles: int
    seconds: float


@dataclasses.dataclass
class QuasiStaticStart:
    """The warm start: ``z`` of the main solve and the poses it was built from."""

    z: np.ndarray
    poses: list[QuasiStaticPose]
    seconds: float

    def summary(self) -> dict:
        return {"seconds": self.seconds, "poses": [
            {**dataclasses.asdict(p), "values": {n: v.tolist() for n, v in p.values.items()}} for p in self.poses]}


class Settle:
    """The settle of one keyframe: its rollout, pose variables and residuals."""

    def __init__(self, problem, residuals, k: int, current: dict, posed: dict, hold_s: float = HOLD_S):
        from .author_problem import build_problem

        spec, pose = problem.spec, problem.spec.keyframes[k]
        dt = problem.model.puppet_dt
        self.k = k
        self.res = residuals
        self.bars = []  # (name, knot index j, knot times up to j, free dofs, bounds, start, posed before j)
        end = 0.0
        for a in problem.param.authored:
            knots = a["knots"]
            j = int(np.argmin(np.abs(knots[1:] - pose.t))) + 1
            before = max(i for i in posed[a["name"]] if i < j)
            column_bounds = residuals.bounds.bounds[a["name"]][0]
            self.bars.append((a["name"], j, knots[:j + 1], a["free"], column_bounds, a["initial"][0], before))
            end = max(end, knots[j])
        # read at rest (HOLD_S after the last posed knot), or at the keyframe if that is later (nearer the motion)
        duration = max(1, round(max(end + hold_s, pose.t) / dt)) * dt
        bars = tuple(BarFreedom(name=name, knots=tuple(float(t) for t in times), free=BAR_DOFS)
                     for name, _, times, *_ in self.bars)
        self.spec = dataclasses.replace(spec, duration=duration, bars=bars, end_at_rest=False,
                                        keyframes=(dataclasses.replace(pose, t=duration, weight=1.0),))
        self.problem = build_problem(self.spec)
        self.initial = {a["name"]: a["initial"] for a in self.problem.param.authored}
        self.current = current
        # the pose variables: (bar, knot, dof, bound a or NaN, start value, reference value)
        self.coordinates = []
        for name, j, _, free, bounds, start, _ in self.bars:
            for column, dof in enumerate(free):
                self.coordinates.append((name, j, int(dof), float(bounds[column]), float(start[dof]),
                                         float(current[name][j, dof])))
        keep = (residuals.entry_keyframe == k) & (residuals.entry_kind != "rest")
        self.weights = (residuals.entry_weight * residuals.entry_mask)[keep]

    def knot_values(self, u: np.ndarray) -> dict[str, np.ndarray]:
        """Per bar, the knot values ``(j + 1, 6)`` [m, deg] of the settle for pose variables ``u``."""
        values = {name: self.current[name][:j + 1].copy() for name, j, *_ in self.bars}
        for (name, j, dof, bound, start, ref), ui in zip(self.coordinates, u):
            if not np.isnan(bound):
                values[name][j, dof] = start + bound * np.sin(ui)
            elif dof < 3:
                values[name][j, dof] = ref + POSITION_SCALE * ui
            else:
                values[name][j, dof] = ref + np.degrees(ANGLE_SCALE * ui)
        for name, j, times, _, _, _, before in self.bars:  # knots not posed: linear in time
            for i in range(before + 1, j):
                w = (times[i] - times[before]) / (times[j] - times[before])
                values[name][i] = (1 - w) * values[name][before] + w * values[name][j]
        return values

    def u0(self) -> np.ndarray:
        """The pose variables of the current knot values (bounded ones within 95 % of their bound)."""
        return np.array([np.arcsin(np.clip((ref - start) / bound, -0.95, 0.95)) if not np.isnan(bound) else 0.0
                         for _, _, _, bound, start, ref in self.coordinates])

    def samples(self, count: int) -> np.ndarray:
        """``count`` random pose variables: bounded positions uniform over their bound, unbounded
        ones within ``UNBOUNDED_RANGE`` of the current value, angles within ``ANGLE_RANGE_DEG`` (fixed seed)."""
        rng = np.random.default_rng(SEED + self.k)
        unit = rng.uniform(-1.0, 1.0, size=(count, len(self.coordinates)))
        scale = np.array([np.pi / 2 if not np.isnan(bound) else UNBOUNDED_RANGE if dof < 3
                          else np.radians(ANGLE_RANGE_DEG) / ANGLE_SCALE
                          for _, _, dof, bound, _, _ in self.coordinates])
        return unit * scale

    def outputs(self, u: np.ndarray) -> dict[str, np.ndarray]:
        values = self.knot_values(u)
        y = {name: (values[name][1:] - initial[1:]) * np.where(np.arange(6) >= 3, np.pi / 180.0, 1.0)
             for name, initial in self.initial.items()}
        return self.problem.forward(y)

    def residuals(self, outputs: dict) -> np.ndarray:
        key = self.problem.objective.keyframe_residuals(outputs)
        errors = np.concatenate([np.asarray(key[kind]).ravel() for kind in ("point", "body", "joint", "orientation")])
        return self.weights * errors

    def speed(self, outputs: dict) -> float:
        return float(np.linalg.norm(self.problem.objective.end_velocity(outputs), axis=1).max())


def quasi_static_start(problem, residuals, *, max_steps: int = MAX_STEPS, deadline: float | None = None,
                       say: Callable[[str], None] = lambda line: None, hold_s: float = HOLD_S) -> QuasiStaticStart:
    """The quasi-static warm start of ``problem`` (see the module).

    Args:
        problem: an :class:`fitting.author.AuthoringProblem`.
        residuals: its :class:`fitting.author_solve.KeyframeResiduals` (weights, bounds, and the
            targets the reachability pre-check left out).
        max_steps: LM trial points per keyframe; deadline: ``time.perf_counter()`` after which no
            new keyframe is posed.
        say: receives one line per keyframe.
        hold_s: how long the pose is held before the settled state is read [s].
    """
    started = time.perf_counter()
    current = {a["name"]: a["initial"].copy() for a in problem.param.authored}  # (K, 6) knots [m, deg]
    posed = {a["name"]: {0} for a in problem.param.authored}
    poses = []
    for k, pose in enumerate(problem.spec.keyframes):
        if deadline is not None and time.perf_counter() >= deadline:
            break
        t0 = time.perf_counter()
        settle = Settle(problem, residuals, k, current, posed, hold_s)
        if not np.any(settle.weights > 0) or not settle.coordinates:
            continue  # every target of this keyframe left out, or nothing to pose
        count = [0]

        def r(u):
            count[0] += 1
            return settle.residuals(settle.outputs(u))

        def jac(u, r0):
            out = np.zeros((len(r0), len(u)))
            for j in range(len(u)):
                trial = u.copy()
                trial[j] += FD_STEP
                out[:, j] = (r(trial) - r0) / FD_STEP
            return out

        u0 = settle.u0()
        r0 = r(u0)
        cost_start = 0.5 * float(r0 @ r0)
        best, best_cost = u0, cost_start
        for u in settle.samples(SAMPLES_PER_COORDINATE * len(u0)):
            ru = r(u)
            cost = 0.5 * float(ru @ ru)
            if np.isfinite(cost) and cost < best_cost:
                best, best_cost = u, cost
        result = levenberg_marquardt(r, jac, best, max_steps=max_steps, deadline=deadline, max_step=MAX_STEP,
                                     stall_steps=4, stall_rtol=0.02)
        values = settle.knot_values(result.x)
        outputs = settle.outputs(result.x)
        speed = settle.speed(outputs)
        for name, j, *_ in settle.bars:
            current[name][:j + 1] = values[name]
            posed[name].add(j)
        errors = _errors(settle, outputs)
        poses.append(QuasiStaticPose(
            keyframe=k, t=pose.t, knots={name: float(times[j]) for name, j, times, *_ in settle.bars},
            values={name: values[name][j].copy() for name, j, *_ in settle.bars}, cost_start=cost_start,
            cost_sampled=best_cost, cost=result.cost, errors=errors, speed=speed, at_rest=speed <= REST_SPEED,
            status=result.status, settles=count[0], seconds=time.perf_counter() - t0))
        text = ", ".join(f"{n} {v * 1000:.3g} mm" if not n.endswith(" deg") else f"{n[:-4]} {v:.3g} deg"
                         for n, v in errors.items())
        say(f"quasi-static pose of keyframe {k + 1}: cost {cost_start:.4g} -> {best_cost:.4g} (best of "
            f"{SAMPLES_PER_COORDINATE * len(u0)} samples) -> {result.cost:.4g} ({result.status}); "
            f"{count[0]} settles, {time.perf_counter() - t0:.1f} s; settled "
            f"{'at rest' if speed <= REST_SPEED else 'NOT at rest'} ({speed:.3g} m/s): {text}")
    for a in problem.param.authored:  # knots after the last posed one: held at it
        last = max(posed[a["name"]])
        current[a["name"]][last + 1:] = current[a["name"]][last]
    y = {a["name"]: ((current[a["name"]][1:] - a["initial"][1:])
                     * np.where(np.arange(6) >= 3, np.pi / 180.0, 1.0))[:, a["free"]]
         for a in problem.param.authored}
    return QuasiStaticStart(z=residuals.bounds.z_of_y(y), poses=poses, seconds=time.perf_counter() - started)


def _errors(settle: Settle, outputs: dict) -> dict[str, float]:
    """Target name -> error of the settled state: positions [m] (key ``name`` or ``name (body)``),
    joints and orientations [deg] (keys ending in `` deg``)."""
    key = settle.problem.objective.keyframe_residuals(outputs)
    pose = settle.spec.keyframes[0]
    out = {}
    for i, name in enumerate(pose.points):
        out[name] = float(np.linalg.norm(key["point"][i]))
    for i, name in enumerate(pose.bodies):
        out[f"{name} (body)"] = float(np.linalg.norm(key["body"][i]))
    i = 0
    for name, angles in pose.joints.items():
        out[f"{name} deg"] = float(np.degrees(np.abs(key["joint"][i:i + len(angles)]).max()))
        i += len(angles)
    for i, name in enumerate(pose.orientations):
        half = min(float(np.linalg.norm(key["orientation"][i])) / 2.0, 1.0)
        out[f"{name} (orientation) deg"] = float(np.degrees(2.0 * np.arcsin(half)))
    return out
