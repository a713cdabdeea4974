"""Typed readers for the tables of a TOML scene file.

Every reader takes the table, the key, and a ``where`` that names the file and the
table path (``"hanging.toml: [strings.head]"``), and raises :class:`SceneError` naming
the file, the key, the value received and what was expected. Scene loaders call these
at the Python boundary so that a user's mistake never reaches a kernel.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "SceneError",
    "check_keys",
    "read_bool",
    "read_choice",
    "read_float",
    "read_int",
    "read_str",
    "read_table",
    "read_toml_file",
    "read_vec3",
]

_MISSING = object()


class SceneError(ValueError):
    """A scene file (or scene dictionary) that cannot be used as written.

    Attributes:
        where: the file and table, e.g. ``"scenes/hanging.toml: [strings.head]"``.
        key: the offending key.
        received: the value found (or ``None`` when the key is missing).
        expected: a description of what would have been accepted.
    """

    def __init__(self, where: str, key: str, received: Any, expected: str):
        self.where = where
        self.key = key
        self.received = received
        self.expected = expected
        got = "nothing (the key is missing)" if received is _MISSING else repr(received)
        super().__init__(f"{where}: key '{key}': got {got}; expected {expected}")


def read_toml_file(path: Path, expected: str = "an existing TOML file",
                   error: type[SceneError] = SceneError) -> dict[str, Any]:
    """The table of a TOML file.

    Args:
        path: the file.
        expected: what the message says was expected when the file does not exist.
        error: the error raised (a ``SceneError`` subclass names the kind of file).

    Returns:
        The parsed table.

    Raises:
        SceneError: (or ``error``) the file does not exist or is not valid TOML.
    """
    if not path.is_file():
        raise error(str(path), "(file)", str(path), expected)
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise error(str(path), "(file)", "invalid TOML", f"valid TOML ({err})") from None
    except UnicodeDecodeError as err:
        raise error(str(path), "(file)", f"bytes that are not UTF-8 ({err.reason} at byte {err.start})",
                    "a TOML file in UTF-8") from None
    except OSError as err:
        raise error(str(path), "(file)", f"an unreadable file ({err.strerror or err})", expected) from None


def check_keys(table: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    """Refuses keys that the table does not define (catches typos such as ``stifness``)."""
    allowed = sorted(allowed)
    for key in table:
        if key not in allowed:
            raise SceneError(where, key, table[key], f"one of the known keys {allowed}")


def _fetch(table: Mapping[str, Any], key: str, where: str, default: Any) -> Any:
    if key in table:
        return table[key]
    if default is _MISSING:
        raise SceneError(where, key, _MISSING, "a value (this key is required)")
    return default


def _check_bounds(value, where: str, key: str, noun: str, minimum, maximum) -> None:
    if minimum is not None and value < minimum:
        raise SceneError(where, key, value, f"{noun} >= {minimum}")
    if maximum is not None and value > maximum:
        raise SceneError(where, key, value, f"{noun} <= {maximum}")


def read_float(table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING, *,
               minimum: float | None = None, maximum: float | None = None, positive: bool = False) -> float:
    """Reads a finite real number, optionally bounded (``positive`` means > 0)."""
    value = _fetch(table, key, where, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(where, key, value, "a number")
    value = float(value)
    if not math.isfinite(value):
        raise SceneError(where, key, value, "a finite number (not NaN or infinity)")
    if positive and not value > 0.0:
        raise SceneError(where, key, value, "a number > 0")
    _check_bounds(value, where, key, "a number", minimum, maximum)
    return value


def read_int(table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING, *,
             minimum: int | None = None, maximum: int | None = None) -> int:
    """Reads an integer, optionally bounded."""
    value = _fetch(table, key, where, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise SceneError(where, key, value, "an integer")
    _check_bounds(value, where, key, "an integer", minimum, maximum)
    return value


def read_bool(table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING) -> bool:
    """Reads ``true`` or ``false``."""
    value = _fetch(table, key, where, default)
    if not isinstance(value, bool):
        raise SceneError(where, key, value, "true or false")
    return value


def read_str(table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING) -> str:
    """Reads a non-empty string."""
    value = _fetch(table, key, where, default)
    if not isinstance(value, str) or not value:
        raise SceneError(where, key, value, "a non-empty string")
    return value


def read_choice(
    table: Mapping[str, Any], key: str, where: str, choices: Iterable[str], default: Any = _MISSING
) -> str:
    """Reads a string that must be one of ``choices``."""
    choices = list(choices)
    value = _fetch(table, key, where, default)
    if value not in choices:
        raise SceneError(where, key, value, f"one of {choices}")
    return value


def read_vec3(
    table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING
) -> tuple[float, float, float]:
    """Reads a list of three finite numbers, e.g. a position in metres."""
    value = _fetch(table, key, where, default)
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == 3
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)
    )
    if not ok:
        raise SceneError(where, key, value, "a list of three numbers, e.g. [0.0, 1.2, 0.0]")
    if not all(math.isfinite(float(c)) for c in value):
        raise SceneError(where, key, value, "three finite numbers (no NaN or infinity)")
    return (float(value[0]), float(value[1]), float(value[2]))


def read_table(
    table: Mapping[str, Any], key: str, where: str, default: Any = _MISSING
) -> Mapping[str, Any]:
    """Reads a sub-table (``[section]`` in TOML)."""
    value = _fetch(table, key, where, default)
    if not isinstance(value, Mapping):
        raise SceneError(where, key, value, "a table")
    return value
