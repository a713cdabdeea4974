"""Spatial-algebra helpers (``compute_`` functions) for the articulated-body kernels.

Conventions (Featherstone, world frame, about the world origin, float64):

- a spatial motion vector is ``(omega, v_O)``: angular velocity, then the velocity of the
  body-fixed point that is at the world origin; a point ``p`` moves with
  ``v_O + omega x p``.
- a spatial force vector is ``(n_O, f)``: moment about the world origin, then force.
- quaternions are stored MuJoCo-style ``(w, x, y, z)`` in joint coordinates and
  converted to Warp's ``(x, y, z, w)`` on read.
"""

from __future__ import annotations

import warp as wp

spatial6 = wp.types.vector(length=6, dtype=wp.float64)
spatial66 = wp.types.matrix(shape=(6, 6), dtype=wp.float64)

EPS2 = wp.constant(wp.float64(1.0e-24))


@wp.func
def compute_spatial(top: wp.vec3d, bottom: wp.vec3d) -> spatial6:
    """Stacks two 3-vectors into a spatial vector."""
    return spatial6(top[0], top[1], top[2], bottom[0], bottom[1], bottom[2])


@wp.func
def compute_top(s: spatial6) -> wp.vec3d:
    """Angular part of a motion vector (moment part of a force vector)."""
    return wp.vec3d(s[0], s[1], s[2])


@wp.func
def compute_bottom(s: spatial6) -> wp.vec3d:
    """Linear part of a motion vector (force part of a force vector)."""
    return wp.vec3d(s[3], s[4], s[5])


@wp.func
def compute_rotation_motion(axis: wp.vec3d, point: wp.vec3d) -> spatial6:
    """Unit rotation about ``axis`` (world, unit) through ``point`` (world) [1/s per rad/s]."""
    return compute_spatial(axis, wp.cross(point, axis))


@wp.func
def compute_cross_motion(m: spatial6, s: spatial6) -> spatial6:
    """Spatial cross product ``m x s`` of two motion vectors (rate of a moving axis)."""
    w = compute_top(m)
    v = compute_bottom(m)
    return compute_spatial(wp.cross(w, compute_top(s)), wp.cross(w, compute_bottom(s)) + wp.cross(v, compute_top(s)))


@wp.func
def compute_cross_force(m: spatial6, f: spatial6) -> spatial6:
    """Spatial cross product ``m x* f`` of a motion vector and a force vector."""
    w = compute_top(m)
    v = compute_bottom(m)
    return compute_spatial(wp.cross(w, compute_top(f)) + wp.cross(v, compute_bottom(f)), wp.cross(w, compute_bottom(f)))


@wp.func
def compute_spatial_blocks(top_left: wp.mat33d, top_right: wp.mat33d, bottom_left: wp.mat33d,
                           bottom_right: wp.mat33d) -> spatial66:
    """The 6x6 matrix of four 3x3 blocks ``[[top_left, top_right], [bottom_left, bottom_right]]``."""
    M = spatial66()
    for i in range(3):
        for j in range(3):
            M[i, j] = top_left[i, j]
            M[i, j + 3] = top_right[i, j]
            M[i + 3, j] = bottom_left[i, j]
            M[i + 3, j + 3] = bottom_right[i, j]
    return M


@wp.func
def compute_spatial_inertia(mass: wp.float64, inertia: wp.vec3d, rot: wp.quatd, com: wp.vec3d) -> spatial66:
    """Spatial inertia about the world origin of a body.

    Args:
        mass: [kg].
        inertia: principal moments about the centre of mass, body frame [kg m^2].
        rot: body orientation (Warp order x, y, z, w).
        com: centre of mass, world [m].
    """
    R = wp.quat_to_matrix(rot)
    Ic = R * wp.diag(inertia) * wp.transpose(R)
    C = wp.skew(com)
    top_left = Ic - mass * C * C
    top_right = mass * C
    return compute_spatial_blocks(top_left, top_right, wp.transpose(top_right), wp.diag(wp.vec3d(mass, mass, mass)))


@wp.func
def compute_point_inertia(point: wp.vec3d, A: wp.mat33d) -> spatial66:
    """``P^T A P`` with ``P = [-[p]x, I]`` the map from a spatial motion to the velocity of
    ``point``: the joint-space stiffness/damping of a point spring is ``J^T A J``, and
    ``J = P S``, so adding this to a body's spatial inertia adds ``J^T A J`` to the
    composite-rigid-body matrix.
    """
    C = wp.skew(point)
    return compute_spatial_blocks(C * A * (-C), C * A, A * (-C), A)


@wp.func
def compute_point_wrench(point: wp.vec3d, force: wp.vec3d) -> spatial6:
    """Spatial force (moment about the origin, force) of ``force`` applied at ``point``."""
    return compute_spatial(wp.cross(point, force), force)


@wp.func
def compute_quat_from_mj(w: wp.float64, x: wp.float64, y: wp.float64, z: wp.float64) -> wp.quatd:
    """Unit Warp quaternion from MuJoCo-ordered components (normalised as MuJoCo does)."""
    return wp.normalize(wp.quatd(x, y, z, w))


@wp.func
def compute_quat_integrate(r: wp.quatd, omega_local: wp.vec3d, h: wp.float64) -> wp.quatd:
    """``r * exp(h omega / 2)``, normalised: MuJoCo's ``mju_quatIntegrate``.

    The rotation angle uses ``sqrt(|omega h|^2 + 1e-24)`` so that the gradient is finite
    at zero angular velocity (relative change of the result below 1e-24).
    """
    phi = wp.sqrt(wp.dot(omega_local, omega_local) * h * h + EPS2)
    s = wp.sin(wp.float64(0.5) * phi) / phi * h
    dq = wp.quatd(omega_local[0] * s, omega_local[1] * s, omega_local[2] * s, wp.cos(wp.float64(0.5) * phi))
    return wp.normalize(r * dq)


@wp.func
def compute_smooth_norm(v: wp.vec3d) -> wp.float64:
    """``sqrt(|v|^2 + 1e-24)``: a norm with a finite gradient at zero."""
    return wp.sqrt(wp.dot(v, v) + EPS2)
