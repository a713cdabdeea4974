"""Marionette rollouts without per-step Python overhead, and the simulate driver.

:class:`MarionetteRollout` captures ``K`` puppet steps (``K n`` string steps, about one
picture frame: ``K = round(frame_period / puppet_dt)``) as one Warp graph and replays it;
bar inputs for the chunk are written into the captured control buffers before each
replay, and per-step outputs are copied out after it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
import warp as wp
from tqdm import tqdm

from dmarionette.capture import CapturedChunk, ping_pong
from dmarionette.marionette.solver import MarionetteControl, MarionetteModel, MarionetteState, SolverMarionette, bar_inputs

__all__ = ["MarionetteRollout", "MarionetteTrajectory", "simulate_marionette", "simulate_worlds"]


@dataclasses.dataclass
class MarionetteTrajectory:
    """A simulated marionette (the contents of a trajectory file, docs/trajectory.md).

    Frame arrays (``F`` frames; frame 0 is the initial state): ``frame_time`` [s] ``(F,)``,
    ``particle_q`` [m] ``(F, P, 3)``, ``joint_q`` ``(F, q_count)``, ``body_pos`` [m]
    ``(F, bodies, 3)``, ``body_rot`` (Warp quaternions x, y, z, w) ``(F, bodies, 4)``,
    ``bar_pos`` [m] ``(F, B, 3)``, ``bar_rot`` ``(F, B, 3, 3)``, ``top_q`` [m] ``(F, S, 3)``.
    String-step arrays (``T`` steps): ``step_time`` [s], ``tie_force`` [N] ``(T, S, 3)``,
    ``string_taut`` ``(T, S)``, ``bar_feedback`` and ``bar_reaction`` [N] ``(T, B, 3)``.
    """

    frame_time: np.ndarray
    particle_q: np.ndarray
    joint_q: np.ndarray
    body_pos: np.ndarray
    body_rot: np.ndarray
    bar_pos: np.ndarray
    bar_rot: np.ndarray
    top_q: np.ndarray
    step_time: np.ndarray
    tie_force: np.ndarray
    string_taut: np.ndarray
    bar_feedback: np.ndarray
    bar_reaction: np.ndarray
    string_names: list[str]
    string_start: np.ndarray
    string_rest_length: np.ndarray
    body_names: list[str]
    body_shape: list
    bar_names: list[str]
    string_dt: float
    puppet_dt: float
    frame_steps: int
    wall_seconds: float


class MarionetteRollout:
    """Replays captured chunks of ``chunk_steps`` puppet steps.

    Args:
        solver: the marionette stepper.
        chunk_steps: puppet steps per replay (one picture frame each replay).
    """

    def __init__(self, solver: SolverMarionette, chunk_steps: int):
        if chunk_steps < 1:
            raise ValueError(f"chunk_steps: got {chunk_steps}; expected an integer >= 1")
        self.solver = solver
        self.model: MarionetteModel = solver.model
        self.chunk_steps = int(chunk_steps)
        m = self.model
        self._controls = [MarionetteControl(m) for _ in range(self.chunk_steps)]
        self._state = m.state()
        self._spare = m.state()
        k, n, s, b = self.chunk_steps, m.substeps, m.strings.string_count, m.bar_rows * m.world_count
        with wp.ScopedDevice(m.device):
            self._tie_force = wp.zeros((k, n, s), dtype=wp.vec3d)
            self._taut = wp.zeros((k, n, s), dtype=wp.int32)
            self._feedback = wp.zeros((k, n, b), dtype=wp.vec3d)
            self._reaction = wp.zeros((k, n, b), dtype=wp.vec3d)
        self._chunk = CapturedChunk(self._launch, m.device, warm_up=self._warm_up)
        # Host views of the captured buffers, made once: ``wp.array.numpy()`` costs a few µs a call,
        # which at 33 puppet steps per chunk was a third of a fully coupled (1 kHz) rollout's time.
        self._control_views = [(c.top_q.numpy(), c.bar_q.numpy(), c.bar_qd.numpy()) for c in self._controls]
        self._output_views = {"tie_force": self._tie_force.numpy(), "string_taut": self._taut.numpy(),
                              "bar_feedback": self._feedback.numpy(), "bar_reaction": self._reaction.numpy()}

    def _launch(self) -> None:
        ping_pong(self._step, self._state, self._spare, self.chunk_steps)

    def _step(self, k: int, state_in: MarionetteState, state_out: MarionetteState) -> None:
        self.solver.step(state_in, state_out, self._controls[k])
        wp.copy(self._tie_force[k], state_out.tie_force)
        wp.copy(self._taut[k], state_out.string_taut)
        wp.copy(self._feedback[k], state_out.bar_feedback)
        wp.copy(self._reaction[k], state_out.bar_reaction)

    def _warm_up(self) -> None:
        # One eager step loads every module before capture begins.
        self.solver.step(self._state, self._spare, self._controls[0])
        self._state.assign(self.model.state())

    def run(self, state: MarionetteState, t0: float, chunks: int,
            on_chunk: Callable[[int, MarionetteState], None] | None = None) -> dict[str, np.ndarray]:
        """Advances ``state`` in place by ``chunks * chunk_steps`` puppet steps from time ``t0``.

        ``on_chunk(i, state)`` is called after each chunk (to record a frame). Returns the
        per-string-step outputs (``tie_force``, ``string_taut``, ``bar_feedback``, ``bar_reaction``).
        """
        m = self.model
        n, k = m.substeps, self.chunk_steps
        per_chunk = k * n
        outputs = {name: [] for name in self._output_views}
        self._state.assign(state)
        # The bars' inputs for the whole rollout, evaluated at once (vectorised spline evaluation).
        all_tops, all_bar_q, all_bar_qd = bar_inputs(m, t0 + m.string_dt * np.arange(1, chunks * per_chunk + 1))
        for c in range(chunks):
            for i, (top_q, bar_q, bar_qd) in enumerate(self._control_views):
                rows = slice(c * per_chunk + i * n, c * per_chunk + (i + 1) * n)
                top_q[...] = all_tops[rows]
                bar_q[...] = all_bar_q[rows]
                bar_qd[...] = all_bar_qd[rows]
            self._chunk.run()
            # The views share the buffers: copy before the next replay overwrites them.
            for name, view in self._output_views.items():
                outputs[name].append(view.reshape(per_chunk, *view.shape[2:]).copy())
            if on_chunk is not None:
                on_chunk(c, self._state)
        state.assign(self._state)
        return {name: np.concatenate(values) for name, values in outputs.items()}


def _frame(model: MarionetteModel, state: MarionetteState) -> tuple[np.ndarray, ...]:
    """One frame of every world: particles ``(W P, 3)``, joint coordinates, body poses ``(W, ...)``."""
    model.puppet_solver.eval_kinematics(state.puppet)
    # String particles as float64 on the host whatever the strings' precision (a copy either way).
    return (state.strings.particle_q.numpy().astype(np.float64), state.puppet.joint_q.numpy().copy(),
            state.puppet.body_pos.numpy().copy(), state.puppet.body_rot.numpy().copy())


def simulate_marionette(model: MarionetteModel, duration: float, *, progress: bool = True,
                        frame_hz: float = 30.0) -> MarionetteTrajectory:
    """Simulates ``duration`` seconds from the rest state, keeping frames at about ``frame_hz``
    (one world; :func:`simulate_worlds` runs a batched model)."""
    if model.world_count != 1:
        raise ValueError(f"simulate_marionette: the model has {model.world_count} worlds; use simulate_worlds")
    return simulate_worlds(model, duration, progress=progress, frame_hz=frame_hz)[0]


def simulate_worlds(model: MarionetteModel, duration: float, *, progress: bool = True,
                    frame_hz: float = 30.0) -> list[MarionetteTrajectory]:
    """Simulates every world of ``model`` for ``duration`` seconds from its rest state in the same
    launches; one trajectory per world (``wall_seconds``: the batch's, shared)."""
    if not duration > 0.0:
        raise ValueError(f"duration: got {duration}; expected a positive number of seconds")
    chunk = max(1, round(1.0 / (frame_hz * model.puppet_dt)))
    rollout = MarionetteRollout(SolverMarionette(model), chunk)
    frame_steps = chunk * model.substeps
    chunks = max(1, int(np.ceil(duration / (frame_steps * model.string_dt))))
    state = model.state()
    frames = [_frame(model, state)]
    name = model.scene.name if model.world_count == 1 else f"{model.scene.name} x {model.world_count} worlds"
    with tqdm(total=chunks * frame_steps, unit="step", disable=not progress, desc=name) as bar:
        def record(c, s):
            frames.append(_frame(model, s))
            bar.update(frame_steps)

        start = time.perf_counter()
        outputs = rollout.run(state, 0.0, chunks, on_chunk=record)
        wall = time.perf_counter() - start
    frame_time = frame_steps * model.string_dt * np.arange(chunks + 1)
    particle_q, joint_q, body_pos, body_rot = (np.stack(a) for a in zip(*frames))
    tops = bar_inputs(model, frame_time)[0]
    steps = chunks * frame_steps
    strings = model.strings
    per_world, rows, particles = model.strings_per_world, model.bar_rows, strings.particle_count // model.world_count
    rest_length = strings.string_rest_length.numpy().astype(np.float64)
    trajectories = []
    for w, scene in enumerate(model.world_scenes):
        ss, bb, pp = (slice(w * x, (w + 1) * x) for x in (per_world, rows, particles))
        bar_pos = np.zeros((len(frame_time), rows, 3))
        bar_rot = np.tile(np.eye(3), (len(frame_time), rows, 1, 1))
        for b, bar in enumerate(scene.bars):
            bar_pos[:, b], _, bar_rot[:, b] = bar.trajectory.pose(frame_time)
        trajectories.append(MarionetteTrajectory(
            frame_time=frame_time, particle_q=particle_q[:, pp], joint_q=joint_q[:, w], body_pos=body_pos[:, w],
            body_rot=body_rot[:, w], bar_pos=bar_pos, bar_rot=bar_rot, top_q=tops[:, ss],
            step_time=model.string_dt * np.arange(1, steps + 1),
            string_names=list(strings.string_names[ss]), string_start=strings.string_start_np[:per_world + 1].copy(),
            string_rest_length=rest_length[ss].copy(),
            body_names=list(model.puppet.body_names), body_shape=list(model.puppet.body_shape),
            bar_names=list(model.bar_names), string_dt=model.string_dt, puppet_dt=model.puppet_dt,
            frame_steps=frame_steps, wall_seconds=wall,
            tie_force=outputs["tie_force"][:, ss], string_taut=outputs["string_taut"][:, ss],
            bar_feedback=outputs["bar_feedback"][:, bb], bar_reaction=outputs["bar_reaction"][:, bb]))
    return trajectories
