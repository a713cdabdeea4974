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
def string_terms(scalar) -> SimpleNamespace:
    """Builds the string force terms for the float type ``scalar`` (``wp.float32``/``wp.float64``)."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def compute_string_spring(x_a: vec3, x_b: vec3, stiffness: scalar, rest_length: scalar):
        """Spring between neighbours a and b, paper term 1: ``f_a = -k_s (|x_a - x_b| - d) u``.

        Returns the force on ``a`` and ``K_aa = df_a/dx_a`` (and ``K_ab = -K_aa``).

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
        return force, jacobian

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
        compute_string_spring=compute_string_spring,
        compute_internal_friction=compute_internal_friction,
        compute_air_drag=compute_air_drag,
        compute_ground_contact=compute_ground_contact,
        compute_ground_friction=compute_ground_friction,
        compute_string_tie=compute_string_tie,
    )
