"""The gradient problem the marionette-gradient tests share: the ``hanging`` puppet on its main
bar, pre-tensioned strings (tests/grad/test_marionette_gradients.py explains the choices),
a fixed random linear loss, and its directional derivatives against central differences."""

from __future__ import annotations

import dataclasses

import numpy as np

import dmarionette as dm
from dmarionette.grad.engine import MarionetteGradient, RolloutInputs
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette

PUPPET_STEPS = 30           # 1 s at 30 Hz
PRETENSION = (3.0, 2.0, 2.0, 2.0)  # N, head, back, knees
CONTACT_GROUND = 0.075      # m: the feet come down on it after about 0.35 s


def smooth_scene(name: str, particle_count: int | None = None):
    """The built-in scene ``name`` as shipped (joint limits and its other effects on) with smooth
    contact, and ``particle_count`` particles per string when given (fewer: a cheaper rollout)."""
    scene = dm.load_scene(name)
    if particle_count is not None:
        scene = dataclasses.replace(
            scene, strings=tuple(dataclasses.replace(s, particle_count=particle_count) for s in scene.strings))
    return dataclasses.replace(scene, contact=dict(scene.contact, smooth=True))


def gradient_scene(contact: bool):
    scene = dm.load_scene("hanging")
    keep = [i for i, s in enumerate(scene.strings) if not s.name.startswith("hand")]
    strings = tuple(dataclasses.replace(scene.strings[i], particle_count=10) for i in keep)
    effects = dict(scene.body_effects, body_ground=contact, joint_limits=False)
    scene = dataclasses.replace(scene, strings=strings, string_body_points=tuple(scene.string_body_points[i] for i in keep),
                                bars=scene.bars[:1], body_effects=effects, contact=dict(scene.contact, smooth=True),
                                ground_height=CONTACT_GROUND if contact else scene.ground_height)
    straight = MarionetteModel(scene, optimization_level=0)  # the string lengths bar -> body point
    strings = tuple(dataclasses.replace(s, length=straight.strings.specs[i].length - PRETENSION[i] / s.stiffness)
                    for i, s in enumerate(scene.strings))
    return dataclasses.replace(scene, strings=strings)


class Problem:
    def __init__(self, contact: bool, scene=None, puppet_steps: int = PUPPET_STEPS, checkpoint_steps: int = 4):
        scene = gradient_scene(contact) if scene is None else scene
        self.model = MarionetteModel(scene, optimization_level=0, requires_grad=True)
        # 7 segments of 4 puppet steps and one of 2 (a shorter last segment is planned apart)
        self.engine = MarionetteGradient(self.model, puppet_steps, checkpoint_steps=checkpoint_steps)
        self.inputs = self.engine.scene_inputs()
        rng = np.random.default_rng(3)
        self.weights = {k: rng.normal(size=s) / np.sqrt(np.prod(s)) for k, s in self.engine.output_shapes.items()}
        self.outputs = self.engine.forward(self.inputs)
        self.grads = self.engine.backward(self.weights)

    def loss(self, inputs: RolloutInputs) -> float:
        out = self.engine.forward(inputs)
        return sum(float(np.sum(w * getattr(out, k))) for k, w in self.weights.items())

    def fd(self, name: str, direction: np.ndarray, eps: float) -> float:
        """Richardson-extrapolated central difference of the loss along ``direction`` of input ``name``."""
        base = getattr(self.inputs, name)

        def central(e):
            plus = dataclasses.replace(self.inputs, **{name: base + e * direction})
            minus = dataclasses.replace(self.inputs, **{name: base - e * direction})
            return (self.loss(plus) - self.loss(minus)) / (2.0 * e)

        return (4.0 * central(eps / 2.0) - central(eps)) / 3.0

    def check(self, tolerance: float) -> dict[str, float]:
        """Worst relative error per input group over its directions."""
        rng = np.random.default_rng(5)
        worst = {}
        cases = []
        for name in ("top_q", "bar_q", "bar_qd", "joint_q0", "joint_qd0"):
            cases.append((name, rng.normal(size=self.engine.input_shapes[name]), 1e-6))
        for name, eps in (("particle_q0", 1e-5), ("particle_qd0", 1e-2)):  # the strings' initial state
            for _ in range(3):
                cases.append((name, rng.normal(size=self.engine.input_shapes[name]), eps))
        for name in ("tie_stiffness", "tie_damping", "string_stiffness"):
            base = getattr(self.inputs, name)
            for i in range(len(base)):
                unit = np.zeros_like(base)
                unit[i] = 1.0
                cases.append((name, unit, 1e-3 * base[i]))
        for name, direction, eps in cases:
            analytic = float(np.sum(getattr(self.grads, name) * direction))
            numeric = self.fd(name, direction, eps)
            error = abs(analytic - numeric) / abs(numeric)
            worst[name] = max(worst.get(name, 0.0), error)
        self.engine.forward(self.inputs)  # leave the engine at the base inputs
        print({k: f"{v:.1e}" for k, v in worst.items()})
        assert max(worst.values()) <= tolerance, worst
        return worst


def string_margins(model: MarionetteModel, puppet_steps: int = PUPPET_STEPS) -> tuple[float, bool]:
    """Smallest relative segment stretch ``(l - d) / d`` after any string step of the scene's
    rollout (the first step starts from straight strings), and whether every string stayed taut."""
    solver = SolverMarionette(model)
    a, b, control = model.state(), model.state(), model.control()
    start = model.strings.string_start_np
    rest = model.strings.string_rest_length.numpy()
    smallest, taut = np.inf, True
    for p in range(puppet_steps):
        control.set_bars(model, p * model.puppet_dt)
        solver.begin_step(a, b)
        for j in range(model.substeps):
            solver.step_string(a, b, control, j)
            q = solver.string_state_after(b, j).particle_q.numpy()
            for s in range(model.strings.string_count):
                length = np.linalg.norm(np.diff(q[start[s]:start[s + 1]], axis=0), axis=1)
                smallest = min(smallest, float(np.min((length - rest[s]) / rest[s])))
        solver.end_step(a, b)
        taut &= bool(np.all(b.string_taut.numpy() == 1))
        a, b = b, a
    return smallest, taut
