"""Forward-mode (tangent-linear) step of the whole puppet step, point springs and contact included.

:class:`PuppetStepTangent` runs one :meth:`SolverArticulation.step
<dmarionette.articulation.solver.SolverArticulation.step>` and its P directional derivatives,
pass by pass in the step's order: body kinematics and the dynamics and integration with
the generated tangent kernels (:mod:`dmarionette.kernels.articulation_tangent`, a
direction loop per world), the applied forces, the point springs (paper eq. 2 against the
coupling's anchors) and the compiled-in contacts with the interleaved tangent kernels of
the hand-written kernels (:mod:`dmarionette.kernels.kernel_tangent`, a thread per
direction and item). Each tangent launch writes the pass's primal outputs too, so the
step's numbers are the solver's.

What is differentiated (:class:`PuppetControlTangent`, all with a leading direction axis
``P``): the state (``joint_q``, ``joint_qd``; :class:`TangentState`),
the joint forces, the applied body forces and torques, the springs' anchors and anchor
velocities, and the springs' stiffness and damping (the calibrated tie constants ``k``,
``k_d``; one row per spring, or per world and spring where the model has per-world
constants). Constant: masses, inertias, joint damping and limits, gravity, the contact
constants, the spring points, ``dt``.

A pass of the same kinematics may reuse the contacts' tangents of an earlier one
(:meth:`PuppetStepTangent.eval_contacts` with ``keep``, then ``step(..., contacts_kept=True)``:
the marionette's trial step and its puppet step, ``grad/marionette_tangent``), the contacts'
primal evaluated again (the solver's launch), their tangents added once more.

Chaining steps gives the JVP of a rollout with respect to the initial state and every
step's inputs (``tests/articulation/test_puppet_tangent.py``: a 10-step rollout against the
tape's VJP; ``tests/articulation/test_puppet_step_tangent.py``: springs and contact, and the kept
contact tangents against the step's own).
"""

from __future__ import annotations

import warp as wp

from dmarionette.articulation.solver import ArticulationControl, ArticulationState, SolverArticulation
from dmarionette.kernels.articulation_forces import eval_body_external_forces, eval_body_point_springs
from dmarionette.kernels.articulation_tangent import build_articulation_tangent_kernels
from dmarionette.kernels.body_load_tangent import apply_body_load_tangents
from dmarionette.kernels.kernel_tangent import UNROLL, tangent_kernel

__all__ = ["PuppetControlTangent", "PuppetStepTangent", "TangentState"]


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


class PuppetControlTangent:
    """P tangents of an :class:`ArticulationControl` and of the spring constants (zeros).

    Attributes:
        joint_f: (P, world_count, qd_count).
        body_force, body_torque: (P, world_count, body_count) vec3d.
        spring_anchor_pos, spring_anchor_vel: (P, world_count, spring_count) vec3d.
        spring_stiffness, spring_damping: (P, rows) with the model's rows of constants.
    """

    def __init__(self, model, direction_count: int, world_count: int):
        P, n, dev = direction_count, world_count, model.device
        self.joint_f = wp.zeros((P, n, model.qd_count), dtype=wp.float64, device=dev)
        self.body_force = wp.zeros((P, n, model.body_count), dtype=wp.vec3d, device=dev)
        self.body_torque = wp.zeros((P, n, model.body_count), dtype=wp.vec3d, device=dev)
        springs = max(model.spring_count, 1)
        self.spring_anchor_pos = wp.zeros((P, n, springs), dtype=wp.vec3d, device=dev)
        self.spring_anchor_vel = wp.zeros((P, n, springs), dtype=wp.vec3d, device=dev)
        rows = max(model.spring_stiffness.shape[0], 1)
        self.spring_stiffness = wp.zeros((P, rows), dtype=wp.float64, device=dev)
        self.spring_damping = wp.zeros((P, rows), dtype=wp.float64, device=dev)


def _launch(kernel, dim, values: dict, device) -> None:
    """Launches a generated articulation tangent kernel with its arguments taken by parameter name."""
    wp.launch(kernel, dim=dim, inputs=[values[a.label] for a in kernel.adj.args], device=device)


class PuppetStepTangent:
    """Steps a puppet state and P tangents of it (module doc).

    Args:
        solver: the primal solver (model, contacts, implicit or explicit).
        direction_count: P.
        world_count: worlds of the states stepped.
        optimization_level: C++ optimisation of the generated articulation tangent kernels.
    """

    def __init__(self, solver: SolverArticulation, direction_count: int, world_count: int = 1,
                 optimization_level: int = 2):
        m = solver.model
        self.solver = solver
        self.model = m
        self.direction_count = int(direction_count)
        self.world_count = int(world_count)
        self.kernels = build_articulation_tangent_kernels(m.topology, optimization_level)
        self.workspace = m.workspace(world_count)
        self.tan_body = self.body_tangents()
        self.tan_spring_force = wp.zeros((self.direction_count, self.world_count, max(m.spring_count, 1)),
                                         dtype=wp.vec3d, device=m.device)
        self._forces = tangent_kernel(eval_body_external_forces, unroll=UNROLL)
        self._springs = tangent_kernel(eval_body_point_springs, unroll=UNROLL)
        contacts = solver.contacts
        self._contacts = [tangent_kernel(k, unroll=UNROLL) for k in contacts.kernels] if contacts.any else []
        # the contacts' tangents of the last eval_contacts(..., keep=True) alone (for step(..., contacts_kept=True))
        self.kept_contacts = {n: wp.zeros((self.direction_count, self.world_count, m.body_count),
                                          dtype=getattr(self.workspace, n).dtype, device=m.device)
                              for n in ("body_wrench", "body_stiffness")}

    def tangent_state(self) -> TangentState:
        """Zero tangents for a state of this model."""
        return TangentState(self.model, self.direction_count, self.world_count)

    def control_tangent(self) -> PuppetControlTangent:
        """Zero tangents of a control and of the spring constants."""
        return PuppetControlTangent(self.model, self.direction_count, self.world_count)

    def step(self, state_in: ArticulationState, tangent_in: TangentState, state_out: ArticulationState,
             tangent_out: TangentState, control: ArticulationControl, tangent_control: PuppetControlTangent,
             dt: float, *, contacts_kept: bool = False) -> None:
        """One step of the state (the solver's step, pass for pass) and of its P tangents.

        ``contacts_kept``: the contacts' tangents are those the last :meth:`eval_contacts` with
        ``keep=True`` kept, a pass of the same kinematics (``state_in``'s and ``tangent_in``'s) and
        ``dt``: only the primal contacts are evaluated here (the solver's launch), and the kept
        tangents added (:meth:`apply_kept_contacts`; the marionette's trial step and its puppet step,
        ``grad/marionette_tangent``). The caller answers for the kinematics being the same.

        Raises:
            ValueError: what :meth:`SolverArticulation.check_step` raises.
        """
        s, ws = self.solver, self.workspace
        s.check_step(state_in, state_out, control, dt)
        h, hi = s.step_sizes(dt)
        self.eval_kinematics(state_in, tangent_in, ws, self.tan_body)
        self.eval_external_forces(ws, self.tan_body, control, tangent_control)
        self.eval_point_springs(ws, self.tan_body, control, tangent_control, hi)
        if contacts_kept:
            self.apply_kept_contacts(ws, self.tan_body, hi)
        else:
            self.eval_contacts(ws, self.tan_body, hi)
        self.solve_dynamics(state_in, tangent_in, state_out, tangent_out, control, tangent_control, ws,
                            self.tan_body, h, hi)
        self.integrate(state_in, tangent_in, state_out, tangent_out, h)

    def body_tangents(self, world_count: int | None = None) -> dict:
        """Zero tangents of a workspace's body kinematics and loads: name -> (P, world_count, body_count)."""
        m, ws = self.model, self.workspace
        shape = (self.direction_count, world_count or self.world_count, m.body_count)
        return {n: wp.zeros(shape, dtype=getattr(ws, n).dtype, device=m.device)
                for n in ("body_pos", "body_rot", "body_w", "body_v", "body_wrench", "body_stiffness")}

    # ------------------------------------------------------------------ passes (SolverArticulation's)
    def eval_kinematics(self, state, tangent: TangentState, out, tan_out: dict) -> None:
        """Body kinematics of ``state`` into ``out`` (a workspace or kinematics), tangents into ``tan_out``."""
        _launch(self.kernels.eval_body_kinematics_tangent, state.world_count, dict(
            joint_q=state.joint_q, joint_qd=state.joint_qd, direction_count=self.direction_count,
            tan_joint_q=tangent.joint_q, tan_joint_qd=tangent.joint_qd,
            **{k: getattr(out, k) for k in ("body_pos", "body_rot", "body_w", "body_v")},
            **{"tan_" + k: tan_out[k] for k in ("body_pos", "body_rot", "body_w", "body_v")}), self.model.device)

    def eval_external_forces(self, ws, tb: dict, control, tc: PuppetControlTangent) -> None:
        """Applied forces (resets the wrench and stiffness, and their tangents)."""
        self._forces.launch((ws.world_count, self.model.body_count), self.direction_count,
                            [ws.body_pos, control.body_force, control.body_torque, ws.body_wrench, ws.body_stiffness],
                            {"body_pos": tb["body_pos"], "body_force": tc.body_force, "body_torque": tc.body_torque,
                             "body_wrench": tb["body_wrench"], "body_stiffness": tb["body_stiffness"]},
                            self.model.device)

    def eval_point_springs(self, ws, tb: dict, control, tc: PuppetControlTangent, h) -> None:
        """The point springs (eq. 2) against the anchors, implicit over ``h``."""
        m = self.model
        if not m.spring_count:
            return
        body = [ws.body_pos, ws.body_rot, ws.body_w, ws.body_v]
        self._springs.launch(
            (ws.world_count, m.spring_count), self.direction_count,
            [m.spring_body, m.spring_point, m.spring_stiffness, m.spring_damping, *body,
             control.spring_anchor_pos, control.spring_anchor_vel, h, ws.spring_force, ws.body_wrench,
             ws.body_stiffness],
            {**{k: tb[k] for k in ("body_pos", "body_rot", "body_w", "body_v")},
             "spring_stiffness": tc.spring_stiffness, "spring_damping": tc.spring_damping,
             "spring_anchor_pos": tc.spring_anchor_pos, "spring_anchor_vel": tc.spring_anchor_vel,
             "spring_force": self.tan_spring_force, "body_wrench": tb["body_wrench"],
             "body_stiffness": tb["body_stiffness"]}, m.device)

    def solve_dynamics(self, state_in, tangent_in: TangentState, state_out, tangent_out: TangentState, control,
                       tc: PuppetControlTangent, ws, tb: dict, h, h_implicit) -> None:
        """``(M + h D + h^2 K) qdd = tau`` and its tangent."""
        m = self.model
        limits = {}
        if m.topology.joint_limits:
            limits = dict(dof_limit_lower=m.dof_limit_lower, dof_limit_upper=m.dof_limit_upper,
                          limit_stiffness=wp.float64(m.limit_stiffness), limit_damping=wp.float64(m.limit_damping))
        _launch(self.kernels.solve_body_dynamics_tangent, state_in.world_count, dict(
            body_mass=m.body_mass, body_inertia=m.body_inertia, dof_damping=m.dof_damping, gravity=m.gravity,
            **limits, joint_q=state_in.joint_q, joint_qd=state_in.joint_qd,
            **{k: getattr(ws, k) for k in ("body_pos", "body_rot", "body_w", "body_v", "body_wrench",
                                           "body_stiffness")},
            joint_f=control.joint_f, h=h, h_implicit=h_implicit, direction_count=self.direction_count,
            tan_joint_q=tangent_in.joint_q, tan_joint_qd=tangent_in.joint_qd, **{"tan_" + k: v for k, v in tb.items()},
            tan_joint_f=tc.joint_f, joint_qdd=state_out.joint_qdd, joint_qd_out=state_out.joint_qd,
            tan_joint_qdd=tangent_out.joint_qdd, tan_joint_qd_out=tangent_out.joint_qd), m.device)

    def integrate(self, state_in, tangent_in: TangentState, state_out, tangent_out: TangentState, h) -> None:
        """``q' = q (+) h qd'`` and its tangent."""
        _launch(self.kernels.integrate_joint_coordinates_tangent, state_in.world_count, dict(
            joint_q=state_in.joint_q, joint_qd=state_out.joint_qd, h=h, direction_count=self.direction_count,
            tan_joint_q=tangent_in.joint_q, tan_joint_qd=tangent_out.joint_qd, joint_q_out=state_out.joint_q,
            tan_joint_q_out=tangent_out.joint_q), self.model.device)

    def eval_contacts(self, ws, tb: dict, h, keep: bool = False) -> None:
        """The compiled-in contacts and their tangents (``ContactSet.launches``, as its ``eval``).

        ``keep``: the contacts' tangents are also kept alone (:attr:`kept_contacts`, for a later
        :meth:`apply_kept_contacts` of the same kinematics): they are accumulated there, from zero,
        and then added into ``tb``'s (the sum in another order than point by point: the tangents
        differ from the unkept ones by rounding; the primal is the same)."""
        tans = {k: tb[k] for k in ("body_pos", "body_rot", "body_w", "body_v", "body_wrench", "body_stiffness")}
        if keep:
            for a in self.kept_contacts.values():
                a.zero_()
            tans.update(self.kept_contacts)
        for kernel, dim, inputs in self.solver.contacts.launches(ws, h):
            self._contacts[kernel].launch(dim, self.direction_count, [*inputs, ws.body_wrench, ws.body_stiffness],
                                          tans, self.model.device)
        if keep and self._contacts:
            self._add_kept(tb)

    def apply_kept_contacts(self, ws, tb: dict, h) -> None:
        """The compiled-in contacts of ``ws`` (the solver's launches: the primal only) and, into ``tb``,
        the tangents the last :meth:`eval_contacts` with ``keep=True`` kept (which must have been of
        the same kinematics and ``h``: one differentiation of the contacts for both passes)."""
        self.solver.contacts.eval(ws, h)
        if self._contacts:
            self._add_kept(tb)

    def _add_kept(self, tb: dict) -> None:
        k = self.kept_contacts
        wp.launch(apply_body_load_tangents, dim=k["body_wrench"].shape,
                  inputs=[k["body_wrench"], k["body_stiffness"], tb["body_wrench"], tb["body_stiffness"]],
                  device=self.model.device)
