"""Refuses settings the simulator cannot run, with a clear message.

:func:`check_marionette_settings` is meant to be called where a marionette is built
(``MarionetteModel.__init__``); :func:`check_string_settings`
where strings are built from a scene (``StringModel.from_scene``, or at the end of
``scene_from_table``). Every refusal comes from a measurement in ``tests/marionette/test_hard_cases*.py``:

- **float32 strings at a string step below 1e-4 s** (:func:`check_string_settings`).

- **a tied string with ``tie_stiffness = 0``**: the coupling hands the puppet the mean
  string force as an anchor offset ``F / k`` (``kernels/string_body_coupling.py``,
  ``apply_string_forces_to_anchors``), so ``k = 0`` gives ``0 / 0 = NaN`` and the whole
  puppet becomes NaN on the first step (measured). A string that should not pull is
  left untied (no ``body_point``).
- (**no longer refused: a long puppet step under several string steps.** With the tie path
  extrapolated as ``x + H v`` the energy of the motion grew below 25 Hz (+0.002 J at 20 Hz
  up to +135 J at 1 Hz, the ``hanging`` sway at string_hz = 1000), so ``puppet_hz >= 25``
  was required with ``n > 1``. With the path from a trial puppet step
  (``kernels/string_body_coupling.py``) the same sway, and with still bars, stays below the
  bars' work down to 10 Hz (largest excess over 6 s: -0.024 J at 20 Hz, -0.029 J at 15 Hz,
  -0.019 J at 10 Hz) and blows up at 5 Hz (+1,456 J), which the 10 Hz minimum below refuses.)
- (**no longer refused: tension-only strings under a slower puppet**, ``[effects]
  tension_only = true`` with ``string_hz / puppet_hz`` rounding to more than 1. With the
  ``x + H v`` tie path the coupling pumped energy in when a string went slack and taut
  within a puppet step: with still bars the puppet did not settle (1.3 mm/s after 6 s), a
  shoulder thrown into its limit gained 0.62 J, on 10x stiffer strings the puppet was
  pumped 13 cm up in 4 s; so ``puppet_hz = string_hz`` was required. With the trial-step
  path, at 30 Hz: still bars settle (1.3e-3 mm/s after 6 s), the thrown shoulder loses
  0.14 J, the 10x puppet settles within 3 mm of its start, and every hard case of
  ``tests/marionette/test_hard_cases*.py`` run with tension-only strings stays within its energy bound
  (``tests/marionette/test_tension_only_marionette.py`` keeps three of them).)
- **any puppet step longer than 0.1 s**: measured with the puppet at the string rate
  (``n = 1``): excess -0.038 J at 10 Hz, but thousands of joules and more within 10 s at
  4 Hz (string particles metres below the ground); under 1 kHz strings -0.019 J at 10 Hz,
  +1,456 J at 5 Hz (the sway, 6 s). So ``puppet_hz >= 10`` always.
"""

from __future__ import annotations

from dmarionette.scene.fields import SceneError

__all__ = ["MAX_FLOAT32_STRING_HZ", "MIN_PUPPET_HZ", "check_marionette_settings",
           "check_string_settings"]

MIN_PUPPET_HZ = 10.0
"""Lowest puppet rate [Hz] accepted (measured energy-consistent at 10 Hz, with the puppet at the
string rate and under 1 kHz strings; blowing up at 4 Hz and 5 Hz respectively)."""

MAX_FLOAT32_STRING_HZ = 1.0e4
"""Highest string rate [Hz] at which float32 strings were measured to track float64 (see the module doc)."""


def check_string_settings(scene) -> None:
    """Raises :class:`SceneError` for string settings that cannot work (any scene, with or
    without a puppet): float32 with a string step so small that a step's position
    increment ``h v`` nears float32's resolution at the scene's scale (``1.2e-7 m`` at 1 m).

    Measured on the ``strings`` scene swaying at 5 Hz (top speed 1.6 m/s), largest
    float32 - float64 particle gap: 1.9e-7 m after 0.2 s at 1 kHz, 3.2e-6 m after 0.5 s at
    10 kHz, 1.1e-4 m after 0.5 s at 100 kHz (growing: 1 mm within a 5-s scene), 2.6e-4 m
    after only 0.05 s at 1 MHz.
    """
    if scene.precision == "float32" and scene.string_hz > MAX_FLOAT32_STRING_HZ:
        raise SceneError(f"{scene.source}: [rates]", "string_hz", scene.string_hz,
                         f"<= {MAX_FLOAT32_STRING_HZ:g} Hz with [solver] precision = \"float32\" (a step of "
                         f"{1.0 / scene.string_hz:g} s moves a particle by less than float32 resolves at 1 m, "
                         "and the strings drift from the float64 answer); use precision = \"float64\"")


def check_marionette_settings(scene) -> None:
    """Raises :class:`SceneError` (a ``ValueError``) for settings a marionette cannot run.

    Args:
        scene: a loaded :class:`~dmarionette.scene.scene.Scene` with a ``[puppet]``.
    """
    check_string_settings(scene)
    source = scene.source
    if scene.puppet_hz < MIN_PUPPET_HZ:
        raise SceneError(f"{source}: [rates]", "puppet_hz", scene.puppet_hz,
                         f">= {MIN_PUPPET_HZ:g} Hz (a puppet step above {1.0 / MIN_PUPPET_HZ:g} s lets the "
                         "string-body coupling blow up: measured at 4 Hz); raise puppet_hz (and string_hz)")
    for spec, point in zip(scene.strings, scene.string_body_points):
        if point is not None and not spec.tie_stiffness > 0.0:
            raise SceneError(f"{source}: [[strings]] {spec.name!r}", "tie_stiffness", spec.tie_stiffness,
                             "> 0 N/m for a string tied to a body point (the coupling divides the string force "
                             "by it); to have a string that does not pull, leave out its body_point")
