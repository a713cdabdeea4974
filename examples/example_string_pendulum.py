"""A load on a string swings as a pendulum; its period matches 2 pi sqrt(L/g).

Run:  python examples/example_string_pendulum.py
"""

import math

import numpy as np
import warp as wp

import dmarionette as dm

wp.config.log_level = wp.LOG_WARNING


def main(swings: float = 3.0) -> dict:
    """Simulates a 0.5 m pendulum for ``swings`` periods; returns the measured and expected period."""
    g, length, theta, load, stiffness = 9.81, 0.5, 0.05, 0.1, 2000.0
    # Start at the stretched length the load holds the string at, so it does not bounce.
    arm = length + g * load / stiffness
    top = (0.0, 1.0, 0.0)
    bottom = (arm * math.sin(theta), 1.0 - arm * math.cos(theta), 0.0)
    spec = dm.StringSpec(name="pendulum", top=top, bottom=bottom, length=length, particle_count=20,
                         mass=1e-4, load_mass=load, stiffness=stiffness, internal_friction=0.0, air_drag=0.0)
    effects = dm.StringEffects(internal_friction=False, air_drag=False, ground_contact=False)
    model = dm.StringModel([spec], effects=effects, gravity=(0.0, -g, 0.0), ground_height=0.0)
    dt, chunk = 1e-3, 10
    expected = 2 * math.pi * math.sqrt(arm / g) * (1 + theta**2 / 16)
    steps = chunk * int(swings * expected / (dt * chunk))
    rollout = dm.StringRollout(dm.SolverStringImplicit(model), dt, chunk_steps=chunk)
    result = rollout.run(model.state(), np.broadcast_to(np.array([top]), (steps, 1, 3)))
    x = result.frames[:, -1, 0]
    t = dt * chunk * np.arange(1, len(x) + 1)
    i = np.nonzero(np.signbit(x[:-1]) != np.signbit(x[1:]))[0]
    crossings = t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])
    measured = 2 * float(np.mean(np.diff(crossings)))
    return {"measured_period_s": measured, "expected_period_s": expected}


def check(result: dict) -> None:
    """The period agrees to 0.1 % (tests/strings/test_string_physics.py derives a 3e-4 bound)."""
    assert abs(result["measured_period_s"] - result["expected_period_s"]) < 1e-3 * result["expected_period_s"]


if __name__ == "__main__":
    out = main()
    check(out)
    print(f"period: measured {out['measured_period_s']:.4f} s, 2 pi sqrt(L/g) (1 + theta^2/16) = "
          f"{out['expected_period_s']:.4f} s")
