"""Float32 strings inside the float64 marionette (``[solver] precision = "float32"``).

The puppet stays float64; the strings run in float32 and ``SolverMarionette`` converts what
crosses (``kernels/precision_boundary``). Checked here: the float32 marionette tracks the
float64 one within float32 rounding, at the paper's rates and fully coupled; its energy stays
within the bars' work (as the hard cases check it); the live loop's per-tick graphs give the
same float32 answer as the captured rollout; a float64 marionette launches no conversion;
gradients refuse float32. (The float64 path itself is unchanged: ``tests/marionette/test_marionette.py``
and the other marionette tests run it.)

**Tolerance.** A float32 coordinate of size ``X`` is rounded to within ``u X`` (``u = 2^-24``)
each time a string step writes it. Model: one such rounding per string step, uncorrelated
from step to step (round-to-nearest of a value that keeps changing), carried to the puppet
by the ties and not amplified, since the hanging marionette is damped (strings, ties and
joints all dissipate): the gap then grows like a random walk, ``sqrt(N) u X`` after ``N``
string steps, and that is asserted at every frame (``X`` = the largest coordinate of the
scene, 1.31 m; at 6 s, ``N = 6000``: 6.0e-6 m). The worst case, every rounding adding up in
one direction, would be ``N u X`` (4.7e-4 m), too loose to catch anything. Measured (6 s of
the ``hanging`` sway, body centres): largest gap 4.3e-7 m at 30 Hz and 6.0e-7 m with the
puppet at 1 kHz, at most 0.12x and 0.14x the random-walk bound at its frame; the gap does
not grow over the run (it stays at 1e-7 .. 6e-7 m from 0.5 s on), as a damped system's should.
"""

import dataclasses

import numpy as np
import pytest
import warp as wp

from dmarionette.marionette import solver as marionette_module
from dmarionette.marionette.solver import MarionetteModel, SolverMarionette
from dmarionette.marionette.energy import simulate_energy_balance
from dmarionette.grad.engine import MarionetteGradient
from dmarionette.marionette.rollout import simulate_marionette

from tests.support.hard_cases import TOL_ENERGY, energy_excess
from tests.support.live import drive_like_the_scene

wp.config.log_level = wp.LOG_WARNING
U32 = 2.0 ** -24  # float32 unit roundoff (round to nearest)
SECONDS = 6.0


def fast_model(scene, **changes):
    return MarionetteModel(dataclasses.replace(scene, **changes), optimization_level=0)


@pytest.fixture(scope="module", params=[30.0, 1000.0], ids=["puppet_30Hz", "puppet_1kHz"])
def pair(request, hanging):
    """The ``hanging`` sway for 6 s in float64 and with float32 strings, at one puppet rate."""
    runs = {}
    for precision in ("float64", "float32"):
        model = fast_model(hanging, precision=precision, puppet_hz=request.param)
        runs[precision] = (model, simulate_marionette(model, SECONDS, progress=False))
    return runs


def test_float32_strings_track_float64_within_float32_rounding(pair):
    model32, run32 = pair["float32"]
    model64, run64 = pair["float64"]
    assert model32.strings.scalar is wp.float32 and model32.strings.particle_mass.dtype == wp.float32
    assert model64.strings.scalar is wp.float64
    for name in ("particle_q", "body_pos", "tie_force", "bar_feedback", "bar_reaction"):
        value = getattr(run32, name)
        assert value.dtype == np.float64 and np.all(np.isfinite(value)), name
    scale = float(np.abs(run64.particle_q).max())  # X, the largest coordinate [m]
    gap = np.linalg.norm(run32.body_pos[:, :12] - run64.body_pos[:, :12], axis=2).max(axis=1)
    bound = np.sqrt(run64.frame_time / run64.string_dt) * U32 * scale  # sqrt(N) u X (module doc)
    print(f"\npuppet {1 / model32.puppet_dt:g} Hz: largest body gap {gap.max():.3e} m, "
          f"at most {np.max(gap[1:] / bound[1:]):.3f} x sqrt(N) u X (final bound {bound[-1]:.2e} m)")
    assert gap[0] == 0.0 and gap.max() > 0.0  # the same start; float32 really is float32
    assert np.all(gap <= bound)


def test_float32_marionette_gains_no_energy(hanging):
    """As the hard cases check it (``tests/marionette/test_hard_cases.py``): finite, and
    ``E(t) - E(0) <= W_bars + TOL_ENERGY`` at every frame. Float32 strings add a rounding of the
    energy read from float32 positions: each segment's ``k_s (l - d) dl`` with ``dl ~ u X``,
    about 1e-7 J per segment at the hanging stretch, 3e-5 J over the 294 segments, well inside
    TOL_ENERGY. Measured: largest excess -0.0116 J (energy only falls), bar work 0.036 J."""
    model = fast_model(hanging, precision="float32")
    r = simulate_energy_balance(model, SECONDS)
    excess = energy_excess(r)
    print(f"\nfloat32: largest excess {excess[1:].max():.3e} J, bar work {r['bar_work'][-1]:.4f} J")
    assert r["finite"]
    assert excess.max() <= TOL_ENERGY


def test_live_ticks_reproduce_the_float32_rollout(hanging):
    """The live loop's per-tick graphs (each converts its own bar tops) equal the captured
    rollout with float32 strings, and hand the view float64 particles."""
    model = fast_model(hanging, precision="float32")
    live, _, offline = drive_like_the_scene(model, 10)
    assert offline.frame_time[-1] == pytest.approx(live.time)
    np.testing.assert_allclose(live.state.puppet.joint_q.numpy()[0], offline.joint_q[-1], rtol=0, atol=1e-12)
    particles = live.latest_particle_q()
    assert particles.dtype == np.float64
    np.testing.assert_array_equal(particles, offline.particle_q[-1])


def test_float64_launches_no_conversion_and_float32_converts_each_crossing(hanging, monkeypatch):
    """Float64: the strings read the control buffers themselves (same memory) and nothing is
    converted. Float32: per puppet step, the tie path (2 arrays) once, and per string step the
    bar tops in and the tie force out: ``2 + 2 n`` conversions."""
    calls = []
    real = marionette_module.convert_vec3
    monkeypatch.setattr(marionette_module, "convert_vec3", lambda a, b, device: (calls.append(1), real(a, b, device)))
    for precision, expected in (("float64", 0), ("float32", None)):
        model = fast_model(hanging, precision=precision)
        solver = SolverMarionette(model)
        state, nxt, control = model.state(), model.state(), model.control()
        calls.clear()
        solver.step(state, nxt, control)
        if expected is None:
            expected = 2 + 2 * model.substeps
        assert len(calls) == expected, precision
        views = solver.string_controls(control)
        same = all(v.top_q.ptr == control.top_q[j].ptr for j, v in enumerate(views))
        assert same == (precision == "float64"), precision


def test_gradients_refuse_float32(hanging):
    scene = dataclasses.replace(hanging, precision="float32")
    with pytest.raises(ValueError, match=r"precision = 'float32'.*gradients of a marionette are float64 only"):
        MarionetteModel(scene, optimization_level=0, requires_grad=True)
    with pytest.raises(ValueError, match=r"precision = 'float32'.*MarionetteGradient needs a float64 marionette"):
        MarionetteGradient(fast_model(hanging, precision="float32"), puppet_steps=2)
