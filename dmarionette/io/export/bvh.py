"""The puppet motion as a BVH file (Biovision Hierarchy), for Blender and motion-capture tools.

Format written (documented for users in ``docs/export.md``):

- **Hierarchy**: the puppet's joint tree. The root is the puppet's root body (the torso)
  with 6 channels ``Xposition Yposition Zposition Xrotation Zrotation Yrotation``; every
  other body is a ``JOINT`` named after the body, with 3 channels
  ``Xrotation Zrotation Yrotation``. Leaf bodies end in an ``End Site``. A free ball (the
  ``ball`` scene) is not part of the tree and is not written (the glTF export has it).
- **Units**: metres (``OFFSET`` and positions) and degrees (rotations), 6 decimals
  (1 micrometre, 1e-6 degree). Blender's BVH importer maps one BVH unit to one Blender
  unit, so import with *Scale* 1.0 for true size; for a tool that expects centimetres,
  scale by 100.
- **Axes**: the simulator's: y up, the puppet faces +z, its left is +x (right-handed);
  Blender's importer converts from y up (its default *Forward* -Z, *Up* Y is fine).
- **Motion**: one frame per trajectory frame, ``Frame Time`` = the trajectory's frame
  period (1/30 s for the default 30 Hz puppet rate), or resampled to ``fps`` if given.

How body frames map to BVH joint frames. A body frame has its origin at the body's centre
of mass and, at rest, is aligned with the world. The BVH joint of body ``b`` has the same
axes as the body frame but its origin at the joint centre, the child anchor
``a_c(b)`` (``anchor_child`` of the joint above ``b``), so that BVH rotations turn the body
about its joint; the root joint's origin is the root body's centre of mass. With ``x_b``,
``R_b`` the simulated body position and rotation:

- joint origin (world): ``o_b = x_b + R_b a_c(b)`` (root: ``o = x``);
- rotation channels: the parent-relative rotation ``R_p^T R_b = Rx(X) Rz(Z) Ry(Y)``
  (channel order; intrinsic, as every BVH reader composes them);
- ``OFFSET`` of ``b`` in its parent's joint frame: ``a_p(b) - a_c(p)`` (``anchor_parent`` of
  ``b``'s joint minus the parent's own child anchor; the root's anchor is its centre, 0).

The offset is constant because both anchors are fixed in the parent body, and it is exact
because the simulator works in reduced coordinates: the joint's two anchors coincide in
the world at every step (``o_b = x_p + R_p a_p(b)``). :func:`export_bvh` checks that the
trajectory satisfies this (to 1e-6 m) before writing, which also catches a puppet
description that does not match the trajectory. The root's ``OFFSET`` is zero and its
position channels carry the root's world position, so readers that add the offset to the
position channels and those that replace it agree. At rest (all channels zero) the BVH
skeleton is the puppet's rest pose with the root at the origin.

For hinge and universal joints the channels are the joint angles themselves (the joints
turn ``Rx`` then ``Rz`` in the default puppet), within the Euler range; angles are chosen
continuous from frame to frame (no 360-degree jumps, the equivalent Euler triple nearer the
previous frame), so that an importer's interpolation between frames does what the puppet did.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.io.export.common import (
    BodyMotion,
    ExportError,
    body_motion,
    check_puppet_matches,
    resolve_puppet,
)
from dmarionette.rotations import continuous_quats, matrix_to_euler_xzy, matrix_to_quat, quat_slerp, quat_to_matrix
from dmarionette.scene.puppet import PuppetDescription

__all__ = ["BVH_ROTATION_CHANNELS", "bvh_local_rotations", "export_bvh"]

BVH_ROTATION_CHANNELS = ("Xrotation", "Zrotation", "Yrotation")
"""The rotation channel order of every joint: ``R = Rx(X) Rz(Z) Ry(Y)``."""

_DECIMALS = 6


def bvh_local_rotations(motion: BodyMotion, puppet: PuppetDescription) -> np.ndarray:
    """Parent-relative rotations of the puppet's bodies, ``(F, J, 4)`` quaternions (x, y, z, w).

    Row 0 is the root's world rotation; row ``b`` is ``R_p^T R_b`` for body ``b``'s parent ``p``.
    Signs are continuous along the frames.
    """
    count = len(puppet.bodies)
    world = quat_to_matrix(motion.body_rot[:, :count])
    local = world.copy()
    for b, p in enumerate(puppet.parent_index()):
        if p >= 0:
            local[:, b] = np.swapaxes(world[:, p], -1, -2) @ world[:, b]
    return continuous_quats(matrix_to_quat(local))


def _resample(times: np.ndarray, root_pos: np.ndarray, local: np.ndarray, new_times: np.ndarray):
    """Root position (linear) and joint rotations (slerp) at ``new_times`` inside ``times``."""
    i = np.clip(np.searchsorted(times, new_times, side="right") - 1, 0, len(times) - 2)
    u = np.clip((new_times - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0)
    pos = root_pos[i] + u[:, None] * (root_pos[i + 1] - root_pos[i])
    rot = quat_slerp(local[i], local[i + 1], np.broadcast_to(u[:, None], (len(u), local.shape[1])))
    return pos, continuous_quats(rot)


def _frame_period(motion: BodyMotion, fps: float | None, where: str) -> tuple[float, np.ndarray | None]:
    """The frame time [s] and, when resampling, the new frame times."""
    t = motion.frame_time
    if fps is not None:
        if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0.0):
            raise ExportError(f"{where}: fps: got {fps!r}; expected a frame rate > 0 [1/s] or None (the "
                              "trajectory's own frames)")
        if len(t) < 2:
            return 1.0 / fps, None
        count = int(np.floor((t[-1] - t[0]) * fps + 1e-9)) + 1
        return 1.0 / fps, t[0] + np.arange(count) / fps
    if len(t) < 2:
        return 1.0 / 30.0, None
    steps = np.diff(t)
    period = float(np.mean(steps))
    if np.max(np.abs(steps - period)) > 1e-6 * period:
        f = int(np.argmax(np.abs(steps - period)))
        raise ExportError(f"{where}: field 'frame_time': got unevenly spaced frames (frame {f} to {f + 1}: "
                          f"{steps[f]:.9g} s, mean {period:.9g} s); expected evenly spaced frames for BVH's single "
                          "Frame Time, or pass fps= to resample")
    return period, None


def _fmt(values: np.ndarray) -> str:
    """Fixed-point numbers; values that round to zero are written as 0 (no ``-0.000000``)."""
    values = np.where(np.abs(values) < 0.5 * 10.0**-_DECIMALS, 0.0, values)
    return " ".join(f"{v:.{_DECIMALS}f}" for v in values)


def _hierarchy(puppet: PuppetDescription) -> tuple[list[str], list[int]]:
    """The HIERARCHY lines and the body index of each channel block, in file order."""
    parents = puppet.parent_index()
    children: dict[int, list[int]] = {}
    for b, p in enumerate(parents):
        children.setdefault(p, []).append(b)
    anchor = [np.zeros(3)] + [np.asarray(j.anchor_child, dtype=np.float64) for j in puppet.joints]
    lines, order = ["HIERARCHY"], []

    def visit(b: int, depth: int) -> None:
        pad = "\t" * depth
        body = puppet.bodies[b]
        if b == 0:
            lines.append(f"ROOT {body.name}")
            offset = np.zeros(3)
            channels = "CHANNELS 6 Xposition Yposition Zposition " + " ".join(BVH_ROTATION_CHANNELS)
        else:
            lines.append(f"{pad}JOINT {body.name}")
            offset = np.asarray(puppet.joints[b - 1].anchor_parent) - anchor[parents[b]]
            channels = "CHANNELS 3 " + " ".join(BVH_ROTATION_CHANNELS)
        lines.extend([f"{pad}{{", f"{pad}\tOFFSET {_fmt(offset)}", f"{pad}\t{channels}"])
        order.append(b)
        for c in children.get(b, []):
            visit(c, depth + 1)
        if not children.get(b):
            # The far end of the body: the point opposite the joint through the centre of mass.
            tip = -2.0 * anchor[b]
            if np.linalg.norm(tip) < 1e-9:
                size = body.size[0] if body.shape == "sphere" else 0.5 * body.size[1]
                tip = np.array([0.0, size, 0.0])
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {_fmt(tip)}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    visit(0, 0)
    return lines, order


def export_bvh(trajectory: Any, path: str | Path, *, fps: float | None = None,
               puppet: PuppetDescription | None = None) -> Path:
    """Writes the puppet motion of ``trajectory`` as a BVH file (format: module docstring).

    Args:
        trajectory: a :class:`~dmarionette.marionette.rollout.MarionetteTrajectory` (or the
            result of :func:`~dmarionette.io.export.common.read_marionette_trajectory`).
        path: the ``.bvh`` file to write; parent folders are created.
        fps: output frame rate [1/s]. None (default): one BVH frame per trajectory frame,
            ``Frame Time`` = the trajectory's frame period. Given: frames at ``t0 + k / fps``
            up to the last frame, the root position interpolated linearly and every joint
            rotation by slerp between the neighbouring trajectory frames.
        puppet: the puppet the trajectory was simulated with (its joint tree and anchors).
            Default: the trajectory's ``puppet`` attribute if it has one, else the default
            marionette. Checked against the motion (body names, coinciding joint anchors).

    Returns:
        ``path``.

    Raises:
        ExportError: a trajectory without puppet motion, malformed or non-finite fields,
            uneven frame times without ``fps``, a bad ``fps``, or a puppet that does not
            match the trajectory.
    """
    path = Path(path)
    where = str(getattr(trajectory, "source", None) or "trajectory")
    motion = body_motion(trajectory, where)
    puppet = resolve_puppet(trajectory, puppet)
    check_puppet_matches(motion, puppet, where)
    frame_time, new_times = _frame_period(motion, fps, where)

    local = bvh_local_rotations(motion, puppet)
    root_pos = motion.body_pos[:, 0]
    if new_times is not None:
        root_pos, local = _resample(motion.frame_time, root_pos, local, new_times)
    lines, order = _hierarchy(puppet)
    frames, joints = local.shape[:2]

    euler = np.empty((frames, joints, 3))
    previous = None
    for f in range(frames):
        previous = euler[f] = matrix_to_euler_xzy(quat_to_matrix(local[f]), previous)
    columns = [root_pos] + [np.degrees(euler[:, b]) for b in order]
    table = np.concatenate(columns, axis=1)

    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {frame_time:.9f}"]
    lines += [_fmt(row) for row in table]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path
