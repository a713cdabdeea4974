"""Penalty contacts of the puppet's shapes: ground plane, a static box (chair), a free ball.

Every contact is a point force between two bodies (or a body and the static world):

- normal: ``f_n = max(k d - c v_n, 0)`` for penetration ``d > 0`` ("hard"), or the smooth
  option ``f_n = k s + c sigma v_eps softplus(-v_n / v_eps)`` with
  ``s = delta softplus(d / delta)``, ``sigma = sigmoid(d / delta)`` (smooth gradients
  everywhere; a force ``k delta log 2`` acts at zero gap and it decays as
  ``exp(-gap / delta)``; the damping resists approach only, so the force is never
  attractive);
- friction: regularised Coulomb, ``f_t = -mu f_n v_t / sqrt(|v_t|^2 + v_eps^2)``.

The step treats the stiff parts implicitly like the string springs: the normal stiffness
and damping (``h c + h^2 k`` along ``n n^T``) and the friction's viscous slope
(``h mu f_n / sqrt(|v_t|^2 + v_eps^2)`` in the tangent plane) enter ``body_stiffness``, and
the force gets the matching ``- h k v_n n`` term. Between the puppet and the ball (two
moving bodies, whose coupling block would break the tree sparsity of the system matrix)
the force is instead made implicit through a conservative effective mass, with exactly
opposite forces on the two bodies, so momentum is conserved.

Effects not asked for are neither compiled nor launched: each contact kind is its own
kernel, and the hard/smooth choice is a compile-time closure.
"""


import functools
from dataclasses import dataclass

import numpy as np
import warp as wp

from dmarionette.kernels.articulation_math import (
    compute_point_inertia,
    compute_point_wrench,
    compute_smooth_norm,
    spatial6,
    spatial66,
)

__all__ = ["ContactConstants", "ContactSet", "ContactSettings", "GroundPlane", "StaticBox"]


@dataclass(frozen=True)
class ContactSettings:
    """Which contacts exist (compile-time) and their constants.

    Attributes:
        ground: contact with the plane ``y = ground_height``.
        ground_height: [m].
        chair: a static axis-aligned box ``(centre, half_extents)`` [m], or None.
        ball: contact between the puppet and the model's free ball (if it has one).
        smooth: softplus normal force (smooth gradients) instead of ``max(., 0)``.
        stiffness: normal stiffness per contact point [N/m].
        damping: normal damping per contact point [N s/m].
        friction: Coulomb coefficient.
        friction_velocity: regularisation velocity ``v_eps`` of the friction [m/s].
        smooth_distance: softplus width ``delta`` [m] (smooth option).
    """

    ground: bool = False
    ground_height: float = 0.0
    chair: tuple | None = None
    ball: bool = False
    smooth: bool = False
    stiffness: float = 2000.0
    damping: float = 5.0
    friction: float = 0.6
    friction_velocity: float = 0.01
    smooth_distance: float = 0.5e-3


@wp.struct
class ContactConstants:
    """The constants every contact kernel reads (from :class:`ContactSettings`), as one named parameter.

    Attributes:
        stiffness: normal stiffness per contact point [N/m].
        damping: normal damping per contact point [N s/m].
        friction: Coulomb coefficient.
        friction_velocity: regularisation velocity ``v_eps`` of the friction [m/s].
        smooth_distance: softplus width ``delta`` [m] (smooth option).
    """

    stiffness: wp.float64
    damping: wp.float64
    friction: wp.float64
    friction_velocity: wp.float64
    smooth_distance: wp.float64


@wp.func
def compute_softplus(x: wp.float64) -> wp.float64:
    """``log(1 + exp(x))`` without overflow.

    The value is ``max(x, 0) + log(1 + exp(-|x|))`` bit for bit, but written so that the tape
    differentiates it exactly everywhere: Warp's adjoints of ``max`` and ``abs`` at a tie
    (``max(0, 0)`` sends nothing to ``x``, ``abs'(0) = +1``) made that formula's derivative at
    exactly ``x = 0`` -0.5 instead of 0.5, and every smooth contact at rest (normal velocity
    exactly 0, the default start) has ``x = 0`` in its damping term. Here ``m = -|x|`` is a
    ``where`` whose ``x <= 0`` branch is ``x`` itself (slope +1 at 0), and the exponent is never
    positive (two ``where`` branches ``log(1 + exp(+-x))`` would overflow in the branch not
    taken, whose zero adjoint times ``inf`` is a NaN). ``tests/kernels/test_adjoint_switches.py``.
    """
    zero = wp.float64(0.0)
    m = wp.where(x > zero, -x, x)
    return wp.where(x > zero, x, zero) + wp.log(wp.float64(1.0) + wp.exp(m))


@wp.func
def compute_sigmoid(x: wp.float64) -> wp.float64:
    """``1 / (1 + exp(-x))`` with exponentials of ``-|x|`` only (finite gradient for any x)."""
    e = wp.exp(-wp.abs(x))
    return wp.where(x >= wp.float64(0.0), wp.float64(1.0) / (wp.float64(1.0) + e), e / (wp.float64(1.0) + e))


@wp.func
def compute_normal_hard(d: wp.float64, vn: wp.float64, k: wp.float64, c: wp.float64, delta: wp.float64,
                        v_eps: wp.float64):
    """Normal force and its stiffness and damping slopes, ``max(k d - c v_n, 0)`` when d > 0."""
    zero = wp.float64(0.0)
    fn = wp.where(d > zero, wp.max(k * d - c * vn, zero), zero)
    on = wp.where(fn > zero, wp.float64(1.0), zero)
    return fn, on * k, on * c


@wp.func
def compute_touching_hard(d: wp.float64) -> bool:
    """Whether a hard contact of penetration ``d`` can act: at ``d <= 0`` its force, its implicit
    block and their derivatives are all exactly zero (``compute_normal_hard``), so a kernel skips
    the point; most points of a puppet are apart most of the time (issue 19: the ground kernel
    was two thirds of a puppet step)."""
    return d > wp.float64(0.0)


@wp.func
def compute_touching_smooth(d: wp.float64) -> bool:
    """A smooth contact acts at every distance (its softplus force is never exactly zero)."""
    return True


@wp.func
def compute_normal_smooth(d: wp.float64, vn: wp.float64, k: wp.float64, c: wp.float64, delta: wp.float64,
                          v_eps: wp.float64):
    """Smooth normal force ``k s + c sigma v_eps softplus(-v_n / v_eps)`` and its slopes:
    softplus penetration, damping that only resists approach; every term >= 0 and
    vanishing away from contact."""
    s = delta * compute_softplus(d / delta)
    sig = compute_sigmoid(d / delta)
    fn = k * s + c * sig * v_eps * compute_softplus(-vn / v_eps)
    return fn, k * sig, c * sig * compute_sigmoid(-vn / v_eps)


def _contact_responses(normal_fn):
    """The two contact responses built on the normal force ``normal_fn`` (hard or smooth):
    against a static surface, and between two moving bodies."""

    @wp.func
    def compute_contact_terms(n: wp.vec3d, d: wp.float64, v_rel: wp.vec3d, contact: ContactConstants):
        """What both responses are made of: normal velocity ``v_n``, the normal force
        and its stiffness and damping slopes, the tangential velocity ``v_t`` and the
        friction's viscous coefficient ``mu f_n / sqrt(|v_t|^2 + v_eps^2)``."""
        k = contact.stiffness
        c = contact.damping
        mu = contact.friction
        v_eps = contact.friction_velocity
        delta = contact.smooth_distance
        vn = wp.dot(v_rel, n)
        fn, kn, cn = normal_fn(d, vn, k, c, delta, v_eps)
        vt = v_rel - vn * n
        ct = mu * fn / wp.sqrt(wp.dot(vt, vt) + v_eps * v_eps)
        return vn, fn, kn, cn, vt, ct

    @wp.func
    def compute_contact_response(
        p: wp.vec3d, n: wp.vec3d, d: wp.float64, v_rel: wp.vec3d, h: wp.float64,
        contact: ContactConstants,
    ):
        """Force on the body the normal points into, and its implicit 3x3 block."""
        vn, fn, kn, cn, vt, ct = compute_contact_terms(n, d, v_rel, contact)
        f = (fn - h * kn * vn) * n - ct * vt
        nn = wp.outer(n, n)
        A = (h * cn + h * h * kn) * nn + (h * ct) * (wp.identity(3, dtype=wp.float64) - nn)
        return f, A

    @wp.func
    def compute_pair_response(
        n: wp.vec3d, d: wp.float64, v_rel: wp.vec3d, h: wp.float64, m_eff: wp.float64,
        contact: ContactConstants,
    ) -> wp.vec3d:
        """Force between two moving bodies, implicit through an effective mass ``m_eff``:
        the force that the 1-D implicit step of a point of mass ``m_eff`` would feel, so
        that both bodies get exactly opposite impulses (momentum is conserved)."""
        vn, fn, kn, cn, vt, ct = compute_contact_terms(n, d, v_rel, contact)
        f_n = (fn - h * kn * vn) * m_eff / (m_eff + h * cn + h * h * kn)
        f_t = -ct * m_eff / (m_eff + h * ct)
        return f_n * n + f_t * vt

    return compute_contact_response, compute_pair_response


@wp.func
def compute_box_closest(u: wp.vec3d, half: wp.vec3d):
    """Signed distance of a point ``u`` (box frame) to a centred box, outward normal, and
    the closest surface point."""
    q = wp.vec3d(wp.clamp(u[0], -half[0], half[0]), wp.clamp(u[1], -half[1], half[1]), wp.clamp(u[2], -half[2], half[2]))
    dv = u - q
    outside = wp.dot(dv, dv) > wp.float64(0.0)
    dist = compute_smooth_norm(dv)
    n = dv / dist
    if not outside:
        # inside: the nearest face
        gap = half - wp.vec3d(wp.abs(u[0]), wp.abs(u[1]), wp.abs(u[2]))
        axis = int(0)
        if gap[1] < gap[axis]:
            axis = 1
        if gap[2] < gap[axis]:
            axis = 2
        sgn = wp.where(u[axis] < wp.float64(0.0), wp.float64(-1.0), wp.float64(1.0))
        n = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
        n[axis] = sgn
        dist = -gap[axis]
        q = u
        q[axis] = sgn * half[axis]
    return dist, n, q


@wp.struct
class GroundPlane:
    """The ground: the plane ``y = height`` [m], its outward normal up."""

    height: wp.float64


@wp.struct
class StaticBox:
    """A static axis-aligned box (the chair): centre and half extents [m]."""

    centre: wp.vec3d
    half: wp.vec3d


@wp.func
def compute_ground_distance(centre: wp.vec3d, ground: GroundPlane):
    """Signed distance of a point above the ground, and the ground's outward normal."""
    return centre[1] - ground.height, wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))


@wp.func
def compute_box_distance(centre: wp.vec3d, box: StaticBox):
    """Signed distance of a point outside a static box, and the box's outward normal there."""
    dist, n, q = compute_box_closest(centre - box.centre, box.half)
    return dist, n


def _static_surface_kernel(name: str, Surface, surface_distance, response, touching):
    """Builds the contact kernel of box corners and spheres against one kind of static surface
    (``Surface``, a struct, and its ``surface_distance(centre, surface) -> (dist, n)``); points
    where ``touching(d)`` is false add nothing."""

    @wp.kernel(module="unique", name=name)
    def eval_body_surface_contact(
        # Model:
        point_body: wp.array(dtype=wp.int32),
        point_local: wp.array(dtype=wp.vec3d),
        point_radius: wp.array(dtype=wp.float64),
        contact: ContactConstants,
        surface: Surface,
        # State in:
        body_pos: wp.array2d(dtype=wp.vec3d),
        body_rot: wp.array2d(dtype=wp.quatd),
        body_w: wp.array2d(dtype=wp.vec3d),
        body_v: wp.array2d(dtype=wp.vec3d),
        # Control:
        h: wp.float64,
        # State out:
        body_wrench: wp.array2d(dtype=spatial6),
        body_stiffness: wp.array2d(dtype=spatial66),
    ):
        """Box corners and spheres (``point_radius`` 0 for a corner) against a static surface:
        the ground plane or the chair's box."""
        w, i = wp.tid()
        b = point_body[i]
        x = body_pos[w, b]
        centre = x + wp.quat_rotate(body_rot[w, b], point_local[i])
        dist, n = surface_distance(centre, surface)
        d = point_radius[i] - dist
        if touching(d):
            p = centre - point_radius[i] * n
            v = body_v[w, b] + wp.cross(body_w[w, b], p - x)
            f, A = response(p, n, d, v, h, contact)
            wp.atomic_add(body_wrench, w, b, compute_point_wrench(p, f))
            wp.atomic_add(body_stiffness, w, b, compute_point_inertia(p, A))

    return eval_body_surface_contact


@functools.cache
def _kernels(smooth: bool):
    response, pair_response = _contact_responses(compute_normal_smooth if smooth else compute_normal_hard)
    touching = compute_touching_smooth if smooth else compute_touching_hard
    eval_body_ground_contact = _static_surface_kernel("eval_body_ground_contact", GroundPlane,
                                                      compute_ground_distance, response, touching)
    eval_body_box_contact = _static_surface_kernel("eval_body_box_contact", StaticBox, compute_box_distance,
                                                   response, touching)

    @wp.kernel(module="unique")
    def eval_body_ball_contact(
        # Model:
        pair_body: wp.array(dtype=wp.int32),
        pair_is_sphere: wp.array(dtype=wp.int32),
        pair_half: wp.array(dtype=wp.vec3d),
        pair_mass: wp.array(dtype=wp.float64),
        ball_body: int,
        ball_radius: wp.float64,
        contact: ContactConstants,
        # State in:
        body_pos: wp.array2d(dtype=wp.vec3d),
        body_rot: wp.array2d(dtype=wp.quatd),
        body_w: wp.array2d(dtype=wp.vec3d),
        body_v: wp.array2d(dtype=wp.vec3d),
        # Control:
        h: wp.float64,
        # State out:
        body_wrench: wp.array2d(dtype=spatial6),
        body_stiffness: wp.array2d(dtype=spatial66),
    ):
        """Puppet boxes and sphere against the free ball; equal and opposite forces."""
        w, i = wp.tid()
        b = pair_body[i]
        x = body_pos[w, b]
        rot = body_rot[w, b]
        c = body_pos[w, ball_body]
        u = wp.quat_rotate_inv(rot, c - x)
        half = pair_half[i]
        dist = wp.float64(0.0)
        n_local = wp.vec3d()
        q = wp.vec3d()
        if pair_is_sphere[i] != 0:
            dist = compute_smooth_norm(u)
            n_local = u / dist
            q = n_local * half[0]
            dist = dist - half[0]
        else:
            dist, n_local, q = compute_box_closest(u, half)
        n = wp.quat_rotate(rot, n_local)  # from the puppet body towards the ball
        p = x + wp.quat_rotate(rot, q)
        d = ball_radius - dist
        if touching(d):
            v_body = body_v[w, b] + wp.cross(body_w[w, b], p - x)
            v_ball = body_v[w, ball_body] + wp.cross(body_w[w, ball_body], p - c)
            f = pair_response(n, d, v_ball - v_body, h, pair_mass[i], contact)
            wp.atomic_add(body_wrench, w, ball_body, compute_point_wrench(p, f))
            wp.atomic_add(body_wrench, w, b, compute_point_wrench(p, -f))

    return eval_body_ground_contact, eval_body_box_contact, eval_body_ball_contact


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


class ContactSet:
    """Contact candidates of a model and the launchers of the contact kernels it asks for.

    Args:
        model: an :class:`~dmarionette.articulation.solver.ArticulationModel`; its ``contacts``
            settings say which kernels exist.
    """

    def __init__(self, model):
        self.model = model
        s: ContactSettings = model.contacts
        self.settings = s
        dev = model.device
        self.constants = ContactConstants()
        for name in ("stiffness", "damping", "friction", "friction_velocity", "smooth_distance"):
            setattr(self.constants, name, getattr(s, name))
        self.ground = GroundPlane()
        self.ground.height = s.ground_height
        self.chair = StaticBox()
        if s.chair is not None:
            self.chair.centre = wp.vec3d(*s.chair[0])
            self.chair.half = wp.vec3d(*s.chair[1])
        body, local, radius = [], [], []
        for b, (shape, size) in enumerate(model.body_shape):
            if not model.body_contact[b]:
                continue
            if shape == "sphere":
                body.append(b)
                local.append((0.0, 0.0, 0.0))
                radius.append(size[0])
            else:
                for corner in _CORNERS * (np.asarray(size) / 2):
                    body.append(b)
                    local.append(corner)
                    radius.append(0.0)
        self.point_count = len(body)
        self.point_body = wp.array(np.array(body, dtype=np.int32), dtype=wp.int32, device=dev)
        self.point_local = wp.array(np.array(local), dtype=wp.vec3d, device=dev)
        self.point_radius = wp.array(np.array(radius), dtype=wp.float64, device=dev)
        self.ball_body = model.body_names.index("ball") if model.ball is not None else -1
        pb, ps, ph, pm = [], [], [], []
        masses = model.body_mass.numpy()
        for b, (shape, size) in enumerate(model.body_shape):
            if b == self.ball_body or not model.body_contact[b]:
                continue
            pb.append(b)
            ps.append(1 if shape == "sphere" else 0)
            ph.append((size[0], 0.0, 0.0) if shape == "sphere" else tuple(np.asarray(size) / 2))
            if self.ball_body >= 0:
                # a quarter of the reduced mass: a lower bound on the effective mass at
                # the contact point (rotation lowers it), which keeps the step stable
                ma = masses[self.ball_body]
                pm.append(0.25 * ma * masses[b] / (ma + masses[b]))
        self.pair_count = len(pb)
        self.pair_body = wp.array(np.array(pb, dtype=np.int32), dtype=wp.int32, device=dev)
        self.pair_is_sphere = wp.array(np.array(ps, dtype=np.int32), dtype=wp.int32, device=dev)
        self.pair_half = wp.array(np.array(ph).reshape(-1, 3), dtype=wp.vec3d, device=dev)
        self.pair_mass = wp.array(np.array(pm or [0.0]), dtype=wp.float64, device=dev)
        self.any = s.ground or s.chair is not None or (s.ball and self.ball_body >= 0)
        if self.any:
            self.kernels = _kernels(bool(s.smooth))

    def launches(self, state, h) -> list[tuple[int, tuple[int, int], list]]:
        """The compiled-in contacts' launches for ``state``: ``(kernel index in`` :attr:`kernels`
        ``, dim, inputs)``, the outputs being ``state``'s ``body_wrench``, ``body_stiffness``
        (the plain pass and its tangent, ``articulation.step_tangent``, launch the same list)."""
        if not self.any:
            return []
        s = self.settings
        bodies = [state.body_pos, state.body_rot, state.body_w, state.body_v]
        pts = [self.point_body, self.point_local, self.point_radius, self.constants]
        out = []
        if s.ground:
            out.append((0, (state.world_count, self.point_count), [*pts, self.ground, *bodies, h]))
        if s.chair is not None:
            out.append((1, (state.world_count, self.point_count), [*pts, self.chair, *bodies, h]))
        if s.ball and self.ball_body >= 0:
            out.append((2, (state.world_count, self.pair_count),
                        [self.pair_body, self.pair_is_sphere, self.pair_half, self.pair_mass, self.ball_body,
                         wp.float64(self.model.ball.radius), self.constants, *bodies, h]))
        return out

    def eval(self, state, h) -> None:
        """Adds the contact forces and implicit blocks of ``state`` (kinematics filled)."""
        for kernel, dim, inputs in self.launches(state, h):
            wp.launch(self.kernels[kernel], dim=dim, inputs=inputs,
                      outputs=[state.body_wrench, state.body_stiffness], device=self.model.device)
