"""The puppet in Foxglove's well-known schemas, so Foxglove's 3D panel and Rerun draw a session.

Three channels, protobuf-encoded (``foxglove-schemas-protobuf``; Rerun's MCAP importer decodes
Foxglove schemas in protobuf, not in JSON), one message each per puppet state. The methods
take ``(log_time [ns], t [s], bar_poses, body_pos, body_rot)``: ``t``, the simulated time, is
not in Foxglove's schemas (the JSON channels hold it); the messages are stamped with the log
time.

- ``/foxglove/transforms`` (``foxglove.FrameTransforms``): ``map`` -> ``world`` (a quarter turn
  about x: the simulator's y-up world shown z-up), ``world`` -> ``body/NAME`` for every body and
  ``world`` -> ``bar/NAME`` for every bar.
- ``/foxglove/scene`` (``foxglove.SceneUpdate``): one entity per body (its box or sphere, locked
  to its frame), one per bar (a thin box along its attach points), ``strings`` (a straight line
  per string from its bar attach point to its body point, red when taut) and ``forces`` (an arrow
  per bar: the exact reaction of its strings, 1 cm per newton).
- ``/foxglove/points`` (``foxglove.PointCloud``, frame ``world``): the body centres, then each
  string's two ends (bar attach point, body point), x y z float32: what Rerun draws (its
  importer turns ``PointCloud`` into ``Points3D``; it converts no ``SceneUpdate``).

Everything is computed from what the session's own channels hold (bar poses, puppet states,
feedback, taut flags), so an old session gets these channels too (``index_session``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2
from google.protobuf.duration_pb2 import Duration

from dmarionette.rotations import euler_to_matrix

__all__ = ["FOXGLOVE_TOPICS", "FoxglovePuppet", "file_descriptor_set"]

#: topic -> schema name of the Foxglove channels.
FOXGLOVE_TOPICS = {"/foxglove/transforms": "foxglove.FrameTransforms", "/foxglove/scene": "foxglove.SceneUpdate",
                   "/foxglove/points": "foxglove.PointCloud"}
_MESSAGES = {"foxglove.FrameTransforms": FrameTransforms, "foxglove.SceneUpdate": SceneUpdate,
             "foxglove.PointCloud": PointCloud}
_Y_UP_TO_Z_UP = (np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))  # (x, y, z, w): +90 deg about x
_FORCE_SCALE = 0.01  # arrow length [m] per newton
_BAR_COLOR = (0.55, 0.35, 0.2, 1.0)
_BODY_COLOR = (0.85, 0.75, 0.6, 1.0)


def file_descriptor_set(schema_name: str) -> bytes:
    """The serialized ``FileDescriptorSet`` of ``schema_name`` and every file it imports (the
    schema data MCAP's ``protobuf`` schema encoding asks for)."""
    message = _MESSAGES[schema_name]
    files, seen = descriptor_pb2.FileDescriptorSet(), set()

    def add(file_descriptor) -> None:
        if file_descriptor.name in seen:
            return
        seen.add(file_descriptor.name)
        for dependency in file_descriptor.dependencies:
            add(dependency)
        file_descriptor.CopyToProto(files.file.add())

    add(message.DESCRIPTOR.file)
    return files.SerializeToString()


def _stamp(target, t_ns: int) -> None:
    target.seconds, target.nanos = divmod(int(t_ns), 1_000_000_000)


def _set_pose(pose, position, quat_xyzw) -> None:
    pose.position.x, pose.position.y, pose.position.z = map(float, position)
    q = pose.orientation
    q.x, q.y, q.z, q.w = map(float, quat_xyzw)


def _set_color(color, rgba) -> None:
    color.r, color.g, color.b, color.a = rgba


class FoxglovePuppet:
    """Builds the Foxglove messages of one session from its metadata and scene.

    Args:
        metadata: the session's ``"dmarionette"`` record (decoded): ``bodies``, ``bars``,
            ``bar_attach``, ``strings``, ``string_bars``.
        scene: the session's scene (body shapes, string body points, ball), or ``None``
            (then bodies are drawn as 5 cm spheres and strings are not drawn).
    """

    def __init__(self, metadata: Mapping, scene=None):
        self.bodies = list(metadata["bodies"])
        self.bars = list(metadata["bars"])
        self.strings = list(metadata["strings"])
        self.bar_attach = {b: {s: np.asarray(p, float) for s, p in v.items()}
                           for b, v in (metadata.get("bar_attach") or {}).items()}
        self.string_bars = list(metadata.get("string_bars") or [None] * len(self.strings))
        self.shapes: dict[str, tuple[str, tuple[float, float, float]]] = {}
        self._shape_cache: dict[tuple[str, ...], SceneUpdate] = {}
        self.string_points: list[tuple[int, np.ndarray] | None] = [None] * len(self.strings)
        puppet = getattr(scene, "puppet", None)
        if puppet is not None:
            for body in puppet.bodies:
                self.shapes[body.name] = (body.shape, tuple(map(float, body.size)))
            points = {p.name: p for p in puppet.points}
            index = {name: i for i, name in enumerate(self.bodies)}
            for i, point in enumerate(getattr(scene, "string_body_points", ()) or ()):
                if i < len(self.strings) and point in points and points[point].body in index:
                    self.string_points[i] = (index[points[point].body], np.asarray(points[point].position, float))
        ball = getattr(scene, "ball", None)
        if ball is not None and "ball" in self.bodies:
            radius = getattr(ball, "radius", None) or (ball.get("radius") if isinstance(ball, Mapping) else None)
            self.shapes["ball"] = ("sphere", (float(radius or 0.05), 0.0, 0.0))

    # ----------------------------------------------------------------------------------------

    def transforms(self, log_time: int, t: float, bar_poses: Mapping[str, tuple], body_pos, body_rot) -> bytes:
        """``foxglove.FrameTransforms`` at ``log_time`` [ns]: ``map`` -> ``world``, world -> each
        body and each bar of ``bar_poses`` (name -> (position [m], XYZ Euler [deg]))."""
        message = FrameTransforms()
        frames = [("map", "world", (0.0, 0.0, 0.0), _Y_UP_TO_Z_UP)]
        frames += [("world", f"body/{name}", p, q) for name, p, q in zip(self.bodies, body_pos, body_rot)]
        for name, (position, angles) in bar_poses.items():
            frames.append(("world", f"bar/{name}", position, _euler_quat(angles)))
        for parent, child, position, quat in frames:
            transform = message.transforms.add()
            _stamp(transform.timestamp, log_time)
            transform.parent_frame_id, transform.child_frame_id = parent, child
            transform.translation.x, transform.translation.y, transform.translation.z = map(float, position)
            r = transform.rotation
            r.x, r.y, r.z, r.w = map(float, quat)
        return message.SerializeToString()

    def scene_update(self, log_time: int, t: float, bar_poses: Mapping[str, tuple], body_pos, body_rot,
                     reactions: Mapping[str, Sequence[float]] | None = None,
                     taut: Sequence[int] | None = None) -> bytes:
        """``foxglove.SceneUpdate`` at ``log_time`` [ns]: body and bar shapes (frame-locked),
        strings and force arrows (world frame); ``reactions``: bar -> force [N], world."""
        message = SceneUpdate()
        message.CopyFrom(self._shapes(tuple(bar_poses)))  # the shapes (frame-locked), built once
        for entity in message.entities:
            _stamp(entity.timestamp, log_time)
        strings = self._entity(message, log_time, "world", "strings", frame_locked=False)
        for i, top, bottom in self.string_ends(bar_poses, body_pos, body_rot):
            line = strings.lines.add()
            line.type = line.LINE_STRIP
            line.thickness = 0.004
            _set_pose(line.pose, (0, 0, 0), (0, 0, 0, 1))
            for p in (top, bottom):
                point = line.points.add()
                point.x, point.y, point.z = map(float, p)
            tight = taut is not None and i < len(taut) and taut[i]
            _set_color(line.color, (0.9, 0.1, 0.1, 1.0) if tight else (0.9, 0.9, 0.9, 1.0))
        forces = self._entity(message, log_time, "world", "forces", frame_locked=False)
        for name, force in (reactions or {}).items():
            force = np.asarray(force, float)
            length = float(np.linalg.norm(force)) * _FORCE_SCALE
            if name not in bar_poses or not np.isfinite(length) or length < 1e-6:
                continue
            arrow = forces.arrows.add()
            _set_pose(arrow.pose, bar_poses[name][0], _quat_x_to(force))
            arrow.shaft_length, arrow.shaft_diameter = 0.8 * length, 0.01
            arrow.head_length, arrow.head_diameter = 0.2 * length, 0.025
            _set_color(arrow.color, (0.1, 0.4, 1.0, 1.0))
        return message.SerializeToString()

    def string_ends(self, bar_poses: Mapping[str, tuple], body_pos, body_rot) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``(string index, top, bottom)`` [m], world, of each string whose bar pose and body point are known."""
        bar_rotation = {name: euler_to_matrix(np.asarray(angles, float)) for name, (_, angles) in bar_poses.items()}
        ends = []
        for i, (name, bar) in enumerate(zip(self.strings, self.string_bars)):
            end = self.string_points[i]
            if bar not in bar_poses or end is None or name not in self.bar_attach.get(bar, {}):
                continue
            top = np.asarray(bar_poses[bar][0], float) + bar_rotation[bar] @ self.bar_attach[bar][name]
            body, local = end
            ends.append((i, top, np.asarray(body_pos[body], float) + _rotate(body_rot[body], local)))
        return ends

    def points(self, log_time: int, t: float, bar_poses: Mapping[str, tuple], body_pos, body_rot) -> bytes:
        """``foxglove.PointCloud`` at ``log_time`` [ns], frame ``world``: body centres, then the two
        ends of each string (float32 x, y, z)."""
        message = PointCloud()
        _stamp(message.timestamp, log_time)
        message.frame_id = "world"
        _set_pose(message.pose, (0, 0, 0), (0, 0, 0, 1))
        message.point_stride = 12
        for k, axis in enumerate("xyz"):
            message.fields.add(name=axis, offset=4 * k, type=PackedElementField.FLOAT32)
        ends = [p for _, top, bottom in self.string_ends(bar_poses, body_pos, body_rot) for p in (top, bottom)]
        points = np.concatenate([np.asarray(body_pos, np.float64).reshape(-1, 3), np.reshape(ends, (-1, 3))])
        message.data = points.astype("<f4").tobytes()
        return message.SerializeToString()

    def _shapes(self, bars: tuple[str, ...]) -> SceneUpdate:
        """The body and bar entities (shapes locked to their frames), cached per set of bars."""
        cached = self._shape_cache.get(bars)
        if cached is not None:
            return cached
        message = SceneUpdate()
        for name in self.bodies:
            entity = self._entity(message, 0, f"body/{name}", f"body/{name}", frame_locked=True)
            shape, size = self.shapes.get(name, ("sphere", (0.025, 0.0, 0.0)))
            primitive = entity.spheres.add() if shape == "sphere" else entity.cubes.add()
            _set_pose(primitive.pose, (0, 0, 0), (0, 0, 0, 1))
            extent = (2 * size[0],) * 3 if shape == "sphere" else size
            primitive.size.x, primitive.size.y, primitive.size.z = map(float, extent)
            _set_color(primitive.color, _BODY_COLOR)
        for name in bars:
            points = list(self.bar_attach.get(name, {}).values())
            entity = self._entity(message, 0, f"bar/{name}", f"bar/{name}", frame_locked=True)
            cube = entity.cubes.add()
            lo, hi = (np.min(points, 0), np.max(points, 0)) if points else (np.zeros(3), np.zeros(3))
            _set_pose(cube.pose, (lo + hi) / 2, (0, 0, 0, 1))
            cube.size.x, cube.size.y, cube.size.z = map(float, np.maximum(hi - lo, 0.02))
            _set_color(cube.color, _BAR_COLOR)
        self._shape_cache[bars] = message
        return message

    @staticmethod
    def _entity(message, log_time: int, frame_id: str, entity_id: str, *, frame_locked: bool):
        entity = message.entities.add()
        _stamp(entity.timestamp, log_time)
        entity.frame_id, entity.id, entity.frame_locked = frame_id, entity_id, frame_locked
        entity.lifetime.CopyFrom(Duration())  # zero: until replaced by the next update
        return entity


def _rotate(quat_xyzw, v: np.ndarray) -> np.ndarray:
    """``v`` rotated by the unit quaternion (x, y, z, w): v + 2 u x (u x v + w v), in plain floats
    (``np.cross`` costs 50 us a call)."""
    x, y, z, w = (float(c) for c in quat_xyzw)
    a, b, c = (float(e) for e in v)
    tx, ty, tz = y * c - z * b + w * a, z * a - x * c + w * b, x * b - y * a + w * c
    return np.array([a + 2.0 * (y * tz - z * ty), b + 2.0 * (z * tx - x * tz), c + 2.0 * (x * ty - y * tx)])


def _euler_quat(angles_deg) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of ``R = Rz Ry Rx`` (XYZ angles [deg], as
    :func:`dmarionette.rotations.euler_to_matrix`), in plain floats, w >= 0."""
    hx, hy, hz = (math.radians(float(a)) / 2.0 for a in angles_deg)
    cx, sx, cy, sy, cz, sz = math.cos(hx), math.sin(hx), math.cos(hy), math.sin(hy), math.cos(hz), math.sin(hz)
    q = (sx * cy * cz - cx * sy * sz, cx * sy * cz + sx * cy * sz, cx * cy * sz - sx * sy * cz,
         cx * cy * cz + sx * sy * sz)
    return tuple(-c for c in q) if q[3] < 0.0 else q


def _quat_x_to(direction: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) turning +x onto ``direction`` (Foxglove arrows point along +x)."""
    d = direction / np.linalg.norm(direction)
    w = 1.0 + d[0]
    if w < 1e-9:  # opposite to +x: half a turn about z
        return np.array([0.0, 0.0, 1.0, 0.0])
    q = np.array([0.0, -d[2], d[1], w])  # (x, y, z) = x_axis cross d
    return q / np.linalg.norm(q)
