"""What a force must pass before it reaches a motor.

:class:`ForceSafetyFilter` applies, in order: non-finite -> zero; ramp-in (a factor rising
from 0 to 1 over ``ramp_time`` after start); the continuous-force limit (an exponential
average of the force magnitude may not exceed the device's continuous rating); the peak
clamp to the device's ``max_force``. Every clamp scales the vector, so the direction the
simulation asked for is kept. The watchdog (zero force when the physics stalls) lives in
the servo loop, which owns the clock.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from .device import HapticDeviceSpec

__all__ = ["ForceSafetyFilter", "SafetyConfig", "clamp_force"]

TINY_FORCE_LIMIT = 1e-300
"""A limit [N] below which a clamped force is written as zero. Scaled down to such a limit, a
force's components fall into float64's subnormal range (below ~2.2e-308), where they keep too
few bits for the direction, and rounding can put the magnitude above the limit (hypothesis
found both: a 1e-323 N limit gave a vector 20 % off the asked direction and 40 % above the
limit). No device renders 1e-300 N; zero keeps both promises (within the limit, no other
direction)."""


def _scaled_to(f: np.ndarray, n: float, limit: float) -> np.ndarray:
    """``f`` (magnitude ``n`` > ``limit``) scaled to magnitude ``limit``, direction kept.

    ``(f / n) * limit``, not ``f * (limit / n)``: for a huge force and a small limit the ratio
    ``limit / n`` is subnormal and has lost precision (a 1e51 N force clamped to 1.3e-262 N came
    out 1e-12 above the limit). ``f / n`` is a unit vector, so the product rounds per component.
    """
    if limit < TINY_FORCE_LIMIT:
        return np.zeros(3)
    return (f / n) * limit


def clamp_force(force: Any, max_force: float) -> np.ndarray:
    """Scales a force down to at most ``max_force`` [N], keeping its direction.

    Args:
        force: Force [N], shape (3,).
        max_force: Largest allowed magnitude [N], >= 0.

    Returns:
        The clamped force [N], shape (3,); zero when any component is not finite.
    """
    f = np.asarray(force, dtype=float).reshape(3)
    if not np.all(np.isfinite(f)):
        return np.zeros(3)
    n = math.hypot(*f)  # no overflow for huge finite forces (f @ f would be inf)
    if n > max_force:
        return _scaled_to(f, n, max_force)
    return f.copy()


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    """Settings of the force path.

    Attributes:
        ramp_time: Time over which forces ramp in from zero after start [s]; 0 disables.
        max_force: Peak limit [N]; None uses the device spec's ``max_force``. A value above
            the spec is refused.
        continuous_time_constant: Time constant of the average force magnitude that is held
            to the device's ``max_continuous_force`` [s]; 0 disables that limit.
        watchdog_timeout: Longest time a physics request may stay unanswered before the
            servo loop sends zero [s]. With the 1 kHz loop's tick this keeps the reaction to a
            stall under 5 ms (measured about 2.1-2.4 ms, more on a loaded machine).
        rearm_ramp_time: Ramp-in time after the physics recovers from a watchdog trip [s].
    """

    ramp_time: float = 1.0
    max_force: float | None = None
    continuous_time_constant: float = 1.0
    watchdog_timeout: float = 0.002
    rearm_ramp_time: float = 0.2

    def __post_init__(self) -> None:
        if not (self.ramp_time >= 0.0 and self.continuous_time_constant >= 0.0):
            raise ValueError(f"SafetyConfig: ramp_time and continuous_time_constant must be >= 0 s, got "
                             f"{self.ramp_time} and {self.continuous_time_constant}")
        if not (0.0 < self.watchdog_timeout <= 0.004):
            raise ValueError("SafetyConfig: watchdog_timeout must be in (0, 0.004] s so a stall reaches "
                             f"zero force within 5 ms; got {self.watchdog_timeout}")


class ForceSafetyFilter:
    """Stateful force filter for one run of the loop (ramp and continuous-force state).

    Args:
        spec: The device's limits.
        config: Ramp, limits, watchdog settings.
    """

    def __init__(self, spec: HapticDeviceSpec, config: SafetyConfig = SafetyConfig()) -> None:
        limit = spec.max_force if config.max_force is None else config.max_force
        if not (0.0 <= limit <= spec.max_force):
            raise ValueError(f"SafetyConfig.max_force={config.max_force} N is outside [0, {spec.max_force}] N, "
                             f"the limit of device {spec.name!r}")
        self.spec = spec
        self.config = config
        self.max_force = float(limit)
        self._average = 0.0
        self._last_t: float | None = None
        self._ramp_origin = 0.0
        self._ramp_time = config.ramp_time
        self.clamp_count = 0
        """Times the peak or continuous limit cut a force."""
        self.nonfinite_count = 0
        """Times a non-finite force was replaced by zero."""

    def rearm(self, t: float) -> None:
        """Restarts the ramp at loop time ``t`` [s], over ``rearm_ramp_time`` (after a watchdog trip)."""
        self._ramp_origin = t
        self._ramp_time = self.config.rearm_ramp_time

    def ramp_factor(self, t: float) -> float:
        """Ramp-in factor in [0, 1] at loop time ``t`` [s] (smoothstep, so no jerk)."""
        if self._ramp_time <= 0.0:
            return 1.0
        x = min(max((t - self._ramp_origin) / self._ramp_time, 0.0), 1.0)
        return x * x * (3.0 - 2.0 * x)

    def __call__(self, force: Any, t: float) -> np.ndarray:
        """Safe version of ``force`` [N] (3,) at loop time ``t`` [s]; zero if not finite."""
        f = np.asarray(force, dtype=float).reshape(3)
        if not np.all(np.isfinite(f)):
            self.nonfinite_count += 1
            f = np.zeros(3)
        f = f * self.ramp_factor(t)
        n = math.hypot(*f)  # no overflow for huge finite forces (f @ f would be inf)
        limit = self.max_force
        tau = self.config.continuous_time_constant
        if tau > 0.0:
            dt = 0.0 if self._last_t is None else max(t - self._last_t, 0.0)
            self._last_t = t
            # Allow at most what keeps the running average at the continuous rating.
            a = 1.0 - math.exp(-dt / tau) if dt > 0.0 else 0.0
            if a > 0.0 and self._average + a * (n - self._average) > self.spec.max_continuous_force:
                allowed = self._average + (self.spec.max_continuous_force - self._average) / a
                limit = min(limit, max(allowed, self.spec.max_continuous_force))
        if n > limit:
            self.clamp_count += 1
            f = _scaled_to(f, n, limit)
            n = limit if limit >= TINY_FORCE_LIMIT else 0.0
        if tau > 0.0 and self._last_t is not None:
            self._average += (1.0 - math.exp(-dt / tau) if dt > 0.0 else 0.0) * (n - self._average)
        return f
