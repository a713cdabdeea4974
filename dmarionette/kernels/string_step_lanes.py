"""The plain implicit string step with ``K`` strings per thread, one SIMD lane per string (issue 19).

``integrate_string_lanes`` is ``string_step.integrate_string_implicit`` (the printed-spring step
in one launch) rewritten on lane vectors: one thread steps a *group* of ``K`` strings of equal
particle count in lockstep, so the peeled rows (``j == 1``, the last row) are the same for every
lane, and the per-lane branches become selects (ground contact ``x_y < ground_height``: both
sides computed, then a blend; the spring's ``max`` clamp; the taut flag). Every operation is the
scalar kernel's, in its order and rounding (``lane_ops``: one packed Clang vector instruction per
lane operation; Warp's ``mat33 * mat33`` is a chain of ``fma``, reproduced; the ``x + 0`` terms
the scalar code adds are added here too), so each lane gives the scalar kernel's bits
(``tests/strings/test_string_step_lanes.py``). Measured (``docs/lanes_status.md``).

Layout: the simulator's own arrays, read and written in place (a particle's ``vec3d`` per
particle, strings contiguous via ``string_start``): a row's positions of the ``K`` strings are
gathered into a ``3 x K`` matrix (row ``i`` = component ``i`` of the ``K`` strings), a block is
``9 x K``, a string constant a ``K`` vector. The group table (``lane_groups``): the ``K`` string
indices of each group; a group with fewer than ``K`` strings repeats one of its strings in its
padding lanes, which compute but write nothing.

What it writes: as ``integrate_string_implicit`` for a plain step, ``particle_q_out``,
``particle_qd_out``, ``tie_force``, ``string_taut`` and ``particle_dv``. Not the workspace's
``scratch_c``/``scratch_d`` (``C'_j``, ``d'_j`` of the solve): only the step's own back
substitution reads them on a plain step (the adjoint reads the keep kernel's, in a taped step's
workspace), so they go to laned scratch arrays of the group plan (``lane_c``, ``lane_d``: one
``9 x K``/``3 x K`` entry per row of a group, group ``g``'s rows from ``group_base[g]``).

Built with ``keep`` (a taped step's), it also stores the pivot inverses (``lane_inverse``), and
its ``lane_c`` is the taped step's own: the laned hand-written adjoint
(``string_step_adjoint_lanes``) reads both, as the scalar adjoint reads the scalar keep kernel's.
Float64 and CPU only (the snippets are Clang C++), printed springs (the tension-only springs'
active-set solve needs ``A`` stored). On by default where it applies (``SolverStringImplicit.lanes``).
"""

import functools

from types import SimpleNamespace

import numpy as np
import warp as wp

from .lane_ops import native_lane_memory, native_lane_ops
from .string_model_arrays import string_model_arrays_type

f64 = wp.float64

LANES = 4  # strings per thread: 4 doubles = one AVX2 register (docs/simd_probe.md: 32 ns vs 83 for 6 x 50)


def lane_groups(string_start: np.ndarray, lanes: int = LANES):
    """The group table of strings with start offsets ``string_start`` (``L + 1``): strings of equal
    particle count, in index order, ``lanes`` to a group; the last group of a count padded with
    copies of its first string. Returns ``(group_string (G, lanes) int32, group_real (G,) int32,
    group_base (G,) int32, rows)``: each group's string indices, its real lane count, the offset
    of its rows in the laned scratch, and the scratch's length."""
    counts = np.diff(np.asarray(string_start, dtype=np.int64))
    group_string, group_real, group_base, rows = [], [], [], 0
    for n in sorted(set(counts.tolist())):
        members = np.flatnonzero(counts == n)
        for i in range(0, len(members), lanes):
            real = members[i:i + lanes]
            group_string.append(np.concatenate([real, np.repeat(real[:1], lanes - len(real))]))
            group_real.append(len(real))
            group_base.append(rows)
            rows += int(n)
    return (np.asarray(group_string, dtype=np.int32).reshape(-1, lanes), np.asarray(group_real, dtype=np.int32),
            np.asarray(group_base, dtype=np.int32), rows)


@functools.cache
def lane_types(lanes: int = LANES):
    """``(lane, ivec, lvec, lmat)``: a float64 per lane, a string or particle index per lane, a
    ``vec3d`` per lane (``3 x K``), a ``mat33d`` per lane (``9 x K``, row ``3 i + j`` = entry ``(i, j)``)."""
    return (wp.types.vector(lanes, f64), wp.types.vector(lanes, wp.int32), wp.types.matrix((3, lanes), f64),
            wp.types.matrix((9, lanes), f64))


@functools.cache
def lane_step_functions(lanes: int = LANES) -> SimpleNamespace:
    """The laned step's ``@wp.func`` helpers for ``lanes`` strings per thread, shared by the laned
    step (``integrate_string_lanes``) and its adjoint (``string_step_adjoint_lanes``): gathers from
    and scatters to the simulator's arrays (``lane_ops.native_lane_memory``; a scatter writes the
    real lanes only), a group's strings and their first particles (``compute_lane_group``) and
    constants (``gather_string_constants``, also for the tangent, ``string_step_tangent_lanes``), the scalar
    kernel's vector and matrix operations on lanes in its order and rounding, and the printed spring
    (``compute_lane_spring``)."""
    LANES_ = lanes
    lane, ivec, lvec, lmat = lane_types(lanes)
    vec3 = wp.vec3d
    nat = native_lane_ops(lanes)
    ladd, lsub, lmul, ldiv, lsqrt, lmax, fma = nat.add, nat.sub, nat.mul, nat.div, nat.sqrt, nat.max, nat.fma
    mem = native_lane_memory(lanes)
    StringModelArrays = string_model_arrays_type(f64)

    # --- gathers from and scatters to the simulator's arrays (lane_ops.native_lane_memory) ------

    @wp.func
    def gather_string(a: wp.array(dtype=f64), strings: ivec):
        return mem.gather(a, strings, 0)

    @wp.func
    def gather_string3(a: wp.array(dtype=vec3), strings: ivec):
        return mem.gather3(a, strings, 0)

    @wp.func
    def gather_particle(a: wp.array(dtype=f64), starts: ivec, j: int):
        return mem.gather(a, starts, j)

    @wp.func
    def gather_particle3(a: wp.array(dtype=vec3), starts: ivec, j: int):
        return mem.gather3(a, starts, j)

    @wp.func
    def scatter3(a: wp.array(dtype=vec3), index: ivec, j: int, real: int, v: lvec):
        """``a[index[k] + j] = v[:, k]`` for the real lanes ``k < real``."""
        mem.scatter3(a, index, j, real, v)

    @wp.func
    def compute_lane_group(g: int, group_string: wp.array(dtype=ivec), group_real: wp.array(dtype=wp.int32),
                           group_base: wp.array(dtype=wp.int32), string_start: wp.array(dtype=wp.int32)):
        """Group ``g`` of the group table (``lane_groups``): its strings, how many of them are real,
        its first laned row, each string's first particle, and the particle count (every string of
        a group has as many)."""
        strings = group_string[g]
        starts = ivec()
        for k in range(LANES_):
            starts[k] = string_start[strings[k]]
        s0 = strings[0]
        return strings, group_real[g], group_base[g], starts, string_start[s0 + 1] - string_start[s0]

    @wp.func
    def gather_string_constants(strings: ivec, model: StringModelArrays):
        """The group's strings' ten constants, each a lane vector: ``k_s, d, k_f, k_air``, the ground's
        stiffness, absorption and friction, ``tied`` and the tie's ``k`` and ``k_d`` as stored (the
        step's ``k_t = tied k``, ``k_dt = tied k_d`` are the caller's)."""
        return (gather_string(model.string_stiffness, strings), gather_string(model.string_rest_length, strings),
                gather_string(model.string_internal_friction, strings), gather_string(model.string_air_drag, strings),
                gather_string(model.string_ground_stiffness, strings),
                gather_string(model.string_ground_absorption, strings),
                gather_string(model.string_ground_friction, strings), gather_string(model.string_tied, strings),
                gather_string(model.string_tie_stiffness, strings), gather_string(model.string_tie_damping, strings))

    # --- the scalar kernel's operations on lanes ----------------------------------------------

    @wp.func
    def lneg(a: lane):
        """``-a`` of a float as Warp computes it (``0 - a``: ``-(+0) = +0``), lane by lane."""
        return lsub(lane(f64(0.0)), a)

    @wp.func
    def vadd(a: lvec, b: lvec):
        r = lvec()
        for i in range(3):
            r[i] = ladd(a[i], b[i])
        return r

    @wp.func
    def vsub(a: lvec, b: lvec):
        r = lvec()
        for i in range(3):
            r[i] = lsub(a[i], b[i])
        return r

    @wp.func
    def madd(a: lmat, b: lmat):
        r = lmat()
        for e in range(9):
            r[e] = ladd(a[e], b[e])
        return r

    @wp.func
    def msub(a: lmat, b: lmat):
        r = lmat()
        for e in range(9):
            r[e] = lsub(a[e], b[e])
        return r

    @wp.func
    def lsum3(a0: lane, a1: lane, a2: lane, b0: lane, b1: lane, b2: lane):
        """``(a0 b0 + a1 b1) + a2 b2``, each operation rounded (``dot``, ``mat33 * vec3``)."""
        return ladd(ladd(lmul(a0, b0), lmul(a1, b1)), lmul(a2, b2))

    @wp.func
    def lscale(s: lane, v: lvec):
        r = lvec()
        for i in range(3):
            r[i] = lmul(s, v[i])
        return r

    @wp.func
    def ldot3(a0: lane, a1: lane, a2: lane, b0: lane, b1: lane, b2: lane):
        """As ``mat33 * mat33``: ``fma(a2, b2, fma(a1, b1, a0 b0))``."""
        return fma(a2, b2, fma(a1, b1, lmul(a0, b0)))

    @wp.func
    def lmatmul(a: lmat, b: lmat):
        r = lmat()
        for i in range(3):
            for j in range(3):
                r[3 * i + j] = ldot3(a[3 * i], a[3 * i + 1], a[3 * i + 2], b[j], b[3 + j], b[6 + j])
        return r

    @wp.func
    def ltmatmul(a: lmat, b: lmat):
        r = lmat()
        for i in range(3):
            for j in range(3):
                r[3 * i + j] = ldot3(a[i], a[3 + i], a[6 + i], b[j], b[3 + j], b[6 + j])
        return r

    @wp.func
    def lmul_vec(a: lmat, v: lvec):
        r = lvec()
        for i in range(3):
            r[i] = lsum3(a[3 * i], a[3 * i + 1], a[3 * i + 2], v[0], v[1], v[2])
        return r

    @wp.func
    def ltmul_vec(a: lmat, v: lvec):
        r = lvec()
        for i in range(3):
            r[i] = lsum3(a[i], a[3 + i], a[6 + i], v[0], v[1], v[2])
        return r

    @wp.func
    def lcofactor(a: lane, b: lane, c: lane, d: lane):
        return lsub(lmul(a, b), lmul(c, d))

    @wp.func
    def linverse(m: lmat):
        """``wp.inverse`` (cofactors, determinant ``row 0 . (row 1 x row 2)``, times ``1 / det``);
        no zero-determinant branch (the step's pivots are SPD)."""
        b = lmat()
        b[0] = lcofactor(m[4], m[8], m[5], m[7])
        b[3] = lcofactor(m[5], m[6], m[3], m[8])
        b[6] = lcofactor(m[3], m[7], m[4], m[6])
        b[1] = lcofactor(m[2], m[7], m[1], m[8])
        b[4] = lcofactor(m[0], m[8], m[2], m[6])
        b[7] = lcofactor(m[1], m[6], m[0], m[7])
        b[2] = lcofactor(m[1], m[5], m[2], m[4])
        b[5] = lcofactor(m[2], m[3], m[0], m[5])
        b[8] = lcofactor(m[0], m[4], m[1], m[3])
        rcp = ldiv(lane(f64(1.0)), lsum3(m[0], m[1], m[2], b[0], b[3], b[6]))
        r = lmat()
        for e in range(9):
            r[e] = lmul(b[e], rcp)
        return r

    @wp.func
    def compute_lane_spring(x_a: lvec, x_b: lvec, stiffness: lane, rest_length: lane):
        """``string_spring.compute_string_spring_printed``: the force on ``a`` and ``K_aa``."""
        e = vsub(x_a, x_b)
        length = lsqrt(lsum3(e[0], e[1], e[2], e[0], e[1], e[2]))
        u = lvec()
        for i in range(3):
            u[i] = ldiv(e[i], length)
        neg_k = lneg(stiffness)
        one = lane(f64(1.0))
        force = lscale(lmul(neg_k, lsub(length, rest_length)), u)
        geometric = lmax(lsub(one, ldiv(rest_length, length)), lane(f64(0.0)))
        w = lscale(lmul(neg_k, lsub(one, geometric)), u)
        kg = lmul(stiffness, geometric)
        zero = lane(f64(0.0))
        jac = lmat()
        for i in range(3):
            for j in range(3):
                if i == j:
                    jac[3 * i + j] = lsub(lmul(w[i], u[j]), kg)
                else:
                    jac[3 * i + j] = lsub(lmul(w[i], u[j]), zero)
        return force, jac

    return SimpleNamespace(
        gather_string=gather_string, gather_string3=gather_string3, gather_particle=gather_particle,
        gather_particle3=gather_particle3, scatter3=scatter3, compute_lane_group=compute_lane_group,
        gather_string_constants=gather_string_constants, lneg=lneg,
        vadd=vadd, vsub=vsub, madd=madd, msub=msub,
        lsum3=lsum3, lscale=lscale, lmatmul=lmatmul, ltmatmul=ltmatmul, lmul_vec=lmul_vec, ltmul_vec=ltmul_vec,
        linverse=linverse, compute_lane_spring=compute_lane_spring)


@functools.cache
def integrate_string_lanes_kernel(effects: tuple[bool, bool, bool, bool, bool], lanes: int = LANES,
                                  keep: bool = False):
    """Builds ``integrate_string_lanes`` (float64, printed springs) for an effect set
    ``(gravity, internal_friction, air_drag, ground_contact, ground_friction)`` (compile-time
    switches, ``StringEffects.as_tuple``) and ``lanes`` strings per thread.

    ``keep``: also keep the pivot inverses in ``lane_inverse`` (laned, as ``lane_c``), for the
    laned hand-written adjoint (``string_step_adjoint_lanes``), as ``string_step``'s ``keep``: a
    compile-time switch, the plain step stores nothing more."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    KEEP = keep
    LANES_ = lanes
    lane, ivec, lvec, lmat = lane_types(lanes)
    vec3 = wp.vec3d
    nat = native_lane_ops(lanes)
    ladd, lsub, lmul, ldiv, lsqrt, lselect_less = nat.add, nat.sub, nat.mul, nat.div, nat.sqrt, nat.where_less
    f = lane_step_functions(lanes)
    gather_string, gather_string3, gather_particle, gather_particle3, scatter3 = (
        f.gather_string, f.gather_string3, f.gather_particle, f.gather_particle3, f.scatter3)
    lneg, vadd, vsub, madd, msub, lsum3, lscale = f.lneg, f.vadd, f.vsub, f.madd, f.msub, f.lsum3, f.lscale
    lmatmul, ltmatmul, lmul_vec, ltmul_vec, linverse = f.lmatmul, f.ltmatmul, f.lmul_vec, f.ltmul_vec, f.linverse
    compute_lane_spring = f.compute_lane_spring
    compute_lane_group, gather_string_constants = f.compute_lane_group, f.gather_string_constants
    StringModelArrays = string_model_arrays_type(f64)

    @wp.func
    def compute_lane_system_row(
        j: int, is_last: bool, x: lvec, v: lvec, v_prev: lvec, v_next: lvec, mass: lane,
        f_prev: lvec, k_prev: lmat, f_next: lvec, k_next: lmat, top_dx: lvec, top_dv: lvec,
        friction: lane, air_drag: lane, ground_stiffness: lane, ground_absorption: lane, ground_friction: lane,
        tie_stiffness: lane, tie_damping: lane, tie_x: lvec, tie_v: lvec, gravity: vec3,
        ground_height: f64, dt: f64,
    ):
        """``string_system.compute_string_system_row`` on lanes (same effect switches)."""
        zero = lane(f64(0.0))
        hl = lane(dt)
        h2 = lane(dt * dt)
        d_xz = zero
        d_y = zero
        k_c = zero
        k_y = zero
        force = -f_prev  # a vector's negation is a true one (vec.h), unlike a float's
        stiff = k_prev
        upper = lmat()
        if not is_last:
            force = vsub(f_next, f_prev)
            stiff = madd(k_prev, k_next)
            for e in range(9):
                upper[e] = lmul(h2, k_next[e])
        w_prev = lscale(h2, vsub(v, v_prev))
        if j == 1:
            w_prev = vsub(lscale(h2, v), lscale(hl, top_dx))
        rhs_k = lmul_vec(k_prev, w_prev)
        if not is_last:
            rhs_k = vadd(rhs_k, lmul_vec(k_next, lscale(h2, vsub(v, v_next))))
        if wp.static(FRICTION):  # internal friction, D = -k_f I per segment
            neg_f = lneg(friction)
            force = vadd(force, lscale(neg_f, vsub(v, v_prev)))
            d_xz = ladd(d_xz, neg_f)
            if j == 1:
                rhs_k = vsub(rhs_k, lscale(hl, lscale(neg_f, top_dv)))
            if not is_last:
                force = vadd(force, lscale(neg_f, vsub(v, v_next)))
                d_xz = ladd(d_xz, neg_f)
                g = lmul(hl, neg_f)
                for e in range(9):
                    if e % 4 == 0:
                        upper[e] = ladd(upper[e], g)
                    else:
                        upper[e] = ladd(upper[e], zero)
        if wp.static(GRAVITY):
            for i in range(3):
                force[i] = ladd(force[i], lmul(mass, lane(gravity[i])))
        if wp.static(AIR):
            neg_air = lneg(air_drag)
            force = vadd(force, lscale(neg_air, v))
            d_xz = ladd(d_xz, neg_air)
        d_y = d_xz
        if wp.static(GROUND):  # both sides on every lane, then a select
            gh = lane(ground_height)
            y = x[1]
            f_gy = lsub(lmul(ground_stiffness, lsub(gh, y)), lmul(ground_absorption, v[1]))
            force_x = lselect_less(y, gh, ladd(force[0], zero), force[0])
            force_y = lselect_less(y, gh, ladd(force[1], f_gy), force[1])
            force_z = lselect_less(y, gh, ladd(force[2], zero), force[2])
            k_y = lselect_less(y, gh, lneg(ground_stiffness), k_y)
            d_y = lselect_less(y, gh, ladd(d_y, lneg(ground_absorption)), d_y)
            if wp.static(GROUND_FRICTION):
                neg_gf = lneg(ground_friction)
                force_x = lselect_less(y, gh, ladd(force_x, lmul(neg_gf, v[0])), force_x)
                force_y = lselect_less(y, gh, ladd(force_y, zero), force_y)
                force_z = lselect_less(y, gh, ladd(force_z, lmul(neg_gf, v[2])), force_z)
                d_xz = lselect_less(y, gh, ladd(d_xz, neg_gf), d_xz)
            force[0] = force_x
            force[1] = force_y
            force[2] = force_z
        if is_last:
            # the tie, eq. 2: f = -(-k (x_b - x) - k_d (v_b - v)), K = -k I, D = -k_d I
            f_body = vsub(lscale(lneg(tie_stiffness), vsub(tie_x, x)), lscale(tie_damping, vsub(tie_v, v)))
            force = vadd(force, -f_body)
            k_c = lneg(tie_stiffness)
            d_xz = ladd(d_xz, lneg(tie_damping))
            d_y = ladd(d_y, lneg(tie_damping))
        a_xz = lsub(lsub(mass, lmul(hl, d_xz)), lmul(h2, k_c))
        a_y = lsub(lsub(mass, lmul(hl, d_y)), lmul(h2, ladd(k_c, k_y)))
        neg_h2 = lneg(h2)
        diag = lmat()
        for e in range(9):
            diag[e] = lmul(neg_h2, stiff[e])
        diag[0] = ladd(diag[0], a_xz)
        diag[4] = ladd(diag[4], a_y)
        diag[8] = ladd(diag[8], a_xz)
        rhs = vadd(lscale(hl, force), rhs_k)
        rhs[0] = ladd(rhs[0], lmul(h2, lmul(k_c, v[0])))
        rhs[1] = ladd(rhs[1], lmul(h2, lmul(ladd(k_c, k_y), v[1])))
        rhs[2] = ladd(rhs[2], lmul(h2, lmul(k_c, v[2])))
        return diag, upper, rhs

    @wp.func
    def compute_lane_forward_row(
        j: int, first: bool, is_last: bool, starts: ivec, row: int, x: lvec, v: lvec, v_prev: lvec,
        f_prev: lvec, k_prev: lmat, upper_prev: lmat, d_prev: lvec, c_prev: lmat,
        particle_q: wp.array(dtype=vec3), particle_qd: wp.array(dtype=vec3), particle_mass: wp.array(dtype=f64),
        stiffness: lane, rest_length: lane, top_dx: lvec, top_dv: lvec, friction: lane, air_drag: lane,
        ground_stiffness: lane, ground_absorption: lane, ground_friction: lane, tie_stiffness: lane,
        tie_damping: lane, tie_x: lvec, tie_v: lvec, gravity: vec3, ground_height: f64, dt: f64,
        lane_inverse: wp.array(dtype=lmat), lane_c: wp.array(dtype=lmat), lane_d: wp.array(dtype=lvec),
    ):
        """``string_step``'s ``compute_forward_row`` for row ``j`` of the group's strings
        (``first``: ``j == 1``); ``C'_j``, ``d'_j`` (and with ``keep`` the pivot inverse) to the
        laned scratch at ``row``."""
        x_next = x
        v_next = lvec()
        f_next = lvec()
        k_next = lmat()
        if not is_last:
            x_next = gather_particle3(particle_q, starts, j + 1)
            v_next = gather_particle3(particle_qd, starts, j + 1)
            f_next, k_next = compute_lane_spring(x, x_next, stiffness, rest_length)
        jj = 2
        if first:
            jj = 1
        diag, upper, rhs = compute_lane_system_row(
            jj, is_last, x, v, v_prev, v_next, gather_particle(particle_mass, starts, j), f_prev, k_prev, f_next,
            k_next, top_dx, top_dv, friction, air_drag, ground_stiffness, ground_absorption, ground_friction,
            tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt)
        inv = lmat()
        c = lmat()
        d = lvec()
        if first:
            inv = linverse(diag)
            c = lmatmul(inv, upper)
            d = lmul_vec(inv, rhs)
        else:
            inv = linverse(msub(diag, ltmatmul(upper_prev, c_prev)))
            c = lmatmul(inv, upper)
            d = lmul_vec(inv, vsub(rhs, ltmul_vec(upper_prev, d_prev)))
        if wp.static(KEEP):
            lane_inverse[row] = inv
        lane_c[row] = c
        lane_d[row] = d
        return c, d, upper, x_next, v_next, v, f_next, k_next

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_lanes(
        # Model (the group table, ``lane_groups``, then the strings):
        group_string: wp.array(dtype=ivec),
        group_real: wp.array(dtype=wp.int32),
        group_base: wp.array(dtype=wp.int32),
        model: StringModelArrays,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Control:
        top_q: wp.array(dtype=vec3),
        tie_q: wp.array(dtype=vec3),
        tie_qd: wp.array(dtype=vec3),
        dt: f64,
        # State out (first the laned scratch: pivot inverses, only if built with ``keep``, C', d'):
        lane_inverse: wp.array(dtype=lmat),
        lane_c: wp.array(dtype=lmat),
        lane_d: wp.array(dtype=lvec),
        particle_dv: wp.array(dtype=vec3),
        particle_q_out: wp.array(dtype=vec3),
        particle_qd_out: wp.array(dtype=vec3),
        tie_force: wp.array(dtype=vec3),
        string_taut: wp.array(dtype=wp.int32),
    ):
        strings, real, base, starts, n = compute_lane_group(wp.tid(), group_string, group_real, group_base,
                                                            model.string_start)
        last = n - 1
        particle_mass = model.particle_mass
        gravity = model.gravity
        ground_height = model.ground_height
        # The strings' constants, read once.
        (stiffness, rest_length, friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tied,
         tie_stiffness_k, tie_damping_k) = gather_string_constants(strings, model)
        tie_stiffness = lmul(tied, tie_stiffness_k)
        tie_damping = lmul(tied, tie_damping_k)
        tie_x = gather_string3(tie_q, strings)
        tie_v = gather_string3(tie_qd, strings)
        top = gather_string3(top_q, strings)
        hl = lane(dt)
        q0 = gather_particle3(particle_q, starts, 0)
        qd0 = gather_particle3(particle_qd, starts, 0)
        # Motion of the kinematic top particle over the step.
        top_dx = vsub(top, q0)
        top_dv = lvec()
        for i in range(3):
            top_dv[i] = lsub(ldiv(top_dx[i], hl), qd0[i])

        # Forward sweep, the first and last rows peeled as in the scalar kernel.
        x = gather_particle3(particle_q, starts, 1)
        f_prev, k_prev = compute_lane_spring(q0, x, stiffness, rest_length)
        c, d, upper, x_next, v_next, v, f_next, k_next = compute_lane_forward_row(
            1, True, last == 1, starts, base + 1, x, gather_particle3(particle_qd, starts, 1), qd0, f_prev, k_prev,
            lmat(), lvec(), lmat(), particle_q, particle_qd, particle_mass, stiffness, rest_length,
            top_dx, top_dv, friction, air_drag, ground_stiffness, ground_absorption, ground_friction,
            tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt, lane_inverse, lane_c, lane_d)
        for j in range(2, last):
            c, d, upper, x_next, v_next, v, f_next, k_next = compute_lane_forward_row(
                j, False, False, starts, base + j, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q,
                particle_qd, particle_mass, stiffness, rest_length, top_dx, top_dv, friction, air_drag,
                ground_stiffness, ground_absorption, ground_friction, tie_stiffness, tie_damping, tie_x, tie_v,
                gravity, ground_height, dt, lane_inverse, lane_c, lane_d)
        if last > 1:
            c, d, upper, x_next, v_next, v, f_next, k_next = compute_lane_forward_row(
                last, False, True, starts, base + last, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q,
                particle_qd, particle_mass, stiffness, rest_length, top_dx, top_dv, friction, air_drag,
                ground_stiffness, ground_absorption, ground_friction, tie_stiffness, tie_damping, tie_x, tie_v,
                gravity, ground_height, dt, lane_inverse, lane_c, lane_d)

        # Back substitution and v1 = v0 + dv, x1 = x0 + h v1, upwards; real lanes written.
        dv = d
        x_last = lvec()
        v_last = lvec()
        for i in range(last):
            j = last - i
            if j < last:
                dv = vsub(lane_d[base + j], lmul_vec(lane_c[base + j], dv))
            scatter3(particle_dv, starts, j, real, dv)
            v1 = vadd(gather_particle3(particle_qd, starts, j), dv)
            x1 = vadd(gather_particle3(particle_q, starts, j), lscale(hl, v1))
            scatter3(particle_qd_out, starts, j, real, v1)
            scatter3(particle_q_out, starts, j, real, x1)
            if j == last:
                x_last = x1
                v_last = v1
        scatter3(particle_dv, starts, 0, real, lvec())
        # The top particle follows its attach point (string_integrate.integrate_string_particles).
        v_top = lvec()
        for i in range(3):
            v_top[i] = ldiv(lsub(top[i], q0[i]), hl)
        scatter3(particle_qd_out, starts, 0, real, v_top)
        scatter3(particle_q_out, starts, 0, real, top)
        # Tie force (eq. 2) and taut flag (string_integrate.compute_string_outputs).
        force = vsub(lscale(lneg(tie_stiffness), vsub(tie_x, x_last)), lscale(tie_damping, vsub(tie_v, v_last)))
        e = vsub(x_last, top)
        length = lsqrt(lsum3(e[0], e[1], e[2], e[0], e[1], e[2]))
        taut_distance = gather_string(model.string_taut_distance, strings)
        scatter3(tie_force, strings, 0, real, force)
        for k in range(LANES_):
            if k < real:
                taut = int(0)
                if length[k] > taut_distance[k]:
                    taut = 1
                string_taut[strings[k]] = taut

    return integrate_string_lanes
