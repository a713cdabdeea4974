"""The sweep's table: ``sweep.csv`` written row by row as variants finish, and ``sweep.md`` at the end.

``sweep.csv`` has one row per finished variant, in the order they finished: ``variant`` (the
1-based grid index), one column per ``--set`` key with the value as given, then the summary
columns of :func:`dmarionette.sweep.run.run_variant`. Numbers are written exactly (Python's
shortest round-trip form: reading the file back gives the very floats computed); a row is
flushed to disk as soon as it is written, so a run that is killed keeps every finished row, and
``--resume`` reads them back and runs only the variants that have none.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["RowWriter", "read_rows", "summary_columns", "write_markdown"]


def summary_columns(string_names: Sequence[str], bar_names: Sequence[str]) -> list[str]:
    """The summary columns of a row, in table order."""
    return ["simulated_s", "torso_min_m", "torso_max_m", *(f"taut_{n}" for n in string_names),
            *(f"feedback_max_{b}_N" for b in bar_names), *(f"reaction_max_{b}_N" for b in bar_names),
            "energy_excess_J", "bar_work_J", "finite", "first_non_finite_s", "real_time_factor", "wall_s"]


def _text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # exact: float(repr(x)) == x
    return str(value)


class RowWriter:
    """Appends rows to ``sweep.csv``, one line per variant, flushed as written.

    Args:
        path: the CSV file.
        columns: ``["variant", *keys, *summary columns]``.
        append: keep the rows already in the file (``--resume``); else start it anew.
    """

    def __init__(self, path: Path, columns: Sequence[str], *, append: bool = False):
        self.path = Path(path)
        self.columns = list(columns)
        fresh = not (append and self.path.is_file() and self.path.stat().st_size > 0)
        if not fresh:
            _drop_partial_line(self.path)
        self._file = self.path.open("w" if fresh else "a", newline="")
        self._writer = csv.writer(self._file)
        if fresh:
            self._writer.writerow(self.columns)
            self._file.flush()

    def write(self, row: Mapping[str, object]) -> None:
        """Writes one row (its keys: the columns) and flushes it to disk."""
        self._writer.writerow([_text(row[c]) for c in self.columns])
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _drop_partial_line(path: Path) -> None:
    """Cuts a last line left without its newline (a run killed while writing it)."""
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


def _value(text: str):
    if text in ("true", "false"):
        return text == "true"
    try:
        return float(text)
    except ValueError:
        return text


def read_rows(path: Path, keys: Sequence[str], summary: Sequence[str]) -> list[dict]:
    """The rows of an existing ``sweep.csv`` written by a sweep of the same ``--set`` keys (``--resume``).

    Values: ``variant`` an int; the ``--set`` columns as written (text); the summary columns as
    floats, ``finite`` a bool. A last line cut short by a kill (no newline) is left out.

    Raises:
        ValueError: the file's header is not ``["variant", *keys, *summary]`` (another sweep's table).
    """
    columns = ["variant", *keys, *summary]
    text = Path(path).read_text()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]  # a last line cut short by a kill
    lines = list(csv.reader(text.splitlines()))
    if not lines:
        return []
    if lines[0] != columns:
        raise ValueError(f"--resume: {str(path)!r} has the columns {lines[0]}; expected {columns} (the same "
                         "scene, --set keys and strings as this sweep); remove it or choose another --out")
    rows = []
    for line in lines[1:]:
        if len(line) != len(columns) or not line[0].isdigit():
            continue
        row: dict = {"variant": int(line[0])}
        row.update(zip(keys, line[1:1 + len(keys)]))
        row.update((c, _value(t)) for c, t in zip(summary, line[1 + len(keys):]))
        rows.append(row)
    return rows


def _cell(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "**no**"
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def write_markdown(path: Path, rows: Sequence[Mapping[str, object]], keys: Sequence[str], columns: Sequence[str],
                   header: str) -> Path:
    """``sweep.md``: ``header``, then a table of ``rows`` (sorted by variant) with 4 significant digits."""
    shown = ["variant", *keys, *(c for c in columns if c not in ("first_non_finite_s",))]
    lines = [header, "", "| " + " | ".join(shown) + " |", "|" + "|".join(" ---: " for _ in shown) + "|"]
    for row in sorted(rows, key=lambda r: int(r["variant"])):
        lines.append("| " + " | ".join(_cell(row[c]) for c in shown) + " |")
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)
