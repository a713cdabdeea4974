"""Many string steps per Python call, without per-step Python overhead.

:class:`StringRollout` records ``chunk_steps`` consecutive steps once as a Warp graph
(CPU graph capture, Warp >= 1.19; a CUDA graph on a GPU) and replays it: each replay runs
the whole chunk in native code. Per-step inputs are read from ``(chunk_steps, S)``
buffers filled before each replay; per-step outputs (tie forces, taut flags) are
written to buffers of the same shape.

Not for gradients: on a ``wp.Tape`` call :meth:`SolverStringImplicit.step` with ``tape=`` directly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import warp as wp

from dmarionette.capture import CapturedChunk, ping_pong
from dmarionette.strings.model import StringControl, StringModel, StringState
from dmarionette.strings.solver import SolverStringImplicit

__all__ = ["StringRollout", "StringRolloutResult", "upload_values"]


@dataclasses.dataclass
class StringRolloutResult:
    """What a rollout produced.

    Attributes:
        tie_force: force of each tie on its body point after every step [N], ``(T, S, 3)``.
        string_taut: taut flag of each string after every step, ``(T, S)``.
        frames: particle positions once per chunk [m], ``(F, P, 3)``; frame ``i`` is the
            state after ``(i + 1) * chunk_steps`` steps.
        frame_velocities: particle velocities at the same frames [m/s], ``(F, P, 3)``.
    """

    tie_force: np.ndarray
    string_taut: np.ndarray
    frames: np.ndarray
    frame_velocities: np.ndarray


def upload_values(dst: wp.array, values: np.ndarray) -> None:
    """Writes host values into a Warp array (in place on the CPU, where ``numpy()`` is a view)."""
    if dst.device.is_cpu:
        dst.numpy()[...] = values
    else:
        dst.assign(wp.array(np.ascontiguousarray(values), dtype=dst.dtype, device=dst.device))


class StringRollout:
    """Replays a captured chunk of string steps.

    Args:
        solver: the stepper.
        dt: string step [s].
        chunk_steps: steps per captured graph; positions can be sampled once per chunk.
    """

    def __init__(self, solver: SolverStringImplicit, dt: float, chunk_steps: int = 50):
        if chunk_steps < 1:
            raise ValueError(f"chunk_steps: got {chunk_steps}; expected an integer >= 1")
        self.solver = solver
        self.model: StringModel = solver.model
        self.dt = float(dt)
        self.chunk_steps = int(chunk_steps)
        m = self.model
        shape = (self.chunk_steps, m.string_count)
        with wp.ScopedDevice(m.device):
            self._top_q = wp.zeros(shape, dtype=m.vec3)
            self._tie_q = wp.zeros(shape, dtype=m.vec3)
            self._tie_qd = wp.zeros(shape, dtype=m.vec3)
            self._tie_force = wp.zeros(shape, dtype=m.vec3)
            self._taut = wp.zeros(shape, dtype=wp.int32)
        self._state = m.state()
        self._spare = m.state()
        self._controls = [
            StringControl(self._top_q[k], self._tie_q[k], self._tie_qd[k]) for k in range(self.chunk_steps)
        ]
        self._chunk = CapturedChunk(self._launch, m.device, warm_up=self._warm_up)

    def _launch(self) -> None:
        """The launches of one chunk: ping-pong between two states, ending in ``self._state``."""
        ping_pong(self._step, self._state, self._spare, self.chunk_steps)

    def _step(self, k: int, state_in: StringState, state_out: StringState) -> None:
        self.solver.step(state_in, state_out, self._controls[k], self.dt)
        wp.copy(self._tie_force[k], state_out.tie_force)
        wp.copy(self._taut[k], state_out.string_taut)

    def _warm_up(self) -> None:
        # One eager step on scratch states loads every module before capture begins.
        self.solver.step(self._state, self.model.state(), self._controls[0], self.dt)
        self._state.assign(self.model.state())

    def run(
        self,
        state: StringState,
        top_q: np.ndarray,
        tie_q: np.ndarray | None = None,
        tie_qd: np.ndarray | None = None,
        *,
        on_chunk: Callable[[int], None] | None = None,
    ) -> StringRolloutResult:
        """Advances ``state`` in place by ``T`` steps.

        Args:
            state: the start state; holds the final state on return.
            top_q: attach point of each string's top at the end of each step [m], ``(T, S, 3)``;
                ``T`` must be a multiple of ``chunk_steps``.
            tie_q: body point of each tie at the end of each step [m], ``(T, S, 3)``; by
                default the model's fixed tie points.
            tie_qd: body point velocities [m/s], ``(T, S, 3)``; zero by default.
            on_chunk: called with the number of steps done after each chunk (progress).
        """
        m = self.model
        top_q = np.asarray(top_q, dtype=np.float64)
        steps = top_q.shape[0]
        expected = (steps, m.string_count, 3)
        if top_q.shape != expected or steps % self.chunk_steps != 0:
            raise ValueError(f"top_q: got shape {top_q.shape}; expected {expected} with T a multiple of "
                             f"chunk_steps={self.chunk_steps}")
        if tie_q is None:
            tie_q = np.broadcast_to(m.tie_points(), expected)
        if tie_qd is None:
            tie_qd = np.zeros(expected)
        for name, value in (("top_q", top_q), ("tie_q", tie_q), ("tie_qd", tie_qd)):
            if np.shape(value) != expected or not np.all(np.isfinite(value)):
                raise ValueError(f"{name}: expected finite values of shape {expected}; got {np.shape(value)}")
        chunks = steps // self.chunk_steps
        tie_force = np.zeros(expected)
        taut = np.zeros(expected[:2], dtype=np.int32)
        frames = np.zeros((chunks, m.particle_count, 3))
        frame_velocities = np.zeros_like(frames)
        self._state.assign(state)
        for c in range(chunks):
            rows = slice(c * self.chunk_steps, (c + 1) * self.chunk_steps)
            upload_values(self._top_q, top_q[rows])
            upload_values(self._tie_q, tie_q[rows])
            upload_values(self._tie_qd, tie_qd[rows])
            self._chunk.run()
            tie_force[rows] = self._tie_force.numpy()
            taut[rows] = self._taut.numpy()
            frames[c] = self._state.particle_q.numpy()
            frame_velocities[c] = self._state.particle_qd.numpy()
            if on_chunk is not None:
                on_chunk((c + 1) * self.chunk_steps)
        state.assign(self._state)
        return StringRolloutResult(tie_force=tie_force, string_taut=taut, frames=frames,
                                   frame_velocities=frame_velocities)
