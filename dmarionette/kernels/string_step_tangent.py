"""The tangent-linear (forward-mode) model of the whole implicit string step, for P directions.

Issue 13, item 4: Jacobian-vector products of the string step, for many tangent directions in
one launch (Warp 1.19 has no forward mode, so it is written by hand, as the reverse one is). It
is the exact transpose of ``string_step_adjoint`` (whose module doc states the step): with
``A`` symmetric and factorised by the forward (``string_step`` built with ``keep``: the pivot
inverses and ``C'``, and ``dv``),

    A(x0, v0) dv = b(x0, v0, top, tie)   =>   A dv' = b' - A' dv

so each direction costs one assembly of ``r = b' - A' dv`` per row and two substitutions with
the stored factorisation (no 3x3 inverse), then

    v1' = v0' + dv',  x1' = x0' + h v1'     top particle: x1' = top',  v1' = (top' - x0_top') / h
    F' = -k_t' (x_tie - x1_last) - k_t (x_tie' - x1_last') - k_dt' (v_tie - v1_last) - k_dt (v_tie' - v1_last')

Differentiated (every input the adjoint differentiates): the start state ``x0``, ``v0`` (the top
particle's too: it enters through ``top_dx = top - x0_top``, ``top_dv = top_dx / h - v0_top`` and the
top segment), the tops, the tie targets and their velocities, the particle masses and each
string's constants ``k_s``, ``d``, ``k_f``, ``k_air``, ground repulsion, absorption and friction,
tie ``k``, ``k_d`` and the ``tied`` flag (``k_t = tied k``, ``k_dt = tied k_d``).
``gravity``, ``ground_height`` and ``dt`` are kernel values (no tangent), as in the adjoint.

Branches, as the forward takes them and the adjoint differentiates them: the ground term where a
particle starts below the ground (``x0_y < ground_height``; no tangent of the switch), and the
clamp of the spring's geometric stiffness ``g = max(1 - d/l, 0)`` (``g' = 0`` while the segment is
compressed, ``string_spring.string_spring_tangent_functions``). The taut flag has no tangent.
Printed springs only: the tension-only springs' step (an active-set solve) has no tangent here
(``grad.string_tangent`` refuses such a model).

Layout: one thread per (direction, string), ``dim = (P, S)``, so P directions are one launch; the
tangents have a leading direction axis (``(P, particle_count)``, ``(P, string_count)`` of vec3;
the constants ``(P, string_count, 10)`` in :data:`CONSTANTS` order). Each thread re-evaluates the
primal spring parts it needs (each segment's spring and its tangent twice, once per row it
touches; nothing stored by the forward beyond its factorisation and ``dv``); no 3x3 inverse, two
sweeps of matrix-vector products. The forward substitution's ``y`` is kept in
``particle_qd_out_dot`` and overwritten by the back substitution. Each term is the derivative of the forward's
(``string_system.compute_string_system_row``, ``string_terms``, ``string_tie``); the springs' is
``string_spring_tangent_functions``. A change to a term must be mirrored here and in the adjoint:
``tests/grad/test_string_step_tangent.py`` checks the two against each other (the dot-product
identity) and against central differences.
"""

import functools

import warp as wp

from .string_spring import string_spring_tangent_functions

__all__ = ["CONSTANTS", "string_step_tangent_kernel"]

# The per-string constants whose tangents the kernel reads, in the order of its ``string_constants_dot``.
CONSTANTS = ("string_stiffness", "string_rest_length", "string_internal_friction", "string_air_drag",
             "string_ground_stiffness", "string_ground_absorption", "string_ground_friction",
             "string_tie_stiffness", "string_tie_damping", "string_tied")


@functools.cache
def string_step_tangent_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool]):
    """Builds ``integrate_string_implicit_tangent`` for a float type and an effect set
    (``effects`` as ``integrate_string_implicit_kernel``'s), printed springs."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    const_t = wp.types.vector(9, scalar)  # the string's constants' tangents, k_t and k_dt times ``tied``
    spring = string_spring_tangent_functions(scalar)
    compute_spring_tangent = spring.compute_spring_tangent
    k_product = spring.compute_jacobian_product
    k_tangent_product = spring.compute_jacobian_tangent_product

    @wp.func
    def compute_row_tangent(
        p: int,
        j: int,
        is_last: bool,
        k: int,
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        particle_mass: wp.array(dtype=scalar),
        particle_dv: wp.array(dtype=vec3),
        pivot_inverse: wp.array(dtype=mat33),
        particle_q_dot: wp.array2d(dtype=vec3),
        particle_qd_dot: wp.array2d(dtype=vec3),
        particle_mass_dot: wp.array2d(dtype=scalar),
        solve_dot: wp.array2d(dtype=vec3),
        stiffness: scalar,
        rest_length: scalar,
        friction: scalar,
        air_drag: scalar,
        ground_stiffness: scalar,
        ground_absorption: scalar,
        ground_friction: scalar,
        tie_stiffness: scalar,
        tie_damping: scalar,
        tie_x: vec3,
        tie_v: vec3,
        c_dot: const_t,
        tie_x_dot: vec3,
        tie_v_dot: vec3,
        gravity: vec3,
        ground_height: scalar,
        dt: scalar,
        top_dx: vec3,
        top_dv: vec3,
        top_dx_dot: vec3,
        top_dv_dot: vec3,
        y_prev: vec3,
    ):
        """Row ``p`` (``j = p - start``; ``is_last``: the chain's last particle) of direction ``k``:
        ``r = b' - A' dv`` (its two segments' springs and their tangents evaluated here) and its
        forward substitution ``y = inv_p (r - A_{p,p-1} y_prev)`` into ``solve_dot``; returns ``y``.
        Everything is read from the arrays: nothing but ``y`` is carried from row to row. (A first
        version carried the segment below to the next row, 15 values returned through the dynamic
        loop, as the forward carries 8: the rows after the loop came out wrong, by amounts that
        changed with unrelated edits of this function (Warp 1.19, CPU); not pursued.)"""
        zero = scalar(0.0)
        h2 = dt * dt
        stiffness_dot = c_dot[0]
        rest_dot = c_dot[1]
        friction_dot = c_dot[2]
        air_dot = c_dot[3]
        ground_stiffness_dot = c_dot[4]
        ground_absorption_dot = c_dot[5]
        ground_friction_dot = c_dot[6]
        tie_stiffness_dot = c_dot[7]
        tie_damping_dot = c_dot[8]
        x = particle_q[p]
        x_dot = particle_q_dot[k, p]
        v = particle_qd[p]
        v_dot = particle_qd_dot[k, p]
        v_prev = particle_qd[p - 1]
        v_prev_dot = particle_qd_dot[k, p - 1]
        dv_prev = particle_dv[p - 1]
        u_a, alpha_a, beta_a, u_a_dot, alpha_a_dot, beta_a_dot, f_a_dot = compute_spring_tangent(
            particle_q[p - 1], x, particle_q_dot[k, p - 1] - x_dot, stiffness, rest_length, stiffness_dot, rest_dot)
        dv = particle_dv[p]
        mass = particle_mass[p]
        mass_dot = particle_mass_dot[k, p]
        x_next = x
        x_next_dot = vec3(zero)
        v_next = vec3(zero)
        v_next_dot = vec3(zero)
        dv_next = vec3(zero)
        u_b = vec3(zero)
        alpha_b = zero
        beta_b = zero
        u_b_dot = vec3(zero)
        alpha_b_dot = zero
        beta_b_dot = zero
        f_b_dot = vec3(zero)
        if not is_last:
            x_next = particle_q[p + 1]
            x_next_dot = particle_q_dot[k, p + 1]
            v_next = particle_qd[p + 1]
            v_next_dot = particle_qd_dot[k, p + 1]
            dv_next = particle_dv[p + 1]
            u_b, alpha_b, beta_b, u_b_dot, alpha_b_dot, beta_b_dot, f_b_dot = compute_spring_tangent(
                x, x_next, x_dot - x_next_dot, stiffness, rest_length, stiffness_dot, rest_dot)
        # The springs: force -f_a (+ f_b); rhs_k = K_a w_prev (+ K_b h^2 (v - v_next)); diag's
        # -h^2 (K_a + K_b), upper's h^2 K_b, lower's h^2 K_a (j > 1). Their tangents' part of
        # b' - A' dv, one K' product per segment: K_a' (w_prev + h^2 (dv - dv_prev)) + K_a w_prev'.
        force_dot = -f_a_dot
        w_prev = h2 * (v - v_prev)
        w_prev_dot = h2 * (v_dot - v_prev_dot)
        s_prev = w_prev + h2 * (dv - dv_prev)
        if j == 1:
            w_prev = h2 * v - dt * top_dx  # next to the top: h K_j0 dx_0, no lower block
            w_prev_dot = h2 * v_dot - dt * top_dx_dot
            s_prev = w_prev + h2 * dv
        r = k_tangent_product(u_a, alpha_a, u_a_dot, alpha_a_dot, beta_a_dot, s_prev) + k_product(
            u_a, alpha_a, beta_a, w_prev_dot)
        if not is_last:
            force_dot = force_dot + f_b_dot
            s_next = h2 * (v - v_next) + h2 * (dv - dv_next)
            r = r + k_tangent_product(u_b, alpha_b, u_b_dot, alpha_b_dot, beta_b_dot, s_next) + k_product(
                u_b, alpha_b, beta_b, h2 * (v_dot - v_next_dot))
        # Every other term's Jacobian is diagonal: damping diag(d_xz, d_y, d_xz), stiffness
        # diag(k_c, k_c + k_y, k_c); their tangents.
        d_xz_dot = zero
        k_c = zero
        k_c_dot = zero
        k_y = zero
        k_y_dot = zero
        if wp.static(FRICTION):
            # f = -k_f (v - v_prev) (- k_f (v - v_next)); D = -k_f I each; the off-diagonal blocks' -h k_f I.
            force_dot = force_dot - friction_dot * (v - v_prev) - friction * (v_dot - v_prev_dot)
            d_xz_dot = d_xz_dot - friction_dot
            if j == 1:
                r = r + dt * (friction_dot * top_dv + friction * top_dv_dot)  # rhs's h k_f dv_0
            if j > 1:
                r = r + (dt * friction_dot) * dv_prev
            if not is_last:
                force_dot = force_dot - friction_dot * (v - v_next) - friction * (v_dot - v_next_dot)
                d_xz_dot = d_xz_dot - friction_dot
                r = r + (dt * friction_dot) * dv_next
        if wp.static(GRAVITY):
            force_dot = force_dot + mass_dot * gravity
        if wp.static(AIR):
            force_dot = force_dot - air_dot * v - air_drag * v_dot
            d_xz_dot = d_xz_dot - air_dot
        d_y_dot = d_xz_dot
        if wp.static(GROUND):
            if x[1] < ground_height:
                # f_y = k_rep (h_ground - y) - k_abs v_y; K_yy = -k_rep, D_yy = -k_abs.
                force_dot = force_dot + vec3(
                    zero, ground_stiffness_dot * (ground_height - x[1]) - ground_stiffness * x_dot[1]
                    - ground_absorption_dot * v[1] - ground_absorption * v_dot[1], zero)
                k_y = -ground_stiffness
                k_y_dot = -ground_stiffness_dot
                d_y_dot = d_y_dot - ground_absorption_dot
                if wp.static(GROUND_FRICTION):
                    force_dot = force_dot + vec3(-ground_friction_dot * v[0] - ground_friction * v_dot[0], zero,
                                                 -ground_friction_dot * v[2] - ground_friction * v_dot[2])
                    d_xz_dot = d_xz_dot - ground_friction_dot
        if is_last:
            # The tie (eq. 2), f = k_t (x_tie - x) + k_dt (v_tie - v); K = -k_t I, D = -k_dt I.
            force_dot = (force_dot + tie_stiffness_dot * (tie_x - x) + tie_stiffness * (tie_x_dot - x_dot)
                         + tie_damping_dot * (tie_v - v) + tie_damping * (tie_v_dot - v_dot))
            k_c = -tie_stiffness
            k_c_dot = -tie_stiffness_dot
            d_xz_dot = d_xz_dot - tie_damping_dot
            d_y_dot = d_y_dot - tie_damping_dot
        # a = M - h D - h^2 K on the diagonal; b's h f and h^2 K v0 of the diagonal terms.
        a_xz_dot = mass_dot - dt * d_xz_dot - h2 * k_c_dot
        a_y_dot = mass_dot - dt * d_y_dot - h2 * (k_c_dot + k_y_dot)
        r = r + dt * force_dot + h2 * vec3(
            k_c_dot * v[0] + k_c * v_dot[0],
            (k_c_dot + k_y_dot) * v[1] + (k_c + k_y) * v_dot[1],
            k_c_dot * v[2] + k_c * v_dot[2]) - vec3(a_xz_dot * dv[0], a_y_dot * dv[1], a_xz_dot * dv[2])
        # Forward substitution with the stored pivot inverse; A_{p,p-1} = A_{p-1,p} = h^2 K_a - h k_f I.
        g_upper = zero  # the friction's part of A_{p-1,p}: -h k_f I
        if wp.static(FRICTION):
            g_upper = -dt * friction
        if j > 1:
            r = r - (h2 * k_product(u_a, alpha_a, beta_a, y_prev) + g_upper * y_prev)
        y = pivot_inverse[p] * r
        solve_dot[k, p] = y
        return y

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit_tangent(
        # Model:
        string_start: wp.array(dtype=wp.int32),
        particle_mass: wp.array(dtype=scalar),
        string_stiffness: wp.array(dtype=scalar),
        string_rest_length: wp.array(dtype=scalar),
        string_internal_friction: wp.array(dtype=scalar),
        string_air_drag: wp.array(dtype=scalar),
        string_ground_stiffness: wp.array(dtype=scalar),
        string_ground_absorption: wp.array(dtype=scalar),
        string_ground_friction: wp.array(dtype=scalar),
        string_tie_stiffness: wp.array(dtype=scalar),
        string_tie_damping: wp.array(dtype=scalar),
        string_tied: wp.array(dtype=scalar),
        gravity: vec3,
        ground_height: scalar,
        # State in (the step's start, then what the forward, built with ``keep``, wrote):
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        particle_q_out: wp.array(dtype=vec3),
        particle_qd_out: wp.array(dtype=vec3),
        # Control:
        top_q: wp.array(dtype=vec3),
        tie_q: wp.array(dtype=vec3),
        tie_qd: wp.array(dtype=vec3),
        dt: scalar,
        # Tangents in (leading axis: the direction):
        particle_q_dot: wp.array2d(dtype=vec3),
        particle_qd_dot: wp.array2d(dtype=vec3),
        top_q_dot: wp.array2d(dtype=vec3),
        tie_q_dot: wp.array2d(dtype=vec3),
        tie_qd_dot: wp.array2d(dtype=vec3),
        particle_mass_dot: wp.array2d(dtype=scalar),
        string_constants_dot: wp.array3d(dtype=scalar),
        # Tangents out:
        particle_q_out_dot: wp.array2d(dtype=vec3),
        particle_qd_out_dot: wp.array2d(dtype=vec3),
        tie_force_dot: wp.array2d(dtype=vec3),
    ):
        k, s = wp.tid()
        start = string_start[s]
        last = string_start[s + 1] - 1
        zero = scalar(0.0)
        stiffness = string_stiffness[s]
        rest_length = string_rest_length[s]
        friction = string_internal_friction[s]
        air_drag = string_air_drag[s]
        ground_stiffness = string_ground_stiffness[s]
        ground_absorption = string_ground_absorption[s]
        ground_friction = string_ground_friction[s]
        tied = string_tied[s]
        tied_dot = string_constants_dot[k, s, 9]
        tie_stiffness = tied * string_tie_stiffness[s]
        tie_damping = tied * string_tie_damping[s]
        tie_stiffness_dot = tied_dot * string_tie_stiffness[s] + tied * string_constants_dot[k, s, 7]
        tie_damping_dot = tied_dot * string_tie_damping[s] + tied * string_constants_dot[k, s, 8]
        c_dot = const_t(
            string_constants_dot[k, s, 0], string_constants_dot[k, s, 1], string_constants_dot[k, s, 2],
            string_constants_dot[k, s, 3], string_constants_dot[k, s, 4], string_constants_dot[k, s, 5],
            string_constants_dot[k, s, 6], tie_stiffness_dot, tie_damping_dot)
        tie_x = tie_q[s]
        tie_v = tie_qd[s]
        tie_x_dot = tie_q_dot[k, s]
        tie_v_dot = tie_qd_dot[k, s]
        top = top_q[s]
        top_dot = top_q_dot[k, s]
        x_top = particle_q[start]
        x_top_dot = particle_q_dot[k, start]
        top_dx = top - x_top
        top_dv = top_dx / dt - particle_qd[start]
        top_dx_dot = top_dot - x_top_dot
        top_dv_dot = top_dx_dot / dt - particle_qd_dot[k, start]

        # Forward sweep: each row's r = b' - A' dv and its forward substitution (rows as the
        # forward's: the first and the last apart, the rows between compiled with their flags known).
        y = compute_row_tangent(
            start + 1, 1, start + 1 == last, k, particle_q, particle_qd, particle_mass, particle_dv, pivot_inverse,
            particle_q_dot, particle_qd_dot, particle_mass_dot, particle_qd_out_dot, stiffness, rest_length,
            friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tie_stiffness, tie_damping,
            tie_x, tie_v, c_dot, tie_x_dot, tie_v_dot, gravity, ground_height, dt, top_dx, top_dv, top_dx_dot,
            top_dv_dot, vec3(zero))
        for p in range(start + 2, last):
            y = compute_row_tangent(
                p, 2, False, k, particle_q, particle_qd, particle_mass, particle_dv, pivot_inverse,
                particle_q_dot, particle_qd_dot, particle_mass_dot, particle_qd_out_dot, stiffness, rest_length,
                friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tie_stiffness,
                tie_damping, tie_x, tie_v, c_dot, tie_x_dot, tie_v_dot, gravity, ground_height, dt, top_dx, top_dv,
                top_dx_dot, top_dv_dot, y)
        if last > start + 1:
            y = compute_row_tangent(
                last, last - start, True, k, particle_q, particle_qd, particle_mass, particle_dv, pivot_inverse,
                particle_q_dot, particle_qd_dot, particle_mass_dot, particle_qd_out_dot, stiffness, rest_length,
                friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tie_stiffness,
                tie_damping, tie_x, tie_v, c_dot, tie_x_dot, tie_v_dot, gravity, ground_height, dt, top_dx, top_dv,
                top_dx_dot, top_dv_dot, y)

        # Back substitution (dv'_j = y_j - C'_j dv'_{j+1}) and v1' = v0' + dv', x1' = x0' + h v1', upwards.
        ddv = vec3(zero)
        for i in range(last - start):
            p = last - i
            if p < last:
                ddv = particle_qd_out_dot[k, p] - scratch_c[p] * ddv
            else:
                ddv = particle_qd_out_dot[k, p]
            v1_dot = particle_qd_dot[k, p] + ddv
            particle_qd_out_dot[k, p] = v1_dot
            particle_q_out_dot[k, p] = particle_q_dot[k, p] + dt * v1_dot
        particle_q_out_dot[k, start] = top_dot
        particle_qd_out_dot[k, start] = top_dx_dot / dt
        # The tie force on the new state (eq. 2, ``string_integrate.compute_string_outputs``).
        tie_force_dot[k, s] = (-tie_stiffness_dot * (tie_x - particle_q_out[last])
                               - tie_stiffness * (tie_x_dot - particle_q_out_dot[k, last])
                               - tie_damping_dot * (tie_v - particle_qd_out[last])
                               - tie_damping * (tie_v_dot - particle_qd_out_dot[k, last]))

    return integrate_string_implicit_tangent
