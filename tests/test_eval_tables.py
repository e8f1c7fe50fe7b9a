"""COLMAP sparse depth, the evaluation tables and the benchmark pipeline.

References: hand-projected points, scipy (pearsonr, spearmanr, norm), brute-force loops for
coverage and AUSE, an oracle uncertainty (AUSE 0); end-to-end runs on the tiny synthetic scene
and on fern images_16 (marked slow)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import torch
from torch import nn

from stochastic_fields.cameras import make_cameras
from stochastic_fields.capture_points import dense_depth_score_mask, load_capture_points
from stochastic_fields.config import save_config, set_dotted
from stochastic_fields.constants import DEPTH_NLL_VARIANCE_FLOOR, NLL_VARIANCE_FLOOR
from stochastic_fields.data import load_dataset
from stochastic_fields.data.colmap import ColmapPoints, read_points3d_binary
from stochastic_fields.evaluation import DENSE_DEPTH_SCORED
from stochastic_fields import sparse_depth as CD
from stochastic_fields_bench import tables as T
from stochastic_fields_bench.tables import json_default
from stochastic_fields.models.registry import METHODS
from stochastic_fields.renderer import MAP_NAMES, RenderOptions



# ------------------------------------------------------------------------------ sparse depth


def _hand_camera():
    K = torch.tensor([[[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]]])
    return make_cameras(K, torch.eye(4)[None], 48, 64)


def test_projection_of_hand_placed_points():
    pts = np.array([
        [0.0, 0.0, 2.0],      # u = 32, v = 24 -> pixel (24, 32), depth 2
        [0.1, -0.05, 4.0],    # u = 34.5, v = 22.75 -> pixel (22, 34), depth 4
        [0.0, 0.0, -1.0],     # behind the camera
        [10.0, 0.0, 1.0],     # u = 1032: outside the image
        [0.001, 0.0, 3.0],    # u = 32.033: same pixel as the first, farther -> hidden
    ])
    sd = CD.project_sparse_depth(_hand_camera(), pts, [0])[0]
    got = sorted(zip(sd.rows.tolist(), sd.cols.tolist(), sd.depth.tolist(), sd.point_index.tolist()))
    assert got == [(22, 34, pytest.approx(4.0), 1), (24, 32, pytest.approx(2.0), 0)]
    assert sd.num_candidates == 3 and sd.visibility == "zbuffer"
    assert np.allclose(sd.uv[np.argsort(sd.point_index)], [[32.0, 24.0], [34.5, 22.75]])
    depth_map = np.arange(48 * 64, dtype=np.float64).reshape(48, 64)
    assert sorted(sd.sample(depth_map).tolist()) == [22 * 64 + 34, 24 * 64 + 32]


def _fake_points(xyz: np.ndarray, tracks: list[list[int]]) -> ColmapPoints:
    lengths = np.array([len(t) for t in tracks])
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    ids = np.concatenate([np.array(t, dtype=np.int32) for t in tracks])
    P = len(tracks)
    return ColmapPoints(ids=np.arange(P, dtype=np.uint64), xyz=xyz, rgb=np.zeros((P, 3), np.uint8),
                        error=np.zeros(P), track_offsets=offsets, track_image_ids=ids,
                        track_point2d_idx=np.zeros(ids.size, np.int32))


def test_track_visibility_maps_image_ids_to_views():
    pts = _fake_points(np.zeros((4, 3)), [[1, 2], [2], [3, 1], [2, 3]])
    vis = CD.track_visibility(pts, 3)
    assert [v.tolist() for v in vis] == [[0, 2], [0, 1, 3], [2, 3]]
    assert CD.track_visibility(pts, 2) is None  # image id 3 does not exist among 2 views


@pytest.fixture(scope="module")
def fern16(shared_data):
    return load_dataset(shared_data / "nerf_llff_data" / "fern", images="images_16")


def test_fern_points_project_inside_with_plausible_depths(fern16):
    sparse = CD.sparse_depth_for_dataset(fern16)
    assert sorted(sparse) == fern16.test_indices
    for v, sd in sparse.items():
        assert sd.visibility == "tracks"
        assert len(sd) > 500
        assert ((sd.rows >= 0) & (sd.rows < fern16.height) & (sd.cols >= 0) & (sd.cols < fern16.width)).all()
        assert len(set(zip(sd.rows.tolist(), sd.cols.tolist()))) == len(sd)  # one point per pixel
        near, far = float(fern16.near[v]), float(fern16.far[v])
        inside = (sd.depth >= near) & (sd.depth <= far)
        assert inside.mean() > 0.99, (v, inside.mean())  # LLFF bounds are percentiles of these depths
        # the points sit on the pixel they were projected to: uv inside that pixel
        assert np.all(np.floor(sd.uv[:, 0]) == sd.cols) and np.all(np.floor(sd.uv[:, 1]) == sd.rows)


def test_wrong_image_id_match_falls_back_to_zbuffer(fern16, shared_data):
    pts = read_points3d_binary(CD.points_file(shared_data / "nerf_llff_data" / "fern"))
    V = fern16.num_views
    pts.track_image_ids = (pts.track_image_ids % V + 1).astype(np.int32)  # every id off by one view
    views = fern16.test_indices[:4]
    auto = CD.sparse_depth_for_dataset(fern16, views, points=pts)
    assert {sd.visibility for sd in auto.values()} == {"zbuffer"}
    zbuf = CD.sparse_depth_for_dataset(fern16, views, visibility="zbuffer")
    assert all(np.array_equal(auto[v].depth, zbuf[v].depth) for v in views)
    with pytest.raises(ValueError, match="do not match"):
        CD.sparse_depth_for_dataset(fern16, views, points=pts, visibility="tracks")


def test_missing_points_file_is_named(tmp_path, tiny_scene):
    ds = load_dataset(tiny_scene)
    with pytest.raises(FileNotFoundError, match="points3D.bin"):
        CD.sparse_depth_for_dataset(ds)


def _brute_ause_rmse(err: np.ndarray, unc: np.ndarray, F: int = 100) -> float:
    P = err.size

    def curve(key):
        order = sorted(range(P), key=lambda i: -key[i])  # stable: ties keep input order
        vals = []
        for i in range(F):
            kept = order[(i * P) // F:]
            vals.append(math.sqrt(sum(err[j] ** 2 for j in kept) / len(kept)))
        return np.array(vals)

    diff = curve(unc) - curve(np.abs(err))
    f = np.arange(F) / F
    return float(np.sum(0.5 * (diff[1:] + diff[:-1]) * np.diff(f)))


def test_paired_depth_scores_against_references():
    rng = np.random.default_rng(3)
    gt = rng.uniform(10.0, 50.0, 300)
    std = rng.uniform(0.05, 2.0, 300)
    std[:5] = 1e-5  # below the NLL floor's std (1e-3)
    pred = gt + std * rng.normal(size=300) * rng.uniform(0.5, 2.0, 300)
    s = CD.paired_depth_scores(gt, pred, std)
    err = pred - gt
    assert s["num_used"] == 300
    assert s["abs_rel"] == pytest.approx(np.mean(np.abs(err) / gt), rel=1e-12)
    assert s["rmse"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-12)
    nll = -scipy.stats.norm.logpdf(gt, pred, np.sqrt(np.maximum(std ** 2, DEPTH_NLL_VARIANCE_FLOOR))).mean()
    assert s["nll"] == pytest.approx(nll, rel=1e-10)
    assert s["pearson"].value == pytest.approx(scipy.stats.pearsonr(np.abs(err), std)[0], abs=1e-12)
    assert s["spearman"].value == pytest.approx(scipy.stats.spearmanr(np.abs(err), std)[0], abs=1e-12)
    for level, key in zip(CD.COVERAGE_LEVELS, ("coverage_68", "coverage_95")):
        z = scipy.stats.norm.ppf(0.5 + level / 2)
        assert s[key] == pytest.approx(sum(abs(e) <= z * sd for e, sd in zip(err, std)) / 300, abs=1e-12)
    assert s["ause_rmse"] == pytest.approx(_brute_ause_rmse(err, std ** 2), rel=1e-9, abs=1e-12)


def test_paired_depth_scores_undefined_cases():
    few = CD.paired_depth_scores(np.array([2.0]), np.array([2.1]), np.array([0.1]))
    assert few["num_used"] == 1 and math.isnan(few["rmse"]) and not few["pearson"].defined
    const = CD.paired_depth_scores(np.array([2.0, 3.0, 4.0]), np.array([2.1, 2.5, 4.0]), np.full(3, 0.2))
    assert not const["pearson"].defined and "constant depth std" in const["pearson"].reason
    assert math.isnan(const["ause_rmse"]) and const["sparsification"] is None
    assert const["rmse"] == pytest.approx(math.sqrt((0.01 + 0.25) / 3))


def test_sparse_depth_scores_mask_low_opacity():
    pts = np.array([[0.0, 0.0, 2.0], [0.1, -0.05, 4.0], [-0.1, 0.1, 3.0]])
    sd = CD.project_sparse_depth(_hand_camera(), pts, [0])[0]
    depth = np.full((48, 64), 3.5)
    std = np.full((48, 64), 0.5)
    std[24, 32] = 0.25
    opacity = np.ones((48, 64))
    opacity[22, 34] = 0.2  # the point at depth 4 is on a ray that hit nothing
    s = CD.sparse_depth_scores(depth, std, sd, opacity=opacity, opacity_mask=0.5)
    assert s["num_points"] == 3 and s["num_used"] == 2
    assert s["rmse"] == pytest.approx(math.sqrt((1.5 ** 2 + 0.5 ** 2) / 2))


def test_depth_parts_rank_errors_by_each_part_alone():
    """depth_parts/spearman_<part> is scipy's Spearman of |error| with that part's std, at the
    pixels the total is scored on (opacity mask); a part the maps lack is left out."""
    from stochastic_fields.evaluation import depth_samples, score_depth

    rng = np.random.default_rng(0)
    H, W = 12, 16
    gt = rng.uniform(2.0, 4.0, (H, W))
    epistemic, spread = rng.uniform(0.01, 0.5, (H, W)), rng.uniform(0.01, 0.5, (H, W))
    pred = gt + rng.normal(0.0, 1.0, (H, W)) * epistemic  # errors follow the epistemic part
    opacity = np.ones((H, W))
    opacity[:3] = 0.1  # not scored
    products = {"depth_mean": pred, "depth_std": np.hypot(epistemic, spread), "opacity": opacity,
                "depth_std_epistemic": epistemic, "depth_std_spread": spread}
    scores = score_depth(depth_samples(products, gt_depth=gt))
    keep = opacity > 0.5
    err = np.abs(pred - gt)[keep]
    for part, std in (("epistemic", epistemic), ("spread", spread)):
        assert scores[f"depth_parts/spearman_{part}"].value == pytest.approx(
            scipy.stats.spearmanr(err, std[keep])[0], abs=1e-12)
        assert scores[f"depth_parts/spearman_{part}"].n == keep.sum()
    assert scores["depth_parts/spearman_epistemic"].value > 0.5 > scores["depth_parts/spearman_spread"].value
    del products["depth_std_spread"]
    assert "depth_parts/spearman_spread" not in score_depth(depth_samples(products, gt_depth=gt))


# ------------------------------------------------------------------------------ configuration


def test_method_specs_build_valid_configs(tmp_path):
    base = T.base_config(T.BenchmarkSettings(tiny=True, overrides=(("render.num_samples", 12),)))
    assert base.render.num_samples == 12 and base.data.images == "images_8"
    kls = {}
    for name, spec in T.METHOD_SPECS.items():
        cfg = T.method_config(spec, base, tmp_path)
        assert cfg.method in METHODS
        assert cfg.train.iterations == base.train.iterations and cfg.train.seed == base.train.seed
        kls[name] = cfg.loss.kl
    assert (kls["snerf"], kls["snerf_kl_none"], kls["snerf_kl_fixed_prior"]) == ("full", "none", "fixed_prior")
    with pytest.raises(ValueError, match="unknown option 'loss.nope'"):
        set_dotted(base, "loss.nope", 1)


def test_resuming_needs_the_same_config(tmp_path):
    cfg = T.method_config(T.METHOD_SPECS["snerf"], T.base_config(T.BenchmarkSettings(tiny=True)), tmp_path)
    save_config(cfg, tmp_path / "config.json")
    T.check_compatible(tmp_path, cfg)
    more = T.method_config(T.METHOD_SPECS["snerf"], T.base_config(T.BenchmarkSettings(tiny=True, iterations=99,
                                                                                       device="cpu")), tmp_path)
    T.check_compatible(tmp_path, more)  # more iterations, another device: resumable
    assert T.config_fingerprint(more) != T.config_fingerprint(cfg)
    other = T.method_config(T.METHOD_SPECS["snerf_kl_none"], T.base_config(T.BenchmarkSettings(tiny=True)), tmp_path)
    with pytest.raises(ValueError, match="loss.kl"):
        T.check_compatible(tmp_path, other)


# ------------------------------------------------------------------------------ tables


def _fake_result(nll, pearson, render_s, train_s, psnr=20.0, undefined=0):
    names = ("nll", "pearson_mse_var", "spearman_mse_var", "psnr", "ssim", "ause_rmse", "ause_rmse_normalised",
             "ause_mae", "ause_mae_normalised", "auce_colour", "calibration_gap_colour", "render_s")
    values = {"nll": nll, "pearson_mse_var": pearson, "spearman_mse_var": pearson, "psnr": psnr}
    summary = {k: {"mean": values.get(k, 0.1), "num_views": 3,
                   "num_undefined": undefined if k in ("pearson_mse_var", "spearman_mse_var") else 0} for k in names}
    return {"metrics": {"summary": summary, "pooled": {"pearson_mse_var": pearson}, "num_draws": 4,
                        "depth_source": None, "conventions": {"nll": "test convention"}},
            "stages": {"train": {"train_s": train_s, "steps": 10}}, "timing": {"render_s": render_s},
            "config": {"train": {"iterations": 10, "rays_per_batch": 64, "seed": 0},
                       "field": {"backend": "grid", "grid_max_cells": 100},
                       "render": {"num_samples": 8, "num_draws": 4},
                       "data": {"images": "images_16", "split_every": 5}},
            "curves": {}}


def test_tables_from_results():
    nan = float("nan")
    results = {
        "fern": {"deterministic": _fake_result(9000.0, nan, 2.0, 10.0, undefined=3),
                 "snerf": _fake_result(1.0, 0.5, 4.0, 30.0), "snerf_kl_none": _fake_result(2.0, 0.3, 4.0, 25.0)},
        "flower": {"deterministic": _fake_result(8000.0, nan, 1.0, 20.0, undefined=3),
                   "snerf": _fake_result(3.0, 0.7, 5.0, 40.0), "snerf_kl_none": _fake_result(4.0, 0.1, 5.0, 50.0)},
    }
    results["fern"]["deterministic"]["config"]["render"]["num_draws"] = 16  # a baseline saved before K changed
    for scene in results:
        results[scene]["snerf"]["metrics"]["num_draws"] = 8
    tables = T.build_tables(results, command="python benchmarks/eval_tables.py --tiny")
    assert tables["budget"]["snerf_num_draws"] == 8  # the K S-NeRF rendered with, not a baseline's stored one
    t1 = tables["table1"]
    assert list(t1) == ["snerf", "deterministic"]  # Table-1 order, methods that ran
    assert t1["snerf"]["nll"] == {"fern": 1.0, "flower": 3.0, "average": 2.0}
    assert t1["snerf"]["paper"]["fern"] == (2.01, 0.69)
    assert math.isnan(t1["deterministic"]["pearson"]["average"])
    assert t1["deterministic"]["correlation_undefined_views"] == {"fern": 3, "flower": 3}
    t2 = tables["table2"]["snerf"]
    assert t2["render_ratio"]["fern"] == pytest.approx(2.0) and t2["render_ratio"]["flower"] == pytest.approx(5.0)
    assert t2["train_ratio"]["average"] == pytest.approx(np.mean([3.0, 2.0]))
    assert list(tables["table3"]) == ["snerf_kl_none", "snerf"]
    assert tables["table3"]["snerf_kl_none"]["paper"]["flower"] == (1.41, 0.54)
    md = T.format_markdown(tables)
    for text in ("Table 1", "Table 2", "Table 3", "1.000 [2.01]", "undef.", "S-NeRF w/o KL", "test convention",
                 "--tiny", "iterations=10"):
        assert text in md, text
    json.dumps(tables, default=json_default)


# ------------------------------------------------------------------------------ evaluate_run


class StubModel(nn.Module):
    """Returns fixed maps for one view (a stand-in for a trained model)."""

    def __init__(self, maps: dict[str, torch.Tensor], num_draws: int = 4):
        super().__init__()
        self.anchor = nn.Parameter(torch.zeros(1))
        self.maps = maps
        self.num_draws = num_draws

    def default_render_options(self):
        return RenderOptions(num_draws=self.num_draws)

    def render_view(self, rays, options=None, *, generator=None):
        K = (options or self.default_render_options()).num_draws
        return {**self.maps, "z_scale": rays.z_scale, "num_draws": torch.full(rays.shape, float(K))}


def _stub_maps(ds, view, colour_var, rng):
    gt = ds.images[view].double()
    noise = torch.as_tensor(rng.normal(0, 0.05, tuple(gt.shape)))
    z = ds.rays(view).z_scale.double()
    gt_depth = ds.depths[view].double()
    depth_cam = torch.where(gt_depth > 0, gt_depth * 1.02 + 0.01, torch.full_like(gt_depth, 5.0))
    H, W = gt_depth.shape
    maps = {"colour_mean": (gt + noise).float(), "colour_var": colour_var(noise).float(),
            "depth_mean": (depth_cam / z).float(), "depth_var_epistemic": torch.zeros(H, W),
            "depth_var_spread": torch.as_tensor(rng.uniform(1e-4, 1e-2, (H, W))).float(),
            "opacity": (gt_depth > 0).float()}
    maps["depth_var_total"] = maps["depth_var_epistemic"] + maps["depth_var_spread"]
    assert set(MAP_NAMES) <= set(maps)
    return maps, gt.numpy(), noise


def test_evaluate_run_with_an_oracle_uncertainty(tiny_scene, tmp_path):
    ds = load_dataset(tiny_scene)
    v = ds.test_indices[0]
    rng = np.random.default_rng(0)
    maps, gt, noise = _stub_maps(ds, v, lambda e: e ** 2, rng)
    result = T.evaluate_run(StubModel(maps), ds, tmp_path, views=[v], product_views=0, progress=False)
    s = result["summary"]
    mean = maps["colour_mean"].double().numpy()
    var = maps["colour_var"].double().numpy()
    nll = -scipy.stats.norm.logpdf(gt, mean, np.sqrt(np.maximum(var, NLL_VARIANCE_FLOOR))).mean()
    assert s["nll"]["mean"] == pytest.approx(nll, rel=1e-9)
    mse = ((gt - mean) ** 2).mean(-1).ravel()
    assert s["pearson_mse_var"]["mean"] == pytest.approx(scipy.stats.pearsonr(mse, var.mean(-1).ravel())[0], abs=1e-6)
    # oracle: per-pixel uncertainty = per-pixel MSE, so RMSE sparsification is the oracle curve
    assert s["ause_rmse"]["mean"] == pytest.approx(0.0, abs=1e-12)
    assert result["pooled"]["ause_rmse"] == pytest.approx(0.0, abs=1e-12)
    assert s["ause_mae"]["mean"] > 0  # ranking by variance is not the MAE oracle
    # depth against the dataset's exact depth maps, on the pixels whose surface lies in a SCORE block
    assert result["depth_source"] == "dense"
    assert result["conventions"]["dense_depth_scored"] == DENSE_DEPTH_SCORED
    gt_depth = ds.depths[v].numpy().astype(np.float64)
    mask = dense_depth_score_mask(ds, load_capture_points(ds), v)
    assert 0 < mask.sum() < (gt_depth > 0).sum() and not (mask & (gt_depth <= 0)).any()
    assert s["depth/abs_rel"]["mean"] == pytest.approx(np.mean((0.02 * gt_depth[mask] + 0.01) / gt_depth[mask]),
                                                       rel=1e-5)
    assert s["depth/num_used"]["mean"] == mask.sum()
    with np.load(tmp_path / "curves.npz") as curves:
        assert {"colour_sparsification_rmse.ause", "colour_calibration.coverage",
                "depth_calibration.coverage"} <= set(curves.files)
    assert json.loads((tmp_path / "metrics.json").read_text())["summary"]["nll"]["mean"] == pytest.approx(nll)


def test_evaluate_run_with_a_constant_uncertainty(tiny_scene, tmp_path):
    ds = load_dataset(tiny_scene)
    v = ds.test_indices[0]
    maps, _, _ = _stub_maps(ds, v, lambda e: torch.zeros_like(e), np.random.default_rng(1))
    result = T.evaluate_run(StubModel(maps, num_draws=1), ds, tmp_path, views=[v], product_views=1, progress=False)
    s = result["summary"]
    assert s["pearson_mse_var"]["num_undefined"] == 1 and math.isnan(s["pearson_mse_var"]["mean"])
    assert math.isnan(s["ause_rmse"]["mean"]) and math.isnan(result["pooled"]["ause_rmse"])
    assert result["pooled"]["correlation_undefined_reason"] == "constant uncertainty"
    assert result["num_draws"] == 1 and s["num_draws"]["mean"] == 1  # the K the render reported
    assert math.isfinite(s["nll"]["mean"]) and s["auce_colour"]["mean"] == pytest.approx(0.5, abs=0.01)
    assert (tmp_path / "views" / f"view_{v:03d}_colour_mean.png").is_file()


# ------------------------------------------------------------------------------ end to end

TINY_OVERRIDES = (("render.num_samples", 8), ("render.num_draws", 4), ("field.grid_max_cells", 12 ** 3),
                  ("train.rays_per_batch", 64), ("loss.random_points_per_axis", 4))


@pytest.mark.slow
def test_every_method_end_to_end_on_the_synthetic_scene(tiny_scene, tmp_path):
    settings = T.BenchmarkSettings(iterations=2, max_views=1, timing_repeats=1, tiny=True, device="cpu",
                                   overrides=TINY_OVERRIDES, product_views=1)
    logs: list[str] = []
    tables = T.run_benchmark([str(tiny_scene)], T.DEFAULT_METHODS, tmp_path, settings, progress=False,
                             log=logs.append)
    scene = Path(tiny_scene).name
    assert set(tables["table2"]) == set(T.DEFAULT_METHODS)
    for m, e in tables["table2"].items():
        assert e["render_s"][scene] > 0 and math.isfinite(e["nll"][scene]), m
    assert tables["depth_sources"] == ["dense"]
    assert (tmp_path / "tables.md").is_file() and (tmp_path / "tables.json").is_file()
    # (after 2 steps no ray is opaque enough for depth scores: depth plots are covered on fern)
    assert {Path(p).name for p in tables["plots"]} >= {f"{scene}_sparsification_rmse.png",
                                                       f"{scene}_calibration_colour.png",
                                                       f"{scene}_ablation_calibration_colour.png"}
    assert "Table 5: depth against dense" in (tmp_path / "tables.md").read_text()
    stamps = {p: p.stat().st_mtime_ns for p in tmp_path.glob("*/*/stages.json")}
    assert len(stamps) == len(T.DEFAULT_METHODS)
    logs.clear()
    T.run_benchmark([str(tiny_scene)], T.DEFAULT_METHODS, tmp_path, settings, progress=False, log=logs.append)
    assert all(line.endswith("skipped") for line in logs), logs
    assert stamps == {p: p.stat().st_mtime_ns for p in tmp_path.glob("*/*/stages.json")}


@pytest.mark.slow
def test_benchmark_script_on_fern_images_16(shared_data, tmp_path, capsys, load_script):
    script = load_script("benchmarks/eval_tables.py")
    argv = ["--tiny", "--scenes", "fern", "--methods", "deterministic", "snerf", "--iterations", "5",
            "--max-views", "1", "--data-root", str(shared_data / "nerf_llff_data"), "--out", str(tmp_path),
            "--device", "cpu", "--quiet", "--no-timing", "--product-views", "0"]
    argv += [a for k, v in TINY_OVERRIDES for a in ("--set", f"{k}={v}")]
    assert script.main(argv) == 0
    printed = capsys.readouterr().out
    assert "Table 1" in printed and "[2.01]" in printed
    tables = json.loads((tmp_path / "tables.json").read_text())
    assert tables["scenes"] == ["fern"] and tables["depth_sources"] == ["sparse"]
    assert tables["budget"]["images"] == "images_16" and tables["budget"]["num_samples"] == 8
    assert math.isnan(tables["table2"]["snerf"]["render_s"]["fern"])  # --no-timing: Table 2 has no render time
    assert tables["per_scene"]["fern"]["snerf"]["depth"]["num_used"] > 100
    assert math.isnan(tables["table1"]["deterministic"]["pearson"]["fern"])  # JSON NaN: undefined
    for name in ("fern_sparsification_rmse.png", "fern_calibration_colour.png", "fern_calibration_depth.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 1000
    with pytest.raises(SystemExit):
        script.main(argv + ["--set", "nonsense"])
    # the few-view protocol into its own folder: the split and the published-comparison column
    few = tmp_path / "fewview3"
    assert script.main([a if a != str(tmp_path) else str(few) for a in argv] + ["--protocol", "fewview", "--views", "3"]) == 0
    tables = json.loads((few / "tables.json").read_text())
    assert "3 of the others train" in tables["protocol"]
    assert tables["per_scene"]["fern"]["snerf"]["num_views"] == 1
    assert np.isfinite(tables["quality"]["snerf"]["ause_rmse_max_normalised"]["fern"])
    assert "AUSE RMSE max-norm." in (few / "tables.md").read_text()


def test_view_selection_and_budget():
    views = [1, 2, 3, 4, 6, 7, 8, 9, 11, 12, 13, 14, 16, 17, 18, 19]  # fern's 16 test views
    cpu = T.BenchmarkSettings()
    assert T.select_views(views, cpu) == [1, 7, 13, 19]  # 4 spread evenly, both ends
    assert T.select_views(views, T.BenchmarkSettings(budget="full")) == views
    assert T.select_views(views, T.BenchmarkSettings(max_views=2)) == [1, 19]
    assert T.select_views(views[:3], T.BenchmarkSettings(max_views=10)) == views[:3]
    with pytest.raises(ValueError, match="max_views"):
        T.select_views(views, T.BenchmarkSettings(max_views=0))
    cfg = T.base_config(cpu)
    assert (cfg.train.iterations, cfg.field.grid_max_cells) == (1000, 250_000)
    full = T.base_config(T.BenchmarkSettings(budget="full"))
    assert (full.train.iterations, full.field.grid_max_cells) == (3000, 2_000_000)
    assert T.base_config(T.BenchmarkSettings(iterations=7)).train.iterations == 7  # explicit beats the budget
    with pytest.raises(ValueError, match="budget"):
        T.base_config(T.BenchmarkSettings(budget="gpu"))


def test_cpu_budget_steps_follow_the_training_pixels():
    """Study 28's rule by hand: min(2 base, max(base, ceil(base P / P_ref))), P_ref = 4 x 504 x 378."""
    from types import SimpleNamespace

    from stochastic_fields_bench.budget import CPU_BUDGET_REFERENCE_PIXELS, cpu_budget_steps

    photo = 504 * 378
    assert CPU_BUDGET_REFERENCE_PIXELS == 762_048
    assert [cpu_budget_steps(1000, n * photo) for n in (1, 4, 5, 7, 8, 9, 17, 29)] == \
        [1000, 1000, 1250, 1750, 2000, 2000, 2000, 2000]
    assert cpu_budget_steps(1000, 4 * photo + 1) == 1001  # the ceiling, in integers
    assert cpu_budget_steps(7, 0) == 7 and cpu_budget_steps(7, 10 * photo) == 14
    with pytest.raises(ValueError, match="base_steps"):
        cpu_budget_steps(0, photo)

    def scene(views: int, height: int = 378, width: int = 504) -> SimpleNamespace:
        return SimpleNamespace(train_indices=list(range(views)), height=height, width=width, forward_facing=True)

    cpu = T.BenchmarkSettings()
    assert [T.base_config(cpu, scene(n)).train.iterations for n in (4, 7, 29)] == [1000, 1750, 2000]
    assert T.base_config(cpu, scene(7, 189, 252)).train.iterations == 1000  # images_16: a quarter of the pixels
    assert T.base_config(T.BenchmarkSettings(iterations=1000), scene(7)).train.iterations == 1000  # explicit wins
    assert T.base_config(T.BenchmarkSettings(budget="full"), scene(7)).train.iterations == 3000
    assert T.base_config(T.BenchmarkSettings(tiny=True), scene(7)).train.iterations == 20


def test_protocols_split_every_method_alike(shared_data):
    """--protocol: the paper's split, the few-view literature's (RegNeRF's training views, every 8th
    view tests, all of them scored) and the dense one, on fern (hand-worked indices as tests/test_split.py)."""
    root = shared_data / "nerf_llff_data"
    paper = T.scene_inputs("fern", T.BenchmarkSettings(images="images_16"), root, log=lambda _m: None)[1]
    assert list(paper.train_indices) == [0, 5, 10, 15]
    few = T.BenchmarkSettings(images="images_16", protocol="fewview", train_views=3)
    _, ds, views, sparse = T.scene_inputs("fern", few, root, log=lambda _m: None)
    assert list(ds.train_indices) == [1, 10, 19] and list(ds.test_indices) == views == [0, 8, 16]
    assert set(sparse) == {0, 8, 16}
    cfg = T.base_config(few, ds)
    assert (cfg.data.split, cfg.data.holdout_every, cfg.data.train_views) == ("fewview", 8, 3)
    dense = T.BenchmarkSettings(images="images_16", protocol="dense")
    _, ds, views, _ = T.scene_inputs("fern", dense, root, log=lambda _m: None)
    assert len(ds.train_indices) == 17 and views == [0, 8, 16]
    assert T.base_config(dense).data.split == "capture"
    assert "every 8th view tests, 3 of the others train" in few.describe_protocol()
    with pytest.raises(ValueError, match="protocol must be one of"):
        T.base_config(T.BenchmarkSettings(protocol="sparse"))
    with pytest.raises(ValueError, match="at least 1 training view"):
        T.base_config(T.BenchmarkSettings(protocol="fewview", train_views=0))


def test_resume_check_counts_missing_options_as_defaults(tmp_path):
    from stochastic_fields.config import to_dict

    cfg = T.base_config(T.BenchmarkSettings())
    saved = to_dict(cfg)
    del saved["render"]["occupancy_num_std"]  # a run folder from before the option existed
    (tmp_path / "config.json").write_text(json.dumps(saved))
    T.check_compatible(tmp_path, cfg)  # same computation: accepted
    fp = T.config_fingerprint(cfg)
    cfg.render.occupancy_num_std = 2.0
    with pytest.raises(ValueError, match="occupancy_num_std"):
        T.check_compatible(tmp_path, cfg)
    assert T.config_fingerprint(cfg) != fp
    cfg.render.occupancy_num_std = 3.0
    assert T.config_fingerprint(cfg) == fp
    cfg.train.iterations = 5000  # more steps resume the same run
    T.check_compatible(tmp_path, cfg)


def test_the_depth_weight_default_changes_retrain_only_snerf_default_runs():
    """loss.lambda_depth went 0.1 -> 0.3 (study 4) -> 1.0 (study 6): a run stored at 0.1 keeps its
    fingerprint (the entry stays left out), one stored at 0.3 keeps its own, a run at the new default
    gets a new one, the baselines (no depth term) none, and a saved config from before the option
    existed loads with the depth term off."""
    from stochastic_fields.config import ExperimentConfig, flatten, saved_config, to_dict
    from stochastic_fields_bench.runner import semantic_options

    assert ExperimentConfig().loss.lambda_depth == 1.0
    stored = ExperimentConfig()
    stored.loss.lambda_depth = 0.1
    assert "loss.lambda_depth" not in semantic_options(flatten(to_dict(stored)))
    assert semantic_options(flatten(to_dict(ExperimentConfig())))["loss.lambda_depth"] == 1.0
    assert T.config_fingerprint(ExperimentConfig()) != T.config_fingerprint(stored)
    study4 = ExperimentConfig()
    study4.loss.lambda_depth = 0.3
    assert semantic_options(flatten(to_dict(study4)))["loss.lambda_depth"] == 0.3
    assert len({T.config_fingerprint(c) for c in (ExperimentConfig(), stored, study4)}) == 3
    for method in ("ensemble", "deterministic"):
        a, b = ExperimentConfig(method=method), ExperimentConfig(method=method)
        b.loss.lambda_depth = 0.1
        assert T.config_fingerprint(a) == T.config_fingerprint(b)
    old = to_dict(ExperimentConfig())
    del old["loss"]["lambda_depth"]
    assert saved_config(old).loss.lambda_depth == 0.0


def test_the_observed_kl_weight_default_change_keeps_every_stored_run():
    """loss.lambda_observed went 5e-2 -> 1.25e-2 (study 16b): a run stored at 5e-2 keeps its
    fingerprint, a run at the new default (the study's override) gets a new one, the paper S-NeRF
    rows pin 5e-2 so their stored runs are not retrained, and the baselines (no KL) ignore it."""
    from stochastic_fields.config import ExperimentConfig, flatten, to_dict
    from stochastic_fields_bench.methods import METHOD_SPECS, method_config
    from stochastic_fields_bench.runner import semantic_options

    assert ExperimentConfig().loss.lambda_observed == 1.25e-2
    stored = ExperimentConfig()
    stored.loss.lambda_observed = 5e-2
    assert "loss.lambda_observed" not in semantic_options(flatten(to_dict(stored)))
    assert semantic_options(flatten(to_dict(ExperimentConfig())))["loss.lambda_observed"] == 1.25e-2
    assert T.config_fingerprint(ExperimentConfig()) != T.config_fingerprint(stored)
    for name in ("snerf", "snerf_predictive", "snerf_kl_none", "snerf_kl_fixed_prior"):
        assert method_config(METHOD_SPECS[name], ExperimentConfig(), Path("s")).loss.lambda_observed == 5e-2
    assert method_config(METHOD_SPECS["snerf_default"], ExperimentConfig(), Path("s")).loss.lambda_observed == 1.25e-2
    for method in ("ensemble", "deterministic", "mc_dropout", "nerfw"):
        a, b = ExperimentConfig(method=method), ExperimentConfig(method=method)
        b.loss.lambda_observed, b.loss.lambda_random, b.loss.kl = 5e-2, 0.5, "none"
        assert T.config_fingerprint(a) == T.config_fingerprint(b)


def test_the_point_noise_default_change_retrains_only_runs_that_take_the_depth_likelihood():
    """loss.depth_relative_std went 0.01 -> 0.03 (study 35): a run stored at 0.01 keeps its
    fingerprint, a run at the new default gets a new one (a stored 1% run is not taken for it), and
    runs without the depth likelihood (the paper S-NeRF rows, lambda_depth 0; the baselines) ignore it."""
    from stochastic_fields.config import ExperimentConfig, flatten, to_dict
    from stochastic_fields_bench.methods import METHOD_SPECS, method_config
    from stochastic_fields_bench.runner import semantic_options

    assert ExperimentConfig().loss.depth_relative_std == 0.03
    stored = ExperimentConfig()
    stored.loss.depth_relative_std = 0.01
    assert "loss.depth_relative_std" not in semantic_options(flatten(to_dict(stored)))
    assert semantic_options(flatten(to_dict(ExperimentConfig())))["loss.depth_relative_std"] == 0.03
    assert T.config_fingerprint(ExperimentConfig()) != T.config_fingerprint(stored)
    for name in ("snerf", "snerf_predictive", "snerf_kl_none", "snerf_kl_fixed_prior"):
        a = method_config(METHOD_SPECS[name], ExperimentConfig(), Path("s"))
        b = method_config(METHOD_SPECS[name], ExperimentConfig(), Path("s"))
        b.loss.depth_relative_std, b.loss.depth_rays_per_batch = 0.01, 7
        assert a.loss.lambda_depth == 0.0 and T.config_fingerprint(a) == T.config_fingerprint(b)
    off = ExperimentConfig()
    off.loss.lambda_depth = 0.0
    assert "loss.lambda_depth" in semantic_options(flatten(to_dict(off)))  # switching it off still retrains
    for method in ("ensemble", "deterministic", "mc_dropout", "nerfw"):
        a, b = ExperimentConfig(method=method), ExperimentConfig(method=method)
        b.loss.depth_relative_std = 0.01
        assert T.config_fingerprint(a) == T.config_fingerprint(b)


def test_a_changed_default_names_the_value_stored_fingerprints_left_out():
    """Fingerprints leave out values equal to the defaults, so a default that changes silently gives a
    run at the new value the fingerprint of runs stored at the old one (as loss.depth_relative_std's did
    before study 35's entry). Every default of tests/fingerprinted_defaults.json (the defaults when this
    guard was added) must still hold, or the old value must be in runner._FINGERPRINT_REFERENCE (or
    config.LEGACY_VALUES), and then the snapshot is updated. New options are free (their defaults keep
    the old behaviour)."""
    from stochastic_fields.config import LEGACY_VALUES, ExperimentConfig, flatten, to_dict
    from stochastic_fields_bench.runner import _FINGERPRINT_REFERENCE

    snapshot = json.loads((Path(__file__).parent / "fingerprinted_defaults.json").read_text())
    now = json.loads(json.dumps(flatten(to_dict(ExperimentConfig()))))
    referenced = set(LEGACY_VALUES) | set(_FINGERPRINT_REFERENCE)
    changed = {k: (v, now[k]) for k, v in snapshot.items() if k in now and now[k] != v and k not in referenced}
    assert not changed, f"defaults changed without a fingerprint reference (old, new): {changed}"


def test_render_only_options_rescore_a_stored_run_without_retraining(tmp_path):
    """Study 7 changed the render defaults (K 16 -> 8, Rao-Blackwellised colours): a run stored with
    the old values keeps its training fingerprint and is accepted for resuming (the differing
    render options are returned), its calibrate/eval fingerprints change; an option that shapes
    training still refuses the folder."""
    from stochastic_fields.config import ExperimentConfig, to_dict
    from stochastic_fields_bench.runner import RENDER_ONLY_OPTIONS

    assert {"render.num_draws", "render.colour_estimator"} <= set(RENDER_ONLY_OPTIONS)
    new = T.base_config(T.BenchmarkSettings())
    assert (new.render.num_draws, new.render.colour_estimator) == (8, "rao_blackwell")
    old = T.base_config(T.BenchmarkSettings())
    old.render.num_draws, old.render.colour_estimator = 16, "draws"
    (tmp_path / "config.json").write_text(json.dumps(to_dict(old)))
    assert T.check_compatible(tmp_path, new) == ["render.colour_estimator", "render.num_draws"]
    assert T.check_compatible(tmp_path, old) == []
    train_fp = [T.config_fingerprint(c, leave_out=RENDER_ONLY_OPTIONS) for c in (old, new)]
    assert train_fp[0] == train_fp[1]
    # the stored training fingerprint (computed before the option was left out) is unchanged
    assert train_fp[0] == T.config_fingerprint(old)
    assert T.config_fingerprint(old, "eval") != T.config_fingerprint(new, "eval")
    # the baselines render their own K from deterministic passes: nothing of theirs changes
    for method in ("deterministic", "ensemble", "mc_dropout", "nerfw"):
        a, b = ExperimentConfig(method=method), ExperimentConfig(method=method)
        b.render.num_draws, b.render.colour_estimator = 16, "draws"
        assert T.config_fingerprint(a, "eval") == T.config_fingerprint(b, "eval")
    # the runner updates only the render options of the stored config.json, nothing it was trained with
    from stochastic_fields.config import load_config
    from stochastic_fields_bench.runner import update_render_options

    stored = T.base_config(T.BenchmarkSettings())
    stored.render.num_draws, stored.render.colour_estimator, stored.loss.noise_head_decoupled = 16, "draws", False
    (tmp_path / "config.json").write_text(json.dumps(to_dict(stored)))
    update_render_options(tmp_path, new, ["render.num_draws", "render.colour_estimator"])
    updated = load_config(tmp_path / "config.json")
    assert (updated.render.num_draws, updated.render.colour_estimator) == (8, "rao_blackwell")
    assert updated.loss.noise_head_decoupled is False and new.loss.noise_head_decoupled is True
    with pytest.raises(ValueError, match="not a render-only option"):
        update_render_options(tmp_path, new, ["loss.kl"])
    trained = T.base_config(T.BenchmarkSettings())
    trained.loss.lambda_random *= 2
    with pytest.raises(ValueError, match="lambda_random"):
        T.check_compatible(tmp_path, trained)
    assert ExperimentConfig().render.num_draws == 8


def test_renders_are_timed_interleaved():
    """Interleaved timing renders A, B, A, B, ... with each variant's own options and a generator seeded 0."""
    from stochastic_fields_bench.runner import time_renders_interleaved

    calls = []

    class Recorder:
        def __init__(self, name):
            self.name = name

        def render_view(self, rays, options, *, generator):
            calls.append((self.name, options, float(torch.rand(1, generator=generator))))

    times = time_renders_interleaved({"a": (Recorder("a"), "opt_a"), "b": (Recorder("b"), None)}, rays=None, repeats=3)
    assert [c[:2] for c in calls] == [("a", "opt_a"), ("b", None)] * 3
    assert len({c[2] for c in calls}) == 1  # every render's generator starts from seed 0
    assert set(times) == {"a", "b"} and all(len(v) == 3 and min(v) >= 0 for v in times.values())


def test_table6_reports_the_narrowest_third():
    """Table 6 carries the narrowest third of the 95% bands (coverage at 68% and 95%, its widest
    half-width) beside the pooled levels, from each run's pooled depth intervals."""
    from stochastic_fields import metrics as M
    from stochastic_fields.evaluation import INTERVAL_KEYS

    result = _fake_result(1.0, 0.5, 4.0, 30.0)
    result["metrics"]["depth_source"] = "sparse"
    intervals = {k: 0.5 for k in INTERVAL_KEYS}
    intervals.update({"coverage_68_narrowest_third": 0.612, "coverage_95_narrowest_third": 0.917,
                      M.NARROWEST_WIDTH_KEY: 0.083})
    result["metrics"]["pooled"]["depth_intervals"] = intervals
    md = T.format_markdown(T.build_tables({"fern": {"snerf": result}}, command="test"))
    table6 = md.split("## Table 6")[1].split("## ")[0]
    assert "narrowest third: cov. 68%" in table6 and "its widest half-width 95%" in table6
    row = next(line for line in table6.splitlines() if line.startswith("| S-NeRF"))
    assert row.rstrip(" |").endswith("0.612 | 0.917 | 0.083")
