"""Forces on bodies: external wrenches and point spring-dampers (paper eq. 2).

Each kernel adds to ``body_wrench`` (spatial force about the world origin) and
``body_stiffness`` (the body-space matrix ``h D + h^2 K`` of the implicit step, see
``compute_point_inertia``). ``eval_body_external_forces`` runs first and *writes* both
arrays, so no separate zeroing is needed (and graph capture stays simple).
"""

from __future__ import annotations

import warp as wp

from dmarionette.kernels.articulation_math import (
    compute_point_inertia,
    compute_point_wrench,
    compute_spatial,
    spatial6,
    spatial66,
)
from dmarionette.kernels.string_tie import compute_tie_force


@wp.kernel
def eval_body_external_forces(
    # State in:
    body_pos: wp.array2d(dtype=wp.vec3d),
    # Control:
    body_force: wp.array2d(dtype=wp.vec3d),
    body_torque: wp.array2d(dtype=wp.vec3d),
    # State out:
    body_wrench: wp.array2d(dtype=spatial6),
    body_stiffness: wp.array2d(dtype=spatial66),
):
    """Applied force at each body centre and torque (world) -> wrench about the origin."""
    w, b = wp.tid()
    f = body_force[w, b]
    body_wrench[w, b] = compute_spatial(wp.cross(body_pos[w, b], f) + body_torque[w, b], f)
    body_stiffness[w, b] = spatial66()


@wp.func
def compute_point_state(pos: wp.vec3d, rot: wp.quatd, omega: wp.vec3d, vel: wp.vec3d, point: wp.vec3d):
    """World position and velocity of a body-frame point."""
    r = wp.quat_rotate(rot, point)
    return pos + r, vel + wp.cross(omega, r)


@wp.kernel
def eval_body_point_springs(
    # Model:
    spring_body: wp.array(dtype=wp.int32),
    spring_point: wp.array(dtype=wp.vec3d),
    spring_stiffness: wp.array(dtype=wp.float64),
    spring_damping: wp.array(dtype=wp.float64),
    # State in:
    body_pos: wp.array2d(dtype=wp.vec3d),
    body_rot: wp.array2d(dtype=wp.quatd),
    body_w: wp.array2d(dtype=wp.vec3d),
    body_v: wp.array2d(dtype=wp.vec3d),
    # Control:
    spring_anchor_pos: wp.array2d(dtype=wp.vec3d),
    spring_anchor_vel: wp.array2d(dtype=wp.vec3d),
    h: wp.float64,
    # State out:
    spring_force: wp.array2d(dtype=wp.vec3d),
    body_wrench: wp.array2d(dtype=spatial6),
    body_stiffness: wp.array2d(dtype=spatial66),
):
    """Paper eq. 2, ``f = -k (x - x_a) - k_d (v - v_a)`` (``string_tie.compute_tie_force``), implicit
    in ``x`` and ``v``.

    The force added is the linearised backward-Euler one,
    ``-k (x - x_a) - (k_d + h k) (v - v_a)``, and ``(h k_d + h^2 k) J^T J`` enters the
    system matrix through ``body_stiffness``. ``h`` here is the implicit step (0 for an
    explicit force). ``spring_force`` receives the force on the body (the string feels
    its opposite).
    """
    w, s = wp.tid()
    b = spring_body[s]
    # One set of constants shared by all worlds, or one per world (world after world).
    row = s
    if spring_stiffness.shape[0] > spring_body.shape[0]:
        row = w * spring_body.shape[0] + s
    k = spring_stiffness[row]
    kd = spring_damping[row]
    x, v = compute_point_state(body_pos[w, b], body_rot[w, b], body_w[w, b], body_v[w, b], spring_point[s])
    # Eq. 2 against the anchor, with the damping of the linearised backward-Euler step.
    f = compute_tie_force(x, v, spring_anchor_pos[w, s], spring_anchor_vel[w, s], k, kd + h * k)
    spring_force[w, s] = f
    wp.atomic_add(body_wrench, w, b, compute_point_wrench(x, f))
    c = h * kd + h * h * k
    eye = wp.identity(3, dtype=wp.float64)
    wp.atomic_add(body_stiffness, w, b, compute_point_inertia(x, c * eye))


@wp.kernel
def eval_body_points(
    # Model:
    point_body: wp.array(dtype=wp.int32),
    point_local: wp.array(dtype=wp.vec3d),
    # State in:
    body_pos: wp.array2d(dtype=wp.vec3d),
    body_rot: wp.array2d(dtype=wp.quatd),
    body_w: wp.array2d(dtype=wp.vec3d),
    body_v: wp.array2d(dtype=wp.vec3d),
    # State out:
    point_pos: wp.array2d(dtype=wp.vec3d),
    point_vel: wp.array2d(dtype=wp.vec3d),
):
    """World positions and velocities of body-frame points, shape (world_count, point_count)."""
    w, i = wp.tid()
    b = point_body[i]
    x, v = compute_point_state(body_pos[w, b], body_rot[w, b], body_w[w, b], body_v[w, b], point_local[i])
    point_pos[w, i] = x
    point_vel[w, i] = v
