"""Forward-mode (tangent) kernels of the string-body coupling (``kernels/string_body_coupling``:
the trial step's linearised string load ``eval_string_response``, the tie path
``eval_tie_path``, the anchors ``apply_string_forces_to_anchors``), transformed by
``kernels/kernel_tangent``.

(a) Dot-product identity against Warp's reverse mode of the same kernel on a ``wp.Tape``
    (``tests/support/tangents``: 1e-10 of the sum of the terms' magnitudes), P = 1, 3, 5;
    float64 strings, internal friction on and off. Two worlds of two tied strings each:
    world 0 generic (string 0 taut, its axial ramp strictly inside (0, 1), its last segment
    stretched; string 1 slack: ramp clamped at 0, last segment short of its rest length);
    world 1 at the switches, in exact binary fractions (straight strings whose segments are
    exactly at rest length, so the tension ``k_s max(l - d, 0)`` is at its kink, and whose span
    is exactly the taut distance, so the ramp's clamp is at its lower kink). The tie path
    has a tied and an untied string (``string_point < 0``).
(b) Central differences on world 0 (the string response, the anchors and the tie path),
    step study as ``tests/support/tangents.assert_central_differences``.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.kernels.articulation_math import spatial6, spatial66
from dmarionette.kernels.string_model_arrays import string_model_arrays_type
from dmarionette.kernels.string_body_coupling import (
    apply_string_forces_to_anchors_kernel,
    eval_string_response_kernel,
    eval_tie_path,
)
from tests.support.tangents import (assert_central_differences, assert_dot_product, central_difference_study,
                                   struct_value)

WORLDS, PER_WORLD, BODIES, N = 2, 2, 3, 3
REST = 0.25
H = 1.0 / 30.0


def _arr(a, dtype):
    return wp.array(np.asarray(a), dtype=dtype, device="cpu")


def _chain(top, steps):
    """Particles from ``top`` along the given segment vectors."""
    return np.cumsum(np.vstack([top, steps]), axis=0)


def _strings(rng):
    """(string_start, particle_q, particle_qd, rest, taut distance) of the four strings (module doc)."""
    taut_dir = np.array([0.1, -1.0, 0.05])
    taut_dir /= np.linalg.norm(taut_dir)
    jitter = 0.02 * rng.standard_normal((4, 3))
    s0 = _chain([0.0, 1.5, 0.0], [0.2 * taut_dir + jitter[0], 0.2 * taut_dir + jitter[1], 0.2 * taut_dir,
                                  0.27 * taut_dir + jitter[3]])
    s1 = _chain([0.3, 1.5, 0.0], [[0.0, -0.2, 0.05], [0.1, 0.1, 0.0], [0.0, -0.2, -0.1], [0.05, -0.15, 0.1]])
    down = [[0.0, -REST, 0.0]] * 4
    s2 = _chain([-0.5, 1.5, 0.0], down)
    s3 = _chain([0.5, 1.5, 0.25], down)
    chains = [s0, s1, s2, s3]
    start = np.cumsum([0] + [len(c) for c in chains]).astype(np.int32)
    q = np.vstack(chains)
    rest_total = REST * 4
    taut = np.array([0.7, 0.7, 4 * REST, 4 * REST])  # world 1: span exactly the taut distance
    assert 0.7 < np.linalg.norm(s0[-1] - s0[0]) < rest_total and np.linalg.norm(s1[-1] - s1[0]) < 0.7
    return start, q, 0.5 * rng.standard_normal(q.shape), taut


def _bodies(rng):
    rot = rng.standard_normal((WORLDS, BODIES, 4))
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    return {"body_pos": _arr(rng.standard_normal((WORLDS, BODIES, 3)) * 0.2 + [0.0, 0.5, 0.0], wp.vec3d),
            "body_rot": _arr(rot, wp.quatd),
            "body_w": _arr(rng.standard_normal((WORLDS, BODIES, 3)), wp.vec3d),
            "body_v": _arr(rng.standard_normal((WORLDS, BODIES, 3)), wp.vec3d)}


def _response_case(friction: bool, rng):
    start, q, _qd, taut = _strings(rng)
    kernel = eval_string_response_kernel(wp.float64, friction, N)
    strings = struct_value(string_model_arrays_type(wp.float64), string_start=_arr(start, wp.int32),
                           string_stiffness=_arr(rng.uniform(500.0, 2000.0, 4), wp.float64),
                           string_rest_length=_arr([REST] * 4, wp.float64),
                           string_tie_stiffness=_arr(rng.uniform(100.0, 1000.0, 4), wp.float64),
                           string_taut_distance=_arr(taut, wp.float64),
                           string_internal_friction=_arr(rng.uniform(0.5, 2.0, 4), wp.float64))
    args = {
        "spring_body": _arr([0, 2], wp.int32), "spring_point": _arr(0.05 * rng.standard_normal((2, 3)), wp.vec3d),
        "spring_string": _arr([0, 1], wp.int32), "strings_per_world": wp.int32(PER_WORLD),
        "strings": strings,
        **_bodies(rng),
        "particle_q": _arr(q, wp.vec3d),
        "tie_force": _arr(rng.standard_normal((N, 4, 3)), wp.vec3d),
        "h": wp.float64(H),
        "body_wrench": wp.zeros((WORLDS, BODIES), dtype=spatial6, device="cpu"),
        "body_stiffness": wp.zeros((WORLDS, BODIES), dtype=spatial66, device="cpu"),
    }
    return kernel, (WORLDS, 2), args


def _anchor_case(rng):
    kernel = apply_string_forces_to_anchors_kernel(N)
    args = {"spring_string": _arr([1, 0], wp.int32), "strings_per_world": wp.int32(PER_WORLD),
            "string_tie_stiffness": _arr(rng.uniform(100.0, 1000.0, 4), wp.float64),
            "tie_force": _arr(rng.standard_normal((N, 4, 3)), wp.vec3d),
            "tie_q": _arr(rng.standard_normal((N, 4, 3)), wp.vec3d),
            "tie_qd": _arr(rng.standard_normal((N, 4, 3)), wp.vec3d),
            "dt": wp.float64(1e-3),
            "spring_anchor_pos": wp.zeros((WORLDS, 2), dtype=wp.vec3d, device="cpu"),
            "spring_anchor_vel": wp.zeros((WORLDS, 2), dtype=wp.vec3d, device="cpu")}
    return kernel, (WORLDS, 2), args


def _path_case(rng):
    args = {"string_point": _arr([1, -1, 0, 2], wp.int32), "strings_per_world": wp.int32(PER_WORLD),
            "point_end": _arr(rng.standard_normal((WORLDS, 3, 3)), wp.vec3d),
            "tie_target": _arr(rng.standard_normal((4, 3)), wp.vec3d),
            "dt": wp.float64(1e-3),
            "tie_q": wp.zeros((N, 4), dtype=wp.vec3d, device="cpu"),
            "tie_qd": wp.zeros((N, 4), dtype=wp.vec3d, device="cpu"),
            "tie_target_out": wp.zeros(4, dtype=wp.vec3d, device="cpu")}
    return eval_tie_path, (N, 4), args


@pytest.mark.parametrize("P", [1, 3, 5])
@pytest.mark.parametrize("friction", [False, True])
def test_string_response_dot_product(friction, P):
    rng = np.random.default_rng(3 + P)
    assert_dot_product(*_response_case(friction, rng), P, rng)


@pytest.mark.parametrize("P", [1, 3, 5])
def test_anchors_dot_product(P):
    rng = np.random.default_rng(13 + P)
    assert_dot_product(*_anchor_case(rng), P, rng)


@pytest.mark.parametrize("P", [1, 3, 5])
def test_tie_path_dot_product(P):
    rng = np.random.default_rng(17 + P)
    assert_dot_product(*_path_case(rng), P, rng)


def _world0(args):
    """World 0 of the string response (its springs read strings 0 and 1 only)."""
    out = dict(args)
    for n in ("body_pos", "body_rot", "body_w", "body_v", "body_wrench", "body_stiffness"):
        out[n] = wp.clone(args[n][:1])
    return out


@pytest.mark.parametrize("case", ["response", "response_friction", "anchors", "tie_path"])
def test_coupling_central_differences(case):
    rng = np.random.default_rng(29)
    if case.startswith("response"):
        kernel, dim, args = _response_case(case.endswith("friction"), rng)
        kernel, dim, args = kernel, (1, dim[1]), _world0(args)
    else:
        kernel, dim, args = _anchor_case(rng) if case == "anchors" else _path_case(rng)
    study = central_difference_study(kernel, dim, args, rng)
    for s in study:
        print(f"{case}: eps {s[0]:.0e} error {s[1]:.3e} |Jv| {s[2]:.3e}")
    assert_central_differences(study, case)
