"""The tie of a string's last particle to a body point, paper eq. 2, defined once.

``f_body = -k (x_body - x_string) - k_d (v_body - v_string)``, with ``x_string`` the
string's last particle (or, seen from the puppet's implicit step, the anchor the coupling
hands it); the string feels ``f_string = -f_body``.

Everything that evaluates eq. 2 calls :func:`compute_tie_force`:

- the string system (``string_system.eval_string_system``, through
  ``string_terms.compute_string_tie``: the string's side, with its Jacobians);
- the tie force of a string step (``string_integrate.eval_string_tie_force``);
- the body's point springs (``articulation_forces.eval_body_point_springs``: the same
  spring against the coupling's anchor, its damping ``k_d + h k`` the linearised
  backward-Euler step's);
- the coupling's anchor (``string_body_coupling.apply_string_forces_to_anchors``) is eq. 2
  solved for the anchor, :func:`compute_tie_anchor`.

The functions are generic over the float type (``float32`` strings, ``float64`` puppet):
their arguments' types choose the overload.
"""

from typing import Any

import warp as wp

__all__ = ["compute_tie_anchor", "compute_tie_force"]


@wp.func
def compute_tie_force(x_body: Any, v_body: Any, x_string: Any, v_string: Any, stiffness: Any, damping: Any):
    """Paper eq. 2: the force on the body, ``-k (x_body - x_string) - k_d (v_body - v_string)``.

    Args:
        x_body, v_body: the body point's position [m] and velocity [m/s].
        x_string, v_string: the string's end (last particle, or the anchor) [m], [m/s].
        stiffness: ``k`` [N/m] (times the string's ``tied`` flag where a string may be cut).
        damping: ``k_d`` [N s/m] (the same).

    Returns:
        The force on the body [N]; the string feels its opposite.
    """
    return -stiffness * (x_body - x_string) - damping * (v_body - v_string)


@wp.func
def compute_tie_anchor(x_body: Any, force: Any, stiffness: Any):
    """Eq. 2 solved for the string's end: the point ``A = x_body + F / k`` whose tie spring
    pulls a body point at rest at ``x_body`` with the force ``F`` (damping aside).

    Args:
        x_body: the body point [m].
        force: the force the tie is to put on the body [N].
        stiffness: ``k`` [N/m].
    """
    return x_body + force / stiffness
