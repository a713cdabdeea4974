"""Coupling of strings and puppet (paper eq. 2), both ways, across the two rates.

Between two puppet steps (``H = n h``: ``n`` string steps of ``h``):

- prediction (``eval_string_response``, in a trial puppet step): the puppet takes a trial
  step of ``H`` from ``t0`` in which each tied string is replaced by its linearisation as
  its tie sees it, ``f = F0 - K (x - x0) - C (v - v0)``, implicit (the trial step's
  linearised backward Euler). ``F0`` is the string's pull: the mean of the tie forces of
  the previous puppet step (zero before the first); ``K = k_ax u u^T + (T / L) (I - u u^T)``:
  along the string (``u`` from the body point to the top particle, ``L`` apart) the tie and
  the whole string in series, ``k_ax = k k_string / (k + k_string)``, ramped in as the
  string straightens from the §3.2 taut distance to its rest length; across it, the
  geometric stiffness of a straight string under its tension ``T`` (that of its last
  segment; 0 when slack); ``C`` the whole string's internal friction (paper term 2 acts on
  every relative velocity, so it is isotropic) in series with the tie, whose spring over
  one step acts like a damper ``k H``. Everything else is the real step's: gravity, joint
  limits, contacts, joint damping. The trial's tied points at ``t0 + H`` are the
  prediction ``x_p``;
- body -> strings (``eval_tie_path``): the tie target of each string moves in a straight
  line, at constant velocity, from where it was at ``t0`` (the end of the previous path)
  to ``x_p``; the strings treat the tie implicitly against that path at every string
  step. The path is continuous from one puppet step to the next: starting it afresh at
  ``x_b(t0)`` would make the target jump by the last prediction error, and the light end
  particle would be kicked by ``k`` times that error;
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
  (Eq. 2 itself is ``string_tie.compute_tie_force``, the anchor ``string_tie.compute_tie_anchor``;
  the string's tension in the linear model is ``string_spring.compute_string_tension``.)

Handing the body the string's *end particle* as the anchor instead would tie the body to
its own extrapolation: the light end particle only tracks the predicted path, and the
string's pull would reach the body only through the tie's small stretch.

**Why a trial step** (the paper runs the two rates asynchronously and says nothing of how
they meet; this is ours). The earlier predictor, ``x_p = x_b(t0) + H v_b(t0)``, ignores
every acceleration within the step: when a joint limit stopped a tied limb within a
33 ms step, the strings had already been dragged up to ``H |v|`` along a path the body
never took and the stiff tie pulled the body after it; the string and tie springs stored
that energy and handed it back (+1.14 J with a shoulder thrown at 20 rad/s into its limit
at 30 Hz, when the motion had 0.17 J). The trial step sees the limit (whose activation
looks ahead, ``articulation_codegen._limits``) and the strings' pull, so the path is where
the body goes: that case now loses energy like the 1 kHz reference, and the body points
stay within 5.3 mm (RMS) of it instead of 74 mm (``tests/marionette/test_hard_cases_puppet.py``); on
the default sway the torso stays within 1.4 mm of the fully coupled run instead of 21.7 mm
(``tests/marionette/test_marionette.py``), and a puppet as slow as 10 Hz under 1 kHz strings keeps
within the energy bound (``settings_check``).

Each part of the linear model is there because a hard case failed without it. ``F0``:
the tie's momentary pull against the body point, ``k (x_last - x_b)``, holds the last
prediction error times the stiff ``k``, explicit in the trial (diverged); against the tie
target, ``k (x_last - x_t)``, it carries the light end particle's transients (after the
bars' 5 m/s jerks the ties of slack strings were stretched by newtons' worth: +0.77 J);
the pull of the last segment, ``k_s`` times a float32 length, is rounding noise times
``k_s`` = 24,500 N/m (float32 strings left float64 by 43x their rounding bound at 30 Hz);
the mean of the last step's tie forces is none of these (it lags the pull by half a
puppet step, which the implicit ``K`` and ``C`` carry: stable in every hard case). No tie damping, and the
strings' friction implicit: ``C H / m`` is 1 to 7 for a 25 g hand at 30 Hz with the
default and 10x strings, and explicit the hands' swing grew sixfold per step. The
geometric stiffness across the string: the tie's ``k`` there stopped a thrown arm dead.
The taut ramp and the limits' look-ahead band are continuous so that rounding does not
switch them differently. The cost is one more puppet step per puppet step (its kernels
are the real step's), and the previous step's tie forces are part of the carried state
(``marionette_grad.Checkpoint``).

With ``n = 1`` (the puppet at the string rate) this is a staggered coupling of two
implicit integrators with the same trial step. The gap the coupling leaves at 30 Hz is
measured by the tests and ``dmarionette bench accuracy`` against the fully coupled run.
"""

import functools

import warp as wp

from .articulation_forces import compute_point_state
from .articulation_math import compute_point_inertia, compute_point_wrench, spatial6, spatial66
from .string_model_arrays import string_model_arrays_type
from .string_spring import string_spring_functions
from .string_tie import compute_tie_anchor


@functools.cache
def eval_string_response_kernel(scalar, internal_friction: bool, substeps: int):
    """Builds ``eval_string_response`` for strings of float type ``scalar`` (float32 strings are
    widened to float64 as they are read; the puppet side is float64), with the strings'
    internal friction compiled in or out, for ``n = substeps`` string steps per puppet step
    (the mean of the previous step's tie forces is unrolled, as in
    :func:`apply_string_forces_to_anchors_kernel`, so that the reverse pass replays it)."""
    vec3 = wp.types.vector(3, scalar)
    StringModelArrays = string_model_arrays_type(scalar)  # the strings' constants (string_model_arrays)
    spring = string_spring_functions(wp.float64)  # the strings' values are widened as they are read
    FRICTION = bool(internal_friction)
    n = int(substeps)

    @wp.kernel(module="unique", module_options={"max_unroll": max(n, 16)})
    def eval_string_response(
        # Model:
        spring_body: wp.array(dtype=wp.int32),
        spring_point: wp.array(dtype=wp.vec3d),
        spring_string: wp.array(dtype=wp.int32),
        strings_per_world: wp.int32,
        strings: StringModelArrays,
        # State in:
        body_pos: wp.array2d(dtype=wp.vec3d),
        body_rot: wp.array2d(dtype=wp.quatd),
        body_w: wp.array2d(dtype=wp.vec3d),
        body_v: wp.array2d(dtype=wp.vec3d),
        particle_q: wp.array(dtype=vec3),
        tie_force: wp.array2d(dtype=wp.vec3d),
        h: wp.float64,
        # State out:
        body_wrench: wp.array2d(dtype=spatial6),
        body_stiffness: wp.array2d(dtype=spatial66),
    ):
        """The trial step's load of tied string ``i``: ``f = F0 - K (x - x0) - C (v - v0)``, implicit
        (module doc).

        ``F0``: the mean of the previous puppet step's tie forces (``tie_force``, ``(n, S)``);
        ``K = k_ax u u^T + T / L (I - u u^T)`` with ``u`` from the body point to the string's
        top particle, ``L`` their distance, ``T`` the tension of the string's last segment
        (``k_s`` times its stretch, 0 if slack) and ``k_ax`` the tie and the whole string
        (``k_s / segments``) in series, ramped in from the taut distance to the rest length;
        ``C`` the whole string's
        friction in series with ``k h``. The linearised backward-Euler force ``F0 - h K v``
        goes to the wrench, ``h^2 K + h C`` to the system matrix.
        """
        w, i = wp.tid()
        b = spring_body[i]
        s = w * strings_per_world + spring_string[i]  # the strings of world w follow those of the worlds before
        x, v = compute_point_state(body_pos[w, b], body_rot[w, b], body_w[w, b], body_v[w, b], spring_point[i])
        first = strings.string_start[s]
        last = strings.string_start[s + 1] - 1
        k = wp.float64(strings.string_tie_stiffness[s])
        # The string's pull: the mean of the tie forces of the previous puppet step. (The
        # momentary tie force k (x_last - x_t) carries the light end particle's transients:
        # after the bars' 5 m/s jerks, newtons' worth while the string is slack, +4.8 J. The pull
        # of the last segment, k_s times a float32 length, is rounding noise times k_s = 24,500
        # N/m: float32 strings then left float64 by 43 x their rounding bound at 30 Hz.)
        force = wp.vec3d()
        for j in range(wp.static(n)):
            force += tie_force[j, s]
        force = force / wp.float64(wp.static(float(n)))
        segment = wp.length(wp.vec3d(particle_q[last - 1]) - wp.vec3d(particle_q[last]))
        along = wp.vec3d(particle_q[first]) - x
        length = wp.length(along)
        zero = wp.float64(0.0)
        eye = wp.identity(3, dtype=wp.float64)
        stiffness = wp.mat33d()
        if length > zero:
            u = along / length
            uu = wp.outer(u, u)
            tension = spring.compute_string_tension(segment, wp.float64(strings.string_stiffness[s]),
                                                    wp.float64(strings.string_rest_length[s]))
            stiffness = (tension / length) * (eye - uu)
            # Along the string: the tie and the whole string in series, ramped in from the §3.2
            # taut distance to the rest length (a continuous switch: a step in it would turn
            # rounding into a different path).
            span = wp.length(wp.vec3d(particle_q[last]) - wp.vec3d(particle_q[first]))
            taut = wp.float64(strings.string_taut_distance[s])
            rest = wp.float64(strings.string_rest_length[s]) * wp.float64(last - first)
            ramp = wp.clamp((span - taut) / wp.max(rest - taut, wp.float64(1e-9)), zero, wp.float64(1.0))
            whole = wp.float64(strings.string_stiffness[s]) / wp.float64(last - first)
            stiffness = stiffness + (ramp * k * whole / (k + whole)) * uu
        damping = wp.float64(0.0)
        if wp.static(FRICTION):
            # The whole string's friction in series with the tie, whose spring over one step acts
            # like a damper k h: 1 / c = 1 / c_string + 1 / (k h) (a cut tie transmits nothing).
            whole_friction = wp.float64(strings.string_internal_friction[s]) / wp.float64(last - first)
            damping = whole_friction * (k * h) / (whole_friction + k * h)
        f = force - h * (stiffness * v)
        wp.atomic_add(body_wrench, w, b, compute_point_wrench(x, f))
        wp.atomic_add(body_stiffness, w, b, compute_point_inertia(x, (h * h) * stiffness + (h * damping) * eye))

    return eval_string_response


@wp.kernel
def eval_tie_path(
    # Model:
    string_point: wp.array(dtype=wp.int32),
    strings_per_world: wp.int32,
    # State in:
    point_end: wp.array2d(dtype=wp.vec3d),
    tie_target: wp.array(dtype=wp.vec3d),
    # Control:
    dt: wp.float64,
    # State out:
    tie_q: wp.array2d(dtype=wp.vec3d),
    tie_qd: wp.array2d(dtype=wp.vec3d),
    tie_target_out: wp.array(dtype=wp.vec3d),
):
    """tie_q[j, s]: from tie_target[s] to the trial step's end point in n equal steps (zero if untied);
    string ``s`` belongs to world ``s // strings_per_world``."""
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
    end = point_end[s // strings_per_world, p]
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
        strings_per_world: wp.int32,
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
        """Anchor of body spring ``i`` of world ``w`` at t0: the predicted end point plus the mean tie
        force over k, moved back along the path velocity by the puppet step ``H = n dt``."""
        w, i = wp.tid()
        s = w * strings_per_world + spring_string[i]
        mean = wp.vec3d()
        for j in range(wp.static(n)):
            mean += tie_force[j, s]
        count = wp.float64(wp.static(float(n)))
        mean = mean / count
        velocity = tie_qd[wp.static(last), s]
        spring_anchor_pos[w, i] = (compute_tie_anchor(tie_q[wp.static(last), s], mean, string_tie_stiffness[s])
                                   - (count * dt) * velocity)
        spring_anchor_vel[w, i] = velocity

    return apply_string_forces_to_anchors
