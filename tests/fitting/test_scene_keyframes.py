"""The keyframe files of the paper's scenes (examples/keyframes_chair_stand.toml,
examples/keyframes_ball_kick.toml): valid input for ``dmarionette author`` on the scenes as
shipped, and targets a standing puppet really has, derived from the puppet's dimensions.

The chair's file is solved by the tool (its authored scene is tested in
tests/fitting/test_chair_authored.py), the ball's not yet (docs/authoring.md, "The paper's
scenes"); these checks keep the files consistent with the puppet and the scenes so that they stay
the right problems to solve.
"""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("optimistix")

from fitting import load_keyframes  # noqa: E402
from fitting.keyframes import puppet_step as puppet_dt  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CHAIR = ROOT / "examples" / "keyframes_chair_stand.toml"
BALL = ROOT / "examples" / "keyframes_ball_kick.toml"


def _standing_torso_height(puppet) -> float:
    """Torso centre above the ground [m] with hips, knees and ankles at 0 and the soles on the
    ground: half the foot, then each joint's anchors from the foot up to the torso."""
    bodies = {b.name: b for b in puppet.bodies}
    joints = {j.name: j for j in puppet.joints}
    height = 0.5 * bodies["foot_left"].size[1]
    for name in ("ankle_left", "knee_left", "hip_left"):  # child frame -> joint -> parent frame
        height += joints[name].anchor_child[1] - joints[name].anchor_parent[1]
    return height


def _straight(pose, names):
    return all(np.allclose(pose.joints[n], 0.0) for n in names)


def test_chair_keyframes_end_standing_in_front_of_the_shipped_chair():
    """Every keyframe of the chair file is standing: knees straight and the torso at the standing
    height, clear of the chair (the file no longer targets hips, nor a lift off the seat: issue 15
    does not ask for them, and the authored scene is checked standing, hips and feet included, by
    tests/fitting/test_chair_authored.py)."""
    spec = load_keyframes(CHAIR)
    scene = spec.scene
    assert scene.name == "chair_scripted" and scene.chair is not None  # the chair, scripted start
    assert all(scene.body_effects[k] for k in ("chair", "body_ground", "joint_limits"))
    standing = _standing_torso_height(scene.puppet)
    assert standing == pytest.approx(0.39, abs=1e-9)  # 0.01 + 0.01 + 0.14 + 0.14 + 0.09 (docs/puppet.md)
    centre, half = (np.array(v) for v in scene.chair)
    front = centre[2] + half[2]
    legs = {b.name: b for b in scene.puppet.bodies}["upper_leg_left"].size[2] / 2
    for pose in spec.keyframes:  # standing: knees straight, torso at the standing height, clear of the chair
        assert _straight(pose, ("knee_left", "knee_right"))
        torso = np.array(pose.bodies["torso"])
        assert torso[1] == pytest.approx(standing, abs=1e-9)
        assert torso[2] - legs > front
    assert spec.keyframes[-1].t == pytest.approx(spec.duration, abs=puppet_dt(scene))  # still standing at the end


def test_ball_keyframes_swing_the_right_foot_into_the_shipped_ball():
    spec = load_keyframes(BALL)
    scene = spec.scene
    assert scene.name == "ball_scripted" and scene.ball is not None
    assert all(scene.body_effects[k] for k in ("ball", "body_ground", "joint_limits"))
    bodies = {b.name: b for b in scene.puppet.bodies}
    kick, follow = spec.keyframes
    foot = np.array(kick.bodies["foot_right"])
    ball = np.array(scene.ball.position)
    toe = foot[2] + bodies["foot_right"].size[2] / 2
    assert toe > ball[2] - scene.ball.radius  # the foot's front is inside where the ball starts
    assert abs(foot[0] - ball[0]) < scene.ball.radius  # in line with it
    assert foot[1] > bodies["foot_right"].size[1] / 2  # off the ground
    torso = np.array(follow.bodies["torso"])
    assert torso[1] == pytest.approx(_standing_torso_height(scene.puppet), abs=1e-9)
    assert torso[2] > scene.puppet.root_position[2] + 0.1  # it follows the ball forward, 10 cm at least
    assert _straight(follow, ("knee_left", "knee_right"))
