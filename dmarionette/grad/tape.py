"""Segments of a marionette rollout on a ``wp.Tape``, and their reverse pass.

:class:`TapedSegment` replays ``SolverMarionette.step``'s passes (begin: body points, the
trial puppet step and the tie path; ``n`` string steps with feedback; end: anchors and the puppet step) for ``K``
puppet steps with one array for every quantity a step writes. ``SolverMarionette`` reuses
scratch buffers from step to step (the tie path, the tied points, the string states
between substeps, the puppet control); on a tape an array written after it was read gives
silently wrong gradients, so none of them is reused here. Tension-only strings take the
active set of each string step from an unrecorded pass into a workspace of the step's own
(as ``SolverStringImplicit.step`` does under a tape), then record the passes with it. The string substeps write their
tie force and taut flags straight into rows of the step's ``(n, S)`` output arrays (no
copies), and the tied points are evaluated on a shallow copy of the puppet state with its
own body-pose arrays (the puppet step evaluates its input state's body poses again).

The arrays of a ``C``-step segment are allocated once (a :class:`_Plan`) and reused by
every segment (a shorter last one uses its first steps): for each segment length the
forward launches on the tape and the reverse pass are captured as two Warp graphs (CPU
or CUDA) and replayed per segment, with the checkpoint, the inputs and the cotangent
seeds written into the planned arrays in place between the replays. Without capture the
same launches run one by one.

The forward values are those of ``SolverMarionette`` (same kernels, same order), which
:meth:`TapedSegment.backward` checks: the taped re-run must end exactly where the untaped
run did.
"""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import warp as wp

from dmarionette.kernels.string_body_coupling import apply_string_forces_to_anchors_kernel, eval_tie_path
from dmarionette.marionette.solver import predict_puppet_step, trial_fields, trial_view
from dmarionette.strings.model import StringControl
from dmarionette.strings.rollout import upload_values
from dmarionette.strings.solver import StringWorkspace

__all__ = ["StateAdjoint", "TapedSegment"]


class _Strings:
    """The string-state attributes the string solver reads and writes."""

    def __init__(self, particle_q, particle_qd, tie_force, string_taut):
        self.particle_q = particle_q
        self.particle_qd = particle_qd
        self.tie_force = tie_force
        self.string_taut = string_taut


class _Plan:
    """Every array of a ``steps``-long taped segment (allocated once), and its graphs."""

    def __init__(self, model, steps: int):
        m = model
        self.device = m.device
        self.steps = steps
        self.grads: list[wp.array] = []  # every gradient buffer to clear before a reverse pass
        self.arrays: list[wp.array] = []  # every array of the plan (for its memory)
        n, s, b = m.substeps, m.strings.string_count, max(m.bar_count, 1)
        p, nb, npt = m.strings.particle_count, m.puppet.body_count, len(m.puppet.point_names)
        z = self.zeros
        self.states = []
        for _ in range(steps + 1):
            st = _Strings(z(p, wp.vec3d), z(p, wp.vec3d), None, None)
            state = type("State", (), {})()
            state.strings = st
            state.puppet = m.puppet.state(requires_grad=True)
            self._track(state.puppet)
            state.tie_force = z((n, s), wp.vec3d)
            state.string_taut = z((n, s), wp.int32, grad=False)
            state.bar_feedback = z((n, b), wp.vec3d)
            state.bar_reaction = z((n, b), wp.vec3d)
            state.tie_target = z(s, wp.vec3d)
            self.states.append(state)
        self.controls = []
        self.steps_arrays = []
        for _ in range(steps):
            c = type("Control", (), {})()
            c.top_q, c.bar_q, c.bar_qd = z((n, s), wp.vec3d), z((n, b), wp.vec3d), z((n, b), wp.vec3d)
            self.controls.append(c)
            self.steps_arrays.append(self._step_arrays(m, n, s, p, nb, npt))
        self.final_points = self._points_arrays(nb, npt)

    def zeros(self, shape, dtype, grad=True) -> wp.array:
        a = wp.zeros(shape, dtype=dtype, requires_grad=grad, device=self.device)
        self.arrays.append(a)
        if grad:
            self.grads.append(a.grad)
        return a

    @property
    def nbytes(self) -> int:
        """Bytes of the plan's arrays and their gradients."""
        return sum(a.capacity for a in self.arrays) + sum(g.capacity for g in self.grads)

    def _track(self, obj) -> None:
        for value in vars(obj).values():
            if isinstance(value, wp.array):
                self.arrays.append(value)
                if value.requires_grad:
                    self.grads.append(value.grad)

    def _points_arrays(self, nb, npt) -> dict:
        z = self.zeros
        return {"body_pos": z((1, nb), wp.vec3d), "body_rot": z((1, nb), wp.quatd), "body_w": z((1, nb), wp.vec3d),
                "body_v": z((1, nb), wp.vec3d), "point_q": z((1, npt), wp.vec3d), "point_qd": z((1, npt), wp.vec3d)}

    def _step_arrays(self, m, n, s, p, nb, npt) -> dict:
        z = self.zeros
        arrays = self._points_arrays(nb, npt)
        arrays["tie_q"], arrays["tie_qd"] = z((n, s), wp.vec3d), z((n, s), wp.vec3d)
        arrays["string_q"] = [z(p, wp.vec3d) for _ in range(n - 1)]
        arrays["string_qd"] = [z(p, wp.vec3d) for _ in range(n - 1)]
        workspaces = []
        for _ in range(n):
            ws = StringWorkspace.allocate(m.strings, requires_grad=True)
            self._track(ws)
            workspaces.append(ws)
        arrays["workspaces"] = workspaces
        if m.strings.effects.tension_only:
            # The active-set pass of each string step, unrecorded (no gradients); its
            # segment_active is the recorded pass's forced set, read again backwards.
            actives = []
            for _ in range(n):
                ws = StringWorkspace.allocate(m.strings, requires_grad=False)
                self._track(ws)
                actives.append(ws)
            arrays["active_workspaces"] = actives
        control = m.puppet.control(requires_grad=True)
        self._track(control)
        arrays["puppet_control"] = control
        # The trial step (string_body_coupling): its input's body fields, its end state, its points.
        fields = trial_fields(m.puppet, requires_grad=True)
        self._track(SimpleNamespace(**fields))
        arrays["trial_fields"] = fields
        trial = m.puppet.state(requires_grad=True)
        self._track(trial)
        arrays["trial"] = trial
        arrays["point_end"], arrays["point_end_qd"] = z((1, npt), wp.vec3d), z((1, npt), wp.vec3d)
        return arrays


class StateAdjoint:
    """Adjoint of the carried state at a segment boundary (host arrays, ``Checkpoint`` layout)."""

    def __init__(self, state):
        self.particle_q = state.strings.particle_q.grad.numpy().copy()
        self.particle_qd = state.strings.particle_qd.grad.numpy().copy()
        self.joint_q = state.puppet.joint_q.grad.numpy().copy()
        self.joint_qd = state.puppet.joint_qd.grad.numpy().copy()
        self.tie_target = state.tie_target.grad.numpy().copy()
        self.tie_force = state.tie_force.grad.numpy().copy()

    def seed(self, state) -> None:
        _add_grad(state.strings.particle_q, self.particle_q)
        _add_grad(state.strings.particle_qd, self.particle_qd)
        _add_grad(state.puppet.joint_q, self.joint_q)
        _add_grad(state.puppet.joint_qd, self.joint_qd)
        _add_grad(state.tie_target, self.tie_target)
        _add_grad(state.tie_force, self.tie_force)


def _add_grad(array: wp.array, values) -> None:
    current = array.grad.numpy()
    upload_values(array.grad, current + np.asarray(values).reshape(current.shape))


class TapedSegment:
    """Records puppet steps ``a .. b-1`` of a rollout on a tape and runs their reverse pass.

    Args:
        model: the ``MarionetteModel`` (``requires_grad=True``).
        solver: the ``SolverMarionette`` of the untaped forward (its feedback kernel is reused).
        parameters: the model arrays whose gradients the engine accumulates over segments.
        steps: the longest segment (puppet steps); one set of arrays of that length serves
            every segment (a shorter last one uses its first steps).
        capture: replay each segment length's taped forward and reverse pass as Warp graphs.
    """

    def __init__(self, model, solver, parameters: list[wp.array], steps: int, capture: bool = True):
        self.model = model
        self.solver = solver
        self.parameters = parameters
        self.steps = int(steps)
        self.capture = bool(capture)
        self._plan: _Plan | None = None
        self._graphs: dict[tuple[int, bool], tuple] = {}

    @property
    def nbytes(self) -> int:
        """Bytes of the planned segment's arrays and gradients (not the graphs' own records)."""
        return self._plan.nbytes if self._plan is not None else 0

    # ------------------------------------------------------------------ the taped step
    def _points(self, puppet_state, arrays: dict):
        """Body poses and tied points of ``puppet_state`` into ``arrays`` (a shallow copy of
        the state holds them, so the puppet step's own kinematics pass writes different ones)."""
        m = self.model
        view = copy.copy(puppet_state)
        for name in ("body_pos", "body_rot", "body_w", "body_v"):
            setattr(view, name, arrays[name])
        m.puppet_solver.eval_kinematics(view)
        m.puppet_solver.eval_points(view, arrays["point_q"], arrays["point_qd"])

    def _step(self, state_in, state_out, control, arrays: dict, tape) -> None:
        """One puppet step on ``tape`` into the planned ``arrays``."""
        m = self.model
        n, s = m.substeps, m.strings.string_count
        self._points(state_in.puppet, arrays)
        trial = arrays["trial"]
        predict_puppet_step(m, self.solver._response, trial_view(state_in.puppet, arrays["trial_fields"]),
                            state_in.strings, state_in.tie_force, trial, arrays["puppet_control"])
        m.puppet_solver.eval_kinematics(trial)
        m.puppet_solver.eval_points(trial, arrays["point_end"], arrays["point_end_qd"])
        tie_q, tie_qd = arrays["tie_q"], arrays["tie_qd"]
        wp.launch(eval_tie_path, dim=(n, s),
                  inputs=[m.string_point_wp, arrays["point_end"], state_in.tie_target, wp.float64(m.string_dt)],
                  outputs=[tie_q, tie_qd, state_out.tie_target], device=m.device)
        previous = state_in.strings
        feedback = self.solver._feedback
        weight = wp.vec3d(*(m.puppet_mass * np.asarray(m.scene.gravity)))
        st, solver = m.strings, m.string_solver
        h = wp.float64(m.string_dt)
        for j in range(n):
            if j == n - 1:
                q, qd = state_out.strings.particle_q, state_out.strings.particle_qd
            else:
                q, qd = arrays["string_q"][j], arrays["string_qd"][j]
            nxt = _Strings(q, qd, state_out.tie_force[j], state_out.string_taut[j])
            control_j = StringControl(control.top_q[j], tie_q[j], tie_qd[j])
            ws = arrays["workspaces"][j]
            # SolverStringImplicit.step's passes under a tape, with this step's own workspaces.
            forced = solver._none_forced  # the printed spring: every segment active
            if "active_workspaces" in arrays:
                # Tension-only: the active set found by an unrecorded pass, then the recorded
                # passes with it held fixed (the gradient of the step away from its kinks).
                active = arrays["active_workspaces"][j]
                solver.eval_active_set(previous, control_j, h, active)
                forced = active.segment_active
            solver.eval_string_spring(previous, forced, ws)
            solver.eval_string_system(previous, control_j, h, ws)
            solver.solve_string_system(ws, tape)
            if "active_workspaces" in arrays:
                _copy_unrecorded(ws.particle_dv, active.particle_dv)
            solver.integrate_string(previous, nxt, control_j, h, ws)
            solver.eval_string_tie_force(nxt, control_j)
            if feedback is not None:
                wp.launch(feedback, dim=st.string_count,
                          inputs=[st.string_start, m.string_bar_wp, st.string_stiffness, st.string_rest_length,
                                  st.string_internal_friction, wp.float64(m.scene.feedback_stiffness),
                                  wp.float64(m.scene.feedback_damping), weight,
                                  nxt.particle_q, nxt.particle_qd, nxt.string_taut,
                                  control.bar_q[j], control.bar_qd[j]],
                          outputs=[state_out.bar_feedback[j], state_out.bar_reaction[j]], device=m.device)
            previous = nxt
        puppet_control = arrays["puppet_control"]
        if len(m.spring_string):
            wp.launch(apply_string_forces_to_anchors_kernel(n), dim=len(m.spring_string),
                      inputs=[m.spring_string_wp, st.string_tie_stiffness, state_out.tie_force, tie_q, tie_qd,
                              wp.float64(m.string_dt)],
                      outputs=[puppet_control.spring_anchor_pos, puppet_control.spring_anchor_vel], device=m.device)
        m.puppet_solver.step(state_in.puppet, state_out.puppet, puppet_control, m.puppet_dt)

    def _forward(self, plan: _Plan, steps: int, last: bool, tape, clear: list[wp.array]) -> None:
        """The launches of a ``steps``-long segment on ``tape``; then the gradient buffers ``clear`` zeroed."""
        with tape:
            for k in range(steps):
                self._step(plan.states[k], plan.states[k + 1], plan.controls[k], plan.steps_arrays[k], tape)
            if last:
                self._points(plan.states[steps].puppet, plan.final_points)
        for g in clear:
            g.zero_()

    def _residue(self, plan: _Plan, steps: int, last: bool) -> list[wp.array]:
        """The gradient buffers a reverse pass leaves non-zero.

        Warp's adjoint of a plain array store reads the element's gradient and zeroes it, so
        after a reverse pass only the buffers of arrays that are read but never stored to in
        the segment (its start state, its inputs) or only accumulated into (atomic adds: the
        bar feedback) hold anything. Found by a reverse pass with every gradient buffer set
        to ones; only these are cleared before each replay (clearing all of them cost about
        a fifth of the reverse pass). The model parameters' gradients are restored after.
        """
        saved = [a.grad.numpy().copy() for a in self.parameters]
        warm = wp.Tape()
        self._forward(plan, steps, last, warm, plan.grads)
        for g in plan.grads:
            upload_values(g, np.ones(g.numpy().shape))
        warm.backward()
        residue = [g for g in plan.grads if np.any(g.numpy() != 0.0)]
        for g in plan.grads:
            g.zero_()
        for a, g in zip(self.parameters, saved):
            upload_values(a.grad, g)
        return residue

    def _prepare(self, steps: int, last: bool):
        """The planned arrays, and the captured graphs of a ``(steps, last)`` segment (None
        without capture)."""
        if self._plan is None:
            self._plan = _Plan(self.model, self.steps)
        plan = self._plan
        if not self.capture:
            return plan, None
        key = (steps, last)
        if key not in self._graphs:
            # The eager pass of _residue also loads every module before capture begins.
            clear = self._residue(plan, steps, last)
            tape = wp.Tape()
            with wp.ScopedCapture(device=self.model.device) as forward:
                self._forward(plan, steps, last, tape, clear)
            with wp.ScopedCapture(device=self.model.device) as reverse:
                tape.backward()
            self._graphs[key] = (forward.graph, reverse.graph, tape)
        return plan, self._graphs[key]

    # ------------------------------------------------------------------ reverse pass
    def backward(self, checkpoint, inputs, a: int, b: int, *, last: bool, cotangents: dict,
                 adjoint_end: StateAdjoint | None, grads: dict, expected_end=None) -> StateAdjoint:
        """Re-runs puppet steps ``a .. b-1`` from ``checkpoint`` on a tape and pulls back.

        Args:
            checkpoint: the state at step ``a`` (``marionette_grad.Checkpoint``).
            inputs: the rollout's ``RolloutInputs`` (the model's constants already set from them).
            a, b: the segment's first and one-past-last puppet step.
            last: ``b`` is the rollout's end (its final row of per-puppet-step outputs is seeded here).
            cotangents: output name -> full-rollout cotangent array (missing: zero).
            adjoint_end: adjoint of the state at step ``b`` (None: zero).
            grads: input name -> full-rollout gradient arrays; the segment's rows are added.
            expected_end: the untaped state at step ``b`` (a ``Checkpoint``), to check the re-run.

        Returns:
            The adjoint of the state at step ``a``.
        """
        m = self.model
        n = m.substeps
        steps = b - a
        if steps > self.steps:
            raise ValueError(f"segment {a}..{b}: {steps} puppet steps; planned for at most {self.steps}")
        plan, graphs = self._prepare(steps, last)
        states = plan.states[:steps + 1]
        controls = plan.controls[:steps]
        checkpoint.load(states[0])
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            upload_values(control.top_q, inputs.top_q[rows])
            upload_values(control.bar_q, inputs.bar_q[rows])
            upload_values(control.bar_qd, inputs.bar_qd[rows])
        if graphs is not None:
            wp.capture_launch(graphs[0])
        else:
            tape = wp.Tape()  # not reset(): that would clear the parameters' accumulated gradients
            self._forward(plan, steps, last, tape, plan.grads)
        if expected_end is not None:
            _check_rerun(expected_end, states[-1], a, b)
        # Seed: the per-step outputs of this segment, then the state adjoint from the next one.
        records = list(plan.steps_arrays[:steps]) + ([plan.final_points] if last else [])
        for k, arrays in enumerate(records):
            p = a + k
            if "joint_q" in cotangents:
                _add_grad(states[k].puppet.joint_q, cotangents["joint_q"][p])
            if "point_pos" in cotangents:
                _add_grad(arrays["point_q"], cotangents["point_pos"][p])
            if "body_pos" in cotangents:
                _add_grad(arrays["body_pos"], cotangents["body_pos"][p])
            if "body_rot" in cotangents:
                _add_grad(arrays["body_rot"], cotangents["body_rot"][p])
        for k in range(steps):
            rows = slice((a + k) * n, (a + k + 1) * n)
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                if name in cotangents:
                    _add_grad(getattr(states[k + 1], name), cotangents[name][rows])
        if adjoint_end is not None:
            adjoint_end.seed(states[-1])
        if graphs is not None:
            wp.capture_launch(graphs[1])
        else:
            tape.backward()
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            grads["top_q"][rows] += control.top_q.grad.numpy()
            grads["bar_q"][rows] += control.bar_q.grad.numpy()
            grads["bar_qd"][rows] += control.bar_qd.grad.numpy()
        return StateAdjoint(states[0])


def _copy_unrecorded(dest: wp.array, src: wp.array) -> None:
    """``dest <- src`` off the tape.

    Used for the tension-only step's ``dv``: deliberately, the taped step integrates the
    active-set pass's ``dv`` (which is the untaped solver's, bit for bit) rather than the
    recorded solve's. Where a segment snaps taut in the step, the untaped solve adds its
    block to the already assembled system in place and solves again, while the recorded
    pass assembles the system with it from scratch: the same system up to the order of
    the sums, so the two ``dv`` differ by rounding. With the copy the taped re-run ends
    exactly where the untaped forward did (``_check_rerun``); the recorded adjoint uses
    the recorded system with this ``dv``, which changes the gradient by rounding only.
    """
    runtime = wp._src.context.runtime
    tape, runtime.tape = runtime.tape, None
    try:
        wp.copy(dest, src)
    finally:
        runtime.tape = tape


def _check_rerun(expected, state, a: int, b: int) -> None:
    got = (state.strings.particle_q.numpy(), state.puppet.joint_q.numpy())
    want = (expected.particle_q, expected.joint_q)
    for name, g, w in zip(("string particle_q", "joint_q"), got, want):
        if not np.array_equal(g, w):
            raise RuntimeError(f"taped re-run of puppet steps {a}..{b}: {name} differs from the forward pass by "
                               f"{np.max(np.abs(g - w)):.3g} (the taped step must replay SolverMarionette exactly)")
