"""Descriptions of strings and of the string effects a scene switches on (paper §2.2).

Whole-string constants as a scene gives them; :mod:`dmarionette.strings.model` converts
them to the kernels' per-segment constants.
"""

from __future__ import annotations

import dataclasses

__all__ = ["StringEffects", "StringSpec"]


@dataclasses.dataclass(frozen=True)
class StringEffects:
    """Which string effects are compiled into the kernels (the spring is always on)."""

    gravity: bool = True
    internal_friction: bool = True
    air_drag: bool = True
    ground_contact: bool = True
    ground_friction: bool = True
    #: Tension-only segment springs (no push when shorter than the rest length), a deliberate
    #: deviation from the paper's printed spring (``kernels/string_terms``); off by default:
    #: the 30 Hz string-body coupling is not ready for it (refused there by ``settings_check``).
    tension_only: bool = False

    def as_tuple(self) -> tuple[bool, bool, bool, bool, bool]:
        """The switches in kernel order; ground friction needs ground contact."""
        return (
            self.gravity,
            self.internal_friction,
            self.air_drag,
            self.ground_contact,
            self.ground_contact and self.ground_friction,
        )


@dataclasses.dataclass(frozen=True)
class StringSpec:
    """One string as described in a scene (whole-string constants; see the module doc)."""

    name: str
    top: tuple[float, float, float]
    bottom: tuple[float, float, float]
    length: float
    particle_count: int = 50
    mass: float = 0.002
    load_mass: float = 0.0
    stiffness: float = 500.0
    internal_friction: float = 0.5
    air_drag: float = 0.01
    ground_stiffness: float = 2000.0
    ground_absorption: float = 5.0
    ground_friction: float = 2.0
    tied: bool = False
    tie_point: tuple[float, float, float] | None = None
    tie_stiffness: float = 300.0
    tie_damping: float = 3.0
    taut_fraction: float = 0.98
