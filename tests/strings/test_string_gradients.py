"""Gradients of a loss on final string positions (Warp tape) against central finite differences.

Float64, 500 steps at 1 ms of a loaded string whose top moves, with gravity, internal
friction and air drag on (ground contact off: its switch is not differentiable). The
loss is L = sum_i w_i . x_i(T) with fixed random weights. Each gradient is checked as a
directional derivative g . u against (L(p + e u) - L(p - e u)) / (2 e). Central
differences have truncation error O(e^2) and rounding error O(1e-16 |L| / (e |g|)), and
a step must not straddle a kink of the loss. A segment passing through slack is such a kink
(the geometric stiffness is clamped there): the problem starts near equilibrium and moves
gently enough that no segment of the free string goes slack (checked by a test below). The
step for each case was chosen from a sweep over e = 1e-3 ... 1e-9 of the parameter:
- free string constants and paths, e = 1e-6 (top path: 6e-12 at 1e-6);
- tied string constants, e = 1e-4: these gradients are up to 1e4 times smaller than the
  loss, so rounding dominates small steps (k_s: 6e-7 at 1e-4, 8e-5 at 1e-6);
- initial state: 1e-7 m, 1e-5 m/s.
"""

import contextlib

import numpy as np
import pytest
import warp as wp
from tests.support.strings import make_model, spec

from dmarionette.strings.model import StringControl, StringEffects
from dmarionette.strings.solver import SolverStringImplicit

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

    def __init__(self, tied=False, tension_only=False):
        self.model = make_model(
            [spec(particle_count=12, top=(0.0, 1.0, 0.0), bottom=(0.0, 0.499, 0.0), length=0.5, load_mass=0.05,
                  internal_friction=0.3, air_drag=0.05, stiffness=800.0, tied=tied, tie_point=(0.25, 0.55, 0.1),
                  tie_stiffness=300.0, tie_damping=3.0)],
            effects=StringEffects(ground_contact=False, tension_only=tension_only), requires_grad=True,
        )
        rng = np.random.default_rng(7)
        self.weight = wp.array(rng.normal(size=(self.model.particle_count, 3)), dtype=wp.vec3d)
        t = DT * np.arange(1, STEPS + 1)
        self.top_path = np.zeros((STEPS, 1, 3))
        self.top_path[:, 0] = np.stack([0.02 * np.sin(6.0 * t), 1.0 + 0.005 * np.sin(9.0 * t), 0.03 * t], axis=1)
        # The body point a tied string holds moves on a circle (its velocity is consistent).
        self.tie_path = np.zeros((STEPS, 1, 3))
        self.tie_path[:, 0] = np.stack([0.25 + 0.05 * np.cos(4.0 * t), 0.55 + 0.05 * np.sin(4.0 * t), 0.1 + 0 * t], 1)
        self.tie_velocity = np.zeros((STEPS, 1, 3))
        self.tie_velocity[:, 0] = np.stack([-0.2 * np.sin(4.0 * t), 0.2 * np.cos(4.0 * t), 0 * t], 1)
        self.solver = SolverStringImplicit(self.model)

    def controls(self):
        m = self.model
        return [StringControl.from_numpy(m, self.top_path[k], self.tie_path[k], self.tie_velocity[k])
                for k in range(STEPS)]

    def loss(self, initial=None, tape=None):
        """Runs the rollout (on ``tape`` if given); returns (loss array, controls, first state)."""
        m = self.model
        states = [m.state() if initial is None else m.state(*initial)]
        states += [m.state() for _ in range(STEPS)]
        controls = self.controls()
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        with tape if tape is not None else contextlib.nullcontext():
            for k in range(STEPS):
                self.solver.step(states[k], states[k + 1], controls[k], DT, tape=tape)
            wp.launch(weighted_position_sum, dim=m.particle_count, inputs=[states[-1].particle_q, self.weight],
                      outputs=[loss])
        return loss, controls, states[0]


def _taped(**options):
    """A ``Problem(**options)``'s loss run on a tape and differentiated: ``(problem, controls, first)``."""
    problem = Problem(**options)
    tape = wp.Tape()
    loss, controls, first = problem.loss(tape=tape)
    tape.backward(loss)
    return problem, controls, first


@pytest.fixture(scope="module")
def taped():
    return _taped()


def _central(f, eps):
    return (f(+eps) - f(-eps)) / (2 * eps)


def _check(analytic, numeric):
    assert abs(analytic - numeric) <= TOLERANCE * abs(numeric), (analytic, numeric)
    assert abs(numeric) > 1e-8  # the direction matters to the loss


def test_the_free_string_stays_taut_so_the_loss_is_smooth():
    problem = Problem()
    m = problem.model
    states = [m.state() for _ in range(STEPS + 1)]
    rest = m.string_rest_length.numpy()[0]
    for k, control in enumerate(problem.controls()):
        problem.solver.step(states[k], states[k + 1], control, DT)
        lengths = np.linalg.norm(np.diff(states[k + 1].particle_q.numpy(), axis=0), axis=1)
        assert lengths.min() > rest, (k, lengths.min(), rest)


def _check_constant(problem, name: str, relative_step: float) -> float:
    """The taped gradient of the loss w.r.t. the first string's constant ``name`` against central
    differences at ``relative_step``; returns the taped value."""
    array = getattr(problem.model, name)
    analytic = float(array.grad.numpy()[0])
    base = float(array.numpy()[0])

    def loss_at(delta):
        array.numpy()[0] = base + delta
        value = float(problem.loss()[0].numpy()[0])
        array.numpy()[0] = base
        return value

    _check(analytic, _central(loss_at, relative_step * base))
    return analytic


def _check_path(problem, attr: str, direction: np.ndarray, analytic: float) -> None:
    """The taped directional derivative ``analytic`` of the loss along ``direction`` of the input
    path ``problem.<attr>`` against central differences."""
    base = getattr(problem, attr).copy()

    def loss_at(delta):
        setattr(problem, attr, base + delta * direction)
        value = float(problem.loss()[0].numpy()[0])
        setattr(problem, attr, base)
        return value

    _check(analytic, _central(loss_at, 1e-6))


@pytest.mark.parametrize("name", ["string_stiffness", "string_internal_friction", "string_air_drag"])
def test_gradient_wrt_string_constants(taped, name, relative_step=1e-6):
    problem, _, _ = taped
    _check_constant(problem, name, relative_step)


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
    _check_path(problem, "top_path", direction, analytic)


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


@pytest.fixture(scope="module")
def taped_tied():
    return _taped(tied=True)


@pytest.mark.parametrize("name", ["string_tie_stiffness", "string_tie_damping", "string_stiffness"])
def test_gradient_of_a_tied_string_wrt_its_constants(taped_tied, name):
    """Through the eq. 2 tie to a moving body point (the coupling the puppet will use)."""
    test_gradient_wrt_string_constants(taped_tied, name, relative_step=1e-4)


def test_gradient_wrt_body_point_path(taped_tied):
    """With respect to the tied body point's positions (a smooth random perturbation)."""
    problem, controls, _ = taped_tied
    rng = np.random.default_rng(5)
    t = DT * np.arange(1, STEPS + 1)
    direction = np.zeros(problem.tie_path.shape)
    for axis in range(3):
        direction[:, 0, axis] = rng.normal() * np.sin(2 * np.pi * 1.5 * t + rng.uniform(0, 2 * np.pi))
    analytic = sum(float(np.sum(c.tie_q.grad.numpy() * direction[k])) for k, c in enumerate(controls))
    _check_path(problem, "tie_path", direction, analytic)


@pytest.fixture(scope="module")
def taped_tension_only():
    return _taped(tension_only=True)


@pytest.mark.parametrize("name", ["string_stiffness", "string_internal_friction"])
def test_gradient_with_tension_only_springs(taped, taped_tension_only, name, relative_step=1e-6):
    """The tension-only springs' taped step (an unrecorded pass finds the active set, the
    recorded pass assembles and solves with it): on the same always-taut problem it gives
    the printed spring's loss and gradient, and matches central differences."""
    problem, _, _ = taped_tension_only
    analytic = _check_constant(problem, name, relative_step)
    printed = float(getattr(taped[0].model, name).grad.numpy()[0])
    assert abs(analytic - printed) <= 1e-9 * abs(printed), (analytic, printed)
