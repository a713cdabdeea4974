"""The grid of a sweep: ``--set KEY=V1,V2,...`` flags, their cartesian product, one validated scene each.

A ``KEY`` names a field of the scene's TOML file (docs/scenes.md), as a dotted path:

- ``strings.KEY``: that constant on every string (it replaces the ``[string_defaults]`` value and
  any value a ``[[strings]]`` table sets itself), e.g. ``strings.tie_stiffness``;
- ``strings.NAME.KEY``: that constant on the string named ``NAME`` only, e.g.
  ``strings.hand_left.tie_stiffness``;
- any other path: the key of that table, e.g. ``rates.puppet_hz``, ``string_defaults.mass``,
  ``feedback.stiffness``, ``contact.friction``, ``world.ground_height``, ``puppet.root_position``.

The string constants also answer to the names ``calibrate`` uses: ``k`` (eq. 2 ``tie_stiffness``),
``k_d`` (``tie_damping``) and ``k_s`` (the string's ``stiffness``), so ``strings.k=200,400`` works.

A value is read as a TOML value (``300``, ``2.5e3``, ``true``, ``[0.0, 1.3, 0.0]``, ``"float32"``);
a bare word that is not TOML (``float32``) is taken as a string. Values are separated by commas
outside brackets and quotes.

Every variant's table is validated by the scene loader itself
(:func:`dmarionette.scene.scene.scene_from_table`): a bad key or value gets the scene's named error
(file, table, key, value received, what was expected), with the ``--set`` flags of the variant
that carries it, before any variant is simulated.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from dmarionette.scene.fields import SceneError, read_toml_file
from dmarionette.scene.scene import Scene, load_scene, scene_from_table

__all__ = ["ALIASES", "MAX_VARIANTS", "SweepAxis", "Variant", "parse_set", "sweep_variants"]

ALIASES = {"k": "tie_stiffness", "k_d": "tie_damping", "k_s": "stiffness"}
"""The names ``calibrate`` uses for the string constants -> the scene's keys."""

MAX_VARIANTS = 10_000
"""The largest grid a sweep accepts (a typo such as a missing comma should not start days of work)."""


@dataclasses.dataclass(frozen=True)
class SweepAxis:
    """One ``--set`` flag.

    Attributes:
        key: the key as canonical dotted path (aliases resolved), e.g. ``strings.tie_stiffness``.
        texts: the values as given, e.g. ``("200", "400")``.
        values: the values as parsed (TOML), e.g. ``(200, 400)``.
        flag: the flag as given (for messages), e.g. ``strings.k=200,400``.
    """

    key: str
    texts: tuple[str, ...]
    values: tuple[Any, ...]
    flag: str


@dataclasses.dataclass(frozen=True)
class Variant:
    """One point of the grid.

    Attributes:
        index: 1-based position in the grid (the first axis varies slowest).
        settings: ``key -> value text`` for every axis, in axis order.
        scene: the validated scene with these settings.
    """

    index: int
    settings: Mapping[str, str]
    scene: Scene

    def label(self) -> str:
        """``strings.tie_stiffness=200, rates.puppet_hz=30``."""
        return ", ".join(f"{k}={v}" for k, v in self.settings.items())


def _split_values(text: str) -> list[str]:
    """Splits at commas outside brackets and quotes: ``1,[0,1,2],"a,b"`` -> three values."""
    parts, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote is not None:
            if ch == quote:
                quote = None
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def _parse_value(text: str) -> Any:
    """A TOML value; a bare word that is not TOML is a string."""
    try:
        return tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        return text


def _canonical_key(key: str, flag: str) -> str:
    parts = key.split(".")
    if not key or any(not p for p in parts):
        raise SceneError(f"--set {flag}", "KEY", key, "a dotted scene key such as strings.k, strings.hand_left.k or "
                                                      "rates.puppet_hz (docs/sweep.md)")
    if parts[0] == "strings" and len(parts) in (2, 3):
        parts[-1] = ALIASES.get(parts[-1], parts[-1])
    elif parts[0] == "string_defaults" and len(parts) == 2:
        parts[-1] = ALIASES.get(parts[-1], parts[-1])
    return ".".join(parts)


def parse_set(flag: str) -> SweepAxis:
    """Reads one ``--set KEY=V1,V2,...`` flag (the key's form and the values' syntax only).

    Raises:
        SceneError: naming the flag, what was received and what was expected.
    """
    key, equals, values = flag.partition("=")
    if not equals:
        raise SceneError(f"--set {flag}", "KEY=V1,V2,...", flag, "KEY=V1,V2,... (e.g. strings.k=200,400)")
    key = _canonical_key(key.strip(), flag)
    texts = _split_values(values)
    for i, text in enumerate(texts):
        if not text:
            raise SceneError(f"--set {flag}", key, values, f"values separated by commas, none empty (value {i + 1} "
                                                           "is empty)")
    if len(set(texts)) != len(texts):
        raise SceneError(f"--set {flag}", key, values, "each value once")
    return SweepAxis(key=key, texts=tuple(texts), values=tuple(_parse_value(t) for t in texts), flag=flag)


def _set_key(table: dict, axis: SweepAxis, value: Any, source: str) -> None:
    """Writes ``value`` at ``axis.key`` in the raw scene ``table`` (in place)."""
    parts = axis.key.split(".")
    where = f"{source}: --set {axis.flag}"
    if parts[0] == "strings":
        entries = table.get("strings")
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise SceneError(where, "strings", entries, "a scene with [[strings]] tables")
        names = [e.get("name") for e in entries]
        if len(parts) == 2:
            targets = entries
        elif len(parts) == 3:
            if parts[1] not in names:
                raise SceneError(where, parts[1], axis.key,
                                 f"strings.KEY or strings.NAME.KEY with NAME one of {sorted(map(str, names))}")
            targets = [entries[names.index(parts[1])]]
        else:
            raise SceneError(where, axis.key, axis.key, "strings.KEY (every string) or strings.NAME.KEY (one string)")
        for entry in targets:
            entry[parts[-1]] = value
        return
    node = table
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            path = ".".join(parts[: i + 1])
            raise SceneError(where, path, child, f"a table to set {parts[-1]!r} in; {path} is not one")
        node = child
    node[parts[-1]] = value


def sweep_variants(scene: str | Path, axes: Sequence[SweepAxis]) -> list[Variant]:
    """The cartesian product of ``axes`` on ``scene``, every variant validated by the scene loader.

    Args:
        scene: a built-in scene name or a TOML file (as ``dmarionette simulate`` takes it).
        axes: the ``--set`` flags (:func:`parse_set`); the first varies slowest.

    Returns:
        The variants, in grid order.

    Raises:
        SceneError: the scene, a key or a value is refused (the scene's own message, naming the file,
            the table, the key, the value and what was expected, with the variant's ``--set`` values);
            two flags set the same key; the grid has more than :data:`MAX_VARIANTS` variants.
    """
    base = load_scene(scene)  # the scene as given must load first: its errors are its own
    if base.puppet is None or not base.bars:
        raise SceneError(base.source, "puppet", None, "a marionette scene ([puppet] and [bars]): a sweep reports "
                                                      "the torso, the ties and the bars' feedback")
    seen: dict[str, str] = {}
    for axis in axes:
        if axis.key in seen:
            raise SceneError(f"--set {axis.flag}", axis.key, axis.flag,
                             f"each key in one --set only (--set {seen[axis.key]} sets it too)")
        seen[axis.key] = axis.flag
    count = 1
    for axis in axes:
        count *= len(axis.texts)
    if count > MAX_VARIANTS:
        raise SceneError(", ".join(f"--set {a.flag}" for a in axes), "(grid)", f"{count} variants",
                         f"at most {MAX_VARIANTS} variants")
    raw = read_toml_file(Path(base.source))
    variants = []
    for index, combo in enumerate(itertools.product(*(range(len(a.texts)) for a in axes)), start=1):
        table = copy.deepcopy(raw)
        for axis, i in zip(axes, combo):
            _set_key(table, axis, axis.values[i], base.source)
        settings = {axis.key: axis.texts[i] for axis, i in zip(axes, combo)}
        try:
            variant_scene = scene_from_table(table, base.source)
        except SceneError as error:
            label = ", ".join(f"{k}={v}" for k, v in settings.items())
            raise SceneError(f"{error.where} (variant {index} of {count}: --set {label})", error.key,
                             error.received, error.expected) from None
        variants.append(Variant(index=index, settings=settings, scene=variant_scene))
    return variants
