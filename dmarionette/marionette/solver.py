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

import dataclasses

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
from dmarionette.marionette.workspace import MarionetteWorkspace, PuppetPoints, StringStepOutput
from dmarionette.strings.solver import SolverStringImplicit

__all__ = ["MarionetteControl", "MarionetteModel", "MarionetteState", "MarionetteWorkspace", "SolverMarionette"]


class MarionetteModel:
    """Strings + puppet + bars built from a scene, for one world or ``W`` worlds at once.

    A batched model (``world_count = W``, or :meth:`from_scenes` with one scene per world) steps
    ``W`` independent marionettes in the same launches: its strings are the ``W`` worlds'
    strings one world after another (``W S`` strings: a string step runs one thread per
    (world, string)), the puppet states have ``W`` worlds (one thread per (world, body)), and
    the bars are ``W B`` rows. Worlds differ in what lives in arrays: every string constant
    (``k``, ``k_d``, ``k_s``, masses, lengths...), the bar motions and the initial pose;
    everything compiled into the kernels or sized by them is shared and must be equal
    (:func:`check_world_scenes`). ``W = 1`` is exactly the unbatched model.

    Attributes:
        scene: the scene it was built from (world 0's).
        world_scenes: one scene per world, ``(W,)``.
        world_count: ``W``.
        strings: the :class:`StringModel` of all worlds' strings, in the scene's ``[solver]
            precision``; ``strings_per_world`` ``S`` of them per world.
        precision: ``"float64"`` or ``"float32"``: the strings' float type (the puppet is float64).
        string_tie_stiffness: eq. 2 ``k`` of each string as float64 for the puppet side (the
            anchor offset ``F / k``) [N/m], ``(W S,)``: the strings' own array in float64 (so
            fitted values and gradients are shared), a float64 copy of it in float32.
        puppet: the :class:`ArticulationModel` (springs: one per tied string, in string order;
            one set of spring constants per world).
        substeps: string steps per puppet step ``n``; ``puppet_dt = n * string_dt``.
        string_dt, puppet_dt: [s].
        bar_names: ``(B,)``; string_bar: bar index of each string of a world (-1: none), ``(S,)``.
        bar_rows: rows per world of the bar arrays, ``max(B, 1)``.
        string_point: puppet point index each string of a world is tied to (-1: none), ``(S,)``.
        spring_string: string index (within its world) of each body spring, ``(N,)``.
        q_initial: world 0's start coordinates; q_initial_worlds: every world's, ``(W, q_count)``.
        puppet_mass: total puppet mass [kg] (eq. 4's ``m``).
        requires_grad: whether the strings' and puppet's fittable arrays (and the states
            made from them) carry gradients, for taped rollouts (``dmarionette.grad.engine``).
    """

    def __init__(self, scene: Scene, *, world_count: int = 1, optimization_level: int = 2, device=None,
                 requires_grad: bool = False, world_scenes=None):
        if not (isinstance(world_count, (int, np.integer)) and world_count >= 1):
            raise ValueError(f"world_count: got {world_count!r}; expected an integer >= 1")
        if world_scenes is None:
            world_scenes = (scene,) * int(world_count)
        elif world_count != 1:
            raise ValueError("MarionetteModel: give world_count (copies of scene) or world_scenes, not both")
        world_scenes = tuple(world_scenes)
        if scene.puppet is None:
            raise ValueError(f"{scene.source}: a marionette needs a [puppet] table")
        if requires_grad and scene.precision != "float64":
            raise ValueError(f"{scene.source}: [solver] precision = {scene.precision!r}: gradients of a "
                             "marionette are float64 only; use precision = \"float64\" for fitting")
        check_world_scenes(world_scenes)
        for world in world_scenes:
            check_marionette_settings(world)  # settings measured not to work are refused, with the reason
        self.scene = scene
        self.world_scenes = world_scenes
        self.world_count = len(world_scenes)
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
            scene.puppet, ball=ball, contacts=contacts, joint_limits=e["joint_limits"],
            one_sided_limits=e["one_sided_limits"], gravity=scene.gravity,
            springs=tuple((p, scene.strings[i].tie_stiffness, scene.strings[i].tie_damping) for i, p in tied),
            device=str(self.device), requires_grad=self.requires_grad,
            spring_worlds=self.world_count if self.world_count > 1 else 1)
        self.puppet_solver = SolverArticulation(self.puppet, optimization_level=optimization_level)
        # Where the tied points are in each world's initial pose: its strings start straight from bar to point.
        self.q_initial_worlds = np.stack([initial_joint_q(self.puppet, world) for world in world_scenes])
        self.q_initial = self.q_initial_worlds[0]
        point_names = self.puppet.point_names
        specs = []
        for w, world in enumerate(world_scenes):
            point_q = self._rest_points(w)
            for spec, body_point in zip(world.strings, world.string_body_points):
                if body_point is not None:
                    bottom = tuple(float(v) for v in point_q[point_names.index(body_point)])
                    length = spec.length or float(np.linalg.norm(np.subtract(spec.top, bottom)))
                    spec = dataclasses.replace(spec, bottom=bottom, tie_point=bottom, length=length)
                specs.append(spec)
        self.strings = StringModel(specs, effects=scene.effects, gravity=scene.gravity,
                                   ground_height=scene.ground_height, precision=self.precision, device=self.device,
                                   requires_grad=self.requires_grad)
        self.strings_per_world = len(names)
        self.string_solver = SolverStringImplicit(self.strings)
        self.bar_names = [b.name for b in scene.bars]
        self.bar_rows = max(len(self.bar_names), 1)
        bar_of = {s: i for i, b in enumerate(scene.bars) for s in b.attach}
        self.string_bar = np.array([bar_of.get(n, -1) for n in names], dtype=np.int32)
        self.string_point = np.array([point_names.index(p) if p else -1 for p in scene.string_body_points],
                                     dtype=np.int32)
        self.spring_string = np.array([i for i, _ in tied], dtype=np.int32)
        self.puppet_mass = float(sum(b.mass for b in scene.puppet.bodies))
        # The kernels' view of all worlds: world w's strings and bar rows follow those of the worlds before.
        worlds = np.arange(self.world_count)
        string_bar = np.where(self.string_bar[None] >= 0, self.string_bar[None] + self.bar_rows * worlds[:, None], -1)
        if len(self.spring_string):
            k = np.array([[world.strings[i].tie_stiffness for i in self.spring_string] for world in world_scenes])
            k_d = np.array([[world.strings[i].tie_damping for i in self.spring_string] for world in world_scenes])
            upload_values(self.puppet.spring_stiffness, k.reshape(-1))  # one set per world (W = 1: the set)
            upload_values(self.puppet.spring_damping, k_d.reshape(-1))
        with wp.ScopedDevice(self.device):
            self.string_bar_wp = wp.array(string_bar.reshape(-1).astype(np.int32), dtype=wp.int32)
            self.string_point_wp = wp.array(np.tile(self.string_point, self.world_count), dtype=wp.int32)
            self.spring_string_wp = wp.array(self.spring_string, dtype=wp.int32)
            self.string_tie_stiffness = self.strings.string_tie_stiffness if self.precision == "float64" \
                else wp.array([s.tie_stiffness for s in specs], dtype=wp.float64)

    @classmethod
    def from_scenes(cls, scenes, **kwargs) -> MarionetteModel:
        """A batched model with one world per scene (``check_world_scenes`` says what may differ);
        keyword arguments as for the constructor."""
        scenes = tuple(scenes)
        if not scenes:
            raise ValueError("MarionetteModel.from_scenes: got no scenes; expected one per world")
        return cls(scenes[0], world_scenes=scenes, **kwargs)

    def _rest_points(self, world: int) -> np.ndarray:
        """World ``world``'s puppet points at its start pose, ``(points, 3)``."""
        state = self.puppet.state()
        state.joint_q.assign(wp.array(self.q_initial_worlds[world][None], dtype=wp.float64, device=self.device))
        return self.eval_world_points(state)[0][0]

    def initial_puppet_state(self, requires_grad: bool = False) -> ArticulationState:
        """The puppet at its start pose (``q_initial_worlds``), at rest, all worlds."""
        state = self.puppet.state(self.world_count, requires_grad=requires_grad)
        state.joint_q.assign(wp.array(self.q_initial_worlds, dtype=wp.float64, device=self.device))
        return state

    @property
    def bar_count(self) -> int:
        return len(self.bar_names)

    def eval_world_points(self, state: ArticulationState) -> tuple[np.ndarray, np.ndarray]:
        """World positions [m] and velocities [m/s] of the puppet's named points in each world of
        ``state``, ``(worlds, points, 3)`` each (fills ``state``'s body poses on the way:
        ``SolverArticulation.eval_kinematics``)."""
        n = len(self.puppet.point_names)
        q = wp.zeros((state.world_count, n), dtype=wp.vec3d, device=self.device)
        qd = wp.zeros((state.world_count, n), dtype=wp.vec3d, device=self.device)
        self.puppet_solver.eval_kinematics(state)
        self.puppet_solver.eval_points(state, q, qd)
        return q.numpy(), qd.numpy()

    def eval_points(self, state: ArticulationState) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`eval_world_points` for a one-world ``state``: ``(points, 3)`` each."""
        if state.world_count != 1:
            raise ValueError(f"eval_points: a state of {state.world_count} worlds; use eval_world_points")
        q, qd = self.eval_world_points(state)
        return q[0], qd[0]

    def state(self, requires_grad: bool = False) -> MarionetteState:
        """The start state: puppet at its rest pose, strings straight from bar to body point, at rest
        (``requires_grad``: its float arrays carry gradients, for taped steps)."""
        return MarionetteState(self, requires_grad)

    def control(self, requires_grad: bool = False) -> MarionetteControl:
        """Control buffers for one puppet step, holding the bars at their t = 0 pose."""
        control = MarionetteControl(self, requires_grad)
        control.set_bars(self, 0.0)
        return control


# What every world of a batched marionette shares (compiled into its kernels or sizing them), by the
# name a user knows it by.
_SHARED = {
    "[rates] string_hz": lambda s: s.string_hz,
    "[rates] puppet_hz": lambda s: s.puppet_hz,
    "[solver] precision": lambda s: s.precision,
    "[effects] (strings)": lambda s: s.effects,
    "[effects] (puppet)": lambda s: dict(s.body_effects),
    "[contact]": lambda s: dict(s.contact),
    "gravity": lambda s: tuple(s.gravity),
    "ground height": lambda s: s.ground_height,
    "[puppet]": lambda s: s.puppet,
    "[chair]": lambda s: s.chair,
    "[ball]": lambda s: s.ball,
    "string names": lambda s: [x.name for x in s.strings],
    "string particle counts": lambda s: [x.particle_count for x in s.strings],
    "string body points": lambda s: tuple(s.string_body_points),
    "bars and their strings": lambda s: [(b.name, tuple(b.attach)) for b in s.bars],
    "[feedback] stiffness": lambda s: s.feedback_stiffness,
    "[feedback] damping": lambda s: s.feedback_damping,
}


def check_world_scenes(scenes) -> None:
    """Raises ``ValueError`` naming the first world and setting that differs from world 0's where
    the worlds of a batched marionette must agree (the kernels and launch sizes are shared;
    string constants, bar motions and the initial pose may differ)."""
    first = scenes[0]
    for w, scene in enumerate(scenes[1:], start=1):
        for name, read in _SHARED.items():
            if read(scene) != read(first):
                raise ValueError(f"world {w} ({scene.source}): {name} = {read(scene)!r}; every world of a batched "
                                 f"marionette needs world 0's ({first.source}) {read(first)!r} (the worlds share "
                                 "their kernels; string constants, bar motions and the initial pose may differ)")


class MarionetteState:
    """What evolves, and what one puppet step reports.

    Attributes:
    Per-string and per-bar arrays hold all worlds, world after world (``W S`` strings, ``W``
    times ``bar_rows`` bars; ``W = 1``: ``S`` and ``B``).

    Attributes:
        strings: the string state at the end of the step.
        puppet: the puppet state (``W`` worlds).
        tie_force: eq. 2 force of each tie on its body point after each string step [N],
            ``(n, W S)`` of vec3d; the next puppet step's trial step reads its mean (zero in
            the start state).
        string_taut: taut flags after each string step, ``(n, W S)``.
        bar_feedback: eq. 4 feedback per bar after each string step [N], ``(n, W B)``.
        bar_reaction: exact reaction of the strings on each bar after each string step [N], ``(n, W B)``.
        tie_target: where each string's tie target is at the end of the step [m], ``(W S,)``
            (the start of the next step's path; see ``string_body_coupling``).
    """

    def __init__(self, model: MarionetteModel, requires_grad: bool = False):
        rg = requires_grad
        self.strings: StringState = model.strings.state()
        self.puppet: ArticulationState = model.initial_puppet_state(rg)
        n, s, b = model.substeps, model.strings.string_count, model.bar_rows * model.world_count
        with wp.ScopedDevice(model.device):
            self.tie_force = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=rg)
            self.string_taut = wp.zeros((n, s), dtype=wp.int32)
            self.bar_feedback = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=rg)
            self.bar_reaction = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=rg)
            self.tie_target = wp.array(model.strings.tie_points(), dtype=wp.vec3d, requires_grad=rg)

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
        top_q: attach point of each string's top at the end of each string step [m], ``(n, W S)``.
        bar_q, bar_qd: bar centre position [m] and velocity [m/s] (the device proxy of eq. 4),
            ``(n, W B)`` (``B`` = ``model.bar_rows``).
        t0: time at the start of the step [s] (host side, used by :meth:`set_bars`).
    """

    def __init__(self, model: MarionetteModel, requires_grad: bool = False):
        n, s, b = model.substeps, model.strings.string_count, model.bar_rows * model.world_count
        with wp.ScopedDevice(model.device):
            self.top_q = wp.zeros((n, s), dtype=wp.vec3d, requires_grad=requires_grad)
            self.bar_q = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=requires_grad)
            self.bar_qd = wp.zeros((n, b), dtype=wp.vec3d, requires_grad=requires_grad)
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
    """String tops ``(T, W S, 3)``, bar centres ``(T, W B, 3)`` and their velocities at ``times``
    (each world's from its own scene, world after world)."""
    per_world = model.strings_per_world
    specs = model.strings.specs
    tops, bar_q, bar_qd = [], [], []
    for w, scene in enumerate(model.world_scenes):
        tops.append(scene.top_positions(np.array([s.top for s in specs[w * per_world:(w + 1) * per_world]]), times))
        q = np.zeros((len(times), model.bar_rows, 3))
        qd = np.zeros_like(q)
        for b, bar in enumerate(scene.bars):
            q[:, b], qd[:, b], _ = bar.trajectory.pose(times)
        bar_q.append(q)
        bar_qd.append(qd)
    return tuple(np.concatenate(a, axis=1) if len(a) > 1 else a[0] for a in (tops, bar_q, bar_qd))


class SolverMarionette:
    """Steps a :class:`MarionetteModel` by one puppet step (``n`` string steps).

    Every pass takes the step's :class:`MarionetteWorkspace` (keyword ``workspace``; default:
    :attr:`workspace`, reused by plain runs) and the ``wp.Tape`` it is recorded on (keyword
    ``tape``; None for a plain step). A taped step needs a workspace of its own
    (:meth:`new_workspace`); :meth:`step` makes one when given only a tape. The gradient
    engine (``grad/tape.py``) records exactly these methods.

    Args:
        model: the marionette.
    """

    def __init__(self, model: MarionetteModel):
        self.model = model
        m = model
        self._feedback = eval_bar_feedback_kernel(m.strings.scalar, m.scene.effects.internal_friction,
                                                  m.scene.effects.tension_only, bar_scalar=wp.float64) \
            if m.scene.body_effects["feedback"] and m.bar_count else None
        self._response = eval_string_response_kernel(m.strings.scalar, m.scene.effects.internal_friction, m.substeps)
        self.workspace = self.new_workspace(taped=False)

    def new_workspace(self, taped: bool = True) -> MarionetteWorkspace:
        """A workspace for one taped step (``taped``), or one that plain steps may reuse."""
        return MarionetteWorkspace.allocate(self.model, taped=taped)

    def _workspace(self, tape, workspace: MarionetteWorkspace | None) -> MarionetteWorkspace:
        if workspace is not None:
            return workspace
        if tape is not None:
            raise ValueError("SolverMarionette: a taped pass needs its step's own workspace (new_workspace()); "
                             "got workspace=None")
        return self.workspace

    def string_state_after(self, state_out: MarionetteState, j: int, *,
                           workspace: MarionetteWorkspace | None = None) -> StringState:
        """The string state that holds string step ``j``'s result in the step into ``state_out``
        (``state_out.strings`` for the last string step, else one of the workspace's)."""
        if j == self.model.substeps - 1:
            return state_out.strings
        states = (workspace or self.workspace).string_states
        return states[j % len(states)]

    def string_controls(self, control: MarionetteControl, *,
                        workspace: MarionetteWorkspace | None = None) -> list[StringControl]:
        """The controls of the n string steps: views of ``control``'s buffers and the
        workspace's tie path (float32 strings: of their own float32 copies); cached in the
        workspace (a taped rollout re-run from Python would otherwise make n views per string step)."""
        ws = workspace or self.workspace
        key = id(control)
        if key in ws.control_views:
            return ws.control_views[key][1]
        if ws.narrow is None:
            top_q, tie_q, tie_qd = control.top_q, ws.tie_q, ws.tie_qd
        else:
            top_q, tie_q, tie_qd = ws.narrow.top_q, ws.narrow.tie_q, ws.narrow.tie_qd
        views = [StringControl(top_q[j], tie_q[j], tie_qd[j]) for j in range(self.model.substeps)]
        ws.control_views[key] = (control, views)
        return views

    def string_step_outputs(self, state_out: MarionetteState, *,
                            workspace: MarionetteWorkspace | None = None) -> list[StringStepOutput]:
        """Where the n string steps into ``state_out`` write (float64 strings): each its string
        state's particles (:meth:`string_state_after`) and its rows of ``state_out``'s tie force and
        taut flags; cached in ``state_out`` for the last workspace it was stepped with (so that each
        one's ``StringStateArrays`` is built once, not per string step)."""
        ws = workspace or self.workspace
        cached = getattr(state_out, "_string_step_outputs", None)
        if cached is not None and cached[0] is ws:
            return cached[1]
        views = []
        for j in range(self.model.substeps):
            particles = self.string_state_after(state_out, j, workspace=ws)
            views.append(StringStepOutput(particles.particle_q, particles.particle_qd, state_out.tie_force[j],
                                          state_out.string_taut[j]))
        state_out._string_step_outputs = (ws, views)
        return views

    def step(self, state_in: MarionetteState, state_out: MarionetteState, control: MarionetteControl,
             dt: float | None = None, *, tape: wp.Tape | None = None,
             workspace: MarionetteWorkspace | None = None) -> None:
        """Advances ``state_in`` by one puppet step into ``state_out`` (``dt`` must equal
        ``puppet_dt``); ``state_in`` is only read."""
        m = self.model
        if dt is not None and abs(dt - m.puppet_dt) > 1e-12 * m.puppet_dt:
            raise ValueError(f"dt: got {dt}; this marionette steps by puppet_dt = {m.puppet_dt} "
                             f"({m.substeps} string steps of {m.string_dt})")
        ws = workspace if workspace is not None else (self.new_workspace() if tape is not None else self.workspace)
        self.begin_step(state_in, state_out, tape=tape, workspace=ws)  # body points, tie path (body -> strings)
        for j in range(m.substeps):
            self.step_string(state_in, state_out, control, j, tape=tape, workspace=ws)  # eq. 2, eq. 4
        self.end_step(state_in, state_out, tape=tape, workspace=ws)  # mean tie force -> anchors, puppet step

    def begin_step(self, state_in: MarionetteState, state_out: MarionetteState, *, tape: wp.Tape | None = None,
                   workspace: MarionetteWorkspace | None = None) -> None:
        """Passes before the string steps (a live loop runs them at the first tick of a puppet step)."""
        ws = self._workspace(tape, workspace)
        self.eval_body_points(state_in, ws.points)      # tied body points at t0
        self.predict_body_points(state_in, ws)          # trial puppet step: the tied points at t0 + H
        self.eval_tie_path(state_in, state_out, ws)     # the strings' tie targets over the step
        if ws.narrow is not None:
            self.apply_tie_path_to_strings(ws)          # float64 -> float32 string controls
        if self._feedback is not None:
            state_out.bar_feedback.zero_()
            state_out.bar_reaction.zero_()

    def step_string(self, state_in: MarionetteState, state_out: MarionetteState, control: MarionetteControl,
                    j: int, *, tape: wp.Tape | None = None, workspace: MarionetteWorkspace | None = None) -> None:
        """String step ``j`` of the puppet step: from ``state_in`` (j = 0) through the workspace's
        string states to ``state_out`` (j = n - 1, :meth:`string_state_after`); the tie force and
        taut flags into row ``j`` of ``state_out``'s, and the feedback."""
        m = self.model
        ws = self._workspace(tape, workspace)
        previous = state_in.strings if j == 0 else self.string_state_after(state_out, j - 1, workspace=ws)
        particles = self.string_state_after(state_out, j, workspace=ws)
        string_ws = ws.string_workspaces[j % len(ws.string_workspaces)]
        controls = self.string_controls(control, workspace=ws)
        if ws.narrow is None:
            # The tie force and taut flags go straight into this string step's rows of state_out.
            nxt = self.string_step_outputs(state_out, workspace=ws)[j]
            m.string_solver.step(previous, nxt, controls[j], m.string_dt, tape=tape, workspace=string_ws)
        else:
            nxt = particles
            convert_vec3(control.top_q[j], ws.narrow.top_q[j], m.device)  # bar tops -> float32
            m.string_solver.step(previous, nxt, controls[j], m.string_dt, tape=tape, workspace=string_ws)
            convert_vec3(nxt.tie_force, state_out.tie_force[j], m.device)  # float32 -> float64 tie force
            wp.copy(state_out.string_taut[j], nxt.string_taut)
        if self._feedback is not None:
            self.eval_bar_feedback(nxt, control, state_out, j)

    def end_step(self, state_in: MarionetteState, state_out: MarionetteState, *, tape: wp.Tape | None = None,
                 workspace: MarionetteWorkspace | None = None) -> None:
        """Passes after the string steps (strings -> body)."""
        ws = self._workspace(tape, workspace)
        self.apply_string_forces_to_anchors(state_out, ws)  # mean tie force -> body springs' anchors
        self.step_puppet(state_in, state_out, ws, tape)     # implicit puppet step

    def eval_body_points(self, state: MarionetteState, points: PuppetPoints) -> None:
        """``state``'s body kinematics and named points into ``points``."""
        ps = self.model.puppet_solver
        ps.eval_kinematics(state.puppet, points.kinematics)
        ps.eval_points(points.kinematics, points.point_q, points.point_qd)

    def predict_body_points(self, state_in: MarionetteState, ws: MarionetteWorkspace) -> None:
        """The trial puppet step (``string_body_coupling``): the puppet step's passes with each tied
        string's linearised pull in place of its spring, into ``ws.trial``; its points at ``t0 + H``
        into ``ws.trial_points``."""
        m = self.model
        ps, tw, puppet = m.puppet_solver, ws.trial_workspace, state_in.puppet
        h, hi = ps.step_sizes(m.puppet_dt)
        ps.eval_kinematics(puppet, tw)                           # body poses and velocities at t0
        ps.eval_external_forces(tw, ws.puppet_control)           # applied wrenches; resets h D + h^2 K
        self.eval_string_response(state_in, tw, hi)              # the strings' linearised pull
        ps.eval_contacts(tw, hi)                                 # ground / chair / ball penalties
        ps.solve_dynamics(puppet, ws.trial, ws.puppet_control, tw, h, hi)  # (M + h D + h^2 K) qdd = tau
        ps.integrate(puppet, ws.trial, h)                        # q' = q (+) h qd'
        ps.eval_kinematics(ws.trial, ws.trial_points.kinematics)
        ps.eval_points(ws.trial_points.kinematics, ws.trial_points.point_q, ws.trial_points.point_qd)

    def eval_string_response(self, state_in: MarionetteState, tw, h) -> None:
        """Each tied string's linearised pull on its body (``eval_string_response``; ``tie_force``:
        the previous puppet step's, the input state's) into ``tw``'s wrenches and stiffness blocks."""
        m = self.model
        s = m.strings
        if len(m.spring_string) == 0:
            return
        wp.launch(self._response, dim=(tw.world_count, len(m.spring_string)),
                  inputs=[m.puppet.spring_body, m.puppet.spring_point, m.spring_string_wp,
                          wp.int32(m.strings_per_world), s.arrays, tw.body_pos, tw.body_rot, tw.body_w, tw.body_v,
                          state_in.strings.particle_q, state_in.tie_force, h],
                  outputs=[tw.body_wrench, tw.body_stiffness], device=m.device)

    def eval_tie_path(self, state_in: MarionetteState, state_out: MarionetteState, ws: MarionetteWorkspace) -> None:
        m = self.model
        wp.launch(eval_tie_path, dim=(m.substeps, m.strings.string_count),
                  inputs=[m.string_point_wp, wp.int32(m.strings_per_world), ws.trial_points.point_q,
                          state_in.tie_target, wp.float64(m.string_dt)],
                  outputs=[ws.tie_q, ws.tie_qd, state_out.tie_target], device=m.device)

    def apply_tie_path_to_strings(self, ws: MarionetteWorkspace) -> None:
        """Float32 strings: the tie path (float64, from the puppet) into their float32 controls."""
        m = self.model
        convert_vec3(ws.tie_q, ws.narrow.tie_q, m.device)
        convert_vec3(ws.tie_qd, ws.narrow.tie_qd, m.device)

    def eval_bar_feedback(self, strings: StringState, control: MarionetteControl, state_out: MarionetteState,
                          j: int) -> None:
        m = self.model
        s = m.strings
        weight = wp.vec3d(*(m.puppet_mass * np.asarray(m.scene.gravity)))
        wp.launch(self._feedback, dim=s.string_count,
                  inputs=[s.arrays, m.string_bar_wp, wp.float64(m.scene.feedback_stiffness),
                          wp.float64(m.scene.feedback_damping), weight, strings.arrays,
                          control.bar_q[j], control.bar_qd[j]],
                  outputs=[state_out.bar_feedback[j], state_out.bar_reaction[j]], device=m.device)

    def apply_string_forces_to_anchors(self, state_out: MarionetteState, ws: MarionetteWorkspace) -> None:
        m = self.model
        if len(m.spring_string) == 0:
            return
        wp.launch(apply_string_forces_to_anchors_kernel(m.substeps), dim=(m.world_count, len(m.spring_string)),
                  inputs=[m.spring_string_wp, wp.int32(m.strings_per_world), m.string_tie_stiffness,
                          state_out.tie_force,
                          ws.tie_q, ws.tie_qd, wp.float64(m.string_dt)],
                  outputs=[ws.puppet_control.spring_anchor_pos, ws.puppet_control.spring_anchor_vel],
                  device=m.device)

    def step_puppet(self, state_in: MarionetteState, state_out: MarionetteState, ws: MarionetteWorkspace,
                    tape: wp.Tape | None = None) -> None:
        m = self.model
        m.puppet_solver.step(state_in.puppet, state_out.puppet, ws.puppet_control, m.puppet_dt, tape=tape,
                             workspace=ws.puppet_workspace)
