"""Analysis (decides nothing): a depth std term from how many training views render the same surface.

The visibility analysis (``visibility_count_analysis.py``) found that the paper split's validation points no
training view's COLMAP track holds err twice as much and under-cover. A render cannot read COLMAP tracks, but
it can ask the training views' rendered depths (``RUN/training_depth.npz``, the free-space check's) whether
they put a surface where the rendered point lies: ``free_space.agreeing_views`` counts the views j with
|z_j(X) - D_j(u)| <= tau z_j(X). This measures, on study 37's today runs (paper split, seeds 12-14) and their
validation photos, (1) the errors by that count on the calibration views and on the validation photos, and
(2) the std term it suggests,

    depth_std = s(0.683) sqrt(sigma^2 + (beta e)^2 + (gamma d (1 - a / T))^2 + (rho d)^2),

a the agreeing views of T, gamma fitted with rho by the map's mean CRPS / depth (through the map's
extra-term slot, ``calibration.fit_edge_weight``'s grid), for tau 2% and 5%, beside the calibration views
rendering the points both views of their pair observed (today) or either (study 38's option). Scored as eval
scores the validation photos: the run's map refitted from the same renders, cross-fitted over the SCORE
blocks. Explored on these runs before this script was written: nothing here chooses a default. Command::

    # inputs: study 37's runs and their validation photos' eval maps (visibility_count_analysis.py's)
    python benchmarks/studies/agreement_term_analysis.py --runs runs/colour_capacity_paper \\
        --evals runs/visibility_analysis --work runs/agreement_analysis \\
        --out benchmarks/results/agreement_term_analysis [--scenes fern] [--seeds 12]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import cached, write_study  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402
from visibility_count_analysis import scores  # noqa: E402

from stochastic_fields.calibration import (RunCalibration, calibration_views, depth_calibration_renders,  # noqa: E402
                                           depth_map_and_folds)
from stochastic_fields.cameras import camera_to_world, invert_rigid  # noqa: E402
from stochastic_fields.capture_points import (backproject_pixels, block_keys, load_capture_points,  # noqa: E402
                                              score_sparse_depth)
from stochastic_fields.evaluation import depth_samples  # noqa: E402
from stochastic_fields.free_space import agreeing_views, load_training_depth, rendered_points  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402

SEEDS = (12, 13, 14)
SCENES = ("fern", "flower")
ARMS = ("both", "either")
#: Relative tolerances tau of the agreement; the first groups the diagnostic table.
TOLERANCES = (0.02, 0.05)
LEVELS = ("50", "68", "90", "95")


def disagreement(points: np.ndarray, depth: np.ndarray, ref) -> dict[str, np.ndarray]:
    """{tau: d (1 - a / T) [N]} and {"count": a [N] at the first tau}: the term's size at each point."""
    out = {}
    for tau in TOLERANCES:
        agree, _ = agreeing_views(points, ref, tolerance=tau)
        out[str(tau)] = depth * (1.0 - agree / len(ref.views))
        if tau == TOLERANCES[0]:
            out["count"] = agree
    return out


def validation_points(scene: str, evals: Path, dataset, capture, ref) -> list[tuple]:
    """Per validation photo of ``scene``: (SparseDepth, products, disagreement at its points, block keys)."""
    out = []
    sparse = score_sparse_depth(dataset, validation_views(scene))
    for v, sd in sparse.items():
        with np.load(evals / "views" / f"view_{v:03d}.npz") as f:
            products = {k: f[k] for k in f.files}
        d = sd.sample(products["depth_mean"])
        X = backproject_pixels(torch.as_tensor(products["intrinsics"]),
                               invert_rigid(torch.as_tensor(products["world_to_camera"])),
                               torch.as_tensor(sd.rows), torch.as_tensor(sd.cols), torch.as_tensor(d)).numpy()
        out.append((sd, products, disagreement(X, d, ref), block_keys(capture.xyz[sd.point_index], capture.xyz)))
    return out


def by_count(count: np.ndarray, rel: np.ndarray, z: np.ndarray, views: int) -> list[dict]:
    """Share, mean abs-rel and median |err| / sigma of the points per agreement count 0..views."""
    return [{"count": g, "share": float(np.mean(count == g)), "abs_rel": float(np.mean(rel[count == g])),
             "median_abs_z": float(np.median(z[count == g])), "points": int(np.sum(count == g))}
            for g in range(views + 1) if np.any(count == g)]


def analyse(scene: str, run: Path, evals: Path, arm: str) -> dict:
    """One run of ``scene`` and arm: the scores of each term (none, each tau) and the errors by agreement count."""
    _, model, dataset = load_trained_model(run, device="cpu")
    ref = load_training_depth(run)
    if ref is None:
        raise SystemExit(f"{run}: no training_depth.npz (calibrate the run with the free-space check first)")
    capture = load_capture_points(dataset)
    renders = depth_calibration_renders(model, dataset, points="held-out", free_space=ref, pair_points=arm)
    cams = calibration_views(dataset)[0]
    centres = camera_to_world(cams).double()[:, :3, 3].numpy()[renders["view"]]
    X = rendered_points(centres, capture.xyz[renders["index"]], renders["depth"] + renders["err"], renders["depth"])
    calib_terms = disagreement(X, renders["depth"], ref)
    val = validation_points(scene, evals, dataset, capture, ref)
    out = {"terms": {}}
    for term in ("none",) + tuple(str(t) for t in TOLERANCES):
        r = dict(renders) if term == "none" else {**renders, "edge": calib_terms[term]}
        depth_map, folds = depth_map_and_folds(r, capture, relative_floor=True, where=str(run))
        cal = RunCalibration(depth=depth_map, points="held-out", training_depth=ref, depth_folds=folds)
        pool = []
        for sd, products, terms, blocks in val:
            p = dict(products)
            if term != "none":
                p["depth_edge"] = np.zeros_like(products["depth_mean"])
                p["depth_edge"][sd.rows, sd.cols] = terms[term]
            pool.append(depth_samples(p, sparse=sd, blocks=blocks))
        out["terms"][term] = {**scores(pool, cal), "beta": depth_map.free_space_weight if depth_map.free_space else 0.0,
                              "rho": depth_map.relative_floor, "gamma": depth_map.edge_weight}
    keep = [sd.sample(p["opacity"]) > OPACITY_MASK for sd, p, _, _ in val]
    vd = [sd.sample(p["depth_mean"]) for sd, p, _, _ in val]
    out["calibration_by_count"] = by_count(calib_terms["count"], renders["abs_err"] / renders["depth"],
                                           renders["abs_err"] / renders["std_raw"], len(ref.views))
    out["validation_by_count"] = by_count(
        np.concatenate([t["count"][k] for (_, _, t, _), k in zip(val, keep)]),
        np.concatenate([(np.abs(sd.depth - d) / d)[k] for (sd, _, _, _), d, k in zip(val, vd, keep)]),
        np.concatenate([(np.abs(sd.depth - d) / sd.sample(p["depth_std_raw"]))[k]
                        for (sd, p, _, _), d, k in zip(val, vd, keep)]), len(ref.views))
    return out


def markdown(results: dict, seeds: list[int]) -> str:
    lines = ["# A depth std term from how many training views render the same surface", "",
             f"Study 37's today runs (paper split, seeds {', '.join(map(str, seeds))}), scored on their validation "
             "photos as eval scores them (cross-fitted). Term: gamma d (1 - a / T), a of the T training views "
             "agreeing within tau. Means over the seeds. Explored on these runs before the script was written: "
             "decides nothing.", "",
             "| scene | calibration points | term | cov 50 / 68 / 90 / 95 | median 95% half-width | IS95 / depth | "
             "CRPS / depth | gamma (seeds) |", "|---|---|---|---|---|---|---|---|"]
    for scene, arms in results.items():
        for arm, terms in arms.items():
            for term, rows in terms.items():
                mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
                cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in rows]):.1f}" for n in LEVELS)
                label = "none (today's map)" if term == "none" else f"tau {100 * float(term):g}%"
                gammas = ", ".join(f"{r['gamma']:.3g}" for r in rows)
                lines.append(f"| {scene} | {arm} | {label} | {cov} | {100 * mean('halfwidth_median_95'):.1f}% | "
                             f"{mean('interval_score_95'):.3f} | {mean('crps'):.4f} | {gammas} |")
    return "\n".join(lines)


def count_markdown(diag: dict) -> str:
    lines = ["", f"## Errors by how many training views agree (tau {100 * TOLERANCES[0]:g}%), pooled over the seeds",
             "", "Calibration: the calibration views' points (both views of the pair observed, today); validation: "
             "the validation photos' SCORE points (opacity > 0.5). |z| = |err| / the raw sigma.", "",
             "| scene | agreeing views | calibration share / abs-rel / median abs z | validation share / abs-rel / "
             "median abs z |", "|---|---|---|---|"]
    for scene, (cal, val) in diag.items():
        for g in sorted(set(cal) | set(val)):
            cell = lambda d: (f"{d[g]['share']:.2f} / {d[g]['abs_rel']:.3f} / {d[g]['median_abs_z']:.2f}"  # noqa: E731
                              if g in d else "-")
            lines.append(f"| {scene} | {g} | {cell(cal)} | {cell(val)} |")
    return "\n".join(lines)


def pooled_by_count(rows: list[list[dict]]) -> dict[int, dict]:
    """Per count: share and abs-rel weighted by points, median |z| as the points-weighted mean of the seeds'."""
    out = {}
    total = sum(r["points"] for seed in rows for r in seed)
    for g in sorted({r["count"] for seed in rows for r in seed}):
        rs = [r for seed in rows for r in seed if r["count"] == g]
        n = sum(r["points"] for r in rs)
        out[g] = {"share": n / total, "abs_rel": sum(r["abs_rel"] * r["points"] for r in rs) / n,
                  "median_abs_z": sum(r["median_abs_z"] * r["points"] for r in rs) / n}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/colour_capacity_paper"))
    ap.add_argument("--evals", type=Path, default=Path("runs/visibility_analysis"))
    ap.add_argument("--work", type=Path, default=Path("runs/agreement_analysis"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/agreement_term_analysis"))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--only", action="store_true", help="compute the given runs' results, write no table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results: dict = {}
    diag: dict = {}
    for scene in args.scenes:
        for arm in ARMS:
            per_seed = [cached(args.work / f"s{seed}" / scene / f"{arm}.json",
                               lambda: analyse(scene, args.runs / f"s{seed}" / "today" / scene / "snerf_default",
                                               args.evals / f"s{seed}" / "today" / scene, arm))
                        for seed in args.seeds]
            terms = per_seed[0]["terms"]
            results.setdefault(scene, {})[arm] = {t: [s["terms"][t] for s in per_seed] for t in terms}
            if arm == "both":
                diag[scene] = (pooled_by_count([s["calibration_by_count"] for s in per_seed]),
                               pooled_by_count([s["validation_by_count"] for s in per_seed]))
    if args.only:
        return
    md = markdown(results, args.seeds) + "\n" + count_markdown(diag) + (
        "\n\nCommand: the module docstring of `benchmarks/studies/agreement_term_analysis.py`.\n")
    write_study(args.out, {"results": results, "by_count": {s: {"calibration": c, "validation": v}
                                                            for s, (c, v) in diag.items()},
                           "seeds": args.seeds, "tolerances": list(TOLERANCES)}, md)


if __name__ == "__main__":
    main()
