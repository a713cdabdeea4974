"""A marionette rollout as a JAX function with a custom VJP (docs/gradients.md).

:func:`marionette_rollout` wraps a :class:`~dmarionette.grad.engine.MarionetteGradient`
engine: ``f(inputs) -> outputs``, dictionaries keyed by the ``RolloutInputs`` and
``RolloutOutputs`` field names, float64 arrays of the engine's shapes. The forward pass and
the reverse pass run the Warp engine on the host through ``jax.pure_callback``, so ``f``
works under ``jax.jit``, ``jax.grad``, ``jax.value_and_grad`` and ``jax.vjp`` (reverse mode
only: Warp's tape has no forward mode, so ``jax.jvp``/``jax.jacfwd`` are refused by JAX).

The optional inputs (``OPTIONAL_INPUT_FIELDS``: the strings' initial state) may be left out
of the dictionary: they then take the engine's ``default_inputs`` (the scene's rest state),
as constants.

The reverse pass gets the inputs as its residual: if the engine's last forward pass was
for other inputs (two rollouts in one program), it runs the forward again first.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from dmarionette.grad.engine import (INPUT_FIELDS, OPTIONAL_INPUT_FIELDS, OUTPUT_FIELDS, MarionetteGradient,
                                         RolloutInputs)

jax.config.update("jax_enable_x64", True)

__all__ = ["marionette_rollout"]


def marionette_rollout(engine: MarionetteGradient) -> Callable[[dict[str, jax.Array]], dict[str, jax.Array]]:
    """The rollout of ``engine`` as a differentiable JAX function.

    Args:
        engine: the Warp engine (its model, rollout length and checkpointing).

    Returns:
        ``f(inputs) -> outputs``: ``inputs`` has every ``RolloutInputs`` field (float64, the
        engine's ``input_shapes``; the ``OPTIONAL_INPUT_FIELDS`` may be left out);
        ``outputs`` every ``RolloutOutputs`` field (``output_shapes``).
    """
    if not isinstance(engine, MarionetteGradient):
        raise TypeError(f"marionette_rollout: got {type(engine).__name__}; expected a MarionetteGradient")
    in_specs = {k: jax.ShapeDtypeStruct(engine.input_shapes[k], jnp.float64) for k in INPUT_FIELDS}
    out_specs = {k: jax.ShapeDtypeStruct(engine.output_shapes[k], jnp.float64) for k in OUTPUT_FIELDS}
    defaults = {k: jnp.asarray(v) for k, v in engine.default_inputs.items()}

    def run_forward(values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        inputs = RolloutInputs(**{k: np.asarray(values[k], dtype=np.float64) for k in INPUT_FIELDS})
        outputs = engine.forward(inputs)
        return {k: getattr(outputs, k) for k in OUTPUT_FIELDS}

    def host_forward(values):
        return run_forward(values)

    def host_backward(values, cotangents):
        # The engine differentiates its own last forward pass, which may have been for other
        # inputs (another rollout in the program, or a direct engine.forward call): then run
        # the forward pass again for these.
        previous = engine.last_inputs
        if previous is None or any(not np.array_equal(getattr(previous, k), np.asarray(values[k]))
                                   for k in INPUT_FIELDS):
            run_forward(values)
        grads = engine.backward({k: np.asarray(v, dtype=np.float64) for k, v in cotangents.items()})
        return {k: getattr(grads, k) for k in INPUT_FIELDS}

    def check(inputs) -> dict[str, jax.Array]:
        if not isinstance(inputs, dict):
            raise TypeError(f"marionette rollout: inputs must be a dict of {list(INPUT_FIELDS)}; "
                            f"got {type(inputs).__name__}")
        inputs = {**{k: defaults[k] for k in OPTIONAL_INPUT_FIELDS if k not in inputs}, **inputs}
        missing = [k for k in INPUT_FIELDS if k not in inputs]
        extra = [k for k in inputs if k not in INPUT_FIELDS]
        if missing or extra:
            raise ValueError(f"marionette rollout inputs: missing {missing}, unknown {extra}; "
                             f"expected exactly {list(INPUT_FIELDS)} (optional: {list(OPTIONAL_INPUT_FIELDS)})")
        values = {}
        for k in INPUT_FIELDS:
            v = jnp.asarray(inputs[k], dtype=jnp.float64)
            if v.shape != in_specs[k].shape:
                raise ValueError(f"marionette rollout inputs[{k!r}]: got shape {v.shape}; "
                                 f"expected {in_specs[k].shape}")
            if not isinstance(inputs[k], jax.core.Tracer) and not np.all(np.isfinite(np.asarray(inputs[k]))):
                # concrete values are checked here; traced ones (under jit) by the engine, whose
                # ValueError then reaches the caller wrapped in JAX's runtime error
                raise ValueError(f"marionette rollout inputs[{k!r}]: contains NaN or infinity; expected finite values")
            values[k] = v
        return values

    @jax.custom_vjp
    def rollout(values):
        return jax.pure_callback(host_forward, out_specs, values, vmap_method="sequential")

    def rollout_fwd(values):
        return rollout(values), values

    def rollout_bwd(values, cotangents):
        grads = jax.pure_callback(host_backward, in_specs, values, cotangents, vmap_method="sequential")
        return (grads,)

    rollout.defvjp(rollout_fwd, rollout_bwd)

    def f(inputs: dict[str, jax.Array]) -> dict[str, jax.Array]:
        return rollout(check(inputs))

    return f
