"""A recorded session with known string constants and measurement noise, to test a calibration.

:func:`record_synthetic_session` simulates a scene whose strings have the *true* constants
(e.g. a different ``k``, ``k_d`` per string) and writes the session a live run would
(``dmarionette.io.session.SessionWriter``, the layout of ``record_simulation``), but with the
scene's *nominal* constants in its metadata, as when a real marionette's strings differ from
what its scene file says. Gaussian noise is added to the recorded body centres and feedback
forces (a motion-capture system and a force sensor), with a fixed seed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dmarionette.marionette.solver import MarionetteModel
from dmarionette.marionette.rollout import MarionetteTrajectory, simulate_marionette
from dmarionette.scene.scene import Scene
from dmarionette.io.session import SessionWriter
from dmarionette.io.session.replay import write_simulated_run

__all__ = ["SPEC_FIELDS", "record_synthetic_session", "with_string_constants"]

#: Calibration names of the string constants -> ``StringSpec`` fields.
SPEC_FIELDS = {"k": "tie_stiffness", "k_d": "tie_damping", "k_s": "stiffness"}


def with_string_constants(scene: Scene, constants: Mapping[str, Sequence[float] | float]) -> Scene:
    """``scene`` with string constants replaced: ``{"k": (S,) or scalar, "k_d": ..., "k_s": ...}``."""
    strings = list(scene.strings)
    for name, values in constants.items():
        if name not in SPEC_FIELDS:
            raise ValueError(f"constant {name!r}: expected one of {sorted(SPEC_FIELDS)}")
        values = np.broadcast_to(np.asarray(values, dtype=np.float64), (len(strings),))
        strings = [dataclasses.replace(s, **{SPEC_FIELDS[name]: float(v)}) for s, v in zip(strings, values)]
    return dataclasses.replace(scene, strings=tuple(strings))


def record_synthetic_session(scene: Scene, scene_text: str, truth: Mapping[str, Sequence[float] | float],
                             duration: float, path: str | Path, *, noise_position: float = 0.0,
                             noise_force: float = 0.0, seed: int = 0, optimization_level: int = 2,
                             progress: bool = False, delay: float = 0.0) -> tuple[MarionetteTrajectory, Path]:
    """Simulates ``scene`` with the ``truth`` constants and writes a session with noisy targets.

    Args:
        scene: the nominal scene (its constants go into the session's metadata).
        scene_text: its TOML text (stored in the session).
        truth: true string constants, ``{"k": (S,), "k_d": (S,), ...}`` (see :data:`SPEC_FIELDS`).
        duration: simulated seconds (rounded up to whole picture frames of puppet steps).
        path: the ``.mcap`` file.
        noise_position: standard deviation of the noise on each recorded body-centre
            coordinate [m].
        noise_force: standard deviation of the noise on each feedback-force component [N].
        seed: of the noise.
        optimization_level: Warp optimisation of the puppet kernels.
        progress: progress bar while simulating.
        delay: the targets lag the recorded bar inputs by this many seconds
            (:mod:`fitting.calibration_delay`): the bar poses written at ``t`` are those of ``t +
            delay`` (the targets and puppet states at ``t`` are the simulation's at ``t``). Exact
            for the delay model when the bars are still over the first ``delay`` seconds
            (:func:`fitting.synthetic_scenes.motion_scene_text` ``hold``).

    Returns:
        The noise-free simulated trajectory and the path written.
    """
    model = MarionetteModel(with_string_constants(scene, truth), optimization_level=optimization_level)
    trajectory = simulate_marionette(model, duration, progress=progress, frame_hz=1.0 / model.puppet_dt)
    rng = np.random.default_rng(seed)
    body_pos = trajectory.body_pos + noise_position * rng.standard_normal(trajectory.body_pos.shape)
    reaction = trajectory.bar_reaction + noise_force * rng.standard_normal(trajectory.bar_reaction.shape)
    eq4 = trajectory.bar_feedback + noise_force * rng.standard_normal(trajectory.bar_feedback.shape)
    path = Path(path)
    with SessionWriter(path, scene, scene_text, recorder="simulation") as writer:
        write_simulated_run(writer, trajectory, scene.bars, feedback=scene.body_effects["feedback"], delay=delay,
                            body_pos=body_pos, bar_feedback=eq4, bar_reaction=reaction)
        writer.write_metadata("synthetic", {"truth": {k: np.broadcast_to(np.asarray(v, float), (len(scene.strings),))
                                                      .tolist() for k, v in truth.items()},
                                            "noise_position": noise_position, "noise_force": noise_force,
                                            "seed": seed, "delay": delay})
    return trajectory, path
