"""Tangent-linear (forward-mode) kernels of hand-written Warp kernels, by an "interleaved"
source-to-source transformation: each statement's primal, then its tangent.

Warp's tape is reverse mode only. :func:`tangent_kernel` parses a kernel's Python source
with :mod:`ast` and writes a kernel ``<key>_tangent`` that runs one thread per (direction,
original thread): ``wp.tid()`` gains a leading direction index, so the launch is
``dim = (P, *dim)`` and loops need no per-direction storage (or, ``unroll``, a kernel
``<key>_tangent_w<w>`` that runs the primal once for a block of ``w`` directions: "Two layouts"
below). Control flow is kept as it
is (forward mode needs no tape): ``if``/``for`` (static or dynamic bounds), early
``return``, ``+=`` on locals, element writes of local vectors and matrices. Every active
value ``y`` gets its tangent ``tan_y`` right after it. Calls of project ``@wp.func``s
with an active argument are transformed recursively into ``<name>_jvp<n>`` functions
(one per function and pattern of active arguments) that return the primal results and
then the tangents of the active ones; a closure's free names (the hard or smooth normal
force of ``body_contact``, the strings' float type, ``wp.static`` constants) are resolved
to the objects the closure holds. The source written is kept in the cache folder
(``DMARIONETTE_CACHE``; ``articulation_codegen.import_generated``, as the generated articulation
kernels), the closures' objects handed to the module as its globals.

Where it lives: this module, the entry (:func:`tangent_kernel`, :data:`TANGENT_NAMES`) and the
launcher (:class:`TangentKernel`); :mod:`kernel_tangent_transform`, the analysis and the emission
of statements (:class:`~dmarionette.kernels.kernel_tangent_transform.TangentTransform`);
:mod:`kernel_tangent_rules`, the derivative rule of each operator and builtin.

Tangent kernel signature: the primal kernel's parameters in their groups, with a ``Tangent
in`` group after the input groups holding ``tan_<name>`` for every array parameter named in
``tangent_names`` (default :data:`TANGENT_NAMES`), then for every array field of a struct
parameter that the kernel reads (``model.string_stiffness[s]``) and whose field name is in
``tangent_names`` (a struct's tangents are named by their fields, as the arrays' were before
they went into the struct: ``string_stiffness``, ``particle_q``; a field named like another
parameter or field raises, as does a write into a struct's field), and a last group
``Tangent out`` holding ``tan_<name>`` for every array it writes (plain writes and
``wp.atomic_add``); :meth:`TangentKernel.launch` takes the tangent arrays by name (the primal's
arguments in signature order or by name) and checks the names it is given. Each tangent
array has a leading direction axis (``wp.array2d`` -> ``wp.array3d``, same
dtype). The tangent kernel also writes the primal outputs (the direction-0 threads
only), so one launch gives the pass and its P directional derivatives; an output that the
primal accumulates (``wp.atomic_add``) is accumulated in its tangent too, so the caller
initialises it as it initialises the primal. Everything else is constant (tangent 0):
scalar parameters, structs' scalar fields and unnamed array fields (contact constants, surfaces),
integer arrays, and arrays not named.

Rules (:mod:`kernel_tangent_rules`): each the derivative of the formula the primal evaluates,
ties broken as Warp 1.19's adjoints break them, so that the tangent agrees with the tape's
reverse mode of the same kernel to rounding, also at a switch (``wp.max``, ``wp.min``,
``wp.clamp``, ``wp.abs``, ``wp.where``, ``wp.length`` at 0: the branch taken).

Covered (each checked against the tape by the dot-product identity, at and away from its
switches, and against central differences): ``articulation_forces`` (``eval_body_external_forces``,
``eval_body_point_springs``, ``eval_body_points``, ``compute_point_state``), ``body_contact``
(ground, chair box and ball, hard and smooth), ``string_body_coupling``
(``eval_string_response``, ``eval_tie_path``, ``apply_string_forces_to_anchors``) and
``bar_feedback`` (eq. 4 and the exact reaction, printed and tension-only springs); their
users are :class:`~dmarionette.articulation.step_tangent.PuppetStepTangent` and
:class:`~dmarionette.grad.marionette_tangent.MarionetteTangent`.

Why interleaved and not hand-written tangents: no derivative to keep in sync by hand (a
change of a kernel changes its tangent), and the transformer is the one place where a rule
lives.

Two layouts (``unroll``). ``unroll = 0``: one thread per (direction, original thread), as above;
loops and branches stay as they are with no per-direction storage, but every direction's thread
evaluates the whole primal again. ``unroll = n > 0`` (what the callers use, :data:`UNROLL`): one
thread per (block of ``w`` directions, original thread), ``w`` the largest divisor of P up to n
(:meth:`TangentKernel.width`; one kernel per ``w``, built on first use; ``w = 1`` runs the
one-direction layout's kernel, the same launch): ``wp.tid()`` gains the
block index ``_blk``, each primal statement is written once and each tangent statement ``w``
times, once per direction, on locals of their own (``tan_y_d0`` ... ``tan_y_d<w-1>``; a jvp
function takes and returns the ``w`` tangents of each active value). Control flow needs nothing
more: the tangents of every direction live in the one thread that runs the primal's loops and
branches, so every construct the one-direction layout handles (loops of data-dependent trip
count carrying active values, early returns, atomics, element writes) is handled, and no kernel
falls back. The primal is evaluated P / w times instead of P times; each direction's tangent
statements are the same expressions on the same primal values as in the one-direction layout,
and the generated kernels give the same primal and tangents bit for bit (tested). The price is
code size (the tangent part ``w`` times) and a prime P above n runs ``w = 1``. The one-direction
layout's source is unchanged by the option.

Anything else (another builtin, ``**``, keyword arguments on an active call, an active
``if`` condition or index, a tuple returned into an expression) raises
:class:`~dmarionette.kernels.articulation_tangent.TangentError` naming the construct: no
term is ever dropped silently.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping

import warp as wp

from dmarionette.kernels.articulation_codegen import import_generated
from dmarionette.kernels.kernel_tangent_transform import (TANGENT_PREFIX, TangentBuilder, TangentTransform,
                                                          parameter_groups)

__all__ = ["TANGENT_NAMES", "TangentKernel", "UNROLL", "tangent_kernel"]

# The callers' layout: up to this many directions per thread, the primal once per block
# (:func:`tangent_kernel`'s ``unroll``; docs/gradients.md "Forward mode").
UNROLL = 8

# Array parameters whose tangents the kernels take (by name; every other input is a constant).
TANGENT_NAMES = frozenset({
    # the body and joint state
    "body_pos", "body_rot", "body_w", "body_v", "joint_q", "joint_qd",
    # the puppet's applied loads and spring anchors (Control), its tie constants
    "body_force", "body_torque", "spring_anchor_pos", "spring_anchor_vel", "spring_stiffness", "spring_damping",
    # the strings: particle state, tie forces and path, their constants
    "particle_q", "particle_qd", "tie_force", "tie_q", "tie_qd", "tie_target", "point_end",
    "string_stiffness", "string_rest_length", "string_internal_friction", "string_tie_stiffness",
    "string_tie_damping",
    # the bars
    "bar_q", "bar_qd",
})


class TangentKernel:
    """A generated tangent kernel and how to launch it.

    Attributes:
        kernel: the Warp kernel ``<key>_tangent``.
        params: the primal kernel's parameter names, in order.
        arrays: the primal kernel's array parameters, in order (the names a tangent may have).
        tangent_inputs: the inputs whose tangent arrays it takes, in order.
        tangent_outputs: the arrays it writes, whose tangent arrays follow, in order.
        source: the generated source.
    """

    def __init__(self, kernel, params, arrays, arguments, tangent_inputs, tangent_outputs, source, unroll=0,
                 variant=None):
        self.kernel = kernel
        self.params = params
        self.arrays = arrays
        self.arguments = arguments
        self.tangent_inputs = tangent_inputs
        self.tangent_outputs = tangent_outputs
        self.source = source
        self.unroll = unroll
        self._variant = variant  # width -> the kernel unrolled over that many directions (unroll > 0)

    def width(self, directions: int) -> int | None:
        """The directions one thread runs for ``directions`` directions: None in the one-direction
        layout (``unroll`` 0); else the largest divisor of ``directions`` up to ``unroll``."""
        if not self.unroll:
            return None
        return max(w for w in range(1, min(self.unroll, int(directions)) + 1) if directions % w == 0)

    def launch(self, dim, directions: int, args: list | Mapping, tangents: Mapping, device=None) -> None:
        """Launches the primal pass and its tangents along ``directions`` directions.

        Args:
            dim: the primal kernel's launch dimensions.
            directions: the number of directions P.
            args: the primal kernel's arguments (inputs then outputs): a list in signature order, or
                a mapping with every parameter's name.
            tangents: name -> array with the leading direction axis, for every name in
                ``tangent_inputs`` and ``tangent_outputs``; a tangent of another array parameter of
                the primal is accepted and unused (one mapping may serve kernels that read or write
                different parts of the same state).
            device: the device of the launch.

        Raises:
            ValueError: ``args`` of the wrong length or names, or ``tangents`` missing a name or
                holding one that is no array parameter of the primal kernel (naming the kernel, the
                name received and the names expected).
        """
        key = self.kernel.key
        dim = (dim,) if isinstance(dim, int) else tuple(dim)
        if isinstance(args, Mapping):
            _check_names(key, "argument", args, self.params, self.params)
            args = [args[n] for n in self.params]
        elif len(args) != len(self.params):
            raise ValueError(f"{key}: {len(args)} arguments for {len(self.params)} parameters {self.params}")
        _check_names(key, "tangent", tangents, self.tangent_inputs + self.tangent_outputs, self.arrays)
        values = dict(zip(self.params, args))
        values.update({f"{TANGENT_PREFIX}{n}": a for n, a in tangents.items()})
        width = self.width(directions)
        if width is None:
            kernel, lead = self.kernel, int(directions)
        else:
            kernel, lead = self._variant(width), int(directions) // width
        wp.launch(kernel, dim=(lead, *dim), inputs=[values[n] for n in self.arguments], device=device)


def _check_names(key: str, what: str, given: Mapping, expected: list, allowed: list) -> None:
    """Raises ValueError where a name of ``expected`` is not in ``given`` or one of ``given`` is not in
    ``allowed``."""
    for name in given:
        if name not in allowed:
            others = [n for n in allowed if n not in expected]
            raise ValueError(f"{key}: unknown {what} name {name!r}; expected the names {expected}"
                             + (f" (those of its other array parameters, {others}, are accepted)" if others else ""))
    missing = [n for n in expected if n not in given]
    if missing:
        raise ValueError(f"{key}: no {what} {missing[0]!r} among {list(given)}; expected the names {expected}")


_CACHE: dict = {}


def tangent_kernel(kernel, tangent_names=TANGENT_NAMES, unroll: int = 0) -> TangentKernel:
    """The tangent kernel of a Warp kernel (cached per kernel, set of tangent names and ``unroll``).

    Args:
        kernel: a ``@wp.kernel`` (hand-written; closures are resolved).
        tangent_names: names of the array parameters whose tangents the kernel takes.
        unroll: 0, one thread per (direction, thread), the primal recomputed per direction; n > 0, one
            thread per (block of directions, thread), the primal evaluated once per block and each
            tangent statement written once per direction of the block, blocks of up to n directions
            (:meth:`TangentKernel.width`; one kernel per width, built on first use).
    """
    key = (id(kernel), frozenset(tangent_names), int(unroll))
    if key in _CACHE:
        return _CACHE[key]
    names = frozenset(tangent_names)
    variants: dict = {}

    def variant(width):  # width 1: the one-direction layout's kernel (the same launch, (P, *dim))
        if width not in variants:
            variants[width] = _build(kernel, names, width if width > 1 else None)
        return variants[width][0]

    k, t, source = _build(kernel, names, int(unroll) if unroll > 1 else None)
    if unroll:
        variants[int(unroll)] = (k, t, source)
    ins = [a for a in t.params if a in t.active_arrays and a not in t.outputs]
    ins += [f for f in t.fields if f in t.active_fields]
    arrays = [a for a in t.params if a in t.arrays] + list(t.fields)
    result = TangentKernel(k, t.params, arrays, t.arguments, ins, list(t.outputs), source, int(unroll), variant)
    _CACHE[key] = result
    return result


def _build(kernel, tangent_names: frozenset, width: int | None):
    """(generated kernel, its transform, its source) of the one-direction layout (``width`` None) or
    the layout unrolled over ``width`` directions."""
    b = TangentBuilder(width)
    t = TangentTransform(b, kernel.func, set(), kernel=True, tangent_names=tangent_names)
    name = f"{kernel.key}_tangent" if width is None else f"{kernel.key}_tangent_w{width}"
    body = t.emit_kernel(name, parameter_groups(kernel.func))
    source = ("# Generated by dmarionette.kernels.kernel_tangent; do not edit.\n" + b.described_globals()
              + "import warp as wp\n\nwp.set_module_options({'enable_backward': False})\n\n\n"
              + "\n\n".join(b.funcs + [body]))
    digest = hashlib.sha256(source.encode()).hexdigest()[:16]
    module = import_generated(f"dmarionette_tangent_{kernel.key}_{digest}", source, b.env)
    return getattr(module, name), t, source
