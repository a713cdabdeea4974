"""The marionette: strings, puppet and control bars together (paper §2-4).

One puppet step of ``H = n h`` (``n = round(string_hz / puppet_hz)`` string steps of ``h``;
``n = 1`` runs the puppet at the string rate) is a short list of named passes::

    eval_body_points            tied body points: positions and velocities at t0
    predict_body_points         a trial puppet step under the strings' linearised pull: where the
                                tied points will be at t0 + H
    eval_tie_path               the strings' tie targets over the n string steps (body -> strings)
    n x  step strings           backward Euler, bottoms tied by eq. 2 to the path
         eval_bar_feedback      eq. 4 and the exact reaction, per bar, every string step
    apply_string_forces_to_anchors  mean tie force + the stiff tie around the path (strings -> body)
    step puppet                 implicit puppet step with the eq. 2 springs

See :mod:`dmarionette.kernels.string_body_coupling` for how forces and positions cross
between the two rates.

Precision: the puppet is float64 (its solver is float64 only). The strings follow the
scene's ``[solver] precision``: float64 by default, or float32, in which case the string
model, solver and state are float32 and :class:`SolverMarionette` converts what crosses
(``kernels/precision_boundary``): the bar tops and the tie path into float32 string
controls, the tie force out into the float64 :class:`MarionetteState` arrays (the bar
feedback kernel widens its own inputs). Everything outside the strings (the
``MarionetteState`` and ``MarionetteControl`` arrays, rollouts, live loop, sessions,
energy) stays float64 either way; a float64 marionette launches no conversion.
"""

from __future__ import annotations

import copy
import dataclasses
from types import SimpleNamespace

import numpy as np
import warp as wp

from dmarionette.articulation.solver import (
    ArticulationState,
    BallDescription,
    ContactSettings,
    SolverArticulation,
    build_articulation_model,
)
from dmarionette.kernels.bar_feedback import eval_bar_feedback_kernel
from dmarionette.kernels.precision_boundary import convert_vec3
from dmarionette.kernels.string_body_coupling import (
    apply_string_forces_to_anchors_kernel,
    eval_string_response_kernel,
    eval_tie_path,
)
from dmarionette.scene.scene import Scene
from dmarionette.scene.settings_check import check_marionette_settings
from dmarionette.strings.model import StringControl, StringModel, StringState
from dmarionette.strings.rollout import upload_values
from dmarionette.strings.solver import SolverStringImplicit

__all__ = ["MarionetteControl", "MarionetteModel", "MarionetteState", "SolverMarionette"]


class MarionetteModel:
    """Strings + puppet + bars built from a scene.

    Attributes:
        scene: the scene it was built from.
        strings: the :class:`StringModel`, in the scene's ``[solver] precision``.
        precision: ``"float64"`` or ``"float32"``: the strings' float type (the puppet is float64).
        string_tie_stiffness: eq. 2 ``k`` of each string as float64 for the puppet side (the
            anchor offset ``F / k``) [N/m], ``(S,)``: the strings' own array in float64 (so
            fitted values and gradients are shared), a float64 copy of it in float32.
        puppet: the :class:`ArticulationModel` (springs: one per tied string, in string order).
        substeps: string steps per puppet step ``n``; ``puppet_dt = n * string_dt``.
        string_dt, puppet_dt: [s].
        bar_names: ``(B,)``; string_bar: bar index of each string (-1: none), ``(S,)``.
        string_point: puppet point index each string is tied to (-1: none), ``(S,)``.
        spring_string: string index of each body spring, ``(N,)``.
        puppet_mass: total puppet mass [kg] (eq. 4's ``m``).
        requires_grad: whether the strings' and puppet's fittable arrays (and the states
            made from them) carry gradients, for taped rollouts (``marionette_grad``).
    """

    def __init__(self, scene: Scene, *, optimization_level: int = 2, device=None, requires_grad: bool = False):
        if scene.puppet is None:
            raise ValueError(f"{scene.source}: a marionette needs a [puppet] table")
        if requires_grad and scene.precision != "float64":
            raise ValueError(f"{scene.source}: [solver] precision = {scene.precision!r}: gradients of a "
                             "marionette are float64 only; use precision = \"float64\" for fitting")
        check_marionette_settings(scene)  # settings measured not to work are refused, with the reason
        self.scene = scene
        self.requires_grad = bool(requires_grad)
        self.precision = scene.precision
        self.device = wp.get_device(device)
        self.string_dt = scene.string_dt
        self.substeps = max(1, round(scene.string_hz / scene.puppet_hz))
        self.puppet_dt = self.substeps * self.string_dt
        names = [s.name for s in scene.strings]
        tied = [(i, p) for i, p in enumerate(scene.string_body_points) if p is not None]
        e = scene.body_effects
        ball = BallDescription(position=scene.ball.position, radius=scene.ball.radius, mass=scene.ball.mass) \
            if scene.ball is not None else None
        c = scene.contact
        contacts = ContactSettings(ground=e["body_ground"], ground_height=scene.ground_height, chair=scene.chair,
                                   ball=ball is not None, smooth=c["smooth"], stiffness=c["stiffness"],
                                   damping=c["damping"], friction=c["friction"],
                                   friction_velocity=c["friction_velocity"], smooth_distance=c["smooth_distance"])
        self.puppet = build_articulation_model(
            scene.puppet, ball=ball, contacts=contacts, joint_limits=e["joint_limits"], gravity=scene.gravity,
            springs=tuple((p, scene.strings[i].tie_stiffness, scene.strings[i].tie_damping) for i, p in tied),
            device=str(self.device), requires_grad=self.requires_grad)
        self.puppet_solver = SolverArticulation(self.puppet, optimization_level=optimization_level)
        # Where the tied points are in the initial pose: the strings start straight from bar to point.
        self.q_initial = initial_joint_q(self.puppet, scene)
        point_q, point_qd = self.eval_points(self._initial_puppet_state())
        point_names = self.puppet.point_names
        specs = []
        for spec, body_point in zip(scene.strings, scene.string_body_points):
            if body_point is not None:
                bottom = tuple(float(v) for v in point_q[point_names.index(body_point)])
                length = spec.length or float(np.linalg.norm(np.subtract(spec.top, bottom)))
                spec = dataclasses.replace(spec, bottom=bottom, tie_point=bottom, length=length)
            specs.append(spec)
        self.strings = StringModel(specs, effects=scene.effects, gravity=scene.gravity,
                                   ground_height=scene.ground_height, precision=self.precision, device=self.device,
                                   requires_grad=self.requires_grad)
        self.string_solver = SolverStringImplicit(self.strings)
        self.bar_names = [b.name for b in scene.bars]
        bar_of = {s: i for i, b in enumerate(scene.bars) for s in b.attach}
        self.string_bar = np.array([bar_of.get(n, -1) for n in names], dtype=np.int32)
        self.string_point = np.array([point_names.index(p) if p else -1 for p in scene.string_body_points],
                                     dtype=np.int32)
        self.spring_string = np.array([i for i, _ in tied], dtype=np.int32)
        self.puppet_mass = float(sum(b.mass for b in scene.puppet.bodies))
        with wp.ScopedDevice(self.device):
            self.string_bar_wp = wp.array(self.string_bar, dtype=wp.int32)
            self.string_point_wp = wp.array(self.string_point, dtype=wp.int32)
            self.spring_string_wp = wp.array(self.spring_string, dtype=wp.int32)
            self.string_tie_stiffness = self.strings.string_tie_stiffness if self.precision == "float64" \
                else wp.array([s.tie_stiffness for s in specs], dtype=wp.float64)

    def _initial_puppet_state(self) -> ArticulationState:
        state = self.puppet.state()
        state.joint_q.assign(wp.array(self.q_initial[None], dtype=wp.float64, device=self.device))
        return state

    @property
    def bar_count(self) -> int:
        return len(self.bar_names)

    def eval_points(self, state: ArticulationState) -> tuple[np.ndarray, np.ndarray]:
        """World positions [m] and velocities [m/s] of the puppet's named points, ``(points, 3)`` each."""
        n = len(self.puppet.point_names)
        q = wp.zeros((1, n), dtype=wp.vec3d, device=self.device)
        qd = wp.zeros((1, n), dtype=wp.vec3d, device=self.device)
        self.puppet_solver.eval_kinematics(state)
        self.puppet_solver.eval_points(state, q, qd)
        return q.numpy()[0], qd.numpy()[0]

    def state(self) -> MarionetteState:
        """The start state: puppet at its rest pose, strings straight from bar to body point, at rest."""
        return MarionetteState(self)

    def control(self) -> MarionetteControl:
        """Control buffers for one puppet step, holding the bars at their t = 0 pose."""
        control = MarionetteControl(self)
        control.set_bars(self, 0.0)
        return control


class MarionetteState:
    """What evolves, and what one puppet step reports.

    Attributes:
        strings: the string state at the end of the step.
        puppet: the puppet state (one world).
        tie_force: eq. 2 force of each tie on its body point after each string step [N],
            ``(n, S)`` of vec3d; the next puppet step's trial step reads its mean (zero in
            the start state).
        string_taut: taut flags after each string step, ``(n, S)``.
        bar_feedback: eq. 4 feedback per bar after each string step [N], ``(n, B)``.
        bar_reaction: exact reaction of the strings on each bar after each string step [N], ``(n, B)``.
        tie_target: where each string's tie target is at the end of the step [m], ``(S,)``
            (the start of the next step's path; see ``string_body_coupling``).
    """

    def __init__(self, model: MarionetteModel):
        self.strings: StringState = model.strings.state()
        self.puppet: ArticulationState = model._initial_puppet_state()
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        with wp.ScopedDevice(model.device):
            self.tie_force = wp.zeros((n, s), dtype=wp.vec3d)
            self.string_taut = wp.zeros((n, s), dtype=wp.int32)
            self.bar_feedback = wp.zeros((n, b), dtype=wp.vec3d)
            self.bar_reaction = wp.zeros((n, b), dtype=wp.vec3d)
            self.tie_target = wp.array(model.strings.tie_points(), dtype=wp.vec3d)

    def assign(self, other: MarionetteState) -> None:
        """Copies ``other`` (same model) into this state."""
        self.strings.assign(other.strings)
        for name in ("joint_q", "joint_qd", "joint_qdd"):
            getattr(self.puppet, name).assign(getattr(other.puppet, name))
        for name in ("tie_force", "string_taut", "bar_feedback", "bar_reaction", "tie_target"):
            getattr(self, name).assign(getattr(other, name))


class MarionetteControl:
    """Inputs of one puppet step: the bars over its ``n`` string steps.

    Attributes:
        top_q: attach point of each string's top at the end of each string step [m], ``(n, S)``.
        bar_q, bar_qd: bar centre position [m] and velocity [m/s] (the device proxy of eq. 4),
            ``(n, B)``.
        t0: time at the start of the step [s] (host side, used by :meth:`set_bars`).
    """

    def __init__(self, model: MarionetteModel):
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        with wp.ScopedDevice(model.device):
            self.top_q = wp.zeros((n, s), dtype=wp.vec3d)
            self.bar_q = wp.zeros((n, b), dtype=wp.vec3d)
            self.bar_qd = wp.zeros((n, b), dtype=wp.vec3d)
        self.t0 = 0.0

    def set_bars(self, model: MarionetteModel, t0: float) -> None:
        """Fills the buffers from the scene's bar trajectories for the step starting at ``t0``."""
        self.t0 = float(t0)
        times = t0 + model.string_dt * np.arange(1, model.substeps + 1)
        tops, bar_q, bar_qd = bar_inputs(model, times)
        upload_values(self.top_q, tops)
        if model.bar_count:
            upload_values(self.bar_q, bar_q)
            upload_values(self.bar_qd, bar_qd)


def initial_joint_q(puppet_model, scene: Scene) -> np.ndarray:
    """The puppet's start coordinates: its rest pose with the scene's ``[initial_pose]`` angles."""
    q = puppet_model.q_rest.copy()
    offset = 7  # the free root: position, quaternion
    for joint in scene.puppet.joints:
        count = 4 if joint.type == "ball" else len(joint.axes)
        if joint.name in scene.initial_pose:
            q[offset:offset + count] = np.radians(scene.initial_pose[joint.name])
        offset += count
    return q


def bar_inputs(model: MarionetteModel, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """String tops ``(T, S, 3)``, bar centres ``(T, B, 3)`` and their velocities at ``times``."""
    scene = model.scene
    tops = scene.top_positions(np.array([s.top for s in model.strings.specs]), times)
    bar_q = np.zeros((len(times), max(model.bar_count, 1), 3))
    bar_qd = np.zeros_like(bar_q)
    for b, bar in enumerate(scene.bars):
        bar_q[:, b], bar_qd[:, b], _ = bar.trajectory.pose(times)
    return tops, bar_q, bar_qd


class SolverMarionette:
    """Steps a :class:`MarionetteModel` by one puppet step (``n`` string steps).

    Args:
        model: the marionette.
    """

    def __init__(self, model: MarionetteModel):
        self.model = model
        m = model
        self._feedback = eval_bar_feedback_kernel(m.strings.scalar, m.scene.effects.internal_friction,
                                                  m.scene.effects.tension_only, bar_scalar=wp.float64) \
            if m.scene.body_effects["feedback"] and m.bar_count else None
        self._spare = (m.strings.state(), m.strings.state())
        n_points = len(m.puppet.point_names)
        n, s = m.substeps, m.strings.string_count
        with wp.ScopedDevice(m.device):
            self._point_q = wp.zeros((1, n_points), dtype=wp.vec3d)
            self._point_qd = wp.zeros((1, n_points), dtype=wp.vec3d)
            self._point_end = wp.zeros((1, n_points), dtype=wp.vec3d)
            self._point_end_qd = wp.zeros((1, n_points), dtype=wp.vec3d)
            self._tie_q = wp.zeros((n, s), dtype=wp.vec3d)
            self._tie_qd = wp.zeros((n, s), dtype=wp.vec3d)
            # Float32 strings: their own controls, converted from the float64 ones (module doc).
            self._narrow = None if m.precision == "float64" else SimpleNamespace(
                top_q=wp.zeros((n, s), dtype=m.strings.vec3), tie_q=wp.zeros((n, s), dtype=m.strings.vec3),
                tie_qd=wp.zeros((n, s), dtype=m.strings.vec3))
        self._puppet_control = m.puppet.control()
        self._string_control_cache = {}
        self._response = eval_string_response_kernel(m.strings.scalar, m.scene.effects.internal_friction, m.substeps)
        self._trial = m.puppet.state()              # the trial step's end state
        self._trial_fields = trial_fields(m.puppet)  # its input's body fields (state_in's stay untouched)
        self._trial_views = {}

    def _string_controls(self, control: MarionetteControl) -> list[StringControl]:
        """The controls of the n string steps: views of ``control``'s buffers and the tie path
        (float32 strings: of their own float32 copies), made once per control (the cache holds
        the control, so its id stays unique)."""
        key = id(control)
        if key not in self._string_control_cache:
            if self._narrow is None:
                top_q, tie_q, tie_qd = control.top_q, self._tie_q, self._tie_qd
            else:
                top_q, tie_q, tie_qd = self._narrow.top_q, self._narrow.tie_q, self._narrow.tie_qd
            views = [StringControl(top_q[j], tie_q[j], tie_qd[j]) for j in range(self.model.substeps)]
            self._string_control_cache[key] = (control, views)
        return self._string_control_cache[key][1]

    def step(self, state_in: MarionetteState, state_out: MarionetteState, control: MarionetteControl,
             dt: float | None = None) -> None:
        """Advances ``state_in`` by one puppet step into ``state_out`` (``dt`` must equal ``puppet_dt``)."""
        m = self.model
        if dt is not None and abs(dt - m.puppet_dt) > 1e-12 * m.puppet_dt:
            raise ValueError(f"dt: got {dt}; this marionette steps by puppet_dt = {m.puppet_dt} "
                             f"({m.substeps} string steps of {m.string_dt})")
        self.begin_step(state_in, state_out)            # body points, tie path (body -> strings)
        for j in range(m.substeps):
            self.step_string(state_in, state_out, control, j)  # string step j + feedback (eq. 2, eq. 4)
        self.end_step(state_in, state_out)              # mean tie force -> anchors, puppet step

    def begin_step(self, state_in: MarionetteState, state_out: MarionetteState) -> None:
        """Passes before the string steps (a live loop runs them at the first tick of a puppet step)."""
        self.eval_body_points(state_in)                 # tied body points at t0
        self.predict_body_points(state_in)              # trial puppet step: the tied points at t0 + H
        self.eval_tie_path(state_in, state_out)         # the strings' tie targets over the step
        if self._narrow is not None:
            self.apply_tie_path_to_strings()            # float64 -> float32 string controls
        if self._feedback is not None:
            state_out.bar_feedback.zero_()
            state_out.bar_reaction.zero_()

    def step_string(self, state_in: MarionetteState, state_out: MarionetteState, control: MarionetteControl,
                    j: int) -> None:
        """String step ``j`` of the puppet step: from ``state_in`` (j = 0) through two spare string
        states to ``state_out`` (j = n - 1); records the tie force, taut flags and feedback."""
        m = self.model
        previous = state_in.strings if j == 0 else self._spare[(j - 1) % 2]
        nxt = state_out.strings if j == m.substeps - 1 else self._spare[j % 2]
        if self._narrow is not None:
            convert_vec3(control.top_q[j], self._narrow.top_q[j], m.device)  # bar tops -> float32
        m.string_solver.step(previous, nxt, self._string_controls(control)[j], m.string_dt)
        if self._narrow is None:
            wp.copy(state_out.tie_force[j], nxt.tie_force)
        else:
            convert_vec3(nxt.tie_force, state_out.tie_force[j], m.device)  # float32 -> float64 tie force
        wp.copy(state_out.string_taut[j], nxt.string_taut)
        if self._feedback is not None:
            self.eval_bar_feedback(nxt, control, state_out, j)

    def string_state_after(self, state_out: MarionetteState, j: int) -> StringState:
        """The string state holding string step ``j``'s result: a spare state before the last step, then ``state_out.strings``."""
        return state_out.strings if j == self.model.substeps - 1 else self._spare[j % 2]

    def end_step(self, state_in: MarionetteState, state_out: MarionetteState) -> None:
        """Passes after the string steps (strings -> body)."""
        self.apply_string_forces_to_anchors(state_out)  # mean tie force -> body springs' anchors
        self.step_puppet(state_in, state_out)           # implicit puppet step

    def eval_body_points(self, state_in: MarionetteState) -> None:
        self.model.puppet_solver.eval_kinematics(state_in.puppet)
        self.model.puppet_solver.eval_points(state_in.puppet, self._point_q, self._point_qd)

    def predict_body_points(self, state_in: MarionetteState) -> None:
        """Trial puppet step under the strings' linearised pull (``string_body_coupling``); its
        tied points at ``t0 + H`` into ``_point_end``."""
        m = self.model
        key = id(state_in.puppet)
        if key not in self._trial_views:
            self._trial_views[key] = (state_in.puppet, trial_view(state_in.puppet, self._trial_fields))
        view = self._trial_views[key][1]
        predict_puppet_step(m, self._response, view, state_in.strings, state_in.tie_force, self._trial, self._puppet_control)
        m.puppet_solver.eval_kinematics(self._trial)
        m.puppet_solver.eval_points(self._trial, self._point_end, self._point_end_qd)

    def eval_tie_path(self, state_in: MarionetteState, state_out: MarionetteState) -> None:
        m = self.model
        wp.launch(eval_tie_path, dim=(m.substeps, m.strings.string_count),
                  inputs=[m.string_point_wp, self._point_end, state_in.tie_target, wp.float64(m.string_dt)],
                  outputs=[self._tie_q, self._tie_qd, state_out.tie_target], device=m.device)

    def apply_tie_path_to_strings(self) -> None:
        """Float32 strings: the tie path (float64, from the puppet) into their float32 controls."""
        m = self.model
        convert_vec3(self._tie_q, self._narrow.tie_q, m.device)
        convert_vec3(self._tie_qd, self._narrow.tie_qd, m.device)

    def eval_bar_feedback(self, strings: StringState, control: MarionetteControl, state_out: MarionetteState,
                          j: int) -> None:
        m = self.model
        s = m.strings
        weight = wp.vec3d(*(m.puppet_mass * np.asarray(m.scene.gravity)))
        wp.launch(self._feedback, dim=s.string_count,
                  inputs=[s.string_start, m.string_bar_wp, s.string_stiffness, s.string_rest_length,
                          s.string_internal_friction, wp.float64(m.scene.feedback_stiffness),
                          wp.float64(m.scene.feedback_damping), weight,
                          strings.particle_q, strings.particle_qd, strings.string_taut,
                          control.bar_q[j], control.bar_qd[j]],
                  outputs=[state_out.bar_feedback[j], state_out.bar_reaction[j]], device=m.device)

    def apply_string_forces_to_anchors(self, state_out: MarionetteState) -> None:
        m = self.model
        if len(m.spring_string) == 0:
            return
        wp.launch(apply_string_forces_to_anchors_kernel(m.substeps), dim=len(m.spring_string),
                  inputs=[m.spring_string_wp, m.string_tie_stiffness, state_out.tie_force,
                          self._tie_q, self._tie_qd, wp.float64(m.string_dt)],
                  outputs=[self._puppet_control.spring_anchor_pos, self._puppet_control.spring_anchor_vel],
                  device=m.device)

    def step_puppet(self, state_in: MarionetteState, state_out: MarionetteState) -> None:
        m = self.model
        m.puppet_solver.step(state_in.puppet, state_out.puppet, self._puppet_control, m.puppet_dt)


TRIAL_FIELDS = ("body_pos", "body_rot", "body_w", "body_v", "body_wrench", "body_stiffness", "spring_force")


def trial_fields(puppet_model, requires_grad: bool = False) -> dict[str, wp.array]:
    """Arrays for the body fields a trial step writes into its input state (``TRIAL_FIELDS``)."""
    scratch = puppet_model.state(requires_grad=requires_grad)
    return {name: getattr(scratch, name) for name in TRIAL_FIELDS}


def trial_view(puppet_state: ArticulationState, fields: dict[str, wp.array]) -> ArticulationState:
    """``puppet_state`` with its own ``fields``: the trial step reads its coordinates and writes
    its body fields elsewhere (the real step, and a tape, see them untouched)."""
    view = copy.copy(puppet_state)
    for name, array in fields.items():
        setattr(view, name, array)
    return view


def predict_puppet_step(model: MarionetteModel, response, view: ArticulationState, strings: StringState,
                        tie_force: wp.array, trial_out: ArticulationState, control) -> None:
    """The trial puppet step of ``string_body_coupling``: ``view`` (the step's input, see
    :func:`trial_view`) into ``trial_out``, each tied string replaced by its linearised pull
    (``response``: an ``eval_string_response_kernel``; ``tie_force``: the previous puppet
    step's, ``(n, S)``, the input state's)."""
    m = model
    s = m.strings

    def string_loads(state, h):
        if len(m.spring_string) == 0:
            return
        wp.launch(response, dim=(state.world_count, len(m.spring_string)),
                  inputs=[m.puppet.spring_body, m.puppet.spring_point, m.spring_string_wp, s.string_start,
                          s.string_stiffness, s.string_rest_length, s.string_tie_stiffness, s.string_taut_distance,
                          s.string_internal_friction,
                          state.body_pos, state.body_rot, state.body_w, state.body_v,
                          strings.particle_q, tie_force, h],
                  outputs=[state.body_wrench, state.body_stiffness], device=m.device)

    m.puppet_solver.step(view, trial_out, control, m.puppet_dt, point_loads=string_loads)
