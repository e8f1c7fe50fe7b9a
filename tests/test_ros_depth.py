"""REP 118 depth images, CameraInfo and predictive bands, read back with the consumers' libraries
(imageio/tifffile, Open3D, PyYAML), on the synthetic scene's exact geometry."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import yaml
from test_export import ExactDepthModel  # the exact-geometry stand-in model of the export tests

from stochastic_fields.products.export import ExportOptions, dataset_view_specs, export_views, surface_distances
from stochastic_fields.products.ros_depth import (MetricScale, integrate_tsdf_open3d, metres_per_unit_from_known_distance,
                                                  ros_intrinsics)

VIEWS = [1, 2, 3, 6, 7, 11]


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    from stochastic_fields.data import load_dataset

    return load_dataset(tiny_scene)


@pytest.fixture(scope="module")
def ros_export(tiny_scene, dataset, tmp_path_factory):
    """An export in the 'ros' format (scene units are metres: metres_per_unit = 1)."""
    out = tmp_path_factory.mktemp("ros_export")
    model = ExactDepthModel(tiny_scene / "scene.ply", rel_range=(0.002, 0.05))
    opts = ExportOptions(formats=("npz", "ros"), metres_per_unit=1.0, save_draws=True, progress=False)
    summary = export_views(model, dataset_view_specs(dataset, VIEWS), out, opts, mesh_path=tiny_scene / "scene.ply")
    return out, summary


def test_ros_depth_files_match_the_maps(ros_export, dataset):
    import imageio.v3 as iio
    import tifffile

    out, summary = ros_export
    assert summary["metres_per_unit"] == 1.0 and "--metres-per-unit" in summary["scale_source"]
    z = np.load(out / "views" / "view_001.npz")
    valid = z["valid"]
    depth_m = tifffile.imread(out / "views" / "view_001_depth_m.tiff")
    assert depth_m.dtype == np.float32 and np.all(np.isnan(depth_m[~valid]))
    np.testing.assert_array_equal(depth_m[valid], z["depth_mean"][valid])
    std_m = tifffile.imread(out / "views" / "view_001_depth_std_m.tiff")
    np.testing.assert_array_equal(std_m[valid], z["depth_std"][valid])
    mm = iio.imread(out / "views" / "view_001_depth_mm.png")
    assert mm.dtype == np.uint16 and np.all(mm[~valid] == 0) and np.all(mm[valid] > 0)
    assert np.max(np.abs(mm[valid] / 1000.0 - z["depth_mean"][valid])) <= 0.0005 + 1e-6  # half a millimetre
    std_mm = iio.imread(out / "views" / "view_001_depth_std_mm.png")
    np.testing.assert_array_equal(std_mm[valid], np.maximum(np.round(z["depth_std"][valid].astype(np.float64) * 1000), 1))
    # the npz carries camera, units, scale, colour std and the predictive bands
    assert float(z["metres_per_unit"]) == 1.0 and str(z["units"]) == "scene units"
    assert z["colour_std"].shape == (dataset.height, dataset.width, 3)
    np.testing.assert_allclose(z["depth_band90_upper"] - z["depth_mean"], 1.6448536 * z["depth_std"], rtol=1e-4, atol=1e-6)


def test_camera_info_convention_backprojects_onto_the_surface(ros_export, dataset, tiny_scene):
    """CameraInfo K (integer pixel centres) used as Open3D's PinholeCameraIntrinsic puts the
    exported depths on the true surface; our +0.5 K would not."""
    import open3d as o3d

    out, _ = ros_export
    info = json.loads((out / "views" / "view_002_camera_info.json").read_text())
    doc = yaml.safe_load((out / "views" / "view_002_camera_info.yaml").read_text())
    assert doc["camera_matrix"]["data"] == info["K"] and doc["image_width"] == dataset.width
    K_ours = np.load(out / "views" / "view_002.npz")["intrinsics"]
    K = np.asarray(info["K"]).reshape(3, 3)
    np.testing.assert_allclose(K, ros_intrinsics(K_ours))
    assert K[0, 2] == pytest.approx(K_ours[0, 2] - 0.5) and info["D"] == [0.0] * 5
    np.testing.assert_allclose(np.asarray(info["P"]).reshape(3, 4)[:, :3], K)
    gt = dataset.depths[2].numpy().astype(np.float32)  # exact depths: isolates the intrinsics
    intr = o3d.camera.PinholeCameraIntrinsic(dataset.width, dataset.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    cloud = o3d.geometry.PointCloud.create_from_depth_image(o3d.geometry.Image(gt), intr,
                                                            np.asarray(info["world_to_camera"]), depth_scale=1.0,
                                                            depth_trunc=1e3)
    d_ok = surface_distances(np.asarray(cloud.points), tiny_scene / "scene.ply")
    intr_bad = o3d.camera.PinholeCameraIntrinsic(dataset.width, dataset.height, K[0, 0], K[1, 1], K_ours[0, 2],
                                                 K_ours[1, 2])
    bad = o3d.geometry.PointCloud.create_from_depth_image(o3d.geometry.Image(gt), intr_bad,
                                                          np.asarray(info["world_to_camera"]), depth_scale=1.0,
                                                          depth_trunc=1e3)
    d_bad = surface_distances(np.asarray(bad.points), tiny_scene / "scene.ply")
    assert np.median(d_ok) < 1e-3 < np.median(d_bad)


def test_open3d_tsdf_of_the_exported_millimetres(ros_export, tiny_scene):
    """Open3D's TSDF integration of the 16-bit depth + CameraInfo as written gives a mesh on the
    true surface; dropping the least certain pixels (std above its 80th percentile) is no worse."""
    import imageio.v3 as iio

    out, _ = ros_export
    v = out / "views"
    pairs = [(v / f"view_{i:03d}_depth_mm.png", v / f"view_{i:03d}_camera_info.json") for i in VIEWS]
    stds = [v / f"view_{i:03d}_depth_std_mm.png" for i in VIEWS]
    mesh = integrate_tsdf_open3d(pairs, voxel_size=0.03)
    verts = mesh.vertex.positions.numpy()
    assert len(verts) > 1000
    d_all = surface_distances(verts, tiny_scene / "scene.ply")
    all_std = np.concatenate([iio.imread(p)[iio.imread(p) > 0] for p in stds])
    cut = float(np.percentile(all_std, 80))
    masked = integrate_tsdf_open3d(pairs, voxel_size=0.03, max_std_mm=cut, std_images=stds)
    d_masked = surface_distances(masked.vertex.positions.numpy(), tiny_scene / "scene.ply")
    print(f"TSDF mesh to true surface: all pixels mean {d_all.mean():.4f} m ({len(verts)} vertices); "
          f"std <= {cut:.0f} mm: {d_masked.mean():.4f} m ({len(d_masked)} vertices)")
    assert d_all.mean() < 0.03  # one voxel
    assert d_masked.mean() <= d_all.mean() * 1.0001


class PredictiveModel(ExactDepthModel):
    """Draws whose predictive distribution holds the truth like one more draw: epistemic spread
    s_e around a centre offset by s_e * b, plus a termination spread s_t = 2 s_e (the true surface
    sits at an offset s_t * c inside each trajectory's blur); b, c ~ N(0, 1) per pixel."""

    def render_view(self, rays, options=None, *, generator=None):
        import open3d as o3d

        options = options or self.default_render_options()
        K, keep_draws = options.num_draws, options.keep_draws
        H, W = rays.shape
        o, d = rays.origins.double().numpy(), rays.directions.double().numpy()
        t = self.scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], -1).astype(np.float32)))["t_hit"].numpy()
        hit = np.isfinite(t)
        t = np.where(hit, t, rays.far.numpy()).astype(np.float64)
        rng = np.random.default_rng(5)
        s_e = np.where(hit, 0.02 * t, 0.0)
        s_t = 2.0 * s_e
        centre = t + s_e * rng.normal(size=(H, W)) + s_t * rng.normal(size=(H, W))
        draws = centre[..., None] + s_e[..., None] * rng.normal(size=(H, W, K))
        f = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
        maps = {"colour_mean": f(np.full((H, W, 3), 0.5)), "colour_var": f(np.zeros((H, W, 3))),
                "depth_mean": f(draws.mean(-1)), "depth_var_epistemic": f(draws.var(-1)),
                "depth_var_spread": f(s_t ** 2), "depth_var_total": f(draws.var(-1) + s_t ** 2),
                "opacity": f(hit), "z_scale": rays.z_scale.float()}
        if keep_draws:
            maps["depth_draws"] = f(draws)
        return maps


def test_band90_holds_its_level_and_draw_quantiles_do_not(tmp_path, tiny_scene, dataset):
    model = PredictiveModel(tiny_scene / "scene.ply", num_draws=32)
    opts = ExportOptions(formats=("npz",), quantiles=(0.05, 0.95), progress=False)
    s = export_views(model, dataset_view_specs(dataset, VIEWS), tmp_path, opts, mesh_path=tiny_scene / "scene.ply")
    inside_band, inside_q = [], []
    for i in VIEWS:
        z = np.load(tmp_path / "views" / f"view_{i:03d}.npz")
        gt = dataset.depths[i].numpy()
        m = z["valid"] & (gt > 0)
        inside_band.append((z["depth_band90_lower"][m] <= gt[m]) & (gt[m] <= z["depth_band90_upper"][m]))
        inside_q.append((z["depth_draw_q5"][m] <= gt[m]) & (gt[m] <= z["depth_draw_q95"][m]))
    band, q = np.concatenate(inside_band).mean(), np.concatenate(inside_q).mean()
    n = sum(len(a) for a in inside_band)
    # float64 reference: the same generative model per pixel (scale-free: s_e = 1, s_t = 2, gt = 0)
    K, rng = 32, np.random.default_rng(11)
    centre = rng.normal(size=200_000) + 2.0 * rng.normal(size=200_000)
    draws = centre[:, None] + rng.normal(size=(200_000, K))
    mean, std = draws.mean(-1), np.sqrt(draws.var(-1) + 4.0)
    expect_band = np.mean(np.abs(mean) <= 1.6448536 * std)
    lo, hi = np.quantile(draws, [0.05, 0.95], axis=-1)
    expect_q = np.mean((lo <= 0) & (0 <= hi))
    print(f"90% band coverage {band:.3f} (reference {expect_band:.3f}); draw 5-95% quantiles {q:.3f} "
          f"(reference {expect_q:.3f}) over {n} pixels")
    tol = 4 * math.sqrt(0.25 / n)  # four binomial standard errors at worst
    assert abs(band - expect_band) < tol and abs(band - 0.9) < 0.02
    assert abs(q - expect_q) < tol and q < 0.6
    assert s["ground_truth"]["calibration"]["gaussian_total_std"]["90"] == pytest.approx(band, abs=0.01)


def test_scale_is_required_and_known_distance(dataset):
    with pytest.raises(ValueError, match="metres-per-unit"):
        ExportOptions(formats=("npz", "ros")).validate()
    with pytest.raises(ValueError, match="positive"):
        ExportOptions(formats=("ros",), metres_per_unit=-1.0).validate()
    w2c = dataset.cameras.extrinsics.double().numpy()
    c = -np.einsum("vji,vj->vi", w2c[:, :3, :3], w2c[:, :3, 3])
    scale = metres_per_unit_from_known_distance(w2c, 0, 5, 2.5)
    assert scale.metres_per_unit == pytest.approx(2.5 / np.linalg.norm(c[0] - c[5]))
    assert "camera centres 0 and 5" in scale.source
    with pytest.raises(ValueError, match="out of range"):
        metres_per_unit_from_known_distance(w2c, 0, 99, 1.0)
    with pytest.raises(ValueError, match="positive"):
        MetricScale(0.0, "x")
