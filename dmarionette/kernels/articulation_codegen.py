"""Kernels specialised to one articulation topology, written out as straight-line Warp code.

A puppet has a fixed tree per model, so its kinematics, composite-rigid-body mass matrix,
recursive Newton-Euler bias forces and the tree-sparse Cholesky (``L^T L``) factorisation
are unrolled here into one straight-line kernel per pass, with the tree baked in as
constants. Straight-line (SSA) code is what Warp differentiates exactly: no dynamic loop,
no value written twice. The generated source is written to a cache folder (named by its
hash) and imported, so Warp compiles it once per topology and caches the binary.

Generated kernels (one thread per world):

- ``eval_body_kinematics``: joint coordinates -> body poses and velocities.
- ``solve_body_dynamics``: ``(M + h D + h^2 K) qdd = tau`` and ``qd_out = qd + h qdd``
  (``h_implicit`` = h, or 0 for the explicit comparison step).
- ``integrate_joint_coordinates``: ``q_out = q (+) h qd_out`` (quaternions on the sphere).
- ``eval_mass_matrix``: the joint-space mass matrix (tests and inspection).

The emitted code reads like the algorithms in Featherstone, *Rigid Body Dynamics
Algorithms* (2008): CRBA (Table 6.2), LTL factorisation and solves (Tables 6.3, 6.4), all
quantities in world coordinates about the world origin (see ``articulation_math``).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ArticulationTopology", "Emitter", "JointTopology", "build_articulation_kernels", "import_generated"]

_CACHE: dict[str, object] = {}


@dataclass(frozen=True)
class JointTopology:
    """The joint that attaches one body to its parent (or to the world for a root).

    Attributes:
        type: ``"free"``, ``"ball"``, ``"universal"`` or ``"hinge"``.
        parent: parent body index, -1 for a free root.
        q_start, qd_start: first coordinate and first velocity index.
        axes: rotation axes in the child frame (universal: two, hinge: one).
        anchor_parent, anchor_child: joint centre in parent / child frame [m].
        lower, upper: limits per axis [rad] (ball: ``(0,)``, ``(cone,)``); empty for free.
    """

    type: str
    parent: int
    q_start: int
    qd_start: int
    axes: tuple = ()
    anchor_parent: tuple = (0.0, 0.0, 0.0)
    anchor_child: tuple = (0.0, 0.0, 0.0)
    lower: tuple = ()
    upper: tuple = ()


# Joint limits: the band [rad] before a limit over which its implicit part is switched on
# (``_limits``). 1e-3 rad made the step so steep in ``q`` that calibration's finite-difference
# fit (``tests/fitting/test_calibration.py``) missed a string's k by 5 standard errors and its k_d by 8;
# at 5e-2 rad (2.9 deg) it recovers every constant within 1.8 of them.
LIMIT_BAND = 5e-2
# The one-sided look-ahead (issue 13, ``_limits`` and ``_limit_brake``): the start band is
# switched off by a start velocity away from the limit over LIMIT_AWAY_SPEED [rad/s]
# (``clamp(1 + qd / LIMIT_AWAY_SPEED, 0, 1)`` at an upper limit), and a brake judged by the
# step's *end* angle (a trial solve) keeps that angle LIMIT_INNER [rad] before the limit.
# LIMIT_BRAKE_GAP [rad] is the least gap the brake's weight is computed with, and
# LIMIT_BRAKE_MAX its largest weight (1: the limit's whole implicit part, ``c + k h``). The
# last two are set from the hard cases (docs/puppet.md, "Joint limits"): a brake as strong
# as the closed form asks (weights up to 1e3) or as steep as a 1e-2 rad gap makes it lets
# the coupling's trial step and the real step brake differently, and the stiff ties take up
# the difference (+8 J over the bars' jerks at 4.6 m/s); up to 1 it lets a foot turned round
# by the ground within a step go 0.81 rad through its limit.
LIMIT_AWAY_SPEED = 1e-1
LIMIT_INNER = 1e-2
LIMIT_BRAKE_GAP = 3e-2
LIMIT_BRAKE_MAX = 2.0

_Q_COUNT = {"free": 7, "ball": 4, "universal": 2, "hinge": 1}
_QD_COUNT = {"free": 6, "ball": 3, "universal": 2, "hinge": 1}


@dataclass(frozen=True)
class ArticulationTopology:
    """A forest of bodies (one joint per body, parents first) and compile-time switches.

    Attributes:
        joints: per body, in body order.
        joint_limits: whether joint limits are compiled in.
        one_sided_limits: the one-sided look-ahead (issue 13; ``_limits``, ``_limit_brake``;
            the default); False: the two-sided band, which also brakes motion away from a
            limit (``docs/puppet.md``, "Joint limits").
    """

    joints: tuple[JointTopology, ...]
    joint_limits: bool = True
    one_sided_limits: bool = True

    @property
    def body_count(self) -> int:
        return len(self.joints)

    @property
    def q_count(self) -> int:
        return sum(_Q_COUNT[j.type] for j in self.joints)

    @property
    def qd_count(self) -> int:
        return sum(_QD_COUNT[j.type] for j in self.joints)

    def dof_body(self) -> list[int]:
        """Body index per velocity dof."""
        return [b for b, j in enumerate(self.joints) for _ in range(_QD_COUNT[j.type])]

    def dof_parent(self) -> list[int]:
        """Featherstone's lambda: the previous dof on the path to the root (-1 at a root)."""
        lam = []
        last = {}  # body -> its last dof
        for b, j in enumerate(self.joints):
            prev = last[j.parent] if j.parent >= 0 else -1
            for k in range(_QD_COUNT[j.type]):
                lam.append(prev)
                prev = j.qd_start + k
            last[b] = prev
        return lam


def _axes(j: JointTopology) -> list[tuple[int, str]]:
    """Each axis of a hinge or universal joint ``j``: its dof and its coordinate's expression."""
    return [(j.qd_start + k, f"joint_q[w, {j.q_start + k}]") for k in range(len(j.axes))]


def _f(x: float) -> str:
    return f"wp.float64({float(x)!r})"


def _v(x) -> str:
    return f"wp.vec3d({_f(x[0])}, {_f(x[1])}, {_f(x[2])})"


_E = ("wp.vec3d(one, zero, zero)", "wp.vec3d(zero, one, zero)", "wp.vec3d(zero, zero, one)")

# Parameter lines the generated kernels' signatures share (the signatures are laid out as
# ``tools/lint_kernels.py`` checks: Model, State in, Control, State out).
_BODY_MODEL = """    body_mass: wp.array(dtype=wp.float64),
    body_inertia: wp.array(dtype=wp.vec3d),
"""
_JOINT_STATE = """    joint_q: wp.array2d(dtype=wp.float64),
    joint_qd: wp.array2d(dtype=wp.float64),
"""
_BODY_POSE = """    body_pos: wp.array2d(dtype=wp.vec3d),
    body_rot: wp.array2d(dtype=wp.quatd),
"""
_BODY_VELOCITY = """    body_w: wp.array2d(dtype=wp.vec3d),
    body_v: wp.array2d(dtype=wp.vec3d),
"""

_HEADER = '''# Generated by dmarionette.kernels.articulation_codegen; do not edit.
import warp as wp
from dmarionette.kernels.articulation_math import (
    spatial6, spatial66, compute_spatial, compute_top, compute_bottom,
    compute_rotation_motion, compute_cross_motion, compute_cross_force,
    compute_spatial_inertia, compute_quat_from_mj, compute_quat_integrate,
    compute_smooth_norm,
)
'''


class Emitter:
    def __init__(self, topo: ArticulationTopology):
        self.t = topo
        self.lines: list[str] = []
        self.solve: dict | None = None  # the last kernel's linear solve (see _factor_and_solve)

    def __call__(self, line: str) -> None:
        self.lines.append("    " + line)

    def begin(self, constants: bool = True) -> None:
        """Starts a kernel body: the thread index ``w`` and (``constants``) float64 ``zero``, ``one``."""
        self.lines = []
        self.solve = None
        self("w = wp.tid()")
        if constants:
            self("zero = wp.float64(0.0)")
            self("one = wp.float64(1.0)")

    def kernel(self, signature: str) -> str:
        """The kernel's source: ``signature`` (decorator, def line, docstring), then the body
        emitted since :meth:`begin`."""
        return signature + "\n".join(self.lines) + "\n"

    # -------------------------------------------------------------- kinematics
    def kinematics(self) -> str:
        e = self
        e.begin()
        for b, j in enumerate(self.t.joints):
            s, d = j.q_start, j.qd_start
            q = [f"joint_q[w, {s + i}]" for i in range(_Q_COUNT[j.type])]
            qd = [f"joint_qd[w, {d + i}]" for i in range(_QD_COUNT[j.type])]
            if j.type == "free":
                e(f"x{b} = wp.vec3d({q[0]}, {q[1]}, {q[2]})")
                e(f"r{b} = compute_quat_from_mj({q[3]}, {q[4]}, {q[5]}, {q[6]})")
                e(f"v{b} = wp.vec3d({qd[0]}, {qd[1]}, {qd[2]})")
                e(f"w{b} = wp.quat_rotate(r{b}, wp.vec3d({qd[3]}, {qd[4]}, {qd[5]}))")
            else:
                p = j.parent
                e(f"an{b} = x{p} + wp.quat_rotate(r{p}, {_v(j.anchor_parent)})")
                e(f"va{b} = v{p} + wp.cross(w{p}, an{b} - x{p})")
                if j.type == "hinge":
                    a = _v(j.axes[0])
                    e(f"r{b} = r{p} * wp.quat_from_axis_angle({a}, {q[0]})")
                    e(f"w{b} = w{p} + wp.quat_rotate(r{p}, {a}) * {qd[0]}")
                elif j.type == "universal":
                    a1, a2 = _v(j.axes[0]), _v(j.axes[1])
                    e(f"rm{b} = r{p} * wp.quat_from_axis_angle({a1}, {q[0]})")
                    e(f"r{b} = rm{b} * wp.quat_from_axis_angle({a2}, {q[1]})")
                    e(f"w{b} = w{p} + wp.quat_rotate(r{p}, {a1}) * {qd[0]} + wp.quat_rotate(rm{b}, {a2}) * {qd[1]}")
                else:  # ball
                    e(f"r{b} = r{p} * compute_quat_from_mj({q[0]}, {q[1]}, {q[2]}, {q[3]})")
                    e(f"w{b} = w{p} + wp.quat_rotate(r{b}, wp.vec3d({qd[0]}, {qd[1]}, {qd[2]}))")
                e(f"x{b} = an{b} - wp.quat_rotate(r{b}, {_v(j.anchor_child)})")
                e(f"v{b} = va{b} + wp.cross(w{b}, x{b} - an{b})")
            e(f"body_pos[w, {b}] = x{b}")
            e(f"body_rot[w, {b}] = r{b}")
            e(f"body_w[w, {b}] = w{b}")
            e(f"body_v[w, {b}] = v{b}")
        sig = f"""@wp.kernel
def eval_body_kinematics(
    # State in:
{_JOINT_STATE}    # State out:
{_BODY_POSE}{_BODY_VELOCITY}):
    \"\"\"Forward kinematics: body centre positions, orientations, angular and linear velocities (world).\"\"\"
"""
        return self.kernel(sig)

    # -------------------------------------------------------------- shared parts
    def _read_bodies(self, with_velocity: bool) -> None:
        e = self
        for b in range(self.t.body_count):
            e(f"x{b} = body_pos[w, {b}]")
            e(f"r{b} = body_rot[w, {b}]")
            if with_velocity:
                e(f"w{b} = body_w[w, {b}]")
                e(f"V{b} = compute_spatial(w{b}, body_v[w, {b}] - wp.cross(w{b}, x{b}))")
            e(f"I{b} = compute_spatial_inertia(body_mass[{b}], body_inertia[{b}], r{b}, x{b})")

    def _motion_subspace(self, with_velocity: bool) -> None:
        """S{j} per dof (world, about the origin) and c{j} = dS_j/dt qd_j."""
        e = self
        for b, j in enumerate(self.t.joints):
            d = j.qd_start
            if j.type == "free":
                for k in range(3):
                    e(f"S{d + k} = compute_spatial(wp.vec3d(zero, zero, zero), {_E[k]})")
                for k in range(3):
                    e(f"S{d + 3 + k} = compute_rotation_motion(wp.quat_rotate(r{b}, {_E[k]}), x{b})")
                moving = [None, None, None, f"V{b}", f"V{b}", f"V{b}"]
            else:
                p = j.parent
                e(f"an{b} = x{p} + wp.quat_rotate(r{p}, {_v(j.anchor_parent)})")
                if j.type == "hinge":
                    e(f"S{d} = compute_rotation_motion(wp.quat_rotate(r{b}, {_v(j.axes[0])}), an{b})")
                    moving = [f"V{p}"]
                elif j.type == "universal":
                    e(f"S{d} = compute_rotation_motion(wp.quat_rotate(r{p}, {_v(j.axes[0])}), an{b})")
                    e(f"S{d + 1} = compute_rotation_motion(wp.quat_rotate(r{b}, {_v(j.axes[1])}), an{b})")
                    moving = [f"V{p}", f"V{b}"]
                else:
                    for k in range(3):
                        e(f"S{d + k} = compute_rotation_motion(wp.quat_rotate(r{b}, {_E[k]}), an{b})")
                    moving = [f"V{b}"] * 3
            if with_velocity:
                for k, m in enumerate(moving):
                    e(f"qd{d + k} = joint_qd[w, {d + k}]")
                    if m is not None:
                        e(f"c{d + k} = compute_cross_motion({m}, S{d + k}) * qd{d + k}")

    def _crba(self, with_stiffness: bool) -> dict:
        """Composite inertias and the lower triangle of H; returns {(j, k): name}."""
        e = self
        t = self.t
        children = {b: [] for b in range(t.body_count)}
        for b, j in enumerate(t.joints):
            if j.parent >= 0:
                children[j.parent].append(b)
        for b in reversed(range(t.body_count)):
            terms = [f"I{b}"]
            if with_stiffness:
                terms.append(f"body_stiffness[w, {b}]")
            terms += [f"Ic{c}" for c in children[b]]
            e(f"Ic{b} = " + " + ".join(terms))
        lam = t.dof_parent()
        body = t.dof_body()
        H = {}
        for j in range(t.qd_count):
            e(f"G{j} = Ic{body[j]} * S{j}")
            H[j, j] = f"H{j}_{j}"
            e(f"H{j}_{j} = wp.dot(G{j}, S{j})")
            k = lam[j]
            while k >= 0:
                H[j, k] = f"H{j}_{k}"
                e(f"H{j}_{k} = wp.dot(G{j}, S{k})")
                k = lam[k]
        return H

    def mass_matrix(self) -> str:
        e = self
        e.begin()
        self._read_bodies(False)
        self._motion_subspace(False)
        H = self._crba(False)
        for (j, k), name in H.items():
            e(f"mass_matrix[w, {j}, {k}] = {name}")
            if j != k:
                e(f"mass_matrix[w, {k}, {j}] = {name}")
        sig = f"""@wp.kernel
def eval_mass_matrix(
    # Model:
{_BODY_MODEL}    # State in:
{_BODY_POSE}    # State out:
    mass_matrix: wp.array3d(dtype=wp.float64),
):
    \"\"\"Joint-space mass matrix (entries outside the tree pattern are left untouched).\"\"\"
"""
        return self.kernel(sig)

    # -------------------------------------------------------------- dynamics
    def dynamics(self) -> str:
        e = self
        t = self.t
        e.begin()
        e("g = gravity[0]")
        self._read_bodies(True)
        self._motion_subspace(True)
        # Recursive Newton-Euler: velocity-product and gravity accelerations, bias forces.
        dof_of = {b: [] for b in range(t.body_count)}
        for d, b in enumerate(t.dof_body()):
            dof_of[b].append(d)
        children = {b: [] for b in range(t.body_count)}
        for b, j in enumerate(t.joints):
            base = f"A{j.parent}" if j.parent >= 0 else "compute_spatial(wp.vec3d(zero, zero, zero), -g)"
            if j.parent >= 0:
                children[j.parent].append(b)
            terms = [base] + [f"c{d}" for d in dof_of[b] if not (j.type == "free" and d - j.qd_start < 3)]
            e(f"A{b} = " + " + ".join(terms))
            e(f"f{b} = I{b} * A{b} + compute_cross_force(V{b}, I{b} * V{b}) - body_wrench[w, {b}]")
        for b in reversed(range(t.body_count)):
            e(f"F{b} = " + " + ".join([f"f{b}"] + [f"F{c}" for c in children[b]]))
        for d, b in enumerate(t.dof_body()):
            e(f"tau{d} = joint_f[w, {d}] - dof_damping[{d}] * qd{d} - wp.dot(S{d}, F{b})")
            e(f"hd{d} = h_implicit * dof_damping[{d}]")
        H = self._crba(True)
        diag_extra = {d: [f"hd{d}"] for d in range(t.qd_count)}
        tau = {d: f"tau{d}" for d in range(t.qd_count)}
        if t.joint_limits:
            self._limits(diag_extra, tau, H)
        for d in range(t.qd_count):
            e(f"Hd{d} = {H[d, d]} + " + " + ".join(diag_extra[d]))
            H[d, d] = f"Hd{d}"
        if t.joint_limits and t.one_sided_limits:
            trial = self._factor_and_solve(H, tau, prefix="t")
            self._limit_brake(H, tau, trial)
        self._factor_and_solve(H, tau)
        for d in range(t.qd_count):
            e(f"joint_qdd[w, {d}] = qdd{d}")
            e(f"joint_qd_out[w, {d}] = qd{d} + h * qdd{d}")
        limit_args = ""
        if t.joint_limits:
            limit_args = """    dof_limit_lower: wp.array(dtype=wp.float64),
    dof_limit_upper: wp.array(dtype=wp.float64),
    limit_stiffness: wp.float64,
    limit_damping: wp.float64,
"""
        sig = f"""@wp.kernel
def solve_body_dynamics(
    # Model:
{_BODY_MODEL}    dof_damping: wp.array(dtype=wp.float64),
    gravity: wp.array(dtype=wp.vec3d),
{limit_args}    # State in:
{_JOINT_STATE}{_BODY_POSE}{_BODY_VELOCITY}    body_wrench: wp.array2d(dtype=spatial6),
    body_stiffness: wp.array2d(dtype=spatial66),
    # Control:
    joint_f: wp.array2d(dtype=wp.float64),
    h: wp.float64,
    h_implicit: wp.float64,
    # State out:
    joint_qdd: wp.array2d(dtype=wp.float64),
    joint_qd_out: wp.array2d(dtype=wp.float64),
):
    \"\"\"Linearised implicit velocity update (M + h D + h^2 K) qdd = tau; qd_out = qd + h qdd.\"\"\"
"""
        return self.kernel(sig)

    def _limits(self, diag_extra: dict, tau: dict, H: dict) -> None:
        """Penalty joint limits, implicit in stiffness and damping (active side only).

        A limit acts in a step if the angle is past it at the start *or* the start velocity
        carries it past within the step (``q + h qd``): activated by the start state alone,
        a joint entering its limit went up to ``|qd| h`` past it before any torque acted
        (0.6 rad for a shoulder at 20 rad/s at 30 Hz), and the penalty energy ``1/2 k e^2``
        appeared from nothing. The spring's constant part is ``-k max(q - upper, 0)``
        (nothing before the crossing), so in the entering step the limit acts through its
        implicit part ``-(c + k h) qd'`` only, which opposes the motion: it takes energy out
        and never pulls a joint towards its limit. The implicit part is switched on over a
        band of ``LIMIT_BAND`` before the limit, ``w = clamp((max(q, q + h qd) - upper) /
        band + 1, 0, 1)``, so that the step is continuous in ``q`` and ``qd`` (an on/off
        switch there turned float32 rounding of the strings into different motions: 7x the
        rounding bound of ``tests/marionette/test_marionette_float32.py``). With
        ``one_sided_limits`` (issue 13; the default, ``docs/puppet.md``) ``w`` is multiplied by ``clamp(1 + qd / LIMIT_AWAY_SPEED, 0, 1)`` (upper limit; the
        cone: ``qd`` is the rate of its angle, ``n . omega``), so motion away from a limit is
        not braked; a joint turned round within the step is caught by ``_limit_brake``.
        """
        e = self
        e("kl = limit_stiffness")
        e(f"band = wp.float64({LIMIT_BAND!r})")
        one_sided = self.t.one_sided_limits
        if one_sided:
            e(f"away = wp.float64({LIMIT_AWAY_SPEED!r})")
            e(f"inner = wp.float64({LIMIT_INNER!r})")
        e("dl = limit_damping + h_implicit * limit_stiffness")
        e("hl = h_implicit * limit_damping + h_implicit * h_implicit * limit_stiffness")
        for b, j in enumerate(self.t.joints):
            d = j.qd_start
            if j.type in ("hinge", "universal"):
                for i, q in _axes(j):
                    e(f"qe{i} = {q} + h_implicit * qd{i}")
                    ua = la = ""
                    if one_sided:
                        e(f"ua{i} = wp.clamp(one + qd{i} / away, zero, one)")
                        e(f"la{i} = wp.clamp(one - qd{i} / away, zero, one)")
                        ua, la = f"ua{i} * ", f"la{i} * "
                    e(f"up{i} = {ua}wp.clamp((wp.max({q}, qe{i}) - dof_limit_upper[{i}]) / band + one, zero, one)")
                    e(f"lo{i} = {la}wp.clamp((dof_limit_lower[{i}] - wp.min({q}, qe{i})) / band + one, zero, one)")
                    e(f"tl{i} = tau{i} - kl * (wp.max({q} - dof_limit_upper[{i}], zero) + wp.min({q} - dof_limit_lower[{i}], zero)) - (up{i} + lo{i}) * dl * qd{i}")
                    tau[i] = f"tl{i}"
                    diag_extra[i].append(f"(up{i} + lo{i}) * hl")
            elif j.type == "ball":
                s = j.q_start
                # rotation angle theta of the ball quaternion, axis n (local = world-invariant)
                e(f"qb{b} = compute_quat_from_mj(joint_q[w, {s}], joint_q[w, {s + 1}], joint_q[w, {s + 2}], joint_q[w, {s + 3}])")
                e(f"sg{b} = wp.where(qb{b}[3] < zero, -one, one)")
                e(f"nv{b} = wp.vec3d(qb{b}[0], qb{b}[1], qb{b}[2]) * sg{b}")
                e(f"sn{b} = compute_smooth_norm(nv{b})")
                e(f"th{b} = wp.float64(2.0) * wp.atan2(sn{b}, qb{b}[3] * sg{b})")
                e(f"n{b} = nv{b} / sn{b}")
                e(f"om{b} = wp.vec3d(qd{d}, qd{d + 1}, qd{d + 2})")
                e(f"rt{b} = h_implicit * wp.dot(n{b}, om{b})")
                ba = ""
                if one_sided:
                    e(f"ba{b} = wp.clamp(one + wp.dot(n{b}, om{b}) / away, zero, one)")
                    ba = f"ba{b} * "
                e(f"ac{b} = {ba}wp.clamp((wp.max(th{b}, th{b} + rt{b}) - dof_limit_upper[{d}]) / band + one, zero, one)")
                e(f"tb{b} = n{b} * (ac{b} * (-kl * wp.max(th{b} - dof_limit_upper[{d}], zero) - dl * wp.dot(n{b}, om{b})))")
                for k in range(3):
                    e(f"tl{d + k} = tau{d + k} + tb{b}[{k}]")
                    tau[d + k] = f"tl{d + k}"
                for k in range(3):
                    for m in range(k + 1):
                        e(f"Hb{d + k}_{d + m} = {H[d + k, d + m]} + ac{b} * hl * n{b}[{k}] * n{b}[{m}]")
                        H[d + k, d + m] = f"Hb{d + k}_{d + m}"

    def _limit_brake(self, H: dict, tau: dict, trial: dict) -> None:
        """The one-sided look-ahead's brake on the step's *end* angle (issue 13).

        ``trial`` is the solve of the step with the limits' start part (``_limits``): its ``L``
        and solution. Per limit, the trial's end angle is compared with the point
        ``LIMIT_INNER`` before the limit; where it gets past, a brake ``-w (c + k h) qd'`` (the
        limit's implicit part with weight ``w``, on top of the start band's) is added. A brake
        of weight ``w`` scales the end velocity along the joint's axis by ``1 / (1 + w beta)``,
        ``beta = h (c + k h) (H^-1)_nn`` (exact for one braked limit, by Sherman-Morrison), so
        with the gap ``g`` to the point and the trial's advance ``a`` the end angle lands on the
        point for ``w = (a - g) / (beta g)``. Written ``clamp(min((a - g) / (beta max(g, G)),
        a / (beta G)), 0, LIMIT_BRAKE_MAX)`` with ``G = LIMIT_BRAKE_GAP``: continuous, 0 for
        an end velocity away from the limit (``a <= 0``), full within ``G`` of the point.
        ``(H^-1)_nn = |L^-T n|^2`` by a triangular solve over the joint's ancestors with the
        trial's factor. Hinges and universal axes: ``n`` the axis, ``a = h qd'_trial``. The
        cone (ball joint): ``a`` is the rotation angle of the trial's end orientation (the
        step's own quaternion integration, so that a fast turn across the cone's axis counts)
        minus the start angle, the brake acts on all three rates (``-w (c + k h) omega'``)
        and ``n`` is the direction of the trial's end velocity. Braking along the start
        angle's axis only (as the start band does) let the neck go 1.28 rad through its cone
        over the bars' jerks at 4.6 m/s and gained 0.67 J. The brake only opposes the end
        velocity: it takes energy out.
        """
        e = self
        L, x = trial["L"], trial["x"]
        lam = self.t.dof_parent()
        e(f"bmax = wp.float64({LIMIT_BRAKE_MAX!r})")
        e("btiny = wp.float64(1e-30)")
        e(f"gfloor = wp.float64({LIMIT_BRAKE_GAP!r})")

        def inverse_diagonal(name: str, top: int, r: dict) -> None:
            path = []
            i = top
            while i >= 0:
                path.append(i)
                i = lam[i]
            for pos, k in enumerate(path):
                terms = [r[k]] if k in r else []
                terms += [f"- {L[m, k]} * ty{name}_{m}" for m in path[:pos]]
                if not terms:
                    e(f"ty{name}_{k} = zero")
                else:
                    e(f"ty{name}_{k} = ({' '.join(terms)}) / {L[k, k]}")
            e(f"hi{name} = " + " + ".join(f"ty{name}_{k} * ty{name}_{k}" for k in path))

        def weight(name: str, advance: str, gap: str) -> str:
            return (f"wp.clamp(wp.min(({advance} - {gap}) / (bt{name} * wp.max({gap}, gfloor)), "
                    f"{advance} / (bt{name} * gfloor)), zero, bmax)")

        for b, j in enumerate(self.t.joints):
            d = j.qd_start
            if j.type in ("hinge", "universal"):
                for i, q in _axes(j):
                    e(f"ta{i} = h * (qd{i} + h * {x[i]})")
                    inverse_diagonal(f"{i}", i, {i: "one"})
                    e(f"bt{i} = wp.max(h * dl * hi{i}, btiny)")
                    e(f"gu{i} = dof_limit_upper[{i}] - inner - {q}")
                    e(f"gl{i} = {q} - dof_limit_lower[{i}] - inner")
                    e(f"bw{i} = {weight(str(i), f'ta{i}', f'gu{i}')} + {weight(str(i), f'-ta{i}', f'gl{i}')}")
                    e(f"tk{i} = {tau[i]} - bw{i} * dl * qd{i}")
                    tau[i] = f"tk{i}"
                    e(f"Hk{i}_{i} = {H[i, i]} + bw{i} * hl")
                    H[i, i] = f"Hk{i}_{i}"
            elif j.type == "ball":
                # The cone: the end angle of the trial's rotation (integrated as the step does,
                # so that a fast turn across the axis counts), an isotropic brake on the
                # joint's angular velocity, and (H^-1) along the trial's end velocity.
                nm = f"b{b}"
                s = j.q_start
                e(f"tw{nm} = wp.vec3d(qd{d} + h * {x[d]}, qd{d + 1} + h * {x[d + 1]}, qd{d + 2} + h * {x[d + 2]})")
                e(f"te{nm} = compute_quat_integrate(qb{b}, tw{nm}, h)")
                e(f"ts{nm} = wp.where(te{nm}[3] < zero, -one, one)")
                e(f"tn{nm} = compute_smooth_norm(wp.vec3d(te{nm}[0], te{nm}[1], te{nm}[2]) * ts{nm})")
                e(f"ta{nm} = wp.float64(2.0) * wp.atan2(tn{nm}, te{nm}[3] * ts{nm}) - th{b}")
                e(f"tu{nm} = tw{nm} / compute_smooth_norm(tw{nm})")
                inverse_diagonal(nm, d + 2, {d + k: f"tu{nm}[{k}]" for k in range(3)})
                e(f"bt{nm} = wp.max(h * dl * hi{nm}, btiny)")
                e(f"gu{nm} = dof_limit_upper[{d}] - inner - th{b}")
                e(f"bw{nm} = {weight(nm, f'ta{nm}', f'gu{nm}')}")
                for k in range(3):
                    e(f"tk{d + k} = {tau[d + k]} - bw{nm} * dl * qd{d + k}")
                    tau[d + k] = f"tk{d + k}"
                    e(f"Hk{d + k}_{d + k} = {H[d + k, d + k]} + bw{nm} * hl")
                    H[d + k, d + k] = f"Hk{d + k}_{d + k}"

    def _factor_and_solve(self, H: dict, tau: dict, prefix: str = "") -> dict:
        """Tree-sparse L^T L factorisation of H and the two triangular solves.

        Records in ``self.solve`` what ``articulation_tangent`` needs to differentiate the solve
        as a whole (``H qdd = tau``: ``qdd' = H^-1 (tau' - H' qdd)`` with this ``L``): the names of
        H's entries (``H``, lower triangle), of the right-hand side (``b``), of ``L``, of the
        solution (``x``), the dof parents (``lam``) and the names this part defines (``internal``).
        With a ``prefix`` (the joint limits' trial solve) its names are prefixed and nothing is
        recorded: that solve is plain straight-line code to ``articulation_tangent``. Returns
        the names of ``L`` and of the solution (``L``, ``x``).
        """
        e = self
        n = self.t.qd_count
        lam = self.t.dof_parent()
        first = len(self.lines)

        def anc(i):
            while i >= 0:
                yield i
                i = lam[i]

        cur = dict(H)
        version = {}

        def fresh(i, j):
            version[i, j] = version.get((i, j), 0) + 1
            return f"{prefix}H{i}_{j}_{version[i, j]}"

        L = {}
        for k in reversed(range(n)):
            L[k, k] = f"{prefix}L{k}_{k}"
            e(f"{prefix}L{k}_{k} = wp.sqrt({cur[k, k]})")
            for i in anc(lam[k]):
                L[k, i] = f"{prefix}L{k}_{i}"
                e(f"{prefix}L{k}_{i} = {cur[k, i]} / {prefix}L{k}_{k}")
            for i in anc(lam[k]):
                for j in anc(i):
                    name = fresh(i, j)
                    e(f"{name} = {cur[i, j]} - {L[k, i]} * {L[k, j]}")
                    cur[i, j] = name
        x = dict(tau)
        xv = {}

        def xfresh(i):
            xv[i] = xv.get(i, 0) + 1
            return f"{prefix}x{i}_{xv[i]}"

        for i in reversed(range(n)):
            name = xfresh(i)
            e(f"{name} = {x[i]} / {L[i, i]}")
            x[i] = name
            for j in anc(lam[i]):
                name = xfresh(j)
                e(f"{name} = {x[j]} - {L[i, j]} * {x[i]}")
                x[j] = name
        for i in range(n):
            terms = " - ".join([x[i]] + [f"{L[i, j]} * {prefix}qdd{j}" for j in anc(lam[i])])
            e(f"{prefix}qdd{i} = ({terms}) / {L[i, i]}")
        sol = {i: f"{prefix}qdd{i}" for i in range(n)}
        if prefix:
            return dict(L=L, x=sol)
        internal = [line.strip().split(" = ", 1)[0] for line in self.lines[first:]]
        self.solve = dict(H=dict(H), b=dict(tau), L=L, x={i: f"qdd{i}" for i in range(n)}, lam=lam,
                          internal=internal)
        return dict(L=L, x=sol)

    # -------------------------------------------------------------- integration
    def integrate(self) -> str:
        e = self
        e.begin(constants=False)
        for j in self.t.joints:
            s, d = j.q_start, j.qd_start
            if j.type in ("free", "ball"):
                o = 0
                if j.type == "free":
                    for k in range(3):
                        e(f"joint_q_out[w, {s + k}] = joint_q[w, {s + k}] + h * joint_qd[w, {d + k}]")
                    o = 3
                e(f"r{s} = compute_quat_integrate(compute_quat_from_mj(joint_q[w, {s + o}], joint_q[w, {s + o + 1}], "
                  f"joint_q[w, {s + o + 2}], joint_q[w, {s + o + 3}]), wp.vec3d(joint_qd[w, {d + o}], "
                  f"joint_qd[w, {d + o + 1}], joint_qd[w, {d + o + 2}]), h)")
                e(f"joint_q_out[w, {s + o}] = r{s}[3]")
                for k in range(3):
                    e(f"joint_q_out[w, {s + o + 1 + k}] = r{s}[{k}]")
            else:
                for k in range(_QD_COUNT[j.type]):
                    e(f"joint_q_out[w, {s + k}] = joint_q[w, {s + k}] + h * joint_qd[w, {d + k}]")
        sig = f"""@wp.kernel
def integrate_joint_coordinates(
    # State in:
{_JOINT_STATE}    # Control:
    h: wp.float64,
    # State out:
    joint_q_out: wp.array2d(dtype=wp.float64),
):
    \"\"\"q_out = q (+) h qd (joint_qd is the new velocity): free/ball quaternions as r * exp(h w / 2).\"\"\"
"""
        return self.kernel(sig)


def _cache_dir() -> Path:
    root = os.environ.get("DMARIONETTE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "dmarionette"
    )
    path = Path(root) / "generated"
    path.mkdir(parents=True, exist_ok=True)
    return path


def build_articulation_kernels(topo: ArticulationTopology, optimization_level: int = 1):
    """Generates, writes and imports the kernels for ``topo`` (cached per topology).

    Returns:
        A module with ``eval_body_kinematics``, ``solve_body_dynamics``,
        ``integrate_joint_coordinates`` and ``eval_mass_matrix``.
    """
    em = Emitter(topo)
    options = f'wp.set_module_options({{"optimization_level": {int(optimization_level)}}})\n'
    source = "\n\n".join([_HEADER + options, em.kinematics(), em.dynamics(), em.integrate(), em.mass_matrix()])
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    return import_generated(f"dmarionette_articulation_{digest}", source)


def import_generated(name: str, source: str, namespace: dict | None = None):
    """Writes ``source`` to the cache folder as ``name.py`` (unless there already) and imports it (once
    per process); ``name`` carries the source's hash. ``namespace``: globals the module is given before
    it runs (objects its source refers to by name but cannot import, e.g. a closure's values)."""
    if name in _CACHE:
        return _CACHE[name]
    path = _cache_dir() / f"{name}.py"
    if not path.exists() or path.read_text() != source:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(source)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    module.__dict__.update(namespace or {})
    sys.modules[name] = module
    spec.loader.exec_module(module)
    _CACHE[name] = module
    return module
