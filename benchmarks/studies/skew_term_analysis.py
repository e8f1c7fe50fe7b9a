"""Analysis (decides nothing): the distance between a pixel's mean and median depth as a depth std term.

A pixel's predictive depth distribution is the mixture over its K trajectories of each one's termination
distribution along the ray (``termination.py``). Where the trajectories split their mass between a near
and a far surface the distribution is skewed and its mean lies between the surfaces, away from its median
(the analysis of the median as the depth map's point estimate, docs/studies.md). The skew
k = |mean - median| is what the total std sigma (the spread about the mean) does not single out. Arms,
each map fitted on the same calibration renders as ``calibrate`` fits today's (free-space check,
depth-proportional term, parallax term, level map; cross-fitted folds), the depth map the mean as today:

* ``today``: sigma;
* ``term``: k as the map's extra term (the edge term's slot: hypot(std, gamma k), gamma fitted by the
  CRPS, ``calibration.fit_edge_weight``);
* ``sum``: sqrt(sigma^2 + k^2) in place of sigma: the root mean square deviation about the median,
  E[(D - median)^2]^(1/2) (the law of total variance about another point), no weight fitted.

The median comes from a second render of the same rays with the same generator (the same K draws,
``render.depth_estimate`` "median"): at the calibration points, and over each validation photo with the
chunk seeds ``eval`` renders it with (``renderer.seeded_chunks(0, view)``), checked against the photo's
stored std. Scored on the validation photos' SCORE points as ``eval`` scores them (its stored maps:
``stochastic-fields eval --run RUN --views ... --out EVALS``, which writes EVALS/views).

    OMP_NUM_THREADS=1 python benchmarks/studies/skew_term_analysis.py \\
        --run capture_fern_s41 RUN EVALS --run capture_flower_s41 RUN EVALS ... \\
        --work runs/skew_term --out benchmarks/results/skew_term_analysis
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import cached, pooled_map_scores, write_study  # noqa: E402

import stochastic_fields.calibration as calibration  # noqa: E402
from stochastic_fields.calibration import depth_calibration_renders, depth_map_and_folds, render_at_points  # noqa: E402
from stochastic_fields.cameras import generate_rays_for_view  # noqa: E402
from stochastic_fields.capture_points import block_keys, load_capture_points, score_sparse_depth  # noqa: E402
from stochastic_fields.evaluation import depth_samples  # noqa: E402
from stochastic_fields.free_space import checked_std, load_training_depth  # noqa: E402
from stochastic_fields.renderer import seeded_chunks  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402

ARMS = ("today", "term", "sum")
LEVELS = ("50", "68", "90", "95", "99")


@contextlib.contextmanager
def median_depth_maps(model):
    """Within: the model renders the median as its depth map (the same draws; variances unchanged)."""
    saved = model.render_settings
    model.render_settings = dataclasses.replace(saved, depth_estimate="median")
    try:
        yield model
    finally:
        model.render_settings = saved


def skew_at_points(model, cams, near, far, sparse, depth, *, seed: int = 0, options=None) -> np.ndarray:
    """|mean - median| [N] at the rays ``render_at_points`` renders for the calibration (``depth``: their
    mean depths, camera z; the same generator seed, hence the same draws)."""
    with median_depth_maps(model):
        r = render_at_points(model, cams, near, far, sparse, generator=torch.Generator().manual_seed(seed),
                             options=options)
    return np.abs(np.asarray(depth) - r["depth_mean"])


def skew_map(model, dataset, view: int, products: dict) -> np.ndarray:
    """[H, W] |mean - median| over a validation photo, rendered with ``eval``'s chunk seeds."""
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far)
    with torch.no_grad(), median_depth_maps(model):
        maps = model.render_view(rays, generator=seeded_chunks(0, view))
    z = maps["z_scale"].double().numpy()
    median = maps["depth_mean"].double().numpy() * z
    std = np.sqrt(np.clip(maps["depth_var_total"].double().numpy(), 0, None)) * z
    stored = products["depth_std_raw"]
    if not np.allclose(std, stored, rtol=1e-4, atol=1e-6 * float(np.nanmax(stored))):
        raise RuntimeError(f"view {view}: the median render's std differs from eval's stored std: not the same draws")
    return np.abs(products["depth_mean"] - median)


def arm_scores(arm: str, renders: dict, val: list, capture, ref, where: str) -> dict:
    """The validation photos' scores under ``arm``'s map (module doc)."""
    r = {k: v for k, v in renders.items() if k != "edge"}
    if arm == "term":
        r["edge"] = renders["edge"]
    elif arm == "sum":
        raw = np.hypot(renders["std_raw"], renders["edge"])
        r.update(std_raw=raw, std=checked_std(raw, renders["violation"]))
    depth_map, folds = depth_map_and_folds(r, capture, relative_floor=True, where=where)
    pool = []
    for sd, products, skew, blocks in val:
        p = dict(products)
        if arm == "term":
            p["depth_edge"] = skew
        elif arm == "sum":
            p["depth_std_raw"] = np.hypot(products["depth_std_raw"], skew)
        pool.append(depth_samples(p, sparse=sd, blocks=blocks))
    return {**pooled_map_scores(depth_map, folds, ref, pool),
            "gamma": depth_map.edge_weight, "kappa": depth_map.parallax_weight, "rho": depth_map.relative_floor}


def analyse(run: Path, evals: Path, term_at_points=skew_at_points, term_map=skew_map) -> dict:
    """Every arm's scores of one run at the photos ``evals/views`` holds, with the term's renders' cost.
    The term k: ``term_at_points`` (as ``skew_at_points``) at the calibration renders' rays and
    ``term_map`` (as ``skew_map``) over each validation photo; the skew |mean - median| by default."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    ref = load_training_depth(run)
    capture = load_capture_points(dataset)
    views = sorted(int(f.stem.split("_")[1]) for f in (evals / "views").glob("view_*.npz"))
    original = calibration.edge_at_points
    calibration.edge_at_points = term_at_points
    try:  # the calibration renders, with the term at their rays in the edge slot
        renders = depth_calibration_renders(model, dataset, points="held-out", free_space=ref, edges=True,
                                            parallax=ref)
    finally:
        calibration.edge_at_points = original
    val, t0 = [], time.perf_counter()
    for v, sd in score_sparse_depth(dataset, views).items():
        with np.load(evals / "views" / f"view_{v:03d}.npz") as f:
            products = {k: f[k] for k in f.files}
        val.append((sd, products, term_map(model, dataset, v, products),
                    block_keys(capture.xyz[sd.point_index], capture.xyz)))
    term_render_s = (time.perf_counter() - t0) / max(len(val), 1)
    return {"arms": {arm: arm_scores(arm, renders, val, capture, ref, str(run)) for arm in ARMS},
            "median_render_s_per_view": term_render_s, "views": views,
            "skew_median_over_std": float(np.median(renders["edge"] / renders["std_raw"]))}


def arm_row(label: str, arm: str, rows: list[dict]) -> str:
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in rows]):.1f}" for n in LEVELS)
    return (f"| {label} | {arm} | {cov} | {100 * mean('halfwidth_median_95'):.1f}% | {mean('interval_score_95'):.3f} | "
            f"{mean('crps'):.4f} | {mean('spearman_per_view'):.3f} |")


def markdown(results: dict, *, title: str = "The distance between a pixel's mean and median depth as a depth std term",
             script: str = "skew_term_analysis.py", render: str = "median") -> str:
    """The study page: every run's arms, the seeds' means per group, each run's fitted weights and the cost
    of the term's ``render`` (titled ``title``, its command in ``script``'s docstring)."""
    head = ("| runs | arm | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
            "depth Spearman per view |")
    lines = [f"# {title}", "",
             "Each arm's map fitted on the same calibration renders (today's: free-space check, depth-proportional "
             "and parallax terms, level map), scored on the validation photos' SCORE points, cross-fitted. "
             "Decides nothing.", "", head, "|---|---|---|---|---|---|---|"]
    for label, r in results.items():
        lines += [arm_row(label, arm, [r["arms"][arm]]) for arm in ARMS]
    groups: dict[str, list[str]] = {}
    for label in results:
        groups.setdefault(re.sub(r"_s\d+$", "", label), []).append(label)
    if any(len(v) > 1 for v in groups.values()):
        lines += ["", "Means over the seeds of each group (LABEL_sSEED):", "", head, "|---|---|---|---|---|---|---|"]
        for group, labels in groups.items():
            if len(labels) > 1:
                lines += [arm_row(f"{group} ({len(labels)} seeds)", arm, [results[x]["arms"][arm] for x in labels])
                          for arm in ARMS]
    lines += ["", f"| run | gamma (term) | kappa today / term / sum | {render} render s / view | median k / sigma (calibration) |",
              "|---|---|---|---|---|"]
    for label, r in results.items():
        a = r["arms"]
        lines.append(f"| {label} | {a['term']['gamma']:.3g} | {a['today']['kappa']:.3g} / {a['term']['kappa']:.3g} / "
                     f"{a['sum']['kappa']:.3g} | {r['median_render_s_per_view']:.1f} | {r['skew_median_over_std']:.3f} |")
    return "\n".join(lines) + f"\n\nCommand: the module docstring of `benchmarks/studies/{script}`.\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", nargs=3, action="append", required=True, metavar=("LABEL", "RUN", "EVALS"))
    ap.add_argument("--work", type=Path, default=Path("runs/skew_term"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/skew_term_analysis"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = {}
    for label, run, evals in args.run:
        results[label] = cached(args.work / f"{label}.json", lambda: analyse(Path(run), Path(evals)))
        print(label, {arm: (round(100 * a["halfwidth_median_95"], 1), round(a["interval_score_95"], 3),
                            round(a["spearman_per_view"], 3)) for arm, a in results[label]["arms"].items()}, flush=True)
    write_study(args.out, {"results": results}, markdown(results))


if __name__ == "__main__":
    main()
