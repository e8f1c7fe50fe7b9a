"""Study 18 (benchmarks/studies/photo_calibration_study.py): the depth map fitted on the photos that neither
train nor are scored. Which photos, which points they see, the rule by hand, and the committed
decision recomputed (docs/uncertainty.md)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from stochastic_fields.capture_points import CALIBRATE, SCORE, depth_map_observes, load_capture_points

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks/results/uncertainty_study/photo_calibration"


def test_unused_views_are_those_that_neither_train_nor_are_evaluated(load_script):
    script = load_script("benchmarks/studies/photo_calibration_study.py")
    dataset = SimpleNamespace(train_indices=[0, 5, 10], num_views=12)
    assert script.unused_views(dataset, [1, 11]) == [2, 3, 4, 6, 7, 8, 9]
    assert script.unused_views(SimpleNamespace(train_indices=[0], num_views=2), [1]) == []


def test_photo_points_are_the_roles_points_each_depth_map_shows(tiny_scene, load_script):
    """On a dense-depth scene a photo's points are exactly the stand-in points of the role that its
    depth map observes, each at its projection (continuous uv) with its camera depth."""
    from stochastic_fields.cameras import project_points, select_cameras
    from stochastic_fields.data import load_dataset

    script = load_script("benchmarks/studies/photo_calibration_study.py")
    ds = load_dataset(tiny_scene)
    capture = load_capture_points(ds)
    photos = [v for v in range(ds.num_views) if v not in set(ds.train_indices)][:3]
    for role in (CALIBRATE, SCORE):
        sparse = script.photo_points(ds, capture, photos, role)
        assert sorted(sparse) == photos
        for v in photos:
            sd = sparse[v]
            seen = set(np.flatnonzero(depth_map_observes(ds, capture.xyz, v) & (capture.roles == role)).tolist())
            got = sd.point_index.tolist()
            assert set(got) <= seen and len(got) == len(set(got))  # one point per pixel: a subset at most
            assert len(got) >= 0.5 * len(seen)
            assert (capture.roles[sd.point_index] == role).all()
            if len(sd):
                import torch

                cam = select_cameras(ds.cameras, [v])
                cam = type(cam)(cam.intrinsics.double(), cam.extrinsics.double(), cam.height.double(), cam.width.double())
                uv, z = project_points(cam, torch.from_numpy(capture.xyz[sd.point_index]))
                np.testing.assert_allclose(sd.uv, uv[0].numpy(), atol=1e-4)
                np.testing.assert_allclose(sd.depth, z[0].numpy(), rtol=1e-6)


def test_cross_fitted_coverage_judges_each_block_by_the_others(load_script):
    """Two blocks whose fitting points have |z| = 1 (block 0) and 3 (block 1); every scored point
    has |z| = 2. Cross-fitted in two folds, block 0's points get block 1's map (bound 3: inside at
    every level) and block 1's get block 0's (bound 1: outside): half inside at every level. Fitted
    on both blocks, the same points would all fall inside the 95% interval."""
    from stochastic_fields.calibration import QuantileCalibration

    script = load_script("benchmarks/studies/photo_calibration_study.py")  # puts benchmarks/ on the path
    from study_helpers import coverage
    n = 60
    fitting = {"abs_err": np.r_[np.ones(n), 3 * np.ones(n)], "std": np.ones(2 * n), "block": np.r_[np.zeros(n), np.ones(n)]}
    scored = {"abs_err": 2 * np.ones(4), "std": np.ones(4), "block": np.array([0, 0, 1, 1])}
    for seed in (0, 1, 2):
        assert script.cross_fitted_coverage(scored, fitting, folds=2, seed=seed) == pytest.approx([0.5, 0.5])
    pooled = QuantileCalibration.fit_errors(fitting["abs_err"], fitting["std"], quantity="depth_std")
    assert coverage(scored["abs_err"], scored["std"], pooled)[1] == 1.0
    # a block with no scored point is skipped; the coverage is over the scored points only
    three = {"abs_err": np.r_[fitting["abs_err"], np.ones(n)], "std": np.ones(3 * n),
             "block": np.r_[fitting["block"], 2 * np.ones(n)]}
    got = script.cross_fitted_coverage({**scored, "block": np.array([2, 2, 2, 2])}, three, folds=3)
    assert got == pytest.approx([1.0, 1.0])  # block 2 judged by blocks 0 and 1: bound Q_p of {1, 3}


def _run(views: float, photos: float, score_blocks: float = 0.0, one=(0.05,), cross=(0.0, 0.0)) -> dict:
    cov = lambda d: [0.683 + d, 0.95]  # noqa: E731  (distance = d)
    return {"coverage": {"views": cov(views), "photos": cov(photos), "photos_score_blocks": cov(score_blocks)},
            "distance": {"views": views, "photos": photos, "photos_score_blocks": score_blocks},
            "one_photo": {str(i): {"points": 100, "coverage": cov(d), "distance": d} for i, d in enumerate(one)},
            "cross_fitted": {"views": cov(cross[0]), "photos": cov(cross[1])}}


def test_rule_by_hand(load_script):
    """Means over a scene's seeds; each scene may lose at most 0.02 of distance, and the mean over
    scenes must gain at least 0.02."""
    script = load_script("benchmarks/studies/photo_calibration_study.py")
    good = script.decide({"runs": {"a/0": _run(0.10, 0.04), "a/1": _run(0.08, 0.04), "b/0": _run(0.05, 0.06)}})
    assert good["passes"] and good["worse_on"] == []
    assert good["scenes"]["a"]["distance_views"] == pytest.approx(0.09)
    assert good["mean_distance_gain"] == pytest.approx((0.05 - 0.01) / 2)
    small = script.decide({"runs": {"a/0": _run(0.10, 0.09), "b/0": _run(0.05, 0.04)}})
    assert not small["passes"] and small["worse_on"] == []
    worse = script.decide({"runs": {"a/0": _run(0.20, 0.02), "b/0": _run(0.05, 0.08)}})
    assert not worse["passes"] and worse["worse_on"] == ["b"] and worse["mean_distance_gain"] > 0.02
    one = script.decide({"runs": {"a/0": _run(0.1, 0.1, one=(0.02, 0.08)), "a/1": _run(0.1, 0.1, one=(0.05,))}})
    assert one["scenes"]["a"]["one_photo_maps"] == 3
    assert one["scenes"]["a"]["one_photo_distance_mean"] == pytest.approx(0.05)
    assert one["scenes"]["a"]["one_photo_distance_range"] == pytest.approx([0.02, 0.08])
    cross = script.decide({"runs": {"a/0": _run(0.1, 0.1, cross=(0.02, 0.04)), "a/1": _run(0.1, 0.1, cross=(0.04, 0.0))}})
    assert cross["scenes"]["a"]["coverage_cross_fitted"]["views"] == pytest.approx([0.683 + 0.03, 0.95])
    assert cross["scenes"]["a"]["coverage_cross_fitted"]["photos"] == pytest.approx([0.683 + 0.02, 0.95])


def test_committed_decision_recomputed(load_script):
    """The committed study: the photos fail the rule (flower's distance grows), and the same photos'
    map fitted on the SCORE blocks holds on every scene (the viewpoints transfer; the blocks do not)."""
    script = load_script("benchmarks/studies/photo_calibration_study.py")
    committed = json.loads((RESULTS / "study.json").read_text())
    again = script.decide(committed)
    assert again == committed["decision"]
    assert not again["passes"] and again["worse_on"] == ["flower"]
    for m in again["scenes"].values():
        assert m["seeds"] == 3 and m["distance_photos_score_blocks"] < m["distance_photos"]
        # the cross-fitted virtual-view map holds within 5 points at both levels (study 18's diagnostic)
        assert np.abs(np.subtract(m["coverage_cross_fitted"]["views"], [0.6827, 0.95])).max() <= 0.05
    groups = script.coverage_groups(committed)
    assert list(groups) == ["synthetic", "fern", "flower"]
    assert groups["flower"][1]["coverage"] == committed["runs"]["flower/1"]["coverage"]["photos"]
    assert groups["flower"][1]["coverage_raw"] == committed["runs"]["flower/1"]["coverage"]["views"]


def test_study_18b_confirms_the_cross_fitted_map_on_fresh_seeds(load_script):
    """Study 18b's rule, recomputed from its committed runs (seeds 3 and 4, never looked at before):
    on each scene's mean over the two seeds the cross-fitted virtual-view map holds both levels within
    5 points of nominal, while today's CALIBRATE-only map does not on the synthetic scene and flower."""
    script = load_script("benchmarks/studies/photo_calibration_study.py")
    committed = json.loads((RESULTS.parent / "photo_calibration_18b" / "study.json").read_text())
    again = script.decide(committed)
    assert again == committed["decision"]
    assert sorted(r.split("/")[1] for r in committed["runs"]) == ["3", "3", "3", "4", "4", "4"]
    for scene, m in again["scenes"].items():
        assert m["seeds"] == 2
        assert np.abs(np.subtract(m["coverage_cross_fitted"]["views"], [0.6827, 0.95])).max() <= 0.05, scene
    assert again["scenes"]["synthetic"]["distance_views"] > 0.05 and again["scenes"]["flower"]["distance_views"] > 0.05


def _validation_run(calibrate: float, held: float) -> dict:
    cov = lambda d: [0.6827 + d, 0.95]  # noqa: E731  (distance = d)
    return {"photo_validation": {"scored_points": 10, "coverage": {"calibrate": cov(calibrate), "held-out": cov(held)},
                                 "distance": {"calibrate": calibrate, "held-out": held}}}


def test_study_18c_rule_by_hand_and_its_committed_decision(load_script):
    """Study 18c judges the held-out default on the unused photos only: each scene's seed mean may lose
    at most 0.02 of distance and the mean over scenes must gain 0.02. The committed study (seeds 0-4,
    no test view rendered) keeps the default."""
    script = load_script("benchmarks/studies/photo_calibration_study.py")
    keep = script.decide_validation({"runs": {"a/0": _validation_run(0.10, 0.03), "a/1": _validation_run(0.08, 0.03),
                                              "b/0": _validation_run(0.04, 0.05)}})
    assert keep["passes"] and keep["scenes"]["a"]["distance_held-out"] == pytest.approx(0.03)
    assert keep["mean_distance_gain"] == pytest.approx((0.06 - 0.01) / 2)
    close = script.decide_validation({"runs": {"a/0": _validation_run(0.07, 0.03), "b/0": _validation_run(0.04, 0.05)}})
    assert not close["passes"] and close["mean_distance_gain"] == pytest.approx(0.015)
    worse = script.decide_validation({"runs": {"a/0": _validation_run(0.20, 0.0), "b/0": _validation_run(0.02, 0.05)}})
    assert not worse["passes"] and worse["worse_on"] == ["b"]
    small = script.decide_validation({"runs": {"a/0": _validation_run(0.05, 0.04)}})
    assert not small["passes"] and small["worse_on"] == []
    committed = json.loads((RESULTS.parent / "photo_validation" / "study.json").read_text())
    again = script.decide_validation(committed)
    assert again == committed["validation"] and again["passes"]
    assert all(m["seeds"] == 5 for m in again["scenes"].values())
