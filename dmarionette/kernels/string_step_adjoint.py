"""The hand-written adjoint of the whole implicit string step, one string per thread.

A taped step with the paper's printed spring runs the one-launch step (``string_step``, built
to keep its pivot inverses), one with tension-only springs its five passes off the tape (the
solve keeping its factorisation), and each records this kernel as its adjoint
(``tape.record_func``), instead of recording the passes and letting Warp differentiate each (issue 13, item 5:
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
stiffness (zero derivative while a segment is compressed). Tension-only springs: the step
with its active set held fixed, as the five taped passes differentiate it (the force only
where a segment is taut; a slack segment the active set forces has the axial block).
``gravity``, ``ground_height`` and ``dt`` are kernel values (no gradient, as under Warp's tape). Gradients are accumulated
into the inputs' ``.grad`` and the outputs' gradients consumed (zeroed), as Warp's adjoint of a
store does, so the rest of the tape sees what Warp's own adjoint would leave. Checked against
the taped five passes to rounding (``tests/grad/test_string_step_adjoint.py``, every effect on).

Each force term is defined once (``string_terms``, ``string_spring``, ``string_tie``) and
assembled once (``string_system.compute_string_system_row``); this kernel is their derivative
written out, so a change to a term must be mirrored here: the test above fails otherwise.
"""

import functools

import warp as wp

from .string_model_arrays import string_constants_function, string_constants_type
from .string_spring import string_spring_adjoint_functions
from .string_state_arrays import string_arrays_types

__all__ = ["string_step_adjoint_kernel"]


@functools.cache
def string_step_adjoint_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool], tension_only: bool = False):
    """Builds ``integrate_string_implicit_adjoint`` for a float type, an effect set (``effects`` as
    ``integrate_string_implicit_kernel``'s) and a spring: printed, or tension-only with the step's
    active set held fixed (``segment_forced``, as the recorded step assembles it; ``strings/solver.py``)."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    TENSION_ONLY = tension_only
    vec3 = wp.types.vector(3, scalar)
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)
    StringConstants = string_constants_type(scalar)
    compute_string_constants = string_constants_function(scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    spring = string_spring_adjoint_functions(scalar)
    compute_outer_moments = spring.compute_outer_moments

    @wp.func
    def compute_parts(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar, forced: int):
        """The segment's spring parts (printed, or tension-only with its active-set flag)."""
        if wp.static(TENSION_ONLY):
            return spring.compute_spring_parts_tension_only(x_a, x_b, stiffness, rest_length, forced)
        return spring.compute_spring_parts(x_a, x_b, stiffness, rest_length)

    @wp.func
    def compute_segment_adjoint(u: vec3, length: scalar, ratio: scalar, alpha: scalar, stiffness: scalar,
                                rest_length: scalar, f_bar: vec3, k_uu: scalar, k_tr: scalar, k_sym: vec3, forced: int):
        """The segment's spring adjoint (printed, or tension-only with its active-set flag)."""
        if wp.static(TENSION_ONLY):
            return spring.compute_spring_adjoint_tension_only(u, length, ratio, alpha, stiffness, rest_length, f_bar,
                                                              k_uu, k_tr, k_sym, forced)
        return spring.compute_spring_adjoint(u, length, ratio, alpha, stiffness, rest_length, f_bar, k_uu, k_tr, k_sym)

    acc_t = wp.types.vector(21, scalar)  # a row's running sums (compute_row_adjoint)

    @wp.func
    def compute_running_sums(acc: acc_t):
        """The running sums ``acc`` holds, by name (``compute_row_adjoint``'s order)."""
        return (acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], acc[8],
                vec3(acc[9], acc[10], acc[11]), vec3(acc[12], acc[13], acc[14]), vec3(acc[15], acc[16], acc[17]),
                vec3(acc[18], acc[19], acc[20]))

    @wp.func
    def compute_row_adjoint(
        p: int,
        j: int,
        is_last: bool,
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        particle_mass: wp.array(dtype=scalar),
        particle_dv: wp.array(dtype=vec3),
        scratch_c: wp.array(dtype=mat33),
        solve_bar: wp.array(dtype=vec3),
        segment_forced: wp.array(dtype=wp.int32),
        particle_q_grad: wp.array(dtype=vec3),
        particle_qd_grad: wp.array(dtype=vec3),
        particle_mass_grad: wp.array(dtype=scalar),
        constants: StringConstants,
        tie_x: vec3,
        tie_v: vec3,
        dt: scalar,
        top_dx: vec3,
        top_dv: vec3,
        x: vec3,
        v: vec3,
        v_next: vec3,
        lam_next: vec3,
        dv_next: vec3,
        u_n: vec3,
        l_n: scalar,
        ratio_n: scalar,
        alpha_n: scalar,
        beta_n: scalar,
        f_bar_n: vec3,
        uu_n: scalar,
        tr_n: scalar,
        sym_n: vec3,
        acc: acc_t,
    ):
        """The adjoint of row ``p`` (``j = p - start``; ``is_last``: the chain's last particle): its
        ``lambda``, the block row's assembly, the segment above's moments started and the segment
        below's (``u_n`` ...) completed and pulled back to the particles. Called with ``is_last``
        and ``j`` known at the first and the last row, so that the rows between compile without
        their branches (as the forward's ``compute_forward_row``). ``acc``: the string's running
        sums (``k_s``, ``d``, ``k_f``, ``k_air``, ground ``k``, absorption, friction, tie ``k``,
        ``k_d``, then the tie target's, its velocity's, ``top_dx``'s and ``top_dv``'s adjoints).
        Returns the values the next row (``p - 1``) carries, and ``acc``."""
        zero = scalar(0.0)
        h2 = dt * dt
        (stiffness_bar, rest_bar, friction_bar, air_bar, ground_stiffness_bar, ground_absorption_bar,
         ground_friction_bar, tie_stiffness_bar, tie_damping_bar, tie_x_bar, tie_v_bar, top_dx_bar,
         top_dv_bar) = compute_running_sums(acc)
        x_prev = particle_q[p - 1]
        v_prev = particle_qd[p - 1]
        u_p, l_p, ratio_p, alpha_p, beta_p = compute_parts(x_prev, x, constants.stiffness, constants.rest_length,
                                                           segment_forced[p - 1])
        lam = solve_bar[p]
        if not is_last:
            lam = lam - scratch_c[p] * lam_next
        dv = particle_dv[p]
        mass = particle_mass[p]
        # A_bar = -lambda dv^T on the stored blocks (A_{j,j+1} also stands, transposed, at
        # (j+1, j)), b_bar = lambda. diag = -h^2 (K_prev + K_next) + diag(a_xz, a_y, a_xz), so
        # K_prev_bar and K_next_bar get h^2 lambda dv^T; upper = h^2 K_next - h k_f I gets
        # -(lambda dv_next^T + dv lambda_next^T).
        rhs_bar = lam
        a_xz_bar = -(lam[0] * dv[0] + lam[2] * dv[2])
        a_y_bar = -lam[1] * dv[1]
        force_row_bar = dt * rhs_bar
        v_bar = vec3(zero)
        v_prev_bar = vec3(zero)
        v_next_bar = vec3(zero)
        x_bar = vec3(zero)
        k_c = zero
        k_y = zero
        if is_last:
            k_c = -constants.tie_stiffness
        below = False
        if wp.static(GROUND):
            below = x[1] < constants.ground_height
            if below:
                k_y = -constants.ground_stiffness
        k_c_bar = h2 * wp.dot(rhs_bar, v) - h2 * (a_xz_bar + a_y_bar)
        k_y_bar = h2 * rhs_bar[1] * v[1] - h2 * a_y_bar
        v_bar = v_bar + h2 * vec3(k_c * rhs_bar[0], (k_c + k_y) * rhs_bar[1], k_c * rhs_bar[2])
        mass_bar = a_xz_bar + a_y_bar
        d_xz_bar = -dt * a_xz_bar
        d_y_bar = -dt * a_y_bar
        d_base_bar = d_xz_bar + d_y_bar  # d_y starts as d_xz (friction and air drag)
        if is_last:
            # The tie (eq. 2), f = k_t (x_tie - x) + k_dt (v_tie - v); K = -k_t I, D = -k_dt I.
            tie_x_bar = tie_x_bar + constants.tie_stiffness * force_row_bar
            tie_v_bar = tie_v_bar + constants.tie_damping * force_row_bar
            x_bar = x_bar - constants.tie_stiffness * force_row_bar
            v_bar = v_bar - constants.tie_damping * force_row_bar
            tie_stiffness_bar = tie_stiffness_bar + wp.dot(tie_x - x, force_row_bar) - k_c_bar
            tie_damping_bar = tie_damping_bar + wp.dot(tie_v - v, force_row_bar) - d_base_bar
        if wp.static(GROUND):
            if below:
                # f_y = k_rep (h_ground - y) - k_abs v_y; K_yy = -k_rep, D_yy = -k_abs.
                ground_stiffness_bar = (ground_stiffness_bar + (constants.ground_height - x[1]) * force_row_bar[1]
                                        - k_y_bar)
                x_bar = x_bar - vec3(zero, constants.ground_stiffness * force_row_bar[1], zero)
                ground_absorption_bar = ground_absorption_bar - v[1] * force_row_bar[1] - d_y_bar
                v_bar = v_bar - vec3(zero, constants.ground_absorption * force_row_bar[1], zero)
                if wp.static(GROUND_FRICTION):
                    ground_friction_bar = (ground_friction_bar - v[0] * force_row_bar[0]
                                           - v[2] * force_row_bar[2] - d_xz_bar)
                    v_bar = v_bar - vec3(constants.ground_friction * force_row_bar[0], zero,
                                         constants.ground_friction * force_row_bar[2])
        if wp.static(AIR):
            air_bar = air_bar - wp.dot(v, force_row_bar) - d_base_bar
            v_bar = v_bar - constants.air_drag * force_row_bar
        if wp.static(GRAVITY):
            mass_bar = mass_bar + wp.dot(constants.gravity, force_row_bar)
        if wp.static(FRICTION):
            friction_bar = friction_bar - wp.dot(v - v_prev, force_row_bar) - d_base_bar
            v_bar = v_bar - constants.friction * force_row_bar
            v_prev_bar = v_prev_bar + constants.friction * force_row_bar
            if j == 1:
                friction_bar = friction_bar + dt * wp.dot(top_dv, rhs_bar)
                top_dv_bar = top_dv_bar + (dt * constants.friction) * rhs_bar
            if not is_last:
                # tr(upper_bar) = -(lambda . dv_next + dv . lambda_next); upper's -h k_f I.
                friction_bar = (friction_bar - wp.dot(v - v_next, force_row_bar) - d_base_bar
                                + dt * (wp.dot(lam, dv_next) + wp.dot(dv, lam_next)))
                v_bar = v_bar - constants.friction * force_row_bar
                v_next_bar = v_next_bar + constants.friction * force_row_bar
        # The segment above: force -f_prev, diag's -h^2 K_prev, rhs_k's K_prev w_prev.
        w_prev = h2 * (v - v_prev)
        if j == 1:
            w_prev = h2 * v - dt * top_dx
        uu_p, tr_p, sym_p = compute_outer_moments(h2 * lam, dv, u_p)
        uu, tr, sym = compute_outer_moments(rhs_bar, w_prev, u_p)
        uu_p = uu_p + uu
        tr_p = tr_p + tr
        sym_p = sym_p + sym
        w_bar = alpha_p * wp.dot(u_p, rhs_bar) * u_p + beta_p * rhs_bar  # K_prev^T rhs_bar
        v_bar = v_bar + h2 * w_bar
        if j == 1:
            top_dx_bar = top_dx_bar - dt * w_bar
        else:
            v_prev_bar = v_prev_bar - h2 * w_bar
        if not is_last:
            # The segment below: force +f_next, diag's -h^2 K_next, upper's h^2 K_next, rhs_k's
            # K_next h^2 (v - v_next); then its spring's adjoint (it is complete).
            f_bar_n = f_bar_n + force_row_bar
            uu, tr, sym = compute_outer_moments(h2 * lam, dv, u_n)
            uu_n = uu_n + uu
            tr_n = tr_n + tr
            sym_n = sym_n + sym
            uu, tr, sym = compute_outer_moments(-h2 * lam, dv_next, u_n)
            uu_n = uu_n + uu
            tr_n = tr_n + tr
            sym_n = sym_n + sym
            uu, tr, sym = compute_outer_moments(-h2 * dv, lam_next, u_n)
            uu_n = uu_n + uu
            tr_n = tr_n + tr
            sym_n = sym_n + sym
            w_next = h2 * (v - v_next)
            uu, tr, sym = compute_outer_moments(rhs_bar, w_next, u_n)
            uu_n = uu_n + uu
            tr_n = tr_n + tr
            sym_n = sym_n + sym
            w_next_bar = h2 * (alpha_n * wp.dot(u_n, rhs_bar) * u_n + beta_n * rhs_bar)
            v_bar = v_bar + w_next_bar
            v_next_bar = v_next_bar - w_next_bar
            e_bar, k_s_bar, d_bar = compute_segment_adjoint(u_n, l_n, ratio_n, alpha_n, constants.stiffness,
                                                             constants.rest_length, f_bar_n, uu_n, tr_n, sym_n,
                                                             segment_forced[p])
            stiffness_bar = stiffness_bar + k_s_bar
            rest_bar = rest_bar + d_bar
            x_bar = x_bar + e_bar
            particle_q_grad[p + 1] = particle_q_grad[p + 1] - e_bar
            particle_qd_grad[p + 1] = particle_qd_grad[p + 1] + v_next_bar
        particle_q_grad[p] = particle_q_grad[p] + x_bar
        particle_qd_grad[p] = particle_qd_grad[p] + v_bar
        particle_qd_grad[p - 1] = particle_qd_grad[p - 1] + v_prev_bar
        particle_mass_grad[p] = particle_mass_grad[p] + mass_bar
        # Row p - 1 is next: segment p - 1 becomes the one below.
        u_n = u_p
        l_n = l_p
        ratio_n = ratio_p
        alpha_n = alpha_p
        beta_n = beta_p
        f_bar_n = -force_row_bar
        uu_n = uu_p
        tr_n = tr_p
        sym_n = sym_p
        lam_next = lam
        dv_next = dv
        v_next = v
        v = v_prev
        x = x_prev
        acc_out = acc_t(
            stiffness_bar, rest_bar, friction_bar, air_bar, ground_stiffness_bar, ground_absorption_bar,
            ground_friction_bar, tie_stiffness_bar, tie_damping_bar, tie_x_bar[0], tie_x_bar[1], tie_x_bar[2],
            tie_v_bar[0], tie_v_bar[1], tie_v_bar[2], top_dx_bar[0], top_dx_bar[1], top_dx_bar[2], top_dv_bar[0],
            top_dv_bar[1], top_dv_bar[2])
        return x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n, f_bar_n, uu_n, tr_n, sym_n, acc_out

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit_adjoint(
        # Model:
        model: StringModelArrays,
        # State in (the step's start, then what the forward, built with ``keep``, wrote):
        state_in: StringStateArrays,
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        state_out: StringStateArrays,
        segment_forced: wp.array(dtype=wp.int32),
        # Control:
        control: StringControlArrays,
        dt: scalar,
        # State out (scratch: the solve's forward substitution):
        solve_bar: wp.array(dtype=vec3),
        # Adjoint in and out (the state out's gradients; read, then consumed: zeroed):
        state_out_grad: StringStateArrays,
        # Adjoint out (accumulated: the state in's, the control's and the model's, each its arrays' ``.grad``):
        state_in_grad: StringStateArrays,
        control_grad: StringControlArrays,
        model_grad: StringModelArrays,
    ):
        s = wp.tid()
        particle_q, particle_qd = state_in.particle_q, state_in.particle_qd
        particle_q_out, particle_qd_out = state_out.particle_q, state_out.particle_qd
        particle_q_out_grad, particle_qd_out_grad = state_out_grad.particle_q, state_out_grad.particle_qd
        particle_q_grad, particle_qd_grad = state_in_grad.particle_q, state_in_grad.particle_qd
        start = model.string_start[s]
        last = model.string_start[s + 1] - 1
        zero = scalar(0.0)
        h2 = dt * dt
        particle_mass = model.particle_mass
        constants = compute_string_constants(model, s)
        tie_x = control.tie_q[s]
        tie_v = control.tie_qd[s]
        top = control.top_q[s]
        top_dx = top - particle_q[start]
        top_dv = top_dx / dt - particle_qd[start]
        g_upper = zero  # the friction's part of A_{j,j+1}: h D_j,j+1 = -h k_f I
        if wp.static(FRICTION):
            g_upper = -dt * constants.friction

        # 1. The outputs: the tie force (eq. 2 on the new state) and the top particle.
        force_bar = state_out_grad.tie_force[s]
        state_out_grad.tie_force[s] = vec3(zero)
        tie_stiffness_bar = -wp.dot(tie_x - particle_q_out[last], force_bar)
        tie_damping_bar = -wp.dot(tie_v - particle_qd_out[last], force_bar)
        tie_x_bar = -constants.tie_stiffness * force_bar
        tie_v_bar = -constants.tie_damping * force_bar
        x_top_bar = particle_q_out_grad[start]
        v_top_bar = particle_qd_out_grad[start]
        particle_q_out_grad[start] = vec3(zero)
        particle_qd_out_grad[start] = vec3(zero)
        top_bar = x_top_bar + v_top_bar / dt
        particle_q_grad[start] = particle_q_grad[start] - v_top_bar / dt

        # 2. Forward substitution of A lambda = dv_bar, top to bottom (A_{j-1,j} = h^2 K_{j-1} - h k_f I).
        y_prev = vec3(zero)
        x_prev = particle_q[start]
        for p in range(start + 1, last + 1):
            x = particle_q[p]
            x_bar = particle_q_out_grad[p]
            v_bar = particle_qd_out_grad[p]
            particle_q_out_grad[p] = vec3(zero)
            particle_qd_out_grad[p] = vec3(zero)
            if p == last:
                x_bar = x_bar + constants.tie_stiffness * force_bar
                v_bar = v_bar + constants.tie_damping * force_bar
            r = v_bar + dt * x_bar  # dv_bar: x1 = x0 + h (v0 + dv)
            particle_q_grad[p] = particle_q_grad[p] + x_bar
            particle_qd_grad[p] = particle_qd_grad[p] + r
            if p > start + 1:
                u, _l, _ratio, alpha, beta = compute_parts(x_prev, x, constants.stiffness, constants.rest_length,
                                                           segment_forced[p - 1])
                r = r - (h2 * (alpha * wp.dot(u, y_prev)) * u + (h2 * beta + g_upper) * y_prev)
            y_prev = pivot_inverse[p] * r
            solve_bar[p] = y_prev
            x_prev = x

        # 3. Back substitution, bottom to top, and each row's adjoint (``compute_row_adjoint``). Segment p
        # (below row p) is complete once rows p + 1 (its "prev") and p (its "next") are done; its
        # K_bar is kept as moments (``compute_outer_moments``), its parts carried from row p + 1.
        acc = acc_t(zero)
        lam_next = vec3(zero)
        dv_next = vec3(zero)
        v_next = vec3(zero)
        x = particle_q[last]
        v = particle_qd[last]
        # The segment below the row (none below the last): parts, and its adjoint so far.
        u_n = vec3(zero)
        l_n = zero
        ratio_n = zero
        alpha_n = zero
        beta_n = zero
        f_bar_n = vec3(zero)
        uu_n = zero
        tr_n = zero
        sym_n = vec3(zero)
        x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n, f_bar_n, uu_n, tr_n, sym_n, acc = (
            compute_row_adjoint(
                last, last - start, True, particle_q, particle_qd, particle_mass, particle_dv, scratch_c, solve_bar,
                segment_forced, particle_q_grad, particle_qd_grad, model_grad.particle_mass, constants, tie_x, tie_v,
                dt, top_dx, top_dv, x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n, f_bar_n, uu_n,
                tr_n, sym_n, acc))
        for i in range(last - start - 2):
            x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n, f_bar_n, uu_n, tr_n, sym_n, acc = (
                compute_row_adjoint(
                    last - 1 - i, 2, False, particle_q, particle_qd, particle_mass, particle_dv, scratch_c,
                    solve_bar, segment_forced, particle_q_grad, particle_qd_grad, model_grad.particle_mass, constants,
                    tie_x, tie_v, dt, top_dx, top_dv, x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n,
                    beta_n, f_bar_n, uu_n, tr_n, sym_n, acc))
        if last > start + 1:
            x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n, f_bar_n, uu_n, tr_n, sym_n, acc = (
                compute_row_adjoint(
                    start + 1, 1, False, particle_q, particle_qd, particle_mass, particle_dv, scratch_c, solve_bar,
                    segment_forced, particle_q_grad, particle_qd_grad, model_grad.particle_mass, constants, tie_x,
                    tie_v, dt, top_dx, top_dv, x, v, v_next, lam_next, dv_next, u_n, l_n, ratio_n, alpha_n, beta_n,
                    f_bar_n, uu_n, tr_n, sym_n, acc))
        (stiffness_bar, rest_bar, friction_bar, air_bar, ground_stiffness_bar, ground_absorption_bar,
         ground_friction_bar, rows_tie_stiffness_bar, rows_tie_damping_bar, rows_tie_x_bar, rows_tie_v_bar, top_dx_bar,
         top_dv_bar) = compute_running_sums(acc)
        tie_stiffness_bar = tie_stiffness_bar + rows_tie_stiffness_bar
        tie_damping_bar = tie_damping_bar + rows_tie_damping_bar
        tie_x_bar = tie_x_bar + rows_tie_x_bar
        tie_v_bar = tie_v_bar + rows_tie_v_bar
        # The top segment (the top particle at the start of the step to particle start + 1).
        e_bar, k_s_bar, d_bar = compute_segment_adjoint(u_n, l_n, ratio_n, alpha_n, constants.stiffness,
                                                         constants.rest_length, f_bar_n, uu_n, tr_n, sym_n,
                                                         segment_forced[start])
        stiffness_bar = stiffness_bar + k_s_bar
        rest_bar = rest_bar + d_bar
        particle_q_grad[start] = particle_q_grad[start] + e_bar
        particle_q_grad[start + 1] = particle_q_grad[start + 1] - e_bar
        # top_dx = top - x0_start, top_dv = top_dx / h - v0_start.
        top_dx_bar = top_dx_bar + top_dv_bar / dt
        particle_qd_grad[start] = particle_qd_grad[start] - top_dv_bar
        top_bar = top_bar + top_dx_bar
        particle_q_grad[start] = particle_q_grad[start] - top_dx_bar

        control_grad.top_q[s] = control_grad.top_q[s] + top_bar
        control_grad.tie_q[s] = control_grad.tie_q[s] + tie_x_bar
        control_grad.tie_qd[s] = control_grad.tie_qd[s] + tie_v_bar
        model_grad.string_stiffness[s] = model_grad.string_stiffness[s] + stiffness_bar
        model_grad.string_rest_length[s] = model_grad.string_rest_length[s] + rest_bar
        model_grad.string_internal_friction[s] = model_grad.string_internal_friction[s] + friction_bar
        model_grad.string_air_drag[s] = model_grad.string_air_drag[s] + air_bar
        model_grad.string_ground_stiffness[s] = model_grad.string_ground_stiffness[s] + ground_stiffness_bar
        model_grad.string_ground_absorption[s] = (model_grad.string_ground_absorption[s]
                                                  + ground_absorption_bar)
        model_grad.string_ground_friction[s] = model_grad.string_ground_friction[s] + ground_friction_bar
        # k_t = tied k, k_dt = tied k_d.
        model_grad.string_tie_stiffness[s] = (model_grad.string_tie_stiffness[s]
                                              + constants.tied * tie_stiffness_bar)
        model_grad.string_tie_damping[s] = model_grad.string_tie_damping[s] + constants.tied * tie_damping_bar
        model_grad.string_tied[s] = (model_grad.string_tied[s] + model.string_tie_stiffness[s] * tie_stiffness_bar
                               + model.string_tie_damping[s] * tie_damping_bar)

    return integrate_string_implicit_adjoint
