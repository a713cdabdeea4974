"""A batched marionette: ``W`` worlds in the same launches (issue #16, ``MarionetteModel.from_scenes``).

The worlds do not interact and every kernel computes each (world, string) and (world, body)
with the same arithmetic as a one-world model, so a batched run must give, world by world,
exactly (bit for bit, on the CPU) the trajectories of ``W`` separate runs. The scene is the
shipped ``hanging`` as shipped (50 particles per string, joint limits, ground contact and
feedback on), the worlds differ in ``k`` and in the hand bar's place (so in their string
tops and lengths), and the run lasts 1.5 s (the main bar starts rocking at 1 s).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.marionette.rollout import simulate_marionette, simulate_worlds
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.sweep.grid import parse_set, sweep_variants

wp.config.log_level = wp.LOG_WARNING

DURATION = 1.5
FIELDS = ("particle_q", "joint_q", "body_pos", "body_rot", "bar_pos", "bar_rot", "top_q", "tie_force",
          "string_taut", "bar_feedback", "bar_reaction", "string_rest_length", "string_start")


@pytest.fixture(scope="module")
def scenes():
    axes = [parse_set("strings.k=200,450"), parse_set("bars.hand.position=[0.0,1.2,0.12],[0.03,1.22,0.1]")]
    return [v.scene for v in sweep_variants("hanging", axes)]


@pytest.fixture(scope="module")
def runs(scenes):
    batched = simulate_worlds(MarionetteModel.from_scenes(scenes, optimization_level=0), DURATION, progress=False)
    single = [simulate_marionette(MarionetteModel(s, optimization_level=0), DURATION, progress=False) for s in scenes]
    return batched, single


def test_each_world_is_bit_for_bit_its_own_run(runs):
    batched, single = runs
    assert len(batched) == len(single) == 4
    for w, (got, want) in enumerate(zip(batched, single)):
        for name in FIELDS:
            a, b = getattr(got, name), getattr(want, name)
            assert a.shape == b.shape, (w, name)
            assert np.array_equal(a, b), (w, name, np.max(np.abs(a - b)))
        assert got.string_names == want.string_names and got.bar_names == want.bar_names


def test_the_worlds_move_differently(runs):
    batched, _ = runs
    torso = [t.body_pos[:, 0] for t in batched]
    spread = min(np.max(np.abs(torso[a] - torso[b])) for a in range(4) for b in range(a))
    print(f"\nsmallest torso difference between two worlds: {spread * 1e3:.2f} mm")
    assert spread > 1e-4


def test_copies_of_one_scene_are_the_one_world_run(scenes):
    model = MarionetteModel(scenes[0], world_count=3, optimization_level=0)
    assert model.world_count == 3 and model.strings.string_count == 3 * model.strings_per_world
    runs = simulate_worlds(model, 0.2, progress=False)
    want = simulate_marionette(MarionetteModel(scenes[0], optimization_level=0), 0.2, progress=False)
    for run in runs:
        assert np.array_equal(run.joint_q, want.joint_q) and np.array_equal(run.tie_force, want.tie_force)


def test_worlds_that_differ_in_what_the_kernels_share_are_refused_by_name():
    hanging = dm.load_scene("hanging")
    fewer = dataclasses.replace(hanging, strings=tuple(dataclasses.replace(s, particle_count=20)
                                                       for s in hanging.strings))
    with pytest.raises(ValueError, match=r"world 1 .*string particle counts = \[20, 20"):
        MarionetteModel.from_scenes([hanging, fewer])
    faster = dataclasses.replace(hanging, puppet_hz=60.0)
    with pytest.raises(ValueError, match=r"world 1 .*\[rates\] puppet_hz = 60.0.*world 0's .*30.0"):
        MarionetteModel.from_scenes([hanging, faster])
    with pytest.raises(ValueError, match="world_count: got 0"):
        MarionetteModel(hanging, world_count=0)
    with pytest.raises(ValueError, match="use simulate_worlds"):
        simulate_marionette(MarionetteModel(hanging, world_count=2, optimization_level=0), 0.1, progress=False)
