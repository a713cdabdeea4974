"""Mechanical energy of a marionette and the work the control bars put in.

The bars are not simulated: they move each string's top particle kinematically
(``integrate_string_particles``). The only way energy enters the system is through
those top particles, so an energy-consistent simulation satisfies, for any ``t``,

    E(t) - E(0) = W_bars(0..t) - D(0..t),   D >= 0,

with ``D`` everything the dampers (internal friction, air drag, ground absorption and
friction, tie and joint damping, contact damping) and the integrators (backward Euler
is dissipative) take out. The hard-case tests check ``E(t) - E(0) <= W_bars + tol``.

**Energy** (:func:`marionette_energy`), all in joules, gravity potential relative to
``y = 0``:

- strings: :func:`~dmarionette.strings.model.string_energy` (kinetic energy of the free
  particles, gravity, segment springs, string-ground penalty springs); its ``tie`` term
  is not used, because in a marionette the tie joins the last particle to a moving body
  point;
- ties (paper eq. 2): ``1/2 k |x_point - x_last|^2`` per tied string, ``x_point`` the
  body point, ``x_last`` the string's last particle;
- puppet (and ball): ``1/2 m |v|^2 + 1/2 w^T R I R^T w`` per body, and ``-m g . x``;
- puppet contact penalties (hard contacts): ``1/2 k d^2`` for each box corner or sphere
  ``d`` below the ground or inside the chair (the kernels' normal force is
  ``max(k d - c v_n, 0)``, whose elastic part is ``k d``); joint-limit penalties:
  ``1/2 k_limit e^2`` for each hinge/universal angle ``e`` beyond its limit and for the
  neck's rotation angle beyond its cone.
- **excluded**: the puppet-ball contact (closest points between box and sphere) and the
  smooth (softplus) contact variant. Both store a non-negative energy, so leaving it out
  only lowers ``E(t)``; as long as no such contact is active at ``t = 0`` (true in every
  scene tested), ``E(t) - E(0)`` can only be underestimated by the exclusion, and the
  bound ``E(t) - E(0) <= W`` remains a valid check.

The penalty parts (``puppet_contact``, ``puppet_limit``) are reported but are not
always "paid for" at the puppet rate: a contact penalty is switched on by the state at
the start of a puppet step, so a point that crosses into the ground or chair during a
step ends it up to ``v H`` deep without any force having acted, and ``1/2 k d^2`` appears
from nothing (measured: 2.3 J in a landing at 30 Hz); the following implicit steps take
most of it out. Joint limits look ahead (``articulation_codegen._limits``; before they
did, a shoulder thrown at 20 rad/s into its limit at 30 Hz made 3 J this way), but their
penalty energy is still only bounded, not balanced, by the work that drove the joint in. The hard-case tests therefore check
the energy of the motion, ``total - puppet_contact - puppet_limit`` (same argument:
non-negative terms, zero at the start).

**Bar work** (:class:`BarWorkMeter`): over one string step the bar moves top particle
``0`` of each string from ``x0`` to ``x0'``. Particle 0 is massless for the dynamics
(kinematic), so the bar exerts on it the opposite of the force the string exerts on it,
``R = f_spring(segment 0) + f_friction(segment 0)`` (what ``kernels/bar_feedback.py``
calls the exact reaction, here per string). The work of one string step is the
trapezoid rule along the straight move,

    W = -1/2 (R(start) + R(end)) . (x0' - x0),

which is exact for a linear spring force along the move; its error per step is
``O(k_s |x0' - x0|^3 / d)``-ish and is what the tests' tolerance must cover. With still
bars ``x0' = x0`` and ``W = 0`` exactly.

The meter wraps a string solver (``SolverStringImplicit``) and adds one kernel launch
after every string step, so it also works inside captured graphs
(``MarionetteRollout``). Install it on a marionette with :func:`install_bar_work_meter`
(it replaces ``model.string_solver`` by the meter, which steps the original solver).
The meter is a diagnostic: its accumulation is in place, so it has no meaningful
gradient; do not install it on a model used under a ``wp.Tape``.
"""


import functools

import numpy as np
import warp as wp

from dmarionette.kernels.bar_feedback import bar_reaction_function
from dmarionette.kernels.string_model_arrays import string_model_arrays_type
from dmarionette.kernels.string_state_arrays import string_state_arrays_type
from dmarionette.rotations import quat_to_matrix
from dmarionette.strings.model import StringModel, string_energy

__all__ = [
    "BarWorkMeter",
    "simulate_energy_balance",
    "install_bar_work_meter",
    "marionette_energy",
    "puppet_contact_depths",
    "puppet_energy",
    "puppet_limit_violation",
]

# Box corners in units of half sizes (the order of ``kernels/body_contact``'s candidates does not matter here).
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


@functools.cache
def _eval_bar_work_kernel(scalar, internal_friction: bool, tension_only: bool):
    vec3 = wp.types.vector(3, scalar)
    StringModelArrays = string_model_arrays_type(scalar)
    StringStateArrays = string_state_arrays_type(scalar)
    # The force of the state itself, as the feedback's exact reaction.
    compute_top_force = bar_reaction_function(scalar, internal_friction, tension_only)

    @wp.kernel(module="unique")
    def eval_bar_work(
        # Model:
        model: StringModelArrays,
        # State in (the step's start and its end):
        state_in: StringStateArrays,
        state_out: StringStateArrays,
        # State out (accumulated):
        bar_work: wp.array(dtype=wp.float64),
    ):
        """Work [J] of the bar on each string's top particle over one step (trapezoid rule)."""
        s = wp.tid()
        a = model.string_start[s]
        k = model.string_stiffness[s]
        d = model.string_rest_length[s]
        c = model.string_internal_friction[s]
        r0 = compute_top_force(state_in.particle_q[a], state_in.particle_q[a + 1], state_in.particle_qd[a],
                               state_in.particle_qd[a + 1], k, d, c)
        r1 = compute_top_force(state_out.particle_q[a], state_out.particle_q[a + 1], state_out.particle_qd[a],
                               state_out.particle_qd[a + 1], k, d, c)
        dx = state_out.particle_q[a] - state_in.particle_q[a]
        w = -scalar(0.5) * wp.dot(r0 + r1, dx)
        bar_work[s] = bar_work[s] + wp.float64(w)

    return eval_bar_work


class BarWorkMeter:
    """A string solver that also accumulates the work of the bars on the strings' tops.

    Args:
        solver: the string solver to step (``SolverStringImplicit``); its ``model`` is used.

    Attributes:
        bar_work: accumulated work per string [J], ``(S,)`` float64 Warp array; reset with
            :meth:`reset`.
    """

    def __init__(self, solver):
        self.solver = solver
        self.model: StringModel = solver.model
        m = self.model
        self._kernel = _eval_bar_work_kernel(m.scalar, m.effects.internal_friction, m.effects.tension_only)
        self.bar_work = wp.zeros(m.string_count, dtype=wp.float64, device=m.device)

    def reset(self) -> None:
        self.bar_work.zero_()

    def total(self, strings: range | None = None) -> float:
        """Work of all bars since the last reset [J] (a copy, read on the host); ``strings``: on
        these strings only (one world of a batched marionette)."""
        work = self.bar_work.numpy()
        return float(np.sum(work if strings is None else work[strings.start:strings.stop]))

    def step(self, state_in, state_out, control, dt: float, *, tape=None, workspace=None) -> None:
        """The wrapped solver's step, then the bar work of that step."""
        self.solver.step(state_in, state_out, control, dt, tape=tape, workspace=workspace)
        m = self.model
        wp.launch(self._kernel, dim=m.string_count,
                  inputs=[m.arrays, state_in.arrays, state_out.arrays],
                  outputs=[self.bar_work], device=m.device)

    def __getattr__(self, name):
        # Everything else (eval_* passes, model) as the wrapped solver.
        return getattr(self.solver, name)


def install_bar_work_meter(model) -> BarWorkMeter:
    """Makes ``model``'s string steps (a :class:`~dmarionette.marionette.solver.MarionetteModel`) meter
    the bar work; returns the meter. Install before building the ``SolverMarionette`` and
    any captured rollout (the meter's kernel must be part of the captured graph)."""
    if isinstance(model.string_solver, BarWorkMeter):
        return model.string_solver
    meter = BarWorkMeter(model.string_solver)
    model.string_solver = meter
    return meter


def puppet_contact_depths(model, body_pos: np.ndarray, body_rot: np.ndarray) -> dict[str, np.ndarray]:
    """Penetration [m] of every contact candidate (box corners, spheres) of a marionette's puppet.

    Args:
        model: a ``MarionetteModel``.
        body_pos: body centres ``(bodies, 3)``; body_rot: Warp quaternions ``(bodies, 4)``.

    Returns:
        ``ground``: depth below the ground plane (negative: above), ``(candidates,)``;
        ``chair``: depth inside the chair box (0 outside; absent without a chair).
    """
    contacts = model.puppet_solver.contacts
    body = contacts.point_body.numpy()
    local = contacts.point_local.numpy()
    radius = contacts.point_radius.numpy()
    rot = quat_to_matrix(np.asarray(body_rot, dtype=np.float64))
    centre = np.asarray(body_pos)[body] + np.einsum("nij,nj->ni", rot[body], local)
    out = {"ground": radius - (centre[:, 1] - model.scene.ground_height)}
    if model.scene.chair is not None:
        c, half = (np.asarray(v, dtype=np.float64) for v in model.scene.chair)
        u = centre - c
        outside = np.maximum(np.abs(u) - half, 0.0)
        distance_out = np.linalg.norm(outside, axis=1)
        inside = np.all(np.abs(u) <= half, axis=1)
        depth_in = np.min(half - np.abs(u), axis=1)  # distance to the nearest face from inside
        out["chair"] = np.where(inside, depth_in + radius, np.maximum(radius - distance_out, 0.0))
    return out


def puppet_limit_violation(model, joint_q: np.ndarray) -> np.ndarray:
    """How far each limited coordinate is beyond its limit [rad] (0 inside), ``(qd_count,)``.

    Hinge and universal angles against ``dof_limit_lower/upper``; the neck's (ball joint's)
    rotation angle against its cone (stored as the upper limit of its first dof). Free
    joints are unlimited (0).
    """
    puppet = model.puppet
    lower = puppet.dof_limit_lower.numpy()
    upper = puppet.dof_limit_upper.numpy()
    q = np.asarray(joint_q, dtype=np.float64)
    violation = np.zeros(puppet.qd_count)
    for joint in puppet.topology.joints:
        qs, ds = joint.q_start, joint.qd_start
        if joint.type == "free":
            continue
        if joint.type == "ball":
            w = min(abs(q[qs]), 1.0)
            angle = 2.0 * np.arccos(w)
            violation[ds] = max(angle - upper[ds], 0.0)
            continue
        count = len(joint.axes)
        for i in range(count):
            a = q[qs + i]
            violation[ds + i] = max(a - upper[ds + i], lower[ds + i] - a, 0.0)
    return violation


def puppet_energy(model, state, world: int = 0) -> dict[str, float]:
    """Kinetic, gravity and penalty (contact, joint limit) energy of the puppet [J].

    Args:
        model: a ``MarionetteModel``; state: its ``MarionetteState`` (the puppet's body
            fields are recomputed here from ``joint_q``, ``joint_qd``).
        world: which world of a batched marionette.
    """
    puppet = model.puppet
    model.puppet_solver.eval_kinematics(state.puppet)
    pos = state.puppet.body_pos.numpy()[world].copy()
    rot = state.puppet.body_rot.numpy()[world].copy()
    v = state.puppet.body_v.numpy()[world].copy()
    w = state.puppet.body_w.numpy()[world].copy()
    mass = puppet.body_mass.numpy()
    inertia = puppet.body_inertia.numpy()
    r = quat_to_matrix(rot)
    w_body = np.einsum("nji,nj->ni", r, w)  # R^T w
    kinetic = 0.5 * float(np.sum(mass * np.sum(v**2, axis=1)) + np.sum(inertia * w_body**2))
    g = np.asarray(model.scene.gravity, dtype=np.float64)
    gravity = -float(np.sum(mass * (pos @ g)))
    contact = 0.0
    c = puppet.contacts
    if (c.ground or c.chair is not None) and not c.smooth:
        depths = puppet_contact_depths(model, pos, rot)
        k = c.stiffness
        if c.ground:
            contact += 0.5 * k * float(np.sum(np.maximum(depths["ground"], 0.0) ** 2))
        if "chair" in depths:
            contact += 0.5 * k * float(np.sum(depths["chair"] ** 2))
    limit = 0.0
    if puppet.topology.joint_limits:
        e = puppet_limit_violation(model, state.puppet.joint_q.numpy()[world])
        limit = 0.5 * puppet.limit_stiffness * float(np.sum(e**2))
    return {"kinetic": kinetic, "gravity": gravity, "contact": contact, "limit": limit,
            "total": kinetic + gravity + contact + limit}


def marionette_energy(model, state, world: int = 0) -> dict[str, float]:
    """Mechanical energy of a marionette state [J] (see the module doc for what is in it), of
    world ``world`` of a batched marionette.

    Returns the parts ``string_kinetic``, ``string_gravity``, ``string_spring``, ``string_ground``,
    ``tie``, ``puppet_kinetic``, ``puppet_gravity``, ``puppet_contact``, ``puppet_limit`` and
    ``total``.
    """
    strings = model.strings
    first = world * model.strings_per_world
    q = state.strings.particle_q.numpy().astype(np.float64)
    qd = state.strings.particle_qd.numpy().astype(np.float64)
    s = string_energy(strings, q, qd, strings=range(first, first + model.strings_per_world))
    p = puppet_energy(model, state, world)
    point_q = model.eval_world_points(state.puppet)[0][world]
    tie = 0.0
    last = strings.string_start_np[1:] - 1
    for i, point in enumerate(model.string_point):
        if point >= 0:
            k = model.world_scenes[world].strings[i].tie_stiffness
            tie += 0.5 * k * float(np.sum((point_q[point] - q[last[first + i]]) ** 2))
    parts = {
        "string_kinetic": s["kinetic"], "string_gravity": s["gravity"], "string_spring": s["spring"],
        "string_ground": s["ground"], "tie": tie, "puppet_kinetic": p["kinetic"],
        "puppet_gravity": p["gravity"], "puppet_contact": p["contact"], "puppet_limit": p["limit"],
    }
    parts["total"] = float(sum(parts.values()))
    return parts


def simulate_energy_balance(model, duration: float, *, frame_hz: float = 30.0, state=None, t0: float = 0.0,
                            on_frame=None) -> dict[str, np.ndarray]:
    """Simulates ``model`` (captured-graph rollout) and records the energy balance per frame.

    Installs a :class:`BarWorkMeter` on ``model`` (see :func:`install_bar_work_meter`).

    Args:
        model: a ``MarionetteModel``.
        duration: [s]; rounded up to whole frames of ``round(1 / (frame_hz * puppet_dt))``
            puppet steps.
        frame_hz: how often the energy is evaluated (the cost per frame is a few host reads).
        state: start state (default ``model.state()``); advanced in place.
        t0: time of the start state [s] (for the bar trajectories).
        on_frame: optional ``on_frame(frame_index, state)`` called after each frame.

    Returns:
        ``time`` [s] ``(F,)`` (frame 0 is the start), ``energy`` [J] ``(F,)`` (total),
        ``parts`` (dict of ``(F,)`` arrays), ``bar_work`` [J] ``(F,)`` (cumulative from the
        start), ``finite`` (all string and puppet coordinates finite at every frame),
        ``ground_depth`` and ``chair_depth`` [m] ``(F,)`` (largest puppet penetration),
        ``limit_violation`` [rad] ``(F,)`` (largest joint-limit violation),
        ``particle_min_y`` [m] ``(F,)`` (lowest string particle), ``joint_q`` ``(F, q)``, ``joint_qd``
        ``(F, qd)``,
        ``body_pos`` ``(F, bodies, 3)``, ``tie_force_max`` [N] ``(S,)`` (largest eq. 2 force
        of each tie over the run, at every string step), ``tie_force_last`` [N] ``(S, 3)`` (mean
        eq. 2 force of each tie over the last frame).
    """
    from dmarionette.marionette.solver import SolverMarionette
    from dmarionette.marionette.rollout import MarionetteRollout

    meter = install_bar_work_meter(model)
    chunk = max(1, round(1.0 / (frame_hz * model.puppet_dt)))
    rollout = MarionetteRollout(SolverMarionette(model), chunk)
    frame_steps = chunk * model.substeps
    chunks = max(1, int(np.ceil(duration / (frame_steps * model.string_dt) - 1e-9)))
    state = model.state() if state is None else state
    meter.reset()
    records = []

    def record(state_now):
        q = state_now.strings.particle_q.numpy()
        jq = state_now.puppet.joint_q.numpy()[0].copy()
        jqd = state_now.puppet.joint_qd.numpy()[0].copy()
        finite = bool(np.all(np.isfinite(q)) and np.all(np.isfinite(state_now.strings.particle_qd.numpy()))
                      and np.all(np.isfinite(jq)) and np.all(np.isfinite(state_now.puppet.joint_qd.numpy())))
        if finite:
            energy = marionette_energy(model, state_now)
            pos = state_now.puppet.body_pos.numpy()[0].copy()
            rot = state_now.puppet.body_rot.numpy()[0].copy()
            depths = puppet_contact_depths(model, pos, rot)
            ground = float(np.max(depths["ground"]))
            chair = float(np.max(depths["chair"])) if "chair" in depths else 0.0
            limit = float(np.max(puppet_limit_violation(model, jq))) if model.puppet.topology.joint_limits else 0.0
        else:
            energy = {"total": np.nan}
            pos = np.full((model.puppet.body_count, 3), np.nan)
            ground = chair = limit = np.nan
        records.append((energy, meter.total(), finite, ground, chair, limit, float(np.min(q[:, 1])), jq, pos, jqd))

    record(state)

    def on_chunk(c, s):
        record(s)
        if on_frame is not None:
            on_frame(c + 1, s)

    outputs = rollout.run(state, t0, chunks, on_chunk=on_chunk)
    energies, work, finite, ground, chair, limit, pmin, jq, pos, jqd = zip(*records)
    keys = [k for k in energies[0] if k != "total"]
    return {
        "time": t0 + frame_steps * model.string_dt * np.arange(len(records)),
        "energy": np.array([e["total"] for e in energies]),
        "parts": {k: np.array([e.get(k, np.nan) for e in energies]) for k in keys},
        "bar_work": np.array(work),
        "finite": bool(all(finite)),
        "ground_depth": np.array(ground),
        "chair_depth": np.array(chair),
        "limit_violation": np.array(limit),
        "particle_min_y": np.array(pmin),
        "joint_q": np.array(jq),
        "joint_qd": np.array(jqd),
        "body_pos": np.array(pos),
        "tie_force_max": np.linalg.norm(outputs["tie_force"], axis=2).max(axis=0),
        "tie_force_last": outputs["tie_force"][-frame_steps:].mean(axis=0),
    }
