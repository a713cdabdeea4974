"""Scenes: TOML files that say what is simulated, with which constants, at which rates.

A scene has these tables (all optional except ``[scene]`` and ``[[strings]]``); every key
is documented in ``docs/scenes.md``:

- ``[scene]`` name, description, default ``duration`` [s];
- ``[rates]`` ``string_hz`` (default 1000) and ``puppet_hz`` (default 30);
- ``[solver]`` ``precision`` (``"float64"`` default, or ``"float32"``);
- ``[effects]`` which effects are compiled in: string effects (``gravity``,
  ``internal_friction``, ``air_drag``, ``ground_contact``, ``ground_friction``) and, with a
  puppet, ``body_ground``, ``chair``, ``ball``, ``joint_limits``, ``one_sided_limits``, ``feedback``;
- ``[world]`` ``gravity`` [m/s^2] and ``ground_height`` [m];
- ``[string_defaults]`` constants shared by every string (see :mod:`string_model`);
- ``[[strings]]`` one table per string: ``name``, ``top``, ``bottom`` (or, with a puppet, the
  ``body_point`` it is tied to) and any default;
- ``[motion]`` scripted motion of the string tops when there are no bars;
- ``[puppet]`` the puppet description (see :mod:`puppet`), ``[bars.NAME]`` the control bars
  (see :mod:`control_bar`), ``[feedback]``, ``[contact]``, ``[chair]``, ``[ball]``.

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

from dmarionette.scene.fields import (
    SceneError,
    check_keys,
    read_bool,
    read_choice,
    read_float,
    read_int,
    read_str,
    read_table,
    read_toml_file,
    read_vec3,
)
from dmarionette.scene.bars import ControlBar, bar_from_table
from dmarionette.scene.strings import StringEffects, StringSpec

__all__ = ["Scene", "StringMotion", "builtin_scenes", "load_scene", "resolve_puppet_table", "scene_from_table"]

SCENE_DIR = Path(__file__).parent / "builtin"
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
_STRING_KEYS = {"name", "top", "bottom", "length", "bottom_end", "tie_point", "body_point", *_STRING_CONSTANTS}
_EFFECTS = [f.name for f in dataclasses.fields(StringEffects)]
_BODY_EFFECTS = {"body_ground": True, "chair": False, "ball": False, "joint_limits": True, "one_sided_limits": True,
                 "feedback": True}
_CONTACT = {
    # key: (default, reader options); see dmarionette.kernels.body_contact.ContactSettings
    "stiffness": (2000.0, {"positive": True}),
    "damping": (5.0, {"minimum": 0.0}),
    "friction": (0.6, {"minimum": 0.0}),
    "friction_velocity": (0.01, {"positive": True}),
    "smooth_distance": (0.5e-3, {"positive": True}),
}


@dataclasses.dataclass(frozen=True)
class BallSpec:
    """A free ball in the scene: centre [m], radius [m], mass [kg]."""

    position: tuple[float, float, float]
    radius: float
    mass: float


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
    string_body_points: tuple[str | None, ...] = ()
    bars: tuple[ControlBar, ...] = ()
    body_effects: Mapping[str, bool] = dataclasses.field(default_factory=lambda: dict(_BODY_EFFECTS))
    feedback_stiffness: float = 5.0
    feedback_damping: float = 0.5
    contact: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    chair: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    ball: BallSpec | None = None
    initial_pose: Mapping[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)

    def top_positions(self, rest_tops: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Where each string's top is at ``times`` [m], ``(T, S, 3)``: strings on a bar follow
        it; the others follow ``[motion]`` from their rest tops ``(S, 3)``."""
        tops = self.motion.top_positions(rest_tops, times)
        names = [s.name for s in self.strings]
        for bar in self.bars:
            carried = [i for i, n in enumerate(names) if n in bar.attach]
            tops[:, carried] = bar.attach_points(times, [names[i] for i in carried])
        return tops

    @property
    def string_dt(self) -> float:
        """String (and feedback) step [s]."""
        return 1.0 / self.string_hz


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
    return scene_from_table(read_toml_file(path), str(path))


def scene_from_table(table: Mapping[str, Any], source: str, *, allow_untested: bool = False) -> Scene:
    """Validates a parsed scene table; ``source`` names it in errors (a file path).

    Constants outside the ranges the simulator has been tested for
    (:data:`dmarionette.scene.limits.TESTED_RANGES`) are refused unless ``allow_untested``
    (or the scene's ``[solver] allow_untested = true``); a ``[scene] duration`` whose
    trajectory would not fit in memory is refused with the estimate.
    """
    if not isinstance(table, Mapping):
        raise SceneError(source, "(file)", type(table).__name__, "a table of scene tables")
    check_keys(table, ["scene", "rates", "solver", "effects", "world", "string_defaults", "strings",
                       "motion", "puppet", "bars", "feedback", "contact", "chair", "ball", "initial_pose"],
               f"{source}: top level")
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
    check_keys(solver, ["precision", "allow_untested"], f"{source}: [solver]")
    precision = read_choice(solver, "precision", f"{source}: [solver]", ["float64", "float32"], "float64")
    allow_untested = read_bool(solver, "allow_untested", f"{source}: [solver]", False) or allow_untested

    effects_table = read_table(table, "effects", source, {})
    where = f"{source}: [effects]"
    check_keys(effects_table, [*_EFFECTS, *_BODY_EFFECTS], where)
    defaults = StringEffects()
    effects = StringEffects(**{k: read_bool(effects_table, k, where, getattr(defaults, k)) for k in _EFFECTS})
    body_effects = {k: read_bool(effects_table, k, where, v) for k, v in _BODY_EFFECTS.items()}

    world = read_table(table, "world", source, {})
    where = f"{source}: [world]"
    check_keys(world, ["gravity", "ground_height"], where)
    gravity = read_vec3(world, "gravity", where, (0.0, -9.81, 0.0))
    ground_height = read_float(world, "ground_height", where, 0.0)

    defaults = _read_string_defaults(read_table(table, "string_defaults", source, {}), f"{source}: [string_defaults]")
    puppet = None
    if "puppet" in table:
        from dmarionette.scene.puppet import puppet_from_table

        puppet = puppet_from_table(resolve_puppet_table(read_table(table, "puppet", source), source),
                                   f"{source}: [puppet]")
    bars_table = read_table(table, "bars", source, {})
    bars = tuple(bar_from_table(n, read_table(bars_table, n, f"{source}: [bars]"), f"{source}: [bars.{n}]",
                                Path(source).parent) for n in bars_table)
    strings, body_points = _read_strings(table, source, defaults, puppet, bars)
    motion = _read_motion(read_table(table, "motion", source, {}), f"{source}: [motion]")

    feedback = read_table(table, "feedback", source, {})
    where = f"{source}: [feedback]"
    check_keys(feedback, ["stiffness", "damping"], where)
    contact_table = read_table(table, "contact", source, {})
    where_c = f"{source}: [contact]"
    check_keys(contact_table, [*_CONTACT, "smooth"], where_c)
    contact = {k: read_float(contact_table, k, where_c, d, **o) for k, (d, o) in _CONTACT.items()}
    contact["smooth"] = read_bool(contact_table, "smooth", where_c, False)
    initial_pose = _read_initial_pose(read_table(table, "initial_pose", source, {}), f"{source}: [initial_pose]",
                                      puppet)
    chair = _read_chair(table, source) if body_effects["chair"] else None
    ball = _read_ball(table, source) if body_effects["ball"] else None

    scene = Scene(name=name, description=description, source=source, duration=duration,
                 string_hz=string_hz, puppet_hz=puppet_hz, precision=precision, effects=effects,
                 gravity=gravity, ground_height=ground_height, strings=strings, motion=motion,
                 puppet=puppet, string_body_points=body_points, bars=bars, body_effects=body_effects,
                 feedback_stiffness=read_float(feedback, "stiffness", where, 5.0, minimum=0.0),
                 feedback_damping=read_float(feedback, "damping", where, 0.5, minimum=0.0),
                 contact=contact, chair=chair, ball=ball, initial_pose=initial_pose)
    # Settings the simulator was measured not to handle are refused here, with the reason.
    from dmarionette.scene.limits import check_duration, check_tested_ranges
    from dmarionette.scene.settings_check import check_marionette_settings, check_string_settings

    if not allow_untested:
        check_tested_ranges(scene)
    check_duration(scene, duration, f"{source}: [scene]")
    check_string_settings(scene)
    if puppet is not None:
        check_marionette_settings(scene)
    return scene


def resolve_puppet_table(table: Mapping[str, Any], source: str) -> Mapping[str, Any]:
    """A scene's ``[puppet]`` table with its ``include`` resolved.

    ``include = "puppet.toml"`` loads that file's ``[puppet]`` table (next to the scene or built
    in); the other keys of the scene's ``[puppet]`` table override its top-level keys.

    Args:
        table: the scene's ``[puppet]`` table.
        source: the scene file's path (an include is looked for next to it), for messages too.

    Returns:
        The table itself when it includes nothing, else the merged table.
    """
    if "include" not in table:
        return table
    where = f"{source}: [puppet]"
    name = read_str(table, "include", where)
    path = Path(source).parent / name
    if not path.is_file():
        path = SCENE_DIR / name
    if not path.is_file():
        raise SceneError(where, "include", name, f"a puppet file next to the scene or built in ({SCENE_DIR})")
    base = read_toml_file(path, "a puppet TOML file").get("puppet")
    if not isinstance(base, Mapping):
        raise SceneError(str(path), "puppet", None, "a [puppet] table")
    merged = dict(base)
    merged.update({k: v for k, v in table.items() if k != "include"})
    return merged




def _read_initial_pose(table: Mapping[str, Any], where: str, puppet) -> dict[str, tuple[float, ...]]:
    """``joint_name = [angles in degrees]``, one per axis of a hinge or universal joint."""
    if not table:
        return {}
    if puppet is None:
        raise SceneError(where, next(iter(table)), table[next(iter(table))], "no initial_pose without a [puppet]")
    joints = {j.name: j for j in puppet.joints}
    pose = {}
    for name, angles in table.items():
        joint = joints.get(name)
        if joint is None or joint.type not in ("hinge", "universal"):
            choices = sorted(n for n, j in joints.items() if j.type in ("hinge", "universal"))
            raise SceneError(where, name, angles, f"the name of a hinge or universal joint, one of {choices}")
        ok = isinstance(angles, list) and len(angles) == len(joint.axes) and all(
            isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in angles)
        if not ok:
            raise SceneError(where, name, angles, f"a list of {len(joint.axes)} finite angles in degrees")
        pose[name] = tuple(float(a) for a in angles)
    return pose


def _read_chair(table: Mapping[str, Any], source: str):
    where = f"{source}: [chair]"
    chair = read_table(table, "chair", f"{source}: top level (effects.chair = true)")
    check_keys(chair, ["centre", "half_extents"], where)
    half = read_vec3(chair, "half_extents", where)
    if min(half) <= 0.0:
        raise SceneError(where, "half_extents", list(half), "three positive half sizes [m]")
    return read_vec3(chair, "centre", where), half


def _read_ball(table: Mapping[str, Any], source: str) -> BallSpec:
    where = f"{source}: [ball]"
    ball = read_table(table, "ball", f"{source}: top level (effects.ball = true)")
    check_keys(ball, ["position", "radius", "mass"], where)
    return BallSpec(position=read_vec3(ball, "position", where),
                    radius=read_float(ball, "radius", where, positive=True),
                    mass=read_float(ball, "mass", where, positive=True))


def _read_constant(table: Mapping[str, Any], key: str, where: str, default: Any):
    options = _STRING_CONSTANTS[key][1]
    if key == "particle_count":
        return read_int(table, key, where, default, **options)
    return read_float(table, key, where, default, **options)


def _read_string_defaults(table: Mapping[str, Any], where: str) -> dict[str, Any]:
    check_keys(table, _STRING_CONSTANTS, where)
    return {key: _read_constant(table, key, where, default) for key, (default, _) in _STRING_CONSTANTS.items()}


def _read_strings(table: Mapping[str, Any], source: str, defaults: dict[str, Any], puppet=None,
                  bars: tuple[ControlBar, ...] = ()) -> tuple[tuple[StringSpec, ...], tuple[str | None, ...]]:
    """The strings, and for each the puppet point it is tied to (or None).

    With a puppet, ``body_point`` names the point a string is tied to and its bottom starts
    there (filled in when the marionette is built: the placeholder is the top); with bars,
    a string whose name a bar's ``attach`` lists hangs from that bar (its ``top`` is filled
    in from the bar at t = 0).
    """
    entries = table.get("strings")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, Mapping) for e in entries):
        raise SceneError(f"{source}: top level", "strings", entries if entries is not None else None,
                         "one or more [[strings]] tables")
    known = [e.get("name") for e in entries]
    for bar in bars:  # before the strings are read: a misspelt attach name is named as such
        for name in bar.attach:
            if name not in known:
                raise SceneError(f"{source}: [bars.{bar.name}.attach]", name, list(bar.attach[name]),
                                 f"the name of a string, one of {sorted(str(n) for n in known)}")
    on_bar = {name: bar for bar in bars for name in bar.attach}
    point_names = [p.name for p in puppet.points] if puppet is not None else []
    specs, body_points, names = [], [], set()
    for i, entry in enumerate(entries):
        where = f"{source}: [[strings]] #{i + 1}"
        check_keys(entry, _STRING_KEYS, where)
        name = read_str(entry, "name", where)
        where = f"{source}: [[strings]] '{name}'"
        if name in names:
            raise SceneError(where, "name", name, "a name no other string has")
        names.add(name)
        body_point = None
        if "body_point" in entry:
            if puppet is None:
                raise SceneError(where, "body_point", entry["body_point"], "no body_point unless the scene has a [puppet]")
            body_point = read_choice(entry, "body_point", where, point_names)
        if name in on_bar:
            if "top" in entry:
                raise SceneError(where, "top", entry["top"], f"no top: bar '{on_bar[name].name}' carries this string")
            top = tuple(float(v) for v in on_bar[name].attach_points(np.zeros(1), [name])[0, 0])
        else:
            top = read_vec3(entry, "top", where)
        bottom = top if body_point is not None else read_vec3(entry, "bottom", where)
        if body_point is not None and "bottom" in entry:
            raise SceneError(where, "bottom", entry["bottom"], "no bottom: the string starts at its body_point")
        span = float(np.linalg.norm(np.subtract(top, bottom)))
        # Unstretched length: by default the top-to-bottom distance (the string starts unstretched).
        if body_point is not None:
            length = read_float(entry, "length", where, 0.0, minimum=0.0)  # 0: set from the puppet's pose
        else:
            length = read_float(entry, "length", where, **({"default": span} if span > 0.0 else {}), positive=True)
        end = "tied" if body_point is not None else read_choice(entry, "bottom_end", where, ["free", "tied"], "free")
        tie_point = read_vec3(entry, "tie_point", where, bottom) if end == "tied" else None
        if end == "free" and "tie_point" in entry:
            raise SceneError(where, "tie_point", entry["tie_point"], "no tie_point unless bottom_end = \"tied\"")
        constants = {key: _read_constant(entry, key, where, defaults[key]) for key in _STRING_CONSTANTS}
        specs.append(StringSpec(name=name, top=top, bottom=bottom, length=length, tied=end == "tied",
                                tie_point=tie_point, **constants))
        body_points.append(body_point)
    for bar in bars:
        for name in bar.attach:
            if name not in names:
                raise SceneError(f"{source}: [bars.{bar.name}.attach]", name, list(bar.attach[name]),
                                 f"the name of a string, one of {sorted(names)}")
    return tuple(specs), tuple(body_points)


def _read_motion(table: Mapping[str, Any], where: str) -> StringMotion:
    check_keys(table, ["kind", "amplitude", "frequency"], where)
    kind = read_choice(table, "kind", where, ["still", "sway"], "still")
    amplitude = read_vec3(table, "amplitude", where, (0.0, 0.0, 0.0))
    frequency = read_float(table, "frequency", where, 0.5, minimum=0.0)
    return StringMotion(kind=kind, amplitude=amplitude, frequency=frequency)
