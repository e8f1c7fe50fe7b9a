"""benchmarks/studies/ranking_cross_analysis.py: two runs' errors and stds ranked against each other."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import train_tiny_run


def test_cross_scores_by_hand(load_script):
    script = load_script("benchmarks/studies/ranking_cross_analysis.py")
    rng = np.random.default_rng(0)
    gt = rng.uniform(2.0, 6.0, 4000)
    noise = rng.normal(size=4000)
    std_a = np.exp(rng.uniform(np.log(1e-3), np.log(1e-1), 4000))  # two decades
    pred_a = gt + std_a * noise  # errors in proportion to the std: ranked well
    pred_b = gt * 1.03 + 0.1 * std_a * noise  # a 3% bias every point shares, ranked by nothing
    s = script.cross_scores(gt, pred_a, std_a, pred_b, std_a)
    assert s["points"] == 4000 and s["stds_agree"] == pytest.approx(1.0)
    assert s["a_ranks_a"] > 0.5 and s["a_ranks_a"] == pytest.approx(s["b_ranks_a"])
    assert abs(s["b_ranks_b"]) < 0.3  # the bias hides the ranking ...
    assert s["median_signed_b"] == pytest.approx(0.03, abs=1e-3)
    assert s["unbiased_ranking_b"] > 0.5  # ... until it is removed
    assert s["large_share_a"] == pytest.approx(np.mean(np.abs(pred_a - gt) / gt > 0.05))
    assert s["large_share_b"] == 0.0 and np.isnan(s["large_rank_quantile_b"])
    assert s["abs_rel_b"] == pytest.approx(np.mean(np.abs(pred_b - gt) / gt))


def test_a_run_against_itself_reproduces_eval(tiny_scene, tmp_path, load_script):
    from stochastic_fields.cli import main as cli

    run = train_tiny_run(tiny_scene, tmp_path / "run")
    assert cli(["eval", "--run", str(run), "--out", str(tmp_path / "eval"), "--quiet"]) == 0
    script = load_script("benchmarks/studies/ranking_cross_analysis.py")
    out = tmp_path / "cross"
    pair = f"tiny={run}:{tmp_path / 'eval'}:{tmp_path / 'eval'}"
    assert script.main(["--pair", pair, "--labels", "one", "same", "--out", str(out)]) == 0
    row = json.loads((out / "ranking_cross_analysis.json").read_text())["rows"][0]
    pooled = json.loads((tmp_path / "eval" / "metrics.json").read_text())["pooled"]["depth"]
    assert row["points"] == pooled["num_used"]
    assert row["a_ranks_a"] == pytest.approx(pooled["spearman"], abs=1e-6)
    assert row["a_ranks_b"] == row["b_ranks_a"] == row["a_ranks_a"]
    assert row["abs_rel_a"] == pytest.approx(pooled["abs_rel"], rel=1e-5)
    assert "| own std ranks own errors |" in (out / "ranking_cross_analysis.md").read_text()


def test_refuses_what_is_not_a_pair(tmp_path, load_script):
    script = load_script("benchmarks/studies/ranking_cross_analysis.py")
    with pytest.raises(SystemExit):
        script.main(["--pair", "fern", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        script.main(["--pair", f"fern={tmp_path}:{tmp_path}:{tmp_path}", "--out", str(tmp_path)])


def test_ranking_at_share_keeps_the_groups_and_sets_the_mix(load_script):
    script = load_script("benchmarks/studies/ranking_cross_analysis.py")
    rng = np.random.default_rng(1)
    std = rng.uniform(0.0, 1.0, 10000)
    large = rng.uniform(size=10000) < 0.1 + 0.3 * std  # large errors where the std is large
    err = np.where(large, 10.0, 1.0) + rng.uniform(0.0, 0.1, 10000)  # no order inside a group
    own = script._spearman(err, std)
    more = script._ranking_at_share(err, std, large, 0.5)
    assert more > own  # with as many large errors as small ones, the same std ranks better
    assert script._ranking_at_share(err, std, large, float(large.mean())) == pytest.approx(own, abs=0.02)
    assert np.isnan(script._ranking_at_share(err, std, np.zeros(10000, bool), 0.5))
