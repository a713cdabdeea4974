"""What one puppet step reads from the previous one: the carried state of a rollout.

A checkpoint (``engine.Checkpoint``) keeps these arrays' values at a segment's start; the
adjoint handed between segments (``tape.StateAdjoint``) keeps their gradients.
"""

from __future__ import annotations

import warp as wp

__all__ = ["CARRIED_FIELDS", "carried_arrays"]

CARRIED_FIELDS = ("particle_q", "particle_qd", "joint_q", "joint_qd", "tie_target", "tie_force")
"""String particle positions and velocities, puppet coordinates and velocities, the tie targets,
and the previous puppet step's tie forces ``(n, S)`` (the next trial step reads their mean)."""


def carried_arrays(state) -> dict[str, wp.array]:
    """The carried arrays of a ``MarionetteState``-like ``state``, by :data:`CARRIED_FIELDS` name."""
    return {"particle_q": state.strings.particle_q, "particle_qd": state.strings.particle_qd,
            "joint_q": state.puppet.joint_q, "joint_qd": state.puppet.joint_qd,
            "tie_target": state.tie_target, "tie_force": state.tie_force}
