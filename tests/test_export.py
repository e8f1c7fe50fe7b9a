"""``stochastic-fields export`` end to end: exact-geometry model, a real run folder, the CLI.

The exact-geometry model renders the synthetic scene's ray-cast depth plus heteroscedastic
Gaussian draws (``D_k = t_hit + s * z_k``, ``s`` a log-uniform fraction of the depth), so the
exported numbers can be checked against the mesh and against numpy recomputations from the
draws the export itself saved.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from stochastic_fields.renderer import RenderOptions
from stochastic_fields.products.depth_maps import DepthProducts
from stochastic_fields.products.export import (
    CalibrationAccumulator, ExportOptions, dataset_view_specs, export_views, load_cameras_json)
from stochastic_fields.products.pointcloud import read_ply


class ExactDepthModel(nn.Module):
    """Stand-in for a trained model: exact depth of the mesh with known, pixel-varying noise."""

    def __init__(self, mesh_path: Path, rel_range=(0.002, 0.05), num_draws: int = 16):
        super().__init__()
        import open3d as o3d
        import trimesh

        self.anchor = nn.Parameter(torch.zeros(1))  # export asks the model for its device
        mesh = trimesh.load(str(mesh_path), force="mesh", process=False)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        self.rel_range, self.num_draws = rel_range, num_draws

    def default_render_options(self):
        return RenderOptions(num_draws=self.num_draws)

    def render_options(self, **changes):
        return self.default_render_options().with_changes(**changes)

    def render_view(self, rays, options=None, *, generator=None):
        import open3d as o3d

        options = options or self.default_render_options()
        K, keep_draws = options.num_draws, options.keep_draws
        H, W = rays.shape
        o, d = rays.origins.double().numpy(), rays.directions.double().numpy()
        t = self.scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], -1).astype(np.float32)))["t_hit"].numpy()
        hit = np.isfinite(t)
        t = np.where(hit, t, rays.far.numpy()).astype(np.float64)
        rng = np.random.default_rng(0)
        lo, hi = np.log(self.rel_range[0]), np.log(self.rel_range[1])
        s = np.where(hit, np.exp(rng.uniform(lo, hi, (H, W))) * t, 0.0)
        draws = t[..., None] + s[..., None] * rng.normal(size=(H, W, K))
        f = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
        maps = {"colour_mean": f(np.full((H, W, 3), 0.5)), "colour_var": f(np.zeros((H, W, 3))),
                "depth_mean": f(draws.mean(-1)), "depth_var_epistemic": f(draws.var(-1)),
                "depth_var_spread": f(np.zeros((H, W))), "depth_var_total": f(draws.var(-1)),
                "opacity": f(hit), "z_scale": rays.z_scale.float(), "num_draws": f(np.full((H, W), K))}
        if keep_draws:
            maps["depth_draws"] = f(draws)
        return maps


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    from stochastic_fields.data import load_dataset

    return load_dataset(tiny_scene)


@pytest.fixture(scope="module")
def exact_model(tiny_scene):
    return ExactDepthModel(tiny_scene / "scene.ply")


def _no_temp_files(folder: Path) -> None:
    leftovers = [p for p in folder.rglob("*") if p.name.startswith(".") or ".tmp" in p.name]
    assert not leftovers, leftovers


def test_export_exact_geometry(tmp_path, tiny_scene, dataset, exact_model):
    out = tmp_path / "export"
    opts = ExportOptions(formats=("npz", "png16", "tiff"), fuse=True, covariance=True, save_draws=True,
                         free_space_thresholds=(2.0, 3.0, 3.5), colour_by="uncertainty", progress=False)
    specs = dataset_view_specs(dataset, [1, 2])
    s = export_views(exact_model, specs, out, opts, mesh_path=tiny_scene / "scene.ply")
    # counts per stage
    hits = int(sum((dataset.depths[v] > 0).sum() for v in (1, 2)))
    c = s["counts"]
    assert c["pixels"] == 2 * dataset.height * dataset.width
    assert c["after_opacity"] == c["after_filters"] == hits
    assert 0 < c["after_fusion"] < c["after_filters"]
    assert set(s["files"]) >= {"views/view_001.npz", "views/view_002_depth_mean.png", "views/view_002_depth_draw_q5.json",
                               "views/view_001.tiff", "clouds/view_001.ply", "fused.ply", "fused_cloud.png",
                               "views/view_002_free_space.npz"}
    assert all((out / f).is_file() for f in s["files"]) and (out / "summary.json").is_file()
    _no_temp_files(out)
    # geometry: points lie on the mesh, and the confident half is far closer
    sd = s["ground_truth"]["surface_distance"]
    assert sd["num_points"] == hits and sd["mean"] < 0.01
    assert sd["most_confident_50_mean"] < 0.5 * sd["mean"] < sd["least_confident_50_mean"]
    assert s["ground_truth"]["surface_distance_fused"]["mean"] < 0.01
    # quantiles and free space recomputed from the draws the export saved
    z = np.load(out / "views" / "view_001.npz")
    draws = z["depth_draws"].astype(np.float64)
    np.testing.assert_allclose(z["depth_draw_q5"], np.quantile(draws, 0.05, axis=-1), rtol=1e-6)
    np.testing.assert_allclose(z["depth_mean"], draws.mean(-1), rtol=1e-5)
    np.testing.assert_allclose(z["depth_mean"][z["valid"]], dataset.depths[1].numpy()[z["valid"]], rtol=0.05)
    fs = np.load(out / "views" / "view_001_free_space.npz")
    for i, t in enumerate((2.0, 3.0, 3.5)):
        np.testing.assert_array_equal(fs["prob_depth_greater_draws"][i], np.mean(draws > np.float32(t), axis=-1))
        # the predictive P(depth > t) agrees with the exported 90% band: below 5% exactly beyond its upper
        # edge, above 95% exactly before its lower edge (pixels within float32 rounding of an edge left out)
        prob, v = fs["prob_depth_greater"][i], z["valid"]
        for edge, side in ((z["depth_band90_upper"], 0.05), (z["depth_band90_lower"], 0.95)):
            clear = v & (np.abs(t - edge) > 1e-4 * t)
            assert clear.sum() > 0
            np.testing.assert_array_equal((prob < side)[clear], (t > edge)[clear])
    # the per-view PLY carries covariances; the fused one counts merged points
    cloud, _ = read_ply(out / "clouds" / "view_001.ply")
    assert {"cov_xx", "cov_zz", "depth_std", "confidence", "opacity"} <= set(cloud.attributes)
    fused, _ = read_ply(out / "fused.ply")
    assert fused.attributes["count"].sum() == c["after_filters"]
    assert s["colour_mapping"]["vmax"] > 0 and s["colour_mapping"]["colour_by"] == "uncertainty"


def test_keep_fraction_and_max_std_in_export(tmp_path, dataset, exact_model):
    opts = ExportOptions(formats=("npz",), keep_fraction=0.5, max_std=0.05, progress=False)
    s = export_views(exact_model, dataset_view_specs(dataset, [3]), tmp_path, opts)
    c = s["per_view"]["view_003"]["counts"]
    assert c["std"] < c["opacity"] and c["keep_fraction"] == math.ceil(c["rel_std"] / 2)
    cloud, _ = read_ply(tmp_path / "clouds" / "view_003.ply")
    assert len(cloud) == c["keep_fraction"] and cloud.attributes["depth_std"].max() <= 0.05


def test_calibration_matches_numpy():
    """Means off by std * e, draws spread std around the mean: both intervals cover ~nominal,
    and the reported fractions equal a direct numpy computation."""
    rng = np.random.default_rng(1)
    H, W, K = 40, 50, 400
    gt = rng.uniform(1.0, 4.0, (H, W))
    gt[0, :5] = 0.0  # no ground truth there
    std = rng.uniform(0.01, 0.1, (H, W))
    mean = gt + std * rng.normal(size=(H, W))
    draws = mean[..., None] + std[..., None] * rng.normal(size=(H, W, K))
    opacity = np.where(rng.uniform(size=(H, W)) < 0.9, 1.0, 0.0)
    p = DepthProducts(mean.astype(np.float32), std.astype(np.float32), std.astype(np.float32),
                      np.zeros((H, W), np.float32), opacity.astype(np.float32), np.zeros((0, H, W), np.float32),
                      np.zeros(0), np.zeros((H, W, 3), np.float32), opacity >= 0.5, np.eye(3), np.eye(4), K, 0.1, 5.0,
                      depth_draws=draws.astype(np.float32))
    acc = CalibrationAccumulator()
    acc.add(p, gt.astype(np.float32))
    cal = acc.summary()
    m = (gt > 0) & (opacity >= 0.5)
    g, mu, sd = gt.astype(np.float32)[m], mean.astype(np.float32)[m], std.astype(np.float32)[m]
    dr = draws.astype(np.float32)[m]
    q = np.quantile(dr.astype(np.float64), [0.158655254, 0.841344746, 0.025, 0.975], axis=-1)
    assert cal["num_pixels"] == m.sum()
    assert cal["gaussian_total_std"]["68"] == pytest.approx(np.mean(np.abs(mu - g) <= sd))
    assert cal["gaussian_total_std"]["95"] == pytest.approx(np.mean(np.abs(mu - g) <= 1.959963985 * sd))
    assert cal["draw_quantiles"]["68"] == pytest.approx(np.mean((g >= q[0]) & (g <= q[1])))
    assert cal["draw_quantiles"]["95"] == pytest.approx(np.mean((g >= q[2]) & (g <= q[3])))
    for key, nominal in (("68", 0.6827), ("95", 0.95)):
        assert abs(cal["gaussian_total_std"][key] - nominal) < 0.04
        assert abs(cal["draw_quantiles"][key] - nominal) < 0.05


def test_interrupted_export_leaves_no_partial_file(tmp_path, dataset, exact_model, monkeypatch):
    import tifffile

    calls = {"n": 0}
    real = tifffile.imwrite

    def failing_imwrite(path, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:  # second view: half a file, then the process is "killed"
            Path(path).write_bytes(b"II*\x00partial")
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    monkeypatch.setattr(tifffile, "imwrite", failing_imwrite)
    out = tmp_path / "export"
    with pytest.raises(KeyboardInterrupt):
        export_views(exact_model, dataset_view_specs(dataset, [1, 2]), out,
                     ExportOptions(formats=("npz", "tiff"), progress=False))
    # the export is written into a fresh folder swapped in when complete: nothing of it remains
    assert not out.exists() and list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- a real run folder
@pytest.fixture(scope="module")
def run_dir(tiny_scene, tmp_path_factory):
    """A run folder as the trainer leaves it (config.json + checkpoint.pt) holding the tiny preset's
    freshly initialised model: the export pipeline does not care how long it trained. The model is
    built from the run's own training views, as the trainer builds it (the grid's shape follows them)."""
    from stochastic_fields import config as C
    from stochastic_fields.checkpoint import save_checkpoint
    from stochastic_fields.models.registry import build_model
    from stochastic_fields.scenes import load_run_dataset

    cfg = C.preset("tiny")
    cfg.data.path = str(tiny_scene)
    cfg.train.device = "cpu"
    run = tmp_path_factory.mktemp("run")
    torch.manual_seed(0)
    model = build_model(cfg, load_run_dataset(cfg, run))
    C.save_config(cfg, run / "config.json")
    save_checkpoint(run / "checkpoint.pt", {"model": model.state_dict(), "step": 0})
    return run


def test_cli_export_of_a_run(tmp_path, run_dir, dataset):
    from stochastic_fields.cli import main

    out = tmp_path / "out"
    rc = main(["export", "--run", str(run_dir), "--views", "1,6", "--min-opacity", "0", "--formats", "npz,png16",
               "--fuse", "--quantiles", "0.1,0.5,0.9", "--quiet", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    H, W = dataset.height, dataset.width
    assert s["views"] == ["view_001", "view_006"] and s["num_draws"] == 8  # the tiny preset's K
    assert s["counts"]["after_opacity"] == 2 * H * W  # min-opacity 0 keeps every pixel
    z = np.load(out / "views" / "view_006.npz")
    assert z["depth_draw_q50"].shape == (H, W) and np.all(z["depth_draw_q10"] <= z["depth_draw_q90"])
    np.testing.assert_allclose(z["world_to_camera"], dataset.cameras.extrinsics[6].double().numpy(), atol=0)
    assert np.all((z["depth_mean"] > 0) & (z["depth_mean"] <= float(dataset.far[6]) * (1 + 1e-5)))
    _no_temp_files(out)


def test_cli_export_from_cameras_json(tmp_path, run_dir, dataset):
    from stochastic_fields.cli import main

    K = dataset.cameras.intrinsics[2, :3, :3].double().numpy()
    w2c = dataset.cameras.extrinsics[2].double().numpy()
    K_half = K.copy()
    K_half[:2] *= 0.5
    cams = [{"K": K.tolist(), "world_to_camera": w2c.tolist(), "width": dataset.width, "height": dataset.height},
            {"name": "small", "K": K_half.tolist(), "world_to_camera": w2c.tolist(), "width": dataset.width // 2,
             "height": dataset.height // 2, "near": 1.0, "far": 5.0}]
    path = tmp_path / "cams.json"
    path.write_text(json.dumps(cams))
    out = tmp_path / "out"
    assert main(["export", "--run", str(run_dir), "--cameras", str(path), "--formats", "npz", "--quiet",
                 "--out", str(out)]) == 0
    small = np.load(out / "views" / "small.npz")
    assert small["depth_mean"].shape == (dataset.height // 2, dataset.width // 2) and float(small["far"]) == 5.0
    np.testing.assert_allclose(small["intrinsics"], K_half, rtol=1e-6)
    assert (out / "views" / "cam_000.npz").is_file() and (out / "clouds" / "small.ply").is_file()


def test_cli_bad_inputs(tmp_path, run_dir, capsys):
    from stochastic_fields.cli import main

    empty = tmp_path / "empty_run"
    empty.mkdir()
    assert main(["export", "--run", str(empty), "--quiet"]) == 2
    assert "checkpoint.pt" in capsys.readouterr().err
    assert main(["export", "--run", str(tmp_path / "missing"), "--quiet"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["export", "--run", str(run_dir), "--views", "1,99", "--quiet"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main(["export", "--run", str(run_dir), "--quantiles", "0.5,1.5", "--quiet"]) == 2
    assert "1.5" in capsys.readouterr().err
    bad = tmp_path / "bad_cams.json"
    bad.write_text(json.dumps([{"K": [[50, 0, 32], [0, 50, 24]], "world_to_camera": np.eye(4).tolist(),
                                "width": 64, "height": 48}]))
    assert main(["export", "--run", str(run_dir), "--cameras", str(bad), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad_cams.json" in err and "'K' must be 3x3" in err and "(2, 3)" in err
    assert not (run_dir / "export").exists()  # nothing written for rejected input


@pytest.mark.parametrize("camera, message", [
    ({"world_to_camera": np.eye(4).tolist(), "width": 4, "height": 3}, "has no 'K'"),
    ({"K": np.eye(3).tolist(), "world_to_camera": np.eye(3).tolist(), "width": 4, "height": 3}, "must be 4x4"),
    ({"K": np.eye(3).tolist(), "world_to_camera": (2 * np.eye(4)).tolist(), "width": 4, "height": 3}, "rigid"),
    ({"K": np.eye(3).tolist(), "world_to_camera": np.eye(4).tolist(), "width": 4.5, "height": 3}, "'width'"),
    ({"K": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "world_to_camera": np.eye(4).tolist(), "width": 4, "height": 3}, "fx"),
    ({"K": np.eye(3).tolist(), "world_to_camera": np.eye(4).tolist(), "width": 4, "height": 3, "near": 3, "far": 2},
     "near < far"),
])
def test_cameras_json_validation(tmp_path, camera, message):
    path = tmp_path / "c.json"
    path.write_text(json.dumps([camera]))
    with pytest.raises(ValueError, match="c.json") as info:
        load_cameras_json(path, default_near=0.5, default_far=5.0)
    assert message in str(info.value)
    with pytest.raises(FileNotFoundError):
        load_cameras_json(tmp_path / "nope.json", default_near=0.5, default_far=5.0)


def test_cli_eval_with_either_colour_estimator(tmp_path, run_dir):
    """``--colour-estimator`` overrides the run's setting at render time: both score the same view,
    with the same colour mean up to Monte-Carlo noise."""
    from stochastic_fields.cli import main

    summaries = {}
    for estimator in ("draws", "rao_blackwell"):
        out = tmp_path / estimator
        assert main(["eval", "--run", str(run_dir), "--views", "1", "--num-draws", "32", "--no-products", "--quiet",
                     "--colour-estimator", estimator, "--out", str(out)]) == 0
        summaries[estimator] = json.loads((out / "metrics.json").read_text())["summary"]
    psnr = {k: v["psnr"]["mean"] for k, v in summaries.items()}
    assert all(np.isfinite(v["nll"]["mean"]) for v in summaries.values())
    assert abs(psnr["draws"] - psnr["rao_blackwell"]) < 0.2, psnr
    with pytest.raises(SystemExit):  # argparse names the valid choices
        main(["eval", "--run", str(run_dir), "--colour-estimator", "exact", "--quiet"])
