"""Sweeps: a grid of scene variants (``--set KEY=V1,V2,...``), one rollout and one summary row each.

``dmarionette sweep`` (docs/sweep.md); from Python::

    from dmarionette.sweep import parse_set, run_variants, sweep_variants

    variants = sweep_variants("hanging", [parse_set("strings.k=200,400"), parse_set("strings.k_d=2,4")])
    rows = run_variants([v.scene for v in variants], duration=2.0)
"""

from .grid import SweepAxis as SweepAxis
from .grid import Variant as Variant
from .grid import parse_set as parse_set
from .grid import sweep_variants as sweep_variants
from .run import run_variant as run_variant
from .run import run_variants as run_variants

__all__ = ["SweepAxis", "Variant", "parse_set", "run_variant", "run_variants", "sweep_variants"]
