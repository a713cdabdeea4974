"""Assembly of one backward-Euler step of a set of strings as block-tridiagonal systems.

For the free particles ``j = 1 .. n-1`` of a chain (particle 0 follows the bar and is
kinematic), linearised backward Euler (Baraff & Witkin 1998) reads

    (M - h D - h^2 K) dv = h f0 + h^2 K v0 + h (K_j0 dx_0 + D_j0 dv_0)

where ``K = df/dx``, ``D = df/dv`` at the start of the step, and ``dx_0``, ``dv_0`` are the
known motion of the kinematic top particle over the step. Neighbours only interact
through their segment, so ``A`` is block-tridiagonal with 3x3 blocks: this kernel
writes, per particle, the diagonal block, the block coupling it to the next particle
(``A_{j,j+1}``; ``A_{j+1,j}`` is its transpose) and the right-hand side.

The spring (the costliest term) has its own kernel, ``eval_string_spring``, evaluated
once per segment; every other term of a particle is evaluated in ``eval_string_system``,
one ``@wp.func`` per physical term (see :mod:`string_terms`; the tie, eq. 2, is
:mod:`string_tie`'s), rather than one kernel per term: on the CPU a launch costs more
than the arithmetic of a cheap term for 300 particles, and the step must run at 1 kHz
with room to spare. Effects a scene turns off
are removed at code generation with ``wp.static``: the kernel built for that scene does
not contain them.

A particle's block row is :func:`string_system_row_function`'s ``compute_string_system_row``,
shared with the one-launch plain step (``string_step``). It uses the Jacobians' structure:
every term but the springs has a diagonal Jacobian (friction, air drag and the tie ``-k I``,
the ground only in ``y``; x and z alike), so damping and the non-spring stiffness are scalars,
the two spring blocks are summed once, and ``h^2 K v0 - h^2 K_jk v0_k`` is one product per
segment, ``K_jk (h^2 (v0_j - v0_k))``: about a third of the flops of forming ``M - h D - h^2 K``
from full 3x3 terms (issue 19; the sums' order changed, so results moved by rounding,
``docs/performance.md``).
"""


import functools

import warp as wp

from .string_model_arrays import string_constants_function, string_constants_type
from .string_state_arrays import string_arrays_types
from .string_terms import string_terms


@functools.cache
def eval_string_spring_kernel(scalar, tension_only: bool = False):
    """Builds ``eval_string_spring``: per segment ``(p, p+1)``, the (tension-only) force on ``p``,
    ``K_pp`` if the segment is active, else the block it would use once activated (see
    ``string_spring``; the printed spring is always active)."""
    t = string_terms(scalar, tension_only)
    vec3, mat33 = t.vec3, t.mat33
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)

    @wp.kernel(module="unique")
    def eval_string_spring(
        # Model:
        model: StringModelArrays,
        # State in:
        state_in: StringStateArrays,
        segment_forced: wp.array(dtype=wp.int32),
        # State out:
        segment_force: wp.array(dtype=vec3),
        segment_jacobian: wp.array(dtype=mat33),
        segment_jacobian_active: wp.array(dtype=mat33),
        segment_active: wp.array(dtype=wp.int32),
    ):
        """Tension-only springs: ``segment_forced[p] = 1`` activates segment ``p`` whether or not
        it is taut now (the active set a previous solve found); the segment is active if taut
        or forced, and ``segment_jacobian`` holds its block if active, zero if not. The
        printed spring writes only ``segment_force`` and ``segment_jacobian`` (always active)."""
        p = wp.tid()
        s = model.particle_string[p]
        if p == model.string_start[s + 1] - 1:
            # The last particle starts no segment.
            segment_force[p] = vec3(scalar(0.0))
            segment_jacobian[p] = mat33(scalar(0.0))
            segment_jacobian_active[p] = mat33(scalar(0.0))
            segment_active[p] = 0
            return
        f, k, taut = t.compute_string_spring(state_in.particle_q[p], state_in.particle_q[p + 1],
                                             model.string_stiffness[s], model.string_rest_length[s])
        segment_force[p] = f
        if wp.static(not tension_only):
            segment_jacobian[p] = k  # the printed spring is always active
            return
        active = wp.max(taut, segment_forced[p])
        segment_active[p] = active
        if active == 1:
            segment_jacobian[p] = k
        else:
            segment_jacobian[p] = mat33(scalar(0.0))
            segment_jacobian_active[p] = k  # read by the solve only for inactive segments

    return eval_string_spring


@functools.cache
def string_system_row_function(scalar, effects: tuple[bool, bool, bool, bool, bool]):
    """Builds ``compute_string_system_row``: one free particle's block row of ``A dv = b``, the
    arithmetic that both schedules of the step share (``eval_string_system``, one particle per
    thread, and ``integrate_string_implicit``, one string per thread), so they agree bit for bit."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    t = string_terms(scalar)
    vec3, mat33 = t.vec3, t.mat33
    StringConstants = string_constants_type(scalar)

    @wp.func
    def compute_string_system_row(
        j: int,
        is_last: bool,
        x: vec3,
        v: vec3,
        v_prev: vec3,
        v_next: vec3,
        mass: scalar,
        f_prev: vec3,
        k_prev: mat33,
        f_next: vec3,
        k_next: mat33,
        top_dx: vec3,
        top_dv: vec3,
        constants: StringConstants,
        tie_x: vec3,
        tie_v: vec3,
        dt: scalar,
    ):
        """The block row of free particle ``j >= 1`` of a chain (module doc).

        Args:
            j: the particle's index in its chain (``1``: next to the kinematic top).
            is_last: the chain's last particle (no segment below it; its tie acts).
            x, v: the particle's position [m] and velocity [m/s] at the start of the step.
            v_prev, v_next: its neighbours' velocities [m/s] (``v_next``: any value if ``is_last``).
            mass: [kg].
            f_prev, k_prev: the segment above, seen from the particle above (force on it [N],
                ``K_aa`` [N/m]: ``compute_string_spring``); the particle feels ``-f_prev``.
            f_next, k_next: the segment below, seen from this particle (unused if ``is_last``).
            top_dx, top_dv: the kinematic top particle's motion over the step [m], [m/s].
            constants: the string's (``compute_string_constants``: ``k_f``, ``k_air``, the ground's,
                the tie's ``k``, ``k_d`` times its ``tied`` flag, gravity, the ground's height).
            tie_x, tie_v: the tie target [m], [m/s].
            dt: the step [s].

        Returns:
            ``(A_jj, A_{j,j+1}, b_j)`` (``A_{j,j+1}`` zero for the last particle).
        """
        zero = scalar(0.0)
        h2 = dt * dt
        # The springs' blocks are full 3x3; every other term's Jacobian is diagonal, kept as
        # scalars: damping ``D = diag(d_xz, d_y, d_xz)``, stiffness ``diag(k_c, k_c + k_y, k_c)``.
        d_xz = zero
        d_y = zero
        k_c = zero
        k_y = zero

        # The segments above and below (paper term 1): (segment p-1 -> p was evaluated from
        # p-1's side: the force on p is its opposite).
        force = -f_prev
        stiff = k_prev
        upper = mat33(zero)
        if not is_last:
            force = f_next - f_prev
            stiff = k_prev + k_next
            upper = h2 * k_next
        # h^2 K v0 - h^2 K_jk v0_k over the two segments; next to the top, h K_j0 dx_0 instead.
        w_prev = h2 * (v - v_prev)
        if j == 1:
            w_prev = h2 * v - dt * top_dx
        rhs_k = k_prev * w_prev
        if not is_last:
            rhs_k = rhs_k + k_next * (h2 * (v - v_next))
        if wp.static(FRICTION):
            # Internal friction (term 2) with each neighbour; its D = -k_f I per segment.
            friction = constants.friction  # read once: Warp's tape sums its two uses' adjoints as before
            f_f, d_f = t.compute_internal_friction(v, v_prev, friction)
            force = force + f_f
            d_xz = d_xz + d_f[0, 0]
            if j == 1:
                rhs_k = rhs_k - dt * (d_f[0, 0] * top_dv)  # h D_j0 dv_0 with D_j0 = -D_jj
            if not is_last:
                f_f, d_f = t.compute_internal_friction(v, v_next, friction)
                force = force + f_f
                d_xz = d_xz + d_f[0, 0]
                g = dt * d_f[0, 0]
                upper = upper + mat33(g, zero, zero, zero, g, zero, zero, zero, g)
        if wp.static(GRAVITY):
            force = force + mass * constants.gravity  # paper term 3
        if wp.static(AIR):
            f_a, d_a = t.compute_air_drag(v, constants.air_drag)  # paper term 4, D = -k_air I
            force = force + f_a
            d_xz = d_xz + d_a[0, 0]
        d_y = d_xz
        if wp.static(GROUND):
            if x[1] < constants.ground_height:
                # Paper term 6 (penalty and damper, ``compute_ground_contact``), term 5 in x and z.
                f_g, k_g, d_g = t.compute_ground_contact(x, v, constants.ground_height, constants.ground_stiffness,
                                                         constants.ground_absorption)
                force = force + f_g
                k_y = k_g[1, 1]
                d_y = d_y + d_g[1, 1]
                if wp.static(GROUND_FRICTION):
                    f_gf, d_gf = t.compute_ground_friction(v, constants.ground_friction)
                    force = force + f_gf
                    d_xz = d_xz + d_gf[0, 0]
        if is_last:
            # The tie (eq. 2): K = -k I, D = -k_d I.
            f_t, k_t, d_t = t.compute_string_tie(x, v, tie_x, tie_v, constants.tie_stiffness,
                                                 constants.tie_damping)
            force = force + f_t
            k_c = k_t[0, 0]
            d_xz = d_xz + d_t[0, 0]
            d_y = d_y + d_t[0, 0]

        # A = M - h D - h^2 K, b = h f0 + h^2 K v0 (+ the neighbours' and the top's terms).
        a_xz = mass - dt * d_xz - h2 * k_c
        a_y = mass - dt * d_y - h2 * (k_c + k_y)
        s = -h2 * stiff
        diag = mat33(s[0, 0] + a_xz, s[0, 1], s[0, 2],
                     s[1, 0], s[1, 1] + a_y, s[1, 2],
                     s[2, 0], s[2, 1], s[2, 2] + a_xz)
        rhs = dt * force + rhs_k + h2 * vec3(k_c * v[0], (k_c + k_y) * v[1], k_c * v[2])
        return diag, upper, rhs

    return compute_string_system_row


@functools.cache
def eval_string_system_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool]):
    """Builds ``eval_string_system`` for a float type and an effect set.

    Args:
        scalar: ``wp.float64`` or ``wp.float32``.
        effects: ``(gravity, internal_friction, air_drag, ground_contact, ground_friction)``
            as compile-time switches.
    """
    t = string_terms(scalar)
    vec3, mat33 = t.vec3, t.mat33
    compute_string_system_row = string_system_row_function(scalar, effects)
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)
    compute_string_constants = string_constants_function(scalar)

    @wp.kernel(module="unique")
    def eval_string_system(
        # Model:
        model: StringModelArrays,
        # State in:
        state_in: StringStateArrays,
        segment_force: wp.array(dtype=vec3),
        segment_jacobian: wp.array(dtype=mat33),
        # Control:
        control: StringControlArrays,
        dt: scalar,
        # State out:
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        system_rhs: wp.array(dtype=vec3),
    ):
        p = wp.tid()
        s = model.particle_string[p]
        start = model.string_start[s]
        last = model.string_start[s + 1] - 1
        j = p - start
        zero = scalar(0.0)
        if j == 0:
            # Kinematic top particle: not an unknown; an identity row keeps the array tidy.
            system_diag[p] = wp.identity(n=3, dtype=scalar)
            system_upper[p] = mat33(zero)
            system_rhs[p] = vec3(zero)
            return
        is_last = p == last
        v_next = vec3(zero)
        f_next = vec3(zero)
        k_next = mat33(zero)
        if not is_last:
            v_next = state_in.particle_qd[p + 1]
            f_next = segment_force[p]
            k_next = segment_jacobian[p]
        # Motion of the kinematic top particle over the step (used when j == 1).
        top_dx = control.top_q[s] - state_in.particle_q[start]
        top_dv = top_dx / dt - state_in.particle_qd[start]
        diag, upper, rhs = compute_string_system_row(
            j, is_last, state_in.particle_q[p], state_in.particle_qd[p], state_in.particle_qd[p - 1], v_next,
            model.particle_mass[p],
            segment_force[p - 1], segment_jacobian[p - 1], f_next, k_next, top_dx, top_dv,
            compute_string_constants(model, s), control.tie_q[s], control.tie_qd[s], dt,
        )
        system_diag[p] = diag
        system_upper[p] = upper
        system_rhs[p] = rhs

    return eval_string_system
