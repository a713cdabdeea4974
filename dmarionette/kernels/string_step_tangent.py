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

Layout: one thread per string, ``dim = S``. The tangents have a leading direction axis (``(P,
particle_count)``, ``(P, string_count)`` of vec3; the constants ``(P, string_count, 10)`` in
:data:`CONSTANTS` order); the particles' (``x0'``, ``v0'``, ``x1'``, ``v1'``, ``m'``) may be stored
direction-minor instead (``tangent_directions.direction_minor``: the ``(particle_count, P)`` array's
transposed view, the same ``(P, particle_count)`` indexing for every other kernel), and the kernel
built with ``minor`` reads and writes a group of directions of one particle as contiguous lane
vectors (``grad.string_tangent`` picks it where every array has room for the launch's lane groups:
real directions, or the padding ``direction_minor`` allocates, which the padding lanes then write).
The kept factorisation is read where the forward left it: the scalar step's layout, or the laned
step's (``factor_lanes``: a string's lane of its group's ``9 x 4`` rows, no unpacking launch). First
a pass over the string's segments, once per step for all directions: each segment's spring parts
(``u, l, 1 / l, 1 - d/l, alpha, beta``), and with ``maps`` its part of ``b' - A' dv`` as a linear
map of the direction (``E``, ``C`` below); where the directions are in lanes, 4 consecutive segments
per lane vector (:func:`_segment_pass`, one body for both). Then one group of directions at a time
(the string's constants' tangents read once per group): the forward sweep row by row, ``x'``, ``v'``
of the next particle, the upper segment's part ``c`` and the substitution's ``y`` carried from row
to row in registers (``y`` also kept in ``particle_qd_out_dot``), then the back substitution bottom
to top, ``dv'`` carried, with ``v1'`` and ``x1'`` written as it goes. Each segment's part of a row
is computed once per direction and shared by its two rows (+c in the row above, -c in the row below,
exactly), the internal friction's terms of the segment folded into it; the other terms (mass, air
drag, ground, tie) are diagonal, each added to ``r`` on its own as a product of the direction with
primal coefficients of the row.

Directions in SIMD lanes (``lanes = 4`` or ``8``, float64 on the CPU, the default of
``grad.string_tangent`` from P = 2, in launches of 8, then 4, then 1, :func:`direction_chunks`; each
launch's ``directions`` a slice of the P, the first one computing the segment pass for the others):
the same body on ``tangent_directions``' values, each group one lane vector of directions, a tangent
scalar a lane vector and a tangent vector a ``3 x K`` lane matrix (Clang vector snippets: packed
AVX2 instructions; 8 lanes are two independent 4-wide halves per operation, no 512-bit instruction
seen), the primal values scalars as before; P is padded up to a multiple of ``K`` (the padding lanes
repeat the last direction and write nothing). The body is written with the namespace's functions
(``vadd``, ``vscl``, ``outer``, ...) rather than Warp's operators, so that both layouts share it;
each is the scalar operation it stands for, in the scalar kernel's order, so the laned tangent
agrees with the scalar one built with the same ``maps`` to rounding
(``tests/grad/test_string_step_tangent.py`` asserts 1e-13). Deviations from a literal derivative of
the forward's expressions (rounding only): ``/ h`` of the tangents is a product with ``1 / h``
(computed once); the segment pass's spring parts use products with ``1 / l`` (one division, not
``compute_spring_parts``' four); sums are regrouped (a segment's part once for its two rows, each
diagonal term's coefficients gathered, ``h^2 K - h k_f I`` as one product).

Cost (``PYTHONPATH=$PWD python benchmarks/bench_string_tangent.py --repeats 5 --clock cpu``, the
``strings`` scene's six strings of 50 particles, 1,000 steps, thread CPU time, 2-core machine under
load 2.3 from other work): a rollout of P = 1, 4, 12, 16 tangents costs 2.42, 3.29, 6.59, 7.63 laned
forward rollouts (``--no-lanes``, one direction at a time: 2.39, 5.75, 13.00, 16.78); with wall time
(the default clock) 2.47, 3.38, 6.67, 7.61, against 4.04, 5.55, 12.33, 15.54 before this layout
(commit f0b0766, run just before in the same session; 3.86-4.09, 5.44-5.97, 11.63-12.28, 15.09-15.59
in three earlier sessions). The issue's 1 + 0.5 P = 1.5, 3, 7, 9: met at P = 12 and 16, not at P =
1, 4. Where it goes (1,000 captured steps each, in laned forward rollouts of ~6.85 ms, load ~2.2):
the laned forward with ``keep`` 0.86; this kernel's fixed part 0.15 (the segment pass with the
spring parts, on lanes of segments; 0.26 one segment at a time, P = 1), 0.6 with the linear maps;
then each direction 1.33 (P = 1, scalar), 0.57 (a group of 4, spring tangents), 0.48 (groups of 8,
spring tangents), 0.44 (8 + 4, maps), 0.39 (groups of 8, maps); the upload of the per-step tangents
and the download of the tie forces' 0.05-0.35. Each change on its own (the tangent rollout of P = 1,
4, 12, 16 in ms, one after the other, load 1.0-1.8; the first five with wall time, the rest thread
CPU time): reading the laned factorisation in place instead of unpacking it, 27.3, 39.8, 85.5, 106.7
-> 24.9, 35.4, 79.3, 101.1; each segment's spring parts and part of ``r`` once (not once per row
side) -> 22.1, 34.4, 76.8, 99.0; the friction folded into the segment, ``A_{p,p-1}`` as one product
-> 20.2, 32.3, 70.0, 91.4; the back substitution per group, fused with ``v1'``, ``x1'`` -> 19.2,
29.8, 63.6, 81.5; the directions outside the row loop (constants once per group, ``x'``, ``v'``,
``c``, ``y`` in registers) -> 18.9, 26.1, 58.3, 74.5; the linear maps from two groups on and the
rows' diagonal terms by coefficients -> 18.0, 26.9, 56.8, 68.5; 8 lanes where cheaper -> 17.7, 25.9,
54.3, 58.3; then, tangent kernel alone (1,000 steps, two interleaved A/B runs each): the segment
pass with one division, P = 4 19.0, 19.1 -> 18.3, 17.7; launches of 8, then 4, then 1 lanes, P = 9
46.6, 45.1 -> 38.2, 40.0 and P = 12 47.7, 46.1 -> 45.2, 45.4; the segment pass on lanes of segments,
P = 12 46.1, 47.2 -> 42.5, 42.8 and P = 16 54.7, 53.0 -> 52.5, 49.0 (P = 1, 4 unchanged); the laned
pass keeping each group of 4 segments as one 9 x 4 block, P = 4 18.5, 19.1 -> 16.8, 17.0, P = 12
43.6, 42.4 -> 40.7, 40.6, P = 16 52.9, 51.3 -> 47.7, 47.7. Tried and dropped (no gain beyond the
noise): the gathers' addresses with one multiply per access instead of one per lane (~3 %), ``y``,
``v0'``, ``x0'`` kept contiguous per group for the back substitution instead of gathered again, the
segments' ``h^2 K - h k_f I`` stored as a matrix, ``E`` built entry by entry or from precomputed
scaled vectors, the (scalar) segment pass two segments per iteration; for P = 1, the segment pass on
lanes of segments (the scalar kernel's otherwise; 16.7 -> 16.7 ms, the rollout, 1,000 steps).
Measured pieces at P = 12 (tangent kernel 47.5 ms; removing each, results wrong, as an experiment):
the back substitution 10.4, the rows' diagonal terms 4.9, the maps' products ``E e' + C k'`` 5.1,
the fixed part 9.2 (then a scalar segment pass, one mat33 per segment). Then the particles' tangents
direction-minor (``minor``, the rollouts' layout: a group's directions of one particle three 4-wide
loads or stores and shuffles instead of a gather or scatter of one vec3 per lane; seven per row and
group, and the masses' one load), the rollout of P = 1, 4, 12, 16 tangents against the leading
direction axis in the same process (``bench_string_tangent.py --repeats 5 --layout both``, wall
time, load 1.1, then 1.6; thread CPU time, load 1.0), ms: P = 4 24.5, 23.9, 23.8 -> 21.2, 21.7,
21.0; P = 12 47.5, 49.4, 48.6 -> 41.3, 41.3, 43.0; P = 16 59.5, 58.6, 55.3 -> 51.8, 50.3, 49.3 (P =
1: the scalar kernel, the same); in laned forward rollouts (the second run) 3.07, 5.84, 7.10 against
3.38, 6.97, 8.28, P = 1 2.48; with padding lanes in the last group (into the storage's padding),
``--directions 3 6 10``, load 2.0: 23.3, 34.0, 49.3 -> 21.2, 30.7, 41.4. A runtime test of the
layout per transfer (instead of a kernel per layout) cost more than the gathers it saved (P = 16
60.0 ms). At P = 1 (2.4-2.5 forwards with this kernel, the target 1.5) ``grad.string_tangent`` runs
``string_step_tangent_lanes`` instead where the forward is laned: the strings in lanes, as the
forward has them (4 strings per lane vector), not the directions (its doc has the cost). With one group of directions (P = 2-8) the linear maps and the spring
tangents now tie (measured within 1 ms); the spring tangents are kept there.

Each term is the derivative of the forward's (``string_system.compute_string_system_row``,
``string_terms``, ``string_tie``); the springs' is ``string_spring_tangent_functions``. A change
to a term must be mirrored here and in the adjoint: ``tests/grad/test_string_step_tangent.py``
checks the two against each other (the dot-product identity) and against central differences.
"""

import functools

from types import SimpleNamespace

import numpy as np
import warp as wp

from .lane_ops import native_lane_memory, native_lane_ops
from .string_model_arrays import string_constants_function
from .string_spring import string_spring_adjoint_functions, string_spring_tangent_functions
from .string_state_arrays import string_arrays_types
from .string_step_lanes import lane_step_functions, lane_types
from .tangent_directions import tangent_directions

__all__ = ["CONSTANTS", "DIRECTION_LANES", "WIDE_DIRECTION_LANES", "direction_chunks", "lane_factor_rows",
           "string_step_tangent_kernel"]

# Tangent directions per SIMD lane vector with ``lanes``: 4 doubles (one AVX2 register) or 8 (each
# operation two independent 4-wide halves, more work per instruction: a group of 8 directions
# measured ~1.6x a group of 4, one direction alone ~0.65x, ``benchmarks/bench_string_tangent.py``).
DIRECTION_LANES = 4
WIDE_DIRECTION_LANES = 8


def direction_chunks(directions: int) -> list[tuple[int, int]]:
    """The launches for ``directions`` tangents in SIMD lanes, ``(lanes, count)`` each, directions in
    order: 8 lanes while 5 or more are left, then 4 lanes for 2-4, one direction alone (``lanes =
    1``) for the last one (P = 12: 8 + 4; P = 9: 8 + 1), the cheapest mix by the costs above."""
    chunks = []
    left = directions
    while left > 0:
        lanes = WIDE_DIRECTION_LANES if left >= 5 else DIRECTION_LANES if left >= 2 else 1
        count = min(lanes, left)
        chunks.append((lanes, count))
        left -= count
    return chunks


# The per-string constants whose tangents the kernel reads, in the order of its ``string_constants_dot``.
CONSTANTS = ("string_stiffness", "string_rest_length", "string_internal_friction", "string_air_drag",
             "string_ground_stiffness", "string_ground_absorption", "string_ground_friction",
             "string_tie_stiffness", "string_tie_damping", "string_tied")


@functools.cache
def string_step_tangent_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool], lanes: int = 1,
                               factor_lanes: int = 0, maps: bool = True, segments: bool = True,
                               segment_lanes: int = 1, minor: bool = False):
    """Builds ``integrate_string_implicit_tangent`` for a float type, an effect set (``effects`` as
    ``integrate_string_implicit_kernel``'s) and ``lanes`` directions per value (1: one at a time,
    any float type and device; 4 or 8: in SIMD lanes, float64 on the CPU; ``tangent_directions``),
    printed springs. ``factor_lanes``: 0, the kept factorisation in the scalar step's layout (one
    ``mat33`` per particle); ``K``, in the laned step's (``string_step_lanes`` with ``keep``, ``K``
    strings per group: particle ``p`` of string ``s`` at row ``p + string_factor_row[s]``, lane
    ``string_factor_lane[s]``, :func:`lane_factor_rows`), read there directly. ``maps``: each
    segment's part of ``b' - A' dv`` from its linear maps ``E``, ``C`` (built once per step in
    ``segment_e``, ``segment_c``: cheaper per direction, dearer per step; ``grad.string_tangent``
    takes them from two groups of directions on), else from the spring's tangent; either way from
    the spring parts ``u, l, 1 / l, 1 - d/l, alpha, beta`` kept once per step in ``segment_parts``.
    ``segments``: compute them (the step's first launch), else read those an earlier launch of the
    same step (its other directions, the same ``maps`` and ``segment_lanes``) left.
    ``segment_lanes``: the pass one segment at a time (1) or ``DIRECTION_LANES`` consecutive ones in
    SIMD lanes (float64 CPU), each group of them kept as one laned ``9 x K`` block
    (:func:`_segment_values`). ``minor`` (with ``lanes``): the particles' tangent arrays (in, out, the
    masses') stored direction-minor (``tangent_directions.direction_minor``) and every lane group
    whole (``directions`` a multiple of ``lanes``): each group's transfer one contiguous load or
    store (``tangent_directions``), no gather."""
    GRAVITY, FRICTION, AIR, GROUND, GROUND_FRICTION = effects
    MAPS = maps
    SEGMENTS = segments
    vec3 = wp.types.vector(3, scalar)
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)
    compute_string_constants = string_constants_function(scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    factor = _factor_load(scalar, factor_lanes)
    SEGMENT_LANES = segment_lanes
    store_segments = _segment_pass(scalar, segment_lanes, maps)
    segment_values = _segment_values(scalar, segment_lanes)
    SM, load_segment = segment_values.SM, segment_values.load9
    FM, load_factor = factor.FM, factor.load
    compute_spring_parts = string_spring_adjoint_functions(scalar).compute_spring_parts
    t = tangent_directions(scalar, lanes, minor)
    TS, TV, STEP = t.TS, t.TV, t.step
    load, load_constant, load3, store3 = t.load, t.load_constant, t.load3, t.store3
    sload3, sstore3 = t.sload3, t.sstore3  # the strings' (P, S) arrays: a leading direction axis
    vadd, vsub, vneg, vscl, sadd, ssub, sneg, sscl = t.vadd, t.vsub, t.vneg, t.vscl, t.sadd, t.ssub, t.sneg, t.sscl
    outer, mat, tvec = t.outer, t.mat, t.tvec
    spring = string_spring_tangent_functions(scalar, lanes)
    compute_spring_tangent = spring.compute_spring_tangent
    k_product = spring.compute_jacobian_product
    k_tangent_product = spring.compute_jacobian_tangent_product

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit_tangent(
        # Model:
        model: StringModelArrays,
        # State in (the step's start, then what the forward, built with ``keep``, wrote):
        state_in: StringStateArrays,
        pivot_inverse: wp.array(dtype=FM),
        scratch_c: wp.array(dtype=FM),
        string_factor_row: wp.array(dtype=wp.int32),
        string_factor_lane: wp.array(dtype=wp.int32),
        particle_dv: wp.array(dtype=vec3),
        state_out: StringStateArrays,
        # Control:
        control: StringControlArrays,
        dt: scalar,
        # Tangent in (leading axis: the direction):
        particle_q_dot: wp.array2d(dtype=vec3),
        particle_qd_dot: wp.array2d(dtype=vec3),
        top_q_dot: wp.array2d(dtype=vec3),
        tie_q_dot: wp.array2d(dtype=vec3),
        tie_qd_dot: wp.array2d(dtype=vec3),
        particle_mass_dot: wp.array2d(dtype=scalar),
        string_constants_dot: wp.array3d(dtype=scalar),
        # Tangent out (first a scratch: each segment's spring parts, E, C, written and read within the step):
        segment_parts: wp.array(dtype=SM),
        segment_e: wp.array(dtype=SM),
        segment_c: wp.array(dtype=SM),
        particle_q_out_dot: wp.array2d(dtype=vec3),
        particle_qd_out_dot: wp.array2d(dtype=vec3),
        tie_force_dot: wp.array2d(dtype=vec3),
    ):
        s = wp.tid()
        directions = particle_q_dot.shape[0]
        start = model.string_start[s]
        last = model.string_start[s + 1] - 1
        factor_row = string_factor_row[s]
        factor_lane = string_factor_lane[s]
        zero = scalar(0.0)
        h2 = dt * dt
        constants = compute_string_constants(model, s)
        stiffness, rest_length = constants.stiffness, constants.rest_length
        tied, tie_stiffness, tie_damping = constants.tied, constants.tie_stiffness, constants.tie_damping
        tie_x = control.tie_q[s]
        tie_v = control.tie_qd[s]
        top = control.top_q[s]
        top_dx = top - state_in.particle_q[start]
        top_dv = top_dx / dt - state_in.particle_qd[start]
        g_upper = zero  # the friction's part of A_{p,p+1}: h D = -h k_f I
        inv_dt = scalar(1.0) / dt  # (a product per direction, not a division: not the forward's rounding)
        if wp.static(FRICTION):
            g_upper = -dt * constants.friction

        # Each segment's part of b' - A' dv as a linear map of the direction, once per step (P-independent),
        # for the segment (p, p + 1) below the top one (spring parts u, l, g = max(1 - d/l, 0), alpha,
        # beta of e = x_p - x_{p+1}; s = h^2 z, z = (v_p - v_{p+1}) + (dv_p - dv_{p+1}); P = I - u u^T):
        #     c = K' s + (h^2 K - h k_f I) (v_p' - v_{p+1}') + h f' - h k_f' z
        #       = E e' + W (v_p' - v_{p+1}') + C (k_s', d', k_f'),
        #     E = k_s G (u (u.s) - s) u^T + (alpha / l) ((u.s) I + u s^T) P - h k_s (u u^T + ((l - d) / l) P)
        #     W = h^2 alpha u u^T + (h^2 beta - h k_f) I   (= A_{p,p+1}; applied from the parts, not stored),
        #     C = [-(1 - g) (u.s) u - g s - h (l - d) u,  k_s D (u (u.s) - s) + h k_s u,  -h z],
        # with g' = G l' + D d' (G = d / l^2, D = -1 / l while 1 - d/l > 0, else 0: the clamp's flat
        # side), from l' = u.e', u' = P e' / l, alpha' = -(1 - g) k_s' + k_s g', beta' = -g k_s' - k_s g',
        # f' = -(k_s' (l - d) + k_s (l' - d')) u - k_s (l - d) u' (``string_spring_tangent_functions``).
        # The friction's terms of the segment's two rows, gathered: h (-k_f' (v_p - v_{p+1}) - k_f
        # (v_p' - v_{p+1}')) of the force, +h k_f' dv_{p+1} of -A_{p,p+1}' dv_{p+1}, -h k_f' dv_p of the
        # diagonal's -A_pp' dv_p. c enters row p as +c and row p + 1 as -c (z, v_p' - v_{p+1}', e' and
        # the spring force on p change sign exactly with the segment's ends).
        if wp.static(SEGMENTS):  # SEGMENT_LANES segments at a time
            for p0 in range(start + 1, last, SEGMENT_LANES):
                store_segments(p0, wp.min(SEGMENT_LANES, last - p0), state_in.particle_q, state_in.particle_qd, particle_dv,
                               stiffness, rest_length, dt, segment_parts, segment_e, segment_c)
        tie_stiffness_k = model.string_tie_stiffness[s]
        tie_damping_k = model.string_tie_damping[s]
        x_last = state_out.particle_q[last]
        v_last = state_out.particle_qd[last]
        v0_top = state_in.particle_qd[start]

        # One group of directions at a time (the string's constants' tangents read once per group):
        # the forward sweep, row by row, every row's r = b' - A' dv and its forward substitution
        # y = inv_p (r - A_{p,p-1} y_prev), y carried to the next row and kept in particle_qd_out_dot;
        # then the back substitution. Row p's segments: the lower one's c computed (+c), the upper
        # one's carried from row p - 1 (-c); the top segment (row 1 only, not shared): h K_10 dx_0 and
        # K' (w_top + h^2 dv), no lower block, from its spring parts. Every other term's Jacobian is
        # diagonal; each term's part of r, linear in the direction, is added on its own.
        for k in range(0, directions, STEP):
            stiffness_dot = load_constant(string_constants_dot, k, directions, s, 0)
            rest_dot = load_constant(string_constants_dot, k, directions, s, 1)
            friction_dot = TS(zero)
            if wp.static(FRICTION):
                friction_dot = load_constant(string_constants_dot, k, directions, s, 2)
            air_dot = TS(zero)
            if wp.static(AIR):
                air_dot = load_constant(string_constants_dot, k, directions, s, 3)
            constants_dot = tvec(stiffness_dot, rest_dot, friction_dot)
            x_dot = load3(particle_q_dot, k, directions, start + 1)
            v_dot = load3(particle_qd_dot, k, directions, start + 1)
            c_a = TV(zero)
            y_prev = TV(zero)
            for p in range(start + 1, last + 1):
                j = p - start
                is_last = p == last
                x = state_in.particle_q[p]
                v = state_in.particle_qd[p]
                dv = particle_dv[p]
                r = TV(zero)
                if j == 1:  # the top segment; top_dx' = top' - x0_top'
                    u_t, l_t, ratio_t, alpha_t, beta_t = compute_spring_parts(state_in.particle_q[start], x, stiffness,
                                                                              rest_length)
                    x_top_dot = load3(particle_q_dot, k, directions, start)
                    top_dx_dot = vsub(sload3(top_q_dot, k, directions, s), x_top_dot)
                    u_t_dot, alpha_t_dot, beta_t_dot, f_t_dot = compute_spring_tangent(
                        u_t, l_t, scalar(1.0) / l_t, ratio_t, stiffness, rest_length, vsub(x_top_dot, x_dot),
                        stiffness_dot, rest_dot)
                    r = vsub(vadd(k_tangent_product(u_t, alpha_t, u_t_dot, alpha_t_dot, beta_t_dot,
                                                    h2 * v - dt * top_dx + h2 * dv),
                                  k_product(u_t, alpha_t, beta_t, vsub(vscl(h2, v_dot), vscl(dt, top_dx_dot)))),
                             vscl(dt, f_t_dot))
                    if wp.static(FRICTION):
                        # f = -k_f (v - v_0), D = -k_f I; rhs's h k_f dv_0, dv_0 = top_dx / h - v0_top:
                        # h k_f' (dv_0 - (v - v_0) - dv) + h k_f (dv_0' - (v' - v_0')).
                        v_top_dot = load3(particle_qd_dot, k, directions, start)
                        r = vadd(vadd(r, outer(dt * (top_dv - (v - v0_top) - dv), friction_dot)),
                                 vscl(dt * constants.friction, vsub(vsub(vscl(inv_dt, top_dx_dot), v_top_dot),
                                                          vsub(v_dot, v_top_dot))))
                else:  # the upper segment's -c, from row p - 1
                    r = vneg(c_a)
                c_b = TV(zero)
                x_next_dot = TV(zero)
                v_next_dot = TV(zero)
                if not is_last:
                    x_next_dot = load3(particle_q_dot, k, directions, p + 1)
                    v_next_dot = load3(particle_qd_dot, k, directions, p + 1)
                    parts = load_segment(segment_parts, p, start + 1)
                    u_b = vec3(parts[0, 0], parts[0, 1], parts[0, 2])
                    w_part = k_product(u_b, h2 * parts[2, 0], h2 * parts[2, 1] + g_upper, vsub(v_dot, v_next_dot))
                    if wp.static(MAPS):
                        c_b = vadd(vadd(mat(load_segment(segment_e, p, start + 1), vsub(x_dot, x_next_dot)), w_part),
                                   mat(load_segment(segment_c, p, start + 1), constants_dot))
                    else:
                        u_b_dot, alpha_b_dot, beta_b_dot, f_b_dot = compute_spring_tangent(
                            u_b, parts[1, 0], parts[1, 1], parts[1, 2], stiffness, rest_length,
                            vsub(x_dot, x_next_dot), stiffness_dot, rest_dot)
                        z_b = (v - state_in.particle_qd[p + 1]) + (dv - particle_dv[p + 1])
                        c_b = vadd(vadd(k_tangent_product(u_b, parts[2, 0], u_b_dot, alpha_b_dot, beta_b_dot, h2 * z_b),
                                        w_part), vscl(dt, f_b_dot))
                        if wp.static(FRICTION):
                            c_b = vsub(c_b, outer(dt * z_b, friction_dot))
                    r = vadd(r, c_b)
                # The mass: h g m' of the force, -m' dv of the diagonal.
                mass_coefficient = -dv
                if wp.static(GRAVITY):
                    mass_coefficient = dt * constants.gravity - dv
                r = vadd(r, outer(mass_coefficient, load(particle_mass_dot, k, directions, p)))
                if wp.static(AIR):
                    # f = -k_a v, D = -k_a I: h (-k_a' v - k_a v') - h k_a' dv.
                    r = vsub(r, vadd(outer(dt * (v + dv), air_dot), vscl(dt * constants.air_drag, v_dot)))
                if wp.static(GROUND):
                    if x[1] < constants.ground_height:
                        # f_y = k_rep (h_ground - y) - k_abs v_y; K_yy = -k_rep, D_yy = -k_abs: the force's
                        # h f_y', b's h^2 K_yy' v_y + h^2 K_yy v_y', the diagonal's -(h k_abs' + h^2 k_rep') dv_y.
                        ground_stiffness_dot = load_constant(string_constants_dot, k, directions, s, 4)
                        ground_absorption_dot = load_constant(string_constants_dot, k, directions, s, 5)
                        k_rep, k_abs = constants.ground_stiffness, constants.ground_absorption
                        r_y = sadd(sadd(sscl(dt * (constants.ground_height - x[1]) - h2 * (v[1] + dv[1]),
                                             ground_stiffness_dot),
                                        sscl(-dt * (v[1] + dv[1]), ground_absorption_dot)),
                                   ssub(sscl(-dt * k_rep, x_dot[1]), sscl(dt * k_abs + h2 * k_rep, v_dot[1])))
                        r_x = TS(zero)
                        r_z = TS(zero)
                        if wp.static(GROUND_FRICTION):
                            # f_xz = -k_gf v_xz, D_xz = -k_gf: h (-k_gf' v - k_gf v') - h k_gf' dv.
                            ground_friction_dot = load_constant(string_constants_dot, k, directions, s, 6)
                            r_x = ssub(sscl(-dt * (v[0] + dv[0]), ground_friction_dot),
                                       sscl(dt * constants.ground_friction, v_dot[0]))
                            r_z = ssub(sscl(-dt * (v[2] + dv[2]), ground_friction_dot),
                                       sscl(dt * constants.ground_friction, v_dot[2]))
                        r = vadd(r, tvec(r_x, r_y, r_z))
                if is_last:
                    # The tie (eq. 2), f = k_t (x_tie - x) + k_dt (v_tie - v); K = -k_t I, D = -k_dt I;
                    # k_t = tied k, k_dt = tied k_d: the force's h f', b's h^2 (K' v + K v'), the
                    # diagonal's -(h k_dt' + h^2 k_t') dv.
                    tied_dot = load_constant(string_constants_dot, k, directions, s, 9)
                    tie_stiffness_dot = sadd(sscl(tie_stiffness_k, tied_dot),
                                             sscl(tied, load_constant(string_constants_dot, k, directions, s, 7)))
                    tie_damping_dot = sadd(sscl(tie_damping_k, tied_dot),
                                           sscl(tied, load_constant(string_constants_dot, k, directions, s, 8)))
                    r = vadd(vadd(vadd(r, outer(dt * (tie_x - x) - h2 * (v + dv), tie_stiffness_dot)),
                                  outer(dt * (tie_v - v - dv), tie_damping_dot)),
                             vsub(vadd(vscl(dt * tie_stiffness, vsub(sload3(tie_q_dot, k, directions, s), x_dot)),
                                       vscl(dt * tie_damping, vsub(sload3(tie_qd_dot, k, directions, s), v_dot))),
                                  vscl(h2 * tie_stiffness, v_dot)))
                # Forward substitution with the stored pivot inverse; A_{p,p-1} = A_{p-1,p}, the upper segment's W.
                if j > 1:
                    parts = load_segment(segment_parts, p - 1, start + 1)
                    r = vsub(r, k_product(vec3(parts[0, 0], parts[0, 1], parts[0, 2]), h2 * parts[2, 0],
                                          h2 * parts[2, 1] + g_upper, y_prev))
                y_prev = mat(load_factor(pivot_inverse, p + factor_row, factor_lane), r)
                store3(particle_qd_out_dot, k, directions, p, y_prev)
                c_a = c_b
                x_dot = x_next_dot
                v_dot = v_next_dot

            # Back substitution (dv'_j = y_j - C'_j dv'_{j+1}), bottom to top, dv' carried from row to
            # row, and with it v1' = v0' + dv', x1' = x0' + h v1'; the top particle, x1' = top',
            # v1' = (top' - x0_top') / h; the tie force on the new state (eq. 2,
            # ``string_integrate.compute_string_outputs``).
            dv_dot = y_prev
            for i in range(last - start):
                p = last - i
                if p < last:
                    dv_dot = vsub(load3(particle_qd_out_dot, k, directions, p),
                                  mat(load_factor(scratch_c, p + factor_row, factor_lane), dv_dot))
                v1_dot = vadd(load3(particle_qd_dot, k, directions, p), dv_dot)
                store3(particle_qd_out_dot, k, directions, p, v1_dot)
                store3(particle_q_out_dot, k, directions, p, vadd(load3(particle_q_dot, k, directions, p),
                                                                 vscl(dt, v1_dot)))
            top_dot = sload3(top_q_dot, k, directions, s)
            store3(particle_q_out_dot, k, directions, start, top_dot)
            store3(particle_qd_out_dot, k, directions, start,
                   vscl(inv_dt, vsub(top_dot, load3(particle_q_dot, k, directions, start))))
            tied_dot = load_constant(string_constants_dot, k, directions, s, 9)
            tie_stiffness_dot = sadd(sscl(tie_stiffness_k, tied_dot),
                                     sscl(tied, load_constant(string_constants_dot, k, directions, s, 7)))
            tie_damping_dot = sadd(sscl(tie_damping_k, tied_dot),
                                   sscl(tied, load_constant(string_constants_dot, k, directions, s, 8)))
            # F' = -k_t' (x_tie - x1) - k_t (x_tie' - x1') - k_dt' (v_tie - v1) - k_dt (v_tie' - v1')
            sstore3(tie_force_dot, k, directions, s, vsub(vsub(vsub(
                outer(tie_x - x_last, sneg(tie_stiffness_dot)),
                vscl(tie_stiffness, vsub(sload3(tie_q_dot, k, directions, s),
                                         load3(particle_q_out_dot, k, directions, last)))),
                outer(tie_v - v_last, tie_damping_dot)),
                vscl(tie_damping, vsub(sload3(tie_qd_dot, k, directions, s),
                                       load3(particle_qd_out_dot, k, directions, last)))))

    return integrate_string_implicit_tangent


def lane_factor_rows(string_start, group_string, group_real, group_base, string_count: int):
    """``(string_factor_row, string_factor_lane)`` (NumPy int32, one per string) of the laned step's
    group table (``string_step_lanes.lane_groups``): particle ``p`` of string ``s`` is row
    ``p + string_factor_row[s]`` of the laned factorisation (``group_base[g] + j`` for ``p =
    string_start[s] + j``), lane ``string_factor_lane[s]``; the padding lanes' copies are skipped."""
    row = np.zeros(string_count, dtype=np.int32)
    lane = np.zeros(string_count, dtype=np.int32)
    for g in range(len(group_base)):
        for l in range(int(group_real[g])):
            s = int(group_string[g][l])
            row[s] = int(group_base[g]) - int(string_start[s])
            lane[s] = l
    return row, lane


@functools.cache
def _factor_load(scalar, factor_lanes: int) -> SimpleNamespace:
    """``FM`` (the kept factorisation's dtype) and ``load(a, row, lane)``: the ``mat33`` at ``row``
    (scalar layout, ``lane`` unused) or lane ``lane`` of the laned ``9 x K`` matrix at ``row`` (entry
    ``(i, m)`` at ``[3 i + m, lane]``), nine loads, no copy of the other lanes."""
    mat33 = wp.types.matrix((3, 3), scalar)
    if factor_lanes == 0:
        @wp.func
        def load(a: wp.array(dtype=mat33), row: int, lane: int):
            return a[row]

        return SimpleNamespace(FM=mat33, load=load)
    if scalar is not wp.float64:
        raise TypeError(f"a laned factorisation: float64 only, got {scalar}")
    lmat = wp.types.matrix((9, factor_lanes), wp.float64)

    @wp.func_native(f"""
    const double* m = (const double*)((const char*)a.data + (long)row * (long)a.strides[0]) + lane;
    wp::mat_t<3, 3, wp::float64> r;
    for (int e = 0; e < 9; ++e) r.data[e / 3][e % 3] = m[e * {factor_lanes}];
    return r;
    """)
    def load_lane(a: wp.array(dtype=lmat), row: int, lane: int) -> wp.mat33d:
        ...

    return SimpleNamespace(FM=lmat, load=load_lane)


@functools.cache
def _segment_values(scalar, lanes: int) -> SimpleNamespace:
    """The values of the segment pass: one segment per value (``lanes = 1``, any float type and
    device: Warp's operations) or ``lanes`` consecutive segments in SIMD lanes (float64 on the CPU:
    ``lane_ops``' Clang vector snippets, each lane the scalar operation in the same order). ``L``, ``V``:
    a scalar and a vec3 of the segments; ``load3(a, p0, count, j)``: ``a[p + j]`` for the segments
    ``p = p0 ... p0 + count - 1`` (the padding lanes repeat the last); ``const``, ``add``, ``sub``,
    ``mul``, ``div``, ``sqrt``, ``max``, ``where_pos(x, a, b)`` (``a`` where ``x > 0``), ``vadd``, ``vsub``,
    ``vscl``, ``vdot``; ``store9(a, p0, count, m)``: the nine ``L`` of ``m`` (a ``3 x 3`` matrix,
    row-major) kept for the segments, in ``a`` of ``SM`` (one ``mat33`` per segment; in lanes one
    ``9 x lanes`` block per group of segments, at its first segment's index, the layout of the laned
    factorisation); ``load9(a, p, first)``: segment ``p``'s ``mat33`` (``first``: the string's first
    segment of the pass, where its groups start)."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    if lanes == 1:
        L, V = scalar, vec3
        M = wp.types.vector(9, scalar)

        @wp.func
        def const(x: scalar):
            return x

        @wp.func
        def load3(a: wp.array(dtype=vec3), p0: int, count: int, j: int):
            return a[p0 + j]

        @wp.func
        def div(a: scalar, b: scalar):
            return a / b

        @wp.func
        def sqrt(a: scalar):
            return wp.sqrt(a)

        @wp.func
        def vmax(a: scalar, b: scalar):
            return wp.max(a, b)

        @wp.func
        def where_pos(x: scalar, a: scalar, b: scalar):
            r = b
            if x > scalar(0.0):
                r = a
            return r

        @wp.func
        def store9(a: wp.array(dtype=mat33), p0: int, count: int, m: M):
            a[p0] = mat33(m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8])

        @wp.func
        def load9(a: wp.array(dtype=mat33), p: int, first: int):
            return a[p]

        # The arithmetic one direction at a time already has (the same operation each).
        t = tangent_directions(scalar)
        return SimpleNamespace(L=L, V=V, M=M, SM=mat33, load9=load9, store9=store9, const=const, load3=load3,
                               add=t.sadd, sub=t.ssub, mul=t.sscl, div=div, sqrt=sqrt, max=vmax, where_pos=where_pos,
                               vadd=t.vadd, vsub=t.vsub, vscl=t.vscl, vdot=t.dot)
    if scalar is not wp.float64:
        raise TypeError(f"the segment pass in lanes: float64 only, got {scalar}")
    lane, ivec, lvec, _lmat = lane_types(lanes)
    nine = wp.types.matrix((9, lanes), wp.float64)
    nat = native_lane_ops(lanes)
    mem = native_lane_memory(lanes)
    f = lane_step_functions(lanes)
    LANES_ = lanes

    @wp.func
    def const(x: wp.float64):
        return lane(x)

    @wp.func
    def load3(a: wp.array(dtype=wp.vec3d), p0: int, count: int, j: int):
        index = ivec()
        for l in range(LANES_):
            index[l] = p0 + wp.min(l, count - 1)
        return mem.gather3(a, index, j)

    @wp.func
    def where_pos(x: lane, a: lane, b: lane):
        return nat.where_less(lane(wp.float64(0.0)), x, a, b)

    @wp.func
    def vscl(s: lane, v: lvec):
        return f.lscale(s, v)

    @wp.func
    def vdot(a: lvec, b: lvec):
        return f.lsum3(a[0], a[1], a[2], b[0], b[1], b[2])

    @wp.func
    def store9(a: wp.array(dtype=nine), p0: int, count: int, m: nine):
        a[p0] = m  # the block of the segments p0 ... p0 + lanes - 1, one store

    load_lane = _factor_load(wp.float64, lanes).load

    @wp.func
    def load9(a: wp.array(dtype=nine), p: int, first: int):
        """Segment ``p``'s ``mat33``: lane ``(p - first) % lanes`` of the block at its group's first segment."""
        q = p - first
        lane_index = q % LANES_
        return load_lane(a, p - lane_index, lane_index)

    return SimpleNamespace(L=lane, V=lvec, M=nine, SM=nine, load9=load9, store9=store9, const=const, load3=load3,
                           add=nat.add, sub=nat.sub, mul=nat.mul, div=nat.div, sqrt=nat.sqrt, max=nat.max,
                           where_pos=where_pos, vadd=f.vadd, vsub=f.vsub, vscl=vscl, vdot=vdot)


@functools.cache
def _segment_pass(scalar, lanes: int, maps: bool):
    """``store_segments(p0, count, ...)``: the segment pass (the kernel's comment) for the segments
    ``(p, p + 1)``, ``p = p0 ... p0 + count - 1`` (``count <= lanes``), one body for one segment per
    value or ``lanes`` of them in SIMD lanes (:func:`_segment_values`: the same operations in the
    same order). ``segment_parts[p]``: the rows ``u``, ``(l, 1 / l, 1 - d/l)``, ``(alpha, beta, 0)``;
    with ``maps`` also ``E`` in ``segment_e[p]`` and ``C`` in ``segment_c[p]``."""
    g = _segment_values(scalar, lanes)
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    L, V, M, SM = g.L, g.V, g.M, g.SM
    const, add, sub, mul, div, sqrt, vmax, where_pos = g.const, g.add, g.sub, g.mul, g.div, g.sqrt, g.max, g.where_pos
    vadd, vsub, vscl, vdot, load3, store9 = g.vadd, g.vsub, g.vscl, g.vdot, g.load3, g.store9
    MAPS = maps

    @wp.func
    def neg(a: L):
        return sub(const(scalar(0.0)), a)

    @wp.func
    def columns(a: V, b: V, c: V):
        """The nine values (row-major) of the ``3 x 3`` matrix with the columns ``a``, ``b``, ``c``."""
        m = M()
        for i in range(3):
            m[3 * i] = a[i]
            m[3 * i + 1] = b[i]
            m[3 * i + 2] = c[i]
        return m

    @wp.func
    def rank_two(a: L, b_vec: V, b: L, c: L, d: L, u: V):
        """``a b_vec u^T + b u b_vec^T + c u u^T + d I``, entry by entry (nine values, row-major)."""
        m = M()
        for i in range(3):
            ab = mul(a, b_vec[i])
            bu = mul(b, u[i])
            cu = mul(c, u[i])
            for j in range(3):
                m[3 * i + j] = add(add(mul(ab, u[j]), mul(bu, b_vec[j])), mul(cu, u[j]))
            m[4 * i] = add(m[4 * i], d)
        return m

    @wp.func
    def store_segments(p0: int, count: int, particle_q: wp.array(dtype=vec3), particle_qd: wp.array(dtype=vec3),
                       particle_dv: wp.array(dtype=vec3), stiffness: scalar, rest_length: scalar, dt: scalar,
                       segment_parts: wp.array(dtype=SM), segment_e: wp.array(dtype=SM),
                       segment_c: wp.array(dtype=SM)):
        zero = const(scalar(0.0))
        one = const(scalar(1.0))
        ks = const(stiffness)
        d = const(rest_length)
        h = const(dt)
        h2 = const(dt * dt)
        # ``compute_spring_parts`` with one division (products with 1 / l: the tangent's primal within
        # an ulp or so of the forward's, as the step's other parts are).
        e = vsub(load3(particle_q, p0, count, 0), load3(particle_q, p0, count, 1))
        length = sqrt(vdot(e, e))
        inv_l = div(one, length)
        u = vscl(inv_l, e)
        ratio = sub(one, mul(d, inv_l))
        geometric = vmax(ratio, zero)
        alpha = mul(neg(ks), sub(one, geometric))
        beta = mul(neg(ks), geometric)
        parts = M()
        for i in range(3):
            parts[i] = u[i]
        parts[3] = length
        parts[4] = inv_l
        parts[5] = ratio
        parts[6] = alpha
        parts[7] = beta
        parts[8] = zero
        store9(segment_parts, p0, count, parts)
        if wp.static(MAPS):
            z = vadd(vsub(load3(particle_qd, p0, count, 0), load3(particle_qd, p0, count, 1)),
                     vsub(load3(particle_dv, p0, count, 0), load3(particle_dv, p0, count, 1)))
            s_z = vscl(h2, z)
            g_l = where_pos(ratio, mul(mul(d, inv_l), inv_l), zero)
            g_d = where_pos(ratio, neg(inv_l), zero)
            ur = vdot(u, s_z)
            stretch = sub(length, d)
            bend = vsub(vscl(ur, u), s_z)  # = -P s
            # E with ((u.s) I + u s^T) P = (u.s) P - u bend^T: two rank-one terms, multiples of I, u u^T.
            hks = mul(h, ks)
            e_iso = mul(sub(mul(alpha, ur), mul(hks, stretch)), inv_l)
            store9(segment_e, p0, count,
                   rank_two(mul(ks, g_l), bend, neg(mul(alpha, inv_l)), neg(add(e_iso, hks)), e_iso, u))
            col_ks = vsub(vscl(sub(neg(mul(sub(one, geometric), ur)), mul(h, stretch)), u), vscl(geometric, s_z))
            col_d = vadd(vscl(mul(ks, g_d), bend), vscl(hks, u))
            col_kf = vscl(neg(h), z)
            store9(segment_c, p0, count, columns(col_ks, col_d, col_kf))

    return store_segments
