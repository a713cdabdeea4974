"""Benchmark: authoring a 2 s, three-keyframe motion on one core (issue 15 target: <= 30 s).

The problem: the ``hanging`` scene at the paper's rates (strings 1 kHz, puppet 30 Hz), the
hand bar free in x, y, z (knots every 0.5 s) and the main bar in height (knots every 1 s);
three keyframes (t = 0.66, 1.32, 1.98 s: both hands; the left hand and left elbow; head
and torso) whose targets are recorded from a reference bar motion, so they are reachable.
``--method`` (default ``lm_fd``: Levenberg-Marquardt, forward-difference Jacobian, hard device
limits) from the scene's still bars, ``--max-steps`` steps at most (default 40).

Reported (JSON on stdout): wall time of each phase (model build and kernel load, the
reference rollout, the solve with its JIT compilation, the simulator's replay and the
exports), rollout passes and their time, the keyframe errors, and the peak resident memory
of the process (``ru_maxrss``; the baseline after importing JAX and Warp is given too).
The process, with all its threads (Warp, XLA), is pinned to one CPU core
(``os.sched_setaffinity``).
With ``--compare-lm`` the same problem without the per-step device terms is also solved
with Levenberg-Marquardt (reverse-mode Jacobian: one backward pass per residual), and
with BFGS for the same problem, so the two costs can be compared.

Usage::

    .venv/bin/python benchmarks/bench_author.py [--particles 50] [--max-steps 40] [--repeats 1]
                                                [--method lm_fd|bfgs|lm|gauss_newton] [--continuation]
                                                [--jacobian secant|fd]
                                                [--jacobians] [--puppet-hz HZ] [--compare-lm]
                                                [--out out/bench_author]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import time
from pathlib import Path

import numpy as np

REFERENCE = {"hand": [[0.03, 0.04, 0.0], [-0.02, 0.05, 0.02], [0.01, 0.03, -0.01], [0.0, 0.02, 0.0]],
             "main": [[0.02], [-0.01]]}
TARGETS = [(0.66, ["hand_left", "hand_right"], [], []), (1.32, ["hand_left"], [], ["elbow_left"]),
           (1.98, ["head"], ["torso"], [])]


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def keyframes_table(particles: int, max_steps: int, device: str = "omni", targets=None,
                    puppet_hz: float | None = None) -> dict:
    head = {"scene": "hanging", "duration": 2.0, "particle_count": particles, "device": device, "force_scale": 0.2}
    if puppet_hz is not None:
        head["puppet_hz"] = puppet_hz
    return {
        "author": head,
        "bars": {"hand": {"knots": [0.0, 0.5, 1.0, 1.5, 2.0], "free": ["x", "y", "z"]},
                 "main": {"knots": [0.0, 1.0, 2.0], "free": ["y"]}},
        "weights": {"smoothness": 0.01},
        "solver": {"max_steps": max_steps},
        "keyframes": targets or [{"t": t, "points": {n: [0.0, 0.5, 0.0] for n in p},
                                  "bodies": {n: [0.0, 0.5, 0.0] for n in b}, "joints": {n: [0.0] for n in j}}
                                 for t, p, b, j in TARGETS],
    }


def record_targets(problem) -> list[dict]:
    import jax.numpy as jnp

    objective = problem.objective
    out = {k: np.asarray(v) for k, v in objective.outputs({k: jnp.array(v) for k, v in REFERENCE.items()}).items()}
    puppet = problem.model.puppet
    targets, joint = [], 0
    for (t, points, bodies, joints), step in zip(TARGETS, objective.steps):
        entry = {"t": t, "points": {n: out["point_pos"][step, puppet.point_names.index(n)].tolist() for n in points},
                 "bodies": {n: out["body_pos"][step, puppet.body_names.index(n)].tolist() for n in bodies},
                 "joints": {}}
        for n in joints:
            entry["joints"][n] = [float(np.degrees(out["joint_q"][step, objective.cols["joint"][joint]]))]
            joint += 1
        targets.append(entry)
    return targets


def run_once(args, out: Path) -> dict:
    import tomli_w

    from fitting import author, build_problem, keyframes_from_table, load_keyframes

    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    placeholder = keyframes_from_table(keyframes_table(args.particles, args.max_steps, puppet_hz=args.puppet_hz),
                                       str(out / "keyframes.toml"))
    reference = build_problem(placeholder)
    targets = record_targets(reference)
    reference_s = time.perf_counter() - start
    path = out / "keyframes.toml"
    path.write_text(tomli_w.dumps(keyframes_table(args.particles, args.max_steps, targets=targets,
                                                   puppet_hz=args.puppet_hz)))
    summary = author(load_keyframes(path), out, progress=not args.quiet, animation=False, method=args.method,
                     continuation=args.continuation, jacobian=args.jacobian)
    result = {
        "method": args.method, "continuation": args.continuation, "jacobian": args.jacobian,
        "reference_s": reference_s, "author_s": summary["seconds"],
        "steps": summary["steps"], "converged": summary["converged"], "status": summary["status"],
        "verdicts": [{"status": v["status"], "errors": v["errors"]} for v in summary["verdicts"]],
        "limits_after": summary["limits_after"],
        "loss_before": summary["loss_before"], "loss_after": summary["loss_after"],
        "max_keyframe_error_before_m": max(e["max_position_error_m"] for e in summary["keyframes_before"]),
        "max_keyframe_error_after_m": max(e["max_position_error_m"] for e in summary["keyframes_after"]),
        "max_joint_error_after_deg": max(e["max_joint_error_deg"] for e in summary["keyframes_after"]),
        "rollouts": summary["rollouts"], "replay_gap": summary["replay_gap"],
        "first_step_s": summary["history"][0]["elapsed"],
        "per_step_s": (summary["history"][-1]["elapsed"] - summary["history"][0]["elapsed"])
        / max(1, len(summary["history"]) - 1),
    }
    if args.compare_lm:
        result["lm_vs_bfgs"] = compare_lm(args, targets)
    if args.jacobians:
        result["jacobians"] = compare_jacobians(load_keyframes(path))
    return result


def compare_jacobians(spec) -> dict:
    """The keyframe errors' Jacobian in the solver's variables z at the start, three ways:
    forward differences (n + 1 forward rollouts, what ``lm_fd`` uses), central differences
    (2n), and reverse mode (one checkpointed backward pass per residual, through JAX); time
    and the largest gap to reverse mode, relative to its largest entry."""
    import jax
    import jax.numpy as jnp

    from fitting import build_problem
    from fitting.author_solve import KeyframeResiduals

    problem = build_problem(spec)
    res = KeyframeResiduals(problem)
    z = res.bounds.z0()
    res.outputs(z)  # the first rollout captures the engine's graphs: not timed
    report = {"coordinates": int(z.size), "residuals": int(len(res.entry_keyframe))}
    weights = res.row_weights()
    start = time.perf_counter()
    r = res.residuals(z)
    forward = res.jacobian(z, r)[:len(weights)] / weights[:, None]
    report["forward_difference_s"] = time.perf_counter() - start
    start = time.perf_counter()
    central = np.zeros_like(forward)
    for j in range(z.size):
        step = np.zeros_like(z)
        step[j] = 1e-5
        central[:, j] = (res.errors(res._rollout(z + step)) - res.errors(res._rollout(z - step))) / 2e-5
    report["central_difference_s"] = time.perf_counter() - start
    objective = problem.objective

    def errors(zz):
        key = objective.keyframe_residuals(objective.outputs(res.bounds.y(zz)))
        return jnp.concatenate([key["point"].ravel(), key["body"].ravel(), key["joint"].ravel()])

    jacobian = jax.jacrev(errors)
    start = time.perf_counter()
    reverse = np.asarray(jacobian(jnp.asarray(z)))
    report["reverse_mode_s"] = time.perf_counter() - start  # (includes tracing; the passes dominate)
    scale = np.abs(reverse).max()
    report["forward_vs_reverse"] = float(np.abs(forward - reverse).max() / scale)
    report["central_vs_reverse"] = float(np.abs(central - reverse).max() / scale)
    return report


def compare_lm(args, targets) -> dict:
    """BFGS and LM on the problem without the per-step device terms (short residual vector)."""
    from fitting import build_problem, keyframes_from_table, solve

    table = keyframes_table(args.particles, args.max_steps, device="none", targets=targets, puppet_hz=args.puppet_hz)
    problem = build_problem(keyframes_from_table(table, "bench_author (device = none)"))
    rows = int(problem.objective.residual_vector(problem.param.initial()).size)
    report = {"residuals": rows}
    for method, steps in (("bfgs", args.max_steps), ("lm", args.lm_steps)):
        before = dict(problem.counts)
        result = solve(problem.objective, problem.param.initial(), method=method, max_steps=steps,
                       progress=not args.quiet, counter=problem.counter, y_scale=problem.param.y_scale())
        report[method] = {"seconds": result.seconds, "steps": len(result.history) - 1,
                          "loss_after": result.history[-1]["loss"],
                          "forward": problem.counts["forward"] - before["forward"],
                          "backward": problem.counts["backward"] - before["backward"],
                          "backward_s": problem.counts["backward_s"] - before["backward_s"]}
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50, help="particles per string (default: the scene's 50)")
    parser.add_argument("--max-steps", type=int, default=40)
    parser.add_argument("--puppet-hz", type=float, default=None,
                        help="puppet rate (default: the scene's 30 Hz; the string rate 1000 couples them fully)")
    parser.add_argument("--lm-steps", type=int, default=4, help="Levenberg-Marquardt steps for --compare-lm")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--compare-lm", action="store_true",
                        help="also optimistix LM against BFGS without the device terms (slow)")
    parser.add_argument("--method", default="lm_fd", choices=["lm_fd", "bfgs", "lm", "gauss_newton"])
    parser.add_argument("--continuation", action="store_true", help="lm_fd: keyframes switched on in time order")
    parser.add_argument("--jacobian", default="secant", choices=["secant", "fd"], help="lm_fd's Jacobian updates")
    parser.add_argument("--jacobians", action="store_true",
                        help="also time forward / central differences and reverse mode for the Jacobian")
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("out") / "bench_author")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    import jax  # noqa: F401
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # stdout carries the JSON
    wp.config.quiet = True
    wp.init()
    baseline = _rss_mib()
    from fitting import enable_compilation_cache

    enable_compilation_cache()  # as the command does
    runs = [run_once(args, args.out / f"run{i}") for i in range(args.repeats)]
    totals = [r["author_s"]["total"] + r["reference_s"] for r in runs]
    print(json.dumps({"particles": args.particles, "max_steps": args.max_steps, "puppet_hz": args.puppet_hz,
                      "repeats": args.repeats,
                      "cpu_affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
                      "load_average": os.getloadavg(), "median_total_s": statistics.median(totals),
                      "median_author_s": statistics.median(r["author_s"]["total"] for r in runs),
                      "baseline_rss_mib": baseline, "peak_rss_mib": _rss_mib(), "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
