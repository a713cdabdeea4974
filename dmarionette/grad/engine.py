"""Gradients through whole marionette rollouts (Warp tape, checkpointed; docs/gradients.md).

:class:`MarionetteGradient` runs a rollout of ``P`` puppet steps (``T = P n`` string steps)
from host inputs (:class:`RolloutInputs`: the bars, per-string constants, the puppet's
initial state) and returns its outputs (:class:`RolloutOutputs`); :meth:`backward` maps
cotangents of any of the outputs to gradients with respect to every input.

Checkpointing: the forward pass runs segments of
``checkpoint_steps = C`` puppet steps without a tape (captured as Warp graphs) and keeps
only the state at each segment's start: string particle positions and velocities, puppet
``joint_q``/``joint_qd``, the tie targets and the last step's tie forces (the coupling's
trial step reads their mean), which is everything one step reads from the previous one. The backward pass takes the segments in reverse: it restores the
checkpoint, re-runs the segment on a ``wp.Tape`` with one fresh array per written quantity
per step (:mod:`dmarionette.grad.tape`: ``SolverMarionette.step`` itself, a fresh workspace per step), seeds the cotangents of the segment's outputs and the
state adjoint arriving from the next segment, runs ``tape.backward`` and passes the adjoint
of the segment's start state on. The peak memory is one segment's tape (``C n`` string
steps) plus the checkpoints (``P / C``) and the host outputs.

The default ``C`` is ``ceil(sqrt(P))`` (least memory when a checkpoint weighs as much as a
step's tape), capped at ``SEGMENT_STRING_STEPS / n`` puppet steps. A taped string step weighs
far more than a checkpoint (``hanging``: about 90 KiB of tape per string step, 19 KiB per
checkpoint), and a short segment's arrays are still warm when its reverse pass reads them: the
backward of the 16 s ``hanging`` rollout takes about 0.68x the time with ``C = 6`` (18 MiB of
tape) as with ``ceil(sqrt(480)) = 22`` (70 MiB), and needs less memory (docs/gradients.md).

What is differentiated, and the mapping to the kernels' constants:

- ``tie_stiffness`` ``k`` and ``tie_damping`` ``k_d`` (eq. 2, per string) act twice: on the
  string side (``strings.string_tie_stiffness``/``_damping``: the implicit tie of the last
  particle, and the anchor offset ``F / k`` of the coupling) and on the puppet side
  (``puppet.spring_stiffness``/``_damping``, one spring per tied string, ``model.spring_string``);
  their gradient is the sum of both.
- ``string_stiffness`` is the scene's whole-string stiffness ``k`` [N/m] (``[[strings]]
  stiffness``); the kernels use the per-segment ``k_s = k (n - 1)`` (``string_model``),
  so ``dL/dk = (n - 1) dL/dk_s``.
- ``joint_q0``/``joint_qd0`` start the puppet, ``particle_q0``/``particle_qd0`` the strings
  (default: the scene's rest state, straight from bar to body point, at rest); the tie
  targets start at the scene's rest tie points, so a ``joint_q0`` away from the rest pose
  pulls the ties towards the new pose over the first puppet step.

Worlds: a batched model (``MarionetteModel(..., world_count=W)`` or ``from_scenes``) runs ``W``
rollouts in the same launches; :meth:`MarionetteGradient.forward` then takes a list of ``W``
:class:`RolloutInputs` and returns a list of :class:`RolloutOutputs`, and
:meth:`~MarionetteGradient.backward` takes a list of ``W`` cotangent dicts and returns each
world's gradients (the worlds do not interact, so world ``w``'s gradient is that of its own
rollout: ``tests/grad/test_world_gradients.py``). Inside, the inputs and outputs are laid out as
the kernels hold them: strings and bars world after world, puppet arrays with a world axis.

Forward mode: :meth:`MarionetteGradient.jvp` carries P tangent directions through one rollout
(:mod:`dmarionette.grad.rollout_tangent`; one world).

Not differentiable (discontinuous; keep the loss away from them): the taut flag of a
string (eq. 4's feedback switches on and off with it), the slack clamp of a segment's
geometric stiffness, string-ground contact and hard (non-smooth) body contact, and
joint-limit onsets. The smooth body contact (``[contact] smooth = true``) is smooth.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import warp as wp

from dmarionette.capture import CapturedChunk, ping_pong
from dmarionette.grad.carried import carried_arrays
from dmarionette.grad.rollout_tangent import RolloutTangent
from dmarionette.grad.tape import TapedSegment
from dmarionette.marionette.solver import MarionetteControl, MarionetteModel, SolverMarionette, bar_inputs
from dmarionette.strings.rollout import upload_values

__all__ = ["INPUT_FIELDS", "OPTIONAL_INPUT_FIELDS", "OUTPUT_FIELDS", "SEGMENT_STRING_STEPS", "MarionetteGradient",
           "RolloutInputs", "RolloutOutputs"]


SEGMENT_STRING_STEPS = 165
"""The most string steps of a default taped segment (5 puppet steps at 30 Hz / 1 kHz; module doc)."""


@dataclasses.dataclass
class RolloutInputs:
    """Inputs of a rollout (host float64 arrays; ``T = puppet_steps * substeps`` string steps).

    Attributes:
        top_q: string top (attach) positions at the end of each string step [m], ``(T, S, 3)``.
        bar_q: bar centre (eq. 4's device proxy) at the end of each string step [m], ``(T, B, 3)``
            (``B = max(bars, 1)``; a scene without bars has one unused row).
        bar_qd: its velocity [m/s], ``(T, B, 3)``.
        tie_stiffness: eq. 2 ``k`` per string [N/m], ``(S,)`` (the same ``k`` acts on the string
            and the puppet side); ``> 0`` for tied strings.
        tie_damping: eq. 2 ``k_d`` per string [N s/m], ``(S,)``, ``>= 0``.
        string_stiffness: the scene's whole-string (end-to-end) stiffness ``k`` [N/m], ``(S,)``,
            ``> 0`` (the kernels' per-segment ``k_s = k (n - 1)``).
        joint_q0: initial puppet coordinates, ``(q_count,)`` (``articulation`` layout).
        joint_qd0: initial puppet velocities, ``(qd_count,)``.
        particle_q0: initial string particle positions [m], ``(particles, 3)`` (the strings'
            particles in ``model.strings`` order); None: the scene's rest state (straight from
            bar to body point). The top particle of each string follows its bar from the first
            step on.
        particle_qd0: initial string particle velocities [m/s], ``(particles, 3)``; None: at rest.
    """

    top_q: np.ndarray
    bar_q: np.ndarray
    bar_qd: np.ndarray
    tie_stiffness: np.ndarray
    tie_damping: np.ndarray
    string_stiffness: np.ndarray
    joint_q0: np.ndarray
    joint_qd0: np.ndarray
    particle_q0: np.ndarray | None = None
    particle_qd0: np.ndarray | None = None


@dataclasses.dataclass
class RolloutOutputs:
    """Outputs of a rollout (host float64 arrays; ``P`` puppet steps, ``T`` string steps).

    Attributes:
        joint_q: puppet coordinates at every puppet step, ``(P + 1, q_count)`` (row 0: initial).
        point_pos: world positions of the puppet's named points (``model.puppet.point_names``)
            [m], ``(P + 1, points, 3)``.
        body_pos: body origins (centres of mass) [m], ``(P + 1, bodies, 3)``.
        body_rot: body orientations, quaternions ``(x, y, z, w)`` (as in
            ``MarionetteTrajectory``), ``(P + 1, bodies, 4)``.
        tie_force: eq. 2 force of each tie on its body point after each string step [N],
            ``(T, S, 3)``.
        bar_feedback: eq. 4 feedback per bar after each string step [N], ``(T, B, 3)``.
        bar_reaction: exact reaction of the strings on each bar [N], ``(T, B, 3)``.
    """

    joint_q: np.ndarray
    point_pos: np.ndarray
    body_pos: np.ndarray
    body_rot: np.ndarray
    tie_force: np.ndarray
    bar_feedback: np.ndarray
    bar_reaction: np.ndarray


INPUT_FIELDS = tuple(f.name for f in dataclasses.fields(RolloutInputs))
# Inputs that may be left out (None): they then take the scene's rest state (``MarionetteGradient.default_inputs``).
OPTIONAL_INPUT_FIELDS = tuple(f.name for f in dataclasses.fields(RolloutInputs) if f.default is None)
OUTPUT_FIELDS = tuple(f.name for f in dataclasses.fields(RolloutOutputs))


@dataclasses.dataclass
class Checkpoint:
    """Everything a puppet step reads from the previous one (host copies)."""

    particle_q: np.ndarray
    particle_qd: np.ndarray
    joint_q: np.ndarray
    joint_qd: np.ndarray
    tie_target: np.ndarray
    tie_force: np.ndarray  # the previous puppet step's, (n, S, 3): the next trial step reads its mean

    @classmethod
    def of(cls, state) -> Checkpoint:
        return cls(**{name: array.numpy().copy() for name, array in carried_arrays(state).items()})

    def load(self, state) -> None:
        for name, array in carried_arrays(state).items():
            upload_values(array, getattr(self, name))


class _PlainChunk:
    """``steps`` puppet steps without a tape, captured as one Warp graph (CPU or CUDA).

    Per-step inputs are written into ``controls`` before a replay; per-step outputs are
    copied into the ``(steps, ...)`` buffers by the graph.
    """

    def __init__(self, engine: MarionetteGradient, steps: int, capture: bool):
        m = engine.model
        self.engine = engine
        self.steps = steps
        n, s, b, w = m.substeps, m.strings.string_count, m.bar_rows * m.world_count, m.world_count
        self.controls = [MarionetteControl(m) for _ in range(steps)]
        with wp.ScopedDevice(m.device):
            self.joint_q = wp.zeros((steps, w, m.puppet.q_count), dtype=wp.float64)
            self.point_pos = wp.zeros((steps, w, len(m.puppet.point_names)), dtype=wp.vec3d)
            self.body_pos = wp.zeros((steps, w, m.puppet.body_count), dtype=wp.vec3d)
            self.body_rot = wp.zeros((steps, w, m.puppet.body_count), dtype=wp.quatd)
            self.tie_force = wp.zeros((steps, n, s), dtype=wp.vec3d)
            self.bar_feedback = wp.zeros((steps, n, b), dtype=wp.vec3d)
            self.bar_reaction = wp.zeros((steps, n, b), dtype=wp.vec3d)
        self.chunk = CapturedChunk(self.launch, m.device, capture=capture, warm_up=self._warm_up)

    def _warm_up(self) -> None:
        # One eager pass loads every module before capture begins; the state is put back.
        saved = Checkpoint.of(self.engine.state)
        self.launch()
        saved.load(self.engine.state)

    def launch(self) -> None:
        e = self.engine
        ping_pong(self._step, e.state, e.spare, self.steps)

    def _step(self, k: int, state_in, state_out) -> None:
        solver = self.engine.solver
        solver.step(state_in, state_out, self.controls[k])
        points = solver.workspace.points  # the input state's body poses and points (begin_step)
        wp.copy(self.joint_q[k], state_in.puppet.joint_q)
        wp.copy(self.point_pos[k], points.point_q)
        wp.copy(self.body_pos[k], points.kinematics.body_pos)
        wp.copy(self.body_rot[k], points.kinematics.body_rot)
        wp.copy(self.tie_force[k], state_out.tie_force)
        wp.copy(self.bar_feedback[k], state_out.bar_feedback)
        wp.copy(self.bar_reaction[k], state_out.bar_reaction)

    def run(self) -> None:
        self.chunk.run()


class MarionetteGradient:
    """Checkpointed rollouts of a marionette and their gradients.

    Args:
        model: built with ``requires_grad=True``. The engine owns it: :meth:`forward` writes
            the inputs' constants into its arrays (:meth:`scene_inputs` keeps the scene's).
        puppet_steps: ``P``, the rollout length in puppet steps (``T = P * model.substeps``).
        checkpoint_steps: puppet steps per taped segment ``C`` (default ``ceil(sqrt(P))``, at most
            ``SEGMENT_STRING_STEPS // substeps`` and at least 1: module doc).
        capture: run the untaped forward segments, and the taped segments' forward and
            reverse passes, as captured Warp graphs (no per-launch Python cost: 5-6x faster
            on the CPU, measured); False launches them one by one (same numbers).
    """

    def __init__(self, model: MarionetteModel, puppet_steps: int, *, checkpoint_steps: int | None = None,
                 capture: bool = True):
        if getattr(model, "precision", "float64") != "float64":
            raise ValueError(f"{model.scene.source}: [solver] precision = {model.precision!r}: MarionetteGradient "
                             "needs a float64 marionette (gradients are float64: the puppet, the tape and the "
                             "strings' adjoints); use precision = \"float64\" for fitting")
        if not getattr(model, "requires_grad", False):
            raise ValueError("MarionetteGradient: the model was built without gradients; build it with "
                             "MarionetteModel(scene, requires_grad=True)")
        if not (isinstance(puppet_steps, (int, np.integer)) and puppet_steps >= 1):
            raise ValueError(f"puppet_steps: got {puppet_steps!r}; expected an integer >= 1")
        if checkpoint_steps is None:
            checkpoint_steps = min(math.ceil(math.sqrt(puppet_steps)), max(1, SEGMENT_STRING_STEPS // model.substeps))
        if not (isinstance(checkpoint_steps, (int, np.integer)) and checkpoint_steps >= 1):
            raise ValueError(f"checkpoint_steps: got {checkpoint_steps!r}; expected an integer >= 1")
        self.model = model
        self.puppet_steps = int(puppet_steps)
        self.checkpoint_steps = min(int(checkpoint_steps), self.puppet_steps)
        self.string_steps = self.puppet_steps * model.substeps
        m = model
        self.segments = [(a, min(a + self.checkpoint_steps, self.puppet_steps))
                         for a in range(0, self.puppet_steps, self.checkpoint_steps)]
        self._keep_only_differentiated_gradients()
        self.solver = SolverMarionette(m)
        self.state = m.state()
        self.spare = m.state()
        self._rest = Checkpoint.of(self.state)
        s = m.strings
        self.world_count = w = m.world_count
        self.segments_per_string = s.string_particle_count.astype(np.float64) - 1.0
        self._scene_constants = (s.string_tie_stiffness.numpy().copy(), s.string_tie_damping.numpy().copy(),
                                 s.string_stiffness.numpy() / self.segments_per_string)
        b, per_world, particles = m.bar_rows, m.strings_per_world, s.particle_count // w
        p, t, q, qd = self.puppet_steps, self.string_steps, m.puppet.q_count, m.puppet.qd_count
        points, bodies = len(m.puppet.point_names), m.puppet.body_count
        # Each world's (the API's) shapes, and the kernels' layout of all worlds (_join / _split).
        self.input_shapes = {
            "top_q": (t, per_world, 3), "bar_q": (t, b, 3), "bar_qd": (t, b, 3),
            "tie_stiffness": (per_world,), "tie_damping": (per_world,), "string_stiffness": (per_world,),
            "joint_q0": (q,), "joint_qd0": (qd,), "particle_q0": (particles, 3), "particle_qd0": (particles, 3),
        }
        self.output_shapes = {
            "joint_q": (p + 1, q), "point_pos": (p + 1, points, 3), "body_pos": (p + 1, bodies, 3),
            "body_rot": (p + 1, bodies, 4), "tie_force": (t, per_world, 3), "bar_feedback": (t, b, 3),
            "bar_reaction": (t, b, 3),
        }
        self._flat_outputs = {name: _joined_shape(shape, _WORLD_AXIS[name], w)
                              for name, shape in self.output_shapes.items()}
        self._chunks = {}
        self._tangents = {}  # direction count -> RolloutTangent (jvp)
        self.capture = bool(capture)
        self._taped = TapedSegment(m, self.solver, self._parameter_arrays(), self.checkpoint_steps, capture=capture)
        self._inputs: RolloutInputs | None = None  # the last forward's, all worlds in the kernels' layout
        self._checkpoints: list[Checkpoint] = []

    # ------------------------------------------------------------------ inputs
    @property
    def default_inputs(self) -> dict[str, np.ndarray]:
        """The values the optional inputs (``OPTIONAL_INPUT_FIELDS``) take when None: the
        strings' rest state (straight from bar to body point, at rest); world 0's."""
        return self._world_defaults(0)

    def _world_defaults(self, world: int) -> dict[str, np.ndarray]:
        rows = slice(world * self.input_shapes["particle_q0"][0], (world + 1) * self.input_shapes["particle_q0"][0])
        return {"particle_q0": self._rest.particle_q[rows].copy(), "particle_qd0": self._rest.particle_qd[rows].copy()}

    def scene_inputs(self, t0: float = 0.0) -> RolloutInputs | list[RolloutInputs]:
        """The scene's own inputs: its bar trajectories from ``t0`` [s], its constants, its rest state
        (a batched model: a list, one per world, each from its own scene)."""
        m = self.model
        times = float(t0) + m.string_dt * np.arange(1, self.string_steps + 1)
        top_q, bar_q, bar_qd = bar_inputs(m, times)
        flat = RolloutInputs(top_q=top_q, bar_q=bar_q, bar_qd=bar_qd,
                             tie_stiffness=self._scene_constants[0].copy(), tie_damping=self._scene_constants[1].copy(),
                             string_stiffness=self._scene_constants[2].copy(), joint_q0=m.q_initial_worlds.copy(),
                             joint_qd0=np.zeros((self.world_count, m.puppet.qd_count)),
                             particle_q0=self._rest.particle_q.copy(), particle_qd0=self._rest.particle_qd.copy())
        worlds = self._split_inputs(flat)
        return worlds[0] if self.world_count == 1 else worlds

    def check_inputs(self, inputs: RolloutInputs, world: int = 0) -> RolloutInputs:
        """Validated float64 copies of world ``world``'s ``inputs`` (raises ``ValueError`` naming the field)."""
        if not isinstance(inputs, RolloutInputs):
            raise TypeError(f"inputs: got {type(inputs).__name__}; expected a RolloutInputs")
        where = "RolloutInputs" if self.world_count == 1 else f"world {world}: RolloutInputs"
        values = {}
        defaults = self._world_defaults(world)
        for name in INPUT_FIELDS:
            if name in defaults and getattr(inputs, name) is None:
                values[name] = defaults[name]
                continue
            values[name] = _checked(f"{where}.{name}", getattr(inputs, name), self.input_shapes[name])
        tied = self.model.string_point >= 0
        names = self.model.scene.strings
        for i, spec in enumerate(names):
            name = spec.name
            k, k_d, k_s = (float(values[f][i]) for f in ("tie_stiffness", "tie_damping", "string_stiffness"))
            if tied[i] and not k > 0.0:
                raise ValueError(f"{where}.tie_stiffness[{i}] (string {name!r}): got {k}; expected > 0 N/m "
                                 "for a string tied to a body point (the coupling divides by it)")
            if not k_d >= 0.0:
                raise ValueError(f"{where}.tie_damping[{i}] (string {name!r}): got {k_d}; expected >= 0 N s/m")
            if not k_s > 0.0:
                raise ValueError(f"{where}.string_stiffness[{i}] (string {name!r}): got {k_s}; "
                                 "expected > 0 N/m")
        return RolloutInputs(**values)

    def _worlds(self, value, what: str) -> tuple[list, bool]:
        """``value`` as one item per world, and whether it came as one world's (not a list)."""
        if self.world_count == 1 and not isinstance(value, (list, tuple)):
            return [value], True
        if not isinstance(value, (list, tuple)) or len(value) != self.world_count:
            got = f"a list of {len(value)}" if isinstance(value, (list, tuple)) else type(value).__name__
            raise ValueError(f"{what}: got {got}; expected a list of {self.world_count} (one per world)")
        return list(value), False

    def _join_inputs(self, worlds: list[RolloutInputs]) -> RolloutInputs:
        return RolloutInputs(**{name: _join([getattr(x, name) for x in worlds], _WORLD_AXIS[name])
                                for name in INPUT_FIELDS})

    def _split_inputs(self, flat: RolloutInputs) -> list[RolloutInputs]:
        parts = {name: _split(getattr(flat, name), _WORLD_AXIS[name], self.world_count) for name in INPUT_FIELDS}
        return [RolloutInputs(**{name: parts[name][w] for name in INPUT_FIELDS}) for w in range(self.world_count)]

    def set_constants(self, inputs: RolloutInputs) -> None:
        m = self.model
        s, pup = m.strings, m.puppet
        upload_values(s.string_tie_stiffness, inputs.tie_stiffness)
        upload_values(s.string_tie_damping, inputs.tie_damping)
        upload_values(s.string_stiffness, inputs.string_stiffness * self.segments_per_string)
        if len(m.spring_string):
            springs = self._spring_strings()
            upload_values(pup.spring_stiffness, inputs.tie_stiffness[springs])
            upload_values(pup.spring_damping, inputs.tie_damping[springs])

    def _spring_strings(self) -> np.ndarray:
        """The string (all worlds' numbering) of each entry of the puppet's spring constants."""
        m = self.model
        if m.puppet.spring_worlds == 1:
            return m.spring_string
        return (m.spring_string[None] + m.strings_per_world * np.arange(self.world_count)[:, None]).reshape(-1)

    def start_state(self, inputs: RolloutInputs, tie_target0=None, tie_force0=None) -> Checkpoint:
        r = self._rest
        tie_target = r.tie_target.copy() if tie_target0 is None else tie_target0
        tie_force = np.zeros_like(r.tie_force) if tie_force0 is None else tie_force0
        return Checkpoint(inputs.particle_q0.copy(), inputs.particle_qd0.copy(), inputs.joint_q0.copy(),
                          inputs.joint_qd0.copy(), tie_target, tie_force)

    def _start_arrays(self, tie_target0, tie_force0) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``forward``'s ``tie_target0`` and ``tie_force0`` (each world's, checked) in the kernels' layout."""
        per_world, n = self.model.strings_per_world, self.model.substeps
        joined = []
        for name, value, shape, axis in (("tie_target0", tie_target0, (per_world, 3), 0),
                                         ("tie_force0", tie_force0, (n, per_world, 3), 1)):
            if value is None:
                joined.append(None)
                continue
            worlds, _ = self._worlds(value, name)
            label = (lambda w: name) if self.world_count == 1 else (lambda w: f"{name}[{w}]")
            joined.append(_join([_checked(label(w), v, shape) for w, v in enumerate(worlds)], ("concat", axis)))
        return joined[0], joined[1]

    # ------------------------------------------------------------------ forward
    def _chunk(self, steps: int) -> _PlainChunk:
        if steps not in self._chunks:
            self._chunks[steps] = _PlainChunk(self, steps, self.capture)
        return self._chunks[steps]

    def forward(self, inputs: RolloutInputs | list[RolloutInputs], *, tie_target0=None,
                tie_force0=None) -> RolloutOutputs | list[RolloutOutputs]:
        """Runs the rollout without a tape, keeping the checkpoints; returns all outputs.

        ``inputs``: a :class:`RolloutInputs`, or for a batched model a list of one per world
        (then the outputs are a list too, and so are ``tie_target0`` and ``tie_force0``).

        ``tie_target0`` (the tie targets [m], ``(S, 3)``) and ``tie_force0`` (the previous puppet
        step's tie forces [N], ``(n, S, 3)``) complete a start state taken mid-motion (a
        multiple-shooting window, ``fitting.calibration_windows``); default: the scene's rest tie
        points and no force, as at the start of a session. They are constants: :meth:`backward`
        returns no gradient for them.
        """
        worlds, single = self._worlds(inputs, "inputs")
        inputs = self._join_inputs([self.check_inputs(x, w) for w, x in enumerate(worlds)])
        tie_target0, tie_force0 = self._start_arrays(tie_target0, tie_force0)
        m = self.model
        self.set_constants(inputs)
        shapes = self._flat_outputs
        out = {name: np.zeros(shape) for name, shape in shapes.items()}
        n = m.substeps
        checkpoints = []
        start = self.start_state(inputs, tie_target0, tie_force0)
        start.load(self.state)
        for a, b in self.segments:
            checkpoints.append(Checkpoint.of(self.state))
            chunk = self._chunk(b - a)
            for k, control in enumerate(chunk.controls):
                rows = slice((a + k) * n, (a + k + 1) * n)
                upload_values(control.top_q, inputs.top_q[rows])
                upload_values(control.bar_q, inputs.bar_q[rows])
                upload_values(control.bar_qd, inputs.bar_qd[rows])
            chunk.run()
            out["joint_q"][a:b] = chunk.joint_q.numpy()
            out["point_pos"][a:b] = chunk.point_pos.numpy()
            out["body_pos"][a:b] = chunk.body_pos.numpy()
            out["body_rot"][a:b] = chunk.body_rot.numpy()
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                out[name][a * n:b * n] = getattr(chunk, name).numpy().reshape(-1, *shapes[name][1:])
        # The last row: the final state's pose and points.
        p = self.puppet_steps
        point_q, _ = m.eval_world_points(self.state.puppet)  # fills the body poses too
        out["joint_q"][p] = self.state.puppet.joint_q.numpy()
        out["point_pos"][p] = point_q
        out["body_pos"][p] = self.state.puppet.body_pos.numpy()
        out["body_rot"][p] = self.state.puppet.body_rot.numpy()
        self._inputs = inputs
        self._checkpoints = checkpoints
        parts = {name: _split(value, _WORLD_AXIS[name], self.world_count) for name, value in out.items()}
        outputs = [RolloutOutputs(**{name: parts[name][w] for name in OUTPUT_FIELDS}) for w in range(self.world_count)]
        return outputs[0] if single else outputs

    @property
    def last_inputs(self) -> RolloutInputs | list[RolloutInputs] | None:
        """The inputs of the last :meth:`forward` (what :meth:`backward` differentiates), or None
        (a batched model: one per world)."""
        if self._inputs is None:
            return None
        worlds = self._split_inputs(self._inputs)
        return worlds[0] if self.world_count == 1 else worlds

    # ------------------------------------------------------------------ backward
    def backward(self, cotangents: dict[str, np.ndarray] | list[dict[str, np.ndarray]]
                 ) -> RolloutInputs | list[RolloutInputs]:
        """Gradients of ``L`` with respect to the inputs of the last :meth:`forward`.

        Args:
            cotangents: ``dL/d output`` for any subset of :class:`RolloutOutputs` field names,
                each of that output's shape (missing outputs: zero); a batched model: a list
                of one such dict per world.

        Returns:
            ``dL/d input`` for every field, with :class:`RolloutInputs` shapes (a batched
            model: a list, one per world).
        """
        if self._inputs is None:
            raise RuntimeError("MarionetteGradient.backward: call forward(inputs) first")
        worlds, single = self._worlds(cotangents, "cotangents")
        checked = []
        for w, given in enumerate(worlds):
            if not isinstance(given, dict):
                raise TypeError(f"cotangents: got {type(given).__name__}; expected a dict of output name -> array")
            where = "cotangents" if single else f"cotangents[{w}]"
            for name in given:
                if name not in self.output_shapes:
                    raise ValueError(f"{where}: unknown output {name!r}; expected some of {list(OUTPUT_FIELDS)}")
            checked.append({name: _checked(f"{where}[{name!r}]", value, self.output_shapes[name])
                            for name, value in given.items()})
        named = set().union(*checked)
        cot = {name: _join([c.get(name, np.zeros(self.output_shapes[name])) for c in checked], _WORLD_AXIS[name])
               for name in named}
        m = self.model
        self.set_constants(self._inputs)  # another engine on the same model may have run since
        params = self._parameter_arrays()
        for a in params:
            a.grad.zero_()
        grads = {name: np.zeros(np.shape(getattr(self._inputs, name))) for name in INPUT_FIELDS}
        for index in reversed(range(len(self.segments))):  # the state adjoint goes from one to the next
            a, b = self.segments[index]
            adjoint = self._taped.backward(self._checkpoints[index], self._inputs, a, b,
                                           last=b == self.puppet_steps, cotangents=cot, grads=grads)
        grads["joint_q0"] = adjoint.joint_q
        grads["joint_qd0"] = adjoint.joint_qd
        grads["particle_q0"] = adjoint.particle_q
        grads["particle_qd0"] = adjoint.particle_qd
        s, pup = m.strings, m.puppet
        k_grad = s.string_tie_stiffness.grad.numpy().copy()
        kd_grad = s.string_tie_damping.grad.numpy().copy()
        if len(m.spring_string):
            springs = self._spring_strings()
            np.add.at(k_grad, springs, pup.spring_stiffness.grad.numpy())
            np.add.at(kd_grad, springs, pup.spring_damping.grad.numpy())
        grads["tie_stiffness"] = k_grad
        grads["tie_damping"] = kd_grad
        grads["string_stiffness"] = s.string_stiffness.grad.numpy() * self.segments_per_string
        result = self._split_inputs(RolloutInputs(**grads))
        return result[0] if single else result

    # ------------------------------------------------------------------ forward mode
    def jvp(self, inputs: RolloutInputs, tangents: dict[str, np.ndarray]
            ) -> tuple[RolloutOutputs, dict[str, np.ndarray]]:
        """The rollout at ``inputs`` and its directional derivatives along P directions at once
        (forward mode, :class:`~dmarionette.grad.rollout_tangent.RolloutTangent`; one world).

        Args:
            inputs: a :class:`RolloutInputs` (checked as :meth:`forward` checks it).
            tangents: input field name -> directions, ``(P, *input_shapes[name])``, for any subset of
                ``INPUT_FIELDS`` (missing: zero); every given field has the same ``P``.

        Returns:
            The outputs (as :meth:`forward`'s, which this does not replace: :meth:`backward` still
            differentiates the last :meth:`forward`) and every output's tangent, output name ->
            ``(P, *output_shapes[name])``.
        """
        if self.world_count != 1:
            raise ValueError(f"MarionetteGradient.jvp: a model of {self.world_count} worlds; the rollout JVP "
                             "runs one world (build one engine per world)")
        if not isinstance(tangents, dict) or not tangents:
            got = type(tangents).__name__ if not isinstance(tangents, dict) else "an empty dict"
            raise ValueError(f"tangents: got {got}; expected a dict of input name -> (P, *input shape) array")
        counts = {name: np.shape(value)[0] if np.ndim(value) else None for name, value in tangents.items()}
        direction_count = next(iter(counts.values()))
        if direction_count is None or direction_count < 1 or any(c != direction_count for c in counts.values()):
            raise ValueError(f"tangents: leading (direction) axes {counts}; expected the same P >= 1 for every field")
        inputs = self.check_inputs(inputs)
        for name in tangents:
            if name not in self.input_shapes:
                raise ValueError(f"tangents: unknown input {name!r}; expected some of {list(INPUT_FIELDS)}")
        checked = {name: _checked(f"tangents[{name!r}]", tangents[name], (direction_count, *shape))
                   if name in tangents else np.zeros((direction_count, *shape))
                   for name, shape in self.input_shapes.items()}
        if direction_count not in self._tangents:
            self._tangents[direction_count] = RolloutTangent(self, direction_count)
        out, dot = self._tangents[direction_count].jvp(inputs, checked)
        return RolloutOutputs(**out), dot

    def memory(self) -> dict[str, int]:
        """Bytes the engine holds for gradients: ``checkpoints`` (host, one per segment),
        ``tape`` (the planned taped segments' arrays and gradients: one per segment length
        used), ``outputs`` (the host outputs and input copies of the last forward)."""
        checkpoints = sum(sum(a.nbytes for a in vars(c).values()) for c in self._checkpoints)
        host = sum(np.asarray(getattr(self._inputs, k)).nbytes for k in INPUT_FIELDS) if self._inputs else 0
        host += sum(int(np.prod(s)) * 8 for s in self.output_shapes.values())
        return {"checkpoints": checkpoints, "tape": self._taped.nbytes, "outputs": host}

    def _keep_only_differentiated_gradients(self) -> None:
        """Drops the gradients of the model arrays no input maps to (masses, rest lengths,
        drag, ground and joint constants...): every adjoint kernel would otherwise
        accumulate into them too, atomically, at every string step (measured: the segment
        springs' reverse pass cost 6x their forward with them, 2.7x without)."""
        kept = {id(a) for a in self._parameter_arrays()}
        for owner in (self.model.strings, self.model.puppet):
            for value in vars(owner).values():
                if isinstance(value, wp.array) and value.requires_grad and id(value) not in kept:
                    value.requires_grad = False
        self.model.strings.refresh_arrays()  # the kernels' struct of the string arrays, with their gradients now

    def _parameter_arrays(self) -> list[wp.array]:
        s, pup = self.model.strings, self.model.puppet
        arrays = [s.string_tie_stiffness, s.string_tie_damping, s.string_stiffness]
        if len(self.model.spring_string):
            arrays += [pup.spring_stiffness, pup.spring_damping]
        return arrays


# How each world's input or output joins the others' in the kernels' layout: strings, particles and
# bars world after world along an axis ("concat"), puppet arrays on a new world axis ("stack").
_WORLD_AXIS = {
    "top_q": ("concat", 1), "bar_q": ("concat", 1), "bar_qd": ("concat", 1),
    "tie_stiffness": ("concat", 0), "tie_damping": ("concat", 0), "string_stiffness": ("concat", 0),
    "particle_q0": ("concat", 0), "particle_qd0": ("concat", 0),
    "joint_q0": ("stack", 0), "joint_qd0": ("stack", 0),
    "joint_q": ("stack", 1), "point_pos": ("stack", 1), "body_pos": ("stack", 1), "body_rot": ("stack", 1),
    "tie_force": ("concat", 1), "bar_feedback": ("concat", 1), "bar_reaction": ("concat", 1),
}


def _join(values: list[np.ndarray], how: tuple[str, int]) -> np.ndarray:
    kind, axis = how
    return np.stack(values, axis=axis) if kind == "stack" else np.concatenate(values, axis=axis)


def _split(value: np.ndarray, how: tuple[str, int], worlds: int) -> list[np.ndarray]:
    kind, axis = how
    if kind == "stack":
        return [np.take(value, w, axis=axis) for w in range(worlds)]
    return [part.copy() for part in np.split(value, worlds, axis=axis)]


def _joined_shape(shape: tuple[int, ...], how: tuple[str, int], worlds: int) -> tuple[int, ...]:
    kind, axis = how
    if kind == "stack":
        return shape[:axis] + (worlds,) + shape[axis:]
    return shape[:axis] + (shape[axis] * worlds,) + shape[axis + 1:]


def _checked(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite values, else a ``ValueError`` naming it."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {type(value).__name__}; expected a float array of shape {shape}") from None
    if array.shape != tuple(shape):
        raise ValueError(f"{name}: got shape {array.shape}; expected {tuple(shape)}")
    if not np.all(np.isfinite(array)):
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ValueError(f"{name}: non-finite value {array[tuple(bad)]} at index {tuple(int(i) for i in bad)}; "
                         "expected finite values")
    return array.copy()
