"""The stages of the keyframe solve after a conflict (fitting/author_solve.py): the knot coordinates
that cannot move a keyframe (solved in time order, the earlier keyframes stay as they are).
The whole pipeline on a problem that needs them: tests/fitting/test_ball_authored.py."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("optimistix")

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "keyframes_three_poses.toml"


@pytest.fixture(scope="module")
def residuals():
    """The README example with hand knots every 0.25 s up to 1 s, then 1.5 s."""
    import tomllib

    from fitting import build_problem, keyframes_from_table
    from fitting.author_solve import KeyframeResiduals

    table = tomllib.loads(EXAMPLE.read_text())
    table["bars"]["hand"]["knots"] = [0.0, 0.25, 0.5, 0.75, 1.0, 1.5]
    return KeyframeResiduals(build_problem(keyframes_from_table(table, str(EXAMPLE))))


def test_later_columns_follow_the_splines_locality(residuals):
    """Catmull-Rom: knot j moves the path from knot j-2's time on (the tangent at knot j-1 uses it). With
    hand knots 0, 0.25, 0.5, 0.75, 1, 1.5 s and main knots 0, 0.75, 1.5 s, and keyframes at 0.495, 0.99 and
    1.485 s (taken with one puppet step, 33 ms, of margin): only the hand's last knot (acting from 0.75 s)
    cannot move keyframe 1, and nothing is later than keyframe 2."""
    z = residuals.bounds.z0()
    names = residuals.bounds.names()
    assert [names[i] for i in residuals.later_columns(z, 0)] == ["hand.x@1.5s", "hand.y@1.5s", "hand.z@1.5s"]
    assert len(residuals.later_columns(z, 1)) == 0


def test_later_columns_leave_the_keyframe_exactly_as_it_was(residuals):
    """Causality: the rollout up to the keyframe is the same to the bit when they change (by a lot); every
    other coordinate changes it, but those that act only within the margin."""
    z = residuals.bounds.z0()
    count = len(residuals.entry_keyframe)
    first = residuals.entry_keyframe == 0
    base = residuals.errors(residuals.outputs(z))[:count]
    later = set(residuals.later_columns(z, 0).tolist())
    names = residuals.bounds.names()
    margin = {"hand.x@1s", "hand.y@1s", "hand.z@1s"}  # acting from 0.5 s: after the keyframe, within the margin
    assert later
    for j in range(len(z)):
        moved = z.copy()
        moved[j] += 0.4  # 2 cm of the knot
        errors = residuals.errors(residuals.outputs(moved))[:count]
        if j in later or names[j] in margin:
            assert np.array_equal(errors[first], base[first]), names[j]
        else:
            assert not np.array_equal(errors[first], base[first]), names[j]
        if j in later:
            assert not np.array_equal(errors[~first], base[~first])  # it does move the later keyframes
