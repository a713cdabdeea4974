"""A recording delay as an optional unknown (docs/calibration.md, "Delay";
fitting/calibration_delay.py): the targets of a session lag its bar inputs by 12 ms.

The session: the rolls-and-yaws motion of the suite after 0.1 s of still bars (so the delay
model's "bars at rest before the session" holds exactly), 1.1 s, the suite's constants and noise
(0.3 mm, 0.02 N), bar poses recorded 12 ms ahead of the targets.
"""

import json

import numpy as np
import pytest
import warp as wp

pytest.importorskip("jax")
pytest.importorskip("optimistix")

import dmarionette as dm  # noqa: E402
from fitting.calibrate import CalibrationProblem, parse_parameters  # noqa: E402
from fitting.calibration_data import read_calibration_data  # noqa: E402
from fitting.calibration_delay import delayed  # noqa: E402
from fitting.calibration_fit import calibrate_session  # noqa: E402
from fitting.calibration_report import format_table  # noqa: E402
from fitting.calibration_verdict import EXIT_NOT_EXPLAINED, EXIT_OK  # noqa: E402
from fitting.synthetic_scenes import SUITE, SUITE_NOISE, motion_scene_text  # noqa: E402
from fitting.synthetic_session import record_synthetic_session  # noqa: E402

wp.config.log_level = wp.LOG_WARNING
NOISE = {"noise_position": SUITE_NOISE[0], "noise_force": SUITE_NOISE[1]}
DELAY = 0.012
TRUTH = SUITE["roll_yaw"][2]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("delay")
    text = motion_scene_text("roll_yaw", 1.1, hold=0.1)
    (folder / "delayed.toml").write_text(text)
    _, path = record_synthetic_session(dm.load_scene(folder / "delayed.toml"), text, TRUTH, 1.1,
                                       folder / "delayed.mcap", seed=7, optimization_level=0, delay=DELAY, **NOISE)
    return path


def test_delayed_reads_a_series_later():
    x = np.arange(10.0)[:, None] ** 2  # a quadratic: Catmull-Rom reproduces it exactly inside
    np.testing.assert_array_equal(delayed(x, 0.0, 0.001), x)
    np.testing.assert_allclose(delayed(x, 0.003, 0.001)[3:, 0], np.arange(7.0) ** 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(delayed(x, 0.003, 0.001)[:3, 0], 0.0)  # held before the first sample
    np.testing.assert_allclose(delayed(x, 0.0025, 0.001)[4:9, 0], (np.arange(4, 9) - 2.5) ** 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(delayed(x, -0.002, 0.001)[:8, 0], np.arange(2.0, 10.0) ** 2)  # leading
    np.testing.assert_allclose(delayed(x, -0.002, 0.001)[8:, 0], 81.0)  # held after the last


def test_the_delayed_inputs_reproduce_the_recording_at_the_truth(session):
    """At the true constants and the true delay only the noise is left (RMS 1 in noise scales);
    without the delay, 15 noise scales (measured)."""
    data = read_calibration_data(session, "both")
    params = parse_parameters("k,k_d", data)
    rms = {}
    for d in (0.0, DELAY):
        problem = CalibrationProblem(data, params, start=TRUTH, optimization_level=0, delay=d, **NOISE)
        r = problem.host_residuals(problem.theta_start)
        rms[d] = float(np.sqrt(np.mean(r**2)))
    assert abs(rms[DELAY] - 1.0) < 5 / np.sqrt(2 * len(r)), rms
    assert rms[0.0] > 5.0, rms


def test_fit_delay_recovers_the_delay_and_the_constants(session, tmp_path, capsys):
    """From the scene's constants and a delay of 0 (default windows): the delay within 3 standard
    errors (measured 11.991 ms +- 0.017 ms) and every constant within the suite's tolerances
    (k within 1 %, k_d within 5 %, 3 standard errors), exit code 0; the command prints it."""
    from dmarionette.cli import main

    out = tmp_path / "out"
    code = main(["calibrate", str(session), "--targets", "both", "--fit-delay", "--noise-position",
                 str(SUITE_NOISE[0]), "--noise-force", str(SUITE_NOISE[1]), "--fast-compile", "--quiet",
                 "--out", str(out)])
    printed = capsys.readouterr().out
    summary = json.loads((out / "calibration.json").read_text())
    rows = {row["label"]: row for row in summary["constants"]}
    print(printed)
    assert code == EXIT_OK, printed
    delay = rows["delay"]
    assert summary["delay"]["fitted"] and summary["delay"]["seconds"] == delay["fitted"]
    assert 0 < delay["standard_error"] < 1e-3 and abs(delay["fitted"] - DELAY) <= 3 * delay["standard_error"], delay
    assert summary["units"]["delay"] == "s" and "delay " in printed
    assert (out / "calibration.png").stat().st_size > 10_000  # the picture with a delay row in the table
    for name in (r["label"] for r in summary["constants"] if r["label"] != "delay"):
        row = rows[name]
        kind, string = name.split("[")
        truth = TRUTH[kind][["head", "back", "knee_left", "knee_right", "hand_left", "hand_right"]
                            .index(string.rstrip("]"))]
        assert abs(row["fitted"] - truth) <= 3 * row["standard_error"], row
        assert abs(row["fitted"] / truth - 1) < (0.01 if kind == "k" else 0.05), row


def test_without_the_delay_the_data_are_not_explained(session):
    """The same session fitted without --fit-delay: residuals 30x the noise, structured in time:
    exit code 3 (measured after 100 steps: reduced chi^2 31 and 29, z 28 and 58; 8 steps here)."""
    result = calibrate_session(session, targets="both", optimization_level=0, max_steps=8, **NOISE)
    v = result.verdict
    assert v.exit_code == EXIT_NOT_EXPLAINED and not result.converged, v.warnings
    assert not v.explains_data and any("does not explain the data" in w for w in v.warnings)
    assert "**RESULT:" in format_table(result)


def test_delay_options_are_checked(session, capsys):
    with pytest.raises(ValueError, match="--fit-delay runs with --solver lm-fd only"):
        calibrate_session(session, optimization_level=0, fit_delay=True, solver="bfgs", duration=0.1)
    with pytest.raises(ValueError, match=r"--delay: got 0.5 s; expected a delay .* within \+-0.1 s"):
        calibrate_session(session, optimization_level=0, delay=0.5, duration=0.1)
    from dmarionette.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", str(session), "--delay", "0.2", "--quiet"])
    assert exit_info.value.code == 2 and "--delay" in capsys.readouterr().err
