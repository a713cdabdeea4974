"""Host-side rotations (dmarionette.rotations): round trips, known rotations, the quaternion
order at the boundaries, and the Euler conventions against closed forms."""

import ast
import pathlib

import numpy as np
import pytest

from dmarionette.rotations import (
    continuous_quats,
    euler_to_matrix,
    from_wxyz,
    matrix_to_euler,
    matrix_to_euler_xzy,
    matrix_to_quat,
    nearest_rotation,
    normalize_quat,
    quat_rotate,
    quat_slerp,
    quat_to_matrix,
    to_wxyz,
)

ROTATIONS = pathlib.Path(__file__).resolve().parents[1] / "dmarionette" / "rotations.py"


def rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, 3:4] < 0.0, -q, q)


def test_module_is_a_numpy_only_leaf():
    """It imports nothing from dmarionette (so hw/ and descriptions may use it), only NumPy."""
    modules = set()
    for node in ast.walk(ast.parse(ROTATIONS.read_text())):
        if isinstance(node, ast.Import):
            modules |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "relative import"
            modules.add(node.module.split(".")[0])
    assert modules <= {"__future__", "typing", "numpy"}, modules


def test_known_quaternions_are_x_y_z_w():
    """A turn of angle a about axis n is (sin(a/2) n, cos(a/2)): Warp's order."""
    for axis, closed_form in ((0, rx), (1, ry), (2, rz)):
        for a in (0.3, -1.2, np.pi / 2, np.pi):
            q = np.zeros(4)
            q[axis], q[3] = np.sin(a / 2), np.cos(a / 2)
            np.testing.assert_allclose(quat_to_matrix(q), closed_form(a), atol=1e-15)
            np.testing.assert_allclose(matrix_to_quat(closed_form(a)), q, atol=1e-15)
    np.testing.assert_array_equal(quat_to_matrix([0.0, 0.0, 0.0, 1.0]), np.eye(3))


def test_quaternion_matrix_round_trip():
    """matrix_to_quat inverts quat_to_matrix (w >= 0), batched, including turns near 180 deg."""
    rng = np.random.default_rng(0)
    q = random_quats(rng, 200)
    q[:4] = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    q[4] = normalize_quat([1.0, 1.0, 0.0, 1e-9])  # nearly a half turn
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-14)
    np.testing.assert_allclose(matrix_to_quat(r), q, atol=1e-14)
    assert matrix_to_quat(r.reshape(20, 10, 3, 3)).shape == (20, 10, 4)
    assert np.all(matrix_to_quat(r)[:, 3] >= 0.0)


def test_quat_rotate_equals_the_matrix():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(7, 3))
    for q in random_quats(rng, 10):
        np.testing.assert_allclose(quat_rotate(q, v), v @ quat_to_matrix(q).T, atol=1e-14)


def test_boundary_orders_reorder_only():
    """to_wxyz/from_wxyz move w and nothing else, batched, and invert each other exactly."""
    q = np.array([[0.1, 0.2, 0.3, 0.9], [-0.5, 0.5, -0.5, 0.5]])
    np.testing.assert_array_equal(to_wxyz(q), [[0.9, 0.1, 0.2, 0.3], [0.5, -0.5, 0.5, -0.5]])
    np.testing.assert_array_equal(from_wxyz(to_wxyz(q)), q)
    np.testing.assert_array_equal(to_wxyz(from_wxyz(q)), q)
    # The identity: (0, 0, 0, 1) in the project's order, (1, 0, 0, 0) for viser and device samples.
    np.testing.assert_array_equal(to_wxyz([0.0, 0.0, 0.0, 1.0]), [1.0, 0.0, 0.0, 0.0])
    # A quarter turn about z given as (w, x, y, z) gives the same matrix as (x, y, z, w).
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    np.testing.assert_allclose(quat_to_matrix(from_wxyz([c, 0.0, 0.0, s])), rz(np.pi / 2), atol=1e-15)
    out = to_wxyz(q)
    out[0, 0] = 7.0
    assert q[0, 3] == 0.9  # a copy


def test_normalize_quat_and_nearest_rotation_refuse_what_is_not_a_rotation():
    np.testing.assert_allclose(normalize_quat([0.0, 0.0, 0.0, 2.0]), [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="non-zero finite"):
        normalize_quat([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="non-zero finite"):
        normalize_quat([np.nan, 0.0, 0.0, 1.0])
    drifted = rz(0.4) + 1e-6 * np.random.default_rng(2).normal(size=(3, 3))
    r = nearest_rotation(drifted)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(r, rz(0.4), atol=1e-5)
    with pytest.raises(ValueError, match="reflection"):
        nearest_rotation(np.diag([1.0, 1.0, -1.0]))


def test_euler_angles_compose_as_rz_ry_rx_and_invert():
    """Bar angles [deg]: R = Rz(c) Ry(b) Rx(a), against the closed forms; matrix_to_euler inverts it."""
    rng = np.random.default_rng(3)
    angles = np.column_stack([rng.uniform(-180, 180, 50), rng.uniform(-89, 89, 50), rng.uniform(-180, 180, 50)])
    a, b, c = np.radians(angles).T
    closed = np.stack([rz(c[k]) @ ry(b[k]) @ rx(a[k]) for k in range(50)])
    np.testing.assert_allclose(euler_to_matrix(angles), closed, atol=1e-14)
    np.testing.assert_allclose(matrix_to_euler(closed), angles, atol=1e-10)
    np.testing.assert_allclose(matrix_to_euler(closed[0]), angles[0], atol=1e-10)  # one matrix
    np.testing.assert_allclose(euler_to_matrix([0.0, 0.0, 90.0]), rz(np.pi / 2), atol=1e-15)


def test_bvh_euler_angles_compose_as_rx_rz_ry_and_stay_continuous():
    """BVH channels [rad]: R = Rx(a) Rz(b) Ry(c); with ``previous`` the nearer equivalent triple."""
    rng = np.random.default_rng(4)
    a, b, c = rng.uniform(-3, 3, 30), rng.uniform(-1.5, 1.5, 30), rng.uniform(-3, 3, 30)
    closed = np.stack([rx(a[k]) @ rz(b[k]) @ ry(c[k]) for k in range(30)])
    np.testing.assert_allclose(matrix_to_euler_xzy(closed), np.column_stack([a, b, c]), atol=1e-10)
    # A hinge about x turning past 180 deg keeps counting up instead of jumping to -180.
    turns = np.radians(np.arange(0.0, 400.0, 10.0))
    previous, got = None, []
    for t in turns:
        previous = matrix_to_euler_xzy(rx(t)[None], previous)
        got.append(previous[0])
    np.testing.assert_allclose(np.array(got), np.column_stack([turns, 0 * turns, 0 * turns]), atol=1e-10)
    # Gimbal lock (b = 90 deg): c keeps its previous value, and the angles still give R.
    locked = rx(0.7) @ rz(np.pi / 2) @ ry(0.2)
    angles = matrix_to_euler_xzy(locked[None], np.array([[0.0, 1.5, 0.2]]))[0]
    assert angles[2] == 0.2
    np.testing.assert_allclose(rx(angles[0]) @ rz(angles[1]) @ ry(angles[2]), locked, atol=1e-12)


def test_continuous_quats_and_slerp():
    rng = np.random.default_rng(5)
    q = random_quats(rng, 1)[0]
    frames = np.stack([q, -q, q, -q])
    np.testing.assert_array_equal(continuous_quats(frames), np.stack([q, q, q, q]))
    # slerp between two turns about z goes at constant rate, and the short way for -q1.
    q0, q1 = np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, np.sin(0.5), np.cos(0.5)])
    u = np.linspace(0.0, 1.0, 5)
    expected = np.column_stack([0 * u, 0 * u, np.sin(0.5 * u), np.cos(0.5 * u)])
    np.testing.assert_allclose(quat_slerp(np.tile(q0, (5, 1)), np.tile(q1, (5, 1)), u), expected, atol=1e-15)
    np.testing.assert_allclose(quat_slerp(np.tile(q0, (5, 1)), np.tile(-q1, (5, 1)), u), expected, atol=1e-15)


def test_fitting_jax_euler_to_matrix_equals_numpy():
    """fitting.bar_spline keeps a JAX twin of euler_to_matrix (to differentiate through); same convention."""
    pytest.importorskip("jax")
    from fitting.bar_spline import euler_to_matrix as euler_to_matrix_jax

    angles = np.random.default_rng(6).uniform(-120.0, 120.0, size=(40, 3))
    np.testing.assert_allclose(np.asarray(euler_to_matrix_jax(angles)), euler_to_matrix(angles), atol=1e-12)
