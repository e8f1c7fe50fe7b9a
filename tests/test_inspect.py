"""RunInspector (the notebook's logic) on a tiny trained run: renders, the pixel probe, the point
cloud, metrics and figures, checked against independent references (scipy's normal, numpy
re-derivations of ray geometry and expected depth, kornia projection, hand-counted coverage)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from scipy import stats

from stochastic_fields.cameras import generate_rays_for_view, intrinsics_3x3, project_points, select_cameras
from stochastic_fields.config import preset
from stochastic_fields.view_maps import OPACITY_MASK
from stochastic_fields.inspect import (MAP_SPECS, RunInspector, format_scores, plotly_cloud_figure,
                                       static_cloud_figure)
from stochastic_fields.samplers import sample_along_rays
from stochastic_fields.scenes import load_run_dataset
from stochastic_fields.trainer import Trainer

#: Rays per render chunk in the test run: the 64x48 views (3072 rays) then have three full chunks
#: and a partial one, so the probe's chunk arithmetic is exercised across boundaries.
CHUNK = 1000


def _train_tiny(run_dir, scene, method: str = "snerf", iterations: int = 10):
    """A few seconds of training: a 10x learning rate and no TV term carve a surface quickly
    (about half the pixels of a test view end up with opacity > 0.5)."""
    cfg = preset("tiny")
    cfg.method = method
    cfg.data.path = str(scene)
    cfg.train.iterations = iterations
    cfg.train.rays_per_batch = 128
    cfg.train.lr = 5e-2
    cfg.train.tv_weight = 0.0
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    cfg.render.chunk_rays = CHUNK
    Trainer(cfg, run_dir, load_run_dataset(cfg, run_dir)).train(progress=False)
    return run_dir


@pytest.fixture(scope="module")
def inspector(tmp_path_factory, tiny_scene) -> RunInspector:
    run = _train_tiny(tmp_path_factory.mktemp("inspect_run"), tiny_scene)
    return RunInspector(run)


@pytest.fixture(scope="module")
def view(inspector) -> int:
    return inspector.dataset.test_indices[0]


# --------------------------------------------------------------------------- basics
def test_views_cover_the_split_test_first(inspector):
    views = inspector.views()
    ds = inspector.dataset
    assert [v.index for v in views] == list(ds.test_indices) + list(ds.train_indices)
    assert {v.split for v in views[: len(ds.test_indices)]} == {"test"}
    first = views[0]
    assert first.name == ds.image_paths[first.index].name
    assert first.label == f"test {first.index:03d} ({first.name})"
    assert "64x48" in inspector.summary()


def test_render_shapes_and_internal_consistency(inspector, view):
    K = inspector.default_num_draws
    p = inspector.render(view, K, "alpha")
    H, W = 48, 64
    for name in ("depth_mean", "depth_std", "depth_std_epistemic", "depth_std_spread", "opacity",
                 "colour_abs_error", "depth_abs_error"):
        assert p[name].shape == (H, W), name
    assert p["colour_mean"].shape == p["colour_std"].shape == (H, W, 3)
    assert p["depth_draws"].shape == (H, W, K)
    draws = p["depth_draws"].astype(np.float64)
    # camera-z statistics over the K draws: mean and population std
    np.testing.assert_allclose(p["depth_mean"], draws.mean(-1), rtol=1e-5)
    np.testing.assert_allclose(p["depth_std_epistemic"], draws.std(-1), rtol=1e-3, atol=1e-5)
    total = np.sqrt(p["depth_std_epistemic"].astype(np.float64) ** 2 + p["depth_std_spread"].astype(np.float64) ** 2)
    np.testing.assert_allclose(p["depth_std"], total, rtol=1e-4, atol=1e-6)
    # errors against ground truth, recomputed here
    gt = inspector.dataset.images[view].numpy()
    gt_depth = inspector.dataset.depths[view].numpy()
    np.testing.assert_allclose(p["colour_abs_error"], np.abs(p["colour_mean"] - gt).mean(-1), atol=1e-6)
    surface = gt_depth > 0
    assert np.isnan(p["depth_abs_error"][~surface]).all() and (~surface).any()
    np.testing.assert_allclose(p["depth_abs_error"][surface], np.abs(p["depth_mean"] - gt_depth)[surface], atol=1e-5)
    assert ((p["opacity"] >= 0) & (p["opacity"] <= 1 + 1e-6)).all()


# --------------------------------------------------------------------------- pixel probe
@pytest.mark.parametrize("quadrature", ["alpha", "trapezoid"])
@pytest.mark.parametrize("u, v", [(39, 15), (40, 15), (63, 47)])  # pixels 999 | 1000 (chunk edge), last chunk
def test_probe_draws_are_the_render_draws(inspector, view, quadrature, u, v):
    K = inspector.default_num_draws
    probe = inspector.probe_pixel(view, u, v, K, quadrature)
    maps = inspector.render(view, K, quadrature)
    np.testing.assert_array_equal(probe["depth_draws"], maps["depth_draws"][v, u])
    assert probe["depth_mean"] == pytest.approx(float(maps["depth_mean"][v, u]), rel=1e-5)
    assert probe["depth_std"] == pytest.approx(float(maps["depth_std"][v, u]), rel=1e-4, abs=1e-6)
    assert probe["opacity"] == pytest.approx(float(maps["opacity"][v, u]), rel=1e-5, abs=1e-7)
    # the returned weights are the ones behind the draws: D_k = sum w t / sum w, camera z = t z_scale
    w = probe["weights"].astype(np.float64)  # [K, S]
    acc = w.sum(-1)
    hit = acc > 1e-3
    depth_from_w = (w * probe["z"].astype(np.float64)).sum(-1) / np.where(hit, acc, 1.0)
    np.testing.assert_allclose(depth_from_w[hit], probe["depth_draws"][hit], rtol=1e-4)
    np.testing.assert_allclose(acc.mean(), probe["opacity"], rtol=1e-4, atol=1e-6)


def test_probe_ray_geometry_matches_an_independent_derivation(inspector, view):
    u, v = 11, 37
    probe = inspector.probe_pixel(view, u, v, 3)
    ds = inspector.dataset
    K = intrinsics_3x3(ds.cameras)[view].double().numpy()
    d_cam = np.array([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], 1.0])
    z_scale = 1.0 / np.linalg.norm(d_cam)
    S = inspector.model.render_settings.num_samples
    near, far = float(ds.near[view]) / z_scale, float(ds.far[view]) / z_scale  # camera-z bounds -> ray distance
    edges = near + (far - near) * np.arange(S + 1) / S
    np.testing.assert_allclose(probe["t"], 0.5 * (edges[:-1] + edges[1:]), rtol=1e-5)
    np.testing.assert_allclose(probe["z"], probe["t"] * z_scale, rtol=1e-5)
    assert probe["t"].shape == probe["density_mean"].shape == probe["density_std"].shape == (S,)
    assert probe["weights"].shape == (3, S) and probe["depth_draws"].shape == (3,)
    gt_depth = float(ds.depths[view][v, u])
    assert probe["gt_depth"] == (pytest.approx(gt_depth) if gt_depth > 0 else None)
    np.testing.assert_allclose(probe["gt_colour"], ds.images[view][v, u].numpy())


def test_probe_density_moments_match_scipy_rectified_normal(inspector, view):
    """E[relu(Y)] = m Phi(m/s) + s phi(m/s); E[relu(Y)^2] = (m^2 + s^2) Phi(m/s) + m s phi(m/s)."""
    # a pixel whose ray crosses the object, so densities are far from zero somewhere
    maps = inspector.render(view)
    v, u = np.unravel_index(np.argmax(maps["opacity"]), maps["opacity"].shape)
    probe = inspector.probe_pixel(view, int(u), int(v))
    ds = inspector.dataset
    rays = generate_rays_for_view(ds.cameras, view, ds.near, ds.far)[int(v), int(u)].reshape(1)
    samples = sample_along_rays(rays, inspector.model.render_settings.num_samples,
                                spacing=inspector.model.render_settings.spacing)
    with torch.no_grad():
        params = inspector.model.field(samples.positions, samples.directions)
    m = params.density_loc[0].double().numpy()
    s = params.density_scale[0].double().numpy()
    z = m / s
    mean = m * stats.norm.cdf(z) + s * stats.norm.pdf(z)
    second = (m * m + s * s) * stats.norm.cdf(z) + m * s * stats.norm.pdf(z)
    std = np.sqrt(np.maximum(second - mean * mean, 0.0))
    assert mean.max() > 0.1  # the check is not vacuous
    np.testing.assert_allclose(probe["density_mean"], mean, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(probe["density_std"], std, rtol=1e-3, atol=1e-5)


def test_probe_rejects_bad_pixels_and_views(inspector, view):
    with pytest.raises(IndexError, match="u=64"):
        inspector.probe_pixel(view, 64, 0)
    with pytest.raises(IndexError, match="v=-1"):
        inspector.probe_pixel(view, 0, -1)
    with pytest.raises(IndexError, match="view 99"):
        inspector.render(99)
    with pytest.raises(ValueError, match="quadrature"):
        inspector.render(view, 4, "simpson")
    with pytest.raises(ValueError, match="num_draws"):
        inspector.render(view, 0)


# --------------------------------------------------------------------------- point cloud
def test_point_cloud_reprojects_onto_its_pixels(inspector, view):
    maps = inspector.render(view)
    cloud = inspector.point_cloud([view], min_opacity=0.3)
    keep = maps["opacity"] >= 0.3
    assert len(cloud) == int(keep.sum()) > 0
    a = cloud.attributes
    np.testing.assert_array_equal(a["depth_std"], maps["depth_std"][keep])
    np.testing.assert_array_equal(a["opacity"], maps["opacity"][keep])
    np.testing.assert_array_equal(cloud.rgb, maps["colour_mean"][keep])
    cams = select_cameras(inspector.dataset.cameras, [view])
    uv, z = project_points(cams, torch.as_tensor(cloud.positions, dtype=torch.float64))
    rows, cols = np.nonzero(keep)  # row-major, as back-projected
    np.testing.assert_array_equal(a["row"], rows)
    np.testing.assert_allclose(z[0].numpy(), maps["depth_mean"][keep], rtol=1e-4)
    np.testing.assert_allclose(uv[0].numpy(), np.stack([cols + 0.5, rows + 0.5], -1), atol=1e-3)
    other = inspector.dataset.test_indices[1]
    both = inspector.point_cloud([view, other], min_opacity=0.3)
    assert len(both) > len(cloud) and set(np.unique(a_v := both.attributes["view"])) == {view, other}
    assert (a_v[: len(cloud)] == view).all()


def test_point_cloud_confidence_threshold(inspector, view):
    maps = inspector.render(view)
    valid = maps["opacity"] >= OPACITY_MASK
    depth, std = maps["depth_mean"][valid].astype(np.float64), maps["depth_std"][valid].astype(np.float64)
    confidence = np.exp(-(std / depth) / 0.05)  # the documented definition, recomputed
    full = inspector.point_cloud(view)
    np.testing.assert_allclose(full.attributes["confidence"], confidence, rtol=1e-5)
    threshold = float(np.median(confidence))
    kept = inspector.point_cloud(view, min_confidence=threshold)
    assert len(kept) == int((full.attributes["confidence"] >= threshold).sum())
    assert 0 < len(kept) < len(full) and kept.attributes["confidence"].min() >= threshold
    assert len(inspector.point_cloud(view, min_confidence=1.0)) == int((std == 0).sum())
    with pytest.raises(ValueError, match="min_confidence"):
        inspector.point_cloud(view, min_confidence=1.5)
    with pytest.raises(ValueError, match="min_opacity"):
        inspector.point_cloud(view, min_opacity=-0.1)


def test_depth_products_share_the_render(inspector, view):
    maps = inspector.render(view, None, "trapezoid")
    dp = inspector.depth_products(view, None, "trapezoid")
    np.testing.assert_array_equal(dp.depth_mean, maps["depth_mean"])
    np.testing.assert_array_equal(dp.valid, maps["opacity"] >= OPACITY_MASK)
    q = np.quantile(maps["depth_draws"].astype(np.float64), [0.05, 0.95], axis=-1)
    np.testing.assert_allclose(dp.depth_quantiles, q, rtol=1e-5)


def test_cloud_figures_apply_the_threshold(inspector, view):
    cloud = inspector.point_cloud(view)
    points, colours, std = cloud.positions, cloud.rgb, cloud.attributes["depth_std"]
    threshold = float(np.median(std))
    fig = plotly_cloud_figure(points, colours, std, threshold)
    trace = fig.data[0]
    np.testing.assert_allclose(np.sort(np.asarray(trace.x)), np.sort(points[std <= threshold][:, 0]))
    np.testing.assert_allclose(np.asarray(trace.marker.color), std[std <= threshold])
    assert trace.marker.cmax == pytest.approx(float(np.percentile(std, 99)))
    rgb = plotly_cloud_figure(points, colours, std, None, colour_by="rgb", max_points=10)
    assert len(rgb.data[0].x) == 10 and str(rgb.data[0].marker.color[0]).startswith("rgb(")
    with pytest.raises(ValueError, match="colour_by"):
        plotly_cloud_figure(points, colours, std, colour_by="depth")
    static = static_cloud_figure(points, colours, std, threshold)
    assert isinstance(static, Figure)
    kept = int((std <= threshold).sum())
    assert [len(c.get_offsets()) for ax in static.axes if ax.name == "3d" for c in ax.collections] == [kept, kept]
    empty = plotly_cloud_figure(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), 0.5)
    assert len(empty.data[0].x) == 0
    assert isinstance(static_cloud_figure(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), Figure)


# --------------------------------------------------------------------------- metrics and figures
def test_view_metrics_coverage_matches_a_hand_count(inspector, view):
    m = inspector.view_metrics(view)
    maps = inspector.render(view)
    gt = inspector.dataset.images[view].numpy().astype(np.float64)
    res = np.abs(gt - maps["colour_mean"]).ravel()
    std = maps["colour_std"].astype(np.float64).ravel()
    cal = m["colour_calibration"]
    for p in (0.5, 0.9):
        i = int(np.argmin(np.abs(cal.levels - p)))
        zp = stats.norm.ppf(0.5 + cal.levels[i] / 2)
        assert cal.coverage[i] == pytest.approx(np.mean((res == 0) | (res <= zp * std)), abs=1e-12)
    mask = m["depth_mask"]
    gt_depth = inspector.dataset.depths[view].numpy()
    np.testing.assert_array_equal(mask, (gt_depth > 0) & (maps["opacity"] > OPACITY_MASK))
    assert m["depth_calibration"].num_values == int(mask.sum())
    assert m["depth_sparsification"].num_pixels == int(mask.sum())
    assert m["scores"]["psnr"] == pytest.approx(-10 * math.log10(np.mean((gt - maps["colour_mean"]) ** 2)), rel=1e-4)
    text = format_scores(m["scores"])
    assert "psnr" in text and "depth/rmse" in text


def test_metric_figures_plot_the_metric_curves(inspector, view):
    m = inspector.view_metrics(view)
    fig = inspector.sparsification_figure(view)
    assert len(fig.axes) == 2  # colour and depth
    model_line = fig.axes[0].lines[0]
    np.testing.assert_allclose(model_line.get_ydata(), m["colour_sparsification"].model_normalised)
    np.testing.assert_allclose(fig.axes[1].lines[1].get_ydata(), m["depth_sparsification"].oracle_normalised)
    cal = inspector.calibration_figure(view)
    lines = cal.axes[0].lines  # ideal, colour, depth
    np.testing.assert_allclose(lines[1].get_ydata(), m["colour_calibration"].coverage)
    np.testing.assert_allclose(lines[2].get_ydata(), m["depth_calibration"].coverage)


def test_interval_figure_draws_the_views_intervals(inspector, view):
    m = inspector.view_metrics(view)
    iv = m["depth_intervals"]
    assert iv["num_values"] == int(m["depth_mask"].sum())
    assert m["scores"]["depth_intervals/coverage_95"] == pytest.approx(iv["coverage_95"])
    # the pooled coverage is the calibration curve's at the same levels (one distribution)
    cal = m["depth_calibration"]
    i95 = int(np.argmin(np.abs(cal.levels - 0.95)))
    assert iv["coverage_95"] == pytest.approx(cal.coverage[i95], abs=2.0 / iv["num_values"] + 0.011)
    fig = inspector.interval_figure(view)
    lines = fig.axes[0].lines  # ideal, all, narrowest third, widest third
    np.testing.assert_allclose(lines[1].get_ydata(), iv["coverage"])
    np.testing.assert_allclose(lines[2].get_ydata(), iv["width_groups"]["coverage"][0])
    np.testing.assert_allclose(lines[3].get_ydata(), iv["width_groups"]["coverage"][-1])


@pytest.mark.parametrize("name", list(MAP_SPECS))
def test_map_figures_have_colour_bars_with_units(inspector, view, name):
    if name not in inspector.map_names():  # the free-space map (its run is below), the edge and parallax maps
        spec = MAP_SPECS[name]
        flag = "--edge-term" if spec.needs_edge_term else "--parallax-term" if spec.needs_parallax_term else "--free-space"
        with pytest.raises(KeyError, match=f"calibrate --run RUN {flag}"):
            inspector.map_figure(view, name)
        return
    fig = inspector.map_figure(view, name)
    assert isinstance(fig, Figure)
    image = fig.axes[0].images[0].get_array()
    if name == "colour_mean":
        assert len(fig.axes) == 1 and image.shape == (48, 64, 3)
        assert MAP_SPECS[name].unit in fig.axes[0].get_xlabel()
        return
    assert len(fig.axes) == 2 and fig.axes[1].get_ylabel() == MAP_SPECS[name].unit
    values = inspector.render(view)[name]
    values = values.mean(-1) if values.ndim == 3 else values
    shown = np.ma.filled(image.astype(np.float64), np.nan)
    if MAP_SPECS[name].depth:  # empty rays greyed out
        assert np.isnan(shown[inspector.render(view)["opacity"] <= OPACITY_MASK]).all()
    ok = np.isfinite(shown)
    np.testing.assert_allclose(shown[ok], values[ok], rtol=1e-6)


def test_map_figure_rejects_unknown_maps(inspector, view):
    with pytest.raises(KeyError, match="unknown map 'depth_var'"):
        inspector.map_figure(view, "depth_var")


def test_probe_and_overview_figures(inspector, view):
    fig = inspector.probe_figure(view, 32, 24, 7)
    hist = fig.axes[1]
    assert sum(bar.get_height() for bar in hist.containers[0]) == 7
    probe = inspector.probe_pixel(view, 32, 24, 7)
    np.testing.assert_allclose(fig.axes[2].lines[0].get_ydata(), probe["density_mean"])
    over = inspector.overview_figure(view)
    assert len([ax for ax in over.axes if ax.images]) == 1 + len(inspector.map_names())


# --------------------------------------------------------------------------- other methods
def test_baseline_runs_render_but_cannot_be_probed(tmp_path, tiny_scene):
    run = _train_tiny(tmp_path / "det", tiny_scene, method="deterministic", iterations=3)
    ins = RunInspector(run)
    assert not ins.is_stochastic_field
    view = ins.dataset.test_indices[0]
    p = ins.render(view)
    assert p["depth_mean"].shape == (48, 64)
    np.testing.assert_allclose(p["depth_std_epistemic"], 0.0, atol=1e-6)  # one deterministic trajectory
    with pytest.raises(NotImplementedError, match="deterministic"):
        ins.probe_pixel(view, 0, 0)


def test_missing_run_folder_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        RunInspector(tmp_path / "nowhere")


# --------------------------------------------------------------------------- cache (last: it clears it)
def test_render_cache_per_view_k_and_quadrature(inspector):
    view = inspector.dataset.test_indices[-1]  # a view no other test renders
    a = inspector.render(view, 4, "alpha")
    assert inspector.render(view, 4, "alpha") is a
    c = inspector.render(view, 4, "trapezoid")
    assert c is not a and not np.array_equal(a["colour_mean"], c["colour_mean"])  # other weights
    # defaults resolve to the run's render settings and share their cache entry
    d = inspector.render(view)
    assert d is not a and d["depth_draws"].shape[-1] == inspector.default_num_draws != 4
    assert inspector.render(view, inspector.default_num_draws, inspector.default_quadrature) is d
    assert inspector.depth_products(view) is inspector.depth_products(view, inspector.default_num_draws)
    keys = {(view, 4, "alpha"), (view, 4, "trapezoid"), (view, inspector.default_num_draws, "alpha")}
    assert keys <= set(inspector.cached_keys())
    inspector.clear_cache()
    assert inspector.cached_keys() == []
    # a fresh render of the same key reproduces the same draws (seeded per view and chunk)
    np.testing.assert_array_equal(inspector.render(view, 4, "alpha")["depth_draws"], a["depth_draws"])


def test_colour_estimator_switch_re_renders(inspector):
    """Switching between drawn and Rao-Blackwellised colours (the run's default) clears the cache and
    renders the same colour mean up to Monte-Carlo noise, with the same density draws behind the
    depths (same seeds)."""
    view = inspector.dataset.test_indices[-1]
    default = inspector.colour_estimator
    assert default == inspector.model.default_render_options().colour_estimator == "rao_blackwell"
    with pytest.raises(ValueError, match="colour_estimator"):
        inspector.colour_estimator = "exact"
    try:
        inspector.colour_estimator = "draws"
        drawn = inspector.render(view, 8, "alpha")
        inspector.colour_estimator = "rao_blackwell"
        assert inspector.cached_keys() == [] and "rao_blackwell" in inspector.summary()
        rb = inspector.render(view, 8, "alpha")
        assert rb is not drawn
        assert np.abs(rb["colour_mean"] - drawn["colour_mean"]).mean() < 0.02
        assert np.isfinite(rb["colour_std"]).all() and (rb["colour_std"] >= 0).all()
        # one draw block per chunk here: the density noise is the first normals of each chunk's seed either way
        np.testing.assert_allclose(rb["depth_draws"], drawn["depth_draws"], rtol=1e-5, atol=1e-6)
    finally:
        inspector.colour_estimator = "draws"
        inspector.colour_estimator = default
    assert inspector.cached_keys() == []


def test_inspector_applies_the_run_calibration_as_eval_does(inspector, view, tmp_path):
    """A run with calibration.json: the notebook's depth_std is the recalibrated one (raw kept),
    equal to what a fresh inspector without the file renders times s(0.683)."""
    import shutil

    from stochastic_fields.calibration import (CALIBRATION_LEVELS, QuantileCalibration, RunCalibration,
                                               save_run_calibration)

    run = tmp_path / "run"
    shutil.copytree(inspector.run_dir, run)
    scales = np.full(CALIBRATION_LEVELS.shape, 3.0)
    save_run_calibration(run, RunCalibration(depth=QuantileCalibration("depth_std", CALIBRATION_LEVELS, scales, 100)))
    calibrated = RunInspector(run).render(view)
    raw = inspector.render(view)
    np.testing.assert_allclose(calibrated["depth_std_raw"], raw["depth_std"], rtol=1e-6)
    np.testing.assert_allclose(calibrated["depth_std"], 3.0 * raw["depth_std"], rtol=1e-5)

    # with the free-space check: the violation map shown, and depth_std = s sqrt(raw^2 + e^2)
    from stochastic_fields.free_space import render_training_depth, save_training_depth, violation_map

    ref = render_training_depth(inspector.model, inspector.dataset, progress=False)
    save_training_depth(run, ref)
    save_run_calibration(run, RunCalibration(depth=QuantileCalibration("depth_std", CALIBRATION_LEVELS, scales, 100,
                                                                       free_space=True)))
    checked = RunInspector(run)
    assert "depth_free_space" in checked.map_names() and "depth_free_space" not in inspector.map_names()
    maps = checked.render(view)
    ds = inspector.dataset
    e = violation_map(raw["depth_mean"], intrinsics_3x3(ds.cameras)[view].double().numpy(),
                      ds.cameras.extrinsics[view].double().numpy(), ref, mask=raw["opacity"] > OPACITY_MASK)
    np.testing.assert_allclose(maps["depth_free_space"], e, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(maps["depth_std"], 3.0 * np.hypot(raw["depth_std"].astype(np.float64), e), rtol=1e-5)
    assert checked.map_figure(view, "depth_free_space").axes[1].get_ylabel() == MAP_SPECS["depth_free_space"].unit


def test_notebook_maps_are_the_models_own_render(inspector, view):
    """The notebook renders through ``render_view`` (empty-space skipping and all), chunk-seeded:
    the same maps as the model renders for eval with those generators."""
    from stochastic_fields.view_maps import camera_z_maps

    model = inspector.model
    assert model.occupancy is not None  # the run skips empty space, so a loop of its own would differ
    K = inspector.default_num_draws
    options = model.render_options(num_draws=K, quadrature=inspector.default_quadrature, keep_draws=True)
    maps = model.render_view(inspector._rays(view), options, generator=lambda c: inspector._generator(view, c))
    assert float(maps["field_evals_per_ray"].mean()) < model.render_settings.num_samples
    mine, theirs = inspector.render(view), camera_z_maps(maps)
    for name in ("colour_mean", "depth_mean", "depth_draws", "opacity"):
        np.testing.assert_array_equal(mine[name], theirs[name], err_msg=name)
