"""``dmarionette sweep`` end to end on the shipped ``hanging`` scene (joint limits, ground contact and
feedback on; 8 particles per string to keep CI short): a 2 x 2 grid of the eq. 2 constants writes a row per
variant whose numbers are exactly those of ``simulate_marionette`` / ``simulate_energy_balance`` runs of the
same variants built independently (``dataclasses.replace`` on the loaded scene, not the sweep's TOML edit);
a killed run keeps its rows and ``--resume`` runs only the missing variants."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import dmarionette as dm
import dmarionette.sweep.run
from dmarionette.cli import main
from dmarionette.first_run import build_marionette
from dmarionette.marionette.energy import simulate_energy_balance
from dmarionette.sweep.table import read_rows, summary_columns
from tests.support.sweep import comparable

DURATION = 2.0  # s: the main bar starts to sway at 1 s
PARTICLES = 8
K = ("200", "400")  # eq. 2 k [N/m]
K_D = ("2", "4")  # eq. 2 k_d [N s/m]
KEYS = ["strings.particle_count", "strings.tie_stiffness", "strings.tie_damping"]
STRINGS = ["head", "back", "knee_left", "knee_right", "hand_left", "hand_right"]
BARS = ["main", "hand"]


def sweep_argv(out, *extra):
    return ["sweep", "hanging", "--set", f"strings.particle_count={PARTICLES}", "--set", f"strings.k={','.join(K)}",
            "--set", f"strings.k_d={','.join(K_D)}", "--duration", str(DURATION), "--out", str(out), "--quiet",
            *extra]


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    assert main(sweep_argv(out, "--ray", "off")) == 0
    return out, read_rows(out / "sweep.csv", KEYS, summary_columns(STRINGS, BARS))


def direct_scene(k: str, k_d: str):
    scene = dm.load_scene("hanging")
    strings = tuple(dataclasses.replace(s, particle_count=PARTICLES, tie_stiffness=float(k), tie_damping=float(k_d))
                    for s in scene.strings)
    return dataclasses.replace(scene, strings=strings)


def test_a_2x2_sweep_writes_a_row_per_variant_equal_to_direct_simulations(swept):
    out, rows = swept
    assert (out / "sweep.md").is_file() and (out / "sweep.png").stat().st_size > 10_000
    assert [r["variant"] for r in rows] == [1, 2, 3, 4]  # in-process: in grid order
    assert [(r["strings.tie_stiffness"], r["strings.tie_damping"]) for r in rows] == [
        (k, k_d) for k in K for k_d in K_D]
    for row in rows:
        scene = direct_scene(row["strings.tie_stiffness"], row["strings.tie_damping"])
        trajectory = dm.simulate_marionette(build_marionette(scene, quiet=True), DURATION, progress=False)
        torso = trajectory.body_pos[:, 0, 1]
        assert row["finite"] is True and math.isnan(row["first_non_finite_s"])
        assert row["simulated_s"] == trajectory.step_time[-1]
        assert (row["torso_min_m"], row["torso_max_m"]) == (torso.min(), torso.max())
        for s, name in enumerate(STRINGS):
            assert row[f"taut_{name}"] == trajectory.string_taut[:, s].mean()
        for b, name in enumerate(BARS):
            assert row[f"feedback_max_{name}_N"] == np.linalg.norm(trajectory.bar_feedback[:, b], axis=1).max()
            assert row[f"reaction_max_{name}_N"] == np.linalg.norm(trajectory.bar_reaction[:, b], axis=1).max()
        balance = simulate_energy_balance(build_marionette(scene, quiet=True), DURATION)
        motion = balance["energy"] - balance["parts"]["puppet_contact"] - balance["parts"]["puppet_limit"]
        assert row["energy_excess_J"] == (motion - motion[0] - balance["bar_work"])[1:].max()
        assert row["bar_work_J"] == balance["bar_work"][-1]
        assert row["real_time_factor"] > 0.0 and row["wall_s"] > 0.0


def test_the_rows_are_physical(swept):
    _, rows = swept
    by = {(r["strings.tie_stiffness"], r["strings.tie_damping"]): r for r in rows}
    for row in rows:
        # The hard-case bound: the simulation makes no energy beyond the bars' work (1e-3 J, tests/support).
        assert row["energy_excess_J"] <= 1e-3
        assert row["bar_work_J"] > 0.0  # the main bar sways from 1 s on and lifts the puppet's side
        assert all(row[f"taut_{s}"] == 1.0 for s in STRINGS)  # a hanging puppet keeps its strings taut
        assert 0.3 < row["torso_min_m"] < row["torso_max_m"] <= 0.49 + 1e-9  # it starts at its rest 0.49 m and sags
    for k_d in K_D:  # stiffer ties stretch less under the same weight: the puppet sags less
        assert by["400", k_d]["torso_min_m"] > by["200", k_d]["torso_min_m"]


def test_a_killed_run_keeps_its_rows_and_resume_runs_only_the_missing_variants(swept, tmp_path, monkeypatch):
    out, rows = swept
    lines = (out / "sweep.csv").read_text().splitlines(keepends=True)
    # as a kill leaves it: the header, two rows and the third cut mid-line
    (tmp_path / "sweep.csv").write_text("".join(lines[:3]) + lines[3][: len(lines[3]) // 2])
    ran = []
    original = dmarionette.sweep.run.run_variant

    def counting(scene, duration, optimization_level=2):
        ran.append(scene.strings[0].tie_stiffness)
        return original(scene, duration, optimization_level)

    monkeypatch.setattr(dmarionette.sweep.run, "run_variant", counting)
    assert main(sweep_argv(tmp_path, "--ray", "off", "--resume", "--no-picture", "--worlds-per-batch", "1")) == 0
    assert ran == [400.0, 400.0]  # variants 3 and 4 only
    again = read_rows(tmp_path / "sweep.csv", KEYS, summary_columns(STRINGS, BARS))
    assert [r["variant"] for r in again] == [1, 2, 3, 4]
    for before, after in zip(rows, again):
        assert comparable(before) == comparable(after)



def test_resume_with_another_duration_is_refused_naming_both(swept, tmp_path, capsys):
    out, _ = swept
    (tmp_path / "sweep.csv").write_text((out / "sweep.csv").read_text())
    argv = sweep_argv(tmp_path, "--ray", "off", "--resume", "--no-picture")
    argv[argv.index("--duration") + 1] = "1.0"
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "has variant 1 simulated for 2.013 s; this sweep asks for 1 s" in err, err


def test_a_non_finite_variant_is_marked_in_its_row_and_the_sweep_exits_1(tmp_path, monkeypatch, capsys):
    original = dmarionette.sweep.run.run_variant

    def diverging(scene, duration, optimization_level=2):
        row = original(scene, duration, optimization_level)
        if scene.strings[0].tie_stiffness == 400.0:  # as a row of a variant that blew up at 0.5 s reads
            row.update({k: math.nan for k in row if k.startswith(("torso", "taut", "feedback", "reaction", "energy",
                                                                   "bar_work"))}, finite=False, first_non_finite_s=0.5)
        return row

    monkeypatch.setattr(dmarionette.sweep.run, "run_variant", diverging)
    argv = ["sweep", "hanging", "--set", f"strings.particle_count={PARTICLES}", "--set", "strings.k=200,400",
            "--duration", "0.2", "--out", str(tmp_path), "--ray", "off", "--quiet", "--worlds-per-batch", "1"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert ("error: 1 of 2 variants produced a non-finite value: variant 2 (strings.particle_count=8, "
            "strings.tie_stiffness=400) at t = 0.5 s") in err
    rows = read_rows(tmp_path / "sweep.csv", KEYS[:2], summary_columns(STRINGS, BARS))
    assert [r["finite"] for r in rows] == [True, False]
    table = (tmp_path / "sweep.md").read_text()
    assert "| 1 | 8 | 200 |" in table and "| 2 | 8 | 400 |" in table and table.count("**no**") == 1
