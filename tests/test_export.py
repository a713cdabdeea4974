"""Motion export (BVH, glTF): files read back by independent readers reproduce the simulated poses.

Two motions: a short real simulation (the ``hanging`` scene, 0.5 s; puppet kernels without
optimisation) and a synthetic one with large known rotations (whole turns, exactly 180
degrees, gimbal lock of the Euler channels) plus a free ball, built here by forward
kinematics with quaternions, independently of the exporters' matrix code.

BVH readers: ``bvh`` (raw channel values, float64; forward kinematics done here from the
BVH definition) and ``bvhio`` (its own forward kinematics, float32). glTF readers:
``pygltflib`` (the JSON and the binary chunk; the structure is checked here against the
rules of the glTF 2.0 specification that the Khronos validator checks for these files)
and ``trimesh`` (meshes and node transforms).

Tolerances come from the number formats. BVH: 6 decimals, so positions are off by at most
5e-7 m and angles by 5e-7 deg = 8.7e-9 rad; the deepest chain (torso, hip, knee, ankle) has
4 joints of 3 channels, so a rotation is off by at most 12 x 8.7e-9 = 1.05e-7 rad, and a
position by 5e-7 m plus lever arms (< 0.3 m) times that (3e-8 m): tolerances 2e-7 rad and
1e-6 m. bvhio computes in float32 (relative 6e-8 per operation, values < 1 m): 1e-5 m.
glTF: float32 values, compared with the float64 poses rounded once to float32.
"""

import json
import struct
import subprocess
import sys
import types

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.export_bvh import export_bvh
from dmarionette.export_common import ExportError, read_marionette_trajectory
from dmarionette.export_gltf import export_gltf
from dmarionette.puppet import load_puppet
from dmarionette.trajectory_file import write_marionette_trajectory

bvh_reader = pytest.importorskip("bvh")
bvhio = pytest.importorskip("bvhio")
pygltflib = pytest.importorskip("pygltflib")
trimesh = pytest.importorskip("trimesh")

wp.config.log_level = wp.LOG_WARNING
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


def _qmatrix(q):
    return np.stack([_qrotate(q, e) for e in np.eye(3)], axis=-1)


SYNTH_FRAMES = 61
SYNTH_DT = 1.0 / 30.0


def _synthetic():
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
                                 bar_rot=_qmatrix(rot[:, :1]))
    return traj, known


@pytest.fixture(scope="module")
def synthetic():
    return _synthetic()


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """0.5 s of the hanging marionette, and its trajectory file."""
    scene = dm.load_scene("hanging")
    model = dm.MarionetteModel(scene, optimization_level=0)
    trajectory = dm.simulate_marionette(model, 0.5, progress=False)
    path = write_marionette_trajectory(tmp_path_factory.mktemp("sim") / "trajectory.npz", trajectory, scene)
    return trajectory, scene, path


# ----------------------------------------------------------------------------- BVH reading

def _elementary(channel, degrees):
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    return {"X": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "Y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "Z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[channel[0]]


def _bvh_fk(path):
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


def _check_bvh_poses(path, trajectory, puppet):
    """FK of the file reproduces every body's centre and rotation at every frame; returns the errors."""
    mocap, fk = _bvh_fk(path)
    assert mocap.nframes == len(trajectory.frame_time)
    rot = _qmatrix(np.asarray(trajectory.body_rot))
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


def _channels(path):
    mocap = bvh_reader.Bvh(path.read_text())
    return mocap, {n: np.array([[float(v) for v in mocap.frame_joint_channels(f, n, mocap.joint_channels(n))]
                                for f in range(mocap.nframes)]) for n in mocap.get_joints_names()}


# ----------------------------------------------------------------------------- BVH tests

def test_bvh_of_a_simulation_reproduces_the_body_poses(simulated, tmp_path):
    trajectory, scene, _ = simulated
    path = export_bvh(trajectory, tmp_path / "motion.bvh", puppet=scene.puppet)
    pos_err, rot_err, bvhio_err = _check_bvh_poses(path, trajectory, scene.puppet)
    print(f"simulated BVH: position {pos_err:.2e} m, rotation {rot_err:.2e}, bvhio {bvhio_err:.2e} m")


def test_bvh_hierarchy_is_the_joint_tree_with_constant_offsets(simulated, tmp_path):
    trajectory, scene, _ = simulated
    puppet = scene.puppet
    mocap = bvh_reader.Bvh(export_bvh(trajectory, tmp_path / "m.bvh").read_text())
    names = [b.name for b in puppet.bodies]
    assert mocap.get_joints_names() == names            # depth-first, the puppet's body order
    assert mocap.frame_time == pytest.approx(trajectory.frame_time[1] - trajectory.frame_time[0], abs=1e-9)
    assert mocap.joint_channels("torso") == ["Xposition", "Yposition", "Zposition",
                                             "Xrotation", "Zrotation", "Yrotation"]
    assert tuple(mocap.joint_offset("torso")) == (0.0, 0.0, 0.0)
    parents = puppet.parent_index()
    for b, joint in enumerate(puppet.joints, start=1):
        assert mocap.joint_parent(names[b]).name == names[parents[b]]
        assert mocap.joint_channels(names[b]) == ["Xrotation", "Zrotation", "Yrotation"]
        above = np.zeros(3) if parents[b] == 0 else np.asarray(puppet.joints[parents[b] - 1].anchor_child)
        np.testing.assert_allclose(mocap.joint_offset(names[b]), np.asarray(joint.anchor_parent) - above, atol=5e-7)
    # The simulated joints never come apart: each joint's anchors coincide (reduced coordinates).
    rot = _qmatrix(trajectory.body_rot)
    for b, joint in enumerate(puppet.joints, start=1):
        p = parents[b]
        gap = (trajectory.body_pos[:, p] + rot[:, p] @ np.asarray(joint.anchor_parent)
               - trajectory.body_pos[:, b] - rot[:, b] @ np.asarray(joint.anchor_child))
        assert np.abs(gap).max() < 1e-12


def test_bvh_hinge_and_universal_channels_are_the_joint_angles(simulated, tmp_path):
    trajectory, scene, _ = simulated
    _, channels = _channels(export_bvh(trajectory, tmp_path / "m.bvh"))
    q = 7
    checked = 0
    for joint in scene.puppet.joints:
        values = channels[joint.child]                 # X, Z, Y [deg]
        if joint.type == "ball":
            q += 4
            continue
        n = len(joint.axes)
        angles = np.degrees(trajectory.joint_q[:, q:q + n])
        q += n
        np.testing.assert_allclose(values[:, 0], angles[:, 0], atol=BVH_ANGLE_TOL)
        np.testing.assert_allclose(values[:, 1], angles[:, 1] if n == 2 else 0.0, atol=BVH_ANGLE_TOL)
        np.testing.assert_allclose(values[:, 2], 0.0, atol=BVH_ANGLE_TOL)
        checked += 1
    assert q == trajectory.joint_q.shape[1] and checked == 10
    assert np.abs(np.degrees(trajectory.joint_q[:, 7:])).max() > 0.1   # the joints did move


def test_bvh_of_large_rotations_reproduces_the_poses(synthetic, tmp_path):
    trajectory, known = synthetic
    puppet = load_puppet()
    path = export_bvh(trajectory, tmp_path / "big.bvh")
    pos_err, rot_err, _ = _check_bvh_poses(path, trajectory, puppet)
    print(f"synthetic BVH: position {pos_err:.2e} m, rotation {rot_err:.2e}")
    mocap, channels = _channels(path)
    assert "ball" not in mocap.get_joints_names()
    # A hinge turning 340 deg: the X channel is its angle, continuous through 180 deg.
    np.testing.assert_allclose(channels["lower_leg_left"][:, 0], np.degrees(known["knee_left"]), atol=BVH_ANGLE_TOL)
    np.testing.assert_allclose(channels["lower_leg_left"][:, 1:], 0.0, atol=BVH_ANGLE_TOL)
    # Rx then Rz with Z through 90 deg (gimbal lock at frame 45) and on to 120 deg.
    a, b = (np.degrees(v) for v in known["shoulder_left"])
    assert b[45] == pytest.approx(90.0)
    np.testing.assert_allclose(channels["upper_arm_left"][:, 0], a, atol=1e-5)
    np.testing.assert_allclose(channels["upper_arm_left"][:, 1], b, atol=1e-5)
    np.testing.assert_allclose(channels["upper_arm_left"][:, 2], 0.0, atol=1e-5)
    # Every channel is continuous: no jump of a whole turn between frames.
    for name, values in channels.items():
        assert np.abs(np.diff(values[:, -3:], axis=0)).max() < 90.0, name


def test_bvh_resampled_to_another_frame_rate(synthetic, tmp_path):
    trajectory, _ = synthetic
    puppet = load_puppet()
    mocap, fk = _bvh_fk(export_bvh(trajectory, tmp_path / "60.bvh", fps=2.0 / SYNTH_DT))
    assert mocap.nframes == 2 * SYNTH_FRAMES - 1
    assert mocap.frame_time == pytest.approx(SYNTH_DT / 2.0, abs=1e-9)
    rot = _qmatrix(trajectory.body_rot)
    for b, body in enumerate(puppet.bodies):
        origin, r = fk[body.name]
        np.testing.assert_allclose(r[::2], rot[:, b], atol=BVH_ROT_TOL)     # at the original frames: the poses
    # Between frames: the root halfway, and each joint rotation the slerp midpoint.
    origin, _ = fk["torso"]
    np.testing.assert_allclose(origin[1::2], 0.5 * (trajectory.body_pos[1:, 0] + trajectory.body_pos[:-1, 0]),
                               atol=BVH_POS_TOL)
    _, knee = fk["lower_leg_left"]
    _, thigh = fk["upper_leg_left"]
    relative = np.swapaxes(thigh, 1, 2) @ knee
    half = np.radians(340.0) * (np.arange(1, 2 * SYNTH_FRAMES - 1, 2) / 2) / (SYNTH_FRAMES - 1)
    np.testing.assert_allclose(relative[1::2, 1, 1], np.cos(half), atol=BVH_ROT_TOL)
    np.testing.assert_allclose(relative[1::2, 2, 1], np.sin(half), atol=BVH_ROT_TOL)


def test_bvh_refuses_a_puppet_that_does_not_match(synthetic, tmp_path):
    import dataclasses

    trajectory, _ = synthetic
    puppet = load_puppet()
    joints = list(puppet.joints)
    joints[3] = dataclasses.replace(joints[3], anchor_parent=(0.0, -0.06, 0.0))
    with pytest.raises(ExportError, match=rf"joint '{joints[3].name}'.*apart at frame.*another puppet"):
        export_bvh(trajectory, tmp_path / "x.bvh", puppet=dataclasses.replace(puppet, joints=tuple(joints)))
    renamed = types.SimpleNamespace(**{**vars(trajectory), "body_names": ["pelvis"] + trajectory.body_names[1:]})
    with pytest.raises(ExportError, match=r"body_names.*'pelvis'.*expected the bodies of puppet"):
        export_bvh(renamed, tmp_path / "x.bvh")


def test_bvh_refuses_bad_input(synthetic, tmp_path):
    trajectory, _ = synthetic
    fields = vars(trajectory)
    uneven = dict(fields, frame_time=fields["frame_time"] * (1.0 + 0.01 * np.arange(SYNTH_FRAMES)))
    with pytest.raises(ExportError, match=r"frame_time.*unevenly spaced.*fps="):
        export_bvh(types.SimpleNamespace(**uneven), tmp_path / "x.bvh")
    export_bvh(types.SimpleNamespace(**uneven), tmp_path / "x.bvh", fps=30.0)   # resampling accepts them
    for fps in (0.0, -5.0, float("nan")):
        with pytest.raises(ExportError, match=r"fps: got"):
            export_bvh(trajectory, tmp_path / "x.bvh", fps=fps)
    nan = fields["body_pos"].copy()
    nan[4, 2, 1] = np.nan
    with pytest.raises(ExportError, match=r"'body_pos'.*non-finite value at index \(4, 2, 1\)"):
        export_bvh(types.SimpleNamespace(**dict(fields, body_pos=nan)), tmp_path / "x.bvh")
    with pytest.raises(ExportError, match=r"'body_rot'.*shape \(61, 13, 3\); expected \(61, 13, 4\)"):
        export_bvh(types.SimpleNamespace(**dict(fields, body_rot=fields["body_rot"][..., :3])), tmp_path / "x.bvh")
    backwards = dict(fields, frame_time=fields["frame_time"][::-1].copy())
    with pytest.raises(ExportError, match=r"frame_time.*strictly increasing"):
        export_gltf(types.SimpleNamespace(**backwards), tmp_path / "x.glb")
    with pytest.raises(ExportError, match=r"field 'body_pos': got nothing"):
        export_gltf(types.SimpleNamespace(frame_time=[0.0], body_names=["a"]), tmp_path / "x.glb")


# ----------------------------------------------------------------------------- glTF reading

_COMPONENT = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


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
    assert len(children) == len(set(children)) and 0 not in children     # a tree under node 0
    assert gltf.scenes[gltf.scene].nodes == [0]
    for mesh in gltf.meshes:
        for prim in mesh.primitives:
            positions = _accessor(gltf, blob, prim.attributes.POSITION)
            normals = _accessor(gltf, blob, prim.attributes.NORMAL)
            indices = _accessor(gltf, blob, prim.indices).astype(np.int64)
            assert prim.mode == 4 and len(indices) % 3 == 0 and indices.max() < len(positions)
            assert len(normals) == len(positions)
            np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
            tri = positions[indices.reshape(-1, 3)].astype(np.float64)
            facing = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            assert np.all(np.einsum("ij,ij->i", facing, tri.mean(axis=1)) > 0.0)   # CCW from outside
            assert gltf.materials[prim.material].pbrMetallicRoughness is not None
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


def _node_tracks(gltf, blob):
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


def _check_gltf_poses(path, trajectory):
    gltf, blob = _validate_glb(path)
    tracks = _node_tracks(gltf, blob)
    names = list(trajectory.body_names)
    assert [n.name for n in gltf.nodes] == ["marionette"] + names + [f"bar_{b}" for b in trajectory.bar_names]
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


def _check_trimesh(path, trajectory):
    """trimesh (another reader) sees the body meshes at their frame-0 world poses."""
    scene = trimesh.load(str(path), force="scene")
    rot = _qmatrix(np.asarray(trajectory.body_rot)[0])
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


# ----------------------------------------------------------------------------- glTF tests

def test_gltf_of_a_simulation_decodes_to_the_body_poses(simulated, tmp_path):
    trajectory, _, _ = simulated
    path = export_gltf(trajectory, tmp_path / "motion.glb")
    gltf, worst = _check_gltf_poses(path, trajectory)
    _check_trimesh(path, trajectory)
    assert len(gltf.animations[0].channels) == 2 * (len(trajectory.body_names) + len(trajectory.bar_names))
    print(f"simulated glTF: worst quaternion component error {worst:.2e}")


def test_gltf_of_large_rotations_and_a_ball(synthetic, tmp_path):
    trajectory, _ = synthetic
    path = export_gltf(trajectory, tmp_path / "big.glb")
    gltf, worst = _check_gltf_poses(path, trajectory)
    _check_trimesh(path, trajectory)
    assert gltf.nodes[13].name == "ball"
    tracks = _node_tracks(gltf, gltf.binary_blob())
    np.testing.assert_allclose(tracks["bar_main"]["translation"], trajectory.bar_pos[:, 0], atol=1e-7)
    print(f"synthetic glTF: worst quaternion component error {worst:.2e}")


def test_gltf_refuses_times_that_collide_in_float32(synthetic, tmp_path):
    trajectory, _ = synthetic
    close = dict(vars(trajectory), frame_time=1000.0 + 1e-6 * np.arange(SYNTH_FRAMES))
    with pytest.raises(ExportError, match=r"equal in float32"):
        export_gltf(types.SimpleNamespace(**close), tmp_path / "x.glb")


# ----------------------------------------------------------------------------- files and command line

def test_trajectory_file_reads_back_with_its_scene_puppet(simulated):
    trajectory, scene, path = simulated
    loaded = read_marionette_trajectory(path)
    for name in ("frame_time", "body_pos", "body_rot", "joint_q", "bar_pos", "bar_rot", "tie_force"):
        assert np.array_equal(getattr(loaded, name), getattr(trajectory, name)), name
    assert loaded.body_names == trajectory.body_names and loaded.bar_names == trajectory.bar_names
    assert [(s, tuple(z)) for s, z in loaded.body_shape] == [(s, tuple(z)) for s, z in trajectory.body_shape]
    assert loaded.puppet == scene.puppet


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "dmarionette.cli", "export", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_export_command_writes_both_files(simulated, tmp_path):
    trajectory, scene, path = simulated
    run = _cli(path, "--out", tmp_path / "out")
    assert run.returncode == 0, run.stderr
    files = json.loads(run.stdout)
    assert set(files) == {"bvh", "gltf"}
    _check_bvh_poses(tmp_path / "out" / "motion.bvh", trajectory, scene.puppet)
    _check_gltf_poses(tmp_path / "out" / "motion.glb", trajectory)
    run = _cli(path, "--out", tmp_path / "bvh", "--format", "bvh", "--fps", "60")
    assert run.returncode == 0, run.stderr
    assert [p.name for p in (tmp_path / "bvh").iterdir()] == ["motion.bvh"]
    assert bvh_reader.Bvh((tmp_path / "bvh" / "motion.bvh").read_text()).frame_time == pytest.approx(1 / 60, abs=1e-9)


def test_export_command_refuses_missing_and_corrupt_files(simulated, tmp_path):
    _, _, path = simulated
    cases = {}
    cases["missing"] = (tmp_path / "nothing.npz", r"nothing.npz: no such file")
    (tmp_path / "text.npz").write_text("not an archive")
    cases["text"] = (tmp_path / "text.npz", r"text.npz: not a NumPy .npz archive")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(path.read_bytes()[:2000])
    cases["truncated"] = (cut, r"cut.npz: (cannot be read|not a NumPy)")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(tmp_path / "nobody.npz", **{k: v for k, v in arrays.items() if k != "body_rot"})
    cases["no body_rot"] = (tmp_path / "nobody.npz", r"nobody.npz: fields \['body_rot'\]: got nothing")
    meta = json.loads(str(arrays["metadata"]))
    np.savez(tmp_path / "strings.npz", **dict(arrays, metadata=np.array(json.dumps(dict(meta, kind=None)))))
    cases["strings only"] = (tmp_path / "strings.npz", r"metadata.kind': got None; expected 'marionette'")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    cases["other npz"] = (tmp_path / "other.npz", r"other.npz: field 'metadata': got nothing")
    for label, (file, message) in cases.items():
        run = _cli(file, "--out", tmp_path / "out")
        assert run.returncode == 2, (label, run.stdout, run.stderr)
        assert "Traceback" not in run.stderr, label
        assert len(run.stderr.strip().splitlines()) == 1, (label, run.stderr)
        import re

        assert re.search(message, run.stderr), (label, run.stderr)
