"""``dmarionette sweep --ray local`` as a user runs it, in a process of its own: it starts the embedded
cluster on loopback, runs the variants on its worker, writes the in-process numbers, and leaves no Ray
process behind."""

from __future__ import annotations

import os
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


def ray_processes() -> set[int]:
    found = set()
    for entry in Path("/proc").iterdir():
        try:
            title = (entry / "cmdline").read_bytes() if entry.name.isdigit() else b""
        except OSError:
            continue
        if title.startswith(b"ray::") or b"raylet" in title.split(b"\0")[0] or b"gcs_server" in title.split(b"\0")[0]:
            found.add(int(entry.name))
    return found


def test_sweep_ray_local_starts_its_cluster_writes_the_in_process_numbers_and_stops_it(tmp_path):
    argv = ["sweep", "hanging", "--set", "strings.particle_count=6", "--set", "strings.k=250,350", "--duration",
            "0.5", "--quiet", "--no-picture"]
    assert main([*argv, "--ray", "off", "--out", str(tmp_path / "off")]) == 0
    before = ray_processes()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "dmarionette.cli", *argv, "--ray", "local", "--workers", "1",
                           "--out", str(tmp_path / "ray")], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    on_ray = sorted(read_rows(tmp_path / "ray" / "sweep.csv", KEYS, SUMMARY), key=lambda r: r["variant"])
    off = read_rows(tmp_path / "off" / "sweep.csv", KEYS, SUMMARY)
    assert [comparable(r) for r in on_ray] == [comparable(r) for r in off]
    for _ in range(100):  # the cluster it started is gone with it (its processes may take a moment to exit)
        if ray_processes() <= before:
            break
        time.sleep(0.1)
    assert ray_processes() <= before
