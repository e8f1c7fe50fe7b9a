"""The free-space check (``free_space``): violations by hand (in front, behind, outside, behind the
camera, transparent pixels, excluded views), a training view's own depth violating nothing, the
points a render puts on its rays, the stored file (round trip, malformed and pickled files
refused), and end to end on a mesh: the checked std ranks an error the reported std leaves out."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from scipy import stats

from stochastic_fields.free_space import (TRAINING_DEPTH_FILE, TrainingDepth, agreeing_views, checked_std,
                                          free_space_violation,
                                          load_training_depth, rendered_points, save_training_depth, violation_map)


def _two_views() -> TrainingDepth:
    """View 3: at the origin looking along +z, surface at z = 5, column 0 transparent. View 8: one
    unit behind it (centre (0, 0, -1)), surface at its z = 4.5. Both 10 x 10 pixels, f = 10."""
    K = np.array([[10.0, 0, 5.0], [0, 10.0, 5.0], [0, 0, 1]])
    w2c = np.repeat(np.eye(4)[None], 2, 0)
    w2c[1, 2, 3] = 1.0  # x_cam = x_world + (0, 0, 1)
    depth = np.stack([np.full((10, 10), 5.0), np.full((10, 10), 4.5)]).astype(np.float32)
    opacity = np.ones_like(depth)
    opacity[0, :, 0] = 0.0
    return TrainingDepth(np.array([3, 8]), np.stack([K, K]), w2c, depth, opacity)


def test_free_space_violation_by_hand():
    ref = _two_views()
    points = np.array([
        [0.0, 0.0, 3.0],    # in front of both surfaces: 5 - 3 = 2 (view 3), 4.5 - 4 = 0.5 (view 8)
        [0.0, 0.0, 6.0],    # behind both: occluded, no violation
        [0.0, 0.0, -2.0],   # behind both cameras
        [-0.9, 0.0, 2.0],   # view 3's transparent column 0 (u = 0.5); view 8: u = 2, 4.5 - 3 = 1.5
        [10.0, 0.0, 1.0],   # outside both images
        [0.0, 0.0, 5.0],    # on view 3's surface: 0; view 8: 4.5 - 6 < 0
    ])
    np.testing.assert_allclose(free_space_violation(points, ref), [2.0, 0.0, 0.0, 1.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(free_space_violation(points, ref, exclude=[3]), [0.5, 0, 0, 1.5, 0, 0], atol=1e-12)
    assert free_space_violation(np.zeros((0, 3)), ref).shape == (0,)


def test_agreeing_views_by_hand():
    ref = _two_views()  # view 3's surface at its z = 5, view 8's at its z = 4.5 (world z = 3.5)
    points = np.array([
        [0.0, 0.0, 5.0],    # on view 3's surface; view 8: z 6 against 4.5 (hidden there)
        [0.0, 0.0, 3.5],    # on view 8's surface; view 3: z 3.5 against 5 (in front)
        [0.0, 0.0, 5.1],    # view 3: |5.1 - 5| = 0.1 <= 0.05 * 5.1; view 8: no
        [-1.6, 0.0, 3.5],   # view 3's transparent column (u = 0.43); on view 8's surface (u = 1.44)
        [10.0, 0.0, 1.0],   # outside both images
        [0.0, 0.0, -2.0],   # behind both cameras
    ])
    agree, seen = agreeing_views(points, ref, tolerance=0.05)
    np.testing.assert_array_equal(agree, [1, 1, 1, 1, 0, 0])
    np.testing.assert_array_equal(seen, [2, 2, 2, 1, 0, 0])
    agree, _ = agreeing_views(points, ref, tolerance=0.01)  # 0.1 > 0.01 * 5.1
    np.testing.assert_array_equal(agree, [1, 1, 0, 1, 0, 0])
    agree, _ = agreeing_views(points, ref, tolerance=0.5)  # |6 - 4.5| <= 3 and |3.5 - 5| <= 1.75
    np.testing.assert_array_equal(agree, [2, 2, 2, 1, 0, 0])
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="tolerance"):
            agreeing_views(points, ref, tolerance=bad)


def test_a_training_view_violates_nothing_on_its_own_depth_and_a_floater_by_its_distance():
    rng = np.random.default_rng(0)
    K = np.array([[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]])
    a = np.deg2rad(20.0)
    w2c = np.eye(4)
    w2c[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    w2c[:3, 3] = [0.3, -0.2, 1.0]
    depth = rng.uniform(2.0, 6.0, size=(24, 32))
    ref = TrainingDepth(np.array([0]), K[None], w2c[None], depth[None].astype(np.float32),
                        np.ones((1, 24, 32), np.float32))
    own = violation_map(depth.astype(np.float32), K, w2c, ref)
    assert np.abs(own).max() < 1e-5 * depth.max()  # float32 depths; the same pixel centres
    floater = depth.copy()
    floater[5, 7] -= 1.25
    got = violation_map(floater, K, w2c, ref, mask=np.arange(24 * 32).reshape(24, 32) % 2 == 1)
    assert got[5, 7] == pytest.approx(1.25, abs=1e-5) and got.dtype == np.float32
    assert np.abs(np.delete(got.reshape(-1), 5 * 32 + 7)).max() < 1e-5 * depth.max()
    np.testing.assert_allclose(checked_std(np.array([3.0, 0.0]), np.array([4.0, 2.0])), [5.0, 2.0])


def test_rendered_points_lie_on_the_ray_at_the_rendered_depth():
    got = rendered_points(np.array([[0.0, 0, 0], [1, 1, 1]]), np.array([[1.0, 2, 4], [1, 1, 3]]),
                          np.array([4.0, 2.0]), np.array([2.0, 3.0]))
    np.testing.assert_allclose(got, [[0.5, 1.0, 2.0], [1.0, 1.0, 4.0]])


def test_training_depth_file_round_trip_and_refusals(tmp_path):
    assert load_training_depth(tmp_path) is None
    ref = _two_views()
    path = save_training_depth(tmp_path, ref)
    assert path == tmp_path / TRAINING_DEPTH_FILE
    back = load_training_depth(tmp_path)
    for name in ("views", "intrinsics", "world_to_camera", "depth", "opacity"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ref, name))
    assert back.psnr is None  # a file without the pose check's PSNR (written before it) still loads
    scored = dataclasses.replace(ref, psnr=np.array([24.5, np.inf]))  # +inf: a view rendered exactly
    save_training_depth(tmp_path, scored)
    np.testing.assert_array_equal(load_training_depth(tmp_path).psnr, scored.psnr)
    with pytest.raises(ValueError, match=r"psnr must be \[2\]"):
        dataclasses.replace(ref, psnr=np.array([24.5]))
    np.savez(path, views=ref.views, intrinsics=ref.intrinsics, world_to_camera=ref.world_to_camera,
             depth=ref.depth)  # no opacity
    with pytest.raises(ValueError, match=f"{TRAINING_DEPTH_FILE}.*malformed"):
        load_training_depth(tmp_path)
    np.savez(path, views=ref.views, intrinsics=ref.intrinsics, world_to_camera=ref.world_to_camera,
             depth=np.full_like(ref.depth, np.nan), opacity=ref.opacity)
    with pytest.raises(ValueError, match="non-finite"):
        load_training_depth(tmp_path)
    np.savez(path, views=np.array([object()]), intrinsics=ref.intrinsics, world_to_camera=ref.world_to_camera,
             depth=ref.depth, opacity=ref.opacity)  # a pickled object is never loaded
    with pytest.raises(ValueError, match="malformed"):
        load_training_depth(tmp_path)
    with pytest.raises(ValueError, match=r"depth and opacity must both be \[2, H, W\]"):
        TrainingDepth(ref.views, ref.intrinsics, ref.world_to_camera, ref.depth, ref.opacity[:1])


def test_checked_std_ranks_an_error_the_reported_std_misses(tmp_path):
    """End to end on the synthetic mesh (training views rendered by the model, calibration views,
    projection, camera z): the training views see the exact surface; the calibration renders add an
    error the reported std leaves out. The points rendered in front of the surface violate the
    training views' free space, so the checked std ranks the errors far better; an exact model's
    checked std stays its reported one."""
    from stochastic_fields.calibration import depth_calibration_errors
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene
    from stochastic_fields.free_space import render_training_depth
    from test_depth_likelihood_calibration import _MeshDepthModel

    scene = make_synthetic_scene(tmp_path / "scene", num_views=20, width=192, height=144, seed=0)
    ds = load_dataset(scene, split_every=5)
    exact = _MeshDepthModel(scene / "scene.ply", 0.0)
    ref = render_training_depth(exact, ds, progress=False)
    assert ref.depth.shape == (4, 144, 192) and list(ref.views) == list(ds.train_indices)
    err, raw, _ = depth_calibration_errors(exact, ds)
    err_c, checked, source = depth_calibration_errors(exact, ds, free_space=ref)
    np.testing.assert_array_equal(err, err_c)
    assert "free space" in source and (checked >= raw).all()
    assert np.median(checked / raw) < 1.05  # an exact surface violates (almost) nothing

    missed = _MeshDepthModel(scene / "scene.ply", 1.0, abs_std=0.3, std_spread=0.5)
    err, raw, _ = depth_calibration_errors(missed, ds)
    _, checked, _ = depth_calibration_errors(missed, ds, free_space=ref)
    assert stats.spearmanr(err, checked)[0] > stats.spearmanr(err, raw)[0] + 0.2


@pytest.mark.parametrize("bad", ["intrinsics", "views"])
def test_training_depth_refuses_mismatched_cameras(bad):
    ref = _two_views()
    kwargs = dict(views=ref.views, intrinsics=ref.intrinsics, world_to_camera=ref.world_to_camera,
                  depth=ref.depth, opacity=ref.opacity)
    kwargs[bad] = kwargs[bad][:1] if bad == "intrinsics" else np.zeros(0, np.int64)
    with pytest.raises(ValueError, match="training depth"):
        TrainingDepth(**kwargs)


def _checked_run_calibration(scale: float = 2.0):
    from stochastic_fields.calibration import CALIBRATION_LEVELS, QuantileCalibration, RunCalibration

    depth = QuantileCalibration("depth_std", CALIBRATION_LEVELS, np.full(len(CALIBRATION_LEVELS), scale), 100, "test",
                                free_space=True)
    return RunCalibration(depth=depth, training_depth=_two_views())


def test_apply_calibration_checks_each_pixel_against_the_training_views():
    """View 3's own camera renders its surface (z = 5) except one pixel at z = 3: that pixel violates
    view 3's free space by 2 (view 8's by 0.5), so its std is s sqrt(1 + 2^2); the rest keep s * 1.
    Transparent pixels are not checked; without the camera the map cannot be applied."""
    from stochastic_fields.calibration import apply_calibration

    cal = _checked_run_calibration()
    depth = np.full((10, 10), 5.0, np.float32)
    depth[4, 6] = 3.0
    opacity = np.ones((10, 10), np.float32)
    opacity[7, 7], depth[7, 7] = 0.0, 1.0  # would violate, but transparent
    products = {"depth_mean": depth, "depth_std": np.ones((10, 10), np.float32), "opacity": opacity}
    ref = cal.training_depth
    out = apply_calibration(products, cal, camera=(ref.intrinsics[0], ref.world_to_camera[0]))
    expected_e = np.zeros((10, 10))
    expected_e[4, 6] = 2.0
    np.testing.assert_allclose(out["depth_free_space"], expected_e, atol=1e-6)
    np.testing.assert_allclose(out["depth_std"], 2.0 * np.hypot(1.0, expected_e), rtol=1e-6)
    assert out["depth_std_raw"] is products["depth_std"] and out["depth_std"].dtype == np.float32
    with pytest.raises(ValueError, match="checks free space"):
        apply_calibration(products, cal)
    with pytest.raises(ValueError, match="free-space violation"):
        cal.depth.calibrated_std(np.ones(3))
    np.testing.assert_allclose(cal.depth.calibrated_std(np.array([3.0]), np.array([4.0])), [10.0])


def test_checked_calibration_file_needs_its_training_depths(tmp_path):
    from stochastic_fields.calibration import CALIBRATION_FILE, describe, load_run_calibration, save_run_calibration

    cal = _checked_run_calibration()
    save_training_depth(tmp_path, cal.training_depth)
    save_run_calibration(tmp_path, cal)
    back = load_run_calibration(tmp_path)
    assert back.depth.free_space and back.training_depth.depth.shape == (2, 10, 10)
    assert "free-space violation" in describe(back)
    (tmp_path / TRAINING_DEPTH_FILE).unlink()
    with pytest.raises(ValueError, match=f"{CALIBRATION_FILE}.*{TRAINING_DEPTH_FILE} is missing"):
        load_run_calibration(tmp_path)
    data = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    data["depth"]["free_space"] = "yes"
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(data))
    with pytest.raises(ValueError, match="free_space must be true or false"):
        load_run_calibration(tmp_path)
    del data["depth"]["free_space"]  # written before the check existed: none
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(data))
    assert not load_run_calibration(tmp_path).depth.free_space


def _check_weight_data(seed: int = 0, n: int = 1500):
    """Errors of N(0, sigma), sigma ~ U(0.01, 0.05), at depths ~ U(2, 10) where the check is silent; at
    a fifth of the points a wrong surface with error ~ e |N(0, 1)| that sigma misses, e = 1: (abs_err,
    sigma, e, depth). (Stds and depths vary, or rho = 1 would make every std alike and tie the grid.)"""
    rng = np.random.default_rng(seed)
    sigma, depth = rng.uniform(0.01, 0.05, n), rng.uniform(2.0, 10.0, n)
    e = np.where(np.arange(n) % 5 == 0, 1.0, 0.0)
    err = np.abs(rng.normal(size=n)) * np.hypot(sigma, e)
    return err, sigma, e, depth


def test_check_weight_follows_whether_the_violation_explains_the_errors():
    """fit_check_weight: where the violation is the missed error, the full weight (the grid's end);
    where it fires on points whose errors sigma already explains, 0 (the unchecked map); by hand,
    the chosen weight has the smallest CRPS / depth of the grid."""
    from stochastic_fields.calibration import (CHECK_WEIGHT_GRID, fit_check_weight, fit_relative_floor,
                                              relative_crps)

    err, sigma, e, depth = _check_weight_data()
    assert fit_check_weight(err, sigma, e, depth) == 1.0
    rng = np.random.default_rng(1)
    honest = np.abs(rng.normal(size=err.size)) * sigma  # the same violations, errors that ignore them
    assert fit_check_weight(honest, sigma, e, depth) == 0.0
    half = np.abs(rng.normal(size=err.size)) * np.hypot(sigma, 0.3 * e)  # the violation at a third of its size
    beta = fit_check_weight(half, sigma, e, depth)
    crps = [relative_crps(half, checked_std(sigma, b * e), depth, fit_relative_floor(half, checked_std(sigma, b * e), depth))
            for b in CHECK_WEIGHT_GRID]
    assert beta == CHECK_WEIGHT_GRID[int(np.argmin(crps))] and 0.15 < beta < 0.6
    with pytest.raises(ValueError, match="violation"):
        fit_check_weight(err, sigma, -e - 1.0, depth)


def test_a_weighted_check_round_trips_and_scales_only_the_violation():
    """A map with weight beta applies s sqrt(raw^2 + (beta e)^2); the weight survives the file; files
    without it read as the full check; a negative weight is refused naming the file; a fitted weight
    of 0 leaves a map that needs no violation."""
    from stochastic_fields.calibration import QuantileCalibration, _fit_depth_map

    err, sigma, e, depth = _check_weight_data()
    renders = {"abs_err": err, "std": checked_std(sigma, e), "std_raw": sigma, "violation": e, "depth": depth,
               "source": "test"}
    m, std = _fit_depth_map(renders, floor=False, relative_floor=True, check_weight=0.25)
    assert m.free_space and m.free_space_weight == 0.25
    np.testing.assert_allclose(std, np.hypot(sigma, 0.25 * e))
    raw, v = np.array([0.1, 0.2]), np.array([0.0, 0.4])
    np.testing.assert_allclose(m.calibrated_std(raw, v, np.array([1.0, 1.0])),
                               m.std_scale * np.hypot(np.hypot(raw, 0.25 * v), m.relative_floor))
    back = QuantileCalibration.from_dict(m.to_dict())
    assert back.free_space_weight == 0.25
    data = m.to_dict()
    del data["free_space_weight"]
    assert QuantileCalibration.from_dict(data).free_space_weight == 1.0
    data["free_space_weight"] = -1.0
    with pytest.raises(ValueError, match="calibration.json.*weight"):
        QuantileCalibration.from_dict(data, where="RUN/calibration.json")
    rng = np.random.default_rng(1)
    unchecked, _ = _fit_depth_map({**renders, "abs_err": np.abs(rng.normal(size=err.size)) * sigma},
                                  floor=False, relative_floor=True)
    assert not unchecked.free_space
    np.testing.assert_allclose(unchecked.calibrated_std(raw), unchecked.std_scale * raw)
    with pytest.raises(ValueError, match="weight"):
        _fit_depth_map(renders, floor=False, relative_floor=True, check_weight=float("nan"))


@pytest.mark.slow
def test_a_run_calibrated_with_the_free_space_check_applies_it_in_eval_and_export(tmp_path):
    """calibrate_run(free_space=True) stores the training views' depths first, then a map that says so;
    eval writes each view's violation map and a depth std of s sqrt(raw^2 + (beta e)^2 + (rho d)^2) at the
    given weight beta; the depth products
    (export, notebook) apply the same."""
    import torch

    from stochastic_fields.calibration import calibrate_run, load_run_calibration
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.products.depth_maps import compute_depth_products
    from stochastic_fields.view_maps import view_camera_arrays

    from conftest import train_tiny_synthetic_run

    model, ds = train_tiny_synthetic_run(tmp_path)
    cal = calibrate_run(tmp_path, model=model, dataset=ds, free_space=True, check_weight=0.5, progress=False)
    assert cal.depth.free_space and cal.depth.free_space_weight == 0.5 and (tmp_path / TRAINING_DEPTH_FILE).is_file()
    stored = load_run_calibration(tmp_path)
    np.testing.assert_array_equal(stored.training_depth.depth, cal.training_depth.depth)
    v = int(ds.test_indices[0])
    evaluate(model, ds, tmp_path / "eval", views=[v], progress=False, calibration=stored)
    with np.load(tmp_path / "eval" / "views" / f"view_{v:03d}.npz") as f:
        e, std, raw, depth = f["depth_free_space"], f["depth_std"], f["depth_std_raw"], f["depth_mean"]
    rho = cal.depth.relative_floor  # the depth-proportional term (default on) joins the check's e
    np.testing.assert_allclose(std, cal.depth.std_scale * np.hypot(np.hypot(raw.astype(np.float64), 0.5 * e),
                                                                   rho * depth.astype(np.float64)), rtol=1e-5)
    assert (tmp_path / "eval" / "views" / f"view_{v:03d}_depth_free_space.png").is_file()
    cam = view_camera_arrays(ds, v)
    with torch.no_grad():
        maps = model.render_view(ds.rays(v), model.render_options(keep_draws=True))
    products = compute_depth_products(maps, cam["intrinsics"], cam["world_to_camera"], near=cam["near"],
                                      far=cam["far"], calibration=stored)
    e = violation_map(products.depth_mean, cam["intrinsics"], cam["world_to_camera"], stored.training_depth,
                      mask=products.opacity > 0.5)
    np.testing.assert_allclose(products.depth_std,
                               cal.depth.std_scale * np.hypot(np.hypot(products.depth_std_raw.astype(np.float64), 0.5 * e),
                                                              rho * products.depth_mean.astype(np.float64)), rtol=1e-5)


def test_free_space_study_scores_and_rule_by_hand(load_script):
    """benchmarks/studies/free_space_study.py: Spearman per view (mean) and pooled, and the rule on hand-made
    runs (mean per-view gain, per-scene tolerances on both Spearmans and the distance), and the
    committed studies' decisions (13 and 13b) recomputed from their runs."""
    from pathlib import Path

    script = load_script("benchmarks/studies/free_space_study.py")
    err = np.array([1.0, 2.0, 3.0, 4.0, 3.0, 2.0, 1.0, 0.5])
    std = np.array([1.0, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0])
    view = np.array([0, 0, 0, 0, 5, 5, 5, 5])
    got = script.spearman_scores(err, std, view)
    assert got["per_view"] == pytest.approx(0.0)  # +1 on view 0, -1 on view 5
    assert got["pooled"] == pytest.approx(stats.spearmanr(err, std)[0])

    def run(sp_plain, sp_checked, d_plain=0.05, d_checked=0.05, pooled_drop=0.0):
        return {"spearman": {"plain": {"per_view": sp_plain, "pooled": sp_plain},
                             "checked": {"per_view": sp_checked, "pooled": sp_checked - pooled_drop}},
                "coverage": {"plain": [0.7, 0.95], "checked": [0.68, 0.95]},
                "distance": {"plain": d_plain, "checked": d_checked}}

    good = {"runs": {"a/0": run(0.6, 0.65), "a/1": run(0.6, 0.63), "b/0": run(0.5, 0.51)}}
    d = script.decide(good)
    assert d["taken"] and d["scenes"]["a"]["seeds"] == 2 and d["mean_spearman_gain"] == pytest.approx(0.025)
    small = script.decide({"runs": {"a/0": run(0.6, 0.61), "b/0": run(0.5, 0.51)}})
    assert not small["taken"] and small["worse_on"] == []
    for bad_b in (run(0.5, 0.6, 0.05, 0.08), run(0.5, 0.6, pooled_drop=0.2)):
        bad = script.decide({"runs": {"a/0": run(0.6, 0.7), "b/0": bad_b}})
        assert not bad["taken"] and bad["worse_on"] == ["b"]
    results = Path(__file__).resolve().parents[1] / "benchmarks/results/uncertainty_study"
    for folder in ("free_space_16b", "free_space"):  # study 13b (on study 16b's default), then study 13
        committed = json.loads((results / folder / "study.json").read_text())
        again = script.decide(committed)
        assert again == committed["decision"] and again["worse_on"] == ["fern"] and not again["taken"]
    groups = script.coverage_groups(committed)  # the figure's bars: one per seed run and map
    assert list(groups) == ["synthetic", "fern", "flower"] and [r["group"] for r in groups["fern"]] == [
        "seed 0", "seed 1", "seed 2"]
    assert groups["fern"][2]["coverage"] == committed["runs"]["fern/2"]["coverage"]["checked"]
    assert groups["fern"][2]["coverage_raw"] == committed["runs"]["fern/2"]["coverage"]["plain"]


def test_carved_points_by_hand():
    """View 3 of ``_two_views`` with a spread of 0.1: a point is carved in front of 5 - 0.3 - 0.25 = 4.45,
    not behind it, not where the ray ended broadly or faintly, and never without the spread."""
    from stochastic_fields.free_space import carved_points

    ref = _two_views()
    ref.views, ref.intrinsics, ref.world_to_camera = ref.views[:1], ref.intrinsics[:1], ref.world_to_camera[:1]
    ref.depth, ref.opacity = ref.depth[:1], ref.opacity[:1].copy()
    ref.spread = np.full_like(ref.depth, 0.1)
    ref.spread[0, 2, 5] = 0.3  # broad: 0.3 >= 0.05 * 5
    ref.opacity[0, 7, 5] = 0.8  # faint
    points = np.array([[0.0, 0.0, 4.4], [0.0, 0.0, 4.5], [0.0, -1.0, 4.0], [0.0, 1.0, 4.0], [0.0, 0.0, -1.0]])
    # pixels (row, col): (5, 5), (5, 5), (2, 5) broad, (7, 5) faint, behind the camera
    np.testing.assert_array_equal(carved_points(points, ref), [True, False, False, False, False])
    assert carved_points(points, ref, margin=0.0)[1]  # 4.5 < 5 - 0.3
    ref.spread = None
    with pytest.raises(ValueError, match="spread"):
        carved_points(points, ref)


def test_carve_free_space_empties_only_cells_in_front_of_the_surface():
    """A model without a grid gets an all-occupied one; against one view looking along +z at a wall at
    z = 5, exactly the cells whose centre lies in front of 5 - 0.3 - 0.25 = 4.45 are emptied."""
    from stochastic_fields.free_space import carve_free_space
    from stochastic_fields.scene_region import SceneRegion

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.anchor = torch.nn.Parameter(torch.zeros(1))
            self.region = SceneRegion("aabb", torch.tensor([[-0.4, -0.4, 2.0], [0.4, 0.4, 6.0]]))
            self.occupancy = None

    ref = _two_views()
    ref.views, ref.intrinsics, ref.world_to_camera = ref.views[:1], ref.intrinsics[:1], ref.world_to_camera[:1]
    ref.depth, ref.opacity = ref.depth[:1], np.ones_like(ref.depth[:1])
    ref.spread = np.full_like(ref.depth, 0.1)
    model = Model()
    share = carve_free_space(model, ref, resolution=8)
    grid = model.occupancy
    assert grid.resolution.tolist() == [8, 8, 8]
    z_centres = 2.0 + (np.arange(8) + 0.5) * 0.5  # 2.25 ... 5.75
    expected = np.broadcast_to(z_centres >= 4.45, (8, 8, 8))  # every cell projects inside the image
    np.testing.assert_array_equal(grid.occupancy.numpy(), expected)
    assert share == pytest.approx(1.0 - expected.mean())


def test_carve_study_rule_by_hand(load_script):
    """benchmarks/studies/carve_study.py: abs-rel must fall on every scene, the other measures stay within
    study 8's tolerances; the committed decision recomputes from its runs."""
    from pathlib import Path

    script = load_script("benchmarks/studies/carve_study.py")

    def scores(psnr=20.0, nll=-1.0, colour=0.5, abs_rel=0.1, depth=0.6, distance=0.05):
        return {"psnr": psnr, "nll": nll, "colour_spearman": colour, "depth_abs_rel": abs_rel,
                "depth_spearman_view": depth, "depth_spearman_pooled": depth, "coverage": [0.7, 0.95],
                "distance": distance}

    def run(**carved):
        return {"plain": scores(), "carved": scores(**{"abs_rel": 0.09, **carved})}

    assert script.decide({"runs": {"a/0": run(), "b/0": run(psnr=19.85, nll=-0.96, depth=0.59)}})["taken"]
    for bad, key in ((dict(abs_rel=0.1), "depth_abs_rel"), (dict(psnr=19.7), "psnr"), (dict(nll=-0.9), "nll"),
                     (dict(colour=0.47), "colour_spearman"), (dict(depth=0.5), "depth_spearman_view"),
                     (dict(distance=0.08), "distance")):
        d = script.decide({"runs": {"a/0": run(), "b/0": run(**bad)}})
        assert not d["taken"] and d["failed"] == {"b": [key]}
    committed = json.loads((Path(__file__).resolve().parents[1] / "benchmarks/results/uncertainty_study/carve"
                            / "study.json").read_text())
    again = script.decide(committed)
    assert again == committed["decision"] and again["failed"] == {"flower": ["depth_spearman_view", "distance"]}
    with_check = json.loads((Path(__file__).resolve().parents[1] / "benchmarks/results/uncertainty_study"
                             / "carve_check" / "study.json").read_text())  # study 15
    assert script.decide(with_check) == with_check["decision"]
    assert with_check["decision"]["failed"] == {"flower": ["depth_spearman_view"]}


def test_free_space_study_cross_fitted_coverage_by_hand(load_script):
    """Study 13c's coverage of a held-out map: two blocks of space (two clusters of capture points,
    both SCORE), renders with |z| = 1 in one and 3 in the other; every scored point has |z| = 2.
    Cross-fitted, each cluster is judged by the other's map: half inside at either level."""
    from types import SimpleNamespace

    from stochastic_fields.capture_points import SCORE

    script = load_script("benchmarks/studies/free_space_study.py")
    n = 100
    xyz = np.r_[np.zeros((n, 3)), np.ones((n, 3))] + np.random.default_rng(0).uniform(0, 0.01, (2 * n, 3))
    capture = SimpleNamespace(xyz=xyz, roles=np.full(2 * n, SCORE, np.int8))
    renders = {"abs_err": np.r_[np.ones(n), 3 * np.ones(n)], "std": np.ones(2 * n), "index": np.arange(2 * n)}
    scored = {"gt": np.full(4, 5.0), "depth_mean": np.full(4, 7.0), "abs_err": np.full(4, 2.0), "std": np.ones(4),
              "xyz": xyz[[0, 1, n, n + 1]]}
    assert script.cross_fitted_coverage(renders, scored, capture) == pytest.approx([0.5, 0.5])


def test_study_13c_decision_recomputed(load_script):
    """Study 13c (the check under the held-out map, scored cross-fitted): ranking up on every scene,
    but flower's intervals move away from nominal by more than the tolerance; not taken."""
    from pathlib import Path

    script = load_script("benchmarks/studies/free_space_study.py")
    path = Path(__file__).resolve().parents[1] / "benchmarks/results/uncertainty_study/free_space_13c/study.json"
    committed = json.loads(path.read_text())
    again = script.decide(committed)
    assert committed["points"] == "held-out"
    assert again == committed["decision"] and again["worse_on"] == ["flower"] and not again["taken"]
    assert all(m["spearman_per_view_checked"] > m["spearman_per_view_plain"] for m in again["scenes"].values())


def test_calibrate_command_takes_a_weight_or_refuses_it(capsys):
    """``--free-space-weight``: a number >= 0 (default: fitted, None); anything else one clear line."""
    from stochastic_fields.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["calibrate", "--run", "r"]).free_space_weight is None
    assert parser.parse_args(["calibrate", "--run", "r", "--free-space-weight", "0.3"]).free_space_weight == 0.3
    for bad in ("-1", "nan", "inf", "half"):
        with pytest.raises(SystemExit):
            parser.parse_args(["calibrate", "--run", "r", "--free-space-weight", bad])
        assert "--free-space-weight: expected" in capsys.readouterr().err
