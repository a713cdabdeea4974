"""Forward-mode sensitivities (JVPs) of whole marionette rollouts, P directions at once.

:class:`RolloutTangent` runs the rollout of a :class:`~dmarionette.grad.engine.MarionetteGradient`
(its model, solver, rollout length and input/output layout) with
:class:`~dmarionette.grad.marionette_tangent.MarionetteTangent` puppet step by puppet step: the
state and its P tangents are carried along, so no checkpoint or tape is needed (the memory is
two states and two tangent states, each step's control and its tangents, and the outputs). The
rollout's launches are captured once as a Warp graph (``dmarionette.capture``, as the engine's
forward: without it the Python cost of the many small launches is most of the time, measured:
0.65 s against 0.13 s for 30 puppet steps, P = 4) and replayed per call, with the start state, the
controls, the constants and their directions written in between on the host. ``MarionetteGradient.jvp``
delegates here.

Each input field maps onto the step's tangents exactly as the reverse engine maps its gradient
(``grad/engine.py``'s module doc): ``top_q``, ``bar_q``, ``bar_qd`` per string step onto each
puppet step's control tangent; ``tie_stiffness``/``tie_damping`` onto both sides (the strings'
tie and the puppet's point springs: ``MarionetteConstantsTangent``); ``string_stiffness``, the
whole-string ``k``, onto the kernels' ``k_s = k (n - 1)`` (its direction times ``n - 1``);
``joint_q0``/``joint_qd0``, ``particle_q0``/``particle_qd0`` onto the start state's tangent. The
start's tie targets and previous tie forces are constants (as in :meth:`MarionetteGradient.forward`).

Outputs as :meth:`MarionetteGradient.forward` writes them: ``joint_q``, ``point_pos``,
``body_pos``, ``body_rot`` of every puppet state (rows 0..P; here from the tangent kinematics
pass of each state, the same primal as the solver's ``eval_body_points``), and ``tie_force``,
``bar_feedback``, ``bar_reaction`` after every string step.

One world only (a batched model is refused with a ValueError).

Checked (``tests/grad/test_rollout_jvp.py``, 1 s of ``hanging``): against the reverse engine by the
dot-product identity for every input group (measured 1e-15 relative), against central differences.
Cost (``python benchmarks/bench_gradients.py --seconds 1 --memory-seconds 0 --repeats 5 --jvp``,
CPU, two runs at load 0.7-0.9, stop 28): a 1 s rollout's JVP for P = 1, 4, 12, 16 directions takes
1.9, 2.9-3.0, 5.9-6.1, 7.2-7.3 captured forward rollouts (issue 13's target ``1 + 0.5 P``: 1.5, 3,
7, 9; missed at P = 1). This module's part of that (measured against the code before, same
session): the host writes every step's controls and their tangents as one array per field
(3.5-3.6, 5.2-5.4, 11.5-11.7, 14.7-15.2 -> 3.3-3.5, 4.9-5.0, 10.8-11.0, 13.6-14.1 forwards at the
time, together with the step's kept contact tangents). Where it goes
(``benchmarks/profile_tangent.py``; ``docs/gradients.md``, "Forward mode"): mostly the string
steps keeping their factorisation (about one forward) and their tangent kernels
(``kernels/string_step_tangent``, ``kernels/string_step_tangent_lanes``).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.capture import CapturedChunk
from dmarionette.grad.marionette_tangent import MarionetteTangent
from dmarionette.kernels.articulation_forces import eval_body_points
from dmarionette.kernels.kernel_tangent import UNROLL, tangent_kernel
from dmarionette.marionette.solver import MarionetteControl
from dmarionette.strings.rollout import upload_values

__all__ = ["RolloutTangent"]


class RolloutTangent:
    """JVPs of ``engine``'s rollout for ``direction_count`` directions (module doc).

    Args:
        engine: a :class:`~dmarionette.grad.engine.MarionetteGradient` of one world (its ``capture``
            choice: a captured graph, or the launches one by one, the same numbers).
        direction_count: P, the directions each :meth:`jvp` takes.
        optimization_level: C++ optimisation of the generated puppet tangent kernels.
    """

    def __init__(self, engine, direction_count: int, optimization_level: int = 2):
        m = engine.model
        if engine.world_count != 1:
            raise ValueError(f"MarionetteGradient.jvp: a model of {engine.world_count} worlds; the rollout JVP "
                             "runs one world (build one engine per world)")
        if not (isinstance(direction_count, (int, np.integer)) and direction_count >= 1):
            raise ValueError(f"direction_count: got {direction_count!r}; expected an integer >= 1")
        self.engine = engine
        self.model = m
        self.direction_count = P = int(direction_count)
        steps, n = engine.puppet_steps, m.substeps
        self.step = MarionetteTangent(engine.solver, P, optimization_level)
        self.states = [m.state(), m.state()]
        self.tangents = [self.step.tangent_state(), self.step.tangent_state()]
        self.controls = [MarionetteControl(m) for _ in range(steps)]
        self.control_tangents = [self.step.control_tangent() for _ in range(steps)]
        # every step's control field (and its tangent) one row of one array, so that :meth:`load` writes
        # each field once (one small write per step and field was most of the host's time: measured
        # 2.0-3.5 ms of a 30-step JVP, a quarter of a forward rollout)
        self._control_rows = _rows(self.controls, _CONTROL_FIELDS, m.device, axis=0)
        self._tangent_rows = _rows(self.control_tangents, _CONTROL_FIELDS, m.device, axis=1)  # (P, steps, ...)
        self.constants = self.step.constants_tangent()
        points, bodies, q = len(m.puppet.point_names), m.puppet.body_count, m.puppet.q_count
        s, b = m.strings.string_count, m.bar_rows
        self.kinematics = m.puppet.kinematics(1)
        self.body = self.step.puppet.body_tangents()
        with wp.ScopedDevice(m.device):
            self.point_q = wp.zeros((1, points), dtype=wp.vec3d)
            self.point_qd = wp.zeros((1, points), dtype=wp.vec3d)
            self.point_q_dot = wp.zeros((P, 1, points), dtype=wp.vec3d)
            self.point_qd_dot = wp.zeros((P, 1, points), dtype=wp.vec3d)
            # every output (primal, and tangents with P after the step axis), written by the graph
            self.out = {"joint_q": wp.zeros((steps + 1, 1, q), dtype=wp.float64),
                        "point_pos": wp.zeros((steps + 1, 1, points), dtype=wp.vec3d),
                        "body_pos": wp.zeros((steps + 1, 1, bodies), dtype=wp.vec3d),
                        "body_rot": wp.zeros((steps + 1, 1, bodies), dtype=wp.quatd),
                        **{k: wp.zeros((steps, n, max(c, 1)), dtype=wp.vec3d)
                           for k, c in (("tie_force", s), ("bar_feedback", b), ("bar_reaction", b))}}
            self.dot = {k: wp.zeros((a.shape[0], P, *a.shape[1:]), dtype=a.dtype) for k, a in self.out.items()}
        self._points = tangent_kernel(eval_body_points, unroll=UNROLL)
        self._chunk: CapturedChunk | None = None  # built at the first jvp (its warm-up needs real inputs)

    def jvp(self, inputs, tangents: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The rollout's outputs at ``inputs`` (a checked, one-world ``RolloutInputs``) and their
        tangents along ``tangents`` (every input field, ``(P, *input_shape)``, checked by
        ``MarionetteGradient.jvp``): two dicts, output name ->
        the output's shape, and ``(P, *shape)``. :meth:`load`, then the captured :meth:`launch`, then
        :meth:`read`."""
        self.load(inputs, tangents)
        if self._chunk is None:
            self._chunk = CapturedChunk(self.launch, self.model.device, capture=self.engine.capture)
            self._start(inputs, tangents)  # the warm-up ran the rollout from the start state
        self._chunk.run()
        return self.read()

    def load(self, inputs, tangents: dict[str, np.ndarray]) -> None:
        """The host's part before the launches: the constants, every step's control and their tangents,
        the start state and its tangent written into the arrays :meth:`launch` reads (arguments as
        :meth:`jvp`'s)."""
        e, P = self.engine, self.direction_count
        e.set_constants(inputs)
        c = self.constants
        upload_values(c.tie_stiffness, tangents["tie_stiffness"])
        upload_values(c.tie_damping, tangents["tie_damping"])
        upload_values(c.string_stiffness, tangents["string_stiffness"] * e.segments_per_string)
        self.step.spread_constants(c)
        steps = e.puppet_steps
        for name in _CONTROL_FIELDS:
            value, dot = getattr(inputs, name), tangents[name]
            if value.size:
                upload_values(self._control_rows[name], value.reshape(steps, -1, *value.shape[1:]))
                upload_values(self._tangent_rows[name], dot.reshape(P, steps, -1, *dot.shape[2:]))
        self._start(inputs, tangents)

    def read(self) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The host's part after the launches: the outputs and their tangents (as :meth:`jvp` returns
        them) copied from the arrays :meth:`launch` wrote."""
        e, P = self.engine, self.direction_count
        out = {k: a.numpy().copy() for k, a in self.out.items()}  # not views of what the next call overwrites
        dot = {k: np.moveaxis(a.numpy(), 1, 0).copy() for k, a in self.dot.items()}
        out = {k: out[k][:, 0] if k in _POSES else v.reshape(e.output_shapes[k]) for k, v in out.items()}
        dot = {k: dot[k][:, :, 0] if k in _POSES else v.reshape(P, *e.output_shapes[k]) for k, v in dot.items()}
        return out, dot

    def _start(self, inputs, tangents: dict[str, np.ndarray]) -> None:
        """The start state and its tangent into ``states[0]``, ``tangents[0]``."""
        self.engine.start_state(inputs).load(self.states[0])
        t = self.tangents[0]
        for a in (t.tie_force, t.tie_target, t.bar_feedback, t.bar_reaction, t.puppet.joint_qdd):
            a.zero_()
        upload_values(t.puppet.joint_q, tangents["joint_q0"][:, None])
        upload_values(t.puppet.joint_qd, tangents["joint_qd0"][:, None])
        upload_values(t.particle_q, tangents["particle_q0"])
        upload_values(t.particle_qd, tangents["particle_qd0"])

    def launch(self) -> None:
        """The rollout's launches, and nothing of the host's (what :meth:`jvp` captures once as a graph
        and replays): the steps between the two states in turn, each output copied into its row.
        Starts from what the last :meth:`load` wrote; its outputs are read by :meth:`read`. Public for
        profilers (``benchmarks/profile_tangent.py`` captures groups of these launches on their own)."""
        state, spare = self.states
        t, t_spare = self.tangents
        for k in range(self.engine.puppet_steps):
            self._pose(state, t, k)
            self.step.step(state, t, spare, t_spare, self.controls[k], self.control_tangents[k], spread=False)
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                wp.copy(self.out[name][k], getattr(spare, name))
                wp.copy(self.dot[name][k], getattr(t_spare, name))
            state, spare, t, t_spare = spare, state, t_spare, t
        self._pose(state, t, self.engine.puppet_steps)

    def _pose(self, state, t, k: int) -> None:
        """Row ``k`` of the pose outputs (``joint_q``, points, body poses) of ``state`` and their tangents."""
        m, P, kin, tb = self.model, self.direction_count, self.kinematics, self.body
        self.step.puppet.eval_kinematics(state.puppet, t.puppet, kin, tb)
        self._points.launch((1, len(m.puppet.point_names)), P,
                            [m.puppet.point_body, m.puppet.point_local, kin.body_pos, kin.body_rot, kin.body_w,
                             kin.body_v, self.point_q, self.point_qd],
                            {**{name: tb[name] for name in ("body_pos", "body_rot", "body_w", "body_v")},
                             "point_pos": self.point_q_dot, "point_vel": self.point_qd_dot}, m.device)
        for name, value, tangent in (("joint_q", state.puppet.joint_q, t.puppet.joint_q),
                                     ("point_pos", self.point_q, self.point_q_dot),
                                     ("body_pos", kin.body_pos, tb["body_pos"]),
                                     ("body_rot", kin.body_rot, tb["body_rot"])):
            wp.copy(self.out[name][k], value)
            wp.copy(self.dot[name][k], tangent)


# The pose outputs, held with a world axis of one (``(rows, 1, ...)``).
_POSES = ("joint_q", "point_pos", "body_pos", "body_rot")
# The control fields (of ``MarionetteControl`` and ``MarionetteControlTangent``), one row per string step.
_CONTROL_FIELDS = ("top_q", "bar_q", "bar_qd")


def _rows(controls: list, fields: tuple[str, ...], device, axis: int) -> dict[str, wp.array]:
    """Each field of ``controls`` (one per puppet step) made a view of one array with a step axis at
    ``axis`` (0: ``(steps, *field shape)``, each step's field contiguous; 1: ``(P, steps, ...)`` for
    tangents ``(P, ...)``, the layout of the host's directions, each step's a strided view); returns the
    arrays by field."""
    rows = {}
    for name in fields:
        first = getattr(controls[0], name)
        shape = list(first.shape)
        shape.insert(axis, len(controls))
        rows[name] = wp.zeros(tuple(shape), dtype=first.dtype, device=device)
        for k, control in enumerate(controls):
            setattr(control, name, rows[name][k] if axis == 0 else rows[name][:, k])
    return rows
