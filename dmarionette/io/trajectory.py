"""The trajectory file (NumPy ``.npz``, documented in docs/trajectory.md) and its summary."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dmarionette.scene.scene import Scene
from dmarionette.strings.simulate import StringTrajectory

__all__ = ["FORMAT_VERSION", "read_trajectory", "summarize", "write_trajectory"]

FORMAT_VERSION = 1


def write_trajectory(path: str | Path, trajectory: StringTrajectory, scene: Scene) -> Path:
    """Writes ``trajectory`` to ``path`` (``.npz``); every array is named as in docs/trajectory.md."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {
        "format": "dmarionette-trajectory",
        "format_version": FORMAT_VERSION,
        "scene": scene.name,
        "scene_source": scene.source,
        "string_dt": trajectory.string_dt,
        "frame_steps": trajectory.frame_steps,
        "precision": scene.precision,
        "effects": {k: bool(v) for k, v in vars(scene.effects).items()},
    }
    np.savez_compressed(
        path,
        metadata=np.array(json.dumps(metadata)),
        frame_time=trajectory.frame_time,
        particle_q=trajectory.particle_q,
        top_q=trajectory.top_q,
        step_time=trajectory.step_time,
        tie_force=trajectory.tie_force,
        string_taut=trajectory.string_taut.astype(np.int8),
        string_names=np.array(trajectory.string_names),
        string_start=trajectory.string_start,
        string_rest_length=trajectory.string_rest_length,
        energy=trajectory.energy,
    )
    return path


def read_trajectory(path: str | Path) -> dict:
    """Reads a trajectory file into a dict of arrays plus ``metadata`` (a dict)."""
    with np.load(Path(path), allow_pickle=False) as data:
        out = {key: data[key] for key in data.files}
    out["metadata"] = json.loads(str(out["metadata"]))
    if out["metadata"].get("format") != "dmarionette-trajectory":
        raise ValueError(f"{path}: not a dmarionette trajectory file (metadata format is "
                         f"{out['metadata'].get('format')!r})")
    return out


def summarize(trajectory: StringTrajectory, scene: Scene) -> dict:
    """A short summary: timing, and per string its stretch, taut fraction and tie force."""
    simulated = float(trajectory.step_time[-1])
    q = trajectory.particle_q
    strings = {}
    for s, name in enumerate(trajectory.string_names):
        a, b = trajectory.string_start[s], trajectory.string_start[s + 1]
        segments = np.linalg.norm(np.diff(q[:, a:b], axis=1), axis=2).sum(axis=1)
        length = trajectory.string_rest_length[s] * (b - a - 1)
        strings[name] = {
            "max_stretch_percent": round(float(100.0 * (segments.max() / length - 1.0)), 4),
            "taut_fraction": round(float(trajectory.string_taut[:, s].mean()), 4),
            "max_tie_force_N": round(float(np.linalg.norm(trajectory.tie_force[:, s], axis=1).max()), 6),
        }
    finite = bool(np.all(np.isfinite(q)) and np.all(np.isfinite(trajectory.tie_force)))
    return {
        "scene": scene.name,
        "simulated_seconds": round(simulated, 6),
        "string_steps": int(len(trajectory.step_time)),
        "string_dt": trajectory.string_dt,
        "wall_seconds": round(trajectory.wall_seconds, 4),
        "real_time_factor": round(simulated / trajectory.wall_seconds, 2) if trajectory.wall_seconds > 0 else None,
        "steps_per_second": round(len(trajectory.step_time) / trajectory.wall_seconds, 1)
        if trajectory.wall_seconds > 0 else None,
        "all_finite": finite,
        "energy_J": {"initial": float(trajectory.energy[0]), "final": float(trajectory.energy[-1])},
        "strings": strings,
    }


def write_marionette_trajectory(path: str | Path, trajectory, scene: Scene) -> Path:
    """Writes a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (docs/trajectory.md)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {
        "format": "dmarionette-trajectory",
        "format_version": FORMAT_VERSION,
        "kind": "marionette",
        "scene": scene.name,
        "scene_source": scene.source,
        "string_dt": trajectory.string_dt,
        "puppet_dt": trajectory.puppet_dt,
        "frame_steps": trajectory.frame_steps,
        "precision": scene.precision,
        "effects": {**{k: bool(v) for k, v in vars(scene.effects).items()}, **scene.body_effects},
        "body_shape": [[shape, list(size)] for shape, size in trajectory.body_shape],
    }
    arrays = {name: getattr(trajectory, name) for name in (
        "frame_time", "particle_q", "joint_q", "body_pos", "body_rot", "bar_pos", "bar_rot", "top_q",
        "step_time", "tie_force", "bar_feedback", "bar_reaction", "string_start", "string_rest_length")}
    np.savez_compressed(path, metadata=np.array(json.dumps(metadata)),
                        string_taut=trajectory.string_taut.astype(np.int8),
                        string_names=np.array(trajectory.string_names), body_names=np.array(trajectory.body_names),
                        bar_names=np.array(trajectory.bar_names), **arrays)
    return path


def summarize_marionette(trajectory, scene: Scene) -> dict:
    """Timing, finiteness, and per string its taut fraction and largest tie force; per bar its feedback."""
    simulated = float(trajectory.step_time[-1])
    finite = all(bool(np.all(np.isfinite(getattr(trajectory, name))))
                 for name in ("particle_q", "body_pos", "tie_force", "bar_feedback", "bar_reaction"))
    pelvis = trajectory.body_pos[:, 0, 1]
    return {
        "scene": scene.name,
        "simulated_seconds": round(simulated, 6),
        "string_steps": int(len(trajectory.step_time)),
        "puppet_steps": int(round(simulated / trajectory.puppet_dt)),
        "string_dt": trajectory.string_dt,
        "puppet_dt": trajectory.puppet_dt,
        "wall_seconds": round(trajectory.wall_seconds, 4),
        "real_time_factor": round(simulated / trajectory.wall_seconds, 2) if trajectory.wall_seconds > 0 else None,
        "all_finite": finite,
        "torso_height_m": {"initial": round(float(pelvis[0]), 4), "final": round(float(pelvis[-1]), 4),
                           "max": round(float(pelvis.max()), 4)},
        "strings": {name: {"taut_fraction": round(float(trajectory.string_taut[:, s].mean()), 4),
                           "max_tie_force_N": round(float(np.linalg.norm(trajectory.tie_force[:, s], axis=1).max()), 4)}
                    for s, name in enumerate(trajectory.string_names)},
        "bars": {name: {"max_feedback_N": round(float(np.linalg.norm(trajectory.bar_feedback[:, b], axis=1).max()), 4),
                        "max_reaction_N": round(float(np.linalg.norm(trajectory.bar_reaction[:, b], axis=1).max()), 4)}
                 for b, name in enumerate(trajectory.bar_names)},
    }
