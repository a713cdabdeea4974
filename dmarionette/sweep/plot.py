"""``sweep.png``: the per-variant summaries against the first ``--set`` key.

Six panels: torso height (lowest and highest), taut fraction (mean and lowest over the strings),
peak eq. 4 feedback (largest over the bars), energy excess, real-time factor and wall time.
The x axis is the first key that takes more than one value (numeric when its values all are
numbers, else in the order given); each combination of the other varying keys' values is one
line; keys with one value are named in the title. Non-finite variants are drawn
as gaps.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dmarionette.render.pyplot import headless_pyplot

__all__ = ["plot_sweep"]


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def plot_sweep(path: Path, rows: Sequence[Mapping[str, object]], keys: Sequence[str], string_names: Sequence[str],
               bar_names: Sequence[str], title: str) -> Path:
    """Draws ``rows`` (the sweep's rows, any order) into ``path`` (PNG).

    Args:
        path: the picture to write.
        rows: the rows (``variant``, the ``keys`` as text, the summary columns as numbers).
        keys: the ``--set`` keys; the first that varies is the x axis (none: the variant index).
        string_names, bar_names: the strings and bars of the scene (column names).
        title: the figure's title.
    """
    plt = headless_pyplot()

    rows = sorted(rows, key=lambda r: int(r["variant"]))
    varying = [k for k in keys if len({str(r[k]) for r in rows}) > 1]
    fixed = [f"{k}={rows[0][k]}" for k in keys if k not in varying] if rows else []
    x_key = varying[0] if varying else "variant"
    x_texts = list(dict.fromkeys(str(r[x_key]) for r in rows))
    numeric = all(_number(t) is not None for t in x_texts)
    x_of = {t: (_number(t) if numeric else float(i)) for i, t in enumerate(x_texts)}
    groups: dict[str, list] = {}
    for row in rows:
        label = ", ".join(f"{k}={row[k]}" for k in varying[1:])
        groups.setdefault(label, []).append(row)

    def value(row, column) -> float:
        v = row[column]
        return float(v) if isinstance(v, (int, float)) else math.nan

    panels = [
        ("torso height [m] (solid: highest, dashed: lowest)", [("torso_max_m", "-"), ("torso_min_m", "--")]),
        ("taut fraction (solid: mean, dashed: lowest string)", [("taut_mean", "-"), ("taut_min", "--")]),
        ("peak eq. 4 feedback [N] (largest bar)", [("feedback_max", "-")]),
        ("energy excess E - E0 - W_bars [J]", [("energy_excess_J", "-")]),
        ("real-time factor (rollout)", [("real_time_factor", "-")]),
        ("wall time per variant [s]", [("wall_s", "-")]),
    ]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for g, (label, members) in enumerate(groups.items()):
        members = sorted(members, key=lambda r: x_of[str(r[x_key])])
        xs = np.array([x_of[str(r[x_key])] for r in members])
        derived = {
            "taut_mean": [np.mean([value(r, f"taut_{s}") for s in string_names]) for r in members],
            "taut_min": [np.min([value(r, f"taut_{s}") for s in string_names]) for r in members],
            "feedback_max": [np.max([value(r, f"feedback_max_{b}_N") for b in bar_names]) for r in members],
        }
        for ax, (_, series) in zip(axes.flat, panels):
            for column, style in series:
                ys = derived[column] if column in derived else [value(r, column) for r in members]
                ax.plot(xs, ys, style, marker="o", color=colours[g % len(colours)],
                        label=(label or None) if style == "-" else None)
    for ax, (name, _) in zip(axes.flat, panels):
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(x_key)
        ax.grid(alpha=0.3)
        if not numeric:
            ax.set_xticks(range(len(x_texts)), x_texts, rotation=30, fontsize=8)
    if any(groups):
        handles, labels = axes.flat[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=8)
    fig.suptitle(title + (f"\n{', '.join(fixed)} in every variant" if fixed else ""), fontsize=10)
    fig.tight_layout(rect=(0.0, 0.06 if any(groups) else 0.0, 1.0, 1.0))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)
