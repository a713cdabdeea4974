"""Kinematics of the Novint Falcon, a three-legged delta-style parallel robot.

Geometry (R. E. Stamper's parallel-manipulator model, dimensions as measured by the
libnifalcon project): three identical legs, at azimuths ``phi_i`` around the device's
z axis (which points out of the device towards the user). Each leg has a motor-driven
thigh of length ``a`` turning by ``theta_i`` in the leg's (u, w) plane, and a parallelogram
shin of length ``b`` joined to the thigh and to the end effector by offsets ``e`` and ``d``;
the parallelogram keeps the end effector's orientation fixed, so the end effector only
translates. In leg ``i``'s frame, ``(u, v, w) = R_i P + (-r, -s, 0)`` with
``R_i = [[cos phi_i, sin phi_i, 0], [-sin phi_i, cos phi_i, 0], [0, 0, 1]]``, the
end-effector centre satisfies

    u = a cos(theta) - c + K cos(theta_2),   w = a sin(theta) + K sin(theta_2),
    v = b cos(theta_3) - f,                  K = d + e + b sin(theta_3),

with passive angles theta_2, theta_3. Eliminating them gives one constraint per leg,

    g_i(P, theta_i) = (u + c - a cos theta_i)^2 + (w - a sin theta_i)^2 - K(v)^2 = 0,
    K(v) = d + e + sqrt(b^2 - (v + f)^2),

which this module solves for ``theta_i`` (inverse kinematics, closed form) or for ``P``
(forward kinematics, Newton's method on the three constraints). Forces map to motor
torques through the Jacobian, ``J^T tau = F`` with ``J = d theta / d P``.

Encoders: 320-slot wheels read in quadrature (1280 ticks per motor turn) on a capstan
drive of ratio 14.25 mm / 110 mm; encoder 0 is about 35 degrees of thigh angle.
All lengths in metres, angles in radians.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

__all__ = ["FalconGeometry", "FalconKinematics", "FalconKinematicsError"]


class FalconKinematicsError(ValueError):
    """A position outside the reachable workspace, or forward kinematics that did not converge."""


@dataclasses.dataclass(frozen=True)
class FalconGeometry:
    """Dimensions of the Falcon [m, rad] (libnifalcon's measurements of the device).

    Attributes:
        a: Thigh length.
        b: Shin (parallelogram) length.
        c: End-effector centre offset, u component.
        d: Shin to end-effector joint offset.
        e: Knee to shin joint offset.
        f: End-effector centre offset, v component.
        r: Leg base offset from the origin, u component.
        s: Leg base offset from the origin, v component.
        leg_azimuth: Leg azimuths phi_i, shape (3,): 90, -30, -150 degrees plus 15 degrees
            (the legs are tilted from the desk plane).
        encoder_ticks_per_turn: Quadrature ticks per motor revolution (4 x 320 slots).
        capstan_ratio: Motor shaft diameter / arm drum diameter (14.25 mm / 110 mm).
        theta_at_zero_ticks: Thigh angle when the encoder reads 0 (about 35 degrees).
    """

    a: float = 0.060
    b: float = 0.1025
    c: float = 0.01443
    d: float = 0.01125
    e: float = 0.01125
    f: float = -0.025
    r: float = 0.0400
    s: float = -0.02309
    leg_azimuth: tuple[float, float, float] = (math.pi / 2 + math.pi / 12, -math.pi / 6 + math.pi / 12,
                                               -5 * math.pi / 6 + math.pi / 12)
    encoder_ticks_per_turn: float = 4 * 320
    capstan_ratio: float = 0.01425 / 0.110
    theta_at_zero_ticks: float = math.radians(35.0)

    @property
    def radians_per_tick(self) -> float:
        """Thigh rotation per encoder tick [rad]."""
        return 2 * math.pi / self.encoder_ticks_per_turn * self.capstan_ratio


class FalconKinematics:
    """Inverse and forward kinematics, Jacobian and encoder conversions of the Falcon.

    Positions are in libnifalcon's device frame [m]: x right, y up, z out of the device
    towards the user, origin at the centre of the leg bases (the grip's workspace is
    around z = 0.11 m).

    Args:
        geometry: Device dimensions.
    """

    def __init__(self, geometry: FalconGeometry = FalconGeometry()) -> None:
        self.geometry = geometry
        g = geometry
        # Rows of R_i map the device frame to leg i's (u, v, w) frame.
        self._rot = np.array([[[math.cos(p), math.sin(p), 0.0], [-math.sin(p), math.cos(p), 0.0], [0.0, 0.0, 1.0]]
                              for p in g.leg_azimuth])
        self._offset = np.array([-g.r, -g.s, 0.0])
        self._guess = np.array([0.0, 0.0, 0.11])

    def _legs(self, position: np.ndarray) -> np.ndarray:
        """End-effector centre in each leg's frame, shape (3 legs, 3 = u, v, w)."""
        return self._rot @ position + self._offset

    def _shin_reach(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = self.geometry
        q = g.b * g.b - (v + g.f) ** 2
        if np.any(q <= 0.0):
            raise FalconKinematicsError("Falcon kinematics: position outside the workspace (a shin would have to "
                                        "be longer than b)")
        root = np.sqrt(q)
        return g.d + g.e + root, root

    def leg_angles(self, position: Any) -> np.ndarray:
        """Inverse kinematics: thigh angles for an end-effector position.

        Args:
            position: End-effector position [m], shape (3,), libnifalcon frame.

        Returns:
            Thigh angles theta_i [rad], shape (3,).

        Raises:
            FalconKinematicsError: The position is not reachable.
        """
        g = self.geometry
        uvw = self._legs(np.asarray(position, dtype=float).reshape(3))
        u, v, w = uvw[:, 0] + g.c, uvw[:, 1], uvw[:, 2]
        k, _ = self._shin_reach(v)
        rho = np.hypot(u, w)
        # (u + c) cos(theta) + w sin(theta) = rho cos(theta - alpha) = rhs
        rhs = (u * u + w * w + g.a * g.a - k * k) / (2.0 * g.a)
        if np.any(rho == 0.0) or np.any(np.abs(rhs) > rho):
            raise FalconKinematicsError(f"Falcon kinematics: position {np.asarray(position).tolist()} m is outside "
                                        "the workspace (a thigh cannot reach it)")
        # The branch with the knee outwards, the Falcon's assembly.
        return np.arctan2(w, u) - np.arccos(rhs / rho)

    def constraints(self, position: Any, theta: Any) -> np.ndarray:
        """The leg-closure residuals g_i(P, theta_i) [m^2], shape (3,); zero when consistent."""
        g = self.geometry
        uvw = self._legs(np.asarray(position, dtype=float).reshape(3))
        t = np.asarray(theta, dtype=float).reshape(3)
        k, _ = self._shin_reach(uvw[:, 1])
        return (uvw[:, 0] + g.c - g.a * np.cos(t)) ** 2 + (uvw[:, 2] - g.a * np.sin(t)) ** 2 - k * k

    def _constraint_jacobians(self, position: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dg/dP (3, 3), dg/dtheta (3,)) at a configuration."""
        g = self.geometry
        uvw = self._legs(position)
        k, root = self._shin_reach(uvw[:, 1])
        du = 2.0 * (uvw[:, 0] + g.c - g.a * np.cos(theta))
        dw = 2.0 * (uvw[:, 2] - g.a * np.sin(theta))
        dv = 2.0 * k * (uvw[:, 1] + g.f) / root
        dg_duvw = np.stack([du, dv, dw], axis=1)
        dg_dp = np.einsum("ij,ijk->ik", dg_duvw, self._rot)
        dg_dtheta = du * g.a * np.sin(theta) - dw * g.a * np.cos(theta)
        return dg_dp, dg_dtheta

    def position(self, theta: Any, guess: Any = None, tol: float = 1e-12, max_iter: int = 30) -> np.ndarray:
        """Forward kinematics: end-effector position for thigh angles (Newton's method).

        Args:
            theta: Thigh angles [rad], shape (3,).
            guess: Starting position [m], (3,); the last solution by default (warm start).
            tol: Convergence threshold on the residuals [m^2].
            max_iter: Newton iterations before giving up.

        Returns:
            Position [m], shape (3,), libnifalcon frame.

        Raises:
            FalconKinematicsError: No convergence (angles not from a reachable pose).
        """
        t = np.asarray(theta, dtype=float).reshape(3)
        p = (self._guess if guess is None else np.asarray(guess, dtype=float)).copy()
        for _ in range(max_iter):
            try:
                r = self.constraints(p, t)
                if np.max(np.abs(r)) < tol:
                    self._guess = p
                    return p.copy()
                dg_dp, _ = self._constraint_jacobians(p, t)
                step = np.linalg.solve(dg_dp, r)
            except (FalconKinematicsError, np.linalg.LinAlgError):
                p = 0.5 * (p + np.array([0.0, 0.0, 0.11]))  # pulled outside: back towards the centre
                continue
            n = np.linalg.norm(step)
            p = p - (step if n < 0.02 else step * (0.02 / n))  # at most 2 cm per iteration
        raise FalconKinematicsError(f"Falcon forward kinematics did not converge for angles {t.tolist()} rad")

    def jacobian(self, position: Any) -> np.ndarray:
        """``d theta / d P`` [rad/m], shape (3, 3), at a position."""
        p = np.asarray(position, dtype=float).reshape(3)
        theta = self.leg_angles(p)
        dg_dp, dg_dtheta = self._constraint_jacobians(p, theta)
        return -dg_dp / dg_dtheta[:, None]

    def joint_torques(self, position: Any, force: Any) -> np.ndarray:
        """Motor-side thigh torques [N m] that render a force [N] at a position: ``J^T tau = F``."""
        return np.linalg.solve(self.jacobian(position).T, np.asarray(force, dtype=float).reshape(3))

    def angles_from_encoders(self, ticks: Any) -> np.ndarray:
        """Thigh angles [rad], shape (3,), from encoder ticks, shape (3,)."""
        g = self.geometry
        return np.asarray(ticks, dtype=float) * g.radians_per_tick + g.theta_at_zero_ticks

    def encoders_from_angles(self, theta: Any) -> np.ndarray:
        """Encoder ticks (rounded to integers), shape (3,), for thigh angles [rad]."""
        g = self.geometry
        return np.rint((np.asarray(theta, dtype=float) - g.theta_at_zero_ticks) / g.radians_per_tick).astype(int)
