"""The puppet motion as an animated USD stage (``.usda`` text or ``.usdc`` binary), for
Omniverse, Isaac Sim, Newton, Blender and ``usdview``. Needs ``usd-core`` (the ``usd`` extra).

Contents (documented for users in ``docs/export.md``):

- **Stage**: ``upAxis = "Y"``, ``metersPerUnit = 1``, ``timeCodesPerSecond`` =
  ``framesPerSecond`` = the trajectory's frame rate (30 for the 30 Hz scenes), time code =
  frame time [s] x ``timeCodesPerSecond`` (frame ``k`` of a 30 Hz trajectory at code ``k``),
  ``startTimeCode`` / ``endTimeCode`` the first and last frame. Default prim ``/marionette``.
- **Bodies**: ``/marionette/bodies/NAME``, an ``Xform`` with a ``translate`` (double3, the
  centre of mass [m], world) and an ``orient`` (quatd, signs kept continuous so that USD's
  interpolation takes the short way) op sampled at every frame; under it
  ``shape``, a ``Cube`` (``size = 1`` scaled to the box's full extents) or a ``Sphere``
  (``radius``), centred on the body frame. The hierarchy is flat: each body holds its world
  pose, as in the glTF export.
- **Bars**: ``/marionette/bars/NAME``, an ``Xform`` animated the same way (centre and axes),
  with a thin ``Cube`` marker.
- **Strings** (when the trajectory has its particles): ``/marionette/strings/NAME``, a
  linear ``BasisCurves`` with one curve through the string's particles, ``points``
  sampled at every frame (the simulated particles, float32), ``widths`` 4 mm.
- **Not exported**: the ground, the chair, forces.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.io.export.common import ExportError, bar_tracks, body_motion, string_tracks
from dmarionette.rotations import continuous_quats

__all__ = ["USD_HINT", "export_usd", "usd_available"]

USD_HINT = ("USD export needs the 'pxr' module of usd-core, which is not installed: "
            "pip install -e '.[usd]' (or pip install usd-core)")


def usd_available() -> bool:
    """Whether ``pxr`` (usd-core) imports; ``usd_available.hint`` says what to install."""
    try:
        import pxr.Usd  # noqa: F401
    except ImportError:
        return False
    return True


usd_available.hint = USD_HINT


def _frame_rate(times: np.ndarray) -> float:
    """Frames per second of ``times``: 1 / the median step, rounded to 1e-6 Hz (1 for one frame)."""
    if len(times) < 2:
        return 1.0
    return float(np.round(1.0 / np.median(np.diff(times)), 6))


def export_usd(trajectory: Any, path: str | Path, *, strings: bool = True) -> Path:
    """Writes the puppet motion of ``trajectory`` as an animated USD stage (module docstring).

    Args:
        trajectory: a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (or what
            :func:`~dmarionette.io.export.common.read_marionette_trajectory` returns, or an
            object with the same fields), as for :func:`~dmarionette.io.export.gltf.export_gltf`.
        path: the ``.usda`` (text) or ``.usdc`` / ``.usd`` (binary) file; parent folders are
            created; replaced if it exists.
        strings: write the strings when the trajectory has them.

    Returns:
        ``path``.

    Raises:
        ExportError: ``pxr`` is missing, a trajectory without body motion or with malformed
            fields, an extension USD does not write.
    """
    path = Path(path)
    where = str(getattr(trajectory, "source", None) or "trajectory")
    if not usd_available():
        raise ExportError(f"{path}: {USD_HINT}")
    from pxr import Gf, Tf, Usd, UsdGeom, Vt

    if path.suffix not in (".usda", ".usdc", ".usd"):
        raise ExportError(f"{path}: extension {path.suffix!r}; expected .usda (text), .usdc or .usd (binary)")
    motion = body_motion(trajectory, where)
    fps = _frame_rate(motion.frame_time)
    codes = motion.frame_time * fps
    whole = np.round(codes)
    codes = np.where(np.abs(codes - whole) < 1e-6, whole, codes)  # frame k at code k, not 30.999999999999996
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(float(codes[0]))
    stage.SetEndTimeCode(float(codes[-1]))
    root = UsdGeom.Xform.Define(stage, "/marionette")
    stage.SetDefaultPrim(root.GetPrim())
    stage.GetRootLayer().documentation = f"dmarionette export_usd of {where}"

    def animated_xform(prim_path: str, pos: np.ndarray, rot: np.ndarray) -> UsdGeom.Xform:
        xform = UsdGeom.Xform.Define(stage, prim_path)
        translate = xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        orient = xform.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
        for code, p, (x, y, z, w) in zip(codes, pos, continuous_quats(rot)):  # USD slerps: no sign flips
            translate.Set(Gf.Vec3d(*map(float, p)), float(code))
            orient.Set(Gf.Quatd(float(w), float(x), float(y), float(z)), float(code))
        return xform

    UsdGeom.Scope.Define(stage, "/marionette/bodies")
    for b, (name, (shape, size)) in enumerate(zip(motion.body_names, motion.body_shape)):
        body = f"/marionette/bodies/{Tf.MakeValidIdentifier(name)}"
        animated_xform(body, motion.body_pos[:, b], motion.body_rot[:, b])
        if shape == "sphere":
            sphere = UsdGeom.Sphere.Define(stage, f"{body}/shape")
            sphere.CreateRadiusAttr(float(size[0]))
            sphere.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-size[0]), Gf.Vec3f(size[0])]))
        else:
            cube = UsdGeom.Cube.Define(stage, f"{body}/shape")
            cube.CreateSizeAttr(1.0)
            cube.AddScaleOp().Set(Gf.Vec3f(*map(float, size)))
    bars = bar_tracks(trajectory, motion.frame_count)
    if bars:
        UsdGeom.Scope.Define(stage, "/marionette/bars")
    for name, pos, rot in bars:
        bar = f"/marionette/bars/{Tf.MakeValidIdentifier(name)}"
        animated_xform(bar, pos, rot)
        marker = UsdGeom.Cube.Define(stage, f"{bar}/shape")
        marker.CreateSizeAttr(1.0)
        marker.AddScaleOp().Set(Gf.Vec3f(0.3, 0.02, 0.02))
    chains = string_tracks(trajectory, motion.frame_count, where) if strings else None
    if chains:
        UsdGeom.Scope.Define(stage, "/marionette/strings")
        for name, q in chains:
            curve = UsdGeom.BasisCurves.Define(stage, f"/marionette/strings/{Tf.MakeValidIdentifier(name)}")
            curve.CreateTypeAttr(UsdGeom.Tokens.linear)
            curve.CreateCurveVertexCountsAttr(Vt.IntArray([q.shape[1]]))
            curve.CreateWidthsAttr(Vt.FloatArray([0.004]))
            curve.SetWidthsInterpolation(UsdGeom.Tokens.constant)
            points = curve.CreatePointsAttr()
            for code, frame in zip(codes, q.astype(np.float32)):
                points.Set(Vt.Vec3fArray.FromNumpy(frame), float(code))
    stage.GetRootLayer().Save()
    return path
