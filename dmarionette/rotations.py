"""Rotations on the host (NumPy): quaternions, rotation matrices and Euler angles.

The one place for host-side rotation conversions. It imports nothing from dmarionette, so
every subsystem (the haptic package :mod:`dmarionette.hw` included) may use it.

Conventions:

- **Quaternions are** ``(x, y, z, w)``, Warp's order (``wp.quat``), everywhere in the
  project's arrays (``body_rot``, trajectory files, glTF, which is ``(x, y, z, w)`` too).
  Where an interface stores ``(w, x, y, z)`` — haptic device samples
  (:attr:`dmarionette.hw.HapticSample.orientation`), session files, the shared-memory
  link, viser — convert at that boundary with :func:`to_wxyz` / :func:`from_wxyz` and
  nothing else.
- **Rotation matrices** act on column vectors, ``v_world = R v_body``, shape ``(..., 3, 3)``.
- **Bar angles** are XYZ Euler angles in degrees composed as ``R = Rz Ry Rx``
  (:func:`euler_to_matrix`, inverse :func:`matrix_to_euler`). **BVH** channels are
  intrinsic X-Z-Y angles in radians, ``R = Rx Rz Ry`` (:func:`matrix_to_euler_xzy`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "continuous_quats",
    "euler_to_matrix",
    "from_wxyz",
    "matrix_to_euler",
    "matrix_to_euler_xzy",
    "matrix_to_quat",
    "nearest_rotation",
    "normalize_quat",
    "quat_rotate",
    "quat_slerp",
    "quat_to_matrix",
    "to_wxyz",
]

GIMBAL_TOLERANCE = 1e-9
"""``cos`` of the middle Euler angle below which :func:`matrix_to_euler_xzy` treats a rotation as gimbal-locked."""


# ------------------------------------------------------------------ quaternion order at the boundary


def to_wxyz(q: Any) -> np.ndarray:
    """Quaternions ``(x, y, z, w)`` reordered to ``(w, x, y, z)``, ``(..., 4) -> (..., 4)`` (a copy)."""
    return np.asarray(q)[..., [3, 0, 1, 2]]


def from_wxyz(q: Any) -> np.ndarray:
    """Quaternions ``(w, x, y, z)`` reordered to ``(x, y, z, w)``, ``(..., 4) -> (..., 4)`` (a copy)."""
    return np.asarray(q)[..., [1, 2, 3, 0]]


# ------------------------------------------------------------------ quaternions (x, y, z, w)


def normalize_quat(q: Any) -> np.ndarray:
    """The unit quaternion of ``q``, shape (4,); the order is kept.

    Raises:
        ValueError: ``q`` is zero or not finite.
    """
    q = np.asarray(q, dtype=float).reshape(4)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"normalize_quat: need a non-zero finite quaternion, got {q.tolist()}")
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions ``(x, y, z, w)``: ``(..., 4) -> (..., 3, 3)``."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(x, y, z, w)`` of rotation matrices, ``(..., 3, 3) -> (..., 4)``, w >= 0.

    Shepperd's method: each quaternion is computed from its largest component, so the
    result is accurate to rounding for every rotation, including those near 180 degrees.
    The matrices must be rotations; :func:`nearest_rotation` first for drifted ones.
    """
    r = np.asarray(r, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    trace = flat[:, 0, 0] + flat[:, 1, 1] + flat[:, 2, 2]
    diag = np.stack([flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2], trace], axis=1)
    pick = np.argmax(diag, axis=1)
    for k in range(4):
        m = flat[pick == k]
        if not len(m):
            continue
        if k == 3:
            s = 2.0 * np.sqrt(1.0 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2])
            q = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                          (m[:, 1, 0] - m[:, 0, 1]) / s, 0.25 * s], axis=1)
        else:
            i, j, l = k, (k + 1) % 3, (k + 2) % 3
            s = 2.0 * np.sqrt(1.0 + m[:, i, i] - m[:, j, j] - m[:, l, l])
            q = np.empty((len(m), 4))
            q[:, i] = 0.25 * s
            q[:, j] = (m[:, j, i] + m[:, i, j]) / s
            q[:, l] = (m[:, l, i] + m[:, i, l]) / s
            q[:, 3] = (m[:, l, j] - m[:, j, l]) / s
        out[pick == k] = q
    out *= np.where(out[:, 3:4] < 0.0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(r.shape[:-2] + (4,))


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``v`` (k, 3) rotated by the unit quaternion ``q`` ``(x, y, z, w)`` (4,)."""
    u, w = q[:3], q[3]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def continuous_quats(q: np.ndarray) -> np.ndarray:
    """Flips signs along axis 0 so that consecutive quaternions have a non-negative dot product.

    ``q`` and ``-q`` are the same rotation; interpolating between neighbours of one sign
    takes the short way round. Shape ``(F, ..., 4)``; either order.
    """
    q = np.array(q, dtype=np.float64, copy=True)
    for f in range(1, len(q)):
        dot = np.sum(q[f] * q[f - 1], axis=-1, keepdims=True)
        q[f] *= np.where(dot < 0.0, -1.0, 1.0)
    return q


def quat_slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions ``(..., 4)`` at ``u`` in [0, 1] ``(...,)``, the short way."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[..., None] < 0.0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-8
    s = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1.0 - u, np.sin((1.0 - u) * theta) / s)
    w1 = np.where(small, u, np.sin(u * theta) / s)
    q = w0[..., None] * q0 + w1[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# ------------------------------------------------------------------ rotation matrices


def nearest_rotation(r: Any) -> np.ndarray:
    """The rotation nearest to ``r`` (3, 3) (polar factor by SVD): tolerates small drift, e.g. from encoders.

    Raises:
        ValueError: ``r`` is nearer a reflection than a rotation.
    """
    r = np.asarray(r, dtype=float).reshape(3, 3)
    u, _, vt = np.linalg.svd(r)
    r = u @ vt
    if np.linalg.det(r) < 0.0:
        raise ValueError(f"nearest_rotation: matrix is a reflection, not a rotation: {r.tolist()}")
    return r


# ------------------------------------------------------------------ Euler angles


def euler_to_matrix(angles_deg: np.ndarray) -> np.ndarray:
    """Rotation matrices ``Rz Ry Rx`` from XYZ angles in degrees, ``(..., 3) -> (..., 3, 3)``."""
    a = np.radians(np.asarray(angles_deg, dtype=np.float64))
    cx, cy, cz = np.cos(a[..., 0]), np.cos(a[..., 1]), np.cos(a[..., 2])
    sx, sy, sz = np.sin(a[..., 0]), np.sin(a[..., 1]), np.sin(a[..., 2])
    r = np.empty(a.shape[:-1] + (3, 3))
    r[..., 0, 0] = cy * cz
    r[..., 0, 1] = sx * sy * cz - cx * sz
    r[..., 0, 2] = cx * sy * cz + sx * sz
    r[..., 1, 0] = cy * sz
    r[..., 1, 1] = sx * sy * sz + cx * cz
    r[..., 1, 2] = cx * sy * sz - sx * cz
    r[..., 2, 0] = -sy
    r[..., 2, 1] = sx * cy
    r[..., 2, 2] = cx * cy
    return r


def matrix_to_euler(r: np.ndarray) -> np.ndarray:
    """XYZ Euler angles [deg] of ``R = Rz Ry Rx``, ``(..., 3, 3) -> (..., 3)`` (inverse of :func:`euler_to_matrix`).

    The middle angle (about y) is in [-90, 90] deg; the others in (-180, 180].
    """
    r = np.asarray(r, dtype=np.float64)
    ry = np.arcsin(np.clip(-r[..., 2, 0], -1.0, 1.0))
    rx = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    rz = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return np.degrees(np.stack([rx, ry, rz], axis=-1))


def matrix_to_euler_xzy(r: np.ndarray, previous: np.ndarray | None = None) -> np.ndarray:
    """Intrinsic X-Z-Y Euler angles [rad] of rotation matrices, ``R = Rx(a) Rz(b) Ry(c)`` (BVH's channels).

    Args:
        r: rotation matrices, shape ``(N, 3, 3)``.
        previous: angles ``(N, 3)`` of the previous frame, or None. Given, each result is
            the one of the two equivalent triples (``(a, b, c)`` and
            ``(a + pi, pi - b, c + pi)``), each angle shifted by whole turns, nearest to it.
            At gimbal lock (``|b| = 90 deg``) only ``a -/+ c`` is defined; ``c`` then keeps
            its previous value (0 without one).

    Returns:
        ``(N, 3)`` angles ``(a, b, c)`` [rad]: about x, then z, then y.
    """
    r = np.asarray(r, dtype=np.float64)
    cos_b = np.hypot(r[:, 0, 0], r[:, 0, 2])
    b = np.arctan2(-r[:, 0, 1], cos_b)
    a = np.arctan2(r[:, 2, 1], r[:, 1, 1])
    c = np.arctan2(r[:, 0, 2], r[:, 0, 0])
    locked = cos_b < GIMBAL_TOLERANCE
    if np.any(locked):
        c_keep = previous[locked, 2] if previous is not None else np.zeros(np.count_nonzero(locked))
        rl = r[locked]
        up = -rl[:, 0, 1] > 0.0
        a_minus_c = np.arctan2(rl[:, 2, 0], rl[:, 2, 2])   # b = +90 deg: R depends on a - c only
        a_plus_c = np.arctan2(-rl[:, 1, 2], rl[:, 2, 2])   # b = -90 deg: R depends on a + c only
        c[locked] = c_keep
        a[locked] = np.where(up, a_minus_c + c_keep, a_plus_c - c_keep)
    angles = np.stack([a, b, c], axis=1)
    if previous is None:
        return angles
    other = np.stack([a + np.pi, np.pi - b, c + np.pi], axis=1)
    best = []
    for candidate in (angles, other):
        turns = np.round((previous - candidate) / (2.0 * np.pi))
        best.append(candidate + 2.0 * np.pi * turns)
    distance = [np.abs(x - previous).sum(axis=1) for x in best]
    return np.where((distance[1] < distance[0])[:, None], best[1], best[0])
