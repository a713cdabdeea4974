"""The live view in a web browser (viser): puppet, strings, bars and forces, updated live.

:class:`LiveViewServer` serves a three.js page (viser) on ``http://HOST:PORT``. Its own
thread waits for the snapshots the physics publishes (:mod:`dmarionette.live.view`) and
sends each one to the browsers as a handful of scene updates (one per node kind: boxes,
spheres, strings and their colours, bars, arrows, the drag handle), so one frame is ~8
small websocket messages whatever the number of bodies. It never touches the simulation
state, and the physics never waits for it.

For a simulated device the driven bar carries a transform gizmo (``/drag/BAR``): dragging it
(arrows move, rings rotate) calls the ``drag`` callback given by
:func:`dmarionette.live.run.run_live`, which hands the pose to the device
(:meth:`dmarionette.hw.HapticDeviceSimulated.drag_to`); the bar then follows the device like
any device-driven bar. Other devices: no gizmo. With two devices (one per bar) each
device-driven bar has its own gizmo, moving its own device, and its own force-sent arrow.

Needs the ``view`` extra: ``pip install 'dmarionette[view]'``.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import final

import numpy as np

from dmarionette.live.view import AbstractLiveView, LiveSnapshot, LiveViewGeometry, SnapshotBuffer, string_colors
from dmarionette.rotations import from_wxyz, matrix_to_quat, normalize_quat, quat_to_matrix, to_wxyz

__all__ = ["LiveViewServer"]

BODY_RGB = (70, 130, 180)
BALL_RGB = (220, 20, 60)
BAR_RGB = (139, 69, 19)
REACTION_RGB = (220, 20, 60)
SENT_RGB = (65, 105, 225)

_UNIT_BOX_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)],
                              dtype=np.float32)
# Two triangles per face, outward (counter-clockwise seen from outside); vertex index = 4x + 2y + z.
_UNIT_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                            [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.uint32)


def _icosphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (unit radius) and faces of an icosphere."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11],
         [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    vertices = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def middle(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = vertices[a] + vertices[b]
                vertices.append(m / np.linalg.norm(m))
                cache[key] = len(vertices) - 1
            return cache[key]

        f = [g for a, b, c in f for g in ([a, middle(a, b), middle(c, a)], [b, middle(b, c), middle(a, b)],
                                          [c, middle(c, a), middle(b, c)],
                                          [middle(a, b), middle(b, c), middle(c, a)])]
    return np.array(vertices, dtype=np.float32), np.array(f, dtype=np.uint32)


@final
class LiveViewServer(AbstractLiveView):
    """A browser view of a live session, served by viser on ``host:port``.

    Use as a context manager (or call :meth:`close`); pass it to
    :func:`dmarionette.live.run.run_live` as ``view``.

    Args:
        geometry: What the scene looks like (:meth:`LiveViewGeometry.from_model`).
        host: Address to serve on; loopback by default (the view accepts drags, which move
            the simulated device: do not expose it to a network you do not trust).
        port: TCP port; 0 picks a free one (see :attr:`port`). If the port is taken, viser
            tries the next ones.
        rate_hz: Snapshots per second the physics publishes and the view sends [Hz].
        arrow_scale: Length of the force arrows per newton [m/N].
    """

    def __init__(self, geometry: LiveViewGeometry, *, host: str = "127.0.0.1", port: int = 8080,
                 rate_hz: float = 40.0, arrow_scale: float = 0.03) -> None:
        try:
            import viser
        except ImportError:
            raise RuntimeError("the browser view needs viser: pip install 'dmarionette[view]' "
                               "(or run with --view none)") from None
        if not 0 <= int(port) <= 65535:
            raise ValueError(f"--view-port: got {port}; expected a TCP port 0-65535 (0: any free port)")
        self.geometry = geometry
        self.rate_hz = float(rate_hz)
        self.arrow_scale = float(arrow_scale)
        self.buffer = SnapshotBuffer()
        self.frames_sent = 0
        """Snapshots sent to the scene so far."""
        self.update_seconds = 0.0
        """Wall time spent in :meth:`update` so far [s] (the view thread's work per frame, summed)."""
        self.last_sent: LiveSnapshot | None = None
        """The last snapshot sent (what the scene shows)."""
        self._drags: list[Callable[[np.ndarray, np.ndarray], None] | None] = []
        self._dragging: set[int] = set()  # devices whose gizmo the mouse holds
        self._gizmo_lock = threading.Lock()  # the dragged set and the view thread's gizmo writes
        self._stop = threading.Event()
        if not (np.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"view rate: got {rate_hz!r} Hz; expected a finite rate > 0")
        with contextlib.redirect_stdout(sys.stderr):  # viser's banner; stdout carries the CLI's JSON summary
            self._server = viser.ViserServer(host=host, port=int(port), label="dmarionette live", verbose=False)
        self.host = host
        self.port = self._server.get_port()
        try:
            self._build_scene()
        except BaseException:
            self._stop_server()
            raise
        self._thread = threading.Thread(target=self._run, name="dmarionette-view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """Where to point the browser."""
        return f"http://{self.host}:{self.port}"

    @property
    def server(self):
        """The underlying ``viser.ViserServer``."""
        return self._server

    @property
    def is_running(self) -> bool:
        """True while the update thread runs."""
        return self._thread.is_alive()

    def _build_scene(self) -> None:
        g, scene = self.geometry, self._server.scene
        scene.set_up_direction("+y")
        self._server.initial_camera.position = (0.75, 1.05, 1.05)
        self._server.initial_camera.look_at = (0.0, 0.75, 0.0)
        scene.add_grid("/ground", width=3.0, height=3.0, plane="xz", position=(0.0, g.ground_height, 0.0),
                       cell_size=0.1, section_size=0.5)
        if g.chair is not None:
            centre, half = g.chair
            scene.add_box("/chair", color=(210, 180, 140), dimensions=tuple(2.0 * np.asarray(half)),
                          position=tuple(centre))
        self._boxes = [i for i, (shape, _) in enumerate(g.body_shape) if shape == "box"]
        self._spheres = [i for i, (shape, _) in enumerate(g.body_shape) if shape != "box"]
        identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(g.body_shape), 1))
        zeros = np.zeros((len(g.body_shape), 3))
        self._box_node = scene.add_batched_meshes_simple(
            "/puppet/boxes", _UNIT_BOX_VERTICES, _UNIT_BOX_FACES, identity[self._boxes], zeros[self._boxes],
            batched_scales=np.array([g.body_shape[i][1] for i in self._boxes], dtype=np.float32),
            batched_colors=BODY_RGB, flat_shading=True, lod="off") if self._boxes else None
        sphere_vertices, sphere_faces = _icosphere(2)
        colors = np.array([BALL_RGB if g.body_names[i] == "ball" else BODY_RGB for i in self._spheres], np.uint8)
        self._sphere_node = scene.add_batched_meshes_simple(
            "/puppet/spheres", sphere_vertices, sphere_faces, identity[self._spheres], zeros[self._spheres],
            batched_scales=np.array([g.body_shape[i][1][0] for i in self._spheres], dtype=np.float32),
            batched_colors=colors.reshape(-1, 3), lod="off") if self._spheres else None
        self._segments = g.string_segments()
        self._segment_string = g.string_of_segment()
        self._string_node = scene.add_line_segments(
            "/strings", np.zeros((len(self._segments), 2, 3), np.float32), (255, 140, 0), thickness=0.004)
        self._bar_segments = [(b, k) for b, attach in enumerate(g.bar_attach) for k in range(len(attach))]
        self._bar_node = scene.add_line_segments(
            "/bars", np.zeros((len(self._bar_segments), 2, 3), np.float32), BAR_RGB, thickness=0.012)
        devices = g.device_bars
        # One reaction arrow per bar, then one force-sent arrow per device (on its bar).
        arrow_colors = np.array([REACTION_RGB] * len(g.bar_names) + [SENT_RGB] * len(devices), dtype=np.uint8)
        self._arrow_node = scene.add_arrows(
            "/forces", np.zeros((len(g.bar_names) + len(devices), 2, 3), np.float32), arrow_colors,
            shaft_radius=0.004, head_radius=0.01, head_length=0.02)
        self._gizmos = []
        for i, b in enumerate(devices):
            gizmo = scene.add_transform_controls(f"/drag/{g.bar_names[b]}", scale=0.18, depth_test=False,
                                                 visible=False)
            gizmo.on_update(self._gizmo_callback(i))
            self._gizmos.append(gizmo)
        self._drags = [None] * len(devices)
        self._status = self._server.gui.add_markdown("waiting for the first snapshot")
        self._server.gui.add_markdown(
            "**Strings:** dark = taut, orange = slack. **Arrows** "
            f"({self.arrow_scale:g} m/N): red = the strings' pull on each bar, blue = the force sent to the "
            "device (after the safety filter), one per device. With a simulated device, drag the gizmo on "
            "its bar (arrows move it, rings turn it): the device follows the mouse from then on.")

    @property
    def drag_handles_visible(self) -> tuple[bool, ...]:
        """Whether each device's drag handle (gizmo) shows, in :attr:`LiveViewGeometry.device_bars` order."""
        return tuple(bool(gizmo.visible) for gizmo in self._gizmos)

    def connect_device(self, drag: Callable[[np.ndarray, np.ndarray], None] | None) -> None:
        """Sets what a drag of the (first) driven bar calls: ``drag(position [m] (3,), rotation
        (3, 3))`` in the world frame, from viser's callback thread; None hides the gizmo."""
        self.connect_devices([drag] + [None] * (len(self._gizmos) - 1))

    def connect_devices(self, drags: Sequence[Callable[[np.ndarray, np.ndarray], None] | None]) -> None:
        """Sets what a drag of each device's bar calls (``drags[i]`` for ``geometry.device_bars[i]``,
        as :meth:`connect_device`); None hides that bar's gizmo."""
        if len(drags) != len(self._gizmos):
            raise ValueError(f"connect_devices: got {len(drags)} drag callbacks for {len(self._gizmos)} "
                             f"device-driven bars {[self.geometry.bar_names[b] for b in self.geometry.device_bars]}")
        self._drags = list(drags)
        for gizmo, drag in zip(self._gizmos, drags):
            gizmo.visible = drag is not None

    def _gizmo_callback(self, device: int):
        # A coroutine: viser awaits it in its message loop, in message order, right after it has
        # set the gizmo's pose from the message. A plain function would run later in viser's
        # thread pool, possibly out of order (an update before its start) and after the view
        # thread had put the gizmo back on the bar, so the drag read the bar's pose (seen once:
        # a dragged device that never moved).
        async def on_update(event) -> None:
            self._on_gizmo(device, event)

        return on_update

    def _on_gizmo(self, device: int, event) -> None:
        # Under the gizmo lock: once "start" has marked the gizmo dragged, no write of the view
        # thread (which holds the lock while it moves the gizmos) can overwrite the dragged pose.
        with self._gizmo_lock:
            if event.phase == "start":
                self._dragging.add(device)
            elif event.phase == "end":
                self._dragging.discard(device)
            target = event.target
            drag = self._drags[device]
            if drag is not None and event.phase in ("start", "update"):
                rotation = quat_to_matrix(from_wxyz(normalize_quat(target.wxyz)))
                drag(np.array(target.position, dtype=np.float64), rotation)

    def _run(self) -> None:
        while not self._stop.is_set():
            snapshot = self.buffer.wait(0.1)
            if snapshot is not None and not self._stop.is_set():
                self.update(snapshot)

    def update(self, snapshot: LiveSnapshot) -> None:
        """Sends one snapshot to the scene (the view's thread calls it for each new snapshot)."""
        g = self.geometry
        began = time.perf_counter()
        with self._server.atomic():
            if self._box_node is not None:
                self._box_node.batched_positions = snapshot.body_pos[self._boxes]
                self._box_node.batched_wxyzs = snapshot.body_wxyz[self._boxes]
            if self._sphere_node is not None:
                self._sphere_node.batched_positions = snapshot.body_pos[self._spheres]
                self._sphere_node.batched_wxyzs = snapshot.body_wxyz[self._spheres]
            self._string_node.points = snapshot.particle_q[self._segments]
            colors = string_colors(snapshot.string_taut)[self._segment_string]
            self._string_node.colors = np.repeat(colors[:, None, :], 2, axis=1)
            self._bar_node.points = np.array([
                [snapshot.bar_pos[b], snapshot.bar_pos[b] + snapshot.bar_rot[b] @ g.bar_attach[b][k]]
                for b, k in self._bar_segments])
            devices = list(g.device_bars)
            sent = snapshot.forces_sent()
            tails = np.concatenate([snapshot.bar_pos, snapshot.bar_pos[devices]])
            forces = np.concatenate([snapshot.bar_reaction, sent])
            self._arrow_node.points = np.stack([tails, tails + self.arrow_scale * forces], axis=1)
            with self._gizmo_lock:
                for i, (gizmo, b) in enumerate(zip(self._gizmos, devices)):
                    if i not in self._dragging:  # the mouse holds it: do not pull it back
                        gizmo.position = snapshot.bar_pos[b]
                        gizmo.wxyz = to_wxyz(matrix_to_quat(snapshot.bar_rot[b]))
            if snapshot.sequence % 10 == 1:
                taut = int(np.count_nonzero(snapshot.string_taut))
                self._status.content = (
                    f"t = {snapshot.t:.2f} s · {taut}/{len(g.string_names)} strings taut · "
                    "|force sent| " + ", ".join(f"{np.linalg.norm(f):.2f}" for f in sent) + " N" +
                    (" · **bar dragged**" if snapshot.dragged else ""))
        self.last_sent = snapshot
        self.frames_sent += 1
        self.update_seconds += time.perf_counter() - began

    def close(self) -> None:
        """Stops the update thread and the server (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._stop_server()

    def _stop_server(self) -> None:
        if self._server is None:
            return
        # viser prints "Server stopped" on stdout, which carries the CLI's JSON summary.
        with contextlib.redirect_stdout(sys.stderr):
            self._server.stop()
        self._server = None
