"""The calibration test problem shared by tests/fitting/test_calibration*.py (docs/calibration.md,
"Tests"): ``examples/calibration_scene.toml`` with per-string eq. 2 constants and its noise."""

from pathlib import Path

SCENE = Path(__file__).resolve().parents[2] / "examples" / "calibration_scene.toml"
#: The true constants per string (head, back, knee_left, knee_right, hand_left, hand_right).
TRUTH = {"k": [330.0, 280.0, 310.0, 260.0, 350.0, 240.0], "k_d": [3.4, 2.6, 3.1, 2.2, 3.8, 2.9]}
NOISE_POSITION, NOISE_FORCE = 1e-4, 1e-2  # [m], [N]
