"""Running the variants of a sweep (as the worlds of batched rollouts), each summarised into one row.

:func:`run_variants` is the one function that runs a list of variants (scenes) and returns their
rows. Its callers hand it a batch of ``--worlds-per-batch`` variants at a time (in this process or
on a Ray worker, :func:`dmarionette.scale.map_variants`); the variants of a batch that can share
one batched marionette run as its worlds, in the same launches (:func:`run_batch`).

A row (:func:`run_variant`) holds, for the rollout of ``duration`` seconds from the rest state:

- ``simulated_s``: simulated time [s] (whole picture frames, as ``dmarionette simulate`` rounds);
- ``torso_min_m``, ``torso_max_m``: the torso's (root body's) lowest and highest centre height [m]
  over the frames (about 30 Hz, the initial state included), as ``simulate``'s summary reads it;
- ``taut_<string>``: the fraction of string steps each string was taut;
- ``feedback_max_<bar>_N``: the largest eq. 4 feedback on each bar [N], every string step;
  ``reaction_max_<bar>_N``: the largest exact reaction (what ``live`` sends by default) [N];
- ``energy_excess_J``: the largest ``E(t) - E(0) - W_bars(t)`` over the frames after the start [J],
  with ``E`` the energy of the motion (:func:`dmarionette.marionette.energy.marionette_energy` less
  the contact and joint-limit penalties, as the hard-case tests check it) and ``W_bars`` the bars'
  work (:class:`dmarionette.marionette.energy.BarWorkMeter`); ``bar_work_J``: ``W_bars`` at the end.
  Positive means the simulation made energy;
- ``finite``: every particle, body and force finite at every frame and step (else the row's
  numbers are NaN from the first non-finite frame on and ``first_non_finite_s`` says when);
- ``real_time_factor``: simulated seconds per second of the captured rollout itself (the
  per-frame energy readings excluded, as ``simulate``'s), and ``wall_s``: the whole variant,
  model building and graph capture included [s].

The rollout is ``dmarionette.simulate_marionette``'s: the same :class:`MarionetteRollout` with
the same chunk (one ~30 Hz frame) and the same number of chunks, so its trajectory, and every
number above but the timings, is bit for bit the one ``simulate_marionette`` gives (tested).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from dmarionette.scene.scene import Scene

__all__ = ["FRAME_HZ", "kernel_key", "run_batch", "run_variant", "run_variants", "warm_up"]

FRAME_HZ = 30.0
"""Frames per second at which the torso and the energy are read (``simulate_marionette``'s default)."""

_MODULES_READY: set = set()  # (optimization level, precision, effects) whose kernels this process has loaded
_WARP_STARTED: list = []  # [True] once this process has started Warp here


def _init_process() -> None:
    """Warp started in this process as the command line starts it, once."""
    if _WARP_STARTED:
        return
    from dmarionette.scale.ray_map import init_worker_warp

    init_worker_warp()
    _WARP_STARTED.append(True)


def kernel_key(scene: Scene, optimization_level: int = 2) -> tuple:
    """What decides which Warp modules a rollout of ``scene`` runs (variants with equal keys share them):
    the optimisation level, the strings' precision, the effects compiled in, and the string steps per
    puppet step (the coupling kernels unroll them). Sizes and constants are not part of it (they are
    arrays and launch dimensions)."""
    substeps = max(1, round(scene.string_hz / scene.puppet_hz))  # as MarionetteModel counts them
    return (optimization_level, scene.precision, scene.effects, tuple(sorted(scene.body_effects.items())), substeps)


def warm_up(scene: Scene, optimization_level: int = 2) -> None:
    """Compiles (or loads from the cache) the kernels a rollout of ``scene`` runs, in this process.

    A Ray worker calls it once when it starts, so that its first variant does not pay for it; the
    loaded modules stay in the process for every later variant with the same kernels.
    """
    _init_process()
    from dmarionette.first_run import build_marionette

    key = kernel_key(scene, optimization_level)
    if key not in _MODULES_READY:
        build_marionette(scene, optimization_level=optimization_level, quiet=True)
        _MODULES_READY.add(key)


def run_variant(scene: Scene, duration: float, optimization_level: int = 2) -> dict:
    """One variant's row (see the module doc): :func:`run_batch` of that variant alone."""
    return run_batch([scene], duration, optimization_level)[0]


def run_batch(scenes: Sequence[Scene], duration: float, optimization_level: int = 2) -> list[dict]:
    """The rows of variants that can share one batched marionette (one world each, the same launches).

    Builds ``MarionetteModel.from_scenes(scenes)`` (the variants must agree in what the kernels
    share: :func:`dmarionette.marionette.solver.check_world_scenes`), rolls every world out together
    and summarises each world as :func:`run_variant` would alone (the worlds do not interact: each
    world's numbers are bit for bit its own run's, ``tests/marionette/test_worlds.py``).

    Args:
        scenes: the variants' validated scenes (marionettes).
        duration: simulated seconds [s] (> 0).
        optimization_level: Warp's optimisation level of the puppet kernels (0: ``--fast-compile``).

    Returns:
        One row per scene: column name -> number (``finite`` a bool). ``real_time_factor`` is the
        batch's: simulated seconds per second of its rollout (every world advances together), and
        ``wall_s`` the batch's wall time shared equally by its worlds.
    """
    from dmarionette.marionette.energy import install_bar_work_meter, marionette_energy
    from dmarionette.marionette.rollout import MarionetteRollout
    from dmarionette.marionette.solver import MarionetteModel, SolverMarionette

    start = time.perf_counter()
    warm_up(scenes[0], optimization_level)
    model = MarionetteModel.from_scenes(scenes, optimization_level=optimization_level)
    worlds, per_world = model.world_count, model.strings_per_world
    meter = install_bar_work_meter(model)  # before the solver and the capture: part of the graph
    chunk = max(1, round(1.0 / (FRAME_HZ * model.puppet_dt)))
    rollout = MarionetteRollout(SolverMarionette(model), chunk)
    frame_steps = chunk * model.substeps
    chunks = max(1, int(np.ceil(duration / (frame_steps * model.string_dt))))  # as simulate_marionette
    state = model.state()
    meter.reset()
    torso, motion, work, finite = ([[] for _ in range(worlds)] for _ in range(4))
    particles = model.strings.particle_count // worlds
    reading = [0.0]  # seconds spent reading frames (not the simulator's)

    def read(s) -> None:
        begin = time.perf_counter()
        q, qd = s.strings.particle_q.numpy(), s.strings.particle_qd.numpy()
        jq, jqd = s.puppet.joint_q.numpy(), s.puppet.joint_qd.numpy()
        for w in range(worlds):
            rows = slice(w * particles, (w + 1) * particles)
            ok = bool(np.all(np.isfinite(q[rows])) and np.all(np.isfinite(qd[rows]))
                      and np.all(np.isfinite(jq[w])) and np.all(np.isfinite(jqd[w])))
            if ok:
                energy = marionette_energy(model, s, w)  # fills the body poses from the joints on the way
                motion[w].append(energy["total"] - energy["puppet_contact"] - energy["puppet_limit"])
                torso[w].append(float(s.puppet.body_pos.numpy()[w][0, 1]))
            else:
                motion[w].append(math.nan)
                torso[w].append(math.nan)
            work[w].append(meter.total(range(w * per_world, (w + 1) * per_world)))
            finite[w].append(ok)
        reading[0] += time.perf_counter() - begin

    read(state)
    run_start = time.perf_counter()
    outputs = rollout.run(state, 0.0, chunks, on_chunk=lambda c, s: read(s))
    rollout_s = time.perf_counter() - run_start - reading[0]
    steps = chunks * frame_steps
    simulated = steps * model.string_dt
    wall = time.perf_counter() - start
    rows = []
    for w in range(worlds):
        ss, bb = slice(w * per_world, (w + 1) * per_world), slice(w * model.bar_rows, (w + 1) * model.bar_rows)
        own = {name: value[:, bb if name.startswith("bar_") else ss] for name, value in outputs.items()}
        rows.append(_summary(model, own, simulated, frame_steps, torso[w], motion[w], work[w], finite[w]))
        rows[-1]["real_time_factor"] = simulated / rollout_s if rollout_s > 0.0 else math.nan
        rows[-1]["wall_s"] = wall / worlds
    return rows


def _summary(model, outputs: dict, simulated: float, frame_steps: int, torso: list, motion: list, work: list,
             finite: list) -> dict:
    """One world's row from its per-step outputs and per-frame readings (the module doc's columns)."""
    outputs_finite = all(bool(np.all(np.isfinite(v))) for v in outputs.values())
    all_finite = all(finite) and outputs_finite
    motion_a, work_a = np.asarray(motion), np.asarray(work)
    excess = motion_a - motion_a[0] - work_a
    row: dict = {"simulated_s": simulated}
    torso_a = np.asarray(torso)
    row["torso_min_m"] = float(np.min(torso_a)) if all_finite else math.nan
    row["torso_max_m"] = float(np.max(torso_a)) if all_finite else math.nan
    for s, spec in enumerate(model.scene.strings):
        row[f"taut_{spec.name}"] = float(outputs["string_taut"][:, s].mean())
    for b, name in enumerate(model.bar_names):
        row[f"feedback_max_{name}_N"] = float(np.linalg.norm(outputs["bar_feedback"][:, b], axis=1).max())
        row[f"reaction_max_{name}_N"] = float(np.linalg.norm(outputs["bar_reaction"][:, b], axis=1).max())
    row["energy_excess_J"] = float(np.max(excess[1:])) if all_finite else math.nan
    row["bar_work_J"] = float(work_a[-1]) if all_finite else math.nan
    row["finite"] = all_finite
    row["first_non_finite_s"] = math.nan
    if not all_finite:
        bad = [i for i, ok in enumerate(finite) if not ok]
        row["first_non_finite_s"] = bad[0] * frame_steps * model.string_dt if bad else simulated
        for key in [k for k in row if k.startswith(("taut_", "feedback_max_", "reaction_max_"))]:
            row[key] = math.nan
    return row


def run_variants(scenes: Sequence[Scene], duration: float | None, optimization_level: int = 2) -> list[dict]:
    """The rows of several variants (the unit of work a sweep hands a worker: one batch).

    Consecutive variants that can share a batched marionette (the same kernels and sizes:
    :func:`~dmarionette.marionette.solver.check_world_scenes`, and the same duration) run as the
    worlds of one model (:func:`run_batch`); a variant alone runs as :func:`run_variant`.

    Args:
        scenes: the variants' validated scenes.
        duration: simulated seconds of every rollout [s]; None: each scene's ``[scene] duration``.
        optimization_level: Warp's optimisation level of the puppet kernels.

    Returns:
        One row per scene, in order.
    """
    from dmarionette.marionette.solver import check_world_scenes

    groups: list[list[Scene]] = []
    for scene in scenes:
        if groups:
            first = groups[-1][0]
            try:
                check_world_scenes([first, scene])
                same = first.duration == scene.duration or duration is not None
            except ValueError:
                same = False
            if same:
                groups[-1].append(scene)
                continue
        groups.append([scene])
    rows = []
    for group in groups:
        seconds = group[0].duration if duration is None else duration
        rows += [run_variant(group[0], seconds, optimization_level)] if len(group) == 1 else \
            run_batch(group, seconds, optimization_level)
    return rows
