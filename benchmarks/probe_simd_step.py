"""Probe for issue 19, part 2: the whole one-launch printed-spring string step with ``K`` strings
per thread in lockstep (one SIMD lane per string), against the project's scalar kernel.

Run:  python benchmarks/probe_simd_step.py [--particles 50] [--strings 6 8 64] [--lanes 4 8]
          [--steps 200] [--repeats 9] [--no-avx512]

The laned kernel (``lane_step_kernel``) is ``string_step.integrate_string_implicit`` (every effect
on: gravity, internal friction, air drag, ground contact and friction; the tie on the last
particle) rewritten on lane vectors, structure of arrays: a position is a ``3 x K`` matrix (row
``i`` = component ``i`` of the ``K`` strings), a block ``9 x K``, a string constant a ``K``
vector. Strings have equal particle counts, so ``j == 1`` and "last row" are the same for every
lane (the loop peels them as the scalar kernel does); the per-lane branches become selects:
ground contact (``x_y < ground_height``: both sides computed, ``wp.where`` lane by lane), the
spring's ``max`` clamp and the taut flag. Every operation is written in the scalar kernel's
order and rounding (Warp's generated C++ is not contracted; its ``mat33 * mat33`` is a chain of
``fma``, reproduced with ``probe_simd_lanes.lane_fma``; ``x + 0`` terms that the scalar code
adds, e.g. the zero entries of ``f_ground``, are added here too), so each lane can give the
scalar kernel's bits.

Two styles of lane operations (``lane_step_kernel``): ``native``, each operation a Clang
``ext_vector_type`` snippet (``native_lane_ops``: one packed instruction whatever LLVM's SLP
vectorizer does), and ``warp``, Warp's own ``+``, ``-``, ``wp.cw_mul``, ``wp.cw_div`` on
``vector(K)`` (packing left to the SLP vectorizer). Only ``native`` must be bit-identical (the
probe fails otherwise): with Warp's default CPU flags (``-mllvm=-slp-recursion-max-depth=4``)
the ``warp`` style computed lane 1 wrongly here (other lanes exact; exact with
``-fno-slp-vectorize`` or without the depth flag, ``--lane-flags``; not diagnosed further:
an LLVM SLP vectorizer defect or undefined behaviour in the generated code); the probe prints
its agreement as measured.

It builds a ``StringModel`` of ``L`` strings of ``n`` particles (all effects on, varied
constants, some particles below the ground, most strings tied), checks the laned step against
``integrate_string_implicit_kernel(wp.float64, effects)`` after 1 and after ``--steps`` steps
(fails, exit 1, if ``native`` is not bit-identical), times both (thread CPU time of one launch replayed from a
CPU graph, median of ``--repeats``; ns per particle-step), and counts packed vs scalar
double instructions with ``objdump`` (``probe_simd_lanes``' helpers). Findings:
``docs/simd_probe.md``, "The whole step".
"""

import argparse
import functools
import glob
import os

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

from dmarionette.kernels.lane_ops import native_lane_ops  # noqa: E402 (moved to the package)
from dmarionette.kernels.string_step import integrate_string_implicit_kernel  # noqa: E402
from dmarionette.strings.model import StringEffects, StringModel, StringSpec  # noqa: E402

import probe_simd_lanes as probe  # noqa: E402  (this folder is on sys.path when run as a script)
from probe_simd_lanes import (  # noqa: E402
    cost, forward_instructions, from_lanes, innermost_loop, instruction_counts, lane_fma, to_lanes)

LANE_FLAGS = None  # --lane-flags: compiler flags of the laned kernel's module (None: Warp's)
STYLES = ("native", "warp")  # only "native" must be bit-identical (see main)
EFFECTS = StringEffects()  # every effect on, printed springs
f64 = wp.float64


# --- the laned step ------------------------------------------------------------------------------

@functools.cache
def lane_step_kernel(lanes: int, style: str = "native"):
    """``integrate_string_implicit`` for ``lanes`` strings per thread (module doc). ``style``:
    the lane operations as Warp's (``"warp"``: ``+``, ``-``, ``wp.cw_mul``, ``wp.cw_div`` on
    ``vector(K)``, ``sqrt``, ``max``, ``where`` in unrolled loops over the lanes; packing is
    left to LLVM's SLP vectorizer) or as native snippets (``"native"``, ``native_lane_ops``)."""
    lane = wp.types.vector(lanes, f64)
    lvec = wp.types.matrix((3, lanes), f64)
    lmat = wp.types.matrix((9, lanes), f64)
    LANES, NATIVE = lanes, style == "native"
    fma = lane_fma(lanes)
    nat = native_lane_ops(lanes)

    @wp.func
    def ladd(a: lane, b: lane):
        if wp.static(NATIVE):
            return nat.add(a, b)
        return a + b

    @wp.func
    def lsub(a: lane, b: lane):
        if wp.static(NATIVE):
            return nat.sub(a, b)
        return a - b

    @wp.func
    def lmul(a: lane, b: lane):
        if wp.static(NATIVE):
            return nat.mul(a, b)
        return wp.cw_mul(a, b)

    @wp.func
    def ldiv(a: lane, b: lane):
        if wp.static(NATIVE):
            return nat.div(a, b)
        return wp.cw_div(a, b)

    @wp.func
    def lneg(a: lane):
        """``-a`` of a float as Warp computes it (``0 - a``: ``-(+0) = +0``), lane by lane."""
        return lsub(lane(f64(0.0)), a)

    @wp.func
    def lsqrt(a: lane):
        if wp.static(NATIVE):
            return nat.sqrt(a)
        r = lane()
        for k in range(LANES):
            r[k] = wp.sqrt(a[k])
        return r

    @wp.func
    def lmax(a: lane, b: lane):
        if wp.static(NATIVE):
            return nat.max(a, b)
        r = lane()
        for k in range(LANES):
            r[k] = wp.max(a[k], b[k])
        return r

    @wp.func
    def lselect_less(x: lane, y: lane, a: lane, b: lane):
        """``a`` where ``x < y``, else ``b``, lane by lane."""
        if wp.static(NATIVE):
            return nat.where_less(x, y, a, b)
        r = lane()
        for k in range(LANES):
            r[k] = wp.where(x[k] < y[k], a[k], b[k])
        return r

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
        """``s v`` (a scalar per lane times a 3-vector)."""
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
    def lspring(x_a: lvec, x_b: lvec, stiffness: lane, rest_length: lane):
        """``string_spring.compute_string_spring_printed``: force on ``a`` and ``K_aa``."""
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

    @wp.func
    def lrow(
        j: int, is_last: bool, x: lvec, v: lvec, v_prev: lvec, v_next: lvec, mass: lane,
        f_prev: lvec, k_prev: lmat, f_next: lvec, k_next: lmat, top_dx: lvec, top_dv: lvec,
        friction: lane, air_drag: lane, ground_stiffness: lane, ground_absorption: lane, ground_friction: lane,
        tie_stiffness: lane, tie_damping: lane, tie_x: lvec, tie_v: lvec, gravity: wp.vec3d,
        ground_height: f64, dt: f64,
    ):
        """``string_system.compute_string_system_row`` with every effect on, on lanes."""
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
        # internal friction (D = -k_f I per segment)
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
        # gravity, air drag
        for i in range(3):
            force[i] = ladd(force[i], lmul(mass, lane(gravity[i])))
        neg_air = lneg(air_drag)
        force = vadd(force, lscale(neg_air, v))
        d_xz = ladd(d_xz, neg_air)
        d_y = d_xz
        # ground contact and friction: both sides on every lane, then a select
        gh = lane(ground_height)
        y = x[1]
        f_gy = lsub(lmul(ground_stiffness, lsub(gh, y)), lmul(ground_absorption, v[1]))
        force_x = lselect_less(y, gh, ladd(force[0], zero), force[0])
        force_y = lselect_less(y, gh, ladd(force[1], f_gy), force[1])
        force_z = lselect_less(y, gh, ladd(force[2], zero), force[2])
        k_y = lselect_less(y, gh, lneg(ground_stiffness), k_y)
        d_y = lselect_less(y, gh, ladd(d_y, lneg(ground_absorption)), d_y)
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
    def lforward_row(
        p: int, j: int, is_last: bool, x: lvec, v: lvec, v_prev: lvec, f_prev: lvec, k_prev: lmat,
        upper_prev: lmat, d_prev: lvec, c_prev: lmat,
        particle_q: wp.array(dtype=lvec), particle_qd: wp.array(dtype=lvec), particle_mass: wp.array(dtype=lane),
        stiffness: lane, rest_length: lane, top_dx: lvec, top_dv: lvec, friction: lane, air_drag: lane,
        ground_stiffness: lane, ground_absorption: lane, ground_friction: lane, tie_stiffness: lane,
        tie_damping: lane, tie_x: lvec, tie_v: lvec, gravity: wp.vec3d, ground_height: f64, dt: f64,
        scratch_c: wp.array(dtype=lmat), scratch_d: wp.array(dtype=lvec),
    ):
        """``string_step``'s ``compute_forward_row`` on lanes."""
        x_next = x
        v_next = lvec()
        f_next = lvec()
        k_next = lmat()
        if not is_last:
            x_next = particle_q[p + 1]
            v_next = particle_qd[p + 1]
            f_next, k_next = lspring(x, x_next, stiffness, rest_length)
        diag, upper, rhs = lrow(
            j, is_last, x, v, v_prev, v_next, particle_mass[p], f_prev, k_prev, f_next, k_next, top_dx, top_dv,
            friction, air_drag, ground_stiffness, ground_absorption, ground_friction, tie_stiffness, tie_damping,
            tie_x, tie_v, gravity, ground_height, dt)
        c = lmat()
        d = lvec()
        if j == 1:
            inv = linverse(diag)
            c = lmatmul(inv, upper)
            d = lmul_vec(inv, rhs)
        else:
            inv = linverse(msub(diag, ltmatmul(upper_prev, c_prev)))
            c = lmatmul(inv, upper)
            d = lmul_vec(inv, vsub(rhs, ltmul_vec(upper_prev, d_prev)))
        scratch_c[p] = c
        scratch_d[p] = d
        return c, d, upper, x_next, v_next, v, f_next, k_next

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_lanes(
        # Model (per group of K strings, n particles each):
        particle_count: int,
        particle_mass: wp.array(dtype=lane),
        string_stiffness: wp.array(dtype=lane),
        string_rest_length: wp.array(dtype=lane),
        string_internal_friction: wp.array(dtype=lane),
        string_air_drag: wp.array(dtype=lane),
        string_ground_stiffness: wp.array(dtype=lane),
        string_ground_absorption: wp.array(dtype=lane),
        string_ground_friction: wp.array(dtype=lane),
        string_tie_stiffness: wp.array(dtype=lane),
        string_tie_damping: wp.array(dtype=lane),
        string_tied: wp.array(dtype=lane),
        string_taut_distance: wp.array(dtype=lane),
        gravity: wp.vec3d,
        ground_height: f64,
        # State in:
        particle_q: wp.array(dtype=lvec),
        particle_qd: wp.array(dtype=lvec),
        # Control:
        top_q: wp.array(dtype=lvec),
        tie_q: wp.array(dtype=lvec),
        tie_qd: wp.array(dtype=lvec),
        dt: f64,
        # State out:
        scratch_c: wp.array(dtype=lmat),
        scratch_d: wp.array(dtype=lvec),
        particle_dv: wp.array(dtype=lvec),
        particle_q_out: wp.array(dtype=lvec),
        particle_qd_out: wp.array(dtype=lvec),
        tie_force: wp.array(dtype=lvec),
        string_taut: wp.array(dtype=lane),
    ):
        s = wp.tid()
        start = s * particle_count
        last = start + particle_count - 1
        stiffness = string_stiffness[s]
        rest_length = string_rest_length[s]
        friction = string_internal_friction[s]
        air_drag = string_air_drag[s]
        ground_stiffness = string_ground_stiffness[s]
        ground_absorption = string_ground_absorption[s]
        ground_friction = string_ground_friction[s]
        tied = string_tied[s]
        tie_stiffness = lmul(tied, string_tie_stiffness[s])
        tie_damping = lmul(tied, string_tie_damping[s])
        tie_x = tie_q[s]
        tie_v = tie_qd[s]
        top = top_q[s]
        hl = lane(dt)
        top_dx = vsub(top, particle_q[start])
        top_dv = lvec()
        for i in range(3):
            top_dv[i] = lsub(ldiv(top_dx[i], hl), particle_qd[start][i])

        x = particle_q[start + 1]
        f_prev, k_prev = lspring(particle_q[start], x, stiffness, rest_length)
        c, d, upper, x_next, v_next, v, f_next, k_next = lforward_row(
            start + 1, 1, False, x, particle_qd[start + 1], particle_qd[start], f_prev, k_prev,
            lmat(), lvec(), lmat(), particle_q, particle_qd, particle_mass, stiffness, rest_length,
            top_dx, top_dv, friction, air_drag, ground_stiffness, ground_absorption, ground_friction,
            tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt, scratch_c, scratch_d)
        for p in range(start + 2, last):
            c, d, upper, x_next, v_next, v, f_next, k_next = lforward_row(
                p, 2, False, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q, particle_qd, particle_mass,
                stiffness, rest_length, top_dx, top_dv, friction, air_drag, ground_stiffness, ground_absorption,
                ground_friction, tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt,
                scratch_c, scratch_d)
        c, d, upper, x_next, v_next, v, f_next, k_next = lforward_row(
            last, 2, True, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q, particle_qd, particle_mass,
            stiffness, rest_length, top_dx, top_dv, friction, air_drag, ground_stiffness, ground_absorption,
            ground_friction, tie_stiffness, tie_damping, tie_x, tie_v, gravity, ground_height, dt,
            scratch_c, scratch_d)

        dv = d
        for i in range(last - start):
            p = last - i
            if p < last:
                dv = vsub(scratch_d[p], lmul_vec(scratch_c[p], dv))
            particle_dv[p] = dv
            v1 = vadd(particle_qd[p], dv)
            particle_qd_out[p] = v1
            particle_q_out[p] = vadd(particle_q[p], lscale(hl, v1))
        particle_dv[start] = lvec()
        q0 = particle_q[start]
        qd0 = lvec()
        for i in range(3):
            qd0[i] = ldiv(lsub(top[i], q0[i]), hl)
        particle_qd_out[start] = qd0
        particle_q_out[start] = top
        x_last = particle_q_out[last]
        tie_force[s] = vsub(lscale(lneg(tie_stiffness), vsub(tie_x, x_last)),
                            lscale(tie_damping, vsub(tie_v, particle_qd_out[last])))
        e = vsub(x_last, top)
        length = lsqrt(lsum3(e[0], e[1], e[2], e[0], e[1], e[2]))
        string_taut[s] = lselect_less(string_taut_distance[s], length, lane(f64(1.0)), lane(f64(0.0)))

    if LANE_FLAGS is not None:  # this module only (the scalar kernel keeps Warp's flags)
        integrate_string_lanes.module.options["cpu_compiler_flags"] = LANE_FLAGS
    return integrate_string_lanes


# --- a model, its laned copy, the two steps -----------------------------------------------------

GROUND_HEIGHT = 0.45


def make_model(strings: int, particles: int, seed: int = 19) -> StringModel:
    """``strings`` strings of ``particles`` particles, every effect on: tops at y = 1, bottoms at
    y = 0.2-0.45 (below the ground at 0.45 for most: particles in contact), varied constants, three
    in four tied (to points near their bottoms)."""
    rng = np.random.default_rng(seed)
    specs = []
    for s in range(strings):
        top = (0.1 * s, 1.0, 0.05 * (s % 3))
        bottom = (0.1 * s + rng.uniform(-0.3, 0.3), rng.uniform(0.2, 0.45), rng.uniform(-0.2, 0.2))
        span = float(np.linalg.norm(np.subtract(top, bottom)))
        tied = s % 4 != 3
        specs.append(StringSpec(
            name=f"s{s}", top=top, bottom=bottom, length=span * rng.uniform(0.97, 1.05), particle_count=particles,
            mass=rng.uniform(0.001, 0.004), load_mass=0.0, stiffness=rng.uniform(300.0, 900.0),
            internal_friction=rng.uniform(0.2, 0.8), air_drag=rng.uniform(0.005, 0.02),
            ground_stiffness=rng.uniform(1000.0, 3000.0), ground_absorption=rng.uniform(2.0, 8.0),
            ground_friction=rng.uniform(1.0, 3.0), tied=tied,
            tie_point=tuple(np.add(bottom, rng.uniform(-0.02, 0.02, 3))) if tied else None,
            tie_stiffness=rng.uniform(200.0, 400.0), tie_damping=rng.uniform(2.0, 4.0)))
    return StringModel(specs, effects=EFFECTS, gravity=(0.0, -9.81, 0.0), ground_height=GROUND_HEIGHT)


class ScalarStep:
    """The project's one-launch step (``integrate_string_implicit``) on ``model``, ping-ponging two
    states."""

    def __init__(self, model: StringModel, q: np.ndarray, qd: np.ndarray, dt: float):
        self.model, self.dt = model, dt
        self.kernel = integrate_string_implicit_kernel(wp.float64, EFFECTS.as_tuple())
        self.states = [model.state(q, qd), model.state(q, qd)]
        self.control = model.control()
        n = model.particle_count
        self.scratch = [wp.zeros(1, dtype=wp.mat33d), wp.zeros(n, dtype=wp.mat33d), wp.zeros(n, dtype=wp.vec3d),
                        wp.zeros(n, dtype=wp.vec3d)]

    def launch(self, flip: bool = False):
        m, (a, b) = self.model, self.states
        c = self.control
        wp.launch(self.kernel, dim=m.string_count, inputs=[
            m.string_start, m.particle_mass, m.string_stiffness, m.string_rest_length,
            m.string_internal_friction, m.string_air_drag, m.string_ground_stiffness, m.string_ground_absorption,
            m.string_ground_friction, m.string_tie_stiffness, m.string_tie_damping, m.string_tied,
            m.string_taut_distance, m.gravity, m.ground_height, a.particle_q, a.particle_qd,
            c.top_q, c.tie_q, c.tie_qd, wp.float64(self.dt)],
            outputs=[*self.scratch, b.particle_q, b.particle_qd, b.tie_force, b.string_taut])
        if flip:
            self.states.reverse()

    def result(self):
        """``(q, qd, tie_force, taut)`` of the last step, ``(L, n, 3)``, ``(L, n, 3)``, ``(L, 3)``, ``(L,)``."""
        s, (L, n) = self.states[0], (self.model.string_count, int(self.model.string_particle_count[0]))
        return (s.particle_q.numpy().reshape(L, n, 3), s.particle_qd.numpy().reshape(L, n, 3),
                s.tie_force.numpy(), s.string_taut.numpy().astype(np.float64))


class LaneStep:
    """``lane_step_kernel(K)`` on the same model and state; strings beyond ``L`` are padding
    (copies of the last string), not counted."""

    def __init__(self, model: StringModel, q: np.ndarray, qd: np.ndarray, dt: float, lanes: int,
                 style: str = "native"):
        self.model, self.dt, self.lanes = model, dt, lanes
        L, n = model.string_count, int(model.string_particle_count[0])
        self.L, self.n, self.groups = L, n, -(-L // lanes)
        self.kernel = lane_step_kernel(lanes, style)
        lane = wp.types.vector(lanes, f64)
        lvec, lmat = wp.types.matrix((3, lanes), f64), wp.types.matrix((9, lanes), f64)
        self.lvec, self.lmat, self.lane = lvec, lmat, lane

        def strings(a):  # (L, ...) -> padded with copies of the last string
            a = np.asarray(a, dtype=np.float64)
            return np.concatenate([a, np.repeat(a[-1:], self.groups * lanes - L, axis=0)])

        def per_string(name):  # (L,) -> (groups,) lane vectors
            return wp.array(strings(getattr(model, name).numpy()).reshape(self.groups, lanes), dtype=lane)

        def particles(x):  # (L, n, 3) -> (groups * n,) of 3 x K
            return wp.array(to_lanes(strings(x), lanes, 0.0), dtype=lvec)

        def points(x):  # (L, 3) -> (groups,) of 3 x K
            return particles(np.asarray(x)[:, None, :])

        self.constants = [per_string(name) for name in (
            "string_stiffness", "string_rest_length", "string_internal_friction", "string_air_drag",
            "string_ground_stiffness", "string_ground_absorption", "string_ground_friction",
            "string_tie_stiffness", "string_tie_damping", "string_tied", "string_taut_distance")]
        mass = strings(model.particle_mass.numpy().reshape(L, n))
        self.mass = wp.array(np.ascontiguousarray(mass.reshape(self.groups, lanes, n).transpose(0, 2, 1))
                             .reshape(-1, lanes), dtype=lane)
        c = model.control()
        self.control = [points(c.top_q.numpy()), points(c.tie_q.numpy()), points(c.tie_qd.numpy())]
        self.states = [[particles(q.reshape(L, n, 3)), particles(qd.reshape(L, n, 3))] for _ in range(2)]
        count = self.groups * n
        self.scratch = [wp.zeros(count, dtype=lmat), wp.zeros(count, dtype=lvec), wp.zeros(count, dtype=lvec)]
        self.outputs = [wp.zeros(self.groups, dtype=lvec), wp.zeros(self.groups, dtype=lane)]
        self.particles, self.points = particles, points

    def launch(self, flip: bool = False):
        m, (a, b) = self.model, self.states
        wp.launch(self.kernel, dim=self.groups, inputs=[
            self.n, self.mass, *self.constants, m.gravity, m.ground_height, a[0], a[1], *self.control,
            wp.float64(self.dt)], outputs=[*self.scratch, b[0], b[1], *self.outputs])
        if flip:
            self.states.reverse()

    def result(self):
        q, qd = (from_lanes(x.numpy(), self.L, self.n, self.lanes) for x in self.states[0])
        tie = from_lanes(self.outputs[0].numpy(), self.L, 1, self.lanes)[:, 0]
        taut = self.outputs[1].numpy().reshape(-1)[:self.L]
        return q, qd, tie, taut


def initial_state(model: StringModel, seed: int = 23):
    """The straight strings with random velocities (|v| up to 0.5 m/s): friction, drag and
    ground damping all act from the first step."""
    q = model.initial_positions()
    qd = np.random.default_rng(seed).uniform(-0.5, 0.5, q.shape)
    return q, qd


def run_steps(step, steps: int):
    for _ in range(steps):
        step.launch(flip=True)
    return step.result()


def compare(a, b):
    """``(bit-identical count, total, max |a - b| / max |a|)`` over ``q, qd, tie_force, taut``
    (per array, the largest; ``inf`` where one side is not finite)."""
    same = total = 0
    worst = 0.0
    for x, y in zip(a, b):
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        same += int(np.count_nonzero(x.view(np.int64) == y.view(np.int64)))
        total += x.size
        scale = np.abs(x).max() or 1.0
        diff = np.abs(x - y)
        diff[~np.isfinite(diff)] = np.inf  # a NaN or infinity on one side counts as infinitely far
        worst = max(worst, float(diff.max() / scale))
    return same, total, worst


def kernel_object(kernel) -> str:
    """The object file of ``kernel``'s module as loaded now: its cache directory is named by the
    module's identifier, which depends on its compiler flags (``probe_simd_lanes.kernel_object``
    assumes one object per module name; with ``--lane-flags`` there are two)."""
    module = kernel.module
    hits = glob.glob(os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim=1), "*.o"))
    if len(hits) != 1:
        raise RuntimeError(f"expected one object for module {module.name!r}, found {hits}")
    return hits[0]


probe.kernel_object = kernel_object  # forward_instructions looks it up there


# --- main ---------------------------------------------------------------------------------------

def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50, help="particles per string")
    parser.add_argument("--strings", type=int, nargs="+", default=[6, 8, 64])
    parser.add_argument("--lanes", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--steps", type=int, default=200, help="steps of the long agreement check")
    parser.add_argument("--dt", type=float, default=1e-3)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--no-avx512", action="store_true",
                        help="compile for the host CPU without AVX-512 (an AVX2/FMA machine)")
    parser.add_argument("--lane-flags", default=None,
                        help="CPU compiler flags of the laned kernel only (default: Warp's, as the scalar kernel)")
    args = parser.parse_args()
    if args.no_avx512:
        wp.config.cpu_compiler_flags += " -target-feature -avx512f"
    global LANE_FLAGS
    LANE_FLAGS = args.lane_flags
    if LANE_FLAGS is not None and args.no_avx512:
        LANE_FLAGS += " -target-feature -avx512f"
    wp.init()
    print(f"CPU compiler flags: {wp.config.cpu_compiler_flags!r}; laned kernel: {LANE_FLAGS or 'the same'!r}\n")

    failures = []
    print(f"## Agreement with integrate_string_implicit (float64, {args.particles} particles, dt {args.dt})\n")
    print("| strings | lanes | steps | below ground at the start | bit-identical (q, qd, tie force, taut)"
          " | max rel. difference |")
    print("|---:|---:|---:|---:|---:|---:|")
    for strings in args.strings:
        model = make_model(strings, args.particles)
        q, qd = initial_state(model)
        below = int(np.count_nonzero(q[:, 1] < GROUND_HEIGHT))
        for steps in (1, args.steps):
            ref = run_steps(ScalarStep(model, q, qd, args.dt), steps)
            if not np.all(np.isfinite(ref[0])):
                failures.append(f"scalar step not finite after {steps} steps")
            for k in args.lanes:
                for style in STYLES:
                    same, total, worst = compare(ref, run_steps(LaneStep(model, q, qd, args.dt, k, style), steps))
                    print(f"| {strings} | {k} {style} | {steps} | {below}/{q.shape[0]} | {same}/{total}"
                          f" | {worst:.1e} |")
                    if same != total and style == "native":
                        failures.append(f"lanes {k} {style}, {strings} strings, {steps} steps:"
                                        f" {same}/{total} bit-identical")

    print(f"\n## Time: thread CPU, median of {args.repeats} replays, ns per particle-step\n")
    print("| strings | scalar | " + " | ".join(f"lanes {k} {style}" for k in args.lanes for style in STYLES) + " |")
    print("|---:|---:|" + "---:|" * (len(args.lanes) * len(STYLES)))
    for strings in args.strings:
        model = make_model(strings, args.particles)
        q, qd = initial_state(model)
        steps = [ScalarStep(model, q, qd, args.dt)] + [LaneStep(model, q, qd, args.dt, k, style)
                                                        for k in args.lanes for style in STYLES]
        count = max(50, 1_000_000 // (strings * args.particles))
        ns = [cost(s.launch, count, args.repeats) * 1e9 / (strings * args.particles) for s in steps]
        print(f"| {strings} | " + " | ".join(f"{v:.1f}" for v in ns) + " |")

    print("\n## Instructions in each kernel's compiled forward function (objdump -d, static counts)\n")
    print("Whole function, then its largest innermost loop (the forward sweep's middle rows: spring, row,"
          " elimination of one particle of K strings), and that loop per particle (/ K).\n")
    print("| kernel | part | all | packed double xmm / ymm / zmm | scalar double | moves |")
    print("|---|---|---:|---:|---:|---:|")
    kernels = [("scalar (integrate_string_implicit)", integrate_string_implicit_kernel(wp.float64, EFFECTS.as_tuple()),
                1)] + [(f"lanes {k} {style}", lane_step_kernel(k, style), k)
                     for k in args.lanes for style in STYLES]
    for name, kernel, k in kernels:
        whole = forward_instructions(kernel)
        loop = innermost_loop(whole)
        for part, c, div in (("function", instruction_counts(whole), 1), ("loop", instruction_counts(loop), 1),
                             ("loop / K", instruction_counts(loop), k)):
            if part == "loop / K" and k == 1:
                continue
            print(f"| {name} | {part} | {c['all'] / div:.0f} | {c['packed xmm'] / div:.0f}"
                  f" / {c['packed ymm'] / div:.0f} / {c['packed zmm'] / div:.0f} | {c['scalar'] / div:.0f}"
                  f" | {c['moves'] / div:.0f} |")
    for failure in failures:
        print(f"FAILED: {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
