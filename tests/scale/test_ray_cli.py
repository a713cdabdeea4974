"""``dmarionette sweep --ray local`` as a user runs it, in a process of its own: it starts the embedded
cluster on loopback and runs the variants on its worker; Ctrl-C after the first row stops it with exit code
130, keeps the finished rows (the in-process numbers) and leaves no Ray process behind; ``--resume`` then
runs only the rest."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from dmarionette.cli import main
from dmarionette.sweep.table import read_rows, summary_columns
from tests.support.sweep import comparable

ROOT = Path(__file__).resolve().parents[2]
KEYS = ["strings.particle_count", "strings.tie_stiffness"]
SUMMARY = summary_columns(["head", "back", "knee_left", "knee_right", "hand_left", "hand_right"], ["main", "hand"])
# One variant per task (--worlds-per-batch 1), so that the interrupt lands between rows.
ARGV = ["sweep", "hanging", "--set", "strings.particle_count=6", "--set", "strings.k=250,300,350,400,450,500",
        "--duration", "1.0", "--quiet", "--no-picture", "--worlds-per-batch", "1"]


def ray_processes() -> set[int]:
    found = set()
    for entry in Path("/proc").iterdir():
        try:
            title = (entry / "cmdline").read_bytes() if entry.name.isdigit() else b""
        except OSError:
            continue
        program = title.split(b"\0")[0]
        if title.startswith(b"ray::") or program.endswith((b"raylet", b"gcs_server")):
            found.add(int(entry.name))
    return found


def rows(folder: Path) -> list[dict]:
    return sorted(read_rows(folder / "sweep.csv", KEYS, SUMMARY), key=lambda r: r["variant"])


def test_sweep_ray_local_interrupted_keeps_its_rows_stops_its_cluster_and_resumes(tmp_path):
    assert main([*ARGV, "--ray", "off", "--out", str(tmp_path / "off")]) == 0
    reference = {r["variant"]: comparable(r) for r in rows(tmp_path / "off")}
    before = ray_processes()
    out = tmp_path / "ray"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    sweep = subprocess.Popen([sys.executable, "-m", "dmarionette.cli", *ARGV, "--ray", "local", "--workers", "1",
                              "--out", str(out)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 300
    while time.monotonic() < end and sweep.poll() is None:
        if (out / "sweep.csv").is_file() and len((out / "sweep.csv").read_text().splitlines()) >= 2:
            break  # the first row is in
        time.sleep(0.05)
    sweep.send_signal(signal.SIGINT)
    _, err = sweep.communicate(timeout=120)
    assert sweep.returncode == 130, err
    assert "Traceback" not in err and f"interrupted; kept what was written before the interrupt" in err, err
    kept = rows(out)
    assert 1 <= len(kept) < 6
    assert all(comparable(r) == reference[r["variant"]] for r in kept)  # Ray's rows are the in-process ones
    for _ in range(100):  # the cluster it started is gone with it (its processes may take a moment to exit)
        if ray_processes() <= before:
            break
        time.sleep(0.1)
    assert ray_processes() <= before
    assert main([*ARGV, "--ray", "off", "--resume", "--out", str(out)]) == 0
    assert [comparable(r) for r in rows(out)] == list(reference.values())
