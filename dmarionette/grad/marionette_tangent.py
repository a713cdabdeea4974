"""Forward-mode (tangent-linear) step of the marionette: one :meth:`SolverMarionette.step
<dmarionette.marionette.solver.SolverMarionette.step>` and its P directional derivatives.

:class:`MarionetteTangent` runs the step's passes in the solver's order, each with its
tangent (one launch per pass for all P directions, which also computes the pass's primal):

- ``begin_step``: the input's body points (primal only: nothing of the step reads them),
  the trial puppet step (kinematics, applied forces, the strings' linearised pull
  ``eval_string_response``, contacts, dynamics, integration: :class:`PuppetStepTangent`'s
  passes and the interleaved tangent of the coupling kernel), its body points at
  ``t0 + H``, the tie path;
- ``n`` string steps (:class:`~dmarionette.grad.string_tangent.StringStepTangent`, the string
  step keeping its factorisation and its tangent-linear model), each followed by the bar
  feedback (eq. 4 and the exact reaction);
- ``end_step``: the anchors (mean tie force, the tie around the path) and the puppet step
  with its point springs (:class:`~dmarionette.articulation.step_tangent.PuppetStepTangent`).
  Its contacts are those of the trial step (the same kinematics, of the input state, and the
  same ``h``): their tangents, kept from the trial, are added (``contacts_kept``) and only
  their primal evaluated again (the solver's launch), which halves the contacts' cost (the
  largest of the puppet's: 1.6 of a forward rollout's time for 1 s of ``hanging`` at P = 16).

What is differentiated (:class:`MarionetteTangentState`, :class:`MarionetteControlTangent`,
leading direction axis ``P``): the state (the puppet's ``joint_q``, ``joint_qd``; the strings'
particle positions and velocities; the previous step's tie forces; the tie target) and the
control (the string tops and the bars' eq. 4 proxies ``bar_q``, ``bar_qd`` over the step), and
optionally (:class:`MarionetteConstantsTangent`) the constants calibration fits, per string:
the tie's ``k`` and ``k_d`` (eq. 2, on both sides: the strings' tie, the trial's response, the
anchors' ``F / k`` and the puppet's point springs, whose rows are the tied strings') and the
segment stiffness ``k_s`` (the strings, the response's tension and axial stiffness, the
exact reaction). Every other model constant is a constant of this JVP (masses, lengths,
friction, drag, ground constants, the puppet's). Float64 strings with the printed spring
only (float32 strings and tension-only springs are refused).

Checked against the tape's reverse mode of the same steps by the dot-product identity
(``tests/grad/test_marionette_tangent.py``: two puppet steps of the shipped ``hanging`` scene, and
of ``chair``, whose contacts act).
Cost (``python benchmarks/bench_marionette_tangent.py --opt 2 --directions 1 4 8 16``, CPU,
under load): P = 1, 4, 8, 16 tangents cost 3.0, 3.1, 3.8, 4.9 plain steps (issue 13's target
``1 + 0.5 P``: 1.5, 3, 5, 9); the 33 string steps dominate both.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.articulation.step_tangent import PuppetStepTangent, TangentState
from dmarionette.grad.string_tangent import CONSTANTS, StringStepTangent
from dmarionette.kernels.articulation_forces import eval_body_points
from dmarionette.kernels.kernel_tangent import UNROLL, tangent_kernel
from dmarionette.kernels.tangent_directions import direction_minor
from dmarionette.kernels.bar_feedback import eval_bar_feedback_kernel
from dmarionette.kernels.string_body_coupling import (apply_string_forces_to_anchors_kernel,
                                                      eval_string_response_kernel, eval_tie_path)
from dmarionette.marionette.solver import MarionetteControl, MarionetteState, SolverMarionette
from dmarionette.strings.rollout import upload_values

__all__ = ["MarionetteConstantsTangent", "MarionetteControlTangent", "MarionetteTangent", "MarionetteTangentState"]


class MarionetteTangentState:
    """P tangents of a :class:`MarionetteState` (zeros).

    Attributes:
        puppet: the puppet state's (``joint_q``, ``joint_qd``, ``joint_qdd``).
        particle_q, particle_qd: ``(P, particles)`` vec3d (stored direction-minor: a view of
            ``(particles, P)``, ``kernels.tangent_directions.direction_minor``).
        tie_force: ``(P, n, S)``; tie_target: ``(P, S)``.
        bar_feedback, bar_reaction: ``(P, n, W B)``.
    """

    def __init__(self, model, direction_count: int):
        P, n, dev = direction_count, model.substeps, model.device
        s, b = model.strings.string_count, model.bar_rows * model.world_count
        self.puppet = TangentState(model.puppet, P, model.world_count)
        # stored direction-minor, as the string tangent loads them fastest (``tangent_directions``)
        self.particle_q = direction_minor(P, model.strings.particle_count, wp.vec3d, dev)
        self.particle_qd = direction_minor(P, model.strings.particle_count, wp.vec3d, dev)
        self.tie_force = wp.zeros((P, n, s), dtype=wp.vec3d, device=dev)
        self.tie_target = wp.zeros((P, s), dtype=wp.vec3d, device=dev)
        self.bar_feedback = wp.zeros((P, n, max(b, 1)), dtype=wp.vec3d, device=dev)
        self.bar_reaction = wp.zeros((P, n, max(b, 1)), dtype=wp.vec3d, device=dev)


class MarionetteControlTangent:
    """P tangents of a :class:`MarionetteControl` (zeros): top_q ``(P, n, S)``, bar_q and bar_qd
    ``(P, n, W B)``."""

    def __init__(self, model, direction_count: int):
        P, n, dev = direction_count, model.substeps, model.device
        s, b = model.strings.string_count, model.bar_rows * model.world_count
        self.top_q = wp.zeros((P, n, s), dtype=wp.vec3d, device=dev)
        self.bar_q = wp.zeros((P, n, max(b, 1)), dtype=wp.vec3d, device=dev)
        self.bar_qd = wp.zeros((P, n, max(b, 1)), dtype=wp.vec3d, device=dev)


class MarionetteConstantsTangent:
    """P directions in the calibrated constants (zeros), per string of all worlds, as the kernels read
    them: ``tie_stiffness`` ``k`` [N/m], ``tie_damping`` ``k_d`` [N s/m] and ``string_stiffness``, the
    segment stiffness ``k_s`` [N/m] (``model.strings.string_stiffness``); each ``(P, W S)``."""

    def __init__(self, model, direction_count: int):
        shape, dev = (direction_count, model.strings.string_count), model.device
        self.tie_stiffness = wp.zeros(shape, dtype=wp.float64, device=dev)
        self.tie_damping = wp.zeros(shape, dtype=wp.float64, device=dev)
        self.string_stiffness = wp.zeros(shape, dtype=wp.float64, device=dev)


class MarionetteTangent:
    """Steps a marionette state and P tangents of it (module doc).

    Args:
        solver: the marionette's solver (float64 strings, printed springs).
        direction_count: P.
        optimization_level: C++ optimisation of the generated puppet tangent kernels.
    """

    def __init__(self, solver: SolverMarionette, direction_count: int, optimization_level: int = 2):
        m = solver.model
        if m.precision != "float64":
            raise NotImplementedError("MarionetteTangent: float32 strings (the precision boundary has no tangent "
                                      "here); use [solver] precision = \"float64\"")
        self.solver = solver
        self.model = m
        self.direction_count = P = int(direction_count)
        self.puppet = PuppetStepTangent(m.puppet_solver, P, m.world_count, optimization_level)
        self.strings = StringStepTangent(m.string_solver, P)
        self.workspace = solver.new_workspace(taped=False)
        self.trial = self.puppet.tangent_state()
        self.trial_body = self.puppet.body_tangents()
        self.points_body = self.puppet.body_tangents()
        points = len(m.puppet.point_names)
        dev, n, s = m.device, m.substeps, m.strings.string_count
        self.trial_point_q = wp.zeros((P, m.world_count, points), dtype=wp.vec3d, device=dev)
        self.trial_point_qd = wp.zeros((P, m.world_count, points), dtype=wp.vec3d, device=dev)
        self.tie_q = wp.zeros((P, n, s), dtype=wp.vec3d, device=dev)
        self.tie_qd = wp.zeros((P, n, s), dtype=wp.vec3d, device=dev)
        self.particles = [(direction_minor(P, m.strings.particle_count, wp.vec3d, dev),
                           direction_minor(P, m.strings.particle_count, wp.vec3d, dev)) for _ in range(2)]
        self.mass_dot = direction_minor(P, m.strings.particle_count, m.strings.scalar, dev)
        self.constants_dot = wp.zeros((P, s, len(CONSTANTS)), dtype=m.strings.scalar, device=dev)
        self.puppet_control = self.puppet.control_tangent()  # zero but for the anchors
        self._zeros: dict = {}
        self._constants: dict = {}
        self._points = tangent_kernel(eval_body_points, unroll=UNROLL)
        self._tie_path = tangent_kernel(eval_tie_path, unroll=UNROLL)
        self._anchors = tangent_kernel(apply_string_forces_to_anchors_kernel(m.substeps), unroll=UNROLL)
        effects = m.scene.effects
        # the solver's kernels (the factories are cached: the same kernel objects)
        # (each unrolled: the primal once per block of up to UNROLL directions, kernel_tangent)
        self._response = (tangent_kernel(eval_string_response_kernel(m.strings.scalar, effects.internal_friction,
                                                                     m.substeps), unroll=UNROLL)
                          if len(m.spring_string) else None)
        self._feedback = (tangent_kernel(eval_bar_feedback_kernel(m.strings.scalar, effects.internal_friction,
                                                                  effects.tension_only, bar_scalar=wp.float64),
                                         unroll=UNROLL)
                          if m.scene.body_effects["feedback"] and m.bar_count else None)

    def tangent_state(self) -> MarionetteTangentState:
        return MarionetteTangentState(self.model, self.direction_count)

    def control_tangent(self) -> MarionetteControlTangent:
        return MarionetteControlTangent(self.model, self.direction_count)

    def constants_tangent(self) -> MarionetteConstantsTangent:
        return MarionetteConstantsTangent(self.model, self.direction_count)

    def spread_constants(self, tk: MarionetteConstantsTangent | None) -> None:
        """Writes the constants' directions ``tk`` (None: zero) where the step's passes read them."""
        self._constants = self._spread_constants(tk)

    def _spread_constants(self, tk: MarionetteConstantsTangent | None) -> dict:
        """The constants' directions where each pass reads them: the string step's ``constants_dot``
        columns, the puppet springs' rows (spring ``i`` of world ``w`` is string ``w S + spring_string[i]``);
        returns the coupling kernels' tangent arrays by name."""
        m, P = self.model, self.direction_count
        if tk is None:
            self.constants_dot.zero_()
            self.puppet_control.spring_stiffness.zero_()
            self.puppet_control.spring_damping.zero_()
            return {}
        c = np.zeros((P, m.strings.string_count, len(CONSTANTS)))
        k, kd, ks = tk.tie_stiffness.numpy(), tk.tie_damping.numpy(), tk.string_stiffness.numpy()
        c[..., CONSTANTS.index("string_tie_stiffness")] = k
        c[..., CONSTANTS.index("string_tie_damping")] = kd
        c[..., CONSTANTS.index("string_stiffness")] = ks
        upload_values(self.constants_dot, c)
        if len(m.spring_string):
            worlds = m.puppet.spring_stiffness.shape[0] // len(m.spring_string)
            rows = np.concatenate([w * m.strings_per_world + m.spring_string for w in range(worlds)])
            upload_values(self.puppet_control.spring_stiffness, k[:, rows])
            upload_values(self.puppet_control.spring_damping, kd[:, rows])
        return {"string_tie_stiffness": tk.tie_stiffness, "string_stiffness": tk.string_stiffness}

    def step(self, state_in: MarionetteState, tangent_in: MarionetteTangentState, state_out: MarionetteState,
             tangent_out: MarionetteTangentState, control: MarionetteControl,
             tangent_control: MarionetteControlTangent,
             tangent_constants: MarionetteConstantsTangent | None = None, *, spread: bool = True) -> None:
        """One puppet step of the state and of its P tangents (``tangent_out`` other arrays than
        ``tangent_in``); ``tangent_constants``: directions in the calibrated constants (None: zero).
        ``spread=False``: the constants' directions as the last :meth:`spread_constants` left them
        (no host work: the step's launches can be captured as a graph, ``grad/rollout_tangent``)."""
        m, sv, ws, P = self.model, self.solver, self.workspace, self.direction_count
        dev = m.device
        if spread:
            self.spread_constants(tangent_constants)
        # ---- begin_step
        sv.eval_body_points(state_in, ws.points)
        self._predict(state_in, tangent_in, ws)
        self._tie_path.launch((m.substeps, m.strings.string_count), P,
                              [m.string_point_wp, wp.int32(m.strings_per_world), ws.trial_points.point_q,
                               state_in.tie_target, wp.float64(m.string_dt), ws.tie_q, ws.tie_qd, state_out.tie_target],
                              {"point_end": self.trial_point_q, "tie_target": tangent_in.tie_target,
                               "tie_q": self.tie_q, "tie_qd": self.tie_qd, "tie_target_out": tangent_out.tie_target},
                              dev)
        if self._feedback is not None:
            for a in (state_out.bar_feedback, state_out.bar_reaction, tangent_out.bar_feedback,
                      tangent_out.bar_reaction):
                a.zero_()
        # ---- the string steps
        controls = sv.string_controls(control, workspace=ws)
        q_dot, qd_dot = tangent_in.particle_q, tangent_in.particle_qd
        for j in range(m.substeps):
            previous = state_in.strings if j == 0 else sv.string_state_after(state_out, j - 1, workspace=ws)
            nxt = sv.string_step_outputs(state_out, workspace=ws)[j]
            q_out, qd_out = ((tangent_out.particle_q, tangent_out.particle_qd) if j == m.substeps - 1
                             else self.particles[j % 2])
            self.strings.step(previous, nxt, controls[j], m.string_dt, q_dot, qd_dot, q_out, qd_out,
                              tangent_out.tie_force[:, j], tangent_control.top_q[:, j], self.tie_q[:, j],
                              self.tie_qd[:, j], self.mass_dot, self.constants_dot)
            if self._feedback is not None:
                self._eval_feedback(nxt, q_out, qd_out, control, tangent_control, state_out, tangent_out, j)
            q_dot, qd_dot = q_out, qd_out
        # ---- end_step
        if len(m.spring_string):
            self._anchors.launch((m.world_count, len(m.spring_string)), P,
                                 [m.spring_string_wp, wp.int32(m.strings_per_world), m.string_tie_stiffness,
                                  state_out.tie_force, ws.tie_q, ws.tie_qd, wp.float64(m.string_dt),
                                  ws.puppet_control.spring_anchor_pos, ws.puppet_control.spring_anchor_vel],
                                 {"tie_force": tangent_out.tie_force, "tie_q": self.tie_q, "tie_qd": self.tie_qd,
                                  "string_tie_stiffness": self._constant("string_tie_stiffness"),
                                  "spring_anchor_pos": self.puppet_control.spring_anchor_pos,
                                  "spring_anchor_vel": self.puppet_control.spring_anchor_vel}, dev)
        self.puppet.step(state_in.puppet, tangent_in.puppet, state_out.puppet, tangent_out.puppet,
                         ws.puppet_control, self.puppet_control, m.puppet_dt, contacts_kept=True)

    def _predict(self, state_in, tangent_in: MarionetteTangentState, ws) -> None:
        """The trial puppet step (``SolverMarionette.predict_body_points``) and its tangent."""
        m, pt, P = self.model, self.puppet, self.direction_count
        ps, tw, puppet, tb = m.puppet_solver, ws.trial_workspace, state_in.puppet, self.trial_body
        h, hi = ps.step_sizes(m.puppet_dt)
        pt.eval_kinematics(puppet, tangent_in.puppet, tw, tb)
        pt.eval_external_forces(tw, tb, ws.puppet_control, self.puppet_control)
        if self._response is not None:
            s = m.strings
            self._response.launch(
                (tw.world_count, len(m.spring_string)), P,
                [m.puppet.spring_body, m.puppet.spring_point, m.spring_string_wp, wp.int32(m.strings_per_world),
                 s.arrays, tw.body_pos, tw.body_rot, tw.body_w, tw.body_v,
                 state_in.strings.particle_q, state_in.tie_force, hi, tw.body_wrench, tw.body_stiffness],
                {**{k: tb[k] for k in ("body_pos", "body_rot", "body_w", "body_v", "body_wrench", "body_stiffness")},
                 "particle_q": tangent_in.particle_q, "tie_force": tangent_in.tie_force,
                 **{k: self._constant(k) for k in self._response.tangent_inputs if k.startswith("string_")}},
                m.device)
        pt.eval_contacts(tw, tb, hi, keep=True)  # the same as the puppet step's (end_step): kept for it
        pt.solve_dynamics(puppet, tangent_in.puppet, ws.trial, self.trial, ws.puppet_control, self.puppet_control,
                          tw, tb, h, hi)
        pt.integrate(puppet, tangent_in.puppet, ws.trial, self.trial, h)
        kin, pb = ws.trial_points.kinematics, self.points_body
        pt.eval_kinematics(ws.trial, self.trial, kin, pb)
        self._points.launch((m.world_count, len(m.puppet.point_names)), P,
                            [m.puppet.point_body, m.puppet.point_local, kin.body_pos, kin.body_rot, kin.body_w,
                             kin.body_v, ws.trial_points.point_q, ws.trial_points.point_qd],
                            {**{k: pb[k] for k in ("body_pos", "body_rot", "body_w", "body_v")},
                             "point_pos": self.trial_point_q, "point_vel": self.trial_point_qd}, m.device)

    def _constant(self, name: str) -> wp.array:
        """The tangent of string constant ``name`` in this step (zero unless a calibrated one is moved)."""
        return self._constants[name] if name in self._constants else self._zero_constant(name)

    def _zero_constant(self, name: str) -> wp.array:
        """A zero tangent of the string constant ``name`` (``model.strings``' array)."""
        a = getattr(self.model.strings, name)
        if name not in self._zeros:
            self._zeros[name] = wp.zeros((self.direction_count, *a.shape), dtype=a.dtype, device=self.model.device)
        return self._zeros[name]

    def _eval_feedback(self, strings, q_dot, qd_dot, control, tc: MarionetteControlTangent, state_out,
                       tangent_out: MarionetteTangentState, j: int) -> None:
        m = self.model
        s = m.strings
        weight = wp.vec3d(*(m.puppet_mass * np.asarray(m.scene.gravity)))
        self._feedback.launch(
            s.string_count, self.direction_count,
            [s.arrays, m.string_bar_wp, wp.float64(m.scene.feedback_stiffness), wp.float64(m.scene.feedback_damping),
             weight, strings.arrays, control.bar_q[j], control.bar_qd[j],
             state_out.bar_feedback[j], state_out.bar_reaction[j]],
            {"particle_q": q_dot, "particle_qd": qd_dot, "bar_q": tc.bar_q[:, j], "bar_qd": tc.bar_qd[:, j],
             "bar_feedback": tangent_out.bar_feedback[:, j], "bar_reaction": tangent_out.bar_reaction[:, j],
             **{k: self._constant(k) for k in self._feedback.tangent_inputs if k.startswith("string_")}},
            m.device)
