"""Forward-mode (tangent-linear) steps of the articulated puppet: JVPs of rollouts, P directions at once.

:class:`ArticulationTangent` advances a state *and* P tangents of it (directional
derivatives of ``joint_q``, ``joint_qd`` along P input directions) by one step of
:class:`~dmarionette.articulation.solver.SolverArticulation`, with the tangent kernels of
:mod:`dmarionette.kernels.articulation_tangent` (one launch per pass for all P directions;
they compute the primal step too). Chaining steps gives the JVP of a rollout with respect
to the initial state and the joint forces of every step.

Scope: the puppet's own step (kinematics, dynamics with joint limits, integration). A model
with point springs (strings) or compiled-in contact is refused, and so is a control with
applied body forces or torques (their wrench depends on the body poses): those kernels
(``articulation_forces``, ``body_contact``) have no tangent yet. Model constants (masses,
inertias, damping, limits, gravity) are constants of the JVP.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.articulation.solver import ArticulationControl, ArticulationState, SolverArticulation
from dmarionette.kernels.articulation_tangent import build_articulation_tangent_kernels

__all__ = ["ArticulationTangent", "TangentState"]


class TangentState:
    """P tangents of an :class:`ArticulationState`.

    Attributes:
        joint_q: shape (P, world_count, q_count), float64.
        joint_qd: shape (P, world_count, qd_count).
        joint_qdd: shape (P, world_count, qd_count) (of the step that produced it).
    """

    def __init__(self, model, direction_count: int, world_count: int):
        shape = (direction_count, world_count)
        self.joint_q = wp.zeros(shape + (model.q_count,), dtype=wp.float64, device=model.device)
        self.joint_qd = wp.zeros(shape + (model.qd_count,), dtype=wp.float64, device=model.device)
        self.joint_qdd = wp.zeros(shape + (model.qd_count,), dtype=wp.float64, device=model.device)


def _launch(kernel, dim: int, values: dict, device) -> None:
    """Launches ``kernel`` with its arguments taken from ``values`` by parameter name."""
    wp.launch(kernel, dim=dim, inputs=[values[a.label] for a in kernel.adj.args], device=device)


class ArticulationTangent:
    """Steps a state and P tangents of it (see the module doc).

    Args:
        solver: the primal solver (its model and implicit/explicit choice).
        direction_count: P.
        world_count: worlds of the states stepped.
        optimization_level: C++ optimisation of the tangent kernels.

    Raises:
        ValueError: a model with point springs or contact (no tangent for those yet).
    """

    def __init__(self, solver: SolverArticulation, direction_count: int, world_count: int = 1,
                 optimization_level: int = 2):
        m = solver.model
        c = m.contacts
        if m.spring_count or c.ground or c.chair is not None or c.ball:
            raise ValueError("ArticulationTangent: the model has point springs or contact; their kernels have "
                             "no tangent yet (only the puppet's own step does)")
        self.solver = solver
        self.model = m
        self.direction_count = direction_count
        self.world_count = world_count
        self.kernels = build_articulation_tangent_kernels(m.topology, optimization_level)
        self.workspace = m.workspace(world_count)
        shape = (direction_count, world_count, m.body_count)
        self.tan_body = {n: wp.zeros(shape, dtype=t, device=m.device) for n, t in
                         (("body_pos", wp.vec3d), ("body_rot", wp.quatd), ("body_w", wp.vec3d),
                          ("body_v", wp.vec3d), ("body_wrench", self.workspace.body_wrench.dtype),
                          ("body_stiffness", self.workspace.body_stiffness.dtype))}

    def tangent_state(self) -> TangentState:
        """Zero tangents for a state of this model."""
        return TangentState(self.model, self.direction_count, self.world_count)

    def step(self, state_in: ArticulationState, tangent_in: TangentState, state_out: ArticulationState,
             tangent_out: TangentState, control: ArticulationControl, tangent_joint_f: wp.array,
             dt: float) -> None:
        """One step of the state and its tangents.

        Args:
            state_in, tangent_in: the state and its P tangents (read).
            state_out, tangent_out: where the next state and its tangents go.
            control: the step's control (its body forces and torques must be zero).
            tangent_joint_f: P tangents of ``control.joint_f``, shape (P, world_count, qd_count).
            dt: the step [s].

        Raises:
            ValueError: what :meth:`SolverArticulation.check_step` raises, or applied body forces or torques.
        """
        s, m, ws = self.solver, self.model, self.workspace
        s.check_step(state_in, state_out, control, dt)
        if np.any(control.body_force.numpy()) or np.any(control.body_torque.numpy()):
            raise ValueError("ArticulationTangent.step: applied body forces or torques; their wrench has "
                             "no tangent yet (it depends on the body poses)")
        h, hi = s.step_sizes(dt)
        P, n, dev = self.direction_count, state_in.world_count, m.device
        body = {k: getattr(ws, k) for k in ("body_pos", "body_rot", "body_w", "body_v")}
        tan = {"tan_" + k: v for k, v in self.tan_body.items()}
        _launch(self.kernels.eval_body_kinematics_tangent, n, dict(
            joint_q=state_in.joint_q, joint_qd=state_in.joint_qd, direction_count=P,
            tan_joint_q=tangent_in.joint_q, tan_joint_qd=tangent_in.joint_qd, **body, **tan), dev)
        s.eval_external_forces(ws, control)  # the torque-free wrench (zero) and stiffness reset
        _launch(self.kernels.solve_body_dynamics_tangent, n, dict(
            body_mass=m.body_mass, body_inertia=m.body_inertia, dof_damping=m.dof_damping, gravity=m.gravity,
            dof_limit_lower=m.dof_limit_lower, dof_limit_upper=m.dof_limit_upper,
            limit_stiffness=wp.float64(m.limit_stiffness), limit_damping=wp.float64(m.limit_damping),
            joint_q=state_in.joint_q, joint_qd=state_in.joint_qd, **body, body_wrench=ws.body_wrench,
            body_stiffness=ws.body_stiffness, joint_f=control.joint_f, h=h, h_implicit=hi, direction_count=P,
            tan_joint_q=tangent_in.joint_q, tan_joint_qd=tangent_in.joint_qd, **tan,
            tan_joint_f=tangent_joint_f, joint_qdd=state_out.joint_qdd, joint_qd_out=state_out.joint_qd,
            tan_joint_qdd=tangent_out.joint_qdd, tan_joint_qd_out=tangent_out.joint_qd), dev)
        _launch(self.kernels.integrate_joint_coordinates_tangent, n, dict(
            joint_q=state_in.joint_q, joint_qd=state_out.joint_qd, h=h, direction_count=P,
            tan_joint_q=tangent_in.joint_q, tan_joint_qd=tangent_out.joint_qd, joint_q_out=state_out.joint_q,
            tan_joint_q_out=tangent_out.joint_q), dev)
