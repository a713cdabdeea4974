"""What accuracy costs in time: a sweep of the settings that trade one for the other.

One fixed scripted motion (the ``hanging`` marionette, its main bar swaying 6 cm and
tilting 10° within 3 s) is simulated under each setting and compared with a reference:

- error: RMS over a 20 Hz time grid of the 12 body centres' distance to the reference [m],
  and RMS of the main bar's eq. 4 feedback force difference [N];
- cost: wall-clock seconds of stepping per simulated second, one core (captured graphs,
  compiled kernels).

The reference is refined until it stops changing: ``R1`` (100 particles per string,
strings and puppet at 4 kHz) is compared with ``R2`` (200 particles, 8 kHz); their gap is
reported as the reference's own error and must be well below the errors of the sweep.

Knobs, one at a time around the paper's settings (50 particles, strings 1 kHz, puppet 30 Hz,
float64, printed springs, hard contact): particles per string, string step, puppet rate, the
strings' precision (float32 strings under the float64 puppet, at the paper's settings and
with the puppet at the string rate), the solver variant ``[effects] tension_only`` (segment
springs that do not push; at 30 Hz and with the puppet at the string rate), and the contact
model. The reference uses the printed springs, so a tension-only row's error
also holds how much that variant changes the motion itself.
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from dmarionette.scene.bars import BarTrajectory
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.marionette.rollout import MarionetteTrajectory, simulate_marionette
from dmarionette.render.pyplot import headless_pyplot
from dmarionette.scene.scene import Scene, load_scene

__all__ = ["Setting", "accuracy_scene", "run_sweep", "sweep_settings", "write_outputs"]

PAPER = {"particles": 50, "string_hz": 1000.0, "puppet_hz": 30.0, "contact": "hard", "precision": "float64",
         "springs": "printed"}
GRID_HZ = 20.0


@dataclasses.dataclass(frozen=True)
class Setting:
    """One point of the sweep."""

    knob: str
    particles: int = PAPER["particles"]
    string_hz: float = PAPER["string_hz"]
    puppet_hz: float = PAPER["puppet_hz"]
    contact: str = PAPER["contact"]
    #: The strings' float type (``[solver] precision``; the puppet is float64 either way).
    precision: str = PAPER["precision"]
    #: ``"printed"`` (the paper's spring) or ``"tension_only"`` (``[effects] tension_only``).
    springs: str = PAPER["springs"]

    @property
    def is_paper(self) -> bool:
        return (self.particles, self.string_hz, self.puppet_hz, self.contact, self.precision,
                self.springs) == tuple(PAPER.values())

    def label(self) -> str:
        extras = "".join(f", {value}" for value, default in ((self.precision, PAPER["precision"]),
                                                              (self.springs, PAPER["springs"])) if value != default)
        return (f"{self.particles} p, strings {self.string_hz:g} Hz, puppet {self.puppet_hz:g} Hz, "
                f"{self.contact}{extras}")


def accuracy_scene(seconds: float) -> Scene:
    """The ``hanging`` marionette with a livelier scripted main bar (see the module doc)."""
    scene = load_scene("hanging")
    main, hand = scene.bars
    p0 = np.array(main.trajectory.positions[0])
    t = np.array([0.0, 0.4, 1.0, 1.6, 2.2, 3.0]) * seconds / 3.0
    offsets = np.array([[0, 0, 0], [0, 0, 0], [0.06, -0.02, 0.02], [-0.04, 0.0, -0.02], [0.0, 0.01, 0.0], [0, 0, 0]])
    rotations = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 10.0], [5.0, 0, -8.0], [0, 0, 0], [0, 0, 0]])
    bar = dataclasses.replace(main, trajectory=BarTrajectory(t, p0 + offsets, rotations))
    return dataclasses.replace(scene, bars=(bar, hand))


def sweep_settings(grid: str = "full") -> list[Setting]:
    """The settings of the ``full`` or ``reduced`` (CI) grid."""
    if grid == "reduced":
        return [Setting("particles", particles=50), Setting("puppet_hz", puppet_hz=62.5),
                Setting("puppet_hz", puppet_hz=250.0)] + [
            Setting("particles @ 1 kHz puppet", particles=n, puppet_hz=1000.0) for n in (5, 20)] + [
            # Each beside a float64 printed-spring row above with the same other settings.
            Setting("precision", precision="float32"),
            Setting("springs", particles=20, puppet_hz=1000.0, springs="tension_only")]
    settings = [Setting("particles", particles=n) for n in (5, 10, 25, 50, 100, 200)]
    # At 30 Hz the puppet step dominates the error; with the puppet at the string rate the
    # strings' own resolution shows.
    settings += [Setting("particles @ 1 kHz puppet", particles=n, puppet_hz=1000.0) for n in (5, 10, 25, 50, 100)]
    settings += [Setting("string_step", string_hz=hz, puppet_hz=min(30.0, hz)) for hz in (500.0, 2000.0, 4000.0)]
    settings += [Setting("puppet_hz", puppet_hz=hz) for hz in (62.5, 125.0, 250.0, 500.0, 1000.0)]
    # Float32 strings beside the float64 rows "particles" 50 and "particles @ 1 kHz puppet" 50.
    settings += [Setting("precision", precision="float32", puppet_hz=hz) for hz in (30.0, 1000.0)]
    # Tension-only springs at the paper's rates and with the puppet at the string rate.
    settings += [Setting("springs", springs="tension_only")]
    settings += [Setting("springs", puppet_hz=1000.0, springs="tension_only", precision=p)
                 for p in ("float64", "float32")]
    settings += [Setting("contact", contact="smooth")]
    return settings


def _scene_for(base: Scene, setting: Setting) -> Scene:
    strings = tuple(dataclasses.replace(s, particle_count=setting.particles) for s in base.strings)
    contact = dict(base.contact, smooth=setting.contact == "smooth")
    effects = dataclasses.replace(base.effects, tension_only=setting.springs == "tension_only")
    return dataclasses.replace(base, strings=strings, string_hz=setting.string_hz, puppet_hz=setting.puppet_hz,
                               contact=contact, precision=setting.precision, effects=effects)


def _on_grid(trajectory: MarionetteTrajectory, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body centres ``(G, 12, 3)`` and main-bar feedback ``(G, 3)`` interpolated on ``grid``."""
    body = trajectory.body_pos[:, :12]
    bodies = np.stack([[np.interp(grid, trajectory.frame_time, body[:, b, i]) for i in range(3)]
                       for b in range(body.shape[1])]).transpose(2, 0, 1)
    feedback = np.stack([np.interp(grid, trajectory.step_time, trajectory.bar_feedback[:, 0, i]) for i in range(3)], 1)
    return bodies, feedback


def _errors(run: tuple[np.ndarray, np.ndarray], reference: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    body = float(np.sqrt(np.mean(np.sum((run[0] - reference[0]) ** 2, axis=2))))
    feedback = float(np.sqrt(np.mean(np.sum((run[1] - reference[1]) ** 2, axis=1))))
    return body, feedback


def run_sweep(seconds: float = 3.0, grid: str = "full", optimization_level: int = 2, repeats: int = 3,
              progress: Callable[[str], None] = print) -> tuple[list[dict], dict]:
    """Runs the references and the sweep; returns (rows, reference summary)."""
    base = accuracy_scene(seconds)
    times = np.arange(0.0, seconds + 1e-9, 1.0 / GRID_HZ)

    def simulate(setting: Setting, timed: bool) -> tuple[tuple[np.ndarray, np.ndarray], float]:
        model = MarionetteModel(_scene_for(base, setting), optimization_level=optimization_level)
        trajectory = simulate_marionette(model, seconds, progress=False)
        walls = [trajectory.wall_seconds]
        if timed:
            walls += [simulate_marionette(model, seconds, progress=False).wall_seconds for _ in range(repeats - 1)]
        simulated = float(trajectory.step_time[-1])
        return _on_grid(trajectory, times[times <= trajectory.frame_time[-1]]), float(np.median(walls)) / simulated

    coarse = grid == "reduced"
    settings = sweep_settings(grid)
    # One reference per spring model: a tension-only row is compared with a tension-only
    # reference, so that its error is the numerical error of its settings; how much the variant
    # changes the motion itself is reported apart (``tension_only_vs_printed_*``).
    references, summary = {}, {}
    for springs in dict.fromkeys(["printed"] + [s.springs for s in settings]):
        r1 = Setting("reference", particles=50 if coarse else 100, string_hz=2000.0 if coarse else 4000.0,
                     puppet_hz=2000.0 if coarse else 4000.0, springs=springs)
        r2 = Setting("reference", particles=100 if coarse else 200, string_hz=4000.0 if coarse else 8000.0,
                     puppet_hz=4000.0 if coarse else 8000.0, springs=springs)
        progress(f"reference R1: {r1.label()}")
        references[springs], _ = simulate(r1, timed=False)
        progress(f"reference R2: {r2.label()}")
        finer, _ = simulate(r2, timed=False)
        gap = _errors(finer, references[springs])
        prefix = "" if springs == "printed" else f"{springs}_"
        summary.update({f"{prefix}R1": r1.label(), f"{prefix}R2": r2.label(),
                        f"{prefix}R1_vs_R2_body_rms_m": gap[0], f"{prefix}R1_vs_R2_feedback_rms_N": gap[1]})
    if "tension_only" in references:
        effect = _errors(references["tension_only"], references["printed"])
        summary.update({"tension_only_vs_printed_body_rms_m": effect[0],
                        "tension_only_vs_printed_feedback_rms_N": effect[1]})
    rows = []
    for setting in settings:
        progress(f"{setting.knob}: {setting.label()}")
        run, cost = simulate(setting, timed=True)
        body, feedback = _errors(run, references[setting.springs])
        rows.append({"knob": setting.knob, "particles": setting.particles, "string_hz": setting.string_hz,
                     "puppet_hz": setting.puppet_hz, "precision": setting.precision,
                     "springs": setting.springs, "contact": setting.contact,
                     "paper": setting.is_paper, "body_rms_m": body, "feedback_rms_N": feedback,
                     "wall_s_per_sim_s": cost})
    return rows, summary


def _pareto(rows: Sequence[dict]) -> list[dict]:
    front, best = [], np.inf
    for row in sorted(rows, key=lambda r: r["wall_s_per_sim_s"]):
        if row["body_rms_m"] < best:
            front.append(row)
            best = row["body_rms_m"]
    return front


def _float32_twins(rows: Sequence[dict]) -> list[tuple[dict, dict]]:
    """Pairs (float32 row, float64 row with the same particles, rates, springs and contact)."""
    same = ("particles", "string_hz", "puppet_hz", "springs", "contact")
    pairs = []
    for row in rows:
        if row["precision"] == "float32":
            twin = [r for r in rows if r["precision"] == "float64" and all(r[k] == row[k] for k in same)]
            if twin:
                pairs.append((row, twin[0]))
    return pairs


def write_outputs(rows: Sequence[dict], summary: dict, out: Path) -> dict[str, Path]:
    """Writes ``accuracy.csv``, ``accuracy.png`` (Pareto plot) and ``accuracy.md`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": out / "accuracy.csv", "plot": out / "accuracy.png", "table": out / "accuracy.md"}
    with files["csv"].open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        f"Reference R1 ({summary['R1']}) vs. R2 ({summary['R2']}): body RMS "
        f"{summary['R1_vs_R2_body_rms_m'] * 1e3:.3f} mm, feedback RMS {summary['R1_vs_R2_feedback_rms_N']:.4f} N.",
        "",
    ]
    if "tension_only_R1" in summary:
        lines += [
            f"Tension-only rows are compared with their own reference, R1 ({summary['tension_only_R1']}); vs. R2 "
            f"({summary['tension_only_R2']}): body RMS {summary['tension_only_R1_vs_R2_body_rms_m'] * 1e3:.3f} mm, "
            f"feedback RMS {summary['tension_only_R1_vs_R2_feedback_rms_N']:.4f} N. The variant itself moves the "
            f"puppet by {summary['tension_only_vs_printed_body_rms_m'] * 1e3:.3f} mm body RMS "
            f"({summary['tension_only_vs_printed_feedback_rms_N']:.4f} N feedback RMS) from the printed-spring "
            "reference: a change of model, not an error.",
            "",
        ]
    twins = _float32_twins(rows)
    if twins:
        worst = max(abs(a["body_rms_m"] - b["body_rms_m"]) for a, b in twins)
        lines += [f"Float32 strings change the body RMS error by at most {worst * 1e9:.1f} nm from the float64 row "
                  f"with the same other settings ({len(twins)} pairs), below the table's 1 µm resolution.", ""]
    lines += [
        "| knob | particles | strings Hz | puppet Hz | precision | springs | contact | body RMS [mm] "
        "| feedback RMS [N] | wall s / sim s |",
        "|---|---:|---:|---:|---|---|---|---:|---:|---:|",
    ]
    for r in rows:
        mark = " **(paper)**" if r["paper"] else ""
        lines.append(f"| {r['knob']}{mark} | {r['particles']} | {r['string_hz']:g} | {r['puppet_hz']:g} "
                     f"| {r['precision']} | {r['springs']} | {r['contact']} | {r['body_rms_m'] * 1e3:.3f} "
                     f"| {r['feedback_rms_N']:.3f} | {r['wall_s_per_sim_s']:.4f} |")
    files["table"].write_text("\n".join(lines) + "\n")

    plt = headless_pyplot()

    fig, ax = plt.subplots(figsize=(8, 5.5))
    markers = {"particles": "o", "particles @ 1 kHz puppet": "v", "string_step": "s", "puppet_hz": "^",
               "precision": "P", "springs": "X", "contact": "D"}
    for knob, marker in markers.items():
        chosen = [r for r in rows if r["knob"] == knob]
        if chosen:
            ax.scatter([r["wall_s_per_sim_s"] for r in chosen], [r["body_rms_m"] * 1e3 for r in chosen],
                       marker=marker, s=45, label=knob.replace("_", " "))
            for r in chosen:
                value = {"particles": f"{r['particles']} p", "particles @ 1 kHz puppet": f"{r['particles']} p",
                         "string_step": f"{1e3 / r['string_hz']:g} ms",
                         "puppet_hz": f"{r['puppet_hz']:g} Hz", "contact": r["contact"],
                         "precision": "f32" if r["precision"] == "float32" else "f64",
                         "springs": "t-only" + (" f32" if r["precision"] == "float32" else "")}[knob]
                ax.annotate(value, (r["wall_s_per_sim_s"], r["body_rms_m"] * 1e3), fontsize=7,
                            xytext=(4, 3), textcoords="offset points")
    front = _pareto(rows)
    ax.plot([r["wall_s_per_sim_s"] for r in front], [r["body_rms_m"] * 1e3 for r in front], "k--", lw=0.8,
            label="Pareto front")
    paper = [r for r in rows if r["paper"]]
    if paper:
        ax.scatter([paper[0]["wall_s_per_sim_s"]], [paper[0]["body_rms_m"] * 1e3], marker="*", s=300,
                   facecolor="none", edgecolor="red", lw=1.5, label="paper's settings", zorder=5)
    ax.axvline(1.0, color="0.6", lw=0.8, ls=":", label="real time")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("cost: wall seconds per simulated second (one core)")
    ax.set_ylabel("error: RMS body position vs. reference [mm]")
    ax.set_title(f"What accuracy costs (reference gap {summary['R1_vs_R2_body_rms_m'] * 1e3:.3f} mm)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(files["plot"], dpi=120)
    plt.close(fig)
    return files
