"""What the hard-case tests share (tests/marionette/test_hard_cases.py explains the energy
check and the penetration and joint-limit bounds): bar paths with velocity steps and for
ever swaying, the common assertions and the bounds."""

import dataclasses

import numpy as np

from dmarionette.marionette.solver import MarionetteModel
from dmarionette.rotations import euler_to_matrix

G = 9.81
TOL_ENERGY = 1e-3  # J, see the module doc


class PiecewiseLinearPath:
    """A bar path with velocity steps (a stand-in for ``BarTrajectory``, whose spline is C1):
    straight lines between timed positions, held before the first and after the last."""

    def __init__(self, times, positions, rotation=(0.0, 0.0, 0.0)):
        self.times = np.asarray(times, dtype=np.float64)
        self.positions = np.asarray(positions, dtype=np.float64)
        self.rotations = np.tile(np.asarray(rotation, dtype=np.float64), (len(self.times), 1))

    def pose(self, times):
        t = np.asarray(times, dtype=np.float64)
        pos = np.stack([np.interp(t, self.times, self.positions[:, i]) for i in range(3)], axis=1)
        i = np.clip(np.searchsorted(self.times, t, side="left") - 1, 0, len(self.times) - 2)
        vel = (self.positions[i + 1] - self.positions[i]) / (self.times[i + 1] - self.times[i])[:, None]
        vel[(t <= self.times[0]) | (t > self.times[-1])] = 0.0
        return pos, vel, euler_to_matrix(np.tile(self.rotations[0], (len(t), 1)))


def jerked_bars(scene, speed, distance=0.1):
    """Both bars of ``scene`` jump from rest to ``speed`` [m/s], travel ``distance`` [m] and stop
    dead; four times (up at 1 s, sideways at 2 s, down at 3 s, back at 4 s)."""
    main, hand = scene.bars
    p0, h0 = np.array(main.trajectory.positions[0]), np.array(hand.trajectory.positions[0])
    d, v = distance, speed
    times = [0.0, 1.0, 1.0 + d / v, 2.0, 2.0 + d / v, 3.0, 3.0 + d / v, 4.0, 4.0 + d / v]
    offsets = np.array([[0, 0, 0], [0, 0, 0], [0, d, 0], [0, d, 0], [d, d, 0], [d, d, 0], [d, 0, 0], [d, 0, 0],
                        [0, 0, 0]], dtype=np.float64)
    return (dataclasses.replace(main, trajectory=PiecewiseLinearPath(times, p0 + offsets)),
            dataclasses.replace(hand, trajectory=PiecewiseLinearPath(times, h0 + offsets)))


def lowered_bars(scene):
    """Both bars of ``scene`` still for 1 s, then lowered steadily until 3 s, the main bar by 1.2 m
    (0.6 m/s) and the hand bar by 1.1 m, then held: the strings go slack and the puppet lies down."""
    main, hand = scene.bars
    p0, h0 = np.array(main.trajectory.positions[0]), np.array(hand.trajectory.positions[0])
    times = [0.0, 1.0, 3.0]
    return (dataclasses.replace(main, trajectory=PiecewiseLinearPath(times, [p0, p0, p0 - [0, 1.2, 0]])),
            dataclasses.replace(hand, trajectory=PiecewiseLinearPath(times, [h0, h0, h0 - [0, 1.1, 0]])))


def with_lookahead(scene, variant: str):
    """``scene`` with the joint-limit look-ahead ``variant``: ``"band"`` (two-sided,
    ``[effects] one_sided_limits = false``) or ``"one_sided"`` (the default since issue 13)."""
    return dataclasses.replace(scene, body_effects={**scene.body_effects, "one_sided_limits": variant == "one_sided"})


def fast_model(scene, **changes):
    """The marionette of ``scene`` with ``changes``; puppet kernels compiled without optimisation."""
    return MarionetteModel(dataclasses.replace(scene, **changes), optimization_level=0)


def energy_excess(r):
    """``E(t) - E(0) - W(0..t)`` without the puppet's penalty energies (test_hard_cases' module doc), per frame [J]."""
    motion = r["energy"] - r["parts"]["puppet_contact"] - r["parts"]["puppet_limit"]
    return motion - motion[0] - r["bar_work"]


def check_case(name, model, r, *, ground=None, limit=None, chair=None, string_ground=None, limit_measured=None):
    """The common assertions; prints the measured numbers (pytest -s)."""
    assert r["finite"], f"{name}: non-finite state"
    excess = energy_excess(r)
    print(f"\n{name}: max excess after the start {excess[1:].max():.3e} J, bar work {r['bar_work'][-1]:.4f} J, "
          f"ground {r['ground_depth'].max() * 1e3:.2f} mm, chair {r['chair_depth'].max() * 1e3:.2f} mm, "
          f"limit {r['limit_violation'].max():.4f} rad (bound {limit if limit is not None else np.nan:.3f}), "
          f"lowest particle {r['particle_min_y'].min() * 1e3:.2f} mm")
    assert excess.max() <= TOL_ENERGY, (name, excess.max())
    if ground is not None:
        assert r["ground_depth"].max() <= ground, (name, r["ground_depth"].max(), ground)
    if chair is not None:
        assert r["chair_depth"].max() <= chair, (name, r["chair_depth"].max(), chair)
    if limit is not None:
        assert r["limit_violation"].max() <= limit, (name, r["limit_violation"].max(), limit)
    if limit_measured is not None:
        assert r["limit_violation"].max() <= 1.5 * limit_measured, (name, r["limit_violation"].max(), limit_measured)
    if string_ground is not None:
        assert r["particle_min_y"].min() >= model.scene.ground_height - string_ground, (name, string_ground)


def limit_bound(model, r):
    """``qd_max H + sqrt(2 (E(0) + max W - G_floor + TOL_ENERGY) / k_lim)`` [rad] (test_hard_cases' module doc)."""
    lowest = min(0.0, -float(r["ground_depth"].max()), float(r["particle_min_y"].min()))
    mass = model.puppet_mass + sum(s.mass + s.load_mass for s in model.strings.specs)
    floor = mass * G * lowest
    available = r["energy"][0] + max(float(r["bar_work"].max()), 0.0) - floor + TOL_ENERGY
    overshoot = float(np.max(np.abs(r["joint_qd"][:, 6:]))) * model.puppet_dt
    return overshoot + float(np.sqrt(2.0 * available / model.puppet.limit_stiffness))


def contact_bound(model, speed):
    """``v H + M g / k`` [m] (test_hard_cases' module doc)."""
    return speed * model.puppet_dt + model.puppet_mass * G / model.puppet.contacts.stiffness


def still_bar(bar):
    return dataclasses.replace(bar, trajectory=PiecewiseLinearPath([0.0, 1.0], [bar.trajectory.positions[0]] * 2,
                                                                    bar.trajectory.rotations[0]))


class SwayPath:
    """A bar swaying for ever: ``p0 + a sin(2 pi f t)`` and a roll of ``r sin(2 pi f t)`` degrees
    about the bar's forward axis (z)."""

    def __init__(self, p0, amplitude, roll_deg, frequency):
        self.p0, self.a = np.asarray(p0, dtype=np.float64), np.asarray(amplitude, dtype=np.float64)
        self.roll, self.f = float(roll_deg), float(frequency)
        self.positions, self.rotations = self.p0[None], np.zeros((1, 3))

    def pose(self, times):
        t = np.asarray(times, dtype=np.float64)
        w = 2 * np.pi * self.f
        s, c = np.sin(w * t)[:, None], np.cos(w * t)[:, None]
        angles = np.zeros((len(t), 3))
        angles[:, 2] = self.roll * s[:, 0]
        return self.p0 + self.a * s, w * self.a * c, euler_to_matrix(angles)
