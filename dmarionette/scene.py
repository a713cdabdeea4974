"""Scenes: TOML files that say what is simulated, with which constants, at which rates.

A scene has these tables (all optional except ``[scene]`` and ``[[strings]]``); every key
is documented in ``docs/scenes.md``:

- ``[scene]`` name, description, default ``duration`` [s];
- ``[rates]`` ``string_hz`` (default 1000) and ``puppet_hz`` (default 30);
- ``[solver]`` ``precision`` (``"float64"`` default, or ``"float32"``);
- ``[effects]`` which effects are compiled in (``gravity``, ``internal_friction``,
  ``air_drag``, ``ground_contact``, ``ground_friction``; all on by default);
- ``[world]`` ``gravity`` [m/s^2] and ``ground_height`` [m];
- ``[string_defaults]`` constants shared by every string (see :mod:`string_model`);
- ``[[strings]]`` one table per string: ``name``, ``top``, ``bottom`` and any default;
- ``[motion]`` scripted motion of the string tops (``kind = "still"`` or ``"sway"``);
- ``[puppet]`` the puppet description (see :mod:`puppet`).

Loading validates everything and raises :class:`SceneError` naming the file, the key,
the value received and what was expected.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .scene_fields import (
    SceneError,
    check_keys,
    read_bool,
    read_choice,
    read_float,
    read_int,
    read_str,
    read_table,
    read_vec3,
)
from .string_model import StringEffects, StringModel, StringSpec

__all__ = ["Scene", "StringMotion", "builtin_scenes", "load_scene", "scene_from_table"]

SCENE_DIR = Path(__file__).parent / "scenes"
DEFAULT_SCENE = "hanging"

_STRING_CONSTANTS = {
    # key: (default, reader options)
    "particle_count": (50, {"minimum": 2, "maximum": 100_000}),
    "mass": (0.002, {"positive": True}),
    "load_mass": (0.0, {"minimum": 0.0}),
    "stiffness": (500.0, {"positive": True}),
    "internal_friction": (0.5, {"minimum": 0.0}),
    "air_drag": (0.01, {"minimum": 0.0}),
    "ground_stiffness": (2000.0, {"minimum": 0.0}),
    "ground_absorption": (5.0, {"minimum": 0.0}),
    "ground_friction": (2.0, {"minimum": 0.0}),
    "tie_stiffness": (300.0, {"minimum": 0.0}),
    "tie_damping": (3.0, {"minimum": 0.0}),
    "taut_fraction": (0.98, {"positive": True, "maximum": 2.0}),
}
_STRING_KEYS = {"name", "top", "bottom", "length", "bottom_end", "tie_point", *_STRING_CONSTANTS}
_EFFECTS = [f.name for f in dataclasses.fields(StringEffects)]


@dataclasses.dataclass(frozen=True)
class StringMotion:
    """Scripted motion of the string tops (a stand-in for the control bars).

    ``kind = "still"`` keeps the tops fixed; ``"sway"`` moves every top by
    ``amplitude * sin(2 pi frequency t)`` [m].
    """

    kind: str = "still"
    amplitude: tuple[float, float, float] = (0.0, 0.0, 0.0)
    frequency: float = 0.5

    def top_positions(self, tops: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Top attach points at ``times`` [s], shape ``(T, S, 3)``, from rest tops ``(S, 3)``."""
        tops = np.asarray(tops, dtype=np.float64)
        offset = np.zeros((len(times), 3))
        if self.kind == "sway":
            offset = np.sin(2.0 * math.pi * self.frequency * np.asarray(times))[:, None] * np.array(self.amplitude)
        return tops[None, :, :] + offset[:, None, :]


@dataclasses.dataclass(frozen=True)
class Scene:
    """A loaded, validated scene."""

    name: str
    description: str
    source: str
    duration: float
    string_hz: float
    puppet_hz: float
    precision: str
    effects: StringEffects
    gravity: tuple[float, float, float]
    ground_height: float
    strings: tuple[StringSpec, ...]
    motion: StringMotion
    puppet: Any = None

    @property
    def string_dt(self) -> float:
        """String (and feedback) step [s]."""
        return 1.0 / self.string_hz

    def build_string_model(self, *, device=None, requires_grad: bool = False,
                           precision: str | None = None, effects: StringEffects | None = None) -> StringModel:
        """The strings of this scene as a :class:`StringModel` (overrides for tests and benchmarks)."""
        return StringModel(
            self.strings,
            effects=self.effects if effects is None else effects,
            gravity=self.gravity,
            ground_height=self.ground_height,
            precision=self.precision if precision is None else precision,
            device=device,
            requires_grad=requires_grad,
        )


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with the package (files with a ``[scene]`` table)."""
    names = []
    for path in sorted(SCENE_DIR.glob("*.toml")):
        with path.open("rb") as f:
            if "scene" in tomllib.load(f):
                names.append(path.stem)
    return names


def load_scene(name_or_path: str | Path) -> Scene:
    """Loads a scene by built-in name (``"hanging"``) or from a TOML file path."""
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = SCENE_DIR / f"{name_or_path}.toml"
        if not path.exists():
            raise SceneError(str(name_or_path), "scene", str(name_or_path),
                             f"a TOML file path or a built-in scene name: {builtin_scenes()}")
    if not path.is_file():
        raise SceneError(str(path), "scene", str(path), "an existing TOML file")
    try:
        with path.open("rb") as f:
            table = tomllib.load(f)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(str(path), "(file)", "invalid TOML", f"valid TOML ({error})") from None
    return scene_from_table(table, str(path))


def scene_from_table(table: Mapping[str, Any], source: str) -> Scene:
    """Validates a parsed scene table; ``source`` names it in errors (a file path)."""
    check_keys(table, ["scene", "rates", "solver", "effects", "world", "string_defaults", "strings",
                       "motion", "puppet"], f"{source}: top level")
    head = read_table(table, "scene", f"{source}: top level")
    where = f"{source}: [scene]"
    check_keys(head, ["name", "description", "duration"], where)
    name = read_str(head, "name", where)
    description = read_str(head, "description", where) if "description" in head else ""
    duration = read_float(head, "duration", where, 5.0, positive=True)

    rates = read_table(table, "rates", source, {})
    where = f"{source}: [rates]"
    check_keys(rates, ["string_hz", "puppet_hz"], where)
    string_hz = read_float(rates, "string_hz", where, 1000.0, positive=True, maximum=1.0e6)
    puppet_hz = read_float(rates, "puppet_hz", where, 30.0, positive=True, maximum=string_hz)

    solver = read_table(table, "solver", source, {})
    check_keys(solver, ["precision"], f"{source}: [solver]")
    precision = read_choice(solver, "precision", f"{source}: [solver]", ["float64", "float32"], "float64")

    effects_table = read_table(table, "effects", source, {})
    where = f"{source}: [effects]"
    check_keys(effects_table, _EFFECTS, where)
    effects = StringEffects(**{k: read_bool(effects_table, k, where, True) for k in _EFFECTS})

    world = read_table(table, "world", source, {})
    where = f"{source}: [world]"
    check_keys(world, ["gravity", "ground_height"], where)
    gravity = read_vec3(world, "gravity", where, (0.0, -9.81, 0.0))
    ground_height = read_float(world, "ground_height", where, 0.0)

    defaults = _read_string_defaults(read_table(table, "string_defaults", source, {}), f"{source}: [string_defaults]")
    strings = _read_strings(table, source, defaults)
    motion = _read_motion(read_table(table, "motion", source, {}), f"{source}: [motion]")

    puppet = None
    if "puppet" in table:
        from .puppet import puppet_from_table

        puppet = puppet_from_table(read_table(table, "puppet", source), f"{source}: [puppet]")

    return Scene(name=name, description=description, source=source, duration=duration,
                 string_hz=string_hz, puppet_hz=puppet_hz, precision=precision, effects=effects,
                 gravity=gravity, ground_height=ground_height, strings=strings, motion=motion,
                 puppet=puppet)


def _read_constant(table: Mapping[str, Any], key: str, where: str, default: Any):
    options = _STRING_CONSTANTS[key][1]
    if key == "particle_count":
        return read_int(table, key, where, default, **options)
    return read_float(table, key, where, default, **options)


def _read_string_defaults(table: Mapping[str, Any], where: str) -> dict[str, Any]:
    check_keys(table, _STRING_CONSTANTS, where)
    return {key: _read_constant(table, key, where, default) for key, (default, _) in _STRING_CONSTANTS.items()}


def _read_strings(table: Mapping[str, Any], source: str, defaults: dict[str, Any]) -> tuple[StringSpec, ...]:
    entries = table.get("strings")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, Mapping) for e in entries):
        raise SceneError(f"{source}: top level", "strings", entries if entries is not None else None,
                         "one or more [[strings]] tables")
    specs, names = [], set()
    for i, entry in enumerate(entries):
        where = f"{source}: [[strings]] #{i + 1}"
        check_keys(entry, _STRING_KEYS, where)
        name = read_str(entry, "name", where)
        where = f"{source}: [[strings]] '{name}'"
        if name in names:
            raise SceneError(where, "name", name, "a name no other string has")
        names.add(name)
        top = read_vec3(entry, "top", where)
        bottom = read_vec3(entry, "bottom", where)
        span = float(np.linalg.norm(np.subtract(top, bottom)))
        # Unstretched length: by default the top-to-bottom distance (the string starts unstretched).
        length = read_float(entry, "length", where, **({"default": span} if span > 0.0 else {}), positive=True)
        end = read_choice(entry, "bottom_end", where, ["free", "tied"], "free")
        tie_point = read_vec3(entry, "tie_point", where, bottom) if end == "tied" else None
        if end == "free" and "tie_point" in entry:
            raise SceneError(where, "tie_point", entry["tie_point"], "no tie_point unless bottom_end = \"tied\"")
        constants = {key: _read_constant(entry, key, where, defaults[key]) for key in _STRING_CONSTANTS}
        specs.append(StringSpec(name=name, top=top, bottom=bottom, length=length, tied=end == "tied",
                                tie_point=tie_point, **constants))
    return tuple(specs)


def _read_motion(table: Mapping[str, Any], where: str) -> StringMotion:
    check_keys(table, ["kind", "amplitude", "frequency"], where)
    kind = read_choice(table, "kind", where, ["still", "sway"], "still")
    amplitude = read_vec3(table, "amplitude", where, (0.0, 0.0, 0.0))
    frequency = read_float(table, "frequency", where, 0.5, minimum=0.0)
    return StringMotion(kind=kind, amplitude=amplitude, frequency=frequency)
