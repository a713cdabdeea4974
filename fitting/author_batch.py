"""``dmarionette author a.toml b.toml ...``: several keyframes files, one authoring job each
(docs/authoring.md, "Several files").

Every file is loaded and checked, and every output folder (``OUT/<file name>``, default
``out/<file name>``) proven writable, before any job starts. The jobs then run on Ray workers
(``--ray local`` or a cluster address; :func:`dmarionette.scale.imap_variants`: warm workers, a dead
worker restarted and its job retried) or one after another in this process (``--ray off``). A job
runs :func:`fitting.author.author` with the file's options and writes the job's folder where it
runs, as it finishes, so a killed run loses only the jobs in flight. A worker on a cluster node
that does not see the folder (no shared file system) writes into a temporary folder and hands its
files back; this process then writes them to the job's folder (``summary.json``'s ``files`` name
it; ``trajectory.npz``'s ``scene_source`` keeps the temporary folder's name).

At the end a table (file, verdict, worst keyframe errors, exit code, folder) and the same as JSON;
the command's exit code is the worst job's (:data:`SEVERITY`). A job whose file turns out bad only
while it runs (an error) is a row with exit code 2; the others go on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["EXIT_WORKER_LOST", "SEVERITY", "AuthorJob", "run_author_batch", "run_author_job", "worst_exit_code",
           "worst_keyframe_errors"]

#: Exit codes from best to worst: every keyframe reached (0); some unreachable, shown so (4); not
#: converged, a keyframe missed that was not shown unreachable (3); a device limit exceeded (5); an
#: error (2). The batch exits with the worst of its jobs'.
SEVERITY = (0, 4, 3, 5, 2)
#: A Ray worker died more often than the retries allow (the finished jobs' folders are kept).
EXIT_WORKER_LOST = 6


@dataclasses.dataclass(frozen=True)
class AuthorJob:
    """One keyframes file's authoring: its validated spec, its output folder (absolute, created by the
    command) and :func:`fitting.author.author`'s options."""

    spec: Any
    out: str
    options: dict


def worst_exit_code(codes: list[int]) -> int:
    """The worst of ``codes`` by :data:`SEVERITY` (0 for none)."""
    return max(codes, key=SEVERITY.index, default=0)


def start_author_worker() -> None:
    """A worker's setup: Warp started quietly, JAX's compilation cache on (as the command has them)."""
    from dmarionette.scale.ray_map import init_worker_warp

    from .author import enable_compilation_cache

    init_worker_warp()
    enable_compilation_cache()


def run_author_job(job: AuthorJob) -> dict:
    """Authors one file (where a worker runs): into its output folder when that folder is there (this
    machine, or a cluster node sharing the file system), else into a temporary folder whose files come back.

    Returns:
        ``{"summary": ...}`` (written in place), ``{"summary": ..., "folder": the temporary folder, "files":
        {relative path: bytes}}``, or ``{"error": message}`` for a bad input found while it ran
        (``ValueError``, ``RuntimeError``).
    """
    from .author import author

    try:
        if Path(job.out).is_dir():
            return {"summary": author(job.spec, job.out, progress=False, **job.options)}
        with tempfile.TemporaryDirectory(prefix="dmarionette-author-") as folder:
            summary = author(job.spec, folder, progress=False, **job.options)
            root = Path(folder)
            files = {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
    except (ValueError, RuntimeError) as error:
        return {"error": str(error)}
    return {"summary": summary, "folder": folder, "files": files}


def _write_job(result: dict, out: Path) -> dict:
    """Writes the files of a job that ran away from ``out`` there; its summary's ``files`` then name ``out``
    (also in summary.json; trajectory.npz's ``scene_source`` still names the folder where it ran)."""
    for name, data in result["files"].items():
        path = out / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    summary, folder = result["summary"], result["folder"]
    summary["files"] = {k: str(out / Path(v).relative_to(folder)) if v.startswith(folder + "/") else v
                        for k, v in summary["files"].items()}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def worst_keyframe_errors(summary: dict) -> dict[str, float]:
    """An authoring summary's largest keyframe errors after the solve: position [m], angle [deg]."""
    after = summary["keyframes_after"]
    return {"max_keyframe_error_m": max(e["max_position_error_m"] for e in after),
            "max_keyframe_error_deg": max(max(e["max_joint_error_deg"], e["max_orientation_error_deg"]) for e in after)}


def _row(path: Path, out: Path, result: dict) -> dict:
    if "error" in result:
        return {"file": str(path), "folder": str(out), "status": "error", "exit_code": 2, "error": result["error"],
                "max_keyframe_error_m": None, "max_keyframe_error_deg": None}
    summary = result["summary"]
    return {"file": str(path), "folder": str(out), "status": summary["status"], "exit_code": summary["exit_code"],
            **worst_keyframe_errors(summary)}


def _table(rows: list[dict]) -> str:
    lines = ["| file | verdict | worst position error [mm] | worst angle error [deg] | exit code | folder |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        error_m, error_deg = r["max_keyframe_error_m"], r["max_keyframe_error_deg"]
        lines.append(f"| {r['file']} | {r['status']} | {'-' if error_m is None else f'{error_m * 1000:.3g}'} | "
                     f"{'-' if error_deg is None else f'{error_deg:.3g}'} | {r['exit_code']} | {r['folder']} |")
    return "\n".join(lines)


def run_author_batch(args: argparse.Namespace, mode: str, verdict_text: Callable[[dict], str]) -> int:
    """Runs ``dmarionette author`` on several files (``args.keyframes``) in ``mode`` (module doc);
    ``verdict_text(summary)``: a finished job's verdict lines (printed as it finishes)."""
    from dmarionette.cli_checks import optimization_level
    from dmarionette.scale import WorkerLostError, imap_variants

    from .keyframes import load_keyframes

    paths = [Path(p).resolve() for p in args.keyframes]  # a worker may run in another folder
    specs = [load_keyframes(p) for p in paths]  # every file checked before any job
    base = args.out if args.out is not None else Path("out")
    seen: dict[str, Path] = {}
    for given, path in zip(args.keyframes, paths):
        if path.stem in seen:
            raise ValueError(f"keyframes: {str(seen[path.stem])!r} and {str(given)!r} would both write "
                             f"{str(base / path.stem)!r}; expected files with different names")
        seen[path.stem] = Path(given)
    folders = [args.outputs.folder("--out", base / p.stem) for p in paths]
    options = {"max_steps": args.max_steps, "method": args.method, "max_seconds": args.max_seconds,
               "continuation": args.continuation, "jacobian": args.jacobian, "warm_start": args.warm_start,
               "animation": not args.no_animation,
               "exports": not args.no_export, "optimization_level": optimization_level(args),
               "checkpoint_steps": args.checkpoint_steps, "fps": args.fps}
    jobs = [AuthorJob(spec, str(folder.resolve()), options) for spec, folder in zip(specs, folders)]
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if not args.quiet else (lambda text: None)
    where = "this process" if mode == "off" else ("a local Ray cluster" if mode == "local" else f"Ray at {mode}")
    say(f"author: {len(jobs)} keyframes files, one job each, in {where}")
    rows: dict[int, dict] = {}
    lost = None
    try:
        for index, result in imap_variants(run_author_job, jobs, ray=mode, workers=args.workers,
                                           setup=start_author_worker):
            if "files" in result:
                result = {**result, "summary": _write_job(result, folders[index])}
            rows[index] = _row(args.keyframes[index], folders[index], result)
            say(f"[{len(rows)}/{len(jobs)}] {args.keyframes[index]}: {rows[index]['status']}, exit code "
                f"{rows[index]['exit_code']} -> {folders[index]}")
            say(f"error: {result['error']}" if "error" in result else verdict_text(result["summary"]))
    except WorkerLostError as error:
        lost = error
    ordered = [rows[i] for i in sorted(rows)]
    print(_table(ordered))
    code = worst_exit_code([r["exit_code"] for r in ordered])
    if lost is not None:
        missing = [str(args.keyframes[i]) for i in range(len(jobs)) if i not in rows]
        print(f"error: {lost}; not authored: {', '.join(missing)}", file=sys.stderr)
        code = EXIT_WORKER_LOST
    print(json.dumps({"jobs": ordered, "exit_code": code}, indent=2))
    return code
