"""Force terms of a particle string (paper §2.2), as Warp functions.

Each term returns the force on one particle and its Jacobians with respect to that
particle's position (``K = df/dx``) and velocity (``D = df/dv``); the implicit
integrator assembles them into ``A = M - h D - h^2 K`` (Baraff & Witkin 1998).

The per-particle terms (internal friction, air drag, ground contact and friction) are
defined here; the two terms that other parts of the simulator also evaluate live in files
of their own and are gathered into the namespace :func:`string_terms` returns: the segment
spring (term 1, :mod:`string_spring`) and the tie to the body (eq. 2, :mod:`string_tie`).
Gravity (term 3) is ``m g`` in ``string_system.eval_string_system``.

The functions are built per float type (float64 by default, float32 on request) by
:func:`string_terms`, which caches one set per type.
"""


import functools
from types import SimpleNamespace

import warp as wp

from .string_spring import string_spring_functions
from .string_tie import compute_tie_force


@functools.cache
def string_terms(scalar, tension_only: bool = False) -> SimpleNamespace:
    """Builds the string force terms for the float type ``scalar`` (``wp.float32``/``wp.float64``);
    ``tension_only`` chooses the segment spring (``compute_string_spring``): the paper's
    printed spring (default) or the tension-only one (``StringEffects.tension_only``)."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    spring = string_spring_functions(scalar)

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

        ``f_string = -f_body`` (``string_tie.compute_tie_force``). Returns the force on the
        particle, ``K = -k I`` and ``D = -k_d I``.
        """
        eye = wp.identity(n=3, dtype=scalar)
        force = -compute_tie_force(x_body, v_body, x, v, stiffness, damping)
        return force, -stiffness * eye, -damping * eye

    return SimpleNamespace(
        vec3=vec3,
        mat33=mat33,
        compute_string_spring=(spring.compute_string_spring_tension_only if tension_only
                               else spring.compute_string_spring_printed),
        compute_string_tension=spring.compute_string_tension,
        compute_internal_friction=compute_internal_friction,
        compute_air_drag=compute_air_drag,
        compute_ground_contact=compute_ground_contact,
        compute_ground_friction=compute_ground_friction,
        compute_string_tie=compute_string_tie,
    )
