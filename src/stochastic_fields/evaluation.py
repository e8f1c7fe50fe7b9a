"""The one evaluation loop: render views of a trained model, write their products, score them
(docs/definitions.md §6). The CLI (``render``, ``eval``, ``demo``), the benchmark tables, the
speed benchmark and the notebook all score through this module.

For each view: ``views/view_XXX.npz`` (float32 maps, camera-z metric depth, the camera: see
``view_maps``) and viewable PNGs for the first ``product_views`` views; per-view scores
(:func:`score_view`); and, pooled over every scored pixel of all views, the colour and depth
scores with their sparsification and calibration curves (``curves.npz``). ``metrics.json``
holds the per-view values, their means (undefined values counted, not averaged), the pooled
scores, the K each view was rendered with and the conventions behind every number.

Depth is scored against the dataset's depth maps (pixels with ground truth and opacity >
``OPACITY_MASK``) or, when ``sparse_depth`` is given, against projected SfM points (LLFF,
``sparse_depth``), the same way for every source. A model whose uncertainty map is constant
(the deterministic NeRF) has undefined correlations and AUSE: a ranking by a constant is
arbitrary.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import imageio.v3 as iio

from . import metrics as M
from .calibration import apply_calibration, cross_fitted_depth_quantiles, cross_fitted_depth_scores
from .distributed import map_sharded
from .io_utils import atomic_path, atomic_write_text
from .renderer import RenderOptions, seeded_chunks
from .sparse_depth import paired_depth_scores, sparse_depth_conventions
from .view_maps import OPACITY_MASK, camera_z_maps, draws_summary, view_camera_arrays
from .visualize import colourise, to_uint8_rgb
from .capture_points import block_keys, dense_depth_block_keys, dense_depth_score_mask, load_capture_points
from .plots import plot_interval_reliability
from .pose_check import view_groups_record

#: The per-view depth scores kept under ``depth/`` (and ``depth_raw/``) in metrics.json.
DEPTH_SCORE_KEYS: tuple[str, ...] = ("abs_rel", "rmse", "nll", "ause_rmse", "ause_rmse_normalised", "pearson",
                                     "spearman", "coverage_68", "coverage_95", "auce", "num_used")

#: The parts of S-NeRF's total depth variance (docs/definitions.md §3.4), by the view maps holding
#: their std: ``depth_parts/spearman_<part>`` ranks the depth errors by that part alone.
DEPTH_STD_PARTS: dict[str, str] = {"epistemic": "depth_std_epistemic", "spread": "depth_std_spread"}


# ----------------------------------------------------------------------------- files of a view
def _save_png(path: Path, rgb: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, rgb)


def write_view_products(out_dir: Path, name: str, products: dict[str, np.ndarray], gt_colour: np.ndarray | None,
                        gt_depth: np.ndarray | None, camera: dict[str, np.ndarray] | None = None) -> None:
    """``name.npz`` (the maps, plus ``camera``'s arrays: see ``view_maps.view_camera_arrays``) and PNGs."""
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
    for key in ("depth_free_space", "depth_edge", "depth_parallax"):  # the calibration's terms (calibrate)
        if key in products:
            _save_png(out_dir / f"{name}_{key}.png", colourise(products[key], cmap="magma", mask=mask, vmin=0.0)[0])
    if gt_colour is not None:
        _save_png(out_dir / f"{name}_gt_colour.png", to_uint8_rgb(gt_colour))
    if gt_depth is not None:
        _save_png(out_dir / f"{name}_gt_depth.png", colourise(gt_depth, cmap="turbo", mask=gt_depth > 0, vmin=lo, vmax=hi)[0])


# ----------------------------------------------------------------------------- scores of a view
@dataclasses.dataclass
class DepthSamples:
    """Rendered depth at the ground-truth samples of one view (camera z, scene units), [M] each."""

    gt: np.ndarray
    pred: np.ndarray
    std: np.ndarray
    std_raw: np.ndarray
    """The std before recalibration (equal to ``std`` without a calibration)."""
    parts: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    """The std of each part of the total variance (``DEPTH_STD_PARTS``) where the maps have it."""
    violation: np.ndarray | None = None
    """Each sample's free-space violation, where the products have it (``depth_free_space``)."""
    block: np.ndarray | None = None
    """Block of space of each sample's surface (``capture_points.block_keys``), where the run's
    calibration has cross-fitted folds that judge the samples by block."""
    edge: np.ndarray | None = None
    """Each sample's occlusion-edge size, where the products have it (``depth_edge``)."""
    parallax: np.ndarray | None = None
    """Each sample's parallax angle (degrees), where the products have it (``depth_parallax``)."""


def depth_samples(products: dict[str, np.ndarray], gt_depth: np.ndarray | None = None,
                  sparse=None, blocks: np.ndarray | None = None) -> DepthSamples | None:
    """The view's depth ground truth and the rendered depth there: the ``sparse`` points
    (``sparse_depth.SparseDepth``) or the pixels of ``gt_depth`` [H, W] (> 0 where a surface is),
    in both cases only where the rendered opacity exceeds ``OPACITY_MASK``; None without either.
    ``blocks``: the block key of each sparse point [M] or pixel [H, W], kept as ``DepthSamples.block``."""
    d, op, s = products["depth_mean"], products["opacity"], products["depth_std"]
    s_raw = products.get("depth_std_raw", s)
    e = products.get("depth_free_space")
    edge = products.get("depth_edge")
    parallax = products.get("depth_parallax")
    parts = {name: products[key] for name, key in DEPTH_STD_PARTS.items() if key in products}
    if sparse is not None:
        keep = sparse.sample(op) > OPACITY_MASK
        return DepthSamples(sparse.depth[keep], sparse.sample(d)[keep], sparse.sample(s)[keep],
                            sparse.sample(s_raw)[keep], {k: sparse.sample(v)[keep] for k, v in parts.items()},
                            None if e is None else sparse.sample(e)[keep],
                            None if blocks is None else np.asarray(blocks)[keep],
                            None if edge is None else sparse.sample(edge)[keep],
                            None if parallax is None else sparse.sample(parallax)[keep])
    if gt_depth is None:
        return None
    mask = (gt_depth > 0) & (op > OPACITY_MASK)
    return DepthSamples(gt_depth[mask], d[mask], s[mask], s_raw[mask], {k: v[mask] for k, v in parts.items()},
                        None if e is None else e[mask], None if blocks is None else np.asarray(blocks)[mask],
                        None if edge is None else edge[mask], None if parallax is None else parallax[mask])


def pool_depth_samples(pool: Sequence[DepthSamples]) -> DepthSamples:
    """Every view's depth samples as one, float64; the parts every view has."""
    def cat(arrays) -> np.ndarray:
        return np.concatenate(list(arrays)).astype(np.float64) if pool else np.zeros(0)

    names = sorted(set.intersection(*(set(p.parts) for p in pool))) if pool else []
    every = lambda key: pool and all(getattr(p, key) is not None for p in pool)  # noqa: E731
    return DepthSamples(*(cat(getattr(p, k) for p in pool) for k in ("gt", "pred", "std", "std_raw")),
                        {k: cat(p.parts[k] for p in pool) for k in names},
                        cat(p.violation for p in pool) if every("violation") else None,
                        np.concatenate([p.block for p in pool]).astype(np.int64) if every("block") else None,
                        cat(p.edge for p in pool) if every("edge") else None,
                        cat(p.parallax for p in pool) if every("parallax") else None)


def depth_part_rankings(samples: DepthSamples) -> dict[str, M.CorrelationResult]:
    """``depth_parts/spearman_<part>``: Spearman of |depth error| with each part's std alone
    (which part of the variance ranks the errors; the total's is ``depth/spearman``)."""
    err = np.abs(samples.pred - samples.gt)
    return {f"depth_parts/spearman_{name}": M.spearman(err, std, "|depth error|", f"depth std, {name}")
            for name, std in samples.parts.items()}


def interval_scale_of(calibration, quantity: str = "depth"):
    """The level-dependent interval multiplier of a recalibrated std (``quantity``: "depth" or
    "colour"), or None (Gaussian intervals: no calibration, or none of that quantity)."""
    cal = None if calibration is None else getattr(calibration, quantity)
    return None if cal is None else cal.relative_scale


#: The reliability diagram and sharpness histogram of the pooled depth intervals, in eval's folder.
INTERVAL_PLOT = "depth_intervals.png"


#: The interval scores that a calibration's cross-fitted folds replace (``cross_fitted_interval_scores``).
CROSS_FITTED_KEYS: tuple[str, ...] = ("nll", "coverage_68", "coverage_95", "auce", "calibration")


def calibrated_depth_scores(samples: DepthSamples, calibration=None) -> dict[str, Any]:
    """``sparse_depth.paired_depth_scores`` of the calibrated std, with the interval scores
    (``CROSS_FITTED_KEYS``) cross-fitted where the calibration has folds and the samples their
    blocks (``calibration.cross_fitted_depth_scores``); ranking and error scores are the run's map's."""
    scale = interval_scale_of(calibration)
    scores = paired_depth_scores(samples.gt, samples.pred, samples.std, interval_scale=scale)
    quantiles = lambda t: M.gaussian_quantiles(samples.pred, samples.std, t, scale)  # noqa: E731
    folds = None if calibration is None else calibration.depth_folds
    if folds is not None and samples.block is not None and samples.gt.size >= 2:
        fold = folds.fold_of(samples.block)
        scores.update(cross_fitted_depth_scores(samples.gt, samples.pred, samples.std_raw, fold, folds,
                                                violation=samples.violation, edge=samples.edge,
                                                parallax=samples.parallax))
        quantiles = cross_fitted_depth_quantiles(samples.pred, samples.std_raw, fold, folds,
                                                 violation=samples.violation, edge=samples.edge,
                                                 parallax=samples.parallax)
    scores["intervals"] = M.interval_sharpness(samples.gt, quantiles) if samples.gt.size >= 2 else None
    return scores


def score_depth(samples: DepthSamples, calibration=None, scores: dict | None = None) -> dict[str, Any]:
    """``depth/<score>`` (and, with a calibration, the raw std's ``depth_raw/<score>``) of
    ``calibrated_depth_scores``, ``DEPTH_SCORE_KEYS`` only. ``scores``: those scores if already
    computed."""
    if scores is None:
        scores = calibrated_depth_scores(samples, calibration)
    out = {f"depth/{k}": scores[k] for k in DEPTH_SCORE_KEYS}
    out.update({f"depth_intervals/{k}": v for k, v in interval_summary(scores.get("intervals")).items()})
    out.update(depth_part_rankings(samples))
    if calibration is not None and calibration.depth is not None:
        raw = paired_depth_scores(samples.gt, samples.pred, samples.std_raw)
        out.update({f"depth_raw/{k}": raw[k] for k in DEPTH_SCORE_KEYS})
    return out


@dataclasses.dataclass
class ColourTerms:
    """Per-pixel colour quantities of one view, computed once: its own scores and the scores
    pooled over views (rank correlations, sparsification, NLL, calibration) all derive from them."""

    mse: np.ndarray
    """[P] mean_c (gt - mean)^2 (``metrics.pixel_mse``), float64."""
    err_mae: np.ndarray
    """[P] mean_c |gt - mean| (``metrics.pixel_errors``, 'mae'), float64."""
    unc: np.ndarray
    """[P] mean_c var (``metrics.pixel_uncertainty``), float64."""
    nll: np.ndarray
    """[P] Gaussian NLL per pixel, averaged over channels (``metrics.gaussian_nll_per_pixel``)."""
    calibration: M.CalibrationResult
    """Coverage of the central intervals, pooled over pixels and channels (``metrics.calibration_curve``)."""

    @property
    def err_rmse(self) -> np.ndarray:
        """[P] sqrt(mse) (``metrics.pixel_errors``, 'rmse')."""
        return np.sqrt(self.mse)

    @staticmethod
    def of(products: dict[str, np.ndarray], gt_colour: np.ndarray, interval_scale=None) -> "ColourTerms":
        """``interval_scale``: the recalibrated colour std's level multiplier (``interval_scale_of``), or None."""
        mean = products["colour_mean"].astype(np.float64)
        var = products["colour_std"].astype(np.float64) ** 2
        return ColourTerms(mse=M.pixel_mse(gt_colour, mean).numpy().reshape(-1),
                           err_mae=M.pixel_errors(gt_colour, mean, "mae").numpy().reshape(-1),
                           unc=M.pixel_uncertainty(var).numpy().reshape(-1),
                           nll=M.gaussian_nll(gt_colour, mean, var, reduce=False).numpy().reshape(-1),
                           calibration=M.calibration_curve(gt_colour, mean, np.sqrt(var), interval_scale=interval_scale))


def ranking_scores(mse: np.ndarray, err_mae: np.ndarray, unc: np.ndarray) -> dict[str, Any]:
    """How the uncertainty ranks the errors of pixels [P]: Pearson/Spearman of MSE vs variance
    (CorrelationResult) and the RMSE and MAE sparsification curves (SparsificationResult, None for
    a constant uncertainty, whose ranking is arbitrary)."""
    constant = unc.size == 0 or bool(np.ptp(unc) == 0)
    return {"pearson": M.pearson(mse, unc, "error", "uncertainty"),
            "spearman": M.spearman(mse, unc, "error", "uncertainty"),
            "rmse": None if constant else M.sparsification_curve(np.sqrt(mse), unc, metric="rmse"),
            "mae": None if constant else M.sparsification_curve(err_mae, unc, metric="mae")}


def _ause_scores(ranking: dict[str, Any]) -> dict[str, float]:
    return {f"ause_{metric}{suffix}": (math.nan if ranking[metric] is None else getattr(ranking[metric], field))
            for metric in ("rmse", "mae") for suffix, field in (("", "ause"), ("_normalised", "ause_normalised"),
                                                                ("_max_normalised", "ause_max_normalised"))}


def score_colour(products: dict[str, np.ndarray], gt_colour: np.ndarray,
                 terms: ColourTerms | None = None) -> dict[str, Any]:
    """Colour scores of one view: PSNR, SSIM, NLL (variance floor), Pearson/Spearman of per-pixel
    MSE vs variance, AUSE (RMSE, MAE; raw and normalised), AUCE and signed calibration gap. A
    constant uncertainty map has NaN AUSEs (and undefined correlations). ``terms``: the view's
    ``ColourTerms`` if already computed."""
    terms = terms or ColourTerms.of(products, gt_colour)
    mean = products["colour_mean"].astype(np.float64)
    ranking = ranking_scores(terms.mse, terms.err_mae, terms.unc)
    return {"psnr": M.psnr(mean, gt_colour), "ssim": M.ssim(mean, gt_colour), "nll": float(terms.nll.mean()),
            "pearson_mse_var": ranking["pearson"], "spearman_mse_var": ranking["spearman"], **_ause_scores(ranking),
            "auce_colour": terms.calibration.auce, "calibration_gap_colour": terms.calibration.signed_gap}


def score_view(products: dict[str, np.ndarray], gt_colour: np.ndarray, gt_depth: np.ndarray | None = None,
               calibration=None, sparse=None) -> dict[str, Any]:
    """:func:`score_colour` plus :func:`score_depth` where the view has depth ground truth
    (``gt_depth`` [H, W] or ``sparse`` points)."""
    scores = score_colour(products, gt_colour, ColourTerms.of(products, gt_colour, interval_scale_of(calibration, "colour")))
    samples = depth_samples(products, gt_depth, sparse)
    if samples is not None:
        scores.update(score_depth(samples, calibration))
    return scores


# ----------------------------------------------------------------------------- the loop
def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA) so that a wall-clock time covers it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _pack(prefix: str, result) -> dict[str, np.ndarray]:
    return {f"{prefix}.{f.name}": np.asarray(getattr(result, f.name)) for f in dataclasses.fields(result)}


def _plain_scores(scores: dict) -> dict[str, Any]:
    """Depth scores as JSON-ready numbers (correlations by value, no curves; the interval scores under
    ``depth_intervals``)."""
    return {k: (v.value if isinstance(v, M.CorrelationResult) else v)
            for k, v in scores.items() if k not in ("calibration", "sparsification", "intervals")}


#: The scalar interval scores (``metrics.interval_sharpness``) each view and the pool report.
INTERVAL_KEYS: tuple[str, ...] = tuple(
    [f"coverage_{M.level_name(p)}" for p in M.INTERVAL_LEVELS]
    + [f"halfwidth_median_{M.level_name(p)}" for p in M.INTERVAL_LEVELS]
    + [f"halfwidth_p90_{M.level_name(p)}" for p in M.INTERVAL_LEVELS]
    + [f"interval_score_{M.level_name(p)}" for p in M.INTERVAL_SCORE_LEVELS] + ["crps"]
    + [f"coverage_{M.level_name(p)}_{g}" for g in M.WIDTH_GROUP_NAMES for p in M.INTERVAL_SCORE_LEVELS]
    + [M.NARROWEST_WIDTH_KEY])


def interval_summary(intervals: dict | None) -> dict[str, float]:
    """The ``INTERVAL_KEYS`` of ``metrics.interval_sharpness``' output (NaN each when it is None)."""
    return {k: (math.nan if intervals is None else float(intervals[k])) for k in INTERVAL_KEYS}


#: What eval says when the run's calibration was fitted on the SCORE points too without cross-fitted folds.
SCORE_POINTS_SEEN = ("the depth calibration was fitted on the SCORE capture points too and has no cross-fitted "
                     "folds: depth coverage, AUCE and NLL are not an independent test; refit with "
                     "`stochastic-fields calibrate` to score")
#: How the interval scores of a map fitted on every held-out point are made independent.
CROSS_FITTED_SCORES = ("depth coverage, AUCE and NLL cross-fitted: the map was fitted on every held-out capture "
                       "point (CALIBRATE and SCORE); each scored depth is judged by the fold map fitted without "
                       "its SCORE block's fold (calibration.json depth_folds); ranking scores use the run's map")


#: How dense (exact) depth is scored when the scene has capture points (capture_points.dense_depth_score_mask).
DENSE_DEPTH_SCORED = ("exact camera-z depth at the test pixels whose surface point lies in a SCORE block of the "
                      "capture points' spatial split (the FIT blocks trained the depth likelihood, the CALIBRATE "
                      "blocks fitted the recalibration)")


def _conventions(depth_source: str | None, calibration, *, dense_scored_blocks: bool = False) -> dict[str, str]:
    out = {"opacity_mask": f"depth is scored and drawn where the rendered opacity > {OPACITY_MASK}",
           "constant_uncertainty": "a constant uncertainty map (deterministic NeRF) has undefined correlations and "
                                   "AUSE; its NLL uses the variance floor",
           "num_draws": "K actually rendered per view (adaptive K: mean over pixels, with min/max)"}
    if depth_source == "sparse":
        out.update(sparse_depth_conventions())
    if depth_source == "dense":
        out["dense_depth_scored"] = (DENSE_DEPTH_SCORED if dense_scored_blocks
                                     else "exact camera-z depth at every test pixel with a surface (no capture points)")
    if calibration is not None and calibration.colour is not None:
        out["colour_calibration"] = ("colour_std recalibrated on pixels held out from training (calibration.json), "
                                     "intervals at level p scaled by s(p)/s(0.683)")
    if calibration is not None and calibration.depth is not None:
        out["depth_calibration"] = ("depth_std recalibrated (calibration.json), intervals at level p scaled by "
                                    "s(p)/s(0.683); raw scores under depth_raw/")
        if depth_source is not None and not calibration.independent_depth_scores:
            out["depth_calibration_independence"] = SCORE_POINTS_SEEN
        elif depth_source is not None and calibration.depth_folds is not None:
            out["depth_calibration_independence"] = CROSS_FITTED_SCORES
    return out


def _evaluate_view(model, dataset, v: int, out_dir: Path, *, options: RenderOptions, seed: int,
                   device: torch.device, write_products: bool, sparse, calibration,
                   dense_scored: np.ndarray | None = None, blocks: np.ndarray | None = None) -> dict[str, Any]:
    """Render, write and score dataset view ``v``: its scores
    and what the pooled scores need (its ``ColourTerms`` and depth samples), CPU/numpy only (sent
    between ranks as is). ``dense_scored`` [H, W]: the pixels of the exact depth map that score
    depth (None: every pixel with a surface); ``blocks``: the block key of each ``sparse`` point
    [M] or pixel [H, W] (``depth_samples``)."""
    gt_depths = getattr(dataset, "depths", None)
    rays = dataset.rays(v).to(device)
    synchronize(device)
    t0 = time.perf_counter()
    maps = model.render_view(rays, options, generator=seeded_chunks(seed, v, device))
    synchronize(device)
    render_s = time.perf_counter() - t0
    camera = view_camera_arrays(dataset, v)
    products = apply_calibration(camera_z_maps(maps), calibration,
                                 camera=(camera["intrinsics"], camera["world_to_camera"]))
    gt = dataset.images[v].numpy()
    gt_depth = gt_depths[v].numpy() if gt_depths is not None else None
    if write_products:
        write_view_products(out_dir / "views", f"view_{v:03d}", products, gt, gt_depth,
                            camera=camera)
    if gt_depth is not None and dense_scored is not None:  # score the SCORE blocks' surfaces only
        gt_depth = np.where(dense_scored, gt_depth, 0.0)
    colour = ColourTerms.of(products, gt, interval_scale_of(calibration, "colour"))
    scores = score_colour(products, gt, colour)
    if "colour_std_raw" in products:  # the raw std's calibration, beside the recalibrated one
        raw = ColourTerms.of({"colour_mean": products["colour_mean"], "colour_std": products["colour_std_raw"]}, gt)
        scores.update(nll_raw=float(raw.nll.mean()), auce_colour_raw=raw.calibration.auce)
    samples = depth_samples(products, gt_depth, sparse, blocks)
    if samples is not None:
        scores.update(score_depth(samples, calibration))
    scores.update(render_s=render_s, **draws_summary(maps["num_draws"]))
    return {"view": v, "scores": scores, "render_s": render_s, "depth": samples,
            "draws": maps["num_draws"].reshape(-1).cpu(), "colour": colour}


def evaluate(model, dataset, out_dir: Path, *, views: Sequence[int] | None = None,
             options: RenderOptions | None = None, seed: int = 0, sparse_depth: dict | None = None,
             product_views: int | None = None, calibration=None, conventions: dict[str, str] | None = None,
             progress: bool = True, distributed=None) -> dict:
    """Render and score ``views`` (default: the test split) of a trained model; returns the
    metrics dict it writes to ``out_dir/metrics.json`` (and ``curves.npz``).

    Args:
        options: this evaluation's render options (default: the model's).
        seed: seed of the rendering noise; each chunk of each view draws from its own generator
            (``renderer.seeded_chunks(seed, view)``), so a view's maps do not depend on the others
            and equal the notebook's for the same options and seed.
        sparse_depth: {view: ``sparse_depth.SparseDepth``}: score depth at these points instead of
            the dataset's depth maps.
        product_views: write the npz/PNG products of the first N views (default: all; 0: none).
        calibration: a ``calibration.RunCalibration`` applied to the depth std (raw kept as
            ``depth_std_raw``) and to the intervals.
        conventions: extra lines for ``metrics.json``'s conventions (what the caller's numbers mean).
        distributed: a ``distributed.DistContext`` (one rank of a torchrun launch): rank r of W
            renders and scores positions r, r + W, ... of ``views`` and writes their per-view files
            itself (``out_dir`` must be one folder for all ranks: a shared file system across
            hosts); the per-view results are gathered to rank 0, which pools them in the order of
            ``views`` and writes metrics.json and curves.npz, equal to one process's (but for
            the render_s timings). Every rank returns rank 0's result. A rank that fails makes the
            others raise ``DistributedError`` and no metrics.json is written.
    """
    out_dir = Path(out_dir)
    views = list(dataset.test_indices) if views is None else [int(v) for v in views]
    product_views = len(views) if product_views is None else int(product_views)
    options = options or model.default_render_options()
    device = next(model.parameters()).device
    gt_depths = getattr(dataset, "depths", None)
    depth_source = "sparse" if sparse_depth is not None else ("dense" if gt_depths is not None else None)
    capture = load_capture_points(dataset) if depth_source == "dense" else None
    folds = None if depth_source is None or calibration is None else calibration.depth_folds
    if folds is not None and capture is None:
        capture = load_capture_points(dataset)
    if depth_source is not None and calibration is not None and not calibration.independent_depth_scores:
        warnings.warn(f"{SCORE_POINTS_SEEN} (evaluating into {out_dir})", stacklevel=2)

    def blocks_of(v: int) -> np.ndarray | None:
        """The block keys ``_evaluate_view`` judges view ``v``'s depths by (cross-fitted folds only)."""
        if folds is None or capture is None:
            return None
        if depth_source == "dense":
            return dense_depth_block_keys(dataset, capture, v)
        return block_keys(capture.xyz[sparse_depth[v].point_index], capture.xyz)

    ctx = distributed
    records = map_sharded(lambda i: _evaluate_view(model, dataset, views[i], out_dir, options=options, seed=seed,
                                                   device=device, write_products=i < product_views,
                                                   calibration=calibration,
                                                   sparse=None if sparse_depth is None else sparse_depth[views[i]],
                                                   dense_scored=None if depth_source != "dense" or capture is None
                                                   else dense_depth_score_mask(dataset, capture, views[i]),
                                                   blocks=blocks_of(views[i])),
                          len(views), ctx, what="evaluation's per-view results to rank 0", desc="evaluate",
                          progress=progress)
    if records is None:  # not rank 0: rank 0 pools and writes; its result (or its failure) ends every rank's call
        return ctx.broadcast_object(None, what="evaluation's metrics from rank 0")
    report = M.MetricReport()
    report.conventions.update(_conventions(depth_source, calibration,
                                           dense_scored_blocks=depth_source == "dense" and capture is not None))
    report.conventions.update(conventions or {})
    depth_pool: list[DepthSamples] = []
    for rec in records:  # in the order of ``views``, whichever rank rendered them
        if rec["depth"] is not None:
            depth_pool.append(rec["depth"])
        report.add(f"view_{rec['view']:03d}", **rec["scores"])
    render_s = [rec["render_s"] for rec in records]

    result = report.to_dict()
    result.update(draws_summary(torch.cat([rec["draws"] for rec in records])) if records
                  else {"num_draws": options.num_draws})
    result["render_options"] = {k: v for k, v in dataclasses.asdict(options).items() if k not in ("progress",)}
    result["opacity_mask"] = OPACITY_MASK
    result["depth_source"] = depth_source
    result["depth_calibration"] = None if calibration is None else calibration.to_dict()
    curves: dict[str, np.ndarray] = {}
    # pooled colour scores: every evaluated pixel at once
    colour = [rec["colour"] for rec in records]
    mse, err_mae, unc, nll = (np.concatenate([getattr(c, k) for c in colour]) if colour else np.zeros(0)
                              for k in ("mse", "err_mae", "unc", "nll"))
    ranking = ranking_scores(mse, err_mae, unc)
    pooled_out: dict[str, Any] = {
        "num_pixels": int(mse.size), "nll": float(nll.sum()) / max(1, nll.size),
        "pearson_mse_var": ranking["pearson"].value, "spearman_mse_var": ranking["spearman"].value,
        "correlation_undefined_reason": ranking["pearson"].reason, **_ause_scores(ranking),
    }
    levels = M.DEFAULT_CALIBRATION_LEVELS
    counts = sum((c.calibration.coverage * c.calibration.num_values for c in colour), np.zeros_like(levels))
    num_values = sum(c.calibration.num_values for c in colour)
    coverage = counts / max(1, num_values)
    colour_cal = M.CalibrationResult(levels=levels, coverage=coverage, auce=float(np.abs(coverage - levels).mean()),
                                     signed_gap=float((coverage - levels).mean()), num_values=int(num_values))
    pooled_out.update(auce_colour=colour_cal.auce, calibration_gap_colour=colour_cal.signed_gap)
    curves.update(_pack("colour_calibration", colour_cal))
    for metric in ("rmse", "mae"):
        if ranking[metric] is not None:
            curves.update(_pack(f"colour_sparsification_{metric}", ranking[metric]))
    if depth_source is not None:
        pooled = pool_depth_samples(depth_pool)
        ds = calibrated_depth_scores(pooled, calibration)
        pooled_out["depth"] = _plain_scores(ds)
        pooled_out["depth_intervals"] = interval_summary(ds.get("intervals"))
        if ds.get("intervals") is not None:
            iv = ds["intervals"]
            curves.update({"depth_intervals.levels": np.asarray(iv["levels"]),
                           "depth_intervals.coverage": np.asarray(iv["coverage"]),
                           "depth_intervals.halfwidth": np.asarray(iv["halfwidth"], dtype=np.float32)})
            plot_interval_reliability(out_dir / INTERVAL_PLOT, iv, title=f"depth intervals ({iv['num_values']} "
                                      f"{'points' if depth_source == 'sparse' else 'pixels'})")
        pooled_out["depth_parts"] = {k.split("/", 1)[1]: v.value for k, v in depth_part_rankings(pooled).items()}
        if calibration is not None and calibration.depth is not None:
            pooled_out["depth_raw"] = _plain_scores(paired_depth_scores(pooled.gt, pooled.pred, pooled.std_raw))
        if ds["calibration"] is not None:
            curves.update(_pack("depth_calibration", ds["calibration"]))
        if ds["sparsification"] is not None:
            curves.update(_pack("depth_sparsification_rmse", ds["sparsification"]))
    result["pooled"] = pooled_out
    # photos rendered far worse than the others of their group: poses to look at (pose_check)
    result["pose_check"] = view_groups_record(dataset, views, result["per_view"].get("psnr", []))
    result["render_s_per_view"] = float(np.mean(render_s)) if render_s else math.nan
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "curves.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **curves)
    atomic_write_text(out_dir / "metrics.json", json.dumps(result, indent=2, default=float))
    if ctx is not None:
        ctx.broadcast_object(result, what="evaluation's metrics from rank 0")
    return result
