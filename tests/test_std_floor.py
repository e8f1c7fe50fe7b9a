"""The depth map's std floor (``calibration.fit_std_floor``): a known floor recovered from Monte-Carlo
errors, the coverage it restores where one scale cannot (per std tercile), hand-computed application,
rankings unchanged, files with and without it, and the end-to-end fit on a mesh with an error the
reported std leaves out."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (CALIBRATION_LEVELS, ONE_SIGMA_LEVEL, STD_FLOOR_MAX_RATIO,
                                           QuantileCalibration, RunCalibration, apply_calibration, describe,
                                           fit_std_floor)


def _floored_errors(rng, std, tau, factor=1.0):
    """|N(0, factor^2 (std^2 + tau^2))|: a std that misses an error floor tau and a scale factor."""
    return np.abs(rng.normal(size=std.shape)) * factor * np.hypot(std, tau)


def _log_uniform(rng, lo, hi, n):
    return np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))


def test_fit_std_floor_recovers_a_known_floor():
    rng = np.random.default_rng(0)
    std = _log_uniform(rng, 0.01, 10.0, 40000)
    tau = fit_std_floor(_floored_errors(rng, std, 1.0, factor=3.0), std)
    assert tau == pytest.approx(1.0, rel=0.1)
    # at the fitted floor the standardised errors carry no trend in the std
    err = _floored_errors(rng, std, 1.0)
    assert abs(stats.spearmanr(std, err / np.hypot(std, fit_std_floor(err, std)))[0]) < 1e-3


def test_fit_std_floor_hard_cases():
    """No floor where the standardised errors grow with the std (or are constant), the largest tried
    floor where the std ranks errors backwards, clear errors for bad input."""
    std = np.linspace(0.1, 5.0, 200)
    assert fit_std_floor(std * np.linspace(0.5, 2.0, 200), std) == 0.0  # |z| rises with the std
    rng = np.random.default_rng(1)
    assert fit_std_floor(np.abs(rng.normal(size=200)) * std, std) == 0.0  # right std: no significant trend
    assert fit_std_floor(2.0 * std, std) == 0.0  # |z| constant: Spearman undefined
    assert fit_std_floor(std[::-1].copy(), std) == pytest.approx(STD_FLOOR_MAX_RATIO * 5.0)
    tiny = _log_uniform(rng, 1e-9, 1e-7, 5000)  # tiny stds, floor of the same size
    assert fit_std_floor(_floored_errors(rng, tiny, 3e-8), tiny) == pytest.approx(3e-8, rel=0.15)
    huge = _log_uniform(rng, 1e6, 1e9, 5000)
    assert fit_std_floor(_floored_errors(rng, huge, 3e7), huge) == pytest.approx(3e7, rel=0.15)
    with pytest.raises(ValueError, match="stds finite and > 0"):
        fit_std_floor(np.ones(5), np.r_[np.ones(4), 0.0])
    with pytest.raises(ValueError, match="finite and >= 0"):
        fit_std_floor(np.r_[np.ones(4), np.nan], np.ones(5))
    with pytest.raises(ValueError, match=">= 3 paired"):
        fit_std_floor(np.ones(4), np.ones(5))


def _tercile_coverage(err, cal_std, std, level, scale):
    edges = np.quantile(std, [1 / 3, 2 / 3])
    group = np.digitize(std, edges)
    inside = err <= stats.norm.ppf((1 + level) / 2) * cal_std * scale(level)
    return np.array([inside[group == g].mean() for g in range(3)])


def test_floored_map_holds_in_every_std_tercile_where_one_scale_cannot():
    """Known miscalibration: errors of std 2 sqrt(sigma^2 + 1). Fitted on one sample, scored on a fresh
    one: the floored map's 68% and 95% intervals hold in the lowest and highest std tercile alike
    (4 standard errors of a quantile fitted on n and a share scored on n / 3); the scale-only map under-covers the low stds and over-covers the
    high ones."""
    rng = np.random.default_rng(2)
    std = _log_uniform(rng, 0.05, 20.0, 30000)
    err = _floored_errors(rng, std, 1.0, factor=2.0)
    floored = QuantileCalibration.fit_errors(err, std, quantity="depth_std", floor=True)
    plain = QuantileCalibration.fit_errors(err, std, quantity="depth_std", floor=False)
    assert plain.floor == 0.0 and floored.floor == pytest.approx(1.0, rel=0.1)
    assert floored.std_scale == pytest.approx(2.0, rel=0.05)
    std2 = _log_uniform(rng, 0.05, 20.0, 30000)
    err2 = _floored_errors(rng, std2, 1.0, factor=2.0)
    for level in (ONE_SIGMA_LEVEL, 0.95):
        tol = 4 * math.sqrt(level * (1 - level) * (1 / len(std) + 3 / len(std2)))
        good = _tercile_coverage(err2, floored.calibrated_std(std2), std2, level, floored.relative_scale)
        bad = _tercile_coverage(err2, plain.calibrated_std(std2), std2, level, plain.relative_scale)
        assert good == pytest.approx(np.full(3, level), abs=tol)
        assert bad[0] < level - 0.05 and bad[2] > level + 0.02


def test_calibrated_std_by_hand_and_rankings_unchanged():
    scales = np.full(CALIBRATION_LEVELS.shape, 2.5)
    cal = RunCalibration(depth=QuantileCalibration("depth_std", CALIBRATION_LEVELS, scales, 1000, floor=2.0))
    products = {"depth_std": np.array([[1.5, 0.0, 1e30]], np.float64), "depth_mean": np.ones((1, 3))}
    out = apply_calibration(products, cal)
    assert out["depth_std"] == pytest.approx(np.array([[2.5 * 2.5, 2.5 * 2.0, 2.5e30]]))  # 2.5 sqrt(1.5^2 + 2^2)
    assert np.array_equal(out["depth_std_raw"], products["depth_std"])
    f32 = apply_calibration({"depth_std": np.array([3e38, 1.0], np.float32)}, cal)["depth_std"]
    assert f32.dtype == np.float32 and f32[1] == pytest.approx(2.5 * math.sqrt(5.0))
    rng = np.random.default_rng(3)
    std = _log_uniform(rng, 1e-3, 1e3, 2000)
    err = _floored_errors(rng, std, 1.0)
    calibrated = cal.depth.calibrated_std(std)
    assert np.all(np.diff(calibrated[np.argsort(std)]) >= 0)
    assert M.spearman(err, calibrated).value == pytest.approx(M.spearman(err, std).value, abs=1e-12)
    assert "sqrt(raw^2 + 2^2)" in describe(cal)


def test_floor_round_trip_old_files_and_validation():
    rng = np.random.default_rng(4)
    std = _log_uniform(rng, 0.1, 10.0, 500)
    cal = QuantileCalibration.fit_errors(_floored_errors(rng, std, 1.0), std, quantity="depth_std", floor=True)
    back = QuantileCalibration.from_dict(cal.to_dict())
    assert back.floor == cal.floor > 0 and np.array_equal(back.scales, cal.scales)
    old = cal.to_dict()
    del old["floor"]
    assert QuantileCalibration.from_dict(old).floor == 0.0  # written before the floor existed
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="calibration.json: depth: the std floor"):
            RunCalibration.from_dict({"depth": {**cal.to_dict(), "floor": bad}}, where="calibration.json")
    with pytest.raises(ValueError, match="3 errors but 4 stds"):
        QuantileCalibration.fit_errors(np.ones(3), np.ones(4), quantity="depth_std")
    with pytest.raises(ValueError, match="stds must be finite and > 0"):
        QuantileCalibration.fit_errors(np.ones(60), np.r_[np.ones(59), -1.0], quantity="depth_std")


def test_fit_depth_calibration_finds_an_error_the_std_leaves_out(tmp_path):
    """End to end on the synthetic mesh: errors of std sqrt(s^2 + 0.05^2) against a reported std s
    (0.02 t times exp(U(-3, 3)), t the ray's depth). The floored fit finds a floor near 0.05 and s ~ 1;
    without the switch, or for a model whose std is right, no floor."""
    from stochastic_fields.calibration import fit_depth_calibration
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene
    from test_depth_likelihood_calibration import _MeshDepthModel

    scene = make_synthetic_scene(tmp_path / "scene", num_views=20, width=192, height=144, seed=0)
    ds = load_dataset(scene, split_every=5)
    model = _MeshDepthModel(scene / "scene.ply", 1.0, abs_std=0.05, std_spread=3.0)
    floored = fit_depth_calibration(model, ds, floor=True)
    assert floored.num_samples >= 150
    assert floored.floor == pytest.approx(0.05, rel=0.3)
    assert floored.std_scale == pytest.approx(1.0, rel=0.2)
    assert fit_depth_calibration(model, ds, floor=False).floor == 0.0
    exact = _MeshDepthModel(scene / "scene.ply", 1.0, std_spread=3.0)
    assert fit_depth_calibration(exact, ds, floor=True).floor == 0.0


def test_calibrate_command_takes_the_floor_switch():
    import argparse

    from stochastic_fields.calibration import DEPTH_STD_FLOOR
    from stochastic_fields.commands.calibrate import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    assert p.parse_args(["--run", "r"]).std_floor is DEPTH_STD_FLOOR
    assert p.parse_args(["--run", "r", "--std-floor"]).std_floor is True
    assert p.parse_args(["--run", "r", "--no-std-floor"]).std_floor is False


def test_floor_study_coverage_terciles_and_rule_by_hand(load_script):
    """benchmarks/studies/std_floor_study.py: coverage against z_p s(p) sqrt(std^2 + floor^2), the tercile table,
    the distance and gap, and the rule on hand-made runs."""
    script = load_script("benchmarks/studies/std_floor_study.py")
    ones = np.ones(CALIBRATION_LEVELS.shape)
    plain = QuantileCalibration("depth_std", CALIBRATION_LEVELS, ones, 100)
    floored = QuantileCalibration("depth_std", CALIBRATION_LEVELS, ones, 100, floor=3.0)
    std = np.array([1.0, 1.0, 4.0, 4.0, 9.0, 9.0])
    err = np.array([0.5, 2.0, 2.0, 6.0, 5.0, 20.0])
    z68, z95 = stats.norm.ppf((1 + np.array(script.LEVELS)) / 2)
    assert script.coverage(err, std, plain) == pytest.approx([np.mean(err <= z68 * std), np.mean(err <= z95 * std)])
    wide = np.hypot(std, 3.0)
    assert script.coverage(err, std, floored) == pytest.approx([np.mean(err <= z68 * wide), np.mean(err <= z95 * wide)])
    rows = script.tercile_rows(err, std, floored, plain)
    assert [r["group"] for r in rows] == [*script.STD_GROUPS, "all"] and [r["points"] for r in rows] == [2, 2, 2, 6]
    assert rows[0]["coverage_raw"] == pytest.approx([0.5, 0.5])  # 0.5 <= 0.9998, 2.0 > 1.96
    assert rows[0]["coverage"] == pytest.approx([1.0, 1.0])  # bounds 3.16, 6.2
    assert script.gap(rows, "coverage_raw") == pytest.approx(0.0) and script.distance([0.6, 0.99]) == pytest.approx(0.0827, abs=1e-4)

    def run(d_plain, d_floor, g_plain, g_floor):
        return {"distance": {"plain": d_plain, "floored": d_floor}, "gap": {"plain": g_plain, "floored": g_floor},
                "floor": 1.0, "groups": [{"coverage": [0.7, 0.95], "coverage_raw": [0.7, 0.95]}]}

    good = {"runs": {"a/0": run(0.05, 0.05, 0.3, 0.1), "a/1": run(0.05, 0.06, 0.3, 0.1), "b/0": run(0.1, 0.1, 0.1, 0.1)}}
    d = script.decide(good)
    assert d["taken"] and d["scenes"]["a"]["seeds"] == 2 and d["mean_gap_gain"] == pytest.approx(0.1)
    bad = {"runs": {**good["runs"], "b/0": run(0.1, 0.2, 0.1, 0.1)}}
    assert not script.decide(bad)["taken"] and script.decide(bad)["worse_on"] == ["b"]


def test_bounds_study_rule_by_hand(load_script):
    """benchmarks/studies/calibration_bounds_study.py: the mean distance gain and the per-scene tolerances."""
    script = load_script("benchmarks/studies/calibration_bounds_study.py")

    def run(d_today, d_new, g_today=0.1, g_new=0.1):
        return {"choices": {"interpolated": {
            "distance": {"today": d_today, "new": d_new}, "gap": {"today": g_today, "new": g_new},
            "groups": [{"coverage": [0.7, 0.95], "coverage_raw": [0.75, 0.97]}]}}}

    d = script.decide({"runs": {"a/0": run(0.10, 0.05), "b/0": run(0.06, 0.05)}}, "interpolated")
    assert d["taken"] and d["mean_distance_gain"] == pytest.approx(0.03)
    assert not script.decide({"runs": {"a/0": run(0.10, 0.09), "b/0": run(0.06, 0.05)}}, "interpolated")["taken"]
    worse = script.decide({"runs": {"a/0": run(0.10, 0.02), "b/0": run(0.06, 0.05, 0.1, 0.2)}}, "interpolated")
    assert not worse["taken"] and worse["worse_on"] == ["b"]
