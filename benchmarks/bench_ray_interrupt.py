"""How long Ctrl-C of ``dmarionette sweep --ray local`` takes to stop, and where the time goes.

Run:  python benchmarks/bench_ray_interrupt.py [--repeats 3]

- **Ctrl-C**: ``sweep hanging`` (6 variants of 1 s, 6 particles per string) with ``--ray local
  --workers 1`` in a process of its own, SIGINT once its first row is written; the time from the
  signal to the process's exit (as ``tests/scale/test_ray_cli.py`` does it).
- **ray.shutdown**: a local cluster of 1 CPU with one actor, killed; then ``ray.shutdown()`` timed,
  and each of the cluster's processes' stop inside it (``ray._private.node.Node._kill_process_type``
  wrapped: Ray's internals, for this diagnosis only); and the same with
  ``dmarionette.scale.shutdown_ray()``, which ends Ray's autoscaler monitor first.
- **Interpreter exit**: ``python -c 'import warp, ray'`` (and each alone): the time from the last
  line of the script to the process's exit (Python's finalisation of what those imported).

Medians over ``--repeats``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SWEEP = ["sweep", "hanging", "--set", "strings.particle_count=6", "--set", "strings.k=250,300,350,400,450,500",
         "--duration", "1.0", "--quiet", "--no-picture", "--ray", "local", "--workers", "1"]
SHUTDOWN = """
import os, sys, time
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
from dmarionette.scale import start_local_ray
import ray, ray._private.node as node
parts = {}
kill = node.Node._kill_process_type
def timed(self, kind, **kw):
    start = time.monotonic(); kill(self, kind, **kw); parts[kind] = time.monotonic() - start
node.Node._kill_process_type = timed
start_local_ray(1)
@ray.remote
class Probe:
    def pid(self): return os.getpid()
probe = Probe.remote(); ray.get(probe.pid.remote()); ray.kill(probe)
from dmarionette.scale import shutdown_ray
stop = shutdown_ray if sys.argv[1:] == ["ours"] else ray.shutdown
start = time.monotonic(); stop(); total = time.monotonic() - start
print(total, *[f"{k}={v:.3f}" for k, v in parts.items()])
"""


def env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def interrupt_once(folder: Path) -> float:
    """Seconds from SIGINT to the exit of a ``sweep --ray local`` interrupted after its first row."""
    shutil.rmtree(folder, ignore_errors=True)
    sweep = subprocess.Popen([sys.executable, "-m", "dmarionette.cli", *SWEEP, "--out", str(folder)], cwd=ROOT,
                             env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    table = folder / "sweep.csv"
    while sweep.poll() is None and not (table.is_file() and len(table.read_text().splitlines()) >= 2):
        time.sleep(0.02)
    start = time.monotonic()
    sweep.send_signal(signal.SIGINT)
    _, err = sweep.communicate(timeout=120)
    took = time.monotonic() - start
    if sweep.returncode != 130:
        raise RuntimeError(f"the sweep exited with {sweep.returncode}, not 130: {err[-500:]}")
    return took


def exit_after(code: str) -> float:
    """Seconds from the last line of ``python -c code`` to the process's exit."""
    script = code + "\nimport sys, time\nprint(time.monotonic(), file=sys.stderr)"
    run = subprocess.run([sys.executable, "-c", script], env=env(), stderr=subprocess.PIPE, text=True, check=True)
    return time.monotonic() - float(run.stderr.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="bench-ray-interrupt-")) / "sweep"
    load = os.getloadavg()[0]
    stop = [interrupt_once(folder) for _ in range(args.repeats)]
    runs: dict = {"ray.shutdown()": [], "dmarionette.scale.shutdown_ray()": []}
    for _ in range(args.repeats):
        for name, extra in zip(runs, ([], ["ours"])):
            line = subprocess.run([sys.executable, "-c", SHUTDOWN, *extra], env=env(), capture_output=True,
                                  text=True, check=True).stdout.split()
            runs[name].append((float(line[0]), dict(part.split("=") for part in line[1:])))
    exits = {what: statistics.median(exit_after(what) for _ in range(args.repeats))
             for what in ("import warp, ray", "import warp", "import ray", "pass")}

    print(f"# Ctrl-C of sweep --ray local (load {load:.1f} before, {os.getloadavg()[0]:.1f} after; medians of "
          f"{args.repeats})\n")
    print(f"SIGINT -> exit: {statistics.median(stop):.2f} s (runs: {', '.join(f'{s:.2f}' for s in stop)})")
    for name, shutdowns in runs.items():
        parts = {k: statistics.median(float(s[1][k]) for s in shutdowns) for k in shutdowns[0][1]}
        print(f"{name} of a 1-CPU local cluster: {statistics.median(s[0] for s in shutdowns):.2f} s; its "
              f"processes' stops: {', '.join(f'{k} {v:.2f} s' for k, v in parts.items())}")
    print("interpreter exit after the last line: " + ", ".join(f"{k!r} {v:.2f} s" for k, v in exits.items()))


if __name__ == "__main__":
    main()
