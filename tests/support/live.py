"""Driving the live marionette tick by tick as a device would, with the scene's own bar motion."""

from __future__ import annotations

import numpy as np

from dmarionette.hw import HapticSample
from dmarionette.live.run import LiveMarionette, make_physics_step
from dmarionette.marionette.rollout import simulate_marionette


def drive_like_the_scene(model, puppet_steps: int):
    """Runs ``puppet_steps`` puppet steps of ticks of a :class:`LiveMarionette` whose ``main`` bar
    follows the scene's own trajectory (a device sampled at every tick).

    Returns:
        ``(live, forces, offline)``: the live marionette after the ticks, the force of every tick
        ``(ticks, 3)``, and the captured offline rollout of the same duration.
    """
    live = LiveMarionette(model)
    steps = puppet_steps * model.substeps
    times = model.string_dt * np.arange(1, steps + 1)
    position, _, rotation = model.scene.bars[0].trajectory.pose(times)
    step = make_physics_step(live, "main", steps * model.string_dt)
    forces = np.array([step(HapticSample.make(time=times[k], position=position[k], orientation=rotation[k]),
                            times[k]) for k in range(steps)])
    offline = simulate_marionette(model, puppet_steps * model.puppet_dt - 1e-9, progress=False)
    return live, forces, offline
