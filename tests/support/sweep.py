"""What the sweep tests share: the rows of a sweep compared without their timings."""

import math

TIMINGS = ("real_time_factor", "wall_s")


def comparable(row: dict) -> dict:
    """A row without its timing columns, NaN as the text 'nan' (so that equal rows compare equal)."""
    return {k: ("nan" if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items() if k not in TIMINGS}
