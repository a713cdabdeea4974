"""The implicit (backward Euler) string stepper, paper §2.2.

One step is five named passes::

    eval_string_spring     each segment's spring force and stiffness (printed or tension-only), once per segment
    eval_string_system     forces and Jacobians of every term -> block-tridiagonal A dv = b
    solve_string_system    exact O(n) block Thomas solve, one chain per thread (tension-only springs:
                           segments the solution ends taut are activated, the chain solved again)
    integrate_string       v1 = v0 + dv, x1 = x0 + h v1; the top particle follows its bar
    eval_string_tie_force  eq. 2 force on each body point, taut flags (paper §3.2)

Under a ``wp.Tape`` each step allocates its own intermediates (one array per step, as
Warp's reverse pass needs) and the solve records its hand-written adjoint. The active set of
the tension-only springs (which segments are in the system) is found first by an unrecorded
pass; the recorded pass then assembles and solves the system with that active set, so the
gradient is that of the step with the active set held fixed (the derivative of the
piecewise-smooth step away from its kinks).
"""

from __future__ import annotations

import dataclasses

import warp as wp

from dmarionette.kernels.string_integrate import integrate_string_kernels
from dmarionette.kernels.string_solve import solve_string_system_kernels
from dmarionette.kernels.string_system import eval_string_spring_kernel, eval_string_system_kernel
from dmarionette.strings.model import StringControl, StringModel, StringState

__all__ = ["SolverStringImplicit", "StringWorkspace"]


@dataclasses.dataclass
class StringWorkspace:
    """Intermediate arrays of one step (segment springs, block rows of ``A``, ``b``, ``dv``, scratch)."""

    segment_force: wp.array
    segment_jacobian: wp.array
    segment_jacobian_active: wp.array
    segment_active: wp.array
    system_diag: wp.array
    system_upper: wp.array
    system_rhs: wp.array
    particle_dv: wp.array
    scratch_c: wp.array
    scratch_d: wp.array
    scratch_rhs_bar: wp.array
    scratch_inverse: wp.array  # pivot inverses of a recorded solve, read by its adjoint

    @classmethod
    def allocate(cls, model: StringModel, requires_grad: bool) -> StringWorkspace:
        n = model.particle_count
        with wp.ScopedDevice(model.device):
            def zeros(dtype, grad):
                return wp.zeros(n, dtype=dtype, requires_grad=grad)

            return cls(
                segment_force=zeros(model.vec3, requires_grad),
                segment_jacobian=zeros(model.mat33, requires_grad),
                segment_jacobian_active=zeros(model.mat33, False),  # read only by the unrecorded solve
                segment_active=zeros(wp.int32, False),
                system_diag=zeros(model.mat33, requires_grad),
                system_upper=zeros(model.mat33, requires_grad),
                system_rhs=zeros(model.vec3, requires_grad),
                particle_dv=zeros(model.vec3, requires_grad),
                scratch_c=zeros(model.mat33, False),
                scratch_d=zeros(model.vec3, False),
                scratch_rhs_bar=zeros(model.vec3, False),
                scratch_inverse=zeros(model.mat33, False),
            )


def _active_tape():
    return wp._src.context.runtime.tape


class SolverStringImplicit:
    """Backward-Euler stepper for a :class:`StringModel`.

    Args:
        model: the strings to simulate; its ``effects`` choose the kernels compiled.
    """

    def __init__(self, model: StringModel):
        self.model = model
        self._tension_only = model.effects.tension_only
        self._eval_spring = eval_string_spring_kernel(model.scalar, self._tension_only)
        self._eval_system = eval_string_system_kernel(model.scalar, model.effects.as_tuple())
        (self._solve, self._solve_active, self._solve_recorded,
         self._solve_adjoint) = solve_string_system_kernels(model.scalar)
        self._integrate, self._eval_tie = integrate_string_kernels(model.scalar)
        self._workspace = StringWorkspace.allocate(model, requires_grad=False)
        self._none_forced = wp.zeros(model.particle_count, dtype=wp.int32, device=model.device)

    def step(self, state_in: StringState, state_out: StringState, control: StringControl, dt: float) -> None:
        """Advances the strings by ``dt`` seconds from ``state_in`` into ``state_out``.

        ``state_out`` must be a different object from ``state_in``.
        """
        m = self.model
        tape = _active_tape()
        h = m.scalar(dt)
        forced = self._none_forced
        if tape is not None and self._tension_only:
            # The active set, unrecorded (segments taut at the start or at the end of the step),
            # in arrays of this step's own (the recorded pass reads the flags again backwards) ...
            ws = StringWorkspace.allocate(m, requires_grad=False)
            self.eval_active_set(state_in, control, h, ws)
            forced = ws.segment_active
            # ... then the recorded step with that active set.
            ws = StringWorkspace.allocate(m, requires_grad=True)
        elif tape is not None:
            ws = StringWorkspace.allocate(m, requires_grad=True)
        else:
            ws = self._workspace
        self.eval_string_spring(state_in, forced, ws)  # spring force and stiffness per segment
        self.eval_string_system(state_in, control, h, ws)  # all force terms -> A dv = b
        if tape is None and self._tension_only:
            self.solve_string_system_active(state_in, control, h, ws)  # block Thomas + active set
        else:
            self.solve_string_system(ws, tape)  # block Thomas (with the active set found above)
        self.integrate_string(state_in, state_out, control, h, ws)  # v1 = v0 + dv, x1 = x0 + h v1
        self.eval_string_tie_force(state_out, control)  # eq. 2 force on bodies, taut flags

    def eval_active_set(self, state_in, control, h, ws: StringWorkspace) -> None:
        """Tension-only springs: the active set of a step from ``state_in`` (segments taut at
        the start or at the end of the step) into ``ws.segment_active``, and that step's
        ``ws.particle_dv``; never recorded, even under a tape (``ws`` needs no gradients)."""
        runtime = wp._src.context.runtime
        tape, runtime.tape = runtime.tape, None
        try:
            self.eval_string_spring(state_in, self._none_forced, ws)
            self.eval_string_system(state_in, control, h, ws)
            self.solve_string_system_active(state_in, control, h, ws)
        finally:
            runtime.tape = tape

    def eval_string_spring(self, state_in, forced, ws: StringWorkspace) -> None:
        m = self.model
        wp.launch(
            self._eval_spring,
            dim=m.particle_count,
            inputs=[m.particle_string, m.string_start, m.string_stiffness, m.string_rest_length,
                    state_in.particle_q, forced],
            outputs=[ws.segment_force, ws.segment_jacobian, ws.segment_jacobian_active, ws.segment_active],
            device=m.device,
        )

    def eval_string_system(self, state_in, control, h, ws: StringWorkspace) -> None:
        m = self.model
        wp.launch(
            self._eval_system,
            dim=m.particle_count,
            inputs=[
                m.particle_string, m.string_start, m.particle_mass,
                m.string_internal_friction, m.string_air_drag,
                m.string_ground_stiffness, m.string_ground_absorption, m.string_ground_friction,
                m.string_tie_stiffness, m.string_tie_damping, m.string_tied,
                m.gravity, m.ground_height,
                state_in.particle_q, state_in.particle_qd, ws.segment_force, ws.segment_jacobian,
                control.top_q, control.tie_q, control.tie_qd, h,
            ],
            outputs=[ws.system_diag, ws.system_upper, ws.system_rhs],
            device=m.device,
        )

    def solve_string_system_active(self, state_in, control, h, ws: StringWorkspace) -> None:
        """The solve with the springs' active set resolved in place (not differentiable)."""
        m = self.model
        wp.launch(
            self._solve_active,
            dim=m.string_count,
            inputs=[m.string_start, m.string_rest_length, state_in.particle_q, state_in.particle_qd,
                    ws.segment_jacobian_active, control.top_q, h],
            outputs=[ws.segment_active, ws.system_diag, ws.system_upper, ws.system_rhs,
                     ws.scratch_c, ws.scratch_d, ws.particle_dv],
            device=m.device,
            record_tape=False,
        )

    def solve_string_system(self, ws: StringWorkspace, tape) -> None:
        m = self.model
        if tape is None:
            wp.launch(
                self._solve,
                dim=m.string_count,
                inputs=[m.string_start, ws.system_diag, ws.system_upper, ws.system_rhs],
                outputs=[ws.scratch_inverse, ws.scratch_c, ws.scratch_d, ws.particle_dv],
                device=m.device,
            )
            return
        # Under a tape: the same solve keeping its factorisation for the adjoint below.
        wp.launch(
            self._solve_recorded,
            dim=m.string_count,
            inputs=[m.string_start, ws.system_diag, ws.system_upper, ws.system_rhs],
            outputs=[ws.scratch_inverse, ws.scratch_c, ws.scratch_d, ws.particle_dv],
            device=m.device,
            record_tape=False,
        )

        def backward():
            # Reads the factorisation the recorded solve kept in ws (scratch_inverse, scratch_c).
            wp.launch(
                self._solve_adjoint,
                dim=m.string_count,
                inputs=[m.string_start, ws.system_upper, ws.scratch_inverse, ws.scratch_c, ws.particle_dv],
                outputs=[
                    ws.scratch_d, ws.scratch_rhs_bar, ws.particle_dv.grad,
                    ws.system_diag.grad, ws.system_upper.grad, ws.system_rhs.grad,
                ],
                device=m.device,
            )

        tape.record_func(backward, arrays=[ws.system_diag, ws.system_upper, ws.system_rhs, ws.particle_dv])

    def integrate_string(self, state_in, state_out, control, h, ws: StringWorkspace) -> None:
        m = self.model
        wp.launch(
            self._integrate,
            dim=m.particle_count,
            inputs=[
                m.particle_string, m.string_start,
                state_in.particle_q, state_in.particle_qd, ws.particle_dv, control.top_q, h,
            ],
            outputs=[state_out.particle_q, state_out.particle_qd],
            device=m.device,
        )

    def eval_string_tie_force(self, state_out, control) -> None:
        m = self.model
        wp.launch(
            self._eval_tie,
            dim=m.string_count,
            inputs=[
                m.string_start, m.string_tie_stiffness, m.string_tie_damping, m.string_tied,
                m.string_taut_distance, state_out.particle_q, state_out.particle_qd,
                control.tie_q, control.tie_qd,
            ],
            outputs=[state_out.tie_force, state_out.string_taut],
            device=m.device,
        )
