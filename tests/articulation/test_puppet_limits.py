"""Joint limits and the stable range of the implicit step with stiff string springs."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from dmarionette.articulation.solver import SolverArticulation, build_articulation_model
from dmarionette.scene.puppet import load_puppet


H30 = 1.0 / 30.0
POINTS = ("head", "back", "hand_left", "hand_right", "knee_left", "knee_right")


def hung_puppet(k=500.0, kd=1.0, points=POINTS):
    """The puppet hung by point springs (the strings' ends) at its attach points, anchors
    2 cm above the rest positions of the points."""
    model = build_articulation_model(load_puppet(), springs=tuple((p, k, kd) for p in points))
    solver = SolverArticulation(model, optimization_level=0)
    rest = model.state()
    solver.eval_kinematics(rest)
    pos = wp.zeros((1, len(model.point_names)), dtype=wp.vec3d)
    vel = wp.zeros_like(pos)
    solver.eval_points(rest, pos, vel)
    anchors = pos.numpy()[0][[model.point_names.index(p) for p in points]]
    anchors[:, 1] += 0.02
    control = model.control()
    control.spring_anchor_pos.assign(anchors[None])
    return model, solver, control


@pytest.fixture(scope="module")
def hung():
    return hung_puppet()


@pytest.fixture(scope="module")
def floating():
    """The puppet floating without gravity: a joint torque is then balanced by the limit
    alone at equilibrium, so the limit's penetration is exactly torque / k_limit."""
    model = build_articulation_model(load_puppet(), gravity=(0.0, 0.0, 0.0))
    return model, SolverArticulation(model, optimization_level=0), model.control()


def _run(model, solver, control, duration, dt=H30, qd0=None, record=None):
    a, b = model.state(), model.state()
    if qd0 is not None:
        a.joint_qd.assign(qd0[None])
    for _ in range(int(round(duration / dt))):
        solver.step(a, b, control, dt)
        a, b = b, a
        if record is not None:
            record(a)
    return a


def test_elbow_limit_holds(floating):
    """A torque of 0.02 N m bends the left elbow of the floating puppet into its lower
    limit (-150 deg) at 30 Hz. After 3 s the penalty limit balances the torque: the
    elbow sits within torque / k_limit (0.004 rad) of the limit, on the far side; the
    tolerance on that is the residual motion, 1e-3 rad."""
    model, solver, control = floating
    dof = 11  # root 0-5, neck 6-8, shoulder_left 9-10, elbow_left 11
    lower = model.dof_limit_lower.numpy()[dof]
    tau = 0.02
    f = np.zeros(model.qd_count)
    f[dof] = -tau
    control.joint_f.assign(f[None])
    allowed = tau / model.limit_stiffness
    angles = []
    _run(model, solver, control, 3.0, record=lambda s: angles.append(s.joint_q.numpy()[0, dof + 2]))
    control.joint_f.zero_()
    late = np.array(angles[-30:])
    print(f"elbow: limit {np.degrees(lower):.1f} deg, min over last second {np.degrees(late.min()):.2f} deg, "
          f"allowed {np.degrees(lower - allowed):.2f} deg; min over run {np.degrees(min(angles)):.2f} deg")
    assert np.abs(late - (lower - allowed)).max() <= 1e-3


def test_neck_cone_limit_holds(floating):
    """A torque of 0.03 N m about the head's x axis tips the head of the floating puppet
    into its 60 deg cone; at rest the angle exceeds the cone by torque / k_limit
    (0.006 rad), to within 1e-3 rad of residual motion."""
    model, solver, control = floating
    cone = model.dof_limit_upper.numpy()[6]
    f = np.zeros(model.qd_count)
    f[6] = 0.03
    control.joint_f.assign(f[None])
    allowed = 0.03 / model.limit_stiffness
    angles = []

    def record(s):
        w = abs(s.joint_q.numpy()[0, 7])
        angles.append(2.0 * np.arccos(min(w, 1.0)))

    _run(model, solver, control, 3.0, record=record)
    control.joint_f.zero_()
    late = np.array(angles[-30:])
    print(f"neck: cone {np.degrees(cone):.1f} deg, last second {np.degrees(late.min()):.3f}..{np.degrees(late.max()):.3f} deg, "
          f"allowed {np.degrees(cone + allowed):.2f} deg")
    assert np.abs(late - (cone + allowed)).max() <= 1e-3


@pytest.mark.parametrize("k", [1e2, 1e3, 1e4, 1e5])
def test_stiff_strings_stable_at_30hz(hung, k):
    """The stable range of the linearised implicit step: the hung puppet, kicked with
    random joint velocities, stays bounded and settles at 30 Hz for string stiffness up
    to 1e5 N/m (explicit Euler would need h < 2 / sqrt(k / m), ~2 ms at k = 1e3 N/m on
    a 25 g forearm). ``benchmarks/puppet_stability.py`` prints the full table."""
    model, solver, control = hung
    model.spring_stiffness.fill_(k)
    try:
        rng = np.random.default_rng(1)
        end = _run(model, solver, control, 3.0, qd0=rng.normal(size=model.qd_count))
    finally:
        model.spring_stiffness.fill_(500.0)
    qd = end.joint_qd.numpy()[0]
    print(f"k={k:.0e}: max |qd| after 3 s {np.abs(qd).max():.3g}")
    assert np.all(np.isfinite(qd))
    assert np.abs(qd).max() < 1.0
