"""The per-tick marionette of live puppetry (paper §3-4), and the physics callback the servo loop runs.

:class:`LiveMarionette` advances the marionette by one string step per call, running the
puppet every ``n`` calls: the passes of one puppet step are captured as ``n`` Warp graphs
(:class:`dmarionette.capture.CapturedChunk`), one per string-step index, so a tick costs one
graph replay and a little host work.

:func:`make_physics_step` turns a haptic device's samples into a bar's pose: the device tip sits
at the bar's centre (paper §3.1) and is mapped to the world by ``P' = S W P`` (eq. 3,
:class:`dmarionette.hw.mapping.DeviceMapping`); the force sent back is the driven bar's
feedback, through ``W``'s rotation only, then the servo loop's safety filter.

Several devices may drive several bars (the paper's two Omnis, one per bar): each has its
own mapping (its origin at its bar's start), feels its own bar's force and has its own
safety filter, all in the same servo ticks (:class:`dmarionette.hw.ServoLoop` with a sequence
of devices); this runs in the ``"thread"`` physics mode.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from dmarionette.capture import CapturedChunk
from dmarionette.live.view import scripted_rotations
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette, bar_inputs
from dmarionette.rotations import euler_to_matrix, matrix_to_euler
from dmarionette.scene.bars import bar_attach_points

__all__ = ["LiveMarionette", "LiveTick", "make_physics_step"]


@dataclasses.dataclass
class LiveTick:
    """What one tick produced (world frame)."""

    t: float
    bar_feedback: np.ndarray  # eq. 4 per bar [N], (B, 3)
    bar_reaction: np.ndarray  # exact reaction per bar [N], (B, 3)
    string_taut: np.ndarray  # (S,)
    puppet_stepped: bool  # True on the tick that completed a puppet step


class LiveMarionette:
    """Steps a marionette one string step at a time.

    Args:
        model: the marionette (its scene's bars give the poses of bars no device drives).
    """

    def __init__(self, model: MarionetteModel):
        self.model = model
        self.solver = SolverMarionette(model)
        self.state = model.state()
        self._next = model.state()
        self.control = model.control()
        self.tick = 0
        n, s, b = model.substeps, model.strings.string_count, max(model.bar_count, 1)
        # One chunk per string-step index; the first chunk's warm-up loads every module.
        self._chunks = [CapturedChunk(lambda j=j: self._launch_string_step(j), model.device,
                                      warm_up=self._load_modules if j == 0 else _loaded) for j in range(n)]
        self._top_q = self.control.top_q.numpy()  # host views of the control buffers (CPU)
        self._bar_q = self.control.bar_q.numpy()
        self._bar_qd = self.control.bar_qd.numpy()
        self._feedback = self._next.bar_feedback.numpy()
        self._reaction = self._next.bar_reaction.numpy()
        self._taut = self._next.string_taut.numpy()
        # Where the latest string state is after string step j of a puppet step (host views).
        self._particle_after = [self.solver.string_state_after(self._next, j).particle_q.numpy() for j in range(n)]
        assert self._top_q.shape == (n, s, 3) and self._bar_q.shape == (n, b, 3)

    def reset(self) -> None:
        """Back to the scene's rest state at time 0 (the captured graphs are kept)."""
        self.state.assign(self.model.state())
        self._next.assign(self.state)
        self.tick = 0

    def _load_modules(self) -> None:
        """One eager puppet step loads every module (none may compile while capturing); then back to rest."""
        self.solver.step(self.state, self._next, self.control)
        self.reset()

    def _launch_string_step(self, j: int) -> None:
        """The launches of tick ``j`` of a puppet step: string step ``j``, the puppet step's passes
        around it at the first and last tick (then the result becomes the state)."""
        if j == 0:
            self.model.puppet_solver.eval_kinematics(self.state.puppet)  # the state's body poses, for the view
            self.solver.begin_step(self.state, self._next)
        self.solver.step_string(self.state, self._next, self.control, j)
        if j == self.model.substeps - 1:
            self.solver.end_step(self.state, self._next)
            self.state.assign(self._next)

    def steps(self) -> dict[str, float]:
        """What has run so far: ``string_steps``, ``puppet_steps`` and ``simulated_seconds``."""
        return {"string_steps": self.tick, "puppet_steps": self.tick // self.model.substeps,
                "simulated_seconds": round(self.time, 4)}

    @property
    def time(self) -> float:
        """Simulated time [s] after the ticks run so far."""
        return self.tick * self.model.string_dt

    def latest_particle_q(self) -> np.ndarray:
        """Host view of the string particles after the latest tick [m], ``(P, 3)`` float64 (do not
        keep it: the next ticks overwrite it). Float32 strings give a float64 copy instead."""
        return np.asarray(self._particle_after[(self.tick - 1) % self.model.substeps], dtype=np.float64)

    def latest_string_taut(self) -> np.ndarray:
        """Host view of the taut flags after the latest tick, ``(S,)``."""
        return self._taut[(self.tick - 1) % self.model.substeps]

    def advance(self, tops: np.ndarray, bar_q: np.ndarray, bar_qd: np.ndarray) -> LiveTick:
        """One string step with the string tops ``(S, 3)`` and bar centres/velocities ``(B, 3)`` at its end."""
        j = self.tick % self.model.substeps
        self._top_q[j] = tops
        if self.model.bar_count:
            self._bar_q[j] = bar_q
            self._bar_qd[j] = bar_qd
        self._chunks[j].run()
        self.tick += 1
        return LiveTick(t=self.time, bar_feedback=self._feedback[j].copy(), bar_reaction=self._reaction[j].copy(),
                        string_taut=self._taut[j].copy(), puppet_stepped=j == self.model.substeps - 1)


def make_physics_step(live: LiveMarionette, driven_bar: str | Sequence[str], duration: float, *,
                      feedback: str = "reaction", force_scale: float = 1.0,
                      on_tick: Callable[[LiveTick, dict], None] | None = None, view=None):
    """A world-frame physics callback for the servo loop: the device (or devices) drive bars.

    Args:
        live: the marionette stepped per tick.
        driven_bar: the bar whose centre follows the (mapped) device tip; or a sequence of
            distinct bars, one per device, in the servo loop's device order. Other bars follow
            the scene's trajectories.
        duration: how long the session may run [s]; the scripted bars' inputs are evaluated
            for it beforehand (a spline evaluation per tick would cost a large part of a tick).
        feedback: ``"reaction"`` (the strings' pull on the bar) or ``"eq4"`` (the paper's eq. 4 as
            printed, which spans the whole string length and is large).
        force_scale: multiplies the force before it leaves (the safety filter clamps after).
        on_tick: called each tick with the tick and every bar's pose at its end,
            ``{bar: (position (3,), rotation (3,) XYZ deg)}``.
        view: a :class:`dmarionette.live.view.LiveViewPublisher` given a snapshot whenever one
            is due (a clock read per tick otherwise), or None.

    Returns:
        For one bar (a name): ``step(sample_world, t) -> force_world (3,)`` (wrap with
        ``DeviceMapping.wrap``). For a sequence: ``step(samples_world, t) -> forces_world
        (n, 3)``, row ``i`` the force on bar ``i`` (wrap with ``DeviceMapping.wrap_many``).
    """
    model = live.model
    names = [s.name for s in model.scene.strings]
    bars = model.scene.bars
    several = not isinstance(driven_bar, str)
    driven_names = list(driven_bar) if several else [driven_bar]
    for name in driven_names:
        if name not in model.bar_names:
            raise ValueError(f"driven bar: got {name!r}; expected one of {model.bar_names}")
    if not driven_names or len(set(driven_names)) != len(driven_names):
        raise ValueError(f"driven bars: got {driven_names}; expected distinct bars, one per device")
    if feedback not in ("reaction", "eq4"):
        raise ValueError(f"feedback: got {feedback!r}; expected 'reaction' or 'eq4'")
    driven = [model.bar_names.index(name) for name in driven_names]
    carried = [[i for i, n in enumerate(names) if n in bar.attach] for bar in bars]
    local = [np.array([bar.attach[names[i]] for i in idx]).reshape(-1, 3) for bar, idx in zip(bars, carried)]
    # A device's previous position, for the bar velocity (eq. 4's proxy) as a backward difference:
    # at first the bar's start, where the device's mapping puts its origin and the strings start.
    previous = [np.asarray(bars[b].trajectory.pose(np.zeros(1))[0][0], dtype=np.float64) for b in driven]
    ticks = int(np.ceil(duration / model.string_dt)) + 2
    tick_times = model.string_dt * np.arange(1, ticks + 1)  # the end of each string step
    scripted = bar_inputs(model, tick_times)
    scripted_angles = [bar.trajectory.angles(tick_times) for bar in bars]

    def step_all(samples, _t: float) -> np.ndarray:
        k = min(live.tick, ticks - 1)  # past the planned duration the scripted bars hold still
        tops, bar_q, bar_qd = scripted[0][k].copy(), scripted[1][k].copy(), scripted[2][k].copy()
        rotations = []
        for i, (b, sample) in enumerate(zip(driven, samples, strict=True)):
            position = np.asarray(sample.position, dtype=np.float64)
            velocity = (position - previous[i]) / model.string_dt
            previous[i] = position
            # The rotation as the session records it (XYZ Euler angles), so that a replay drives the
            # bar with the very matrix the live step used (the round trip changes it by rounding only).
            rotation = euler_to_matrix(matrix_to_euler(sample.rotation))
            rotations.append(rotation)
            bar_q[b], bar_qd[b] = position, velocity
            tops[carried[b]] = bar_attach_points(position, rotation, local[b])
        tick = live.advance(tops, bar_q, bar_qd)
        if on_tick is not None:
            poses = {name: (bar_q[b], scripted_angles[b][k]) for b, name in enumerate(model.bar_names)}
            for b, rotation in zip(driven, rotations):
                poses[model.bar_names[b]] = (bar_q[b], matrix_to_euler(rotation))
            on_tick(tick, poses)
        if view is not None and view.due():
            all_rotations = scripted_rotations(scripted_angles, k)
            for b, rotation in zip(driven, rotations):
                all_rotations[b] = rotation
            view.publish(live, bar_q, all_rotations, tick.bar_reaction)
        force = tick.bar_reaction[driven] if feedback == "reaction" else tick.bar_feedback[driven]
        return force_scale * force

    if several:
        return step_all

    def step(sample, t: float) -> np.ndarray:
        return step_all((sample,), t)[0]

    return step


def _loaded() -> None:
    """The warm-up of the chunks after the first: their modules are loaded already."""
