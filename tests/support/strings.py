"""Helpers shared by the string tests: small models and rollouts."""

import numpy as np
import warp as wp

from dmarionette.strings.model import StringControl, StringEffects, StringModel, StringSpec
from dmarionette.strings.rollout import StringRollout
from dmarionette.strings.solver import SolverStringImplicit

wp.config.log_level = wp.LOG_WARNING

ONLY_GRAVITY = StringEffects(gravity=True, internal_friction=False, air_drag=False,
                             ground_contact=False, ground_friction=False)
ALL_ON = StringEffects(gravity=True, internal_friction=True, air_drag=True, ground_contact=True, ground_friction=True)
NOTHING = StringEffects(gravity=False, internal_friction=False, air_drag=False,
                        ground_contact=False, ground_friction=False)
G = 9.81


def make_model(specs, effects=ONLY_GRAVITY, **kwargs) -> StringModel:
    return StringModel(specs, effects=effects, gravity=(0.0, -G, 0.0), ground_height=0.0, **kwargs)


def roll(model, dt, steps, state=None, top_q=None, chunk=None, tie_q=None):
    """Runs ``steps`` steps with fixed tops (or ``top_q`` of shape (T, S, 3)); returns (state, result)."""
    chunk = chunk or steps
    state = model.state() if state is None else state
    if top_q is None:
        top_q = np.broadcast_to(np.array([s.top for s in model.specs]), (steps, model.string_count, 3)).copy()
    rollout = StringRollout(SolverStringImplicit(model), dt, chunk_steps=chunk)
    result = rollout.run(state, top_q, tie_q=tie_q)
    return state, result


def zero_crossing_times(t, x):
    """Times where x changes sign, by linear interpolation between samples."""
    i = np.nonzero(np.signbit(x[:-1]) != np.signbit(x[1:]))[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def spec(**kwargs) -> StringSpec:
    base = dict(name="s", top=(0.0, 1.0, 0.0), bottom=(0.0, 0.5, 0.0), length=0.5, particle_count=20,
                mass=0.002, load_mass=0.0, stiffness=500.0, internal_friction=0.0, air_drag=0.0)
    base.update(kwargs)
    return StringSpec(**base)


def swung_controls(model, steps: int, dt: float):
    """Tops swung at 2 Hz by 10 cm and lowered 0.3 m (the bottoms reach the ground); ties circling."""
    tops = np.array([s.top for s in model.specs])
    ties = model.tie_points()
    for k in range(steps):
        t = (k + 1) * dt
        top = tops + np.array([0.1 * np.sin(4 * np.pi * t), -0.3 * min(t / 0.3, 1.0), 0.05 * np.cos(4 * np.pi * t)])
        tie = ties + 0.05 * np.array([np.sin(6 * t), 0.0, np.cos(6 * t) - 1.0])
        tie_v = 0.3 * np.array([np.cos(6 * t), 0.0, -np.sin(6 * t)]) * np.ones_like(ties)
        yield StringControl.from_numpy(model, top, tie, tie_v)


def three_strings() -> list[StringSpec]:
    """The gradient tests' strings: one swinging onto the ground, one tied to a point, one slack at the top."""
    return [spec(name="ground", particle_count=9, top=(0.0, 0.15, 0.0), bottom=(0.5, 0.02, 0.0), length=0.6,
                 internal_friction=0.3, air_drag=0.05, ground_stiffness=2000.0, ground_absorption=5.0,
                 ground_friction=2.0),
            spec(name="tied", particle_count=7, top=(0.5, 1.0, 0.0), bottom=(0.5, 0.6, 0.0), length=0.4,
                 internal_friction=0.2, air_drag=0.02, tied=True, tie_point=(0.6, 0.55, 0.1), tie_stiffness=300.0,
                 tie_damping=3.0),
            spec(name="slack", particle_count=6, top=(1.0, 1.0, 0.0), bottom=(1.0, 0.75, 0.05), length=0.35,
                 load_mass=0.02)]


def wiggled_controls(model, steps: int, dt: float) -> list[StringControl]:
    """The gradient tests' controls: tops swung a few cm and raised 3 cm/s, ties circling 5 cm at 4 rad/s."""
    t = dt * np.arange(1, steps + 1)[:, None]
    tops = np.array([s.top for s in model.specs])[None] + np.stack(
        [0.05 * np.sin(7.0 * t), -0.02 * np.sin(5.0 * t), 0.03 * t], axis=-1)
    tie = model.tie_points()[None] + np.stack([0.05 * np.cos(4.0 * t), 0.05 * np.sin(4.0 * t), 0.0 * t], axis=-1)
    tie_v = np.stack([-0.2 * np.sin(4.0 * t), 0.2 * np.cos(4.0 * t), 0.0 * t], axis=-1) * np.ones_like(tie)
    return [StringControl.from_numpy(model, tops[k], tie[k], tie_v[k]) for k in range(steps)]


def repeated_specs(base, shift) -> list[StringSpec]:
    """Strings for the lane tests: each ``(copies, spec keywords)`` of ``base`` repeated ``copies``
    times, copy ``i`` moved by ``i * shift`` and its constants scaled by ``1 + 0.07 i`` (stiffness,
    friction, drag, ground, tie), every other copy of a tied string cut: groups of equal particle
    count whose lanes differ."""
    specs = []
    for b, (copies, kwargs) in enumerate(base):
        for i in range(copies):
            f = 1.0 + 0.07 * i
            k = dict(kwargs)
            offset = i * np.asarray(shift, dtype=float)
            k["top"] = tuple(np.add(k["top"], offset))
            k["bottom"] = tuple(np.add(k["bottom"], offset))
            if k.get("tie_point") is not None:
                k["tie_point"] = tuple(np.add(k["tie_point"], offset))
                k["tied"] = i % 2 == 0
            for name in ("internal_friction", "air_drag", "ground_stiffness", "ground_absorption",
                         "ground_friction", "tie_stiffness", "tie_damping"):
                if name in k:
                    k[name] = k[name] * f
            specs.append(spec(name=f"s{b}_{i}", stiffness=500.0 * f, **k))
    return specs


def step_in_lockstep(model, first, second, steps: int = 400, dt: float = 1e-3):
    """Runs two ways of stepping ``model`` side by side from ``model.state()`` under
    :func:`swung_controls` and asserts after every step that they agree bit for bit: the state
    outputs (positions, velocities, tie forces, taut flags) and the workspaces' ``particle_dv``.

    Args:
        first, second: ``(step, workspace)``: ``step(state_in, state_out, control, dt)`` and the
            workspace whose ``particle_dv`` it writes.

    Returns:
        (whether a particle went below the ground at some step, the first's last state).
    """
    (step_a, ws_a), (step_b, ws_b) = first, second
    a, b = model.state(), model.state()
    c, d = model.state(), model.state()
    reached_ground = False
    for control in swung_controls(model, steps, dt):
        step_a(a, b, control, dt)
        step_b(c, d, control, dt)
        for name in ("particle_q", "particle_qd", "tie_force", "string_taut"):
            np.testing.assert_array_equal(getattr(b, name).numpy(), getattr(d, name).numpy(), err_msg=name)
        np.testing.assert_array_equal(ws_a.particle_dv.numpy(), ws_b.particle_dv.numpy())
        reached_ground |= bool(np.min(b.particle_q.numpy()[:, 1]) < 0.0)
        a, b, c, d = b, a, d, c
    return reached_ground, a


# The constants of a string model that a taped step differentiates (arrays of StringModel).
STRING_CONSTANTS = ["particle_mass", "string_stiffness", "string_rest_length", "string_internal_friction",
                    "string_air_drag", "string_ground_stiffness", "string_ground_absorption",
                    "string_ground_friction", "string_tie_stiffness", "string_tie_damping", "string_tied"]


@wp.kernel
def weighted_sum(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))


def taped_rollout(solver, states, controls, dt: float, rng, workspaces=None) -> tuple[wp.Tape, wp.array]:
    """Steps ``states[k] -> states[k + 1]`` under ``controls[k]`` (in ``workspaces[k]`` if given) on a
    tape, then a loss: random weights (normal, from ``rng``) times the last state's positions,
    velocities and tie forces. Returns (tape, loss) for ``tape.backward(loss)``."""
    model = solver.model
    weight = wp.array(rng.normal(size=(model.particle_count, 3)), dtype=wp.vec3d)
    force_weight = wp.array(rng.normal(size=(model.string_count, 3)), dtype=wp.vec3d)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for k in range(len(controls)):
            solver.step(states[k], states[k + 1], controls[k], dt, tape=tape,
                        workspace=None if workspaces is None else workspaces[k])
        wp.launch(weighted_sum, dim=model.particle_count, inputs=[states[-1].particle_q, weight], outputs=[loss])
        wp.launch(weighted_sum, dim=model.particle_count, inputs=[states[-1].particle_qd, weight], outputs=[loss])
        wp.launch(weighted_sum, dim=model.string_count, inputs=[states[-1].tie_force, force_weight], outputs=[loss])
    return tape, loss


def rollout_gradients(model, states, controls) -> dict[str, np.ndarray]:
    """After the backward pass of :func:`taped_rollout`: the gradients of the initial positions and
    velocities (``particle_q0_grad``, ``particle_qd0_grad``), of every step's controls (``top_q_grad``,
    ... with a leading step axis) and of :data:`STRING_CONSTANTS` (``<name>_grad``)."""
    out = {"particle_q0_grad": states[0].particle_q.grad.numpy(),
           "particle_qd0_grad": states[0].particle_qd.grad.numpy()}
    for name in ("top_q", "tie_q", "tie_qd"):
        out[name + "_grad"] = np.array([getattr(c, name).grad.numpy() for c in controls])
    for name in STRING_CONSTANTS:
        out[name + "_grad"] = getattr(model, name).grad.numpy()
    return out
