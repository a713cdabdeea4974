"""Control bars (paper §2.3): keyframe splines, CSV files of timed poses, attach points."""

import numpy as np
import pytest

from dmarionette.scene.bars import (
    BarTrajectory,
    ControlBar,
    read_bar_trajectory_csv,
    write_bar_trajectory_csv,
)
from dmarionette.rotations import euler_to_matrix
from dmarionette.scene.fields import SceneError

KEYS = BarTrajectory(np.array([0.0, 1.0, 2.5, 4.0]),
                     np.array([[0.0, 1.3, 0.0], [0.1, 1.2, 0.0], [0.0, 1.4, 0.2], [-0.1, 1.3, 0.1]]),
                     np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 5.0], [0.0, -20.0, 0.0], [0.0, 0.0, 0.0]]))


def test_spline_passes_through_keyframes_and_holds_outside():
    position, velocity, rotation = KEYS.pose(KEYS.times)
    np.testing.assert_allclose(position, KEYS.positions, atol=1e-12)
    np.testing.assert_allclose(rotation, euler_to_matrix(KEYS.rotations), atol=1e-12)
    np.testing.assert_allclose(velocity[[0, -1]], 0.0, atol=1e-12)  # starts and stops at rest
    held, held_velocity, _ = KEYS.pose(np.array([-1.0, 9.0]))
    np.testing.assert_allclose(held, KEYS.positions[[0, -1]])
    np.testing.assert_allclose(held_velocity, 0.0)


def test_spline_velocity_is_the_derivative_and_is_continuous():
    t = np.linspace(0.05, 3.95, 400)
    eps = 1e-6
    position, velocity, _ = KEYS.pose(t)
    numeric = (KEYS.pose(t + eps)[0] - KEYS.pose(t - eps)[0]) / (2 * eps)
    np.testing.assert_allclose(velocity, numeric, atol=1e-6)
    for knot in KEYS.times[1:-1]:  # C1 at interior keyframes
        left = KEYS.pose(np.array([knot - 1e-9]))[1]
        right = KEYS.pose(np.array([knot + 1e-9]))[1]
        np.testing.assert_allclose(left, right, atol=1e-6)


def test_euler_angles_compose_as_rz_ry_rx():
    angles = np.array([20.0, -35.0, 50.0])
    a = np.radians(angles)
    rx = np.array([[1, 0, 0], [0, np.cos(a[0]), -np.sin(a[0])], [0, np.sin(a[0]), np.cos(a[0])]])
    ry = np.array([[np.cos(a[1]), 0, np.sin(a[1])], [0, 1, 0], [-np.sin(a[1]), 0, np.cos(a[1])]])
    rz = np.array([[np.cos(a[2]), -np.sin(a[2]), 0], [np.sin(a[2]), np.cos(a[2]), 0], [0, 0, 1]])
    np.testing.assert_allclose(euler_to_matrix(angles), rz @ ry @ rx, atol=1e-14)


def test_attach_points_move_with_the_bar():
    bar = ControlBar("main", {"head": (0.0, 0.0, 0.0), "knee_left": (0.1, 0.0, 0.0)},
                     BarTrajectory(np.array([0.0]), np.array([[0.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 90.0]])))
    points = bar.attach_points(np.array([0.0]), ["head", "knee_left"])
    np.testing.assert_allclose(points[0], [[0.0, 1.0, 0.0], [0.0, 1.1, 0.0]], atol=1e-12)  # yaw 90°: x -> y


def test_csv_round_trip(tmp_path):
    t = np.linspace(0.0, 4.0, 81)
    path = write_bar_trajectory_csv(tmp_path / "bar.csv", KEYS, t)
    back = read_bar_trajectory_csv(path)
    np.testing.assert_allclose(back.pose(t)[0], KEYS.pose(t)[0], atol=1e-8)
    np.testing.assert_allclose(back.pose(t)[2], KEYS.pose(t)[2], atol=1e-8)


@pytest.mark.parametrize(
    "text,key,expected",
    [
        ("t,x,y,z,rx,ry,rz\n0,0,1,0,0,0,0\n0,0,1,0,0,0,0\n", "t", "later than the previous"),
        ("time,x,y,z,rx,ry,rz\n0,0,1,0,0,0,0\n", "header", "t,x,y,z,rx,ry,rz"),
        ("t,x,y,z,rx,ry,rz\n0,0,one,0,0,0,0\n", "row", "seven numbers"),
        ("t,x,y,z,rx,ry,rz\n0,0,nan,0,0,0,0\n", "row", "finite"),
    ],
)
def test_bad_csv_is_refused_with_file_line_and_expectation(tmp_path, text, key, expected):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(SceneError) as error:
        read_bar_trajectory_csv(path)
    assert str(path) in str(error.value) and f"'{key}'" in str(error.value) and expected in str(error.value)


def test_scene_bar_from_a_csv_file(tmp_path):
    """A bar's motion may come from a CSV file named relative to the scene file."""
    import dmarionette as dm

    write_bar_trajectory_csv(tmp_path / "main.csv", KEYS, np.linspace(0.0, 4.0, 41))
    (tmp_path / "scene.toml").write_text(
        '[scene]\nname = "csv"\n\n[[strings]]\nname = "a"\nbottom = [0.0, 0.5, 0.0]\n\n'
        '[bars.main]\ntrajectory_file = "main.csv"\n\n[bars.main.attach]\na = [0.0, 0.0, 0.0]\n')
    scene = dm.load_scene(tmp_path / "scene.toml")
    np.testing.assert_allclose(scene.bars[0].trajectory.pose(np.array([2.5]))[0][0], [0.0, 1.4, 0.2], atol=1e-8)
    assert scene.strings[0].top == pytest.approx((0.0, 1.3, 0.0))  # the string hangs from the bar at t = 0
