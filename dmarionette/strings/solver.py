"""The implicit (backward Euler) string stepper, paper §2.2.

One step is five named passes::

    eval_string_spring     each segment's spring force and stiffness (printed or tension-only), once per segment
    eval_string_system     forces and Jacobians of every term -> block-tridiagonal A dv = b
    solve_string_system    exact O(n) block Thomas solve, one chain per thread (tension-only springs:
                           segments the solution ends taut are activated, the chain solved again)
    integrate_string       v1 = v0 + dv, x1 = x0 + h v1; the top particle follows its bar
    eval_string_tie_force  eq. 2 force on each body point, taut flags (paper §3.2)

A step with the printed spring launches them as one kernel instead,
``integrate_string_implicit`` (``kernels/string_step``: one string per thread, the same
functions in the same order, so the same numbers bit for bit; about 1.2x faster,
``docs/performance.md``); on a tape it also keeps its pivot inverses. A plain float64 step on
the CPU can run it with four strings per thread in SIMD lanes instead (``kernels/string_step_lanes``,
issue 19: the same numbers bit for bit; :attr:`SolverStringImplicit.lanes`, on by default). The
tension-only springs launch the five passes. A step on a tape runs off the tape and records the hand-written adjoint
of the whole step (``kernels/string_step_adjoint``, ``tape.record_func``; issue 13: backward /
forward of a marionette gradient 4.3-5.1 -> about 3); with lanes, the laned step keeping its pivot
inverses and the laned adjoint (``kernels/string_step_adjoint_lanes``: the same gradients bit for
bit); with ``hand_adjoint = False`` it records the five passes instead (Warp's adjoints: the
reference its tests compare with).

A step recorded on a tape is asked for explicitly (``step(..., tape=tape)``): it writes its
intermediates into a workspace of its own (given, or allocated by the step), read by its
adjoint. With the five passes recorded (one array per step, as Warp's reverse pass needs) the
solve records its hand-written adjoint. The active set of the tension-only springs (which segments are in
the system) is found first by an unrecorded pass (launches with ``record_tape=False``); the
step then assembles and solves the system with that active set (recorded, or kept for the
hand-written adjoint), so the gradient
is that of the step with the active set held fixed (the derivative of the piecewise-smooth
step away from its kinks). The step then integrates the unrecorded pass's ``dv``, which is
the plain step's bit for bit: where a segment snaps taut in the step, the plain solve adds
its block to the assembled system in place and solves again, while the recorded pass
assembles the system with it from scratch (the same system up to the order of the sums),
so the two ``dv`` differ by rounding; with the copy a taped step ends exactly where the
plain one does, and the recorded adjoint uses the recorded system with that ``dv`` (the
gradient changes by rounding only).
"""

from __future__ import annotations

import dataclasses

import warp as wp

from dmarionette.kernels.string_integrate import integrate_string_kernels
from dmarionette.kernels.string_model_arrays import DIFFERENTIABLE_FIELDS, string_model_arrays_type
from dmarionette.kernels.string_solve import copy_particle_dv, solve_string_system_kernels
from dmarionette.kernels.string_state_arrays import (
    CONTROL_FIELDS, STATE_GRAD_FIELDS, string_control_arrays_type, string_state_arrays_type, struct_of,
)
from dmarionette.kernels.string_step import integrate_string_implicit_kernel
from dmarionette.kernels.string_step_lanes import LANES, integrate_string_lanes_kernel, lane_groups, lane_types
from dmarionette.kernels.string_step_adjoint import string_step_adjoint_kernel
from dmarionette.kernels.string_step_adjoint_lanes import lane_parts_type, string_step_adjoint_lanes_kernel
from dmarionette.kernels.string_system import eval_string_spring_kernel, eval_string_system_kernel
from dmarionette.strings.model import StringControl, StringModel, StringState

__all__ = ["SolverStringImplicit", "StringWorkspace"]


@dataclasses.dataclass
class StringWorkspace:
    """Intermediate arrays of one step (segment springs, block rows of ``A``, ``b``, ``dv``, scratch).

    A *lean* workspace (:meth:`allocate` with ``lean``) has only what a taped step with the
    hand-written adjoint writes and reads: ``particle_dv`` (laned steps: their pivot inverses and
    ``C'`` go to ``lane_inverse``/``lane_c``), and for the scalar one-launch step also
    ``KEPT_SCALAR``. The other fields are None until a pass that needs them is given the workspace
    (``SolverStringImplicit._scalar_arrays`` fills them)."""

    segment_force: wp.array | None
    segment_jacobian: wp.array | None
    segment_jacobian_active: wp.array | None
    segment_active: wp.array | None
    system_diag: wp.array | None
    system_upper: wp.array | None
    system_rhs: wp.array | None
    particle_dv: wp.array
    scratch_c: wp.array | None
    scratch_d: wp.array | None
    scratch_rhs_bar: wp.array | None
    scratch_inverse: wp.array | None  # pivot inverses of a recorded solve, read by its adjoint
    active_set: StringWorkspace | None = None  # a taped tension-only step's unrecorded active-set pass
    # A taped laned step's pivot inverses and C' (laned: a 9 x K block per row of a group), read by
    # its laned adjoint; set by ``SolverStringImplicit.new_workspace`` (or the step) when lanes are on.
    lane_inverse: wp.array | None = None
    lane_c: wp.array | None = None

    # What the scalar one-launch step with ``keep`` and its hand-written adjoint write and read.
    KEPT_SCALAR = ("scratch_inverse", "scratch_c", "scratch_d", "scratch_rhs_bar")
    # What the five passes (and the tension-only kept step) use besides those.
    PASSES = ("segment_force", "segment_jacobian", "segment_jacobian_active", "segment_active", "system_diag",
              "system_upper", "system_rhs")

    @classmethod
    def allocate(cls, model: StringModel, requires_grad: bool, active_set: bool = False,
                 lean: bool = False, kept_scalar: bool = False) -> StringWorkspace:
        """Arrays for one step's intermediates (``requires_grad``: for a step on a tape;
        ``active_set``: with the unrecorded active-set pass's own, for taped tension-only springs;
        ``lean``: ``particle_dv`` alone, and with ``kept_scalar`` also ``KEPT_SCALAR``: the class doc)."""
        n = model.particle_count
        with wp.ScopedDevice(model.device):
            def zeros(dtype, grad):
                return wp.zeros(n, dtype=dtype, requires_grad=grad)

            if lean:
                ws = cls(particle_dv=zeros(model.vec3, False),
                         **dict.fromkeys(f.name for f in dataclasses.fields(cls) if f.name != "particle_dv"))
                if kept_scalar:
                    ws.scratch_inverse, ws.scratch_c = zeros(model.mat33, False), zeros(model.mat33, False)
                    ws.scratch_d, ws.scratch_rhs_bar = zeros(model.vec3, False), zeros(model.vec3, False)
                return ws
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
                active_set=cls.allocate(model, False) if active_set else None,
            )


class SolverStringImplicit:
    """Backward-Euler stepper for a :class:`StringModel`.

    Args:
        model: the strings to simulate; its ``effects`` choose the kernels compiled.
    """

    def __init__(self, model: StringModel):
        self.model = model
        # On a tape: the step's hand-written adjoint (``kernels/string_step_adjoint``) is recorded;
        # False records the five passes instead (Warp's automatic adjoints, the solve's hand-written
        # one): the reference the tests compare with.
        self.hand_adjoint = True
        self._tension_only = model.effects.tension_only
        self._eval_spring = eval_string_spring_kernel(model.scalar, self._tension_only)
        self._eval_system = eval_string_system_kernel(model.scalar, model.effects.as_tuple())
        (self._solve, self._solve_active, self._solve_recorded,
         self._solve_adjoint) = solve_string_system_kernels(model.scalar)
        self._integrate, self._eval_tie = integrate_string_kernels(model.scalar)
        self._integrate_implicit = None if self._tension_only else \
            integrate_string_implicit_kernel(model.scalar, model.effects.as_tuple())
        self._integrate_implicit_keep = None if self._tension_only else \
            integrate_string_implicit_kernel(model.scalar, model.effects.as_tuple(), keep=True)
        self._integrate_implicit_adjoint = string_step_adjoint_kernel(model.scalar, model.effects.as_tuple(),
                                                                      self._tension_only)
        # A plain step with printed springs, float64, on the CPU can run K strings per thread in
        # SIMD lanes (``kernels/string_step_lanes``; the Clang vector snippets do not compile for
        # CUDA): :attr:`lanes`. Every string is in a group of strings of its particle count; a
        # count no other string shares makes a group of one real lane and K - 1 padding lanes.
        self._lanes_supported = not self._tension_only and model.scalar is wp.float64 and model.device.is_cpu
        self._lanes = False
        self._integrate_lanes = None
        self._integrate_lanes_keep = None  # a taped step's laned kernel, and its laned adjoint
        self._integrate_lanes_adjoint = None
        self._lane_plan = None  # (group arrays, laned scratch), built when lanes are turned on
        self._grad_sinks: dict = {}  # stand-ins for the gradients of arrays that have none
        self._model_grad_cache = None  # (the gradient arrays, their StringModelArrays): _model_grad
        self.workspace = StringWorkspace.allocate(model, requires_grad=False)  # plain steps reuse it
        self._none_forced = wp.zeros(model.particle_count, dtype=wp.int32, device=model.device)
        self.lanes = self._lanes_supported  # on wherever the laned kernel applies (issue 19)

    def new_workspace(self, taped: bool = True) -> StringWorkspace:
        """A workspace of one step's own (``taped``: with gradients where the five passes are
        recorded (not for the hand-written adjoint, which needs none), for tension-only
        springs the active-set pass's arrays, and with :attr:`lanes` the laned step's pivot
        inverses and ``C'``; the scalar one-launch step's: a lean workspace with ``KEPT_SCALAR``)."""
        if taped and self.hand_adjoint and self.lanes:
            ws = StringWorkspace.allocate(self.model, requires_grad=False, lean=True)  # what the laned path writes
            self._add_lane_keep(ws)
            return ws
        if taped and self.hand_adjoint and not self._tension_only:
            return StringWorkspace.allocate(self.model, requires_grad=False, lean=True, kept_scalar=True)
        return StringWorkspace.allocate(self.model, requires_grad=taped and not self.hand_adjoint,
                                        active_set=taped and self._tension_only)

    def _scalar_arrays(self, ws: StringWorkspace,
                       needs: tuple[str, ...] = StringWorkspace.KEPT_SCALAR + StringWorkspace.PASSES) -> None:
        """A scalar pass given a lean workspace that lacks arrays it ``needs`` fills it first (a
        launch with a missing array would write through a null pointer)."""
        if any(getattr(ws, name) is None for name in needs):
            self._fill_workspace(ws, taped=True)

    def _fill_workspace(self, ws: StringWorkspace, taped: bool) -> None:
        """Gives a lean workspace (made while :attr:`lanes` was on) the scalar arrays (lanes turned
        off since, or the five taped passes: ``taped`` with gradients where those are recorded)."""
        full = StringWorkspace.allocate(self.model, requires_grad=taped and not self.hand_adjoint,
                                        active_set=taped and self._tension_only)
        for field in dataclasses.fields(StringWorkspace):
            if getattr(ws, field.name) is None:
                setattr(ws, field.name, getattr(full, field.name))

    def step(self, state_in: StringState, state_out: StringState, control: StringControl, dt: float, *,
             tape: wp.Tape | None = None, workspace: StringWorkspace | None = None) -> None:
        """Advances the strings by ``dt`` seconds from ``state_in`` into ``state_out``.

        Args:
            state_in, state_out: two different states (``state_in`` is only read).
            control: the tops and tie targets at the end of the step.
            dt: the step [s].
            tape: the ``wp.Tape`` the step is recorded on (the caller's ``with tape:``), or
                None for a plain step. Required for gradients: the solve's adjoint is recorded
                on it.
            workspace: the step's intermediates (default: :attr:`workspace` for a plain step,
                a :meth:`new_workspace` for a taped one); a taped step needs one of its own
                (from :meth:`new_workspace`).
        """
        m = self.model
        h = m.scalar(dt)
        ws = workspace if workspace is not None else (self.new_workspace() if tape is not None else self.workspace)
        if tape is None and self._integrate_implicit is not None:
            if self.lanes:
                self.integrate_string_lanes(state_in, state_out, control, h, ws)  # K strings per thread
            else:
                self.integrate_string_implicit(state_in, state_out, control, h, ws)  # the five passes in one launch
            return
        if tape is not None and self.hand_adjoint:
            if self._tension_only:
                self.step_tension_only_kept(state_in, state_out, control, h, ws)
                self.record_step_adjoint(state_in, state_out, control, h, ws, tape, ws.active_set.segment_active)
            elif self.lanes:
                self.integrate_string_lanes(state_in, state_out, control, h, ws, keep=True)  # K strings per thread
                self.record_step_adjoint(state_in, state_out, control, h, ws, tape, lanes=True)
            else:
                self.integrate_string_implicit(state_in, state_out, control, h, ws, keep=True)
                self.record_step_adjoint(state_in, state_out, control, h, ws, tape)
            return
        forced = self._none_forced  # every segment in the system (printed springs)
        if tape is not None and self._tension_only:
            self.eval_active_set(state_in, control, h, ws.active_set)  # unrecorded: which segments are taut
            forced = ws.active_set.segment_active
        self.eval_string_spring(state_in, forced, ws)  # spring force and stiffness per segment
        self.eval_string_system(state_in, control, h, ws)  # all force terms -> A dv = b
        if tape is None and self._tension_only:
            self.solve_string_system_active(state_in, control, h, ws)  # block Thomas + active set
        else:
            self.solve_string_system(ws, tape)  # block Thomas (with the active set found above)
        if tape is not None and self._tension_only:
            self.apply_active_set_dv(ws)  # integrate the plain solve's dv (module doc)
        self.integrate_string(state_in, state_out, control, h, ws)  # v1 = v0 + dv, x1 = x0 + h v1
        self.eval_string_tie_force(state_out, control)  # eq. 2 force on bodies, taut flags

    def integrate_string_implicit(self, state_in, state_out, control, h, ws: StringWorkspace,
                                  keep: bool = False) -> None:
        """The plain step's five passes as one launch, one string per thread (printed springs;
        module doc). Writes ``state_out`` and ``ws``'s ``scratch_c``, ``scratch_d`` and
        ``particle_dv`` (not the blocks of ``A``, which it never stores); ``keep``: also the pivot
        inverses (``scratch_inverse``), for the hand-written adjoint. Never recorded."""
        m = self.model
        self._scalar_arrays(ws, StringWorkspace.KEPT_SCALAR)
        wp.launch(
            self._integrate_implicit_keep if keep else self._integrate_implicit,
            dim=m.string_count,
            inputs=self._step_inputs(state_in, control, h),
            outputs=[ws.scratch_inverse, ws.scratch_c, ws.scratch_d, ws.particle_dv, *self._step_outputs(state_out)],
            device=m.device,
            record_tape=False,
        )

    def _step_inputs(self, state_in, control, h) -> list:
        """The one-launch steps' inputs (scalar and laned kernels alike): the model, the state in,
        the control (as arrays, not their structs: ``kernels/string_step``'s module doc) and the step."""
        return [self.model.arrays, state_in.particle_q, state_in.particle_qd, control.top_q, control.tie_q,
                control.tie_qd, h]

    @staticmethod
    def _step_outputs(state_out) -> list:
        """The one-launch steps' state out (as arrays, as :meth:`_step_inputs`)."""
        return [state_out.particle_q, state_out.particle_qd, state_out.tie_force, state_out.string_taut]

    @property
    def lanes(self) -> bool:
        """String steps in SIMD lanes (``kernels/string_step_lanes``: the same numbers as the scalar
        one-launch kernel, bit for bit, about 2x faster for 6 x 50), plain ones and taped ones (the
        laned step with ``keep`` and the laned hand-written adjoint,
        ``kernels/string_step_adjoint_lanes``: the scalar adjoint's gradients, bit for bit).
        **On by default** wherever it applies: printed springs, float64 and a CPU device; elsewhere
        off, and setting it on raises ``ValueError``. ``False`` runs the scalar kernels (the
        benchmarks' comparison). Setting it on builds the kernels and their group table."""
        return self._lanes

    @lanes.setter
    def lanes(self, on: bool) -> None:
        if on and not self._lanes_supported:
            raise ValueError("SolverStringImplicit.lanes: the laned string step needs printed springs, "
                             "float64 and a CPU device")
        if on and self._integrate_lanes is None:
            effects = self.model.effects.as_tuple()
            self._integrate_lanes = integrate_string_lanes_kernel(effects, LANES)
            self._integrate_lanes_keep = integrate_string_lanes_kernel(effects, LANES, keep=True)
            self._integrate_lanes_adjoint = string_step_adjoint_lanes_kernel(effects, LANES)
            self._lane_plan = self._new_lane_plan()
        self._lanes = bool(on)

    def integrate_string_lanes(self, state_in, state_out, control, h, ws: StringWorkspace,
                               keep: bool = False) -> None:
        """:meth:`integrate_string_implicit` with ``LANES`` strings of equal particle count per
        thread (``kernels/string_step_lanes``): the same numbers, bit for bit. Writes ``state_out``
        and ``ws.particle_dv``; ``C'``, ``d'`` go to laned scratch of its own (read by nobody else),
        not to ``ws.scratch_c``/``scratch_d``; ``keep`` (a taped step): the pivot inverses and
        ``C'`` to ``ws.lane_inverse``, ``ws.lane_c`` instead (laned, for the laned adjoint; allocated
        here if ``ws`` was made with lanes off). Never recorded."""
        m = self.model
        if self._integrate_lanes is None:
            raise ValueError("the laned string step needs printed springs, float64 and a CPU device")
        groups, (lane_c, lane_d, *_adjoint_scratch) = self._lane_plan
        lane_inverse = None
        if keep:
            if ws.lane_c is None:
                self._add_lane_keep(ws)
            lane_inverse, lane_c = ws.lane_inverse, ws.lane_c
        wp.launch(
            self._integrate_lanes_keep if keep else self._integrate_lanes,
            dim=groups[1].shape[0],
            inputs=[*groups, *self._step_inputs(state_in, control, h)],
            outputs=[lane_inverse, lane_c, lane_d, ws.particle_dv, *self._step_outputs(state_out)],
            device=m.device,
            record_tape=False,
        )

    @property
    def lane_group_arrays(self) -> list[wp.array]:
        """The laned kernels' group table (string indices, real lanes, scratch offsets per group;
        ``string_step_lanes.lane_groups``), for kernels that read laned arrays; None with lanes off."""
        return None if self._lane_plan is None else self._lane_plan[0]

    def _new_lane_plan(self) -> tuple[list[wp.array], list[wp.array]]:
        """The laned step's group table (``string_step_lanes.lane_groups``: string indices, real
        lanes, scratch offsets per group) and its laned scratch: ``C'``, ``d'`` of each group's rows
        (a plain step's), and the laned adjoint's forward substitution, its terms of the
        particles' gradients and the segments' spring parts (each read only within its launch)."""
        m = self.model
        group_string, group_real, group_base, rows = lane_groups(m.string_start.numpy(), LANES)
        _lane, ivec, lvec, lmat = lane_types(LANES)
        with wp.ScopedDevice(m.device):
            return ([wp.array(group_string, dtype=ivec), wp.array(group_real, dtype=wp.int32),
                     wp.array(group_base, dtype=wp.int32)],
                    [wp.zeros(rows, dtype=lmat), *[wp.zeros(rows, dtype=lvec) for _ in range(4)],
                     wp.zeros(rows, dtype=lane_parts_type(LANES))])

    def _add_lane_keep(self, ws: StringWorkspace) -> None:
        """``ws.lane_inverse``, ``ws.lane_c``: a taped laned step's own, as many rows as the plan's."""
        rows = self._lane_plan[1][0].shape[0]
        _lane, _ivec, _lvec, lmat = lane_types(LANES)
        ws.lane_inverse = wp.zeros(rows, dtype=lmat, device=self.model.device)
        ws.lane_c = wp.zeros(rows, dtype=lmat, device=self.model.device)

    def _grad(self, a: wp.array) -> wp.array:
        """``a.grad``, or a scratch array of its shape for an input that carries no gradient."""
        if a.grad is not None:
            return a.grad
        key = (a.dtype, a.shape)
        if key not in self._grad_sinks:
            self._grad_sinks[key] = wp.zeros(a.shape, dtype=a.dtype, device=a.device)
        return self._grad_sinks[key]

    def step_tension_only_kept(self, state_in, state_out, control, h, ws: StringWorkspace) -> None:
        """A tension-only step off the tape that keeps what its adjoint reads: the active set
        (``ws.active_set.segment_active``), the system assembled with it and solved keeping its
        factorisation (``ws.scratch_inverse``, ``ws.scratch_c``), and the plain step's ``dv`` (module
        doc: the step ends where the plain one does, bit for bit)."""
        m = self.model
        self.eval_active_set(state_in, control, h, ws.active_set)
        self.eval_string_spring(state_in, ws.active_set.segment_active, ws, record=False)
        self.eval_string_system(state_in, control, h, ws, record=False)
        wp.launch(self._solve_recorded, dim=m.string_count,
                  inputs=[m.string_start, ws.system_diag, ws.system_upper, ws.system_rhs],
                  outputs=[ws.scratch_inverse, ws.scratch_c, ws.scratch_d, ws.particle_dv],
                  device=m.device, record_tape=False)
        self.apply_active_set_dv(ws)
        self.integrate_string(state_in, state_out, control, h, ws, record=False)
        self.eval_string_tie_force(state_out, control, record=False)

    def record_step_adjoint(self, state_in, state_out, control, h, ws: StringWorkspace, tape: wp.Tape,
                            forced: wp.array | None = None, lanes: bool = False) -> None:
        """Records the hand-written adjoint of the step just run on ``tape`` (the one-launch step
        with ``keep``, or :meth:`step_tension_only_kept` with the active set ``forced``;
        ``kernels/string_step_adjoint``; ``lanes``: the laned step with ``keep``, and its laned
        adjoint ``kernels/string_step_adjoint_lanes``). It reads ``ws``'s pivot inverses, ``C'``
        and ``dv``: the workspace must not be reused before the adjoint has run (each taped step
        has its own); ``forced``: the tension-only step's active set (None for printed springs)."""
        m = self.model
        if lanes:
            self._record_step_adjoint_lanes(state_in, state_out, control, h, ws, tape)
            return
        self._scalar_arrays(ws, StringWorkspace.KEPT_SCALAR)
        forced = self._none_forced if forced is None else forced
        params, inputs, outputs = self._adjoint_arrays(state_in, state_out, control)

        def backward():
            wp.launch(
                self._integrate_implicit_adjoint,
                dim=m.string_count,
                inputs=[m.arrays, state_in.arrays, ws.scratch_inverse, ws.scratch_c, ws.particle_dv, state_out.arrays,
                        forced, control.arrays, h],
                outputs=[ws.scratch_rhs_bar, *self._step_grads(state_in, state_out, control, params)],
                device=m.device,
                record_tape=False,
            )

        tape.record_func(backward, arrays=[a for a in outputs + inputs + params if a.grad is not None])

    def _model_grad(self, params: list[wp.array]):
        """The gradients of the model's differentiable arrays ``params`` (``_adjoint_arrays``), each
        its ``.grad`` or a sink (:meth:`_grad`), as a ``StringModelArrays`` of the same field names
        (the step adjoints' ``model_grad``); rebuilt only when one of those arrays changed."""
        grads = [self._grad(a) for a in params]
        cached = self._model_grad_cache
        if cached is None or any(g is not c for g, c in zip(grads, cached[0])):
            arrays = string_model_arrays_type(self.model.scalar)()
            for name, grad in zip(DIFFERENTIABLE_FIELDS, grads):
                setattr(arrays, name, grad)
            self._model_grad_cache = cached = (grads, arrays)
        return cached[1]

    def _step_grads(self, state_in, state_out, control, params: list[wp.array]) -> list:
        """The step adjoints' gradients: of the state out (read and consumed), of the state in, the
        control and the model (accumulated), each a struct (:meth:`_grad_arrays`, :meth:`_model_grad`)."""
        return [self._grad_arrays(state_out, string_state_arrays_type, STATE_GRAD_FIELDS),
                self._grad_arrays(state_in, string_state_arrays_type, STATE_GRAD_FIELDS),
                self._grad_arrays(control, string_control_arrays_type, CONTROL_FIELDS), self._model_grad(params)]

    def _grad_arrays(self, owner, struct_type, fields):
        """The gradients of ``owner``'s arrays ``fields`` (each its ``.grad`` or a sink, :meth:`_grad`)
        as a struct of the same field names (``struct_type``: ``string_state_arrays_type`` or
        ``string_control_arrays_type``); cached on ``owner``, rebuilt only when one of them changed."""
        grads = [self._grad(getattr(owner, name)) for name in fields]
        owner._grad_arrays = struct_of(struct_type, fields, grads, getattr(owner, "_grad_arrays", None))
        return owner._grad_arrays[1]

    def _adjoint_arrays(self, state_in, state_out, control) -> tuple[list, list, list]:
        """The step adjoints' differentiable arrays: the constants, the inputs and the outputs
        (in the adjoint kernels' order of their gradients)."""
        m = self.model
        params = [getattr(m, name) for name in DIFFERENTIABLE_FIELDS]
        inputs = [state_in.particle_q, state_in.particle_qd, control.top_q, control.tie_q, control.tie_qd]
        outputs = [state_out.particle_q, state_out.particle_qd, state_out.tie_force]
        return params, inputs, outputs

    def _record_step_adjoint_lanes(self, state_in, state_out, control, h, ws: StringWorkspace, tape: wp.Tape) -> None:
        """:meth:`record_step_adjoint` of the laned step (``lanes=True``): the same inputs and
        gradients, ``ws.lane_inverse`` and ``ws.lane_c`` for the scalar workspace's arrays."""
        m = self.model
        groups, (_lane_c, _lane_d, *adjoint_scratch) = self._lane_plan
        params, inputs, outputs = self._adjoint_arrays(state_in, state_out, control)

        def backward():
            wp.launch(
                self._integrate_lanes_adjoint,
                dim=groups[1].shape[0],
                inputs=[*groups, m.arrays, state_in.arrays, ws.lane_inverse, ws.lane_c, ws.particle_dv,
                        state_out.arrays, control.arrays, h],
                outputs=[*adjoint_scratch, *self._step_grads(state_in, state_out, control, params)],
                device=m.device,
                record_tape=False,
            )

        tape.record_func(backward, arrays=[a for a in outputs + inputs + params if a.grad is not None])

    def eval_active_set(self, state_in, control, h, ws: StringWorkspace) -> None:
        """Tension-only springs: the active set of a step from ``state_in`` (segments taut at
        the start or at the end of the step) into ``ws.segment_active``, and that step's
        ``ws.particle_dv``; never recorded, even under a tape (``ws`` needs no gradients)."""
        self.eval_string_spring(state_in, self._none_forced, ws, record=False)
        self.eval_string_system(state_in, control, h, ws, record=False)
        self.solve_string_system_active(state_in, control, h, ws)

    def apply_active_set_dv(self, ws: StringWorkspace) -> None:
        """``ws.particle_dv`` <- the active-set pass's (``ws.active_set``), off the tape."""
        m = self.model
        wp.launch(copy_particle_dv, dim=m.particle_count, inputs=[ws.active_set.particle_dv],
                  outputs=[ws.particle_dv], device=m.device, record_tape=False)

    def eval_string_spring(self, state_in, forced, ws: StringWorkspace, record: bool = True) -> None:
        m = self.model
        self._scalar_arrays(ws)
        wp.launch(
            self._eval_spring,
            dim=m.particle_count,
            inputs=[m.arrays, state_in.arrays, forced],
            outputs=[ws.segment_force, ws.segment_jacobian, ws.segment_jacobian_active, ws.segment_active],
            device=m.device,
            record_tape=record,
        )

    def eval_string_system(self, state_in, control, h, ws: StringWorkspace, record: bool = True) -> None:
        m = self.model
        self._scalar_arrays(ws)
        wp.launch(
            self._eval_system,
            dim=m.particle_count,
            inputs=[m.arrays, state_in.arrays, ws.segment_force, ws.segment_jacobian, control.arrays, h],
            outputs=[ws.system_diag, ws.system_upper, ws.system_rhs],
            device=m.device,
            record_tape=record,
        )

    def solve_string_system_active(self, state_in, control, h, ws: StringWorkspace) -> None:
        """The solve with the springs' active set resolved in place (not differentiable)."""
        m = self.model
        self._scalar_arrays(ws)
        wp.launch(
            self._solve_active,
            dim=m.string_count,
            inputs=[m.arrays, state_in.arrays, ws.segment_jacobian_active, control.arrays, h],
            outputs=[ws.segment_active, ws.system_diag, ws.system_upper, ws.system_rhs,
                     ws.scratch_c, ws.scratch_d, ws.particle_dv],
            device=m.device,
            record_tape=False,
        )

    def solve_string_system(self, ws: StringWorkspace, tape) -> None:
        m = self.model
        self._scalar_arrays(ws)
        # Under a tape: the same solve keeping its factorisation, for the adjoint recorded below.
        wp.launch(
            self._solve if tape is None else self._solve_recorded,
            dim=m.string_count,
            inputs=[m.string_start, ws.system_diag, ws.system_upper, ws.system_rhs],
            outputs=[ws.scratch_inverse, ws.scratch_c, ws.scratch_d, ws.particle_dv],
            device=m.device,
            record_tape=tape is None,
        )
        if tape is None:
            return

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

    def integrate_string(self, state_in, state_out, control, h, ws: StringWorkspace, record: bool = True) -> None:
        m = self.model
        self._scalar_arrays(ws)
        wp.launch(
            self._integrate,
            dim=m.particle_count,
            inputs=[m.arrays, state_in.arrays, ws.particle_dv, control.arrays, h],
            outputs=[state_out.arrays],
            device=m.device,
            record_tape=record,
        )

    def eval_string_tie_force(self, state_out, control, record: bool = True) -> None:
        m = self.model
        wp.launch(
            self._eval_tie,
            dim=m.string_count,
            inputs=[m.arrays, control.arrays, state_out.arrays],
            device=m.device,
            record_tape=record,
        )
