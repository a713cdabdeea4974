"""MJCF export of a puppet (and optional ball), loadable by MuJoCo.

The exported model has the same generalised coordinates, in the same order, as
:class:`dmarionette.articulation.solver.ArticulationModel`: a free root (``qpos`` = centre
position, quaternion ``w, x, y, z``; ``qvel`` = world linear velocity, body-frame angular
velocity), ball joints as quaternions with child-frame angular velocity, universal joints
as two hinges in axis order, hinges. Body frames sit at the centres of mass (``<inertial
pos="0 0 0">``), aligned with the world at rest; gravity is along -y.

Names: MuJoCo wants every body, joint and geom name unique within its kind, and ``world``
is its own. A puppet's names are kept as they are; the exporter's own elements (the
``ground`` geom, the ``root`` free joint, the ``ball`` body, joint and geom, the universal
joints' ``NAME_0``/``NAME_1`` hinges, a body called ``world``) take a ``_1``, ``_2``, ...
suffix where a puppet name already holds theirs. :func:`mjcf_names` says which MJCF name
each element got (to map MuJoCo's names back to the puppet's).
"""

from __future__ import annotations

import dataclasses
import math
from xml.sax.saxutils import quoteattr

from dmarionette.scene.puppet import PuppetDescription

__all__ = ["MjcfNames", "mjcf_names", "puppet_to_mjcf"]


@dataclasses.dataclass(frozen=True)
class MjcfNames:
    """The MJCF name of every exported element.

    Attributes:
        bodies: puppet body name -> MJCF body name (and, the same, its geom's name).
        joints: puppet joint name -> its MJCF joints (one; two hinges, in axis order, for a
            universal joint).
        root_joint: the root's free joint.
        ground: the ground plane geom.
        ball: the ball's body, free joint and geom names.
    """

    bodies: dict[str, str]
    joints: dict[str, tuple[str, ...]]
    root_joint: str
    ground: str
    ball: tuple[str, str, str]


class _Names:
    def __init__(self, taken=()):
        self.taken = set(taken)

    def take(self, name: str) -> str:
        unique, n = name, 0
        while unique in self.taken:
            n += 1
            unique = f"{name}_{n}"
        self.taken.add(unique)
        return unique


def mjcf_names(puppet: PuppetDescription) -> MjcfNames:
    """The MJCF names :func:`puppet_to_mjcf` gives a puppet's elements (see the module doc)."""
    bodies_ns, joints_ns, geoms_ns = _Names({"world"}), _Names(), _Names()
    bodies = {b.name: bodies_ns.take(b.name) for b in puppet.bodies}
    for name in bodies.values():
        geoms_ns.take(name)
    joints: dict[str, tuple[str, ...]] = {}
    for j in puppet.joints:  # the puppet's own joint names first
        if j.type in ("hinge", "ball"):
            joints[j.name] = (joints_ns.take(j.name),)
    for j in puppet.joints:
        if j.type not in ("hinge", "ball"):
            joints[j.name] = tuple(joints_ns.take(f"{j.name}_{k}") for k in range(len(j.axes)))
    root = joints_ns.take("root")
    ground = geoms_ns.take("ground")
    ball = (bodies_ns.take("ball"), joints_ns.take("ball"), geoms_ns.take("ball"))
    return MjcfNames(bodies=bodies, joints={j.name: joints[j.name] for j in puppet.joints}, root_joint=root,
                     ground=ground, ball=ball)


def _vec(v) -> str:
    return " ".join(repr(float(c)) for c in v)


def puppet_to_mjcf(
    puppet: PuppetDescription,
    *,
    ball=None,
    timestep: float = 1.0 / 30.0,
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0),
    joint_limits: bool = True,
    ground: bool = True,
) -> str:
    """MJCF text of a puppet.

    Args:
        puppet: the description.
        ball: a :class:`~dmarionette.articulation.solver.BallDescription` to add as a free body.
        timestep: MuJoCo ``timestep`` [s] (integrator ``Euler``, which matches ours when
            only joint damping is stiff).
        gravity: [m/s^2].
        joint_limits: export joint ranges as limited joints.
        ground: add a ground plane at y = 0.

    Returns:
        The XML string (``mujoco.MjModel.from_xml_string`` loads it); the names are
        :func:`mjcf_names`'s.

    Raises:
        ValueError: ``timestep`` not a finite positive number.
    """
    if not (math.isfinite(timestep) and timestep > 0.0):
        raise ValueError(f"puppet_to_mjcf: timestep = {timestep!r}; expected a finite step > 0 [s]")
    lines = [
        f"<mujoco model={quoteattr(puppet.name)}>",
        '  <compiler angle="radian" autolimits="false"/>',
        f'  <option gravity="{_vec(gravity)}" timestep="{timestep!r}" integrator="Euler"/>',
        "  <worldbody>",
    ]
    names = mjcf_names(puppet)
    if ground:
        # MuJoCo planes are z-normal; rotate +z onto +y.
        lines.append(f'    <geom name={quoteattr(names.ground)} type="plane" size="5 5 0.1" quat="0.7071067811865476 -0.7071067811865476 0 0"/>')
    children: dict[str, list] = {}
    for j in puppet.joints:
        children.setdefault(j.parent, []).append(j)
    bodies = {b.name: b for b in puppet.bodies}

    def geom(b, indent):
        if b.shape == "sphere":
            g = f'type="sphere" size="{b.size[0]!r}"'
        else:
            g = f'type="box" size="{_vec([s / 2 for s in b.size])}"'
        contact = "" if b.contact else ' contype="0" conaffinity="0"'
        return f'{indent}<geom name={quoteattr(names.bodies[b.name])} {g} mass="0"{contact}/>'

    def inertial(b, indent):
        return f'{indent}<inertial pos="0 0 0" mass="{b.mass!r}" diaginertia="{_vec(b.inertia)}"/>'

    def emit(name, pos, joint, depth):
        ind = "  " * (depth + 2)
        b = bodies[name]
        lines.append(f"{ind}<body name={quoteattr(names.bodies[name])} pos=\"{_vec(pos)}\">")
        if joint is None:
            lines.append(f'{ind}  <freejoint name={quoteattr(names.root_joint)}/>')
        elif joint.type == "ball":
            rng = f' limited="true" range="0 {joint.upper[0]!r}"' if joint_limits else ' limited="false"'
            lines.append(f'{ind}  <joint name={quoteattr(names.joints[joint.name][0])} type="ball" pos="{_vec(joint.anchor_child)}" '
                         f'damping="{joint.damping!r}"{rng}/>')
        else:
            for k, axis in enumerate(joint.axes):
                jname = names.joints[joint.name][k]
                rng = (f' limited="true" range="{joint.lower[k]!r} {joint.upper[k]!r}"' if joint_limits
                       else ' limited="false"')
                lines.append(f'{ind}  <joint name={quoteattr(jname)} type="hinge" pos="{_vec(joint.anchor_child)}" '
                             f'axis="{_vec(axis)}" damping="{joint.damping!r}"{rng}/>')
        lines.append(inertial(b, ind + "  "))
        lines.append(geom(b, ind + "  "))
        for j in children.get(name, []):
            rel = [j.anchor_parent[i] - j.anchor_child[i] for i in range(3)]
            emit(j.child, rel, j, depth + 1)
        lines.append(f"{ind}</body>")

    emit(puppet.root, puppet.root_position, None, 0)
    if ball is not None:
        i = 0.4 * ball.mass * ball.radius**2
        lines += [
            f'    <body name={quoteattr(names.ball[0])} pos="{_vec(ball.position)}">',
            f'      <freejoint name={quoteattr(names.ball[1])}/>',
            f'      <inertial pos="0 0 0" mass="{ball.mass!r}" diaginertia="{i!r} {i!r} {i!r}"/>',
            f'      <geom name={quoteattr(names.ball[2])} type="sphere" size="{ball.radius!r}" mass="0"/>',
            "    </body>",
        ]
    lines += ["  </worldbody>", "</mujoco>", ""]
    return "\n".join(lines)
