"""How closely a replay reproduces a live session: record ``dmarionette live`` sessions with the
simulated device, replay each, print the body-position gap.

Run:  python benchmarks/bench_live_replay_gap.py [--sessions 5] [--duration 1.0]

Each session is ``live --duration D --record FILE --fast-compile`` (the default scene, physics
mode auto) followed by ``replay FILE``; the line per session is the puppet steps compared and the
largest and RMS gap [m] between the recorded and re-simulated body positions.
``tests/live/test_live.py::test_record_info_replay_and_replay_device`` checks that it is 0 (a recording
starts with the state at t = 0, so the replay starts where the live session did).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import pathlib
import tempfile

from dmarionette.cli import main as cli


def session_gap(duration: float) -> dict:
    """Records one live session and replays it; the replay's report."""
    folder = pathlib.Path(tempfile.mkdtemp())
    session = folder / "live.mcap"
    with contextlib.redirect_stdout(io.StringIO()):
        if cli(["live", "--duration", str(duration), "--record", str(session), "--fast-compile"]) != 0:
            raise SystemExit("live failed")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        if cli(["replay", str(session), "--fast-compile", "--quiet"]) != 0:
            raise SystemExit("replay failed")
    return json.loads(out.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, default=5)
    parser.add_argument("--duration", type=float, default=1.0)
    args = parser.parse_args()
    print("| session | puppet steps compared | max gap [m] | RMS gap [m] |\n|---:|---:|---:|---:|")
    for i in range(args.sessions):
        report = session_gap(args.duration)
        print(f"| {i} | {report['frames_compared']} | {report['max_body_gap']:.2e} | {report['rms_body_gap']:.2e} |",
              flush=True)


if __name__ == "__main__":  # the live session's physics may run in a spawned child process
    main()
