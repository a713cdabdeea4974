"""Writing a calibration's results: the table, ``calibration.json``, ``calibration.png`` and the
fitted constants as a scene file (``calibrated.toml``) that ``dmarionette simulate`` loads."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from dmarionette.render.pyplot import headless_pyplot

from .calibration_fit import CalibrationResult
from .synthetic_session import SPEC_FIELDS

__all__ = ["calibrated_scene_table", "format_table", "result_summary", "write_calibrated_scene", "write_outputs"]

_UNITS = {"k": "N/m", "k_d": "N s/m", "k_s": "N/m", "delay": "s"}
_RMS_UNITS = {"bodies": "m", "feedback": "N"}
# StringSpec fields a [[strings]] table may hold (docs/scenes.md): the recorded constants go back in.
_STRING_KEYS = ("particle_count", "mass", "load_mass", "stiffness", "internal_friction", "air_drag",
                "ground_stiffness", "ground_absorption", "ground_friction", "tie_stiffness", "tie_damping",
                "taut_fraction")


def format_table(result: CalibrationResult) -> str:
    """The fitted constants as a text table (what ``dmarionette calibrate`` prints)."""
    lines = [f"{'constant':<22} {'start':>12} {'fitted':>12} {'std. error':>12} {'rel.':>9}  unit"]
    for row in result.table():
        unit = _UNITS[row["label"].split("[")[0]]
        relative = f"{'-':>9}" if row["label"] == "delay" else f"{100 * row['relative_error']:>8.3f}%"
        lines.append(f"{row['label']:<22} {row['start']:>12.5g} {row['fitted']:>12.6g} "
                     f"{row['standard_error']:>12.3g} {relative}  {unit}")
    if result.delay["seconds"] and not result.delay["fitted"]:
        lines.append(f"delay of the targets behind the bar inputs: {result.delay['seconds']:.6g} s (given)")
    for name, (mean, sd) in result.priors.items():
        lines.append(f"prior on {name}: {mean:.6g} ± {sd:.3g} {_UNITS[name]} (Gaussian)")
    lines.append("")
    for target in result.rms_before:
        lines.append(f"RMS residual, {target:<8}: {result.rms_before[target]:.4g} -> {result.rms_after[target]:.4g} "
                     f"{_RMS_UNITS[target]}")
    u = result.uncertainty
    v = result.verdict
    if v is not None:
        for target, chi2 in v.reduced_chi2.items():
            lines.append(f"residual / given noise, {target:<8}: {v.noise_ratio[target]:.3g} (reduced chi^2 {chi2:.3g})")
        for target, w in v.whiteness.items():
            lines.append(f"residual lag-1 autocorrelation, {target:<8}: " +
                         ("not tested (too few samples per channel)" if w is None else
                          f"{w['lag1']:.3g} ({w['z']:.3g} standard deviations of white noise's 0, "
                          f"{w['channels']} channels)"))
    for i, session in enumerate(result.sessions or []):
        parts = ", ".join(f"{t} {session['rms_before'][t]:.4g} -> {session['rms_after'][t]:.4g} {_RMS_UNITS[t]}"
                          for t in session["rms_after"])
        lines.append(f"session {i + 1} of {len(result.sessions)}, {session['session']}: RMS residual {parts}")
    if result.loss["name"] == "huber":
        lines.append(f"loss: Huber, C = {result.loss['scale']:g} noise scales (IRLS, {result.loss['rounds']} rounds in "
                     f"the last stage): {result.loss['outliers']} of {result.loss['rows']} residuals down-weighted "
                     "as outliers; intervals of the weighted residuals, reduced chi^2 from the median |residual|")
    if result.initial_state is not None:
        st = result.initial_state
        lines.append(f"initial states refined at {len(st['windows'])} window starts ({st['unknowns']} unknowns; prior "
                     f"{st['sigma_q']:.3g} rad|m, {st['sigma_qd']:.3g} rad/s|m/s): corrections RMS {st['rms_dq']:.3g} "
                     f"(positions) and {st['rms_dqd']:.3g} (velocities) prior deviations, largest "
                     f"{max(st['max_dq'], st['max_dqd']):.3g}")
    from .calibration_validation import validation_lines

    lines.extend(validation_lines(result.validation, _RMS_UNITS))
    shooting = "one rollout" if result.window_steps is None else \
        f"windows of {result.window_steps} puppet steps ({result.window_steps * result.data.puppet_dt:.3g} s)"
    lines.append(f"solver {result.solver}, {shooting}: {result.solver_steps} steps, {result.message}; "
                 f"{result.cost['forward_passes']} forward and {result.cost['backward_passes']} backward rollouts, "
                 f"{result.cost['seconds']:.1f} s")
    for number, stage in enumerate(result.cost.get("stages") or [], 1):
        if stage.get("retry"):
            lines.append(f"stage {number}: the last stage again with {', '.join(stage['restarted'])} from the start values "
                         f"(they had run off, more than a factor 1e4): {'kept, a lower' if stage['kept'] else 'not kept, a higher'}"
                         " sum of squares")
        elif stage.get("restarted"):
            lines.append(f"stage {number}: started {', '.join(stage['restarted'])} again from the start values (they "
                         "had run off, more than a factor 1e4, in the stage before)")
    lines.append(f"uncertainty: Jacobian by {'forward differences' if result.jacobian['method'] == 'fd' else 'reverse mode'}"
                 f" ({result.jacobian['rows']} residuals, {result.jacobian['forward_passes']} forward and "
                 f"{result.jacobian['backward_passes']} backward rollouts), cond(J^T J) = {u.condition_number:.3g}")
    if v is not None:
        for direction in v.null_directions:
            parts = ", ".join(f"{w:+.2f} {label}" for label, w in direction["components"].items())
            lines.append(f"unidentifiable direction (log space): {parts}; singular value "
                         f"{direction['singular_ratio']:.2g} of the largest, standard error {direction['log_error']:.3g}")
        lines.append("")
        if v.warnings:
            lines.extend(f"**WARNING: {w}**" for w in v.warnings)
        lines.append(f"**RESULT: {_verdict_line(v)} (exit code {v.exit_code})**" if v.exit_code else
                     f"RESULT: {_verdict_line(v)} (exit code 0)")
    return "\n".join(lines)


def _verdict_line(v) -> str:
    from .calibration_verdict import EXIT_CODES

    return EXIT_CODES[v.exit_code]


def _finite_or_text(value):
    """JSON has no infinity: infinite and NaN numbers are written as the strings "inf" and "nan"."""
    if isinstance(value, float) and not np.isfinite(value):
        return "nan" if np.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: _finite_or_text(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_text(v) for v in value]
    return value


def result_summary(result: CalibrationResult) -> dict[str, Any]:
    """A JSON-ready summary (``calibration.json``)."""
    u, d = result.uncertainty, result.data
    verdict = result.verdict.summary() if result.verdict is not None else None
    return _finite_or_text({
        "status": verdict, "window_steps": result.window_steps,
        "priors": {name: {"mean": m, "sd": sd} for name, (m, sd) in result.priors.items()},
        "session": str(d.path), "sessions": result.sessions, "loss": result.loss, "delay": result.delay,
        "initial_state": result.initial_state,
        "scene": d.scene.name, "targets": list(d.targets), "inputs": d.input_source,
        "duration": float(d.frame_time[-1]), "puppet_steps": d.puppet_steps, "string_steps": d.step_count,
        "constants": result.table(),
        "units": {label: _UNITS[label.split("[")[0]] for label in result.labels},
        "rms_before": result.rms_before, "rms_after": result.rms_after, "rms_units": _RMS_UNITS,
        "validation": None if result.validation is None else
        {k: v for k, v in result.validation.items() if k != "residuals"},
        "solver": {"name": result.solver, "steps": result.solver_steps, "converged": result.converged,
                   "message": result.message, **result.cost},
        "uncertainty": {"jacobian": result.jacobian, "condition_number": u.condition_number,
                        "noise_variance": u.noise_variance, "known_noise": result.known_noise,
                        "noise_scales": result.noise, "residual_count": u.residual_count,
                        "correlation": u.correlation.tolist(), "covariance_log": u.covariance.tolist(),
                        "singular_values": u.singular_values.tolist(),
                        "identifiable": [bool(x) for x in u.identifiable]},
    })


def calibrated_scene_table(result: CalibrationResult) -> dict[str, Any]:
    """The session's scene (self-contained: puppet and bar motions inlined) with its recorded
    string constants and the fitted ones, as a TOML table."""
    record = result.data.session.scene_record
    table = json.loads(record["table_json"]) if "table_json" in record else tomllib.loads(record["toml"])
    scene = result.data.scene
    fitted: dict[str, dict[str, float]] = {s.name: {} for s in scene.strings}
    offset = 0
    for p in result.parameters:
        block = result.fitted[offset:offset + p.size]
        for j, i in enumerate(p.strings):
            fitted[scene.strings[i].name][SPEC_FIELDS[p.name]] = float(block[0 if p.shared else j])
        offset += p.size
    by_name = {s.name: s for s in scene.strings}
    for entry in table.get("strings", []):
        spec = by_name.get(entry.get("name"))
        if spec is None:
            continue
        for key in _STRING_KEYS:  # the constants the session ran with (they may differ from its TOML)
            value = getattr(spec, key)
            entry[key] = int(value) if key == "particle_count" else float(value)
        entry.update(fitted[spec.name])
        for name, values in result.string_constants.items():  # frozen ones too: as simulated
            entry[SPEC_FIELDS[name]] = float(values[scene.strings.index(spec)])
    info = table.setdefault("scene", {})
    info["description"] = (f"{info.get('description', '')} Calibrated from {result.data.path.name}: "
                           f"{len(result.labels)} constants ({result.solver}).").strip()
    return table


def write_calibrated_scene(result: CalibrationResult, path: str | Path) -> Path:
    """Writes :func:`calibrated_scene_table` as TOML; ``dmarionette simulate PATH`` loads it."""
    import tomli_w

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f"# Written by dmarionette calibrate from {result.data.path}.\n"
              "# The session's scene with its puppet and bar motions inlined; the strings carry the\n"
              f"# {len(result.labels)} fitted constants (see calibration.json). Format: docs/scenes.md.\n")
    path.write_text(header + tomli_w.dumps(calibrated_scene_table(result)))
    return path


def write_plot(result: CalibrationResult, path: str | Path) -> Path:
    """``calibration.png``: RMS residual over time per target before and after, the constants
    (start, fitted with 2 standard errors, "± ∞" where unidentifiable, the prior's band), the
    verdict in the title and the warnings under the panels."""
    plt = headless_pyplot()

    d = result.data
    names = [name for name in ("k", "k_d", "k_s") if any(label.split("[")[0] == name for label in result.labels)]
    targets = list(result.rms_before)
    fig, axes = plt.subplots(2, max(len(targets), len(names)), figsize=(6 * max(len(targets), len(names)), 7),
                             squeeze=False)
    for c, target in enumerate(targets):
        ax = axes[0, c]
        times = d.frame_time[1:] if target == "bodies" else d.step_time
        scale, unit = (1e3, "mm") if target == "bodies" else (1.0, "N")
        for label, residuals, style in (("before", result.residuals_before, "C3"),
                                        ("after", result.residuals_after, "C0")):
            rms = np.sqrt(np.mean(residuals[target] ** 2, axis=(1, 2))) * scale
            ax.plot(times, rms, style, lw=1, label=f"{label} (RMS {getattr(result, f'rms_{label}')[target] * scale:.3g} {unit})")
        if result.validation is not None:  # the whole session simulated with the fitted constants
            val = result.validation
            whole = np.sqrt(np.mean(val["residuals"][target] ** 2, axis=(1, 2))) * scale
            step = d.frame_time[1] - d.frame_time[0] if target == "bodies" else d.step_time[1] - d.step_time[0]
            first = (d.frame_time[1] if target == "bodies" else d.step_time[0])
            ax.plot(first + step * np.arange(len(whole)), whole, "C2", lw=1, alpha=0.8,
                    label=f"validation, held out t > {val['start_time']:.3g} s (RMS {val['rms'][target] * scale:.3g} "
                          f"{unit}, chi^2 {val['reduced_chi2'][target]:.3g})")
            ax.axvline(val["start_time"], color="k", ls="--", lw=0.8)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"RMS residual [{unit}]")
        ax.set_yscale("log")
        ax.set_title("body centres" if target == "bodies" else "bar reaction")
        ax.legend(fontsize=8)
    for c in range(len(targets), axes.shape[1]):
        axes[0, c].axis("off")
    for c, name in enumerate(names):
        ax = axes[1, c]
        rows = [i for i, label in enumerate(result.labels) if label.split("[")[0] == name]
        x = np.arange(len(rows))
        ax.plot(x, result.start[rows], "x", color="C3", label="start")
        se = result.uncertainty.standard_error[rows]
        finite = np.isfinite(se)
        ax.errorbar(x, result.fitted[rows], yerr=np.where(finite, 2 * se, 0.0), fmt="o", color="C0",
                    capsize=3, label="fitted ± 2 s.e.")
        for xi, yi in zip(x[~finite], result.fitted[rows][~finite]):  # unidentifiable: an unbounded interval
            ax.annotate("± ∞", (xi, yi), textcoords="offset points", xytext=(5, 5), color="C3", fontsize=8)
        if name in result.priors:
            mean, sd = result.priors[name]
            ax.axhspan(mean - sd, mean + sd, color="C2", alpha=0.15, label=f"prior {mean:g} ± {sd:g}")
        ax.set_xticks(x, [result.labels[i].split("[")[1].rstrip("]") for i in rows], rotation=30, fontsize=8)
        ax.set_ylabel(f"{name} [{_UNITS[name]}]")
        ax.legend(fontsize=8)
    for c in range(len(names), axes.shape[1]):
        axes[1, c].axis("off")
    v = result.verdict
    status = "" if v is None else (" — converged" if v.exit_code == 0 else f" — exit code {v.exit_code}")
    together = "" if not result.sessions else f" (residuals: session 1 of {len(result.sessions)} fitted together)"
    fig.suptitle(f"calibration of {d.path.name}{together}: {result.solver}, {result.solver_steps} steps{status}")
    fig.tight_layout()
    if v is not None and v.warnings:  # the warnings, in red, under the panels
        import textwrap

        text = "\n".join(textwrap.fill(f"WARNING: {w}", 160) for w in v.warnings)
        fig.subplots_adjust(bottom=0.08 + 0.035 * text.count("\n") + 0.035 * len(v.warnings))
        fig.text(0.01, 0.01, text, color="C3", fontsize=8, va="bottom")
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_outputs(result: CalibrationResult, out: str | Path, *, plot: bool = True) -> dict[str, str]:
    """Writes ``calibration.json``, ``calibrated.toml`` and ``calibration.png`` into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"scene": str(write_calibrated_scene(result, out / "calibrated.toml"))}
    if plot:
        files["plot"] = str(write_plot(result, out / "calibration.png"))
    summary = result_summary(result)
    summary["files"] = {**files, "summary": str(out / "calibration.json")}
    (out / "calibration.json").write_text(json.dumps(summary, indent=2) + "\n")
    files["summary"] = str(out / "calibration.json")
    return files

