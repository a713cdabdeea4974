"""Calibration on the hard sessions of issue #14 (docs/calibration.md, "Windows", "Honest results").

Five synthetic sessions (``fitting.synthetic_scenes.SUITE``): fast bar motions (bobbing and
yawing, sway, rolls and yaws, a dip that brings the feet to the ground), 1.0-1.5 s, 10 particles
per string, per-string constants 0.3x-3x from the scene's 300 N/m and 3 N s/m, noise 0.3 mm and
0.02 N. One rollout from the scene's constants fails on all five by the issue's criteria (bobbing,
rolls and yaws, dip, extremes: a wrong basin, exit code 3; sway: k_d 7.4 % off; measured:
``python benchmarks/bench_calibrate.py --suite``; the bobbing and the rolls-and-yaws cases are
checked here, with their warnings and exit code). The default (multiple shooting, windows of one puppet step, then of 0.33 s) must recover every
constant within 3 standard errors, ``k`` within 1 % and ``k_d`` within 5 %, from the scene's
constants, and say "converged" (exit code 0). Then the ill-posed requests: they must warn and
exit with their codes, not answer confidently.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest
import warp as wp

pytest.importorskip("jax")
pytest.importorskip("optimistix")

from fitting.calibrate import CalibrationProblem, parse_parameters  # noqa: E402
from fitting.calibration_data import read_calibration_data  # noqa: E402
from fitting.calibration_fit import calibrate_session  # noqa: E402
from fitting.calibration_report import format_table, result_summary  # noqa: E402
from fitting.calibration_verdict import EXIT_NOT_EXPLAINED, EXIT_OK, EXIT_UNIDENTIFIABLE  # noqa: E402
from fitting.calibration_windows import joint_velocity_between, recorded_joint_q, window_bounds  # noqa: E402
from fitting.synthetic_scenes import SUITE, SUITE_NOISE, record_suite_session  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
NOISE = {"noise_position": SUITE_NOISE[0], "noise_force": SUITE_NOISE[1]}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("suite")
    out = {}
    for i, name in enumerate(SUITE):
        scene, trajectory, path = record_suite_session(name, folder / f"{name}.mcap", seed=10 + i,
                                                       optimization_level=0)
        out[name] = (scene, trajectory, path)
    return out


def test_the_suite_is_hard_taut_and_the_dip_reaches_the_ground(sessions):
    for name, (scene, trajectory, _) in sessions.items():
        # eq. 2 loaded throughout; "extremes" (k down to 95 N/m, 0.3x) lets strings go slack at times
        assert trajectory.string_taut.all() or (name == "extremes" and trajectory.string_taut.mean() > 0.9), \
            (name, trajectory.string_taut.mean(axis=0))
        speed = np.abs(np.diff(trajectory.body_pos, axis=0)).max() / np.diff(trajectory.frame_time)[0]
        assert speed > 0.3, (name, speed)  # fast motion [m/s]
    _, dip, _ = sessions["dip"]
    foot = [i for i, b in enumerate(dip.body_names) if b.startswith("foot")]
    assert dip.body_pos[:, foot, 1].min() < 0.02  # the feet's centres reach the ground (boxes 4 cm high)


def test_windows_reproduce_one_rollout_exactly_at_the_truth(sessions):
    """Each window starts from the recorded puppet state and the strings handed over: at the true
    constants the windows give the single rollout's residuals (only the added noise)."""
    _, _, path = sessions["bob_yaw"]
    data = read_calibration_data(path, "both")
    truth = SUITE["bob_yaw"][2]
    params = parse_parameters("k,k_d", data)
    single = CalibrationProblem(data, params, start=truth, optimization_level=0, **NOISE)
    r_single = single.host_residuals(single.theta_start)
    single.use_windows(3)
    r_windows = single.host_residuals(single.theta_start)
    # the puppet restarts from the recorded joint_q (float64 in the file) and the velocity that maps
    # the previous frame to it: equal to the rollout's own state to round-off
    np.testing.assert_allclose(r_windows, r_single, rtol=0, atol=1e-6)
    m = len(r_single)
    assert abs(np.sqrt(np.mean(r_single**2)) - 1.0) < 5 / np.sqrt(2 * m)


def test_joint_velocity_between_inverts_the_integrator(sessions):
    _, trajectory, path = sessions["roll_yaw"]
    data = read_calibration_data(path, "bodies")
    q = recorded_joint_q(data)
    np.testing.assert_array_equal(q, trajectory.joint_q)
    from dmarionette.marionette.solver import MarionetteModel

    model = MarionetteModel(data.scene, optimization_level=0)
    a, b = model.puppet.state(), model.puppet.state()
    for f in (3, 17, 29):
        qd = joint_velocity_between(model.puppet.topology, q[f - 1], q[f], data.puppet_dt)
        a.joint_q.assign(wp.array(q[f - 1][None], dtype=wp.float64))
        b.joint_qd.assign(wp.array(qd[None], dtype=wp.float64))
        model.puppet_solver.integrate(a, b, data.puppet_dt)
        np.testing.assert_allclose(b.joint_q.numpy()[0], q[f], rtol=0, atol=1e-12)


def test_window_bounds_cover_the_session():
    assert window_bounds(10, 3) == [(0, 3), (3, 6), (6, 10)]
    assert window_bounds(11, 3) == [(0, 3), (3, 6), (6, 9), (9, 11)]
    assert window_bounds(2, 5) == [(0, 2)]
    with pytest.raises(ValueError, match="window_steps: got 0"):
        window_bounds(10, 0)


@pytest.mark.parametrize("name", list(SUITE))
def test_recovers_every_constant_from_the_scene_constants(sessions, name):
    _, _, path = sessions[name]
    truth = np.concatenate([SUITE[name][2]["k"], SUITE[name][2]["k_d"]])
    result = calibrate_session(path, targets="both", params="k,k_d", optimization_level=0, **NOISE)
    assert np.allclose(result.start, [300.0] * 6 + [3.0] * 6)  # the scene's constants
    z = (result.fitted - truth) / result.uncertainty.standard_error
    error = result.fitted / truth - 1.0
    print(f"\n{name}: {result.message}, {result.solver_steps} steps, {result.cost['forward_passes']} rollouts; "
          f"relative error {np.round(error, 4)}; in standard errors {np.round(z, 2)}; "
          f"reduced chi^2 {result.verdict.reduced_chi2}")
    assert result.verdict.exit_code == EXIT_OK and result.converged, result.verdict.warnings
    assert np.all(np.abs(z) <= 3.0), z
    assert np.all(np.abs(error[:6]) < 0.01), error[:6]
    assert np.all(np.abs(error[6:]) < 0.05), error[6:]
    assert all(abs(c - 1.0) < 0.1 for c in result.verdict.reduced_chi2.values())
    # the residuals are white in time (measured z -0.8 .. 1.8 over the five; the limit is 4)
    assert not result.verdict.structured, result.verdict.whiteness


def test_one_rollout_lands_in_a_wrong_basin_and_says_so(sessions):
    """The issue's failure, now reported: one rollout over the bobbing session from the scene's
    constants does not explain the data (residuals many times the noise): exit code 3 and a
    bold warning, not "converged"."""
    _, _, path = sessions["bob_yaw"]
    result = calibrate_session(path, targets="both", params="k,k_d", optimization_level=0, window=0, max_steps=10,
                               **NOISE)
    assert result.verdict.exit_code == EXIT_NOT_EXPLAINED and not result.converged
    assert max(result.verdict.reduced_chi2.values()) > 2.0
    text = format_table(result)
    assert "**WARNING: the fit does not explain the data" in text or "**WARNING: the solver did not converge" in text
    assert "**RESULT:" in text
    assert result_summary(result)["status"]["exit_code"] == EXIT_NOT_EXPLAINED


def test_a_wrong_basin_below_the_chi2_limit_is_caught_by_its_structured_residuals(sessions):
    """One rollout on the bobbing-and-yawing session ends in a wrong basin, tens of standard
    errors off (measured 66). Judged with noise scales given roughly, twice the true ones, its
    reduced chi^2 is below 2 (measured 1.68 / 1.29; with the true scales 6.7 / 5.2): the chi^2
    test alone passes it. Its residuals are slow, not noise: the lag-1 autocorrelation test (no
    noise scale involved) says so, in bold, in calibration.json, with exit code 3. (Measured: z
    22 and 41.) Until issue 13 made the joint limits one-sided this was the rolls-and-yaws
    session at 1.5 times the scales; one rollout now fits that one right (1.7 standard errors)."""
    _, _, path = sessions["bob_yaw"]
    rough = {key: 2.0 * value for key, value in NOISE.items()}
    result = calibrate_session(path, targets="both", params="k,k_d", optimization_level=0, window=0, **rough)
    v = result.verdict
    truth = np.concatenate([SUITE["bob_yaw"][2]["k"], SUITE["bob_yaw"][2]["k_d"]])
    assert np.max(np.abs(result.fitted - truth) / result.uncertainty.standard_error) > 10  # a wrong basin
    assert v.solver_converged and all(c < 2.0 for c in v.reduced_chi2.values()), v.reduced_chi2
    assert set(v.structured) == {"bodies", "feedback"} and all(w["z"] > 6 for w in v.whiteness.values())
    assert v.exit_code == EXIT_NOT_EXPLAINED and not result.converged and not v.explains_data
    assert "**WARNING: the residuals are structured: the fitted simulation does not explain the data" in \
        format_table(result)
    status = result_summary(result)["status"]
    assert status["structured"] == v.structured and status["whiteness"]["bodies"]["structured"]


def test_noise_scales_set_too_small_do_not_pass_as_converged(sessions):
    _, _, path = sessions["sway"]
    result = calibrate_session(path, targets="bodies", params="k", duration=0.5, optimization_level=0,
                               noise_position=SUITE_NOISE[0] / 10, start={"k": SUITE["sway"][2]["k"]})
    assert result.verdict.exit_code == EXIT_NOT_EXPLAINED
    assert 50 < result.verdict.reduced_chi2["bodies"] < 200  # ~ 10^2: the noise is ten times the scale
    assert any("does not explain the data" in w for w in result.verdict.warnings)


def test_string_stiffness_on_a_short_session_is_unidentifiable(sessions, tmp_path):
    """``k_s`` of every string besides ``k`` and ``k_d`` (18 constants) from 0.1 s of body poses:
    string and tie act in series, and three frames do not tell them apart. Infinite intervals
    for the constants of the null directions, their names in the warning, exit code 4. (On 0.2 s
    with both targets the same 18 are identified, to 2-9 %: measured, exit code 0.)"""
    _, _, path = sessions["roll_yaw"]
    result = calibrate_session(path, targets="bodies", params="k,k_d,k_s", duration=0.1, optimization_level=0,
                               **NOISE)
    v = result.verdict
    assert v.exit_code == EXIT_UNIDENTIFIABLE, v.warnings
    assert any(label.startswith("k_s[") for label in v.unidentifiable)
    index = [result.labels.index(label) for label in v.unidentifiable]
    assert np.all(np.isinf(result.uncertainty.standard_error[index]))
    assert v.null_directions and any("not identifiable" in w for w in v.warnings)
    summary = result_summary(result)
    assert any(row["standard_error"] == "inf" for row in summary["constants"])
    from fitting.calibration_report import write_outputs

    files = write_outputs(result, tmp_path / "out")  # the picture with infinite intervals and the warnings
    assert Path(files["plot"]).stat().st_size > 10_000
    text = Path(files["summary"]).read_text()
    assert "Infinity" not in text and "NaN" not in text  # strict JSON: infinite intervals as "inf"


def test_slack_strings_make_their_constants_unidentifiable(sessions, tmp_path):
    """Strings that never pull (a scene whose tie constants do not act: the hand strings with
    ``k_d`` only, the bar held still, very short): exit code 4, not a confident answer."""
    _, _, path = sessions["sway"]
    # Too short: one puppet step of body poses for 12 constants.
    result = calibrate_session(path, targets="bodies", params="k,k_d", duration=0.034, optimization_level=0,
                               **NOISE)
    assert result.verdict.exit_code in (EXIT_UNIDENTIFIABLE, EXIT_NOT_EXPLAINED)
    assert result.verdict.unidentifiable, result.verdict.warnings
    assert "**WARNING: not identifiable" in format_table(result)


def test_all_strings_slack_a_confident_answer_is_a_right_one(tmp_path):
    """Every string slack (1.6 m strings, the puppet standing on the ground): the ties carry
    only the strings' weight and the strings flail on the ground. The constants still act,
    through the strings' weight, and the fit finds them: measured exit code 0, reduced chi^2
    1.06, every constant within 3.0 standard errors of the truth (0.1-1 %). A confident answer
    must be a right one: exit code 0 with every constant within 4 standard errors (with 12
    constants a right fit exceeds that with probability ~1e-3). (Under the two-sided joint-limit
    band of before, issue 13, the body residuals became chaotic in the constants: reduced chi^2
    65, exit code 3 with the warning.)"""
    import dmarionette as dm
    from fitting.synthetic_scenes import motion_scene_text
    from fitting.synthetic_session import record_synthetic_session

    # The puppet stands on the ground (smooth contact), the strings are twice as long as the
    # distance from bar to body point: they hang slack, their weight (20 g) all the ties carry.
    text = motion_scene_text("dip", 0.5).replace("root_position = [0.0, 0.49, 0.0]",
                                                 "root_position = [0.0, 0.39, 0.0]")
    text = re.sub(r'(body_point = "\w+")', r"\1\nlength = 1.6", text)
    scene_path = tmp_path / "slack.toml"
    scene_path.write_text(text)
    scene = dm.load_scene(scene_path)
    trajectory, path = record_synthetic_session(scene, text, {"k": 300.0, "k_d": 3.0}, 0.5, tmp_path / "slack.mcap",
                                                noise_position=SUITE_NOISE[0], optimization_level=0)
    assert trajectory.string_taut.mean() < 0.05  # slack at least 95 % of the time (measured 100 %; 98.6 % under the band)
    result = calibrate_session(path, targets="bodies", params="k,k_d", optimization_level=0, **NOISE)
    v = result.verdict
    truth = np.array([300.0] * 6 + [3.0] * 6)
    z = np.abs(result.fitted - truth) / result.uncertainty.standard_error
    assert v.exit_code == 0 and result.converged and not v.warnings, v.warnings
    assert all(c < 2.0 for c in v.reduced_chi2.values()) and np.all(z < 4.0), (v.reduced_chi2, z)


def test_command_prints_the_warning_and_exits_with_its_code(sessions, tmp_path, capsys):
    from dmarionette.cli import main

    _, _, path = sessions["roll_yaw"]
    code = main(["calibrate", str(path), "--params", "k,k_d,k_s", "--duration", "0.1", "--targets", "bodies",
                 "--noise-position", str(SUITE_NOISE[0]), "--noise-force", str(SUITE_NOISE[1]), "--fast-compile",
                 "--quiet", "--no-picture", "--out", str(tmp_path / "out"),
                 "--start", "k=300,k_d=3,k_s=500"])
    printed = capsys.readouterr().out
    assert code == EXIT_UNIDENTIFIABLE, printed
    assert "**WARNING: not identifiable" in printed and "**RESULT:" in printed
    status = json.loads((tmp_path / "out" / "calibration.json").read_text())["status"]
    assert status["exit_code"] == EXIT_UNIDENTIFIABLE and status["unidentifiable"]


def test_priors_parse_and_refuse_bad_entries():
    from fitting.calibrate import parse_priors

    assert parse_priors("k=300±100,k_d=3+-1") == {"k": (300.0, 100.0), "k_d": (3.0, 1.0)}
    for bad, message in (("k=300", "expected NAME=MEAN±SD"), ("k=a±1", "expected NAME=MEAN±SD"),
                         ("q=1±1", "unknown constant 'q'"), ("k=300±0", "expected positive")):
        with pytest.raises(ValueError, match=message):
            parse_priors(bad)


def test_a_prior_pins_down_what_the_data_do_not(sessions, tmp_path, capsys):
    """The unidentifiable request above (k_s on 0.1 s of body poses) with priors (k_s tight,
    k and k_d broad, ascii +-): every direction is determined; the k_s intervals are finite and no
    wider than the prior's deviation; exit code 0; the priors are printed and written."""
    from dmarionette.cli import main

    _, _, path = sessions["roll_yaw"]
    code = main(["calibrate", str(path), "--params", "k,k_d,k_s", "--duration", "0.1", "--targets", "bodies",
                 "--noise-position", str(SUITE_NOISE[0]), "--prior", "k_s=500+-50,k=300±150,k_d=3+-1.5",
                 "--fast-compile", "--quiet",
                 "--no-picture", "--out", str(tmp_path / "out")])
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert summary["priors"]["k_s"] == {"mean": 500.0, "sd": 50.0}
    assert "prior on k_s: 500 ± 50 N/m" in printed
    rows = {row["label"]: row for row in summary["constants"]}
    for label, row in rows.items():
        if label.startswith("k_s["):
            assert row["standard_error"] != "inf" and row["standard_error"] <= 50.0 * 1.01, row
    assert summary["status"]["unidentifiable"] == []
    assert code == EXIT_OK, printed


def test_frozen_constants_keep_their_start_values(sessions):
    _, _, path = sessions["sway"]
    truth = SUITE["sway"][2]
    result = calibrate_session(path, targets="both", duration=0.5, start=truth, freeze="k[head],k_d[back]",
                               optimization_level=0, **NOISE)
    assert "k[head]" not in result.labels and "k_d[back]" not in result.labels and len(result.labels) == 10
    scene = result.data.scene
    from fitting.calibration_report import calibrated_scene_table

    table = {s["name"]: s for s in calibrated_scene_table(result)["strings"]}
    assert table["head"]["tie_stiffness"] == truth["k"][0] and table["back"]["tie_damping"] == truth["k_d"][1]
    assert result.verdict.exit_code == EXIT_OK, result.verdict.warnings
    assert len(scene.strings) == 6
    with pytest.raises(ValueError, match=r"--freeze: got 'k\[nose\]'"):
        calibrate_session(path, targets="both", duration=0.5, freeze="k[nose]", optimization_level=0)


def test_bounds_hold_and_a_constant_at_its_bound_is_warned_about(sessions):
    """Bounds that exclude the truth (k of the head string is 121 N/m, the bound 200:400): the
    solver keeps every k inside, the ones it leaves at a bound are named in a warning, and the
    fit that cannot reach the truth does not pass as converged."""
    _, _, path = sessions["sway"]
    result = calibrate_session(path, targets="both", duration=0.4, bounds="k=200:400", optimization_level=0,
                               max_steps=15, **NOISE)
    k = result.fitted[:6]
    assert np.all((k >= 200 * (1 - 1e-9)) & (k <= 400 * (1 + 1e-9))), k
    assert "k[head]" in result.verdict.at_bound
    assert any("at a bound" in w for w in result.verdict.warnings)
    assert result.verdict.exit_code != EXIT_OK
    with pytest.raises(ValueError, match=r"--bounds k: got 5.0:1.0"):
        calibrate_session(path, duration=0.5, bounds="k=5:1", optimization_level=0)
