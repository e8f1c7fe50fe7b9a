"""The training views' parallax at a rendered point and the depth-std term it gives (``parallax``,
``calibration.fit_parallax_weight``): angles by hand, the term and the calibrated std by hand, the
fitted weight against the one errors were drawn with, and a run calibrated with the term applying
it the same way in eval and export."""

from __future__ import annotations

import numpy as np
import pytest

from stochastic_fields.calibration import (ONE_SIGMA_LEVEL, PARALLAX_WEIGHT_GRID, DepthFolds, QuantileCalibration,
                                           RunCalibration, _fit_depth_map, apply_calibration,
                                           cross_fitted_depth_quantiles, cross_fitted_depth_scores,
                                           fit_parallax_weight)
from stochastic_fields.constants import PARALLAX_MIN_SIN
from stochastic_fields.free_space import TrainingDepth, free_space_violation, violation_map
from stochastic_fields.parallax import (SEE_TOLERANCE, parallax_angle, parallax_map, parallax_term, training_view_maps,
                                       training_view_terms, widest_cosine, widest_cosine_loop)


def _three_views() -> TrainingDepth:
    """Three cameras looking along +z with identity rotation, centres (0, 0, 0), (1, 0, 0) and
    (-2, 0, 0); 40 x 40 pixels, f = 20, principal point at the centre. Each renders a wall at its
    z = 4 (views 0 and 1) and z = 2 (view 2: a surface nearer than the points below hides them)."""
    K = np.array([[20.0, 0, 20.0], [0, 20.0, 20.0], [0, 0, 1]])
    w2c = np.repeat(np.eye(4)[None], 3, 0)
    for t, cx in enumerate((0.0, 1.0, -2.0)):
        w2c[t, 0, 3] = -cx  # x_cam = x_world - cx
    depth = np.stack([np.full((40, 40), 4.0), np.full((40, 40), 4.0), np.full((40, 40), 2.0)]).astype(np.float32)
    return TrainingDepth(np.array([0, 1, 2]), np.stack([K] * 3), w2c, depth, np.ones_like(depth))


def _angle(a: np.ndarray, b: np.ndarray, X: np.ndarray) -> float:
    u, v = a - X, b - X
    return float(np.degrees(np.arccos(u @ v / np.linalg.norm(u) / np.linalg.norm(v))))


def test_parallax_angle_by_hand():
    ref = _three_views()
    X = np.array([[0.5, 0.0, 4.0],    # on views 0 and 1's walls; view 2's wall at z 2 hides it
                  [0.5, 0.0, 3.0],    # in front of the walls of views 0 and 1 (they see it), hidden from view 2
                  [0.5, 0.0, 4.15],   # behind views 0 and 1's walls by less than 5%: they still see it
                  [0.5, 0.0, 4.5],    # behind them by more: no view sees it
                  [0.5, 0.0, -1.0]])  # behind every camera
    angle, seen = parallax_angle(X, ref)
    c0, c1 = np.zeros(3), np.array([1.0, 0, 0])
    np.testing.assert_allclose(angle[:3], [_angle(c0, c1, X[0]), _angle(c0, c1, X[1]), _angle(c0, c1, X[2])],
                               rtol=1e-12)
    np.testing.assert_array_equal(angle[3:], [0.0, 0.0])
    np.testing.assert_array_equal(seen, [2, 2, 2, 0, 0])
    assert 4.15 <= 4.0 / (1.0 - SEE_TOLERANCE)  # the third point lies inside the tolerance, by construction
    # with view 2's wall moved behind the points, all three see them: the widest pair (views 1 and 2) counts
    ref.depth[2] = 10.0
    angle, seen = parallax_angle(X[:2], ref)
    c2 = np.array([-2.0, 0, 0])
    np.testing.assert_allclose(angle, [_angle(c1, c2, X[0]), _angle(c1, c2, X[1])], rtol=1e-12)
    np.testing.assert_array_equal(seen, [3, 3])
    # a transparent pixel sees nothing
    ref.opacity[:] = 0.0
    np.testing.assert_array_equal(parallax_angle(X[:2], ref)[0], [0.0, 0.0])
    assert parallax_angle(np.zeros((0, 3)), ref)[0].shape == (0,)


def test_the_compiled_pair_search_matches_the_pair_loop():
    """The compiled widest_cosine against the numpy pair loop and a naive float64 loop over pairs:
    random visibility, points seen by none or one view (cosine 1), a point at a camera centre (a
    zero ray), views behind the point (angles past 90 degrees)."""
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(9, 3))
    points = rng.normal(size=(400, 3)) * 2.0
    points[0] = centres[4]  # a zero-length ray
    sees = rng.random((400, 9)) < 0.6
    sees[1] = False
    sees[2] = False
    sees[2, 3] = True
    got, loop = widest_cosine(points, centres, sees), widest_cosine_loop(points, centres, sees)
    naive = np.ones(len(points))
    for n in range(len(points)):
        seen = np.flatnonzero(sees[n])
        for a in range(len(seen)):
            for b in range(a + 1, len(seen)):
                u, v = (centres[seen[a]] - points[n]), (centres[seen[b]] - points[n])
                u, v = (w / max(np.linalg.norm(w), np.finfo(np.float64).tiny) for w in (u, v))
                naive[n] = min(naive[n], float(u @ v))
    np.testing.assert_allclose(got, naive, rtol=0, atol=1e-14)
    np.testing.assert_allclose(loop, naive, rtol=0, atol=1e-14)
    assert got[1] == got[2] == 1.0 and (got < 0).any()


def test_parallax_map_back_projects_each_pixel():
    ref = _three_views()
    K, w2c = ref.intrinsics[0], ref.world_to_camera[0]
    depth = np.full((40, 40), 3.0)
    mask = np.zeros((40, 40), bool)
    mask[20, 20] = mask[5, 30] = True
    got = parallax_map(depth, K, w2c, ref, mask=mask)
    for r, c in ((20, 20), (5, 30)):
        X = np.array([(c + 0.5 - 20.0) / 20.0 * 3.0, (r + 0.5 - 20.0) / 20.0 * 3.0, 3.0])
        assert got[r, c] == pytest.approx(parallax_angle(X[None], ref)[0][0], rel=1e-5)
    assert got.dtype == np.float32 and (got[~mask] == 0).all()


def test_one_pass_gives_the_violation_and_the_parallax_of_the_two_passes():
    """training_view_terms and training_view_maps (one projection into each training view for both
    terms) against free_space_violation / parallax_angle and violation_map / parallax_map: the same
    values, to the last bit; None for a term not asked for."""
    ref = _three_views()
    ref.depth[1, :, 25:] = 5.0  # part of view 1's wall farther: some points lie in front of it
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-2, 2, 500), rng.uniform(-1, 1, 500), rng.uniform(1.0, 6.0, 500)])
    violation, angle = training_view_terms(X, ref, free_space=True, parallax=True)
    np.testing.assert_array_equal(violation, free_space_violation(X, ref))
    np.testing.assert_array_equal(angle, parallax_angle(X, ref)[0])
    assert (violation > 0).any() and (angle > 0).any()
    assert training_view_terms(X, ref, free_space=False, parallax=True)[0] is None
    np.testing.assert_array_equal(training_view_terms(X, ref, free_space=True, parallax=False)[0], violation)
    assert training_view_terms(X, ref, free_space=True, parallax=False)[1] is None
    K, w2c = ref.intrinsics[2], ref.world_to_camera[2]
    depth = rng.uniform(2.0, 6.0, (40, 40))
    mask = rng.random((40, 40)) > 0.3
    e, theta = training_view_maps(depth, K, w2c, ref, free_space=True, parallax=True, mask=mask)
    np.testing.assert_array_equal(e, violation_map(depth, K, w2c, ref, mask=mask))
    np.testing.assert_array_equal(theta, parallax_map(depth, K, w2c, ref, mask=mask))
    assert e.dtype == theta.dtype == np.float32 and (e[~mask] == 0).all() and (theta[mask] > 0).any()
    assert training_view_maps(depth, K, w2c, ref, free_space=False, parallax=False) == (None, None)
    e_only, none = training_view_maps(depth, K, w2c, ref, free_space=True, parallax=False, mask=mask)
    assert none is None
    np.testing.assert_array_equal(e_only, e)


def test_terms_at_rendered_capture_points_come_from_one_pass():
    """calibration.training_view_terms_at_points: on each view's ray through its capture point, the
    point at the rendered depth (rendered_points_of) gives the violation and the parallax angle of the
    two passes (free_space_violation, parallax_angle) to the last bit; None for a term not asked for;
    depth_calibration_renders refuses two different training-view references."""
    import torch

    from stochastic_fields.calibration import depth_calibration_renders, rendered_points_of, training_view_terms_at_points
    from stochastic_fields.cameras import make_cameras
    from stochastic_fields.sparse_depth import SparseDepth

    ref = _three_views()
    ref.depth[1, :, 25:] = 5.0
    cams = make_cameras(torch.from_numpy(ref.intrinsics[:2]), torch.from_numpy(ref.world_to_camera[:2]), 40, 40)
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(-1, 1, 60), rng.uniform(-1, 1, 60), rng.uniform(2.5, 5.5, 60)])
    sparse = {v: SparseDepth(v, np.zeros(30, np.int64), np.zeros(30, np.int64), np.zeros((30, 2)),
                             xyz[30 * v:30 * v + 30, 2] - (v == 1), np.arange(30 * v, 30 * v + 30), "tracks", 30)
              for v in (0, 1)}
    gt = np.concatenate([sparse[v].depth for v in (0, 1)])
    depth = gt * rng.uniform(0.7, 1.3, len(gt))
    X = rendered_points_of(cams, sparse, xyz, gt, depth)
    violation, angle = training_view_terms_at_points(cams, sparse, xyz, gt, depth, ref, free_space=True, parallax=True)
    np.testing.assert_array_equal(violation, free_space_violation(X, ref))
    np.testing.assert_array_equal(angle, parallax_angle(X, ref)[0])
    assert (violation > 0).any() and (angle > 0).any()
    only = training_view_terms_at_points(cams, sparse, xyz, gt, depth, ref, free_space=False, parallax=True)
    assert only[0] is None
    np.testing.assert_array_equal(only[1], angle)
    assert training_view_terms_at_points(cams, sparse, xyz, gt, depth, ref, free_space=False,
                                         parallax=False) == (None, None)
    with pytest.raises(ValueError, match="same free_space.TrainingDepth"):
        depth_calibration_renders(None, None, free_space=ref, parallax=_three_views())


def test_parallax_term_by_hand():
    np.testing.assert_allclose(parallax_term(np.array([90.0, 30.0, 0.0]), np.array([2.0, 2.0, 3.0])),
                               [2.0, 4.0, 3.0 / PARALLAX_MIN_SIN], rtol=1e-12)


def _map(parallax_weight=0.002, relative_floor=0.1) -> QuantileCalibration:
    return QuantileCalibration("depth_std", np.array([0.5, 0.6827, 0.95]), np.array([1.1, 1.3, 1.9]), 100, "test",
                               relative_floor=relative_floor, parallax_weight=parallax_weight)


def test_calibrated_std_adds_the_parallax_term_by_hand():
    m = _map()
    raw, depth, angle = np.array([0.3, 1.0]), np.array([2.0, 4.0]), np.array([30.0, 0.0])
    term = np.array([2.0 / 0.5, 4.0 / PARALLAX_MIN_SIN])
    expected = m.std_scale * np.sqrt(raw ** 2 + (0.002 * term) ** 2 + (0.1 * depth) ** 2)
    np.testing.assert_allclose(m.calibrated_std(raw, depth=depth, parallax=angle), expected, rtol=1e-12)
    with pytest.raises(ValueError, match="parallax"):
        m.calibrated_std(raw, depth=depth)
    np.testing.assert_allclose(_map(0.0).calibrated_std(raw, depth=depth), m.std_scale * np.hypot(raw, 0.1 * depth))
    assert m.needs_training_depth and not _map(0.0).needs_training_depth


def test_parallax_weight_round_trips_and_old_files_have_none():
    data = _map().to_dict()
    assert QuantileCalibration.from_dict(data).parallax_weight == 0.002
    del data["parallax_weight"]
    assert QuantileCalibration.from_dict(data).parallax_weight == 0.0
    data["parallax_weight"] = float("nan")
    with pytest.raises(ValueError, match="RUN/calibration.json.*parallax"):
        QuantileCalibration.from_dict(data, where="RUN/calibration.json")


def _parallax_data(kappa: float, n: int = 4000, seed: int = 0):
    rng = np.random.default_rng(seed)
    std = rng.uniform(0.02, 0.2, n)
    depth = rng.uniform(1.0, 5.0, n)
    angle = rng.uniform(0.5, 40.0, n)
    abs_err = np.abs(rng.normal(size=n)) * np.hypot(std, kappa * parallax_term(angle, depth))
    return abs_err, std, angle, depth


def test_fitted_parallax_weight_recovers_the_weight_errors_were_drawn_with():
    abs_err, std, angle, depth = _parallax_data(0.003)
    got = fit_parallax_weight(abs_err, std, angle, depth)
    i = int(np.argmin(np.abs(PARALLAX_WEIGHT_GRID - 0.003)))
    assert PARALLAX_WEIGHT_GRID[i - 1] <= got <= PARALLAX_WEIGHT_GRID[i + 1]
    abs_err, std, angle, depth = _parallax_data(0.0, seed=1)  # errors the std alone explains: a negligible term
    assert fit_parallax_weight(abs_err, std, angle, depth) * np.median(parallax_term(angle, depth)) < 0.1 * np.median(std)
    with pytest.raises(ValueError, match="parallax angle"):
        fit_parallax_weight(abs_err, std, angle[:-1], depth)


def test_depth_map_fit_with_parallax_stores_the_weight_and_folds_apply_it():
    abs_err, std, angle, depth = _parallax_data(0.002, seed=2)
    renders = {"abs_err": abs_err, "std": std, "depth": depth, "parallax": angle, "source": "test"}
    fitted, used = _fit_depth_map(renders, floor=False, relative_floor=True)
    assert fitted.parallax_weight > 0.0005 and "parallax term weight" in fitted.source
    np.testing.assert_allclose(used, np.hypot(std, fitted.parallax_weight * parallax_term(angle, depth)))
    given, _ = _fit_depth_map(renders, floor=False, relative_floor=True, parallax_weight=0.0)
    assert given.parallax_weight == 0.0 and "weight 0" in given.source
    with pytest.raises(ValueError, match="parallax"):
        _fit_depth_map(renders, floor=False, relative_floor=True, parallax_weight=-1.0)
    folds = DepthFolds([np.array([0])], [fitted])
    rng = np.random.default_rng(3)
    gt = depth + rng.normal(size=depth.size) * used
    fold = np.zeros(depth.size, dtype=np.int64)
    scores = cross_fitted_depth_scores(gt, depth, std, fold, folds, parallax=angle)
    s = fitted.calibrated_std(std, depth=depth, parallax=angle)
    assert scores["coverage_68"] == pytest.approx(np.mean(np.abs(gt - depth) <= s))
    q = cross_fitted_depth_quantiles(depth, std, fold, folds, parallax=angle)(
        np.array([0.5 - ONE_SIGMA_LEVEL / 2, 0.5 + ONE_SIGMA_LEVEL / 2]))
    np.testing.assert_allclose(q[:, 1] - depth, s, rtol=1e-6)
    with pytest.raises(ValueError, match="parallax"):
        cross_fitted_depth_scores(gt, depth, std, fold, folds)


def test_apply_calibration_writes_the_parallax_map_and_uses_it():
    ref = _three_views()
    depth = np.full((40, 40), 3.0, dtype=np.float32)
    raw = np.full((40, 40), 0.1, dtype=np.float32)
    opacity = np.ones((40, 40), np.float32)
    opacity[:, :3] = 0.0  # empty pixels get no angle
    products = {"depth_mean": depth, "depth_std": raw, "opacity": opacity}
    cal = RunCalibration(depth=_map(0.002, 0.0), training_depth=ref)
    camera = (ref.intrinsics[0], ref.world_to_camera[0])
    out = apply_calibration(products, cal, camera=camera)
    np.testing.assert_array_equal(out["depth_parallax"], parallax_map(depth, *camera, ref, mask=opacity > 0.5))
    assert (out["depth_parallax"][:, :3] == 0).all() and out["depth_parallax"][20, 20] > 0
    term = parallax_term(out["depth_parallax"], depth)
    np.testing.assert_allclose(out["depth_std"], _map().std_scale * np.hypot(0.1, 0.002 * term), rtol=1e-6)
    with pytest.raises(ValueError, match="camera"):
        apply_calibration(products, cal)
    assert "depth_parallax" not in apply_calibration(products, RunCalibration(depth=_map(0.0, 0.0)))
    # with the free-space check too (the default), both maps come from one pass and equal each map alone
    both = _map(0.002, 0.0)
    both.free_space, both.free_space_weight = True, 0.5
    products["depth_mean"] = np.where(np.arange(40)[None, :] < 20, 3.0, 4.5).astype(np.float32) * np.ones((40, 1))
    out = apply_calibration(products, RunCalibration(depth=both, training_depth=ref), camera=camera)
    mask = opacity > 0.5
    np.testing.assert_array_equal(out["depth_parallax"], parallax_map(products["depth_mean"], *camera, ref, mask=mask))
    np.testing.assert_array_equal(out["depth_free_space"], violation_map(products["depth_mean"], *camera, ref, mask=mask))
    assert (out["depth_free_space"] > 0).any()


def test_calibrate_command_takes_the_parallax_term(capsys):
    from stochastic_fields.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["calibrate", "--run", "r"])
    assert args.parallax_term is True and args.parallax_weight is None  # the default since study 42
    assert parser.parse_args(["calibrate", "--run", "r", "--no-parallax-term"]).parallax_term is False
    args = parser.parse_args(["calibrate", "--run", "r", "--parallax-term", "--parallax-weight", "0.001"])
    assert args.parallax_term is True and args.parallax_weight == 0.001
    with pytest.raises(SystemExit):
        parser.parse_args(["calibrate", "--run", "r", "--parallax-weight", "-1"])
    assert "--parallax-weight: expected" in capsys.readouterr().err


@pytest.mark.slow
def test_a_run_calibrated_with_the_parallax_term_applies_it_in_eval_and_export(tmp_path):
    """calibrate_run(parallax=True) renders the training views, stores them with a map (and fold
    maps) holding the weight; eval writes each view's parallax map and a depth std of
    s sqrt(raw^2 + (kappa d / sin theta)^2 + (rho d)^2); the depth products apply the same."""
    import torch

    from stochastic_fields.calibration import calibrate_run, load_run_calibration
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.free_space import TRAINING_DEPTH_FILE
    from stochastic_fields.products.depth_maps import compute_depth_products
    from stochastic_fields.view_maps import view_camera_arrays

    from conftest import train_tiny_synthetic_run

    model, ds = train_tiny_synthetic_run(tmp_path)
    cal = calibrate_run(tmp_path, model=model, dataset=ds, free_space=False, parallax=True, parallax_weight=0.002,
                        progress=False)
    assert cal.depth.parallax_weight == 0.002 and not cal.depth.free_space
    assert cal.depth_folds is None or all(m.parallax_weight == 0.002 for m in cal.depth_folds.maps)
    assert (tmp_path / TRAINING_DEPTH_FILE).is_file()
    stored = load_run_calibration(tmp_path)
    assert stored.depth.parallax_weight == 0.002 and stored.training_depth is not None
    v = int(ds.test_indices[0])
    evaluate(model, ds, tmp_path / "eval", views=[v], progress=False, calibration=stored)
    cam = view_camera_arrays(ds, v)
    with np.load(tmp_path / "eval" / "views" / f"view_{v:03d}.npz") as f:
        angle, std, raw, depth, opacity = f["depth_parallax"], f["depth_std"], f["depth_std_raw"], f["depth_mean"], f["opacity"]
    np.testing.assert_allclose(angle, parallax_map(depth, cam["intrinsics"], cam["world_to_camera"],
                                                   stored.training_depth, mask=opacity > 0.5), atol=1e-3)
    rho = cal.depth.relative_floor
    np.testing.assert_allclose(std, cal.depth.std_scale * np.sqrt(
        raw.astype(np.float64) ** 2 + (0.002 * parallax_term(angle, depth)) ** 2
        + (rho * depth.astype(np.float64)) ** 2), rtol=1e-5)
    assert (tmp_path / "eval" / "views" / f"view_{v:03d}_depth_parallax.png").is_file()
    with torch.no_grad():
        maps = model.render_view(ds.rays(v), model.render_options(keep_draws=True))
    products = compute_depth_products(maps, cam["intrinsics"], cam["world_to_camera"], near=cam["near"],
                                      far=cam["far"], calibration=stored)
    theta = parallax_map(products.depth_mean, cam["intrinsics"], cam["world_to_camera"], stored.training_depth,
                         mask=products.opacity > 0.5)
    np.testing.assert_allclose(products.depth_std, cal.depth.std_scale * np.sqrt(
        products.depth_std_raw.astype(np.float64) ** 2 + (0.002 * parallax_term(theta, products.depth_mean)) ** 2
        + (rho * products.depth_mean.astype(np.float64)) ** 2), rtol=1e-5)


def test_parallax_study_rule_by_hand(load_script):
    """Study 42's verdict on hand-made group means: each condition fails alone where it should."""
    study = load_script("benchmarks/studies/parallax_term_study.py")

    def arm(is95=1.0, crps=0.08, rho=0.6, band=0.20, cov=(0.5, 0.683, 0.9, 0.95)):
        return {"interval_score_95": is95, "crps": crps, "spearman": rho, "halfwidth_median_95": band,
                **{f"coverage_{n}": c for n, c in zip(study.LEVELS, cov)}}

    today = arm()
    good = {"paper fern": {"today": today, "parallax term": arm(is95=0.9, band=0.215)},
            "capture fern": {"today": today, "parallax term": arm(is95=0.9, band=0.19)}}
    assert study.verdict(good) == (True, [])
    for group, change, words in (("paper fern", {"is95": 1.0}, "IS95"),
                                 ("paper fern", {"is95": 0.9, "crps": 0.0809}, "CRPS"),
                                 ("paper fern", {"is95": 0.9, "rho": 0.594}, "Spearman"),
                                 ("paper fern", {"is95": 0.9, "cov": (0.5, 0.683, 0.849, 0.95)}, "90%"),
                                 ("paper fern", {"is95": 0.9, "band": 0.221}, "band"),
                                 ("capture fern", {"is95": 0.9, "band": 0.201}, "band")):
        means = {g: dict(a) for g, a in good.items()}
        means[group] = {"today": today, "parallax term": arm(**change)}
        taken, failed = study.verdict(means)
        assert not taken and len(failed) == 1 and group in failed[0] and words in failed[0], failed
    # group means average each group's runs
    res = {"fern:15": {"protocol": "paper", "today": {"x": 1.0}, "parallax term": {"x": 3.0}},
           "fern:16": {"protocol": "paper", "today": {"x": 2.0}, "parallax term": {"x": 5.0}},
           "fern:25": {"protocol": "capture", "today": {"x": 7.0}, "parallax term": {"x": 8.0}}}
    assert study.group_means(res) == {"capture fern": {"today": {"x": 7.0}, "parallax term": {"x": 8.0}},
                                      "paper fern": {"today": {"x": 1.5}, "parallax term": {"x": 4.0}}}


def test_parallax_speed_benchmark_writes_its_table(load_script, tmp_path):
    """The cost benchmark on a few points: both searches timed where the loop runs, the angles equal."""
    bench = load_script("benchmarks/parallax_speed.py")
    assert bench.main(["--views", "3", "12", "--points", "500", "--loop-max-views", "3", "--out", str(tmp_path)]) == 0
    import json
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert [r["views"] for r in rows] == [3, 12]
    assert rows[0]["max_diff_deg"] < 1e-10 and rows[1]["loop_s"] is None
    assert 0 < rows[1]["mean_views_seeing"] <= 12
    assert all(r["one_pass_equal"] and r["one_pass_s"] > 0 and r["two_pass_s"] > 0 for r in rows)
    assert "| 12 |" in (tmp_path / "README.md").read_text()


def test_edge_beside_parallax_study_rule_by_hand(load_script):
    """Study 44's verdict on hand-made group means: each condition fails alone where it should, a level
    today's map already misses may stay out if it comes no farther, and the study shares study 42's
    protocol (one implementation of the two arms)."""
    study = load_script("benchmarks/studies/edge_term_parallax_study.py")
    parallax = load_script("benchmarks/studies/parallax_term_study.py")
    assert study.group_means is parallax.group_means

    def arm(is95=1.0, crps=0.08, rho=0.6, band=0.16, cov=(0.5, 0.683, 0.9, 0.95)):
        return {"interval_score_95": is95, "crps": crps, "spearman": rho, "halfwidth_median_95": band,
                **{f"coverage_{n}": c for n, c in zip(("50", "68", "90", "95"), cov)}}

    today = arm()
    good = {"paper flower": {"today": today, "edge term": arm(rho=0.611, band=0.1649)},
            "paper fern": {"today": today, "edge term": arm(rho=0.596, band=0.164, crps=0.0808)},
            "capture fern": {"today": today, "edge term": arm(band=0.16)}}
    assert study.verdict(good) == (True, [])
    for group, change, words in (("paper flower", {"rho": 0.609}, "rise by 0.01"),
                                 ("paper fern", {"rho": 0.594}, "at most -0.005"),
                                 ("paper fern", {"is95": 1.001}, "IS95"),
                                 ("paper fern", {"crps": 0.0809}, "CRPS"),
                                 ("paper fern", {"cov": (0.5, 0.683, 0.849, 0.95)}, "90%"),
                                 ("paper fern", {"band": 0.1651}, "band"),
                                 ("capture fern", {"band": 0.1601}, "band")):
        means = {g: dict(a) for g, a in good.items()}
        means[group] = {"today": today, "edge term": arm(**{"rho": 0.611 if group == "paper flower" else 0.6,
                                                             **change})}
        taken, failed = study.verdict(means)
        assert not taken and len(failed) == 1 and group in failed[0] and words in failed[0], failed
    # fern's 90% level 5.7 points under today may stay out where the term brings it no farther
    short = arm(cov=(0.5, 0.683, 0.843, 0.95))
    means = {**good, "paper fern": {"today": short, "edge term": arm(cov=(0.5, 0.683, 0.845, 0.95))}}
    assert study.verdict(means) == (True, [])
    means["paper fern"]["edge term"] = arm(cov=(0.5, 0.683, 0.842, 0.95))
    assert not study.verdict(means)[0]
    assert study.verdict({"paper fern": good["paper fern"]}) == (False, ["paper flower: no runs"])
