"""The string step's tangent for one direction with the strings in SIMD lanes (issue 13, item 4).

``string_step_tangent`` (read its module doc: the step, its tangent, the branches, the costs) puts
the *directions* in lanes; with one direction (P = 1) that leaves the scalar kernel, one thread per
string, about 1.3 forward string rollouts per direction. This kernel is the same tangent with the
*strings* in lanes, as the laned forward (``string_step_lanes``) has them: one thread per group of
``K`` strings of equal particle count (the forward's group table, ``string_step_lanes.lane_groups``;
padding lanes repeat a string of the group, compute and write nothing), every primal value and the
tangent a lane vector (``lane_ops``' snippets, ``string_step_lanes.lane_step_functions``), the
laned kept factorisation read in place (one ``9 x K`` block per row of a group: all lanes at once).

Per lane the operations are the scalar tangent kernel's without the linear maps (``maps = False``,
what it runs at P = 1), in its order, with these differences (rounding only; the tests assert
1e-13 against it, ``tests/grad/test_string_step_tangent.py``): each segment's spring parts are
computed in the row loop (the segment ``(p, p + 1)`` once, at row ``p``, carried to row ``p + 1``;
the scalar kernel's segment pass stores them, the same expressions), and the branches are selects
on every lane: the ground term where a particle starts below the ground (``x0_y <
ground_height``, both sides computed, the term added where true, else ``+ 0``) and the clamp's
``g' = 0`` while a segment is compressed. Clang may contract a snippet's products and sums into
``fma`` where the scalar kernel's Warp code rounds each (not bit for bit, within 1e-13).

Cost (the ``strings`` scene's six strings of 50 particles: groups of 4 + 2; 1,000 steps; 2-core
machine shared with other work, load 1.1-1.8): the rollout of one tangent 13.0-13.3 ms against
16.7-17.4 with the scalar kernel (``--no-lanes``), wall time, ``bench_string_tangent.py --repeats 5``
then ``--directions 1 --no-lanes``, two runs each; 1.90-1.92 laned forward rollouts against 2.49
(thread CPU time, ``--clock cpu --repeats 9 --directions 1`` with and without ``--no-lanes``, five
alternating runs: 13.5-14.2 against 17.0-17.5 ms).
Where it goes (thread CPU time, experiments with wrong results): the forward with ``keep``, the
uploads and the launch ~7.0 ms (the kernel returning at once), this kernel ~6.5 ms, of it the back
substitution ~1 ms and the forward sweep's loads alone (five gathers of ``3 x K`` per row, the mass,
the pivot inverse, a mat-vec) ~2.6 ms; the segment's spring tangent and ``K' r`` ~0.5 ms. Tried and
dropped (no gain beyond the noise; thread CPU time as above, A/B alternating, three runs each):
``x0'``, ``v0'`` of each row kept
contiguous with ``y`` for the back substitution instead of gathered again (13.1-13.8 -> 13.4-14.1
ms); the top segment's row hoisted out of the row loop (13.0-13.2 -> 13.1-13.4 ms); ``y`` in
``particle_qd_out_dot`` (scattered, gathered back) instead of the laned scratch ``lane_y`` (the same
within noise; ``lane_y`` kept: no scatter). Measured, not built: the particles' tangents carried in
the laned layout between steps (contiguous ``3 x K`` loads and stores instead of four gathers and
two scatters per row; timed with every such access on ``lane_y``, results wrong): 12.4-12.9 ms,
~4 % for a laned carry in the rollout and its conversions. Meeting the issue's 1.5 forwards at
P = 1 would need this kernel at about half its cost (the forward with ``keep``, the uploads and the
launch cost ~1.0 forward already).

Layout: one direction (``P = 1``), passed as the direction's row of each tangent array (``a[0]``
of a ``(1, n)`` array with a leading direction axis or direction-minor,
``tangent_directions.direction_minor``: a 1-d view, any stride; the laned forward's gathers and
scatters, ``lane_ops.native_lane_memory``, read it), the constants ``(S, 10)`` in
``string_step_tangent.CONSTANTS`` order. Float64 on
the CPU, printed springs, the laned forward's factorisation (``keep``) only.
"""

import functools

import warp as wp

from .string_state_arrays import string_arrays_types
from .string_step_lanes import LANES, lane_step_functions, lane_types
from .lane_ops import native_lane_ops

__all__ = ["string_step_tangent_lanes_kernel"]

f64 = wp.float64


@functools.cache
def _constant_gather(lanes: int):
    """``gather_constant(a, strings, c)``: the lane vector of ``a[strings[k], c]`` (the direction's
    ``(S, 10)`` constants' tangents, any strides)."""
    lane = wp.types.vector(lanes, f64)
    ivec = wp.types.vector(lanes, wp.int32)

    @wp.func_native(f"""
    wp::vec_t<{lanes}, wp::float64> r;
    for (int k = 0; k < {lanes}; ++k)
        r.c[k] = *(const double*)((char*)a.data + (long)strings.c[k] * (long)a.strides[0]
                                  + (long)c * (long)a.strides[1]);
    return r;
    """)
    def gather_constant(a: wp.array2d(dtype=wp.float64), strings: ivec, c: int) -> lane:
        ...

    return gather_constant


@functools.cache
def string_step_tangent_lanes_kernel(effects: tuple[bool, bool, bool, bool, bool], lanes: int = LANES):
    """Builds ``integrate_string_implicit_tangent_lanes`` for an effect set (``effects`` as
    ``integrate_string_implicit_kernel``'s) and ``lanes`` strings per thread (the laned forward's
    ``LANES``; its group table and kept factorisation): one direction, float64, CPU, printed springs.
    Launched with ``dim`` = the group count; its arguments are ``string_step_tangent_kernel``'s with
    the laned factorisation (``lane_inverse``, ``lane_c``) and the group table (``group_string``,
    ``group_real``, ``group_base``) for its ``string_factor_row``/``string_factor_lane``, and no
    segment scratch."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    lane, ivec, lvec, lmat = lane_types(lanes)
    vec3 = wp.vec3d
    nat = native_lane_ops(lanes)
    add, sub, mul, div, sqrt, vmax, where_less = nat.add, nat.sub, nat.mul, nat.div, nat.sqrt, nat.max, nat.where_less
    f = lane_step_functions(lanes)
    gather_string3, gather_particle3, gather_particle = f.gather_string3, f.gather_particle3, f.gather_particle
    neg, vadd, vsub, scale, lsum3, mul_vec = f.lneg, f.vadd, f.vsub, f.lscale, f.lsum3, f.lmul_vec
    compute_lane_group, gather_string_constants = f.compute_lane_group, f.gather_string_constants
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(f64)
    tgather3, tgather, tscatter3 = gather_particle3, gather_particle, f.scatter3
    cgather = _constant_gather(lanes)

    @wp.func
    def dot(a: lvec, b: lvec):
        return lsum3(a[0], a[1], a[2], b[0], b[1], b[2])

    @wp.func
    def vneg(a: lvec):
        r = lvec()
        for i in range(3):
            r[i] = neg(a[i])
        return r

    @wp.func
    def spring_parts(x_a: lvec, x_b: lvec, stiffness: lane, rest_length: lane):
        """The segment pass's ``u, l, 1 / l, 1 - d/l, alpha, beta`` (one division) of ``e = x_a - x_b``."""
        one = lane(f64(1.0))
        e = vsub(x_a, x_b)
        length = sqrt(dot(e, e))
        inv_l = div(one, length)
        ratio = sub(one, mul(rest_length, inv_l))
        geometric = vmax(ratio, lane(f64(0.0)))
        return (scale(inv_l, e), length, inv_l, ratio, mul(neg(stiffness), sub(one, geometric)),
                mul(neg(stiffness), geometric))

    @wp.func
    def spring_tangent(u: lvec, length: lane, inv_length: lane, ratio: lane, stiffness: lane, rest_length: lane,
                       e_dot: lvec, stiffness_dot: lane, rest_length_dot: lane):
        """``string_spring_tangent_functions``' ``compute_spring_tangent`` on lanes: ``(u', alpha', beta', f_a')``."""
        one = lane(f64(1.0))
        zero = lane(f64(0.0))
        geometric = vmax(ratio, zero)
        length_dot = dot(u, e_dot)
        u_dot = scale(inv_length, vsub(e_dot, scale(length_dot, u)))
        geometric_dot = where_less(zero, ratio, mul(inv_length, sub(mul(inv_length, mul(rest_length, length_dot)),
                                                                    rest_length_dot)), zero)
        stretch = sub(length, rest_length)
        alpha_dot = add(mul(neg(sub(one, geometric)), stiffness_dot), mul(stiffness, geometric_dot))
        beta_dot = sub(mul(neg(geometric), stiffness_dot), mul(stiffness, geometric_dot))
        force_scale_dot = add(mul(stretch, stiffness_dot), mul(stiffness, sub(length_dot, rest_length_dot)))
        f_dot = vsub(scale(neg(force_scale_dot), u), scale(mul(stiffness, stretch), u_dot))
        return u_dot, alpha_dot, beta_dot, f_dot

    @wp.func
    def k_product(u: lvec, alpha: lane, beta: lane, r: lvec):
        """``K r = alpha u (u . r) + beta r``."""
        return vadd(scale(mul(alpha, dot(u, r)), u), scale(beta, r))

    @wp.func
    def k_tangent_product(u: lvec, alpha: lane, u_dot: lvec, alpha_dot: lane, beta_dot: lane, r: lvec):
        """``K' r`` for a fixed ``r``."""
        ur = dot(u, r)
        return vadd(vadd(scale(mul(ur, alpha_dot), u), scale(alpha, vadd(scale(ur, u_dot), scale(dot(r, u_dot), u)))),
                    scale(beta_dot, r))

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit_tangent_lanes(
        # Model:
        model: StringModelArrays,
        # State in (the step's start, then what the laned forward, built with ``keep``, wrote):
        state_in: StringStateArrays,
        lane_inverse: wp.array(dtype=lmat),
        lane_c: wp.array(dtype=lmat),
        group_string: wp.array(dtype=ivec),
        group_real: wp.array(dtype=wp.int32),
        group_base: wp.array(dtype=wp.int32),
        particle_dv: wp.array(dtype=vec3),
        state_out: StringStateArrays,
        # Control:
        control: StringControlArrays,
        dt: f64,
        # Tangent in (the direction's row of each tangent array, any stride):
        particle_q_dot: wp.array(dtype=vec3),
        particle_qd_dot: wp.array(dtype=vec3),
        top_q_dot: wp.array(dtype=vec3),
        tie_q_dot: wp.array(dtype=vec3),
        tie_qd_dot: wp.array(dtype=vec3),
        particle_mass_dot: wp.array(dtype=f64),
        string_constants_dot: wp.array2d(dtype=f64),
        # Tangent out (first a scratch: the forward substitution's y of each laned row, within the launch):
        lane_y: wp.array(dtype=lvec),
        particle_q_out_dot: wp.array(dtype=vec3),
        particle_qd_out_dot: wp.array(dtype=vec3),
        tie_force_dot: wp.array(dtype=vec3),
    ):
        strings, real, base, starts, n = compute_lane_group(wp.tid(), group_string, group_real, group_base,
                                                            model.string_start)
        last = n - 1
        zero = lane(f64(0.0))
        one = lane(f64(1.0))
        h = lane(dt)
        h2 = lane(dt * dt)
        inv_dt = lane(f64(1.0) / dt)
        gh = lane(model.ground_height)
        (stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tied,
         tie_stiffness_k, tie_damping_k) = gather_string_constants(strings, model)
        tie_stiffness = mul(tied, tie_stiffness_k)
        tie_damping = mul(tied, tie_damping_k)
        tie_x = gather_string3(control.tie_q, strings)
        tie_v = gather_string3(control.tie_qd, strings)
        top = gather_string3(control.top_q, strings)
        x_top = gather_particle3(state_in.particle_q, starts, 0)
        v0_top = gather_particle3(state_in.particle_qd, starts, 0)
        top_dx = vsub(top, x_top)
        top_dv = lvec()
        for i in range(3):
            top_dv[i] = sub(div(top_dx[i], h), v0_top[i])
        g_upper = zero  # the friction's part of A_{p,p+1}: h D = -h k_f I
        if wp.static(FRICTION):
            g_upper = mul(lane(-dt), friction)
        h_gravity = lvec()
        for i in range(3):
            h_gravity[i] = lane(dt * model.gravity[i])

        # The direction's constants, read once.
        stiffness_dot = cgather(string_constants_dot, strings, 0)
        rest_dot = cgather(string_constants_dot, strings, 1)
        friction_dot = zero
        if wp.static(FRICTION):
            friction_dot = cgather(string_constants_dot, strings, 2)
        air_dot = zero
        if wp.static(AIR):
            air_dot = cgather(string_constants_dot, strings, 3)
        ground_stiffness_dot = zero
        ground_absorption_dot = zero
        ground_friction_dot = zero
        if wp.static(GROUND):
            ground_stiffness_dot = cgather(string_constants_dot, strings, 4)
            ground_absorption_dot = cgather(string_constants_dot, strings, 5)
            if wp.static(GROUND_FRICTION):
                ground_friction_dot = cgather(string_constants_dot, strings, 6)
        tied_dot = cgather(string_constants_dot, strings, 9)
        tie_stiffness_dot = add(mul(tie_stiffness_k, tied_dot), mul(tied, cgather(string_constants_dot, strings, 7)))
        tie_damping_dot = add(mul(tie_damping_k, tied_dot), mul(tied, cgather(string_constants_dot, strings, 8)))
        tie_x_dot = tgather3(tie_q_dot, strings, 0)
        tie_v_dot = tgather3(tie_qd_dot, strings, 0)
        top_dot = tgather3(top_q_dot, strings, 0)
        x_top_dot = tgather3(particle_q_dot, starts, 0)

        # The forward sweep (``string_step_tangent``'s, one direction): row j's r = b' - A' dv, its
        # forward substitution y = inv_j (r - A_{j,j-1} y_prev), y kept in lane_y (the group's rows); the
        # segment (j, j + 1)'s parts and its c computed at row j (+c), carried to row j + 1 (-c).
        x = gather_particle3(state_in.particle_q, starts, 1)
        v = gather_particle3(state_in.particle_qd, starts, 1)
        dv = gather_particle3(particle_dv, starts, 1)
        x_dot = tgather3(particle_q_dot, starts, 1)
        v_dot = tgather3(particle_qd_dot, starts, 1)
        c_a = lvec()
        y_prev = lvec()
        u_a = lvec()
        alpha_a = zero
        beta_a = zero
        for j in range(1, last + 1):
            is_last = j == last
            r = lvec()
            if j == 1:  # the top segment; top_dx' = top' - x0_top'
                u_t, l_t, inv_l_t, ratio_t, alpha_t, beta_t = spring_parts(x_top, x, stiffness, rest_length)
                top_dx_dot = vsub(top_dot, x_top_dot)
                u_t_dot, alpha_t_dot, beta_t_dot, f_t_dot = spring_tangent(
                    u_t, l_t, inv_l_t, ratio_t, stiffness, rest_length, vsub(x_top_dot, x_dot), stiffness_dot,
                    rest_dot)
                r = vsub(vadd(k_tangent_product(u_t, alpha_t, u_t_dot, alpha_t_dot, beta_t_dot,
                                                vadd(vsub(scale(h2, v), scale(h, top_dx)), scale(h2, dv))),
                              k_product(u_t, alpha_t, beta_t, vsub(scale(h2, v_dot), scale(h, top_dx_dot)))),
                         scale(h, f_t_dot))
                if wp.static(FRICTION):
                    v_top_dot = tgather3(particle_qd_dot, starts, 0)
                    r = vadd(vadd(r, scale(friction_dot, scale(h, vsub(vsub(top_dv, vsub(v, v0_top)), dv)))),
                             scale(mul(h, friction), vsub(vsub(scale(inv_dt, top_dx_dot), v_top_dot),
                                                          vsub(v_dot, v_top_dot))))
            else:  # the upper segment's -c, from row j - 1
                r = vneg(c_a)
            c_b = lvec()
            x_next = lvec()
            v_next = lvec()
            dv_next = lvec()
            x_next_dot = lvec()
            v_next_dot = lvec()
            u_b = lvec()
            alpha_b = zero
            beta_b = zero
            if not is_last:
                x_next = gather_particle3(state_in.particle_q, starts, j + 1)
                v_next = gather_particle3(state_in.particle_qd, starts, j + 1)
                dv_next = gather_particle3(particle_dv, starts, j + 1)
                x_next_dot = tgather3(particle_q_dot, starts, j + 1)
                v_next_dot = tgather3(particle_qd_dot, starts, j + 1)
                u_b, l_b, inv_l_b, ratio_b, alpha_b, beta_b = spring_parts(x, x_next, stiffness, rest_length)
                w_part = k_product(u_b, mul(h2, alpha_b), add(mul(h2, beta_b), g_upper), vsub(v_dot, v_next_dot))
                u_b_dot, alpha_b_dot, beta_b_dot, f_b_dot = spring_tangent(
                    u_b, l_b, inv_l_b, ratio_b, stiffness, rest_length, vsub(x_dot, x_next_dot), stiffness_dot,
                    rest_dot)
                z_b = vadd(vsub(v, v_next), vsub(dv, dv_next))
                c_b = vadd(vadd(k_tangent_product(u_b, alpha_b, u_b_dot, alpha_b_dot, beta_b_dot, scale(h2, z_b)),
                                w_part), scale(h, f_b_dot))
                if wp.static(FRICTION):
                    c_b = vsub(c_b, scale(friction_dot, scale(h, z_b)))
                r = vadd(r, c_b)
            # The mass: h g m' of the force, -m' dv of the diagonal.
            mass_coefficient = vneg(dv)
            if wp.static(GRAVITY):
                mass_coefficient = vsub(h_gravity, dv)
            r = vadd(r, scale(tgather(particle_mass_dot, starts, j), mass_coefficient))
            v_dv = vadd(v, dv)
            if wp.static(AIR):
                r = vsub(r, vadd(scale(air_dot, scale(h, v_dv)), scale(mul(h, air_drag), v_dot)))
            if wp.static(GROUND):  # both sides on every lane, then the term where x0_y < ground_height
                r_y = add(add(mul(sub(mul(h, sub(gh, x[1])), mul(h2, v_dv[1])), ground_stiffness_dot),
                              mul(mul(lane(-dt), v_dv[1]), ground_absorption_dot)),
                          sub(mul(mul(lane(-dt), ground_stiffness), x_dot[1]),
                              mul(add(mul(h, ground_absorption), mul(h2, ground_stiffness)), v_dot[1])))
                r[1] = add(r[1], where_less(x[1], gh, r_y, zero))
                if wp.static(GROUND_FRICTION):
                    for i in range(0, 3, 2):
                        r_i = sub(mul(mul(lane(-dt), v_dv[i]), ground_friction_dot),
                                  mul(mul(h, ground_friction), v_dot[i]))
                        r[i] = add(r[i], where_less(x[1], gh, r_i, zero))
            if is_last:  # the tie (eq. 2)
                r = vadd(vadd(vadd(r, scale(tie_stiffness_dot, vsub(scale(h, vsub(tie_x, x)), scale(h2, v_dv)))),
                              scale(tie_damping_dot, scale(h, vsub(vsub(tie_v, v), dv)))),
                         vsub(vadd(scale(mul(h, tie_stiffness), vsub(tie_x_dot, x_dot)),
                                   scale(mul(h, tie_damping), vsub(tie_v_dot, v_dot))),
                              scale(mul(h2, tie_stiffness), v_dot)))
            # Forward substitution with the stored pivot inverse; A_{j,j-1} = A_{j-1,j}, the upper segment's W.
            if j > 1:
                r = vsub(r, k_product(u_a, mul(h2, alpha_a), add(mul(h2, beta_a), g_upper), y_prev))
            y_prev = mul_vec(lane_inverse[base + j], r)
            lane_y[base + j] = y_prev
            c_a = c_b
            u_a = u_b
            alpha_a = alpha_b
            beta_a = beta_b
            x = x_next
            v = v_next
            dv = dv_next
            x_dot = x_next_dot
            v_dot = v_next_dot

        # Back substitution (dv'_j = y_j - C'_j dv'_{j+1}), bottom to top, with v1' = v0' + dv',
        # x1' = x0' + h v1'; the top particle, x1' = top', v1' = (top' - x0_top') / h; the tie force.
        dv_dot = y_prev
        for i in range(last):
            j = last - i
            if j < last:
                dv_dot = vsub(lane_y[base + j], mul_vec(lane_c[base + j], dv_dot))
            v1_dot = vadd(tgather3(particle_qd_dot, starts, j), dv_dot)
            tscatter3(particle_qd_out_dot, starts, j, real, v1_dot)
            tscatter3(particle_q_out_dot, starts, j, real, vadd(tgather3(particle_q_dot, starts, j), scale(h, v1_dot)))
        tscatter3(particle_q_out_dot, starts, 0, real, top_dot)
        tscatter3(particle_qd_out_dot, starts, 0, real, scale(inv_dt, vsub(top_dot, x_top_dot)))
        x_last = gather_particle3(state_out.particle_q, starts, last)
        v_last = gather_particle3(state_out.particle_qd, starts, last)
        # F' = -k_t' (x_tie - x1) - k_t (x_tie' - x1') - k_dt' (v_tie - v1) - k_dt (v_tie' - v1')
        tscatter3(tie_force_dot, strings, 0, real, vsub(vsub(vsub(
            scale(neg(tie_stiffness_dot), vsub(tie_x, x_last)),
            scale(tie_stiffness, vsub(tie_x_dot, tgather3(particle_q_out_dot, starts, last)))),
            scale(tie_damping_dot, vsub(tie_v, v_last))),
            scale(tie_damping, vsub(tie_v_dot, tgather3(particle_qd_out_dot, starts, last)))))

    return integrate_string_implicit_tangent_lanes
