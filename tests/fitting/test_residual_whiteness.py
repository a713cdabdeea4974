"""The whiteness test of calibration residuals (fitting/residual_whiteness.py): its statistic is
standard normal under white noise, and structure (correlated noise, a slow error) is caught."""

import numpy as np

from fitting.residual_whiteness import Z_LIMIT, lag1_whiteness


def test_the_lag1_autocorrelation_has_its_exact_white_noise_variance():
    """``Var rho = (T - 1) / (T (T + 2))`` for Gaussian white noise (no mean removed), ``E rho = 0``."""
    rng = np.random.default_rng(0)
    for t in (5, 30):
        r = rng.standard_normal((t, 40_000))
        rho = np.sum(r[1:] * r[:-1], axis=0) / np.sum(r * r, axis=0)
        expected = (t - 1) / (t * (t + 2))
        # the sample variance of 40,000 draws has a relative sampling error ~ sqrt(2 / 40,000) = 0.7 %
        assert abs(rho.var() / expected - 1.0) < 0.03, (t, rho.var(), expected)
        assert abs(rho.mean()) < 4 * np.sqrt(expected / 40_000)


def test_white_noise_gives_a_standard_normal_z_and_rarely_a_false_alarm():
    rng = np.random.default_rng(1)
    z = np.array([lag1_whiteness([rng.standard_normal((30, 36)), rng.standard_normal((12, 36))])["z"]
                  for _ in range(2000)])
    # mean 0 and deviation 1, each within 4 sampling errors of 2000 draws (0.022 and 0.016)
    assert abs(z.mean()) < 0.09 and abs(z.std() - 1.0) < 0.07, (z.mean(), z.std())
    assert np.sum(z > Z_LIMIT) == 0  # 2000 draws at a false-alarm rate of 3.2e-5


def test_structure_is_caught_and_scale_does_not_matter():
    rng = np.random.default_rng(2)
    t = np.arange(30)[:, None]
    noise = rng.standard_normal((30, 36))
    # a slow error of 0.8 noise deviations (chi^2 1.64) with a different phase per channel
    slow = 0.8 * np.sqrt(2) * np.sin(2 * np.pi * t / 30 + np.arange(36)[None, :])
    structured = lag1_whiteness([noise + slow])
    assert structured["structured"] and structured["z"] > 2 * Z_LIMIT, structured
    scaled = lag1_whiteness([1e-4 * (noise + slow)])  # the noise scale cancels
    assert abs(scaled["z"] - structured["z"]) < 1e-9
    ar = np.zeros((200, 6))  # AR(1) noise, phi = 0.3: correlated noise is reported too
    e = rng.standard_normal((200, 6))
    for k in range(1, 200):
        ar[k] = 0.3 * ar[k - 1] + e[k]
    assert lag1_whiteness([ar])["structured"]
    assert not lag1_whiteness([noise])["structured"]


def test_short_or_empty_channels_are_skipped():
    assert lag1_whiteness([np.ones((3, 5))]) is None  # fewer than 4 samples per channel
    result = lag1_whiteness([np.concatenate([np.zeros((10, 1)), np.ones((10, 2))], axis=1)])
    assert result["channels"] == 2 and result["samples"] == 20
