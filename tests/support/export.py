"""Helpers of the export tests: a synthetic motion with known rotations, and readers.

The synthetic motion is built by forward kinematics with quaternions, independently of the
exporters' matrix code. BVH is read with ``bvh`` (raw channel values; forward kinematics
here, from the BVH definition) and ``bvhio`` (its own forward kinematics); glTF with
``pygltflib`` (structure checked here against the glTF 2.0 rules the Khronos validator
applies to such files) and ``trimesh``. Tolerances: see ``tests/io/test_export.py``.
"""

import json
import struct
import types

import bvh as bvh_reader
import bvhio
import numpy as np
import pygltflib
import trimesh

from dmarionette.scene.puppet import load_puppet

BVH_POS_TOL = 1e-6   # [m]
BVH_ROT_TOL = 2e-7   # [rad]
BVH_ANGLE_TOL = 1e-6  # [deg], one channel: 5e-7 rounding

# ----------------------------------------------------------------------------- motions

def _qmul(a, b):
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def _qaxis(axis, angle):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    angle = np.asarray(angle, dtype=np.float64)[..., None]
    return np.concatenate([np.sin(0.5 * angle) * axis, np.cos(0.5 * angle)], axis=-1)


def _qrotate(q, v):
    """Rotates vectors ``v (..., 3)`` by quaternions ``q (..., 4)``: v + 2 w (u x v) + 2 u x (u x v)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_matrix(q):
    return np.stack([_qrotate(q, e) for e in np.eye(3)], axis=-1)


SYNTH_FRAMES = 61
SYNTH_DT = 1.0 / 30.0


def synthetic_motion():
    """The default puppet moved by known large rotations, and a free ball (13 bodies)."""
    puppet = load_puppet()
    names = [b.name for b in puppet.bodies]
    parents = puppet.parent_index()
    f = np.arange(SYNTH_FRAMES)
    s = f / (SYNTH_FRAMES - 1)
    rng = np.random.default_rng(7)
    local = {}
    for j in puppet.joints:
        local[j.child] = _qaxis(rng.normal(size=3), np.radians(rng.uniform(-350.0, 350.0)) * s)
    known = {
        "knee_left": np.radians(340.0) * s,             # a hinge turning past 180 deg: X channel
        "shoulder_left": (np.radians(-150.0) * s, np.radians(120.0) * s),  # X, Z; Z = 90 deg at frame 45
    }
    local["lower_leg_left"] = _qaxis([1, 0, 0], known["knee_left"])
    local["upper_arm_left"] = _qmul(_qaxis([1, 0, 0], known["shoulder_left"][0]),
                                    _qaxis([0, 0, 1], known["shoulder_left"][1]))
    local["head"] = _qaxis([0.3, -1.0, 0.5], np.radians(360.0) * s)   # exactly 180 deg at frame 30
    pos = np.zeros((SYNTH_FRAMES, len(names) + 1, 3))
    rot = np.zeros((SYNTH_FRAMES, len(names) + 1, 4))
    pos[:, 0] = np.stack([0.3 * np.sin(2 * s), 0.45 + 0.1 * s, -0.2 * s], axis=1)
    rot[:, 0] = _qaxis([1.0, 2.0, 3.0], np.radians(359.0) * s)
    for b, j in enumerate(puppet.joints, start=1):
        p = parents[b]
        rot[:, b] = _qmul(rot[:, p], local[j.child])
        pos[:, b] = (pos[:, p] + _qrotate(rot[:, p], np.asarray(j.anchor_parent))
                     - _qrotate(rot[:, b], np.asarray(j.anchor_child)))
    pos[:, -1] = np.stack([0.2 * s, 0.05 + 0.0 * s, 0.2 + 0.0 * s], axis=1)
    rot[:, -1] = _qaxis([0.0, 0.0, 1.0], -np.radians(720.0) * s)
    rot[1::2, ::2] *= -1.0   # q and -q are the same rotation: every other frame flips sign (as input may)
    shapes = [(b.shape, b.size) for b in puppet.bodies] + [("sphere", (0.05, 0.0, 0.0))]
    traj = types.SimpleNamespace(frame_time=f * SYNTH_DT, body_pos=pos, body_rot=rot, body_names=names + ["ball"],
                                 body_shape=shapes, bar_names=["main"], bar_pos=pos[:, :1] + [0.0, 0.3, 0.0],
                                 bar_rot=quat_matrix(rot[:, :1]))
    return traj, known


# ----------------------------------------------------------------------------- BVH reading

def _elementary(channel, degrees):
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[channel[0]]


def bvh_forward_kinematics(path):
    """Per frame and joint: world origin and rotation, from the ``bvh`` package's raw values.

    BVH: a joint's transform in its parent's is translate(OFFSET) then the rotation
    channels multiplied in the listed order; position channels of the root replace its offset.
    """
    mocap = bvh_reader.Bvh(path.read_text())
    names = mocap.get_joints_names()
    out = {n: (np.zeros((mocap.nframes, 3)), np.zeros((mocap.nframes, 3, 3))) for n in names}
    for f in range(mocap.nframes):
        for n in names:
            channels = mocap.joint_channels(n)
            values = [float(v) for v in mocap.frame_joint_channels(f, n, channels)]
            offset = np.array(mocap.joint_offset(n), dtype=np.float64)
            local_r, local_p = np.eye(3), offset.copy()
            for c, v in zip(channels, values):
                if c.endswith("rotation"):
                    local_r = local_r @ _elementary(c, v)
                else:
                    local_p["XYZ".index(c[0])] = v
            parent = mocap.joint_parent(n)
            if parent is None:
                out[n][0][f], out[n][1][f] = local_p, local_r
            else:
                pp, pr = out[parent.name][0][f], out[parent.name][1][f]
                out[n][0][f], out[n][1][f] = pp + pr @ offset, pr @ local_r
    return mocap, out


def check_bvh_poses(path, trajectory, puppet):
    """FK of the file reproduces every body's centre and rotation at every frame; returns the errors."""
    mocap, fk = bvh_forward_kinematics(path)
    assert mocap.nframes == len(trajectory.frame_time)
    rot = quat_matrix(np.asarray(trajectory.body_rot))
    anchor = [np.zeros(3)] + [np.asarray(j.anchor_child) for j in puppet.joints]
    pos_err = rot_err = 0.0
    for b, body in enumerate(puppet.bodies):
        origin, r = fk[body.name]
        centre = origin - r @ anchor[b]           # body centre = joint origin - R a_c
        pos_err = max(pos_err, np.abs(centre - trajectory.body_pos[:, b]).max())
        rot_err = max(rot_err, np.abs(r - rot[:, b]).max())
    assert pos_err <= BVH_POS_TOL
    assert rot_err <= BVH_ROT_TOL
    # bvhio's own forward kinematics (float32): the joint origins.
    root = bvhio.readAsHierarchy(str(path))
    worst = 0.0
    for f in range(mocap.nframes):
        root.loadPose(f)
        for joint, _, _ in root.layout():
            b = [x.name for x in puppet.bodies].index(joint.Name)
            expected = trajectory.body_pos[f, b] + rot[f, b] @ anchor[b]
            worst = max(worst, np.abs(np.array(joint.PositionWorld) - expected).max())
    assert worst <= 1e-5
    return pos_err, rot_err, worst


def read_bvh_channels(path):
    mocap = bvh_reader.Bvh(path.read_text())
    return mocap, {n: np.array([[float(v) for v in mocap.frame_joint_channels(f, n, mocap.joint_channels(n))]
                                for f in range(mocap.nframes)]) for n in mocap.get_joints_names()}



# ----------------------------------------------------------------------------- glTF reading

_COMPONENT = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _accessor(gltf, blob, index):
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    dtype = _COMPONENT[acc.componentType]
    width = _WIDTH[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(blob, dtype=dtype, count=acc.count * width, offset=start)
    return data.reshape(acc.count, width) if width > 1 else data


def _validate_glb(path):
    """The glTF 2.0 rules (specification sections 4.4 and 5) that the Khronos validator checks here.

    Returns the parsed document and the binary chunk.
    """
    raw = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", raw, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(raw))
    json_length, json_type = struct.unpack_from("<II", raw, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    bin_start = 20 + json_length
    bin_length, bin_type = struct.unpack_from("<II", raw, bin_start)
    assert bin_type == 0x004E4942 and bin_length % 4 == 0 and bin_start + 8 + bin_length == len(raw)
    document = json.loads(raw[20:bin_start])
    assert document["asset"]["version"] == "2.0"
    gltf = pygltflib.GLTF2().load_binary(str(path))
    blob = gltf.binary_blob()
    assert len(blob) == bin_length
    (buffer,) = gltf.buffers
    assert buffer.uri is None and bin_length - 3 <= buffer.byteLength <= bin_length
    for view in gltf.bufferViews:
        assert view.buffer == 0 and (view.byteOffset or 0) % 4 == 0
        assert (view.byteOffset or 0) + view.byteLength <= buffer.byteLength
    for i, acc in enumerate(gltf.accessors):
        view = gltf.bufferViews[acc.bufferView]
        size = np.dtype(_COMPONENT[acc.componentType]).itemsize
        assert ((view.byteOffset or 0) + (acc.byteOffset or 0)) % size == 0
        assert (acc.byteOffset or 0) + acc.count * size * _WIDTH[acc.type] <= view.byteLength
        data = _accessor(gltf, blob, i).reshape(acc.count, -1)
        assert acc.min is not None and acc.max is not None, f"accessor {i} lacks min/max"
        assert np.array_equal(np.asarray(acc.min, dtype=data.dtype), data.min(axis=0))
        assert np.array_equal(np.asarray(acc.max, dtype=data.dtype), data.max(axis=0))
    children = [c for node in gltf.nodes for c in (node.children or [])]
    roots = gltf.scenes[gltf.scene].nodes
    assert len(children) == len(set(children)) and not set(roots) & set(children)   # a forest
    assert sorted(children + roots) == list(range(len(gltf.nodes)))                  # every node in the scene
    for mesh in gltf.meshes:
        for prim in mesh.primitives:
            positions = _accessor(gltf, blob, prim.attributes.POSITION)
            indices = _accessor(gltf, blob, prim.indices).astype(np.int64)
            assert indices.max() < len(positions)
            assert gltf.materials[prim.material].pbrMetallicRoughness is not None
            if prim.mode == 1:                                  # LINES (the strings)
                assert len(indices) % 2 == 0
                continue
            normals = _accessor(gltf, blob, prim.attributes.NORMAL)
            assert prim.mode == 4 and len(indices) % 3 == 0
            assert len(normals) == len(positions)
            np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
            tri = positions[indices.reshape(-1, 3)].astype(np.float64)
            facing = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            assert np.all(np.einsum("ij,ij->i", facing, tri.mean(axis=1)) > 0.0)   # CCW from outside
    for skin in gltf.skins or []:
        assert len(set(skin.joints)) == len(skin.joints)
        assert gltf.accessors[skin.inverseBindMatrices].count == len(skin.joints)
        users = [n for n in gltf.nodes if n.skin is not None]
        for node in users:                                       # skinned meshes: root nodes, no transform
            assert gltf.nodes.index(node) in roots and node.translation is None and node.matrix is None
            prim = gltf.meshes[node.mesh].primitives[0]
            assert gltf.accessors[prim.attributes.JOINTS_0].componentType in (5121, 5123)
            weights = _accessor(gltf, blob, prim.attributes.WEIGHTS_0)
            np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-6)
            assert _accessor(gltf, blob, prim.attributes.JOINTS_0).max() < len(skin.joints)
    (animation,) = gltf.animations
    for sampler in animation.samplers:
        times = _accessor(gltf, blob, sampler.input)
        assert gltf.accessors[sampler.input].type == "SCALAR" and times.dtype == np.float32
        assert np.all(np.diff(times) > 0.0) and times[0] >= 0.0
        assert gltf.accessors[sampler.output].count == len(times)
        assert sampler.interpolation == "LINEAR"
    targets = set()
    for channel in animation.channels:
        node = gltf.nodes[channel.target.node]
        assert node.matrix is None                              # animated nodes use TRS
        values = _accessor(gltf, blob, animation.samplers[channel.sampler].output)
        width = {"translation": 3, "rotation": 4}[channel.target.path]
        assert values.shape[1] == width
        if width == 4:
            np.testing.assert_allclose(np.linalg.norm(values, axis=1), 1.0, atol=1e-6)
        targets.add((channel.target.node, channel.target.path))
    assert len(targets) == len(animation.channels)              # one channel per node and path
    return gltf, blob


def gltf_node_tracks(gltf, blob):
    """Per node name: (times, translations, rotations) decoded from the animation."""
    tracks = {}
    (animation,) = gltf.animations
    for channel in animation.channels:
        sampler = animation.samplers[channel.sampler]
        name = gltf.nodes[channel.target.node].name
        entry = tracks.setdefault(name, {})
        entry["time"] = _accessor(gltf, blob, sampler.input)
        entry[channel.target.path] = _accessor(gltf, blob, sampler.output)
    return tracks


def check_gltf_poses(path, trajectory):
    gltf, blob = _validate_glb(path)
    tracks = gltf_node_tracks(gltf, blob)
    names = list(trajectory.body_names)
    expected = ["marionette"] + names + [f"bar_{b}" for b in trajectory.bar_names]
    assert [n.name for n in gltf.nodes[:len(expected)]] == expected
    f32 = np.float32
    worst = 0.0
    for b, name in enumerate(names):
        track = tracks[name]
        assert np.array_equal(track["time"], np.asarray(trajectory.frame_time).astype(f32))
        assert np.array_equal(track["translation"], np.asarray(trajectory.body_pos)[:, b].astype(f32))
        q = np.asarray(trajectory.body_rot)[:, b]
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        got = track["rotation"].astype(np.float64)
        assert np.all(np.einsum("ij,ij->i", got[1:], got[:-1]) >= 0.0)    # short-way interpolation
        q = q * np.sign(np.einsum("ij,ij->i", q, got))[:, None]            # q and -q: the same rotation
        error = np.abs(got - q)
        assert np.all(error <= np.spacing(np.abs(q).astype(f32)).astype(np.float64)), name
        worst = max(worst, error.max())
        node = gltf.nodes[b + 1]
        assert node.translation == [float(v) for v in track["translation"][0]]
        assert node.rotation == [float(v) for v in track["rotation"][0]]
        shape, size = trajectory.body_shape[b]
        positions = _accessor(gltf, blob, gltf.meshes[node.mesh].primitives[0].attributes.POSITION)
        if shape == "box":
            np.testing.assert_allclose(positions.max(axis=0) - positions.min(axis=0), size, rtol=1e-6)
        else:
            np.testing.assert_allclose(np.linalg.norm(positions, axis=1), size[0], rtol=1e-6)
    return gltf, worst


def _skinned_strings(gltf, blob):
    """Per frame, the world positions of the string vertices by the glTF skinning formula.

    ``v_world = sum_i w_i J_i(t) IBM_i v``, with ``J_i(t)`` the joint's world matrix: here
    the joint nodes sit under an identity ``strings`` node and animate their translation.
    """
    (skin,) = gltf.skins
    node = next(n for n in gltf.nodes if n.skin is not None)
    prim = gltf.meshes[node.mesh].primitives[0]
    rest = _accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
    joint = _accessor(gltf, blob, prim.attributes.JOINTS_0)
    weight = _accessor(gltf, blob, prim.attributes.WEIGHTS_0).astype(np.float64)
    bind = _accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
    tracks = gltf_node_tracks(gltf, blob)
    group = gltf.nodes[skin.skeleton]
    assert group.translation is None and group.rotation is None and group.matrix is None
    moved = np.stack([tracks[gltf.nodes[j].name]["translation"] for j in skin.joints], axis=1).astype(np.float64)
    frames = moved.shape[0]
    world = np.zeros((frames, len(rest), 3))
    homogeneous = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    for k in range(4):
        ibm_v = np.einsum("vab,vb->va", bind[joint[:, k]], homogeneous)[:, :3]   # bind space
        world += weight[None, :, k:k + 1] * (ibm_v[None] + moved[:, joint[:, k]])
    indices = _accessor(gltf, blob, prim.indices).reshape(-1, 2)
    return world, indices


def check_gltf_strings(gltf, trajectory):
    """The skinned string vertices are the simulated particles at every frame (float32 rounding)."""
    blob = gltf.binary_blob()
    world, segments = _skinned_strings(gltf, blob)
    q = np.asarray(trajectory.particle_q)
    assert world.shape == q.shape
    # The inverse bind matrix cancels the float32 rest position exactly, so what remains is
    # one float32 rounding of each particle position: at most 2^-24 relative.
    assert np.all(np.abs(world - q) <= 2.0**-24 * np.abs(q))
    error = np.abs(world - q).max()
    start = list(trajectory.string_start)
    expected = [(k, k + 1) for s in range(len(start) - 1) for k in range(start[s], start[s + 1] - 1)]
    assert [tuple(e) for e in segments] == expected                    # segments within each string
    return error


def check_trimesh(path, trajectory):
    """trimesh (another reader) sees the body meshes at their frame-0 world poses."""
    scene = trimesh.load(str(path), force="scene")
    rot = quat_matrix(np.asarray(trajectory.body_rot)[0])
    for b, name in enumerate(trajectory.body_names):
        transform, geometry = scene.graph.get(name)
        np.testing.assert_allclose(transform[:3, 3], trajectory.body_pos[0, b], atol=1e-6)
        np.testing.assert_allclose(transform[:3, :3], rot[b], atol=1e-6)
        shape, size = trajectory.body_shape[b]
        mesh = scene.geometry[geometry]
        expected = size if shape == "box" else (2 * size[0],) * 3
        np.testing.assert_allclose(mesh.extents, expected, rtol=1e-6)
        closed = mesh.copy()
        closed.merge_vertices(merge_tex=True, merge_norm=True)   # flat shading splits the vertices
        assert closed.is_watertight and closed.is_winding_consistent
        assert closed.volume > 0.0                                # faces point outwards
