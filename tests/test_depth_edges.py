"""The occlusion-edge size (``depth_edges``) and the depth map's edge term (``calibration``): a float64
loop over the stencil, hand values, the points' definition against the map's, the std formula, the
fitted weight on data drawn with a known one, and a calibrated run applying it in eval and export."""

from __future__ import annotations

import numpy as np
import pytest

from stochastic_fields.calibration import (EDGE_WEIGHT_GRID, ONE_SIGMA_LEVEL, QuantileCalibration, _fit_depth_map,
                                           apply_calibration, cross_fitted_depth_quantiles, cross_fitted_depth_scores,
                                           DepthFolds, fit_edge_weight)
from stochastic_fields.depth_edges import EDGE_RADIUS_PX, edge_range_at_points, edge_range_map, neighbour_offsets


def naive_edge(depth: np.ndarray, radius: int) -> np.ndarray:
    h, w = depth.shape
    out = np.full((h, w), np.nan)
    for r in range(h):
        for c in range(w):
            vals = [depth[r + dv * radius, c + du * radius] for dv in (-1, 0, 1) for du in (-1, 0, 1)
                    if 0 <= r + dv * radius < h and 0 <= c + du * radius < w
                    and np.isfinite(depth[r + dv * radius, c + du * radius])]
            if vals:
                out[r, c] = max(vals) - min(vals)
    return out


@pytest.mark.parametrize("radius", [1, 2, 3])
def test_edge_map_matches_a_loop_over_the_stencil(radius):
    rng = np.random.default_rng(radius)
    depth = rng.uniform(1.0, 10.0, size=(9, 13))
    depth[2, 3] = np.nan
    depth[5, 0] = np.inf
    got = edge_range_map(depth, radius)
    np.testing.assert_allclose(got, naive_edge(depth, radius), rtol=0, atol=1e-12, equal_nan=True)


def test_edge_map_of_a_step_by_hand():
    """Depth 1 left of column 5, 3 from it: within 2 pixels of the step the range is 2, elsewhere 0;
    a flat map has none; a pixel with nothing finite around it is NaN."""
    depth = np.ones((6, 10))
    depth[:, 5:] = 3.0
    got = edge_range_map(depth, 2)
    expected = np.zeros((6, 10))
    expected[:, 3:7] = 2.0  # columns 3, 4 see column 5 or 6; columns 5, 6 see column 3 or 4
    np.testing.assert_array_equal(got, expected)
    assert np.all(edge_range_map(np.full((4, 4), 7.0)) == 0)
    assert np.isnan(edge_range_map(np.full((3, 3), np.nan), 1)).all()


def test_edge_map_rejects_bad_input():
    with pytest.raises(ValueError, match="depth map"):
        edge_range_map(np.ones(5))
    with pytest.raises(ValueError, match="radius"):
        edge_range_map(np.ones((4, 4)), 1.5)


def test_points_at_pixel_centres_agree_with_the_map():
    """Rays through pixel centres, neighbours read from the same image: the points' edge size is the
    map's at those pixels, borders included."""
    rng = np.random.default_rng(4)
    h, w = 12, 17
    depth = rng.uniform(2.0, 5.0, size=(h, w))
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    uv = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1)

    def lookup(moved):
        c = np.clip(np.floor(moved[:, 0]).astype(int), 0, w - 1)
        r = np.clip(np.floor(moved[:, 1]).astype(int), 0, h - 1)
        return depth[r, c]  # outside the image: a clipped value the function must leave out

    got = edge_range_at_points(lookup, uv, depth.ravel(), w, h)
    np.testing.assert_allclose(got, edge_range_map(depth, EDGE_RADIUS_PX).ravel(), rtol=0, atol=1e-12)
    assert len(neighbour_offsets()) == 8 and (0.0, 0.0) not in neighbour_offsets()


def test_points_leave_out_non_finite_neighbours_and_check_shapes():
    uv = np.array([[5.0, 5.0]])
    calls = iter([np.array([np.nan])] + [np.array([4.0])] * 7)
    got = edge_range_at_points(lambda moved: next(calls), uv, np.array([1.0]), 20, 20)
    assert got[0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="uv"):
        edge_range_at_points(lambda moved: moved[:, 0], np.zeros((2, 3)), np.ones(2), 20, 20)
    with pytest.raises(ValueError, match="render_depth"):
        edge_range_at_points(lambda moved: np.ones(3), np.ones((2, 2)), np.ones(2), 20, 20)


def _map(edge_weight=0.5, relative_floor=0.1) -> QuantileCalibration:
    levels = np.array([0.5, 0.6827, 0.95])
    return QuantileCalibration("depth_std", levels, np.array([1.1, 1.3, 1.9]), 100, "test",
                               relative_floor=relative_floor, edge_weight=edge_weight)


def test_calibrated_std_adds_the_edge_term_by_hand():
    m = _map()
    raw, depth, edge = np.array([0.3, 1.0]), np.array([2.0, 4.0]), np.array([0.8, 0.0])
    expected = m.std_scale * np.sqrt(raw ** 2 + (0.5 * edge) ** 2 + (0.1 * depth) ** 2)
    np.testing.assert_allclose(m.calibrated_std(raw, depth=depth, edge=edge), expected, rtol=1e-14)
    with pytest.raises(ValueError, match="occlusion-edge"):
        m.calibrated_std(raw, depth=depth)
    np.testing.assert_allclose(_map(0.0).calibrated_std(raw, depth=depth), m.std_scale * np.hypot(raw, 0.1 * depth))


def test_edge_weight_round_trips_and_old_files_have_none():
    data = _map().to_dict()
    assert QuantileCalibration.from_dict(data).edge_weight == 0.5
    del data["edge_weight"]
    assert QuantileCalibration.from_dict(data).edge_weight == 0.0
    data["edge_weight"] = -0.1
    with pytest.raises(ValueError, match="RUN/calibration.json.*occlusion-edge"):
        QuantileCalibration.from_dict(data, where="RUN/calibration.json")


def _edge_data(gamma: float, n: int = 4000, seed: int = 0):
    rng = np.random.default_rng(seed)
    std = rng.uniform(0.02, 0.2, n)
    depth = rng.uniform(1.0, 5.0, n)
    edge = np.where(rng.uniform(size=n) < 0.2, rng.uniform(0.5, 3.0, n), 0.0)  # a fifth of the points at edges
    abs_err = np.abs(rng.normal(size=n)) * np.hypot(std, gamma * edge)
    return abs_err, std, edge, depth


def test_fitted_edge_weight_recovers_the_weight_errors_were_drawn_with():
    abs_err, std, edge, depth = _edge_data(0.5)
    got = fit_edge_weight(abs_err, std, edge, depth)
    i = int(np.argmin(np.abs(EDGE_WEIGHT_GRID - 0.5)))
    assert EDGE_WEIGHT_GRID[i - 1] <= got <= EDGE_WEIGHT_GRID[i + 1]
    abs_err, std, edge, depth = _edge_data(0.0, seed=1)
    assert fit_edge_weight(abs_err, std, edge, depth) <= EDGE_WEIGHT_GRID[1]
    assert fit_edge_weight(abs_err, std, np.zeros_like(edge), depth) == 0.0  # ties: no term
    with pytest.raises(ValueError, match="edge size"):
        fit_edge_weight(abs_err, std, -edge - 1.0, depth)


def test_depth_map_fit_with_edges_stores_the_weight_and_folds_apply_it():
    abs_err, std, edge, depth = _edge_data(1.0, seed=2)
    renders = {"abs_err": abs_err, "std": std, "depth": depth, "edge": edge, "source": "test"}
    fitted, used = _fit_depth_map(renders, floor=False, relative_floor=True)
    assert fitted.edge_weight > 0.3 and "occlusion-edge term weight" in fitted.source
    np.testing.assert_allclose(used, np.hypot(std, fitted.edge_weight * edge))
    given, _ = _fit_depth_map(renders, floor=False, relative_floor=True, edge_weight=0.0)
    assert given.edge_weight == 0.0 and "weight 0" in given.source
    with pytest.raises(ValueError, match="occlusion-edge"):
        _fit_depth_map(renders, floor=False, relative_floor=True, edge_weight=-1.0)
    # a fold map judges with the edge term: coverage counted by hand at 68.3%
    m = fitted
    folds = DepthFolds([np.array([0])], [m])
    rng = np.random.default_rng(3)
    pred = depth
    gt = pred + rng.normal(size=depth.size) * np.hypot(std, edge)
    fold = np.zeros(depth.size, dtype=np.int64)
    scores = cross_fitted_depth_scores(gt, pred, std, fold, folds, edge=edge)
    s = m.calibrated_std(std, depth=pred, edge=edge)
    assert scores["coverage_68"] == pytest.approx(np.mean(np.abs(gt - pred) <= s))
    q = cross_fitted_depth_quantiles(pred, std, fold, folds, edge=edge)(np.array([0.5 - ONE_SIGMA_LEVEL / 2, 0.5 + ONE_SIGMA_LEVEL / 2]))
    np.testing.assert_allclose(q[:, 1] - pred, s, rtol=1e-6)
    with pytest.raises(ValueError, match="occlusion-edge"):
        cross_fitted_depth_scores(gt, pred, std, fold, folds)


def test_apply_calibration_writes_the_edge_map_and_uses_it():
    from stochastic_fields.calibration import RunCalibration

    depth = np.ones((6, 10), dtype=np.float32)
    depth[:, 5:] = 3.0
    raw = np.full((6, 10), 0.1, dtype=np.float32)
    products = {"depth_mean": depth, "depth_std": raw, "opacity": np.ones((6, 10), np.float32)}
    out = apply_calibration(products, RunCalibration(depth=_map(0.5, 0.0)))
    np.testing.assert_array_equal(out["depth_edge"], edge_range_map(depth))
    np.testing.assert_allclose(out["depth_std"], _map().std_scale * np.hypot(0.1, 0.5 * out["depth_edge"]), rtol=1e-6)
    assert out["depth_std"].dtype == np.float32
    assert "depth_edge" not in apply_calibration(products, RunCalibration(depth=_map(0.0, 0.0)))


@pytest.mark.slow
def test_a_run_calibrated_with_the_edge_term_applies_it_in_eval_and_export(tmp_path):
    """calibrate_run(edges=True) renders each calibration point's neighbours, stores a map (and fold
    maps) with the weight; eval writes each view's edge map and a depth std of
    s sqrt(raw^2 + (beta e)^2 + (gamma Delta)^2 + (rho d)^2); the depth products apply the same."""
    import torch

    from stochastic_fields.calibration import calibrate_run, load_run_calibration
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.products.depth_maps import compute_depth_products
    from stochastic_fields.view_maps import view_camera_arrays

    from conftest import train_tiny_synthetic_run

    model, ds = train_tiny_synthetic_run(tmp_path)
    cal = calibrate_run(tmp_path, model=model, dataset=ds, free_space=False, edges=True, edge_weight=0.5,
                        progress=False)
    assert cal.depth.edge_weight == 0.5
    assert cal.depth_folds is None or all(m.edge_weight == 0.5 for m in cal.depth_folds.maps)
    stored = load_run_calibration(tmp_path)
    assert stored.depth.edge_weight == 0.5
    v = int(ds.test_indices[0])
    evaluate(model, ds, tmp_path / "eval", views=[v], progress=False, calibration=stored)
    with np.load(tmp_path / "eval" / "views" / f"view_{v:03d}.npz") as f:
        edge, std, raw, depth = f["depth_edge"], f["depth_std"], f["depth_std_raw"], f["depth_mean"]
    np.testing.assert_allclose(edge, edge_range_map(depth), rtol=1e-6)
    rho = cal.depth.relative_floor
    np.testing.assert_allclose(std, cal.depth.std_scale * np.sqrt(raw.astype(np.float64) ** 2 + (0.5 * edge) ** 2
                                                                  + (rho * depth.astype(np.float64)) ** 2), rtol=1e-5)
    assert (tmp_path / "eval" / "views" / f"view_{v:03d}_depth_edge.png").is_file()
    cam = view_camera_arrays(ds, v)
    with torch.no_grad():
        maps = model.render_view(ds.rays(v), model.render_options(keep_draws=True))
    products = compute_depth_products(maps, cam["intrinsics"], cam["world_to_camera"], near=cam["near"],
                                      far=cam["far"], calibration=stored)
    delta = edge_range_map(products.depth_mean)
    np.testing.assert_allclose(products.depth_std, cal.depth.std_scale * np.sqrt(
        products.depth_std_raw.astype(np.float64) ** 2 + (0.5 * delta) ** 2
        + (rho * products.depth_mean.astype(np.float64)) ** 2), rtol=1e-5)
