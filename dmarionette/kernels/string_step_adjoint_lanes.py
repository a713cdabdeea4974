"""The hand-written adjoint of the string step with ``K`` strings per thread, one SIMD lane per string.

``integrate_string_lanes_adjoint`` is ``string_step_adjoint.integrate_string_implicit_adjoint``
(printed springs) on lane vectors, as ``string_step_lanes`` is the one-launch step on them: one
thread takes a group of ``K`` strings of equal particle count (the forward's group table,
``string_step_lanes.lane_groups``), the rows peeled as in the scalar adjoint (the last, the rows
between, the first), the per-lane branches (a particle below the ground, the spring's clamp
``1 - d/l > 0``) computed on every lane and blended by the comparison's mask. Every operation is
the scalar adjoint's, in its order and rounding (``lane_ops``; a float's negation is Warp's
``0 - x``, a vector's a true one; the scalar code's ``0 + x`` starts are added too; ``x - 0`` is
``x`` bit for bit and is left out), so each real lane's gradients are the scalar adjoint's, bit for
bit (``tests/grad/test_string_step_adjoint_lanes.py``). The scalar adjoint has no ``mat33 * mat33``,
so no lane ``fma`` is needed here: Warp's ``dot`` and ``mat33 * vec3`` are not contracted.

It reads what the laned keep step (``string_step_lanes.integrate_string_lanes_kernel(..., keep=True)``)
stored: the pivot inverses and ``C'`` in the laned layout (``lane_inverse``, ``lane_c``: group
``g``'s row ``j`` at ``group_base[g] + j``), and ``particle_dv`` per particle. Its forward
substitution goes to laned scratch (``lane_bar``, and its terms of the particles' gradients
``lane_x_bar``, ``lane_r``), and so do the spring parts of every segment it computes
(``lane_parts``: the back substitution reads them instead of computing them again, a square root
and four divisions per row; computed by the same function from the same positions, so the same
bits). Padding lanes (a group of fewer than ``K`` strings repeats one of its
strings) compute and write nothing: every gradient is read, added to and written back for the real
lanes only, and each string's particles and constants belong to one lane of one thread. A
particle's gradient gets the same terms in the same order as in the scalar adjoint, but summed in
registers across the rows and written once (the scalar adjoint reads and writes it at each of its
up to five terms: in lanes each of those is a gather and a scatter). Float64, CPU, printed springs
only (tension-only springs keep the scalar adjoint, as they keep the five passes forward).
"""

import functools

import warp as wp

from .lane_ops import native_lane_memory, native_lane_ops
from .string_state_arrays import string_arrays_types
from .string_step_lanes import LANES, lane_step_functions, lane_types

__all__ = ["lane_parts_type", "string_step_adjoint_lanes_kernel"]

f64 = wp.float64


@functools.cache
def lane_parts_type(lanes: int = LANES):
    """A row of the laned scratch ``lane_parts``: the spring parts ``(u, l, 1 - d/l, alpha, beta)``
    (``compute_spring_parts``) of the segment above the row's particle, ``8 x K`` (rows 0-2 ``u``,
    3 ``l``, 4 ``1 - d/l``, 5 ``alpha``, 6 ``beta``, 7 unused: a row is four 64-byte lines for K = 4)."""
    return wp.types.matrix((8, lanes), f64)


@functools.cache
def string_step_adjoint_lanes_kernel(effects: tuple[bool, bool, bool, bool, bool], lanes: int = LANES):
    """Builds ``integrate_string_lanes_adjoint`` for an effect set (``effects`` as
    ``integrate_string_lanes_kernel``'s, compile-time switches) and ``lanes`` strings per thread."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    LANES_ = lanes
    lane, ivec, lvec, lmat = lane_types(lanes)
    lacc = wp.types.matrix((21, lanes), f64)  # a row's running sums, as the scalar adjoint's acc_t
    lparts = lane_parts_type(lanes)
    vec3 = wp.vec3d
    nat = native_lane_ops(lanes)
    ladd, lsub, lmul, ldiv, lsqrt, lmax, lselect_less = (
        nat.add, nat.sub, nat.mul, nat.div, nat.sqrt, nat.max, nat.where_less)
    f = lane_step_functions(lanes)
    gather_string3, gather_particle, gather_particle3, scatter3 = (
        f.gather_string3, f.gather_particle, f.gather_particle3, f.scatter3)
    lneg, vadd, vsub, lsum3, lscale, lmul_vec = f.lneg, f.vadd, f.vsub, f.lsum3, f.lscale, f.lmul_vec
    compute_lane_group, gather_string_constants = f.compute_lane_group, f.gather_string_constants
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(f64)

    # --- accumulation into the gradients, real lanes only ---------------------------------------

    mem = native_lane_memory(lanes)

    @wp.func
    def scatter_add3(a: wp.array(dtype=vec3), index: ivec, j: int, real: int, v: lvec):
        """``a[index[k] + j] = a[index[k] + j] + v[:, k]`` for the real lanes."""
        mem.scatter_add3(a, index, j, real, v)

    @wp.func
    def scatter_sub3(a: wp.array(dtype=vec3), index: ivec, j: int, real: int, v: lvec):
        """``a[index[k] + j] = a[index[k] + j] - v[:, k]`` for the real lanes."""
        mem.scatter_sub3(a, index, j, real, v)

    @wp.func
    def scatter_add(a: wp.array(dtype=f64), index: ivec, j: int, real: int, v: lane):
        """``a[index[k] + j] = a[index[k] + j] + v[k]`` for the real lanes."""
        mem.scatter_add(a, index, j, real, v)

    # --- the scalar adjoint's operations on lanes ------------------------------------------------

    @wp.func
    def ldot(a: lvec, b: lvec):
        """``wp.dot`` of two ``vec3d`` per lane: ``(a0 b0 + a1 b1) + a2 b2``."""
        return lsum3(a[0], a[1], a[2], b[0], b[1], b[2])

    @wp.func
    def vdiv(v: lvec, s: lane):
        """``vec3 / scalar``: each component divided."""
        r = lvec()
        for i in range(3):
            r[i] = ldiv(v[i], s)
        return r

    @wp.func
    def acc_vec(acc: lacc, i: int):
        r = lvec()
        r[0] = acc[i]
        r[1] = acc[i + 1]
        r[2] = acc[i + 2]
        return r

    @wp.func
    def compute_lane_running_sums(acc: lacc):
        """The running sums ``acc`` holds, by name (the scalar adjoint's ``compute_running_sums``)."""
        return (acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6], acc[7], acc[8], acc_vec(acc, 9),
                acc_vec(acc, 12), acc_vec(acc, 15), acc_vec(acc, 18))

    @wp.func
    def compute_lane_spring_parts(x_a: lvec, x_b: lvec, stiffness: lane, rest_length: lane):
        """``string_spring``'s ``compute_spring_parts``: ``(u, l, 1 - d/l, alpha, beta)``."""
        e = vsub(x_a, x_b)
        length = lsqrt(ldot(e, e))
        ratio = lsub(lane(f64(1.0)), ldiv(rest_length, length))
        geometric = lmax(ratio, lane(f64(0.0)))
        neg_k = lneg(stiffness)
        return (vdiv(e, length), length, ratio, lmul(neg_k, lsub(lane(f64(1.0)), geometric)),
                lmul(neg_k, geometric))

    @wp.func
    def store_parts(a: wp.array(dtype=lparts), row: int, u: lvec, length: lane, ratio: lane, alpha: lane,
                    beta: lane):
        p = lparts()
        p[0] = u[0]
        p[1] = u[1]
        p[2] = u[2]
        p[3] = length
        p[4] = ratio
        p[5] = alpha
        p[6] = beta
        a[row] = p

    @wp.func
    def load_parts(a: wp.array(dtype=lparts), row: int):
        """The spring parts ``(u, l, 1 - d/l, alpha, beta)`` of the segment above row ``row``'s particle."""
        p = a[row]
        u = lvec()
        u[0] = p[0]
        u[1] = p[1]
        u[2] = p[2]
        return u, p[3], p[4], p[5], p[6]

    @wp.func
    def compute_lane_outer_moments(a: lvec, b: lvec, u: lvec):
        """``compute_outer_moments``: for ``M = a b^T``, ``(u^T M u, tr M, (M + M^T) u)``."""
        ua = ldot(u, a)
        ub = ldot(u, b)
        return lmul(ua, ub), ldot(a, b), vadd(lscale(ub, a), lscale(ua, b))

    @wp.func
    def compute_lane_spring_adjoint(u: lvec, length: lane, ratio: lane, alpha: lane, stiffness: lane,
                                    rest_length: lane, f_bar: lvec, k_uu: lane, k_tr: lane, k_sym: lvec):
        """``compute_spring_adjoint``: ``(e_bar, stiffness_bar, rest_length_bar)``; the clamp's
        branch (``ratio > 0``) as a select."""
        zero = lane(f64(0.0))
        one = lane(f64(1.0))
        stretch = lsub(length, rest_length)
        geometric = lmax(ratio, zero)
        u_f = ldot(u, f_bar)
        u_bar = vadd(lscale(lmul(lneg(stiffness), stretch), f_bar), lscale(alpha, k_sym))
        stiffness_bar = lsub(lsub(lmul(lneg(stretch), u_f), lmul(lsub(one, geometric), k_uu)),
                             lmul(geometric, k_tr))
        length_bar = lmul(lneg(stiffness), u_f)
        rest_bar = lmul(stiffness, u_f)
        g_bar = lmul(stiffness, lsub(k_uu, k_tr))
        length_bar = lselect_less(zero, ratio,
                                  ladd(length_bar, ldiv(lmul(g_bar, rest_length), lmul(length, length))), length_bar)
        rest_bar = lselect_less(zero, ratio, lsub(rest_bar, ldiv(g_bar, length)), rest_bar)
        e_bar = vadd(vdiv(vsub(u_bar, lscale(ldot(u, u_bar), u)), length), lscale(length_bar, u))
        return e_bar, stiffness_bar, rest_bar

    @wp.func
    def compute_lane_row_adjoint(
        first: bool, is_last: bool, starts: ivec, j: int, row: int, real: int,
        particle_q: wp.array(dtype=vec3), particle_qd: wp.array(dtype=vec3),
        particle_dv: wp.array(dtype=vec3), lane_c: wp.array(dtype=lmat), lane_bar: wp.array(dtype=lvec),
        lane_x_bar: wp.array(dtype=lvec), lane_r: wp.array(dtype=lvec), lane_parts: wp.array(dtype=lparts),
        particle_q_grad: wp.array(dtype=vec3), particle_qd_grad: wp.array(dtype=vec3),
        particle_mass_grad: wp.array(dtype=f64),
        stiffness: lane, rest_length: lane, friction: lane, air_drag: lane, ground_stiffness: lane,
        ground_absorption: lane, ground_friction: lane, tie_stiffness: lane, tie_damping: lane, tie_x: lvec,
        tie_v: lvec, gravity: vec3, ground_height: f64, dt: f64, top_dx: lvec, top_dv: lvec,
        v: lvec, v_next: lvec, lam_next: lvec, dv_next: lvec, f_bar_n: lvec, uu_n: lane, tr_n: lane, sym_n: lvec,
        acc: lacc,
        q_pend: lvec, qd_pend: lvec, qd_carry: lvec,
    ):
        """``compute_row_adjoint`` for row ``j`` of the group's strings (``first``: ``j == 1``),
        its ``C'`` and ``lambda`` at ``row`` of the laned scratch. Returns what row ``j - 1`` carries.

        The particles' gradients are summed in registers, in the scalar adjoint's order per
        particle, and written once each (the scalar adjoint reads and writes them at every term):
        ``q_pend``, ``qd_pend``: particle ``j + 1``'s sums so far (written here, with the segment
        below's terms, its last); ``qd_carry``: particle ``j``'s velocity gradient so far (its
        forward-substitution term, row ``j + 1``'s ``v_prev_bar``)."""
        zero = lane(f64(0.0))
        zv = lvec()
        hl = lane(dt)
        h2 = lane(dt * dt)
        (stiffness_bar, rest_bar, friction_bar, air_bar, ground_stiffness_bar, ground_absorption_bar,
         ground_friction_bar, tie_stiffness_bar, tie_damping_bar, tie_x_bar, tie_v_bar, top_dx_bar,
         top_dv_bar) = compute_lane_running_sums(acc)
        x = gather_particle3(particle_q, starts, j)
        v_prev = gather_particle3(particle_qd, starts, j - 1)
        u_p, _l_p, _ratio_p, alpha_p, beta_p = load_parts(lane_parts, row)  # the segment above
        lam = lane_bar[row]
        if not is_last:
            lam = vsub(lam, lmul_vec(lane_c[row], lam_next))
        dv = gather_particle3(particle_dv, starts, j)
        rhs_bar = lam
        a_xz_bar = lneg(ladd(lmul(lam[0], dv[0]), lmul(lam[2], dv[2])))
        a_y_bar = lmul(lneg(lam[1]), dv[1])
        force_row_bar = lscale(hl, rhs_bar)
        v_bar = zv
        v_prev_bar = zv
        v_next_bar = zv
        x_bar = zv
        k_c = zero
        k_y = zero
        if is_last:
            k_c = lneg(tie_stiffness)
        gh = lane(ground_height)
        if wp.static(GROUND):
            k_y = lselect_less(x[1], gh, lneg(ground_stiffness), k_y)
        k_c_bar = lsub(lmul(h2, ldot(rhs_bar, v)), lmul(h2, ladd(a_xz_bar, a_y_bar)))
        k_y_bar = lsub(lmul(lmul(h2, rhs_bar[1]), v[1]), lmul(h2, a_y_bar))
        kv = lvec()
        kv[0] = lmul(k_c, rhs_bar[0])
        kv[1] = lmul(ladd(k_c, k_y), rhs_bar[1])
        kv[2] = lmul(k_c, rhs_bar[2])
        v_bar = vadd(v_bar, lscale(h2, kv))
        mass_bar = ladd(a_xz_bar, a_y_bar)
        neg_dt = lneg(hl)
        d_xz_bar = lmul(neg_dt, a_xz_bar)
        d_y_bar = lmul(neg_dt, a_y_bar)
        d_base_bar = ladd(d_xz_bar, d_y_bar)  # d_y starts as d_xz (friction and air drag)
        if is_last:
            tie_x_bar = vadd(tie_x_bar, lscale(tie_stiffness, force_row_bar))
            tie_v_bar = vadd(tie_v_bar, lscale(tie_damping, force_row_bar))
            x_bar = vsub(x_bar, lscale(tie_stiffness, force_row_bar))
            v_bar = vsub(v_bar, lscale(tie_damping, force_row_bar))
            tie_stiffness_bar = lsub(ladd(tie_stiffness_bar, ldot(vsub(tie_x, x), force_row_bar)), k_c_bar)
            tie_damping_bar = lsub(ladd(tie_damping_bar, ldot(vsub(tie_v, v), force_row_bar)), d_base_bar)
        if wp.static(GROUND):  # below the ground (x_y < h): both sides, then a select
            y = x[1]
            fy = force_row_bar[1]
            ground_stiffness_bar = lselect_less(
                y, gh, lsub(ladd(ground_stiffness_bar, lmul(lsub(gh, y), fy)), k_y_bar), ground_stiffness_bar)
            x_bar[1] = lselect_less(y, gh, lsub(x_bar[1], lmul(ground_stiffness, fy)), x_bar[1])
            ground_absorption_bar = lselect_less(
                y, gh, lsub(lsub(ground_absorption_bar, lmul(v[1], fy)), d_y_bar), ground_absorption_bar)
            v_bar[1] = lselect_less(y, gh, lsub(v_bar[1], lmul(ground_absorption, fy)), v_bar[1])
            if wp.static(GROUND_FRICTION):
                ground_friction_bar = lselect_less(
                    y, gh, lsub(lsub(lsub(ground_friction_bar, lmul(v[0], force_row_bar[0])),
                                     lmul(v[2], force_row_bar[2])), d_xz_bar), ground_friction_bar)
                v_bar[0] = lselect_less(y, gh, lsub(v_bar[0], lmul(ground_friction, force_row_bar[0])), v_bar[0])
                v_bar[2] = lselect_less(y, gh, lsub(v_bar[2], lmul(ground_friction, force_row_bar[2])), v_bar[2])
        if wp.static(AIR):
            air_bar = lsub(lsub(air_bar, ldot(v, force_row_bar)), d_base_bar)
            v_bar = vsub(v_bar, lscale(air_drag, force_row_bar))
        if wp.static(GRAVITY):
            mass_bar = ladd(mass_bar, lsum3(lane(gravity[0]), lane(gravity[1]), lane(gravity[2]),
                                            force_row_bar[0], force_row_bar[1], force_row_bar[2]))
        if wp.static(FRICTION):
            friction_bar = lsub(lsub(friction_bar, ldot(vsub(v, v_prev), force_row_bar)), d_base_bar)
            v_bar = vsub(v_bar, lscale(friction, force_row_bar))
            v_prev_bar = vadd(v_prev_bar, lscale(friction, force_row_bar))
            if first:
                friction_bar = ladd(friction_bar, lmul(hl, ldot(top_dv, rhs_bar)))
                top_dv_bar = vadd(top_dv_bar, lscale(lmul(hl, friction), rhs_bar))
            if not is_last:
                friction_bar = ladd(lsub(lsub(friction_bar, ldot(vsub(v, v_next), force_row_bar)), d_base_bar),
                                    lmul(hl, ladd(ldot(lam, dv_next), ldot(dv, lam_next))))
                v_bar = vsub(v_bar, lscale(friction, force_row_bar))
                v_next_bar = vadd(v_next_bar, lscale(friction, force_row_bar))
        # The segment above: force -f_prev, diag's -h^2 K_prev, rhs_k's K_prev w_prev.
        w_prev = lscale(h2, vsub(v, v_prev))
        if first:
            w_prev = vsub(lscale(h2, v), lscale(hl, top_dx))
        uu_p, tr_p, sym_p = compute_lane_outer_moments(lscale(h2, lam), dv, u_p)
        uu, tr, sym = compute_lane_outer_moments(rhs_bar, w_prev, u_p)
        uu_p = ladd(uu_p, uu)
        tr_p = ladd(tr_p, tr)
        sym_p = vadd(sym_p, sym)
        w_bar = vadd(lscale(lmul(alpha_p, ldot(u_p, rhs_bar)), u_p), lscale(beta_p, rhs_bar))  # K_prev^T rhs_bar
        v_bar = vadd(v_bar, lscale(h2, w_bar))
        if first:
            top_dx_bar = vsub(top_dx_bar, lscale(hl, w_bar))
        else:
            v_prev_bar = vsub(v_prev_bar, lscale(h2, w_bar))
        if not is_last:
            # The segment below, then its spring's adjoint (it is complete).
            neg_h2 = lneg(h2)
            u_n, l_n, ratio_n, alpha_n, beta_n = load_parts(lane_parts, row + 1)
            f_bar_n = vadd(f_bar_n, force_row_bar)
            uu, tr, sym = compute_lane_outer_moments(lscale(h2, lam), dv, u_n)
            uu_n = ladd(uu_n, uu)
            tr_n = ladd(tr_n, tr)
            sym_n = vadd(sym_n, sym)
            uu, tr, sym = compute_lane_outer_moments(lscale(neg_h2, lam), dv_next, u_n)
            uu_n = ladd(uu_n, uu)
            tr_n = ladd(tr_n, tr)
            sym_n = vadd(sym_n, sym)
            uu, tr, sym = compute_lane_outer_moments(lscale(neg_h2, dv), lam_next, u_n)
            uu_n = ladd(uu_n, uu)
            tr_n = ladd(tr_n, tr)
            sym_n = vadd(sym_n, sym)
            w_next = lscale(h2, vsub(v, v_next))
            uu, tr, sym = compute_lane_outer_moments(rhs_bar, w_next, u_n)
            uu_n = ladd(uu_n, uu)
            tr_n = ladd(tr_n, tr)
            sym_n = vadd(sym_n, sym)
            w_next_bar = lscale(h2, vadd(lscale(lmul(alpha_n, ldot(u_n, rhs_bar)), u_n), lscale(beta_n, rhs_bar)))
            v_bar = vadd(v_bar, w_next_bar)
            v_next_bar = vsub(v_next_bar, w_next_bar)
            e_bar, k_s_bar, d_bar = compute_lane_spring_adjoint(u_n, l_n, ratio_n, alpha_n, stiffness, rest_length,
                                                                f_bar_n, uu_n, tr_n, sym_n)
            stiffness_bar = ladd(stiffness_bar, k_s_bar)
            rest_bar = ladd(rest_bar, d_bar)
            x_bar = vadd(x_bar, e_bar)
            scatter3(particle_q_grad, starts, j + 1, real, vsub(q_pend, e_bar))  # particle j + 1 is complete
            scatter3(particle_qd_grad, starts, j + 1, real, vadd(qd_pend, v_next_bar))
        # Particle j: its gradient before this step's adjoint, the forward substitution's term, this row's.
        q_pend_out = vadd(vadd(gather_particle3(particle_q_grad, starts, j), lane_x_bar[row]), x_bar)
        qd_pend_out = vadd(qd_carry, v_bar)
        # Particle j - 1 (the top has no forward-substitution term).
        qd_carry_out = gather_particle3(particle_qd_grad, starts, j - 1)
        if not first:
            qd_carry_out = vadd(qd_carry_out, lane_r[row - 1])
        qd_carry_out = vadd(qd_carry_out, v_prev_bar)
        scatter_add(particle_mass_grad, starts, j, real, mass_bar)
        acc_out = lacc()
        acc_out[0] = stiffness_bar
        acc_out[1] = rest_bar
        acc_out[2] = friction_bar
        acc_out[3] = air_bar
        acc_out[4] = ground_stiffness_bar
        acc_out[5] = ground_absorption_bar
        acc_out[6] = ground_friction_bar
        acc_out[7] = tie_stiffness_bar
        acc_out[8] = tie_damping_bar
        for i in range(3):
            acc_out[9 + i] = tie_x_bar[i]
            acc_out[12 + i] = tie_v_bar[i]
            acc_out[15 + i] = top_dx_bar[i]
            acc_out[18 + i] = top_dv_bar[i]
        # Row j - 1 is next: segment j - 1 becomes the one below.
        return (v_prev, v, lam, dv, -force_row_bar, uu_p, tr_p, sym_p, acc_out, q_pend_out, qd_pend_out,
                qd_carry_out)

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_lanes_adjoint(
        # Model (the group table, ``lane_groups``, then the strings):
        group_string: wp.array(dtype=ivec),
        group_real: wp.array(dtype=wp.int32),
        group_base: wp.array(dtype=wp.int32),
        model: StringModelArrays,
        # State in (the step's start, then what the laned step, built with ``keep``, wrote):
        state_in: StringStateArrays,
        lane_inverse: wp.array(dtype=lmat),
        lane_c: wp.array(dtype=lmat),
        particle_dv: wp.array(dtype=vec3),
        state_out: StringStateArrays,
        # Control:
        control: StringControlArrays,
        dt: f64,
        # State out (laned scratch: forward substitution, gradient terms, spring parts):
        lane_bar: wp.array(dtype=lvec),
        lane_x_bar: wp.array(dtype=lvec),
        lane_r: wp.array(dtype=lvec),
        lane_parts: wp.array(dtype=lparts),
        # Adjoint in and out (the state out's gradients; read, then consumed: zeroed):
        state_out_grad: StringStateArrays,
        # Adjoint out (accumulated: the state in's, the control's and the model's, each its arrays' ``.grad``):
        state_in_grad: StringStateArrays,
        control_grad: StringControlArrays,
        model_grad: StringModelArrays,
    ):
        strings, real, base, starts, n = compute_lane_group(wp.tid(), group_string, group_real, group_base,
                                                            model.string_start)
        particle_q, particle_qd = state_in.particle_q, state_in.particle_qd
        particle_q_out, particle_qd_out = state_out.particle_q, state_out.particle_qd
        particle_q_out_grad, particle_qd_out_grad = state_out_grad.particle_q, state_out_grad.particle_qd
        particle_q_grad, particle_qd_grad = state_in_grad.particle_q, state_in_grad.particle_qd
        last = n - 1
        zero = lane(f64(0.0))
        zv = lvec()
        hl = lane(dt)
        h2 = lane(dt * dt)
        gravity = model.gravity
        ground_height = model.ground_height
        particle_mass_grad = model_grad.particle_mass
        (stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tied,
         tie_stiffness_k, tie_damping_k) = gather_string_constants(strings, model)
        tie_stiffness = lmul(tied, tie_stiffness_k)
        tie_damping = lmul(tied, tie_damping_k)
        tie_x = gather_string3(control.tie_q, strings)
        tie_v = gather_string3(control.tie_qd, strings)
        top = gather_string3(control.top_q, strings)
        q0 = gather_particle3(particle_q, starts, 0)
        top_dx = vsub(top, q0)
        top_dv = vsub(vdiv(top_dx, hl), gather_particle3(particle_qd, starts, 0))
        g_upper = zero  # the friction's part of A_{j,j+1}: h D_j,j+1 = -h k_f I
        if wp.static(FRICTION):
            g_upper = lmul(lneg(hl), friction)

        # 1. The outputs: the tie force (eq. 2 on the new state) and the top particle.
        force_bar = gather_string3(state_out_grad.tie_force, strings)
        scatter3(state_out_grad.tie_force, strings, 0, real, zv)
        tie_stiffness_bar = lneg(ldot(vsub(tie_x, gather_particle3(particle_q_out, starts, last)), force_bar))
        tie_damping_bar = lneg(ldot(vsub(tie_v, gather_particle3(particle_qd_out, starts, last)), force_bar))
        tie_x_bar = lscale(lneg(tie_stiffness), force_bar)
        tie_v_bar = lscale(lneg(tie_damping), force_bar)
        x_top_bar = gather_particle3(particle_q_out_grad, starts, 0)
        v_top_bar = gather_particle3(particle_qd_out_grad, starts, 0)
        scatter3(particle_q_out_grad, starts, 0, real, zv)
        scatter3(particle_qd_out_grad, starts, 0, real, zv)
        top_bar = vadd(x_top_bar, vdiv(v_top_bar, hl))
        scatter_sub3(particle_q_grad, starts, 0, real, vdiv(v_top_bar, hl))

        # 2. Forward substitution of A lambda = dv_bar, top to bottom (A_{j-1,j} = h^2 K_{j-1} - h k_f I).
        y_prev = zv
        x_prev = q0
        for j in range(1, last + 1):
            x = gather_particle3(particle_q, starts, j)
            x_bar = gather_particle3(particle_q_out_grad, starts, j)
            v_bar = gather_particle3(particle_qd_out_grad, starts, j)
            scatter3(particle_q_out_grad, starts, j, real, zv)
            scatter3(particle_qd_out_grad, starts, j, real, zv)
            if j == last:
                x_bar = vadd(x_bar, lscale(tie_stiffness, force_bar))
                v_bar = vadd(v_bar, lscale(tie_damping, force_bar))
            r = vadd(v_bar, lscale(hl, x_bar))  # dv_bar: x1 = x0 + h (v0 + dv)
            lane_x_bar[base + j] = x_bar  # the particle's first gradient terms, added in step 3
            lane_r[base + j] = r
            # The segment above (every segment's parts, read again by the back substitution).
            u, length, ratio, alpha, beta = compute_lane_spring_parts(x_prev, x, stiffness, rest_length)
            store_parts(lane_parts, base + j, u, length, ratio, alpha, beta)
            if j > 1:
                r = vsub(r, vadd(lscale(lmul(h2, lmul(alpha, ldot(u, y_prev))), u),
                                 lscale(ladd(lmul(h2, beta), g_upper), y_prev)))
            y_prev = lmul_vec(lane_inverse[base + j], r)
            lane_bar[base + j] = y_prev
            x_prev = x

        # 3. Back substitution, bottom to top, and each row's adjoint (the last row, the rows
        # between, the first, as the scalar adjoint peels them).
        acc = lacc()
        lam_next = zv
        dv_next = zv
        v_next = zv
        v = gather_particle3(particle_qd, starts, last)
        f_bar_n = zv
        uu_n = zero
        tr_n = zero
        sym_n = zv
        q_pend = zv  # (no particle below the last row)
        qd_pend = zv
        qd_carry = vadd(gather_particle3(particle_qd_grad, starts, last), lane_r[base + last])
        (v, v_next, lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend,
         qd_carry) = compute_lane_row_adjoint(
            last == 1, True, starts, last, base + last, real, particle_q, particle_qd, particle_dv,
            lane_c, lane_bar, lane_x_bar, lane_r, lane_parts, particle_q_grad, particle_qd_grad, particle_mass_grad,
            stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption, ground_friction,
            tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt, top_dx, top_dv, v, v_next,
            lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend, qd_carry)
        for i in range(last - 2):
            (v, v_next, lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend,
             qd_carry) = compute_lane_row_adjoint(
                False, False, starts, last - 1 - i, base + last - 1 - i, real, particle_q, particle_qd,
                particle_dv, lane_c, lane_bar, lane_x_bar, lane_r, lane_parts, particle_q_grad, particle_qd_grad,
                particle_mass_grad, stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption,
                ground_friction, tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt, top_dx, top_dv,
                v, v_next, lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend, qd_carry)
        if last > 1:
            (v, v_next, lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend,
             qd_carry) = compute_lane_row_adjoint(
                True, False, starts, 1, base + 1, real, particle_q, particle_qd, particle_dv, lane_c,
                lane_bar, lane_x_bar, lane_r, lane_parts, particle_q_grad, particle_qd_grad, particle_mass_grad,
                stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption, ground_friction,
                tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt, top_dx, top_dv, v, v_next,
                lam_next, dv_next, f_bar_n, uu_n, tr_n, sym_n, acc, q_pend, qd_pend, qd_carry)
        (stiffness_bar, rest_bar, friction_bar, air_bar, ground_stiffness_bar, ground_absorption_bar,
         ground_friction_bar, rows_tie_stiffness_bar, rows_tie_damping_bar, rows_tie_x_bar, rows_tie_v_bar, top_dx_bar,
         top_dv_bar) = compute_lane_running_sums(acc)
        tie_stiffness_bar = ladd(tie_stiffness_bar, rows_tie_stiffness_bar)
        tie_damping_bar = ladd(tie_damping_bar, rows_tie_damping_bar)
        tie_x_bar = vadd(tie_x_bar, rows_tie_x_bar)
        tie_v_bar = vadd(tie_v_bar, rows_tie_v_bar)
        # The top segment (the top particle at the start of the step to particle 1).
        u_n, l_n, ratio_n, alpha_n, _beta_n = load_parts(lane_parts, base + 1)
        e_bar, k_s_bar, d_bar = compute_lane_spring_adjoint(u_n, l_n, ratio_n, alpha_n, stiffness, rest_length,
                                                            f_bar_n, uu_n, tr_n, sym_n)
        stiffness_bar = ladd(stiffness_bar, k_s_bar)
        rest_bar = ladd(rest_bar, d_bar)
        scatter_add3(particle_q_grad, starts, 0, real, e_bar)
        scatter3(particle_q_grad, starts, 1, real, vsub(q_pend, e_bar))  # particle 1 is complete
        scatter3(particle_qd_grad, starts, 1, real, qd_pend)
        # top_dx = top - x0_start, top_dv = top_dx / h - v0_start.
        top_dx_bar = vadd(top_dx_bar, vdiv(top_dv_bar, hl))
        scatter3(particle_qd_grad, starts, 0, real, vsub(qd_carry, top_dv_bar))
        top_bar = vadd(top_bar, top_dx_bar)
        scatter_sub3(particle_q_grad, starts, 0, real, top_dx_bar)

        scatter_add3(control_grad.top_q, strings, 0, real, top_bar)
        scatter_add3(control_grad.tie_q, strings, 0, real, tie_x_bar)
        scatter_add3(control_grad.tie_qd, strings, 0, real, tie_v_bar)
        scatter_add(model_grad.string_stiffness, strings, 0, real, stiffness_bar)
        scatter_add(model_grad.string_rest_length, strings, 0, real, rest_bar)
        scatter_add(model_grad.string_internal_friction, strings, 0, real, friction_bar)
        scatter_add(model_grad.string_air_drag, strings, 0, real, air_bar)
        scatter_add(model_grad.string_ground_stiffness, strings, 0, real, ground_stiffness_bar)
        scatter_add(model_grad.string_ground_absorption, strings, 0, real, ground_absorption_bar)
        scatter_add(model_grad.string_ground_friction, strings, 0, real, ground_friction_bar)
        # k_t = tied k, k_dt = tied k_d.
        scatter_add(model_grad.string_tie_stiffness, strings, 0, real, lmul(tied, tie_stiffness_bar))
        scatter_add(model_grad.string_tie_damping, strings, 0, real, lmul(tied, tie_damping_bar))
        for k in range(LANES_):
            if k < real:
                s = strings[k]
                model_grad.string_tied[s] = (model_grad.string_tied[s]
                                             + model.string_tie_stiffness[s] * tie_stiffness_bar[k]
                                             + model.string_tie_damping[s] * tie_damping_bar[k])

    return integrate_string_lanes_adjoint
