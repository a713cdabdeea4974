"""Where float32 strings meet the float64 puppet: vectors cast from one float type to the other.

A marionette with ``[solver] precision = "float32"`` runs its strings (model, solver, state)
in float32 and its puppet in float64 (the articulation solver is float64 only). What
crosses between them is converted explicitly, by :func:`convert_vec3` (``SolverMarionette``):

- to the strings (float64 -> float32): the string tops on the bar (``top_q``), one row per
  string step, and the tie path the puppet's points give the strings (``tie_q``, ``tie_qd``),
  once per puppet step;
- from the strings (float32 -> float64): the eq. 2 tie force after every string step, into
  the float64 ``MarionetteState.tie_force`` that the coupling to the puppet and every
  reader (rollouts, live loop, sessions, energy) use. The bar feedback is evaluated by a
  mixed kernel (``bar_feedback.eval_bar_feedback_kernel(..., bar_scalar=wp.float64)``)
  that reads the float32 particles and writes the float64 feedback directly.

A float64 marionette launches none of these (the strings read the control buffers and
write the state arrays themselves).
"""

import functools

import warp as wp

__all__ = ["convert_vec3", "convert_vec3_kernel"]


@functools.cache
def convert_vec3_kernel(scalar_in, scalar_out):
    """Builds ``convert_vec3`` from 3-vectors of ``scalar_in`` to 3-vectors of ``scalar_out``
    (rounded to nearest when narrowing, exact when widening)."""
    vec3_in = wp.types.vector(3, scalar_in)
    vec3_out = wp.types.vector(3, scalar_out)

    @wp.kernel(module="unique")
    def convert_vec3(
        # State in:
        values_in: wp.array(dtype=vec3_in),
        # State out:
        values_out: wp.array(dtype=vec3_out),
    ):
        i = wp.tid()
        values_out[i] = vec3_out(values_in[i])

    return convert_vec3


_SCALAR = {24: wp.float64, 12: wp.float32}  # a 3-vector's float type, by its size in bytes


def convert_vec3(values_in: wp.array, values_out: wp.array, device) -> None:
    """Writes ``values_in`` cast to ``values_out``'s float type into ``values_out``.

    Args:
        values_in: contiguous 3-vectors, any shape (read flat).
        values_out: contiguous 3-vectors of the same shape, another float type.
        device: the Warp device of both.
    """
    if values_in.shape != values_out.shape:
        raise ValueError(f"convert_vec3: shapes differ: {values_in.shape} -> {values_out.shape}")
    flat_in, flat_out = values_in.flatten(), values_out.flatten()
    kernel = convert_vec3_kernel(*(_SCALAR[wp.types.type_size_in_bytes(a.dtype)] for a in (flat_in, flat_out)))
    wp.launch(kernel, dim=flat_in.shape[0], inputs=[flat_in], outputs=[flat_out], device=device)
