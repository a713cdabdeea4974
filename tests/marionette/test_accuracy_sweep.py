"""`dmarionette bench accuracy` on the reduced grid: its files, and error falling with resolution."""

import csv

import numpy as np

from dmarionette.marionette.accuracy import accuracy_scene
from dmarionette.cli import main

U32 = 2.0 ** -24  # float32 unit roundoff
SECONDS = 1.0


def test_reduced_sweep_writes_csv_plot_table_and_error_falls_with_resolution(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "accuracy", "--grid", "reduced", "--seconds", str(SECONDS), "--repeats", "1",
                 "--fast-compile", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "accuracy.csv").open()))
    assert len(rows) == 7
    for row in rows:
        assert float(row["wall_s_per_sim_s"]) > 0 and np.isfinite(float(row["body_rms_m"]))
    assert (out / "accuracy.png").read_bytes().startswith(b"\x89PNG")
    table = (out / "accuracy.md").read_text()
    assert "(paper)" in table and "Reference R1" in table

    def error(precision="float64", springs="printed", **match):
        (row,) = [r for r in rows if all(float(r[k]) == v for k, v in match.items())
                  and r["precision"] == precision and r["springs"] == springs]
        return float(row["body_rms_m"])

    # The puppet step dominates at the paper's settings: error falls as the puppet rate rises...
    by_rate = [error(particles=50, puppet_hz=hz) for hz in (30.0, 62.5, 250.0)]
    assert by_rate[0] > by_rate[1] > by_rate[2]
    # ...and, with the puppet at the string rate, as the strings get more particles.
    assert error(particles=5, puppet_hz=1000.0) > error(particles=20, puppet_hz=1000.0)
    # The references have converged well below every error of the sweep (printed springs first,
    # then the tension-only rows' own reference).
    gaps_mm = [float(part.split(" mm")[0]) for part in table.split("body RMS ")[1:3]]
    assert gaps_mm[0] * 1e-3 < min(float(r["body_rms_m"]) for r in rows if r["springs"] == "printed")
    assert gaps_mm[1] * 1e-3 < error(springs="tension_only", particles=20, puppet_hz=1000.0)
    # Float32 strings: |RMS(a - ref) - RMS(b - ref)| <= RMS(a - b) <= the float32 random-walk
    # bound sqrt(N) u X of tests/marionette/test_marionette_float32.py (N string steps, X the largest
    # coordinate: a bar centre's distance from the origin plus its farthest attach point).
    scene = accuracy_scene(SECONDS)
    scale = max(float(np.linalg.norm(b.trajectory.positions, axis=1).max())
                + max(float(np.linalg.norm(a)) for a in b.attach.values()) for b in scene.bars)
    bound = np.sqrt(SECONDS * scene.string_hz) * U32 * scale
    assert abs(error(precision="float32", particles=50, puppet_hz=30.0) - error(particles=50, puppet_hz=30.0)) <= bound
    # Tension-only rows use their own reference: their error is the settings' numerical error,
    # far below the variant's own effect on the motion (stated in the table).
    effect_mm = float(table.split("moves the puppet by ")[1].split(" mm")[0])
    assert error(springs="tension_only", particles=20, puppet_hz=1000.0) < 0.1 * effect_mm * 1e-3
