"""A marionette rollout as a JAX function with a custom VJP (docs/gradients.md).

:func:`marionette_rollout` wraps a :class:`~dmarionette.grad.engine.MarionetteGradient`
engine: ``f(inputs) -> outputs``, dictionaries keyed by the ``RolloutInputs`` and
``RolloutOutputs`` field names, float64 arrays of the engine's shapes. The forward pass and
the reverse pass run the Warp engine on the host through ``jax.pure_callback``, so ``f``
works under ``jax.jit``, ``jax.grad``, ``jax.value_and_grad`` and ``jax.vjp`` (reverse mode
only: ``jax.jvp``/``jax.jacfwd`` are refused by JAX on it; :func:`marionette_rollout_jvp` is the
same rollout with a custom JVP, forward mode through ``MarionetteGradient.jvp``).

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

__all__ = ["marionette_rollout", "marionette_rollout_jvp"]


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

    check = _input_checker(in_specs, defaults)

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


def marionette_rollout_jvp(engine: MarionetteGradient) -> Callable[[dict[str, jax.Array]], dict[str, jax.Array]]:
    """The rollout of ``engine`` as a JAX function with a custom JVP (forward mode).

    The same function as :func:`marionette_rollout` (same inputs and outputs), differentiated in
    forward mode: its JVP rule runs :meth:`MarionetteGradient.jvp` (the rollout and its tangents,
    :class:`~dmarionette.grad.rollout_tangent.RolloutTangent`) on the host through one
    ``jax.pure_callback``, so ``jax.jvp``, ``jax.jacfwd`` and ``jax.linearize`` work, also under
    ``jax.jit``. ``jax.jacfwd`` (a ``vmap`` of the JVP over the basis directions) reaches the host
    as ONE call with all its directions (``vmap_method="expand_dims"``): one rollout for P
    directions. Reverse mode (``jax.grad``, ``jax.vjp``) needs :func:`marionette_rollout`: the
    tangent callback is not transposable. One-world engines only.

    Args:
        engine: the Warp engine (its model and rollout length).

    Returns:
        ``f(inputs) -> outputs`` as :func:`marionette_rollout`'s.
    """
    if not isinstance(engine, MarionetteGradient):
        raise TypeError(f"marionette_rollout_jvp: got {type(engine).__name__}; expected a MarionetteGradient")
    if engine.world_count != 1:
        raise ValueError(f"marionette_rollout_jvp: a model of {engine.world_count} worlds; expected one world")
    in_specs = {k: jax.ShapeDtypeStruct(engine.input_shapes[k], jnp.float64) for k in INPUT_FIELDS}
    out_specs = {k: jax.ShapeDtypeStruct(engine.output_shapes[k], jnp.float64) for k in OUTPUT_FIELDS}
    defaults = {k: jnp.asarray(v) for k, v in engine.default_inputs.items()}
    check = _input_checker(in_specs, defaults)

    def host_forward(values):
        # pure_callback's "expand_dims" (under vmap) adds leading axes: the inputs may be a batch
        batch, values = _batched(values, engine.input_shapes)
        outs = [engine.forward(RolloutInputs(**{k: values[k][i] for k in INPUT_FIELDS}))
                for i in range(values["top_q"].shape[0])]
        return {k: np.stack([getattr(o, k) for o in outs]).reshape(batch + engine.output_shapes[k])
                for k in OUTPUT_FIELDS}

    def host_jvp(values, dots):
        # One engine.jvp for all directions: under vmap (jax.jacfwd) the tangents come with leading
        # batch axes (the directions) while the inputs, unbatched, come with axes of size 1.
        value_batch = _batch_shape(values, engine.input_shapes)
        dot_batch = _batch_shape(dots, engine.input_shapes)
        batch = tuple(np.broadcast_shapes(value_batch, dot_batch))
        count = int(np.prod(batch, dtype=int))
        dots = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), batch + engine.input_shapes[k]).reshape(
            (count,) + engine.input_shapes[k]) for k, v in dots.items()}
        if int(np.prod(value_batch, dtype=int)) == 1:  # one point, all directions in one rollout
            point = {k: np.asarray(values[k], dtype=np.float64).reshape(engine.input_shapes[k]) for k in INPUT_FIELDS}
            _, dot = engine.jvp(RolloutInputs(**point), dots)
            return {k: dot[k].reshape(batch + engine.output_shapes[k]) for k in OUTPUT_FIELDS}
        # the inputs themselves batched (a vmap over points): one rollout per point
        values = {k: np.broadcast_to(np.asarray(v, dtype=np.float64), batch + engine.input_shapes[k]).reshape(
            (count,) + engine.input_shapes[k]) for k, v in values.items()}
        results = [engine.jvp(RolloutInputs(**{k: values[k][i] for k in INPUT_FIELDS}),
                              {k: dots[k][i:i + 1] for k in INPUT_FIELDS})[1] for i in range(count)]
        return {k: np.stack([d[k][0] for d in results]).reshape(batch + engine.output_shapes[k])
                for k in OUTPUT_FIELDS}

    @jax.custom_jvp
    def rollout(values):
        return jax.pure_callback(host_forward, out_specs, values, vmap_method="expand_dims")

    @rollout.defjvp
    def rollout_jvp(primals, tangents):
        # The primal by its own callback: under jax.jacfwd the tangents are batched and the primal
        # must not be (a callback's results are batched as a whole). One more plain rollout than
        # engine.jvp needs (it computes the primal too); XLA drops it where only tangents are used.
        (values,), (dots,) = primals, tangents
        return rollout(values), jax.pure_callback(host_jvp, out_specs, values, dots, vmap_method="expand_dims")

    def f(inputs: dict[str, jax.Array]) -> dict[str, jax.Array]:
        return rollout(check(inputs))

    return f


def _batch_shape(values: dict, shapes: dict) -> tuple[int, ...]:
    """The leading (vmap) axes of a callback's arguments beyond their ``shapes``, broadcast together."""
    return tuple(np.broadcast_shapes(*(np.shape(v)[:np.ndim(v) - len(shapes[k])] for k, v in values.items())))


def _batched(values: dict, shapes: dict) -> tuple[tuple[int, ...], dict[str, np.ndarray]]:
    """``values`` broadcast to their common leading axes, flattened to one: (those axes, the arrays)."""
    batch = _batch_shape(values, shapes)
    count = int(np.prod(batch, dtype=int))
    return batch, {k: np.broadcast_to(np.asarray(v, dtype=np.float64), batch + shapes[k]).reshape((count,) + shapes[k])
                   for k, v in values.items()}


def _input_checker(in_specs: dict, defaults: dict) -> Callable[[dict], dict[str, jax.Array]]:
    """The wrappers' check of an inputs dict (names, shapes, finite concrete values; defaults filled in)."""

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

    return check
