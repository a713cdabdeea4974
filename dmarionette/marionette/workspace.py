"""What one marionette step writes besides its output state (like MJX's ``Data``).

:class:`SolverMarionette` keeps one :class:`MarionetteWorkspace` for plain runs and reuses
it from step to step; a step recorded on a tape gets one of its own (on a tape an array
written after it was read gives silently wrong gradients), so a taped run and a plain run
call the same methods with different workspaces.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import warp as wp

from dmarionette.articulation.solver import (
    ArticulationControl,
    ArticulationKinematics,
    ArticulationState,
    ArticulationWorkspace,
)
from dmarionette.kernels.string_state_arrays import STATE_FIELDS, string_state_arrays_type, struct_of_arrays
from dmarionette.strings.model import StringState
from dmarionette.strings.solver import StringWorkspace

__all__ = ["MarionetteWorkspace", "PuppetPoints", "StringStepOutput"]


@dataclasses.dataclass
class StringStepOutput:
    """Where one string step of a marionette writes (the string solver's ``state_out``): a string
    state's particles, and the tie force and taut flags straight into that string step's rows
    of the marionette state's ``(n, S)`` arrays (float64 strings).

    Attributes:
        particle_q, particle_qd: [m], [m/s], ``(P,)`` of vec3.
        tie_force: eq. 2 force of each tie on its body point [N], ``(S,)``.
        string_taut: taut flags, ``(S,)``.
        arrays: the above as one kernel argument, a ``StringStateArrays`` (as ``StringState.arrays``).
    """

    particle_q: wp.array
    particle_qd: wp.array
    tie_force: wp.array
    string_taut: wp.array
    _arrays: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def arrays(self):
        """This output's arrays as a ``StringStateArrays`` (class doc)."""
        self._arrays = struct_of_arrays(string_state_arrays_type, self, STATE_FIELDS, self._arrays)
        return self._arrays[1]


@dataclasses.dataclass
class PuppetPoints:
    """Body kinematics of a puppet state and its named points there.

    Attributes:
        kinematics: body poses and velocities (``W`` worlds).
        point_q, point_qd: world positions [m] and velocities [m/s] of the puppet's named
            points (``puppet.point_names`` order), ``(W, points)`` of vec3d.
    """

    kinematics: ArticulationKinematics
    point_q: wp.array
    point_qd: wp.array

    @classmethod
    def allocate(cls, puppet_model, requires_grad: bool = False, world_count: int = 1) -> PuppetPoints:
        n, w = len(puppet_model.point_names), world_count
        with wp.ScopedDevice(puppet_model.device):
            return cls(puppet_model.kinematics(w, requires_grad),
                       wp.zeros((w, n), dtype=wp.vec3d, requires_grad=requires_grad),
                       wp.zeros((w, n), dtype=wp.vec3d, requires_grad=requires_grad))


@dataclasses.dataclass
class MarionetteWorkspace:
    """The derived quantities and scratch of one puppet step (``n`` string steps, ``S`` strings).

    Attributes:
        points: the input state's body kinematics and tied points at ``t0``.
        trial_workspace: the trial puppet step's derived quantities (``string_body_coupling``).
        trial: the trial step's end state.
        trial_points: its body kinematics and points at ``t0 + H`` (the prediction).
        tie_q, tie_qd: the tie path over the string steps [m], [m/s], ``(n, W S)``.
        string_states: the string states between string steps (two in turn for a plain
            run, ``n - 1`` for a taped one); :meth:`SolverMarionette.string_state_after`
            says which holds string step ``j``'s result.
        string_workspaces: the string steps' intermediates (one shared, or one per string step).
        narrow: float32 strings only: their float32 controls (``top_q``, ``tie_q``, ``tie_qd``).
        puppet_control: the puppet step's control (the body springs' anchors).
        puppet_workspace: the puppet step's derived quantities.
        control_views: the string steps' controls of a puppet control seen by this workspace,
            by the control's id (``SolverMarionette.string_controls``; the entry holds the
            control, so the id stays unique).
    """

    points: PuppetPoints
    trial_workspace: ArticulationWorkspace
    trial: ArticulationState
    trial_points: PuppetPoints
    tie_q: wp.array
    tie_qd: wp.array
    string_states: list[StringState]
    string_workspaces: list[StringWorkspace]
    narrow: SimpleNamespace | None
    puppet_control: ArticulationControl
    puppet_workspace: ArticulationWorkspace
    control_views: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def allocate(cls, model, *, taped: bool = False) -> MarionetteWorkspace:
        """A workspace for ``model``'s steps (``taped``: one step on a tape, with gradients)."""
        m, rg = model, taped
        n, s, w = m.substeps, m.strings.string_count, m.world_count
        pup = m.puppet
        with wp.ScopedDevice(m.device):
            narrow = None if m.precision == "float64" else SimpleNamespace(
                top_q=wp.zeros((n, s), dtype=m.strings.vec3), tie_q=wp.zeros((n, s), dtype=m.strings.vec3),
                tie_qd=wp.zeros((n, s), dtype=m.strings.vec3))
            return cls(
                points=PuppetPoints.allocate(pup, rg, w),
                trial_workspace=pup.workspace(w, rg),
                trial=pup.state(w, requires_grad=rg),
                trial_points=PuppetPoints.allocate(pup, rg, w),
                tie_q=wp.zeros((n, s), dtype=wp.vec3d, requires_grad=rg),
                tie_qd=wp.zeros((n, s), dtype=wp.vec3d, requires_grad=rg),
                string_states=[m.strings.state() for _ in range(n - 1 if taped else 2)],
                string_workspaces=[m.string_solver.new_workspace(taped) for _ in range(n if taped else 1)],
                narrow=narrow,
                puppet_control=pup.control(w, requires_grad=rg),
                puppet_workspace=pup.workspace(w, rg),
            )
