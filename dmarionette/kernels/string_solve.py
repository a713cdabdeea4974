"""Exact O(n) solve of each chain's block-tridiagonal system, with its adjoint.

``solve_string_system`` runs the block Thomas algorithm, one chain per thread, on the
free particles ``1 .. n-1`` of each string: forward elimination
``C'_j = (A_jj - L_j C'_{j-1})^{-1} A_{j,j+1}``, ``d'_j = (A_jj - L_j C'_{j-1})^{-1}(b_j - L_j d'_{j-1})``
with ``L_j = A_{j-1,j}^T``, then back substitution ``x_j = d'_j - C'_j x_{j+1}``.
The system is symmetric positive definite (see ``compute_string_spring``), so no pivoting
is needed.

``solve_string_system_active`` is the same solve with the tension-only springs' active set
resolved (``string_spring.compute_string_spring_tension_only``): a segment that was slack at the start of
the step is not in the system; if the solution ends it taut, its block (``K``, assembled as
``eval_string_system`` would) is added to the chain's system in place and the chain is
solved again, until no further segment ends taut (each pass only adds segments, so it ends;
at most ``MAX_ACTIVE_SET_PASSES`` re-solves, a cap the tests never reach). Only chains where a
segment snaps taut pay for a second solve.

Its loop carries values from one particle to the next, which Warp's automatic adjoint
does not replay correctly, so the solve has a hand-written adjoint instead:
for ``A x = b`` with ``A`` symmetric, ``b_bar = A^{-1} x_bar`` (the same solve) and
``A_bar = -b_bar x^T``, restricted to the stored blocks: ``diag_bar_j = -b_bar_j x_j^T`` and
``upper_bar_j = -(b_bar_j x_{j+1}^T + x_j b_bar_{j+1}^T)`` (``A_{j,j+1}`` also stands, transposed,
at ``(j+1, j)``). Under a tape the solve is ``solve_string_system_recorded`` (the same values
bit for bit), which keeps the pivot inverses (and ``C'``), so that the adjoint's solve is
substitutions only, without re-factorising; the workspace of a recorded step must then not
be reused before its adjoint has run (each step under a tape has its own). The untaped
solve stores nothing more.
"""


import functools
from types import SimpleNamespace
from typing import Any

import warp as wp

from .string_state_arrays import string_arrays_types

MAX_ACTIVE_SET_PASSES = 8  # re-solves per chain and step at most (each activates >= 1 segment)


@functools.cache
def thomas_row_functions(scalar) -> SimpleNamespace:
    """Builds the two row steps of the block Thomas forward elimination for a float type, shared by
    the solve kernels here and the one-launch step (``string_step``), so both give the same bits.

    Returns:
        A namespace with ``compute_thomas_first_row(A_jj, A_{j,j+1}, b_j)`` (the chain's first free
        row) and ``compute_thomas_row(A_jj, A_{j,j+1}, b_j, A_{j-1,j}, C'_{j-1}, d'_{j-1})``, each
        returning ``(pivot inverse, C'_j, d'_j)``.
    """
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def compute_thomas_first_row(diag: mat33, upper: mat33, rhs: vec3):
        """``inv = A_jj^{-1}``, ``C'_j = inv A_{j,j+1}``, ``d'_j = inv b_j``."""
        inv = wp.inverse(diag)
        return inv, inv * upper, inv * rhs

    @wp.func
    def compute_thomas_row(diag: mat33, upper: mat33, rhs: vec3, upper_prev: mat33, c_prev: mat33, d_prev: vec3):
        """``inv = (A_jj - L_j C'_{j-1})^{-1}`` with ``L_j = A_{j-1,j}^T``, ``C'_j = inv A_{j,j+1}``,
        ``d'_j = inv (b_j - L_j d'_{j-1})``."""
        lower = wp.transpose(upper_prev)
        inv = wp.inverse(diag - lower * c_prev)
        return inv, inv * upper, inv * (rhs - lower * d_prev)

    return SimpleNamespace(compute_thomas_first_row=compute_thomas_first_row, compute_thomas_row=compute_thomas_row)


@functools.cache
def solve_string_system_kernels(scalar):
    """Builds ``(solve_string_system, solve_string_system_active, solve_string_system_recorded,
    solve_string_system_adjoint)`` for a float type."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    thomas = thomas_row_functions(scalar)
    compute_thomas_first_row, compute_thomas_row = thomas.compute_thomas_first_row, thomas.compute_thomas_row
    StringModelArrays, StringStateArrays, StringControlArrays = string_arrays_types(scalar)

    @wp.func
    def compute_back_substitution(
        string_start: wp.array(dtype=wp.int32),
        s: int,
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        solution: wp.array(dtype=vec3),
    ):
        """Back substitution ``x_j = d'_j - C'_j x_{j+1}`` of chain ``s`` (its top particle: 0)."""
        start = string_start[s]
        last = string_start[s + 1] - 1
        solution[last] = scratch_d[last]
        for i in range(last - start - 1):
            p = last - 1 - i
            solution[p] = scratch_d[p] - scratch_c[p] * solution[p + 1]
        solution[start] = vec3(scalar(0.0))

    def block_thomas(keep: bool):
        KEEP = keep

        @wp.func
        def compute_block_thomas(
            string_start: wp.array(dtype=wp.int32),
            s: int,
            system_diag: wp.array(dtype=mat33),
            system_upper: wp.array(dtype=mat33),
            rhs: wp.array(dtype=vec3),
            pivot_inverse: wp.array(dtype=mat33),
            scratch_c: wp.array(dtype=mat33),
            scratch_d: wp.array(dtype=vec3),
            solution: wp.array(dtype=vec3),
        ):
            """The block Thomas solve of chain ``s``; built with ``keep`` it also keeps the pivot
            inverses ``(A_jj - L_j C'_{j-1})^{-1}`` in ``pivot_inverse`` for the adjoint (the same
            values, bit for bit); without, ``pivot_inverse`` is not touched. A compile-time
            switch: a runtime flag cost the untaped solve 6 % (measured)."""
            start = string_start[s]
            last = string_start[s + 1] - 1
            # Forward elimination over the free particles start+1 .. last.
            inv, c, d = compute_thomas_first_row(system_diag[start + 1], system_upper[start + 1], rhs[start + 1])
            if wp.static(KEEP):
                pivot_inverse[start + 1] = inv
            scratch_c[start + 1] = c
            scratch_d[start + 1] = d
            for p in range(start + 2, last + 1):
                inv, c, d = compute_thomas_row(system_diag[p], system_upper[p], rhs[p], system_upper[p - 1],
                                               scratch_c[p - 1], scratch_d[p - 1])
                if wp.static(KEEP):
                    pivot_inverse[p] = inv
                scratch_c[p] = c
                scratch_d[p] = d
            compute_back_substitution(string_start, s, scratch_c, scratch_d, solution)

        return compute_block_thomas

    compute_block_thomas = block_thomas(False)
    compute_block_thomas_keep = block_thomas(True)

    @wp.func
    def compute_block_substitution(
        string_start: wp.array(dtype=wp.int32),
        s: int,
        system_upper: wp.array(dtype=mat33),
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        scratch_d: wp.array(dtype=vec3),
        solution: wp.array(dtype=vec3),
    ):
        """``compute_block_thomas`` for another right-hand side of a chain that
        ``compute_block_thomas_keep`` factorised (pivot inverses and ``C'``): substitutions only."""
        start = string_start[s]
        last = string_start[s + 1] - 1
        scratch_d[start + 1] = pivot_inverse[start + 1] * rhs[start + 1]
        for p in range(start + 2, last + 1):
            lower = wp.transpose(system_upper[p - 1])
            scratch_d[p] = pivot_inverse[p] * (rhs[p] - lower * scratch_d[p - 1])
        compute_back_substitution(string_start, s, scratch_c, scratch_d, solution)

    def solve_kernel(name: str, compute_solve):

        @wp.kernel(module="unique", enable_backward=False, name=name)
        def solve_string_system(
            # Model:
            string_start: wp.array(dtype=wp.int32),
            # State in:
            system_diag: wp.array(dtype=mat33),
            system_upper: wp.array(dtype=mat33),
            system_rhs: wp.array(dtype=vec3),
            # State out (``pivot_inverse``: the factorisation kept for the adjoint, recorded solve only):
            pivot_inverse: wp.array(dtype=mat33),
            scratch_c: wp.array(dtype=mat33),
            scratch_d: wp.array(dtype=vec3),
            particle_dv: wp.array(dtype=vec3),
        ):
            """Block Thomas, one chain per thread; ``solve_string_system_recorded`` (the same values,
            bit for bit) also keeps the pivot inverses, ``solve_string_system`` leaves them."""
            s = wp.tid()
            compute_solve(
                string_start, s, system_diag, system_upper, system_rhs, pivot_inverse, scratch_c, scratch_d, particle_dv
            )

        return solve_string_system

    solve_string_system = solve_kernel("solve_string_system", compute_block_thomas)
    solve_string_system_recorded = solve_kernel("solve_string_system_recorded", compute_block_thomas_keep)

    @wp.func
    def compute_segment_activation(
        string_start: wp.array(dtype=wp.int32),
        s: int,
        rest_length: scalar,
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        top_q: wp.array(dtype=vec3),
        dt: scalar,
        segment_jacobian_active: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        segment_active: wp.array(dtype=wp.int32),
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        system_rhs: wp.array(dtype=vec3),
    ):
        """Activates the inactive segments of chain ``s`` that the solution ``dv`` ends taut
        (``x1 = x0 + dt (v0 + dv)``; the top particle ends at ``top_q``), adding their blocks
        to the system as ``eval_string_system`` assembles them; returns how many."""
        start = string_start[s]
        last = string_start[s + 1] - 1
        added = int(0)
        for p in range(start, last):
            if segment_active[p] == 0:
                x_b = particle_q[p + 1] + dt * (particle_qd[p + 1] + particle_dv[p + 1])
                x_a = top_q[s]
                if p > start:
                    x_a = particle_q[p] + dt * (particle_qd[p] + particle_dv[p])
                if wp.length(x_a - x_b) > rest_length:
                    segment_active[p] = 1
                    added += 1
                    k = segment_jacobian_active[p]
                    hhk = (dt * dt) * k
                    v_b = particle_qd[p + 1]
                    if p == start:
                        # Row of particle start+1: h^2 K v + h K_{j0} dx_0 with K_{j0} = -K.
                        system_rhs[p + 1] = system_rhs[p + 1] + hhk * v_b - dt * (k * (top_q[s] - particle_q[start]))
                    else:
                        v_a = particle_qd[p]
                        system_diag[p] = system_diag[p] - hhk
                        system_upper[p] = system_upper[p] + hhk
                        system_rhs[p] = system_rhs[p] + hhk * (v_a - v_b)
                        system_rhs[p + 1] = system_rhs[p + 1] + hhk * (v_b - v_a)
                    system_diag[p + 1] = system_diag[p + 1] - hhk
        return added

    @wp.kernel(module="unique", enable_backward=False)
    def solve_string_system_active(
        # Model:
        model: StringModelArrays,
        # State in:
        state_in: StringStateArrays,
        segment_jacobian_active: wp.array(dtype=mat33),
        # Control:
        control: StringControlArrays,
        dt: scalar,
        # State in and out (segments activated, their blocks added):
        segment_active: wp.array(dtype=wp.int32),
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        system_rhs: wp.array(dtype=vec3),
        # State out:
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        particle_dv: wp.array(dtype=vec3),
    ):
        s = wp.tid()
        string_start = model.string_start
        # (keeps nothing: its pivot_inverse argument, here scratch_c, is not touched)
        compute_block_thomas(
            string_start, s, system_diag, system_upper, system_rhs, scratch_c, scratch_c, scratch_d, particle_dv
        )
        for _pass in range(MAX_ACTIVE_SET_PASSES):
            added = compute_segment_activation(
                string_start, s, model.string_rest_length[s], state_in.particle_q, state_in.particle_qd,
                control.top_q, dt,
                segment_jacobian_active, particle_dv, segment_active, system_diag, system_upper, system_rhs,
            )
            if added == 0:
                break
            compute_block_thomas(
                string_start, s, system_diag, system_upper, system_rhs, scratch_c, scratch_c, scratch_d, particle_dv
            )

    @wp.kernel(module="unique", enable_backward=False)
    def solve_string_system_adjoint(
        # Model:
        string_start: wp.array(dtype=wp.int32),
        # State in (``solve_string_system_recorded``'s factorisation and solution):
        system_upper: wp.array(dtype=mat33),
        pivot_inverse: wp.array(dtype=mat33),
        scratch_c: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        # State out (scratch):
        scratch_d: wp.array(dtype=vec3),
        scratch_rhs_bar: wp.array(dtype=vec3),
        # Adjoint in and out (read, then consumed: zeroed, as Warp's adjoint of a store does):
        particle_dv_grad: wp.array(dtype=vec3),
        # Adjoint out (accumulated):
        system_diag_grad: wp.array(dtype=mat33),
        system_upper_grad: wp.array(dtype=mat33),
        system_rhs_grad: wp.array(dtype=vec3),
    ):
        """``b_bar = A^{-1} x_bar`` and ``A_bar = -b_bar x^T`` on the stored blocks (module doc),
        added to the gradients of the system; ``x_bar`` (``particle_dv_grad``) is consumed."""
        s = wp.tid()
        start = string_start[s]
        last = string_start[s + 1] - 1
        # b_bar = A^{-1} x_bar, substitutions only (A's factorisation is the forward's).
        compute_block_substitution(
            string_start, s, system_upper, pivot_inverse, scratch_c, particle_dv_grad, scratch_d, scratch_rhs_bar
        )
        for p in range(start + 1, last + 1):
            b_bar = scratch_rhs_bar[p]
            x = particle_dv[p]
            system_rhs_grad[p] = system_rhs_grad[p] + b_bar
            system_diag_grad[p] = system_diag_grad[p] - wp.outer(b_bar, x)
            if p < last:
                upper_bar = wp.outer(b_bar, particle_dv[p + 1]) + wp.outer(x, scratch_rhs_bar[p + 1])
                system_upper_grad[p] = system_upper_grad[p] - upper_bar
        for p in range(start, last + 1):
            particle_dv_grad[p] = vec3(scalar(0.0))  # consumed, as Warp's own adjoints do

    return solve_string_system, solve_string_system_active, solve_string_system_recorded, solve_string_system_adjoint


@wp.kernel
def copy_particle_dv(
    # State in:
    src: wp.array(dtype=Any),
    # State out:
    dst: wp.array(dtype=Any),
):
    """``dst = src``: the taped tension-only step takes the velocity change of its unrecorded
    active-set pass (launched off the tape; ``strings/solver.py`` says why)."""
    i = wp.tid()
    dst[i] = src[i]
