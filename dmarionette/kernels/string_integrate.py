"""Time integration of string particles, and the per-string outputs of a step.

``integrate_string_particles`` applies the velocity change solved for the free
particles (backward Euler: ``v1 = v0 + dv``, ``x1 = x0 + h v1``) and moves the top
particle to its attach point on the bar. ``eval_string_tie_force`` evaluates, on the
new state, the force the string's tie puts on its body point (paper eq. 2) and whether
the string is taut (paper §3.2).
"""


import functools

import warp as wp

from .string_model_arrays import string_model_arrays_type
from .string_tie import compute_tie_force


@functools.cache
def string_output_function(scalar):
    """Builds ``compute_string_outputs``: a string's tie force and taut flag from its new state,
    shared by ``eval_string_tie_force`` and the one-launch step (``string_step``)."""
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def compute_string_outputs(x_first: vec3, x_last: vec3, v_last: vec3, tie_x: vec3, tie_v: vec3,
                               tie_stiffness: scalar, tie_damping: scalar, taut_distance: scalar):
        """Paper eq. 2 (the force on the body [N]; ``tie_stiffness``/``tie_damping`` already times
        the string's ``tied`` flag, so a cut tie gives 0) and §3.2 (taut, ``1``, when the
        first-to-last distance exceeds ``taut_distance`` [m], else ``0``)."""
        force = compute_tie_force(tie_x, tie_v, x_last, v_last, tie_stiffness, tie_damping)
        taut = int(0)
        if wp.length(x_last - x_first) > taut_distance:
            taut = 1
        return force, taut

    return compute_string_outputs


@functools.cache
def integrate_string_kernels(scalar):
    """Builds ``(integrate_string_particles, eval_string_tie_force)`` for a float type."""
    vec3 = wp.types.vector(3, scalar)
    compute_string_outputs = string_output_function(scalar)
    StringModelArrays = string_model_arrays_type(scalar)

    @wp.kernel(module="unique")
    def integrate_string_particles(
        # Model:
        model: StringModelArrays,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        particle_dv: wp.array(dtype=vec3),
        # Control:
        top_q: wp.array(dtype=vec3),
        dt: scalar,
        # State out:
        particle_q_out: wp.array(dtype=vec3),
        particle_qd_out: wp.array(dtype=vec3),
    ):
        p = wp.tid()
        s = model.particle_string[p]
        if p == model.string_start[s]:
            # The top particle follows its attach point; its velocity is the one that
            # moves it there in one backward-Euler step.
            target = top_q[s]
            particle_qd_out[p] = (target - particle_q[p]) / dt
            particle_q_out[p] = target
        else:
            v = particle_qd[p] + particle_dv[p]
            particle_qd_out[p] = v
            particle_q_out[p] = particle_q[p] + dt * v

    @wp.kernel(module="unique")
    def eval_string_tie_force(
        # Model:
        model: StringModelArrays,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Control:
        tie_q: wp.array(dtype=vec3),
        tie_qd: wp.array(dtype=vec3),
        # State out:
        tie_force: wp.array(dtype=vec3),
        string_taut: wp.array(dtype=wp.int32),
    ):
        s = wp.tid()
        first = model.string_start[s]
        last = model.string_start[s + 1] - 1
        x = particle_q[last]
        v = particle_qd[last]
        tied = model.string_tied[s]
        # Paper eq. 2, the force on the body (0 for a cut tie: ``tied`` is 1 or 0), and §3.2's taut flag.
        force, taut = compute_string_outputs(particle_q[first], x, v, tie_q[s], tie_qd[s],
                                             tied * model.string_tie_stiffness[s], tied * model.string_tie_damping[s],
                                             model.string_taut_distance[s])
        tie_force[s] = force
        string_taut[s] = taut

    return integrate_string_particles, eval_string_tie_force
