"""Width, interval score and CRPS of predictive depth distributions (metrics.interval_sharpness)."""

import math

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import norm

from stochastic_fields import metrics as M
from stochastic_fields.calibration import DepthFolds, QuantileCalibration, cross_fitted_depth_quantiles


def test_interval_score_by_hand():
    # alpha = 0.1: width + 20 x the miss
    gt = np.array([5.0, 0.0, 12.0])
    lo, hi = np.array([4.0, 1.0, 8.0]), np.array([6.0, 3.0, 10.0])
    got = M.interval_score(gt, lo, hi, 0.9).numpy()
    np.testing.assert_allclose(got, [2.0, 2.0 + 20.0 * 1.0, 2.0 + 20.0 * 2.0])


def test_gaussian_crps_against_quadrature():
    for y, mu, s in ((0.3, 0.0, 1.0), (5.0, 1.0, 0.2), (-2.0, 0.5, 3.0)):
        ref = integrate.quad(lambda x: (norm.cdf(x, mu, s) - (x >= y)) ** 2, mu - 40 * s, mu + 40 * s,
                             points=[y], limit=200)[0]
        assert float(M.gaussian_crps([y], [mu], [s])[0]) == pytest.approx(ref, rel=1e-6)


def test_quantile_crps_matches_the_closed_form():
    rng = np.random.default_rng(0)
    mu, s = rng.normal(10, 1, 200), rng.uniform(0.1, 2.0, 200)
    y = mu + s * rng.standard_normal(200) * 2.0
    q = mu[:, None] + s[:, None] * norm.ppf(M.crps_levels())[None]
    got = M.crps_from_quantiles(y, q).numpy()
    ref = M.gaussian_crps(y, mu, s).numpy()
    np.testing.assert_allclose(got, ref, rtol=5e-3)


def test_quantile_crps_of_a_point_mass_is_the_absolute_error():
    q = np.full((3, M.CRPS_NUM_LEVELS), 2.0)
    np.testing.assert_allclose(M.crps_from_quantiles([1.0, 2.0, 4.5], q).numpy(), [1.0, 0.0, 2.5], atol=1e-12)


def test_gaussian_quantiles_without_scale_are_the_normal_quantiles():
    t = np.array([0.01, 0.25, 0.5, 0.9, 0.995])
    got = M.gaussian_quantiles([2.0, -1.0], [0.5, 3.0], t)
    ref = np.stack([norm.ppf(t, 2.0, 0.5), norm.ppf(t, -1.0, 3.0)])
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)


def _heavy_tailed_case(n=4000, seed=1):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(2.0, 10.0, n)
    std = rng.uniform(0.05, 0.5, n)
    pred = gt + std * rng.standard_t(2.0, n)
    cal = QuantileCalibration.fit(np.abs(pred - gt)[: n // 2] / std[: n // 2], quantity="depth_std")
    return gt, pred, std, cal


def test_sharpness_coverage_agrees_with_the_calibration_curve():
    gt, pred, std, cal = _heavy_tailed_case()
    calibrated = cal.calibrated_std(std)
    iv = M.interval_sharpness(gt, lambda t: M.gaussian_quantiles(pred, calibrated, t, cal.relative_scale))
    ref = M.calibration_curve(gt, pred, calibrated, levels=list(M.INTERVAL_LEVELS),
                              interval_scale=cal.relative_scale).coverage
    np.testing.assert_allclose(iv["coverage"], ref, atol=1e-12)
    assert iv["coverage_95"] == pytest.approx(ref[3])
    # the width by hand: half-width = z_p s(p) raw std, relative to the truth
    z95 = norm.ppf(0.975)
    half = z95 * cal.scale_at(0.95) * std / gt
    assert iv["halfwidth_median_95"] == pytest.approx(float(np.median(half)), rel=1e-9)
    assert iv["halfwidth_p90_95"] == pytest.approx(float(np.quantile(half, 0.9)), rel=1e-9)
    lo, hi = pred - z95 * cal.scale_at(0.95) * std, pred + z95 * cal.scale_at(0.95) * std
    is95 = (hi - lo) + 40.0 * np.clip(lo - gt, 0, None) + 40.0 * np.clip(gt - hi, 0, None)
    assert iv["interval_score_95"] == pytest.approx(float(np.mean(is95 / gt)), rel=1e-9)


def test_sharpness_of_an_exact_gaussian():
    rng = np.random.default_rng(3)
    n = 20000
    mu, s = np.full(n, 10.0), np.full(n, 0.5)
    gt = mu + s * rng.standard_normal(n)
    iv = M.interval_sharpness(gt, lambda t: M.gaussian_quantiles(mu, s, t))
    for p, c in zip(M.INTERVAL_LEVELS, iv["coverage"]):
        assert c == pytest.approx(p, abs=0.01)
    # E CRPS of the true Gaussian = s / sqrt(pi)
    assert iv["crps"] == pytest.approx(float(np.mean(0.5 / math.sqrt(math.pi) / gt)), rel=0.02)


def test_interval_sharpness_rejects_bad_truth():
    with pytest.raises(ValueError, match="finite and > 0"):
        M.interval_sharpness([1.0, 0.0], lambda t: np.zeros((2, len(t))))


def test_cross_fitted_quantiles_use_each_fold_map():
    gt, pred, std, _ = _heavy_tailed_case(n=600)
    z = np.abs(pred - gt) / std
    maps = [QuantileCalibration.fit(z[:300] * f, quantity="depth_std") for f in (1.0, 3.0)]
    folds = DepthFolds([np.array([0]), np.array([1])], maps)
    fold = np.arange(600) % 2
    q = cross_fitted_depth_quantiles(pred, std, fold, folds)(np.array([0.025, 0.975]))
    for f, m in enumerate(maps):
        i = fold == f
        ref = M.gaussian_quantiles(pred[i], m.calibrated_std(std[i]), [0.025, 0.975], m.relative_scale)
        np.testing.assert_allclose(q[i], ref, rtol=1e-12)
    with pytest.raises(ValueError, match="no fold"):
        cross_fitted_depth_quantiles(pred, std, np.full(600, 2), folds)


def test_event_reliability_by_hand():
    p = np.array([0.0, 0.1, 0.15, 0.9, 0.95, 1.0, 0.5])
    o = np.array([0, 0, 1, 1, 1, 0, 1])
    r = M.event_reliability(p, o)
    # (0 + 0.01 + 0.7225 + 0.01 + 0.0025 + 1 + 0.25) / 7
    assert r["brier"] == pytest.approx(1.995 / 7, abs=1e-12)
    # bins [0, .1): {0} -> 0; [.1, .2): {.1, .15} vs 1/2 -> 2 * .375; [.5, .6): {.5} vs 1; [.9, 1]: {.9, .95, 1} vs 2/3
    assert r["ece"] == pytest.approx((0 + 0.75 + 0.5 + 3 * abs(0.95 - 2 / 3)) / 7, abs=1e-12)
    assert r["accuracy"] == pytest.approx(4 / 7)
    np.testing.assert_allclose(r["bin_count"], [1, 2, 1, 3])
    np.testing.assert_allclose(r["bin_freq"], [0, 0.5, 1, 2 / 3])
    assert (r["confident"], r["confident_wrong"]) == (2, 1)  # p = 0 (right) and p = 1 (wrong); 0.95 is not > 0.95


def test_event_reliability_of_perfect_and_bad_input():
    r = M.event_reliability([1.0, 0.0, 1.0], [1, 0, 1])
    assert r["brier"] == 0.0 and r["ece"] == 0.0 and r["accuracy"] == 1.0
    with pytest.raises(ValueError, match="outcomes must be 0 or 1"):
        M.event_reliability([0.5], [2])
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        M.event_reliability([1.5], [1])
    with pytest.raises(ValueError, match="at least one event"):
        M.event_reliability([], [])


def test_width_groups_by_hand():
    # six depths of 10, bands of half-widths 0.1 .. 0.6 (relative 1% .. 6%), errors chosen per value:
    # the narrowest two miss at every level, the middle two one each, the widest two hold at 95% and miss at 68%
    y = np.full(6, 10.0)
    half95 = np.array([0.3, 0.1, 0.4, 0.2, 0.6, 0.5])  # out of order: the groups sort by width
    err = np.array([0.5, 0.2, 0.0, 0.3, 0.5, 0.45])
    z95 = norm.ppf(0.975)
    std = half95 / z95
    iv = M.interval_sharpness(y, lambda t: M.gaussian_quantiles(y - err, std, t))
    g = iv["width_groups"]
    assert g["num_values"] == [2, 2, 2] and g["level"] == 0.95
    np.testing.assert_allclose(g["upper_edge"], [0.02, 0.04, 0.06], rtol=1e-9)
    np.testing.assert_allclose(g["halfwidth_median"], [0.015, 0.035, 0.055], rtol=1e-9)
    # narrowest third = values 1 (0.1, err 0.2) and 3 (0.2, err 0.3): both outside at every level
    assert iv["coverage_95_narrowest_third"] == 0.0 and iv["coverage_68_narrowest_third"] == 0.0
    # widest third = values 4 (0.6, err 0.5) and 5 (0.5, err 0.45): inside at 95%, outside at 68%
    # (68% half-width = z68 / z95 x 0.5 or 0.6 = 0.26 / 0.31 < the errors)
    assert iv["coverage_95_widest_third"] == 1.0 and iv["coverage_68_widest_third"] == 0.0
    assert iv["halfwidth_95_narrowest_third_max"] == pytest.approx(0.02, rel=1e-9)
    # the groups' coverage averages to the pool's (equal sizes)
    np.testing.assert_allclose(np.mean(g["coverage"], axis=0), iv["coverage"], atol=1e-12)


def test_width_groups_need_as_many_values_as_groups():
    iv = M.interval_sharpness([5.0, 6.0], lambda t: M.gaussian_quantiles([5.0, 6.0], [0.1, 0.2], t))
    assert iv["width_groups"]["coverage"] == [] and math.isnan(iv["coverage_95_narrowest_third"])
    assert math.isnan(iv["halfwidth_95_narrowest_third_max"])
    # unequal sizes: 7 values -> 3, 2, 2 (numpy's array_split), ties kept in input order
    y = np.full(7, 4.0)
    iv = M.interval_sharpness(y, lambda t: M.gaussian_quantiles(y, np.full(7, 0.1), t))
    assert iv["width_groups"]["num_values"] == [3, 2, 2]
