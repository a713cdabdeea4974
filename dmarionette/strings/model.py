"""Model, State and Control of a set of particle strings (paper §2.2).

A string is a chain of ``n >= 2`` particles; particle 0 (the top) follows an attach
point on a control bar, the others are simulated. Strings may have different particle
counts; particles are stored string after string, ``string_start[s] .. string_start[s+1]-1``.

Scene constants are given per whole string (so that they mean the same thing at any
particle count) and converted here to the per-segment / per-particle constants of the
paper's formulas:

=====================  ===============================  ==============================
scene key              meaning                           kernel constant (n particles,
                                                         segment rest length d = L/(n-1))
=====================  ===============================  ==============================
``length`` L           unstretched length [m]            ``d = L/(n-1)``
``mass``               string mass [kg]                  particle mass ``mass/(n-1)``
``stiffness`` k        end-to-end stiffness [N/m]        ``k_s = k (n-1)``
``internal_friction``  end-to-end damping [N s/m]        ``k_f = c (n-1)``
``air_drag``           per metre [N s/m/m]               ``k_air = air_drag d``
``ground_*``           per metre of string lying down    ``x d``
``tie_stiffness``      eq. 2 ``k`` [N/m]                 as is
``tie_damping``        eq. 2 ``k_d`` [N s/m]             as is
=====================  ===============================  ==============================
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import warp as wp

from dmarionette.kernels.string_model_arrays import string_model_arrays
from dmarionette.kernels.string_state_arrays import (
    CONTROL_FIELDS, STATE_FIELDS, string_control_arrays_type, string_state_arrays_type, struct_of_arrays,
)
from dmarionette.scene.strings import StringEffects, StringSpec

__all__ = [
    "StringControl",
    "StringEffects",
    "StringModel",
    "StringSpec",
    "StringState",
    "build_string_model",
    "string_energy",
]

_FLOAT_TYPES = {"float64": wp.float64, "float32": wp.float32}


class StringModel:
    """Constants of a set of strings, as Warp arrays on ``device``.

    Attributes:
        string_count: number of strings ``S``.
        particle_count: total number of particles ``P``.
        scalar: the float type of all arrays (``wp.float64`` by default).
        effects: the :class:`StringEffects` compiled into this model's kernels.
        string_names: names of the strings, shape ``(S,)``.
        string_start: first particle of each string, and ``P`` at the end, shape ``(S+1,)``.
        particle_string: string of each particle, shape ``(P,)``.
        particle_mass: particle mass [kg], shape ``(P,)``.
        string_stiffness: segment spring stiffness ``k_s`` [N/m], shape ``(S,)``.
        string_rest_length: segment rest length ``d`` [m], shape ``(S,)``.
        string_internal_friction: ``k_f`` [N s/m], shape ``(S,)``.
        string_air_drag: ``k_air`` per particle [N s/m], shape ``(S,)``.
        string_ground_stiffness: repulsion penalty per particle [N/m], shape ``(S,)``.
        string_ground_absorption: absorption damper per particle [N s/m], shape ``(S,)``.
        string_ground_friction: ``k_ground`` per particle [N s/m], shape ``(S,)``.
        string_tie_stiffness: eq. 2 ``k`` [N/m], shape ``(S,)``.
        string_tie_damping: eq. 2 ``k_d`` [N s/m], shape ``(S,)``.
        string_tied: 1 where the last particle is tied to a body point, else 0, shape ``(S,)``.
        string_taut_distance: first-to-last distance above which a string is taut [m], ``(S,)``.
        gravity: gravitational acceleration [m/s^2], a 3-vector.
        ground_height: height of the ground plane ``y`` [m].
        arrays: the above (``string_start`` .. ``ground_height``) as one kernel argument, a
            ``StringModelArrays`` (``kernels/string_model_arrays``) holding these same arrays; it
            also holds each array's gradient as it was when built: after changing an array's
            ``requires_grad``, call :meth:`refresh_arrays` (a captured launch checks them and raises).
    """

    def __init__(self, specs: Sequence[StringSpec], *, effects: StringEffects, gravity, ground_height: float,
                 precision: str = "float64", device=None, requires_grad: bool = False):
        if not specs:
            raise ValueError("a string model needs at least one string")
        if precision not in _FLOAT_TYPES:
            raise ValueError(f"precision: got {precision!r}; expected one of {sorted(_FLOAT_TYPES)}")
        self.device = wp.get_device(device)
        self.scalar = _FLOAT_TYPES[precision]
        self.precision = precision
        self.vec3 = wp.types.vector(3, self.scalar)
        self.mat33 = wp.types.matrix((3, 3), self.scalar)
        self.effects = effects
        self.requires_grad = requires_grad
        self.specs = tuple(specs)
        self.string_names = [s.name for s in specs]
        self.string_count = len(specs)
        counts = np.array([s.particle_count for s in specs], dtype=np.int32)
        if np.any(counts < 2):
            raise ValueError(f"every string needs at least 2 particles; got counts {counts.tolist()}")
        start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self.particle_count = int(start[-1])
        self.string_particle_count = counts
        self.string_start_np = start
        self.gravity = self.vec3(*[float(g) for g in gravity])
        self.ground_height = self.scalar(float(ground_height))

        segments = counts - 1
        rest = np.array([s.length for s in specs]) / segments
        mass = np.concatenate(
            [np.full(n, s.mass / (n - 1)) for s, n in zip(specs, counts)]
        )
        for s, first in zip(specs, start[1:]):
            mass[first - 1] += s.load_mass
        per_string = {
            "string_stiffness": [s.stiffness for s in specs] * segments,
            "string_rest_length": rest,
            "string_internal_friction": [s.internal_friction for s in specs] * segments,
            "string_air_drag": np.array([s.air_drag for s in specs]) * rest,
            "string_ground_stiffness": np.array([s.ground_stiffness for s in specs]) * rest,
            "string_ground_absorption": np.array([s.ground_absorption for s in specs]) * rest,
            "string_ground_friction": np.array([s.ground_friction for s in specs]) * rest,
            "string_tie_stiffness": [s.tie_stiffness for s in specs],
            "string_tie_damping": [s.tie_damping for s in specs],
            "string_tied": [1.0 if s.tied else 0.0 for s in specs],
            "string_taut_distance": [s.taut_fraction * s.length for s in specs],
        }
        with wp.ScopedDevice(self.device):
            self.string_start = wp.array(start, dtype=wp.int32)
            self.particle_string = wp.array(np.repeat(np.arange(len(specs)), counts), dtype=wp.int32)
            self.particle_mass = self._array(mass)
            for name, values in per_string.items():
                setattr(self, name, self._array(np.asarray(values, dtype=np.float64)))
        self.arrays = string_model_arrays(self)

    def refresh_arrays(self) -> None:
        """Rebuilds :attr:`arrays` from the model's arrays (after their ``requires_grad`` changed)."""
        self.arrays = string_model_arrays(self)

    @classmethod
    def from_scene(cls, scene, *, device=None, requires_grad: bool = False, precision: str | None = None,
                   effects: StringEffects | None = None) -> StringModel:
        """The strings of a :class:`~dmarionette.scene.scene.Scene` (overrides for tests and benchmarks)."""
        return cls(scene.strings, effects=scene.effects if effects is None else effects, gravity=scene.gravity,
                   ground_height=scene.ground_height, precision=scene.precision if precision is None else precision,
                   device=device, requires_grad=requires_grad)
    def _array(self, values: np.ndarray) -> wp.array:
        return wp.array(values, dtype=self.scalar, requires_grad=self.requires_grad)

    def initial_positions(self) -> np.ndarray:
        """Particles evenly spaced on the straight line from each string's top to its bottom, ``(P, 3)``."""
        pieces = []
        for spec, n in zip(self.specs, self.string_particle_count):
            u = np.linspace(0.0, 1.0, int(n))[:, None]
            pieces.append((1.0 - u) * np.array(spec.top) + u * np.array(spec.bottom))
        return np.concatenate(pieces)

    def tie_points(self) -> np.ndarray:
        """The fixed world points the tied strings hold on to (the bottom otherwise), ``(S, 3)``."""
        return np.array([s.tie_point if s.tie_point is not None else s.bottom for s in self.specs])

    def state(self, positions: np.ndarray | None = None, velocities: np.ndarray | None = None) -> StringState:
        """A new state, by default at :meth:`initial_positions` and at rest."""
        q = self.initial_positions() if positions is None else np.asarray(positions, dtype=np.float64)
        qd = np.zeros_like(q) if velocities is None else np.asarray(velocities, dtype=np.float64)
        return StringState(self, q, qd)

    def control(self) -> StringControl:
        """A control holding the tops where they are now and the ties at their points, at rest."""
        tops = np.array([s.top for s in self.specs])
        return StringControl.from_numpy(self, tops, self.tie_points(), np.zeros((self.string_count, 3)))


class StringState:
    """What evolves.

    Attributes:
        particle_q: particle positions [m], shape ``(P,)`` of vec3.
        particle_qd: particle velocities [m/s], shape ``(P,)`` of vec3.
        tie_force: force of each string's tie on its body point after the step [N] (paper
            eq. 2, ``f_body``; zero for untied strings), shape ``(S,)`` of vec3.
        string_taut: 1 where the string is taut after the step (paper §3.2), shape ``(S,)``.
        arrays: the above as one kernel argument, a ``StringStateArrays``
            (``kernels/string_state_arrays``) holding these same arrays (rebuilt when one of them,
            or its ``.grad``, is replaced).
    """

    def __init__(self, model: StringModel, q: np.ndarray, qd: np.ndarray):
        expected = (model.particle_count, 3)
        for name, value in (("positions", q), ("velocities", qd)):
            if value.shape != expected:
                raise ValueError(f"string state {name}: got shape {value.shape}; expected {expected}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"string state {name}: contains NaN or infinity")
        with wp.ScopedDevice(model.device):
            self.particle_q = wp.array(q, dtype=model.vec3, requires_grad=model.requires_grad)
            self.particle_qd = wp.array(qd, dtype=model.vec3, requires_grad=model.requires_grad)
            self.tie_force = wp.zeros(model.string_count, dtype=model.vec3, requires_grad=model.requires_grad)
            self.string_taut = wp.zeros(model.string_count, dtype=wp.int32)
        self._arrays = None

    @property
    def arrays(self):
        """This state's arrays as a ``StringStateArrays`` (class doc)."""
        self._arrays = struct_of_arrays(string_state_arrays_type, self, STATE_FIELDS, self._arrays)
        return self._arrays[1]

    def assign(self, other: StringState) -> None:
        """Copies ``other`` into this state (same model)."""
        self.particle_q.assign(other.particle_q)
        self.particle_qd.assign(other.particle_qd)
        self.tie_force.assign(other.tie_force)
        self.string_taut.assign(other.string_taut)


class StringControl:
    """Inputs of a string step.

    Attributes:
        top_q: where each string's top particle must be at the end of the step (its attach
            point on the bar) [m], shape ``(S,)`` of vec3.
        tie_q: position of each tied string's body point at the end of the step [m], ``(S,)``.
        tie_qd: velocity of each tied string's body point [m/s], ``(S,)``.
        arrays: the above as one kernel argument, a ``StringControlArrays``
            (``kernels/string_state_arrays``) holding these same arrays (rebuilt when one of them,
            or its ``.grad``, is replaced).
    """

    def __init__(self, top_q: wp.array, tie_q: wp.array, tie_qd: wp.array):
        self.top_q = top_q
        self.tie_q = tie_q
        self.tie_qd = tie_qd
        self._arrays = None

    @property
    def arrays(self):
        """This control's arrays as a ``StringControlArrays`` (class doc)."""
        self._arrays = struct_of_arrays(string_control_arrays_type, self, CONTROL_FIELDS, self._arrays)
        return self._arrays[1]

    @classmethod
    def from_numpy(cls, model: StringModel, top_q, tie_q, tie_qd) -> StringControl:
        """A control from ``(S, 3)`` arrays of positions [m] and velocities [m/s]."""
        expected = (model.string_count, 3)
        arrays = []
        for name, value in (("top_q", top_q), ("tie_q", tie_q), ("tie_qd", tie_qd)):
            value = np.asarray(value, dtype=np.float64)
            if value.shape != expected or not np.all(np.isfinite(value)):
                raise ValueError(f"string control {name}: expected finite values of shape {expected}; "
                                 f"got shape {value.shape}")
            arrays.append(wp.array(value, dtype=model.vec3, device=model.device,
                                   requires_grad=model.requires_grad))
        return cls(*arrays)


def build_string_model(specs: Sequence[StringSpec], **kwargs) -> StringModel:
    """Builds a :class:`StringModel`; keyword arguments as for its constructor."""
    return StringModel(specs, **kwargs)


def string_energy(model: StringModel, q: np.ndarray, qd: np.ndarray, tie_q: np.ndarray | None = None,
                  strings: range | None = None) -> dict[str, float]:
    """Mechanical energy of the strings [J], from host arrays ``q``, ``qd`` of shape ``(P, 3)``.

    Kinetic energy excludes the kinematic top particles (their motion is imposed). Returns
    ``kinetic``, ``gravity`` (relative to ``y = 0``), ``spring``, ``ground`` (penalty spring
    energy of particles below the ground, when ground contact is on), ``tie`` (the eq. 2
    springs of tied strings, to ``tie_q`` or the model's tie points) and ``total``.
    ``strings``: only these strings (one world of a batched marionette); default all.
    """
    q = np.asarray(q, dtype=np.float64)
    qd = np.asarray(qd, dtype=np.float64)
    strings = range(model.string_count) if strings is None else strings
    start = model.string_start_np
    mass = model.particle_mass.numpy().astype(np.float64)
    free = np.zeros(model.particle_count, dtype=bool)
    for s in strings:
        free[start[s] + 1:start[s + 1]] = True
    kinetic = 0.5 * float(np.sum(mass[free] * np.sum(qd[free] ** 2, axis=1)))
    g = np.array(model.gravity, dtype=np.float64)
    gravity = -float(np.sum(mass[free] * (q[free] @ g))) if model.effects.gravity else 0.0
    k_s = model.string_stiffness.numpy()
    rest = model.string_rest_length.numpy()
    spring = 0.0
    ground = 0.0
    k_ground = model.string_ground_stiffness.numpy()
    for s in strings:
        a, b = start[s], start[s + 1]
        lengths = np.linalg.norm(np.diff(q[a:b], axis=0), axis=1)
        stretch = lengths - rest[s]
        if model.effects.tension_only:  # no energy while slack (``kernels/string_terms``)
            stretch = np.maximum(stretch, 0.0)
        spring += 0.5 * float(k_s[s]) * float(np.sum(stretch**2))
        if model.effects.ground_contact:
            depth = np.maximum(float(model.ground_height) - q[a + 1:b, 1], 0.0)
            ground += 0.5 * float(k_ground[s]) * float(np.sum(depth**2))
    chosen = np.asarray(list(strings), dtype=np.int64)
    points = model.tie_points() if tie_q is None else np.asarray(tie_q, dtype=np.float64)
    last = start[1:] - 1
    stretch = np.sum((points[chosen] - q[last[chosen]]) ** 2, axis=1)
    tie = 0.5 * float(np.sum((model.string_tied.numpy() * model.string_tie_stiffness.numpy())[chosen] * stretch))
    total = kinetic + gravity + spring + ground + tie
    return {"kinetic": kinetic, "gravity": gravity, "spring": spring, "ground": ground, "tie": tie,
            "total": total}
