"""``dmarionette sweep SCENE --set KEY=V1,V2,...``: a grid of scene variants, one summary row each.

Exit codes: 0 every variant ran and stayed finite; 1 some variant produced a non-finite value
(its row says when; the others are in the table); 2 bad input (a flag, the scene, a key or a
value), before any work; 3 a Ray worker died more often than the retries allow (the rows that
finished are kept; ``--resume`` runs the rest); 130 Ctrl-C (the finished rows are kept).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

from dmarionette.cli_checks import add_ray_flags, integer, number, optimization_level

__all__ = ["EXIT_NON_FINITE", "EXIT_WORKER_LOST", "add_sweep_command", "run_sweep_command"]

EXIT_NON_FINITE = 1
EXIT_WORKER_LOST = 3


def add_sweep_command(sub) -> None:
    """Adds ``sweep`` to the command line's subcommands (what ``add_subparsers`` returned)."""
    sweep = sub.add_parser(
        "sweep", help="simulate a grid of scene variants (--set KEY=V1,V2,...) and tabulate their summaries",
        description="Simulate every combination of the --set values on SCENE (the cartesian product), each "
                    "variant validated by the scene loader before any work; compatible variants run together as "
                    "the worlds of one model (--worlds-per-batch). Writes OUT/sweep.csv (a row per variant, "
                    "written as each batch finishes), OUT/sweep.md and OUT/sweep.png: torso height range, taut fraction per "
                    "string, peak feedback per bar, energy excess over the bars' work, real-time factor. "
                    "Exit codes: 0 done; 1 a variant went non-finite; 2 bad input; 3 a Ray worker died "
                    "more often than the retries allow (finished rows kept); 130 Ctrl-C. docs/sweep.md.")
    sweep.add_argument("scene", help="a built-in scene name (see 'dmarionette scenes') or a TOML file; a marionette")
    sweep.add_argument("--set", dest="sets", action="append", required=True, metavar="KEY=V1,V2,...",
                       help="a scene key and its values, e.g. strings.k=200,300,400 (every string's eq. 2 k), "
                            "strings.hand_left.k_d=2,4 (one string), strings.particle_count=10,20, "
                            "rates.puppet_hz=30,100, feedback.stiffness=5,10; k, k_d, k_s name tie_stiffness, "
                            "tie_damping, stiffness. Repeat for more keys (docs/sweep.md)")
    sweep.add_argument("--duration", type=number(0.0, low_open=True, unit="s"), default=None,
                       help="simulated seconds per variant (default: the scene's [scene] duration)")
    sweep.add_argument("--out", type=Path, default=None, help="output folder (default: out/sweep/<scene name>)")
    sweep.add_argument("--worlds-per-batch", type=integer(1, 100_000), default=None,
                       help="variants handed to a worker at a time, run as the worlds of one batched model in the "
                            f"same launches (default: the variants shared evenly by the workers, at most "
                            f"{AUTO_WORLDS_PER_BATCH} a batch); 1: one rollout per variant")
    add_ray_flags(sweep, "where the variants run")
    sweep.add_argument("--resume", action="store_true",
                       help="keep the rows of an earlier run's OUT/sweep.csv and run only the missing variants")
    sweep.add_argument("--no-picture", action="store_true", help="skip sweep.png")
    sweep.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    sweep.add_argument("--quiet", action="store_true", help="no progress bars or compile messages")
    sweep.set_defaults(handler=run_sweep_command)


AUTO_WORLDS_PER_BATCH = 64
"""The largest batch ``--worlds-per-batch`` picks by itself: past it a CPU core gains nothing more per
world (``benchmarks/bench_worlds.py``) and a killed run loses more work in flight."""


def worlds_per_batch(pending: int, mode: str, workers: int | None) -> int:
    """The default ``--worlds-per-batch``: the pending variants shared evenly by the workers (one in
    this process; on Ray ``--workers`` or the cluster's CPUs), at most :data:`AUTO_WORLDS_PER_BATCH`."""
    if mode == "off":
        count = 1
    else:
        import ray

        count = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    return max(1, min(AUTO_WORLDS_PER_BATCH, math.ceil(pending / count)))


def _rollout_bytes(scene, duration: float) -> float:
    """The memory [bytes] of one rollout's per-step outputs (tie forces, taut flags, feedback, reaction),
    kept twice while they are joined."""
    steps = duration * scene.string_hz + 1000
    s, b = len(scene.strings), max(len(scene.bars), 1)
    return float(2 * steps * (s * (24 + 4) + b * 48))


def _run_batch(batch: list, duration: float | None, optimization_level: int) -> list[tuple[int, dict]]:
    """A worker's unit of work: ``[(variant index, scene), ...]`` -> ``[(variant index, row), ...]``."""
    from dmarionette.sweep.run import run_variants

    rows = run_variants([scene for _, scene in batch], duration, optimization_level)
    return [(index, row) for (index, _), row in zip(batch, rows)]


def run_sweep_command(args: argparse.Namespace) -> int:
    """Runs ``dmarionette sweep`` (see the module doc for the exit codes)."""
    from dmarionette.cli_checks import check_trajectory_fits
    from dmarionette.scale.ray_map import connect_ray, ray_mode, shutdown_ray
    from dmarionette.sweep.grid import parse_set, sweep_variants
    from dmarionette.sweep.run import FRAME_HZ
    from dmarionette.sweep.table import read_rows, summary_columns

    mode = ray_mode(args.ray)
    axes = [parse_set(flag) for flag in args.sets]
    variants = sweep_variants(args.scene, axes)
    base = variants[0].scene
    for variant in variants:
        duration = variant.scene.duration if args.duration is None else args.duration
        check_trajectory_fits("--duration" if args.duration is not None else
                              f"{variant.scene.source}: [scene] duration (variant {variant.index})",
                              duration, _rollout_bytes(variant.scene, duration))
    out = args.outputs.folder("--out", args.out if args.out is not None else Path("out") / "sweep" / base.name)
    keys = [axis.key for axis in axes]
    summary = summary_columns([s.name for s in base.strings], [b.name for b in base.bars])
    table = out / "sweep.csv"
    done: dict[int, dict] = {}
    if args.resume and table.is_file():
        by_index = {v.index: v for v in variants}
        for row in read_rows(table, keys, summary):
            variant = by_index.get(row["variant"])
            if variant is None or any(row[k] != variant.settings[k] for k in keys):
                continue
            wanted = variant.scene.duration if args.duration is None else args.duration
            if abs(float(row["simulated_s"]) - wanted) > 1.0 / FRAME_HZ + variant.scene.string_dt:
                raise ValueError(f"--resume: {str(table)!r} has variant {variant.index} simulated for "
                                 f"{row['simulated_s']} s; this sweep asks for {wanted:g} s; run without --resume "
                                 "(the table is rewritten) or with the same --duration")
            done[variant.index] = row
    pending = [v for v in variants if v.index not in done]
    level = optimization_level(args)
    # Ray up (or the cluster reached) before any work: a wrong address is an error, not a half-written table.
    started = connect_ray(mode, args.workers) if mode != "off" and pending else False
    if started and getattr(args, "interrupt", None) is not None:
        # From here Ctrl-C raises KeyboardInterrupt and waits for the cluster's shutdown below (about a second),
        # rather than ending this process at once and leaving the cluster's processes behind.
        args.interrupt.disarm()
    try:
        return _sweep(args, variants, pending, done, keys, summary, table, mode, level)
    finally:
        if started:
            shutdown_ray()


def _sweep(args, variants, pending, done, keys, summary, table, mode, level) -> int:
    from tqdm import tqdm

    from dmarionette.first_run import build_marionette
    from dmarionette.scale.ray_map import WorkerLostError, imap_variants
    from dmarionette.sweep.run import kernel_key, warm_up
    from dmarionette.sweep.table import RowWriter, write_markdown

    out = table.parent
    base = variants[0].scene
    string_names = [s.name for s in base.strings]
    bar_names = [b.name for b in base.bars]
    if not args.quiet:
        where = "this process" if mode == "off" else ("a local Ray cluster" if mode == "local" else f"Ray at {mode}")
        per_batch = args.worlds_per_batch or worlds_per_batch(len(pending), mode, args.workers)
        print(f"sweep: {len(variants)} variants ({len(done)} already in {table}), up to {per_batch} worlds a "
              f"batch, in {where}", file=sys.stderr)
    # The kernels compile here under a progress bar, once per kind of variant (precision, effects), before the
    # first row; the rollouts (and Ray's workers) then load them from the cache.
    kinds = {kernel_key(v.scene, level): v.scene for v in [variants[0], *pending]}
    for scene in kinds.values():
        build_marionette(scene, optimization_level=level, quiet=args.quiet)
    writer = RowWriter(table, ["variant", *keys, *summary], append=bool(done))
    rows = list(done.values())
    per_batch = args.worlds_per_batch or worlds_per_batch(len(pending), mode, args.workers)
    batches = [[(v.index, v.scene) for v in pending[i:i + per_batch]] for i in range(0, len(pending), per_batch)]
    settings = {v.index: v.settings for v in variants}
    run = functools.partial(_run_batch, duration=args.duration, optimization_level=level)
    try:
        with tqdm(total=len(pending), unit="variant", desc="sweep", disable=args.quiet) as bar:
            for _, results in imap_variants(run, batches, ray=mode, workers=args.workers,
                                            setup=functools.partial(warm_up, base, level)):
                for index, result in results:
                    row = {"variant": index, **settings[index], **result}
                    writer.write(row)
                    rows.append(row)
                    bar.update(1)
    except WorkerLostError as error:
        print(f"error: {error}; {len(rows)} of {len(variants)} variants are in {table} (--resume runs the rest)",
              file=sys.stderr)
        return EXIT_WORKER_LOST
    finally:
        writer.close()
    scene_text = base.name if Path(args.scene).suffix == "" else str(args.scene)
    header = (f"# sweep of {scene_text}: {len(variants)} variant{'' if len(variants) == 1 else 's'}, "
              f"{'the scene duration' if args.duration is None else f'{args.duration:g} s'} per variant")
    files = {"table": str(table), "markdown": str(write_markdown(out / "sweep.md", rows, keys, summary, header))}
    if not args.no_picture:
        from dmarionette.sweep.plot import plot_sweep

        files["picture"] = str(plot_sweep(out / "sweep.png", rows, keys, string_names, bar_names, header[2:]))
    print(Path(files["markdown"]).read_text())
    print(json.dumps(files, indent=2))
    bad = sorted(int(r["variant"]) for r in rows if r["finite"] is not True)
    if bad:
        named = "; ".join(f"variant {i} ({', '.join(f'{k}={v}' for k, v in settings[i].items())}) at "
                          f"t = {float(next(r for r in rows if int(r['variant']) == i)['first_non_finite_s']):.6g} s"
                          for i in bad[:5])
        print(f"error: {len(bad)} of {len(variants)} variants produced a non-finite value: {named}; their rows "
              "are marked finite = false", file=sys.stderr)
        return EXIT_NON_FINITE
    return 0
