"""Calibration features of issue #14 item 3 (docs/calibration.md): the held-out validation split
(``--validate``), several sessions sharing the constants, the Huber loss.

The sessions are short (1.2 s) recordings of ``examples/calibration_scene.toml`` with known
per-string eq. 2 constants and Gaussian noise (0.1 mm, 0.01 N), every string taut; fits start
from the scene's 300 N/m and 3 N s/m. Puppet kernels compile with ``optimization_level=0``.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import warp as wp

pytest.importorskip("jax")
pytest.importorskip("optimistix")

import dmarionette as dm  # noqa: E402
from fitting.calibration_data import read_calibration_data  # noqa: E402
from fitting.calibration_fit import calibrate_session  # noqa: E402
from fitting.calibration_report import format_table, result_summary, write_outputs  # noqa: E402
from fitting.calibration_validation import judge_validation  # noqa: E402
from fitting.calibration_verdict import EXIT_NOT_EXPLAINED, EXIT_OK, Verdict  # noqa: E402
from fitting.synthetic_session import record_synthetic_session  # noqa: E402

from tests.support.calibration_problem import (  # noqa: E402
    NOISE_FORCE, NOISE_POSITION, SCENE, TRUTH, record_motion)

wp.config.log_level = wp.LOG_WARNING
DURATION = 1.2
START = {"k": 300.0, "k_d": 3.0}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    scene = dm.load_scene(SCENE)
    path = tmp_path_factory.mktemp("features") / "take.mcap"
    record_synthetic_session(scene, SCENE.read_text(), TRUTH, DURATION, path, noise_position=NOISE_POSITION,
                             noise_force=NOISE_FORCE, seed=3, optimization_level=0)
    return path


def _truth():
    return np.concatenate([TRUTH["k"], TRUTH["k_d"]])


def test_validation_split_fits_the_start_and_predicts_the_held_out_end(session, tmp_path):
    result = calibrate_session(session, params="k,k_d", start=START, noise_position=NOISE_POSITION,
                               known_noise=True, optimization_level=0, validate=0.25, duration=0.9)
    v = result.validation
    # fitted on the first floor(0.75 P) puppet steps, judged on the rest
    whole = read_calibration_data(session, duration=0.9).puppet_steps
    fit = int(np.floor(0.75 * whole))
    assert result.data.puppet_steps == fit and v["rows"]["bodies"] == (whole - fit) * len(result.data.bodies) * 3
    assert v["start_time"] == pytest.approx(result.data.frame_time[-1])
    assert v["fraction"] == pytest.approx((whole - fit) / whole)
    # at the fitted constants the held-out residuals are the added noise: reduced chi^2 ~ 1 with a
    # sampling deviation sqrt(2 / m)
    m = v["rows"]["bodies"]
    assert abs(v["reduced_chi2"]["bodies"] - 1.0) < 5 * np.sqrt(2.0 / m), v["reduced_chi2"]
    assert v["rms"]["bodies"] == pytest.approx(NOISE_POSITION * np.sqrt(v["reduced_chi2"]["bodies"]))
    assert result.verdict.exit_code == EXIT_OK and result.converged, result.verdict.warnings
    se = result.uncertainty.standard_error
    assert np.all(np.abs(result.fitted - _truth()) <= 3 * se), (result.fitted - _truth()) / se
    text = format_table(result)
    assert f"validation: held out the last {100 * v['fraction']:.3g} % (t > {v['start_time']:.4g} s)" in text
    assert "held-out RMS residual, bodies" in text
    files = write_outputs(result, tmp_path / "out")
    summary = json.loads(Path(files["summary"]).read_text())
    assert summary["validation"]["reduced_chi2"]["bodies"] == pytest.approx(v["reduced_chi2"]["bodies"])
    assert summary["status"]["validation"]["start_time"] == pytest.approx(v["start_time"])
    assert Path(files["plot"]).stat().st_size > 10_000


def test_constants_that_do_not_predict_the_held_out_part_fail_validation(session):
    """A wrong prior holds k far from the truth: the held-out end is not explained, it is said in
    a warning of its own, and the exit code is 3."""
    result = calibrate_session(session, params="k:shared", start={"k": 300.0}, noise_position=NOISE_POSITION,
                               known_noise=True, optimization_level=0, validate=0.5, prior="k=500±1",
                               window=[1.0 / 3.0], duration=0.6)
    v = result.validation
    assert v["reduced_chi2"]["bodies"] > 2.0
    assert result.verdict.exit_code == EXIT_NOT_EXPLAINED and not result.converged
    assert any("held-out data (--validate)" in w for w in result.verdict.warnings)
    assert "**WARNING: the fit does not explain the held-out data" in format_table(result)
    assert result_summary(result)["status"]["explains_data"] is False


def test_a_failed_validation_alone_turns_a_good_fit_into_exit_code_3():
    verdict = Verdict(solver_converged=True, reduced_chi2={"bodies": 1.0}, noise_ratio={"bodies": 1.0},
                      explains_data=True, unidentifiable=[], null_directions=[], at_bound=[], converged=True,
                      warnings=[], exit_code=EXIT_OK)
    good = {"start_time": 0.9, "fraction": 0.25, "rms": {"bodies": 1e-4}, "reduced_chi2": {"bodies": 1.9},
            "rows": {"bodies": 100}, "residuals": {}}
    judge_validation(verdict, good, {"bodies": 1e-4})
    assert verdict.exit_code == EXIT_OK and verdict.converged and not verdict.warnings
    assert "residuals" not in verdict.validation
    bad = {**good, "reduced_chi2": {"bodies": 2.1}}
    judge_validation(verdict, bad, {"bodies": 1e-4})
    assert verdict.exit_code == EXIT_NOT_EXPLAINED and not verdict.converged and not verdict.explains_data
    assert len(verdict.warnings) == 1 and "reduced chi^2 2.1 > 2" in verdict.warnings[0]


@pytest.mark.parametrize("fraction", [0.0, 1.0, -0.1, 0.99])
def test_a_bad_validation_fraction_is_refused(session, fraction):
    with pytest.raises(ValueError, match="--validate"):
        calibrate_session(session, start=START, optimization_level=0, validate=fraction, duration=0.1)


def test_command_refuses_a_bad_validation_fraction(session, capsys):
    from dmarionette.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", str(session), "--validate", "1", "--quiet"])
    assert exit_info.value.code == 2
    assert "--validate: got '1'; expected a fraction of the session held out, 0 < F < 1" in capsys.readouterr().err


@pytest.fixture(scope="module")
def two_motions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sessions")
    return [record_motion(folder, "sway", 0.6, 21), record_motion(folder, "roll_yaw", 0.6, 22)]


def test_two_sessions_share_one_set_of_constants(two_motions, tmp_path):
    # windows of 1/3 s alone (the default schedule's last stage; its first is tested elsewhere)
    result = calibrate_session(two_motions, params="k,k_d", start=START, noise_position=NOISE_POSITION,
                               known_noise=True, optimization_level=0, window=[1.0 / 3.0])
    truth, se = _truth(), result.uncertainty.standard_error
    assert result.verdict.exit_code == EXIT_OK and result.converged, result.verdict.warnings
    assert np.all(np.abs(result.fitted - truth) <= 3 * se), (result.fitted - truth) / se
    assert np.all(np.abs(result.fitted[:6] / truth[:6] - 1) < 0.01)
    assert np.all(np.abs(result.fitted[6:] / truth[6:] - 1) < 0.05)
    # both sessions' residuals are stacked: the uncertainty counts every row of both
    rows = [read_calibration_data(p).puppet_steps * 12 * 3 for p in two_motions]
    assert result.uncertainty.residual_count == sum(rows)
    assert [s["session"] for s in result.sessions] == [str(p) for p in two_motions]
    for s in result.sessions:  # each session explained to its noise (0.1 mm)
        assert 0.8 * NOISE_POSITION < s["rms_after"]["bodies"] < 1.2 * NOISE_POSITION < s["rms_before"]["bodies"]
    total = np.sqrt(sum(n * s["rms_after"]["bodies"] ** 2 for n, s in zip(rows, result.sessions)) / sum(rows))
    assert result.rms_after["bodies"] == pytest.approx(total)
    # one session alone pins the constants down less well than both together
    alone = calibrate_session(two_motions[0], params="k,k_d", start=START, noise_position=NOISE_POSITION,
                              known_noise=True, optimization_level=0, window=[1.0 / 3.0])
    assert np.all(alone.uncertainty.standard_error > se)
    text = format_table(result)
    assert f"session 2 of 2, {two_motions[1]}: RMS residual bodies" in text
    files = write_outputs(result, tmp_path / "out", plot=False)
    assert json.loads(Path(files["summary"]).read_text())["sessions"][1]["session"] == str(two_motions[1])


def test_sessions_with_other_strings_are_refused_naming_the_file(two_motions, tmp_path, capsys):
    other = record_motion(tmp_path, "sway", 0.2, 23, rename={"hand_right": "hand_r"})
    with pytest.raises(ValueError, match=f"{other}: its strings .* expected those of {two_motions[0]}"):
        calibrate_session([two_motions[0], other], start=START, optimization_level=0)
    from dmarionette.cli import main

    assert main(["calibrate", str(two_motions[0]), str(other), "--quiet", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "error: " in err and f"{other}: its strings" in err and "Traceback" not in err
    with pytest.raises(ValueError, match="--validate with several sessions"):
        calibrate_session(two_motions, start=START, optimization_level=0, validate=0.25)


def _with_outliers(path: Path, count: int, size: float, seed: int):
    """The session's data with ``count`` body coordinates moved by ``+-size`` [m] (gross outliers:
    a marker swap, a tracking glitch)."""
    data = read_calibration_data(path, duration=0.6)
    rng = np.random.default_rng(seed)
    body_pos = data.body_pos.copy()
    frames = rng.choice(np.arange(1, data.puppet_steps + 1), count, replace=False)
    bodies = rng.integers(0, len(data.bodies), count)
    axes = rng.integers(0, 3, count)
    body_pos[frames, bodies, axes] += size * rng.choice([-1.0, 1.0], count)
    return dataclasses.replace(data, body_pos=body_pos)


def test_huber_recovers_the_constants_despite_gross_outliers_where_least_squares_does_not(session):
    data = _with_outliers(session, 4, 0.02, seed=5)  # 4 coordinates 2 cm (200 noise scales) off, in 0.6 s
    common = {"params": "k,k_d", "start": START, "noise_position": NOISE_POSITION, "known_noise": True,
              "optimization_level": 0, "data": data, "window": [1.0 / 3.0]}
    plain = calibrate_session(session, **common)
    robust = calibrate_session(session, loss="huber", **common)
    truth = _truth()
    z_plain = (plain.fitted - truth) / plain.uncertainty.standard_error
    z_robust = (robust.fitted - truth) / robust.uncertainty.standard_error
    print(f"\nplain: {np.round(z_plain, 2)} chi2 {plain.verdict.reduced_chi2}\nhuber: {np.round(z_robust, 2)} "
          f"chi2 {robust.verdict.reduced_chi2} {robust.loss}")
    assert np.max(np.abs(z_plain)) > 3.0  # least squares is pulled off by the outliers
    assert np.all(np.abs(z_robust) <= 3.0)
    # the worst constant of least squares is much closer to the truth with Huber (0.6 s of data:
    # the intervals are wider than the 1.2 s session's, k[hand_left] ~1 %)
    worst = np.argmax(np.abs(z_plain))
    assert abs(robust.fitted[worst] - truth[worst]) < 0.5 * abs(plain.fitted[worst] - truth[worst])
    assert plain.verdict.exit_code == EXIT_NOT_EXPLAINED  # and says the data are not explained
    assert robust.loss["outliers"] >= 4 and robust.verdict.exit_code == EXIT_OK, robust.verdict.warnings
    assert "loss: Huber, C = 1.345 noise scales" in format_table(robust)
    assert result_summary(robust)["loss"]["name"] == "huber"


def test_huber_options_are_checked(session, capsys):
    with pytest.raises(ValueError, match="--huber-scale 2.0 given with --loss l2; it needs --loss huber"):
        calibrate_session(session, start=START, optimization_level=0, huber_scale=2.0, duration=0.1)
    with pytest.raises(ValueError, match="--loss huber runs with --solver lm-fd only"):
        calibrate_session(session, start=START, optimization_level=0, loss="huber", solver="bfgs", duration=0.1)
    with pytest.raises(ValueError, match="--loss: got 'cauchy'"):
        calibrate_session(session, start=START, optimization_level=0, loss="cauchy", duration=0.1)
    from dmarionette.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", str(session), "--loss", "huber", "--huber-scale", "-1", "--quiet"])
    assert exit_info.value.code == 2 and "--huber-scale" in capsys.readouterr().err


def test_huber_weights():
    from fitting.calibration_robust import huber_weights

    np.testing.assert_allclose(huber_weights(np.array([0.0, 1.0, -1.345, 2.69, -13.45]), 1.345),
                               [1.0, 1.0, 1.0, 0.5, 0.1])


def test_command_validates_with_the_huber_loss(session, tmp_path, capsys):
    """The flags reach the fit: a 0.2 s fit of one shared k judged on the held-out 0.1 s."""
    from dmarionette.cli import main

    out = tmp_path / "out"
    code = main(["calibrate", str(session), "--params", "k:shared", "--start", "k=300", "--duration", "0.3",
                 "--validate", "0.3", "--loss", "huber", "--huber-scale", "2", "--window", "0.3333",
                 "--noise-position", "1e-4", "--fast-compile", "--no-picture", "--quiet", "--out", str(out)])
    text = capsys.readouterr().out
    summary = json.loads((out / "calibration.json").read_text())
    assert summary["loss"]["name"] == "huber" and summary["loss"]["scale"] == 2.0
    assert summary["validation"]["fraction"] == pytest.approx(3 / 9)
    assert "validation: held out the last" in text and "loss: Huber, C = 2 noise scales" in text
    assert code == summary["status"]["exit_code"] and f"(exit code {code})" in text
