"""Knots bounded to the device workspace: a smooth squashing map from free variables ``z``.

The workspace is a hard limit of the authored motion, not a penalty: every free position
coordinate of a knot after t = 0 is

    value = start + a * sin(z),

so it can never leave ``[start - a, start + a]`` (MINUIT's transform of a doubly bounded
parameter, James & Roos 1975: its slope fades to 0 at the bound too, but it reaches the bound at
a finite ``z`` where ``tanh`` needs an infinite one, and past it the value turns back, so a solver
that steps onto or past the bound can step off it again). The bar *path* between knots is a linear
combination of the knot values with weights ``w_j(t)`` summing to one (the Hermite spline of
:mod:`fitting.bar_spline` is linear in its values); with the first knot held at the start,
``path(t) - start = sum_{j >= 1} w_j(t) (p_j - start)``, so ``|path(t) - start| <= L a`` with
``L = max_t sum_{j >= 1} |w_j(t)|`` over the rollout's string-step times (the spline's
overshoot factor, 1.07 to 1.25 for evenly spaced knots). Choosing ``a = half / L`` (``half``
the workspace's half-width on that axis around the bar's start) keeps the whole path inside
the box, at every string step, exactly.

Deviation, deliberate: the knots are confined to the box shrunk by ``L``, so the part of
the workspace the spline reaches only by overshooting between knots is given up. An
asymmetric box (start not at its centre) is used as the symmetric box of its smaller
half-width.

Angles and positions without a device are unbounded: ``y = scale * z`` (0.1 rad, 5 cm).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .bar_spline import BarParameterisation, HermiteSpans

jax.config.update("jax_enable_x64", True)

__all__ = ["BoundedKnots", "overshoot_factor"]

POSITION_SCALE = 0.05  # [m] per unit of z, unbounded positions
ANGLE_SCALE = 0.1      # [rad] per unit of z
_INSIDE = 1.0 - 1e-9   # the bound a little inside the box, so rounding cannot cross it
_START_LIMIT = 0.95    # an initial knot at or past the bound starts at 95 % of it


def overshoot_factor(knot_times, times) -> float:
    """``L = max_t sum_{j >= 1} |w_j(t)|`` of the Hermite spline through ``knot_times`` at ``times``.

    Args:
        knot_times: ``(K,)`` [s]; times: ``(T,)`` [s], where the path is sampled.

    Returns:
        The factor by which the path's offset from the first knot can exceed the largest
        offset of the other knots (>= 1 when a query reaches the last knot's span end).
    """
    knots = np.asarray(knot_times, dtype=np.float64)
    if len(knots) < 2:
        return 1.0
    spans = HermiteSpans.make(knots, times)
    values = np.eye(len(knots))  # the spline of each knot's unit value: its weight w_j(t)
    tangents = np.zeros_like(values)  # Catmull-Rom inside, zero at the ends (bar_spline._tangents)
    if len(knots) > 2:
        tangents[1:-1] = (values[2:] - values[:-2]) / (knots[2:] - knots[:-2])[:, None]
    i, u, span = spans.index, spans.u[:, None], spans.span[:, None]
    weights = ((2 * u**3 - 3 * u**2 + 1) * values[i] + (u**3 - 2 * u**2 + u) * span * tangents[i]
               + (-2 * u**3 + 3 * u**2) * values[i + 1] + (u**3 - u**2) * span * tangents[i + 1])
    return float(max(1.0, np.abs(weights[:, 1:]).sum(axis=1).max()))


class BoundedKnots:
    """The map from a flat vector ``z`` to :class:`BarParameterisation`'s ``y`` (JAX-traceable).

    Args:
        param: the authored bars' parameterisation.
        boxes: bar name -> ``(lo, hi)`` world workspace box [m] ``(3,)`` each, or None (no device).

    Attributes:
        size: ``n``, the length of ``z``.
        bounds: bar name -> ``(K - 1, F)`` half-width ``a`` [m] of each bounded coordinate
            (NaN where unbounded: angles, or no device).
        factors: bar name -> the overshoot factor ``L`` of its knots.
    """

    def __init__(self, param: BarParameterisation, boxes: dict | None):
        self.param = param
        self.layout = []
        self.bounds, self.factors = {}, {}
        offset = 0
        for a in param.authored:
            shape = (len(a["knots"]) - 1, len(a["free"]))
            bound = np.full(shape, np.nan)
            start = a["initial"][0, :3]
            if boxes and a["name"] in boxes:
                lo, hi = (np.asarray(v, dtype=np.float64) for v in boxes[a["name"]])
                half = np.minimum(hi - start, start - lo)
                if np.any(half <= 0.0):
                    raise ValueError(f"bar {a['name']!r}: its start {start.tolist()} m is not inside the device "
                                     f"workspace box {lo.tolist()} .. {hi.tolist()} m")
                factor = overshoot_factor(a["knots"], param.times)
                self.factors[a["name"]] = factor
                for column, dof in enumerate(a["free"]):
                    if dof < 3:
                        bound[:, column] = _INSIDE * half[dof] / factor
            self.bounds[a["name"]] = bound
            self.layout.append((a["name"], offset, shape, a["initial"][1:, a["free"]].copy(),
                                np.where(a["free"] < 3, start[np.minimum(a["free"], 2)], 0.0)))
            offset += int(np.prod(shape))
        self.size = offset

    def y(self, z) -> dict[str, jnp.ndarray]:
        """``z (n,) -> y``: bar name -> ``(K - 1, F)`` offsets from the initial knots [m, rad]."""
        z = jnp.asarray(z)
        out = {}
        for name, offset, shape, initial, start in self.layout:
            part = z[offset:offset + int(np.prod(shape))].reshape(shape)
            bound = self.bounds[name]
            free = self.param.authored[[a["name"] for a in self.param.authored].index(name)]["free"]
            unbounded = np.where(free < 3, POSITION_SCALE, ANGLE_SCALE) * part
            bounded = start + np.nan_to_num(bound) * jnp.sin(part) - initial
            out[name] = jnp.where(np.isnan(bound), unbounded, bounded)
        return out

    def z_of_y(self, y: dict) -> np.ndarray:
        """The ``z`` of knots ``y`` (a bounded coordinate past 95 % of its bound is moved to 95 %)."""
        z = np.zeros(self.size)
        for name, offset, shape, initial, start in self.layout:
            free = self.param.authored[[a["name"] for a in self.param.authored].index(name)]["free"]
            values = np.asarray(y[name], dtype=np.float64)
            bound = self.bounds[name]
            unbounded = values / np.where(free < 3, POSITION_SCALE, ANGLE_SCALE)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.clip((initial + values - start) / bound, -_START_LIMIT, _START_LIMIT)
            z[offset:offset + int(np.prod(shape))] = np.where(np.isnan(bound), unbounded, np.arcsin(ratio)).ravel()
        return z

    def z0(self) -> np.ndarray:
        """``z`` of the initial knots (the scene's own bar motion, pulled inside the bounds)."""
        return self.z_of_y(self.param.initial())

    def saturation(self, z) -> dict[str, np.ndarray]:
        """Per bar ``(K - 1, F)``: ``|sin z|`` of bounded coordinates (1 = on the bound), NaN elsewhere."""
        z = np.asarray(z)
        out = {}
        for name, offset, shape, _, _ in self.layout:
            part = np.abs(np.sin(z[offset:offset + int(np.prod(shape))].reshape(shape)))
            out[name] = np.where(np.isnan(self.bounds[name]), np.nan, part)
        return out

    def names(self) -> list[str]:
        """A label per coordinate of ``z``: ``"hand.x@0.5s"``."""
        labels = []
        for name, _, shape, _, _ in self.layout:
            a = self.param.authored[[b["name"] for b in self.param.authored].index(name)]
            dofs = ["x", "y", "z", "rx", "ry", "rz"]
            for k in range(shape[0]):
                labels += [f"{name}.{dofs[d]}@{a['knots'][k + 1]:g}s" for d in a["free"]]
        return labels
