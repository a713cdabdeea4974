"""The control bars' motion in JAX: knots -> the rollout's bar inputs, differentiably.

This reproduces :class:`dmarionette.scene.bars.BarTrajectory` operation for operation (C1
cubic Hermite through the knots, Catmull-Rom tangents inside, zero tangents at both ends,
the pose held outside the knots, XYZ Euler angles ``R = Rz Ry Rx``), so that the optimised
knots written as ``[[bars.NAME.keyframes]]`` of a scene replay the same bar motion in
``dmarionette simulate`` (tested to 1e-12).

Knot *times* are fixed (they set which span each query time falls in); knot positions and
angles are the differentiable values. The span lookup is therefore done once, in NumPy.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dmarionette.scene.bars import BarTrajectory

from .keyframes import BAR_DOFS, AuthorSpec

jax.config.update("jax_enable_x64", True)

__all__ = ["BarParameterisation", "HermiteSpans", "euler_to_matrix", "hermite_evaluate"]


@dataclasses.dataclass(frozen=True)
class HermiteSpans:
    """Where each query time falls among the knots (fixed once the knot times are).

    Attributes:
        knot_times: ``(K,)`` [s].
        index: span of each query time, ``(T,)``; u: position in the span in [0, 1], ``(T,)``.
        span: span length [s], ``(T,)``; held: query outside the knots (rate 0), ``(T,)``.
    """

    knot_times: np.ndarray
    index: np.ndarray
    u: np.ndarray
    span: np.ndarray
    held: np.ndarray

    @classmethod
    def make(cls, knot_times, times) -> HermiteSpans:
        """As ``BarTrajectory._evaluate`` finds the span of each of ``times``."""
        t = np.asarray(knot_times, dtype=np.float64)
        times = np.asarray(times, dtype=np.float64)
        query = np.clip(times, t[0], t[-1])
        held = (times < t[0]) | (times > t[-1])
        if len(t) == 1:
            zeros = np.zeros(len(query))
            return cls(t, np.zeros(len(query), dtype=np.int64), zeros, zeros + 1.0, np.ones(len(query), bool))
        i = np.clip(np.searchsorted(t, query, side="right") - 1, 0, len(t) - 2)
        span = t[i + 1] - t[i]
        return cls(t, i, (query - t[i]) / span, span, held)


def _tangents(knot_times: np.ndarray, values: jnp.ndarray) -> jnp.ndarray:
    """Catmull-Rom tangents inside, zero at both ends (``BarTrajectory._tangents``)."""
    if len(knot_times) <= 2:
        return jnp.zeros_like(values)
    inner = (values[2:] - values[:-2]) / jnp.asarray(knot_times[2:] - knot_times[:-2])[:, None]
    zero = jnp.zeros_like(values[:1])
    return jnp.concatenate([zero, inner, zero])


def hermite_evaluate(spans: HermiteSpans, values: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Value and rate of the spline through ``values`` ``(K, C)`` at the query times, ``(T, C)`` each."""
    if len(spans.knot_times) == 1:
        value = jnp.broadcast_to(values[0], (len(spans.u), values.shape[1]))
        return value, jnp.zeros_like(value)
    m = _tangents(spans.knot_times, values)
    i = spans.index
    span = jnp.asarray(spans.span)[:, None]
    u = jnp.asarray(spans.u)[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    value = h00 * values[i] + h10 * span * m[i] + h01 * values[i + 1] + h11 * span * m[i + 1]
    d00, d10, d01, d11 = 6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1, -6 * u**2 + 6 * u, 3 * u**2 - 2 * u
    rate = (d00 * values[i] + d01 * values[i + 1]) / span + d10 * m[i] + d11 * m[i + 1]
    rate = jnp.where(jnp.asarray(spans.held)[:, None], 0.0, rate)
    return value, rate


def hermite_acceleration_residuals(knot_times: np.ndarray, values: jnp.ndarray) -> jnp.ndarray:
    """Residuals ``r`` with ``sum(r^2) = \\int |d^2 x/dt^2|^2 dt`` over the knots, exactly.

    On a span of length ``s`` the Hermite cubic's acceleration is linear, from ``a0`` to
    ``a1``; ``\\int a^2 = s (a0^2 + a0 a1 + a1^2) / 3 = s/3 (a0 + a1/2)^2 + s/4 a1^2``.
    Returns ``(2 (K-1), C)``.
    """
    t = np.asarray(knot_times, dtype=np.float64)
    if len(t) < 2:
        return jnp.zeros((0, values.shape[1]))
    m = _tangents(t, values)
    s = jnp.asarray(np.diff(t))[:, None]
    p0, p1, m0, m1 = values[:-1], values[1:], m[:-1], m[1:]
    a0 = (-6 * p0 - 4 * s * m0 + 6 * p1 - 2 * s * m1) / s**2
    a1 = (6 * p0 + 2 * s * m0 - 6 * p1 + 4 * s * m1) / s**2
    return jnp.concatenate([jnp.sqrt(s / 3) * (a0 + 0.5 * a1), jnp.sqrt(s / 4) * a1])


def euler_to_matrix(angles_deg: jnp.ndarray) -> jnp.ndarray:
    """``Rz Ry Rx`` from XYZ angles in degrees, ``(..., 3) -> (..., 3, 3)`` (as the NumPy one)."""
    a = jnp.radians(angles_deg)
    cx, cy, cz = jnp.cos(a[..., 0]), jnp.cos(a[..., 1]), jnp.cos(a[..., 2])
    sx, sy, sz = jnp.sin(a[..., 0]), jnp.sin(a[..., 1]), jnp.sin(a[..., 2])
    rows = [
        [cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz],
        [cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz],
        [-sy, sx * cy, cx * cy],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


class BarParameterisation:
    """The authored bars' knots as optimisation variables, and the rollout inputs they give.

    The variables ``y`` are a dict ``bar name -> (K - 1, F)`` array: the free coordinates
    (``F`` of :data:`BAR_DOFS`, in the order of that tuple) of every knot after the first,
    as offsets from the initial knots, positions in metres and angles in radians (so that
    both have a similar scale for the solver). The first knot (t = 0) is held at the scene's
    start pose: the marionette's strings are built straight from it.

    Args:
        spec: the keyframes file (scene, bars, duration).
        model: the marionette built from ``spec.scene`` (string order, bars, rates).
        puppet_steps: puppet steps of the rollout; the inputs cover its string steps,
            at times ``string_dt * (1, ..., puppet_steps * substeps)``.
    """

    def __init__(self, spec: AuthorSpec, model, puppet_steps: int):
        scene = spec.scene
        self.spec = spec
        self.string_dt = model.string_dt
        self.times = model.string_dt * np.arange(1, puppet_steps * model.substeps + 1)
        self.bar_names = [b.name for b in scene.bars]
        string_names = [s.name for s in model.strings.specs]
        self.string_count = len(string_names)
        rest_tops = np.array([s.top for s in model.strings.specs])
        # Everything the optimiser does not move: the scene's own motion, evaluated once.
        self.fixed_tops = scene.top_positions(rest_tops, self.times)
        b_count = max(len(self.bar_names), 1)
        self.fixed_bar_q = np.zeros((len(self.times), b_count, 3))
        self.fixed_bar_qd = np.zeros_like(self.fixed_bar_q)
        for b, bar in enumerate(scene.bars):
            self.fixed_bar_q[:, b], self.fixed_bar_qd[:, b], _ = bar.trajectory.pose(self.times)
        self.authored = []
        for freedom in spec.bars:
            b = self.bar_names.index(freedom.name)
            bar = scene.bars[b]
            knots = np.asarray(freedom.knots)
            initial = np.concatenate([bar.trajectory.pose(knots)[0], bar.trajectory.angles(knots)], axis=1)
            carried = [i for i, n in enumerate(string_names) if n in bar.attach]
            self.authored.append(dict(
                name=freedom.name, index=b, knots=knots, initial=initial,
                free=np.array([BAR_DOFS.index(d) for d in freedom.free]),
                spans=HermiteSpans.make(knots, self.times), strings=np.array(carried, dtype=np.int64),
                local=np.array([bar.attach[string_names[i]] for i in carried], dtype=np.float64)))

    def initial(self) -> dict[str, jnp.ndarray]:
        """``y`` of the initial knots (all offsets zero)."""
        return {a["name"]: jnp.zeros((len(a["knots"]) - 1, len(a["free"]))) for a in self.authored}

    def y_scale(self, position: float = 0.05, angle: float = 0.1) -> dict[str, np.ndarray]:
        """A typical knot change per coordinate of ``y`` (5 cm, 0.1 rad): the solver steps in
        these units, so that its first (identity-Hessian) steps are of a sensible size."""
        return {a["name"]: np.broadcast_to(np.where(a["free"] >= 3, angle, position),
                                           (len(a["knots"]) - 1, len(a["free"]))).copy() for a in self.authored}

    def knot_values(self, y: dict[str, jnp.ndarray]) -> dict[str, jnp.ndarray]:
        """Knot values ``(K, 6)`` per authored bar: positions [m], XYZ angles [deg]."""
        out = {}
        for a in self.authored:
            scale = np.where(a["free"] >= 3, 180.0 / np.pi, 1.0)  # angles: radians -> degrees
            offset = jnp.zeros_like(jnp.asarray(a["initial"])).at[1:, a["free"]].set(y[a["name"]] * scale)
            out[a["name"]] = jnp.asarray(a["initial"]) + offset
        return out

    def trajectories(self, y: dict[str, jnp.ndarray]) -> dict[str, BarTrajectory]:
        """The authored bars as :class:`BarTrajectory` (NumPy), what a scene file stores."""
        values = self.knot_values(y)
        return {a["name"]: BarTrajectory(a["knots"].copy(), np.asarray(values[a["name"]][:, :3]),
                                         np.asarray(values[a["name"]][:, 3:])) for a in self.authored}

    def rollout_inputs(self, y: dict[str, jnp.ndarray]) -> dict[str, jnp.ndarray]:
        """``top_q (T, S, 3)``, ``bar_q``, ``bar_qd (T, B, 3)`` at the string-step times."""
        tops = jnp.asarray(self.fixed_tops)
        bar_q = jnp.asarray(self.fixed_bar_q)
        bar_qd = jnp.asarray(self.fixed_bar_qd)
        values = self.knot_values(y)
        for a in self.authored:
            position, velocity = hermite_evaluate(a["spans"], values[a["name"]][:, :3])
            angles, _ = hermite_evaluate(a["spans"], values[a["name"]][:, 3:])
            rotation = euler_to_matrix(angles)
            attach = position[:, None, :] + jnp.einsum("tij,sj->tsi", rotation, jnp.asarray(a["local"]))
            tops = tops.at[:, a["strings"]].set(attach)
            bar_q = bar_q.at[:, a["index"]].set(position)
            bar_qd = bar_qd.at[:, a["index"]].set(velocity)
        return {"top_q": tops, "bar_q": bar_q, "bar_qd": bar_qd}

    def bar_paths(self, y: dict[str, jnp.ndarray]) -> dict[str, tuple[jnp.ndarray, jnp.ndarray]]:
        """Per authored bar: centre position [m] ``(T, 3)`` and knot values ``(K, 6)``."""
        values = self.knot_values(y)
        return {a["name"]: (hermite_evaluate(a["spans"], values[a["name"]][:, :3])[0], values[a["name"]])
                for a in self.authored}

    def acceleration_residuals(self, y: dict[str, jnp.ndarray]) -> jnp.ndarray:
        """``sqrt``-weighted accelerations of the authored bars' free coordinates: positions
        [m/s^2] and angles [rad/s^2]; ``sum(r^2) = \\int (|a|^2 + |alpha|^2) dt`` (exact for the
        Hermite spline). The held coordinates' accelerations are constants, left out."""
        values = self.knot_values(y)
        parts = []
        for a in self.authored:
            v = values[a["name"]]
            v = jnp.concatenate([v[:, :3], jnp.radians(v[:, 3:])], axis=1)[:, a["free"]]
            parts.append(hermite_acceleration_residuals(a["knots"], v).ravel())
        return jnp.concatenate(parts)
