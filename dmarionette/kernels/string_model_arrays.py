"""The string model's constants as one kernel argument: ``StringModelArrays``, per float type.

Every string kernel reads the same constants of ``strings.model.StringModel``: the strings'
layout (``string_start``), the particles' masses, each string's per-segment and per-particle
constants and the scene's gravity and ground height. They used to be passed one by one, fifteen
arguments repeated in every kernel's signature and every launch's input list; a ``wp.struct``
holds them instead, built once by the model (``StringModel.arrays``) and passed to every string
kernel as ``model``. It holds the model's own arrays (the same objects, not copies): a value
uploaded into one of them in place is seen by every launch, and a taped launch's adjoint reaches
each array's ``.grad`` (Warp's tape mirrors a struct argument's array fields with their
gradients, ``wp.Tape.get_adjoint``).

Who takes it: every string step kernel (the one-launch steps, the five passes, the adjoints and
tangents), the bar work meter (``marionette/energy.py``), the bar feedback
(``bar_feedback.eval_bar_feedback``, as ``model``) and the coupling's linear model of the strings
(``string_body_coupling.eval_string_response``, as ``strings``; the coupling's anchors take the
marionette's float64 copy of the ties' ``k`` instead). The last two have tangents made by
``kernel_tangent``, which gives the fields they read tangents named by the fields
(``string_stiffness``, ...).

The kernels are built per float type by factories, so the struct is too
(:func:`string_model_arrays_type`, one per ``wp.float32``/``wp.float64``), with
:func:`string_constants_function`'s ``compute_string_constants``, the one place a kernel reads a
string's constants ("the string's constants, read once"), into a ``StringConstants`` value
(:func:`string_constants_type`) that the functions of a row take as one argument.
"""

import functools

import warp as wp

__all__ = ["ARRAY_FIELDS", "DIFFERENTIABLE_FIELDS", "string_constants_function", "string_constants_type",
           "string_model_arrays", "string_model_arrays_type"]

# The struct's fields that are arrays of the model (in the kernels' old argument order).
ARRAY_FIELDS = (
    "string_start", "particle_string", "particle_mass", "string_stiffness", "string_rest_length",
    "string_internal_friction", "string_air_drag", "string_ground_stiffness", "string_ground_absorption",
    "string_ground_friction", "string_tie_stiffness", "string_tie_damping", "string_tied", "string_taut_distance",
)

# The fields a step differentiates (a taped step's constants, in the step adjoints' order).
DIFFERENTIABLE_FIELDS = (
    "particle_mass", "string_stiffness", "string_rest_length", "string_internal_friction", "string_air_drag",
    "string_ground_stiffness", "string_ground_absorption", "string_ground_friction", "string_tie_stiffness",
    "string_tie_damping", "string_tied",
)


@functools.cache
def string_model_arrays_type(scalar):
    """The ``StringModelArrays`` struct for the float type ``scalar`` (``wp.float64`` or ``wp.float32``)."""
    vec3 = wp.types.vector(3, scalar)

    @wp.struct
    class StringModelArrays:
        """A string model's constants, one kernel argument: ``StringModel``'s arrays (the same objects)
        and scalars of the same names (units and shapes: ``StringModel``'s attributes)."""

        string_start: wp.array(dtype=wp.int32)
        particle_string: wp.array(dtype=wp.int32)
        particle_mass: wp.array(dtype=scalar)
        string_stiffness: wp.array(dtype=scalar)
        string_rest_length: wp.array(dtype=scalar)
        string_internal_friction: wp.array(dtype=scalar)
        string_air_drag: wp.array(dtype=scalar)
        string_ground_stiffness: wp.array(dtype=scalar)
        string_ground_absorption: wp.array(dtype=scalar)
        string_ground_friction: wp.array(dtype=scalar)
        string_tie_stiffness: wp.array(dtype=scalar)
        string_tie_damping: wp.array(dtype=scalar)
        string_tied: wp.array(dtype=scalar)
        string_taut_distance: wp.array(dtype=scalar)
        gravity: vec3
        ground_height: scalar

    return StringModelArrays


def string_model_arrays(model):
    """A ``StringModelArrays`` of ``model`` (a ``StringModel``): its arrays, gravity and ground height."""
    arrays = string_model_arrays_type(model.scalar)()
    for name in ARRAY_FIELDS:
        setattr(arrays, name, getattr(model, name))
    arrays.gravity = model.gravity
    arrays.ground_height = model.ground_height
    return arrays


@functools.cache
def string_constants_type(scalar):
    """The ``StringConstants`` struct for the float type ``scalar``: one string's constants as a step
    reads them (:func:`string_constants_function`), one value for the functions of a row."""
    vec3 = wp.types.vector(3, scalar)

    @wp.struct
    class StringConstants:
        """One string's constants (``StringModelArrays``' of one string, ``compute_string_constants``).

        Attributes:
            stiffness, rest_length: the segments' ``k_s`` [N/m] and ``d`` [m].
            friction, air_drag: ``k_f`` and ``k_air`` [N s/m].
            ground_stiffness, ground_absorption, ground_friction: the ground's repulsion [N/m],
                absorption and ``k_ground`` [N s/m].
            tied: 1 where the string is tied, else 0.
            tie_stiffness, tie_damping: eq. 2 ``k``, ``k_d`` times ``tied`` (zero for a cut tie).
            gravity: [m/s^2]; ground_height: [m].
        """

        stiffness: scalar
        rest_length: scalar
        friction: scalar
        air_drag: scalar
        ground_stiffness: scalar
        ground_absorption: scalar
        ground_friction: scalar
        tied: scalar
        tie_stiffness: scalar
        tie_damping: scalar
        gravity: vec3
        ground_height: scalar

    return StringConstants


@functools.cache
def string_constants_function(scalar):
    """``compute_string_constants(model, s)`` for the float type ``scalar``: string ``s``'s constants
    from a ``StringModelArrays``, a ``StringConstants`` (:func:`string_constants_type`), each read once."""
    StringModelArrays = string_model_arrays_type(scalar)
    StringConstants = string_constants_type(scalar)

    @wp.func
    def compute_string_constants(model: StringModelArrays, s: int):
        """String ``s``'s constants (:func:`string_constants_function`)."""
        c = StringConstants()
        c.stiffness = model.string_stiffness[s]
        c.rest_length = model.string_rest_length[s]
        c.friction = model.string_internal_friction[s]
        c.air_drag = model.string_air_drag[s]
        c.ground_stiffness = model.string_ground_stiffness[s]
        c.ground_absorption = model.string_ground_absorption[s]
        c.ground_friction = model.string_ground_friction[s]
        c.tied = model.string_tied[s]
        c.tie_stiffness = c.tied * model.string_tie_stiffness[s]
        c.tie_damping = c.tied * model.string_tie_damping[s]
        c.gravity = model.gravity
        c.ground_height = model.ground_height
        return c

    return compute_string_constants
