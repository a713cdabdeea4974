"""Stable range of the puppet step: stable / unstable vs. step size and string stiffness.

The puppet hangs by its six attach points from point spring-dampers (the strings' ends,
paper eq. 2, ``k_d = 1 N s/m``), anchored at the rest positions of the points, and
starts with random joint velocities (1 rad/s scale): the energy available bounds the
physical velocities to a few rad/s (m/s). A run of 3 s (at most 300 steps) is *stable*
when the state stays finite and ``max |qd| < 100``. Compared: the linearised implicit
step (default) and the explicit one (``SolverArticulation(..., implicit=False)``: the
same step with the spring, damping, limit and contact terms left out of the matrix).

Usage::

    .venv/bin/python benchmarks/puppet_stability.py
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dmarionette.articulation.solver import SolverArticulation, build_articulation_model
from dmarionette.scene.puppet import load_puppet

POINTS = ("head", "back", "hand_left", "hand_right", "knee_left", "knee_right")
STEPS = (1.0 / 30.0, 1.0 / 100.0, 1.0 / 1000.0)
STIFFNESS = (1e1, 1e2, 1e3, 1e4, 1e5)


def run(model, solver, control, dt, k, duration=3.0):
    model.spring_stiffness.fill_(k)
    a, b = model.state(), model.state()
    a.joint_qd.assign(np.random.default_rng(1).normal(size=(1, model.qd_count)))
    steps = min(int(round(duration / dt)), 300)
    for _ in range(steps):
        solver.step(a, b, control, dt)
        a, b = b, a
        qd = a.joint_qd.numpy()
        if not np.all(np.isfinite(qd)) or np.abs(qd).max() > 100.0:
            return False
    return True


def main() -> None:
    wp.config.log_level = wp.LOG_WARNING  # no banner
    model = build_articulation_model(load_puppet(), springs=tuple((p, 1.0, 1.0) for p in POINTS))
    rows = []
    for implicit in (True, False):
        solver = SolverArticulation(model, optimization_level=0, implicit=implicit)
        rest = model.state()
        solver.eval_kinematics(rest)
        pos = wp.zeros((1, len(model.point_names)), dtype=wp.vec3d)
        solver.eval_points(rest, pos, wp.zeros_like(pos))
        anchors = pos.numpy()[0][[model.point_names.index(p) for p in POINTS]]
        control = model.control()
        control.spring_anchor_pos.assign(anchors[None])
        for dt in STEPS:
            cells = ["stable" if run(model, solver, control, dt, k) else "**unstable**" for k in STIFFNESS]
            rows.append(f"| {'implicit' if implicit else 'explicit'} | {1.0 / dt:.0f} Hz | " + " | ".join(cells) + " |")
    print("| step | rate | " + " | ".join(f"k = {k:.0e} N/m" for k in STIFFNESS) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in STIFFNESS) + " |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
