"""A first run that talks (issue 17): the compile progress bar, Warp's CUDA-driver notice, --version."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import warp as wp

from dmarionette import first_run

ROOT = Path(__file__).resolve().parents[1]


def test_the_compile_bar_shows_elapsed_time_and_the_modules_compiled(tmp_path):
    stream = io.StringIO()
    with first_run.CompileProgress("test kernels", 3.0, after_s=0.2, interval_s=0.1, cache_dir=tmp_path,
                                   stream=stream) as progress:
        progress.step = "kernel 1/2: eval_fake"
        (tmp_path / "wp_dmarionette.kernels.fake_module_f800b57").mkdir()  # a module compiled
        (tmp_path / "wp_other_0123abc_p123_t456").mkdir()  # one being compiled: not counted
        time.sleep(0.8)
    out = stream.getvalue()
    assert progress.shown and "compiling test kernels" in out and "first run: ~3 s" in out
    assert "1 modules compiled, latest dmarionette.kernels.fake_module" in out and "kernel 1/2: eval_fake" in out
    assert progress.compiled() == ["dmarionette.kernels.fake_module"]


def test_a_fast_block_or_quiet_shows_nothing(tmp_path):
    for quiet, work_s in ((False, 0.0), (True, 0.5)):
        stream = io.StringIO()
        with first_run.CompileProgress("x", 3.0, quiet=quiet, after_s=0.3, interval_s=0.1, cache_dir=tmp_path,
                                       stream=stream) as progress:
            time.sleep(work_s)
        assert stream.getvalue() == "" and not progress.shown


def test_load_kernels_loads_each_module_once_with_a_counter():
    @wp.kernel(module="unique")
    def scale_test_kernel(x: wp.array(dtype=float)):
        i = wp.tid()
        x[i] = 2.0 * x[i]

    calls = []
    holder = {"a": scale_test_kernel, "b": [scale_test_kernel]}
    assert first_run.load_kernels(holder, "cpu", lambda i, n, name: calls.append((i, n, name))) == 1
    assert calls == [(0, 1, "scale_test_kernel")]
    x = wp.array([1.0, 2.0], dtype=float, device="cpu")
    wp.launch(scale_test_kernel, dim=2, inputs=[x], device="cpu")
    assert x.numpy().tolist() == [2.0, 4.0]


def test_warp_start_drops_only_the_cuda_driver_notice(capfd):
    def native_output():
        os.write(2, (first_run.CUDA_DRIVER_NOTICE + " GPU execution will not be available.\n").encode())
        os.write(2, b"Warp CUDA error: Failed to get driver entry point 'cuInit' (CUDA error 1)\n")

    first_run.filter_native_stderr(native_output)
    err = capfd.readouterr().err
    assert first_run.CUDA_DRIVER_NOTICE not in err
    assert "Warp CUDA error: Failed to get driver entry point" in err  # a real error still shows


def test_a_command_prints_no_cuda_notice_and_version_names_both_versions():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-m", "dmarionette.cli", "scenes"], capture_output=True, text=True,
                         env=env, timeout=120)
    assert run.returncode == 0 and "hanging" in run.stdout
    assert "Could not find or load the NVIDIA CUDA driver" not in run.stderr, run.stderr
    run = subprocess.run([sys.executable, "-m", "dmarionette.cli", "--version"], capture_output=True, text=True,
                         env=env, timeout=120)
    assert run.returncode == 0
    assert run.stdout.startswith("dmarionette 0.") and f"(Warp {wp.config.version})" in run.stdout, run.stdout
