"""The free-path recalibration (products/free_path_calibration.py): the isotonic map against hand
values and a naive pool-adjacent-violators loop, the segments a seen point knows, the file, and the
free-path command with and without the map."""

import json
import shutil

import numpy as np
import pytest
import torch
from test_export import dataset, run_dir  # noqa: F401  (fixtures reused: the tiny scene, a tiny-preset run folder)

from stochastic_fields.products.free_path_calibration import (FREE_PATH_CALIBRATION_FILE, FreePathCalibration,
                                                              applies, calibration_events, fit_free_path_calibration,
                                                              known_segments, load_free_path_calibration)
from stochastic_fields.rays import RayBundle

FIT = dict(level=0.5, margins=(0.1,), num_draws=8, step=0.1)


def naive_isotonic(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Pool adjacent violators, float64, one block at a time (the textbook loop)."""
    blocks = [[float(v), float(w), 1] for v, w in zip(values, weights)]
    i = 0
    while i < len(blocks) - 1:
        if blocks[i][0] > blocks[i + 1][0] + 1e-15:
            (v1, w1, n1), (v2, w2, n2) = blocks[i], blocks[i + 1]
            blocks[i:i + 2] = [[(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, n1 + n2]]
            i = max(i - 1, 0)
        else:
            i += 1
    return np.concatenate([[v] * n for v, _, n in blocks])


def test_isotonic_map_by_hand():
    # p = 0: 12 of 20 free; p = 0.5: 4 of 20; p = 1: 40 of 40 -> the first two pool to 16 / 40 = 0.4
    p = np.repeat([0.0, 0.5, 1.0], [20, 20, 40])
    o = np.concatenate([np.repeat([1, 0], [12, 8]), np.repeat([1, 0], [4, 16]), np.ones(40)])
    cal = FreePathCalibration.fit(p, o, **FIT)
    np.testing.assert_allclose(cal.knots_p, [0.0, 0.5, 1.0])
    np.testing.assert_allclose(cal.knots_g, [0.4, 0.4, 1.0])
    np.testing.assert_allclose(cal([0.0, 0.25, 0.75, 1.0, -1.0, 2.0]), [0.4, 0.4, 0.7, 1.0, 0.4, 1.0])
    assert cal.events == 80 and applies(cal, 0.5) and not applies(cal, 0.6) and not applies(None, 0.5)


def test_isotonic_map_against_a_naive_loop():
    rng = np.random.default_rng(0)
    p = rng.integers(0, 17, 400) / 16.0
    o = (rng.random(400) < 0.2 + 0.6 * p + 0.3 * np.sin(9 * p)).astype(float)  # not monotone in p
    cal = FreePathCalibration.fit(p, o, **FIT)
    values, counts = np.unique(p, return_counts=True)
    freq = np.array([o[p == v].mean() for v in values])
    np.testing.assert_allclose(cal.knots_g, naive_isotonic(freq, counts.astype(float)), atol=1e-12)
    assert (np.diff(cal.knots_g) >= 0).all()


def test_bad_maps_and_files(tmp_path):
    with pytest.raises(ValueError, match=">= 50 paired events"):
        FreePathCalibration.fit(np.zeros(10), np.zeros(10), **FIT)
    with pytest.raises(ValueError, match="outcomes be 0 or 1"):
        FreePathCalibration.fit(np.zeros(60), np.full(60, 0.5), **FIT)
    with pytest.raises(ValueError, match="must not decrease"):
        FreePathCalibration([0.0, 1.0], [0.9, 0.1], 0.5, 60, (0.1,), 8, 0.1)
    (tmp_path / FREE_PATH_CALIBRATION_FILE).write_text(json.dumps({"knots_p": [0.0]}))
    with pytest.raises(ValueError, match=FREE_PATH_CALIBRATION_FILE):
        load_free_path_calibration(tmp_path)
    assert load_free_path_calibration(tmp_path / "elsewhere") is None


def test_known_segments_along_a_ray():
    # two rays along +z from the origin, near 1; camera z = 0.8 x ray distance on the second
    rays = RayBundle(origins=torch.zeros(2, 3, dtype=torch.float64),
                     directions=torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]], dtype=torch.float64),
                     near=torch.ones(2, dtype=torch.float64), far=torch.full((2,), 20.0, dtype=torch.float64),
                     z_scale=torch.tensor([1.0, 0.8], dtype=torch.float64))
    seg = known_segments(rays, torch.tensor([10.0, 1.0], dtype=torch.float64), [0.1])
    # ray 0: ends at distance 9 (free) and 11 (blocked); ray 1 (depth 1 = distance 1.25): 0.9 * 1.25 = 1.125 > near
    # and 1.1 * 1.25 = 1.375; its segments start at distance 1
    assert seg["ray"].tolist() == [0, 1, 0, 1]
    np.testing.assert_allclose(seg["outcome"].numpy(), [1, 1, 0, 0])
    np.testing.assert_allclose(seg["depth"].numpy(), [9.0, 0.9, 11.0, 1.1])
    np.testing.assert_allclose(seg["ends"].numpy(), [[0, 0, 9], [0, 0.675, 0.9], [0, 0, 11], [0, 0.825, 1.1]], atol=1e-12)
    np.testing.assert_allclose(seg["starts"].numpy(), [[0, 0, 1], [0, 0.6, 0.8], [0, 0, 1], [0, 0.6, 0.8]], atol=1e-12)
    # a point nearer than (near / (1 - m)) has no free segment
    close = known_segments(rays, torch.tensor([1.05, 10.0], dtype=torch.float64), [0.1])
    assert close["ray"].tolist() == [1, 0, 1]


def test_fit_and_the_free_path_command(tmp_path, run_dir):  # noqa: F811
    from stochastic_fields.cli import main
    from stochastic_fields.products.free_path import segment_free_probability
    from stochastic_fields.trainer import load_trained_model

    run = tmp_path / "run"
    shutil.copytree(run_dir, run)  # the shared fixture stays without a map
    _, model, dataset = load_trained_model(run, device="cpu")
    prob, outcome, source = calibration_events(model, dataset, step=0.05, num_draws=16, max_points=200)
    assert prob.shape == outcome.shape and 0.3 < outcome.mean() < 0.7 and "calibration views" in source
    fitted = fit_free_path_calibration(run, model, dataset)  # what calibrate --free-path and train call
    cal = load_free_path_calibration(run)
    assert cal is not None and cal.level == 0.5 and cal.events > 100
    np.testing.assert_allclose(cal.knots_g, fitted.knots_g)
    q = {"segments": [[[-0.5, 0.0, 0.2], [0.5, 0.0, 0.2]], [[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]]}
    (tmp_path / "q.json").write_text(json.dumps(q))
    args = ["free-path", "--run", str(run), "--queries", str(tmp_path / "q.json"), "--step", "0.05", "--num-draws", "32"]
    assert main(args + ["--out", str(tmp_path / "a.json")]) == 0
    ans = json.loads((tmp_path / "a.json").read_text())
    seg = torch.tensor(q["segments"], dtype=torch.float64)
    ref = segment_free_probability(lambda x: model.field.density_params(x.float()), seg[:, 0], seg[:, 1],
                                   num_draws=32, step=0.05, shared_noise=model.render_settings.shared_noise,
                                   generator=torch.Generator().manual_seed(0))
    assert ans["recalibrated"] is True
    np.testing.assert_allclose(ans["segments"]["probability_free_model"], ref.probability.numpy())
    np.testing.assert_allclose(ans["segments"]["probability_free"], cal(ref.probability.numpy()))
    np.testing.assert_allclose(ans["segments"]["stderr"], ref.stderr.numpy())  # the model's Monte-Carlo error
    assert main(args + ["--raw-probability", "--out", str(tmp_path / "raw.json")]) == 0
    raw = json.loads((tmp_path / "raw.json").read_text())
    assert raw["recalibrated"] is False and "probability_free_model" not in raw["segments"]
    np.testing.assert_allclose(raw["segments"]["probability_free"], ref.probability.numpy())
    assert main(args + ["--level", "0.7", "--out", str(tmp_path / "other.json")]) == 0
    other = json.loads((tmp_path / "other.json").read_text())
    assert other["recalibrated"] is False and "fitted at level 0.5" in other["recalibration"]


def test_free_path_benchmark_rule_by_hand(load_script):
    bench = load_script("benchmarks/free_path_reliability.py")

    def run(brier_model, ece_model, brier_cal, ece_cal):
        return {"pooled": {"free-path (model)": {"brier": brier_model, "ece": ece_model},
                           "free-path (recalibrated)": {"brier": brier_cal, "ece": ece_cal}}}

    results = {"runs": {"capture/fern": run(0.05, 0.04, 0.04, 0.02), "paper/flower": run(0.10, 0.12, 0.104, 0.06),
                        "synthetic": run(0.02, 0.02, 0.05, 0.09)}}  # the synthetic scene does not count
    assert bench.decide(results).startswith("taken")  # Brier within +0.005, mean ECE 0.08 -> 0.04
    results["runs"]["paper/flower"] = run(0.10, 0.12, 0.106, 0.06)  # Brier 0.006 worse
    assert bench.decide(results).startswith("not taken: paper/flower: Brier")
    results["runs"]["paper/flower"] = run(0.10, 0.12, 0.10, 0.10)  # mean ECE 0.08 -> 0.06: not a quarter
    assert "mean ECE falls only" in bench.decide(results)
    del results["runs"]["paper/flower"]["pooled"]["free-path (recalibrated)"]
    assert bench.decide(results).startswith("undecided")


def test_calibrate_on_a_baseline_run_skips_free_paths(tmp_path, tiny_scene, capsys):
    """A deep ensemble's run: `calibrate` fits its depth map and says why free paths are not
    recalibrated (they integrate S-NeRF's random density), instead of failing on the model."""
    from stochastic_fields.cli import main
    from test_inspect import _train_tiny

    run = _train_tiny(tmp_path / "ens", tiny_scene, method="ensemble", iterations=3)
    main(["calibrate", "--run", str(run)])
    out = capsys.readouterr().out
    assert (run / "calibration.json").is_file() and not (run / FREE_PATH_CALIBRATION_FILE).exists()
    assert "free-path not recalibrated" in out and "DeepEnsemble" in out and str(run) in out
    queries = tmp_path / "q.json"
    queries.write_text(json.dumps({"segments": [[[0, 0, 0], [0, 0, 1]]]}))
    assert main(["free-path", "--run", str(run), "--queries", str(queries)]) == 2
    assert "need an S-NeRF run" in capsys.readouterr().err
