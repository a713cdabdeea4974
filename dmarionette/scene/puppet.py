"""The puppet as data: bodies, joints, string attach points, contact shapes.

A puppet is a tree of rigid bodies hung from one free root body. It is read from the
``[puppet]`` table of a scene file (see ``dmarionette/scene/builtin/puppet.toml`` for the
default, the paper's marionette, and ``docs/puppet.md`` for its numbers)::

    [puppet]
    root = "torso"                      # the free body
    root_position = [0.0, 0.39, 0.0]    # its centre of mass at rest [m]

    [puppet.bodies.torso]
    shape = "box"                       # "box" or "sphere"
    size = [0.14, 0.18, 0.07]           # box: full extents [m]; sphere: [radius, 0, 0]
    mass = 0.30                         # [kg]
    # inertia = [ixx, iyy, izz]         # principal moments about the centre [kg m^2];
                                        # default from shape and mass
    # contact = true                    # whether the shape collides

    [puppet.joints.knee_left]
    type = "hinge"                      # "ball", "universal" (two axes) or "hinge"
    parent = "upper_leg_left"
    child = "lower_leg_left"
    axes = [[1.0, 0.0, 0.0]]            # hinge: one axis, universal: two (body frame)
    anchor_parent = [0.0, -0.07, 0.0]   # joint centre in the parent's frame [m]
    anchor_child = [0.0, 0.07, 0.0]     # joint centre in the child's frame [m]
    lower_deg = [-5.0]                  # per axis [deg]; ball joints: cone_deg = 60.0
    upper_deg = [150.0]
    damping = 0.002                     # [N m s/rad]

    [puppet.points.hand_left]
    body = "lower_arm_left"
    position = [0.0, -0.055, 0.0]       # in the body frame [m]

Conventions: every body frame has its origin at the body's centre of mass and its axes
along the shape's axes; at rest (all joint coordinates zero) every body frame is aligned
with the world frame, so the rest position of a child is
``parent_position + anchor_parent - anchor_child``. The y axis points up.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dmarionette.scene.fields import (
    SceneError,
    check_keys,
    read_bool,
    read_choice,
    read_float,
    read_str,
    read_table,
    read_toml_file,
    read_vec3,
)

__all__ = [
    "BodyDescription",
    "JointDescription",
    "PointDescription",
    "PuppetDescription",
    "default_puppet_path",
    "load_puppet",
    "puppet_from_table",
]

JOINT_AXIS_COUNT = {"ball": 0, "universal": 2, "hinge": 1}
"""Number of rotation axes each joint type lists (a ball joint has none)."""

_BODY_KEYS = ("shape", "size", "mass", "inertia", "contact")
_JOINT_KEYS = (
    "type", "parent", "child", "axes", "anchor_parent", "anchor_child",
    "lower_deg", "upper_deg", "cone_deg", "damping",
)
_POINT_KEYS = ("body", "position")
_PUPPET_KEYS = ("name", "root", "root_position", "bodies", "joints", "points")


@dataclass(frozen=True)
class BodyDescription:
    """One rigid body.

    Attributes:
        name: unique body name.
        shape: ``"box"`` or ``"sphere"`` (also the contact shape).
        size: box full extents ``(sx, sy, sz)`` [m], or ``(radius, 0, 0)`` for a sphere.
        mass: [kg], > 0.
        inertia: principal moments about the centre of mass in the body frame
            ``(ixx, iyy, izz)`` [kg m^2], each > 0.
        contact: whether the shape takes part in contacts.
    """

    name: str
    shape: str
    size: tuple[float, float, float]
    mass: float
    inertia: tuple[float, float, float]
    contact: bool = True


@dataclass(frozen=True)
class JointDescription:
    """One joint between a parent and a child body.

    Attributes:
        name: unique joint name.
        type: ``"ball"``, ``"universal"`` or ``"hinge"``.
        parent, child: body names.
        axes: unit rotation axes in the child frame (= parent frame at rest); none for a
            ball joint, two for a universal joint (applied in order), one for a hinge.
        anchor_parent: joint centre in the parent frame [m].
        anchor_child: joint centre in the child frame [m].
        lower, upper: per-axis limits [rad]; for a ball joint one value each:
            ``lower = (0,)`` and ``upper = (cone,)``, the largest rotation angle.
        damping: viscous joint damping [N m s/rad], >= 0.
    """

    name: str
    type: str
    parent: str
    child: str
    axes: tuple[tuple[float, float, float], ...]
    anchor_parent: tuple[float, float, float]
    anchor_child: tuple[float, float, float]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    damping: float


@dataclass(frozen=True)
class PointDescription:
    """A named point on a body (a string attach point).

    Attributes:
        name: point name (``head``, ``back``, ``hand_left`` ...).
        body: body name.
        position: in the body frame [m].
    """

    name: str
    body: str
    position: tuple[float, float, float]


@dataclass(frozen=True)
class PuppetDescription:
    """A tree-shaped puppet, validated.

    Attributes:
        name: puppet name.
        root: name of the free root body.
        root_position: world position of the root's centre of mass at rest [m].
        bodies: bodies in depth-first order from the root (every parent before its
            children; the order of an MJCF body tree).
        joints: one joint per non-root body, in the same order as ``bodies[1:]``.
        points: named attach points.
    """

    name: str
    root: str
    root_position: tuple[float, float, float]
    bodies: tuple[BodyDescription, ...]
    joints: tuple[JointDescription, ...]
    points: tuple[PointDescription, ...]

    def body_index(self, name: str) -> int:
        """Index of body ``name`` in :attr:`bodies`."""
        return [b.name for b in self.bodies].index(name)

    def parent_index(self) -> list[int]:
        """Parent body index per body (-1 for the root)."""
        names = [b.name for b in self.bodies]
        return [-1] + [names.index(j.parent) for j in self.joints]

    def rest_positions(self) -> list[tuple[float, float, float]]:
        """World positions of the body centres at rest (all joint coordinates zero) [m]."""
        pos = [self.root_position]
        for j in self.joints:
            p = pos[self.body_index(j.parent)]
            pos.append(tuple(p[i] + j.anchor_parent[i] - j.anchor_child[i] for i in range(3)))
        return pos

    def total_mass(self) -> float:
        """Sum of the body masses [kg]."""
        return sum(b.mass for b in self.bodies)


def default_puppet_path() -> Path:
    """Path of the default puppet scene, ``dmarionette/scene/builtin/puppet.toml``."""
    return Path(__file__).parent / "builtin" / "puppet.toml"


def load_puppet(path: str | Path | None = None) -> PuppetDescription:
    """Reads the ``[puppet]`` table of a TOML scene file (default: the paper's marionette).

    Raises:
        SceneError: when the file lacks a ``[puppet]`` table or the table is malformed.
    """
    path = Path(path) if path is not None else default_puppet_path()
    data = read_toml_file(path, "an existing puppet TOML file")
    table = read_table(data, "puppet", f"{path}")
    return puppet_from_table(table, f"{path}: [puppet]")


def _default_inertia(shape: str, size: tuple[float, float, float], mass: float):
    if shape == "sphere":
        i = 0.4 * mass * size[0] ** 2
        return (i, i, i)
    sx, sy, sz = size
    return (mass * (sy * sy + sz * sz) / 12.0, mass * (sx * sx + sz * sz) / 12.0,
            mass * (sx * sx + sy * sy) / 12.0)


def _read_numbers(table: Mapping[str, Any], key: str, where: str, count: int, default=None):
    value = table.get(key, default)
    ok = (
        isinstance(value, (list, tuple))
        and len(value) == count
        and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in value)
    )
    if not ok:
        raise SceneError(where, key, value, f"a list of {count} numbers")
    if not all(math.isfinite(float(c)) for c in value):
        raise SceneError(where, key, value, f"{count} finite numbers (no NaN or infinity)")
    return tuple(float(c) for c in value)


def _read_body(name: str, table: Mapping[str, Any], where: str) -> BodyDescription:
    if not isinstance(table, Mapping):
        raise SceneError(where, name, table, "a table describing a body")
    where = f"{where}.{name}"
    check_keys(table, _BODY_KEYS, where)
    shape = read_choice(table, "shape", where, ("box", "sphere"))
    size = read_vec3(table, "size", where)
    needed = size if shape == "box" else size[:1]
    if not all(s > 0.0 for s in needed):
        what = "three extents > 0 [m]" if shape == "box" else "[radius > 0, 0, 0] [m]"
        raise SceneError(where, "size", list(size), what)
    mass = read_float(table, "mass", where, positive=True)
    if "inertia" in table:
        inertia = read_vec3(table, "inertia", where)
        if not all(i > 0.0 for i in inertia):
            raise SceneError(where, "inertia", list(inertia), "three moments > 0 [kg m^2]")
        a, b, c = inertia
        if a + b < c or b + c < a or a + c < b:
            raise SceneError(where, "inertia", list(inertia),
                             "moments satisfying the triangle inequality (a physical body)")
    else:
        inertia = _default_inertia(shape, size, mass)
    contact = read_bool(table, "contact", where, True)
    return BodyDescription(name, shape, size, mass, inertia, contact)


def _read_joint(name: str, table: Mapping[str, Any], where: str) -> JointDescription:
    if not isinstance(table, Mapping):
        raise SceneError(where, name, table, "a table describing a joint")
    where = f"{where}.{name}"
    check_keys(table, _JOINT_KEYS, where)
    jtype = read_choice(table, "type", where, tuple(JOINT_AXIS_COUNT))
    parent = read_str(table, "parent", where)
    child = read_str(table, "child", where)
    n = JOINT_AXIS_COUNT[jtype]
    axes: list[tuple[float, float, float]] = []
    if n:
        raw = table.get("axes")
        if not isinstance(raw, list) or len(raw) != n:
            raise SceneError(where, "axes", raw, f"a list of {n} axis vector(s) for a {jtype} joint")
        for a in raw:
            v = read_vec3({"axes": a}, "axes", where)
            norm = math.sqrt(sum(c * c for c in v))
            if not norm > 1e-9:
                raise SceneError(where, "axes", raw, "non-zero axis vectors")
            axes.append(tuple(c / norm for c in v))
        if n == 2 and abs(sum(axes[0][i] * axes[1][i] for i in range(3))) > 1.0 - 1e-6:
            raise SceneError(where, "axes", raw, "two non-parallel axes for a universal joint")
    elif "axes" in table:
        raise SceneError(where, "axes", table["axes"], "no axes for a ball joint")
    anchor_parent = read_vec3(table, "anchor_parent", where)
    anchor_child = read_vec3(table, "anchor_child", where)
    if jtype == "ball":
        if "lower_deg" in table or "upper_deg" in table:
            key = "lower_deg" if "lower_deg" in table else "upper_deg"
            raise SceneError(where, key, table[key], "cone_deg (not per-axis limits) for a ball joint")
        cone = read_float(table, "cone_deg", where, 180.0, positive=True, maximum=180.0)
        lower, upper = (0.0,), (math.radians(cone),)
    else:
        if "cone_deg" in table:
            raise SceneError(where, "cone_deg", table["cone_deg"], "lower_deg/upper_deg for a "
                             f"{jtype} joint (cone_deg is for ball joints)")
        lo = _read_numbers(table, "lower_deg", where, n, [-180.0] * n)
        hi = _read_numbers(table, "upper_deg", where, n, [180.0] * n)
        for i in range(n):
            if lo[i] > hi[i]:
                raise SceneError(where, "lower_deg", list(lo),
                                 f"lower <= upper on every axis (axis {i}: upper is {hi[i]})")
        lower = tuple(math.radians(v) for v in lo)
        upper = tuple(math.radians(v) for v in hi)
    damping = read_float(table, "damping", where, 0.0, minimum=0.0)
    return JointDescription(name, jtype, parent, child, tuple(axes), anchor_parent,
                            anchor_child, lower, upper, damping)


def puppet_from_table(table: Mapping[str, Any], where: str) -> PuppetDescription:
    """Builds and validates a puppet from a ``[puppet]`` table.

    Args:
        table: the parsed ``[puppet]`` table.
        where: the file and table for error messages, e.g. ``"scene.toml: [puppet]"``.

    Returns:
        The validated description, bodies in topological order.

    Raises:
        SceneError: unknown keys, NaN, non-positive mass/inertia/size, lower > upper,
            a joint naming a missing body, a body with two parents, a cycle, more than
            one root, a body not connected to the root.
    """
    check_keys(table, _PUPPET_KEYS, where)
    name = read_str(table, "name", where, "puppet")
    root = read_str(table, "root", where)
    root_position = read_vec3(table, "root_position", where)
    bodies_t = read_table(table, "bodies", where)
    joints_t = read_table(table, "joints", where, {})
    points_t = read_table(table, "points", where, {})
    bwhere, jwhere, pwhere = f"{where}.bodies", f"{where}.joints", f"{where}.points"

    bodies = {n: _read_body(n, t, bwhere) for n, t in bodies_t.items()}
    if not bodies:
        raise SceneError(where, "bodies", {}, "at least one body")
    if root not in bodies:
        raise SceneError(where, "root", root, f"the name of a body, one of {sorted(bodies)}")
    joints = {n: _read_joint(n, t, jwhere) for n, t in joints_t.items()}

    parent_joint: dict[str, JointDescription] = {}
    for j in joints.values():
        for key in ("parent", "child"):
            body = getattr(j, key)
            if body not in bodies:
                raise SceneError(f"{jwhere}.{j.name}", key, body,
                                 f"the name of a body, one of {sorted(bodies)}")
        if j.parent == j.child:
            raise SceneError(f"{jwhere}.{j.name}", "child", j.child,
                             "a body other than the parent (a joint cannot join a body to itself)")
        if j.child == root:
            raise SceneError(f"{jwhere}.{j.name}", "child", j.child,
                             f"a body other than the root '{root}' (the root is free; "
                             "it has no parent)")
        if j.child in parent_joint:
            raise SceneError(f"{jwhere}.{j.name}", "child", j.child,
                             f"a body with one parent (joint '{parent_joint[j.child].name}' "
                             "already names it as child)")
        parent_joint[j.child] = j

    orphans = sorted(set(bodies) - set(parent_joint) - {root})
    if orphans:
        raise SceneError(where, "root", root,
                         f"the only root: bodies {orphans} have no parent joint "
                         "(exactly one root per puppet)")

    # Depth-first walk from the root (the body order of an MJCF tree, so that exported
    # coordinates come in the same order); a body not reached lies on a cycle (each body
    # has one parent).
    children: dict[str, list[str]] = {}
    for j in joints.values():
        children.setdefault(j.parent, []).append(j.child)
    order: list[str] = []
    stack = [root]
    while stack:
        body = stack.pop()
        order.append(body)
        stack.extend(reversed(children.get(body, [])))
    if len(order) != len(bodies):
        cyc = sorted(set(bodies) - set(order))
        raise SceneError(jwhere, parent_joint[cyc[0]].name, cyc,
                         "a tree: these bodies form a cycle, not connected to the root "
                         f"'{root}'")

    points = []
    for pname, pt in points_t.items():
        w = f"{pwhere}.{pname}"
        if not isinstance(pt, Mapping):
            raise SceneError(pwhere, pname, pt, "a table with body and position")
        check_keys(pt, _POINT_KEYS, w)
        body = read_str(pt, "body", w)
        if body not in bodies:
            raise SceneError(w, "body", body, f"the name of a body, one of {sorted(bodies)}")
        points.append(PointDescription(pname, body, read_vec3(pt, "position", w)))

    return PuppetDescription(
        name=name,
        root=root,
        root_position=root_position,
        bodies=tuple(bodies[n] for n in order),
        joints=tuple(parent_joint[n] for n in order[1:]),
        points=tuple(points),
    )
