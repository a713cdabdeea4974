"""The calibration's finite-difference Jacobian from one batched rollout (issue #16 item 1, #14 item 4).

``CalibrationProblem.fd_jacobian`` runs its ``n + 1`` (central: ``2 n + 1``) rollouts as the worlds
of one batched marionette. The worlds do not interact, so the result must be exactly the
Jacobian of the rollouts run one at a time (the method before), with one-step windows, longer
windows and one rollout; and several sessions stack their batches as they stack residuals.
The session is the suite's 1 s ``sway`` (``fitting.synthetic_scenes``: 10 particles per string,
paper rates, joint limits on), the constants 5 % off the scene's.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from fitting.calibrate import CalibrationProblem, parse_parameters
from fitting.calibration_data import read_calibration_data
from fitting.calibration_sessions import SessionSpec, StackedProblem
from fitting.synthetic_scenes import SUITE_NOISE, record_suite_session

wp.config.log_level = wp.LOG_WARNING


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    _, _, path = record_suite_session("sway", tmp_path_factory.mktemp("batched") / "sway.mcap", optimization_level=0)
    return read_calibration_data(path, "both")


def _one_at_a_time(problem, theta, step):
    value = problem.host_residuals(theta)
    jacobian = np.empty((len(value), len(theta)))
    for j in range(len(theta)):
        up = theta.copy()
        up[j] += step
        jacobian[:, j] = (problem.host_residuals(up) - value) / step
    return value, jacobian


@pytest.mark.parametrize("window", [1, 10, None], ids=["one_step_windows", "ten_step_windows", "one_rollout"])
def test_the_batched_jacobian_is_the_one_at_a_time_jacobian(data, window):
    problem = CalibrationProblem(data, parse_parameters("k,k_d", data), optimization_level=0, window_steps=window,
                                 noise_position=SUITE_NOISE[0], noise_force=SUITE_NOISE[1])
    theta = problem.theta_start + 0.05
    before = problem.counts["forward"]
    value, jacobian = problem.fd_jacobian(theta, central=False)
    assert problem.counts["forward"] - before == 13  # n + 1 rollouts, in one batch
    want_value, want = _one_at_a_time(problem, theta, 1e-6)
    assert np.array_equal(value, want_value)
    assert np.array_equal(jacobian, want)
    assert np.all(np.any(jacobian != 0.0, axis=0))  # every constant moves the residuals


def test_several_sessions_stack_their_batches(data):
    params = parse_parameters("k,k_d", data)
    specs = [SessionSpec(data, params, noise_position=SUITE_NOISE[0], noise_force=SUITE_NOISE[1],
                         optimization_level=0, window_steps=3) for _ in range(2)]
    stacked = StackedProblem(specs)  # in this process
    theta = stacked.theta_start - 0.03
    value, jacobian = stacked.fd_jacobian(theta)  # central
    want_value = stacked.host_residuals(theta)
    assert np.array_equal(value, want_value)
    column = (stacked.host_residuals(theta + 1e-5 * np.eye(len(theta))[4])
              - stacked.host_residuals(theta - 1e-5 * np.eye(len(theta))[4])) / 2e-5
    assert np.array_equal(jacobian[:, 4], column)


def test_the_secant_solver_says_when_its_budget_ran_out_and_converges_when_given_one(data):
    """``lm-fd`` (``fitting.calibration_lm``): one Jacobian (13 rollouts), then one rollout per step.
    From the scene's constants (truths 0.4x-1.9x away) one step's budget (4 trial points) is not
    enough, and it says so; with the default budget it converges to the least-squares optimum,
    where the Gauss-Newton step from a fresh Jacobian is below a tenth of every standard error."""
    from fitting.calibration_fit import fit_problem

    problem = CalibrationProblem(data, parse_parameters("k,k_d", data), optimization_level=0, window_steps=10,
                                 noise_position=SUITE_NOISE[0], noise_force=SUITE_NOISE[1])
    short = fit_problem(problem, solver="lm-fd", max_steps=1)
    assert not short["converged"] and short["message"] == "not converged: the step budget ran out"
    assert short["steps"] == 4
    fit = fit_problem(problem, solver="lm-fd")
    assert fit["converged"], fit["message"]
    value, jacobian = problem.fd_jacobian(fit["theta"], central=True)
    step = np.linalg.lstsq(jacobian, -value, rcond=None)[0]  # Gauss-Newton step, log space
    sd = np.sqrt(np.diag(np.linalg.inv(jacobian.T @ jacobian)))
    print(f"\n{fit['steps']} steps, {fit['forward_passes']} rollouts; largest remaining step "
          f"{np.max(np.abs(step) / sd):.3f} standard errors")
    assert np.all(np.abs(step) <= 0.1 * sd)


def test_a_trial_point_that_blows_up_gives_nan_residuals_not_an_error(data):
    """A solver's trial point far out (one string's ``k_d`` at e^41 N s/m, where the ten-step
    windows' states go non-finite) is a rejected step, not a traceback: the residuals are NaN
    (``levenberg_marquardt`` then raises its damping). In a batch, only that world is NaN; the
    others are bit for bit their one-world rollouts."""
    problem = CalibrationProblem(data, parse_parameters("k,k_d", data), optimization_level=0, window_steps=10,
                                 noise_position=SUITE_NOISE[0], noise_force=SUITE_NOISE[1])
    far = problem.theta_start.copy()
    far[8] = 41.46  # log k_d of the third string
    assert np.all(np.isnan(problem.host_residuals(far)))
    near = problem.theta_start + 0.05
    batched = problem.residuals_at([near, far])  # the worlds of one batched rollout
    assert np.array_equal(batched[0], problem.host_residuals(near)) and np.all(np.isfinite(batched[0]))
    assert np.all(np.isnan(batched[1]))
