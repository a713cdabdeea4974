"""A reachability pre-check: targets no bar motion inside the device limits can reach.

Every string tied to the puppet keeps its tie point within the string's length of its attach
point on the bar: ``|tie - A| <= l (1 + STRETCH)`` (a string stretches much less than
``STRETCH`` under the puppet's weight; ``tests/fitting`` measures it). A puppet site ``p``
(a point or a body centre) is at most ``d(p, tie)`` from the tie point, ``d`` the shortest
path through the puppet's rigid bodies and joints (each body a rigid set of sites: its
centre, its joint anchors, its points; a joint joins its two anchors). So, for *every*
tied string at once,

    |p - A| <= l (1 + STRETCH) + d(p, tie),

with ``A`` anywhere its bar can take it: an authored bar's centre anywhere in the device
workspace box (its free coordinates, unbounded without a device; the others follow the
scene's path) plus the attach point's
distance from the centre (any rotation), a bar that is not authored along its scene path.
A target farther than that from the attach region of some string is unreachable, for every
bar motion, static or not; :func:`unreachable_targets` says by how much.

It is a sufficient test only: a target that passes it may still be out of reach (the
solve then finds that, see :mod:`fitting.author_solve`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .bar_spline import HermiteSpans, hermite_evaluate

__all__ = ["STRETCH", "TargetReach", "site_distances", "unreachable_targets"]

STRETCH = 0.25  # the largest relative stretch of a string allowed for by the bound


@dataclasses.dataclass(frozen=True)
class TargetReach:
    """An unreachable target: where and by how much.

    Attributes:
        keyframe: keyframe index (0-based); name: target name (a point, ``"NAME (body)"``).
        distance: distance from the target to the nearest point of the attach region [m].
        reach: the farthest the target's site can be from that attach point [m].
        string: the string that rules it out.
    """

    keyframe: int
    name: str
    distance: float
    reach: float
    string: str

    def sentence(self) -> str:
        return (f"{self.name}: the target is {self.distance:.3g} m from anywhere string {self.string}'s attach "
                f"point can go, and the puppet holds it within {self.reach:.3g} m of it (the string's length "
                f"with {STRETCH:.0%} stretch, plus the body between): unreachable by "
                f"{self.distance - self.reach:.3g} m")


def site_distances(puppet) -> tuple[list[tuple[str, np.ndarray]], np.ndarray]:
    """Sites of a puppet description and the shortest path lengths between them [m].

    Returns:
        ``sites``: ``(body, local position)`` per site (centres first, in body order, then
        joint anchors, then points); ``distances``: ``(N, N)``.
    """
    sites = [(b.name, np.zeros(3)) for b in puppet.bodies]
    for joint in puppet.joints:
        sites.append((joint.parent, np.asarray(joint.anchor_parent, float)))
        sites.append((joint.child, np.asarray(joint.anchor_child, float)))
    for point in puppet.points:
        sites.append((point.body, np.asarray(point.position, float)))
    n = len(sites)
    dist = np.full((n, n), np.inf)
    for i, (body_i, pos_i) in enumerate(sites):
        for j, (body_j, pos_j) in enumerate(sites):
            if body_i == body_j:
                dist[i, j] = float(np.linalg.norm(pos_i - pos_j))
    base = len(puppet.bodies)
    for k in range(len(puppet.joints)):
        a, b = base + 2 * k, base + 2 * k + 1
        dist[a, b] = dist[b, a] = 0.0
    for k in range(n):  # Floyd-Warshall (tens of sites)
        dist = np.minimum(dist, dist[:, k:k + 1] + dist[k:k + 1, :])
    return sites, dist


def _attach_regions(problem) -> dict[int, tuple[np.ndarray, np.ndarray, float]]:
    """String index -> ``(lo, hi, radius)``: its attach point lies within ``radius`` of the box."""
    param, objective = problem.param, problem.objective
    regions = {}
    authored = {a["index"]: a for a in param.authored}
    for s in range(param.string_count):
        regions[s] = (param.fixed_tops[:, s].min(axis=0), param.fixed_tops[:, s].max(axis=0), 0.0)
    for b, a in authored.items():
        path, _ = hermite_evaluate(HermiteSpans.make(a["knots"], param.times), a["initial"][:, :3])
        path = np.asarray(path)
        lo, hi = path.min(axis=0), path.max(axis=0)
        free = [d for d in a["free"] if d < 3]
        lo, hi = lo.copy(), hi.copy()
        if free and objective.limits is None:
            lo[free], hi[free] = -np.inf, np.inf  # no device: a free coordinate goes anywhere
        elif free:
            box_lo, box_hi = objective.boxes[a["name"]]
            lo[free], hi[free] = box_lo[free], box_hi[free]
        for s, local in zip(a["strings"], a["local"]):
            regions[int(s)] = (lo, hi, float(np.linalg.norm(local)))
    return regions


def unreachable_targets(problem) -> list[TargetReach]:
    """The targets of ``problem``'s keyframes that fail the bound (see the module)."""
    spec, model = problem.spec, problem.model
    puppet = spec.scene.puppet
    sites, dist = site_distances(puppet)
    body_site = {b.name: i for i, b in enumerate(puppet.bodies)}
    base = len(puppet.bodies) + 2 * len(puppet.joints)
    point_site = {p.name: base + i for i, p in enumerate(puppet.points)}
    regions = _attach_regions(problem)
    lengths = np.array([s.length for s in model.strings.specs], dtype=np.float64)
    names = [s.name for s in model.strings.specs]
    ties = {s: point_site[model.puppet.point_names[p]] for s, p in enumerate(model.string_point) if p >= 0}
    out = []
    for k, pose in enumerate(spec.keyframes):
        targets = [(n, point_site[n], v) for n, v in pose.points.items()]
        targets += [(f"{n} (body)", body_site[n], v) for n, v in pose.bodies.items()]
        for label, site, value in targets:
            worst = None
            for s, tie in ties.items():
                if s not in regions:
                    continue
                lo, hi, radius = regions[s]
                gap = np.maximum(np.maximum(lo - value, value - hi), 0.0)
                distance = max(float(np.linalg.norm(gap)) - radius, 0.0)
                reach = lengths[s] * (1.0 + STRETCH) + float(dist[site, tie])
                if distance > reach and (worst is None or distance - reach > worst.distance - worst.reach):
                    worst = TargetReach(keyframe=k, name=label, distance=distance, reach=reach, string=names[s])
            if worst is not None:
                out.append(worst)
    return out
