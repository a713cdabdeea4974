"""A held-out validation split for calibration (docs/calibration.md, "Validation").

``dmarionette calibrate --validate F`` fits the constants on the session's first ``1 - F`` of its
duration, then simulates the *whole* session with the fitted constants (with the same shooting
as the fit's last stage: one rollout, or windows each started from the recorded puppet state) and
reports the residuals on the held-out end alone: their RMS per target in its unit and their
reduced chi-squared against the given noise scales, ``chi2_c = |r_c|^2 / m_c`` (the held-out
rows were not fitted, so no degrees of freedom are subtracted). Above
:data:`fitting.calibration_verdict.CHI2_LIMIT` the fitted constants do not predict data they
were not fitted to: a warning, and exit code 3 (the fit does not explain the data).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .calibration_data import CalibrationData, read_calibration_data
from .calibration_verdict import CHI2_LIMIT, EXIT_NOT_EXPLAINED, Verdict

__all__ = ["held_out_residuals", "judge_validation", "split_for_validation", "validation_lines"]


def split_for_validation(data: CalibrationData, fraction: float, targets: str) -> CalibrationData:
    """The part of ``data`` a ``--validate fraction`` fit is fitted to: its first ``1 - fraction``
    of the duration, whole puppet steps.

    Args:
        data: the whole session (as read, ``--duration`` applied).
        fraction: the share of the duration held out at the end, ``0 < fraction < 1``.
        targets: as ``data`` was read with.

    Raises:
        ValueError: ``fraction`` outside ``(0, 1)``, or a split that leaves no puppet step on
            either side.
    """
    if not (isinstance(fraction, (int, float, np.floating)) and 0.0 < fraction < 1.0):
        raise ValueError(f"--validate: got {fraction!r}; expected a fraction of the session held out, "
                         "0 < F < 1 (e.g. 0.25)")
    total = data.puppet_steps
    fit_steps = int(np.floor((1.0 - fraction) * total + 1e-9))
    if fit_steps < 1 or fit_steps >= total:
        raise ValueError(f"{data.path}: --validate {fraction:g} of {total} puppet steps "
                         f"({total * data.puppet_dt:.3g} s) leaves {fit_steps} to fit and {total - fit_steps} "
                         "held out; expected at least one on each side")
    return read_calibration_data(data.path, targets, duration=(fit_steps + 0.5) * data.puppet_dt,
                                 session=data.session)


def held_out_residuals(problem, theta: np.ndarray, fit_data: CalibrationData) -> dict[str, Any]:
    """Residuals of the held-out end of a session at the fitted constants.

    Args:
        problem: a :class:`fitting.calibrate.CalibrationProblem` over the *whole* session, with
            the fitted parameters and the fit's last shooting (``use_windows``).
        theta: the fitted log-constants ``(n,)``.
        fit_data: the part fitted (:func:`split_for_validation`).

    Returns:
        ``start_time`` [s] (where the held-out part begins), ``fraction``, ``rms`` per target in
        its unit, ``reduced_chi2`` per target (against the given noise), ``rows`` per target, and
        ``residuals``: the unscaled residuals of the whole session per target (body
        ``(P, bodies, 3)`` [m], feedback ``(T, B, 3)`` [N]).
    """
    d = problem.data
    scaled = problem.host_residuals(np.asarray(theta, np.float64))
    first = {"bodies": fit_data.puppet_steps, "feedback": fit_data.step_count}
    rms, chi2, rows, whole = {}, {}, {}, {}
    for target, (a, b) in problem.target_slices().items():
        shape = (d.puppet_steps, len(d.bodies), 3) if target == "bodies" else (d.step_count, len(d.bars), 3)
        r = scaled[a:b].reshape(shape)
        held = r[first[target]:].reshape(-1)
        whole[target] = r * problem.noise[target]
        rows[target] = int(held.size)
        chi2[target] = float(held @ held / held.size)
        rms[target] = float(np.sqrt(np.mean(held**2)) * problem.noise[target])
    return {"start_time": float(fit_data.frame_time[-1]), "fraction": 1.0 - fit_data.puppet_steps / d.puppet_steps,
            "rms": rms, "reduced_chi2": chi2, "rows": rows, "residuals": whole}


def judge_validation(verdict: Verdict, validation: Mapping[str, Any], noise: Mapping[str, float]) -> None:
    """Adds the held-out part's verdict to ``verdict`` (in place): its summary under
    ``verdict.validation``; a reduced chi-squared above :data:`CHI2_LIMIT` on a target is a
    warning, ``explains_data`` and ``converged`` false, and exit code 3."""
    verdict.validation = {k: v for k, v in validation.items() if k != "residuals"}
    bad = {t: c for t, c in validation["reduced_chi2"].items() if c > CHI2_LIMIT}
    for target, c in bad.items():
        unit = "m" if target == "bodies" else "N"
        verdict.warnings.append(
            f"the fit does not explain the held-out data (--validate): on t > {validation['start_time']:.3g} s the "
            f"{target} residuals are {np.sqrt(c):.3g} times the given noise ({noise[target]:.3g} {unit}; reduced "
            f"chi^2 {c:.3g} > {CHI2_LIMIT:g}). The constants reproduce the part they were fitted to but do not "
            "predict the rest: a wrong basin, constants the fitted part does not pin down, or a model that "
            "cannot reproduce the session")
    if bad:
        verdict.explains_data = False
        verdict.converged = False
        verdict.exit_code = EXIT_NOT_EXPLAINED


def validation_lines(validation: Mapping[str, Any] | None, units: Mapping[str, str]) -> list[str]:
    """The printout's lines about the held-out part (none without ``--validate``)."""
    if not validation:
        return []
    lines = [f"validation: held out the last {100 * validation['fraction']:.3g} % (t > "
             f"{validation['start_time']:.4g} s), simulated with the fitted constants:"]
    for target, rms in validation["rms"].items():
        lines.append(f"  held-out RMS residual, {target:<8}: {rms:.4g} {units[target]} (reduced chi^2 "
                     f"{validation['reduced_chi2'][target]:.3g}, {validation['rows'][target]} residuals)")
    return lines

