"""Tangent (forward-mode) rules of the articulated-body helpers and of the Warp builtins that
need more than a one-line rule, for :mod:`dmarionette.kernels.articulation_tangent`.

One ``@wp.func`` per function: ``<name>_tangent(primal args..., tangents of the args...)``
returns the directional derivative of ``<name>`` (:mod:`articulation_math`, or the Warp
builtin of that name) along the given argument tangents. Each differentiates the formula
the primal evaluates (for the builtins, Warp 1.19's ``native/quat.h``), so a tangent
agrees with Warp's adjoint of the same function to rounding, including off the unit
sphere for quaternions. Linear and bilinear functions (``compute_spatial``,
``compute_top``, ``compute_bottom``, ``compute_cross_motion``, ``compute_cross_force``,
``wp.cross``, ``wp.dot``) need no function here: the transformer applies them to the
tangents directly (product rule).
"""

from __future__ import annotations

import warp as wp

from dmarionette.kernels.articulation_math import (
    EPS2,
    compute_spatial,
    compute_spatial_blocks,
    spatial6,
    spatial66,
)

__all__ = [
    "compute_quat_from_mj_tangent",
    "compute_quat_integrate_tangent",
    "compute_rotation_motion_tangent",
    "compute_smooth_norm_tangent",
    "compute_spatial_inertia_tangent_pose",
    "quat_from_axis_angle_tangent",
    "quat_normalize_tangent",
    "quat_rotate_tangent",
]


@wp.func
def quat_rotate_tangent(q: wp.quatd, x: wp.vec3d, q_t: wp.quatd, x_t: wp.vec3d) -> wp.vec3d:
    """Tangent of Warp's ``quat_rotate(q, x) = x (2 w^2 - 1) + u 2 (u.x) + 2 w (u x x)``, ``u = (q.x, q.y, q.z)``
    (the formula as written: valid off the unit sphere too)."""
    two = wp.float64(2.0)
    u = wp.vec3d(q[0], q[1], q[2])
    u_t = wp.vec3d(q_t[0], q_t[1], q_t[2])
    w = q[3]
    w_t = q_t[3]
    c = two * w * w - wp.float64(1.0)
    d = two * wp.dot(u, x)
    c_t = wp.float64(4.0) * w * w_t
    d_t = two * (wp.dot(u_t, x) + wp.dot(u, x_t))
    return (x_t * c + x * c_t + u_t * d + u * d_t
            + (wp.cross(u_t, x) + wp.cross(u, x_t)) * (two * w) + wp.cross(u, x) * (two * w_t))


@wp.func
def quat_normalize_tangent(q: wp.quatd, q_t: wp.quatd) -> wp.quatd:
    """Tangent of Warp's quaternion ``normalize`` (``q / |q|``; the constant identity at ``q = 0``)."""
    l = wp.sqrt(wp.dot(q, q))
    if l > wp.float64(0.0):
        inv = wp.float64(1.0) / l
        return q_t * inv - q * (inv * inv * inv * wp.dot(q, q_t))
    return wp.quatd(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.func
def quat_from_axis_angle_tangent(axis: wp.vec3d, angle: wp.float64, axis_t: wp.vec3d, angle_t: wp.float64) -> wp.quatd:
    """Tangent of ``quat_from_axis_angle(axis, angle) = (axis sin(angle/2), cos(angle/2))`` (axis not normalised)."""
    half = wp.float64(0.5)
    s = wp.sin(angle * half)
    c = wp.cos(angle * half)
    v = axis_t * s + axis * (c * half * angle_t)
    return wp.quatd(v[0], v[1], v[2], -s * half * angle_t)


@wp.func
def compute_rotation_motion_tangent(axis: wp.vec3d, point: wp.vec3d, axis_t: wp.vec3d, point_t: wp.vec3d) -> spatial6:
    """Tangent of ``compute_rotation_motion``."""
    return compute_spatial(axis_t, wp.cross(point_t, axis) + wp.cross(point, axis_t))


@wp.func
def _quat_to_matrix_tangent(q: wp.quatd, q_t: wp.quatd) -> wp.mat33d:
    """Tangent of ``quat_to_matrix`` (Warp builds its columns with ``quat_rotate``, i.e. the matrix
    ``(2 w^2 - 1) I + 2 u u^T + 2 w [u]x``)."""
    two = wp.float64(2.0)
    u = wp.vec3d(q[0], q[1], q[2])
    u_t = wp.vec3d(q_t[0], q_t[1], q_t[2])
    uu = wp.outer(u_t, u)
    return (wp.identity(n=3, dtype=wp.float64) * (wp.float64(4.0) * q[3] * q_t[3]) + (uu + wp.transpose(uu)) * two
            + wp.skew(u) * (two * q_t[3]) + wp.skew(u_t) * (two * q[3]))


@wp.func
def compute_spatial_inertia_tangent_pose(mass: wp.float64, inertia: wp.vec3d, rot: wp.quatd, com: wp.vec3d,
                                         rot_t: wp.quatd, com_t: wp.vec3d) -> spatial66:
    """Tangent of ``compute_spatial_inertia`` along the pose only (mass and inertia constant):
    ``Ic' = X + X^T`` with ``X = R' D R^T``, and ``(C' C + C C')= Y + Y^T`` with ``Y = C' C``."""
    R = wp.quat_to_matrix(rot)
    X = _quat_to_matrix_tangent(rot, rot_t) * (wp.diag(inertia) * wp.transpose(R))
    C_t = wp.skew(com_t)
    Y = C_t * wp.skew(com)
    top_right = mass * C_t
    zero = wp.float64(0.0)
    return compute_spatial_blocks(X + wp.transpose(X) - mass * (Y + wp.transpose(Y)), top_right,
                                  wp.transpose(top_right), wp.diag(wp.vec3d(zero, zero, zero)))


@wp.func
def compute_quat_from_mj_tangent(w: wp.float64, x: wp.float64, y: wp.float64, z: wp.float64,
                                 w_t: wp.float64, x_t: wp.float64, y_t: wp.float64, z_t: wp.float64) -> wp.quatd:
    """Tangent of ``compute_quat_from_mj`` (a normalisation)."""
    return quat_normalize_tangent(wp.quatd(x, y, z, w), wp.quatd(x_t, y_t, z_t, w_t))


@wp.func
def compute_quat_integrate_tangent(r: wp.quatd, omega_local: wp.vec3d, h: wp.float64,
                                   r_t: wp.quatd, omega_local_t: wp.vec3d, h_t: wp.float64) -> wp.quatd:
    """Tangent of ``compute_quat_integrate`` (``normalize(r * dq)``, the formula as written)."""
    half = wp.float64(0.5)
    om2 = wp.dot(omega_local, omega_local)
    phi = wp.sqrt(om2 * h * h + EPS2)
    phi_t = (wp.dot(omega_local, omega_local_t) * h * h + om2 * h * h_t) / phi
    sh = wp.sin(half * phi)
    ch = wp.cos(half * phi)
    s = sh / phi * h
    s_t = (half * ch * phi_t / phi - sh * phi_t / (phi * phi)) * h + sh / phi * h_t
    dq = wp.quatd(omega_local[0] * s, omega_local[1] * s, omega_local[2] * s, ch)
    v_t = omega_local_t * s + omega_local * s_t
    dq_t = wp.quatd(v_t[0], v_t[1], v_t[2], -half * sh * phi_t)
    return quat_normalize_tangent(r * dq, r_t * dq + r * dq_t)


@wp.func
def compute_smooth_norm_tangent(v: wp.vec3d, v_t: wp.vec3d) -> wp.float64:
    """Tangent of ``compute_smooth_norm``."""
    return wp.dot(v, v_t) / wp.sqrt(wp.dot(v, v) + EPS2)
