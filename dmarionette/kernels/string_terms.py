"""Force terms of a particle string (paper §2.2), as Warp functions.

Each term returns the force on one particle and its Jacobians with respect to that
particle's position (``K = df/dx``) and velocity (``D = df/dv``); the implicit
integrator assembles them into ``A = M - h D - h^2 K`` (Baraff & Witkin 1998).

The functions are built per float type (float64 by default, float32 on request) by
:func:`string_terms`, which caches one set per type.
"""


import functools
from types import SimpleNamespace

import warp as wp


@functools.cache
def string_terms(scalar, tension_only: bool = False) -> SimpleNamespace:
    """Builds the string force terms for the float type ``scalar`` (``wp.float32``/``wp.float64``);
    ``tension_only`` chooses the segment spring (``compute_string_spring``): the paper's
    printed spring (default) or the tension-only one (``StringEffects.tension_only``)."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

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
        ground penalty (``tests/test_hard_cases_strings.py``). Here the potential is
        ``1/2 k_s max(l - d, 0)^2`` (``string_model.string_energy``), which is convex in the
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
        pushes), and it costs 5-22 % per string step. It passes the hard cases tried with it,
        strings alone and in a marionette, with the puppet at the string rate and at 30 Hz
        (``tests/test_hard_cases_strings.py``, ``tests/test_tension_only_marionette.py``;
        at 30 Hz it was refused while the coupling extrapolated the tie path as ``x + H v``,
        ``settings_check``).
        """
        e = x_a - x_b
        length = wp.length(e)
        zero = scalar(0.0)
        u = vec3(zero)
        if length > zero:
            u = e / length  # coincident particles (a string folded onto itself): no direction, no force
        force = -stiffness * wp.max(length - rest_length, zero) * u
        taut = int(0)
        jacobian = wp.outer(-stiffness * u, u)
        if length > rest_length:
            taut = 1
            geometric = scalar(1.0) - rest_length / length
            eye = wp.identity(n=3, dtype=scalar)
            jacobian = wp.outer(-stiffness * (scalar(1.0) - geometric) * u, u) - (stiffness * geometric) * eye
        return force, jacobian, taut

    @wp.func
    def compute_internal_friction(v_a: vec3, v_b: vec3, friction: scalar):
        """Internal friction between neighbours, paper term 2: ``f_a = -k_f (v_a - v_b)``.

        As printed in the paper it damps the whole relative velocity (also a rigid
        rotation of the segment), not only the stretch rate. Returns the force on ``a``
        and ``D_aa = -k_f I`` (``D_ab = -D_aa``).
        """
        eye = wp.identity(n=3, dtype=scalar)
        return -friction * (v_a - v_b), -friction * eye

    @wp.func
    def compute_air_drag(v: vec3, drag: scalar):
        """Air resistance, paper term 4: ``f = -k_air v``; returns force and ``D``."""
        eye = wp.identity(n=3, dtype=scalar)
        return -drag * v, -drag * eye

    @wp.func
    def compute_ground_contact(
        x: vec3, v: vec3, ground_height: scalar, stiffness: scalar, absorption: scalar
    ):
        """Ground repulsion and absorption, paper term 6, for a particle below the ground.

        Deliberate deviation: the paper prints ``f_rep = v_y (h_ground - p_y)`` and
        ``f_abs = v_y k_abs``, which are dimensionally loose (a velocity times a length is
        not a force, and the absorption has no sign that opposes motion). We use a
        penalty spring ``f_y = k_rep (h_ground - y)`` for repulsion and a damper
        ``f_y = -k_abs v_y`` for absorption. Returns force, ``K`` and ``D``.
        """
        depth = ground_height - x[1]
        zero = scalar(0.0)
        force = vec3(zero, stiffness * depth - absorption * v[1], zero)
        stiff = mat33(zero)
        stiff[1, 1] = -stiffness
        damp = mat33(zero)
        damp[1, 1] = -absorption
        return force, stiff, damp

    @wp.func
    def compute_ground_friction(v: vec3, friction: scalar):
        """Ground friction in x and z, paper term 5: ``f_x = -k_ground v_x``, ``f_z = -k_ground v_z``."""
        zero = scalar(0.0)
        damp = mat33(zero)
        damp[0, 0] = -friction
        damp[2, 2] = -friction
        return vec3(-friction * v[0], zero, -friction * v[2]), damp

    @wp.func
    def compute_string_tie(x: vec3, v: vec3, x_body: vec3, v_body: vec3, stiffness: scalar, damping: scalar):
        """The tie of a string's last particle to a body point, paper eq. 2, seen from the string.

        ``f_string = k (x_body - x) + k_d (v_body - v) = -f_body``. Returns the force on
        the particle, ``K = -k I`` and ``D = -k_d I``.
        """
        eye = wp.identity(n=3, dtype=scalar)
        force = stiffness * (x_body - x) + damping * (v_body - v)
        return force, -stiffness * eye, -damping * eye

    return SimpleNamespace(
        vec3=vec3,
        mat33=mat33,
        compute_string_spring=compute_string_spring_tension_only if tension_only else compute_string_spring_printed,
        compute_internal_friction=compute_internal_friction,
        compute_air_drag=compute_air_drag,
        compute_ground_contact=compute_ground_contact,
        compute_ground_friction=compute_ground_friction,
        compute_string_tie=compute_string_tie,
    )
