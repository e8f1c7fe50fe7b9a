"""benchmarks/studies/depth_error_anatomy.py: the error sides and edges against hand-computed values,
its interval constructions against float64 loops and Monte-Carlo coverage, and one run end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def anatomy(load_script):
    return load_script("benchmarks/studies/depth_error_anatomy.py")


def test_neighbour_stencil(anatomy):
    offsets = anatomy.neighbour_offsets(2.0)
    assert len(offsets) == 8 == len(set(offsets)) and (0.0, 0.0) not in offsets
    assert all(max(abs(du), abs(dv)) == 2.0 for du, dv in offsets)


def test_error_sides_by_hand(anatomy):
    gt = np.array([1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 3.0])
    pred = np.array([0.5, 0.9, 1.2, 1.0, 2.0, 1.0, 3.0, 3.3, 1.5])
    # relative errors: -0.5 -0.1 +0.2 0 | 0 -0.5 | 0 +0.1 -0.5
    out = anatomy.error_sides(gt, pred, sizes=(0.05, 0.15, 0.3), large=0.15)
    assert out["num_points"] == 9
    by_size = {s["size"]: s for s in out["sizes"]}
    assert by_size[0.05]["share"] == pytest.approx(6 / 9) and by_size[0.05]["in_front"] == pytest.approx(4 / 6)
    assert by_size[0.15]["share"] == pytest.approx(4 / 9) and by_size[0.15]["in_front"] == pytest.approx(3 / 4)
    assert by_size[0.3]["share"] == pytest.approx(3 / 9) and by_size[0.3]["in_front"] == 1.0
    # thirds of the true depths: the four 1.0s, the two 2.0s, the three 3.0s
    near, middle, far = out["thirds"]
    assert near["median_signed"] == pytest.approx(-0.05) and near["share_large"] == pytest.approx(2 / 4)
    assert near["in_front"] == pytest.approx(1 / 2)
    assert middle["share_large"] == pytest.approx(1 / 2) and middle["in_front"] == 1.0
    assert far["median_signed"] == pytest.approx(0.0) and far["in_front"] == 1.0


def test_front_depth_ratio_by_hand(anatomy):
    assert anatomy.front_depth_ratio([-0.5, -0.3, -0.2, -0.1, 0.4], large=0.15) == pytest.approx(0.7)
    assert np.isnan(anatomy.front_depth_ratio([0.2, -0.1], large=0.15))


def test_near_bound_shares_by_hand(anatomy):
    gt = np.array([10.0, 10.0, 10.0, 2.0])
    pred = np.array([2.2, 5.0, 10.0, 2.1])  # errors -78%, -50%, 0, +5%; near 2: the first and last render there
    out = anatomy.near_bound_shares(gt, pred, np.full(4, 2.0), factor=1.25, size=0.3)
    assert out["front_errors"] == pytest.approx(0.5) and out["rendered"] == pytest.approx(0.5)
    assert out["true"] == pytest.approx(0.25)


def test_edge_shares_by_hand(anatomy):
    gt = np.array([1.0, 1.0, 1.0, 1.0])
    pred = np.array([0.5, 0.8, 1.0, 1.05])  # errors 0.5, 0.2, 0, 0.05: the first two are large
    delta = np.array([0.3, 0.05, 0.2, 0.0])  # 0.3 >= 0.25: at an edge; 0.05 < 0.1: not
    std = np.array([0.4, 0.3, 0.1, 0.2])
    out = anatomy.edge_shares(gt, pred, delta, std, large=0.15)
    assert out["large_at_edge"] == pytest.approx(0.5)
    assert out["others_wide_range"] == pytest.approx(0.5)  # 0.2 > 0.15, 0.0 not
    assert out["spearman_std"] == pytest.approx(1.0)


def test_out_of_fold_level_map_against_a_loop_and_its_coverage(anatomy):
    rng = np.random.default_rng(0)
    n = 20000
    std = rng.uniform(0.5, 2.0, n)
    pred = rng.uniform(5.0, 10.0, n)
    gt = pred + std * rng.standard_normal(n) * 1.7  # std under-states the error by 1.7x: the map rescales
    fold = rng.integers(0, 5, n)
    q = anatomy.out_of_fold_level_quantiles(pred, np.abs(gt - pred), std, fold)
    levels = np.array([0.025, 0.5, 0.9])
    got = q(levels)
    for i in (0, 17, 4242):  # float64 loop
        other = fold != fold[i]
        z = np.abs(gt[other] - pred[other]) / std[other]
        for j, t in enumerate(levels):
            want = pred[i] + np.sign(t - 0.5) * np.quantile(z, abs(2 * t - 1)) * std[i]
            assert got[i, j] == pytest.approx(want, rel=1e-12)
    lo, hi = q(np.array([0.025, 0.975])).T
    assert np.mean((gt >= lo) & (gt <= hi)) == pytest.approx(0.95, abs=0.01)


def test_signed_quantiles_hold_each_tail_of_a_skewed_error(anatomy):
    """Errors with a long tail behind the prediction: quantiles of the signed calibration errors hold
    each tail at (1 - p) / 2, where a symmetric map of |t| puts the whole miss on the long side."""
    rng = np.random.default_rng(1)
    n = 40000

    def draw(size):
        return rng.exponential(1.0, size) - 0.5  # skewed, mostly behind

    fold = rng.integers(0, 2, n)
    std = rng.uniform(0.5, 1.5, n)
    pred = np.full(n, 10.0)
    gt = pred + draw(n) * std
    t_outside = {0: draw(30000), 1: draw(30000)}
    q = anatomy.signed_fold_quantiles(pred, std, fold, t_outside)
    lo, hi = q(np.array([0.05, 0.95])).T
    assert np.mean(gt < lo) == pytest.approx(0.05, abs=0.006) and np.mean(gt > hi) == pytest.approx(0.05, abs=0.006)
    sym = anatomy.out_of_fold_level_quantiles(pred, np.abs(gt - pred), std, fold)
    s_lo, s_hi = sym(np.array([0.05, 0.95])).T
    assert np.mean((gt >= s_lo) & (gt <= s_hi)) == pytest.approx(0.90, abs=0.01)
    assert np.mean(gt < s_lo) < 0.01  # the symmetric band misses only behind
    assert np.median(hi - lo) < np.median(s_hi - s_lo)


def test_refuses_what_is_not_a_run(anatomy, tmp_path):
    with pytest.raises(SystemExit):
        anatomy.main(["--run", "fern", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        anatomy.main(["--run", f"paper/fern={tmp_path / 'nothing'}", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        anatomy.main(["--run", f"bad label={tmp_path}", "--out", str(tmp_path)])


@pytest.mark.slow
def test_a_calibrated_fern_run_end_to_end(anatomy, shared_data, tmp_path):
    import torch

    from stochastic_fields.calibration import calibrate_run
    from stochastic_fields.config import preset
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer
    from stochastic_fields_bench.budget import BenchmarkSettings, select_views

    torch.set_num_threads(1)
    cfg = preset("paper")
    cfg.data.path = str(shared_data / "nerf_llff_data" / "fern")
    cfg.data.images = "images_16"
    cfg.render.num_samples = 24
    cfg.render.num_draws = 4
    cfg.train.iterations = 60
    cfg.train.rays_per_batch = 256
    cfg.train.checkpoint_every = 0
    cfg.train.eval_every = 0
    run = tmp_path / "run"
    dataset = load_run_dataset(cfg, run)
    model = Trainer(cfg, run, dataset).train(progress=False)
    calibrate_run(run, model=model, dataset=dataset, progress=False)
    out = tmp_path / "anatomy"
    assert anatomy.main(["--run", f"paper/fern={run}", "--out", str(out), "--quiet"]) == 0
    record = json.loads((out / "anatomy.json").read_text())["runs"]["paper/fern"]
    assert record["which"] == "held-out photos the tables do not score"
    assert record["views"] and not set(record["views"]) & set(dataset.train_indices)
    tables = select_views(sorted(dataset.test_indices), BenchmarkSettings())
    assert not set(record["views"]) & set(tables) and set(record["views"]) | set(tables) == set(dataset.test_indices)
    sides = record["sides"]
    assert sides["num_points"] > 50 and 0.0 <= sides["sizes"][0]["share"] <= 1.0
    product = record["calibration"]["product (symmetric level map)"]
    assert len(product["coverage"]) == 5 and product["halfwidth_median_95"] > 0
    text = (out / "README.md").read_text()
    assert "## 3. What an edge term would buy" in text and "| paper/fern |" in text
    assert (out / "signed_errors.png").stat().st_size > 0
    stamp = (out / "runs" / "paper_fern.json").stat().st_mtime_ns  # resumable: read back, not rendered
    assert anatomy.main(["--run", f"paper/fern={run}", "--out", str(out), "--quiet"]) == 0
    assert (out / "runs" / "paper_fern.json").stat().st_mtime_ns == stamp
