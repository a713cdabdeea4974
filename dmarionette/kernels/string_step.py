"""The whole implicit string step in one launch, one string per thread (the plain step's schedule).

``SolverStringImplicit.step`` without a tape, with the paper's printed spring, runs
``integrate_string_implicit`` instead of its five passes (spring, system, solve, integrate,
tie force) (with ``SolverStringImplicit.lanes``, in float64 on the CPU, its laned form with four
strings per thread, ``string_step_lanes``, the same numbers bit for bit). It computes the same numbers with the
same functions, in another order of work:

- each segment's spring (``string_spring.compute_string_spring_printed``) once, carried in
  registers to the particle below instead of through ``segment_force``/``segment_jacobian``;
- each particle's block row (``string_system.compute_string_system_row``, the function
  ``eval_string_system`` calls) assembled and at once eliminated (the forward sweep of the
  block Thomas solve, ``string_solve``), so ``A`` is never stored: only ``C'_j`` and ``d'_j``
  are, for the back substitution;
- the back substitution and backward-Euler integration in one upward sweep, then the tie
  force and taut flag (``string_integrate.compute_string_outputs``).

Why (``docs/performance.md``): the step is bound by the number of scalar float64
instructions, not by launches (about 0.2 µs each in a captured graph). Assembling and
eliminating in one sweep does not store ``A`` (no write and re-read of ``diag``, ``upper``,
``rhs``), evaluates each spring once (the five passes read each segment twice), reads each
string's constants once, and lets the rows between the first and the last compile with their
flags known. Measured: about 1.2x faster than the five passes with the same arithmetic
(with the old assembly the fusion alone bought ~3 %; the rest is the assembly's structure,
``string_system.compute_string_system_row``).

On a tape too: a taped printed-spring step runs this kernel (built with ``keep``, which also
stores the pivot inverses) off the tape and records the hand-written adjoint of the whole step,
``string_step_adjoint`` (Warp's automatic adjoint does not replay the values its loops carry
from particle to particle). The tension-only springs (``StringEffects.tension_only``) keep the
five passes, on a tape or not: their active-set solve re-solves a chain after adding blocks to
``A``, which needs ``A`` stored. Both schedules call the same ``@wp.func``\\ s in the same order,
so they agree bit for bit (``tests/strings/test_string_step_schedules.py``).

Arguments: the model as its ``StringModelArrays``, but the state in, the control and the state out
as arrays one by one, not as the ``StringStateArrays``/``StringControlArrays`` the other step
kernels take (``string_state_arrays``). Warp (1.19) compiles a CPU kernel whose 1D array arguments
are all contiguous with their strides known (``sizeof`` the element; codegen's
``cpu_linear_contiguous``), and a struct's arrays keep their strides at run time: with the structs,
the laned keep step (``string_step_lanes``, the same arguments) was 4-8 % slower with the particles'
arrays in them and 2-5 % slower (some replays 20-60 %) with only the control and the ties' outputs
in them (``benchmarks/ab_lane_kernels.py``, against e8888c7), so the one-launch steps keep arrays.
"""

import functools

import warp as wp

from .string_integrate import string_output_function
from .string_model_arrays import string_constants_function, string_constants_type, string_model_arrays_type
from .string_solve import thomas_row_functions
from .string_spring import string_spring_functions
from .string_system import string_system_row_function


@functools.cache
def integrate_string_implicit_kernel(scalar, effects: tuple[bool, bool, bool, bool, bool], keep: bool = False):
    """Builds ``integrate_string_implicit`` for a float type and an effect set (printed springs).

    Args:
        scalar: ``wp.float64`` or ``wp.float32``.
        effects: ``(gravity, internal_friction, air_drag, ground_contact, ground_friction)``
            as compile-time switches (``StringEffects.as_tuple``).
        keep: also keep the pivot inverses in ``pivot_inverse``, for the step's hand-written
            adjoint (``string_step_adjoint``; the same values, bit for bit). A compile-time
            switch, as for the recorded solve (``string_solve``): the plain step stores nothing more.
    """
    KEEP = keep
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    compute_string_spring = string_spring_functions(scalar).compute_string_spring_printed
    compute_string_system_row = string_system_row_function(scalar, effects)
    compute_string_outputs = string_output_function(scalar)
    StringModelArrays = string_model_arrays_type(scalar)
    StringConstants = string_constants_type(scalar)
    compute_string_constants = string_constants_function(scalar)
    thomas = thomas_row_functions(scalar)
    compute_thomas_first_row, compute_thomas_row = thomas.compute_thomas_first_row, thomas.compute_thomas_row

    @wp.func
    def compute_forward_row(
        p: int,
        j: int,
        is_last: bool,
        x: vec3,
        v: vec3,
        v_prev: vec3,
        f_prev: vec3,
        k_prev: mat33,
        upper_prev: mat33,
        d_prev: vec3,
        c_prev: mat33,
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        particle_mass: wp.array(dtype=scalar),
        constants: StringConstants,
        top_dx: vec3,
        top_dv: vec3,
        tie_x: vec3,
        tie_v: vec3,
        dt: scalar,
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
    ):
        """Row ``p`` (``j = p - start``) of a chain: the spring of the segment below, the block row
        (``compute_string_system_row``) and its forward elimination (``string_solve``), ``C'_p`` and
        ``d'_p`` stored; returns what the next row needs: ``C'_p, d'_p, A_{p,p+1}``, the next
        particle's position and velocity, this one's velocity, the segment below's force and block."""
        zero = scalar(0.0)
        x_next = x
        v_next = vec3(zero)
        f_next = vec3(zero)
        k_next = mat33(zero)
        if not is_last:
            x_next = particle_q[p + 1]
            v_next = particle_qd[p + 1]
            f_next, k_next, _active = compute_string_spring(x, x_next, constants.stiffness, constants.rest_length)
        diag, upper, rhs = compute_string_system_row(
            j, is_last, x, v, v_prev, v_next, particle_mass[p], f_prev, k_prev, f_next, k_next,
            top_dx, top_dv, constants, tie_x, tie_v, dt,
        )
        inv = mat33(zero)
        c = mat33(zero)
        d = vec3(zero)
        if j == 1:
            inv, c, d = compute_thomas_first_row(diag, upper, rhs)
        else:
            inv, c, d = compute_thomas_row(diag, upper, rhs, upper_prev, c_prev, d_prev)
        if wp.static(KEEP):
            pivot_inverse[p] = inv
        scratch_c[p] = c
        scratch_d[p] = d
        return c, d, upper, x_next, v_next, v, f_next, k_next

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_string_implicit(
        # Model:
        model: StringModelArrays,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Control:
        top_q: wp.array(dtype=vec3),
        tie_q: wp.array(dtype=vec3),
        tie_qd: wp.array(dtype=vec3),
        dt: scalar,
        # State out (``pivot_inverse``: only if built with ``keep``):
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        particle_dv: wp.array(dtype=vec3),
        particle_q_out: wp.array(dtype=vec3),
        particle_qd_out: wp.array(dtype=vec3),
        tie_force: wp.array(dtype=vec3),
        string_taut: wp.array(dtype=wp.int32),
    ):
        s = wp.tid()
        start = model.string_start[s]
        last = model.string_start[s + 1] - 1
        zero = scalar(0.0)
        particle_mass = model.particle_mass
        constants = compute_string_constants(model, s)  # the string's constants, read once
        tie_x = tie_q[s]
        tie_v = tie_qd[s]
        top = top_q[s]
        # Motion of the kinematic top particle over the step.
        top_dx = top - particle_q[start]
        top_dv = top_dx / dt - particle_qd[start]

        # Forward sweep: assemble row p (the segment above carried from p - 1) and eliminate it.
        # The first row (next to the top) and the last (the tie) apart, so that the rows between
        # are compiled with their flags known (``compute_forward_row`` is inlined).
        x = particle_q[start + 1]
        f_prev, k_prev, _active = compute_string_spring(particle_q[start], x, constants.stiffness,
                                                        constants.rest_length)
        c, d, upper, x_next, v_next, v, f_next, k_next = compute_forward_row(
            start + 1, 1, start + 1 == last, x, particle_qd[start + 1], particle_qd[start], f_prev, k_prev,
            mat33(zero), vec3(zero), mat33(zero), particle_q, particle_qd, particle_mass, constants, top_dx, top_dv,
            tie_x, tie_v, dt, pivot_inverse, scratch_c, scratch_d)
        for p in range(start + 2, last):
            c, d, upper, x_next, v_next, v, f_next, k_next = compute_forward_row(
                p, 2, False, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q, particle_qd, particle_mass,
                constants, top_dx, top_dv, tie_x, tie_v, dt, pivot_inverse, scratch_c, scratch_d)
        if last > start + 1:
            c, d, upper, x_next, v_next, v, f_next, k_next = compute_forward_row(
                last, last - start, True, x_next, v_next, v, f_next, k_next, upper, d, c, particle_q, particle_qd,
                particle_mass, constants, top_dx, top_dv, tie_x, tie_v, dt, pivot_inverse, scratch_c, scratch_d)
        d_prev = d

        # Back substitution (x_j = d'_j - C'_j x_{j+1}) and v1 = v0 + dv, x1 = x0 + h v1, upwards.
        dv = d_prev
        for i in range(last - start):
            p = last - i
            if p < last:
                dv = scratch_d[p] - scratch_c[p] * dv
            particle_dv[p] = dv
            v1 = particle_qd[p] + dv
            particle_qd_out[p] = v1
            particle_q_out[p] = particle_q[p] + dt * v1
        particle_dv[start] = vec3(zero)
        # The top particle follows its attach point (string_integrate.integrate_string_particles).
        particle_qd_out[start] = (top - particle_q[start]) / dt
        particle_q_out[start] = top
        force, taut = compute_string_outputs(
            particle_q_out[start], particle_q_out[last], particle_qd_out[last], tie_x, tie_v,
            constants.tie_stiffness, constants.tie_damping, model.string_taut_distance[s],
        )
        tie_force[s] = force
        string_taut[s] = taut

    return integrate_string_implicit
