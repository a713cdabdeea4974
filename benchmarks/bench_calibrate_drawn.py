"""Calibration on sessions drawn like a user's, not chosen: does "converged" mean right?

Run:  python benchmarks/bench_calibrate_drawn.py [--sessions 12] [--first-seed 1] [--fast-compile]
      python benchmarks/bench_calibrate_drawn.py --trace 20 [--fast-compile]

Session ``i`` (seed ``first_seed + i``): the motion ``fitting.synthetic_scenes.MOTIONS[seed % 4]``
(bobbing and yawing, sway, rolls and yaws, a dip to the ground), 1.0, 1.2 or 1.5 s, and per string
``k`` and ``k_d`` drawn log-uniformly from 0.3x-3x of the scene's 300 N/m and 3 N s/m; recorded with
0.3 mm noise on the body coordinates and 0.02 N on the forces (``record_synthetic_session``). Each is
calibrated as ``dmarionette calibrate SESSION --noise-position 3e-4`` does it (the bodies, ``k,k_d``,
the default windows, from the scene's constants; ``--targets both`` adds the bars' forces with
``--noise-force 0.02``), in this process. Printed per session: the exit code, steps, seconds, the constants restarted between stages (``calibration_fit.restart_runaways``),
the largest error in standard errors, and the joint test of the errors against the fit's own
covariance: the Mahalanobis distance ``d^T C^-1 d`` of the log-space errors (chi-squared with 12
degrees of freedom if the intervals are right) and its p-value. A run with exit code 0 whose errors
are far outside its intervals is the failure this measures.

``--trace SEED`` looks at one session's joint test (docs/calibration.md, "Sessions drawn, not
chosen"): the sum of squares of the last stage's residuals (scaled by the noise) at the fit and at
the true constants, what the Jacobian at the fit predicts for their difference (``d^T J^T J d``, ``d``
the log-space error; forward steps of 1e-6 and central steps of 1e-5 ... 1e-2), and the residuals'
change per unit along the line from the fit to the truth at fractions 1e-3 ... 1 of it; then the
same session recorded and fitted again with the joint limits off.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DURATIONS = (1.0, 1.2, 1.5)
NOISE = (3e-4, 0.02)  # [m], [N]


def draw(seed: int) -> tuple[str, float, dict]:
    """The motion, length [s] and true constants of session ``seed``."""
    from fitting.synthetic_scenes import MOTIONS

    rng = np.random.default_rng(100 + seed)
    duration = float(rng.choice(DURATIONS))
    span = (math.log(0.3), math.log(3.0))
    truth = {"k": (300.0 * np.exp(rng.uniform(*span, 6))).round(1).tolist(),
             "k_d": (3.0 * np.exp(rng.uniform(*span, 6))).round(2).tolist()}
    return MOTIONS[seed % len(MOTIONS)], duration, truth


def chi2_survival(x: float, dof: int) -> float:
    """``P(X > x)`` for chi-squared with an even number ``dof`` of degrees of freedom (closed form);
    NaN for a distance that is not a finite non-negative number."""
    if not (math.isfinite(x) and x >= 0.0):
        return float("nan")
    half = x / 2.0
    return math.exp(-half) * sum(half ** j / math.factorial(j) for j in range(dof // 2))


def one(seed: int, folder: Path, level: int, targets: str = "bodies") -> dict:
    from dmarionette.scene.scene import load_scene
    from fitting.calibration_fit import calibrate_session
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    motion, duration, truth = draw(seed)
    text = motion_scene_text(motion, duration)
    (folder / f"{seed}.toml").write_text(text)
    scene = load_scene(folder / f"{seed}.toml")
    _, path = record_synthetic_session(scene, text, truth, duration, folder / f"{seed}.mcap", noise_position=NOISE[0],
                                       noise_force=NOISE[1], seed=seed, optimization_level=level)
    start = time.perf_counter()
    result = calibrate_session(path, targets=targets, params="k,k_d", noise_position=NOISE[0], noise_force=NOISE[1],
                               optimization_level=level)
    seconds = time.perf_counter() - start
    true = np.concatenate([truth["k"], truth["k_d"]])
    se = result.uncertainty.standard_error
    z = np.abs(result.fitted - true) / se
    error = np.log(result.fitted) - np.log(true)
    covariance = np.asarray(result.uncertainty.covariance)
    judged = np.all(np.isfinite(se)) and np.all(np.isfinite(covariance))  # not where a constant is unidentifiable
    distance = float(error @ np.linalg.solve(covariance, error)) if judged else float("nan")
    return {"seed": seed, "motion": motion, "seconds_long": duration, "exit_code": result.verdict.exit_code,
            "steps": result.solver_steps, "seconds": round(seconds, 1),
            "restarted": [label for st in result.cost["stages"] for label in st.get("restarted", [])],
            "max_error_in_se": round(float(np.max(z)), 2), "mahalanobis": round(distance, 1),
            "p": round(chi2_survival(distance, len(true)), 3), "load_average": os.getloadavg()[0]}


def trace(seed: int, folder: Path, level: int, limits: bool = True) -> None:
    """Prints the linearity study of session ``seed`` (``--trace``)."""
    from dmarionette.scene.scene import load_scene
    from fitting.calibrate import CalibrationProblem, parse_parameters
    from fitting.calibration_data import read_calibration_data
    from fitting.calibration_fit import calibrate_session
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    motion, duration, truth = draw(seed)
    text = motion_scene_text(motion, duration)
    if not limits:
        text = text.replace("joint_limits = true", "joint_limits = false")
    (folder / "scene.toml").write_text(text)
    _, path = record_synthetic_session(load_scene(folder / "scene.toml"), text, truth, duration, folder / "s.mcap",
                                       noise_position=NOISE[0], noise_force=NOISE[1], seed=seed,
                                       optimization_level=level)
    result = calibrate_session(path, params="k,k_d", noise_position=NOISE[0], optimization_level=level)
    data = read_calibration_data(path, "bodies")
    problem = CalibrationProblem(data, parse_parameters("k,k_d", data, None), noise_position=NOISE[0],
                                 optimization_level=level, window_steps=result.window_steps)
    theta = np.log(result.fitted)
    true = np.log(np.concatenate([truth["k"], truth["k_d"]]))
    d = true - theta
    at_fit, at_truth = problem.host_residuals(theta), problem.host_residuals(true)
    print(f"\nseed {seed} ({motion}, {duration} s), joint limits {'on' if limits else 'off'}: exit "
          f"{result.verdict.exit_code}; sum of squares at the fit {at_fit @ at_fit:.1f}, at the truth "
          f"{at_truth @ at_truth:.1f} (difference {at_truth @ at_truth - at_fit @ at_fit:.1f})")
    steps = [("forward 1e-6", None)] + [(f"central {h:g}", h) for h in (1e-5, 1e-3, 1e-2)]
    for name, h in steps:
        if h is None:
            _, jac = problem.fd_jacobian(theta, central=False)
        else:
            points = [theta] + [theta + sign * h * np.eye(len(theta))[j] for j in range(len(theta)) for sign in (1, -1)]
            values = problem.residuals_at(points)
            jac = np.stack([(values[1 + 2 * j] - values[2 + 2 * j]) / (2 * h) for j in range(len(theta))], axis=1)
        print(f"  Jacobian ({name}): predicts d^T J^T J d = {d @ (jac.T @ jac) @ d:.1f}")
    for t in (1e-3, 1e-2, 0.1, 0.5, 1.0):
        change = np.linalg.norm(problem.host_residuals(theta + t * d) - at_fit) / t
        print(f"  along the line to the truth, fraction {t:g}: residuals change {change:.2f} per unit")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, default=12)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    parser.add_argument("--targets", default="bodies", choices=["bodies", "feedback", "both"],
                        help="what the sessions are fitted to (default bodies, as --noise-position alone)")
    parser.add_argument("--trace", type=int, default=None, metavar="SEED",
                        help="the linearity study of one session's joint test instead (module doc)")
    args = parser.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    level = 0 if args.fast_compile else 2
    if args.trace is not None:
        for limits in (True, False):
            with tempfile.TemporaryDirectory() as folder:
                trace(args.trace, Path(folder), level, limits)
        return
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(args.first_seed, args.first_seed + args.sessions):
            rows.append(one(seed, Path(folder), level, args.targets))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print("| seed | motion, length | exit | steps | s | restarted | largest error in s.e. | d^T C^-1 d (p) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {r['motion']}, {r['seconds_long']} s | {r['exit_code']} | {r['steps']} | {r['seconds']} | "
              f"{', '.join(r['restarted']) or '-'} | {r['max_error_in_se']} | {r['mahalanobis']} ({r['p']}) |")
    ok = [r for r in rows if r["exit_code"] == 0]
    print(f"\n{len(ok)} of {len(rows)} exit 0; of those, the largest error {max((r['max_error_in_se'] for r in ok), default=0)} "
          f"standard errors; joint p below 0.05 in {sum(r['p'] < 0.05 for r in ok)} (expected {0.05 * len(ok):.1f}); "
          f"exit codes {sorted(set(r['exit_code'] for r in rows))}")


if __name__ == "__main__":
    main()
