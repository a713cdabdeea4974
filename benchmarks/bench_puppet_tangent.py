"""Benchmark: the puppet step's tangent (forward-mode) kernels for P directions against the primal kernels.

One "step" here is the three generated kernels of a puppet step (kinematics, dynamics with
joint limits, integration; without the applied forces, point springs and contacts: ``--step``
adds them). Primal: the three kernels of ``articulation_codegen``. Tangent: their
``_tangent`` kernels (``articulation_tangent``) for P directions, which also compute the
primal values (one launch per kernel for the step and all P directional derivatives).
Each is captured as a Warp CPU graph of ``--count`` steps and replayed ``--repeats``
times; reported: the median thread CPU time per step, and the ratio against the primal
with issue 13's target ``1 + 0.5 P``.

``--step``: also the whole puppet step, ``SolverArticulation.step`` against
``PuppetStepTangent.step``, with two point springs and the smooth ground contact placed under
the lowest body (``tests/articulation/test_puppet_step_tangent.py``'s setup): the contacts'
interleaved tangent kernel recomputes its primal per direction, and the row
``contacts kept`` is the step taking a trial pass's kept contact tangents (the marionette's
puppet step, ``grad/marionette_tangent``: only the contacts' primal evaluated again).

Usage::

    .venv/bin/python benchmarks/bench_puppet_tangent.py [--worlds 16] [--opt 2] [--count 200] [--repeats 9] \\
        [--directions 1 4 12 16] [--per-kernel] [--step]

The tangent module compiles once per topology and optimisation level (cached on disk).
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import warp as wp
from bench_support import graph_cost

from dmarionette.articulation.solver import ContactSettings, SolverArticulation, build_articulation_model
from dmarionette.articulation.step_tangent import PuppetStepTangent
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
    parser.add_argument("--step", action="store_true", help="also the whole step with springs and contact")
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
    if args.step:
        whole_step(args)
    if args.per_kernel:
        P = args.directions[-1]
        ta = _tangent_arrays(base, P, rng)
        print(f"\nper kernel, P = {P}:\n| kernel | primal us | tangent us | x primal |\n| --- | --- | --- | --- |")
        for n in ("eval_body_kinematics", "solve_body_dynamics", "integrate_joint_coordinates"):
            a = graph_cost(_launcher(getattr(primal, n), base, args.worlds), args.count, args.repeats)
            b = graph_cost(_launcher(getattr(tangent, n + "_tangent"), ta, args.worlds), args.count, args.repeats)
            print(f"| {n} | {a * 1e6:.1f} | {b * 1e6:.1f} | {b / a:.2f} |", flush=True)


def whole_step(args) -> None:
    """The ``--step`` table (module doc)."""
    q0 = np.tile(build_articulation_model(load_puppet()).q_rest, (args.worlds, 1))
    probe = build_articulation_model(load_puppet())
    s = probe.state(args.worlds)
    s.joint_q.assign(q0)
    SolverArticulation(probe, optimization_level=args.opt).eval_kinematics(s)
    ground = float(s.body_pos.numpy()[..., 1].min()) + 0.02
    m = build_articulation_model(load_puppet(), springs=(("head", 300.0, 2.0), ("hand_left", 150.0, 1.0)),
                                 contacts=ContactSettings(ground=True, smooth=True, ground_height=ground))
    solver = SolverArticulation(m, optimization_level=args.opt)
    state_in, state_out, control = m.state(args.worlds), m.state(args.worlds), m.control(args.worlds)
    state_in.joint_q.assign(q0)
    control.spring_anchor_pos.assign(np.array([[0.0, 0.62, 0.02], [0.12, 0.3, 0.05]])[None].repeat(args.worlds, 0))
    one = graph_cost(lambda: solver.step(state_in, state_out, control, H), args.count, args.repeats)
    print(f"\nwhole step, springs and smooth ground contact ({m.spring_count} springs, "
          f"{solver.contacts.point_count} contact points): load {os.getloadavg()[0]:.2f}")
    print("| step | us/step | x primal | target 1 + 0.5 P |")
    print("| --- | --- | --- | --- |")
    print(f"| primal (SolverArticulation.step) | {one * 1e6:.1f} | 1.00 | |")
    rng = np.random.default_rng(1)
    for P in args.directions:
        jvp = PuppetStepTangent(solver, P, args.worlds, args.opt)
        t_in, t_out, tc = jvp.tangent_state(), jvp.tangent_state(), jvp.control_tangent()
        t_in.joint_q.assign(rng.normal(size=t_in.joint_q.shape) * 1e-3)
        t_in.joint_qd.assign(rng.normal(size=t_in.joint_qd.shape) * 1e-3)
        jvp.eval_contacts(jvp.workspace, jvp.body_tangents(), wp.float64(H), keep=True)  # something kept
        for label, kept in (("", False), (", contacts kept", True)):
            cost = graph_cost(lambda: jvp.step(state_in, t_in, state_out, t_out, control, tc, H, contacts_kept=kept),
                              args.count, args.repeats)
            print(f"| tangent, P = {P}{label} | {cost * 1e6:.1f} | {cost / one:.2f} | {1 + 0.5 * P:.1f} |", flush=True)


if __name__ == "__main__":
    main()
