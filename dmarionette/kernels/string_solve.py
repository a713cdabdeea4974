"""Exact O(n) solve of each chain's block-tridiagonal system, with its adjoint.

``solve_string_system`` runs the block Thomas algorithm, one chain per thread, on the
free particles ``1 .. n-1`` of each string: forward elimination
``C'_j = (A_jj - L_j C'_{j-1})^{-1} A_{j,j+1}``, ``d'_j = (A_jj - L_j C'_{j-1})^{-1}(b_j - L_j d'_{j-1})``
with ``L_j = A_{j-1,j}^T``, then back substitution ``x_j = d'_j - C'_j x_{j+1}``.
The system is symmetric positive definite (see ``compute_string_spring``), so no pivoting
is needed.

Its loop carries values from one particle to the next, which Warp's automatic adjoint
does not replay correctly, so the solve has a hand-written adjoint instead:
for ``A x = b`` with ``A`` symmetric, ``b_bar = A^{-1} x_bar`` (the same solve) and
``A_bar = -b_bar x^T``, restricted to the stored blocks: ``diag_bar_j = -b_bar_j x_j^T`` and
``upper_bar_j = -(b_bar_j x_{j+1}^T + x_j b_bar_{j+1}^T)`` (``A_{j,j+1}`` also stands, transposed,
at ``(j+1, j)``).
"""


import functools

import warp as wp


@functools.cache
def solve_string_system_kernels(scalar):
    """Builds ``(solve_string_system, solve_string_system_adjoint)`` for a float type."""
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def compute_block_thomas(
        string_start: wp.array(dtype=wp.int32),
        s: int,
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        solution: wp.array(dtype=vec3),
    ):
        start = string_start[s]
        last = string_start[s + 1] - 1
        # Forward elimination over the free particles start+1 .. last.
        inv = wp.inverse(system_diag[start + 1])
        scratch_c[start + 1] = inv * system_upper[start + 1]
        scratch_d[start + 1] = inv * rhs[start + 1]
        for p in range(start + 2, last + 1):
            lower = wp.transpose(system_upper[p - 1])
            inv = wp.inverse(system_diag[p] - lower * scratch_c[p - 1])
            scratch_c[p] = inv * system_upper[p]
            scratch_d[p] = inv * (rhs[p] - lower * scratch_d[p - 1])
        # Back substitution.
        solution[last] = scratch_d[last]
        for i in range(last - start - 1):
            p = last - 1 - i
            solution[p] = scratch_d[p] - scratch_c[p] * solution[p + 1]
        solution[start] = vec3(scalar(0.0))

    @wp.kernel(module="unique", enable_backward=False)
    def solve_string_system(
        # Model:
        string_start: wp.array(dtype=wp.int32),
        # State in:
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        system_rhs: wp.array(dtype=vec3),
        # State out:
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        particle_dv: wp.array(dtype=vec3),
    ):
        s = wp.tid()
        compute_block_thomas(
            string_start, s, system_diag, system_upper, system_rhs, scratch_c, scratch_d, particle_dv
        )

    @wp.kernel(module="unique", enable_backward=False)
    def solve_string_system_adjoint(
        # Model:
        string_start: wp.array(dtype=wp.int32),
        # State in:
        system_diag: wp.array(dtype=mat33),
        system_upper: wp.array(dtype=mat33),
        particle_dv: wp.array(dtype=vec3),
        particle_dv_grad: wp.array(dtype=vec3),
        # State out:
        scratch_c: wp.array(dtype=mat33),
        scratch_d: wp.array(dtype=vec3),
        scratch_rhs_bar: wp.array(dtype=vec3),
        system_diag_grad: wp.array(dtype=mat33),
        system_upper_grad: wp.array(dtype=mat33),
        system_rhs_grad: wp.array(dtype=vec3),
    ):
        s = wp.tid()
        start = string_start[s]
        last = string_start[s + 1] - 1
        compute_block_thomas(
            string_start, s, system_diag, system_upper, particle_dv_grad, scratch_c, scratch_d, scratch_rhs_bar
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

    return solve_string_system, solve_string_system_adjoint
