"""Recorded sessions in MCAP (docs/session.md): write, read (also cut-off files), summarise,
replay.

::

    from dmarionette.io.session import SessionWriter, read_session, replay_session, session_info

    with SessionWriter("take.mcap", scene, scene_text) as writer:   # the live loop, at 1 kHz
        writer.write_device_sample("main", sample)
        writer.write_force("main", t, force)
        writer.write_bar_pose("main", t, position, rotation_deg)
        ...
    session = read_session("take.mcap")       # numpy arrays per channel, metadata, scene
    trajectory, report = replay_session("take.mcap")
"""

from dmarionette.io.session.read import Session as Session
from dmarionette.io.session.read import format_session_info as format_session_info
from dmarionette.io.session.read import read_session as read_session
from dmarionette.io.session.read import session_bar_trajectories as session_bar_trajectories
from dmarionette.io.session.read import session_info as session_info
from dmarionette.io.session.replay import record_simulation as record_simulation
from dmarionette.io.session.replay import replay_session as replay_session
from dmarionette.io.session.replay import scene_for_replay as scene_for_replay
from dmarionette.io.session.format import FORMAT as FORMAT
from dmarionette.io.session.format import FORMAT_VERSION as FORMAT_VERSION
from dmarionette.io.session.write import SCHEMAS as SCHEMAS
from dmarionette.io.session.write import SessionWriter as SessionWriter

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "SCHEMAS",
    "Session",
    "SessionWriter",
    "format_session_info",
    "read_session",
    "record_simulation",
    "replay_session",
    "scene_for_replay",
    "session_bar_trajectories",
    "session_info",
]
