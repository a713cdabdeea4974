"""Running a scene headless: its strings for a given duration, with progress.

A scene without a puppet is its strings alone, their tops moved by the scene's bars (or
``[motion]``); scenes with a puppet run as a marionette (:mod:`marionette_rollout`).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from tqdm import tqdm

from dmarionette.scene.scene import Scene
from dmarionette.strings.model import StringModel, string_energy
from dmarionette.strings.rollout import StringRollout
from dmarionette.strings.solver import SolverStringImplicit

__all__ = ["StringTrajectory", "simulate_strings"]


@dataclasses.dataclass
class StringTrajectory:
    """A simulated string trajectory (the contents of a trajectory file, docs/trajectory.md).

    Attributes:
        frame_time: time of each frame [s], ``(F,)``; frame 0 is the initial state.
        particle_q: particle positions at each frame [m], ``(F, P, 3)``.
        top_q: top attach points at each frame [m], ``(F, S, 3)``.
        step_time: time at the end of each string step [s], ``(T,)``.
        tie_force: eq. 2 force of each tie on its body point after each step [N], ``(T, S, 3)``.
        string_taut: taut flag of each string after each step, ``(T, S)``.
        string_names: ``(S,)``; string_start: first particle of each string and ``P``, ``(S+1,)``.
        energy: total mechanical energy of the strings at each frame [J], ``(F,)``.
        wall_seconds: wall-clock time of the stepping alone [s].
    """

    frame_time: np.ndarray
    particle_q: np.ndarray
    top_q: np.ndarray
    step_time: np.ndarray
    tie_force: np.ndarray
    string_taut: np.ndarray
    string_names: list[str]
    string_start: np.ndarray
    string_rest_length: np.ndarray
    energy: np.ndarray
    string_dt: float
    frame_steps: int
    wall_seconds: float


def simulate_strings(scene: Scene, duration: float | None = None, *, progress: bool = True,
                     model: StringModel | None = None) -> StringTrajectory:
    """Simulates the scene's strings for ``duration`` seconds (the scene's by default).

    Frames are kept every ``round(string_hz / puppet_hz)`` string steps (about the puppet
    and picture rate); the simulated time is rounded up to a whole number of frames.
    """
    duration = scene.duration if duration is None else float(duration)
    if not duration > 0.0:
        raise ValueError(f"duration: got {duration}; expected a positive number of seconds")
    model = StringModel.from_scene(scene) if model is None else model
    dt = scene.string_dt
    frame_steps = max(1, round(scene.string_hz / scene.puppet_hz))
    frames = max(1, int(np.ceil(duration / (dt * frame_steps))))
    steps = frames * frame_steps
    step_time = dt * np.arange(1, steps + 1)
    rest_tops = np.array([s.top for s in model.specs])
    top_q = scene.top_positions(rest_tops, step_time)

    solver = SolverStringImplicit(model)
    rollout = StringRollout(solver, dt, chunk_steps=frame_steps)
    state = model.state()
    q0 = state.particle_q.numpy().copy()
    qd0 = state.particle_qd.numpy().copy()
    with tqdm(total=steps, unit="step", disable=not progress, desc=f"{scene.name}") as bar:
        start = time.perf_counter()
        result = rollout.run(state, top_q, on_chunk=lambda done: bar.update(done - bar.n))
        wall = time.perf_counter() - start

    particle_q = np.concatenate([q0[None], result.frames])
    frame_time = dt * frame_steps * np.arange(frames + 1)
    frame_tops = np.concatenate([scene.top_positions(rest_tops, np.zeros(1)), top_q[frame_steps - 1 :: frame_steps]])
    velocities = np.concatenate([qd0[None], result.frame_velocities])
    energy = np.array([string_energy(model, q, v)["total"] for q, v in zip(particle_q, velocities)])
    return StringTrajectory(
        frame_time=frame_time, particle_q=particle_q, top_q=frame_tops, step_time=step_time,
        tie_force=result.tie_force, string_taut=result.string_taut, string_names=list(model.string_names),
        string_start=model.string_start_np.copy(),
        string_rest_length=model.string_rest_length.numpy().astype(np.float64),
        energy=energy, string_dt=dt, frame_steps=frame_steps, wall_seconds=wall,
    )
