"""The segment spring between neighbouring particles of a string (paper §2.2, term 1), defined once.

Two variants, chosen per scene (``StringEffects.tension_only``): the paper's printed spring
``f_a = -k_s (|x_a - x_b| - d) u`` (default) and the tension-only one
``f_a = -k_s max(|x_a - x_b| - d, 0) u``; both return the force on ``a``, the Jacobian block
``K_aa = df_a/dx_a`` (``K_ab = -K_aa``) and whether the segment is in the implicit system.
:func:`compute_string_tension` is the tension-only spring's magnitude, also read by the
coupling's linear model of a string (``string_body_coupling.eval_string_response``).

Users: the segment pass of the string step (``string_system.eval_string_spring``), the
exact reaction on the bar (``bar_feedback.compute_bar_reaction``: the bar feedback and the
bar work of ``marionette/energy.py``), and the coupling response. The active-set solve of
the tension-only springs (``string_solve``) adds the blocks this spring returns.

Built per float type by :func:`string_spring_functions` (cached), as the other string terms
(``string_terms``). :func:`string_spring_adjoint_functions` holds the printed spring's
derivative as the string step's hand-written adjoint (``string_step_adjoint``) uses it: by
its structure ``K = alpha u u^T + beta I``, next to the spring it differentiates;
:func:`string_spring_tangent_functions` its forward (tangent-linear) derivative, as the string
step's tangent (``string_step_tangent``) uses it.
"""


import functools
from types import SimpleNamespace

import warp as wp

from .tangent_directions import tangent_directions

__all__ = ["string_spring_adjoint_functions", "string_spring_functions", "string_spring_tangent_functions"]


@functools.cache
def string_spring_functions(scalar) -> SimpleNamespace:
    """Builds the segment-spring functions for the float type ``scalar`` (``wp.float32``/``wp.float64``).

    Returns:
        A namespace with ``compute_string_spring_printed``, ``compute_string_spring_tension_only``
        and ``compute_string_tension``.
    """
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def compute_string_tension(length: scalar, stiffness: scalar, rest_length: scalar):
        """Tension [N] of a tension-only segment of length ``length``: ``k_s max(l - d, 0)``."""
        return stiffness * wp.max(length - rest_length, scalar(0.0))

    @wp.func
    def compute_string_spring_printed(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar):
        """Spring between neighbours a and b, paper term 1 as printed: ``f_a = -k_s (|x_a - x_b| - d) u``
        (it also pushes when the segment is shorter than ``d``).

        Returns the force on ``a``, ``K_aa = df_a/dx_a`` (and ``K_ab = -K_aa``), and ``1`` (the
        segment is always in the implicit system).

        Deliberate deviation from an exact Newton linearisation: the geometric
        (transverse) part of the Jacobian, ``(1 - d/l)(I - u u^T)``, is clamped at zero
        while the segment is compressed (``l < d``). The force itself is exact; only the
        system matrix differs, and it stays symmetric positive definite, so the
        block-tridiagonal solve never meets an indefinite pivot when a slack string
        buckles (Choi & Ko, SIGGRAPH 2002).
        """
        e = x_a - x_b
        length = wp.length(e)
        u = e / length
        force = -stiffness * (length - rest_length) * u
        # -k_s (u u^T + c (I - u u^T)) = -k_s c I - k_s (1 - c) u u^T, with c clamped at 0.
        geometric = wp.max(scalar(1.0) - rest_length / length, scalar(0.0))
        eye = wp.identity(n=3, dtype=scalar)
        jacobian = wp.outer(-stiffness * (scalar(1.0) - geometric) * u, u) - (stiffness * geometric) * eye
        return force, jacobian, int(1)

    @wp.func
    def compute_string_spring_tension_only(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar):
        """Spring between neighbours a and b, paper term 1, made tension-only:
        ``f_a = -k_s max(|x_a - x_b| - d, 0) u``, ``u = (x_a - x_b) / |x_a - x_b|``.

        Returns the force on ``a``, the Jacobian block ``K_aa`` the implicit step uses when
        the segment is *active* in the step (``K_ab = -K_aa``), and whether the segment is
        taut now (``1``/``0``).

        **Deliberate deviation from the paper** (chosen with ``StringEffects(tension_only=True)``,
        scene key ``[effects] tension_only = true``; the default is the printed spring,
        ``compute_string_spring_printed``, see the last paragraph): the paper prints
        ``-k_s (|x_a - x_b| - d) u``, which also pushes when the segment is shorter than its
        rest length. A real string does not push: with the printed spring a straight string
        lowered onto the ground acts as a rod and drives its lower particles 0.3 m through the
        ground penalty (``tests/strings/test_hard_cases_strings.py``). Here the potential is
        ``1/2 k_s max(l - d, 0)^2`` (``strings.model.string_energy``), which is convex in the
        positions (the printed spring's is not). For a taut segment (``l > d``) force and
        Jacobian are the paper's, so taut strings behave exactly as before.

        **Linearising across the kink** (backward Euler takes ``K`` at the start of the step):
        a segment is active in a step if it is taut at the start *or at the end* of the
        step; the end is found by the solve (``kernels/string_solve``, an active-set loop:
        solve, activate the segments that end taut, solve again). An active segment uses

        - taut: the exact ``K = -k_s (u u^T + (1 - d/l)(I - u u^T))``;
        - slack now, taut at the end: the axial ``K = -k_s u u^T`` (the force is still the
          exact zero): over the step a spring of rest length ``l``, whose energy starts at
          the true 0 and ends at ``1/2 k_s (l' - l)^2 >= 1/2 k_s max(l' - d, 0)^2``.

        So every active segment's step sees a quadratic surrogate that equals the true
        potential at the start and bounds it from above at the end, and an inactive segment
        is slack at both ends (no force, no energy). Switching ``K`` on only once a segment
        *is* taut (or is predicted taut from ``x + dt v``) lets it stretch by up to
        ``dt |v_a - v_b|`` in a step with no force acting, and ``1/2 k_s stretch^2`` appears
        from nothing (measured: a string without internal friction went unstable while
        hanging still, 4 m/s within 50 ms, NaN after 0.4 s). The energy must count only ``1/2 k_s max(l - d, 0)^2`` too: the
        printed potential also counts compressed segments, energy a tension-only string does
        not store. The geometric (transverse) factor ``(1 - d/l)`` is
        non-negative wherever it is used, so the system matrix stays symmetric positive
        definite and the block-tridiagonal solve never meets an indefinite pivot (Choi & Ko,
        SIGGRAPH 2002, clamp it for the same reason).

        **Why it is not the default:** it is a change of the paper's model (the printed spring
        pushes), and it costs about 3x the printed spring's string step (which runs in SIMD
        lanes; this one does not: ``benchmarks/bench_tension_only.py``). It passes the hard cases tried with it,
        strings alone and in a marionette, with the puppet at the string rate and at 30 Hz
        (``tests/strings/test_hard_cases_strings.py``, ``tests/marionette/test_tension_only_marionette.py``;
        at 30 Hz it was refused while the coupling extrapolated the tie path as ``x + H v``,
        ``settings_check``).
        """
        e = x_a - x_b
        length = wp.length(e)
        zero = scalar(0.0)
        u = vec3(zero)
        if length > zero:
            u = e / length  # coincident particles (a string folded onto itself): no direction, no force
        force = -compute_string_tension(length, stiffness, rest_length) * u
        taut = int(0)
        jacobian = wp.outer(-stiffness * u, u)
        if length > rest_length:
            taut = 1
            geometric = scalar(1.0) - rest_length / length
            eye = wp.identity(n=3, dtype=scalar)
            jacobian = wp.outer(-stiffness * (scalar(1.0) - geometric) * u, u) - (stiffness * geometric) * eye
        return force, jacobian, taut

    return SimpleNamespace(
        compute_string_spring_printed=compute_string_spring_printed,
        compute_string_spring_tension_only=compute_string_spring_tension_only,
        compute_string_tension=compute_string_tension,
    )


@functools.cache
def string_spring_adjoint_functions(scalar) -> SimpleNamespace:
    """Builds the printed spring's pieces that the string step's hand-written adjoint uses
    (``string_step_adjoint``), by the structure of ``compute_string_spring_printed``.

    The printed spring's block is ``K = alpha u u^T + beta I`` with ``alpha = -k_s (1 - g)``,
    ``beta = -k_s g``, ``g = max(1 - d/l, 0)``; the adjoint never forms it: ``K r`` is
    ``alpha u (u . r) + beta r``, and a segment's ``K_bar`` (a sum of outer products ``a b^T``)
    enters only through ``u^T K_bar u``, ``tr K_bar`` and ``(K_bar + K_bar^T) u``, accumulated
    per outer product (``compute_outer_moments``).
    """
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def compute_spring_parts(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar):
        """``(u, l, 1 - d/l, alpha, beta)`` of the segment ``e = x_a - x_b``."""
        e = x_a - x_b
        length = wp.length(e)
        ratio = scalar(1.0) - rest_length / length
        geometric = wp.max(ratio, scalar(0.0))
        return e / length, length, ratio, -stiffness * (scalar(1.0) - geometric), -stiffness * geometric

    @wp.func
    def compute_outer_moments(a: vec3, b: vec3, u: vec3):
        """For ``M = a b^T``: ``(u^T M u, tr M, (M + M^T) u)``."""
        ua = wp.dot(u, a)
        ub = wp.dot(u, b)
        return ua * ub, wp.dot(a, b), ub * a + ua * b

    @wp.func
    def compute_spring_adjoint(u: vec3, length: scalar, ratio: scalar, alpha: scalar, stiffness: scalar,
                               rest_length: scalar, f_bar: vec3, k_uu: scalar, k_tr: scalar, k_sym: vec3):
        """Adjoint of ``f = -k_s (l - d) u`` and ``K`` (parts from ``compute_spring_parts``), given ``f_bar``
        and ``K_bar``'s moments: returns ``(e_bar, stiffness_bar, rest_length_bar)``."""
        one = scalar(1.0)
        stretch = length - rest_length
        geometric = wp.max(ratio, scalar(0.0))
        u_f = wp.dot(u, f_bar)
        u_bar = (-stiffness * stretch) * f_bar + alpha * k_sym
        stiffness_bar = -stretch * u_f - (one - geometric) * k_uu - geometric * k_tr
        length_bar = -stiffness * u_f
        rest_bar = stiffness * u_f
        if ratio > scalar(0.0):  # where the clamp passes 1 - d/l (Warp's adjoint of max: the same side)
            g_bar = stiffness * (k_uu - k_tr)
            length_bar = length_bar + g_bar * rest_length / (length * length)
            rest_bar = rest_bar - g_bar / length
        e_bar = (u_bar - wp.dot(u, u_bar) * u) / length + length_bar * u
        return e_bar, stiffness_bar, rest_bar

    @wp.func
    def compute_spring_parts_tension_only(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar, forced: int):
        """``compute_spring_parts`` of ``compute_string_spring_tension_only`` in a step whose active set
        forces the segment (``forced = 1``) or not: ``(u, l, 1 - d/l, alpha, beta)``, ``alpha = beta = 0``
        for an inactive segment (slack and not forced: no block), ``alpha = -k_s, beta = 0`` for a
        forced slack one (the axial block), the printed spring's parts for a taut one."""
        zero = scalar(0.0)
        e = x_a - x_b
        length = wp.length(e)
        u = vec3(zero)
        ratio = scalar(-1.0)
        if length > zero:
            u = e / length
            ratio = scalar(1.0) - rest_length / length
        alpha = zero
        beta = zero
        if length > rest_length:
            alpha = -stiffness * (scalar(1.0) - ratio)
            beta = -stiffness * ratio
        elif forced == 1:
            alpha = -stiffness
        return u, length, ratio, alpha, beta

    @wp.func
    def compute_spring_adjoint_tension_only(u: vec3, length: scalar, ratio: scalar, alpha: scalar, stiffness: scalar,
                                            rest_length: scalar, f_bar: vec3, k_uu: scalar, k_tr: scalar,
                                            k_sym: vec3, forced: int):
        """``compute_spring_adjoint`` of the tension-only spring ``f = -k_s max(l - d, 0) u`` and its block
        (parts from ``compute_spring_parts_tension_only``): the force and the geometric block only
        where the segment is taut (Warp's adjoint of ``max`` at ``l = d``: the zero side), the axial
        block ``-k_s u u^T`` where a slack segment is forced; nothing for coincident particles."""
        zero = scalar(0.0)
        e_bar = vec3(zero)
        stiffness_bar = zero
        rest_bar = zero
        if length > zero:
            u_bar = alpha * k_sym
            length_bar = zero
            if length > rest_length:
                stretch = length - rest_length
                u_f = wp.dot(u, f_bar)
                u_bar = u_bar - (stiffness * stretch) * f_bar
                stiffness_bar = -stretch * u_f - (scalar(1.0) - ratio) * k_uu - ratio * k_tr
                g_bar = stiffness * (k_uu - k_tr)
                length_bar = -stiffness * u_f + g_bar * rest_length / (length * length)
                rest_bar = stiffness * u_f - g_bar / length
            elif forced == 1:
                stiffness_bar = -k_uu
            e_bar = (u_bar - wp.dot(u, u_bar) * u) / length + length_bar * u
        return e_bar, stiffness_bar, rest_bar

    return SimpleNamespace(compute_spring_parts=compute_spring_parts, compute_outer_moments=compute_outer_moments,
                           compute_spring_adjoint=compute_spring_adjoint,
                           compute_spring_parts_tension_only=compute_spring_parts_tension_only,
                           compute_spring_adjoint_tension_only=compute_spring_adjoint_tension_only)


@functools.cache
def string_spring_tangent_functions(scalar, lanes: int = 1) -> SimpleNamespace:
    """Builds the printed spring's forward derivative (``compute_string_spring_printed``), as the
    string step's tangent-linear kernel uses it (``string_step_tangent``): the transpose of
    :func:`string_spring_adjoint_functions`' ``compute_spring_adjoint``. The tangents are
    ``tangent_directions(scalar, lanes)``' values (one direction, or ``lanes`` directions in SIMD
    lanes); the primal ones (``u``, ``l``, ``alpha``, ...) are scalars and ``vec3``.

    With ``K = alpha u u^T + beta I`` (``alpha = -k_s (1 - g)``, ``beta = -k_s g``,
    ``g = max(1 - d/l, 0)``), the tangent of ``K r`` for a fixed ``r`` is
    ``alpha' u (u . r) + alpha (u' (u . r) + u (u' . r)) + beta' r`` (``compute_jacobian_tangent_product``);
    ``K`` is never formed. ``g' = 0`` while the segment is compressed (``1 - d/l <= 0``: the
    clamp's flat side, as the adjoint and Warp's adjoint of ``max`` take it at the switch).
    """
    vec3 = wp.types.vector(3, scalar)
    t = tangent_directions(scalar, lanes)
    TS, TV, outer, dot = t.TS, t.TV, t.outer, t.dot
    vadd, vsub, vscl, sadd, ssub, sneg, sscl = t.vadd, t.vsub, t.vscl, t.sadd, t.ssub, t.sneg, t.sscl

    @wp.func
    def compute_spring_tangent(u: vec3, length: scalar, inv_length: scalar, ratio: scalar, stiffness: scalar,
                               rest_length: scalar, e_dot: TV, stiffness_dot: TS, rest_length_dot: TS):
        """Tangent of the spring of ``e = x_a - x_b`` (its parts ``u, l, 1 - d/l`` from
        ``string_spring_adjoint_functions``' ``compute_spring_parts``, and ``1 / l``: a caller with many
        directions divides once) along ``e' = e_dot``, ``k_s'``, ``d'``: returns ``(u', alpha', beta', f_a')``."""
        one = scalar(1.0)
        geometric = wp.max(ratio, scalar(0.0))
        length_dot = dot(u, e_dot)
        u_dot = vscl(inv_length, vsub(e_dot, outer(u, length_dot)))  # (e' - l' u) / l
        geometric_dot = TS(scalar(0.0))
        if ratio > scalar(0.0):  # (d l' / l - d') / l
            geometric_dot = sscl(inv_length, ssub(sscl(inv_length, sscl(rest_length, length_dot)), rest_length_dot))
        stretch = length - rest_length
        alpha_dot = sadd(sscl(-(one - geometric), stiffness_dot), sscl(stiffness, geometric_dot))
        beta_dot = ssub(sscl(-geometric, stiffness_dot), sscl(stiffness, geometric_dot))
        # f_a' = -(k_s' (l - d) + k_s (l' - d')) u - k_s (l - d) u'
        force_scale_dot = sadd(sscl(stretch, stiffness_dot), sscl(stiffness, ssub(length_dot, rest_length_dot)))
        f_dot = vsub(outer(u, sneg(force_scale_dot)), vscl(stiffness * stretch, u_dot))
        return u_dot, alpha_dot, beta_dot, f_dot

    @wp.func
    def compute_jacobian_product(u: vec3, alpha: scalar, beta: scalar, r: TV):
        """``K r = alpha u (u . r) + beta r``."""
        return vadd(outer(u, sscl(alpha, dot(u, r))), vscl(beta, r))

    @wp.func
    def compute_jacobian_tangent_product(u: vec3, alpha: scalar, u_dot: TV, alpha_dot: TS, beta_dot: TS,
                                         r: vec3):
        """``K' r`` for a fixed ``r`` (the namespace's doc)."""
        ur = wp.dot(u, r)
        return vadd(vadd(outer(u, sscl(ur, alpha_dot)), vscl(alpha, vadd(vscl(ur, u_dot), outer(u, dot(r, u_dot))))),
                    outer(r, beta_dot))

    return SimpleNamespace(compute_spring_tangent=compute_spring_tangent,
                           compute_jacobian_product=compute_jacobian_product,
                           compute_jacobian_tangent_product=compute_jacobian_tangent_product)
