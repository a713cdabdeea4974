"""fitting's commands of the ``dmarionette`` command line, plugged in through entry points.

- ``dmarionette author KEYFRAMES``: bar motions that reach keyframe poses (docs/authoring.md);
- ``dmarionette calibrate SESSION``: fit string constants to a recorded session (docs/calibration.md).

``dmarionette`` never imports ``fitting``: pyproject.toml declares these functions in the
``dmarionette.commands`` entry-point group, and ``dmarionette.cli`` loads the one a command line
names (see its docstring for the contract). Each adds its subparser to dmarionette's
subcommands, with ``handler`` set to the function that runs it and returns the exit code;
a ``ValueError`` or ``RuntimeError`` it raises is printed as ``error: ...`` with exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dmarionette.cli_checks import Outputs, add_ray_flags, integer, number, optimization_level, start_values

__all__ = ["add_author_command", "add_calibrate_command"]


def add_author_command(commands) -> None:
    """Adds ``dmarionette author`` to ``commands`` (dmarionette's ``add_subparsers()``)."""
    author = commands.add_parser(
        "author", help="keyframes -> bar motions that reach them (needs the fitting extra: jax, optimistix)",
        description="Keyframe authoring (docs/authoring.md): find control-bar motions that make the puppet reach "
                    "the poses of a keyframes file, by gradient-based optimisation through the whole simulation. "
                    "Writes to OUT: authored_scene.toml (the optimised bars as keyframes; 'dmarionette simulate' "
                    "and 'live' take it), initial_scene.toml, trajectory.npz (the simulator's replay), "
                    "motion.bvh and motion.glb, animation_before.gif and animation_after.gif, convergence.png "
                    "and summary.json (per-keyframe errors before and after, the solver history). Prints one "
                    "line per solver step, a verdict per keyframe (reached / unreachable / not converged, with "
                    "the reason), then the summary's main numbers as JSON. Exit codes: 0 every keyframe reached "
                    "within the tolerances and the device limits held; 3 not converged (a keyframe that is "
                    "reachable, or not shown unreachable, was missed: the solver stopped or ran out of steps "
                    "or time); 4 some keyframe unreachable (named; the others reached); 5 a device limit "
                    "exceeded; 2 bad input. Several files: one job each, the exit code the worst job's (0, 4, 3, "
                    "5, 2 from best to worst), 6 a Ray worker died more often than the retries allow.")
    author.add_argument("keyframes", type=Path, nargs="+",
                        help="the keyframes TOML file; several: one authoring job each (on Ray workers with --ray), "
                             "each written to its own folder as it finishes, a table of them at the end, exit code "
                             "the worst job's (docs/authoring.md, 'Several files')")
    author.add_argument("--out", type=Path, default=None,
                        help="output folder (default: out/<keyframes file name>); several files: OUT/<file name> each")
    author.add_argument("--max-steps", type=integer(1, 100_000), default=None,
                        help="solver steps at most (default: the file's [solver] max_steps, else 60)")
    author.add_argument("--method", choices=["lm_fd", "bfgs", "lm", "gauss_newton"], default=None,
                        help="lm_fd (default): Levenberg-Marquardt on the keyframe residuals with a forward-"
                             "difference Jacobian and the device limits as hard limits; bfgs: the scalar loss with "
                             "reverse-mode gradients; lm / gauss_newton: optimistix on the residual vector with a "
                             "reverse-mode Jacobian (one backward pass per residual); the last three keep the "
                             "device limits as penalties (default: the file's [solver] method)")
    author.add_argument("--max-seconds", type=number(0.0, low_open=True, unit="s"), default=None,
                        help="wall-time budget of the solve: no solver step starts after it; a keyframe still "
                             "missed then is reported as not converged (default: the file's [solver] max_seconds, "
                             "else none)")
    author.add_argument("--jacobian", choices=["secant", "fd"], default=None,
                        help="lm_fd: between forward-difference Jacobians (n rollouts each), update the keyframe "
                             "rows by Broyden's secant formula (secant: about one rollout a step) or recompute them "
                             "every step (fd) (default: the file's [solver] jacobian, else secant)")
    author.add_argument("--continuation", action="store_true", default=None,
                        help="lm_fd: switch the keyframes on in time order (default: the file's [solver] "
                             "continuation, else all at once)")
    author.add_argument("--warm-start", choices=["scene", "quasi_static"], default=None,
                        help="lm_fd: start from the scene's own bar motion (scene) or from each keyframe's "
                             "quasi-static pose, the bar pose whose settled puppet is nearest the keyframe "
                             "(quasi_static; used only when it lowers the cost) (default: the file's [solver] "
                             "warm_start, else scene)")
    author.add_argument("--checkpoint-steps", type=integer(1, 1_000_000), default=None,
                        help="puppet steps per taped gradient segment (default: sqrt of the rollout's steps)")
    author.add_argument("--no-animation", action="store_true", help="skip the before/after animations")
    author.add_argument("--no-export", action="store_true", help="skip the BVH and glTF files")
    author.add_argument("--fps", type=number(0.1, 1000.0, unit="Hz"), default=15.0,
                        help="animation frames per second (default: 15)")
    author.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    author.add_argument("--quiet", action="store_true", help="no progress lines")
    add_ray_flags(author, "with several files, where the jobs run", one_in_process=True)
    author.set_defaults(handler=_run_author)


def _ray_mode(args: argparse.Namespace, count: int) -> str:
    """Where ``count`` sessions or files run: ``--ray``'s mode (checked also for one), ``"off"`` for one.
    With Ray, Ctrl-C raises in the command and waits for its workers' and cluster's shutdown."""
    from dmarionette.scale.ray_map import ray_mode

    mode = ray_mode(args.ray)
    if count < 2:
        mode = "off"
    if mode != "off" and getattr(args, "interrupt", None) is not None:
        args.interrupt.disarm()
    return mode


def _run_author(args: argparse.Namespace) -> int:
    # Every package the command needs, checked before any work (tomli_w is imported only when writing).
    try:
        import jax  # noqa: F401
        import optimistix  # noqa: F401
        import tomli_w  # noqa: F401
    except ImportError as error:
        raise RuntimeError(f"'dmarionette author' needs the fitting extra ({error.name} is missing): "
                           "pip install 'dmarionette[fitting]'") from None
    from .author import author, enable_compilation_cache
    from .author_batch import worst_keyframe_errors
    from .keyframes import load_keyframes

    mode = _ray_mode(args, len(args.keyframes))
    if len(args.keyframes) > 1:
        from .author_batch import run_author_batch

        return run_author_batch(args, mode, lambda summary: verdict_text(summary, bold=sys.stderr.isatty()))
    keyframes = args.keyframes[0]
    spec = load_keyframes(keyframes)
    out = _outputs(args).folder("--out", args.out if args.out is not None else Path("out") / keyframes.stem)
    enable_compilation_cache()
    summary = author(spec, out, max_steps=args.max_steps, method=args.method, max_seconds=args.max_seconds,
                     continuation=args.continuation, jacobian=args.jacobian, warm_start=args.warm_start,
                     progress=not args.quiet,
                     animation=not args.no_animation, exports=not args.no_export,
                     optimization_level=optimization_level(args), checkpoint_steps=args.checkpoint_steps,
                     fps=args.fps)
    keys = ("status", "exit_code", "loss_before", "loss_after", "steps", "converged", "replay_gap", "seconds",
            "files")
    print(json.dumps({k: summary[k] for k in keys} | worst_keyframe_errors(summary), indent=2))
    print(verdict_text(summary, bold=sys.stderr.isatty()), file=sys.stderr)
    return summary["exit_code"]


def verdict_text(summary: dict, *, bold: bool = False) -> str:
    """The verdict of an authoring summary, one line per keyframe and message; a miss in bold
    (ANSI when ``bold``, else between ``**``)."""
    strong = (lambda text: f"\033[1m{text}\033[0m") if bold else (lambda text: f"**{text}**")
    tol = summary["tolerances"]
    lines = []
    for v in summary["verdicts"]:
        label = {"reached": "reached", "unreachable": "UNREACHABLE", "not_converged": "NOT CONVERGED"}[v["status"]]
        worst = ", ".join(f"{n} {e:.3g} {v['units'][n]}" if v["units"][n] != "m" else
                          f"{n} {e * 1000:.3g} mm" if e < 1.0 else f"{n} {e:.3g} m" for n, e in v["errors"].items())
        line = f"keyframe {v['index'] + 1} (t = {v['t']:g} s): {label} ({worst})"
        lines.append(line if v["status"] == "reached" else strong(line))
        lines += [f"    {reason}" for reason in v["reasons"]]
    lines += [f"note: {m}" for m in summary["messages"]]
    headline = {"reached": f"every keyframe reached (within {tol['position_m'] * 1000:g} mm and "
                           f"{tol['angle_deg']:g} deg)",
                "not_converged": "NOT CONVERGED: a keyframe was missed that was not shown unreachable",
                "unreachable": "UNREACHABLE keyframes (named above); the others are reached",
                "limit_exceeded": "DEVICE LIMIT EXCEEDED (see the notes)"}[summary["status"]]
    lines.append(f"exit code {summary['exit_code']}: " + (headline if summary["status"] == "reached"
                                                             else strong(headline)))
    return "\n".join(lines)


def add_calibrate_command(commands) -> None:
    """Adds ``dmarionette calibrate`` to ``commands`` (dmarionette's ``add_subparsers()``)."""
    calibrate = commands.add_parser(
        "calibrate", help="fit the strings' constants (eq. 2 k, k_d per string) to a recorded session",
        description="Fit string constants to a recorded session (docs/calibration.md): the recorded bar poses "
                    "drive the simulation, the recorded body centres and/or feedback forces are the targets. "
                    "Prints the fitted values with standard errors (Gauss-Newton) and the residuals before and "
                    "after; writes OUT/calibration.json, OUT/calibration.png and OUT/calibrated.toml (a scene "
                    "with the fitted constants, for 'dmarionette simulate'). Needs the 'fitting' extra. "
                    "Exit codes: 0 converged, the fit explains the data (reduced chi^2 <= 2 against the given "
                    "noise scales, residuals white in time) and every constant is identifiable; 2 bad input; 3 the "
                    "solver did not converge or the fit does not explain the data (reduced chi^2 > 2, or residuals "
                    "structured in time); 4 some constants are not identifiable (their "
                    "intervals are infinite); 6 a Ray worker died more often than the retries allow (several "
                    "sessions on Ray; nothing is written). Warnings are printed in bold (**WARNING: ...**) and "
                    "written to calibration.json's 'status'.")
    calibrate.add_argument("session", type=Path, nargs="+",
                           help="the .mcap session file; several: fitted together with one shared set of constants "
                                "(their residuals stacked; same strings and rates; --solver lm-fd; per-session "
                                "residual RMS in the output; their rollouts on Ray workers with --ray)")
    calibrate.add_argument("--targets", choices=["bodies", "feedback", "both"], default="bodies",
                           help="fit the recorded body centres (default), the bars' feedback (exact reaction), "
                                "or both")
    calibrate.add_argument("--params", default="k,k_d",
                           help="constants to fit, comma-separated: k, k_d (eq. 2, per tied string), k_s (string "
                                "stiffness); ':shared' fits one value for every string (default: k,k_d)")
    calibrate.add_argument("--out", type=Path, default=None, help="output folder (default: out/calibrate/<session>)")
    calibrate.add_argument("--max-steps", type=integer(1, 100_000), default=50,
                           help="solver steps at most (default: 50)")
    calibrate.add_argument("--solver", choices=["lm-fd", "lm-bwd", "bfgs"], default="lm-fd",
                           help="lm-fd: Levenberg-Marquardt, Jacobian by forward differences of the rollout (one "
                                "batched rollout of n + 1 worlds) updated by secant steps (default, cheapest); lm-bwd: reverse-mode Jacobian on --rows residuals; bfgs: "
                                "BFGS on the loss with its reverse-mode gradient")
    calibrate.add_argument("--start", type=start_values, default=None,
                           help="start values, e.g. 'k=250,k_d=2.5' (default: the session scene's constants)")
    calibrate.add_argument("--noise-position", type=number(0.0, low_open=True, unit="m"), default=1e-3,
                           help="noise scale of a body coordinate [m] (default 1e-3)")
    calibrate.add_argument("--noise-force", type=number(0.0, low_open=True, unit="N"), default=1e-2,
                           help="noise scale of a force component [N] (default 1e-2)")
    calibrate.add_argument("--known-noise", action="store_true",
                           help="the noise scales are the true standard deviations (else the residual variance "
                                "is estimated per target)")
    calibrate.add_argument("--duration", type=number(0.0, low_open=True, unit="s"), default=None,
                           help="use only the first S seconds")
    calibrate.add_argument("--rows", type=integer(1, 1_000_000), default=96,
                           help="residuals kept by --solver lm-bwd (default 96)")
    calibrate.add_argument("--prior", type=_priors, default=None,
                           help="Gaussian priors per constant, in its unit: 'k=300±100,k_d=3+-1' (every string's "
                                "constant of that name; a residual row (c - mean) / sd each)")
    calibrate.add_argument("--bounds", type=_bounds, default=None,
                           help="bounds per constant, in its unit: 'k=100:1000,k_d=0.5:10' (the solver keeps every "
                                "string's constant of that name inside; one left at a bound is warned about)")
    calibrate.add_argument("--freeze", type=_labels, default=None,
                           help="per-string constants held at their start values, by label: 'k[head],k_d[back]'")
    calibrate.add_argument("--window", type=_windows, default=None,
                           help="multiple shooting: seconds per window, each window started from the recorded "
                                "puppet state; a comma-separated list fits once per entry, each from the previous "
                                "result (default 1/30 s then 1/3 s, the first stage on the first 2 s only, with "
                                "--solver lm-fd when /puppet/state records joint_q; "
                                "0: one rollout over the whole session)")
    calibrate.add_argument("--validate", type=_fraction, default=None, metavar="F",
                           help="hold out the last fraction F of the session (0 < F < 1, e.g. 0.25): fit on the "
                                "rest, then simulate the whole session with the fitted constants and report the "
                                "held-out residuals (RMS, reduced chi^2); a held-out reduced chi^2 > 2 is a warning "
                                "and exit code 3")
    calibrate.add_argument("--loss", choices=["l2", "huber"], default="l2",
                           help="l2: least squares (default); huber: Huber's robust loss by iteratively reweighted "
                                "least squares (outliers beyond --huber-scale noise scales pull with a constant "
                                "force; --solver lm-fd)")
    calibrate.add_argument("--huber-scale", type=number(0.0, low_open=True), default=None, metavar="C",
                           help="Huber's threshold in noise scales (default 1.345; with --loss huber)")
    calibrate.add_argument("--delay", type=number(-0.1, 0.1, unit="s"), default=0.0, metavar="S",
                           help="the recorded targets lag the bar inputs by S seconds, measured(t) = simulated(t - S) "
                                "(the bar inputs are shifted; default 0); with --fit-delay the start value")
    calibrate.add_argument("--fit-delay", action="store_true",
                           help="fit that delay too (within +-0.1 s, with its standard error; --solver lm-fd)")
    calibrate.add_argument("--fit-initial-state", action="store_true",
                           help="refine the puppet state each shooting window starts from (every window but the "
                                "first, in the last stage; taken from the recording) as unknowns with the prior "
                                "--noise-joint (one session, --solver lm-fd, windows)")
    calibrate.add_argument("--noise-joint", type=number(0.0, low_open=True), default=1e-3, metavar="R",
                           help="noise of the recorded joint_q, the initial states' prior: rad for rotations, m for "
                                "the root's translation (default 1e-3; velocities sqrt(2) R / H)")
    calibrate.add_argument("--fast-compile", action="store_true", help="puppet kernels without optimisation")
    calibrate.add_argument("--no-picture", action="store_true", help="skip calibration.png")
    calibrate.add_argument("--quiet", action="store_true", help="no progress display")
    add_ray_flags(calibrate, "with several sessions, where their rollouts run (a worker keeps a session's model warm; "
                              "the solver step stays in this process)", one_in_process=True)
    calibrate.set_defaults(handler=_run_calibrate)


def _priors(text: str) -> dict:
    """``--prior``: ``NAME=MEAN±SD`` (or ``+-``), comma-separated."""
    from .calibrate import parse_priors

    try:
        return parse_priors(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--prior: ")) from None


def _bounds(text: str) -> dict:
    """``--bounds``: ``NAME=LOW:HIGH``, comma-separated."""
    from .calibrate import parse_bounds

    try:
        return parse_bounds(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--bounds: ")) from None


def _labels(text: str) -> list[str]:
    """``--freeze``: constant labels ``NAME[STRING]``, comma-separated (checked against the session later)."""
    import re

    labels = [part.strip() for part in text.split(",") if part.strip()]
    bad = [label for label in labels if not re.fullmatch(r"(k|k_d|k_s)\[[^\[\]]+\]", label)]
    if not labels or bad:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected labels like 'k[head],k_d[hand_left]' (constant "
                                         "k, k_d or k_s and a string name in brackets)")
    return labels


def _fraction(text: str) -> float:
    """``--validate``: a fraction strictly between 0 and 1."""
    value = number(0.0, 1.0, low_open=True)(text)
    if value >= 1.0:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a fraction of the session held out, 0 < F < 1")
    return value


def _windows(text: str) -> list[float]:
    """``--window``: seconds per window, comma-separated (``0``: one rollout)."""
    parse = number(0.0, 1e4, unit="s")
    values = [parse(part.strip()) for part in text.split(",")]
    if len(values) > 1 and 0.0 in values[:-1]:
        raise argparse.ArgumentTypeError(f"got {text!r}; 0 (one rollout) may only be the last entry")
    return values


def _run_calibrate(args: argparse.Namespace) -> int:
    try:  # the fitting extra (JAX, optimistix) is imported only here
        from .calibration_fit import calibrate_session
        from .calibration_report import format_table, write_outputs
    except ImportError as error:
        raise RuntimeError(f"dmarionette calibrate needs the 'fitting' extra ({error}); install it with "
                           "pip install 'dmarionette[fitting]'") from None
    mode = _ray_mode(args, len(args.session))
    start = args.start or None
    default = Path("out") / "calibrate" / args.session[0].stem
    out = _outputs(args).folder("--out", args.out if args.out is not None else default)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        print(f"calibrating {', '.join(map(str, args.session))} (the first run compiles the puppet kernels)",
              file=sys.stderr)
        bar = tqdm(unit=" rollouts", desc="start", file=sys.stderr)

    def progress(stage: str, count: int) -> None:
        bar.set_description(stage, refresh=False)
        bar.update(count - bar.n)

    from dmarionette.scale.ray_map import WorkerLostError

    from .author_batch import EXIT_WORKER_LOST  # the fitting commands' exit code for a lost worker

    try:
        sessions = args.session if len(args.session) > 1 else args.session[0]
        result = calibrate_session(sessions, targets=args.targets, params=args.params, solver=args.solver,
                                   max_steps=args.max_steps, start=start, noise_position=args.noise_position,
                                   noise_force=args.noise_force, known_noise=args.known_noise,
                                   duration=args.duration, rows=args.rows,
                                   window="default" if args.window is None else args.window,
                                   prior=args.prior, bounds=args.bounds, freeze=args.freeze,
                                   validate=args.validate, loss=args.loss, huber_scale=args.huber_scale,
                                   delay=args.delay, fit_delay=args.fit_delay,
                                   fit_initial_state=args.fit_initial_state, noise_joint=args.noise_joint,
                                   optimization_level=optimization_level(args),
                                   progress=progress if bar is not None else None, ray=mode, workers=args.workers)
    except WorkerLostError as error:  # not the user's input (exit code 2): the cluster lost a worker for good
        print(f"error: {error}; nothing was written to {out} (run it again, or with --ray off)", file=sys.stderr)
        return EXIT_WORKER_LOST
    finally:
        if bar is not None:
            bar.close()
    files = write_outputs(result, out, plot=not args.no_picture)
    print(format_table(result))
    print(json.dumps(files, indent=2))
    return result.verdict.exit_code


def _outputs(args: argparse.Namespace) -> Outputs:
    """The command's output checks (``dmarionette.cli.main`` sets ``args.outputs``; a direct call gets its own)."""
    if getattr(args, "outputs", None) is None:
        args.outputs = Outputs()
    return args.outputs
