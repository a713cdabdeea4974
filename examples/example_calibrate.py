"""Calibrating the strings against a recorded session.

A 1.5 s session of the small marionette in ``calibration_scene.toml`` is simulated with known
eq. 2 constants, a different ``k`` and ``k_d`` for each string, and written as a real MCAP
session with 0.1 mm noise on the body poses and 0.01 N on the bar forces. The session's
metadata says what the scene file says (300 N/m, 3 N s/m for every string), as when a real
marionette's strings differ from its scene file. The calibration starts from those values and
fits the 12 constants to the body poses and the bar reactions together.

Run:  python examples/example_calibrate.py [OUT_DIR]
"""

import sys
import tempfile
from pathlib import Path

import numpy as np
import warp as wp

import dmarionette as dm
from fitting.calibration_fit import calibrate_session
from fitting.calibration_report import format_table, write_outputs
from fitting.synthetic_session import record_synthetic_session

wp.config.log_level = wp.LOG_WARNING
SCENE = Path(__file__).parent / "calibration_scene.toml"
TRUTH = {"k": [330.0, 280.0, 310.0, 260.0, 350.0, 240.0], "k_d": [3.4, 2.6, 3.1, 2.2, 3.8, 2.9]}


def main(out: str | Path | None = None) -> dict:
    """Records the session, calibrates it; returns the truth, the result and the files written."""
    out = Path(tempfile.mkdtemp(prefix="calibrate_")) if out is None else Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene = dm.load_scene(SCENE)
    session = out / "take.mcap"
    record_synthetic_session(scene, SCENE.read_text(), TRUTH, 1.5, session, noise_position=1e-4,
                             noise_force=1e-2, seed=3, optimization_level=0)
    result = calibrate_session(session, targets="both", params="k,k_d", noise_position=1e-4, noise_force=1e-2,
                               optimization_level=0)
    files = write_outputs(result, out)
    return {"truth": np.concatenate([TRUTH["k"], TRUTH["k_d"]]), "result": result, "files": files}


def check(output: dict) -> None:
    """k within 1 %, k_d within 5 %, every constant within 3 standard errors of the truth,
    and the written scene carries the fitted constants."""
    truth, result = output["truth"], output["result"]
    error = (result.fitted - truth) / truth
    assert result.converged, result.message
    assert np.all(np.abs(error[:6]) < 0.01), error[:6]
    assert np.all(np.abs(error[6:]) < 0.05), error[6:]
    assert np.all(np.abs(result.fitted - truth) <= 3 * result.uncertainty.standard_error)
    scene = dm.load_scene(output["files"]["scene"])
    assert [s.tie_stiffness for s in scene.strings] == list(result.fitted[:6])


if __name__ == "__main__":
    output = main(sys.argv[1] if len(sys.argv) > 1 else None)
    check(output)
    print(format_table(output["result"]))
    print("true values:", ", ".join(f"{label} = {v:g}" for label, v in zip(output["result"].labels, output["truth"])))
    print("written:", output["files"])
