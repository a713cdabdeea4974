"""Forward-mode sensitivities (JVPs) of string steps and string rollouts, P directions at once.

Issue 13, item 4 (the strings; the puppet, the coupling and the bar feedback have no tangent yet).
:class:`StringStepTangent` runs one step of a :class:`SolverStringImplicit` forward keeping its
factorisation (the laned step with ``keep``, its pivot inverses and ``C'`` read by the tangent in
the laned layout, where the solver's lanes are on; else the one-launch scalar step with ``keep``)
and then the step's tangent-linear model for P directions (``kernels/string_step_tangent``: a
substitution with the stored factorisation; on the CPU in float64, 4 or 8 directions per SIMD lane
vector, ``kernels/tangent_directions``, one launch per chunk of 8, 4 or 1 directions,
``direction_chunks``; one direction alone with the laned forward: its 4 strings per SIMD lane
vector instead, ``kernels/string_step_tangent_lanes``). :class:`StringRolloutTangent` carries P
tangents through ``T`` steps with prescribed motion (tops and tie targets given per step), as
``StringRollout`` runs the plain steps: chunks of steps captured once as a Warp graph and replayed.

What is differentiated, per direction (:class:`StringTangentInputs`): the initial positions and
velocities, the particle masses, each string's constants (``kernels.string_step_tangent.CONSTANTS``
order) and, per step, the tops, the tie targets and their velocities. The outputs' tangents
(:class:`StringTangentResult`): the tie forces after every step and the final state. Printed
springs only (a tension-only model is refused: the active-set step has no tangent here).

Checked against reverse mode (the taped steps) by the dot-product identity and against central
differences of whole rollouts (``tests/grad/test_string_rollout_tangent.py``). The rollout
carries the particles' tangents direction-minor (``tangent_directions.direction_minor``; the
masses' too), where the tangent kernel loads a lane group's directions contiguously. Cost:
``benchmarks/bench_string_tangent.py --repeats 5 --layout both`` (wall time under load 1.6: P = 1,
4, 12, 16 tangents cost 2.48, 3.07, 5.84, 7.10 laned forward rollouts with the directions in SIMD
lanes for P >= 2 and direction-minor, 2.48, 3.38, 6.97, 8.28 with a leading direction axis; earlier,
thread CPU time, one direction at a time: 2.39, 5.75, 13.00, 16.78); the issue's 1 + 0.5 P = 1.5,
3, 7, 9 met at P = 12 and 16, not at 1 and (just) 4: ``kernels/string_step_tangent``'s doc says
where it goes). P = 1 with the strings in lanes (``kernels/string_step_tangent_lanes``): 1.90-1.92
laned forward rollouts against 2.49 with the scalar kernel (the same session, load 1.1-1.3).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from dmarionette.capture import CapturedChunk
from dmarionette.kernels.string_step_lanes import LANES, lane_groups
from dmarionette.kernels.string_step_tangent import (CONSTANTS, DIRECTION_LANES, direction_chunks, lane_factor_rows,
                                                     string_step_tangent_kernel)
from dmarionette.kernels.string_step_tangent_lanes import string_step_tangent_lanes_kernel
from dmarionette.kernels.tangent_directions import direction_minor, is_direction_minor
from dmarionette.strings.model import StringControl, StringModel, StringState
from dmarionette.strings.rollout import upload_values
from dmarionette.strings.solver import SolverStringImplicit, StringWorkspace

__all__ = ["CONSTANTS", "DIRECTION_LANES", "StringRolloutTangent", "StringStepTangent", "StringTangentInputs",
           "StringTangentResult"]


class StringStepTangent:
    """One string step and its tangent-linear model for ``directions`` tangents.

    Args:
        solver: the stepper (printed springs; its effects choose the kernels).
        directions: the number of tangent directions ``P``.
        lanes: the tangent kernel with 4 or 8 directions in SIMD lanes
            (``kernels.string_step_tangent.direction_chunks``; ``kernels/tangent_directions``: float64
            on the CPU; the same tangents to rounding), else one direction at a time. Default: in
            lanes where supported and ``P >= 2`` (one direction alone fills one lane of four: its
            tangent kernel measured ~1.6x the scalar one's); for ``P = 1`` with the solver's lanes
            on, the strings in SIMD lanes instead (``kernels/string_step_tangent_lanes``: the laned
            forward's groups, ``string_lanes``), unless ``lanes=False`` (the scalar kernel).
    """

    def __init__(self, solver: SolverStringImplicit, directions: int, lanes: bool | None = None):
        model = solver.model
        if model.effects.tension_only:
            raise NotImplementedError("string tangents: tension-only springs (StringEffects.tension_only) have no "
                                      "tangent-linear step; use the printed spring, or reverse mode (a tape)")
        if directions < 1:
            raise ValueError(f"directions: got {directions}; expected an integer >= 1")
        self.solver = solver
        self.model: StringModel = model
        self.directions = int(directions)
        supported = model.scalar is wp.float64 and model.device.is_cpu
        if lanes and not supported:
            raise ValueError("string tangents in lanes: float64 on the CPU only (the lane snippets are Clang C++)")
        self.lanes = (supported and self.directions >= 2) if lanes is None else bool(lanes)
        # One direction with the laned forward: the strings in SIMD lanes instead (one thread per group
        # of the forward's, its factorisation read in place; ``kernels/string_step_tangent_lanes``),
        # unless lanes are switched off (``lanes=False``: the scalar kernel, one thread per string).
        self.string_lanes = supported and solver.lanes and self.directions == 1 and lanes is not False
        self._string_lanes_kernel = (string_step_tangent_lanes_kernel(model.effects.as_tuple(), LANES)
                                     if self.string_lanes else None)
        # Its scratch: the forward substitution's y, one 3 x K lane matrix per laned row (as ``lane_c``).
        self._lane_y = (wp.zeros(lane_groups(model.string_start.numpy(), LANES)[3],
                                 dtype=wp.types.matrix((3, LANES), wp.float64), device=model.device)
                        if self.string_lanes else None)
        # One launch per chunk of directions (in lanes: 8, then 4, then one alone, ``direction_chunks``),
        # the first computing the segments' parts for the others; the segments' linear maps where
        # there is more than one group of directions per string in all (built once per step, they
        # cost more than one group saves; ``kernels/string_step_tangent``).
        chunks = direction_chunks(self.directions) if self.lanes else [(1, self.directions)]
        self.maps = sum(-(-count // lanes) for lanes, count in chunks) > 1
        self._launches = []
        first = 0
        # The segment pass on lanes of 4 segments where the directions are in lanes (float64 CPU),
        # its results in that laned layout for every launch of the step.
        segment_lanes = DIRECTION_LANES if self.lanes else 1
        # Each chunk's kernel for tangent arrays with a leading direction axis, and in lanes one for
        # direction-minor arrays (``tangent_directions.direction_minor``: contiguous transfers instead
        # of gathers; :meth:`step` picks by the arrays it is given).
        for lanes, count in chunks:
            kernels = [string_step_tangent_kernel(model.scalar, model.effects.as_tuple(), lanes,
                                                  LANES if solver.lanes else 0, self.maps, first == 0, segment_lanes,
                                                  minor)
                       for minor in ((False, True) if lanes > 1 else (False,))]
            self._launches.append((kernels, first, lanes, count))
            first += count
        self.workspace = StringWorkspace.allocate(model, requires_grad=False)  # the forward's kept factorisation
        # Where the tangent finds each string's rows of the kept factorisation (laned: its group's rows, its lane).
        rows = np.zeros((2, model.string_count), dtype=np.int32)
        if solver.lanes:
            rows[:] = lane_factor_rows(model.string_start.numpy(), *(a.numpy() for a in solver.lane_group_arrays),
                                       model.string_count)
        self._factor_row, self._factor_lane = (wp.array(r, dtype=wp.int32, device=model.device) for r in rows)
        # Each segment's spring parts and linear maps (E, C), computed once per step by the tangent kernel.
        segment_type = model.mat33 if segment_lanes == 1 else wp.types.matrix((9, segment_lanes), wp.float64)
        self._segments = [wp.zeros(model.particle_count, dtype=segment_type, device=model.device) for _ in range(3)]

    def zeros(self, count: int, dtype=None, minor: bool = False) -> wp.array:
        """A ``(P, count)`` tangent array (vec3 by default); ``minor``: stored direction-minor
        (``tangent_directions.direction_minor``, the layout the laned tangent loads fastest)."""
        m = self.model
        if minor:
            return direction_minor(self.directions, count, dtype or m.vec3, m.device)
        return wp.zeros((self.directions, count), dtype=dtype or m.vec3, device=m.device)

    def step(self, state_in: StringState, state_out: StringState, control: StringControl, dt: float,
             q_dot: wp.array, qd_dot: wp.array, q_out_dot: wp.array, qd_out_dot: wp.array, tie_force_dot: wp.array,
             top_q_dot: wp.array, tie_q_dot: wp.array, tie_qd_dot: wp.array, mass_dot: wp.array,
             constants_dot: wp.array) -> None:
        """Advances ``state_in`` into ``state_out`` (the plain step's numbers: the laned step where the
        solver's :attr:`~SolverStringImplicit.lanes` are on, else the scalar one-launch step) and the
        tangents ``(q_dot, qd_dot)`` (``(P, N)`` vec3) into ``(q_out_dot, qd_out_dot)``, the tie forces'
        into ``tie_force_dot`` (``(P, S)``), given the control's tangents (``(P, S)`` each), the
        masses' (``(P, N)``) and the constants' (``(P, S, 10)``). The tangents out must be other
        arrays than those in."""
        m = self.model
        h = m.scalar(dt)
        ws = self.workspace
        if self.solver.lanes:
            # The laned step keeping its factorisation (the scalar step's numbers bit for bit, about 2x
            # faster); the tangent reads it in the laned layout.
            self.solver.integrate_string_lanes(state_in, state_out, control, h, ws, keep=True)
            inverse, c = ws.lane_inverse, ws.lane_c
        else:
            self.solver.integrate_string_implicit(state_in, state_out, control, h, ws, keep=True)
            inverse, c = ws.scratch_inverse, ws.scratch_c
        tangents_in = (q_dot, qd_dot, top_q_dot, tie_q_dot, tie_qd_dot, mass_dot, constants_dot)
        tangents_out = (q_out_dot, qd_out_dot, tie_force_dot)
        particles = (q_dot, qd_dot, q_out_dot, qd_out_dot, mass_dot)
        if self.string_lanes:
            group_string, group_real, group_base = self.solver.lane_group_arrays
            wp.launch(
                self._string_lanes_kernel,
                dim=group_real.shape[0],
                inputs=[m.arrays, state_in.arrays, inverse, c, group_string, group_real, group_base,
                        ws.particle_dv, state_out.arrays, control.arrays, h, *(a[0] for a in tangents_in)],
                outputs=[self._lane_y, *(a[0] for a in tangents_out)],
                device=m.device,
                record_tape=False,
            )
            return
        for kernels, first, lanes, count in self._launches:
            chunk = slice(first, first + count)
            whole = count == self.directions
            minor = all(is_direction_minor(a, first, lanes) for a in particles)
            wp.launch(
                kernels[-1] if minor else kernels[0],
                dim=m.string_count,
                inputs=[m.arrays, state_in.arrays, inverse, c, self._factor_row, self._factor_lane, ws.particle_dv,
                        state_out.arrays, control.arrays, h, *(a if whole else a[chunk] for a in tangents_in)],
                outputs=[*self._segments, *(a if whole else a[chunk] for a in tangents_out)],
                device=m.device,
                record_tape=False,
            )


@dataclasses.dataclass
class StringTangentInputs:
    """P directions in a string rollout's inputs (NumPy; None: zero). ``P`` directions, ``N``
    particles, ``S`` strings, ``T`` steps.

    Attributes:
        particle_q, particle_qd: the initial state's [m], [m/s], ``(P, N, 3)``.
        particle_mass: [kg], ``(P, N)``.
        constants: each string's constants, ``(P, S, 10)`` in ``CONSTANTS`` order.
        top_q, tie_q, tie_qd: the tops, tie targets and their velocities per step, ``(P, T, S, 3)``.
    """

    particle_q: np.ndarray | None = None
    particle_qd: np.ndarray | None = None
    particle_mass: np.ndarray | None = None
    constants: np.ndarray | None = None
    top_q: np.ndarray | None = None
    tie_q: np.ndarray | None = None
    tie_qd: np.ndarray | None = None


@dataclasses.dataclass
class StringTangentResult:
    """A rollout's outputs and their tangents.

    Attributes:
        tie_force: the ties' forces on their bodies after every step [N], ``(T, S, 3)``.
        particle_q, particle_qd: the final state, ``(N, 3)``.
        tie_force_dot: ``(P, T, S, 3)``; particle_q_dot, particle_qd_dot: ``(P, N, 3)``.
    """

    tie_force: np.ndarray
    particle_q: np.ndarray
    particle_qd: np.ndarray
    tie_force_dot: np.ndarray
    particle_q_dot: np.ndarray
    particle_qd_dot: np.ndarray


class _Carry:
    """A rollout's carried state and its tangents (``ping_pong``'s state)."""

    def __init__(self, stepper: StringStepTangent, minor: bool):
        self.state = stepper.model.state()
        self.q_dot = stepper.zeros(stepper.model.particle_count, minor=minor)
        self.qd_dot = stepper.zeros(stepper.model.particle_count, minor=minor)

    def assign(self, other: _Carry) -> None:
        self.state.assign(other.state)
        wp.copy(self.q_dot, other.q_dot)
        wp.copy(self.qd_dot, other.qd_dot)


class StringRolloutTangent:
    """``T`` steps of prescribed motion with ``P`` tangents carried alongside, in captured chunks.

    Args:
        solver: the stepper (printed springs).
        dt: string step [s].
        directions: the number of tangent directions ``P``.
        chunk_steps: steps per captured graph (``T`` must be a multiple).
        lanes: the tangent directions in SIMD lanes (:class:`StringStepTangent`; default: where supported).
        minor: the carried particle tangents and the masses' stored direction-minor
            (``tangent_directions.direction_minor``: a lane group's directions of one particle
            contiguous, loaded without gathers; the same numbers), else with a leading direction axis.
    """

    def __init__(self, solver: SolverStringImplicit, dt: float, directions: int, chunk_steps: int = 50,
                 lanes: bool | None = None, minor: bool = True):
        self.stepper = StringStepTangent(solver, directions, lanes)
        m = self.model = solver.model
        self.dt = float(dt)
        self.directions = int(directions)
        self.chunk_steps = int(chunk_steps)
        self.minor = bool(minor)
        c, p, s, n = self.chunk_steps, self.directions, m.string_count, m.particle_count
        with wp.ScopedDevice(m.device):
            self._top_q, self._tie_q, self._tie_qd, self._tie_force = (wp.zeros((c, s), dtype=m.vec3) for _ in range(4))
            self._top_q_dot, self._tie_q_dot, self._tie_qd_dot, self._tie_force_dot = (
                wp.zeros((c, p, s), dtype=m.vec3) for _ in range(4))
            self._mass_dot = self.stepper.zeros(n, m.scalar, self.minor)
            self._constants_dot = wp.zeros((p, s, len(CONSTANTS)), dtype=m.scalar)
        self._controls = [StringControl(self._top_q[k], self._tie_q[k], self._tie_qd[k]) for k in range(c)]
        self._carry = _Carry(self.stepper, self.minor)
        self._spare = _Carry(self.stepper, self.minor)
        self._chunk = CapturedChunk(self._launch, m.device, warm_up=self._warm_up)

    def _step(self, k: int, a: _Carry, b: _Carry) -> None:
        self.stepper.step(a.state, b.state, self._controls[k], self.dt, a.q_dot, a.qd_dot, b.q_dot, b.qd_dot,
                          self._tie_force_dot[k], self._top_q_dot[k], self._tie_q_dot[k], self._tie_qd_dot[k],
                          self._mass_dot, self._constants_dot)
        wp.copy(self._tie_force[k], b.state.tie_force)

    def _launch(self) -> None:
        pair = (self._carry, self._spare)
        for k in range(self.chunk_steps):
            self._step(k, pair[k % 2], pair[(k + 1) % 2])
        if self.chunk_steps % 2 == 1:
            self._carry.assign(self._spare)

    def _warm_up(self) -> None:
        # One eager step on scratch arrays loads every module before capture begins.
        self._step(0, self._spare, _Carry(self.stepper, self.minor))

    def run(self, state: StringState, top_q: np.ndarray, tie_q: np.ndarray | None = None,
            tie_qd: np.ndarray | None = None, tangents: StringTangentInputs | None = None) -> StringTangentResult:
        """Runs ``T`` steps from ``state`` (left unchanged) with the tops ``top_q`` (``(T, S, 3)``), the
        tie targets ``tie_q`` (default: the model's tie points) and velocities ``tie_qd`` (default:
        zero), carrying the directions ``tangents``; returns the outputs and their tangents."""
        m = self.model
        tangents = tangents or StringTangentInputs()
        top_q = np.asarray(top_q, dtype=np.float64)
        steps = top_q.shape[0]
        p, s, n, c = self.directions, m.string_count, m.particle_count, self.chunk_steps
        expected = (steps, s, 3)
        if top_q.shape != expected or steps % c != 0:
            raise ValueError(f"top_q: got shape {top_q.shape}; expected {expected} with T a multiple of "
                             f"chunk_steps={c}")
        tie_q = np.broadcast_to(m.tie_points(), expected) if tie_q is None else np.asarray(tie_q, dtype=np.float64)
        tie_qd = np.zeros(expected) if tie_qd is None else np.asarray(tie_qd, dtype=np.float64)

        def given(value, shape):
            if value is None:
                return np.zeros(shape)
            value = np.asarray(value, dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"tangent: got shape {value.shape}; expected {shape}")
            return value

        q_dot = given(tangents.particle_q, (p, n, 3))
        qd_dot = given(tangents.particle_qd, (p, n, 3))
        upload_values(self._mass_dot, given(tangents.particle_mass, (p, n)))
        upload_values(self._constants_dot, given(tangents.constants, (p, s, len(CONSTANTS))))
        # Per step, direction-major in the chunk buffers: (P, T, S, 3) -> (T, P, S, 3).
        top_dot, tie_dot, tie_v_dot = (np.moveaxis(given(v, (p, steps, s, 3)), 0, 1)
                                       for v in (tangents.top_q, tangents.tie_q, tangents.tie_qd))
        self._carry.state.assign(state)
        upload_values(self._carry.q_dot, q_dot)
        upload_values(self._carry.qd_dot, qd_dot)
        tie_force = np.zeros(expected)
        tie_force_dot = np.zeros((steps, p, s, 3))
        for k in range(steps // c):
            rows = slice(k * c, (k + 1) * c)
            for dst, values in ((self._top_q, top_q), (self._tie_q, tie_q), (self._tie_qd, tie_qd),
                                (self._top_q_dot, top_dot), (self._tie_q_dot, tie_dot),
                                (self._tie_qd_dot, tie_v_dot)):
                upload_values(dst, values[rows])
            self._chunk.run()
            tie_force[rows] = self._tie_force.numpy()
            tie_force_dot[rows] = self._tie_force_dot.numpy()
        final = self._carry
        return StringTangentResult(
            tie_force=tie_force, particle_q=final.state.particle_q.numpy().copy(),
            particle_qd=final.state.particle_qd.numpy().copy(), tie_force_dot=np.moveaxis(tie_force_dot, 1, 0),
            particle_q_dot=final.q_dot.numpy().copy(), particle_qd_dot=final.qd_dot.numpy().copy())
