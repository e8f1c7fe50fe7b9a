"""Render held-out views of a trained run, write their maps, and score them (SPEC 3, 6).

For each view: ``views/view_XXX.npz`` (float32 arrays, camera-z metric depth) and viewable
PNGs (colour mean, colour std, depth mean, depth std, ground truth); ``metrics.json`` with
per-view values, means and the conventions behind them.

Depth conventions: ``depth_*`` maps are camera-z depth in scene units (ray distance times
``z_scale``; standard deviations scale the same way). ``depth_std`` is the total standard
deviation (epistemic + termination spread, law of total variance). Depth scores use pixels
with opacity > ``OPACITY_MASK`` and a valid ground truth; rays that hit nothing report
``depth = far`` per draw (see volume_rendering.expected_depth).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from .calibration import ONE_SIGMA_LEVEL, apply_depth_calibration
from .cameras import generate_rays_for_view
from .eval import metrics as M
from .io_utils import atomic_path, atomic_write_text
from .visualize import colourise, to_uint8_rgb

#: opacity above which a pixel counts as a surface hit for depth scores.
OPACITY_MASK = 0.5


def camera_z_maps(maps: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Convert renderer maps (ray distance) into camera-z products, numpy float32."""
    z = maps["z_scale"].cpu().double()
    out = {
        "colour_mean": maps["colour_mean"].cpu().double(),
        "colour_std": maps["colour_var"].cpu().double().clamp_min(0).sqrt(),
        "depth_mean": maps["depth_mean"].cpu().double() * z,
        "depth_std": maps["depth_var_total"].cpu().double().clamp_min(0).sqrt() * z,
        "depth_std_epistemic": maps["depth_var_epistemic"].cpu().double().clamp_min(0).sqrt() * z,
        "depth_std_spread": maps["depth_var_spread"].cpu().double().clamp_min(0).sqrt() * z,
        "opacity": maps["opacity"].cpu().double(),
    }
    if "depth_draws" in maps:
        out["depth_draws"] = maps["depth_draws"].cpu().double() * z[..., None]
    return {k: v.numpy().astype(np.float32) for k, v in out.items()}


def _save_png(path: Path, rgb: np.ndarray) -> None:
    import imageio.v3 as iio

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, rgb)


def view_camera_arrays(dataset, view: int) -> dict[str, np.ndarray]:
    """The camera and units of a dataset view, stored next to its maps in every npz:
    ``intrinsics`` [3, 3] (pixel centres at +0.5), ``world_to_camera`` [4, 4] (OpenCV), ``near``,
    ``far`` (camera z), ``units`` and ``depth_kind``."""
    from .cameras import intrinsics_3x3

    return {
        "intrinsics": intrinsics_3x3(dataset.cameras)[view].double().cpu().numpy(),
        "world_to_camera": dataset.cameras.extrinsics[view].double().cpu().numpy(),
        "near": np.float64(dataset.near[view]), "far": np.float64(dataset.far[view]),
        "units": np.str_("scene units"),
        "depth_kind": np.str_("camera_z; OpenCV camera, pixel (row i, col j) centre at (j + 0.5, i + 0.5)"),
    }


def write_view_products(out_dir: Path, name: str, products: dict[str, np.ndarray], gt_colour: np.ndarray | None,
                        gt_depth: np.ndarray | None, camera: dict[str, np.ndarray] | None = None) -> None:
    """``name.npz`` (the maps, plus ``camera``'s arrays: see :func:`view_camera_arrays`) and PNGs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / f"{name}.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **products, **(camera or {}))
    mask = products["opacity"] > OPACITY_MASK
    _save_png(out_dir / f"{name}_colour_mean.png", to_uint8_rgb(products["colour_mean"]))
    std = products["colour_std"].mean(-1)
    _save_png(out_dir / f"{name}_colour_std.png", colourise(std, cmap="magma", vmin=0.0)[0])
    depth_img, lo, hi = colourise(products["depth_mean"], cmap="turbo", mask=mask)
    _save_png(out_dir / f"{name}_depth_mean.png", depth_img)
    _save_png(out_dir / f"{name}_depth_std.png", colourise(products["depth_std"], cmap="magma", mask=mask, vmin=0.0)[0])
    if gt_colour is not None:
        _save_png(out_dir / f"{name}_gt_colour.png", to_uint8_rgb(gt_colour))
    if gt_depth is not None:
        _save_png(out_dir / f"{name}_gt_depth.png", colourise(gt_depth, cmap="turbo", mask=gt_depth > 0, vmin=lo, vmax=hi)[0])


def depth_interval_scale(calibration, level: float) -> float:
    """Multiplier of ``z_p * depth_std`` for the central interval at ``level``: 1 for Gaussian
    intervals, ``relative_scale(level)`` for a recalibrated std (stochastic_fields.calibration)."""
    if calibration is None or calibration.depth is None:
        return 1.0
    return float(calibration.depth.relative_scale(level))


def score_view(products: dict[str, np.ndarray], gt_colour: np.ndarray, gt_depth: np.ndarray | None,
               calibration=None) -> dict:
    mean, var = products["colour_mean"], products["colour_std"].astype(np.float64) ** 2
    corr = M.mse_uncertainty_correlation(gt_colour, mean, var)
    scores = {
        "psnr": M.psnr(mean, gt_colour),
        "ssim": M.ssim(mean, gt_colour),
        "nll": M.gaussian_nll(gt_colour, mean, var),
        "pearson_mse_var": corr["pearson"],
        "spearman_mse_var": corr["spearman"],
        "ause_rmse": M.colour_sparsification(gt_colour, mean, var, "rmse").ause,
    }
    if gt_depth is not None:
        mask = (gt_depth > 0) & (products["opacity"] > OPACITY_MASK)
        if mask.sum() >= 2:
            d, s = products["depth_mean"], products["depth_std"].astype(np.float64)
            err = M.depth_errors(d, gt_depth, mask)
            scores.update({"depth_abs_rel": err["abs_rel"], "depth_rmse": err["rmse"],
                           "depth_nll": M.depth_nll(gt_depth, d, s ** 2, mask),
                           "depth_err_std_pearson": M.pearson(np.abs(d - gt_depth)[mask], s[mask]),
                           "depth_err_std_spearman": M.spearman(np.abs(d - gt_depth)[mask], s[mask]),
                           "depth_coverage_68": float(np.mean(np.abs(d - gt_depth)[mask]
                                                              <= s[mask] * depth_interval_scale(calibration, ONE_SIGMA_LEVEL))),
                           "depth_coverage_95": float(np.mean(np.abs(d - gt_depth)[mask]
                                                              <= 1.959964 * s[mask] * depth_interval_scale(calibration, 0.95)))})
    return scores


def evaluate(model, dataset, out_dir: Path, *, views: list[int] | None = None, num_draws: int | None = None,
             seed: int = 0, progress: bool = True, write_products: bool = True, calibration=None) -> dict:
    """Render and score ``views`` (default: the test split). Returns the metrics dict it saves.

    ``calibration``: a ``calibration.RunCalibration`` applied to the depth std (raw kept as
    ``depth_std_raw``) and to the depth intervals' coverage."""
    views = list(dataset.test_indices) if views is None else list(views)
    device = next(model.parameters()).device
    generator = torch.Generator(device=device).manual_seed(seed)
    report = M.MetricReport()
    pooled_err, pooled_std = [], []
    for v in tqdm(views, desc="evaluate", disable=not progress):
        rays = generate_rays_for_view(dataset.cameras, v, dataset.near, dataset.far).to(device)
        maps = model.render_view(rays, num_draws=num_draws, generator=generator)
        products = apply_depth_calibration(camera_z_maps(maps), calibration)
        gt = dataset.images[v].numpy()
        gt_depth = dataset.depths[v].numpy() if getattr(dataset, "depths", None) is not None else None
        if write_products:
            write_view_products(Path(out_dir) / "views", f"view_{v:03d}", products, gt, gt_depth,
                                camera=view_camera_arrays(dataset, v))
        report.add(f"view_{v:03d}", **score_view(products, gt, gt_depth, calibration))
        if gt_depth is not None:
            mask = (gt_depth > 0) & (products["opacity"] > OPACITY_MASK)
            pooled_err.append(np.abs(products["depth_mean"] - gt_depth)[mask])
            pooled_std.append(products["depth_std"][mask])
    result = report.to_dict()
    result["num_draws"] = int(num_draws or model.render_settings.num_draws)
    result["opacity_mask"] = OPACITY_MASK
    result["depth_calibration"] = None if calibration is None else calibration.to_dict()
    if pooled_err:
        e, s = np.concatenate(pooled_err), np.concatenate(pooled_std)
        result["pooled_depth"] = {
            "num_pixels": int(e.size),
            "err_std_pearson": M.pearson(e, s).value if e.size > 1 else math.nan,
            "err_std_spearman": M.spearman(e, s).value if e.size > 1 else math.nan,
        }
    atomic_write_text(Path(out_dir) / "metrics.json", json.dumps(result, indent=2, default=float))
    return result
