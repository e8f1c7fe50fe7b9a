"""The depth map's depth-proportional std term rho (``calibration.fit_relative_floor``): its CRPS
against ``metrics.crps_from_quantiles``, a known rho recovered from Monte-Carlo errors, none where the
std already explains the errors, the wrong-surface case it exists for (a few confident renders far
off: one scale per level widens every band, rho does not, and every level still holds on fresh
draws), hand-computed application through ``apply_calibration`` and the cross-fitted scores, files
with and without it, and the command-line switch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (ONE_SIGMA_LEVEL, RELATIVE_FLOOR_GRID, QuantileCalibration, RunCalibration,
                                           apply_calibration, cross_fitted_depth_quantiles, describe,
                                           fit_depth_folds, fit_relative_floor, relative_crps)
from stochastic_fields.cli import build_parser


def _log_uniform(rng, lo, hi, n):
    return np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))


def _wrong_surface_draws(rng, n, share=0.08):
    """Depths 1-10, stds 0.1-10% of them (log-uniform) and errors N(0, std^2); a ``share`` of renders
    on another surface 20-60% of the depth away, with a std of 0.1-0.5% of the depth (confident)."""
    depth = rng.uniform(1.0, 10.0, n)
    std = depth * _log_uniform(rng, 1e-3, 0.1, n)
    err = np.abs(rng.normal(size=n)) * std
    wrong = rng.random(n) < share
    std[wrong] = depth[wrong] * rng.uniform(1e-3, 5e-3, wrong.sum())
    err[wrong] = depth[wrong] * rng.uniform(0.2, 0.6, wrong.sum())
    return err, std, depth


def test_relative_crps_against_the_quantile_form():
    """The CRPS it minimises is metrics.crps_from_quantiles of the distribution the level map of
    the same points gives, for a truth on either side (the distribution is symmetric)."""
    rng = np.random.default_rng(0)
    n, rho = 400, 0.05
    depth = rng.uniform(1.0, 5.0, n)
    std = rng.uniform(0.01, 0.2, n)
    err = np.abs(rng.standard_t(3, size=n)) * std
    total = np.hypot(std, rho * depth)
    t = M.crps_levels()
    half = np.quantile(err / total, np.abs(2 * t - 1))
    quantiles = depth[:, None] + np.sign(t - 0.5)[None, :] * half[None, :] * total[:, None]
    for sign in (1.0, -1.0):
        ref = (M.crps_from_quantiles(depth + sign * err, quantiles).numpy() / depth).mean()
        assert relative_crps(err, std, depth, rho) == pytest.approx(ref, rel=1e-12)


def test_fit_relative_floor_recovers_a_known_term():
    rng = np.random.default_rng(1)
    n = 40000
    depth = _log_uniform(rng, 0.5, 50.0, n)
    std = _log_uniform(rng, 1e-3, 1.0, n)
    err = np.abs(rng.normal(size=n)) * 2.0 * np.hypot(std, 0.04 * depth)  # any scale: the level map takes it
    rho = fit_relative_floor(err, std, depth)
    assert rho == pytest.approx(0.04, rel=0.2)  # grid neighbours are 15% apart


def test_fit_relative_floor_stays_near_zero_when_the_std_explains_the_errors():
    rng = np.random.default_rng(2)
    depth = rng.uniform(1.0, 10.0, 20000)
    std = depth * _log_uniform(rng, 1e-3, 0.1, 20000)
    rho = fit_relative_floor(np.abs(rng.normal(size=20000)) * std, std, depth)
    assert rho * np.median(depth) < 0.1 * np.median(std)


def test_fit_relative_floor_hard_cases_and_bad_input():
    rng = np.random.default_rng(3)
    depth = rng.uniform(1e-6, 2e-6, 3000)  # tiny scenes and huge ones: rho is scale-free
    err, std, _ = _wrong_surface_draws(rng, 3000)
    scale = depth / rng.uniform(1.0, 10.0, 3000)
    small = fit_relative_floor(err * 1e-6, std * 1e-6, np.full(3000, 5.5e-6))
    big = fit_relative_floor(err * 1e6, std * 1e6, np.full(3000, 5.5e6))
    assert small == big and small in RELATIVE_FLOOR_GRID
    assert fit_relative_floor(np.zeros(100), np.ones(100), np.ones(100)) == 0.0  # exact renders: no term
    del scale
    with pytest.raises(ValueError, match=">= 3 paired"):
        fit_relative_floor(np.ones(4), np.ones(5), np.ones(5))
    with pytest.raises(ValueError, match="depths finite and > 0"):
        fit_relative_floor(np.ones(5), np.ones(5), np.r_[np.ones(4), 0.0])
    with pytest.raises(ValueError, match="errors must be finite"):
        fit_relative_floor(np.r_[np.ones(4), np.nan], np.ones(5), np.ones(5))


def test_wrong_surface_renders_no_longer_widen_every_band():
    """8% of confident renders on another surface: one scale per level needs s(95%) of tens of stds
    for every pixel; with rho the median 95% band is less than half as wide, and every level holds on
    fresh draws of the same errors."""
    rng = np.random.default_rng(4)
    fit_err, fit_std, fit_depth = _wrong_surface_draws(rng, 20000)
    plain = QuantileCalibration.fit_errors(fit_err, fit_std, quantity="depth_std")
    relative = QuantileCalibration.fit_errors(fit_err, fit_std, quantity="depth_std", depth=fit_depth)
    assert plain.relative_floor == 0.0 and relative.relative_floor > 0.0
    err, std, depth = _wrong_surface_draws(rng, 20000)
    gt = depth + err * rng.choice([-1.0, 1.0], err.size)
    widths = {}
    for name, m in (("plain", plain), ("relative", relative)):
        iv = M.interval_sharpness(gt, lambda t, m=m: M.gaussian_quantiles(
            depth, m.calibrated_std(std, depth=depth), t, m.relative_scale))
        for level, cov in zip(iv["levels"], iv["coverage"]):
            assert cov == pytest.approx(level, abs=0.02), (name, level)
        widths[name] = iv["halfwidth_median_95"]
    assert widths["relative"] < widths["plain"] / 2.0


def test_calibrated_std_by_hand_through_apply_calibration_and_the_folds():
    m = QuantileCalibration("depth_std", np.array([0.5, ONE_SIGMA_LEVEL, 0.95]), np.array([1.0, 2.0, 3.0]), 100,
                            floor=0.3, relative_floor=0.1)
    raw, depth = np.array([0.4, 1.0]), np.array([2.0, 30.0])
    expected = 2.0 * np.sqrt(raw ** 2 + 0.3 ** 2 + (0.1 * depth) ** 2)
    assert m.calibrated_std(raw, depth=depth) == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match="needs each pixel's rendered depth"):
        m.calibrated_std(raw)
    products = {"depth_mean": depth.reshape(1, 2).astype(np.float32), "depth_std": raw.reshape(1, 2).astype(np.float32)}
    out = apply_calibration(products, RunCalibration(depth=m))
    assert out["depth_std"].reshape(-1) == pytest.approx(expected, rel=1e-6)
    assert out["depth_std_raw"] is products["depth_std"]
    assert "(0.1 depth)^2" in describe(RunCalibration(depth=m))
    # the cross-fitted quantiles use each point's own depth: fold maps fitted with rho, by hand
    rng = np.random.default_rng(5)
    err, std, d = _wrong_surface_draws(rng, 4000)
    keys = rng.integers(0, 10, 4000)
    folds = fit_depth_folds(err, std, keys, np.arange(10), folds=2, depth=d)
    assert all(f.relative_floor > 0 for f in folds.maps)
    fold = folds.fold_of(keys)
    q = cross_fitted_depth_quantiles(d, std, fold, folds)(np.array([0.975]))[:, 0]
    for f, fm in enumerate(folds.maps):
        i = fold == f
        by_hand = d[i] + 1.959963984540054 * fm.calibrated_std(std[i], depth=d[i]) * fm.relative_scale(0.95)
        assert q[i] == pytest.approx(by_hand, rel=1e-9)


def test_relative_floor_round_trip_old_files_and_validation():
    m = QuantileCalibration.fit_errors(*_wrong_surface_draws(np.random.default_rng(6), 500)[:2],
                                       quantity="depth_std", depth=np.linspace(1, 10, 500))
    back = QuantileCalibration.from_dict(m.to_dict())
    assert back.relative_floor == m.relative_floor
    old = m.to_dict()
    del old["relative_floor"]
    assert QuantileCalibration.from_dict(old).relative_floor == 0.0
    bad = dict(m.to_dict(), relative_floor=-0.1)
    with pytest.raises(ValueError, match="depth-proportional term must be finite and >= 0"):
        QuantileCalibration.from_dict(bad, where="run/calibration.json: depth")
    with pytest.raises(ValueError, match="one finite depth > 0 per error"):
        QuantileCalibration.fit_errors(np.ones(60), np.ones(60), quantity="depth_std", depth=np.ones(59))


def test_calibrate_command_takes_the_relative_floor_switch():
    parser = build_parser()
    assert parser.parse_args(["calibrate", "--run", "r", "--relative-floor"]).relative_floor is True
    assert parser.parse_args(["calibrate", "--run", "r", "--no-relative-floor"]).relative_floor is False


def test_torch_free_of_the_fit():
    """The fit runs on numpy alone; torch tensors of the products pass through apply_calibration's
    numpy path unchanged in dtype."""
    m = QuantileCalibration("depth_std", np.array([0.6827]), np.array([1.0]), 100, relative_floor=0.5)
    out = apply_calibration({"depth_mean": np.ones((2, 2), np.float32), "depth_std": np.zeros((2, 2), np.float32)},
                            RunCalibration(depth=m))
    assert out["depth_std"].dtype == np.float32 and np.allclose(out["depth_std"], 0.5)
    assert torch.is_tensor(torch.from_numpy(out["depth_std"]))
