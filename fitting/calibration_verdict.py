"""Whether a calibration found the constants, and what to say when it did not (docs/calibration.md,
"Honest results").

"Converged" means two things here: the solver met its stopping test, *and* the fit explains the
data, i.e. the residuals are as small as the noise the user gave. The test is the reduced
chi-squared of each target against the given noise scales,
``chi2_c = |r_c|^2 / (m_c - n m_c / m)`` (``r`` the residuals divided by the noise scales):
about 1 when the simulation with the fitted constants reproduces the recording up to the
noise; above :data:`CHI2_LIMIT` the fit does not explain the data (a wrong basin, a model that
cannot reproduce the session, or noise scales set too small). Constants that the data do not
determine (:mod:`fitting.uncertainty`: a numerically null direction of ``J``, or one known to no
better than a factor ``e``) are named, get infinite intervals, and make the run fail with its
own code.

A second test needs no noise scale (:mod:`fitting.residual_whiteness`): the residuals of a fit that
explains the data are white in time; a wrong basin leaves slow, structured ones. Per target, the
pooled lag-1 autocorrelation of the residual channels, in the recording's time order, is compared
with its spread under white noise; above :data:`fitting.residual_whiteness.Z_LIMIT` standard
deviations "the residuals are structured": the fit does not explain the data either.

Exit codes of ``dmarionette calibrate`` (:data:`EXIT_CODES`):

- 0: converged, the fit explains the data, every constant identifiable;
- 2: bad input (``error: ...``, from the command line's checks);
- 3: the solver did not converge, or the fit does not explain the data (reduced chi-squared of
  a target above :data:`CHI2_LIMIT`, or its residuals structured in time);
- 4: the fit explains the data but some constants are not identifiable (infinite intervals).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from .residual_whiteness import Z_LIMIT, lag1_whiteness
from .uncertainty import COMPONENT_LIMIT, GaussNewtonUncertainty

__all__ = ["CHI2_LIMIT", "EXIT_CODES", "EXIT_NOT_EXPLAINED", "EXIT_OK", "EXIT_UNIDENTIFIABLE", "Verdict",
           "judge_fit"]

CHI2_LIMIT = 2.0
#: The standard deviation of Gaussian noise over its median absolute value (``robust``).
MAD_TO_SD = 1.482602218505602
EXIT_OK, EXIT_NOT_EXPLAINED, EXIT_UNIDENTIFIABLE = 0, 3, 4
EXIT_CODES = {EXIT_OK: "converged: the fit explains the data and every constant is identifiable",
              2: "bad input (error: ...)",
              EXIT_NOT_EXPLAINED: "not converged, or the fit does not explain the data (reduced chi^2 > 2, or "
                                  "residuals structured in time)",
              EXIT_UNIDENTIFIABLE: "some constants are not identifiable (infinite intervals)"}


@dataclasses.dataclass
class Verdict:
    """What a calibration's result is worth.

    Attributes:
        solver_converged: the solver met its stopping test.
        reduced_chi2: per target, ``|r_c|^2 / dof_c`` with the given noise scales.
        noise_ratio: per target, the residual RMS over the given noise scale (``sqrt`` of the above
            without the degrees of freedom).
        explains_data: every target's reduced chi-squared is at most :data:`CHI2_LIMIT` and no
            target's residuals are structured.
        unidentifiable: labels of the constants with infinite intervals.
        null_directions: each unidentifiable direction: ``singular_ratio`` (its singular value of
            ``J`` over the largest), ``log_error`` (its standard error in log space) and
            ``components`` (label -> weight, those above 0.1).
        at_bound: labels of the constants the solver left at a bound (``--bounds``): the data pull
            them further; their intervals describe the constrained fit only.
        ran_off: label -> ``(start, fitted)`` of the constants that ended more than a factor 1e4
            from their start (``calibration_fit.RUNAWAY_LOG``): the search left the range the
            session informs, so an infinite interval there may be the solver's, not the data's.
        converged: ``solver_converged and explains_data``.
        warnings: plain sentences, one per problem.
        exit_code: :data:`EXIT_CODES`.
        validation: the held-out part's summary (``--validate``,
            :mod:`fitting.calibration_validation`), or None.
        whiteness: per target, the lag-1 whiteness test of its residuals
            (:func:`fitting.residual_whiteness.lag1_whiteness`: ``lag1``, ``z``, ``channels``,
            ``samples``, ``structured``), or None where not tested.
        structured: the targets whose residuals are structured in time (``z`` above the limit).
    """

    solver_converged: bool
    reduced_chi2: dict[str, float]
    noise_ratio: dict[str, float]
    explains_data: bool
    unidentifiable: list[str]
    null_directions: list[dict]
    at_bound: list[str]
    converged: bool
    warnings: list[str]
    exit_code: int
    validation: dict | None = None
    ran_off: dict = dataclasses.field(default_factory=dict)
    whiteness: dict = dataclasses.field(default_factory=dict)
    structured: list = dataclasses.field(default_factory=list)

    def summary(self) -> dict:
        """A JSON-ready dict."""
        return dataclasses.asdict(self)


def judge_fit(residuals: np.ndarray, targets: Mapping[str, tuple[int, int]], noise: Mapping[str, float],
              labels: Sequence[str], uncertainty: GaussNewtonUncertainty, solver_converged: bool,
              solver_message: str, at_bound: Sequence[str] = (), robust: bool = False,
              ran_off: Mapping[str, tuple[float, float]] | None = None,
              series: Mapping[str, Sequence[np.ndarray]] | None = None, nuisance: int = 0) -> Verdict:
    """Judges a fit from its scaled residuals ``(m,)`` at the optimum.

    Args:
        residuals: residuals divided by the given noise scales, ``(m,)``.
        targets: target -> ``(start, stop)`` of its rows.
        noise: the given noise scales per target ([m], [N]).
        labels: the constants' labels ``(n,)``.
        uncertainty: at the optimum.
        solver_converged, solver_message: the solver's own result.
        at_bound: labels of constants at a bound.
        ran_off: label -> ``(start, fitted)`` of constants that ran off (a warning; the exit code
            is decided as without it).
        robust: (``--loss huber``) the residuals' scale per target from their median absolute
            value, ``1.4826 median |r_c|`` (the standard deviation for Gaussian noise, unmoved by a
            few gross outliers), instead of their RMS: ``chi2_c`` is its square times
            ``m_c / dof_c``, ``noise_ratio`` the scale itself.
        series: per target, its scaled residuals in time order, one ``(T, channels)`` array per
            session (multiple shooting or not: the recording's time order), for the whiteness
            test (:func:`fitting.residual_whiteness.lag1_whiteness`); None: not tested.
        nuisance: the last ``nuisance`` parameters are nuisance unknowns with a prior (the windows'
            initial states): not judged for identifiability; a direction is reported only when it
            involves a judged parameter.
    """
    m, n = len(residuals), len(labels)
    chi2, ratio = {}, {}
    for target, (a, b) in targets.items():
        r = residuals[a:b]
        dof = (b - a) - n * (b - a) / m
        square = (MAD_TO_SD * np.median(np.abs(r))) ** 2 if robust else np.mean(r * r)
        chi2[target] = float(square * (b - a) / dof) if dof > 0 else float("inf")
        ratio[target] = float(np.sqrt(square))
    whiteness = {t: lag1_whiteness(blocks) for t, blocks in (series or {}).items()}
    structured = [t for t, w in whiteness.items() if w is not None and w["structured"]]
    explains = all(c <= CHI2_LIMIT for c in chi2.values()) and not structured
    warnings = []
    if not solver_converged:
        warnings.append(f"the solver did not converge ({solver_message}): the constants are where it stopped, "
                        "not an optimum, and their intervals are not reliable")
    for target, c in chi2.items():
        if c > CHI2_LIMIT:
            unit = "m" if target == "bodies" else "N"
            warnings.append(f"the fit does not explain the data: the {target} residuals are {ratio[target]:.3g} times "
                            f"the given noise ({noise[target]:.3g} {unit}; reduced chi^2 {c:.3g} > {CHI2_LIMIT:g}). "
                            "A wrong basin, a model that cannot reproduce the session, or a noise scale set too "
                            "small: the constants and intervals are not to be trusted")
    for target in structured:
        w = whiteness[target]
        warnings.append(f"the residuals are structured: the fitted simulation does not explain the data (the {target} "
                        f"residuals' lag-1 autocorrelation is {w['lag1']:.3g} over {w['channels']} channels, "
                        f"{w['z']:.3g} standard deviations above white noise's 0; limit {Z_LIMIT:g}). Slow errors "
                        "of the simulation, not noise: a wrong basin, a recording delay (--fit-delay) or a model "
                        "that cannot reproduce the session; the constants and intervals are not to be trusted")
    u = uncertainty
    directions = []
    judged = len(labels) - nuisance
    for i in u.unidentifiable_directions:
        vector = u.directions[i]
        if not np.any(np.abs(vector[:judged]) > COMPONENT_LIMIT):
            continue
        components = {labels[j]: float(vector[j]) for j in np.argsort(-np.abs(vector))
                      if abs(vector[j]) > COMPONENT_LIMIT}
        ratio_i = float(u.singular_values[i] / u.singular_values[0]) if u.singular_values[0] > 0 else 0.0
        directions.append({"singular_ratio": ratio_i, "log_error": float(u.direction_error[i]),
                           "components": components})
    unidentifiable = [label for label, ok in zip(labels[:judged], u.identifiable) if not ok]
    if unidentifiable:
        warnings.append(f"not identifiable from this session: {', '.join(unidentifiable)} (cond(J^T J) = "
                        f"{u.condition_number:.3g}; {len(directions)} combination(s) of the constants the data do "
                        "not determine): their intervals are infinite. Fit fewer constants (freeze or share them), "
                        "add a prior, or record a longer or richer motion")
    if at_bound:
        warnings.append(f"at a bound (--bounds): {', '.join(at_bound)}: the data pull them beyond it; their values "
                        "and intervals describe the constrained fit, not the data alone")
    ran_off = dict(ran_off or {})
    if ran_off:
        moved = ", ".join(f"{label} {a:.3g} -> {b:.3g}" for label, (a, b) in ran_off.items())
        warnings.append(f"ran off: {moved} (more than a factor 1e4 from the start): the search left the range "
                        "the session informs, so a missing interval there may be the solver's, not the data's. "
                        "Fit again from other start values (--start) or keep them in range (--bounds)")
    if not solver_converged or not explains:
        code = EXIT_NOT_EXPLAINED
    elif unidentifiable:
        code = EXIT_UNIDENTIFIABLE
    else:
        code = EXIT_OK
    return Verdict(solver_converged=bool(solver_converged), reduced_chi2=chi2, noise_ratio=ratio,
                   explains_data=explains, unidentifiable=unidentifiable, null_directions=directions,
                   at_bound=list(at_bound), ran_off=ran_off,
                   converged=bool(solver_converged and explains), warnings=warnings, exit_code=code,
                   whiteness=whiteness, structured=structured)
