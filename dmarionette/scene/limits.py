"""Plausibility limits: the ranges the simulator has been tested for, and memory estimates.

A finite value can still be nonsense (a 1e30 kg load, a 1e300 N/m string): the solver runs
and leaves NaN, or a stretch of 20,402 %. :data:`TESTED_RANGES` lists, for every constant a
scene sets, the range that the tests and benchmarks exercise (with a margin of about one
order of magnitude around what they use), and why. :func:`check_tested_ranges` refuses a
scene outside it with a :class:`SceneError` naming the file, the table, the key, the value
and the range; ``[solver] allow_untested = true`` (or ``allow_untested=True`` to
:func:`~dmarionette.scene.scene.scene_from_table`) runs it anyway.

:func:`trajectory_bytes` estimates the memory a run keeps (every string step's tie force,
top position and taut flag, every frame's particles), and :func:`check_duration` refuses a
duration whose trajectory would not fit in memory, with the estimate: the CLI calls it
for ``--duration`` too.

``docs/scenes.md`` lists the same table.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

from dmarionette.scene.fields import SceneError

__all__ = ["TESTED_RANGES", "TestedRange", "check_duration", "check_tested_ranges", "memory_budget_bytes",
           "trajectory_bytes"]

OVERRIDE_HINT = "set [solver] allow_untested = true to run it anyway"


@dataclasses.dataclass(frozen=True)
class TestedRange:
    """A range [low, high] (inclusive) a constant has been tested in, its unit and why."""

    low: float
    high: float
    unit: str
    reason: str

    def describe(self) -> str:
        return f"{self.low:g} <= value <= {self.high:g} {self.unit}".rstrip()


TESTED_RANGES: dict[str, TestedRange] = {
    # String constants ([string_defaults] and [[strings]]).
    "mass": TestedRange(1e-6, 10.0, "kg",
                        "string masses in the tests and scenes are 1e-4 to 0.06 kg"),
    "load_mass": TestedRange(0.0, 10.0, "kg",
                             "loads in the tests and scenes are 0 to 0.35 kg; 1e30 kg ran with 20,402 % stretch"),
    "stiffness": TestedRange(1e-2, 1e6, "N/m",
                             "whole-string stiffness in the scenes is 5 to 800 N/m and tests/marionette/test_hard_cases.py runs "
                             "segments up to 1e7 N/m (2e5 N/m for a 50-particle string); 1e300 N/m left NaN"),
    "internal_friction": TestedRange(0.0, 1e4, "N s/m", "the tests use 0 to 5"),
    "air_drag": TestedRange(0.0, 1e3, "N s/m", "the tests use 0 to 0.1"),
    "ground_stiffness": TestedRange(0.0, 1e7, "N/m", "the tests use 0 to 2,000 N/m"),
    "ground_absorption": TestedRange(0.0, 1e4, "1/s", "the tests use 0 to 5"),
    "ground_friction": TestedRange(0.0, 1e3, "", "the tests use 0 to 2"),
    "tie_stiffness": TestedRange(0.0, 1e10, "N/m", "the tests use 1e-9 to 1e9 N/m"),
    "tie_damping": TestedRange(0.0, 1e6, "N s/m", "the tests use 0 to 3"),
    # [world]
    "gravity": TestedRange(0.0, 100.0, "m/s^2 (magnitude)",
                           "the tests use 0 and 9.81 m/s^2; -1e300 left NaN"),
    "ground_height": TestedRange(-1e3, 1e3, "m", "scenes are a few metres across"),
    # Positions ([[strings]] top/bottom, bars, ball, chair).
    "position": TestedRange(-1e3, 1e3, "m", "scenes are a few metres across"),
    # [feedback] and [contact]
    "feedback_stiffness": TestedRange(0.0, 1e6, "N/m", "the tests use 0 to 50 N/m"),
    "feedback_damping": TestedRange(0.0, 1e5, "N s/m", "the tests use 0 to 5"),
    "contact_stiffness": TestedRange(1e-2, 1e7, "N/m", "the tests use 200 to 20,000 N/m"),
    "contact_damping": TestedRange(0.0, 1e5, "N s/m", "the tests use 0 to 50"),
    # Puppet bodies and the ball.
    "body_mass": TestedRange(1e-5, 1e3, "kg", "puppet bodies in the tests are 0.02 to 0.3 kg"),
    "ball_mass": TestedRange(1e-5, 1e3, "kg", "the ball in the tests is 0.08 kg"),
    "ball_radius": TestedRange(1e-4, 10.0, "m", "the ball in the tests has a 0.06 m radius"),
    "joint_damping": TestedRange(0.0, 1e4, "N m s/rad", "the tests use 0 to 0.05"),
    # [motion]
    "motion_frequency": TestedRange(0.0, 1e3, "Hz", "the scenes sway at 0.5 to 5 Hz"),
}
"""Constant -> the range tested for it (see the module doc)."""


def _refuse(where: str, key: str, value: Any, name: str) -> None:
    limit = TESTED_RANGES[name]
    raise SceneError(where, key, value, f"{limit.describe()}, the range the simulator has been tested for "
                     f"({limit.reason}); {OVERRIDE_HINT}")


def _check(value: float, where: str, key: str, name: str) -> None:
    limit = TESTED_RANGES[name]
    if not limit.low <= value <= limit.high:
        _refuse(where, key, value, name)


def _check_position(value, where: str, key: str) -> None:
    limit = TESTED_RANGES["position"]
    if value is not None and any(not limit.low <= float(c) <= limit.high for c in value):
        _refuse(where, key, list(value), "position")


def check_tested_ranges(scene) -> None:
    """Raises :class:`SceneError` for the first constant of ``scene`` outside :data:`TESTED_RANGES`.

    Args:
        scene: a loaded :class:`~dmarionette.scene.scene.Scene`.
    """
    source = scene.source
    if not TESTED_RANGES["gravity"].low <= math.hypot(*scene.gravity) <= TESTED_RANGES["gravity"].high:
        _refuse(f"{source}: [world]", "gravity", list(scene.gravity), "gravity")
    _check(scene.ground_height, f"{source}: [world]", "ground_height", "ground_height")
    for spec in scene.strings:
        where = f"{source}: [[strings]] '{spec.name}'"
        for key in ("mass", "load_mass", "stiffness", "internal_friction", "air_drag", "ground_stiffness",
                    "ground_absorption", "ground_friction", "tie_stiffness", "tie_damping"):
            _check(getattr(spec, key), where, key, key)
        for key in ("top", "bottom", "tie_point"):
            _check_position(getattr(spec, key), where, key)
    for bar in scene.bars:
        for key, values in (("position", bar.trajectory.positions),):
            for v in values:
                _check_position(v, f"{source}: [bars.{bar.name}]", key)
        for name, point in bar.attach.items():
            _check_position(point, f"{source}: [bars.{bar.name}.attach]", name)
    if scene.puppet is not None:
        _check(scene.feedback_stiffness, f"{source}: [feedback]", "stiffness", "feedback_stiffness")
        _check(scene.feedback_damping, f"{source}: [feedback]", "damping", "feedback_damping")
        if scene.contact:
            _check(scene.contact["stiffness"], f"{source}: [contact]", "stiffness", "contact_stiffness")
            _check(scene.contact["damping"], f"{source}: [contact]", "damping", "contact_damping")
        for body in scene.puppet.bodies:
            _check(body.mass, f"{source}: [puppet.bodies.{body.name}]", "mass", "body_mass")
        for joint in scene.puppet.joints:
            _check(joint.damping, f"{source}: [puppet.joints.{joint.name}]", "damping", "joint_damping")
        _check_position(scene.puppet.root_position, f"{source}: [puppet]", "root_position")
    _check_position(scene.motion.amplitude, f"{source}: [motion]", "amplitude")
    _check(scene.motion.frequency, f"{source}: [motion]", "frequency", "motion_frequency")
    if scene.chair is not None:
        for key, value in zip(("centre", "half_extents"), scene.chair):
            _check_position(value, f"{source}: [chair]", key)
    if scene.ball is not None:
        _check(scene.ball.mass, f"{source}: [ball]", "mass", "ball_mass")
        _check(scene.ball.radius, f"{source}: [ball]", "radius", "ball_radius")
        _check_position(scene.ball.position, f"{source}: [ball]", "position")


def memory_budget_bytes() -> int:
    """The most memory a trajectory may take: half of this machine's physical memory (8 GiB if unknown)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")) // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


_JOINT_Q = {"ball": 4, "universal": 2, "hinge": 1}


def trajectory_bytes(scene, duration: float) -> float:
    """The peak memory [bytes] of simulating ``scene`` for ``duration`` seconds, from its sizes.

    Counts the arrays the rollout keeps (float64, docs/trajectory.md): per string step the bars'
    inputs, the tie forces, the taut flags, the bar forces and the step time (kept twice while
    the chunks are concatenated); per frame (about 30 Hz, or the puppet rate for strings alone)
    the particles, their velocities, joints, bodies and bars. ``tests/test_bad_flags.py`` checks
    that it bounds what a real run keeps.
    """
    s = len(scene.strings)
    p = sum(spec.particle_count for spec in scene.strings)
    b = max(len(scene.bars), 1)
    steps = duration * scene.string_hz
    per_step = 8 * (1 + s * 3 * 2 + b * (3 + 4 + 6 + 3 + 3)) + 4 * s  # step time, tops + ties, bar q/qd/forces
    per_step *= 2  # the per-chunk lists and their concatenation
    bodies = len(scene.puppet.bodies) if scene.puppet is not None else 0
    joints = 7 + sum(_JOINT_Q.get(j.type, 4) for j in scene.puppet.joints) if scene.puppet is not None else 0
    frame_hz = min(scene.puppet_hz, 30.0) if scene.puppet is not None else scene.puppet_hz
    per_frame = 8 * (p * 3 * 2 + joints + bodies * 7 + b * 12 + s * 3 + 1)
    return float(steps * per_step + duration * frame_hz * per_frame)


def check_duration(scene, duration: float, where: str, key: str = "duration") -> None:
    """Refuses a duration that is not finite and positive, or whose trajectory would not fit in memory.

    Args:
        scene: the scene to be simulated.
        duration: simulated seconds.
        where: names the source of the duration in the message (``"scene.toml: [scene]"``, or
            ``"command line"`` for a flag).
        key: the key or flag (``"duration"``, ``"--duration"``).

    Raises:
        SceneError: with the estimate and the budget (half of this machine's memory).
    """
    if isinstance(duration, bool) or not isinstance(duration, (int, float)) or not math.isfinite(duration) \
            or not duration > 0.0:
        raise SceneError(where, key, duration, "a finite number of seconds > 0")
    need = trajectory_bytes(scene, duration)
    budget = memory_budget_bytes()
    if need > budget:
        raise SceneError(where, key, duration,
                         f"a duration whose trajectory fits in memory: {duration:g} s of scene '{scene.name}' "
                         f"({scene.string_hz:g} string steps/s, {sum(s.particle_count for s in scene.strings)} "
                         f"particles) needs about {_size(need)}, more than the {_size(budget)} allowed (half of "
                         f"this machine's memory); at most about {duration * budget / need:.4g} s")


def _size(n: float) -> str:
    for unit, scale in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} B"
