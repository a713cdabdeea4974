"""Dumps what the string and marionette steps compute, to compare two versions of the code.

Usage::

    PYTHONPATH=<checkout> python tools/dump_step_results.py OUT.npz          # dump
    python tools/dump_step_results.py --compare A.npz B.npz                  # compare two dumps

The dump holds, as float64 arrays: a strings-only rollout of the ``strings`` scene (6 x 50,
tops swaying, then lowered until the bottoms lie on the ground: spring, friction, air, ground
contact and tie terms all act), the ``hanging`` marionette at the paper's rates (1 s) and fully
coupled at 1 kHz (0.2 s), the same with tension-only springs (0.5 s), and the gradients of a
short ``MarionetteGradient`` rollout (10 puppet steps, ones on every output). ``--compare``
prints, per array, whether the two are equal bit for bit (``np.array_equal``) and otherwise the
largest absolute and relative difference; it exits 0 when all are equal, 1 when any differs, 2
on a path that is not a readable dump. Written for issue 19 (a faster step must compute the
same numbers); ``docs/performance.md`` quotes its output.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np


def _strings() -> dict[str, np.ndarray]:
    from dmarionette.scene.scene import load_scene
    from dmarionette.strings.model import StringModel
    from dmarionette.strings.rollout import StringRollout
    from dmarionette.strings.solver import SolverStringImplicit

    scene = load_scene("strings")
    model = StringModel(scene.strings, effects=scene.effects, gravity=scene.gravity,
                        ground_height=scene.ground_height)
    dt, steps = 1e-3, 1500
    t = dt * np.arange(1, steps + 1)
    tops = np.array([s.top for s in model.specs])
    top_q = np.repeat(tops[None], steps, axis=0)
    top_q[:, :, 0] += 0.08 * np.sin(2 * np.pi * 1.5 * t)[:, None]
    top_q[:, :, 1] -= np.clip(t - 0.5, 0.0, None)[:, None] * 0.6  # lowered: the bottoms reach the ground
    rollout = StringRollout(SolverStringImplicit(model), dt, chunk_steps=50)
    state = model.state()
    result = rollout.run(state, top_q)
    assert np.min(result.frames[:, :, 1]) < scene.ground_height, "the strings did not reach the ground"
    return {"strings/frames": result.frames, "strings/frame_velocities": result.frame_velocities,
            "strings/tie_force": result.tie_force, "strings/taut": result.string_taut.astype(np.float64)}


def _marionette(tag: str, seconds: float, **changes) -> dict[str, np.ndarray]:
    import dmarionette as dm
    from dmarionette.marionette.solver import MarionetteModel, SolverMarionette

    scene = dm.load_scene("hanging")
    if "tension_only" in changes:
        scene = dataclasses.replace(scene, effects=dataclasses.replace(scene.effects, tension_only=True))
    if "puppet_hz" in changes:
        scene = dataclasses.replace(scene, puppet_hz=changes["puppet_hz"])
    model = MarionetteModel(scene)
    solver = SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    q, forces, feedback = [], [], []
    for k in range(round(seconds / model.puppet_dt)):
        control.set_bars(model, k * model.puppet_dt)
        solver.step(a, b, control)
        a, b = b, a
        q.append(a.puppet.joint_q.numpy().copy())
        forces.append(a.tie_force.numpy().copy())
        feedback.append(np.concatenate([a.bar_feedback.numpy(), a.bar_reaction.numpy()]))
    return {f"{tag}/joint_q": np.array(q), f"{tag}/tie_force": np.array(forces),
            f"{tag}/bar_feedback_reaction": np.array(feedback),
            f"{tag}/particle_q": a.strings.particle_q.numpy().copy()}


def _gradients() -> dict[str, np.ndarray]:
    import dmarionette as dm
    from dmarionette.grad.engine import MarionetteGradient
    from dmarionette.marionette.solver import MarionetteModel

    scene = dm.load_scene("hanging")
    model = MarionetteModel(scene, requires_grad=True)
    engine = MarionetteGradient(model, 10)
    inputs = engine.scene_inputs()
    outputs = engine.forward(inputs)
    grads = engine.backward({k: np.ones(s) for k, s in engine.output_shapes.items()})
    out = {f"grad_outputs/{f.name}": np.asarray(getattr(outputs, f.name), dtype=np.float64)
           for f in dataclasses.fields(outputs)}
    out.update({f"grad/{f.name}": np.asarray(getattr(grads, f.name), dtype=np.float64)
                for f in dataclasses.fields(grads) if getattr(grads, f.name) is not None})
    return out


def dump(path: str) -> None:
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    results = _strings()
    results |= _marionette("paper_rates", 1.0)
    results |= _marionette("coupled_1khz", 0.2, puppet_hz=1000.0)
    results |= _marionette("tension_only", 0.5, tension_only=True)
    results |= _gradients()
    np.savez(path, **results)
    print(f"{path}: {len(results)} arrays")


def compare(a_path: str, b_path: str) -> int:
    a, b = np.load(a_path), np.load(b_path)
    worst = 0.0
    for key in sorted(set(a.files) | set(b.files)):
        if key not in a.files or key not in b.files:
            print(f"{key}: only in {'A' if key in a.files else 'B'}")
            worst = np.inf
            continue
        x, y = a[key], b[key]
        if x.shape != y.shape:
            print(f"{key}: shapes {x.shape} and {y.shape}")
            worst = np.inf
            continue
        if np.array_equal(x, y):
            print(f"{key}: equal bit for bit")
            continue
        diff = np.max(np.abs(x - y))
        scale = max(np.max(np.abs(x)), 1e-300)
        worst = max(worst, diff / scale)
        print(f"{key}: max |diff| {diff:.3e} (relative to max |A| {diff / scale:.3e})")
    print("all equal bit for bit" if worst == 0.0 else f"largest relative difference {worst:.3e}")
    return 0 if worst == 0.0 else 1


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("paths", nargs="+", help="OUT.npz, or with --compare the two dumps A.npz B.npz")
    p.add_argument("--compare", action="store_true")
    args = p.parse_args()
    if args.compare:
        if len(args.paths) != 2:
            p.error(f"--compare takes two dumps; got {len(args.paths)} paths")
        for path in args.paths:
            try:
                np.load(path).close()
            except (OSError, ValueError) as e:
                print(f"error: {path}: not a readable .npz dump ({e})", file=sys.stderr)
                sys.exit(2)
        sys.exit(compare(*args.paths))
    if len(args.paths) != 1:
        p.error(f"a dump takes one output path; got {len(args.paths)}")
    out = Path(args.paths[0])
    if not out.parent.is_dir():
        print(f"error: {out}: its folder {out.parent} does not exist", file=sys.stderr)
        sys.exit(2)
    dump(str(out))


if __name__ == "__main__":
    main()
