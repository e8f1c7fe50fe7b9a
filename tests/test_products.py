"""Depth-uncertainty products: estimators, geometry, file formats, fusion (no trained model).

References are independent: numpy's quantile and a per-pixel loop for the draw statistics,
kornia/cameras.project_points for the round trip, analytic planes for normals, hand-computed
inverse-variance means for fusion, Open3D and trimesh for reading PLY files, and the synthetic
scene's exact mesh (Open3D distance queries) for geometry.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from stochastic_fields.cameras import generate_rays_for_view, make_cameras, project_points
from stochastic_fields.products.depth_maps import (
    DepthProducts, draw_quantiles, encode_png16, png16_scale, quantile_name, read_png16, read_tiff, write_npz,
    write_png16, write_tiff)
from stochastic_fields.products.export import surface_distances
from stochastic_fields.products.free_space import (central_level, free_space_volume, pixel_free_space,
                                                   predictive_free_space_volume, predictive_prob_depth_greater,
                                                   prob_depth_greater)
from stochastic_fields.products.fusion import default_voxel_size, fuse_clouds
from stochastic_fields.products.pointcloud import (
    COVARIANCE_NAMES, CloudArrays, PointFilter, cloud_from_products, filter_cloud, point_colours, read_ply, to_open3d,
    write_ply)


# ----------------------------------------------------------------------------- helpers
def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A random rigid world-to-camera [4, 4] (rotation from a QR decomposition)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = rng.normal(size=3)
    return T


def make_products(depth: np.ndarray, std: np.ndarray, K: np.ndarray, w2c: np.ndarray, *, opacity=None,
                  draws: np.ndarray | None = None, far: float = 10.0, levels=(0.05, 0.95)) -> DepthProducts:
    """DepthProducts straight from arrays (no renderer)."""
    H, W = depth.shape
    opacity = np.ones((H, W), np.float32) if opacity is None else opacity.astype(np.float32)
    q = np.zeros((len(levels), H, W), np.float32)
    if draws is not None:
        q = np.quantile(draws, levels, axis=-1).astype(np.float32)
    return DepthProducts(
        depth_mean=depth.astype(np.float32), depth_std=std.astype(np.float32),
        depth_std_epistemic=std.astype(np.float32), depth_std_spread=np.zeros((H, W), np.float32),
        opacity=opacity, depth_quantiles=q, quantile_levels=np.asarray(levels, np.float64),
        colour_mean=np.full((H, W, 3), 0.25, np.float32), valid=opacity >= 0.5,
        intrinsics=np.asarray(K, np.float64), world_to_camera=np.asarray(w2c, np.float64),
        num_draws=16 if draws is None else draws.shape[-1], near=0.1, far=far,
        depth_draws=None if draws is None else draws.astype(np.float32))


def intrinsics(W: int, H: int, f: float = 50.0) -> np.ndarray:
    return np.array([[f, 0.0, W / 2 + 0.3], [0.0, 1.1 * f, H / 2 - 0.2], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- estimators
@pytest.mark.parametrize("K", [1, 2, 7, 16])
def test_draw_quantiles_match_numpy(K):
    rng = np.random.default_rng(K)
    draws = rng.normal(size=(5, 6, K))
    draws[0, 0] = 2.0  # all tied
    levels = (0.95, 0.05, 0.5, 0.158655254, 0.975)  # the given order is kept
    got = draw_quantiles(torch.from_numpy(draws), levels).numpy()
    ref = np.quantile(draws, levels, axis=-1, method="linear")
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_draw_quantiles_hand_value_and_bad_levels():
    assert float(draw_quantiles(torch.tensor([4.0, 1.0, 3.0, 2.0]), [0.25])[0]) == pytest.approx(1.75)
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        draw_quantiles(torch.zeros(3, 4), [0.5, 1.0])
    assert quantile_name(0.05) == "depth_draw_q5" and quantile_name(0.025) == "depth_draw_q2p5"


def test_prob_depth_greater_matches_loop():
    rng = np.random.default_rng(1)
    draws = rng.uniform(1.0, 3.0, size=(4, 5, 9))
    draws[1, 1, :] = 2.0
    d = rng.uniform(1.0, 3.0, size=(4, 5))
    d[1, 1] = 2.0  # ties do not count as beyond d (strict inequality)
    ref = np.zeros((4, 5))
    for i in range(4):
        for j in range(5):
            ref[i, j] = sum(1 for x in draws[i, j] if x > d[i, j]) / 9.0
    np.testing.assert_allclose(prob_depth_greater(draws, d).numpy(), ref, atol=1e-15)
    assert ref[1, 1] == 0.0
    assert float(prob_depth_greater(torch.tensor([1.0, 2.0, 3.0, 4.0]), 2.5)) == 0.5
    # pixel query (several distances) and the threshold volume agree with the loop
    got = pixel_free_space(draws, 2, 3, [1.5, 2.5]).numpy()
    np.testing.assert_allclose(got, [np.mean(draws[2, 3] > 1.5), np.mean(draws[2, 3] > 2.5)])
    vol = free_space_volume(draws, [1.5, 2.0, 2.5]).numpy()
    assert vol.shape == (3, 4, 5)
    np.testing.assert_allclose(vol[2], np.mean(draws > 2.5, axis=-1))
    assert np.all(np.diff(vol, axis=0) <= 0)  # non-increasing in d
    with pytest.raises(IndexError, match="outside"):
        pixel_free_space(draws, 4, 0, 1.0)


def test_predictive_prob_depth_greater_is_the_bands_and_the_scores_distribution():
    """P(depth > d) of a Gaussian against scipy; with a fitted level map, one minus the (1 + p) / 2
    quantile at every exported band edge and quantile, monotone in d, and the share of true depths
    with P(depth > y) inside [(1 - p) / 2, (1 + p) / 2] equal to the band's scored coverage."""
    from scipy.stats import norm

    from stochastic_fields import metrics as M
    from stochastic_fields.calibration import QuantileCalibration

    rng = np.random.default_rng(7)
    mean, std = rng.uniform(1.0, 5.0, (6, 7)), rng.uniform(1e-3, 0.5, (6, 7))
    d = rng.uniform(0.0, 6.0, (6, 7))
    np.testing.assert_allclose(predictive_prob_depth_greater(mean, std, d), norm.sf(d, mean, std), atol=1e-12)
    assert predictive_prob_depth_greater(2.0, 0.1, 2.0 + 0.1 * 1.6448536269514722) == pytest.approx(0.05, abs=1e-12)
    # zero std: all mass at the mean; far tails
    np.testing.assert_array_equal(predictive_prob_depth_greater([2.0, 2.0, 2.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
                                  [1.0, 0.5, 0.0])
    assert predictive_prob_depth_greater(0.0, 1.0, 40.0) == 0.0 and predictive_prob_depth_greater(0.0, 1.0, -40.0) == 1.0
    # a heavy-tailed level map fitted on Student-t errors
    errs = np.abs(rng.standard_t(2, 20000))
    cal = QuantileCalibration.fit(errs, quantity="depth_std")
    m = cal.relative_scale
    for level in (0.5, ONE_SIGMA, 0.9, 0.95, 0.99):
        half = norm.ppf((1 + level) / 2) * float(m(level)) * std
        assert predictive_prob_depth_greater(mean, std, mean + half, m) == pytest.approx(np.full_like(mean, (1 - level) / 2), abs=2e-4)
        assert predictive_prob_depth_greater(mean, std, mean - half, m) == pytest.approx(np.full_like(mean, (1 + level) / 2), abs=2e-4)
    vol = predictive_free_space_volume(mean, std, np.linspace(0, 6, 50), m)
    assert vol.shape == (50, 6, 7) and np.all(np.diff(vol, axis=0) <= 1e-15)
    assert central_level(np.array([0.0]), m)[0] == 0.0
    # the scored coverage counts the same intervals
    n = 4000
    mu, sd = rng.uniform(1.0, 5.0, n), rng.uniform(0.01, 0.3, n)
    y = mu + sd * rng.standard_t(2, n)
    prob = predictive_prob_depth_greater(mu, sd, y, m)
    for level in (0.5, 0.9, 0.95):
        inside = ((prob >= (1 - level) / 2 - 1e-9) & (prob <= (1 + level) / 2 + 1e-9)).mean()
        scored = M.calibration_curve(y, mu, sd, levels=[level], interval_scale=m).coverage[0]
        assert inside == pytest.approx(scored, abs=2.0 / n)
    with pytest.raises(ValueError, match="stds must be finite and >= 0"):
        predictive_prob_depth_greater(1.0, -1.0, 1.0)


ONE_SIGMA = 0.682689492137086


# ----------------------------------------------------------------------------- geometry
def test_round_trip_depth_cloud_projection():
    rng = np.random.default_rng(2)
    H, W = 12, 17
    K, w2c = intrinsics(W, H), random_pose(rng)
    depth = rng.uniform(1.0, 5.0, size=(H, W))
    opacity = np.where(rng.uniform(size=(H, W)) < 0.8, 1.0, 0.0)
    products = make_products(depth, 0.01 * depth, K, w2c, opacity=opacity)
    cloud = cloud_from_products(products, view=3)
    assert len(cloud) == int((opacity >= 0.5).sum())
    cams = make_cameras(torch.from_numpy(K)[None], torch.from_numpy(w2c)[None], H, W)
    uv, z = project_points(cams, torch.from_numpy(cloud.positions))
    uv, z = uv[0].numpy(), z[0].numpy()
    rows, cols = cloud.attributes["row"], cloud.attributes["col"]
    np.testing.assert_array_equal(np.floor(uv[:, 0]).astype(int), cols)
    np.testing.assert_array_equal(np.floor(uv[:, 1]).astype(int), rows)
    np.testing.assert_allclose(uv, np.stack([cols + 0.5, rows + 0.5], 1), atol=1e-6)
    np.testing.assert_allclose(z, depth.astype(np.float32)[rows, cols], rtol=1e-9)
    assert np.all(cloud.attributes["view"] == 3)


def test_normals_of_two_planes_with_a_depth_edge():
    H = W = 24
    K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    w2c = np.eye(4)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    planes = [(np.array([0.3, -0.2, -1.0]), -2.0), (np.array([-0.5, 0.1, -1.0]), -6.0)]  # n . x = c
    left = u < W / 2
    depth = np.zeros((H, W))
    normal_ref = np.zeros((H, W, 3))
    for mask, (n, c) in ((left, planes[0]), (~left, planes[1])):
        depth[mask] = c / (d_cam[mask] @ n)
        n_unit = n / np.linalg.norm(n)
        x = d_cam[mask] * depth[mask][:, None]
        # towards the camera at the origin: n . (0 - x) > 0
        normal_ref[mask] = np.where(((-x) @ n_unit)[:, None] > 0, n_unit, -n_unit)
    opacity = np.ones((H, W))
    opacity[3, 3] = 0.0  # a hole: its neighbours still get normals from their other side
    products = make_products(depth, 0.01 * depth, K, w2c, opacity=opacity, far=20.0)
    cloud = cloud_from_products(products)
    rows, cols = cloud.attributes["row"], cloud.attributes["col"]
    # every pixel, including both sides of the depth edge, gets its own plane's normal
    np.testing.assert_allclose(cloud.normals, normal_ref[rows, cols], atol=1e-5)
    # an isolated valid pixel has no neighbour: its normal points at the camera
    iso = np.zeros((H, W))
    iso[5, 7] = 1.0
    lone = cloud_from_products(make_products(depth, 0.01 * depth, K, w2c, opacity=iso, far=20.0))
    to_cam = -lone.positions[0] / np.linalg.norm(lone.positions[0])
    np.testing.assert_allclose(lone.normals[0], to_cam, atol=1e-6)


def test_covariance_has_ray_and_pixel_footprint_variances():
    rng = np.random.default_rng(3)
    H, W = 6, 8
    K, w2c = intrinsics(W, H, 40.0), random_pose(rng)
    depth = rng.uniform(2.0, 4.0, size=(H, W))
    std = rng.uniform(0.01, 0.2, size=(H, W))
    cloud = cloud_from_products(make_products(depth, std, K, w2c), covariance=True)
    cov = np.stack([cloud.attributes[n] for n in COVARIANCE_NAMES], 1).astype(np.float64).reshape(-1, 3, 3)
    cams = make_cameras(torch.from_numpy(K)[None], torch.from_numpy(w2c)[None], H, W)
    rays = generate_rays_for_view(cams, 0, 0.1, 1.0)
    r, c = cloud.attributes["row"], cloud.attributes["col"]
    d = rays.directions.numpy()[r, c]
    z_scale = rays.z_scale.numpy()[r, c]
    var_ray = (std[r, c] / z_scale) ** 2
    var_lat = (depth[r, c] / math.sqrt(K[0, 0] * K[1, 1])) ** 2 / 12.0
    np.testing.assert_allclose(np.einsum("nij,nj->ni", cov, d), var_ray[:, None] * d, rtol=1e-4, atol=1e-9)
    perp = np.cross(d, [0.0, 0.0, 1.0])
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", cov, perp), var_lat[:, None] * perp, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=0)


# ----------------------------------------------------------------------------- PLY
def _sample_cloud(n_views: int = 2) -> CloudArrays:
    rng = np.random.default_rng(4)
    H, W = 5, 7
    clouds = []
    for v in range(n_views):
        depth = rng.uniform(1.0, 3.0, size=(H, W))
        clouds.append(cloud_from_products(make_products(depth, rng.uniform(0.01, 0.3, (H, W)), intrinsics(W, H),
                                                        random_pose(rng)), view=v, covariance=True))
    cloud = CloudArrays.concatenate(clouds)
    cloud.rgb = rng.uniform(size=cloud.rgb.shape).astype(np.float32)
    return cloud


@pytest.mark.parametrize("colour_by", ["rgb", "uncertainty"])
def test_ply_round_trip_open3d_and_trimesh(tmp_path, colour_by):
    import trimesh

    cloud = _sample_cloud()
    path = tmp_path / "cloud.ply"
    desc = write_ply(path, cloud, colour_by, value_range=(0.0, 0.2) if colour_by == "uncertainty" else None)
    colours, _ = point_colours(cloud, colour_by, value_range=(0.0, 0.2))
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header and "property uchar red" in header
    if colour_by == "uncertainty":
        assert desc["vmin"] == 0.0 and desc["vmax"] == 0.2 and "comment vmax=0.2" in header
        assert "comment quantity=depth_std" in header
    # Open3D
    back, col = read_ply(path)
    assert col.dtype == np.uint8
    np.testing.assert_array_equal(col, colours)
    np.testing.assert_array_equal(back.positions, cloud.positions.astype(np.float32))
    np.testing.assert_array_equal(back.normals, cloud.normals)
    assert set(back.attributes) == set(cloud.attributes)
    for name, values in cloud.attributes.items():
        np.testing.assert_array_equal(back.attributes[name], values, err_msg=name)
        assert back.attributes[name].dtype == values.dtype, name
    # trimesh
    tm = trimesh.load(str(path))
    np.testing.assert_array_equal(np.asarray(tm.vertices), cloud.positions.astype(np.float32))
    np.testing.assert_array_equal(np.asarray(tm.colors)[:, :3], colours)
    raw = tm.metadata["_ply_raw"]["vertex"]["data"]
    for name, values in cloud.attributes.items():
        np.testing.assert_array_equal(raw[name], values, err_msg=name)
    for axis, name in enumerate(("nx", "ny", "nz")):
        np.testing.assert_array_equal(raw[name], cloud.normals[:, axis])
    # the in-memory Open3D cloud carries the same attributes
    pc = to_open3d(cloud, colour_by)
    assert pc.point.colors.numpy().dtype == np.uint8
    np.testing.assert_array_equal(pc.point["confidence"].numpy()[:, 0], cloud.attributes["confidence"])


# ----------------------------------------------------------------------------- map files
def test_png16_round_trip_within_quantisation(tmp_path):
    rng = np.random.default_rng(5)
    far = 6.0
    depth = rng.uniform(0.5, far, size=(20, 30))
    depth[0, 0] = far
    valid = rng.uniform(size=depth.shape) < 0.7
    valid[0, 0] = True
    png, sidecar = write_png16(tmp_path / "d.png", depth, valid, max_depth=far, units="m")
    meta = json.loads(sidecar.read_text())
    scale = png16_scale(far)
    assert meta["scale"] == pytest.approx(far / 65535) and meta["invalid_value"] == 0 and meta["units"] == "m"
    dec, ok = read_png16(png)
    np.testing.assert_array_equal(ok, valid)
    assert np.max(np.abs(dec[valid] - depth[valid])) <= scale / 2 + 1e-12
    assert np.all(dec[~valid] == 0)
    assert encode_png16(depth, valid, scale)[0, 0] == 65535
    assert encode_png16(np.array([[2 * far]]), np.array([[True]]), scale)[0, 0] == 65535  # clipped at the top
    with pytest.raises(ValueError, match="positive"):
        png16_scale(0.0)


def test_tiff_and_npz_round_trip(tmp_path):
    rng = np.random.default_rng(6)
    H, W = 9, 11
    draws = rng.normal(3.0, 0.2, size=(H, W, 16))
    opacity = rng.uniform(size=(H, W))
    p = make_products(draws.mean(-1), draws.std(-1), intrinsics(W, H), random_pose(rng), opacity=opacity, draws=draws)
    maps = read_tiff(write_tiff(tmp_path / "v.tiff", p))
    assert list(maps) == list(p.maps())
    for name, m in p.maps().items():
        assert m.dtype == np.float32
        if name == "opacity":
            np.testing.assert_array_equal(maps[name], m)
        else:
            np.testing.assert_array_equal(maps[name][p.valid], m[p.valid])
            assert np.all(np.isnan(maps[name][~p.valid]))
    z = np.load(write_npz(tmp_path / "v.npz", p, include_draws=True))
    names = ("depth_mean", "depth_std", "depth_std_epistemic", "depth_std_spread", "opacity", "depth_draw_q5", "depth_draw_q95", "depth_band90_lower", "depth_band90_upper")
    for name in names:
        assert z[name].dtype == np.float32 and z[name].shape == (H, W)
    np.testing.assert_array_equal(z["intrinsics"], p.intrinsics)
    np.testing.assert_array_equal(z["world_to_camera"], p.world_to_camera)
    assert int(z["num_draws"]) == 16 and str(z["units"]) == "scene units" and "camera-z" in str(z["conventions"])
    np.testing.assert_array_equal(z["depth_draws"], draws.astype(np.float32))
    np.testing.assert_allclose(z["depth_draw_q95"], np.quantile(draws, 0.95, axis=-1), rtol=1e-6)


# ----------------------------------------------------------------------------- filters and fusion
def _cloud(positions, var, depth=None, rgb=None) -> CloudArrays:
    n = len(positions)
    depth = np.full(n, 2.0) if depth is None else np.asarray(depth, float)
    std = np.sqrt(np.asarray(var, float))
    attrs = {"depth": depth.astype(np.float32), "depth_std": std.astype(np.float32),
             "depth_var": np.asarray(var, np.float32), "confidence": np.exp(-std / depth / 0.05).astype(np.float32),
             "opacity": np.linspace(0.2, 1.0, n).astype(np.float32), "footprint": np.full(n, 0.1, np.float32)}
    rgb = np.zeros((n, 3), np.float32) if rgb is None else np.asarray(rgb, np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (n, 1))
    return CloudArrays(np.asarray(positions, float), normals, rgb, attrs, {"units": "m"})


def test_filters_each_stage():
    var = np.array([0.01, 0.04, 0.09, 0.16, 0.25]) ** 1
    c = _cloud(np.zeros((5, 3)), var, depth=[1.0, 10.0, 1.0, 10.0, 1.0])
    kept, counts = filter_cloud(c, PointFilter(min_opacity=0.5))
    assert counts["opacity"] == int(np.sum(c.attributes["opacity"] >= 0.5)) == len(kept)
    kept, _ = filter_cloud(c, PointFilter(max_std=0.35))
    np.testing.assert_allclose(kept.attributes["depth_var"], [0.01, 0.04, 0.09])
    kept, _ = filter_cloud(c, PointFilter(max_rel_std=0.1))  # std / depth: .1, .02, .3, .04, .5
    np.testing.assert_allclose(kept.attributes["depth"], [1.0, 10.0, 10.0])
    kept, counts = filter_cloud(c, PointFilter(keep_fraction=0.4))  # 2 of 5, highest confidence = lowest rel std
    np.testing.assert_allclose(np.sort(kept.attributes["depth_var"]), [0.04, 0.16])
    assert counts == {"input": 5, "opacity": 5, "std": 5, "rel_std": 5, "keep_fraction": 2}
    with pytest.raises(ValueError, match="keep_fraction"):
        PointFilter(keep_fraction=0.0)
    with pytest.raises(ValueError, match="max_std"):
        PointFilter(max_std=-1.0)


def test_fusion_inverse_variance_by_hand():
    p = np.array([[0.11, 0.12, 0.13], [0.15, 0.18, 0.11], [2.5, 0.1, 0.1]])
    var = np.array([1.0, 4.0, 0.5])
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    a, b = _cloud(p[:2], var[:2], rgb=rgb[:2]), _cloud(p[2:], var[2:], rgb=rgb[2:])
    for c, vs in ((a, var[:2]), (b, var[2:])):
        cov = np.stack([np.diag([v, 2 * v, 3 * v]).reshape(9) for v in vs])
        for k, name in enumerate(COVARIANCE_NAMES):
            c.attributes[name] = cov[:, k].astype(np.float32)
    fused, report = fuse_clouds([a, b], voxel_size=1.0)
    assert report["input"] == 3 and report["fused"] == 2 and report["max_count"] == 2
    order = np.argsort(fused.positions[:, 0])
    f = fused.select(order)
    w = 1.0 / var[:2]
    np.testing.assert_allclose(f.positions[0], (w[0] * p[0] + w[1] * p[1]) / w.sum(), rtol=1e-12)
    np.testing.assert_allclose(f.rgb[0], (w[0] * rgb[0] + w[1] * rgb[1]) / w.sum(), rtol=1e-6)
    assert f.attributes["depth_var"][0] == pytest.approx(1.0 / (1.0 + 0.25))  # 1 / sum(1 / var)
    assert f.attributes["count"].tolist() == [2, 1]
    np.testing.assert_allclose(f.positions[1], p[2])
    assert f.attributes["depth_var"][1] == pytest.approx(0.5)
    cov00 = (w[0] ** 2 * 1.0 + w[1] ** 2 * 4.0) / w.sum() ** 2  # covariance of the weighted mean
    assert f.attributes["cov_xx"][0] == pytest.approx(cov00) and f.attributes["cov_zz"][0] == pytest.approx(3 * cov00)
    assert default_voxel_size(a) == pytest.approx(0.1)
    # a zero variance is floored, not an infinite weight
    z, _ = fuse_clouds(_cloud(p[:2], [0.0, 1.0]), voxel_size=1.0)
    assert np.all(np.isfinite(z.positions)) and np.all(np.isfinite(z.attributes["depth_var"]))


# ----------------------------------------------------------------------------- exact geometry
def test_points_on_true_surface_and_confidence_orders_error(tiny_scene):
    """GT depth back-projects onto scene.ply; with heteroscedastic noise whose std is also the
    predicted std, the more confident half of the points is much closer to the surface."""
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene)
    K = ds.cameras.intrinsics[:, :3, :3].double().numpy()
    w2c = ds.cameras.extrinsics.double().numpy()
    rng = np.random.default_rng(7)
    exact, noisy = [], []
    for v in (0, 7):
        gt = ds.depths[v].numpy().astype(np.float64)
        hit = (gt > 0).astype(np.float64)
        exact.append(cloud_from_products(make_products(gt, np.zeros_like(gt), K[v], w2c[v], opacity=hit), view=v))
        rel = np.exp(rng.uniform(np.log(0.002), np.log(0.05), size=gt.shape))  # log-uniform relative std
        std = rel * gt
        noisy.append(cloud_from_products(make_products(gt + std * rng.normal(size=gt.shape), std, K[v], w2c[v],
                                                       opacity=hit), view=v))
    mesh = tiny_scene / "scene.ply"
    d_exact = surface_distances(CloudArrays.concatenate(exact).positions, mesh)
    assert d_exact.size > 2000 and d_exact.mean() < 2e-4  # float32 ray casting and storage
    cloud = CloudArrays.concatenate(noisy)
    dist = surface_distances(cloud.positions, mesh)
    kept, _ = filter_cloud(cloud, PointFilter(keep_fraction=0.5))
    d_kept = surface_distances(kept.positions, mesh)
    assert len(kept) == math.ceil(len(cloud) / 2)
    assert d_kept.mean() < 0.5 * dist.mean()


def test_colourised_png_and_cloud_picture(tmp_path):
    import imageio.v3 as iio

    from stochastic_fields.products.depth_maps import write_colourised
    from stochastic_fields.products.render_cloud import render_cloud_png

    rng = np.random.default_rng(8)
    H, W = 16, 20
    depth = rng.uniform(1.0, 3.0, (H, W))
    opacity = np.where(rng.uniform(size=(H, W)) < 0.8, 1.0, 0.0)
    p = make_products(depth, 0.05 * depth, intrinsics(W, H), random_pose(rng), opacity=opacity)
    img = iio.imread(write_colourised(tmp_path / "vis.png", p, title="v"))
    assert img.ndim == 3 and img.shape[2] in (3, 4) and img.shape[1] > img.shape[0]
    assert len(np.unique(img.reshape(-1, img.shape[2]), axis=0)) > 50  # maps and colour bars, not a blank canvas
    cloud = cloud_from_products(p)
    pic = iio.imread(render_cloud_png(tmp_path / "cloud.png", cloud, size_px=(400, 300)))
    assert pic.ndim == 3 and len(np.unique(pic.reshape(-1, pic.shape[2]), axis=0)) > 50
    with pytest.raises(ValueError, match="empty"):
        render_cloud_png(tmp_path / "none.png", cloud.select(np.zeros(len(cloud), bool)))
    assert not (tmp_path / "none.png").exists()


def test_splat_keeps_the_nearest_point_at_its_projection():
    from stochastic_fields.products.render_cloud import splat

    w2c = np.eye(4)  # camera at the origin looking along +z
    focal, W, H = 100.0, 40, 30
    # near, far behind it on the same ray, far alone, behind the camera
    pts = np.array([[0.1, -0.05, 2.0], [0.2, -0.1, 4.0], [0.4, -0.05, 4.0], [0.0, 0.0, -1.0]])
    cols = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    img = splat(pts, cols, w2c, focal, (W, H), radius_world=0.0)  # 1-pixel splats
    # (u, v) = f x / z + W / 2: near point -> (25, 12.5); the far point on the same ray is hidden
    np.testing.assert_array_equal(img[12, 25], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(img[13, 25], [1.0, 0.0, 0.0])  # radius 1 px reaches the next row
    np.testing.assert_array_equal(img[13, 30], [0.0, 1.0, 0.0])  # (30, 13.75)
    assert not np.any(np.all(img == [0.0, 0.0, 1.0], axis=-1))  # the hidden point never shows
    assert np.sum(np.any(img != 1.0, axis=-1)) <= 2 * 5  # two 1-px-radius disks, nothing from behind the camera
