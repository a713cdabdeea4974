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
between the replays. Without capture the same launches run one by one.
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
    per-step workspaces, and the final state's body poses and points."""

    def __init__(self, model, solver, steps: int):
        self.steps = steps
        self.states = [model.state(requires_grad=True) for _ in range(steps + 1)]
        self.controls = [MarionetteControl(model, requires_grad=True) for _ in range(steps)]
        self.workspaces = [solver.new_workspace(taped=True) for _ in range(steps)]
        self.final_points = PuppetPoints.allocate(model.puppet, requires_grad=True, world_count=model.world_count)
        self.arrays = _arrays_in([self.states, self.controls, self.workspaces, self.final_points], set())
        self.grads = [a.grad for a in self.arrays if a.requires_grad]  # cleared before a reverse pass

    @property
    def nbytes(self) -> int:
        """Bytes of the plan's arrays and their gradients."""
        return sum(a.capacity for a in self.arrays) + sum(g.capacity for g in self.grads)

    def points(self, k: int, steps: int) -> PuppetPoints:
        """Body poses and points of state ``k`` of a ``steps``-long segment (the input of step
        ``k``, or for ``k = steps`` the final state)."""
        return self.workspaces[k].points if k < steps else self.final_points


class StateAdjoint:
    """Adjoint of the carried state at a segment boundary (host arrays, ``Checkpoint`` layout)."""

    def __init__(self, state):
        for name, array in carried_arrays(state).items():
            setattr(self, name, array.grad.numpy().copy())

    def seed(self, state) -> None:
        for name, array in carried_arrays(state).items():
            _add_grad(array, getattr(self, name))


def _add_grad(array: wp.array, values) -> None:
    current = array.grad.numpy()
    upload_values(array.grad, current + np.asarray(values).reshape(current.shape))


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

    @property
    def nbytes(self) -> int:
        """Bytes of the planned segment's arrays and gradients (not the graphs' own records)."""
        return self._plan.nbytes if self._plan is not None else 0

    # ------------------------------------------------------------------ the taped step
    def _forward(self, plan: _Plan, steps: int, last: bool, tape, clear: list[wp.array]) -> None:
        """The launches of a ``steps``-long segment on ``tape``; then the gradient buffers ``clear`` zeroed."""
        with tape:
            for k in range(steps):
                self.solver.step(plan.states[k], plan.states[k + 1], plan.controls[k], tape=tape,
                                 workspace=plan.workspaces[k])
            if last:
                self.solver.eval_body_points(plan.states[steps], plan.final_points)
        for g in clear:
            g.zero_()

    def _residue(self, plan: _Plan, steps: int, last: bool) -> list[wp.array]:
        """The gradient buffers a reverse pass leaves non-zero.

        Warp's adjoint of a plain array store reads the element's gradient and zeroes it, so
        after a reverse pass only the buffers of arrays that are read but never stored to in
        the segment (its start state, its inputs) or only accumulated into (atomic adds: the
        bar feedback) hold anything. Found by a reverse pass with every gradient buffer set
        to ones; only these are cleared before each replay (clearing all of them cost about
        a fifth of the reverse pass). The model parameters' gradients are restored after.
        """
        saved = [a.grad.numpy().copy() for a in self.parameters]
        warm = wp.Tape()
        self._forward(plan, steps, last, warm, plan.grads)
        for g in plan.grads:
            upload_values(g, np.ones(g.numpy().shape))
        warm.backward()
        residue = [g for g in plan.grads if np.any(g.numpy() != 0.0)]
        for g in plan.grads:
            g.zero_()
        for a, g in zip(self.parameters, saved):
            upload_values(a.grad, g)
        return residue

    def _prepare(self, steps: int, last: bool):
        """The planned arrays, and the captured graphs of a ``(steps, last)`` segment (None
        without capture)."""
        if self._plan is None:
            self._plan = _Plan(self.model, self.solver, self.steps)
        plan = self._plan
        if not self.capture:
            return plan, None
        key = (steps, last)
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
                 adjoint_end: StateAdjoint | None, grads: dict) -> StateAdjoint:
        """Re-runs puppet steps ``a .. b-1`` from ``checkpoint`` on a tape and pulls back.

        Args:
            checkpoint: the state at step ``a`` (``dmarionette.grad.engine.Checkpoint``).
            inputs: the rollout's ``RolloutInputs`` (the model's constants already set from them).
            a, b: the segment's first and one-past-last puppet step.
            last: ``b`` is the rollout's end (its final row of per-puppet-step outputs is seeded here).
            cotangents: output name -> full-rollout cotangent array (missing: zero).
            adjoint_end: adjoint of the state at step ``b`` (None: zero).
            grads: input name -> full-rollout gradient arrays; the segment's rows are added.

        Returns:
            The adjoint of the state at step ``a``.
        """
        m = self.model
        n = m.substeps
        steps = b - a
        if steps > self.steps:
            raise ValueError(f"segment {a}..{b}: {steps} puppet steps; planned for at most {self.steps}")
        plan, graphs = self._prepare(steps, last)
        states = plan.states[:steps + 1]
        controls = plan.controls[:steps]
        checkpoint.load(states[0])
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            upload_values(control.top_q, inputs.top_q[rows])
            upload_values(control.bar_q, inputs.bar_q[rows])
            upload_values(control.bar_qd, inputs.bar_qd[rows])
        if graphs is not None:
            graphs[0].run()
        else:
            tape = wp.Tape()  # not reset(): that would clear the parameters' accumulated gradients
            self._forward(plan, steps, last, tape, plan.grads)
        # Seed: the per-step outputs of this segment, then the state adjoint from the next one.
        for k in range(steps + 1 if last else steps):
            p, points = a + k, plan.points(k, steps)
            if "joint_q" in cotangents:
                _add_grad(states[k].puppet.joint_q, cotangents["joint_q"][p])
            if "point_pos" in cotangents:
                _add_grad(points.point_q, cotangents["point_pos"][p])
            if "body_pos" in cotangents:
                _add_grad(points.kinematics.body_pos, cotangents["body_pos"][p])
            if "body_rot" in cotangents:
                _add_grad(points.kinematics.body_rot, cotangents["body_rot"][p])
        for k in range(steps):
            rows = slice((a + k) * n, (a + k + 1) * n)
            for name in ("tie_force", "bar_feedback", "bar_reaction"):
                if name in cotangents:
                    _add_grad(getattr(states[k + 1], name), cotangents[name][rows])
        if adjoint_end is not None:
            adjoint_end.seed(states[-1])
        if graphs is not None:
            graphs[1].run()
        else:
            tape.backward()
        for k, control in enumerate(controls):
            rows = slice((a + k) * n, (a + k + 1) * n)
            grads["top_q"][rows] += control.top_q.grad.numpy()
            grads["bar_q"][rows] += control.bar_q.grad.numpy()
            grads["bar_qd"][rows] += control.bar_qd.grad.numpy()
        return StateAdjoint(states[0])


def _loaded() -> None:
    """No warm-up: ``TapedSegment._residue``'s eager pass has loaded every module."""
