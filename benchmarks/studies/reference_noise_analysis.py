"""Is the narrow bands' shortfall the model's, or the structure-from-motion points'? (decides nothing)

The width analysis (``width_groups_analysis.py``) found the narrowest third of the depth bands the
least honest at the centre, most on the captures (fern's capture: 57% inside its 68% bands). Those
bands are a few percent of the depth wide, and the points that score them are triangulated, not
exact: a point's depth errs by about

    e_rel = r / (f sin theta)

of its depth, r its mean reprojection error (COLMAP, pixels of the model's camera), f that camera's
focal length in the same pixels and theta the widest angle between two rays of its track (the
photos that observed it) at the point. Where e_rel is not small against a band, the band misses
points whose surface it holds. This splits each third of the bands (sorted by the 95% half-width
over the depth, as eval sorts them) into the points with e_rel below and above the run's median and
reports their coverage: if the narrow bands' shortfall is the points', the well-triangulated half
holds and the other misses.

For each run the rays through its validation photos' SCORE points (paper split: ``tables_cap_study.
validation_views``; other splits: the run's held-out photos) are rendered with seed 0 and the run's
own map applied as render and eval apply it (``QuantileCalibration.calibrated_std`` with the
free-space violation), not cross-fitted (the map saw these points; optimistic alike for both halves).

    python benchmarks/studies/reference_noise_analysis.py --run fern:12=RUN ... \
        --out benchmarks/results/reference_noise_analysis
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from scipy.special import ndtri

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "benchmarks" / "studies"))

from stochastic_fields import metrics as M  # noqa: E402
from stochastic_fields.calibration import (load_run_calibration, render_at_points,  # noqa: E402
                                           training_view_terms_at_points)
from stochastic_fields.cameras import camera_centres  # noqa: E402
from stochastic_fields.capture_points import load_capture_points, score_sparse_depth  # noqa: E402
from stochastic_fields.data.colmap import read_cameras_binary  # noqa: E402
from stochastic_fields.sparse_depth import points_file  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402
from study_helpers import analyse_each, labelled_run_parser  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402

#: Levels whose coverage is reported (one sigma and 95%).
LEVELS: tuple[float, ...] = M.INTERVAL_SCORE_LEVELS


def triangulation_noise(capture, centres: np.ndarray, focal: float) -> np.ndarray:
    """[P] e_rel = r / (f sin theta) of every capture point (module doc): r its reprojection error,
    theta the widest angle between the rays from it (``capture.xyz``, the dataset's frame) to the
    centres [V, 3] of the views in its track (image id = view + 1; sin theta = 1 beyond 90 degrees);
    inf for a track of fewer than two views among ``centres``."""
    pts = capture.colmap
    out = np.full(len(capture.xyz), np.inf)
    for p in range(len(capture.xyz)):
        views = pts.track_image_ids[pts.track_offsets[p]:pts.track_offsets[p + 1]].astype(np.int64) - 1
        views = np.unique(views[(views >= 0) & (views < len(centres))])
        if views.size < 2:
            continue
        rays = centres[views] - capture.xyz[p]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        cos_min = float((rays @ rays.T).min())
        sin_theta = 1.0 if cos_min <= 0.0 else float(np.sqrt(max(1.0 - cos_min ** 2, 0.0)))
        out[p] = float(pts.error[p]) / (focal * max(sin_theta, 1e-12))
    return out


def analyse_run(run: Path, scene: str) -> dict:
    cfg, model, dataset = load_trained_model(run)
    calibration = load_run_calibration(run)
    capture = load_capture_points(dataset)
    if capture is None or capture.colmap is None:
        raise SystemExit(f"{run}: its scene has no COLMAP points with tracks")
    camera = next(iter(read_cameras_binary(points_file(dataset.root).with_name("cameras.bin")).values()))
    noise = triangulation_noise(capture, camera_centres(dataset.cameras).double().numpy(), float(camera.params[0]))
    views = validation_views(scene) if cfg.data.split == "paper" else list(dataset.test_indices)
    sparse = score_sparse_depth(dataset, views)
    r = render_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse,
                         generator=torch.Generator().manual_seed(0))
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_mean"]) & (r["depth_std"] > 0)
    m = calibration.depth
    rendered = np.where(keep, r["depth_mean"], r["gt"])
    # the map's free-space and parallax terms at the same rendered points, in one pass
    violation, parallax = training_view_terms_at_points(dataset.cameras, sparse, capture.xyz, r["gt"], rendered,
                                                        calibration.training_depth, free_space=m.free_space,
                                                        parallax=m.parallax_weight > 0.0)
    std = m.calibrated_std(r["depth_std"], violation, r["depth_mean"], parallax=parallax)
    index = np.concatenate([sparse[v].point_index for v in sparse if len(sparse[v])])
    gt, pred, std, e_rel = r["gt"][keep], r["depth_mean"][keep], std[keep], noise[index][keep]
    z = {p: float(ndtri((1.0 + p) / 2.0)) for p in LEVELS}
    half = {p: z[p] * std * m.relative_scale(p) for p in LEVELS}
    inside = {p: np.abs(gt - pred) <= half[p] for p in LEVELS}
    width = half[0.95] / gt
    thirds = np.array_split(np.argsort(width, kind="stable"), M.WIDTH_GROUPS)
    median_noise = float(np.median(e_rel[np.isfinite(e_rel)]))
    rows = {}
    for name, g in zip(("narrowest", "middle", "widest"), thirds):
        for half_name, sel in (("well triangulated", e_rel[g] <= median_noise), ("poorly triangulated", e_rel[g] > median_noise)):
            idx = g[sel]
            rows[f"{name} third, {half_name}"] = {
                "points": int(idx.size), "median e_rel": float(np.median(e_rel[idx])) if idx.size else float("nan"),
                "median 68% half-width / depth": float(np.median(half[0.682689492137086][idx] / gt[idx])) if idx.size else float("nan"),
                **{f"coverage_{M.level_name(p)}": float(inside[p][idx].mean()) if idx.size else float("nan") for p in LEVELS}}
    return {"views": views, "points": int(gt.size), "median e_rel": median_noise, "rows": rows}


def report(results: dict[str, dict]) -> str:
    lines = ["# Is the narrow bands' shortfall the model's or the SfM points'?", "",
             "Command: " + " ".join(["python benchmarks/studies/reference_noise_analysis.py"] + sys.argv[1:]), "",
             "Coverage (run's own map, not cross-fitted) per third of the 95% bands, split at the run's median "
             "triangulation noise e_rel = r / (f sin theta).", "",
             "| run | third, points | points | median e_rel | median 68% half-width / depth | cov 68 | cov 95 |",
             "|---|---|---|---|---|---|---|"]
    for label, res in results.items():
        for name, row in res["rows"].items():
            lines.append(f"| {label} | {name} | {row['points']} | {100 * row['median e_rel']:.2f}% | "
                         f"{100 * row['median 68% half-width / depth']:.2f}% | {100 * row['coverage_68']:.1f} | "
                         f"{100 * row['coverage_95']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return analyse_each(labelled_run_parser(__doc__), argv, lambda label, run: analyse_run(run, label.split(":")[0]),
                        report, lambda label, result: "done")

if __name__ == "__main__":
    raise SystemExit(main())
