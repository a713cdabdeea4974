"""Segments of a marionette rollout on a ``wp.Tape``, and their reverse pass.

:class:`TapedSegment` records ``K`` puppet steps of ``SolverMarionette.step`` itself
(``step(..., tape=tape, workspace=...)``), each with a :class:`MarionetteWorkspace` of its
own and its own output state, so that no array is written after it was read (on a tape that
gives silently wrong gradients). The plain and the taped run are the same methods: the
string solver records its solve's hand-written adjoint on the tape it is given and, for
tension-only strings, finds the active set by an unrecorded pass (``SolverStringImplicit``);
the taped re-run of a segment therefore ends exactly where the plain forward did
(``tests/grad/test_taped_step.py``).

The arrays of a ``C``-step segment are allocated once (a :class:`_Plan`) and reused by
every segment (a shorter last one uses its first steps): for each segment length the
forward launches on the tape and the reverse pass are captured as two Warp graphs (CPU
or CUDA, :class:`dmarionette.capture.CapturedChunk`) and replayed per segment, with the
checkpoint, the inputs and the cotangent seeds written into the planned arrays in place
between the replays (one copy per field and segment: the per-step arrays are rows of
segment-wide blocks, :class:`_Blocks`). Without capture the same launches run one by one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from dmarionette.capture import CapturedChunk
from dmarionette.grad.carried import carried_arrays
from dmarionette.marionette.solver import MarionetteControl
from dmarionette.marionette.workspace import PuppetPoints
from dmarionette.strings.rollout import upload_values

__all__ = ["StateAdjoint", "TapedSegment"]


def _arrays_in(obj, seen: set[int]) -> list[wp.array]:
    """Every ``wp.array`` held by ``obj`` (an array, a list of them, or an object or dataclass
    holding any of these), once each."""
    if isinstance(obj, wp.array):
        if id(obj) in seen:
            return []
        seen.add(id(obj))
        return [obj]
    if isinstance(obj, (list, tuple)):
        return [a for item in obj for a in _arrays_in(item, seen)]
    if dataclasses.is_dataclass(obj) or hasattr(obj, "__dict__"):
        return [a for value in vars(obj).values() for a in _arrays_in(value, seen)]
    return []


class _Plan:
    """Every array of a ``steps``-long taped segment (allocated once): its states, controls and
    per-step workspaces, and the final state's body poses and points.

    What the host writes or reads per segment is laid out as one array per field over the
    segment (:class:`_Blocks`): the steps' controls, the seeded outputs (``joint_q``, the
    points, body poses, tie forces and bar forces of every state) are views of them, so that a
    segment's inputs, seeds and input gradients move in one copy per field, not one per step.
    """

    def __init__(self, model, solver, steps: int):
        self.steps = steps
        self.states = [model.state(requires_grad=True) for _ in range(steps + 1)]
        self.controls = [MarionetteControl(model, requires_grad=True) for _ in range(steps)]
        self.workspaces = [solver.new_workspace(taped=True) for _ in range(steps)]
        self.final_points = PuppetPoints.allocate(model.puppet, requires_grad=True, world_count=model.world_count)
        self.blocks = _Blocks(self)
        self.arrays = _arrays_in([self.states, self.controls, self.workspaces, self.final_points], set())
        self.grads = [a.grad for a in self.arrays if a.requires_grad]  # cleared before a reverse pass

    @property
    def nbytes(self) -> int:
        """Bytes of the plan's arrays and their gradients."""
        return sum(a.capacity for a in self.arrays) + sum(g.capacity for g in self.grads)


def _stacked(owners: list, name: str) -> wp.array:
    """One array ``(len(owners), *shape)`` holding ``owner.<name>`` of every owner (their values
    copied in); each owner's attribute becomes a view of its row (with its gradient's row)."""
    first = getattr(owners[0], name)
    block = wp.array(np.stack([getattr(o, name).numpy() for o in owners]), dtype=first.dtype, device=first.device,
                     requires_grad=first.requires_grad)
    for k, owner in enumerate(owners):
        setattr(owner, name, block[k])
    return block


class _Blocks:
    """The segment-wide arrays of a :class:`_Plan` (``C`` = its steps), whose rows the plan's
    per-step arrays are:

    - ``top_q``, ``bar_q``, ``bar_qd``: the controls, ``(C, n, ...)``;
    - ``joint_q``, ``tie_force``, ``bar_feedback``, ``bar_reaction``: of states ``0 .. C``, ``(C + 1, ...)``;
    - ``point_pos``, ``body_pos``, ``body_rot``: the body points and poses of the steps' input states
      (rows ``0 .. C - 1``, the workspaces') and of the final state (row ``C``, ``final_points``).
    """

    CONTROLS = ("top_q", "bar_q", "bar_qd")
    STATE_OUTPUTS = ("tie_force", "bar_feedback", "bar_reaction")

    def __init__(self, plan: _Plan):
        for name in self.CONTROLS:
            setattr(self, name, _stacked(plan.controls, name))
        self.joint_q = _stacked([s.puppet for s in plan.states], "joint_q")
        for name in self.STATE_OUTPUTS:
            setattr(self, name, _stacked(plan.states, name))
        # Their gradients from state 1 on (the steps' outputs), made once: a view costs about 9 µs.
        self.output_grads = {name: getattr(self, name).grad[1:] for name in self.STATE_OUTPUTS}
        points = [ws.points for ws in plan.workspaces] + [plan.final_points]
        self.point_pos = _stacked(points, "point_q")
        kinematics = [p.kinematics for p in points]
        self.body_pos = _stacked(kinematics, "body_pos")
        self.body_rot = _stacked(kinematics, "body_rot")


class StateAdjoint:
    """Adjoint of the carried state at the rollout's start (host arrays, ``Checkpoint`` layout)."""

    def __init__(self, state):
        for name, array in carried_arrays(state).items():
            setattr(self, name, array.grad.numpy().copy())


class TapedSegment:
    """Records puppet steps ``a .. b-1`` of a rollout on a tape and runs their reverse pass.

    Args:
        model: the ``MarionetteModel`` (``requires_grad=True``).
        solver: the ``SolverMarionette`` of the untaped forward (the taped steps are its own).
        parameters: the model arrays whose gradients the engine accumulates over segments.
        steps: the longest segment (puppet steps); one set of arrays of that length serves
            every segment (a shorter last one uses its first steps).
        capture: replay each segment length's taped forward and reverse pass as Warp graphs.
    """

    def __init__(self, model, solver, parameters: list[wp.array], steps: int, capture: bool = True):
        self.model = model
        self.solver = solver
        self.parameters = parameters
        self.steps = int(steps)
        self.capture = bool(capture)
        self._plan: _Plan | None = None
        self._graphs: dict[tuple[int, bool], tuple] = {}
        self._clears: dict[tuple[int, bool], list[wp.array]] = {}  # without capture: _residue per segment kind

    @property
    def nbytes(self) -> int:
        """Bytes of the planned segment's arrays and gradients (not the graphs' own records)."""
        return self._plan.nbytes if self._plan is not None else 0

    # ------------------------------------------------------------------ the taped step
    def _forward(self, plan: _Plan, steps: int, last: bool, tape, clear: list[wp.array]) -> None:
        """The launches of a ``steps``-long segment on ``tape``; then, unless ``last``, the adjoint of
        the next segment's start state (left in the plan's start state's gradients by the reverse
        pass that ran before) copied to this segment's end state's; then the gradient buffers
        ``clear`` zeroed (not those just written)."""
        with tape:
            for k in range(steps):
                self.solver.step(plan.states[k], plan.states[k + 1], plan.controls[k], tape=tape,
                                 workspace=plan.workspaces[k])
            if last:
                self.solver.eval_body_points(plan.states[steps], plan.final_points)
        if not last:
            end = carried_arrays(plan.states[steps])
            for name, array in carried_arrays(plan.states[0]).items():
                wp.copy(end[name].grad, array.grad)
            written = {id(a.grad) for a in end.values()}
            clear = [g for g in clear if id(g) not in written]
        for g in clear:
            g.zero_()

    def _residue(self, plan: _Plan, steps: int, last: bool) -> list[wp.array]:
        """The gradient buffers a reverse pass leaves non-zero.

        Warp's adjoint of a plain array store reads the element's gradient and zeroes it, so
        after a reverse pass only the buffers of arrays that are read but never stored to in
        the segment (its start state, its inputs) or only accumulated into (atomic adds: the
        bar feedback) hold anything. Found by a reverse pass with every gradient buffer set
        to ones; only these are cleared before each replay (clearing all of them cost about
        a fifth of the reverse pass). The model parameters' gradients, and the start state's (the
        adjoint a reverse pass that ran before hands to the next segment), are restored after.
        """
        kept = self.parameters + list(carried_arrays(plan.states[0]).values())
        saved = [a.grad.numpy().copy() for a in kept]
        warm = wp.Tape()
        self._forward(plan, steps, last, warm, plan.grads)
        for g in plan.grads:
            upload_values(g, np.ones(g.numpy().shape))
        warm.backward()
        residue = [g for g in plan.grads if np.any(g.numpy() != 0.0)]
        for g in plan.grads:
            g.zero_()
        for a, g in zip(kept, saved):
            upload_values(a.grad, g)
        return residue

    def _prepare(self, steps: int, last: bool):
        """The planned arrays, and the captured graphs of a ``(steps, last)`` segment (None
        without capture)."""
        if self._plan is None:
            self._plan = _Plan(self.model, self.solver, self.steps)
        plan = self._plan
        key = (steps, last)
        if not self.capture:
            if key not in self._clears:  # the eager re-run, too, clears only the residue (one call per buffer)
                self._clears[key] = self._residue(plan, steps, last)
            return plan, None
        if key not in self._graphs:
            # The eager pass of _residue also loads every module before capture begins.
            clear = self._residue(plan, steps, last)
            tape = wp.Tape()
            device = self.model.device
            forward = CapturedChunk(lambda: self._forward(plan, steps, last, tape, clear), device, warm_up=_loaded)
            reverse = CapturedChunk(tape.backward, device, warm_up=_loaded)
            self._graphs[key] = (forward, reverse, tape)
        return plan, self._graphs[key]

    # ------------------------------------------------------------------ reverse pass
    def backward(self, checkpoint, inputs, a: int, b: int, *, last: bool, cotangents: dict,
                 grads: dict) -> StateAdjoint | None:
        """Re-runs puppet steps ``a .. b-1`` from ``checkpoint`` on a tape and pulls back.

        Args:
            checkpoint: the state at step ``a`` (``dmarionette.grad.engine.Checkpoint``).
            inputs: the rollout's ``RolloutInputs`` (the model's constants already set from them).
            a, b: the segment's first and one-past-last puppet step.
            last: ``b`` is the rollout's end (its final row of per-puppet-step outputs is seeded here).
            cotangents: output name -> full-rollout cotangent array (missing: zero).
            grads: input name -> full-rollout gradient arrays; the segment's rows are added.

        Returns:
            For ``a = 0``, the adjoint of the start state; else None. The segments run last to first:
            the adjoint of step ``a``'s state stays in the plan's start state's gradients, and the
            next call (the segment ending at ``a``, not the last) moves it to its end state inside
            its re-run (no host copies between segments).
        """
        m = self.model
        n = m.substeps
        steps = b - a
        if steps > self.steps:
            raise ValueError(f"segment {a}..{b}: {steps} puppet steps; planned for at most {self.steps}")
        plan, graphs = self._prepare(steps, last)
        blocks = plan.blocks
        states = plan.states[:steps + 1]
        checkpoint.load(states[0])
        rows = slice(a * n, b * n)  # the segment's string steps
        for name in blocks.CONTROLS:
            _upload_rows(getattr(blocks, name), steps, getattr(inputs, name)[rows])
        if graphs is not None:
            graphs[0].run()
        else:
            tape = wp.Tape()  # not reset(): that would clear the parameters' accumulated gradients
            self._forward(plan, steps, last, tape, self._clears[(steps, last)])
        # Seed the per-step outputs of this segment (written, not added: nothing else seeds those
        # rows). The final state's points are row C of their blocks whatever the segment's length.
        # The next segment's state adjoint is already in the end state's gradients (the re-run
        # copied it there); the tie force's end row, also a seeded row, gets it added back.
        seeded = steps + 1 if last else steps
        if "joint_q" in cotangents:
            _upload_rows(blocks.joint_q.grad, seeded, cotangents["joint_q"][a:a + seeded])
        for name in ("point_pos", "body_pos", "body_rot"):
            if name in cotangents:
                grad = getattr(blocks, name).grad
                _upload_rows(grad, steps, cotangents[name][a:b])
                if last:
                    upload_values(grad[self.steps], cotangents[name][b])
        handed = None if last else states[steps].tie_force.grad.numpy().copy()  # the next segment's, carried
        for name in blocks.STATE_OUTPUTS:
            if name in cotangents:
                _upload_rows(blocks.output_grads[name], steps, cotangents[name][rows])
        if handed is not None and "tie_force" in cotangents:
            end = states[steps].tie_force.grad
            upload_values(end, end.numpy() + handed)
        if graphs is not None:
            graphs[1].run()
        else:
            tape.backward()
        for name in blocks.CONTROLS:
            grads[name][rows] += getattr(blocks, name).grad.numpy()[:steps].reshape(grads[name][rows].shape)
        return StateAdjoint(states[0]) if a == 0 else None


def _upload_rows(block: wp.array, rows: int, values: np.ndarray) -> None:
    """Writes ``values`` (host, ``rows`` rows' values in any shape) into the first ``rows`` rows of ``block``."""
    if block.device.is_cpu:
        host = block.numpy()  # a view: written in place
        host[:rows] = np.reshape(values, (rows, *host.shape[1:]))
        return
    per_element = np.size(values) // (rows * int(np.prod(block.shape[1:])))  # 3 for a vec3d, 1 for a float
    upload_values(block[:rows], np.reshape(values, (rows, *block.shape[1:], *((per_element,) if per_element > 1 else ()))))


def _loaded() -> None:
    """No warm-up: ``TapedSegment._residue``'s eager pass has loaded every module."""
