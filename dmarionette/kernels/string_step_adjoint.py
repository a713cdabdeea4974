"""The hand-written adjoint of the whole implicit string step (printed springs), one string per thread.

A taped step with the paper's printed spring runs the one-launch step (``string_step``, built
to keep its pivot inverses) and records this kernel as its adjoint (``tape.record_func``),
instead of recording the five passes and letting Warp differentiate each (issue 13, item 5:
Warp's adjoint kernels replay every pass's forward before its reverse, and the reverse of
the assembly differentiates full 3x3 products; that made backward / forward 4.3-5.1).

The step (``string_system``'s module doc) is, per chain, with ``A`` symmetric::

    A(x0, v0) dv = b(x0, v0, top, tie)       v1 = v0 + dv,  x1 = x0 + h v1
    top particle: x1 = top, v1 = (top - x0) / h
    tie force on the body (eq. 2): F = -k_t (x_tie - x1_last) - k_dt (v_tie - v1_last)

and its adjoint, given ``x1_bar``, ``v1_bar`` and ``F_bar``:

1. the outputs: ``x1_last_bar += k_t F_bar``, ``v1_last_bar += k_dt F_bar`` (and the tie's
   constants and target); ``dv_bar = v1_bar + h x1_bar``, ``x0_bar += x1_bar``, ``v0_bar += dv_bar``;
2. the solve: ``lambda = A^{-1} dv_bar`` by substitutions with the forward's pivot inverses and
   ``C'`` (``A^T = A``), then ``b_bar = lambda``, ``A_bar = -lambda dv^T`` on the stored blocks;
3. each block row (``compute_string_system_row``) by hand: every term but the springs has a
   diagonal Jacobian, so their adjoints are a few scalars; the springs' blocks get
   ``K_bar``, and each segment's spring (force and ``K``) is differentiated once, with both
   rows' contributions (``compute_spring_adjoint``).

The function differentiated is exactly the forward's, including its branches: the ground
term where the particle starts below the ground, and the clamp of the spring's geometric
stiffness (zero derivative while a segment is compressed). ``gravity``, ``ground_height`` and
``dt`` are kernel values (no gradient, as under Warp's tape). Gradients are accumulated
into the inputs' ``.grad`` and the outputs' gradients consumed (zeroed), as Warp's adjoint of a
store does, so the rest of the tape sees what Warp's own adjoint would leave. Checked against
the taped five passes to rounding (``tests/grad/test_string_step_adjoint.py``).
"""

import functools

import warp as wp

from .string_spring import string_spring_functions

__all__ = ["string_step_adjoint_kernel"]


@functools.cache
def string_spring_adjoint_function(scalar):
    """Builds ``compute_spring_adjoint``: the adjoint of ``compute_string_spring_printed``."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def compute_spring_adjoint(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar, f_bar: vec3,
                               k_bar: mat33):
        """For ``f = -k_s (l - d) u`` and ``K = -k_s (1 - g) u u^T - k_s g I`` (``g = max(1 - d/l, 0)``,
        ``e = x_a - x_b``, ``l = |e|``, ``u = e / l``), given ``f_bar`` and ``K_bar``: returns
        ``(e_bar, stiffness_bar, rest_length_bar)`` (``x_a_bar = e_bar``, ``x_b_bar = -e_bar``)."""
        one = scalar(1.0)
        e = x_a - x_b
        length = wp.length(e)
        u = e / length
        stretch = length - rest_length
        u_f = wp.dot(u, f_bar)
        u_bar = (-stiffness * stretch) * f_bar
        stiffness_bar = -stretch * u_f
        length_bar = -stiffness * u_f
        rest_bar = stiffness * u_f
        ratio = one - rest_length / length
        geometric = wp.max(ratio, scalar(0.0))
        alpha = -stiffness * (one - geometric)  # K = alpha u u^T + beta I, beta = -k_s g
        alpha_bar = wp.dot(u, k_bar * u)
        beta_bar = k_bar[0, 0] + k_bar[1, 1] + k_bar[2, 2]
        u_bar = u_bar + alpha * ((k_bar + wp.transpose(k_bar)) * u)
        stiffness_bar = stiffness_bar - (one - geometric) * alpha_bar - geometric * beta_bar
        if ratio > scalar(0.0):
            g_bar = stiffness * (alpha_bar - beta_bar)
            length_bar = length_bar + g_bar * rest_length / (length * length)
            rest_bar = rest_bar - g_bar / length
        e_bar = (u_bar - wp.dot(u, u_bar) * u) / length + length_bar * u
        return e_bar, stiffness_bar, rest_bar

    return compute_spring_adjoint


@functools.cache
def string_step_adjoint_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool]):
    """Builds ``integrate_string_implicit_adjoint`` for a float type and an effect set (printed
    springs; ``effects`` as ``integrate_string_implicit_kernel``'s)."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    compute_string_spring = string_spring_functions(scalar).compute_string_spring_printed
    compute_spring_adjoint = string_spring_adjoint_function(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit_adjoint(
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
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Control:
        top_q: wp.array(dtype=vec3),
        tie_q: wp.array(dtype=vec3),
        tie_qd: wp.array(dtype=vec3),
        dt: scalar,
        # The forward's (``integrate_string_implicit`` built with ``keep``):
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        particle_q_out: wp.array(dtype=vec3),
        particle_qd_out: wp.array(dtype=vec3),
        # Scratch:
        segment_force: wp.array(dtype=vec3),
        segment_jacobian: wp.array(dtype=mat33),
        solve_bar: wp.array(dtype=vec3),
        # Adjoint in (consumed: zeroed):
        particle_q_out_grad: wp.array(dtype=vec3),
        particle_qd_out_grad: wp.array(dtype=vec3),
        tie_force_grad: wp.array(dtype=vec3),
        # Adjoint out (accumulated):
        particle_q_grad: wp.array(dtype=vec3),
        particle_qd_grad: wp.array(dtype=vec3),
        top_q_grad: wp.array(dtype=vec3),
        tie_q_grad: wp.array(dtype=vec3),
        tie_qd_grad: wp.array(dtype=vec3),
        particle_mass_grad: wp.array(dtype=scalar),
        string_stiffness_grad: wp.array(dtype=scalar),
        string_rest_length_grad: wp.array(dtype=scalar),
        string_internal_friction_grad: wp.array(dtype=scalar),
        string_air_drag_grad: wp.array(dtype=scalar),
        string_ground_stiffness_grad: wp.array(dtype=scalar),
        string_ground_absorption_grad: wp.array(dtype=scalar),
        string_ground_friction_grad: wp.array(dtype=scalar),
        string_tie_stiffness_grad: wp.array(dtype=scalar),
        string_tie_damping_grad: wp.array(dtype=scalar),
        string_tied_grad: wp.array(dtype=scalar),
    ):
        s = wp.tid()
        start = string_start[s]
        last = string_start[s + 1] - 1
        zero = scalar(0.0)
        h2 = dt * dt
        stiffness = string_stiffness[s]
        rest_length = string_rest_length[s]
        friction = string_internal_friction[s]
        air_drag = string_air_drag[s]
        ground_stiffness = string_ground_stiffness[s]
        ground_absorption = string_ground_absorption[s]
        ground_friction = string_ground_friction[s]
        tied = string_tied[s]
        tie_stiffness = tied * string_tie_stiffness[s]
        tie_damping = tied * string_tie_damping[s]
        tie_x = tie_q[s]
        tie_v = tie_qd[s]
        top = top_q[s]
        top_dx = top - particle_q[start]
        top_dv = top_dx / dt - particle_qd[start]
        g_upper = zero  # the friction's part of A_{j,j+1}: h D_j,j+1 = -h k_f I
        if wp.static(FRICTION):
            g_upper = -dt * friction

        # 1. The outputs: the tie force (eq. 2 on the new state) and the top particle.
        force_bar = tie_force_grad[s]
        tie_force_grad[s] = vec3(zero)
        tie_stiffness_bar = -wp.dot(tie_x - particle_q_out[last], force_bar)
        tie_damping_bar = -wp.dot(tie_v - particle_qd_out[last], force_bar)
        tie_x_bar = -tie_stiffness * force_bar
        tie_v_bar = -tie_damping * force_bar
        x_top_bar = particle_q_out_grad[start]
        v_top_bar = particle_qd_out_grad[start]
        particle_q_out_grad[start] = vec3(zero)
        particle_qd_out_grad[start] = vec3(zero)
        top_bar = x_top_bar + v_top_bar / dt
        particle_q_grad[start] = particle_q_grad[start] - v_top_bar / dt

        # 2. Forward substitution of A lambda = dv_bar (top to bottom), the segments' springs kept.
        y_prev = vec3(zero)
        for p in range(start + 1, last + 1):
            x_bar = particle_q_out_grad[p]
            v_bar = particle_qd_out_grad[p]
            particle_q_out_grad[p] = vec3(zero)
            particle_qd_out_grad[p] = vec3(zero)
            if p == last:
                x_bar = x_bar + tie_stiffness * force_bar
                v_bar = v_bar + tie_damping * force_bar
            dv_bar = v_bar + dt * x_bar  # x1 = x0 + h (v0 + dv)
            particle_q_grad[p] = particle_q_grad[p] + x_bar
            particle_qd_grad[p] = particle_qd_grad[p] + dv_bar
            f, k, _active = compute_string_spring(particle_q[p - 1], particle_q[p], stiffness, rest_length)
            segment_force[p - 1] = f
            segment_jacobian[p - 1] = k
            r = dv_bar
            if p > start + 1:
                upper_prev = h2 * k + mat33(g_upper, zero, zero, zero, g_upper, zero, zero, zero, g_upper)
                r = dv_bar - wp.transpose(upper_prev) * y_prev
            y = pivot_inverse[p] * r
            solve_bar[p] = y
            y_prev = y

        # 3. Back substitution (bottom to top) and each row's adjoint; segment p (below row p) is
        # complete once rows p + 1 and p are done.
        mass_bar_s = zero
        stiffness_bar = zero
        rest_bar = zero
        friction_bar = zero
        air_bar = zero
        ground_stiffness_bar = zero
        ground_absorption_bar = zero
        ground_friction_bar = zero
        top_dx_bar = vec3(zero)
        top_dv_bar = vec3(zero)
        lam_next = vec3(zero)
        dv_next = vec3(zero)
        f_bar_next = vec3(zero)  # the segment below the row: its adjoint from the row below
        k_bar_next = mat33(zero)
        for i in range(last - start):
            p = last - i
            is_last = p == last
            j = p - start
            lam = solve_bar[p]
            if not is_last:
                lam = lam - scratch_c[p] * lam_next
            dv = particle_dv[p]
            x = particle_q[p]
            v = particle_qd[p]
            v_prev = particle_qd[p - 1]
            v_next = vec3(zero)
            if not is_last:
                v_next = particle_qd[p + 1]
            mass = particle_mass[p]
            f_prev = segment_force[p - 1]
            k_prev = segment_jacobian[p - 1]
            k_next = mat33(zero)
            if not is_last:
                k_next = segment_jacobian[p]
            # A_bar = -lambda dv^T on the stored blocks, b_bar = lambda.
            diag_bar = -wp.outer(lam, dv)
            upper_bar = mat33(zero)
            if not is_last:
                upper_bar = -(wp.outer(lam, dv_next) + wp.outer(dv, lam_next))
            rhs_bar = lam
            # diag = -h^2 (K_prev + K_next) + diag(a_xz, a_y, a_xz); rhs = h force + rhs_k + h^2 diag(k_c, k_c + k_y, k_c) v.
            stiff_bar = -h2 * diag_bar
            a_xz_bar = diag_bar[0, 0] + diag_bar[2, 2]
            a_y_bar = diag_bar[1, 1]
            force_row_bar = dt * rhs_bar
            v_bar = vec3(zero)
            v_prev_bar = vec3(zero)
            v_next_bar = vec3(zero)
            x_bar = vec3(zero)
            k_c = zero
            k_y = zero
            if is_last:
                k_c = -tie_stiffness
            below = False
            if wp.static(GROUND):
                below = x[1] < ground_height
                if below:
                    k_y = -ground_stiffness
            k_c_bar = h2 * wp.dot(rhs_bar, v) - h2 * (a_xz_bar + a_y_bar)
            k_y_bar = h2 * rhs_bar[1] * v[1] - h2 * a_y_bar
            v_bar = v_bar + h2 * vec3(k_c * rhs_bar[0], (k_c + k_y) * rhs_bar[1], k_c * rhs_bar[2])
            mass_bar = a_xz_bar + a_y_bar
            d_xz_bar = -dt * a_xz_bar
            d_y_bar = -dt * a_y_bar
            d_base_bar = d_xz_bar + d_y_bar  # d_y starts as d_xz (friction and air drag)
            if is_last:
                # The tie (eq. 2), f = k_t (x_tie - x) + k_dt (v_tie - v); K = -k_t I, D = -k_dt I.
                tie_x_bar = tie_x_bar + tie_stiffness * force_row_bar
                tie_v_bar = tie_v_bar + tie_damping * force_row_bar
                x_bar = x_bar - tie_stiffness * force_row_bar
                v_bar = v_bar - tie_damping * force_row_bar
                tie_stiffness_bar = tie_stiffness_bar + wp.dot(tie_x - x, force_row_bar) - k_c_bar
                tie_damping_bar = tie_damping_bar + wp.dot(tie_v - v, force_row_bar) - d_base_bar
            if wp.static(GROUND):
                if below:
                    # f_y = k_rep (h_ground - y) - k_abs v_y; K_yy = -k_rep, D_yy = -k_abs.
                    ground_stiffness_bar = ground_stiffness_bar + (ground_height - x[1]) * force_row_bar[1] - k_y_bar
                    x_bar = x_bar - vec3(zero, ground_stiffness * force_row_bar[1], zero)
                    ground_absorption_bar = ground_absorption_bar - v[1] * force_row_bar[1] - d_y_bar
                    v_bar = v_bar - vec3(zero, ground_absorption * force_row_bar[1], zero)
                    if wp.static(GROUND_FRICTION):
                        ground_friction_bar = (ground_friction_bar - v[0] * force_row_bar[0]
                                               - v[2] * force_row_bar[2] - d_xz_bar)
                        v_bar = v_bar - vec3(ground_friction * force_row_bar[0], zero,
                                             ground_friction * force_row_bar[2])
            if wp.static(AIR):
                air_bar = air_bar - wp.dot(v, force_row_bar) - d_base_bar
                v_bar = v_bar - air_drag * force_row_bar
            if wp.static(GRAVITY):
                mass_bar = mass_bar + wp.dot(gravity, force_row_bar)
            if wp.static(FRICTION):
                friction_bar = friction_bar - wp.dot(v - v_prev, force_row_bar) - d_base_bar
                v_bar = v_bar - friction * force_row_bar
                v_prev_bar = v_prev_bar + friction * force_row_bar
                if j == 1:
                    friction_bar = friction_bar + dt * wp.dot(top_dv, rhs_bar)
                    top_dv_bar = top_dv_bar + (dt * friction) * rhs_bar
                if not is_last:
                    friction_bar = (friction_bar - wp.dot(v - v_next, force_row_bar) - d_base_bar
                                    - dt * (upper_bar[0, 0] + upper_bar[1, 1] + upper_bar[2, 2]))
                    v_bar = v_bar - friction * force_row_bar
                    v_next_bar = v_next_bar + friction * force_row_bar
            # The springs: force = f_next - f_prev, stiff = K_prev + K_next, upper = h^2 K_next (+ friction),
            # rhs_k = K_prev w_prev + K_next h^2 (v - v_next).
            f_bar_prev = -force_row_bar
            k_bar_prev = stiff_bar
            w_prev = h2 * (v - v_prev)
            if j == 1:
                w_prev = h2 * v - dt * top_dx
            k_bar_prev = k_bar_prev + wp.outer(rhs_bar, w_prev)
            w_bar = wp.transpose(k_prev) * rhs_bar
            v_bar = v_bar + h2 * w_bar
            if j == 1:
                top_dx_bar = top_dx_bar - dt * w_bar
            else:
                v_prev_bar = v_prev_bar - h2 * w_bar
            if not is_last:
                f_bar_next = f_bar_next + force_row_bar
                k_bar_next = k_bar_next + stiff_bar + h2 * upper_bar + wp.outer(rhs_bar, h2 * (v - v_next))
                w_next_bar = h2 * (wp.transpose(k_next) * rhs_bar)
                v_bar = v_bar + w_next_bar
                v_next_bar = v_next_bar - w_next_bar
                # Segment p (this particle to the next) is complete: its spring's adjoint.
                e_bar, k_s_bar, d_bar = compute_spring_adjoint(x, particle_q[p + 1], stiffness, rest_length,
                                                               f_bar_next, k_bar_next)
                stiffness_bar = stiffness_bar + k_s_bar
                rest_bar = rest_bar + d_bar
                x_bar = x_bar + e_bar
                particle_q_grad[p + 1] = particle_q_grad[p + 1] - e_bar
                particle_qd_grad[p + 1] = particle_qd_grad[p + 1] + v_next_bar
            particle_q_grad[p] = particle_q_grad[p] + x_bar
            particle_qd_grad[p] = particle_qd_grad[p] + v_bar
            particle_qd_grad[p - 1] = particle_qd_grad[p - 1] + v_prev_bar
            particle_mass_grad[p] = particle_mass_grad[p] + mass_bar
            f_bar_next = f_bar_prev
            k_bar_next = k_bar_prev
            lam_next = lam
            dv_next = dv
        # The top segment (the top particle at the start of the step to particle start + 1).
        e_bar, k_s_bar, d_bar = compute_spring_adjoint(particle_q[start], particle_q[start + 1], stiffness,
                                                       rest_length, f_bar_next, k_bar_next)
        stiffness_bar = stiffness_bar + k_s_bar
        rest_bar = rest_bar + d_bar
        particle_q_grad[start] = particle_q_grad[start] + e_bar
        particle_q_grad[start + 1] = particle_q_grad[start + 1] - e_bar
        # top_dx = top - x0_start, top_dv = top_dx / h - v0_start.
        top_dx_bar = top_dx_bar + top_dv_bar / dt
        particle_qd_grad[start] = particle_qd_grad[start] - top_dv_bar
        top_bar = top_bar + top_dx_bar
        particle_q_grad[start] = particle_q_grad[start] - top_dx_bar

        top_q_grad[s] = top_q_grad[s] + top_bar
        tie_q_grad[s] = tie_q_grad[s] + tie_x_bar
        tie_qd_grad[s] = tie_qd_grad[s] + tie_v_bar
        string_stiffness_grad[s] = string_stiffness_grad[s] + stiffness_bar
        string_rest_length_grad[s] = string_rest_length_grad[s] + rest_bar
        string_internal_friction_grad[s] = string_internal_friction_grad[s] + friction_bar
        string_air_drag_grad[s] = string_air_drag_grad[s] + air_bar
        string_ground_stiffness_grad[s] = string_ground_stiffness_grad[s] + ground_stiffness_bar
        string_ground_absorption_grad[s] = string_ground_absorption_grad[s] + ground_absorption_bar
        string_ground_friction_grad[s] = string_ground_friction_grad[s] + ground_friction_bar
        # k_t = tied k, k_dt = tied k_d.
        string_tie_stiffness_grad[s] = string_tie_stiffness_grad[s] + tied * tie_stiffness_bar
        string_tie_damping_grad[s] = string_tie_damping_grad[s] + tied * tie_damping_bar
        string_tied_grad[s] = (string_tied_grad[s] + string_tie_stiffness[s] * tie_stiffness_bar
                               + string_tie_damping[s] * tie_damping_bar)

    return integrate_string_implicit_adjoint
