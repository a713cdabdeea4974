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
import re
import subprocess
import sys
import types

import numpy as np
import pytest
import warp as wp

import dmarionette as dm
from dmarionette.cli import main
from dmarionette.io.export.bvh import export_bvh
from dmarionette.io.export.common import ExportError, read_marionette_trajectory
from dmarionette.io.export.gltf import export_gltf
from dmarionette.scene.puppet import load_puppet
from dmarionette.io.trajectory import write_marionette_trajectory

for _reader in ("bvh", "bvhio", "pygltflib", "trimesh"):   # the independent readers (the dev extra)
    pytest.importorskip(_reader)

from tests.support.export import (  # noqa: E402  (after the readers are known to be there)
    BVH_ANGLE_TOL,
    BVH_POS_TOL,
    BVH_ROT_TOL,
    SYNTH_DT,
    SYNTH_FRAMES,
    bvh_forward_kinematics,
    read_bvh_channels,
    check_bvh_poses,
    check_gltf_poses,
    check_gltf_strings,
    check_trimesh,
    gltf_node_tracks,
    quat_matrix,
    synthetic_motion,
    bvh_reader,
)

wp.config.log_level = wp.LOG_WARNING


@pytest.fixture(scope="module")
def synthetic():
    return synthetic_motion()


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """0.5 s of the hanging marionette, and its trajectory file."""
    scene = dm.load_scene("hanging")
    model = dm.MarionetteModel(scene, optimization_level=0)
    trajectory = dm.simulate_marionette(model, 0.5, progress=False)
    path = write_marionette_trajectory(tmp_path_factory.mktemp("sim") / "trajectory.npz", trajectory, scene)
    return trajectory, scene, path


# ----------------------------------------------------------------------------- BVH tests

def test_bvh_of_a_simulation_reproduces_the_body_poses(simulated, tmp_path):
    trajectory, scene, _ = simulated
    path = export_bvh(trajectory, tmp_path / "motion.bvh", puppet=scene.puppet)
    pos_err, rot_err, bvhio_err = check_bvh_poses(path, trajectory, scene.puppet)
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
    rot = quat_matrix(trajectory.body_rot)
    for b, joint in enumerate(puppet.joints, start=1):
        p = parents[b]
        gap = (trajectory.body_pos[:, p] + rot[:, p] @ np.asarray(joint.anchor_parent)
               - trajectory.body_pos[:, b] - rot[:, b] @ np.asarray(joint.anchor_child))
        assert np.abs(gap).max() < 1e-12


def test_bvh_hinge_and_universal_channels_are_the_joint_angles(simulated, tmp_path):
    trajectory, scene, _ = simulated
    _, channels = read_bvh_channels(export_bvh(trajectory, tmp_path / "m.bvh"))
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
    pos_err, rot_err, _ = check_bvh_poses(path, trajectory, puppet)
    print(f"synthetic BVH: position {pos_err:.2e} m, rotation {rot_err:.2e}")
    mocap, channels = read_bvh_channels(path)
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
    mocap, fk = bvh_forward_kinematics(export_bvh(trajectory, tmp_path / "60.bvh", fps=2.0 / SYNTH_DT))
    assert mocap.nframes == 2 * SYNTH_FRAMES - 1
    assert mocap.frame_time == pytest.approx(SYNTH_DT / 2.0, abs=1e-9)
    rot = quat_matrix(trajectory.body_rot)
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


# ----------------------------------------------------------------------------- glTF tests

def test_gltf_of_a_simulation_decodes_to_the_body_poses(simulated, tmp_path):
    trajectory, _, _ = simulated
    path = export_gltf(trajectory, tmp_path / "motion.glb")
    gltf, worst = check_gltf_poses(path, trajectory)
    check_trimesh(path, trajectory)
    string_error = check_gltf_strings(gltf, trajectory)
    particles = trajectory.particle_q.shape[1]
    assert len(gltf.animations[0].channels) == 2 * (len(trajectory.body_names) + len(trajectory.bar_names)) + particles
    print(f"simulated glTF: worst quaternion component error {worst:.2e}, strings {string_error:.2e} m")
    plain = export_gltf(trajectory, tmp_path / "no_strings.glb", strings=False)
    gltf, _ = check_gltf_poses(plain, trajectory)
    assert not gltf.skins and len(gltf.nodes) == 1 + len(trajectory.body_names) + len(trajectory.bar_names)


def test_gltf_of_large_rotations_and_a_ball(synthetic, tmp_path):
    trajectory, _ = synthetic
    path = export_gltf(trajectory, tmp_path / "big.glb")
    gltf, worst = check_gltf_poses(path, trajectory)
    check_trimesh(path, trajectory)
    assert gltf.nodes[13].name == "ball"
    tracks = gltf_node_tracks(gltf, gltf.binary_blob())
    np.testing.assert_allclose(tracks["bar_main"]["translation"], trajectory.bar_pos[:, 0], atol=1e-7)
    print(f"synthetic glTF: worst quaternion component error {worst:.2e}")


def test_gltf_refuses_bad_times_and_strings(synthetic, tmp_path):
    trajectory, _ = synthetic
    close = dict(vars(trajectory), frame_time=1000.0 + 1e-6 * np.arange(SYNTH_FRAMES))
    with pytest.raises(ExportError, match=r"equal in float32"):
        export_gltf(types.SimpleNamespace(**close), tmp_path / "x.glb")
    q = np.zeros((SYNTH_FRAMES, 10, 3))
    strings = dict(vars(trajectory), particle_q=q, string_start=np.array([0, 4, 10]), string_names=["a", "b"])
    export_gltf(types.SimpleNamespace(**strings), tmp_path / "ok.glb")
    for change, message in (
            ({"string_start": np.array([0, 4, 9])}, r"'string_start': got \[0, 4, 9\].*from 0 to 10"),
            ({"string_start": np.array([0, 1, 10])}, r"at least 2 particles a string"),
            ({"particle_q": q[:-1]}, r"'particle_q': got shape \(60, 10, 3\); expected \(61, P, 3\)"),
            ({"particle_q": np.where(np.arange(10)[None, :, None] == 3, np.inf, q)}, r"'particle_q'.*non-finite")):
        with pytest.raises(ExportError, match=message):
            export_gltf(types.SimpleNamespace(**dict(strings, **change)), tmp_path / "x.glb")
    export_gltf(types.SimpleNamespace(**dict(strings, particle_q=q[:-1])), tmp_path / "x.glb", strings=False)


def test_single_frame_trajectories_export(synthetic, tmp_path):
    trajectory, _ = synthetic
    one = types.SimpleNamespace(**{k: (v[:1] if isinstance(v, np.ndarray) else v) for k, v in vars(trajectory).items()})
    mocap = bvh_reader.Bvh(export_bvh(one, tmp_path / "one.bvh").read_text())
    assert mocap.nframes == 1 and mocap.frame_time == pytest.approx(1.0 / 30.0, abs=1e-9)
    check_bvh_poses(tmp_path / "one.bvh", one, load_puppet())
    check_gltf_poses(export_gltf(one, tmp_path / "one.glb"), one)


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
    assert set(files) - {"usd"} == {"bvh", "gltf"}  # "usd" too with usd-core: tests/io/test_export_usd.py
    check_bvh_poses(tmp_path / "out" / "motion.bvh", trajectory, scene.puppet)
    check_gltf_poses(tmp_path / "out" / "motion.glb", trajectory)
    run = _cli(path, "--out", tmp_path / "bvh", "--format", "bvh", "--fps", "60")
    assert run.returncode == 0, run.stderr
    assert [p.name for p in (tmp_path / "bvh").iterdir()] == ["motion.bvh"]
    assert bvh_reader.Bvh((tmp_path / "bvh" / "motion.bvh").read_text()).frame_time == pytest.approx(1 / 60, abs=1e-9)


def test_export_command_refuses_missing_and_corrupt_files(simulated, tmp_path, capsys):
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
    cases["scene without puppet"] = (path, r"--scene: this scene has no \[puppet\]")
    extra = {"scene without puppet": ["--scene", "strings"]}  # a bad --fps: tests/test_bad_flags.py
    for label, (file, message) in cases.items():
        # In-process (the command's own error handling; an escaping exception fails the test).
        assert main(["export", str(file), "--out", str(tmp_path / "out"), *extra.get(label, [])]) == 2, label
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), (label, err)
        assert re.search(message, err), (label, err)
    assert not (tmp_path / "out").exists()


def test_export_command_help():
    run = subprocess.run([sys.executable, "-m", "dmarionette.cli", "export", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0 and "--format" in run.stdout and "docs/export.md" in run.stdout
