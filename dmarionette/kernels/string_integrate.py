"""Time integration of string particles, and the per-string outputs of a step.

``integrate_string_particles`` applies the velocity change solved for the free
particles (backward Euler: ``v1 = v0 + dv``, ``x1 = x0 + h v1``) and moves the top
particle to its attach point on the bar. ``eval_string_tie_force`` evaluates, on the
new state, the force the string's tie puts on its body point (paper eq. 2) and whether
the string is taut (paper §3.2).
"""


import functools

import warp as wp

from .string_state_arrays import string_arrays_types
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
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)

    @wp.kernel(module="unique")
    def integrate_string_particles(
        # Model:
        model: StringModelArrays,
        # State in:
        state_in: StringStateArrays,
        particle_dv: wp.array(dtype=vec3),
        # Control:
        control: StringControlArrays,
        dt: scalar,
        # State out:
        state_out: StringStateArrays,
    ):
        p = wp.tid()
        s = model.particle_string[p]
        if p == model.string_start[s]:
            # The top particle follows its attach point; its velocity is the one that
            # moves it there in one backward-Euler step.
            target = control.top_q[s]
            state_out.particle_qd[p] = (target - state_in.particle_q[p]) / dt
            state_out.particle_q[p] = target
        else:
            v = state_in.particle_qd[p] + particle_dv[p]
            state_out.particle_qd[p] = v
            state_out.particle_q[p] = state_in.particle_q[p] + dt * v

    @wp.kernel(module="unique")
    def eval_string_tie_force(
        # Model:
        model: StringModelArrays,
        # Control:
        control: StringControlArrays,
        # State in and out (its particles read, its ties' forces and taut flags written):
        state: StringStateArrays,
    ):
        s = wp.tid()
        first = model.string_start[s]
        last = model.string_start[s + 1] - 1
        x = state.particle_q[last]
        v = state.particle_qd[last]
        tied = model.string_tied[s]
        # Paper eq. 2, the force on the body (0 for a cut tie: ``tied`` is 1 or 0), and §3.2's taut flag.
        force, taut = compute_string_outputs(state.particle_q[first], x, v, control.tie_q[s], control.tie_qd[s],
                                             tied * model.string_tie_stiffness[s], tied * model.string_tie_damping[s],
                                             model.string_taut_distance[s])
        state.tie_force[s] = force
        state.string_taut[s] = taut

    return integrate_string_particles, eval_string_tie_force
