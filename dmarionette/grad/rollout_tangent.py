"""Forward-mode sensitivities (JVPs) of whole marionette rollouts, P directions at once.

:class:`RolloutTangent` runs the rollout of a :class:`~dmarionette.grad.engine.MarionetteGradient`
(its model, solver, rollout length and input/output layout) with
:class:`~dmarionette.grad.marionette_tangent.MarionetteTangent` puppet step by puppet step: the
state and its P tangents are carried along, so no checkpoint or tape is needed (the memory is
two states and two tangent states, plus the host outputs). ``MarionetteGradient.jvp`` delegates
here.

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
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.grad.engine import INPUT_FIELDS, _checked
from dmarionette.grad.marionette_tangent import MarionetteTangent
from dmarionette.kernels.articulation_forces import eval_body_points
from dmarionette.kernels.kernel_tangent import tangent_kernel
from dmarionette.marionette.solver import MarionetteControl
from dmarionette.strings.rollout import upload_values

__all__ = ["RolloutTangent"]


class RolloutTangent:
    """JVPs of ``engine``'s rollout for ``direction_count`` directions (module doc).

    Args:
        engine: a :class:`~dmarionette.grad.engine.MarionetteGradient` of one world.
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
        self.step = MarionetteTangent(engine.solver, P, optimization_level)
        self.states = [m.state(), m.state()]
        self.tangents = [self.step.tangent_state(), self.step.tangent_state()]
        self.control = MarionetteControl(m)
        self.control_tangent = self.step.control_tangent()
        self.constants = self.step.constants_tangent()
        points = len(m.puppet.point_names)
        self.kinematics = m.puppet.kinematics(1)
        self.body = self.step.puppet.body_tangents()
        with wp.ScopedDevice(m.device):
            self.point_q = wp.zeros((1, points), dtype=wp.vec3d)
            self.point_qd = wp.zeros((1, points), dtype=wp.vec3d)
            self.point_q_dot = wp.zeros((P, 1, points), dtype=wp.vec3d)
            self.point_qd_dot = wp.zeros((P, 1, points), dtype=wp.vec3d)
        self._points = tangent_kernel(eval_body_points)

    def check_tangents(self, tangents) -> dict[str, np.ndarray]:
        """``tangents`` (input field -> ``(P, *input_shape)``) checked; missing fields are zero."""
        e, P = self.engine, self.direction_count
        if not isinstance(tangents, dict):
            raise TypeError(f"tangents: got {type(tangents).__name__}; expected a dict of input name -> array")
        out = {}
        for name, value in tangents.items():
            if name not in e.input_shapes:
                raise ValueError(f"tangents: unknown input {name!r}; expected some of {list(INPUT_FIELDS)}")
            out[name] = _checked(f"tangents[{name!r}]", value, (P, *e.input_shapes[name]))
        return {name: out.get(name, np.zeros((P, *e.input_shapes[name]))) for name in INPUT_FIELDS}

    def jvp(self, inputs, tangents: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The rollout's outputs at ``inputs`` (a checked, one-world ``RolloutInputs``) and their
        tangents along ``tangents`` (checked by :meth:`check_tangents`): two dicts, output name ->
        the output's shape, and ``(P, *shape)``."""
        e, m, P, n = self.engine, self.model, self.direction_count, self.model.substeps
        e._set_constants(inputs)
        c = self.constants
        c.tie_stiffness.assign(tangents["tie_stiffness"])
        c.tie_damping.assign(tangents["tie_damping"])
        c.string_stiffness.assign(tangents["string_stiffness"] * e._segments_per_string)
        out = {name: np.zeros(shape) for name, shape in e.output_shapes.items()}
        dot = {name: np.zeros((P, *shape)) for name, shape in e.output_shapes.items()}
        state, spare = self.states
        e._start_state(inputs).load(state)
        t, t_spare = self.tangents
        for a in vars(t).values():
            if isinstance(a, wp.array):
                a.zero_()
        t.puppet.joint_q.assign(tangents["joint_q0"][:, None])
        t.puppet.joint_qd.assign(tangents["joint_qd0"][:, None])
        t.puppet.joint_qdd.zero_()
        t.particle_q.assign(tangents["particle_q0"])
        t.particle_qd.assign(tangents["particle_qd0"])
        tc = self.control_tangent
        for k in range(e.puppet_steps):
            rows = slice(k * n, (k + 1) * n)
            upload_values(self.control.top_q, inputs.top_q[rows])
            upload_values(self.control.bar_q, inputs.bar_q[rows])
            upload_values(self.control.bar_qd, inputs.bar_qd[rows])
            tc.top_q.assign(tangents["top_q"][:, rows])
            tc.bar_q.assign(tangents["bar_q"][:, rows])
            tc.bar_qd.assign(tangents["bar_qd"][:, rows])
            self._pose(state, t, k, out, dot)
            self.step.step(state, t, spare, t_spare, self.control, tc, c)
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                out[name][rows] = getattr(spare, name).numpy()
                dot[name][:, rows] = getattr(t_spare, name).numpy()
            state, spare, t, t_spare = spare, state, t_spare, t
        self._pose(state, t, e.puppet_steps, out, dot)
        return out, dot

    def _pose(self, state, t, k: int, out: dict, dot: dict) -> None:
        """Row ``k`` of the pose outputs (``joint_q``, points, body poses) of ``state`` and their tangents."""
        m, P, kin, tb = self.model, self.direction_count, self.kinematics, self.body
        self.step.puppet.eval_kinematics(state.puppet, t.puppet, kin, tb)
        self._points.launch((1, len(m.puppet.point_names)), P,
                            [m.puppet.point_body, m.puppet.point_local, kin.body_pos, kin.body_rot, kin.body_w,
                             kin.body_v, self.point_q, self.point_qd],
                            {**{name: tb[name] for name in ("body_pos", "body_rot", "body_w", "body_v")},
                             "point_pos": self.point_q_dot, "point_vel": self.point_qd_dot}, m.device)
        out["joint_q"][k] = state.puppet.joint_q.numpy()[0]
        dot["joint_q"][:, k] = t.puppet.joint_q.numpy()[:, 0]
        out["point_pos"][k] = self.point_q.numpy()[0]
        dot["point_pos"][:, k] = self.point_q_dot.numpy()[:, 0]
        out["body_pos"][k] = kin.body_pos.numpy()[0]
        dot["body_pos"][:, k] = tb["body_pos"].numpy()[:, 0]
        out["body_rot"][k] = kin.body_rot.numpy()[0]
        dot["body_rot"][:, k] = tb["body_rot"].numpy()[:, 0]
