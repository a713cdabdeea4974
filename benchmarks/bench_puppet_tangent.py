"""Benchmark: the puppet step's tangent (forward-mode) kernels for P directions against the primal kernels.

One "step" here is the three generated kernels of a puppet step (kinematics, dynamics with
joint limits, integration; no springs, contact or external-force kernels: those have no
tangent yet). Primal: the three kernels of ``articulation_codegen``. Tangent: their
``_tangent`` kernels (``articulation_tangent``) for P directions, which also compute the
primal values (one launch per kernel for the step and all P directional derivatives).
Each is captured as a Warp CPU graph of ``--count`` steps and replayed ``--repeats``
times; reported: the median thread CPU time per step, and the ratio against the primal
with issue 13's target ``1 + 0.5 P``.

Usage::

    .venv/bin/python benchmarks/bench_puppet_tangent.py [--worlds 16] [--opt 2] [--count 200] [--repeats 9] \\
        [--directions 1 4 12 16] [--per-kernel]

The tangent module compiles once per topology and optimisation level (cached on disk).
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import warp as wp
from bench_support import graph_cost

from dmarionette.articulation.solver import build_articulation_model
from dmarionette.kernels.articulation_codegen import build_articulation_kernels
from dmarionette.kernels.articulation_tangent import build_articulation_tangent_kernels
from dmarionette.scene.puppet import load_puppet

H = 1.0 / 30.0


def _launcher(kernel, arrays: dict, worlds: int):
    """A function launching ``kernel`` with ``arrays`` (by parameter name; scalars as given)."""
    args = [arrays[a.label] for a in kernel.adj.args]
    return lambda: wp.launch(kernel, dim=worlds, inputs=args)


def _arrays(model, worlds: int, rng) -> dict:
    nb, nq, nd = model.body_count, model.q_count, model.qd_count
    q = np.tile(model.q_rest, (worlds, 1))
    q[:, 7:] += rng.normal(size=(worlds, nq - 7)) * 0.1
    f64 = wp.float64

    def arr(shape, dtype=f64, value=None):
        return wp.array(np.zeros(shape) if value is None else value, dtype=dtype)

    return dict(
        body_mass=model.body_mass, body_inertia=model.body_inertia, dof_damping=model.dof_damping,
        gravity=model.gravity, dof_limit_lower=model.dof_limit_lower, dof_limit_upper=model.dof_limit_upper,
        limit_stiffness=f64(model.limit_stiffness), limit_damping=f64(model.limit_damping),
        joint_q=arr((worlds, nq), value=q), joint_qd=arr((worlds, nd), value=rng.normal(size=(worlds, nd))),
        body_pos=arr((worlds, nb, 3), wp.vec3d), body_rot=arr((worlds, nb, 4), wp.quatd),
        body_w=arr((worlds, nb, 3), wp.vec3d), body_v=arr((worlds, nb, 3), wp.vec3d),
        body_wrench=arr((worlds, nb, 6), wp.types.vector(6, f64)),
        body_stiffness=arr((worlds, nb, 6, 6), wp.types.matrix((6, 6), f64)),
        joint_f=arr((worlds, nd), value=rng.normal(size=(worlds, nd)) * 0.01),
        h=f64(H), h_implicit=f64(H), joint_qdd=arr((worlds, nd)), joint_qd_out=arr((worlds, nd)),
        joint_q_out=arr((worlds, nq)),
    )


def _tangent_arrays(base: dict, P: int, rng) -> dict:
    """``base`` plus ``direction_count`` and a ``tan_<name>`` array (P leading) for every array of it."""
    out = dict(base, direction_count=P)
    for name, a in base.items():
        if isinstance(a, wp.array) and a.ndim == 2:  # the state, control and output arrays
            out["tan_" + name] = wp.array(rng.normal(size=(P,) + a.numpy().shape) * 1e-3, dtype=a.dtype)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=16)
    parser.add_argument("--opt", type=int, default=2, help="C++ optimisation level of the generated kernels")
    parser.add_argument("--count", type=int, default=200, help="steps per captured graph")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--directions", type=int, nargs="+", default=[1, 4, 12, 16])
    parser.add_argument("--per-kernel", action="store_true", help="also each kernel alone (largest P)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    model = build_articulation_model(load_puppet())
    primal = build_articulation_kernels(model.topology, args.opt)
    tangent = build_articulation_tangent_kernels(model.topology, args.opt)
    rng = np.random.default_rng(0)
    base = _arrays(model, args.worlds, rng)
    _launcher(primal.eval_body_kinematics, base, args.worlds)()  # body poses for the dynamics

    def step_fn(kernels, arrays, suffix=""):
        launches = [_launcher(getattr(kernels, n + suffix), arrays, args.worlds)
                    for n in ("eval_body_kinematics", "solve_body_dynamics", "integrate_joint_coordinates")]

        def step():
            for launch in launches:
                launch()
        return step

    one = graph_cost(step_fn(primal, base), args.count, args.repeats)
    print(f"warp {wp.config.version}, CPU, float64, -O{args.opt}, {args.worlds} worlds, {model.qd_count} DOF, "
          f"joint limits on; median of {args.repeats} replays of {args.count} steps; load: "
          f"{os.getloadavg()[0]:.2f}")
    print("| step | us/step | x primal | target 1 + 0.5 P |")
    print("| --- | --- | --- | --- |")
    print(f"| primal (3 kernels) | {one * 1e6:.1f} | 1.00 | |")
    for P in args.directions:
        ta = _tangent_arrays(base, P, rng)
        cost = graph_cost(step_fn(tangent, ta, "_tangent"), args.count, args.repeats)
        print(f"| tangent, P = {P} | {cost * 1e6:.1f} | {cost / one:.2f} | {1 + 0.5 * P:.1f} |", flush=True)
    if args.per_kernel:
        P = args.directions[-1]
        ta = _tangent_arrays(base, P, rng)
        print(f"\nper kernel, P = {P}:\n| kernel | primal us | tangent us | x primal |\n| --- | --- | --- | --- |")
        for n in ("eval_body_kinematics", "solve_body_dynamics", "integrate_joint_coordinates"):
            a = graph_cost(_launcher(getattr(primal, n), base, args.worlds), args.count, args.repeats)
            b = graph_cost(_launcher(getattr(tangent, n + "_tangent"), ta, args.worlds), args.count, args.repeats)
            print(f"| {n} | {a * 1e6:.1f} | {b * 1e6:.1f} | {b / a:.2f} |", flush=True)


if __name__ == "__main__":
    main()
