"""A live session recorded by a process that is killed with SIGKILL: readable, at most ~1 s lost.

`dmarionette live --record` runs in a child process (simulated device, puppet kernels
without optimisation, cached after the first test that builds them). The child prints the
moment its servo loop starts on CLOCK_MONOTONIC, which is also the simulated device's clock
and ``time.monotonic()`` here, so a recorded ``device_time`` (seconds since the device
opened, which is after that moment) gives an upper bound on what the kill lost:
``(kill - start) - last device_time``.

The writer flushes every second of wall-clock time (and of simulated time), so the bound is
1 s plus the time from the start line to the device opening (milliseconds) plus the
flusher thread's own scheduling delay; 1.2 s is asserted, and the value printed.
"""

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader

from dmarionette.cli import main
from dmarionette.io.session import read_session

ROOT = Path(__file__).resolve().parents[2]
START = re.compile(r"servo loop starting at CLOCK_MONOTONIC ([0-9.]+) s; physics: (\w+) \(pid (\d+)\)")


def start_live(path: Path, physics: str):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-m", "dmarionette.cli", "live", "--physics", physics,
                             "--duration", "60", "--record", str(path), "--fast-compile"],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    guard = threading.Timer(400.0, proc.kill)  # a hung start must not hang the suite
    guard.start()
    lines = []
    for line in proc.stderr:
        lines.append(line)
        match = START.search(line)
        if match:
            guard.cancel()
            rest = []
            drain = threading.Thread(target=lambda: rest.append(proc.stderr.read()), daemon=True)
            drain.start()  # keep draining, keep the text
            return proc, float(match.group(1)), int(match.group(3)), (drain, rest)
    guard.cancel()
    proc.wait()
    pytest.fail(f"dmarionette live ended (code {proc.returncode}) before its servo loop started:\n{''.join(lines)}")


def standard_reader_topics(path: Path) -> list[str]:
    """Topics of every message the standard mcap reader gets from the (unterminated) file."""
    topics = []
    with path.open("rb") as f:
        try:
            for _, channel, _ in NonSeekingReader(f).iter_messages(log_time_order=False):
                topics.append(channel.topic)
        except McapError:  # the record cut by the kill
            pass
    return topics


def check_recording(path: Path, started: float, killed: float, capsys) -> float:
    topics = standard_reader_topics(path)
    for topic in ("/device/main/sample", "/device/main/force", "/bar/main/pose", "/puppet/state"):
        assert topics.count(topic) > 0, topic
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "/device/main/sample" in out and "/puppet/state" in out
    session = read_session(path)
    assert session.truncated
    samples = session.channels["/device/main/sample"]
    assert topics.count("/device/main/sample") >= len(samples["t"])
    lost = (killed - started) - float(samples["device_time"][-1])
    print(f"recorded {len(samples['t'])} device samples over {samples['device_time'][-1]:.3f} s; "
          f"killed {killed - started:.3f} s after the start line; at most {lost:.3f} s lost")
    assert np.all(np.diff(samples["device_time"]) > 0)
    return lost


def test_recorder_killed_with_sigkill(tmp_path, capsys):
    """The recording process itself (physics in its worker thread, so the writer is in it) is killed."""
    path = tmp_path / "killed.mcap"
    proc, started, _, _ = start_live(path, "thread")
    time.sleep(3.0)
    killed = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(30) == -signal.SIGKILL
    lost = check_recording(path, started, killed, capsys)
    assert lost <= 1.2


def test_physics_process_killed_with_sigkill(tmp_path, capsys):
    """With --physics shm the recording is written by the physics process: killing that one stops the
    servo (clear error, exit 2), and the recording is readable up to the last second."""
    path = tmp_path / "killed_physics.mcap"
    proc, started, physics_pid, (drain, rest) = start_live(path, "shm")
    assert physics_pid != proc.pid
    time.sleep(3.0)
    killed = time.monotonic()
    os.kill(physics_pid, signal.SIGKILL)
    assert proc.wait(60) == 2
    drain.join(10)
    assert f"the physics process (pid {physics_pid}) died (killed by SIGKILL)" in rest[0], rest
    lost = check_recording(path, started, killed, capsys)
    assert lost <= 1.2
