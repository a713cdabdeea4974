"""Device frame <-> world frame, paper eq. 3: ``P' = S W P``.

``W`` (4x4) is a rigid device-to-world transform (rotation + translation), ``S`` (4x4) a
diagonal scale of the haptic workspace. Positions go to the world through both; forces
come back through ``W``'s rotation only (a force is a free vector and is not scaled: the
user feels the simulated newtons). Because a device displacement ``d`` becomes a world
displacement ``S W d``, a world stiffness ``K`` is felt at the device as
``K_dev = R^T K S_3 R`` (``R`` = W's rotation, ``S_3`` = S's 3x3 block): for isotropic
scale ``s`` and scalar ``k``, simply ``k_dev = s k``. The same holds for damping.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from dmarionette.rotations import from_wxyz, matrix_to_quat, nearest_rotation, normalize_quat, quat_to_matrix, to_wxyz

from .device import HapticSample

__all__ = ["DeviceMapping", "rigid_transform", "scale_transform"]

WorldStep = Callable[[HapticSample, float], Any]
"""``step(sample_world, t) -> force_world``: a physics callback that lives in the world frame."""


def scale_transform(scale: Any) -> np.ndarray:
    """Homogeneous scale matrix ``S``, shape (4, 4).

    Args:
        scale: Scalar or per-axis factors, shape (3,); all > 0 (world metres per device metre).
    """
    s = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError(f"scale_transform: scale factors must be finite and > 0, got {s.tolist()}")
    return np.diag([s[0], s[1], s[2], 1.0])


def rigid_transform(rotation: Any = None, translation: Any = None) -> np.ndarray:
    """Homogeneous rigid transform ``W``, shape (4, 4).

    Args:
        rotation: Rotation matrix (3, 3) or quaternion (w, x, y, z) (4,); None for identity.
        translation: Translation [m], shape (3,); None for zero.
    """
    w = np.eye(4)
    if rotation is not None:
        r = np.asarray(rotation, dtype=float)
        w[:3, :3] = quat_to_matrix(from_wxyz(normalize_quat(r))) if r.shape == (4,) else r
    if translation is not None:
        w[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return w


@dataclasses.dataclass(frozen=True)
class DeviceMapping:
    """Maps device samples to the world and world forces back to the device.

    Attributes:
        scale: ``S``, homogeneous diagonal scale, shape (4, 4), entries > 0, ``S[3, 3] = 1``.
        device_to_world: ``W``, homogeneous rigid transform, shape (4, 4).
    """

    scale: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    device_to_world: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        s = np.asarray(self.scale, dtype=float)
        w = np.asarray(self.device_to_world, dtype=float)
        if s.shape != (4, 4) or w.shape != (4, 4):
            raise ValueError(f"DeviceMapping: scale and device_to_world must be 4x4, got {s.shape} and {w.shape}")
        off_diag = s - np.diag(np.diag(s))
        if np.any(off_diag != 0.0) or np.any(np.diag(s)[:3] <= 0.0) or s[3, 3] != 1.0:
            raise ValueError("DeviceMapping: scale must be diagonal, diag(sx, sy, sz, 1) with s > 0 "
                             f"(use scale_transform); got {s.tolist()}")
        r = w[:3, :3]
        if (not np.allclose(r.T @ r, np.eye(3), atol=1e-9) or np.linalg.det(r) <= 0.0
                or not np.allclose(w[3], [0.0, 0.0, 0.0, 1.0])):
            raise ValueError("DeviceMapping: device_to_world must be rigid (orthonormal rotation with "
                             f"det +1, last row 0 0 0 1; use rigid_transform); got {w.tolist()}")
        object.__setattr__(self, "scale", s)
        object.__setattr__(self, "device_to_world", w)

    @staticmethod
    def make(scale: Any = 1.0, rotation: Any = None, translation: Any = None) -> DeviceMapping:
        """Mapping from a scale (scalar or (3,)), a rotation (3x3 or quaternion) and a translation [m]."""
        return DeviceMapping(scale_transform(scale), rigid_transform(rotation, translation))

    @property
    def matrix(self) -> np.ndarray:
        """``S W``, shape (4, 4)."""
        return self.scale @ self.device_to_world

    @property
    def rotation(self) -> np.ndarray:
        """``W``'s rotation, shape (3, 3)."""
        return self.device_to_world[:3, :3]

    @property
    def is_isotropic(self) -> bool:
        """True when S scales every axis by the same factor."""
        d = np.diag(self.scale)[:3]
        return bool(np.all(d == d[0]))

    def position_to_world(self, position: Any) -> np.ndarray:
        """``P' = S W P``.

        Args:
            position: Device positions [m], shape (3,) or (n, 3).

        Returns:
            World positions [m], same shape.
        """
        p = np.asarray(position, dtype=float)
        m = self.matrix
        return p @ m[:3, :3].T + m[:3, 3]

    def position_to_device(self, position: Any) -> np.ndarray:
        """Inverse of :meth:`position_to_world`, shape (3,) or (n, 3)."""
        p = np.asarray(position, dtype=float)
        m = np.linalg.inv(self.matrix)
        return p @ m[:3, :3].T + m[:3, 3]

    def rotation_to_world(self, rotation: Any) -> np.ndarray:
        """World orientation of a device orientation: ``R_world = R_W R_dev``.

        The scale does not act on orientations (a non-uniform scale would shear the bar; the
        bar is rigid and takes only W's rotation).

        Args:
            rotation: Device rotation matrix, shape (3, 3).

        Returns:
            World rotation matrix, shape (3, 3).
        """
        return self.rotation @ np.asarray(rotation, dtype=float)

    def sample_to_world(self, sample: HapticSample) -> tuple[np.ndarray, np.ndarray]:
        """World pose of a sample.

        Returns:
            ``(position [m] (3,), orientation quaternion (w, x, y, z) (4,))`` in the world.
        """
        return (self.position_to_world(sample.position),
                to_wxyz(matrix_to_quat(nearest_rotation(self.rotation_to_world(sample.rotation)))))

    def sample_in_world(self, sample: HapticSample) -> HapticSample:
        """The same sample with position and orientation in the world (time and buttons kept)."""
        position, orientation = self.sample_to_world(sample)
        return HapticSample(sample.time, position, orientation, sample.buttons)

    def wrap(self, world_step: WorldStep) -> Callable[[HapticSample, float], np.ndarray]:
        """A device-frame physics callback for the servo loop from a world-frame one.

        Args:
            world_step: ``step(sample_world, t) -> force_world [N] (3,)``.

        Returns:
            ``step(sample_device, t) -> force_device [N] (3,)``: the sample goes to the world
            by ``S W``, the force comes back by ``R_W^T``.
        """

        def step(sample: HapticSample, t: float) -> np.ndarray:
            return self.force_to_device(world_step(self.sample_in_world(sample), t))

        return step

    @staticmethod
    def wrap_many(mappings: Sequence[DeviceMapping], world_step: Callable[[tuple, float], Any],
                  ) -> Callable[[tuple, float], np.ndarray]:
        """:meth:`wrap` for several devices at once, each through its own mapping.

        Args:
            mappings: one mapping per device, in the servo loop's device order.
            world_step: ``step(samples_world (tuple), t) -> forces_world [N] (n, 3)``.

        Returns:
            ``step(samples_device, t) -> forces_device [N] (n, 3)``: sample ``i`` goes to the
            world by ``S_i W_i``, force row ``i`` comes back by ``R_{W_i}^T``.
        """
        mappings = tuple(mappings)

        def step(samples: tuple, t: float) -> np.ndarray:
            world = tuple(m.sample_in_world(s) for m, s in zip(mappings, samples, strict=True))
            forces = np.asarray(world_step(world, t), dtype=float).reshape(len(mappings), 3)
            return np.stack([m.force_to_device(f) for m, f in zip(mappings, forces)])

        return step

    def force_to_device(self, force: Any) -> np.ndarray:
        """World force [N] to the device frame through W's rotation only: ``R_W^T F``.

        Args:
            force: Force [N], shape (3,) or (n, 3), world frame.

        Returns:
            Force [N] in the device frame, same shape.
        """
        return np.asarray(force, dtype=float) @ self.rotation

    def force_to_world(self, force: Any) -> np.ndarray:
        """Device-frame force [N] to the world: ``R_W F``; shape (3,) or (n, 3)."""
        return np.asarray(force, dtype=float) @ self.rotation.T

    def stiffness_to_device(self, stiffness: Any) -> Any:
        """Stiffness (or damping) felt at the device for a world stiffness.

        Args:
            stiffness: World stiffness [N/m] (or damping [N s/m]): a scalar, or a matrix
                of shape (3, 3) in the world frame.

        Returns:
            ``s k`` (scalar) for a scalar and isotropic scale; otherwise the device-frame
            matrix ``R^T K S_3 R``, shape (3, 3).
        """
        k = np.asarray(stiffness, dtype=float)
        s3 = self.scale[:3, :3]
        if k.ndim == 0:
            if self.is_isotropic:
                return float(k) * float(s3[0, 0])
            k = float(k) * np.eye(3)
        if k.shape != (3, 3):
            raise ValueError(f"stiffness_to_device: need a scalar or a (3, 3) matrix, got shape {k.shape}")
        r = self.rotation
        return r.T @ k @ s3 @ r
