"""What the live view shows, published by the physics without slowing the servo loop.

The physics thread (the servo loop's worker) owns the simulation state. At the view's rate
(wall clock, ~40 Hz by default) and only then, :class:`LiveViewPublisher` copies what a view
needs (particles, body poses, bar poses, taut flags, per-bar reaction, the force last sent
to the device) into a new :class:`LiveSnapshot`, and :class:`SnapshotBuffer` swaps it in
with one reference assignment. A reader (the view's own thread) takes the latest snapshot
whole: the snapshots are never written after they are published, so it can never see a
half-written one, and neither side waits for a lock. That swap is the double buffer: one
snapshot being read, the next being filled. On the tick where a snapshot is due the copy
costs the physics thread ~20 µs; on every other tick one clock read and a comparison.

:class:`LiveViewGeometry` is what does not change (body shapes, string layout, bar attach
points, the ground), and :func:`string_colors` the taut/slack colour code shared by the
browser view (:mod:`dmarionette.live.view_viser`) and the headless picture
(:func:`render_live_snapshot`).
"""

from __future__ import annotations

import abc
import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import final

import numpy as np

from dmarionette.render.pyplot import headless_pyplot
from dmarionette.rotations import euler_to_matrix, from_wxyz, quat_rotate, to_wxyz

__all__ = ["AbstractLiveView", "LiveSnapshot", "LiveViewGeometry", "LiveViewHeadless", "LiveViewPublisher", "SLACK_RGB",
           "SnapshotBuffer", "TAUT_RGB",
           "render_live_snapshot", "string_colors"]

TAUT_RGB = (38, 38, 38)
"""Colour of a taut string (dark grey, as in the offline animation)."""
SLACK_RGB = (255, 140, 0)
"""Colour of a slack string (dark orange, as in the offline animation)."""


def string_colors(taut: np.ndarray) -> np.ndarray:
    """RGB colour per string from its taut flag: :data:`TAUT_RGB` or :data:`SLACK_RGB`.

    Args:
        taut: Taut flag per string, shape (S,) (bool or int; non-zero = taut).

    Returns:
        Colours, uint8, shape (S, 3).
    """
    taut = np.asarray(taut).reshape(-1) != 0
    return np.where(taut[:, None], np.array(TAUT_RGB, np.uint8), np.array(SLACK_RGB, np.uint8)).astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class LiveViewGeometry:
    """The parts of the scene a view draws that do not change during a session.

    Attributes:
        body_names: Puppet bodies (the ball last when the scene has one), shape (Nb,).
        body_shape: Per body ``("box", full extents (3,) [m])`` or ``("sphere", (radius [m], 0, 0))``.
        string_names: Strings, shape (S,).
        string_start: First particle of each string and the particle count at the end, shape (S + 1,).
        bar_names: Control bars, shape (B,).
        bar_attach: Per bar, its strings' attach points in the bar frame [m], shape (k, 3) each.
        driven_bar: Index of the bar the (first) device drives.
        ground_height: Height of the ground [m] (y up).
        chair: ``(centre (3,), half extents (3,))`` [m] of the chair, or None.
        driven_bars: Indices of the bars the devices drive, in device order (``driven_bar`` first);
            each gets a drag handle (simulated devices) and a force-sent arrow. Empty means
            ``(driven_bar,)``: use :attr:`device_bars`.
    """

    body_names: tuple
    body_shape: tuple
    string_names: tuple
    string_start: np.ndarray
    bar_names: tuple
    bar_attach: tuple
    driven_bar: int
    ground_height: float
    chair: tuple | None
    driven_bars: tuple = ()

    @property
    def device_bars(self) -> tuple:
        """Indices of the device-driven bars, one per device in device order."""
        return tuple(self.driven_bars) or (self.driven_bar,)

    @staticmethod
    def from_model(model, driven_bar: str | Sequence[str]) -> LiveViewGeometry:
        """The geometry of a :class:`~dmarionette.marionette.solver.MarionetteModel` whose ``driven_bar`` a
        device drives, or whose bars ``driven_bar`` (a sequence, one per device) the devices drive."""
        scene = model.scene
        names = [driven_bar] if isinstance(driven_bar, str) else list(driven_bar)
        for name in names:
            if name not in model.bar_names:
                raise ValueError(f"driven bar: got {name!r}; expected one of {model.bar_names}")
        if not names or len(set(names)) != len(names):
            raise ValueError(f"driven bars: got {names}; expected distinct bars, one per device")
        return LiveViewGeometry(
            body_names=tuple(model.puppet.body_names), body_shape=tuple(model.puppet.body_shape),
            string_names=tuple(model.strings.string_names), string_start=model.strings.string_start_np.copy(),
            bar_names=tuple(model.bar_names),
            bar_attach=tuple(np.array(list(bar.attach.values()), dtype=np.float64).reshape(-1, 3)
                             for bar in scene.bars),
            driven_bar=model.bar_names.index(names[0]), ground_height=float(scene.ground_height),
            chair=scene.chair, driven_bars=tuple(model.bar_names.index(name) for name in names))

    def string_segments(self) -> np.ndarray:
        """Particle index pairs of every string segment, shape (P - S, 2)."""
        return np.array([(i, i + 1) for a, b in zip(self.string_start[:-1], self.string_start[1:])
                         for i in range(a, b - 1)], dtype=np.int64).reshape(-1, 2)

    def string_of_segment(self) -> np.ndarray:
        """String index of each segment of :meth:`string_segments`, shape (P - S,)."""
        return np.concatenate([np.full(b - a - 1, s, dtype=np.int64) for s, (a, b) in
                               enumerate(zip(self.string_start[:-1], self.string_start[1:]))])


@dataclasses.dataclass(frozen=True)
class LiveSnapshot:
    """One frame of the live session, world frame, SI units (never modified once published).

    Attributes:
        sequence: 1 for the first snapshot published, then +1 each.
        t: Simulated time [s] (string steps run times the string step).
        wall_time: ``time.perf_counter()`` when it was taken [s].
        particle_q: String particles [m], shape (P, 3), after the latest string step.
        body_pos: Body centres [m], shape (Nb, 3), at the start of the current puppet step.
        body_wxyz: Body orientations, unit quaternions (w, x, y, z), shape (Nb, 4).
        bar_pos: Bar centres [m], shape (B, 3).
        bar_rot: Bar orientations, rotation matrices, shape (B, 3, 3).
        string_taut: Taut flag per string after the latest string step, shape (S,).
        bar_reaction: The strings' pull on each bar [N], shape (B, 3).
        force_sent: The force last written to the device, after the safety filter, in the world
            frame [N], shape (3,) (zero before the first write); with several devices one row per
            device, in device order, shape (D, 3) (:meth:`forces_sent` gives (D, 3) either way).
        dragged: True once the view has taken the device over (its drag is the device's input).
    """

    sequence: int
    t: float
    wall_time: float
    particle_q: np.ndarray
    body_pos: np.ndarray
    body_wxyz: np.ndarray
    bar_pos: np.ndarray
    bar_rot: np.ndarray
    string_taut: np.ndarray
    bar_reaction: np.ndarray
    force_sent: np.ndarray
    dragged: bool = False

    def forces_sent(self) -> np.ndarray:
        """The forces last written to the devices [N], world frame, one row per device, shape (D, 3)."""
        return np.asarray(self.force_sent, dtype=np.float64).reshape(-1, 3)


class SnapshotBuffer:
    """The latest :class:`LiveSnapshot`: one writer publishes, readers take it whole.

    Publishing is a reference assignment (atomic in Python) plus an event that wakes a
    waiting reader; neither side holds a lock while it copies or draws.
    """

    def __init__(self) -> None:
        self._latest: LiveSnapshot | None = None
        self._fresh = threading.Event()
        self.published = 0
        """Snapshots published so far."""

    def publish(self, snapshot: LiveSnapshot) -> None:
        """Makes ``snapshot`` the latest (writer side)."""
        self._latest = snapshot
        self.published += 1
        self._fresh.set()

    def latest(self) -> LiveSnapshot | None:
        """The latest snapshot, or None before the first."""
        return self._latest

    def wait(self, timeout: float) -> LiveSnapshot | None:
        """Waits up to ``timeout`` [s] for a snapshot newer than the last one waited for."""
        if not self._fresh.wait(timeout):
            return None
        self._fresh.clear()
        return self._latest


class LiveViewPublisher:
    """Takes snapshots of a :class:`~dmarionette.live.physics.LiveMarionette` at a wall-clock rate.

    Called by the physics step after every tick (:func:`dmarionette.live.physics.make_physics_step`);
    it does real work only when a snapshot is due.

    Args:
        buffer: Where the snapshots go.
        rate_hz: Snapshots per second of wall time [Hz].
        force_to_world: Maps the device-frame force written to the device to the world
            (``DeviceMapping.force_to_world``); identity when None. Several devices: a sequence,
            one per device; snapshots then carry one force-sent row per device.
    """

    def __init__(self, buffer: SnapshotBuffer, rate_hz: float = 40.0, force_to_world=None) -> None:
        if not (np.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"view rate: got {rate_hz!r} Hz; expected a finite rate > 0")
        self.buffer = buffer
        self.period = 1.0 / float(rate_hz)
        self._several = isinstance(force_to_world, (list, tuple))
        self._force_to_world = list(force_to_world) if self._several else [force_to_world]
        self._next = 0.0
        self.force_sent = np.zeros((len(self._force_to_world), 3)) if self._several else np.zeros(3)
        """The force last written to the device [N], device frame (set by the servo thread); with
        several devices one row per device (:meth:`set_force_sent`)."""
        self.dragged = False
        """Set when the view takes the device over."""
        self._views = None

    def set_force_sent(self, device: int, force) -> None:
        """The force last written to device ``device`` [N], device frame (servo thread)."""
        if self._several:
            self.force_sent[device] = force
        else:
            self.force_sent = force

    def due(self) -> bool:
        """True when a snapshot should be taken now (one clock read)."""
        return time.perf_counter() >= self._next

    def publish(self, live, bar_pos: np.ndarray, bar_rot: np.ndarray, bar_reaction: np.ndarray) -> None:
        """Copies the live marionette's state into a new snapshot and publishes it.

        Args:
            live: The :class:`~dmarionette.live.physics.LiveMarionette`, between two ticks.
            bar_pos: Bar centres at the end of the tick [m], shape (B, 3).
            bar_rot: Bar orientations, shape (B, 3, 3).
            bar_reaction: Reaction per bar of the tick [N], shape (B, 3).
        """
        now = time.perf_counter()
        self._next = max(self._next + self.period, now)  # no burst after a stall
        if self._views is None:  # host views of the (fixed) state buffers, made once
            self._views = (live.state.puppet.body_pos.numpy(), live.state.puppet.body_rot.numpy())
        body_pos, body_rot = self._views
        if self._several:
            rows = np.array(self.force_sent, dtype=np.float64)  # a copy: the servo thread writes on
            force = np.array([row if to_world is None else to_world(row)
                              for row, to_world in zip(rows, self._force_to_world)])
        else:
            force = np.asarray(self.force_sent, dtype=np.float64)
            if self._force_to_world[0] is not None:
                force = self._force_to_world[0](force)
        self.buffer.publish(LiveSnapshot(
            sequence=self.buffer.published + 1, t=live.time, wall_time=now,
            particle_q=live.latest_particle_q().copy(), body_pos=body_pos[0].copy(),
            body_wxyz=to_wxyz(body_rot[0]),
            bar_pos=np.array(bar_pos, dtype=np.float64), bar_rot=np.array(bar_rot, dtype=np.float64),
            string_taut=live.latest_string_taut().copy(), bar_reaction=np.array(bar_reaction, dtype=np.float64),
            force_sent=np.array(force, dtype=np.float64), dragged=self.dragged))


class AbstractLiveView(abc.ABC):
    """A view of a live session, fed by :func:`dmarionette.live.run.run_live`.

    Attributes:
        buffer: Where the physics publishes its snapshots.
        rate_hz: Snapshots per second the view wants [Hz].
    """

    buffer: SnapshotBuffer
    rate_hz: float

    @abc.abstractmethod
    def connect_device(self, drag: Callable[[np.ndarray, np.ndarray], None] | None) -> None:
        """What a drag in the view calls, ``drag(position [m] (3,), rotation (3, 3))`` in the world
        frame, or None when the device cannot be moved by the view."""

    def connect_devices(self, drags: Sequence[Callable[[np.ndarray, np.ndarray], None] | None]) -> None:
        """Several devices: ``drags[i]`` is what a drag of device ``i``'s bar (``geometry.device_bars[i]``)
        calls, or None. A view that handles one device only connects the first."""
        self.connect_device(drags[0] if drags else None)

    @abc.abstractmethod
    def close(self) -> None:
        """Stops the view (idempotent)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@final
class LiveViewHeadless(AbstractLiveView):
    """No display: keeps the latest snapshot, for a picture at the end (``live --snapshot FILE``).

    Args:
        rate_hz: Snapshots per second [Hz] (only the last one is used).
    """

    def __init__(self, rate_hz: float = 10.0) -> None:
        self.buffer = SnapshotBuffer()
        self.rate_hz = float(rate_hz)

    def connect_device(self, drag) -> None:
        """Nothing can be dragged without a display."""

    def close(self) -> None:
        """Nothing to stop."""


def scripted_rotations(angles_deg: list[np.ndarray], k: int) -> np.ndarray:
    """Rotation matrices of the scripted bars at tick ``k`` from their XYZ angles [deg], shape (B, 3, 3)."""
    return euler_to_matrix(np.array([a[k] for a in angles_deg]).reshape(-1, 3))


def render_live_snapshot(path: str | Path, geometry: LiveViewGeometry, snapshot: LiveSnapshot, *,
                         title: str = "", arrow_scale: float = 0.03) -> Path:
    """A picture (PNG) of one snapshot: front (x-y) and side (z-y) views, no browser needed.

    Boxes and sphere rings for the bodies, strings coloured by :func:`string_colors`, bars
    as lines from their centre to their attach points, the reaction on each bar (red) and the
    force sent to the device (blue) as arrows of ``arrow_scale`` [m/N].
    """
    plt = headless_pyplot("--snapshot pictures")
    from dmarionette.render.marionette import draw_chair  # here, not at the top: it imports the simulator

    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    ring = np.linspace(0.0, 2.0 * np.pi, 33)
    colors = string_colors(snapshot.string_taut) / 255.0
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    points = np.concatenate([snapshot.particle_q, snapshot.body_pos, snapshot.bar_pos])
    lo, hi = points.min(axis=0) - 0.08, points.max(axis=0) + 0.08
    lo[1] = min(lo[1], geometry.ground_height - 0.03)
    span = float(np.max(hi - lo))
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.5))
    for ax, (axis, label) in zip(axes, ((0, "x [m] (front)"), (2, "z [m] (side)"))):
        centre = 0.5 * (lo[axis] + hi[axis])
        ax.set_xlim(centre - span / 2, centre + span / 2)
        ax.set_ylim(lo[1], lo[1] + span)
        ax.set_aspect("equal")
        ax.axhspan(lo[1], geometry.ground_height, color="0.88")
        ax.set_xlabel(label)
        ax.set_ylabel("y [m]")
        draw_chair(ax, geometry.chair, axis)
        for (shape, size), centre3, q in zip(geometry.body_shape, snapshot.body_pos, snapshot.body_wxyz):
            if shape == "box":
                world = centre3 + quat_rotate(from_wxyz(q), corners * 0.5 * np.asarray(size))
                for i, j in edges:
                    ax.plot(world[[i, j], axis], world[[i, j], 1], color="steelblue", lw=1.0)
            else:
                for loop in (np.stack([np.cos(ring), np.sin(ring), 0 * ring], 1),
                             np.stack([0 * ring, np.sin(ring), np.cos(ring)], 1)):
                    world = centre3 + quat_rotate(from_wxyz(q), size[0] * loop)
                    ax.plot(world[:, axis], world[:, 1], color="steelblue", lw=1.0)
        for s in range(len(geometry.string_names)):
            a, b = geometry.string_start[s], geometry.string_start[s + 1]
            ax.plot(snapshot.particle_q[a:b, axis], snapshot.particle_q[a:b, 1], color=colors[s], lw=1.2)
        for b, attach in enumerate(geometry.bar_attach):
            for point in snapshot.bar_pos[b] + attach @ snapshot.bar_rot[b].T:
                ends = np.stack([snapshot.bar_pos[b], point])
                ax.plot(ends[:, axis], ends[:, 1], color="saddlebrown", lw=3)
            tail, force = snapshot.bar_pos[b], arrow_scale * snapshot.bar_reaction[b]
            ax.annotate("", xy=(tail[axis] + force[axis], tail[1] + force[1]), xytext=(tail[axis], tail[1]),
                        arrowprops={"arrowstyle": "->", "color": "crimson", "lw": 1.5})
        for b, sent in zip(geometry.device_bars, snapshot.forces_sent()):
            tail, force = snapshot.bar_pos[b], arrow_scale * sent
            ax.annotate("", xy=(tail[axis] + force[axis], tail[1] + force[1]), xytext=(tail[axis], tail[1]),
                        arrowprops={"arrowstyle": "->", "color": "royalblue", "lw": 1.5})
    fig.suptitle(f"{title}   t = {snapshot.t:.3f} s\nstrings: dark taut, orange slack; arrows: red = reaction on "
                 f"each bar, blue = force sent to each device ({arrow_scale:g} m/N)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
