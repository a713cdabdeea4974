"""Constants that run off between the windows' stages (``fitting.calibration_fit.RUNAWAY_LOG``).

In a stage of short windows a weakly informed constant can be carried to 0 (its log to minus
hundreds, where ``exp`` underflows and its derivative vanishes); no later stage brings it back,
and the run then ended with exit code 4 ("not identifiable") although the session determines it.
Found on a user-style problem (a 1 s sway with per-string constants drawn 0.3x-3x from the
scene's, 0.3 mm noise): ``k_d[hand_left]`` (4.32 N s/m) ran to 0 in the one-step windows and stayed
there (reduced chi^2 1.04, exit 4). Now the next stage starts it again from its start value when
that fits the next stage's windows better, and a constant that ends run off is named in a warning.
"""

import numpy as np
import pytest
import warp as wp

pytest.importorskip("jax")
pytest.importorskip("optimistix")

from fitting.calibration_fit import (RUNAWAY_LOG, calibrate_session, ran_off, restart_runaways,  # noqa: E402
                                     retry_runaways)
from fitting.calibration_report import format_table  # noqa: E402
from fitting.calibration_verdict import EXIT_OK, judge_fit  # noqa: E402
from fitting.uncertainty import gauss_newton_uncertainty  # noqa: E402

wp.config.log_level = wp.LOG_WARNING

# The sessions runaways were found on (``benchmarks/bench_calibrate_drawn.py``, seeds 1 and 17: the
# "sway" motion, 1 s, noise seeds 1 and 17): in the first stage, then in the last.
TRUTH = {"k": [205.9, 548.3, 351.2, 177.2, 753.3, 666.2], "k_d": [2.08, 8.46, 1.51, 5.75, 4.32, 2.66]}
TRUTH_17 = {"k": [129.5, 361.7, 206.4, 293.5, 180.6, 448.8], "k_d": [2.22, 1.37, 3.25, 6.55, 1.86, 0.9]}


def _calibrate_sway(folder, truth, seed):
    """A 1 s "sway" session recorded with ``truth`` (0.3 mm / 0.02 N noise, ``seed``), calibrated as
    ``dmarionette calibrate SESSION --noise-position 3e-4`` does."""
    from dmarionette.scene.scene import load_scene
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    text = motion_scene_text("sway", 1.0)
    (folder / "scene.toml").write_text(text)
    scene = load_scene(folder / "scene.toml")
    _, path = record_synthetic_session(scene, text, truth, 1.0, folder / "s.mcap", noise_position=3e-4,
                                       noise_force=0.02, seed=seed, optimization_level=0)
    return calibrate_session(path, params="k,k_d", noise_position=3e-4, optimization_level=0)


class _Quadratic:
    """A stand-in problem: residuals ``theta - target`` (one row per parameter), the last
    parameter bounded."""

    def __init__(self, target):
        self.target = np.asarray(target, dtype=np.float64)
        n = len(self.target)
        self.theta_start = np.zeros(n)
        self.log_bounds = (np.r_[np.full(n - 1, -np.inf), -1.0], np.r_[np.full(n - 1, np.inf), 50.0])
        self.labels = [f"c{i}" for i in range(n)]
        self.calls = 0

    def host_residuals(self, theta):
        self.calls += 1
        return np.asarray(theta, dtype=np.float64) - self.target


def test_ran_off_names_unbounded_constants_beyond_a_factor_1e4_and_non_finite_ones():
    problem = _Quadratic([0.0, 0.0, 0.0, 0.0])
    theta = np.array([-RUNAWAY_LOG - 1e-9, RUNAWAY_LOG * 0.999, -np.inf, 40.0])  # the last is bounded
    assert ran_off(problem, theta) == [0, 2]
    assert ran_off(problem, np.array([np.nan, 0.0, 0.0, 0.0])) == [0]


def test_a_runaway_is_started_again_only_when_that_fits_better():
    problem = _Quadratic([0.5, 1.0, 0.0])
    theta = np.array([-700.0, 1.0, 0.0])  # c0 ran to exp(-700) ~ 0; the start (0) is near its target
    restarted, labels, rollouts = restart_runaways(problem, theta)
    assert labels == ["c0"] and rollouts == 2 == problem.calls
    assert np.array_equal(restarted, [0.0, 1.0, 0.0])
    # a constant that really lies far out (its target too): kept where the stage put it
    problem = _Quadratic([-700.0, 1.0, 0.0])
    kept, labels, rollouts = restart_runaways(problem, theta)
    assert labels == [] and rollouts == 2 and kept is theta
    # nothing ran off: no rollout
    problem = _Quadratic([0.5, 1.0, 0.0])
    same, labels, rollouts = restart_runaways(problem, np.array([0.4, 1.0, 0.0]))
    assert labels == [] and rollouts == 0 == problem.calls


def test_after_the_last_stage_a_runaway_is_fitted_again_and_the_lower_loss_kept():
    problem = _Quadratic([0.5, 1.0, 0.0])
    theta = np.array([-700.0, 1.0, 0.0])
    starts = []

    def run_fit(start):  # a stand-in solver that lands on the target from the restarted point
        starts.append(np.array(start))
        return {"theta": problem.target.copy(), "steps": 3, "converged": True}

    kept, retry, labels, rollouts = retry_runaways(problem, theta, run_fit, judged=3)
    assert labels == ["c0"] and rollouts == 2 and retry["kept"] and np.array_equal(kept, problem.target)
    assert np.array_equal(starts[0], [0.0, 1.0, 0.0])
    # a constant that really lies far out: the retry from its start fits worse and is not kept
    far = _Quadratic([-700.0, 1.0, 0.0])
    kept, retry, labels, _ = retry_runaways(far, theta, lambda start: {"theta": start}, judged=3)
    assert not retry["kept"] and kept is theta
    # only the judged constants (not the nuisance unknowns after them) are retried
    kept, retry, labels, rollouts = retry_runaways(problem, theta, run_fit, judged=0)
    assert retry is None and labels == [] and rollouts == 0


def test_a_constant_that_ends_run_off_is_named_in_a_warning():
    rng = np.random.default_rng(0)
    jac = rng.standard_normal((40, 2))
    residuals = rng.standard_normal(40)
    uncertainty = gauss_newton_uncertainty(jac, residuals, np.array([300.0, 1e-300]))
    verdict = judge_fit(residuals, {"bodies": (0, 40)}, {"bodies": 1e-3}, ["k[a]", "k_d[a]"], uncertainty, True,
                        "converged", ran_off={"k_d[a]": (3.0, 0.0)})
    assert verdict.ran_off == {"k_d[a]": (3.0, 0.0)}
    assert any(w.startswith("ran off: k_d[a] 3 -> 0 ") for w in verdict.warnings), verdict.warnings
    # a warning only: the exit code is decided by the chi^2, whiteness and identifiability tests
    plain = judge_fit(residuals, {"bodies": (0, 40)}, {"bodies": 1e-3}, ["k[a]", "k_d[a]"], uncertainty, True,
                      "converged")
    assert verdict.exit_code == plain.exit_code and plain.ran_off == {}


def test_the_session_it_was_found_on_is_now_fitted(tmp_path):
    result = _calibrate_sway(tmp_path, TRUTH, seed=1)
    stages = result.cost["stages"]
    print(f"\nstages {stages}; fitted {np.round(result.fitted, 3)}; reduced chi^2 {result.verdict.reduced_chi2}")
    assert stages[0]["restarted"] == [] and stages[1]["restarted"] == ["k_d[hand_left]"]
    assert "stage 2: started k_d[hand_left] again" in format_table(result)
    assert result.verdict.exit_code == EXIT_OK and not result.verdict.ran_off, result.verdict.warnings
    truth = np.concatenate([TRUTH["k"], TRUTH["k_d"]])
    z = (result.fitted - truth) / result.uncertainty.standard_error
    assert np.all(np.abs(z) <= 3.0), z  # measured: at most 2.16


def test_a_runaway_in_the_last_stage_is_fitted_again(tmp_path):
    """Seed 17 of the drawn sessions: ``k_d[hand_right]`` (0.9 N s/m) ran to 1.7e-8 in the last
    stage (exit 4, "not identifiable"); the last stage again from its start value fits it."""
    result = _calibrate_sway(tmp_path, TRUTH_17, seed=17)
    stages = result.cost["stages"]
    print(f"\nstages {stages}; fitted {np.round(result.fitted, 3)}; reduced chi^2 {result.verdict.reduced_chi2}")
    assert stages[-1].get("retry") and stages[-1]["kept"] and stages[-1]["restarted"] == ["k_d[hand_right]"]
    assert "the last stage again with k_d[hand_right]" in format_table(result)
    assert result.verdict.exit_code == EXIT_OK and not result.verdict.ran_off, result.verdict.warnings
    truth = np.concatenate([TRUTH_17["k"], TRUTH_17["k_d"]])
    z = (result.fitted - truth) / result.uncertainty.standard_error
    assert np.all(np.abs(z) <= 3.0), z  # measured: at most 1.94
