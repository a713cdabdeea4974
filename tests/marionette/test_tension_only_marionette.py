"""Tension-only strings (``[effects] tension_only = true``) in the marionette: fully coupled
(puppet at the string rate) they carry the puppet and pass the hard cases; under the
paper's 30 Hz puppet they settle and stay within the energy bound (refused until the tie
path came from a trial puppet step, ``settings_check``).

Energy, penetration and limit checks as in ``test_hard_cases.py`` (module doc there).
"""

import dataclasses

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.marionette.energy import simulate_energy_balance
from dmarionette.marionette.rollout import simulate_marionette
from dmarionette.scene.scene import SCENE_DIR
from dmarionette.scene.settings_check import check_marionette_settings
from tests.support.hard_cases import G, check_case, contact_bound, limit_bound, lowered_bars, still_bar

wp.config.log_level = wp.LOG_WARNING


@pytest.fixture(scope="module")
def tension_only():
    """The ``hanging`` scene with tension-only strings, the puppet at the string rate (1 kHz)."""
    scene = dm.load_scene("hanging")
    return dataclasses.replace(scene, puppet_hz=scene.string_hz,
                               effects=dataclasses.replace(scene.effects, tension_only=True))


def test_fully_coupled_the_strings_carry_the_puppet_at_rest(tension_only):
    """Still bars, 6 s: the ties' vertical pull balances the puppet's weight and the puppet
    hangs still (tolerances as in ``test_marionette.py::test_at_rest_the_strings_carry_the_puppet``:
    0.2 % of the weight, torso below 1 mm/s). Measured: ties 3.6e-7 of the weight, torso
    at 6.6e-6 m/s."""
    scene = dataclasses.replace(tension_only, bars=tuple(still_bar(b) for b in tension_only.bars))
    model = MarionetteModel(scene, optimization_level=0)
    trajectory = simulate_marionette(model, 6.0, progress=False)
    weight = model.puppet_mass * G
    lift = trajectory.tie_force[-100:, :, 1].sum(axis=1).mean()
    torso_speed = np.linalg.norm(np.diff(trajectory.body_pos[-10:, 0], axis=0), axis=1).max() / (
        trajectory.frame_time[1] - trajectory.frame_time[0])
    print(f"\nties {abs(lift - weight) / weight:.2e} of the weight, torso {torso_speed:.2e} m/s")
    assert abs(lift - weight) <= 2e-3 * weight, (lift, weight)
    assert torso_speed < 1e-3, torso_speed


def test_fully_coupled_all_strings_slack_and_lying_on_the_ground(tension_only):
    """``test_hard_cases.py::test_all_strings_slack_and_lying_on_the_ground`` (both bars lowered
    by 1.2 / 1.1 m at 0.6 m/s, 6 s) with tension-only strings, fully coupled, and the same
    bounds (``H`` is now 1 ms). With the printed spring a straight knee string acted as a
    rod there and pushed its lower end 46 mm into the ground (at 1 kHz fully coupled:
    52 mm); tension-only, the strings fold onto the ground. Measured: lowest particle 1.9 mm
    below the ground, puppet 3.6 mm, energy at most -5.1e-3 J from ``E(0) + W``."""
    bars = lowered_bars(tension_only)
    model = MarionetteModel(dataclasses.replace(tension_only, bars=bars), optimization_level=0)
    r = simulate_energy_balance(model, 6.0)
    v = np.sqrt(2 * G * 0.1) + 0.6
    bound = contact_bound(model, v)
    check_case("slack on the ground, tension-only, 1 kHz", model, r, ground=bound, limit=limit_bound(model, r),
           string_ground=bound + v * model.puppet_dt)


def test_the_scene_key_is_read_from_a_scene_file(tmp_path):
    """``[effects] tension_only`` defaults to false (the printed spring); ``true`` in a scene
    file is read, with the puppet at 30 Hz as with ``puppet_hz = string_hz``."""
    text = (SCENE_DIR / "hanging.toml").read_text()
    assert dm.load_scene("hanging").effects.tension_only is False
    slow = tmp_path / "slow.toml"
    slow.write_text(text.replace("feedback = true", "feedback = true\ntension_only = true", 1)
                    .replace('include = "puppet.toml"', f'include = "{SCENE_DIR / "puppet.toml"}"', 1))
    scene = dm.load_scene(slow)
    assert scene.effects.tension_only is True and scene.puppet_hz == 30.0
    check_marionette_settings(scene)
    fast = tmp_path / "fast.toml"
    fast.write_text(slow.read_text().replace("puppet_hz = 30.0", "puppet_hz = 1000.0", 1))
    assert dm.load_scene(fast).effects.tension_only is True


@pytest.fixture(scope="module")
def tension_only_30_hz():
    """The ``hanging`` scene with tension-only strings at the paper's rates (puppet 30 Hz)."""
    scene = dm.load_scene("hanging")
    return dataclasses.replace(scene, effects=dataclasses.replace(scene.effects, tension_only=True))


def test_at_30_hz_still_bars_settle(tension_only_30_hz):
    """Still bars, 6 s, puppet at 30 Hz: within the energy bound and the puppet hangs still
    (torso below 1 mm/s, as at 1 kHz). With the ``x + H v`` tie path of before it still moved
    at 1.3 mm/s after 6 s, one reason tension-only strings were refused under a slower
    puppet. Measured: torso at 1.3e-6 m/s, energy at most -1.65e-2 J from ``E(0)``."""
    scene = dataclasses.replace(tension_only_30_hz, bars=tuple(still_bar(b) for b in tension_only_30_hz.bars))
    model = MarionetteModel(scene, optimization_level=0)
    r = simulate_energy_balance(model, 6.0)
    check_case("still bars, tension-only, 30 Hz", model, r, ground=0.0, limit=limit_bound(model, r))
    speed = np.linalg.norm(r["body_pos"][-1, 0] - r["body_pos"][-2, 0]) / (r["time"][-1] - r["time"][-2])
    print(f"torso speed at 6 s {speed:.2e} m/s")
    assert speed < 1e-3


def test_at_30_hz_10x_stiffer_strings_settle(tension_only_30_hz):
    """10x stiffer tension-only strings (stiffness, tie stiffness and damping) at 30 Hz, the
    scene's sway, 4 s: finite, within the energy bound, the torso within 1 cm of its start.
    With the ``x + H v`` tie path of before the puppet bounced on its head string and was
    pumped 13 cm up (the case that had tension-only strings refused under a slower puppet).
    Measured: torso -2.7 mm, energy at most -5.0e-3 J from ``E(0) + W``."""
    strings = tuple(dataclasses.replace(s, stiffness=10 * s.stiffness, tie_stiffness=10 * s.tie_stiffness,
                                        tie_damping=10 * s.tie_damping) for s in tension_only_30_hz.strings)
    model = MarionetteModel(dataclasses.replace(tension_only_30_hz, strings=strings), optimization_level=0)
    r = simulate_energy_balance(model, 4.0)
    check_case("10x stiffer, tension-only, 30 Hz", model, r, ground=0.0, limit=limit_bound(model, r))
    rise = r["body_pos"][-1, 0, 1] - r["body_pos"][0, 0, 1]
    print(f"torso {rise * 1e3:+.1f} mm after 4 s")
    assert abs(rise) < 0.01
