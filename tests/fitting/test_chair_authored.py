"""The paper's chair scene, authored (issue 15 item 5): the built-in ``chair`` scene (the
bars ``dmarionette author examples/keyframes_chair_stand.toml`` wrote) ends with the puppet standing
in front of the chair, and the keyframes file is solved (exit 0, every keyframe within the file's
stated accuracy).

The bounds come from the puppet's geometry (dmarionette/scene/builtin/puppet.toml):
- standing torso centre 0.39 m above the ground (tests/fitting/test_scene_keyframes.py derives it),
  within 1 cm below it (a knee bent 5 deg lowers it by 0.5 mm) and not above it by more than a few
  mm of contact give. The hips are NOT bounded here (the keyframes do not target them): the
  authored puppet stands with its hips flexed ~30 deg, the torso leaning forward, and its feet
  tilted onto an edge (foot centres ~18 mm up instead of 10), which keeps the torso at 0.39 m;
- knees within 5 deg of straight (the file asks 1 deg at two instants; the puppet sways a little in
  between);
- feet on the ground: the lowest corner of each foot box within 3 mm of the ground (the penalty
  contact lets it sink about a millimetre under the puppet's weight).
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
KEYFRAMES = ROOT / "examples" / "keyframes_chair_stand.toml"
STANDING_TORSO = 0.39   # [m] above the ground (test_scene_keyframes derives it from puppet.toml)
TORSO_BELOW = 0.010     # [m] (see the module)
TORSO_ABOVE = 0.003     # [m] contact give
KNEE_MAX_DEG = 5.0
FOOT_GAP = 0.003        # [m] the lowest foot corner's distance from the ground
LAST_S = 0.5            # [s] standing for the last half second


def _quat_rotate(q, v):
    """Rotates ``v (..., 3)`` by Warp quaternions ``q (..., 4)`` (x, y, z, w)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


@pytest.fixture(scope="module")
def replay():
    from dmarionette.marionette.rollout import simulate_marionette
    from dmarionette.marionette.solver import MarionetteModel
    from dmarionette.scene.scene import load_scene

    scene = load_scene("chair")
    return scene, simulate_marionette(MarionetteModel(scene), scene.duration, progress=False)


def test_the_authored_chair_is_the_shipped_chair_with_authored_bars(replay):
    scene, _ = replay
    assert scene.name == "chair" and scene.chair is not None
    assert all(scene.body_effects[k] for k in ("chair", "body_ground", "joint_limits"))
    assert scene.puppet.root_position[1] == pytest.approx(0.262)  # it starts seated, as `chair` does


def test_the_puppet_ends_standing_in_front_of_the_chair(replay):
    scene, trajectory = replay
    names = list(trajectory.body_names)
    offset, q = {}, 7
    for joint in scene.puppet.joints:
        offset[joint.name] = q
        q += 4 if joint.type == "ball" else len(joint.axes)
    last = trajectory.frame_time >= trajectory.frame_time[-1] - LAST_S
    assert last.sum() >= 10
    ground = scene.ground_height
    torso = trajectory.body_pos[last, names.index("torso")]
    assert np.all(torso[:, 1] - ground >= STANDING_TORSO - TORSO_BELOW), torso[:, 1].min()
    assert np.all(torso[:, 1] - ground <= STANDING_TORSO + TORSO_ABOVE), torso[:, 1].max()
    centre, half = (np.asarray(v) for v in scene.chair)
    assert np.all(torso[:, 2] > centre[2] + half[2]), torso[:, 2].min()  # in front of the chair, not on it
    for side in ("left", "right"):
        knee = np.degrees(trajectory.joint_q[last, offset[f"knee_{side}"]])
        assert np.all(np.abs(knee) <= KNEE_MAX_DEG), knee
        body = {b.name: b for b in scene.puppet.bodies}[f"foot_{side}"]
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * np.asarray(
            body.size) / 2
        b = names.index(f"foot_{side}")
        world = trajectory.body_pos[last, b][:, None, :] + _quat_rotate(trajectory.body_rot[last, b][:, None, :],
                                                                       corners[None])
        lowest = world[..., 1].min(axis=1) - ground
        assert np.all(np.abs(lowest) <= FOOT_GAP), lowest


def test_the_keyframes_file_is_solved(tmp_path, capsys):
    """``dmarionette author examples/keyframes_chair_stand.toml`` exits 0, every keyframe within the
    file's [solver] tolerances (about 60-100 s on one core)."""
    pytest.importorskip("jax")
    pytest.importorskip("optimistix")
    from dmarionette.cli import main

    code = main(["author", str(KEYFRAMES), "--out", str(tmp_path), "--no-animation", "--no-export", "--quiet"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    print(summary["verdicts"], file=sys.stderr)
    assert code == 0, summary["verdicts"]
    tolerance = summary["tolerances"]
    assert tolerance == {"position_m": 1e-3, "angle_deg": 1.0}
    for verdict in summary["verdicts"]:
        assert verdict["status"] == "reached"
        for name, error in verdict["errors"].items():
            unit = verdict["units"][name]
            assert error <= (tolerance["position_m"] if unit == "m" else tolerance["angle_deg"]), (name, error)
    assert summary["warm_start"]["kind"] == "quasi_static" and summary["warm_start"]["used"]
    # the settles of the chair's quasi-static poses are at rest (feet and seat damp the puppet)
    assert all(pose["at_rest"] for pose in summary["warm_start"]["poses"]), summary["warm_start"]["poses"]
