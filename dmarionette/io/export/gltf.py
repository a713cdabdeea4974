"""The puppet motion as a binary glTF 2.0 file (``.glb``), for Blender and any glTF viewer.

Contents (documented for users in ``docs/export.md``):

- **Scene**: one root node ``marionette`` (identity transform) whose children are one node
  per simulated body, named after it (the puppet's 12 bodies, and ``ball`` in the ball
  scene), each with a mesh of its simulated shape: a box of the body's full extents, or a
  UV sphere (16 x 32) of its radius, centred on the node (the body frame's origin is the
  centre of mass, its axes the shape's axes). Bodies hold world transforms (the hierarchy
  is flat): each pose is the simulated pose itself, with no chain of parent transforms to
  accumulate float32 rounding. Control bars follow as empty nodes ``bar_NAME`` (their
  frame: centre and axes), animated the same way.
- **Animation** ``marionette``: per node a ``translation`` and a ``rotation`` channel, LINEAR
  samplers (glTF: linear for translation, spherical linear for rotation) keyed at the
  trajectory's frame times [s]; quaternion signs are continuous so that each interpolation
  takes the short way round. Node rest transforms are frame 0.
- **Units and axes**: metres, seconds; y up, the puppet faces +z: glTF's own conventions,
  so no conversion is needed (Blender's importer turns y up into its z up itself).
- **Strings** (when the trajectory has ``particle_q`` and ``string_start``): one mesh of
  line segments (glTF ``LINES``), a vertex per string particle, skinned to one joint node
  per particle (``string_NAME_K``, under a node ``strings``) whose ``translation`` is
  animated. Each vertex follows its joint with weight 1 and an inverse bind matrix that
  undoes the joint's frame-0 position, so at every keyframe the vertices are the simulated
  particles (rounded once to float32), and between keyframes they move linearly. The
  ``strings`` node and the mesh node ``string_lines`` are scene roots beside ``marionette``
  (glTF ignores a skinned mesh node's own transform). (A node animates a mesh
  rigidly, and morph targets would need a weight track of frame-count length per frame:
  quadratic in the length of the motion; a skin is linear.) Lines have no thickness:
  Blender shows them as edges in the viewport (give them a *Skin* modifier or convert to a
  curve with a bevel to render them).
- **Not exported**: the ground, the chair, forces.

The container is written here with NumPy and ``json`` (about 100 lines) rather than with
a glTF library: the format is small (a 12-byte header, a JSON chunk and a binary chunk,
each padded to 4 bytes), the writer then needs no extra dependency, and the tests read the
files back with two independent readers (``pygltflib`` and ``trimesh``).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.io.export.common import BodyMotion, ExportError, body_motion
from dmarionette.io.export.common import bar_tracks as _bars
from dmarionette.io.export.common import string_tracks as _strings
from dmarionette.rotations import continuous_quats

__all__ = ["box_mesh", "export_gltf", "sphere_mesh"]

_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_LINES, _TRIANGLES = 1, 4
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
_SPHERE_RINGS, _SPHERE_SEGMENTS = 16, 32
_MATERIALS = [  # name, base colour (linear RGBA)
    ("puppet", [0.62, 0.42, 0.25, 1.0]),
    ("head", [0.85, 0.70, 0.55, 1.0]),
    ("ball", [0.80, 0.10, 0.10, 1.0]),
    ("string", [0.05, 0.05, 0.05, 1.0]),
]


def box_mesh(size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box of full extents ``size`` [m] centred on the origin, flat-shaded.

    Returns:
        positions ``(24, 3)``, unit normals ``(24, 3)`` (4 vertices per face), and
        triangle indices ``(36,)``, counter-clockwise seen from outside (glTF front faces).
    """
    half = 0.5 * np.asarray(size, dtype=np.float64)
    positions, normals, indices = [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v = np.cross(n, u)  # u x v = n: (-u-v, u-v, u+v, -u+v) runs counter-clockwise about n
            base = len(positions)
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                positions.append((n + du * u + dv * v) * half)
                normals.append(n)
            indices += [base, base + 1, base + 2, base, base + 2, base + 3]
    return np.array(positions), np.array(normals), np.array(indices)


def sphere_mesh(radius: float, rings: int = _SPHERE_RINGS,
                segments: int = _SPHERE_SEGMENTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV sphere of ``radius`` [m] centred on the origin, smooth-shaded.

    Returns:
        positions ``((rings + 1) (segments + 1), 3)``, unit normals, triangle indices
        counter-clockwise seen from outside (no degenerate triangles at the poles).
    """
    theta = np.linspace(0.0, np.pi, rings + 1)        # from the +y pole down
    phi = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    normals = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], axis=-1).reshape(-1, 3)
    indices = []
    for i in range(rings):
        for j in range(segments):
            a, b = i * (segments + 1) + j, (i + 1) * (segments + 1) + j
            if i > 0:
                indices += [a, b, a + 1]
            if i < rings - 1:
                indices += [a + 1, b, b + 1]
    return radius * normals, normals, np.array(indices)


class _GlbBuilder:
    """Buffer views and accessors over one binary buffer, every view aligned to 4 bytes."""

    def __init__(self):
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def accessor(self, data: np.ndarray, *, target: int | None = None, minmax: bool = True) -> int:
        data = np.ascontiguousarray(data)
        component = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _USHORT,
                     np.dtype(np.uint32): _UINT}[data.dtype]
        data = data.reshape(len(data), -1) if data.ndim > 2 else data
        width = 1 if data.ndim == 1 else data.shape[1]
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": data.nbytes}
        if target is not None:
            view["target"] = target
        self.blob += data.tobytes()
        self.blob += b"\x00" * (-len(self.blob) % 4)
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(len(data)),
               "type": _TYPES[width]}
        if minmax:
            flat = data.reshape(len(data), width)
            cast = float if component == _FLOAT else int
            acc["min"] = [cast(v) for v in flat.min(axis=0)]
            acc["max"] = [cast(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def glb(self, document: dict) -> bytes:
        document["buffers"] = [{"byteLength": len(self.blob)}]
        document["bufferViews"] = self.views
        document["accessors"] = self.accessors
        text = json.dumps(document, separators=(",", ":")).encode("utf-8")
        text += b" " * (-len(text) % 4)
        total = 12 + 8 + len(text) + 8 + len(self.blob)
        return b"".join([struct.pack("<III", _GLB_MAGIC, 2, total), struct.pack("<II", len(text), _JSON_CHUNK),
                         text, struct.pack("<II", len(self.blob), _BIN_CHUNK), bytes(self.blob)])


def _mesh(builder: _GlbBuilder, shape: str, size: tuple, material: int, name: str) -> dict:
    positions, normals, indices = box_mesh(size) if shape == "box" else sphere_mesh(size[0])
    index_type = np.uint16 if len(positions) < 65535 else np.uint32
    primitive = {
        "attributes": {
            "POSITION": builder.accessor(positions.astype(np.float32), target=_ARRAY_BUFFER),
            "NORMAL": builder.accessor(normals.astype(np.float32), target=_ARRAY_BUFFER),
        },
        "indices": builder.accessor(indices.astype(index_type), target=_ELEMENT_ARRAY_BUFFER),
        "material": material,
        "mode": _TRIANGLES,
    }
    return {"name": name, "primitives": [primitive]}


def _float32_times(motion: BodyMotion, where: str) -> np.ndarray:
    times = motion.frame_time.astype(np.float32)
    if len(times) > 1 and not np.all(np.diff(times) > 0.0):
        f = int(np.argmin(np.diff(times)))
        raise ExportError(f"{where}: field 'frame_time': frames {f} and {f + 1} ({motion.frame_time[f]!r}, "
                          f"{motion.frame_time[f + 1]!r} s) are equal in float32; expected times that stay strictly "
                          "increasing in float32 (glTF keyframe times)")
    return times


def _add_strings(builder: _GlbBuilder, document: dict, strings: list[tuple[str, np.ndarray]]) -> list:
    """The skinned line mesh of the strings; returns ``(node, positions (F, 3))`` tracks of its joints."""
    nodes, meshes = document["nodes"], document["meshes"]
    group = len(nodes)
    nodes.append({"name": "strings", "children": []})
    document["scenes"][0]["nodes"].append(group)
    joints, tracks, indices, rest = [], [], [], []
    for name, q in strings:
        first = len(rest)
        for k in range(q.shape[1]):
            nodes.append({"name": f"string_{name}_{k}"})
            nodes[group]["children"].append(len(nodes) - 1)
            joints.append(len(nodes) - 1)
            tracks.append((len(nodes) - 1, q[:, k], None))
            rest.append(q[0, k])
        indices += [i for k in range(first, len(rest) - 1) for i in (k, k + 1)]
    rest32 = np.asarray(rest).astype(np.float32)
    count = len(rest32)
    bind = np.tile(np.eye(4, dtype=np.float32), (count, 1, 1))
    bind[:, 3, :3] = -rest32   # glTF reads the 16 floats column-major: elements 12-14 are the translation
    joint_ids = np.zeros((count, 4), dtype=np.uint16)
    joint_ids[:, 0] = np.arange(count)
    weights = np.zeros((count, 4), dtype=np.float32)
    weights[:, 0] = 1.0
    primitive = {
        "attributes": {
            "POSITION": builder.accessor(rest32, target=_ARRAY_BUFFER),
            "JOINTS_0": builder.accessor(joint_ids, target=_ARRAY_BUFFER),
            "WEIGHTS_0": builder.accessor(weights, target=_ARRAY_BUFFER),
        },
        "indices": builder.accessor(np.asarray(indices, dtype=np.uint16 if count < 65535 else np.uint32),
                                    target=_ELEMENT_ARRAY_BUFFER),
        "material": len(_MATERIALS) - 1,
        "mode": _LINES,
    }
    meshes.append({"name": "strings", "primitives": [primitive]})
    document.setdefault("skins", []).append({"name": "strings", "joints": joints, "skeleton": group,
                                             "inverseBindMatrices": builder.accessor(bind)})
    nodes.append({"name": "string_lines", "mesh": len(meshes) - 1, "skin": len(document["skins"]) - 1})
    document["scenes"][0]["nodes"].append(len(nodes) - 1)
    return tracks


def export_gltf(trajectory: Any, path: str | Path, *, strings: bool = True) -> Path:
    """Writes the puppet motion of ``trajectory`` as a binary glTF 2.0 file (contents: module docstring).

    Args:
        trajectory: a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (or the
            result of :func:`~dmarionette.io.export.common.read_marionette_trajectory`, or any
            object with ``frame_time``, ``body_pos``, ``body_rot``, ``body_names`` and
            ``body_shape``; ``bar_names``, ``bar_pos`` and ``bar_rot``, and ``particle_q``,
            ``string_start`` and ``string_names`` are optional).
        path: the ``.glb`` file to write; parent folders are created.
        strings: write the strings (a skinned line mesh) when the trajectory has them.

    Returns:
        ``path``.

    Raises:
        ExportError: a trajectory without body motion, malformed or non-finite fields
            (string fields included), frame times that collide in float32.
    """
    path = Path(path)
    where = str(getattr(trajectory, "source", None) or "trajectory")
    motion = body_motion(trajectory, where)
    times = _float32_times(motion, where)
    builder = _GlbBuilder()
    meshes, mesh_of = [], {}
    nodes = [{"name": "marionette", "children": []}]
    tracks = []
    for b, (name, (shape, size)) in enumerate(zip(motion.body_names, motion.body_shape)):
        material = 2 if name == "ball" else (1 if shape == "sphere" else 0)
        key = (shape, size, material)
        if key not in mesh_of:
            mesh_of[key] = len(meshes)
            meshes.append(_mesh(builder, shape, size, material, f"{shape}_{len(meshes)}"))
        nodes.append({"name": name, "mesh": mesh_of[key]})
        tracks.append((len(nodes) - 1, motion.body_pos[:, b], motion.body_rot[:, b]))
    for name, pos, rot in _bars(trajectory, motion.frame_count):
        nodes.append({"name": f"bar_{name}"})
        tracks.append((len(nodes) - 1, pos, rot))

    nodes[0]["children"] = [node for node, _, _ in tracks]
    document = {
        "asset": {"version": "2.0", "generator": "dmarionette export_gltf"},
        "scene": 0,
        "scenes": [{"name": "marionette", "nodes": [0]}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [{"name": n, "pbrMetallicRoughness": {"baseColorFactor": c, "metallicFactor": 0.0,
                                                            "roughnessFactor": 0.8}} for n, c in _MATERIALS],
    }
    chains = _strings(trajectory, motion.frame_count, where) if strings else None
    if chains:
        tracks += _add_strings(builder, document, chains)

    time_accessor = builder.accessor(times)
    samplers, channels = [], []
    for node, pos, rot in tracks:
        pos32 = pos.astype(np.float32)
        animated = [("translation", pos32)]
        nodes[node]["translation"] = [float(v) for v in pos32[0]]
        if rot is not None:
            rot = continuous_quats(rot)
            rot32 = (rot / np.linalg.norm(rot, axis=-1, keepdims=True)).astype(np.float32)
            nodes[node]["rotation"] = [float(v) for v in rot32[0]]
            animated.append(("rotation", rot32))
        for target, values in animated:
            samplers.append({"input": time_accessor, "output": builder.accessor(values), "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": target}})
    document["animations"] = [{"name": "marionette", "samplers": samplers, "channels": channels}]
    data = builder.glb(document)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path
