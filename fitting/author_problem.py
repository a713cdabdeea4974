"""The authoring problem of a keyframes file: the marionette with gradients, its engine, the
bars' parameterisation and the objective (``build_problem``). Its own module so that the
command (:mod:`fitting.author`) and the warm start (:mod:`fitting.quasi_static`) share it without
importing each other."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .bar_spline import BarParameterisation
from .keyframes import AuthorSpec
from .objective import AuthoringObjective

__all__ = ["AuthoringProblem", "build_problem"]


def _count_passes(engine) -> dict:
    """Counts the engine's forward and backward passes (and their time), in place."""
    counts = {"forward": 0, "backward": 0, "forward_s": 0.0, "backward_s": 0.0}

    def counted(name, method):
        def call(*args, **kwargs):
            start = time.perf_counter()
            result = method(*args, **kwargs)
            counts[name] += 1
            counts[f"{name}_s"] += time.perf_counter() - start
            return result
        return call

    engine.forward = counted("forward", engine.forward)
    engine.backward = counted("backward", engine.backward)
    return counts


@dataclasses.dataclass
class AuthoringProblem:
    """Everything a solve needs: the spec, model, engine, parameterisation and objective."""

    spec: AuthorSpec
    model: Any
    engine: Any
    counts: dict
    param: BarParameterisation
    objective: AuthoringObjective
    puppet_steps: int

    def counter(self) -> dict:
        return {k: v for k, v in self.counts.items() if k in ("forward", "backward")}

    def forward(self, y: dict) -> dict[str, np.ndarray]:
        """The rollout's outputs for knots ``y`` (NumPy; no JAX dispatch but the jitted spline)."""
        from dmarionette.grad.engine import OUTPUT_FIELDS, RolloutInputs

        if not hasattr(self, "_inputs"):
            self._inputs = jax.jit(self.param.rollout_inputs)
        inputs = {k: np.asarray(v) for k, v in self._inputs({k: jnp.asarray(v) for k, v in y.items()}).items()}
        constants = {k: np.asarray(v) for k, v in self.objective.constants.items()}
        result = self.engine.forward(RolloutInputs(**constants, **inputs))
        return {k: np.asarray(getattr(result, k)) for k in OUTPUT_FIELDS}


def build_problem(spec: AuthorSpec, *, optimization_level: int = 2,
                  checkpoint_steps: int | None = None) -> AuthoringProblem:
    """Builds the marionette (with gradients), the engine and the objective of ``spec``."""
    try:
        from dmarionette.marionette.solver import MarionetteModel
        from dmarionette.grad.engine import MarionetteGradient

        from .rollout import marionette_rollout
    except ImportError as error:  # pragma: no cover - depends on the install
        raise RuntimeError(f"authoring needs the gradient engine and JAX: {error}") from None
    model = MarionetteModel(spec.scene, optimization_level=optimization_level, requires_grad=True)
    puppet_steps = max(1, int(round(spec.duration / model.puppet_dt)))
    engine = MarionetteGradient(model, puppet_steps, checkpoint_steps=checkpoint_steps)
    counts = _count_passes(engine)
    param = BarParameterisation(spec, model, puppet_steps)
    scene_inputs = engine.scene_inputs()
    constants = {f.name: getattr(scene_inputs, f.name) for f in dataclasses.fields(scene_inputs)
                 if f.name not in ("top_q", "bar_q", "bar_qd")}
    objective = AuthoringObjective(spec, model, param, marionette_rollout(engine), constants)
    return AuthoringProblem(spec=spec, model=model, engine=engine, counts=counts, param=param, objective=objective,
                            puppet_steps=puppet_steps)
