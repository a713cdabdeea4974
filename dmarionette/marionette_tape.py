"""One segment of a marionette rollout on a ``wp.Tape``, and its reverse pass.

:class:`TapedSegment` replays ``SolverMarionette.step``'s passes (begin: body points and
tie path; ``n`` string steps with feedback; end: anchors and the puppet step) with one
fresh array for every quantity a step writes. ``SolverMarionette`` reuses scratch buffers
from step to step (the tie path, the tied points, the string states between substeps, the
puppet control); on a tape an array written after it was read gives silently wrong
gradients, so none of them is reused here. The string substeps write their tie force and
taut flags straight into rows of the step's ``(n, S)`` output arrays (no copies), and the
tied points are evaluated on a shallow copy of the puppet state with its own body-pose
arrays (the puppet step evaluates its input state's body poses again).

The forward values are those of ``SolverMarionette`` (same kernels, same order), which
:meth:`TapedSegment.backward` checks: the taped re-run must end where the untaped run did.
"""

from __future__ import annotations

import copy

import numpy as np
import warp as wp

from .kernels.string_body_coupling import apply_string_forces_to_anchors_kernel, eval_tie_path
from .string_model import StringControl
from .string_rollout import upload_values

__all__ = ["StateAdjoint", "TapedSegment"]


class _Strings:
    """The string-state attributes the string solver reads and writes."""

    def __init__(self, particle_q, particle_qd, tie_force, string_taut):
        self.particle_q = particle_q
        self.particle_qd = particle_qd
        self.tie_force = tie_force
        self.string_taut = string_taut


class _State:
    """A marionette state with gradients (the fields ``MarionetteState`` has)."""

    def __init__(self, model):
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        p = model.strings.particle_count
        with wp.ScopedDevice(model.device):
            self.strings = _Strings(wp.zeros(p, dtype=wp.vec3d, requires_grad=True),
                                    wp.zeros(p, dtype=wp.vec3d, requires_grad=True), None, None)
            self.puppet = model.puppet.state(requires_grad=True)
            self.tie_force = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=True)
            self.string_taut = wp.zeros((n, s), dtype=wp.int32)
            self.bar_feedback = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=True)
            self.bar_reaction = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=True)
            self.tie_target = wp.zeros(s, dtype=wp.vec3d, requires_grad=True)


class _Control:
    def __init__(self, model):
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        with wp.ScopedDevice(model.device):
            self.top_q = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=True)
            self.bar_q = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=True)
            self.bar_qd = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=True)


class StateAdjoint:
    """Adjoint of the carried state at a segment boundary (host arrays, ``Checkpoint`` layout)."""

    def __init__(self, state: _State):
        self.particle_q = state.strings.particle_q.grad.numpy().copy()
        self.particle_qd = state.strings.particle_qd.grad.numpy().copy()
        self.joint_q = state.puppet.joint_q.grad.numpy().copy()
        self.joint_qd = state.puppet.joint_qd.grad.numpy().copy()
        self.tie_target = state.tie_target.grad.numpy().copy()

    def seed(self, state: _State) -> None:
        _add_grad(state.strings.particle_q, self.particle_q)
        _add_grad(state.strings.particle_qd, self.particle_qd)
        _add_grad(state.puppet.joint_q, self.joint_q)
        _add_grad(state.puppet.joint_qd, self.joint_qd)
        _add_grad(state.tie_target, self.tie_target)


def _add_grad(array: wp.array, values) -> None:
    upload_values(array.grad, array.grad.numpy() + np.asarray(values).reshape(array.grad.numpy().shape))


class TapedSegment:
    """Records puppet steps ``a .. b-1`` of a rollout on a tape and runs their reverse pass.

    Args:
        model: the ``MarionetteModel`` (``requires_grad=True``).
        solver: the ``SolverMarionette`` of the untaped forward (its feedback kernel is reused).
    """

    def __init__(self, model, solver):
        self.model = model
        self.solver = solver

    # ------------------------------------------------------------------ the taped step
    def _points(self, puppet_state):
        """Body poses and tied points of ``puppet_state`` into fresh arrays (a shallow copy of
        the state owns the body-pose arrays, so the puppet step's own kinematics pass writes
        different ones)."""
        m = self.model
        view = copy.copy(puppet_state)
        nb = m.puppet.body_count
        with wp.ScopedDevice(m.device):
            view.body_pos = wp.zeros((1, nb), dtype=wp.vec3d, requires_grad=True)
            view.body_rot = wp.zeros((1, nb), dtype=wp.quatd, requires_grad=True)
            view.body_w = wp.zeros((1, nb), dtype=wp.vec3d, requires_grad=True)
            view.body_v = wp.zeros((1, nb), dtype=wp.vec3d, requires_grad=True)
            npt = len(m.puppet.point_names)
            point_q = wp.zeros((1, npt), dtype=wp.vec3d, requires_grad=True)
            point_qd = wp.zeros((1, npt), dtype=wp.vec3d, requires_grad=True)
        m.puppet_solver.eval_kinematics(view)
        m.puppet_solver.eval_points(view, point_q, point_qd)
        return view, point_q, point_qd

    def step(self, state_in: _State, state_out: _State, control: _Control):
        """One puppet step on the active tape; returns ``(body-pose view, tied points)`` of ``state_in``."""
        m = self.model
        n, s = m.substeps, m.strings.string_count
        view, point_q, point_qd = self._points(state_in.puppet)
        with wp.ScopedDevice(m.device):
            tie_q = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=True)
            tie_qd = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=True)
        wp.launch(eval_tie_path, dim=(n, s),
                  inputs=[m.string_point_wp, point_q, point_qd, state_in.tie_target, wp.float64(m.string_dt)],
                  outputs=[tie_q, tie_qd, state_out.tie_target], device=m.device)
        previous = state_in.strings
        feedback = self.solver._feedback
        weight = wp.vec3d(*(m.puppet_mass * np.asarray(m.scene.gravity)))
        st = m.strings
        for j in range(n):
            if j == n - 1:
                q, qd = state_out.strings.particle_q, state_out.strings.particle_qd
            else:
                with wp.ScopedDevice(m.device):
                    q = wp.zeros(st.particle_count, dtype=wp.vec3d, requires_grad=True)
                    qd = wp.zeros(st.particle_count, dtype=wp.vec3d, requires_grad=True)
            nxt = _Strings(q, qd, state_out.tie_force[j], state_out.string_taut[j])
            m.string_solver.step(previous, nxt, StringControl(control.top_q[j], tie_q[j], tie_qd[j]), m.string_dt)
            if feedback is not None:
                wp.launch(feedback, dim=st.string_count,
                          inputs=[st.string_start, m.string_bar_wp, st.string_stiffness, st.string_rest_length,
                                  st.string_internal_friction, wp.float64(m.scene.feedback_stiffness),
                                  wp.float64(m.scene.feedback_damping), weight,
                                  nxt.particle_q, nxt.particle_qd, nxt.string_taut,
                                  control.bar_q[j], control.bar_qd[j]],
                          outputs=[state_out.bar_feedback[j], state_out.bar_reaction[j]], device=m.device)
            previous = nxt
        puppet_control = m.puppet.control(requires_grad=True)
        if len(m.spring_string):
            wp.launch(apply_string_forces_to_anchors_kernel(n), dim=len(m.spring_string),
                      inputs=[m.spring_string_wp, st.string_tie_stiffness, state_out.tie_force, tie_q, tie_qd,
                              wp.float64(m.string_dt)],
                      outputs=[puppet_control.spring_anchor_pos, puppet_control.spring_anchor_vel], device=m.device)
        m.puppet_solver.step(state_in.puppet, state_out.puppet, puppet_control, m.puppet_dt)
        return view, point_q

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
        states = [_State(m) for _ in range(steps + 1)]
        checkpoint.load(states[0])
        controls = [_Control(m) for _ in range(steps)]
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            upload_values(control.top_q, inputs.top_q[rows])
            upload_values(control.bar_q, inputs.bar_q[rows])
            upload_values(control.bar_qd, inputs.bar_qd[rows])
        tape = wp.Tape()
        records = []
        with tape:
            for k in range(steps):
                records.append(self.step(states[k], states[k + 1], controls[k]))
            if last:
                view, point_q, _ = self._points(states[-1].puppet)
                records.append((view, point_q))
        if expected_end is not None:
            _check_rerun(expected_end, states[-1], a, b)
        # Seed: the per-step outputs of this segment, then the state adjoint from the next one.
        for k, (view, point_q) in enumerate(records):
            p = a + k
            if "joint_q" in cotangents:
                _add_grad(states[k].puppet.joint_q, cotangents["joint_q"][p])
            if "point_pos" in cotangents:
                _add_grad(point_q, cotangents["point_pos"][p])
            if "body_pos" in cotangents:
                _add_grad(view.body_pos, cotangents["body_pos"][p])
            if "body_rot" in cotangents:
                _add_grad(view.body_rot, cotangents["body_rot"][p])
        for k in range(steps):
            rows = slice((a + k) * n, (a + k + 1) * n)
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                if name in cotangents:
                    _add_grad(getattr(states[k + 1], name), cotangents[name][rows])
        if adjoint_end is not None:
            adjoint_end.seed(states[-1])
        tape.backward()
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            grads["top_q"][rows] += control.top_q.grad.numpy()
            grads["bar_q"][rows] += control.bar_q.grad.numpy()
            grads["bar_qd"][rows] += control.bar_qd.grad.numpy()
        adjoint = StateAdjoint(states[0])
        tape.launches.clear()  # not reset(): that zeroes the model parameters' accumulated gradients
        return adjoint


def _check_rerun(expected, state: _State, a: int, b: int) -> None:
    got = (state.strings.particle_q.numpy(), state.puppet.joint_q.numpy())
    want = (expected.particle_q, expected.joint_q)
    for name, g, w in zip(("string particle_q", "joint_q"), got, want):
        if not np.array_equal(g, w):
            raise RuntimeError(f"taped re-run of puppet steps {a}..{b}: {name} differs from the forward pass by "
                               f"{np.max(np.abs(g - w)):.3g} (the taped step must replay SolverMarionette exactly)")
