"""Forward-mode (tangent) kernels of the puppet's contacts (``kernels/body_contact``: ground, chair
box, free ball; hard and smooth), transformed by ``kernels/kernel_tangent``.

(a) Dot-product identity against Warp's reverse mode of the same kernel on a ``wp.Tape``
    (``tests/support/tangents``: 1e-10 of the sum of the terms' magnitudes), P = 1, 3, 5.
    Two worlds: world 0 generic (a tilted box with corners in the ground and inside the
    chair, others outside it; a sphere in the ground and in the ball); world 1 at the
    switches, in exact binary fractions: box corners where the hard normal force
    ``max(k d - c v_n, 0)`` is exactly at its kink (``k d = c v_n``), a sphere exactly touching
    the ground (``d = 0``: the hard contact skips it, the smooth one is at its softplus'
    ``x = 0`` and its damping's ``v_n = 0``), the ball outside a box face.
(b) Central differences on world 0 (every active input moved along one random direction),
    step study: the error falls like eps^2 (100x per decade from 1e-3 to 1e-4) until
    rounding takes over; the best step's error is within 100 u^(2/3) of the tangent's scale
    (``tests/support/tangents.assert_central_differences``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.articulation_math import spatial6, spatial66
from dmarionette.kernels.body_contact import ContactSet, ContactSettings
from tests.support.tangents import assert_central_differences, assert_dot_product, central_difference_study

H = 1.0 / 30.0
BOX, HEAD, BALL = 0, 1, 2


def _model(smooth: bool):
    """The fields :class:`ContactSet` reads of a model: a box, a sphere and the free ball."""
    settings = ContactSettings(ground=True, chair=((1.0, 0.3, 0.0), (0.2, 0.3, 0.2)), ball=True, smooth=smooth,
                               stiffness=2048.0, damping=4.0, friction=0.6, friction_velocity=0.01,
                               smooth_distance=0.5e-3)
    return SimpleNamespace(device="cpu", contacts=settings,
                           body_shape=[("box", (0.25, 0.25, 0.25)), ("sphere", (0.05,)), ("sphere", (0.1,))],
                           body_contact=[True, True, True],
                           body_mass=wp.array([1.0, 0.5, 0.3], dtype=wp.float64, device="cpu"),
                           body_names=["torso", "head", "ball"], ball=SimpleNamespace(radius=0.1))


def _state(rng):
    """(pos, rot, w, v) of the two worlds (module doc)."""
    pos = np.zeros((2, 3, 3))
    rot = np.zeros((2, 3, 4))
    rot[..., 3] = 1.0
    w = np.zeros((2, 3, 3))
    v = np.zeros((2, 3, 3))
    # world 0: generic
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    rot[0, BOX] = [*(np.sin(0.15) * axis), np.cos(0.15)]
    pos[0, BOX] = (0.9, 0.12, 0.0)
    pos[0, HEAD] = (0.3, 0.04, 0.1)
    pos[0, BALL] = (0.3, 0.04 + 0.05 + 0.1 - 0.02, 0.12)
    w[0] = 0.5 * rng.standard_normal((3, 3))
    v[0] = 0.3 * rng.standard_normal((3, 3))
    # world 1: at the switches, exactly
    pos[1, BOX] = (-0.5, 0.109375, 0.0)  # bottom corners 2^-6 deep: k d = 2048 / 64 = 32 = c v_n at v_n = 8
    v[1, BOX] = (0.0, 8.0, 0.0)
    pos[1, HEAD] = (0.5, 0.05, 0.0)  # exactly touching the ground, at rest
    pos[1, BALL] = (-0.5 + 0.125 + 0.09, 0.2, 0.05)  # 1 cm into the box's +x face
    v[1, BALL] = (-0.25, 0.0, 0.125)
    arr = lambda a, d: wp.array(a, dtype=d, device="cpu")  # noqa: E731
    return arr(pos, wp.vec3d), arr(rot, wp.quatd), arr(w, wp.vec3d), arr(v, wp.vec3d)


def _cases(smooth: bool, rng):
    """(kernel, dim, args) of the ground, chair and ball kernels."""
    cs = ContactSet(_model(smooth))
    ground, box, ball = cs.kernels
    pos, rot, w, v = _state(rng)
    bodies = {"body_pos": pos, "body_rot": rot, "body_w": w, "body_v": v, "h": wp.float64(H)}
    out = lambda: {"body_wrench": wp.zeros((2, 3), dtype=spatial6, device="cpu"),  # noqa: E731
                   "body_stiffness": wp.zeros((2, 3), dtype=spatial66, device="cpu")}
    points = {"point_body": cs.point_body, "point_local": cs.point_local, "point_radius": cs.point_radius,
              "contact": cs.constants}
    return {
        "ground": (ground, (2, cs.point_count), {**points, "surface": cs.ground, **bodies, **out()}),
        "chair": (box, (2, cs.point_count), {**points, "surface": cs.chair, **bodies, **out()}),
        "ball": (ball, (2, cs.pair_count),
                 {"pair_body": cs.pair_body, "pair_is_sphere": cs.pair_is_sphere, "pair_half": cs.pair_half,
                  "pair_mass": cs.pair_mass, "ball_body": cs.ball_body, "ball_radius": wp.float64(0.1),
                  "contact": cs.constants, **bodies, **out()}),
    }


@pytest.mark.parametrize("P", [1, 3, 5])
@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("which", ["ground", "chair", "ball"])
def test_contact_dot_product(which, smooth, P):
    rng = np.random.default_rng(7 + P)
    kernel, dim, args = _cases(smooth, rng)[which]
    assert_dot_product(kernel, dim, args, P, rng)


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("which", ["ground", "chair", "ball"])
def test_contact_central_differences(which, smooth):
    rng = np.random.default_rng(5)
    kernel, dim, args = _cases(smooth, rng)[which]
    # world 0 only (world 1 sits on the switches, where a difference straddles the kink)
    args = {n: (a[:1] if isinstance(a, wp.array) and a.ndim == 2 else a) for n, a in args.items()}
    study = central_difference_study(kernel, (1, dim[1]), args, rng)
    for s in study:
        print(f"{which} smooth={smooth}: eps {s[0]:.0e} error {s[1]:.3e} |Jv| {s[2]:.3e}")
    assert_central_differences(study, f"{which} smooth={smooth}")
