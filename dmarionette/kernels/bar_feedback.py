"""Force feedback to the bars (paper §3.2), two modes, evaluated every string step.

``eval_bar_feedback`` accumulates, per bar, over the strings it carries:

- **eq. 4** (the paper's model), for taut strings only:
  ``F_i = -k (x_proxy - x_string) - m g - k_d (v_proxy - v_string)``, with ``x_string`` the
  string's *last* particle (as the paper defines it), ``x_proxy``/``v_proxy`` the bar centre
  (the device tip sits at the bar's centre of mass, §3.1), ``k``/``k_d`` the device's
  stiffness and damping, ``m`` the puppet's total mass. The paper's ``g`` is read as the
  magnitude of gravity along the *up* axis, so ``-m g`` is the puppet's weight pulling the
  hand down: in vectors, ``+m g_vec`` with ``g_vec = (0, -9.81, 0)``.
- **exact reaction**: the force the string exerts on its top particle, i.e. on the bar's
  attach point: the first segment's spring force plus its internal friction.

One thread per string, atomically summed per bar, so the kernel is differentiable. It takes
the strings' constants and state as the string steps do, a ``StringModelArrays`` and a
``StringStateArrays`` (``model``, ``state_in``); its tangent (``kernel_tangent``) takes the
tangents of the fields it reads by their names (``particle_q``, ``string_stiffness``, ...). The
exact reaction is :func:`bar_reaction_function`'s ``compute_bar_reaction``, also the force
of the bar work meter (``marionette/energy.py``).
"""

import functools

import warp as wp

from .string_model_arrays import string_model_arrays_type
from .string_state_arrays import string_state_arrays_type
from .string_terms import string_terms


@functools.cache
def bar_reaction_function(scalar, internal_friction: bool, tension_only: bool = False):
    """Builds ``compute_bar_reaction(x_top, x_next, v_top, v_next, stiffness, rest_length, friction)``
    for the strings' float type ``scalar``: the force a string exerts on its top particle (so on
    the bar), the first segment's spring (``string_spring``, the variant of ``tension_only``)
    plus, if ``internal_friction``, its internal friction (paper terms 1 and 2)."""
    t = string_terms(scalar, tension_only)
    vec3 = t.vec3
    FRICTION = bool(internal_friction)

    @wp.func
    def compute_bar_reaction(x_top: vec3, x_next: vec3, v_top: vec3, v_next: vec3, stiffness: scalar,
                             rest_length: scalar, friction: scalar):
        """The exact reaction [N] of a string on its top particle."""
        reaction, _k, _taut = t.compute_string_spring(x_top, x_next, stiffness, rest_length)
        if wp.static(FRICTION):
            f_f, _d = t.compute_internal_friction(v_top, v_next, friction)
            reaction += f_f
        return reaction

    return compute_bar_reaction


def eval_bar_feedback_kernel(scalar, internal_friction: bool, tension_only: bool = False, bar_scalar=None):
    """Builds ``eval_bar_feedback`` for the strings' float type ``scalar`` (internal friction in
    the reaction or not; the segment spring of ``StringEffects.tension_only``).

    ``bar_scalar`` is the float type of the bar side (the control ``bar_q``/``bar_qd``, the
    eq. 4 constants and the two outputs); ``None`` means ``scalar``. Float32 strings under a
    float64 marionette use ``bar_scalar=wp.float64``: the kernel reads the float32 particles,
    widens them (exactly) and evaluates eq. 4 in float64; the exact reaction is evaluated in
    the strings' type, as the string step evaluates the same spring, and widened before it
    is summed. That is the precision boundary for the feedback, in the kernel that reads
    both sides (``kernels/precision_boundary`` converts the rest).
    """
    return _eval_bar_feedback_kernel(scalar, bool(internal_friction), bool(tension_only),
                                     scalar if bar_scalar is None else bar_scalar)


@functools.cache
def _eval_bar_feedback_kernel(scalar, internal_friction: bool, tension_only: bool, bar_scalar):
    vec3 = wp.types.vector(3, scalar)
    bar_vec3 = vec3 if bar_scalar is scalar else wp.types.vector(3, bar_scalar)
    compute_bar_reaction = bar_reaction_function(scalar, internal_friction, tension_only)
    StringModelArrays = string_model_arrays_type(scalar)
    StringStateArrays = string_state_arrays_type(scalar)
    WIDEN = bar_scalar is not scalar

    @wp.kernel(module="unique")
    def eval_bar_feedback(
        # Model:
        model: StringModelArrays,
        string_bar: wp.array(dtype=wp.int32),
        feedback_stiffness: bar_scalar,
        feedback_damping: bar_scalar,
        puppet_weight: bar_vec3,
        # State in:
        state_in: StringStateArrays,
        # Control:
        bar_q: wp.array(dtype=bar_vec3),
        bar_qd: wp.array(dtype=bar_vec3),
        # State out:
        bar_feedback: wp.array(dtype=bar_vec3),
        bar_reaction: wp.array(dtype=bar_vec3),
    ):
        s = wp.tid()
        bar = string_bar[s]
        if bar < 0:
            return
        first = model.string_start[s]
        last = model.string_start[s + 1] - 1
        if state_in.string_taut[s] == 1:
            if wp.static(WIDEN):
                f = (
                    -feedback_stiffness * (bar_q[bar] - bar_vec3(state_in.particle_q[last]))
                    + puppet_weight
                    - feedback_damping * (bar_qd[bar] - bar_vec3(state_in.particle_qd[last]))
                )
            else:
                f = (
                    -feedback_stiffness * (bar_q[bar] - state_in.particle_q[last])
                    + puppet_weight
                    - feedback_damping * (bar_qd[bar] - state_in.particle_qd[last])
                )
            wp.atomic_add(bar_feedback, bar, f)
        reaction = compute_bar_reaction(state_in.particle_q[first], state_in.particle_q[first + 1],
                                        state_in.particle_qd[first], state_in.particle_qd[first + 1],
                                        model.string_stiffness[s], model.string_rest_length[s],
                                        model.string_internal_friction[s])
        if wp.static(WIDEN):
            wp.atomic_add(bar_reaction, bar, bar_vec3(reaction))
        else:
            wp.atomic_add(bar_reaction, bar, reaction)

    return eval_bar_feedback
