"""Flag fuzzing (hypothesis): random bad values for every numeric and output-path flag of every command.

Property, for each example: exit code 2, no traceback, the message names the flag, nothing
written where the output would go. ``dmarionette.cli.main`` runs in process; every command's
work is replaced by a tripwire, so an example that got past validation fails the test instead
of starting a simulation. The valid range of each flag is written here independently of
``dmarionette.cli_checks``, and values inside it are excluded from the examples.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import math
import types
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from dmarionette.cli import find_commands, main

ROOT = Path(__file__).resolve().parents[1]
KEYFRAMES = ROOT / "examples" / "keyframes_three_poses.toml"
COMMANDS = find_commands()
FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                        HealthCheck.too_slow,
                                                                        HealthCheck.filter_too_much])

# (command line before the flag, the flag, its valid range: (kind, low, high, low included)).
POSITIVE = ("float", 0.0, math.inf, False)
NUMERIC_FLAGS = [
    (["simulate", "strings"], "--duration", POSITIVE),
    (["simulate", "strings"], "--fps", ("float", 0.1, 1000.0, True)),
    (["demo"], "--duration", POSITIVE),
    (["demo"], "--fps", ("float", 0.1, 1000.0, True)),
    (["live"], "--duration", POSITIVE),
    (["live"], "--force-scale", ("float", 0.0, math.inf, True)),
    (["live"], "--workspace-scale", POSITIVE),
    (["live"], "--view-port", ("int", 0, 65535, True)),
    (["live"], "--view-hz", ("float", 0.0, 1000.0, False)),
    (["bench", "accuracy"], "--seconds", ("float", 0.1, 60.0, True)),
    (["bench", "accuracy"], "--repeats", ("int", 1, 100, True)),
    (["export", "t.npz"], "--fps", ("float", 0.0, 1000.0, False)),
    (["calibrate", "s.mcap"], "--max-steps", ("int", 1, 100_000, True)),
    (["calibrate", "s.mcap"], "--rows", ("int", 1, 1_000_000, True)),
    (["calibrate", "s.mcap"], "--duration", POSITIVE),
    (["calibrate", "s.mcap"], "--noise-position", POSITIVE),
    (["calibrate", "s.mcap"], "--noise-force", POSITIVE),
    (["calibrate", "s.mcap"], "--delay", ("float", -0.1, 0.1, True)),
    (["calibrate", "s.mcap"], "--noise-joint", POSITIVE),
    (["author", "k.toml"], "--max-steps", ("int", 1, 100_000, True)),
    (["author", "k.toml"], "--checkpoint-steps", ("int", 1, 1_000_000, True)),
    (["author", "k.toml"], "--fps", ("float", 0.1, 1000.0, True)),
    (["calibrate", "a.mcap", "b.mcap"], "--workers", ("int", 1, 100_000, True)),
    (["author", "a.toml", "b.toml"], "--workers", ("int", 1, 100_000, True)),
]


def _valid(text: str, spec) -> bool:
    kind, low, high, low_included = spec
    try:
        value = int(text) if kind == "int" else float(text)
    except ValueError:
        return False
    return math.isfinite(value) and (value >= low if low_included else value > low) and value <= high


_SPECIAL = ["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "-Infinity", "1e309", "-1e309", "0", "-0", "0.0",
            "-1", "-1e-300", "1e300", "1e9", "", " ", "fast", "1,5", "0x10", "1e", "--", "1.5.2", "١٢", "None"]
VALUES = st.one_of(
    st.sampled_from(_SPECIAL),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(allow_nan=False, allow_infinity=False).map(lambda x: f"{x:g}"),
    st.integers(min_value=-10**30, max_value=10**30).map(str),
    st.floats(min_value=-1e6, max_value=1e6).map(lambda x: f"{x:.3f}"),
    st.text(max_size=8),
)


@pytest.fixture(scope="module")
def no_work():
    """Every command's work fails the test if it starts (module-wide: hypothesis reruns the body)."""
    def tripwire(*args, **kwargs):
        raise AssertionError("the work started: a bad flag got past validation")

    names = [("dmarionette.strings.simulate", "simulate_strings"), ("dmarionette.marionette.solver", "MarionetteModel"),
             ("dmarionette.io.session", "replay_session"), ("dmarionette.marionette.accuracy", "run_sweep"),
             ("dmarionette.io.export.bvh", "export_bvh"), ("dmarionette.io.export.gltf", "export_gltf"),
             ("fitting.calibration_fit", "calibrate_session"), ("fitting.author", "author")]
    with pytest.MonkeyPatch.context() as patch:
        for module, name in names:
            patch.setattr(importlib.import_module(module), name, tripwire)
        patch.setattr(importlib.import_module("dmarionette.io.export.common"), "read_marionette_trajectory",
                      lambda path: types.SimpleNamespace(puppet=None, source=None))
        yield


def _run(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main([str(a) for a in argv], commands=COMMANDS)
        except SystemExit as exit_:
            code = exit_.code
    return code, err.getvalue()


@pytest.mark.parametrize("prefix, flag, spec", NUMERIC_FLAGS, ids=[f"{p[0]} {f}" for p, f, _ in NUMERIC_FLAGS])
@FUZZ
@given(text=VALUES)
def test_a_bad_numeric_flag_is_refused(prefix, flag, spec, text, tmp_path_factory, no_work):
    assume(not _valid(text, spec))
    base = tmp_path_factory.mktemp("fuzz")
    output = ["--record", base / "out" / "s.mcap"] if prefix[0] == "live" else ["--out", base / "out"]
    code, err = _run([*prefix, f"{flag}={text}", *output])
    assert code == 2, (text, err)
    assert f"argument {flag}: " in err and "expected" in err, (text, err)
    assert "Traceback" not in err, err
    assert list(base.iterdir()) == [], "something written"


OUTPUT_FLAGS = [
    (["simulate", "strings"], "--out", "folder"),
    (["demo"], "--out", "folder"),
    (["export", "t.npz"], "--out", "folder"),
    (["replay", "s.mcap"], "--out", "folder"),
    (["calibrate", "s.mcap", "--quiet"], "--out", "folder"),
    (["author", KEYFRAMES, "--quiet"], "--out", "folder"),
    (["bench", "accuracy"], "--out", "folder"),
    (["live"], "--record", ".mcap"),
    (["live"], "--snapshot", ".png"),
]
SEGMENT = st.text(alphabet="abcxyz019_-.", min_size=1, max_size=6).filter(lambda s: s not in (".", ".."))


@st.composite
def bad_outputs(draw, expected: str):
    """A path that cannot be the output: under a regular file, in /proc, or of the wrong kind."""
    how = draw(st.sampled_from(["under a file", "the file", "proc", "a folder"] if expected != "folder"
                               else ["under a file", "the file", "proc"]))
    parts = draw(st.lists(SEGMENT, min_size=1, max_size=3))
    name = draw(SEGMENT) + (expected if expected != "folder" else "")
    return how, parts, name


@pytest.mark.parametrize("prefix, flag, expected", OUTPUT_FLAGS, ids=[f"{p[0]} {f}" for p, f, _ in OUTPUT_FLAGS])
@FUZZ
@given(case=st.data())
def test_an_output_path_that_cannot_be_written_is_refused(prefix, flag, expected, case, tmp_path_factory, no_work):
    how, parts, name = case.draw(bad_outputs(expected))
    base = tmp_path_factory.mktemp("fuzz")
    a_file = base / "file.txt"
    a_file.write_text("kept\n")
    made = []
    if how == "under a file":
        path = a_file.joinpath(*parts, name)
    elif how == "the file":
        path = a_file if expected == "folder" else a_file / name
    elif how == "proc":
        path = Path("/proc", "dmarionette-fuzz", *parts, name)
    else:  # an existing folder where a file is expected
        path = base.joinpath(*parts, name)
        path.mkdir(parents=True)
        made = [p.relative_to(base) for p in sorted(base.rglob("*")) if p != a_file]
    code, err = _run([*prefix, flag, path])
    assert code == 2, (path, err)
    assert err.startswith(f"error: {flag}: ") and len(err.strip().splitlines()) == 1, (path, err)
    assert "Traceback" not in err
    assert sorted(p.relative_to(base) for p in base.rglob("*")) == sorted([Path("file.txt"), *made]), "written"
    assert a_file.read_text() == "kept\n"
