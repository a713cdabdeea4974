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
