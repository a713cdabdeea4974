"""The strings' state and control as kernel arguments: ``StringStateArrays`` and ``StringControlArrays``.

A string step reads a state (``strings.model.StringState``: the particles' positions and
velocities) and a control (``StringControl``: the tops, the tie points and their velocities), and
writes a state (positions, velocities, the ties' forces, the taut flags). The one-launch steps
took these arrays one by one, the same twelve arguments repeated in every step kernel's signature
and every launch's input list; a ``wp.struct`` of each object's arrays holds them instead, built
by the object itself (``StringState.arrays``, ``StringControl.arrays``) and passed as
``state_in``, ``control`` and ``state_out``. Like ``StringModelArrays`` (``string_model_arrays``)
they hold the objects' own arrays (the same objects, not copies): a value written into one of
them in place is seen by every launch. A struct value holds its arrays' pointers and their
gradients', as a captured graph does: the objects rebuild it when one of their arrays, or its
``.grad``, is another object than the one it was built from (:func:`struct_of_arrays`).

Per float type (:func:`string_state_arrays_type`, :func:`string_control_arrays_type`; the three
argument types of a step's kernels at once, :func:`string_arrays_types`), as the kernels are.

Who takes them: the step adjoints and tangents (scalar and laned; the adjoints' gradients as
structs of the same types), the five taped passes, the bar work meter and the bar feedback
(``bar_feedback.eval_bar_feedback``, a state as ``state_in``; its tangent, made by
``kernel_tangent``, takes the tangents of the fields it reads by their names, ``particle_q`` and
``particle_qd``). Not the coupling's ``eval_string_response``: it reads one array of the state
(``particle_q``) and the marionette's ``tie_force`` of another shape, a name the struct's field
would clash with in its tangent. Not the one-launch plain
steps (``string_step``, ``string_step_lanes``): Warp specialises a CPU kernel's strides only for
top-level 1D arrays, and the structs made those steps slower (``string_step``'s module doc). Cost on
the host: a taped pass's backward launch gets a new mirror struct per struct argument from Warp's
tape (``wp.Tape.get_adjoint``), about 10 µs each: the five passes' taped backward (the reference
path, ``SolverStringImplicit.hand_adjoint = False``) is about 20 % slower for three short strings;
the bar feedback's two structs, once per string step, made the uncaptured taped backward of a
1 s ``hanging`` rollout about 7 % slower (0.39-0.42 s -> 0.41-0.46 s, ``benchmarks/bench_gradients.py
--seconds 1``, its "no capture" row), the captured one (the default: the mirrors are made once, at
capture) not measurably (0.032-0.033 s -> 0.031-0.032 s).
"""

import functools

import warp as wp

from .string_model_arrays import string_model_arrays_type

__all__ = ["CONTROL_FIELDS", "STATE_FIELDS", "STATE_GRAD_FIELDS", "string_arrays_types", "string_control_arrays_type",
           "string_state_arrays_type", "struct_of", "struct_of_arrays"]

# The fields of each struct (in the kernels' old argument order).
STATE_FIELDS = ("particle_q", "particle_qd", "tie_force", "string_taut")
CONTROL_FIELDS = ("top_q", "tie_q", "tie_qd")
# The state's fields a step differentiates (a gradients' ``StringStateArrays`` holds these; the taut
# flags have none).
STATE_GRAD_FIELDS = ("particle_q", "particle_qd", "tie_force")


@functools.cache
def string_state_arrays_type(scalar):
    """The ``StringStateArrays`` struct for the float type ``scalar`` (``wp.float64`` or ``wp.float32``)."""
    vec3 = wp.types.vector(3, scalar)

    @wp.struct
    class StringStateArrays:
        """A string state's arrays, one kernel argument: ``StringState``'s (the same objects; units
        and shapes: its attributes)."""

        particle_q: wp.array(dtype=vec3)
        particle_qd: wp.array(dtype=vec3)
        tie_force: wp.array(dtype=vec3)
        string_taut: wp.array(dtype=wp.int32)

    return StringStateArrays


@functools.cache
def string_control_arrays_type(scalar):
    """The ``StringControlArrays`` struct for the float type ``scalar``."""
    vec3 = wp.types.vector(3, scalar)

    @wp.struct
    class StringControlArrays:
        """A string control's arrays, one kernel argument: ``StringControl``'s (the same objects;
        units and shapes: its attributes)."""

        top_q: wp.array(dtype=vec3)
        tie_q: wp.array(dtype=vec3)
        tie_qd: wp.array(dtype=vec3)

    return StringControlArrays


def string_arrays_types(scalar):
    """``(StringModelArrays, StringStateArrays, StringControlArrays)`` for the float type ``scalar``: the
    three argument types of a string step's kernels (``string_model_arrays_type``,
    :func:`string_state_arrays_type`, :func:`string_control_arrays_type`)."""
    return string_model_arrays_type(scalar), string_state_arrays_type(scalar), string_control_arrays_type(scalar)


def struct_of(struct_type, fields, arrays, cached):
    """``cached`` (a ``(arrays, struct)`` pair or None) if it was built from these ``arrays`` (the
    same objects), else a new pair: a ``struct_type(scalar)`` (:func:`string_state_arrays_type` or
    :func:`string_control_arrays_type`, ``scalar`` the first array's vectors' float type) holding
    ``arrays`` as its ``fields`` (the others left empty)."""
    if cached is not None and len(cached[0]) == len(arrays) and all(a is b for a, b in zip(arrays, cached[0])):
        return cached
    struct = struct_type(arrays[0].dtype._wp_scalar_type_)()
    for name, array in zip(fields, arrays):
        setattr(struct, name, array)
    return list(arrays), struct


def struct_of_arrays(struct_type, owner, fields, cached):
    """:func:`struct_of` ``owner``'s arrays ``fields``, rebuilt only when one of them, or its
    gradient, is another object than the one it was built from (a struct value holds its arrays'
    gradient pointers too, which a captured launch checks: ``requires_grad`` set or cleared after
    the struct was built)."""
    if cached is not None:
        key = cached[0]
        n = len(fields)
        for i, name in enumerate(fields):
            array = getattr(owner, name)
            if array is not key[i] or array.grad is not key[n + i]:
                break
        else:
            return cached
    arrays = [getattr(owner, name) for name in fields]
    _arrays, struct = struct_of(struct_type, fields, arrays, None)
    return [*arrays, *[a.grad for a in arrays]], struct
