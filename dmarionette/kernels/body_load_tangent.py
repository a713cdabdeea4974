"""Tangents of body loads kept from one pass and added into another's (forward mode, issue 13 item 4).

The marionette's trial puppet step and its puppet step evaluate the contacts of the same bodies
at the same state and ``h`` (``SolverMarionette.predict_body_points`` and
``SolverArticulation.step``), so their contact loads and the tangents of those loads are equal.
:class:`~dmarionette.articulation.step_tangent.PuppetStepTangent` keeps the trial's contact
tangents alone and adds them into the step's with :func:`apply_body_load_tangents` instead of
differentiating the contacts a second time (the step's primal contacts are still evaluated, the
solver's launch: its numbers stay the solver's to the bit).
"""

from __future__ import annotations

import warp as wp

from dmarionette.kernels.articulation_math import spatial6, spatial66

__all__ = ["apply_body_load_tangents"]


@wp.kernel
def apply_body_load_tangents(
    # Tangent in:
    tan_load_wrench: wp.array3d(dtype=spatial6),
    tan_load_stiffness: wp.array3d(dtype=spatial66),
    # Tangent out:
    tan_body_wrench: wp.array3d(dtype=spatial6),
    tan_body_stiffness: wp.array3d(dtype=spatial66),
):
    """Adds the kept loads' tangents (``(P, world_count, body_count)``) into the bodies' tangents."""
    p, w, b = wp.tid()
    wp.atomic_add(tan_body_wrench, p, w, b, tan_load_wrench[p, w, b])
    wp.atomic_add(tan_body_stiffness, p, w, b, tan_load_stiffness[p, w, b])
