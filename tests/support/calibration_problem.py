"""The calibration test problem shared by tests/fitting/test_calibration*.py (docs/calibration.md,
"Tests"): ``examples/calibration_scene.toml`` with per-string eq. 2 constants and its noise."""

from pathlib import Path

import dmarionette as dm

SCENE = Path(__file__).resolve().parents[2] / "examples" / "calibration_scene.toml"
#: The true constants per string (head, back, knee_left, knee_right, hand_left, hand_right).
TRUTH = {"k": [330.0, 280.0, 310.0, 260.0, 350.0, 240.0], "k_d": [3.4, 2.6, 3.1, 2.2, 3.8, 2.9]}
NOISE_POSITION, NOISE_FORCE = 1e-4, 1e-2  # [m], [N]


def record_motion(folder: Path, motion: str, duration: float, seed: int, rename: dict | None = None) -> Path:
    """A session (``.mcap``) of ``motion`` (fitting.synthetic_scenes) with the constants ``TRUTH``, noise
    ``NOISE_POSITION``, ``NOISE_FORCE``; ``rename``: string names replaced (old -> new)."""
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    text = motion_scene_text(motion, duration)
    for old, new in (rename or {}).items():
        text = text.replace(f'name = "{old}"', f'name = "{new}"').replace(f"\n{old} = [", f"\n{new} = [")
    scene_path = folder / f"{motion}_{seed}.toml"
    scene_path.write_text(text)
    _, path = record_synthetic_session(dm.load_scene(scene_path), text, TRUTH, duration,
                                       folder / f"{motion}_{seed}.mcap", noise_position=NOISE_POSITION,
                                       noise_force=NOISE_FORCE, seed=seed, optimization_level=0)
    return path
