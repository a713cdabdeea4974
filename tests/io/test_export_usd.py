"""USD export (docs/export.md): read back with pxr (usd-core), poses against the trajectory.

The synthetic motion (``tests/support/export.py``: large known rotations, quaternion signs flipping
every other frame, a ball) checks body poses; 0.5 s of the simulated hanging marionette
checks the strings (``BasisCurves`` points = the particles) and the command line.
"""

import json
import sys

import numpy as np
import pytest

pxr = pytest.importorskip("pxr", reason="USD export tests need usd-core")
from pxr import Usd, UsdGeom  # noqa: E402

import dmarionette as dm  # noqa: E402
from dmarionette.cli import main  # noqa: E402
from dmarionette.io.export import usd as usd_export  # noqa: E402
from dmarionette.io.export.common import ExportError  # noqa: E402
from dmarionette.io.export.usd import export_usd  # noqa: E402
from dmarionette.io.trajectory import write_marionette_trajectory  # noqa: E402
from dmarionette.rotations import quat_to_matrix  # noqa: E402

from tests.support.export import SYNTH_DT, SYNTH_FRAMES, synthetic_motion  # noqa: E402

POSE_TOL = 1e-12  # [m] and rotation matrix entries: double-precision ops, nothing is rounded


def _world(stage, prim_path, code):
    """(position (3,), rotation matrix (3, 3), column vectors) of a prim at a time code."""
    m = np.array(UsdGeom.XformCache(code).GetLocalToWorldTransform(stage.GetPrimAtPath(prim_path)))
    return m[3, :3], m[:3, :3].T  # USD: row vectors, p' = p M


@pytest.fixture(scope="module")
def synthetic_stage(tmp_path_factory):
    traj, _ = synthetic_motion()
    path = export_usd(traj, tmp_path_factory.mktemp("usd") / "motion.usda")
    return traj, Usd.Stage.Open(str(path))


def test_time_codes_follow_the_frames(synthetic_stage):
    traj, stage = synthetic_stage
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1.0 / SYNTH_DT)
    assert stage.GetFramesPerSecond() == pytest.approx(1.0 / SYNTH_DT)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, SYNTH_FRAMES - 1)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    samples = UsdGeom.Xform(stage.GetPrimAtPath("/marionette/bodies/torso")).GetOrderedXformOps()[0].GetTimeSamples()
    assert samples == [float(k) for k in range(SYNTH_FRAMES)]


@pytest.mark.parametrize("frame", [0, 1, 7, 30, 45, SYNTH_FRAMES - 1])
def test_body_poses_match_the_trajectory(synthetic_stage, frame):
    traj, stage = synthetic_stage
    for b, name in enumerate(traj.body_names):
        position, rotation = _world(stage, f"/marionette/bodies/{name}", float(frame))
        np.testing.assert_allclose(position, traj.body_pos[frame, b], atol=POSE_TOL, err_msg=name)
        np.testing.assert_allclose(rotation, quat_to_matrix(traj.body_rot[frame, b]), atol=POSE_TOL, err_msg=name)
    position, rotation = _world(stage, "/marionette/bars/main", float(frame))
    np.testing.assert_allclose(position, traj.bar_pos[frame, 0], atol=POSE_TOL)
    np.testing.assert_allclose(rotation, traj.bar_rot[frame, 0], atol=POSE_TOL)


def test_between_frames_the_rotation_takes_the_short_way(synthetic_stage):
    """Quaternion signs flip every other frame in the input; USD's slerp must not go round."""
    traj, stage = synthetic_stage
    for b, name in enumerate(traj.body_names):
        _, r0 = _world(stage, f"/marionette/bodies/{name}", 10.0)
        _, r_mid = _world(stage, f"/marionette/bodies/{name}", 10.5)
        _, r1 = _world(stage, f"/marionette/bodies/{name}", 11.0)
        step = np.arccos(np.clip((np.trace(r0.T @ r1) - 1) / 2, -1, 1))
        half = np.arccos(np.clip((np.trace(r0.T @ r_mid) - 1) / 2, -1, 1))
        assert half == pytest.approx(step / 2, abs=1e-9), name


def test_shapes_are_sized_like_the_puppet(synthetic_stage):
    traj, stage = synthetic_stage
    for name, (shape, size) in zip(traj.body_names, traj.body_shape):
        prim = stage.GetPrimAtPath(f"/marionette/bodies/{name}/shape")
        if shape == "sphere":
            assert prim.GetTypeName() == "Sphere"
            assert UsdGeom.Sphere(prim).GetRadiusAttr().Get() == pytest.approx(size[0])
        else:
            assert prim.GetTypeName() == "Cube"
            bound = UsdGeom.Imageable(prim).ComputeLocalBound(0.0, UsdGeom.Tokens.default_).ComputeAlignedRange()
            np.testing.assert_allclose(np.array(bound.GetSize()), size, rtol=1e-6)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """0.5 s of the hanging marionette, its trajectory file, and the CLI's USD export of it."""
    scene = dm.load_scene("hanging")
    trajectory = dm.simulate_marionette(dm.MarionetteModel(scene, optimization_level=0), 0.5, progress=False)
    folder = tmp_path_factory.mktemp("sim")
    path = write_marionette_trajectory(folder / "trajectory.npz", trajectory, scene)
    return trajectory, path


def test_cli_writes_strings_as_animated_curves(simulated, tmp_path, capsys):
    trajectory, path = simulated
    assert main(["export", str(path), "--format", "usd", "--out", str(tmp_path)]) == 0
    files = json.loads(capsys.readouterr().out)
    assert set(files) == {"usd"}
    stage = Usd.Stage.Open(files["usd"])
    fps = 1.0 / float(np.median(np.diff(trajectory.frame_time)))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(fps, rel=1e-6)
    start = np.asarray(trajectory.string_start)
    frames = len(trajectory.frame_time)
    for s, name in enumerate(trajectory.string_names):
        curve = UsdGeom.BasisCurves(stage.GetPrimAtPath(f"/marionette/strings/{name}"))
        assert curve.GetTypeAttr().Get() == UsdGeom.Tokens.linear
        assert list(curve.GetCurveVertexCountsAttr().Get()) == [int(start[s + 1] - start[s])]
        codes = curve.GetPointsAttr().GetTimeSamples()
        np.testing.assert_allclose(codes, trajectory.frame_time * stage.GetTimeCodesPerSecond(), atol=1e-6)
        for k in (0, frames // 2, frames - 1):
            points = np.array(curve.GetPointsAttr().Get(codes[k]))
            expected = trajectory.particle_q[k, start[s]:start[s + 1]].astype(np.float32)
            np.testing.assert_array_equal(points, expected, err_msg=f"{name} frame {k}")
    for k in (0, frames - 1):
        code = codes[k]
        for b, name in enumerate(trajectory.body_names):
            position, rotation = _world(stage, f"/marionette/bodies/{name}", code)
            np.testing.assert_allclose(position, trajectory.body_pos[k, b], atol=1e-12)
            np.testing.assert_allclose(rotation, quat_to_matrix(trajectory.body_rot[k, b]), atol=1e-12)


def test_binary_usdc_reads_back(simulated, tmp_path):
    trajectory, path = simulated
    out = export_usd(dm.read_marionette_trajectory(path), tmp_path / "motion.usdc")
    assert out.read_bytes()[:8] == b"PXR-USDC"
    stage = Usd.Stage.Open(str(out))
    position, _ = _world(stage, "/marionette/bodies/head", stage.GetEndTimeCode())
    np.testing.assert_allclose(position, trajectory.body_pos[-1, trajectory.body_names.index("head")], atol=1e-12)


def test_a_bad_extension_is_refused(simulated, tmp_path):
    trajectory, _ = simulated
    with pytest.raises(ExportError, match=r"motion\.obj.*expected \.usda"):
        export_usd(trajectory, tmp_path / "motion.obj")


def test_without_pxr_usd_says_what_to_install(simulated, tmp_path, capsys, monkeypatch):
    _, path = simulated
    monkeypatch.setitem(sys.modules, "pxr.Usd", None)  # import pxr.Usd raises ImportError
    assert not usd_export.usd_available()
    assert main(["export", str(path), "--format", "usd", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[usd]'" in err[0]
    assert not (tmp_path / "motion.usda").exists()
    assert main(["export", str(path), "--format", "all", "--out", str(tmp_path)]) == 0
    files = json.loads(capsys.readouterr().out)
    assert files["usd"].startswith("skipped:") and "usd-core" in files["usd"]
    assert (tmp_path / "motion.glb").exists() and (tmp_path / "motion.bvh").exists()
