"""Coupling of strings and puppet (paper eq. 2), both ways, across the two rates.

Between two puppet steps (``H = n h``: ``n`` string steps of ``h``):

- body -> strings (``eval_tie_path``): the tie target of each string moves in a straight
  line, at constant velocity, from where it was at ``t0`` (the end of the previous path)
  to where the body point's position and velocity at ``t0`` predict it at ``t0 + H``,
  ``x_p = x_b(t0) + H v_b(t0)``; the strings treat the tie implicitly against that path
  at every string step. The path is continuous from one puppet step to the next: starting
  it afresh at ``x_b(t0)`` would make the target jump by the last prediction error, and
  the light end particle would be kicked by ``k`` times that error;
- strings -> body (``apply_string_forces_to_anchors_kernel``): the body receives the tie force
  the strings actually produced, averaged over the ``n`` string steps, ``F``, and any
  deviation of the body from the predicted path is resisted by the tie's own stiffness
  and damping, treated implicitly by the puppet step:
  ``f_body = F - k (x_b - x_p) - k_d (v_b - v_p)`` at ``t0 + H``. In the puppet's point
  spring form ``-k (x_b - A) - k_d (v_b - V)`` this is the anchor ``A = x_p(t0 + H) + F / k``
  with ``V = v_p``; the puppet's spring takes the anchor at the *start* of its step and
  moves it at ``V`` (``articulation_forces.eval_body_point_springs``), so it is handed
  ``A - H V``. On the predicted path the body gets exactly the impulse the strings
  gave (momentum is exchanged exactly); off it, the error is the stiff tie's, implicit.

Handing the body the string's *end particle* as the anchor instead would tie the body to
its own extrapolation: the light end particle only tracks the predicted path, and the
string's pull would reach the body only through the tie's small stretch.

With ``n = 1`` (the puppet at the string rate) this is a staggered coupling of two
implicit integrators. The predicted path is first-order accurate in ``H``; the gap it
causes at 30 Hz is measured by the tests against the fully coupled run.
"""

import functools

import warp as wp


@wp.kernel
def eval_tie_path(
    # Model:
    string_point: wp.array(dtype=wp.int32),
    # State in:
    point_q: wp.array2d(dtype=wp.vec3d),
    point_qd: wp.array2d(dtype=wp.vec3d),
    tie_target: wp.array(dtype=wp.vec3d),
    # Control:
    dt: wp.float64,
    # State out:
    tie_q: wp.array2d(dtype=wp.vec3d),
    tie_qd: wp.array2d(dtype=wp.vec3d),
    tie_target_out: wp.array(dtype=wp.vec3d),
):
    """tie_q[j, s]: from tie_target[s] to x_b + H v_b in n equal steps (zero if untied)."""
    j, s = wp.tid()
    p = string_point[s]
    if p < 0:
        tie_q[j, s] = wp.vec3d()
        tie_qd[j, s] = wp.vec3d()
        if j == 0:
            tie_target_out[s] = wp.vec3d()
        return
    n = tie_q.shape[0]
    horizon = wp.float64(n) * dt
    start = tie_target[s]
    end = point_q[0, p] + horizon * point_qd[0, p]
    velocity = (end - start) / horizon
    tie_q[j, s] = start + (wp.float64(j + 1) * dt) * velocity
    tie_qd[j, s] = velocity
    if j == 0:
        tie_target_out[s] = end


@functools.cache
def apply_string_forces_to_anchors_kernel(substeps: int):
    """Builds ``apply_string_forces_to_anchors`` for ``n = substeps`` string steps per puppet step.

    The mean over the ``n`` tie forces is a loop with a compile-time bound, unrolled even
    past Warp's default ``max_unroll = 16`` (``n = 33`` at 1 kHz / 30 Hz): a dynamic loop is
    not replayed in Warp's reverse pass, so the mean is zero there and ``dL/dk`` of the
    ``F / k`` offset is lost (measured: a zero gradient of this kernel at n = 33, and
    wrong-signed rollout gradients). The sum runs in the same order either way.
    """
    n = int(substeps)
    last = n - 1

    @wp.kernel(module="unique", module_options={"max_unroll": max(n, 16)})
    def apply_string_forces_to_anchors(
        # Model:
        spring_string: wp.array(dtype=wp.int32),
        string_tie_stiffness: wp.array(dtype=wp.float64),
        # State in:
        tie_force: wp.array2d(dtype=wp.vec3d),
        tie_q: wp.array2d(dtype=wp.vec3d),
        tie_qd: wp.array2d(dtype=wp.vec3d),
        dt: wp.float64,
        # State out:
        spring_anchor_pos: wp.array2d(dtype=wp.vec3d),
        spring_anchor_vel: wp.array2d(dtype=wp.vec3d),
    ):
        """Anchor of body spring ``i`` at t0: the predicted end point plus the mean tie force over
        k, moved back along the path velocity by the puppet step ``H = n dt``."""
        i = wp.tid()
        s = spring_string[i]
        mean = wp.vec3d()
        for j in range(wp.static(n)):
            mean += tie_force[j, s]
        count = wp.float64(wp.static(float(n)))
        mean = mean / count
        velocity = tie_qd[wp.static(last), s]
        spring_anchor_pos[0, i] = tie_q[wp.static(last), s] + mean / string_tie_stiffness[s] - (count * dt) * velocity
        spring_anchor_vel[0, i] = velocity

    return apply_string_forces_to_anchors
