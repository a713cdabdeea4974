"""Gradients of a loss on final string positions (Warp tape) against central finite differences.

Float64, 500 steps at 1 ms of a loaded string whose top moves, with gravity, internal
friction and air drag on (ground contact off: its switch is not differentiable). The
loss is L = sum_i w_i . x_i(T) with fixed random weights. Each gradient is checked as a
directional derivative g . u against (L(p + e u) - L(p - e u)) / (2 e); with e = 1e-6 of
the parameter's scale the truncation error is O(e^2) and rounding O(1e-16 / e), both
far below the 1e-5 relative tolerance.
"""

import numpy as np
import pytest
import warp as wp
from strings_support import make_model, spec

from dmarionette.string_model import StringControl, StringEffects
from dmarionette.string_solver import SolverStringImplicit

STEPS = 500
DT = 1e-3
TOLERANCE = 1e-5


@wp.kernel
def weighted_position_sum(
    q: wp.array(dtype=wp.vec3d), weight: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)
):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(q[i], weight[i]))


class Problem:
    """A loaded, swinging string and a loss on its final positions."""

    def __init__(self):
        self.model = make_model(
            [spec(particle_count=12, top=(0.0, 1.0, 0.0), bottom=(0.3, 0.6, 0.1), length=0.5, load_mass=0.05,
                  internal_friction=0.3, air_drag=0.05, stiffness=800.0)],
            effects=StringEffects(ground_contact=False), requires_grad=True,
        )
        rng = np.random.default_rng(7)
        self.weight = wp.array(rng.normal(size=(self.model.particle_count, 3)), dtype=wp.vec3d)
        t = DT * np.arange(1, STEPS + 1)
        self.top_path = np.zeros((STEPS, 1, 3))
        self.top_path[:, 0] = np.stack([0.05 * np.sin(6.0 * t), 1.0 + 0.02 * np.sin(9.0 * t), 0.03 * t], axis=1)
        self.solver = SolverStringImplicit(self.model)

    def controls(self):
        m = self.model
        tie = np.zeros((1, 3))
        return [StringControl.from_numpy(m, self.top_path[k], tie, tie) for k in range(STEPS)]

    def loss(self, initial=None, tape=None):
        """Runs the rollout (on ``tape`` if given); returns (loss array, controls, first state)."""
        m = self.model
        states = [m.state() if initial is None else m.state(*initial)]
        states += [m.state() for _ in range(STEPS)]
        controls = self.controls()
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        with tape if tape is not None else _nullcontext():
            for k in range(STEPS):
                self.solver.step(states[k], states[k + 1], controls[k], DT)
            wp.launch(weighted_position_sum, dim=m.particle_count, inputs=[states[-1].particle_q, self.weight],
                      outputs=[loss])
        return loss, controls, states[0]


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.fixture(scope="module")
def taped():
    problem = Problem()
    tape = wp.Tape()
    loss, controls, first = problem.loss(tape=tape)
    tape.backward(loss)
    return problem, controls, first


def _central(f, eps):
    return (f(+eps) - f(-eps)) / (2 * eps)


def _check(analytic, numeric):
    assert abs(analytic - numeric) <= TOLERANCE * abs(numeric), (analytic, numeric)
    assert abs(numeric) > 1e-8  # the direction matters to the loss


@pytest.mark.parametrize("name", ["string_stiffness", "string_internal_friction", "string_air_drag"])
def test_gradient_wrt_string_constants(taped, name):
    problem, _, _ = taped
    array = getattr(problem.model, name)
    analytic = float(array.grad.numpy()[0])
    base = float(array.numpy()[0])

    def loss_at(delta):
        array.numpy()[0] = base + delta
        value = float(problem.loss()[0].numpy()[0])
        array.numpy()[0] = base
        return value

    _check(analytic, _central(loss_at, 1e-6 * base))


def test_gradient_wrt_top_trajectory(taped):
    """Along a smooth random perturbation of the bar path (a few random low-frequency sines).

    An independent random jitter at every step would be a velocity jitter of e / dt, which
    excites the stiff string modes and makes the finite difference itself converge only
    at e ~ 1e-8 (measured); a smooth path perturbation is the physically meaningful check.
    """
    problem, controls, _ = taped
    rng = np.random.default_rng(3)
    t = DT * np.arange(1, STEPS + 1)
    direction = np.zeros(problem.top_path.shape)
    for axis in range(3):
        for frequency in (1.0, 2.5, 4.0):
            direction[:, 0, axis] += rng.normal() * np.sin(2 * np.pi * frequency * t + rng.uniform(0, 2 * np.pi))
    analytic = sum(float(np.sum(c.top_q.grad.numpy() * direction[k])) for k, c in enumerate(controls))
    base = problem.top_path.copy()

    def loss_at(delta):
        problem.top_path = base + delta * direction
        value = float(problem.loss()[0].numpy()[0])
        problem.top_path = base
        return value

    _check(analytic, _central(loss_at, 1e-6))


@pytest.mark.parametrize("which", ["particle_q", "particle_qd"])
def test_gradient_wrt_initial_state(taped, which):
    problem, _, first = taped
    m = problem.model
    q0, qd0 = m.initial_positions(), np.zeros((m.particle_count, 3))
    rng = np.random.default_rng(11)
    direction = rng.normal(size=q0.shape)
    direction[0] = 0.0  # the top particle is placed by the control, not by the initial state
    analytic = float(np.sum(getattr(first, which).grad.numpy() * direction))
    scale = 1e-7 if which == "particle_q" else 1e-5

    def loss_at(delta):
        q, qd = (q0 + delta * direction, qd0) if which == "particle_q" else (q0, qd0 + delta * direction)
        return float(problem.loss(initial=(q, qd))[0].numpy()[0])

    _check(analytic, _central(loss_at, scale))
