"""String physics against closed-form answers and conservation laws (paper §2.2)."""

import math

import numpy as np
import pytest
from tests.support.strings import G, NOTHING, ONLY_GRAVITY, make_model, roll, spec, zero_crossing_times

from dmarionette.strings.model import StringEffects, string_energy
from dmarionette.strings.solver import SolverStringImplicit


@pytest.mark.parametrize("particle_count", [2, 7, 50])
def test_static_stretch_of_a_hanging_string_with_a_load(particle_count):
    """A string of mass m_s carrying a load M, top fixed, settles at the discrete closed form.

    Segment i (counted from the top) carries the weight of the n-i particles below it, so
    the total stretch is sum_i T_i / k_s = g (M + m_s n / (2 (n-1))) / k, which tends to the
    continuum answer g (M + m_s/2) / k. At equilibrium backward Euler has dv = 0 exactly,
    so the only error left is the residual motion after settling and float64 rounding.
    """
    n, length, load, string_mass, k = particle_count, 0.5, 0.1, 0.002, 500.0
    model = make_model([spec(particle_count=n, load_mass=load, mass=string_mass, stiffness=k,
                             internal_friction=0.5)], effects=StringEffects(air_drag=False, ground_contact=False))
    state, _ = roll(model, 1e-3, 6000, chunk=500)
    q = state.particle_q.numpy()
    stretch = (1.0 - q[-1, 1]) - length
    discrete = G * (load + string_mass * n / (2 * (n - 1))) / k
    assert abs(stretch - discrete) <= 1e-9 * discrete
    continuum = G * (load + string_mass / 2) / k
    assert abs(stretch - continuum) <= G * string_mass / (2 * (n - 1) * k) * (1 + 1e-6)
    assert np.max(np.abs(state.particle_qd.numpy())) < 1e-9


def test_period_of_a_small_pendulum():
    """A load on a light string swings with T = 2 pi sqrt(L/g) (1 + theta0^2/16).

    Known deviations, all below the 3e-4 tolerance: backward Euler's phase error
    (omega h)^2 / 3 = 7e-6; the string's own mass (m_s/M = 1e-3) shifts the period by
    about m_s / (12 M) = 8e-5; the finite-amplitude series is exact to O(theta0^4) = 6e-6;
    the zero crossings are interpolated linearly, error O((omega h)^2).
    """
    length, load, string_mass, theta0, k, n = 0.5, 0.1, 1e-4, 0.05, 2000.0, 20
    stretch = G * (load + string_mass * n / (2 * (n - 1))) / k  # at rest (see the static test)
    arm = length + stretch
    top = np.array([0.0, 1.0, 0.0])
    bottom = top + arm * np.array([math.sin(theta0), -math.cos(theta0), 0.0])
    model = make_model([spec(particle_count=n, load_mass=load, mass=string_mass, stiffness=k, length=length,
                             top=tuple(top), bottom=tuple(bottom))], effects=ONLY_GRAVITY)
    dt, chunk = 1e-3, 10
    expected = 2 * math.pi * math.sqrt(arm / G) * (1 + theta0**2 / 16)
    steps = chunk * int(4.5 * expected / (dt * chunk))
    _, result = roll(model, dt, steps, chunk=chunk)
    t = dt * chunk * np.arange(1, len(result.frames) + 1)
    crossings = zero_crossing_times(t, result.frames[:, -1, 0])
    period = 2 * np.mean(np.diff(crossings))
    assert len(crossings) >= 8
    assert abs(period - expected) / expected < 3e-4, (period, expected)


def test_transverse_wave_speed_on_a_taut_string():
    """The fundamental of a taut string fixed at both ends has f1 = c / (2 D), c = sqrt(T/mu).

    The string (gravity off) is stretched from rest length L to D, so T = k (D - L); mu is
    its moving mass per length. A chain of beads has omega_1 = 2 sqrt(T/(m a)) sin(pi/(2(n-1)))
    exactly; its relative deviation from the continuum, x^2/6 with x = pi/(2(n-1)), is
    1.2e-4 for n = 60. Backward Euler's phase error (omega h)^2/3 is 7e-6 at h = 1e-5.
    """
    n, span, rest, k, string_mass = 60, 1.0, 0.8, 1000.0, 0.01
    tension = k * (span - rest)
    model = make_model([spec(particle_count=n, top=(0.0, 0.0, 0.0), bottom=(span, 0.0, 0.0), length=rest,
                             mass=string_mass, stiffness=k, tied=True, tie_point=(span, 0.0, 0.0),
                             tie_stiffness=1e9, tie_damping=0.0)], effects=NOTHING)
    x = np.linspace(0.0, span, n)
    q = np.stack([x, 1e-3 * np.sin(np.pi * x / span), np.zeros(n)], axis=1)
    dt, chunk = 1e-5, 10
    mu = string_mass / span
    c = math.sqrt(tension / mu)
    f1 = c / (2 * span)
    steps = chunk * int(3.2 / f1 / (dt * chunk))
    _, result = roll(model, dt, steps, state=model.state(q), chunk=chunk)
    t = dt * chunk * np.arange(1, len(result.frames) + 1)
    crossings = zero_crossing_times(t, result.frames[:, n // 2, 1])
    measured_c = 2 * span / (2 * np.mean(np.diff(crossings)))
    bead_mass, a = string_mass / (n - 1), span / (n - 1)
    discrete_c = 2 * math.sqrt(tension / (bead_mass * a)) * math.sin(math.pi / (2 * (n - 1))) * span / math.pi
    assert abs(measured_c - discrete_c) / discrete_c < 5e-5, (measured_c, discrete_c)
    x_half = math.pi / (2 * (n - 1))
    assert abs(measured_c - c) / c < x_half**2 / 6 + 5e-5, (measured_c, c)


def test_undriven_damped_string_never_gains_energy():
    """Released from horizontal with its top fixed, a damped string only loses energy."""
    model = make_model([spec(particle_count=30, top=(0.0, 1.0, 0.0), bottom=(0.6, 1.0, 0.0), length=0.6,
                             load_mass=0.02, internal_friction=0.2, air_drag=0.05)],
                       effects=StringEffects(ground_contact=False))
    solver = SolverStringImplicit(model)
    a, b = model.state(), model.state()
    control = model.control()
    energies = [string_energy(model, a.particle_q.numpy(), a.particle_qd.numpy())["total"]]
    for _ in range(1500):
        solver.step(a, b, control, 1e-3)
        a, b = b, a
        energies.append(string_energy(model, a.particle_q.numpy(), a.particle_qd.numpy())["total"])
    energies = np.array(energies)
    rounding = 1e-12 * np.max(np.abs(energies))
    assert np.all(np.diff(energies) <= rounding), np.max(np.diff(energies))
    assert energies[-1] < energies[0] - 0.1 * abs(energies[0] - energies.min())


def test_string_dropped_on_the_ground_comes_to_rest_on_it():
    """A horizontal string dropped from 0.2 m (its top falling with it) lands and lies still.

    Tolerances: at rest the ground carries the string's weight, so the mean penetration is
    m g / k_p under the penalty stiffness k_p = ground_stiffness * d, i.e.
    m_s g / (ground_stiffness L) = 1e-5 m here (to 1 %: the held top carries a tiny share);
    a particle may also carry some of its neighbours' weight through the segment springs
    where the lying string is not perfectly straight (measured 0.5 %; allowed 10 %). During
    impact an undamped penalty spring hit at speed v under gravity compresses by at most
    m g / k_p + sqrt((m g / k_p)^2 + v^2 / omega^2) <= v / omega + 2 m g / k_p,
    omega = sqrt(k_p / m), with v the largest speed seen at any step.
    """
    n, length, string_mass, k_ground, height = 40, 1.0, 0.002, 2000.0, 0.2
    model = make_model([spec(particle_count=n, top=(0.0, height, 0.0), bottom=(length, height, 0.0), length=length,
                             mass=string_mass, internal_friction=0.5, air_drag=0.01,
                             ground_stiffness=k_ground, ground_absorption=5.0, ground_friction=2.0)],
                       effects=StringEffects())
    dt, steps = 1e-3, 4000
    t = dt * np.arange(1, steps + 1)
    top_y = np.maximum(height - 0.5 * G * t**2, 0.0)  # the held end falls freely, then rests on the ground
    top_q = np.zeros((steps, 1, 3))
    top_q[:, 0, 1] = top_y
    state, result = roll(model, dt, steps, top_q=top_q, chunk=1)
    depth = -result.frames[:, :, 1]
    speed = np.linalg.norm(result.frame_velocities, axis=2)
    m = string_mass / (n - 1)
    k_p = k_ground * length / (n - 1)
    impact_bound = speed.max() / math.sqrt(k_p / m) + 2 * m * G / k_p
    assert depth.max() <= impact_bound, (depth.max(), impact_bound)
    final_q = state.particle_q.numpy()
    static = m * G / k_p
    assert abs(np.mean(-final_q[1:, 1]) - static) <= 0.01 * static
    assert np.all(-final_q[:, 1] <= 1.1 * static)
    assert np.all(final_q[:, 1] <= 1e-9)  # every particle lies on the ground
    assert np.max(np.linalg.norm(state.particle_qd.numpy(), axis=1)) < 1e-3
