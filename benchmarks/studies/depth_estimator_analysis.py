"""Analysis: which point estimate of a pixel's depth errs least at the capture points?

The depth map is each pixel's mean termination depth: the mean over the K trajectories of each
trajectory's expected termination distance D_k = sum_i w_ik t_i / A_k (``volume_rendering.
expected_depth``). Where a ray's mass splits between a near and a far surface (an occlusion edge, a
thin leaf in front of a wall), the mean lies between them, on no surface. The model's own
predictive distribution (``termination.TerminationMixture``: the mixture over the K trajectories of
each trajectory's termination distribution) has other point estimates that stay on a surface:

- ``mean``: today's depth map (the mixture's mean);
- ``mixture median``: F^-1(0.5) of the mixture (the absolute error's minimiser under the model);
- ``trajectory medians``: the mean over the K trajectories of each one's median termination depth;
- ``median of D_k``: the median over the K trajectories of their expected depths.

Scored as ``eval`` scores depth: the SCORE capture points the validation photos observe (the
capture split's held-out photos), rays through their pixels, opacity > ``OPACITY_MASK``; abs-rel =
mean |d - d*| / d*, and its median, per estimate, on the same render (the same K draws). Also the
share of points where the estimates differ by more than 5% of the depth (split rays) and the
abs-rel of each estimate on them. Decides nothing on its own: a candidate for the depth map's point
estimate would go through a study with a rule (its intervals, its ranking, the paper split).

    OMP_NUM_THREADS=1 python benchmarks/studies/depth_estimator_analysis.py \\
        --run fern=RUN --run flower=RUN --out benchmarks/results/depth_estimator_analysis
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from stochastic_fields.capture_points import SCORE, load_capture_points, rays_through_points
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.termination import TerminationMixture, render_termination
from stochastic_fields.trainer import load_trained_model
from stochastic_fields.view_maps import OPACITY_MASK
from stochastic_fields.volume_rendering import expected_depth

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import photo_points  # noqa: E402

ESTIMATES: tuple[str, ...] = ("mean", "mixture median", "trajectory medians", "median of D_k")
#: Relative difference between the mean and the mixture median above which a ray counts as split.
SPLIT_RELATIVE: float = 0.05


def trajectory_medians(mixture: TerminationMixture) -> np.ndarray:
    """[N, K]: each trajectory's median termination depth (camera z)."""
    K = mixture.weights.shape[1]
    half = torch.full((mixture.num_rays, 1), 0.5, dtype=mixture.t_starts.dtype)
    out = [TerminationMixture(mixture.t_starts, mixture.t_ends, mixture.weights[:, k:k + 1], mixture.far,
                              mixture.z_scale).quantiles(half)[:, 0] for k in range(K)]
    return torch.stack(out, 1).cpu().numpy()


def trajectory_depths(mixture: TerminationMixture) -> np.ndarray:
    """[N, K]: each trajectory's expected termination depth D_k (camera z; far where it hits nothing), as
    the renderer computes it (``volume_rendering.expected_depth`` at the interval midpoints)."""
    t = 0.5 * (mixture.t_starts + mixture.t_ends)
    d = expected_depth(mixture.weights, t[:, None, :], mixture.far[:, None])
    return (d * mixture.z_scale[:, None]).cpu().numpy()


def analyse(run_dir: Path, seed: int) -> dict:
    cfg, model, dataset = load_trained_model(run_dir)
    capture = load_capture_points(dataset)
    views = list(dataset.test_indices)
    sparse = photo_points(dataset, capture, views, SCORE)
    rays, gt = rays_through_points(dataset.cameras, dataset.near, dataset.far, sparse)
    with torch.no_grad():
        stats, mixture = render_termination(model, rays, generator=torch.Generator().manual_seed(seed))
    gt = np.asarray(gt, np.float64)
    keep = (stats["opacity"].cpu().numpy() > OPACITY_MASK) & np.isfinite(stats["depth_mean"].cpu().numpy())
    idx = torch.from_numpy(np.flatnonzero(keep))
    m = mixture.select(idx)
    gt = gt[keep]
    est = {"mean": stats["depth_mean"].cpu().numpy()[keep],
           "mixture median": m.quantiles(torch.full((m.num_rays, 1), 0.5, dtype=torch.float64))[:, 0].cpu().numpy(),
           "trajectory medians": trajectory_medians(m).mean(1),
           "median of D_k": np.median(trajectory_depths(m), 1)}
    split = np.abs(est["mixture median"] - est["mean"]) > SPLIT_RELATIVE * est["mean"]
    rows = {}
    for name in ESTIMATES:
        rel = np.abs(est[name] - gt) / gt
        rows[name] = {"abs_rel": float(rel.mean()), "median_rel": float(np.median(rel)),
                      "abs_rel_split": float(rel[split].mean()) if split.any() else None,
                      "abs_rel_rest": float(rel[~split].mean())}
    return {"run": str(run_dir), "points": int(keep.sum()), "split_share": float(split.mean()), "rows": rows,
            "num_draws": int(m.weights.shape[1])}


def markdown(results: dict, command: str) -> str:
    lines = ["# Which point estimate of a pixel's depth errs least (capture points of the validation photos)", "",
             "Command:", "", f"    {command}", "",
             f"Split rays: the mixture median differs from the mean by more than {SPLIT_RELATIVE:.0%} of the depth.", "",
             "| scene | estimate | abs-rel | median rel. error | abs-rel on split rays | abs-rel elsewhere |",
             "|---|---|---|---|---|---|"]
    for scene, r in results.items():
        for name in ESTIMATES:
            row = r["rows"][name]
            split = "-" if row["abs_rel_split"] is None else f"{row['abs_rel_split']:.4f}"
            lines.append(f"| {scene} ({r['points']} points, {100 * r['split_share']:.1f}% split) | {name} | "
                         f"{row['abs_rel']:.4f} | {row['median_rel']:.4f} | {split} | {row['abs_rel_rest']:.4f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="append", required=True, metavar="SCENE=RUN_DIR")
    ap.add_argument("--seed", type=int, default=0, help="Seed of the render's draws.")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    results = {}
    for item in args.run:
        scene, _, path = item.partition("=")
        results[scene] = analyse(Path(path), args.seed)
        print(json.dumps({scene: results[scene]["rows"]}, indent=1), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    command = "OMP_NUM_THREADS=1 python benchmarks/studies/depth_estimator_analysis.py " + \
        " ".join(f"--run {r}" for r in args.run) + f" --seed {args.seed} --out {args.out}"
    atomic_write_text(args.out / "analysis.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "analysis.md", markdown(results, command))


if __name__ == "__main__":
    main()
