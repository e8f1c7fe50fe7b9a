"""Evaluation metrics against scipy, brute-force float64 loops, Monte-Carlo and hand values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats
import torch

from stochastic_fields.constants import DEPTH_NLL_VARIANCE_FLOOR, NLL_VARIANCE_FLOOR
from stochastic_fields import metrics as M
from stochastic_fields.plots import plot_calibration, plot_sparsification


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# ---------------------------------------------------------------------------------- NLL


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gaussian_nll_matches_scipy_with_floor(rng, dtype):
    shape = (5, 7, 3)
    gt = rng.uniform(0, 1, shape)
    mean = gt + rng.normal(0, 0.05, shape)
    var = rng.uniform(0, 4 * NLL_VARIANCE_FLOOR, shape)  # about a quarter below the floor
    var[0, 0, 0] = 0.0
    assert (var < NLL_VARIANCE_FLOOR).mean() > 0.1
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    # reference from float32-rounded inputs when the inputs are float32
    g64, m64, v64 = (t(a).double().numpy() for a in (gt, mean, var))
    ref = -scipy.stats.norm.logpdf(g64, loc=m64, scale=np.sqrt(np.maximum(v64, NLL_VARIANCE_FLOOR)))
    got = M.gaussian_nll(t(gt), t(mean), t(var))
    assert isinstance(got, float)
    assert got == pytest.approx(ref.mean(), rel=1e-12)
    per_pixel = M.gaussian_nll(t(gt), t(mean), t(var), reduce=False)
    assert per_pixel.shape == (5, 7)
    np.testing.assert_allclose(per_pixel.numpy(), ref.mean(-1), rtol=1e-12)
    np.testing.assert_allclose(M.gaussian_nll_per_pixel(g64, m64, v64).numpy(), ref.mean(-1), rtol=1e-12)


def test_gaussian_nll_floor_is_exact_and_constant_included():
    gt, mean = np.array([[0.3, 0.5, 0.7]]), np.array([[0.31, 0.5, 0.69]])
    below = M.gaussian_nll(gt, mean, np.full((1, 3), NLL_VARIANCE_FLOOR / 10))
    at = M.gaussian_nll(gt, mean, np.full((1, 3), NLL_VARIANCE_FLOOR))
    above = M.gaussian_nll(gt, mean, np.full((1, 3), NLL_VARIANCE_FLOOR * 10))
    assert below == at and above != at
    # gt == mean, var == 1: NLL is exactly 0.5 log(2 pi)
    assert M.gaussian_nll(np.zeros((2, 3)), np.zeros((2, 3)), np.ones((2, 3))) == pytest.approx(
        0.5 * math.log(2 * math.pi), rel=1e-15
    )
    custom = M.gaussian_nll(gt, mean, np.zeros((1, 3)), var_floor=0.25)
    assert custom == pytest.approx(-scipy.stats.norm.logpdf(gt, mean, 0.5).mean(), rel=1e-12)


def test_gaussian_nll_rejects_bad_inputs():
    z = np.zeros((2, 3))
    with pytest.raises(ValueError, match="negative"):
        M.gaussian_nll(z, z, -np.ones((2, 3)))
    with pytest.raises(ValueError, match="shapes"):
        M.gaussian_nll(z, np.zeros((2, 2)), z)
    with pytest.raises(ValueError, match="non-finite"):
        M.gaussian_nll(np.full((2, 3), np.nan), z, z)
    with pytest.raises(ValueError, match="var_floor"):
        M.gaussian_nll(z, z, z, var_floor=0.0)


# ---------------------------------------------------------------------------------- correlation


def test_pearson_spearman_match_scipy_with_ties(rng):
    x = np.round(rng.normal(size=500), 1)  # many ties
    y = np.round(0.6 * x + rng.normal(size=500), 1)
    assert len(np.unique(x)) < 100 and len(np.unique(y)) < 100
    p, s = M.pearson(torch.as_tensor(x), y), M.spearman(x, torch.as_tensor(y))
    assert p.defined and s.defined and p.reason is None and p.n == 500
    assert p.value == pytest.approx(scipy.stats.pearsonr(x, y)[0], abs=1e-12)
    assert s.value == pytest.approx(scipy.stats.spearmanr(x, y)[0], abs=1e-12)
    np.testing.assert_allclose(M.average_ranks(torch.as_tensor(x)).numpy(), scipy.stats.rankdata(x))
    # a monotone but non-linear relation: Spearman exactly 1, Pearson below 1
    z = rng.uniform(0, 3, 200)
    assert M.spearman(z, np.exp(3 * z)).value == pytest.approx(1.0, abs=1e-12)
    assert M.pearson(z, np.exp(3 * z)).value < 0.95


def test_correlation_undefined_for_constant_input(rng):
    x = rng.normal(size=50)
    for fn in (M.pearson, M.spearman):
        r = fn(x, np.full(50, 0.1), x_name="error", y_name="uncertainty")
        assert not r.defined and math.isnan(r.value) and r.reason == "constant uncertainty"
        r = fn(np.ones(3), np.ones(3))
        assert not r.defined and r.reason == "constant x and constant y"
        r = fn([1.0], [2.0])
        assert not r.defined and "fewer than 2" in r.reason
    with pytest.raises(ValueError, match="values"):
        M.pearson(np.ones(3), np.ones(4))


def test_mse_uncertainty_correlation(rng):
    gt = rng.uniform(0, 1, (8, 9, 3))
    var = rng.uniform(1e-4, 1e-2, (8, 9, 3))
    mean = gt + rng.normal(size=(8, 9, 3)) * np.sqrt(var)
    res = M.mse_uncertainty_correlation(gt, mean, var)
    mse, unc = ((gt - mean) ** 2).mean(-1).ravel(), var.mean(-1).ravel()
    assert res["pearson"].value == pytest.approx(scipy.stats.pearsonr(mse, unc)[0], abs=1e-12)
    assert res["spearman"].value == pytest.approx(scipy.stats.spearmanr(mse, unc)[0], abs=1e-12)
    assert res["pearson"].value > 0.2  # errors were drawn with these variances
    const = M.mse_uncertainty_correlation(gt, mean, np.full_like(var, 0.01))
    assert not const["pearson"].defined and const["pearson"].reason == "constant uncertainty"
    assert not const["spearman"].defined and math.isnan(const["spearman"].value)


# ---------------------------------------------------------------------------------- sparsification


def _brute_force_ause(errors, uncertainty, num_fractions, metric):
    """Explicit python loop over fractions, float64."""
    e = np.abs(np.asarray(errors, dtype=np.float64))
    u = np.asarray(uncertainty, dtype=np.float64)
    p = len(e)

    def curve(order):
        out = []
        for i in range(num_fractions):
            kept = [e[j] for j in order[(i * p) // num_fractions:]]
            if metric == "rmse":
                out.append(math.sqrt(sum(k * k for k in kept) / len(kept)))
            else:
                out.append(sum(kept) / len(kept))
        return out

    model = curve(np.argsort(-u, kind="stable"))
    oracle = curve(np.argsort(-e, kind="stable"))
    area = 0.0
    for i in range(num_fractions - 1):
        d0, d1 = model[i] - oracle[i], model[i + 1] - oracle[i + 1]
        area += 0.5 * (d0 + d1) / num_fractions
    return model, oracle, area


@pytest.mark.parametrize("metric", ["rmse", "mae"])
@pytest.mark.parametrize("p", [1, 7, 101, 523])
def test_ause_equals_brute_force(rng, metric, p):
    errors = rng.normal(size=p)
    uncertainty = np.round(np.abs(errors) + rng.uniform(0, 1, p), 1)  # informative, with ties
    res = M.sparsification_curve(torch.as_tensor(errors), uncertainty, metric=metric)
    model, oracle, area = _brute_force_ause(errors, uncertainty, 100, metric)
    np.testing.assert_allclose(res.model, model, rtol=1e-12)
    np.testing.assert_allclose(res.oracle, oracle, rtol=1e-12)
    np.testing.assert_allclose(res.fractions, np.arange(100) / 100)
    assert res.ause == pytest.approx(area, rel=1e-10, abs=1e-14)
    assert res.reference == pytest.approx(model[0], rel=1e-14)
    np.testing.assert_allclose(res.model_normalised, np.asarray(model) / model[0], rtol=1e-12)
    assert res.ause_normalised == pytest.approx(area / model[0], rel=1e-10, abs=1e-14)
    assert M.ause(errors, uncertainty, metric=metric) == res.ause


def test_ause_hand_value():
    # errors 1..4, uncertainty reversed, 4 fractions: oracle MAE [2.5, 2, 1.5, 1], model [2.5, 3, 3.5, 4]
    res = M.sparsification_curve([1.0, 2.0, 3.0, 4.0], [4.0, 3.0, 2.0, 1.0], num_fractions=4, metric="mae")
    np.testing.assert_allclose(res.oracle, [2.5, 2.0, 1.5, 1.0])
    np.testing.assert_allclose(res.model, [2.5, 3.0, 3.5, 4.0])
    assert res.ause == pytest.approx(0.25 * (0 / 2 + 1 + 2 + 3 / 2))  # 1.125
    assert res.ause_normalised == pytest.approx(1.125 / 2.5)


def test_ause_oracle_random_reversed_ordering(rng):
    errors = np.abs(rng.normal(size=2000))
    oracle = M.sparsification_curve(errors, errors)
    assert oracle.ause == 0.0
    np.testing.assert_array_equal(oracle.model, oracle.oracle)
    reversed_ = M.ause(errors, -errors)
    random_ = M.ause(errors, rng.uniform(size=2000))
    assert 0.0 < random_ < reversed_
    assert 0.0 < M.ause(errors, rng.uniform(size=2000), normalised=True) < M.ause(errors, -errors, normalised=True)


def test_sparsification_ties_are_stable_and_zero_errors():
    # all-equal uncertainty: stable sort removes pixels in input order
    res = M.sparsification_curve([5.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], num_fractions=4, metric="mae")
    np.testing.assert_allclose(res.model, [1.25, 0.0, 0.0, 0.0])
    res = M.sparsification_curve([0.0, 0.0, 0.0, 5.0], [1.0, 1.0, 1.0, 1.0], num_fractions=4, metric="mae")
    np.testing.assert_allclose(res.model, [1.25, 5 / 3, 2.5, 5.0])
    zero = M.sparsification_curve(np.zeros(10), np.arange(10.0))
    assert zero.ause == 0.0 and math.isnan(zero.ause_normalised)
    with pytest.raises(ValueError, match="metric"):
        M.sparsification_curve(np.ones(3), np.ones(3), metric="mse")
    with pytest.raises(ValueError, match="non-finite"):
        M.sparsification_curve(np.array([1.0, np.inf]), np.ones(2))


def test_colour_and_depth_sparsification_helpers(rng):
    gt = rng.uniform(0, 1, (6, 5, 3))
    mean = gt + rng.normal(0, 0.1, (6, 5, 3))
    var = rng.uniform(0, 1, (6, 5, 3))
    res = M.colour_sparsification(gt, mean, var)
    e = np.sqrt(((gt - mean) ** 2).mean(-1)).ravel()
    model, _, area = _brute_force_ause(e, var.mean(-1).ravel(), 100, "rmse")
    # at f = 0 the rmse curve is the RMSE over all channel values
    assert res.model[0] == pytest.approx(np.sqrt(((gt - mean) ** 2).mean()), rel=1e-12)
    assert res.ause == pytest.approx(area, rel=1e-10)
    d_gt = rng.uniform(1, 5, (6, 5))
    d_gt[0, :] = 0.0  # invalid
    d_pred, d_var = d_gt + rng.normal(0, 0.2, (6, 5)), rng.uniform(0, 1, (6, 5))
    res = M.depth_sparsification(d_pred, d_gt, d_var, metric="mae")
    ok = d_gt > 0
    ref = M.sparsification_curve(d_pred[ok] - d_gt[ok], d_var[ok], metric="mae")
    assert res.num_pixels == 25 and res.ause == ref.ause


# ---------------------------------------------------------------------------------- calibration


def _brute_force_coverage(gt, mean, std, levels):
    z = scipy.stats.norm.ppf((1 + levels) / 2)
    return np.array([np.mean(np.abs(gt - mean) <= zp * std) for zp in z])


def test_calibration_of_samples_from_prediction(rng):
    n = 40000
    mean = rng.uniform(0, 1, (n // 4, 4))
    std = rng.uniform(0.01, 0.3, (n // 4, 4))
    gt = mean + std * rng.normal(size=mean.shape)
    res = M.calibration_curve(gt, mean, std)
    np.testing.assert_allclose(res.levels, np.linspace(0.01, 0.99, 99))
    np.testing.assert_allclose(res.coverage, _brute_force_coverage(gt, mean, std, res.levels), atol=1.0 / n)
    # MC: each coverage has std <= sqrt(0.25 / n) = 0.0025
    assert res.auce < 0.006
    assert np.abs(res.coverage - res.levels).max() < 0.012
    assert res.num_values == n


def test_calibration_detects_over_and_under_confidence(rng):
    mean = rng.uniform(0, 1, (100, 100, 3))
    std = rng.uniform(0.01, 0.3, (100, 100, 3))
    gt = mean + std * rng.normal(size=mean.shape)
    over = M.calibration_curve(torch.as_tensor(gt), mean, 0.5 * std)
    assert over.verdict == "overconfident" and over.signed_gap < -0.1
    assert (over.coverage < over.levels).all()
    analytic = 2 * scipy.stats.norm.cdf(0.5 * scipy.stats.norm.ppf((1 + over.levels) / 2)) - 1
    np.testing.assert_allclose(over.coverage, analytic, atol=0.012)
    assert over.auce == pytest.approx(np.abs(analytic - over.levels).mean(), abs=0.005)
    under = M.calibration_curve(gt, mean, 2.0 * std)
    assert under.verdict == "underconfident" and (under.coverage > under.levels).all()
    # per channel: only channel 1 is overconfident; pooled coverage = mean of channel coverages
    std_mix = std.copy()
    std_mix[..., 1] *= 0.5
    per = M.calibration_curve_per_channel(gt, mean, std_mix)
    assert len(per) == 3 and all(r.num_values == 100 * 100 for r in per)
    assert per[1].verdict == "overconfident" and per[0].auce < 0.02 and per[2].auce < 0.02
    pooled = M.calibration_curve(gt, mean, std_mix)
    np.testing.assert_allclose(pooled.coverage, np.mean([r.coverage for r in per], axis=0), atol=1e-12)


def test_calibration_depth_with_mask_and_zero_std():
    gt = np.array([[1.0, 2.0], [3.0, 0.0]])
    mean = np.array([[1.0, 2.5], [3.0, 9.0]])
    std = np.array([[0.0, 0.0], [1.0, 1.0]])
    mask = gt > 0
    res = M.calibration_curve(gt, mean, std, levels=[0.5, 0.9], mask=mask)
    # pixel 0: exact hit with std 0 (inside), pixel 1: miss with std 0 (outside), pixel 2: inside
    np.testing.assert_allclose(res.coverage, [2 / 3, 2 / 3])
    assert res.num_values == 3
    with pytest.raises(ValueError, match="levels"):
        M.calibration_curve(gt, mean, std, levels=[0.0, 0.5])
    with pytest.raises(ValueError, match="mask"):
        M.calibration_curve(gt, mean, std, mask=np.ones(3, dtype=bool))


# ---------------------------------------------------------------------------------- image quality


def test_psnr_hand_value(rng):
    gt = rng.uniform(0.2, 0.8, (12, 10, 3))
    assert M.psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    assert M.psnr(torch.as_tensor(gt - 0.01, dtype=torch.float32), torch.as_tensor(gt, dtype=torch.float32)) == (
        pytest.approx(40.0, abs=1e-3)
    )
    assert M.psnr(gt * 255 + 25.5, gt * 255, max_val=255.0) == pytest.approx(20.0, abs=1e-9)


def test_ssim_identity_and_constant_images(rng):
    x = rng.uniform(0, 1, (24, 20, 3))
    assert M.ssim(x, x) == pytest.approx(1.0, abs=1e-9)  # kornia adds eps=1e-12 to the denominator
    assert M.ssim(x, np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1)) < 0.9
    a, b = np.full((16, 16, 3), 0.2), np.full((16, 16, 3), 0.6)
    c1, c2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2
    # flat images: zero (co)variances; kornia adds eps = 1e-12 to the denominator
    expected = (2 * 0.2 * 0.6 + c1) * c2 / ((0.2**2 + 0.6**2 + c1) * c2 + 1e-12)
    assert M.ssim(a, b) == pytest.approx(expected, rel=1e-10)
    assert M.ssim(a[..., 0], b[..., 0]) == pytest.approx(M.ssim(a, b), rel=1e-12)
    with pytest.raises(ValueError, match="shape"):
        M.ssim(np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8, 3)))


# ---------------------------------------------------------------------------------- depth


def test_depth_errors_hand_values():
    pred = np.array([1.0, 2.0, 4.0, 7.0])
    gt = np.array([2.0, 2.0, 2.0, 0.0])  # last pixel has no ground truth
    d = M.depth_errors(pred, gt)
    assert d["abs_rel"] == pytest.approx((0.5 + 0.0 + 1.0) / 3)
    assert d["rmse"] == pytest.approx(math.sqrt(5 / 3))
    assert d["mae"] == pytest.approx(1.0)
    assert d["num_pixels"] == 3
    d2 = M.depth_errors(torch.as_tensor(pred), gt, mask=np.array([True, False, True, False]))
    assert d2["mae"] == pytest.approx(1.5) and d2["abs_rel"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="not finite and > 0"):
        M.depth_errors(pred, gt, mask=np.ones(4, dtype=bool))
    with pytest.raises(ValueError, match="no valid depth"):
        M.depth_errors(pred, np.zeros(4))


def test_depth_nll_matches_scipy(rng):
    gt = rng.uniform(1, 5, (7, 6))
    gt[0, 0] = 0.0
    mean = gt + rng.normal(0, 0.01, gt.shape)
    var = rng.uniform(0, 3 * DEPTH_NLL_VARIANCE_FLOOR, gt.shape)
    ok = gt > 0
    ref = -scipy.stats.norm.logpdf(gt[ok], mean[ok], np.sqrt(np.maximum(var[ok], DEPTH_NLL_VARIANCE_FLOOR)))
    assert M.depth_nll(gt, mean, var) == pytest.approx(ref.mean(), rel=1e-12)
    np.testing.assert_allclose(M.depth_nll(gt, mean, var, reduce=False).numpy(), ref, rtol=1e-12)
    assert M.depth_nll(gt, mean, var, var_floor=1.0) == pytest.approx(
        -scipy.stats.norm.logpdf(gt[ok], mean[ok], 1.0).mean(), rel=1e-12
    )


# ---------------------------------------------------------------------------------- report and plots


def test_metric_report_means_and_conventions():
    report = M.MetricReport()
    undefined = M.CorrelationResult(float("nan"), False, "constant uncertainty", 10)
    report.add("v0", psnr=20.0, pearson=M.CorrelationResult(0.5, True, None, 10), nll=torch.tensor(1.0))
    report.add("v1", psnr=30.0, pearson=undefined, nll=3.0)
    assert report.means() == {"psnr": 25.0, "pearson": 0.5, "nll": 2.0}
    assert report.per_view["pearson"][0] == 0.5 and math.isnan(report.per_view["pearson"][1])
    s = report.summary()
    assert s["pearson"]["num_undefined"] == 1 and s["psnr"]["num_views"] == 2
    text = report.format("LLFF fern")
    assert "nll_variance_floor" in text and f"{NLL_VARIANCE_FLOOR:.6g}" in text and "1 undefined" in text
    assert "i = 0..99" in report.conventions["ause_fractions"]
    assert report.to_dict()["views"] == ["v0", "v1"]
    with pytest.raises(ValueError, match="metrics"):
        report.add("v2", psnr=1.0)


def test_plots_write_png(tmp_path, rng):
    errors = np.abs(rng.normal(size=300))
    sp = {"S-NeRF": M.sparsification_curve(errors, errors + rng.uniform(0, 1, 300)),
          "random": M.sparsification_curve(errors, rng.uniform(size=300))}
    mean, std = rng.uniform(size=500), rng.uniform(0.1, 0.2, 500)
    gt = mean + std * rng.normal(size=500)
    cal = {"S-NeRF": M.calibration_curve(gt, mean, std), "overconfident": M.calibration_curve(gt, mean, 0.5 * std)}
    for path in (plot_sparsification(sp, tmp_path / "sub" / "sparsification.png"),
                 plot_calibration(cal, tmp_path / "calibration.png")):
        data = path.read_bytes()
        assert len(data) > 1000 and data[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["calibration.png", "sparsification.png"]
    with pytest.raises(ValueError, match="png"):
        plot_calibration(cal, tmp_path / "calibration.jpg")


def test_view_panels_show_photo_colour_depth_and_relative_std(tmp_path):
    """The README's picture: four panels, colour bars on the two depth maps, grey where opacity < 0.5."""
    import imageio.v3 as iio

    from stochastic_fields.plots import plot_view_panels, view_panels_figure

    H, W = 12, 16
    rng = np.random.default_rng(0)
    maps = {"colour_mean": rng.uniform(size=(H, W, 3)), "depth_mean": np.full((H, W), 2.0),
            "depth_std": np.full((H, W), 0.2), "opacity": np.ones((H, W))}
    maps["opacity"][:, :4] = 0.1
    fig = view_panels_figure(rng.uniform(size=(H, W, 3)), maps, title="t")
    assert len(fig.axes) == 6  # four panels and two colour bars
    relative = fig.axes[3].images[0].get_array()
    assert np.ma.is_masked(relative) or np.isnan(np.asarray(relative, dtype=float)[:, :4]).all()
    assert np.allclose(np.asarray(relative, dtype=float)[:, 4:], 0.1)
    out = plot_view_panels(tmp_path / "v.png", rng.uniform(size=(H, W, 3)), maps)
    assert iio.improps(out).shape[2] in (3, 4)


def test_ause_max_normalised_divides_each_curve_by_its_maximum():
    """Two pixels, the uncertainty anti-ranked (worked by hand, F = 2, fractions 0 and 0.5):
    model RMSE [sqrt(1/2), 1] (removing the certain-but-wrong pixel last), oracle [sqrt(1/2), 0].
    AUSE = 0.25; divided by the RMSE on all pixels: 0.25 / sqrt(1/2); each curve by its own maximum:
    trapz([sqrt(1/2) - 1, 1 - 0], [0, 0.5]) = (sqrt(1/2) - 1 + 1) / 4."""
    from stochastic_fields.metrics import sparsification_curve

    res = sparsification_curve(np.array([1.0, 0.0]), np.array([0.0, 1.0]), num_fractions=2)
    assert res.ause == pytest.approx(0.25, abs=1e-15)
    assert res.ause_normalised == pytest.approx(0.25 / math.sqrt(0.5), abs=1e-15)
    assert res.ause_max_normalised == pytest.approx(math.sqrt(0.5) / 4, abs=1e-15)
    # a perfect ranking: both conventions give 0; all errors zero: both undefined
    perfect = sparsification_curve(np.array([3.0, 1.0, 2.0]), np.array([3.0, 1.0, 2.0]), num_fractions=3)
    assert perfect.ause_max_normalised == pytest.approx(0.0, abs=1e-15) == perfect.ause_normalised
    assert math.isnan(sparsification_curve(np.zeros(4), np.ones(4)).ause_max_normalised)
