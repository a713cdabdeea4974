"""Recording a live session (MCAP, ``docs/session.md``): the file opened for a scene, and one tick written.

Whichever process steps the marionette writes the recording: the ``dmarionette live``
process with the physics in its worker thread, the physics process otherwise
(:mod:`dmarionette.live.process`). Both go through :class:`dmarionette.live.setup.LivePhysics`,
which calls these.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dmarionette.live.physics import LiveMarionette, LiveTick

if TYPE_CHECKING:  # imported when a session is recorded: the MCAP writer's imports take seconds
    from dmarionette.io.session import SessionWriter

__all__ = ["open_session_writer", "record_start", "record_tick"]


def open_session_writer(path: str | Path, scene, live_metadata: dict[str, Any] | None = None) -> SessionWriter:
    """A session writer for ``scene`` (its file's text kept in the recording).

    Args:
        path: The MCAP file to write.
        scene: The scene stepped live (``scene.source``: its file).
        live_metadata: Written as the ``"live"`` metadata record (devices, mappings, feedback), or None.
    """
    from dmarionette.io.session import SessionWriter

    writer = SessionWriter(path, scene, Path(scene.source).read_text())
    if live_metadata is not None:
        writer.write_metadata("live", live_metadata)
    return writer


def record_start(writer: SessionWriter, live: LiveMarionette) -> None:
    """Writes the state a live session starts from, at t = 0: every bar's pose (the scene's, where a
    device's mapping puts its origin) and the puppet's rest state.

    A replay starts its strings from the first recorded bar pose. Without this record that
    would be the pose after the first tick, which a device has already moved away from the
    start (the more, the longer the first tick waited), and the replay would start from a
    different string state than the live session did.
    """
    model = live.model
    for bar in model.scene.bars:
        position = bar.trajectory.pose(np.zeros(1))[0][0]
        writer.write_bar_pose(bar.name, 0.0, position, bar.trajectory.angles(np.zeros(1))[0])
    puppet = live.state.puppet
    model.puppet_solver.eval_kinematics(puppet)
    writer.write_puppet_state(0.0, puppet.joint_q.numpy()[0].copy(), puppet.body_pos.numpy()[0].copy(),
                              puppet.body_rot.numpy()[0].copy())


def record_tick(writer: SessionWriter, live: LiveMarionette, tick: LiveTick, poses: dict) -> None:
    """Writes one tick of a live session: every bar's pose and feedback, taut flags, and after a
    puppet step the puppet's state.

    Args:
        writer: The session's writer.
        live: The marionette that ran the tick.
        tick: What the tick produced.
        poses: Every bar's pose at the tick's end, ``{bar: (position (3,), rotation (3,) XYZ deg)}``.
    """
    model = live.model
    for b, name in enumerate(model.bar_names):
        writer.write_feedback(name, tick.t, tick.bar_feedback[b], tick.bar_reaction[b])
        writer.write_bar_pose(name, tick.t, *poses[name])
    writer.write_taut(tick.t, tick.string_taut)
    if tick.puppet_stepped:
        puppet = live.state.puppet
        model.puppet_solver.eval_kinematics(puppet)
        writer.write_puppet_state(tick.t, puppet.joint_q.numpy()[0].copy(), puppet.body_pos.numpy()[0].copy(),
                                  puppet.body_rot.numpy()[0].copy())
