"""Full marionette speed on one core: real-time factor at the paper's rates and fully coupled,
and the same marionette in MuJoCo timed in the same run.

Run:  python benchmarks/bench_marionette.py [--seconds 5] [--repeats 5] [--scalar]

The strings run the default laned step (``SolverStringImplicit.lanes``,
``kernels/string_step_lanes``: four strings per thread in SIMD lanes); ``--scalar`` adds both
configurations with the scalar one-launch kernel (``kernels/string_step``, the same numbers bit
for bit), the default before issue 19.

The scene is ``hanging`` (6 strings x 50 particles, 12 bodies, ground contact on, feedback
on), with its swaying bars. Each figure is the median over ``--repeats`` runs of the
stepping alone (captured CPU graphs, kernels compiled with optimisation beforehand; the
first run of this script compiles the puppet kernels, about a minute, then they are
cached). "spread" is (max - min) / median.

MuJoCo: the exported puppet (``dmarionette.articulation.mjcf``) with each string as a spatial tendon
from a mocap bar to the puppet's attach point, limited to the string's rest length (an
inextensible string that can go slack), at the string rate (1 ms, Euler), bars moved
every step. It is a coarser model than ours (no string mass, waves or ground contact of
strings), timed as a reference point for what a general-purpose engine costs.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import time
import xml.etree.ElementTree as ET

import numpy as np
import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel, bar_inputs  # noqa: E402
from dmarionette.marionette.rollout import simulate_marionette  # noqa: E402
from dmarionette.articulation.mjcf import puppet_to_mjcf  # noqa: E402


def _median_rate(run, seconds: float, repeats: int) -> tuple[float, float]:
    walls = [run() for _ in range(repeats)]
    median = statistics.median(walls)
    return seconds / median, (max(walls) - min(walls)) / median


def time_ours(scene, seconds: float, repeats: int, lanes: bool = True) -> tuple[float, float]:
    model = MarionetteModel(scene, optimization_level=2)
    model.string_solver.lanes = lanes
    simulate_marionette(model, 0.2, progress=False)  # compile + capture warm-up
    return _median_rate(lambda: simulate_marionette(model, seconds, progress=False).wall_seconds, seconds, repeats)


def mujoco_marionette(scene) -> tuple[str, MarionetteModel]:
    """MJCF of the puppet with the strings as limited tendons from mocap bars (see module doc)."""
    model = MarionetteModel(scene, optimization_level=0)
    xml = ET.fromstring(puppet_to_mjcf(scene.puppet, timestep=scene.string_dt, ground=True))
    bodies = {b.get("name"): b for b in xml.iter("body")}
    for point in scene.puppet.points:
        ET.SubElement(bodies[point.body], "site", name=f"point_{point.name}",
                      pos=" ".join(repr(float(c)) for c in point.position), size="0.005")
    world = xml.find("worldbody")
    tendon = ET.SubElement(xml, "tendon")
    for b, bar in enumerate(scene.bars):
        body = ET.SubElement(world, "body", name=f"bar_{bar.name}", mocap="true",
                             pos=" ".join(repr(float(c)) for c in bar.trajectory.positions[0]))
        for string_name, local in bar.attach.items():
            ET.SubElement(body, "site", name=f"top_{string_name}", pos=" ".join(repr(float(c)) for c in local),
                          size="0.005")
    for s, (spec, point) in enumerate(zip(model.strings.specs, scene.string_body_points)):
        spatial = ET.SubElement(tendon, "spatial", name=f"string_{spec.name}", limited="true",
                                range=f"0 {spec.length!r}")
        ET.SubElement(spatial, "site", site=f"top_{spec.name}")
        ET.SubElement(spatial, "site", site=f"point_{point}")
    return ET.tostring(xml, encoding="unicode"), model


def time_mujoco(scene, seconds: float, repeats: int) -> tuple[float, float]:
    import mujoco

    xml, model = mujoco_marionette(scene)
    mj = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(mj)
    steps = int(round(seconds / scene.string_dt))
    times = scene.string_dt * np.arange(1, steps + 1)
    bar_pos = bar_inputs(model, times)[1]  # (T, B, 3) bar centres

    def run() -> float:
        mujoco.mj_resetData(mj, data)
        start = time.perf_counter()
        for k in range(steps):
            data.mocap_pos[:] = bar_pos[k]
            mujoco.mj_step(mj, data)
        return time.perf_counter() - start

    run()
    return _median_rate(run, seconds, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--scalar", action="store_true", help="also with the scalar string kernel")
    args = parser.parse_args()
    scene = dm.load_scene("hanging")
    print(f"# Marionette benchmark — {platform.machine()}, Python {platform.python_version()}, "
          f"Warp {wp.config.version}; scene 'hanging'; median of {args.repeats} runs of {args.seconds:g} s\n")
    print("| configuration | real-time factor | spread |")
    print("|---|---:|---:|")
    rows = {}
    configurations = [("dmarionette, paper rates (strings 1 kHz, puppet 30 Hz)", {}, True),
                      ("dmarionette, fully coupled (strings and puppet 1 kHz)", {"puppet_hz": 1000.0}, True)]
    if args.scalar:
        configurations += [(label + ", scalar string kernel", changes, False) for label, changes, _ in configurations]
    for label, changes, lanes in configurations:
        rate, spread = time_ours(dataclasses.replace(scene, **changes), args.seconds, args.repeats, lanes)
        rows[label] = rate
        print(f"| {label} | {rate:.1f}x | {spread:.0%} |")
    try:
        rate, spread = time_mujoco(scene, args.seconds, args.repeats)
    except ImportError:
        print("| MuJoCo | not installed (pip install mujoco) | |")
        return
    print(f"| MuJoCo {__import__('mujoco').__version__}, puppet + 6 limited tendons, 1 ms Euler | {rate:.1f}x | "
          f"{spread:.0%} |")
    print()
    for label, ours in rows.items():
        print(f"- {label.removeprefix('dmarionette, ')}: {ours / rate:.2f} of MuJoCo's rate")


if __name__ == "__main__":
    main()
