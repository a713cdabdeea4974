"""Forward-mode (tangent) kernels of the puppet's point springs, external forces and body points
(``kernels/articulation_forces``, transformed by ``kernels/kernel_tangent``).

Dot-product identity against Warp's reverse mode of the same kernel on a ``wp.Tape``
(``tests/support/tangents``: 1e-10 of the sum of the terms' magnitudes), P = 1, 3, 5 random
directions; the spring constants per spring and per world (the two layouts the kernel
reads); the implicit step ``h`` 0 (explicit) and 1/30 s.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.articulation_forces import eval_body_external_forces, eval_body_point_springs, eval_body_points
from dmarionette.kernels.articulation_math import spatial6, spatial66
from tests.support.tangents import assert_dot_product

WORLDS, BODIES, SPRINGS = 2, 3, 4


def _vec(rng, *shape, dtype=wp.vec3d, scale=1.0):
    n = getattr(dtype, "_length_", 1)
    return wp.array(scale * rng.standard_normal((*shape, n)), dtype=dtype, device="cpu")


def _quat(rng, *shape):
    q = rng.standard_normal((*shape, 4))
    return wp.array(q / np.linalg.norm(q, axis=-1, keepdims=True), dtype=wp.quatd, device="cpu")


def _bodies(rng):
    return {"body_pos": _vec(rng, WORLDS, BODIES), "body_rot": _quat(rng, WORLDS, BODIES),
            "body_w": _vec(rng, WORLDS, BODIES), "body_v": _vec(rng, WORLDS, BODIES)}


def _outputs(*names_dtypes, shape):
    return {n: wp.zeros(shape, dtype=d, device="cpu") for n, d in names_dtypes}


@pytest.mark.parametrize("P", [1, 3, 5])
@pytest.mark.parametrize("per_world", [False, True])
@pytest.mark.parametrize("h", [0.0, 1.0 / 30.0])
def test_point_springs_dot_product(P, per_world, h):
    rng = np.random.default_rng(11 + P + 2 * per_world)
    rows = SPRINGS * (WORLDS if per_world else 1)
    args = {
        "spring_body": wp.array(np.array([0, 2, 1, 2], dtype=np.int32), dtype=wp.int32, device="cpu"),
        "spring_point": _vec(rng, SPRINGS, scale=0.1),
        "spring_stiffness": wp.array(rng.uniform(100, 1000, rows), dtype=wp.float64, device="cpu"),
        "spring_damping": wp.array(rng.uniform(0.1, 5, rows), dtype=wp.float64, device="cpu"),
        **_bodies(rng),
        "spring_anchor_pos": _vec(rng, WORLDS, SPRINGS),
        "spring_anchor_vel": _vec(rng, WORLDS, SPRINGS),
        "h": wp.float64(h),
        **_outputs(("spring_force", wp.vec3d), shape=(WORLDS, SPRINGS)),
        **_outputs(("body_wrench", spatial6), ("body_stiffness", spatial66), shape=(WORLDS, BODIES)),
    }
    assert_dot_product(eval_body_point_springs, (WORLDS, SPRINGS), args, P, rng)


@pytest.mark.parametrize("P", [1, 3, 5])
def test_external_forces_dot_product(P):
    rng = np.random.default_rng(23 + P)
    args = {"body_pos": _vec(rng, WORLDS, BODIES), "body_force": _vec(rng, WORLDS, BODIES),
            "body_torque": _vec(rng, WORLDS, BODIES),
            **_outputs(("body_wrench", spatial6), ("body_stiffness", spatial66), shape=(WORLDS, BODIES))}
    assert_dot_product(eval_body_external_forces, (WORLDS, BODIES), args, P, rng)


@pytest.mark.parametrize("P", [1, 3, 5])
def test_body_points_dot_product(P):
    rng = np.random.default_rng(31 + P)
    args = {"point_body": wp.array(np.array([2, 0, 1, 1, 0], dtype=np.int32), dtype=wp.int32, device="cpu"),
            "point_local": _vec(rng, 5, scale=0.1), **_bodies(rng),
            **_outputs(("point_pos", wp.vec3d), ("point_vel", wp.vec3d), shape=(WORLDS, 5))}
    assert_dot_product(eval_body_points, (WORLDS, 5), args, P, rng)
