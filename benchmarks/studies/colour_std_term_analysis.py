"""Analysis (decides nothing): the rendered colour std as a depth-std term.

Issue 36's open ranking target: on flower, S-NeRF's depth std ranks its depth errors per view worse than
the deep ensemble's (0.664 against 0.694 in the tables). The errors today's std misses are pixels rendered
on the wrong surface, where every trajectory stops at the same wrong depth (the research log's analyses).
Three cues from outside the K trajectories were measured (the free-space check, the parallax term, the
training photos' colour disagreement); the photo disagreement ranked the errors at only 0.05-0.11. This
measures a cue from inside the model that every render already has: the pixel's predictive colour std.
Where the model placed a surface wrongly, the colours it learnt there explain the training photos only
through its view-dependent colour and its noise, and a view between them may see that as colour
uncertainty; where the colour is certain, the surface the photos agree on is likely the right one. It
costs a render nothing (the colour variance is rendered beside the depth).

The term, fixed before any row was read:

* s_c(x) = mean over the three channels of the rendered predictive colour std at the pixel (the colour
  std image ``eval`` writes), rendered with the same rays, options and generator seed as the depth;
* the std term d s_c, with d the rendered camera-z depth, in sigma's units by one factor per run,
  median(sigma) / median(d s_c) over the calibration renders (no validation photo is read), placed in
  the depth map's occlusion-edge slot (``calibration.fit_edge_weight`` fits its weight gamma by the CRPS).

Two arms, each map fitted on the same calibration renders (today's map: free-space check, parallax term,
rho, s(p)) and scored on the validation photos' SCORE points cross-fitted, as ``eval`` scores them
(``laplace_term_analysis.arm_scores``): ``today`` and ``term`` (today's map with the colour term). Runs:
S-NeRF default at the paper split, the tables' budget, seeds 24 and 25 (no study's), fern and flower,
validation photos as ``tables_cap_study.validation_views``. Beside the arms: the term alone's per-view
Spearman against the depth errors at the validation photos' points.

Question and consequence (written before any row, photo_consistency_analysis.py's): the term is the next
study's candidate (a render-time map term, its weight fitted by ``calibrate``, a rule on fresh seeds of
both protocols) if, on the seed means of both scenes, the ``term`` arm keeps every level 50/68/90/95% within
5 points of nominal, its median 95% half-width and 95% interval score are no larger than ``today``'s, and
its per-view depth Spearman rises by at least 0.02 on flower and falls by at most 0.01 on fern. If the
fitted gamma is 0 on most runs, the calibration renders see no use for it and the term is no lever as placed.

    # SEED 24, 25; SCENE fern, flower (two trainings side by side, one thread each)
    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods snerf_default --seed SEED \\
        --no-timing --quiet --out runs/colterm/sSEED/today
    stochastic-fields eval --run runs/colterm/sSEED/today/SCENE/snerf_default --views VALIDATION --quiet \\
        --out runs/colterm/validation/sSEED/today/SCENE/snerf_default
    OMP_NUM_THREADS=1 python benchmarks/studies/colour_std_term_analysis.py --runs runs/colterm --seeds 24 25 \\
        --work runs/colterm/analysis --out benchmarks/results/colour_std_term_analysis
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))

import laplace_term_analysis as lta  # noqa: E402
from study_helpers import write_study  # noqa: E402

from stochastic_fields.capture_points import (block_keys, load_capture_points, rays_through_points,  # noqa: E402
                                              score_sparse_depth)
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402

SCENES = ("fern", "flower")


def colour_std_at_points(model, cameras, near, far, sparse: dict, *, seed: int = 0, options=None) -> np.ndarray:
    """s_c [N] (module doc) at the rays ``calibration.render_at_points`` renders for ``sparse`` (its
    arguments, its ray order, its generator seed: the same draws as the depth)."""
    found = rays_through_points(cameras, near, far, sparse)
    if found is None:
        return np.zeros(0)
    rays, gt = found
    device = next(model.parameters()).device
    with torch.no_grad():
        maps = model.render_view(rays.to(device).reshape(1, len(gt)), options,
                                 generator=torch.Generator(device=device).manual_seed(seed))
    return maps["colour_var"].double().cpu().clamp_min(0).sqrt().reshape(len(gt), -1).mean(-1).numpy()


def analyse(run: Path, evals: Path, views: list[int]) -> dict:
    """Both arms' scores of one run at ``views`` (rendered in ``evals/views``), the factor, and the term
    alone's per-view Spearman."""
    model, dataset, ref = lta.run_with_reference(run)
    capture = load_capture_points(dataset)
    renders, factor = lta.renders_with_term(  # the calibration renders, with the colour term in the edge slot
        model, dataset, ref, lambda m, cams, near, far, sparse, depth, seed=0, options=None: (
            np.asarray(depth, np.float64) * colour_std_at_points(m, cams, near, far, sparse, seed=seed, options=options)))
    val, alone = [], []
    for v, sd in score_sparse_depth(dataset, views).items():
        with np.load(evals / "views" / f"view_{v:03d}.npz") as f:
            products = {k: f[k] for k in f.files}
        rendered = products["depth_mean"][sd.rows, sd.cols].astype(np.float64)
        term = rendered * products["colour_std"][sd.rows, sd.cols].astype(np.float64).mean(-1)
        ok = np.isfinite(term)
        term = np.where(ok, term, 0.0)  # unrendered points are not scored
        val.append((sd, products, factor * term, block_keys(capture.xyz[sd.point_index], capture.xyz)))
        keep = ok & (rendered > 0) & (products["opacity"][sd.rows, sd.cols] > OPACITY_MASK)
        if keep.sum() > 10:
            alone.append(spearmanr(np.abs(rendered[keep] - sd.depth[keep]), term[keep]).correlation)
    arms = {arm: lta.arm_scores(arm, renders, factor * renders["edge"], val, capture, ref, str(run)) for arm in lta.TERM_ARMS}
    return {"arms": arms, "factor": factor, "term_alone_spearman_per_view": float(np.nanmean(alone)),
            "calibration_points": int(renders["abs_err"].size)}


def markdown(results: dict, seeds: list[int], runs: Path) -> str:
    lines = lta.term_arm_markdown(
        "The rendered colour std as a depth-std term",
        f"The `today` runs of `{runs}` (S-NeRF default, paper split, seeds {', '.join(map(str, seeds))}), scored on "
        "their validation photos as eval scores them (cross-fitted); both maps fitted on the same calibration renders, "
        "with the parallax term (today's map). Means over the seeds. Decides nothing.", results, seeds,
        {"term alone": lambda e: f"{e['term_alone_spearman_per_view']:.3f}", "factor": lambda e: f"{e['factor']:.3g}"},
        "the term alone's per-view Spearman and the factor that puts the term in sigma's units")
    return "\n".join(lines) + "\n\nCommand: the module docstring of `benchmarks/studies/colour_std_term_analysis.py`.\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/colterm"))
    ap.add_argument("--seeds", nargs="*", type=int, default=[24, 25])
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=SCENES)
    ap.add_argument("--work", type=Path, default=Path("runs/colterm/analysis"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/colour_std_term_analysis"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = lta.term_arm_results(args.runs, args.work, args.seeds, args.scenes, analyse)
    write_study(args.out, {"results": results, "seeds": args.seeds}, markdown(results, args.seeds, args.runs))


if __name__ == "__main__":
    main()
