"""Imports an exported BVH and glTF into Blender (``bpy``) and compares the poses with the trajectory.

Not run by pytest (the ``bpy`` wheel is ~370 MB and pins its own numpy); run it by hand
with a Python that has ``bpy`` (``pip install bpy`` in a separate virtual environment)::

    python tests/support/blender_import_check.py out/hanging/trajectory.npz out/hanging/motion.bvh \
        out/hanging/motion.glb

It imports with Blender's defaults (BVH: scale 1, forward -Z, up Y; glTF: +Y up), so
Blender's world is the simulator's turned z up: ``(x, y, z) -> (x, -z, y)``. For every
frame it checks, per body, the BVH bone head (the joint centre) and the bone's rotation
relative to its rest pose, and the glTF object's world matrix (position and rotation of
the body), against the trajectory file read with numpy alone. Prints the largest errors;
exits 1 when one exceeds its tolerance (BVH 1e-5 m / 1e-5; glTF 1e-5 m / 1e-5: Blender
stores float32 and interpolates keyframes placed at t * fps).
"""

from __future__ import annotations

import json
import sys

import numpy as np

import bpy

TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _matrix(q):
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def _anchors(metadata, names):
    """Child anchors per body from the scene the trajectory names (tomllib, no dmarionette import)."""
    import tomllib
    from pathlib import Path

    source = Path(metadata["scene_source"])
    table = tomllib.loads(source.read_text())["puppet"]
    if "include" in table:
        base = tomllib.loads((source.parent / table["include"]).read_text())["puppet"]
        table = {**base, **{k: v for k, v in table.items() if k != "include"}}
    anchor = {names[0]: np.zeros(3)}
    for joint in table["joints"].values():
        anchor[joint["child"]] = np.asarray(joint["anchor_child"], dtype=np.float64)
    return anchor


def check_bvh(path, pos, rot, names, anchor):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=path, global_scale=1.0, frame_start=1, use_fps_scale=False,
                            update_scene_fps=False, update_scene_duration=True)
    arm = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    world = np.array(arm.matrix_world)
    rest = {b.name: np.array(b.matrix_local)[:3, :3] for b in arm.data.bones}
    perr = rerr = 0.0
    for f in range(len(pos)):
        bpy.context.scene.frame_set(1 + f)
        for b, name in enumerate(names):
            if name not in arm.pose.bones:
                continue
            m = world @ np.array(arm.pose.bones[name].matrix)
            head = TO_BLENDER @ (pos[f, b] + rot[f, b] @ anchor[name])
            turned = TO_BLENDER @ rot[f, b] @ TO_BLENDER.T
            perr = max(perr, np.abs(m[:3, 3] - head).max())
            rerr = max(rerr, np.abs(m[:3, :3] @ rest[name].T - turned).max())
    return perr, rerr


def check_gltf(path, times, pos, rot, names, particles):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=path)
    scene = bpy.context.scene
    fps = scene.render.fps / scene.render.fps_base
    lines = scene.objects.get("string_lines")
    perr = rerr = serr = 0.0
    for f, t in enumerate(times):
        frame = t * fps
        scene.frame_set(int(np.floor(frame)), subframe=float(frame - np.floor(frame)))
        for b, name in enumerate(names):
            m = np.array(scene.objects[name].matrix_world)
            perr = max(perr, np.abs(m[:3, 3] - TO_BLENDER @ pos[f, b]).max())
            rerr = max(rerr, np.abs(m[:3, :3] - TO_BLENDER @ rot[f, b] @ TO_BLENDER.T).max())
        if lines is not None and particles is not None:
            evaluated = lines.evaluated_get(bpy.context.evaluated_depsgraph_get())
            mesh = evaluated.to_mesh()
            world = np.array(evaluated.matrix_world)
            verts = np.array([world[:3, :3] @ np.array(v.co) + world[:3, 3] for v in mesh.vertices])
            evaluated.to_mesh_clear()
            serr = max(serr, np.abs(verts - particles[f] @ TO_BLENDER.T).max())
    return perr, rerr, serr


def main(argv):
    trajectory, bvh_path, glb_path = argv
    with np.load(trajectory) as data:
        metadata = json.loads(str(data["metadata"]))
        times, pos, quat = data["frame_time"], data["body_pos"], data["body_rot"]
        names = [str(n) for n in data["body_names"]]
        particles = data["particle_q"] if "particle_q" in data.files else None
    rot = _matrix(quat)
    report = {
        "blender": bpy.app.version_string,
        "bvh": check_bvh(bvh_path, pos, rot, names, _anchors(metadata, names)),
        "gltf": check_gltf(glb_path, times, pos, rot, names, particles),
    }
    print(json.dumps(report))
    ok = all(err <= 1e-5 for key in ("bvh", "gltf") for err in report[key])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
