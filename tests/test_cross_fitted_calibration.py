"""The depth map fitted on every held-out capture point, and its cross-fitted fold maps that score it
independently (calibration.DepthFolds; docs/uncertainty.md, studies 18 and 18b): the folds by hand,
the interval scores against a float64 loop, the file format, eval's use of them, end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import ndtri

from stochastic_fields.calibration import (CROSS_FIT_FOLDS, QuantileCalibration, RunCalibration,
                                           cross_fitted_depth_scores, fit_depth_folds, load_run_calibration,
                                           save_run_calibration)
from stochastic_fields.constants import DEPTH_NLL_VARIANCE_FLOOR
from stochastic_fields.sparse_depth import COVERAGE_LEVELS


def _renders(rng, n_blocks: int = 10, per_block: int = 80):
    """Held-out renders in ``n_blocks`` blocks whose error scale grows with the block key."""
    keys = np.repeat(np.arange(n_blocks) * 7, per_block)  # keys need not be 0..B-1
    std = rng.uniform(0.5, 2.0, keys.size)
    err = np.abs(rng.normal(size=keys.size)) * std * (1.0 + keys / 35.0)
    return err, std, keys


def test_folds_deal_the_score_blocks_and_each_map_fits_the_points_outside_its_fold():
    rng = np.random.default_rng(0)
    err, std, keys = _renders(rng)
    score_blocks = np.array([7, 14, 21, 35, 42, 56, 63])  # blocks 0, 28 and 49 are CALIBRATE
    folds = fit_depth_folds(err, std, keys, score_blocks, folds=3, seed=4)
    assert len(folds.blocks) == len(folds.maps) == 3
    dealt = np.concatenate(folds.blocks)
    assert sorted(dealt.tolist()) == score_blocks.tolist()  # a partition of the SCORE blocks
    assert [len(b) for b in folds.blocks] == [3, 2, 2]
    order = np.random.default_rng(4).permutation(score_blocks)
    for f, (blocks, m) in enumerate(zip(folds.blocks, folds.maps)):
        assert sorted(blocks.tolist()) == sorted(order[f::3].tolist())
        outside = ~np.isin(keys, blocks)
        expected = QuantileCalibration.fit_errors(err[outside], std[outside], quantity="depth_std")
        np.testing.assert_allclose(m.scales, expected.scales)
        assert m.num_samples == int(outside.sum())
    assert folds.fold_of(np.array([0, 7, 14, 99])).tolist() == [-1] + [folds.fold_of(np.array([k]))[0] for k in (7, 14)] + [-1]
    again = fit_depth_folds(err, std, keys, score_blocks, folds=3, seed=4)
    assert all(np.array_equal(a, b) for a, b in zip(again.blocks, folds.blocks))
    with pytest.raises(ValueError, match="at least 2 folds and 2 SCORE blocks"):
        fit_depth_folds(err, std, keys, np.array([7]), folds=3)
    with pytest.raises(ValueError, match="at least 2 folds"):
        fit_depth_folds(err, std, keys, score_blocks, folds=1)
    with pytest.raises(ValueError, match="needs at least"):  # a fold map with too few points
        fit_depth_folds(err[:140], std[:140], np.r_[np.zeros(100), 7 * np.ones(40)], np.array([0, 7]), folds=2)


def test_cross_fitted_scores_against_a_float64_loop():
    """Each depth judged by its fold's map: std_i = s_f(0.6827) sqrt(base_i^2 + floor_f^2), the
    interval at level p is +- z_p std_i s_f(p) / s_f(0.6827); coverage, AUCE and NLL pooled."""
    rng = np.random.default_rng(1)
    err, std, keys = _renders(rng)
    folds = fit_depth_folds(err, std, keys, np.unique(keys), folds=4, seed=0, floor=True)
    n = 300
    gt = rng.uniform(2.0, 6.0, n)
    base = rng.uniform(0.01, 0.3, n)
    pred = gt + rng.standard_t(3, n) * base * 1.5
    block = rng.choice(np.unique(keys), n)
    fold = folds.fold_of(block)
    got = cross_fitted_depth_scores(gt, pred, base, fold, folds)

    levels = np.linspace(0.01, 0.99, 99)
    inside = np.zeros(99)
    inside2 = np.zeros(2)
    nll = 0.0
    for i in range(n):
        m = folds.maps[fold[i]]
        s1 = float(np.interp(0.682689492137086, m.levels, m.scales))
        sd = s1 * math.sqrt(base[i] ** 2 + m.floor ** 2)
        for j, p in enumerate(levels):
            bound = ndtri((1 + p) / 2) * sd * float(np.interp(p, m.levels, m.scales)) / s1
            inside[j] += abs(pred[i] - gt[i]) <= bound
        for j, p in enumerate(COVERAGE_LEVELS):
            bound = ndtri((1 + p) / 2) * sd * float(np.interp(p, m.levels, m.scales)) / s1
            inside2[j] += abs(pred[i] - gt[i]) <= bound
        var = max(sd ** 2, DEPTH_NLL_VARIANCE_FLOOR)
        nll += 0.5 * math.log(2 * math.pi * var) + (gt[i] - pred[i]) ** 2 / (2 * var)
    assert got["coverage_68"] == pytest.approx(inside2[0] / n, abs=1e-12)
    assert got["coverage_95"] == pytest.approx(inside2[1] / n, abs=1e-12)
    np.testing.assert_allclose(got["calibration"].coverage, inside / n, atol=1e-12)
    assert got["auce"] == pytest.approx(float(np.abs(inside / n - levels).mean()), abs=1e-12)
    assert got["nll"] == pytest.approx(nll / n, rel=1e-9)
    with pytest.raises(ValueError, match="1 of 300 depths lie in no fold"):
        cross_fitted_depth_scores(gt, pred, base, np.r_[fold[:-1], -1], folds)

    # maps fitted with the free-space check: std_i = s_f(0.6827) sqrt(raw_i^2 + floor_f^2 + e_i^2)
    import copy

    checked = copy.deepcopy(folds)
    for m in checked.maps:
        m.free_space = True
    e = rng.uniform(0.0, 0.2, n)
    with pytest.raises(ValueError, match="free-space violation"):
        cross_fitted_depth_scores(gt, pred, base, fold, checked)
    got_checked = cross_fitted_depth_scores(gt, pred, base, fold, checked, violation=e)
    plain_again = cross_fitted_depth_scores(gt, pred, np.sqrt(base ** 2 + e ** 2), fold, folds)
    for k in ("coverage_68", "coverage_95", "auce", "nll"):
        assert got_checked[k] == pytest.approx(plain_again[k], rel=1e-12)


def test_a_block_judged_by_the_others_not_by_itself():
    """Two blocks: one whose errors are 1 std, one whose errors are 3. Fitted on both, a map would
    cover the 2-std errors of either at 95%; cross-fitted, each block is judged by the other's
    map, so the 1-std block's points fall outside and the 3-std block's inside."""
    n = 200
    err = np.r_[np.full(n, 1.0), np.full(n, 3.0)]
    keys = np.r_[np.zeros(n), np.ones(n)].astype(np.int64)
    folds = fit_depth_folds(err, np.ones(2 * n), keys, np.array([0, 1]), folds=2, seed=0)
    got = cross_fitted_depth_scores(np.full(4, 5.0), np.full(4, 7.0), np.ones(4), folds.fold_of(np.array([0, 0, 1, 1])),
                                    folds)
    assert got["coverage_95"] == pytest.approx(0.5)  # block 0 (judged by 3s) inside, block 1 (by 1s) outside


def test_folds_round_trip_in_calibration_json_and_malformed_ones_are_refused(tmp_path):
    rng = np.random.default_rng(2)
    err, std, keys = _renders(rng)
    folds = fit_depth_folds(err, std, keys, np.unique(keys), seed=3)
    assert len(folds.maps) == CROSS_FIT_FOLDS
    full = QuantileCalibration.fit_errors(err, std, quantity="depth_std")
    cal = RunCalibration(depth=full, points="held-out", depth_folds=folds)
    assert cal.saw_score_points and cal.independent_depth_scores
    assert not RunCalibration(depth=full, points="held-out").independent_depth_scores
    assert RunCalibration(depth=full).independent_depth_scores
    path = save_run_calibration(tmp_path, cal)
    back = load_run_calibration(tmp_path)
    assert back.depth_folds.seed == 3
    assert all(np.array_equal(a, b) for a, b in zip(back.depth_folds.blocks, folds.blocks))
    for a, b in zip(back.depth_folds.maps, folds.maps):
        np.testing.assert_allclose(a.scales, b.scales)
    data = json.loads(path.read_text())
    twice = json.loads(json.dumps(data))
    twice["depth_folds"]["blocks"][1].append(twice["depth_folds"]["blocks"][0][0])
    with pytest.raises(ValueError, match="more than one fold"):
        RunCalibration.from_dict(twice, where=str(path))
    short = json.loads(json.dumps(data))
    short["depth_folds"]["maps"].pop()
    with pytest.raises(ValueError, match=f"{CROSS_FIT_FOLDS} folds and {CROSS_FIT_FOLDS - 1} maps"):
        RunCalibration.from_dict(short, where=str(path))
    for bad, match in (({"blocks": [[1]]}, "malformed depth folds"), ([1, 2], "must be a JSON object")):
        with pytest.raises(ValueError, match=match) as info:
            RunCalibration.from_dict({**data, "depth_folds": bad}, where=str(path))
        assert str(path) in str(info.value)
    broken = json.loads(json.dumps(data))
    broken["depth_folds"]["maps"][2]["scales"][0] = -1.0
    with pytest.raises(ValueError, match="fold 2"):
        RunCalibration.from_dict(broken, where=str(path))


def test_eval_scores_intervals_with_the_folds_and_ranks_with_the_run_map():
    """``calibrated_depth_scores``: coverage, AUCE and NLL are the folds'; abs-rel, Spearman and AUSE
    the run map's; with no folds (or no blocks) everything is the run map's."""
    from stochastic_fields.evaluation import DepthSamples, calibrated_depth_scores
    from stochastic_fields.sparse_depth import paired_depth_scores

    rng = np.random.default_rng(5)
    err, std, keys = _renders(rng)
    folds = fit_depth_folds(err, std, keys, np.unique(keys), seed=0)
    full = QuantileCalibration.fit_errors(err, std, quantity="depth_std")
    n = 120
    gt = rng.uniform(2, 5, n)
    raw = rng.uniform(0.05, 0.2, n)
    pred = gt + rng.normal(size=n) * raw * 2
    block = rng.choice(np.unique(keys), n)
    samples = DepthSamples(gt, pred, full.calibrated_std(raw), raw, {}, None, block)
    cal = RunCalibration(depth=full, points="held-out", depth_folds=folds)
    got = calibrated_depth_scores(samples, cal)
    plain = paired_depth_scores(gt, pred, full.calibrated_std(raw), interval_scale=full.relative_scale)
    cross = cross_fitted_depth_scores(gt, pred, raw, folds.fold_of(block), folds)
    for k in ("coverage_68", "coverage_95", "auce", "nll"):
        assert got[k] == cross[k]
    assert got["coverage_68"] != plain["coverage_68"] or got["nll"] != plain["nll"]
    for k in ("abs_rel", "ause_rmse"):
        assert got[k] == plain[k]
    assert got["spearman"].value == plain["spearman"].value
    no_blocks = calibrated_depth_scores(DepthSamples(gt, pred, full.calibrated_std(raw), raw, {}, None, None), cal)
    assert no_blocks["coverage_68"] == plain["coverage_68"] and no_blocks["nll"] == plain["nll"]


def test_held_out_calibration_end_to_end_stores_folds_and_eval_scores_with_them(tmp_path):
    """On the synthetic scene with a model whose errors are 3x its std: the default calibration fits
    every held-out point, stores folds whose maps are fitted on the renders outside their blocks,
    and eval of the exact depth judges each scored pixel by its block's fold, without the warning
    that the scores saw the map's data."""
    import warnings

    from stochastic_fields.calibration import (DEFAULT_CALIBRATION_POINTS, depth_calibration_renders,
                                               fit_depth_calibration_and_folds)
    from stochastic_fields.capture_points import block_keys, load_capture_points
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene
    from stochastic_fields.evaluation import CROSS_FITTED_SCORES, _conventions
    from test_depth_likelihood_calibration import _MeshDepthModel

    assert DEFAULT_CALIBRATION_POINTS == "held-out"
    scene = make_synthetic_scene(tmp_path / "scene", num_views=20, width=192, height=144, seed=0)
    ds = load_dataset(scene, split_every=5)
    model = _MeshDepthModel(scene / "scene.ply", 3.0)
    full, folds = fit_depth_calibration_and_folds(model, ds)
    assert folds is not None and len(folds.maps) == CROSS_FIT_FOLDS
    r = depth_calibration_renders(model, ds, points="held-out")
    capture = load_capture_points(ds)
    keys = block_keys(capture.xyz, capture.xyz)[r["index"]]
    for blocks, m in zip(folds.blocks, folds.maps):
        outside = ~np.isin(keys, blocks)
        np.testing.assert_allclose(m.scales, QuantileCalibration.fit_errors(r["abs_err"][outside], r["std"][outside],
                                                                            quantity="depth_std").scales)
        assert m.std_scale == pytest.approx(full.std_scale, rel=0.25)  # the same factor, from 4/5 of the data
    only, none = fit_depth_calibration_and_folds(model, ds, points="calibrate")
    assert none is None and only.num_samples < full.num_samples
    cal = RunCalibration(depth=full, points="held-out", depth_folds=folds)
    assert _conventions("dense", cal)["depth_calibration_independence"] == CROSS_FITTED_SCORES

    from stochastic_fields.evaluation import evaluate

    class _Render(_MeshDepthModel):  # colour for eval
        def render_view(self, rays, options=None, *, generator=None):
            import torch

            out = super().render_view(rays, options, generator=generator)
            out.update(colour_mean=torch.full((*rays.shape, 3), 0.5), colour_var=torch.full((*rays.shape, 3), 0.01),
                       depth_var_epistemic=out["depth_var_total"], depth_var_spread=torch.zeros(rays.shape))
            return out

    render = _Render(scene / "scene.ply", 3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no "not an independent test" warning
        res = evaluate(render, ds, tmp_path / "ev", views=[1], calibration=cal, product_views=0, progress=False)
    assert res["conventions"]["depth_calibration_independence"] == CROSS_FITTED_SCORES

    # by hand: the view's SCORE-block surface pixels with opacity > 0.5, each judged by its block's fold
    from stochastic_fields.capture_points import dense_depth_block_keys, dense_depth_score_mask
    from stochastic_fields.view_maps import camera_z_maps

    maps = camera_z_maps(render.render_view(ds.rays(1)))
    gt = ds.depths[1].numpy()
    keep = dense_depth_score_mask(ds, capture, 1) & (gt > 0) & (maps["opacity"] > 0.5)
    blocks = dense_depth_block_keys(ds, capture, 1)[keep]
    by_hand = cross_fitted_depth_scores(gt[keep], maps["depth_mean"][keep], maps["depth_std"][keep],
                                        folds.fold_of(blocks), folds)
    assert keep.sum() > 100 and res["pooled"]["depth"]["num_used"] == int(keep.sum())
    for k in ("coverage_68", "coverage_95", "auce", "nll"):
        assert res["pooled"]["depth"][k] == pytest.approx(by_hand[k], rel=1e-5)
