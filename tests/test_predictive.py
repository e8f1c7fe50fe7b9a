"""Gaussian-mixture predictive depth and its PIT recalibration (predictive.py) against references."""

import numpy as np
import pytest
from scipy import optimize
from scipy.stats import norm

from stochastic_fields import metrics as M
from stochastic_fields.predictive import (PitCalibration, mixture_cdf, mixture_quantiles, neighbourhood_weights,
                                          recalibrated_mixture_quantiles)


def _two_surfaces():
    # a pixel whose mass splits between a near leaf (70%) and the wall behind it (30%), and a plain one
    means = np.array([[2.0, 5.0], [3.0, 3.0]])
    stds = np.array([[0.05, 0.2], [0.1, 0.1]])
    weights = np.array([[0.7, 0.3], [0.5, 0.5]])
    return means, stds, weights


def test_mixture_cdf_against_scipy():
    means, stds, weights = _two_surfaces()
    x = np.array([[1.9, 2.5, 4.9, 6.0], [2.8, 3.0, 3.1, 9.0]])
    ref = sum(weights[:, m, None] * norm.cdf(x, means[:, m, None], stds[:, m, None]) for m in range(2))
    np.testing.assert_allclose(mixture_cdf(x, means, stds, weights), ref, rtol=1e-12)


def test_mixture_quantiles_against_scipy_root_finding():
    means, stds, weights = _two_surfaces()
    t = np.array([0.025, 0.5, 0.69, 0.71, 0.975])
    got = mixture_quantiles(t, means, stds, weights)
    for i in range(2):
        for j, level in enumerate(t):
            f = lambda x: sum(weights[i, m] * norm.cdf(x, means[i, m], stds[i, m]) for m in range(2)) - level  # noqa
            assert got[i, j] == pytest.approx(optimize.brentq(f, -10, 20, xtol=1e-14), abs=1e-9)
    # the two-surface pixel: its median on the leaf, its 97.5% quantile on the wall
    assert got[0, 1] == pytest.approx(2.0 + 0.05 * norm.ppf(0.5 / 0.7), abs=1e-9)
    assert 4.5 < got[0, 4] < 5.5


def test_the_95_interval_covers_a_far_surface_only_where_there_is_one():
    means, stds, weights = _two_surfaces()
    q = mixture_quantiles(np.array([0.025, 0.975]), means, stds, weights)
    assert q[0, 1] - q[0, 0] > 2.5            # spans leaf and wall
    assert q[1, 1] - q[1, 0] == pytest.approx(2 * 1.959964 * 0.1, rel=1e-5)  # a plain Gaussian


def test_one_component_mixture_is_the_gaussian():
    t = np.linspace(0.01, 0.99, 7)
    got = mixture_quantiles(t, np.array([[4.0]]), np.array([[0.3]]), np.array([[1.0]]))
    np.testing.assert_allclose(got[0], norm.ppf(t, 4.0, 0.3), atol=1e-9)


def test_huge_and_tiny_scales():
    means = np.array([[1e3, 1e3 + 1e-6], [0.0, 1e6]])
    stds = np.array([[1e-9, 1e-9], [1e-3, 1e5]])
    weights = np.array([[0.5, 0.5], [0.5, 0.5]])
    q = mixture_quantiles(np.array([0.25, 0.75]), means, stds, weights)
    assert np.isfinite(q).all()
    assert q[0, 0] == pytest.approx(1e3, abs=1e-8) and q[0, 1] == pytest.approx(1e3 + 1e-6, abs=1e-8)
    # float64 resolves 1e3 to 1.1e-13, i.e. 1e-4 of a 1e-9 std: the CDF is exact to that
    np.testing.assert_allclose(mixture_cdf(q, means, stds, weights), [[0.25, 0.75]] * 2, atol=1e-4)


def test_bad_mixtures_are_refused():
    with pytest.raises(ValueError, match="sum to one"):
        mixture_cdf([1.0], [[1.0, 2.0]], [[1.0, 1.0]], [[0.5, 0.6]])
    with pytest.raises(ValueError, match="stds finite and > 0"):
        mixture_cdf([1.0], [[1.0]], [[0.0]], [[1.0]])
    with pytest.raises(ValueError, match="strictly between"):
        mixture_quantiles(np.array([0.0, 0.5]), [[1.0]], [[1.0]], [[1.0]])


def test_pit_recalibration_restores_coverage_of_a_too_narrow_gaussian():
    rng = np.random.default_rng(0)
    n = 20000
    mu, s = rng.uniform(5, 10, n), rng.uniform(0.1, 0.3, n)
    gt = mu + 3.0 * s * rng.standard_normal(n)  # the true spread is 3x the predicted one
    comps = (mu[:, None], s[:, None], np.ones((n, 1)))
    half = n // 2
    pit = PitCalibration.fit(mixture_cdf(gt[:half], *(c[:half] for c in comps)))
    q = lambda t: recalibrated_mixture_quantiles(t, *(c[half:] for c in comps), pit)  # noqa: E731
    iv = M.interval_sharpness(gt[half:], q)
    for p, c in zip(M.INTERVAL_LEVELS, iv["coverage"]):
        assert c == pytest.approx(p, abs=0.015)
    # and the width is the truth's: 95% half-width ~ 1.96 x 3 s
    assert iv["halfwidth_median_95"] == pytest.approx(float(np.median(1.96 * 3 * s[half:] / gt[half:])), rel=0.05)


def test_pit_fit_refuses_bad_values():
    with pytest.raises(ValueError, match="at least"):
        PitCalibration.fit(np.full(10, 0.5))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        PitCalibration.fit(np.full(100, 1.5))


def test_neighbourhood_weights():
    op = np.array([[0.9, 0.9, 0.1, 0.9], [0.2, 0.1, 0.1, 0.1]])
    w = neighbourhood_weights(op, 0.5, 0.5)
    np.testing.assert_allclose(w[0], [0.5 / (0.5 + 2 / 6), 1 / 6 / (0.5 + 2 / 6), 0.0, 1 / 6 / (0.5 + 2 / 6)])
    np.testing.assert_allclose(w[1], [1.0, 0.0, 0.0, 0.0])  # no neighbour with a surface: the pixel alone
