"""Calibration cost: time and peak memory to fit 12 constants (eq. 2 ``k``, ``k_d`` of the six
strings) to a 10 s session, on one core; and what each solver costs.

Run:  python benchmarks/bench_calibrate.py [--seconds 10] [--scene hanging] [--targets both]
      python benchmarks/bench_calibrate.py --compare [--seconds 1.5 --scene examples/calibration_scene.toml]
      python benchmarks/bench_calibrate.py --suite [--fast-compile]

The session is simulated first (not timed) with constants 5-17 % away from the scene's, a
different one per string, with 0.1 mm noise on body coordinates and 0.01 N on forces
(:func:`fitting.synthetic_session.record_synthetic_session`). The calibration then starts from
the scene's constants and runs in a child process pinned to one CPU core (``sched_setaffinity``;
XLA's CPU thread pool limited to one thread; Warp's CPU kernels are single-threaded), so its
peak resident memory (``ru_maxrss``) is its own. Timed: everything ``dmarionette calibrate``
does (reading the session, building the model with optimised kernels already compiled and
cached by a warm-up run, the fit, the uncertainty, the residuals), ``--repeats`` times; the
median is reported.

``--suite`` calibrates the five fast sessions of ``fitting.synthetic_scenes.SUITE`` (issue #14's
hard cases, the test suite's) twice, with one rollout (``window=0``, the method before the issue)
and with the default multiple shooting, from the scene's constants, and prints per session the
exit code, steps, rollouts, seconds, the largest error in standard errors, the largest
relative errors of ``k`` and ``k_d``, the reduced chi-squared and the whiteness test's ``z`` per target.

``--compare`` times the pieces on the session instead: one forward rollout and one backward
pass (median of repeats), and each solver: ``lm-fd`` and ``bfgs`` to convergence, ``lm-bwd``
for ``--bwd-steps`` steps on ``--rows`` residuals (one backward pass per residual per step).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_support import time_forward_backward

ROOT = Path(__file__).resolve().parent.parent
FACTORS = {"k": [1.10, 0.92, 1.05, 0.88, 1.17, 0.95], "k_d": [1.13, 0.87, 1.03, 0.93, 1.08, 0.9]}


def _one_core() -> None:
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})


def record(scene_name: str, seconds: float, path: Path, level: int) -> dict:
    import numpy as np
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import dmarionette as dm
    from fitting.synthetic_session import record_synthetic_session

    scene = dm.load_scene(scene_name)
    truth = {name: (np.array([getattr(s, field) for s in scene.strings]) * np.array(FACTORS[name])).tolist()
             for name, field in (("k", "tie_stiffness"), ("k_d", "tie_damping"))}
    start = time.perf_counter()
    trajectory, _ = record_synthetic_session(scene, Path(scene.source).read_text(), truth, seconds, path,
                                             noise_position=1e-4, noise_force=1e-2, optimization_level=level)
    return {"truth": truth, "record_seconds": time.perf_counter() - start,
            "taut_fraction": float(trajectory.string_taut.mean()), "session_bytes": path.stat().st_size}


def calibrate_child(session: Path, targets: str, level: int, solver: str) -> dict:
    """Runs in the child: one timed calibration; returns its numbers."""
    _one_core()
    import resource

    import numpy as np
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from fitting.calibration_fit import calibrate_session

    start = time.perf_counter()
    result = calibrate_session(session, targets=targets, params="k,k_d", solver=solver, noise_position=1e-4,
                               noise_force=1e-2, optimization_level=level)
    seconds = time.perf_counter() - start
    return {"seconds": seconds, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "steps": result.solver_steps, "converged": result.converged, "cost": result.cost,
            "jacobian": result.jacobian, "fitted": result.fitted.tolist(),
            "standard_error": result.uncertainty.standard_error.tolist(), "labels": result.labels,
            "condition_number": result.uncertainty.condition_number, "rms_before": result.rms_before,
            "rms_after": result.rms_after, "residuals": int(result.cost["residual_count"]),
            "cpu_affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "load_average": os.getloadavg()}


def compare(session: Path, targets: str, level: int, rows: int, bwd_steps: int, repeats: int) -> dict:
    """Costs of the pieces and of each solver on one session (in this process, one core)."""
    _one_core()
    import dataclasses

    import numpy as np
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from fitting.calibrate import CalibrationProblem, parse_parameters
    from fitting.calibration_data import read_calibration_data
    from fitting.calibration_fit import fit_problem

    data = read_calibration_data(session, targets)
    problem = CalibrationProblem(data, parse_parameters("k,k_d", data), noise_position=1e-4, noise_force=1e-2,
                                 optimization_level=level)
    inputs = dataclasses.replace(problem.base, **problem.constants(problem.theta_start))
    engine = problem.engine
    engine.forward(inputs)
    cot = {"body_pos": np.ones(engine.output_shapes["body_pos"])}
    engine.backward(cot)  # compiles the adjoint kernels
    forward, backward = time_forward_backward(engine, inputs, cot, repeats)
    out = {"session": str(session), "targets": targets, "residuals": problem.residual_count,
           "puppet_steps": data.puppet_steps, "forward_s": statistics.median(forward),
           "backward_s": statistics.median(backward), "solvers": {}, "load_average": os.getloadavg()}
    for solver, steps in (("lm-fd", 50), ("bfgs", 200), ("lm-bwd", bwd_steps)):
        fit = fit_problem(problem, solver=solver, max_steps=steps, rows=rows)
        truth_error = None
        meta = data.session.extra_metadata.get("synthetic")
        if meta:
            truth = np.concatenate([meta["truth"]["k"], meta["truth"]["k_d"]])
            truth_error = (np.abs(np.exp(fit["theta"]) - truth) / truth).max()
        out["solvers"][solver] = {k: fit[k] for k in ("steps", "converged", "forward_passes", "backward_passes",
                                                     "seconds")}
        out["solvers"][solver]["rows"] = None if fit["rows"] is None else len(fit["rows"])
        out["solvers"][solver]["max_relative_error"] = None if truth_error is None else float(truth_error)
        out["solvers"][solver]["seconds_per_step"] = fit["seconds"] / max(fit["steps"], 1)
    return out


def suite(level: int) -> list[dict]:
    """One rollout against the default windows on every session of the suite (this process)."""
    import numpy as np
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from fitting.calibration_fit import calibrate_session
    from fitting.synthetic_scenes import SUITE, SUITE_NOISE, record_suite_session

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for i, name in enumerate(SUITE):
            _, _, path = record_suite_session(name, Path(folder) / f"{name}.mcap", seed=10 + i,
                                              optimization_level=level)
            truth = np.concatenate([SUITE[name][2]["k"], SUITE[name][2]["k_d"]])
            for method, window in (("one rollout", 0), ("windows (default)", "default")):
                result = calibrate_session(path, targets="both", window=window, optimization_level=level,
                                           noise_position=SUITE_NOISE[0], noise_force=SUITE_NOISE[1])
                error = result.fitted / truth - 1.0
                se = result.uncertainty.standard_error
                rows.append({"session": name, "seconds_long": SUITE[name][1], "method": method,
                             "exit_code": result.verdict.exit_code, "steps": result.solver_steps,
                             "rollouts": result.cost["forward_passes"], "seconds": round(result.cost["seconds"], 1),
                             "max_error_in_se": float(np.max(np.abs(result.fitted - truth) / se)),
                             "max_rel_error_k": float(np.abs(error[:6]).max()),
                             "max_rel_error_k_d": float(np.abs(error[6:]).max()),
                             "reduced_chi2": result.verdict.reduced_chi2,
                             "whiteness_z": {t: None if w is None else round(w["z"], 2)
                                             for t, w in result.verdict.whiteness.items()},
                             "load_average": os.getloadavg()})
                print(json.dumps(rows[-1]), file=sys.stderr)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="session length [s] (default 10)")
    parser.add_argument("--scene", default="hanging", help="scene of the session (default hanging)")
    parser.add_argument("--targets", default="both", choices=["bodies", "feedback", "both"])
    parser.add_argument("--solver", default="lm-fd", choices=["lm-fd", "lm-bwd", "bfgs"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    parser.add_argument("--compare", action="store_true", help="time the pieces and every solver instead")
    parser.add_argument("--suite", action="store_true",
                        help="one rollout against the default windows on the five fast sessions of the test suite")
    parser.add_argument("--rows", type=int, default=48, help="residuals of lm-bwd (--compare)")
    parser.add_argument("--bwd-steps", type=int, default=2, help="steps of lm-bwd timed (--compare)")
    parser.add_argument("--session", type=Path, default=None, help="(internal) calibrate this session in a child")
    args = parser.parse_args()
    level = 0 if args.fast_compile else 2
    if args.session is not None:
        print(json.dumps(calibrate_child(args.session, args.targets, level, args.solver)))
        return
    if args.suite:
        print(json.dumps(suite(level), indent=2))
        return
    with tempfile.TemporaryDirectory() as folder:
        session = Path(folder) / "session.mcap"
        recorded = record(args.scene, args.seconds, session, level)
        print(f"session: {args.scene}, {args.seconds} s, {recorded['session_bytes'] / 1e6:.1f} MB, recorded in "
              f"{recorded['record_seconds']:.1f} s; strings taut {100 * recorded['taut_fraction']:.1f} % of the time",
              file=sys.stderr)
        if args.compare:
            print(json.dumps(compare(session, args.targets, level, args.rows, args.bwd_steps, args.repeats), indent=2))
            return
        command = [sys.executable, __file__, "--session", str(session), "--targets", args.targets,
                   "--solver", args.solver] + (["--fast-compile"] if args.fast_compile else [])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        subprocess.run(command, check=True, env=env, capture_output=True)  # warm-up: kernels, caches
        runs = []
        for _ in range(args.repeats):
            done = subprocess.run(command, check=True, env=env, capture_output=True, text=True)
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        truth = recorded["truth"]["k"] + recorded["truth"]["k_d"]
        last = runs[-1]
        errors = [abs(f - t) / t for f, t in zip(last["fitted"], truth)]
        z = [abs(f - t) / s for f, t, s in zip(last["fitted"], truth, last["standard_error"])]
        print(json.dumps({
            "scene": args.scene, "session_seconds": args.seconds, "targets": args.targets, "solver": args.solver,
            "residuals": last["residuals"], "seconds_median": statistics.median(r["seconds"] for r in runs),
            "seconds_all": [round(r["seconds"], 2) for r in runs],
            "peak_rss_mib_max": max(r["peak_rss_mib"] for r in runs), "steps": last["steps"],
            "converged": last["converged"], "fit_cost": last["cost"], "uncertainty_jacobian": last["jacobian"],
            "condition_number": last["condition_number"], "max_relative_error_k": max(errors[:6]),
            "max_relative_error_k_d": max(errors[6:]), "max_error_in_standard_errors": max(z),
            "rms_before": last["rms_before"], "rms_after": last["rms_after"],
            "load_average": [r["load_average"] for r in runs], "cpu_affinity": last["cpu_affinity"],
        }, indent=2))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
