"""Multiple shooting for calibration: the session cut into windows, each started from the
recorded puppet state (docs/calibration.md, "Windows").

A single rollout over a long, fast session from wrong constants drifts away from the
recording: the residuals then depend on the constants through the whole chaotic swing, and
Levenberg-Marquardt settles in a wrong basin (issue #14: 10 of 12 constants outside 3 sigma on
a 2 s session). Here every window of ``W`` puppet steps starts again from the recording, so
the residuals stay short-horizon functions of the constants, nearly linear in them.

A window starting at puppet frame ``a > 0`` starts from:

- the puppet: the recorded ``joint_q`` at frame ``a`` (``/puppet/state``) and the velocity that
  the puppet's integrator (``q' = q (+) H qd'``, backward Euler; quaternions ``r exp(H w / 2)``)
  maps frame ``a - 1`` to frame ``a`` with (:func:`joint_velocity_between`; exact for a
  simulated session);
- the strings: the state the previous window's strings ended in (a session does not record
  the strings, and a string's state, its stretch waves and the tie's offset, is not a function of
  the puppet's pose: a straight, quasi-static start was tried first and left errors of 1-3 N in
  the tie forces, 8-30 noise units of residual at the true constants), moved so that their
  tied ends follow the recorded body points (:meth:`WindowedRollout.handed_over`).

So the puppet, which carries the slow, chaotic swing, restarts from the recording in every
window, while the strings, fast and damped, carry over. At the constants the session was
recorded with, the windows reproduce one long rollout to round-off (tested). The windows run
one after the other (the strings' hand-over), not in parallel; several rollouts of the session
(a finite-difference Jacobian's columns) run together as the worlds of a batched model.

The first window starts from the session's start state (the scene's rest state, as the
simulator and the live loop start), exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .calibration_data import CalibrationData

__all__ = ["WindowedRollout", "joint_velocity_between", "recorded_joint_q", "window_bounds"]


def window_bounds(puppet_steps: int, window_steps: int) -> list[tuple[int, int]]:
    """Windows ``[(a, b), ...]`` of puppet frames covering ``0 .. puppet_steps``; the last one
    absorbs a remainder shorter than half a window."""
    if not (isinstance(window_steps, (int, np.integer)) and window_steps >= 1):
        raise ValueError(f"window_steps: got {window_steps!r}; expected an integer >= 1 (puppet steps per window)")
    edges = list(range(0, puppet_steps, int(window_steps))) + [puppet_steps]
    if len(edges) > 2 and edges[-1] - edges[-2] < window_steps / 2:
        del edges[-2]
    return list(zip(edges[:-1], edges[1:]))


def recorded_joint_q(data: CalibrationData) -> np.ndarray | None:
    """The recorded puppet coordinates at frames ``0 .. P`` ``(P + 1, q)``, or None when the
    session has no complete ``/puppet/state`` with ``joint_q`` at every frame."""
    channel = data.session.channels.get("/puppet/state")
    if channel is None or "joint_q" not in channel or len(channel["t"]) == 0:
        return None
    t, q = np.asarray(channel["t"]), np.asarray(channel["joint_q"])
    k = np.rint(t / data.puppet_dt).astype(np.int64)
    on_grid = np.abs(t - k * data.puppet_dt) < 1e-6 * data.puppet_dt
    out = np.full((data.puppet_steps + 1, q.shape[1]), np.nan)
    inside = on_grid & (k >= 0) & (k <= data.puppet_steps)
    out[k[inside]] = q[inside]
    return out if np.all(np.isfinite(out)) else None


def _quat_log_velocity(r0: np.ndarray, r1: np.ndarray, h: float) -> np.ndarray:
    """``w`` with ``r1 = r0 exp(h w / 2)`` (unit quaternions ``(w, x, y, z)``; body-frame ``w``)."""
    w0, v0 = r0[0], -r0[1:]  # conjugate of r0
    w1, v1 = r1[0], r1[1:]
    dw = w0 * w1 - v0 @ v1
    dv = w0 * v1 + w1 * v0 + np.cross(v0, v1)
    if dw < 0.0:  # the short way round
        dw, dv = -dw, -dv
    s = np.linalg.norm(dv)
    angle = 2.0 * np.arctan2(s, dw)
    return (angle / h) * (dv / s) if s > 0.0 else np.zeros(3)


def joint_velocity_between(topology, q0: np.ndarray, q1: np.ndarray, h: float) -> np.ndarray:
    """The velocity ``qd`` the puppet's integrator maps ``q0`` to ``q1`` with in a step of ``h``
    [s] (``q1 = q0 (+) h qd``; the inverse of ``integrate_joint_coordinates``), ``(qd_count,)``.

    Args:
        topology: the puppet's ``ArticulationTopology`` (joint types, coordinate offsets).
        q0, q1: coordinates ``(q_count,)`` (free and ball joints: MuJoCo-ordered quaternions).
        h: the step [s].
    """
    qd = np.zeros(topology.qd_count)
    for j in topology.joints:
        s, d = j.q_start, j.qd_start
        if j.type in ("free", "ball"):
            o = 0
            if j.type == "free":
                qd[d:d + 3] = (q1[s:s + 3] - q0[s:s + 3]) / h
                o = 3
            r0 = q0[s + o:s + o + 4] / np.linalg.norm(q0[s + o:s + o + 4])
            r1 = q1[s + o:s + o + 4] / np.linalg.norm(q1[s + o:s + o + 4])
            qd[d + o:d + o + 3] = _quat_log_velocity(r0, r1, h)
        else:
            count = _dof_count(j.type)
            qd[d:d + count] = (q1[s:s + count] - q0[s:s + count]) / h
    return qd


def _dof_count(joint_type: str) -> int:
    return {"universal": 2, "hinge": 1}[joint_type]


class WindowedRollout:
    """Rollouts of a session cut into windows that start from the recorded puppet state.

    Args:
        model: the ``MarionetteModel`` (built with ``requires_grad=True``).
        data: the session (its ``/puppet/state`` must hold ``joint_q`` at every puppet frame).
        joint_q: the recorded coordinates ``(P + 1, q)`` (:func:`recorded_joint_q`).
        window_steps: puppet steps per window.
        puppet_steps: run only the first puppet steps (default: the whole session); the outputs
            beyond stay zero.
    """

    def __init__(self, model, data: CalibrationData, joint_q: np.ndarray, window_steps: int, *,
                 puppet_steps: int | None = None):
        from dmarionette.grad.engine import MarionetteGradient

        self.model = model
        self.data = data
        self.joint_q = joint_q
        self.window_steps = int(window_steps)
        self.puppet_steps = puppet_steps
        self.windows = window_bounds(data.puppet_steps if puppet_steps is None else int(puppet_steps), window_steps)
        self.engines = {}
        for a, b in self.windows:
            if b - a not in self.engines:
                self.engines[b - a] = MarionetteGradient(model, b - a, checkpoint_steps=b - a)
        h = data.puppet_dt
        topology = model.puppet.topology
        self._tied = model.string_point >= 0
        self._point = np.where(self._tied, model.string_point, 0)
        counts = np.asarray(model.strings.string_particle_count, dtype=int)
        # Each particle's place along its string: 0 at the top, 1 at the tied end; 0 for untied strings.
        self._along = np.concatenate([np.linspace(0.0, 1.0, c) * t for c, t in zip(counts, self._tied)])[:, None]
        # The recorded tie points at every frame (positions only: a window's velocity correction
        # is the difference of two frames', below, the same for the recording and the simulation).
        state = model.puppet.state()
        last = self.windows[-1][1]
        self._recorded_points = np.zeros((last + 1, len(self._tied), 3))
        for f in range(last + 1):
            self._recorded_points[f] = self._points(state, joint_q[f], np.zeros(topology.qd_count))
        self._starts = {a: (joint_q[a].copy(), joint_velocity_between(topology, joint_q[a - 1], joint_q[a], h))
                        for a, _ in self.windows[1:]}
        # A batched model (one world per rollout, ``forward`` of a list): every world's strings are laid
        # out as world 0's; these are world 0's.
        self._particles = model.strings.particle_count // model.world_count
        self._string_of = np.asarray(model.strings.particle_string.numpy())[:self._particles]

    def _points(self, state, joint_q: np.ndarray, joint_qd: np.ndarray) -> np.ndarray:
        """Tie points of the strings [m] ``(S, 3)`` at a puppet pose."""
        import warp as wp

        device = self.model.device
        state.joint_q.assign(wp.array(np.asarray(joint_q)[None], dtype=wp.float64, device=device))
        state.joint_qd.assign(wp.array(np.asarray(joint_qd)[None], dtype=wp.float64, device=device))
        q, _ = self.model.eval_points(state)
        return q[self._point]

    def handed_over(self, a: int, end: dict[str, np.ndarray], end_points: np.ndarray,
                    refine: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[dict, dict]:
        """The start of the window at frame ``a > 0`` from the carried state ``end`` the previous
        window ended in (``dmarionette.grad.carried`` names, host arrays) and its simulated tie
        points at frames ``a - 1`` and ``a`` ``(2, S, 3)``: the recorded puppet state; the
        strings, tie targets and tie forces handed over, moved so that their tied ends follow the
        recorded body points. The shift grows linearly from 0 at the top to, at the tied end, the
        difference ``d`` of the recorded and simulated tie points at frame ``a`` (positions) and
        ``(d_a - d_{a-1}) / H`` (velocities). At the constants the session was recorded with,
        ``d = 0`` and the windows reproduce one long rollout.

        ``refine``: ``(dq, dqd)`` ``(qd_count,)`` each, a correction of the recorded start state
        (``--fit-initial-state``, :mod:`fitting.calibration_initial_state`): the puppet starts from
        ``q_a (+) dq`` with velocity ``qd_a + dqd``, and the strings follow its tie points (at
        frame ``a``, and one step back along the refined velocity for frame ``a - 1``).

        Returns:
            ``(inputs, extra)``: ``RolloutInputs`` fields (``joint_q0``, ``joint_qd0``,
            ``particle_q0``, ``particle_qd0``) and the engine's ``tie_target0``, ``tie_force0``.
        """
        joint_q, joint_qd = self._starts[a]
        recorded = self._recorded_points[a - 1:a + 1]
        if refine is not None:
            from .calibration_initial_state import retract

            topology, h = self.model.puppet.topology, self.data.puppet_dt
            joint_q = retract(topology, joint_q, refine[0])
            joint_qd = joint_qd + refine[1]
            state = self.model.puppet.state()
            zero = np.zeros(topology.qd_count)
            recorded = np.stack([self._points(state, retract(topology, joint_q, -h * joint_qd), zero),
                                 self._points(state, joint_q, zero)])
        difference = np.where(self._tied[None, :, None], recorded - end_points, 0.0)
        dq = difference[1]
        dqd = (difference[1] - difference[0]) / self.data.puppet_dt
        inputs = {"joint_q0": joint_q, "joint_qd0": joint_qd,
                  "particle_q0": end["particle_q"] + self._along * dq[self._string_of],
                  "particle_qd0": end["particle_qd"] + self._along * dqd[self._string_of]}
        extra = {"tie_target0": end["tie_target"] + dq, "tie_force0": end["tie_force"]}
        return inputs, extra

    def forward(self, inputs, refine: dict[int, tuple[np.ndarray, np.ndarray]] | list | None = None
                ) -> dict[str, np.ndarray] | list[dict[str, np.ndarray]]:
        """Runs the windows in order with the constants of ``inputs`` (a ``RolloutInputs`` over
        the whole session), the start states of windows ``a`` in ``refine`` corrected
        (:meth:`handed_over`); returns ``body_pos`` ``(P + 1, bodies, 3)`` (row 0 the session's
        start) and ``bar_reaction`` ``(T, B, 3)``, stitched from the windows.

        On a batched model (``world_count`` ``W``), ``inputs`` is a list of ``W`` (and ``refine``
        None or a list of ``W``) and so is the result: ``W`` rollouts of the session (e.g. the
        finite-difference columns of a Jacobian) in the same launches, each world bit for bit the
        one-world rollout.

        A world whose state goes non-finite (a trial point of the solver far out, e.g. one
        ``k_d`` at 1e18) returns NaN everywhere, which the least-squares solvers reject as a
        step; its later windows start from another world's hand-over (their outputs are
        discarded) so that the batch's launches stay finite."""
        from dmarionette.grad.carried import carried_arrays

        worlds = list(inputs) if isinstance(inputs, (list, tuple)) else [inputs]
        batched = isinstance(inputs, (list, tuple))
        refines = (list(refine) if refine is not None else [None] * len(worlds)) if batched else [refine]
        n, p = self.data.substeps, self.data.puppet_steps
        shape = next(iter(self.engines.values())).output_shapes["body_pos"][1:]
        body_pos = [np.zeros((p + 1, *shape)) for _ in worlds]
        bar_reaction = [np.zeros((p * n, *x.bar_q.shape[1:])) for x in worlds]
        ends, diverged = None, [False] * len(worlds)
        for a, b in self.windows:
            if all(diverged):
                break
            rows = slice(a * n, b * n)
            windows, extras = [], []
            for w, x in enumerate(worlds):
                window = dataclasses.replace(x, top_q=x.top_q[rows], bar_q=x.bar_q[rows], bar_qd=x.bar_qd[rows])
                if a > 0:
                    source = diverged.index(False) if diverged[w] else w
                    start, extra = self.handed_over(a, *ends[source], (refines[source] or {}).get(a))
                    window = dataclasses.replace(window, **start)
                    extras.append(extra)
                windows.append(window)
            engine = self.engines[b - a]
            if batched:
                extra = {name: [e[name] for e in extras] for name in ("tie_target0", "tie_force0")} if extras else {}
                outs = engine.forward(windows, **extra)
            else:
                outs = [engine.forward(windows[0], **(extras[0] if extras else {}))]
            carried = {name: array.numpy().copy() for name, array in carried_arrays(engine.state).items()}
            ends = [(self._world_part(carried, w), out.point_pos[-2:, self._point]) for w, out in enumerate(outs)]
            for w, out in enumerate(outs):
                if a == 0:
                    body_pos[w][0] = out.body_pos[0]
                body_pos[w][a + 1:b + 1] = out.body_pos[1:]
                bar_reaction[w][rows] = out.bar_reaction
                diverged[w] = diverged[w] or not _finite(out.body_pos, ends[w][1], *ends[w][0].values())
        for w in np.flatnonzero(diverged):
            body_pos[w][:] = np.nan
            bar_reaction[w][:] = np.nan
        results = [{"body_pos": q, "bar_reaction": r} for q, r in zip(body_pos, bar_reaction)]
        return results if batched else results[0]

    def _world_part(self, carried: dict[str, np.ndarray], world: int) -> dict[str, np.ndarray]:
        """World ``world``'s share of a batched model's carried state (one world's layout)."""
        if self.model.world_count == 1:
            return carried
        particles = slice(world * self._particles, (world + 1) * self._particles)
        per_world = self.model.strings_per_world
        strings = slice(world * per_world, (world + 1) * per_world)
        return {"particle_q": carried["particle_q"][particles], "particle_qd": carried["particle_qd"][particles],
                "joint_q": carried["joint_q"][world:world + 1], "joint_qd": carried["joint_qd"][world:world + 1],
                "tie_target": carried["tie_target"][strings], "tie_force": carried["tie_force"][:, strings]}


def _finite(*arrays) -> bool:
    """Whether every value of ``arrays`` is finite."""
    return all(bool(np.all(np.isfinite(a))) for a in arrays)
