"""Authoring on keyframes drawn like a user's: reachable targets from random reference motions.

Run:  python benchmarks/bench_author_drawn.py [--variant small|free] [--seeds 1-13] [--fast-compile]

The README's three-poses example (``examples/example_author_keyframes.py``: 1.5 s of ``hanging``,
hands out at 0.495 s, the left hand raised and its elbow bent at 0.99 s, head and torso placed at
1.485 s) with its targets recorded from a *random* reference bar motion inside the Omni's workspace
(seeded), so every target is reachable by construction; the solve starts from the scene's still
bars, as ``dmarionette author`` does.

- ``small``: the example's own freedom (hand bar x, y, z; main bar height; 10 particles per string);
  the reference's knot offsets uniform in +-6 x (-4, +5) x +-2.5 cm (hand) and +-3 cm (main).
- ``free``: both bars x, y, z, 25 particles per string; offsets +-7 x +-5 x +-3 cm (hand) and
  +-5 x +-4 x +-2 cm (main).

Printed per seed: the status (``reached`` or not), the solve's steps, the seconds of the whole
authoring (build, solve, replay), whether a restart's result was kept (docs/authoring.md, "When the
solve misses") and the worst keyframe errors; then how many seeds reached every target.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
VARIANTS = {
    "small": {"hand": ([-0.06, -0.04, -0.025], [0.06, 0.05, 0.025]), "main": ([-0.03], [0.03]),
              "particles": 10, "main_free": ["y"]},
    "free": {"hand": ([-0.07, -0.05, -0.03], [0.07, 0.05, 0.03]), "main": ([-0.05, -0.04, -0.02], [0.05, 0.04, 0.02]),
             "particles": 25, "main_free": ["x", "y", "z"]},
}


def _example():
    """``examples/example_author_keyframes.py`` as a module (its reference, table and target recorder)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("example_author_keyframes",
                                                  ROOT / "examples" / "example_author_keyframes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def one(variant: str, seed: int, folder: Path, level: int) -> dict:
    """Records the targets of seed ``seed``'s reference and authors them; returns the row."""
    import tomli_w

    from fitting import author, build_problem, keyframes_from_table, load_keyframes

    ex, v = _example(), VARIANTS[variant]
    rng = np.random.default_rng(seed)
    reference = {"hand": rng.uniform(*v["hand"], size=(3, 3)).round(3).tolist(),
                 "main": rng.uniform(*v["main"], size=(2, len(v["main"][0]))).round(3).tolist()}

    def table(targets=None):
        t = ex.keyframes_table(targets)
        t["author"]["particle_count"] = v["particles"]
        t["bars"]["main"]["free"] = list(v["main_free"])
        return t

    saved, ex.REFERENCE = ex.REFERENCE, reference
    try:
        placeholder = keyframes_from_table(table(), str(folder / "keyframes.toml"))
        targets = ex.reference_targets(build_problem(placeholder, optimization_level=level))
    finally:
        ex.REFERENCE = saved
    path = folder / "keyframes.toml"
    path.write_text(tomli_w.dumps(table(targets)))
    start = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        summary = author(load_keyframes(path), folder / "out", progress=False, animation=False, exports=False,
                         optimization_level=level)
    after = summary["keyframes_after"]
    return {"seed": seed, "status": summary["status"], "steps": summary["steps"],
            "seconds": round(time.perf_counter() - start, 1),
            "restart_kept": bool((summary.get("warm_start") or {}).get("restart_kept")),
            "mm": round(1e3 * max(e["max_position_error_m"] for e in after), 3),
            "deg": round(max(e["max_joint_error_deg"] for e in after), 3)}


def _seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", choices=sorted(VARIANTS), default="small")
    parser.add_argument("--seeds", default="1-13", help="a seed or a range FIRST-LAST (default 1-13)")
    parser.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    args = parser.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    level = 0 if args.fast_compile else 2
    rows = []
    for seed in _seeds(args.seeds):
        with tempfile.TemporaryDirectory() as folder:
            rows.append(one(args.variant, seed, Path(folder), level))
        print(rows[-1], file=sys.stderr, flush=True)
    print(f"| seed ({args.variant}) | status | steps | s | restart kept | worst mm | worst deg |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {r['status']} | {r['steps']} | {r['seconds']} | {r['restart_kept']} | {r['mm']} | {r['deg']} |")
    print(f"\n{sum(r['status'] == 'reached' for r in rows)} of {len(rows)} reached every target")


if __name__ == "__main__":
    main()
