"""`dmarionette bench accuracy` on the reduced grid: its files, and error falling with resolution."""

import csv

import numpy as np

from dmarionette.cli import main


def test_reduced_sweep_writes_csv_plot_table_and_error_falls_with_resolution(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "accuracy", "--grid", "reduced", "--seconds", "1.0", "--repeats", "1",
                 "--fast-compile", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "accuracy.csv").open()))
    assert len(rows) == 5
    for row in rows:
        assert float(row["wall_s_per_sim_s"]) > 0 and np.isfinite(float(row["body_rms_m"]))
    assert (out / "accuracy.png").read_bytes().startswith(b"\x89PNG")
    table = (out / "accuracy.md").read_text()
    assert "(paper)" in table and "Reference R1" in table

    def error(**match):
        (row,) = [r for r in rows if all(float(r[k]) == v for k, v in match.items())]
        return float(row["body_rms_m"])

    # The puppet step dominates at the paper's settings: error falls as the puppet rate rises...
    by_rate = [error(particles=50, puppet_hz=hz) for hz in (30.0, 62.5, 250.0)]
    assert by_rate[0] > by_rate[1] > by_rate[2]
    # ...and, with the puppet at the string rate, as the strings get more particles.
    assert error(particles=5, puppet_hz=1000.0) > error(particles=20, puppet_hz=1000.0)
    # The reference has converged well below every error of the sweep.
    gap_mm = float(table.split("body RMS ")[1].split(" mm")[0])
    assert gap_mm * 1e-3 < min(float(r["body_rms_m"]) for r in rows)
