"""benchmarks/studies/heads_disagreement_analysis.py: the depth variance split between and within heads."""

from __future__ import annotations

import numpy as np
import pytest


def test_head_parts_against_a_float64_loop(load_script):
    script = load_script("benchmarks/studies/heads_disagreement_analysis.py")
    rng = np.random.default_rng(3)
    draws = rng.normal(5.0, 0.3, (50, 8)) + np.where(np.arange(8) % 2, 0.4, 0.0)  # head 1 lies further away
    draws[7, 5:] = np.nan  # a pixel that got 5 draws: heads 0, 1, 0, 1, 0
    means, between, within = script.head_parts(draws, 2)
    for p in range(len(draws)):
        groups = [[draws[p, k] for k in range(8) if k % 2 == h and np.isfinite(draws[p, k])] for h in range(2)]
        n = sum(len(g) for g in groups)
        mu = [sum(g) / len(g) for g in groups]
        centre = sum(len(g) * m for g, m in zip(groups, mu)) / n
        assert means[p] == pytest.approx(mu, rel=1e-12)
        assert between[p] == pytest.approx(sum(len(g) * (m - centre) ** 2 for g, m in zip(groups, mu)) / n, rel=1e-10)
        assert within[p] == pytest.approx(sum(sum((x - m) ** 2 for x in g) for g, m in zip(groups, mu)) / n, rel=1e-10)
        finite = draws[p][np.isfinite(draws[p])]
        assert between[p] + within[p] == pytest.approx(finite.var(), rel=1e-10)  # the law of total variance


def test_one_value_per_head_has_no_within_part(load_script):
    script = load_script("benchmarks/studies/heads_disagreement_analysis.py")
    draws = np.array([[1.0, 3.0, 1.0, 3.0], [2.0, 2.0, 2.0, 2.0]])
    means, between, within = script.head_parts(draws, 2)
    np.testing.assert_allclose(means, [[1.0, 3.0], [2.0, 2.0]])
    np.testing.assert_allclose(between, [1.0, 0.0])
    np.testing.assert_allclose(within, [0.0, 0.0])


def test_scores_by_hand(load_script):
    script = load_script("benchmarks/studies/heads_disagreement_analysis.py")
    gt = np.array([10.0, 10.0, 10.0, 10.0])
    heads = np.array([[10.0, 10.2], [9.0, 12.4], [8.0, 8.2], [10.0, 10.0]])  # point 1: straddles, head 0 within 10%
    pred = heads.mean(1)
    between = ((heads[:, 0] - heads[:, 1]) / 2) ** 2
    point = {"gt": gt, "pred": pred, "std": np.sqrt(between + 1.0), "between": between,
             "within": np.zeros(4), "spread": np.ones(4), "head_means": heads}
    s = script.scores([point])
    assert s["points"] == 4 and s["abs_rel"] == pytest.approx(np.mean(np.abs(pred - gt) / gt))
    large = np.abs(pred - gt) / gt > 0.05  # points 1 (10.7) and 2 (8.1)
    assert s["large_share"] == 0.5 and large.tolist() == [False, True, True, False]
    assert s["large_heads_straddle"] == 0.5  # point 1 straddles 10, point 2 does not
    assert s["large_some_head_right"] == 0.0  # 9.0 and 8.2 are both more than 5% off
    # the rank quantiles of points 1 and 2 in between (0.01, 2.89, 0.01, 0)
    assert s["large_rank_quantile_between"] == pytest.approx((3 / 3 + 2 / 3) / 2)  # ranks 3 and 2 of 0..3 (ties stable)
    assert s["variance_share_spread"] == pytest.approx(np.median(1.0 / (between + 1.0)))


def test_a_tiny_run_reproduces_the_total_ranking(tiny_scene, tmp_path, load_script):
    """End to end on a trained run with two heads: the pooled ranking by the total std is the tables'
    evaluation's (the same views, points and render seed), and the parts' shares are shares."""
    import json

    from conftest import train_tiny_run

    run = train_tiny_run(tiny_scene, tmp_path / "run")
    assert json.loads((run / "config.json").read_text())["field"]["density_heads"] == 2
    script = load_script("benchmarks/studies/heads_disagreement_analysis.py")
    assert script.main(["--run", f"{tiny_scene}={run}", "--out", str(tmp_path / "out"), "--quiet"]) == 0
    row = json.loads((tmp_path / "out" / "heads_disagreement.json").read_text())["rows"][0]
    assert row["heads"] == 2 and row["points"] > 100
    shares = [row[f"variance_share_{p}"] for p in ("between", "within", "spread")]
    assert all(0 <= s <= 1 for s in shares)
    from stochastic_fields.calibration import load_run_calibration
    from stochastic_fields.trainer import load_trained_model
    from stochastic_fields_bench.budget import BenchmarkSettings
    from stochastic_fields_bench.runner import evaluate_run, scene_inputs

    _, dataset, views, sparse = scene_inputs(str(tiny_scene), BenchmarkSettings(), log=lambda _m: None)
    _, model, _ = load_trained_model(run, dataset=dataset)
    metrics = evaluate_run(model, dataset, tmp_path / "eval", views=views, sparse_depth=sparse, product_views=0,
                           progress=False, calibration=load_run_calibration(run))
    assert row["ranking_pooled_total"] == pytest.approx(metrics["pooled"]["depth"]["spearman"], abs=1e-6)
