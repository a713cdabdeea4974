"""Keyframes files (TOML): what an animator asks the puppet to do, and how the bars may move.

A keyframes file names a scene, the motion's duration, which bars the optimiser may move
(knot times and free degrees of freedom), the objective's weights, and ``[[keyframes]]``:
times with target poses (joint angles in degrees, world positions of named puppet points
or body centres, any subset). Every key is documented in ``docs/authoring.md``.

Loading validates everything and raises :class:`KeyframeError` (a
:class:`dmarionette.scene.fields.SceneError`) naming the file, the key, the value received
and what was expected.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.scene.scene import Scene, load_scene, scene_from_table
from dmarionette.scene.fields import (SceneError, check_keys, read_choice, read_float, read_int, read_str, read_table,
                                      read_toml_file, read_vec3)

__all__ = ["AuthorSpec", "BarFreedom", "KeyframeError", "KeyframePose", "METHODS", "Weights", "auto_knots",
           "keyframes_from_table", "load_keyframes", "BAR_DOFS", "DEVICES", "WARM_STARTS"]

BAR_DOFS = ("x", "y", "z", "rx", "ry", "rz")
"""A bar's six degrees of freedom: centre position [m] and XYZ Euler angles [deg]."""

DEVICES = ("omni", "falcon", "none")
#: ``[solver] method`` choices; the first is the default.
METHODS = ("lm_fd", "bfgs", "lm", "gauss_newton")
"""Device specs the workspace and force terms can use (``none``: no such terms)."""


MAX_TARGET_DISTANCE = 100.0
"""Largest coordinate [m] of a point or body target (the puppet is about 1 m tall; a target of
1e300 m made the fit fail after 45 s with an infinite loss)."""

MAX_TARGET_ANGLE_DEG = 720.0
"""Largest joint target angle [deg] (two turns)."""


class KeyframeError(SceneError):
    """A keyframes file that cannot be used as written (file, key, value, expected)."""


@dataclasses.dataclass(frozen=True)
class Weights:
    """Weights of the objective's terms; the loss is ``0.5 * sum((w r)^2)`` over residuals ``r``.

    Attributes:
        point: per metre of point/body position error [1/m] (100: 1 cm costs 0.5).
        joint: per radian of joint angle error [1/rad] (10: 5.7 deg costs 0.5).
        smoothness: on the bar's acceleration, integrated over time [s^1.5/m] (positions)
            and [s^1.5/rad] (angles): ``0.5 w^2 \\int |a|^2 dt``.
        workspace: per metre outside the device workspace, integrated over time [1/(m s^0.5)].
        rest: with ``[author] end_at_rest``, per m/s of every body centre's speed over the
            last puppet step [s/m] (100: 1 cm/s costs 0.5).
        force: per newton of device force above the device's limit, integrated over time
            [1/(N s^0.5)].
    """

    point: float = 100.0
    joint: float = 10.0
    smoothness: float = 0.05
    workspace: float = 1000.0
    force: float = 10.0
    rest: float = 100.0


@dataclasses.dataclass(frozen=True)
class BarFreedom:
    """How one bar may move: a spline through knots at fixed times, some coordinates free.

    Attributes:
        name: the bar's name in the scene.
        knots: knot times [s], ``(K,)``, starting at 0 and strictly increasing. The knot at
            t = 0 is held at the scene's pose (the strings start straight from it).
        free: the optimised coordinates, a subset of :data:`BAR_DOFS`.
    """

    name: str
    knots: tuple[float, ...]
    free: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class KeyframePose:
    """One keyframe: a time and any subset of target poses.

    Attributes:
        t: time [s].
        joints: joint name -> target angles [deg], one per axis of a hinge or universal joint.
        points: puppet point name -> world position [m].
        bodies: body name -> world position of its centre [m].
        weight: multiplies this keyframe's residuals (> 0; 1 by default).
        orientations: body name -> target world orientation, XYZ Euler angles [deg]
            (``R = Rz Ry Rx``, as the bars').
    """

    t: float
    joints: Mapping[str, tuple[float, ...]]
    points: Mapping[str, tuple[float, float, float]]
    bodies: Mapping[str, tuple[float, float, float]]
    weight: float = 1.0
    orientations: Mapping[str, tuple[float, float, float]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class AuthorSpec:
    """A loaded, validated keyframes file.

    Attributes:
        source: the file's path.
        scene: the scene to author in (with the file's overrides applied).
        scene_table: the scene's parsed TOML table with those overrides (written back out).
        duration: length of the motion [s].
        bars: the bars the optimiser moves.
        keyframes: targets, in time order.
        weights: the objective's weights.
        device: ``"omni"``, ``"falcon"`` or ``"none"``; gives the workspace and force limit.
        workspace_scale: ``S`` of ``P' = S W P`` (the device workspace in the world is scaled by it).
        force_scale: device force = ``force_scale`` x the strings' force on the bar (as ``live``).
        feedback: ``"reaction"`` (the strings' pull, what ``live`` sends) or ``"eq4"``.
        max_force: the device's force limit [N] (from the spec unless overridden).
        max_steps: solver iterations at most; rtol, atol: optimistix's convergence tolerances.
        method: ``"lm_fd"`` (Levenberg-Marquardt on the keyframe residuals, forward-difference
            Jacobian, hard device limits: :mod:`fitting.author_solve`), ``"bfgs"`` (scalar
            loss, reverse-mode gradient) or ``"lm"``/``"gauss_newton"`` (optimistix on the
            residuals, reverse-mode Jacobian).
        position_tolerance: [m], angle_tolerance: [deg]: a keyframe is reached when every
            target is within them.
        max_seconds: the solve's wall-time budget [s], or None.
        continuation: ``lm_fd`` switches keyframes on in time order.
        jacobian: ``lm_fd``'s keyframe Jacobian between forward-difference ones: ``"secant"``
            (Broyden updates) or ``"fd"`` (a forward-difference Jacobian every step).
        end_at_rest: the puppet must end at rest: every body centre's speed over the last
            puppet step within ``rest_tolerance`` [m/s].
        warm_start: ``lm_fd``'s start: ``"scene"`` (the scene's own bar motion) or
            ``"quasi_static"`` (each keyframe's quasi-static pose, :mod:`fitting.quasi_static`).
    """

    source: str
    scene: Scene
    scene_table: Mapping[str, Any]
    duration: float
    bars: tuple[BarFreedom, ...]
    keyframes: tuple[KeyframePose, ...]
    weights: Weights
    device: str
    workspace_scale: float
    force_scale: float
    feedback: str
    max_force: float | None
    max_steps: int
    rtol: float
    atol: float
    method: str
    position_tolerance: float = 1e-3
    angle_tolerance: float = 0.5
    max_seconds: float | None = None
    continuation: bool = False
    jacobian: str = "secant"
    end_at_rest: bool = False
    rest_tolerance: float = 0.01
    warm_start: str = "scene"


#: ``[solver] warm_start`` choices; the first is the default.
WARM_STARTS = ("scene", "quasi_static")

_TOP_KEYS = ["author", "bars", "weights", "solver", "keyframes"]
_AUTHOR_KEYS = ["scene", "duration", "end_at_rest", "particle_count", "string_hz", "puppet_hz", "device",
                "workspace_scale",
                "force_scale", "feedback", "max_force"]


def load_keyframes(path: str | Path) -> AuthorSpec:
    """Loads and validates a keyframes file (format: ``docs/authoring.md``)."""
    path = Path(path)
    return keyframes_from_table(read_toml_file(path, "an existing keyframes TOML file", KeyframeError), str(path))


def keyframes_from_table(table: Mapping[str, Any], source: str) -> AuthorSpec:
    """Validates a parsed keyframes table; ``source`` (a file path) names it in errors and
    relative scene paths are taken from its folder."""
    try:
        return _keyframes_from_table(table, source)
    except KeyframeError:
        raise
    except SceneError as error:  # the same message, under the keyframes file's error type
        raise KeyframeError(error.where, error.key, error.received, error.expected) from None


def _keyframes_from_table(table: Mapping[str, Any], source: str) -> AuthorSpec:
    check_keys(table, _TOP_KEYS, f"{source}: top level")
    head = read_table(table, "author", f"{source}: top level")
    where = f"{source}: [author]"
    check_keys(head, _AUTHOR_KEYS, where)
    scene, scene_table = _read_scene(head, where, Path(source).parent)
    duration = read_float(head, "duration", where, positive=True, maximum=600.0)
    step = puppet_step(scene)
    if duration < step:
        raise KeyframeError(where, "duration", duration, f"at least one puppet step ({step} s)")
    device = read_choice(head, "device", where, DEVICES, "omni")
    feedback = read_choice(head, "feedback", where, ["reaction", "eq4"], "reaction")
    workspace_scale = read_float(head, "workspace_scale", where, 1.0, positive=True)
    force_scale = read_float(head, "force_scale", where, 0.3, minimum=0.0)
    max_force = read_float(head, "max_force", where, positive=True) if "max_force" in head else None
    end_at_rest = head.get("end_at_rest", False)
    if not isinstance(end_at_rest, bool):
        raise KeyframeError(where, "end_at_rest", end_at_rest, "true or false")

    keyframes = _read_keyframes(table, source, scene, duration)
    bars = _read_bars(read_table(table, "bars", f"{source}: top level"), f"{source}: [bars]", scene, duration,
                      [k.t for k in keyframes])
    weights_table = read_table(table, "weights", f"{source}: top level", {})
    where = f"{source}: [weights]"
    check_keys(weights_table, [f.name for f in dataclasses.fields(Weights)], where)
    weights = Weights(**{f.name: read_float(weights_table, f.name, where, f.default, minimum=0.0)
                         for f in dataclasses.fields(Weights)})
    solver = read_table(table, "solver", f"{source}: top level", {})
    where = f"{source}: [solver]"
    check_keys(solver, ["method", "max_steps", "rtol", "atol", "position_tolerance", "angle_tolerance",
                        "max_seconds", "continuation", "jacobian", "rest_tolerance", "warm_start"], where)
    method = read_choice(solver, "method", where, list(METHODS), "lm_fd")
    max_steps = read_int(solver, "max_steps", where, 60, minimum=1, maximum=100_000)
    rtol = read_float(solver, "rtol", where, 1e-6, positive=True)
    atol = read_float(solver, "atol", where, 1e-8, positive=True)
    position_tolerance = read_float(solver, "position_tolerance", where, 1e-3, positive=True, maximum=1.0)
    angle_tolerance = read_float(solver, "angle_tolerance", where, 0.5, positive=True, maximum=180.0)
    max_seconds = read_float(solver, "max_seconds", where, positive=True) if "max_seconds" in solver else None
    continuation = solver.get("continuation", False)
    if not isinstance(continuation, bool):
        raise KeyframeError(where, "continuation", continuation, "true or false")
    jacobian = read_choice(solver, "jacobian", where, ["secant", "fd"], "secant")
    warm_start = read_choice(solver, "warm_start", where, list(WARM_STARTS), WARM_STARTS[0])
    rest_tolerance = read_float(solver, "rest_tolerance", where, 0.01, positive=True, maximum=10.0)
    return AuthorSpec(source=source, scene=scene, scene_table=scene_table, duration=duration, bars=bars,
                      keyframes=keyframes, weights=weights, device=device, workspace_scale=workspace_scale,
                      force_scale=force_scale, feedback=feedback, max_force=max_force, max_steps=max_steps,
                      rtol=rtol, atol=atol, method=method, position_tolerance=position_tolerance,
                      angle_tolerance=angle_tolerance, max_seconds=max_seconds, continuation=continuation,
                      jacobian=jacobian, end_at_rest=end_at_rest, rest_tolerance=rest_tolerance,
                      warm_start=warm_start)


def _read_scene(head: Mapping[str, Any], where: str, folder: Path) -> tuple[Scene, dict[str, Any]]:
    """The scene (a built-in name, or a path relative to the keyframes file) with the overrides
    ``particle_count`` (every string), ``string_hz`` and ``puppet_hz`` applied."""
    name = read_str(head, "scene", where)
    candidate = Path(name) if Path(name).is_absolute() else folder / name
    base = load_scene(candidate if candidate.is_file() else name)
    scene_table = read_toml_file(Path(base.source), "an existing scene TOML file")
    if "puppet" not in scene_table or not scene_table.get("bars"):
        raise KeyframeError(where, "scene", name, "a scene with a [puppet] and [bars] (a marionette)")
    if "particle_count" in head:
        count = read_int(head, "particle_count", where, minimum=2, maximum=100_000)
        scene_table.setdefault("string_defaults", {})["particle_count"] = count
        for entry in scene_table.get("strings", []):
            if isinstance(entry, dict):
                entry.pop("particle_count", None)
    rates = scene_table.setdefault("rates", {})
    for key in ("string_hz", "puppet_hz"):
        if key in head:
            rates[key] = read_float(head, key, where, positive=True, maximum=1.0e6)
    return scene_from_table(scene_table, base.source), scene_table


def auto_knots(keyframe_times: list[float], duration: float, step: float) -> list[float]:
    """Knot times placed from the keyframes: 0, every keyframe time and the end, leaving out a
    time less than two puppet steps ``step`` [s] after the previous knot (the end is kept and
    the knot before it dropped instead)."""
    knots = [0.0]
    for t in list(keyframe_times) + [duration]:
        if t - knots[-1] >= 2.0 * step:
            knots.append(float(t))
        elif t == duration and len(knots) > 1:
            knots[-1] = float(duration)
    return knots if len(knots) >= 2 else [0.0, float(duration)]


def _read_bars(table: Mapping[str, Any], where: str, scene: Scene, duration: float,
               keyframe_times: list[float]) -> tuple[BarFreedom, ...]:
    names = [b.name for b in scene.bars]
    if not table:
        raise KeyframeError(where, "bars", {}, f"at least one [bars.NAME] table, NAME one of {names}")
    bars = []
    for name, entry in table.items():
        if name not in names:
            raise KeyframeError(where, name, "...", f"the name of a bar of scene '{scene.name}', one of {names}")
        w = f"{where.rstrip(']')}.{name}]"
        if not isinstance(entry, Mapping):
            raise KeyframeError(where, name, entry, "a table with knots and free")
        check_keys(entry, ["knots", "free"], w)
        knots = entry.get("knots", "auto")
        if knots == "auto":
            knots = auto_knots(keyframe_times, duration, puppet_step(scene))
        ok = isinstance(knots, list) and len(knots) >= 2 and all(
            isinstance(k, (int, float)) and not isinstance(k, bool) for k in knots)
        if not ok:
            raise KeyframeError(w, "knots", knots, "a list of at least two knot times [s], e.g. [0.0, 0.5, 1.0], "
                                                  "or \"auto\" (the default: 0, the keyframe times and the end)")
        knots = [float(k) for k in knots]
        if not all(math.isfinite(k) for k in knots):
            raise KeyframeError(w, "knots", knots, "finite knot times (no NaN or infinity)")
        if knots[0] != 0.0:
            raise KeyframeError(w, "knots", knots, "a first knot at t = 0 (held at the scene's start pose)")
        bad = [i for i in range(1, len(knots)) if knots[i] <= knots[i - 1]]
        if bad:
            raise KeyframeError(w, "knots", knots, f"strictly increasing times (knot #{bad[0] + 1}, {knots[bad[0]]}, "
                                                  f"is not later than the one before, {knots[bad[0] - 1]})")
        if knots[-1] > duration:
            raise KeyframeError(w, "knots", knots, f"knot times within the duration [0, {duration}] s")
        free = entry.get("free", ["x", "y", "z"])
        ok = isinstance(free, list) and free and all(f in BAR_DOFS for f in free) and len(set(free)) == len(free)
        if not ok:
            raise KeyframeError(w, "free", free, f"a non-empty list of distinct coordinates from {list(BAR_DOFS)}")
        bars.append(BarFreedom(name=name, knots=tuple(knots), free=tuple(d for d in BAR_DOFS if d in free)))
    return tuple(bars)


def _allowed_joints(scene: Scene) -> dict[str, int]:
    """Joint names whose angles a keyframe may target -> axis count (hinges and universals)."""
    return {j.name: len(j.axes) for j in scene.puppet.joints if j.type in ("hinge", "universal")}


def _read_keyframes(table: Mapping[str, Any], source: str, scene: Scene, duration: float) -> tuple[KeyframePose, ...]:
    entries = table.get("keyframes")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, Mapping) for e in entries):
        raise KeyframeError(f"{source}: top level", "keyframes", entries, "one or more [[keyframes]] tables")
    joints_allowed = _allowed_joints(scene)
    ball = sorted(j.name for j in scene.puppet.joints if j.type == "ball")
    point_names = [p.name for p in scene.puppet.points]
    body_names = [b.name for b in scene.puppet.bodies]
    poses = []
    for i, entry in enumerate(entries):
        where = f"{source}: [[keyframes]] #{i + 1}"
        check_keys(entry, ["t", "weight", "joints", "points", "bodies", "orientations"], where)
        t = read_float(entry, "t", where)
        weight = read_float(entry, "weight", where, 1.0, positive=True, maximum=1.0e6)
        if not 0.0 < t <= duration:
            raise KeyframeError(where, "t", t, f"a time inside the motion, 0 < t <= duration ({duration} s)")
        if round(t / puppet_step(scene)) == 0:
            raise KeyframeError(where, "t", t, f"a time at least half a puppet step ({puppet_step(scene) / 2} s) "
                                               "after the start: the start pose is not the bars' to change")
        if poses and t <= poses[-1].t:
            raise KeyframeError(where, "t", t, f"a time later than the previous keyframe's ({poses[-1].t} s): "
                                               "keyframes in time order")
        joints = {}
        joint_table = read_table(entry, "joints", where, {})
        for name, angles in joint_table.items():
            if name not in joints_allowed:
                extra = f" (ball joints {ball} are targeted through point or body positions)" if ball else ""
                raise KeyframeError(f"{where}.joints", name, angles,
                                    f"the name of a hinge or universal joint, one of {sorted(joints_allowed)}{extra}")
            n = joints_allowed[name]
            ok = isinstance(angles, list) and len(angles) == n and all(
                isinstance(a, (int, float)) and not isinstance(a, bool) for a in angles)
            if not ok:
                raise KeyframeError(f"{where}.joints", name, angles,
                                    f"a list of {n} angle{'s' if n > 1 else ''} in degrees (one per joint axis)")
            if not all(math.isfinite(a) for a in angles):
                raise KeyframeError(f"{where}.joints", name, angles, "finite angles (no NaN or infinity)")
            if not all(abs(a) <= MAX_TARGET_ANGLE_DEG for a in angles):
                raise KeyframeError(f"{where}.joints", name, angles,
                                    f"angles within +-{MAX_TARGET_ANGLE_DEG:g} degrees (two turns either way)")
            joints[name] = tuple(float(a) for a in angles)
        points = _read_positions(read_table(entry, "points", where, {}), f"{where}.points", point_names, "point")
        bodies = _read_positions(read_table(entry, "bodies", where, {}), f"{where}.bodies", body_names, "body")
        orientations = {}
        table_o = read_table(entry, "orientations", where, {})
        for name in table_o:
            if name not in body_names:
                raise KeyframeError(f"{where}.orientations", name, table_o[name],
                                    f"the name of a puppet body, one of {body_names}")
            angles = read_vec3(table_o, name, f"{where}.orientations")
            if not all(abs(a) <= MAX_TARGET_ANGLE_DEG for a in angles):
                raise KeyframeError(f"{where}.orientations", name, list(angles),
                                    f"XYZ Euler angles within +-{MAX_TARGET_ANGLE_DEG:g} degrees")
            orientations[name] = tuple(float(a) for a in angles)
        if not (joints or points or bodies or orientations):
            raise KeyframeError(where, "joints/points/bodies/orientations", None,
                                "at least one target: [keyframes.joints], [keyframes.points], [keyframes.bodies] or "
                                "[keyframes.orientations]")
        poses.append(KeyframePose(t=t, joints=joints, points=points, bodies=bodies, weight=weight,
                                  orientations=orientations))
    return tuple(poses)


def _read_positions(table: Mapping[str, Any], where: str, allowed: list[str], what: str) -> dict[str, tuple]:
    positions = {}
    for name in table:
        if name not in allowed:
            raise KeyframeError(where, name, table[name], f"the name of a puppet {what}, one of {allowed}")
        positions[name] = read_vec3(table, name, where)
        if not all(abs(c) <= MAX_TARGET_DISTANCE for c in positions[name]):
            raise KeyframeError(where, name, list(positions[name]),
                                f"a position within +-{MAX_TARGET_DISTANCE:g} m of the origin on every axis (the "
                                "puppet's scale: a target beyond it makes the loss overflow)")
    return positions


def puppet_step(scene: Scene) -> float:
    """The marionette's puppet step [s] for ``scene`` (as :class:`MarionetteModel` rounds it)."""
    return max(1, round(scene.string_hz / scene.puppet_hz)) / scene.string_hz


def keyframe_steps(spec: AuthorSpec, puppet_dt: float) -> np.ndarray:
    """Puppet step index of each keyframe (the step whose end is nearest the keyframe time)."""
    return np.array([int(round(k.t / puppet_dt)) for k in spec.keyframes], dtype=np.int64)
