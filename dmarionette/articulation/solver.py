"""The puppet as an articulated body in reduced coordinates: Model, State, Control, solver.

Generalised coordinates follow MuJoCo exactly, so that an exported MJCF model
(:mod:`dmarionette.articulation.mjcf`) has the same ``qpos``/``qvel`` layout:

====================  =========================================  ==========================
joint                 ``joint_q`` (per joint)                    ``joint_qd`` (per joint)
====================  =========================================  ==========================
free (root, ball)     centre position (world) [m], unit           centre velocity (world)
                      quaternion ``(w, x, y, z)`` body->world     [m/s], angular velocity in
                                                                  the *body* frame [rad/s]
ball (neck)           unit quaternion ``(w, x, y, z)`` child      angular velocity of the
                      relative to parent                          child relative to the
                                                                  parent, in the *child*
                                                                  frame [rad/s]
universal             two angles [rad], applied in axis order     their rates [rad/s]
hinge                 angle [rad]                                 rate [rad/s]
====================  =========================================  ==========================

Body frames have their origin at the centre of mass. Gravity is ``(0, -9.81, 0)``.

The step (:meth:`SolverArticulation.step`) is a linearised implicit Euler step in the
spirit of MuJoCo's ``implicitfast``: joint damping, joint-limit penalties, point
spring-dampers (the strings, paper eq. 2) and contact penalties enter the system matrix,
``(M + h D + h^2 K) qdd = tau``, ``qd' = qd + h qdd``, ``q' = q (+) h qd'``. With only joint
damping this is exactly MuJoCo's ``Euler`` integrator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from dmarionette.kernels.articulation_codegen import (
    ArticulationTopology,
    JointTopology,
    build_articulation_kernels,
)
from dmarionette.kernels.articulation_forces import (
    eval_body_external_forces,
    eval_body_point_springs,
    eval_body_points,
)
from dmarionette.kernels.articulation_math import spatial6, spatial66
from dmarionette.kernels.body_contact import ContactSettings, ContactSet
from dmarionette.scene.puppet import PuppetDescription
from dmarionette.scene.fields import SceneError

__all__ = [
    "ArticulationControl",
    "ArticulationKinematics",
    "ArticulationModel",
    "ArticulationState",
    "ArticulationWorkspace",
    "BallDescription",
    "ContactSettings",
    "SolverArticulation",
    "build_articulation_model",
]

GRAVITY = (0.0, -9.81, 0.0)


@dataclass(frozen=True)
class BallDescription:
    """A free rigid ball (paper Fig. 8: the puppet kicks a ball).

    Attributes:
        radius: [m]. mass: [kg]. position: centre at start [m].
    """

    radius: float = 0.05
    mass: float = 0.05
    position: tuple[float, float, float] = (0.0, 0.05, 0.2)


@dataclass
class ArticulationModel:
    """Constants of an articulated system (a puppet and optional free ball).

    Attributes:
        topology: the joint tree and compile-time switches (see ``articulation_codegen``).
        body_names: body names, ``body_count`` of them (puppet bodies, then ``"ball"``).
        body_shape: per body ``("box", (sx, sy, sz))`` or ``("sphere", (r, 0, 0))`` [m].
        body_contact: per body, whether its shape collides.
        body_mass: [kg], shape (body_count,), float64.
        body_inertia: principal moments about the centre, body frame [kg m^2],
            shape (body_count,) of vec3d.
        dof_damping: joint damping [N m s/rad] (free-joint dofs: 0), shape (qd_count,).
        dof_limit_lower, dof_limit_upper: limits [rad], shape (qd_count,) (ball joints:
            upper of the first dof is the cone angle; free dofs unlimited).
        limit_stiffness: joint-limit penalty stiffness [N m/rad].
        limit_damping: joint-limit penalty damping [N m s/rad].
        gravity: [m/s^2], shape (1,) of vec3d.
        spring_body, spring_point: body index and body-frame point [m] of each point
            spring-damper, shape (spring_count,).
        spring_stiffness, spring_damping: ``k`` [N/m], ``k_d`` [N s/m]: shape (spring_count,),
            shared by all worlds, or (spring_worlds * spring_count,), world after world, one
            set per world (a batched marionette's per-world eq. 2 constants).
        point_names, point_body, point_local: named attach points (from the puppet).
        contacts: compiled-in contact effects.
        q_rest: joint coordinates of the rest pose, shape (q_count,).
    """

    topology: ArticulationTopology
    body_names: list[str]
    body_shape: list[tuple[str, tuple[float, float, float]]]
    body_contact: list[bool]
    body_mass: wp.array
    body_inertia: wp.array
    dof_damping: wp.array
    dof_limit_lower: wp.array
    dof_limit_upper: wp.array
    limit_stiffness: float
    limit_damping: float
    gravity: wp.array
    spring_body: wp.array
    spring_point: wp.array
    spring_stiffness: wp.array
    spring_damping: wp.array
    point_names: list[str]
    point_body: wp.array
    point_local: wp.array
    contacts: ContactSettings
    q_rest: np.ndarray
    puppet: PuppetDescription | None = None
    ball: BallDescription | None = None
    device: str = "cpu"

    @property
    def body_count(self) -> int:
        return self.topology.body_count

    @property
    def q_count(self) -> int:
        return self.topology.q_count

    @property
    def qd_count(self) -> int:
        return self.topology.qd_count

    @property
    def spring_count(self) -> int:
        return self.spring_body.shape[0]

    @property
    def spring_worlds(self) -> int:
        """Worlds with a set of spring constants of their own (1: one set shared by all worlds)."""
        return self.spring_stiffness.shape[0] // self.spring_count if self.spring_count else 1

    def state(self, world_count: int = 1, requires_grad: bool = False) -> "ArticulationState":
        """A state at the rest pose, at rest."""
        return ArticulationState(self, world_count, requires_grad)

    def kinematics(self, world_count: int = 1, requires_grad: bool = False) -> "ArticulationKinematics":
        """Arrays for the body poses and velocities of a state."""
        return ArticulationKinematics(self, world_count, requires_grad)

    def workspace(self, world_count: int = 1, requires_grad: bool = False) -> "ArticulationWorkspace":
        """Arrays for what one step derives (body kinematics, wrenches, stiffness blocks, spring forces)."""
        return ArticulationWorkspace(self, world_count, requires_grad)

    def control(self, world_count: int = 1, requires_grad: bool = False) -> "ArticulationControl":
        """A control with no applied force and spring anchors at rest."""
        return ArticulationControl(self, world_count, requires_grad)


class ArticulationState:
    """What evolves, per world.

    Attributes:
        joint_q: generalised coordinates, shape (world_count, q_count), float64.
        joint_qd: generalised velocities, shape (world_count, qd_count).
        joint_qdd: accelerations of the step that produced this state [(rad or m)/s^2],
            shape (world_count, qd_count).
        body_pos, body_rot, body_w, body_v: body centre position [m], orientation
            (Warp quaternion x, y, z, w), angular velocity [rad/s] and centre velocity
            [m/s], world frame, shape (world_count, body_count): derived from
            ``joint_q``/``joint_qd``, filled only when a caller asks for them
            (:meth:`SolverArticulation.eval_kinematics` with ``out`` left out); no step
            writes them (a step's own body poses are in its :class:`ArticulationWorkspace`).
    """

    def __init__(self, model: ArticulationModel, world_count: int, requires_grad: bool):
        dev, n, rg = model.device, world_count, requires_grad
        self.world_count = world_count
        q = np.tile(model.q_rest, (n, 1))
        self.joint_q = wp.array(q, dtype=wp.float64, device=dev, requires_grad=rg)
        self.joint_qd = wp.zeros((n, model.qd_count), dtype=wp.float64, device=dev, requires_grad=rg)
        self.joint_qdd = wp.zeros((n, model.qd_count), dtype=wp.float64, device=dev, requires_grad=rg)
        _allocate_kinematics(self, model, n, rg)


class ArticulationKinematics:
    """Body poses and velocities of one state (what :meth:`SolverArticulation.eval_kinematics` writes).

    Attributes:
        world_count: worlds.
        body_pos, body_rot, body_w, body_v: as :class:`ArticulationState`'s, shape (world_count, body_count).
    """

    def __init__(self, model: ArticulationModel, world_count: int = 1, requires_grad: bool = False):
        self.world_count = world_count
        _allocate_kinematics(self, model, world_count, requires_grad)


class ArticulationWorkspace(ArticulationKinematics):
    """The derived quantities of one step (like MJX's ``Data``): what the step writes besides
    its output state. A plain run reuses one (the solver's :attr:`SolverArticulation.workspace`);
    a step recorded on a tape needs its own (an array written after it was read gives wrong
    gradients).

    Attributes:
        body_pos, body_rot, body_w, body_v: the input state's body kinematics.
        body_wrench: total applied spatial force about the world origin, shape (world_count, body_count).
        body_stiffness: ``h D + h^2 K`` body blocks, shape (world_count, body_count).
        spring_force: force of each point spring on its body [N], world, shape
            (world_count, spring_count); the string end feels the opposite. It is paper
            eq. 2 plus the implicit step's ``-h k (v - v_anchor)``.
    """

    def __init__(self, model: ArticulationModel, world_count: int = 1, requires_grad: bool = False):
        super().__init__(model, world_count, requires_grad)
        dev, n, rg, nb = model.device, world_count, requires_grad, model.body_count
        self.body_wrench = wp.zeros((n, nb), dtype=spatial6, device=dev, requires_grad=rg)
        self.body_stiffness = wp.zeros((n, nb), dtype=spatial66, device=dev, requires_grad=rg)
        ns = max(model.spring_count, 1)
        self.spring_force = wp.zeros((n, ns), dtype=wp.vec3d, device=dev, requires_grad=rg)


def _allocate_kinematics(owner, model: ArticulationModel, n: int, rg: bool) -> None:
    dev, nb = model.device, model.body_count
    owner.body_pos = wp.zeros((n, nb), dtype=wp.vec3d, device=dev, requires_grad=rg)
    owner.body_rot = wp.zeros((n, nb), dtype=wp.quatd, device=dev, requires_grad=rg)
    owner.body_w = wp.zeros((n, nb), dtype=wp.vec3d, device=dev, requires_grad=rg)
    owner.body_v = wp.zeros((n, nb), dtype=wp.vec3d, device=dev, requires_grad=rg)


class ArticulationControl:
    """Inputs, per world.

    Attributes:
        joint_f: generalised forces [N or N m], shape (world_count, qd_count).
        body_force: force at each body centre, world [N], shape (world_count, body_count).
        body_torque: torque on each body, world [N m], shape (world_count, body_count).
        spring_anchor_pos, spring_anchor_vel: the other end of each point spring (for a
            string: its last particle) [m], [m/s], shape (world_count, spring_count).
    """

    def __init__(self, model: ArticulationModel, world_count: int, requires_grad: bool):
        dev, n, rg = model.device, world_count, requires_grad
        self.joint_f = wp.zeros((n, model.qd_count), dtype=wp.float64, device=dev, requires_grad=rg)
        self.body_force = wp.zeros((n, model.body_count), dtype=wp.vec3d, device=dev, requires_grad=rg)
        self.body_torque = wp.zeros((n, model.body_count), dtype=wp.vec3d, device=dev, requires_grad=rg)
        ns = max(model.spring_count, 1)
        self.spring_anchor_pos = wp.zeros((n, ns), dtype=wp.vec3d, device=dev, requires_grad=rg)
        self.spring_anchor_vel = wp.zeros((n, ns), dtype=wp.vec3d, device=dev, requires_grad=rg)


def _f64(values, dev, dtype=wp.float64):
    return wp.array(np.asarray(values, dtype=np.float64), dtype=dtype, device=dev)


def build_articulation_model(
    puppet: PuppetDescription,
    *,
    ball: BallDescription | None = None,
    springs: tuple[tuple[str, float, float], ...] = (),
    contacts: ContactSettings | None = None,
    joint_limits: bool = True,
    one_sided_limits: bool = True,
    limit_stiffness: float = 5.0,
    limit_damping: float = 0.05,
    gravity: tuple[float, float, float] = GRAVITY,
    device: str = "cpu",
    requires_grad: bool = False,
    spring_worlds: int = 1,
) -> ArticulationModel:
    """Builds the model of a puppet (and optional ball).

    Args:
        puppet: a validated description (:func:`dmarionette.scene.puppet.load_puppet`).
        ball: an extra free sphere, or None.
        springs: point spring-dampers as ``(point_name, k [N/m], k_d [N s/m])``; the
            point names are the puppet's attach points (``head``, ``hand_left`` ...).
        spring_worlds: sets of spring constants (``spring_stiffness``, ``spring_damping``):
            1 shared by all worlds, or one per world of the states stepped (each starting as
            ``springs`` says; a batched marionette writes its worlds' own).
        contacts: which contacts to compile in (default: none).
        joint_limits: compile joint limits in.
        one_sided_limits: the one-sided limit look-ahead (issue 13, ``docs/puppet.md``, "Joint
            limits"; the default); False: the two-sided band of before.
        limit_stiffness, limit_damping: joint-limit penalty [N m/rad], [N m s/rad].
        gravity: [m/s^2].
        device: Warp device.
        requires_grad: give the fittable arrays (masses, inertias, damping, gravity,
            spring constants and points) gradients.
    """
    contacts = contacts or ContactSettings()
    names = [b.name for b in puppet.bodies]
    parents = puppet.parent_index()
    joints = [JointTopology("free", -1, 0, 0)]
    q_rest = list(puppet.root_position) + [1.0, 0.0, 0.0, 0.0]
    damping, lower, upper = [0.0] * 6, [-np.inf] * 6, [np.inf] * 6
    qs, ds = 7, 6
    for b, j in enumerate(puppet.joints, start=1):
        joints.append(JointTopology(j.type, parents[b], qs, ds, j.axes, j.anchor_parent, j.anchor_child,
                                    j.lower, j.upper))
        if j.type == "ball":
            q_rest += [1.0, 0.0, 0.0, 0.0]
            damping += [j.damping] * 3
            lower += [j.lower[0], -np.inf, -np.inf]
            upper += [j.upper[0], np.inf, np.inf]
            qs, ds = qs + 4, ds + 3
        else:
            n = len(j.axes)
            q_rest += [0.0] * n
            damping += [j.damping] * n
            lower += list(j.lower)
            upper += list(j.upper)
            qs, ds = qs + n, ds + n
    shapes = [(b.shape, b.size) for b in puppet.bodies]
    contact = [b.contact for b in puppet.bodies]
    mass = [b.mass for b in puppet.bodies]
    inertia = [b.inertia for b in puppet.bodies]
    if ball is not None:
        joints.append(JointTopology("free", -1, qs, ds))
        q_rest += list(ball.position) + [1.0, 0.0, 0.0, 0.0]
        damping += [0.0] * 6
        lower += [-np.inf] * 6
        upper += [np.inf] * 6
        names.append("ball")
        shapes.append(("sphere", (ball.radius, 0.0, 0.0)))
        contact.append(True)
        mass.append(ball.mass)
        inertia.append((0.4 * ball.mass * ball.radius**2,) * 3)
    topo = ArticulationTopology(tuple(joints), joint_limits=joint_limits, one_sided_limits=one_sided_limits)

    point_names = [p.name for p in puppet.points]
    s_body, s_point, s_k, s_kd = [], [], [], []
    for i, spec in enumerate(springs):
        pname, k, kd = spec
        if pname not in point_names:
            raise SceneError("build_articulation_model", f"springs[{i}]", pname,
                             f"the name of a puppet point, one of {point_names}")
        if not (np.isfinite(k) and k >= 0 and np.isfinite(kd) and kd >= 0):
            raise SceneError("build_articulation_model", f"springs[{i}]", spec, "k >= 0 and k_d >= 0")
        p = puppet.points[point_names.index(pname)]
        s_body.append(names.index(p.body))
        s_point.append(p.position)
        s_k.append(k)
        s_kd.append(kd)
    dev = device
    model = ArticulationModel(
        topology=topo,
        body_names=names,
        body_shape=shapes,
        body_contact=contact,
        body_mass=_f64(mass, dev),
        body_inertia=_f64(inertia, dev, wp.vec3d),
        dof_damping=_f64(damping, dev),
        dof_limit_lower=_f64(np.nan_to_num(lower, neginf=-1e30), dev),
        dof_limit_upper=_f64(np.nan_to_num(upper, posinf=1e30), dev),
        limit_stiffness=float(limit_stiffness),
        limit_damping=float(limit_damping),
        gravity=_f64([gravity], dev, wp.vec3d),
        spring_body=wp.array(np.asarray(s_body or [0], dtype=np.int32), dtype=wp.int32, device=dev)[: len(s_body)],
        spring_point=_f64(np.reshape(s_point or [(0.0, 0.0, 0.0)], (-1, 3)), dev, wp.vec3d)[: len(s_body)],
        spring_stiffness=_f64(np.tile(s_k or [0.0], spring_worlds), dev)[: len(s_body) * spring_worlds],
        spring_damping=_f64(np.tile(s_kd or [0.0], spring_worlds), dev)[: len(s_body) * spring_worlds],
        point_names=point_names,
        point_body=wp.array(np.asarray([names.index(p.body) for p in puppet.points] or [0], dtype=np.int32),
                            dtype=wp.int32, device=dev)[: len(point_names)],
        point_local=_f64(np.reshape([p.position for p in puppet.points] or [(0.0, 0.0, 0.0)], (-1, 3)),
                         dev, wp.vec3d)[: len(point_names)],
        contacts=contacts,
        q_rest=np.asarray(q_rest, dtype=np.float64),
        puppet=puppet,
        ball=ball,
        device=device,
    )
    if requires_grad:
        for name in ("body_mass", "body_inertia", "dof_damping", "gravity", "spring_point",
                     "spring_stiffness", "spring_damping"):
            getattr(model, name).requires_grad = True
    return model


class SolverArticulation:
    """Steps an :class:`ArticulationModel` (linearised implicit Euler, see module doc).

    Args:
        model: the model; its topology's kernels are generated and compiled on first use
            (cached on disk per topology).
        optimization_level: C++ optimisation of the generated kernels: 2 (default) runs
            about 25x faster than 0 but compiles in about a minute instead of 9 s (once
            per topology; the binary is cached). Tests use 0.
        implicit: treat damping, limits, point springs and contacts implicitly (the
            default); False gives the explicit (semi-implicit Euler) step, for
            comparison only.
    """

    def __init__(self, model: ArticulationModel, optimization_level: int = 2, implicit: bool = True):
        self.model = model
        self.implicit = implicit
        self.kernels = build_articulation_kernels(model.topology, optimization_level)
        self.contacts = ContactSet(model)
        self._workspaces: dict[int, ArticulationWorkspace] = {}

    def default_workspace(self, world_count: int = 1) -> ArticulationWorkspace:
        """The workspace plain (untaped) steps of ``world_count`` worlds reuse (what the last
        plain step derived: its input's body kinematics, wrenches, spring forces)."""
        if world_count not in self._workspaces:
            self._workspaces[world_count] = self.model.workspace(world_count)
        return self._workspaces[world_count]

    def step(self, state_in: ArticulationState, state_out: ArticulationState,
             control: ArticulationControl, dt: float, *, tape: wp.Tape | None = None,
             workspace: ArticulationWorkspace | None = None) -> None:
        """Advances ``state_in`` by ``dt`` [s] into ``state_out`` (``state_in`` is only read).

        Args:
            state_in, state_out: two states of this model.
            control: applied forces and the point springs' anchors.
            dt: the step [s].
            tape: the ``wp.Tape`` the step is recorded on (the caller's ``with tape:``), or None.
                A taped step without ``workspace`` derives into fresh arrays of its own.
            workspace: where the step writes its derived quantities (default: the solver's
                :meth:`default_workspace`, or fresh arrays when taped).

        Raises:
            ValueError: ``dt`` negative or not finite, ``state_in is state_out``, or
                states/control of another model or world count.
        """
        self.check_step(state_in, state_out, control, dt)
        ws = self._workspace_of(state_in, tape, workspace)
        h, hi = self.step_sizes(dt)
        self.eval_kinematics(state_in, ws)                         # body poses and velocities
        self.eval_external_forces(ws, control)                     # applied wrenches; resets h D + h^2 K
        self.eval_point_springs(ws, control, hi)                   # strings pull on bodies (eq. 2)
        self.eval_contacts(ws, hi)                                 # ground / chair / ball penalties
        self.solve_dynamics(state_in, state_out, control, ws, h, hi)  # (M + h D + h^2 K) qdd = tau
        self.integrate(state_in, state_out, h)                     # q' = q (+) h qd'

    def _workspace_of(self, state_in, tape, workspace) -> ArticulationWorkspace:
        if workspace is not None:
            return workspace
        if tape is not None:
            return self.model.workspace(state_in.world_count, requires_grad=True)
        return self.default_workspace(state_in.world_count)

    def step_sizes(self, dt: float) -> tuple:
        """``(h, h_implicit)`` of a step of ``dt`` [s] as float64 (``h_implicit`` is 0 for the explicit step)."""
        h = wp.float64(dt)
        return h, (h if self.implicit else wp.float64(0.0))

    def check_step(self, state_in, state_out, control, dt) -> None:
        """Raises ``ValueError`` unless ``step(state_in, state_out, control, dt)`` is well posed."""
        m = self.model
        if not (np.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"SolverArticulation.step: dt = {dt!r}; expected a finite step >= 0 [s]")
        if state_in is state_out:
            raise ValueError("SolverArticulation.step: state_in is state_out; expected two states "
                             "(the step reads one and writes the other)")
        n = state_in.world_count
        for name, arr, cols in (("state_in.joint_q", state_in.joint_q, m.q_count),
                                ("state_out.joint_q", state_out.joint_q, m.q_count),
                                ("control.joint_f", control.joint_f, m.qd_count),
                                ("control.body_force", control.body_force, m.body_count)):
            if arr.shape != (n, cols):
                raise ValueError(f"SolverArticulation.step: {name} has shape {arr.shape}; expected "
                                 f"({n}, {cols}) (world_count, ...) from this model")

    # ------------------------------------------------------------------ passes
    def eval_kinematics(self, state: ArticulationState, out: ArticulationKinematics | None = None) -> None:
        """Body poses and velocities of ``state`` (from ``joint_q/joint_qd``) into ``out``
        (an :class:`ArticulationKinematics` or workspace; default: ``state``'s own body fields)."""
        out = state if out is None else out
        wp.launch(self.kernels.eval_body_kinematics, dim=state.world_count,
                  inputs=[state.joint_q, state.joint_qd],
                  outputs=[out.body_pos, out.body_rot, out.body_w, out.body_v],
                  device=self.model.device)

    def eval_external_forces(self, ws: ArticulationWorkspace, control) -> None:
        """Applied forces into ``ws.body_wrench`` (which it resets, with ``ws.body_stiffness``)."""
        wp.launch(eval_body_external_forces, dim=(ws.world_count, self.model.body_count),
                  inputs=[ws.body_pos, control.body_force, control.body_torque],
                  outputs=[ws.body_wrench, ws.body_stiffness], device=self.model.device)

    def eval_point_springs(self, ws: ArticulationWorkspace, control, h) -> None:
        """The model's point spring-dampers (eq. 2) against ``control``'s anchors, implicit over ``h``."""
        m = self.model
        if m.spring_count == 0:
            return
        wp.launch(eval_body_point_springs, dim=(ws.world_count, m.spring_count),
                  inputs=[m.spring_body, m.spring_point, m.spring_stiffness, m.spring_damping,
                          ws.body_pos, ws.body_rot, ws.body_w, ws.body_v,
                          control.spring_anchor_pos, control.spring_anchor_vel, h],
                  outputs=[ws.spring_force, ws.body_wrench, ws.body_stiffness], device=m.device)

    def eval_contacts(self, ws: ArticulationWorkspace, h) -> None:
        """Ground, chair and ball contact penalties (the compiled-in ones), implicit over ``h``."""
        self.contacts.eval(ws, h)

    def solve_dynamics(self, state_in, state_out, control, ws: ArticulationWorkspace, h, h_implicit) -> None:
        """``(M + h D + h^2 K) qdd = tau`` with ``ws``'s loads: ``state_out.joint_qdd``, ``joint_qd``."""
        m = self.model
        limits = []
        if m.topology.joint_limits:
            limits = [m.dof_limit_lower, m.dof_limit_upper, wp.float64(m.limit_stiffness),
                      wp.float64(m.limit_damping)]
        wp.launch(self.kernels.solve_body_dynamics, dim=state_in.world_count,
                  inputs=[m.body_mass, m.body_inertia, m.dof_damping, m.gravity, *limits,
                          state_in.joint_q, state_in.joint_qd, ws.body_pos, ws.body_rot,
                          ws.body_w, ws.body_v, ws.body_wrench, ws.body_stiffness,
                          control.joint_f, h, h_implicit],
                  outputs=[state_out.joint_qdd, state_out.joint_qd], device=m.device)

    def integrate(self, state_in, state_out, h) -> None:
        """``q' = q (+) h qd'`` into ``state_out.joint_q``."""
        wp.launch(self.kernels.integrate_joint_coordinates, dim=state_in.world_count,
                  inputs=[state_in.joint_q, state_out.joint_qd, h],
                  outputs=[state_out.joint_q], device=self.model.device)

    # ------------------------------------------------------------------ queries
    def eval_points(self, kinematics: ArticulationKinematics, point_pos: wp.array, point_vel: wp.array) -> None:
        """World positions and velocities of the puppet's named points (``model.point_names``
        order) into arrays of shape (world_count, point_count) of vec3d, from body
        ``kinematics`` (a state whose body fields :meth:`eval_kinematics` filled, or the
        ``out`` it filled)."""
        m = self.model
        wp.launch(eval_body_points, dim=(kinematics.world_count, len(m.point_names)),
                  inputs=[m.point_body, m.point_local, kinematics.body_pos, kinematics.body_rot, kinematics.body_w,
                          kinematics.body_v], outputs=[point_pos, point_vel], device=m.device)

    def eval_mass_matrix(self, state: ArticulationState) -> np.ndarray:
        """Joint-space mass matrix, shape (world_count, qd_count, qd_count) (numpy)."""
        m = self.model
        kinematics = m.kinematics(state.world_count)
        self.eval_kinematics(state, kinematics)
        out = wp.zeros((state.world_count, m.qd_count, m.qd_count), dtype=wp.float64, device=m.device)
        wp.launch(self.kernels.eval_mass_matrix, dim=state.world_count,
                  inputs=[m.body_mass, m.body_inertia, kinematics.body_pos, kinematics.body_rot],
                  outputs=[out], device=m.device)
        return out.numpy()
