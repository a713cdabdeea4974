"""Keyframe authoring end to end: keyframes file -> optimised bar motion -> scene, exports, plots.

:func:`build_problem` builds the marionette, the checkpointed gradient engine, the JAX
rollout and the objective; :func:`author` solves it and writes everything
``dmarionette author`` promises (``docs/authoring.md``):

- ``authored_scene.toml``: the scene with the optimised bars as ``[[bars.NAME.keyframes]]``
  (``dmarionette simulate`` / ``live`` take it); ``initial_scene.toml``: the same with the
  initial knots;
- ``trajectory.npz``: the replay of the authored scene by the simulator (what
  ``simulate`` writes), and its gap to the optimiser's own rollout;
- ``motion.bvh`` and ``motion.glb`` (binary glTF): the puppet motion (``dmarionette.io.export.bvh`` /
  ``export_gltf``);
- ``animation_before.gif`` / ``animation_after.gif``; ``convergence.png``;
- ``summary.json``: per-keyframe errors before and after, the solver's history, timings.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from dmarionette.scene.bars import BarTrajectory
from dmarionette.render.pyplot import headless_pyplot
from dmarionette.scene.scene import SCENE_DIR

from .keyframes import AuthorSpec
from .author_problem import AuthoringProblem, build_problem
from .solve import SolveResult, solve

__all__ = ["AuthoringProblem", "author", "authored_scene_table", "build_problem", "enable_compilation_cache",
           "write_scene"]


def enable_compilation_cache(folder: str | Path | None = None) -> Path | None:
    """Keeps JAX's compiled functions (the spline, the smoothness Jacobian, the loss terms) on
    disk, as Warp keeps its kernels: a second ``dmarionette author`` skips their compilation
    (several seconds on one core). ``folder``: default ``$JAX_COMPILATION_CACHE_DIR``, else
    ``~/.cache/dmarionette/jax``. Returns the folder, or None when it cannot be created (the
    cache is only an optimisation: the command then compiles every time)."""
    import os

    folder = Path(folder or os.environ.get("JAX_COMPILATION_CACHE_DIR") or Path.home() / ".cache" / "dmarionette"
                  / "jax")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder


# --------------------------------------------------------------------- scene files
def authored_scene_table(spec: AuthorSpec, trajectories: dict[str, BarTrajectory], *, name: str,
                         description: str) -> dict:
    """The keyframes file's scene table with the authored bars' knots as their keyframes.

    Relative file references (a user's ``[puppet] include``, ``trajectory_file``) are made
    absolute so the table can be written anywhere; the built-in puppet keeps its name.
    """
    table = copy.deepcopy(dict(spec.scene_table))
    folder = Path(spec.scene.source).parent
    head = table.setdefault("scene", {})
    head["name"] = name
    head["description"] = description
    head["duration"] = float(spec.duration)
    puppet = table.get("puppet", {})
    if isinstance(puppet, dict) and "include" in puppet:
        path = folder / puppet["include"]
        if path.is_file() and path.resolve() != (SCENE_DIR / puppet["include"]).resolve():
            puppet["include"] = str(path.resolve())  # a puppet file of the user's, next to the scene
        # else: the built-in puppet file, which a scene anywhere finds by its name
    for bar_name, bar in table.get("bars", {}).items():
        if "trajectory_file" in bar and not Path(bar["trajectory_file"]).is_absolute():
            bar["trajectory_file"] = str((folder / bar["trajectory_file"]).resolve())
        if bar_name in trajectories:
            tr = trajectories[bar_name]
            for key in ("trajectory_file", "position", "rotation"):
                bar.pop(key, None)
            bar["keyframes"] = [{"t": float(t), "position": [float(v) for v in p], "rotation": [float(v) for v in r]}
                                for t, p, r in zip(tr.times, tr.positions, tr.rotations)]
    return table


def write_scene(path: Path, table: dict, header: str) -> Path:
    """Writes a scene table as TOML (floats as shortest round-trip decimals: exact on reload)."""
    import tomli_w

    path.parent.mkdir(parents=True, exist_ok=True)
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    path.write_text(comment + tomli_w.dumps(table))
    return path


# --------------------------------------------------------------------- the command
def _plain(outputs: dict) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in outputs.items()}


def _simulate_scene(path: Path, duration: float, optimization_level: int):
    from dmarionette.marionette.solver import MarionetteModel
    from dmarionette.marionette.rollout import simulate_marionette
    from dmarionette.scene.scene import load_scene

    scene = load_scene(path)
    model = MarionetteModel(scene, optimization_level=optimization_level)
    return scene, simulate_marionette(model, duration, progress=False)


def replay_gap(problem: AuthoringProblem, trajectory, outputs: dict) -> dict:
    """Largest gaps between the simulator's replay and the optimiser's rollout, on common frames."""
    frame_puppet_steps = trajectory.frame_steps // problem.model.substeps
    frames = min(len(trajectory.frame_time), problem.puppet_steps // frame_puppet_steps + 1)
    rows = np.arange(frames) * frame_puppet_steps
    joint = np.abs(trajectory.joint_q[:frames] - outputs["joint_q"][rows]).max()
    body = np.abs(trajectory.body_pos[:frames] - outputs["body_pos"][rows]).max()
    steps = min(len(trajectory.step_time), problem.puppet_steps * problem.model.substeps)
    reaction = np.abs(trajectory.bar_reaction[:steps] - outputs["bar_reaction"][:steps]).max()
    return {"frames_compared": int(frames), "joint_q_max_abs": float(joint), "body_pos_max_abs_m": float(body),
            "bar_reaction_max_abs_N": float(reaction)}


def _plain_verdicts(spec: AuthorSpec, report: list[dict], stopped: str) -> list[dict]:
    """Per keyframe (``bfgs``, ``lm``, ``gauss_newton``): reached within the tolerances, else not converged."""
    verdicts = []
    for k, entry in enumerate(report):
        errors = {**entry["points_m"], **{f"{n} (body)": v for n, v in entry["bodies_m"].items()},
                  **{n: max(abs(a) for a in v) for n, v in entry["joints_deg"].items()},
                  **{f"{n} (orientation)": v for n, v in entry["orientations_deg"].items()}}
        joints = set(entry["joints_deg"]) | {f"{n} (orientation)" for n in entry["orientations_deg"]}
        missed = {n: v for n, v in errors.items()
                  if v > (spec.angle_tolerance if n in joints else spec.position_tolerance)}
        reasons = [f"{n}: {v:.3g} {'deg' if n in joints else 'm'} from the target; the solver {stopped}"
                   for n, v in missed.items()]
        verdicts.append({"index": k, "t": entry["t"], "status": "not_converged" if missed else "reached",
                         "errors": errors, "best": {}, "reasons": reasons,
                         "units": {n: "deg" if n in joints else "m" for n in errors}})
    return verdicts


def _convergence_plot(path: Path, history: list[dict], title: str) -> Path:
    plt = headless_pyplot()

    steps = [h["step"] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    losses = [h["loss"] for h in history]
    a.semilogy(steps, losses, "k-", label="loss")
    bottom = min(v for v in losses if v > 0) * 1e-3  # terms far below the loss are not shown
    for term in history[0]["terms"]:
        values = [h["terms"][term] if h["terms"][term] > bottom else np.nan for h in history]
        if not all(np.isnan(values)):
            a.semilogy(steps, values, "--", label=term)
    a.set_ylim(bottom=bottom)
    a.set_xlabel("solver step")
    a.set_ylabel("loss (0.5 sum r^2)")
    a.legend(fontsize=8)
    grads = [h["grad_norm"] for h in history]
    if all(math.isfinite(g) and g > 0 for g in grads):
        b.semilogy(steps, grads, "b-")
        b.set_ylabel("|gradient| (last accepted point)")
    else:
        b.plot(steps, [h.get("forward", 0) for h in history], "b-")
        b.set_ylabel("forward rollouts")
    b.set_xlabel("solver step")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _export(trajectory, scene, out: Path) -> dict:
    """BVH and glTF files of the puppet motion, where the exporters are installed."""
    files = {}
    try:
        from dmarionette.io.export.bvh import export_bvh
    except ImportError:
        files["bvh"] = "not written: dmarionette.io.export.bvh is not available"
    else:
        files["bvh"] = str(export_bvh(trajectory, out / "motion.bvh", puppet=scene.puppet))
    try:
        from dmarionette.io.export.gltf import export_gltf
    except ImportError:
        files["gltf"] = "not written: dmarionette.io.export.gltf is not available"
    else:
        files["gltf"] = str(export_gltf(trajectory, out / "motion.glb"))
    return files


def author(spec: AuthorSpec, out: str | Path, *, max_steps: int | None = None, method: str | None = None,
           max_seconds: float | None = None, continuation: bool | None = None, jacobian: str | None = None,
           progress: bool = True, animation: bool = True, exports: bool = True, optimization_level: int = 2,
           checkpoint_steps: int | None = None, fps: float = 15.0, warm_start: str | None = None) -> dict:
    """Solves ``spec`` and writes its outputs to ``out``; returns the summary (also ``summary.json``).

    ``method``, ``max_steps``, ``max_seconds``, ``continuation``, ``jacobian`` and ``warm_start``
    override the file's ``[solver]``. The summary's ``status`` is ``"reached"``, ``"not_converged"``,
    ``"unreachable"`` or ``"limit_exceeded"`` and ``exit_code`` the command's exit code for it
    (:data:`fitting.author_solve.EXIT_CODES`); ``verdicts`` says, per keyframe, why.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    say = (lambda line: print(line, file=sys.stderr, flush=True)) if progress else (lambda line: None)
    started = time.perf_counter()
    say(f"building the marionette for {spec.scene.name} (the first run compiles the kernels)")
    problem = build_problem(spec, optimization_level=optimization_level, checkpoint_steps=checkpoint_steps)
    objective, param = problem.objective, problem.param
    built = time.perf_counter()
    y0 = param.initial()
    before = problem.forward(y0)
    method = method or spec.method
    max_steps = max_steps or spec.max_steps
    max_seconds = max_seconds if max_seconds is not None else spec.max_seconds
    say(f"solving with {method}: {sum(int(np.size(v)) for v in y0.values())} knot coordinates, "
        f"{problem.puppet_steps} puppet steps of {problem.model.puppet_dt:.6g} s")
    if method == "lm_fd":
        from .author_solve import solve_keyframes

        outcome = solve_keyframes(problem, max_steps=max_steps, max_seconds=max_seconds,
                                  continuation=spec.continuation if continuation is None else continuation,
                                  position_tolerance=spec.position_tolerance, angle_tolerance=spec.angle_tolerance,
                                  say=say, secant=(jacobian or spec.jacobian) == "secant",
                                  warm_start=warm_start or spec.warm_start)
        y_final = {k: jnp.asarray(v) for k, v in outcome.y.items()}
        history, solve_seconds, solver_result = outcome.history, outcome.seconds, "; ".join(outcome.lm_status)
        verdicts = [dataclasses.asdict(v) for v in outcome.verdicts]
        messages = list(outcome.messages)
        warm = outcome.warm_start
    else:
        result: SolveResult = solve(objective, y0, method=method, max_steps=max_steps, rtol=spec.rtol,
                                    atol=spec.atol, progress=progress, counter=problem.counter,
                                    y_scale=param.y_scale(), max_seconds=max_seconds)
        y_final, history, solve_seconds, solver_result = result.y, result.history, result.seconds, result.result
        verdicts = _plain_verdicts(spec, objective.keyframe_report(problem.forward(y_final)),
                                   "met its termination test there" if result.converged
                                   else "ran out of steps or time")
        messages = []
        warm = None
    after = problem.forward(y_final)
    loss_before, terms_before = objective.loss_terms_of(y0, before)
    loss_after, terms_after = objective.loss_terms_of(y_final, after)
    limits_after = objective.limits_report(y_final, after)
    over = [f"{name}: {entry['max_outside_workspace_m'] * 1000:.3g} mm outside the device workspace"
            for name, entry in limits_after.items() if entry.get("max_outside_workspace_m", 0.0) > 0.0]
    over += [f"{name}: device force {entry['max_device_force_N']:.3g} N above the {entry['max_force_N']:g} N limit"
             for name, entry in limits_after.items() if entry["max_device_force_N"] > entry.get("max_force_N", np.inf)]
    messages += [line for line in over if line not in messages]
    statuses = [v["status"] for v in verdicts]
    status = ("not_converged" if "not_converged" in statuses else "unreachable" if "unreachable" in statuses
              else "limit_exceeded" if over else "reached")
    from .author_solve import EXIT_CODES

    stem = Path(spec.source).stem
    files = {}
    initial_path = write_scene(out / "initial_scene.toml", authored_scene_table(
        spec, param.trajectories(y0), name=f"{stem}_initial", description=f"{stem}: initial bar knots"),
        f"Initial bar knots of the keyframes file {spec.source} (dmarionette author).")
    authored_path = write_scene(out / "authored_scene.toml", authored_scene_table(
        spec, param.trajectories(y_final), name=f"{stem}_authored",
        description=f"{stem}: bars authored from keyframes"),
        f"Bars authored from the keyframes file {spec.source} by dmarionette author.\n"
        "Replay: dmarionette simulate authored_scene.toml")
    files["authored_scene"], files["initial_scene"] = str(authored_path), str(initial_path)
    say("replaying the authored scene with the simulator")
    scene, trajectory = _simulate_scene(authored_path, spec.duration, optimization_level)
    gap = replay_gap(problem, trajectory, after)
    from dmarionette.io.trajectory import write_marionette_trajectory

    files["trajectory"] = str(write_marionette_trajectory(out / "trajectory.npz", trajectory, scene))
    if exports:
        files.update(_export(trajectory, scene, out))
    files["convergence"] = str(_convergence_plot(out / "convergence.png", history,
                                                 f"{stem}: {method}, {len(history) - 1} steps"))
    if animation:
        from dmarionette.render.marionette import render_marionette_animation

        _, before_trajectory = _simulate_scene(initial_path, spec.duration, optimization_level)
        every = max(1, round(1.0 / (fps * (trajectory.frame_time[1] - trajectory.frame_time[0]))))
        for label, traj in (("before", before_trajectory), ("after", trajectory)):
            path, _ = render_marionette_animation(out / f"animation_{label}.gif", traj,
                                                  title=f"{stem}: {label} optimisation",
                                                  ground_height=scene.ground_height, chair=scene.chair,
                                                  every=every)
            files[f"animation_{label}"] = str(path)
    limits = objective.limits
    summary = {
        "keyframes_file": spec.source, "scene": spec.scene.name, "duration_s": spec.duration,
        "puppet_steps": problem.puppet_steps, "puppet_dt_s": problem.model.puppet_dt,
        "string_dt_s": problem.model.string_dt, "method": method,
        "device": None if limits is None else {**{k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                                  for k, v in limits.items()},
                                               "workspace_scale": spec.workspace_scale,
                                               "force_scale": spec.force_scale, "feedback": spec.feedback},
        "weights": dataclasses.asdict(spec.weights),
        "status": status, "exit_code": EXIT_CODES[status], "converged": status == "reached",
        "verdicts": verdicts, "messages": messages,
        "tolerances": {"position_m": spec.position_tolerance, "angle_deg": spec.angle_tolerance},
        "solver_result": solver_result, "steps": len(history) - 1, "loss_before": float(loss_before),
        "loss_after": float(loss_after), "terms_before": {k: float(v) for k, v in terms_before.items()},
        "terms_after": {k: float(v) for k, v in terms_after.items()},
        "keyframes_before": objective.keyframe_report(before), "keyframes_after": objective.keyframe_report(after),
        "limits_before": objective.limits_report(y0, before), "limits_after": limits_after,
        "replay_gap": gap, "rollouts": dict(problem.counts),
        "seconds": {"build": built - started, "solve": solve_seconds, "total": time.perf_counter() - started},
        "knots": {name: {"t": tr.times.tolist(), "position": tr.positions.tolist(), "rotation": tr.rotations.tolist()}
                  for name, tr in param.trajectories(y_final).items()},
        "warm_start": {"kind": (warm_start or spec.warm_start) if method == "lm_fd" else None, **(warm or {})},
        "history": history, "files": files,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
