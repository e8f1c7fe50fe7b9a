"""Analysis (decides nothing): depth maps fitted per agreement group (Mondrian calibration), one map for the
rendered points no training view agrees with, one for those at most half agree with, one for the rest.

The agreement analysis (``agreement_term_analysis.py``) found that how many training views render a surface
where a rendered point lies (``free_space.agreeing_views``) sorts the depth errors sharply (paper fern: abs-rel
0.28 where none of the four agrees, 0.015 where all do), and that the calibration views hold fewer of the
unagreed points than the validation photos (fern: 25% against 39%): one map fitted on their mix may be too
narrow for the photos' mix, and a std term in the count could only add width. A map per group (Vovk's
Mondrian conformal prediction: calibrate within each category of a covariate) follows the mix instead: if
the calibration views' points err like the photos' within each group, each group's levels hold whatever
share of the points it has, and the groups most views agree with get the narrow bands their errors allow.

The groups, by the share a / T of the T training views that agree within tau = 2% of the depth
(``GROUP_BOUNDS``): none (a = 0), at most half (0 < a / T <= 1/2), more than half. Each group's map is
today's (free-space weight, rho, s(p); ``calibration.depth_map_and_folds``) fitted on that group's
calibration renders and cross-fitted over the same deal of the SCORE blocks; a validation point is judged by
its group's fold map. Scored as eval scores the validation photos (paper split, cross-fitted), beside
today's one map refitted from the same renders; the calibration views render the points both views of
their pair observed (today) or either (study 38's option). The groups were fixed before any score was
seen; seed 12 was read first, seeds 13 and 14 confirm it.

Inputs: today's S-NeRF at the tables' budget, seeds 12-14 (study 37's today runs, trained again: the same
scores), and its validation photos rendered with per-view maps (``views/view_XXX.npz``)::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods snerf_default --seed SEED \\
        --no-timing --quiet --out runs/mondrian/sSEED/today
    stochastic-fields eval --run runs/mondrian/sSEED/today/SCENE/snerf_default --views VALIDATION --quiet \\
        --out runs/mondrian/validation/sSEED/today/SCENE/snerf_default
    OMP_NUM_THREADS=1 python benchmarks/studies/agreement_groups_analysis.py --runs runs/mondrian \\
        --seeds 12 13 14 --work runs/mondrian/groups --out benchmarks/results/agreement_groups_analysis

(VALIDATION: ``tables_cap_study.validation_views``, fern 12 photos, flower 23.)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))

from agreement_term_analysis import validation_points  # noqa: E402
from study_helpers import cached, write_study  # noqa: E402

from stochastic_fields import metrics as M  # noqa: E402
from stochastic_fields.calibration import (calibration_views, cross_fitted_depth_quantiles,  # noqa: E402
                                           depth_calibration_renders, depth_map_and_folds)
from stochastic_fields.cameras import camera_to_world  # noqa: E402
from stochastic_fields.capture_points import load_capture_points  # noqa: E402
from stochastic_fields.evaluation import depth_samples, pool_depth_samples  # noqa: E402
from stochastic_fields.free_space import agreeing_views, load_training_depth, rendered_points  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402

SCENES = ("fern", "flower")
ARMS = ("both", "either")
#: Relative tolerance tau of the agreement (the agreement analysis's first).
TOLERANCE = 0.02
#: Upper bounds of the groups' agreeing shares a / T (the last group: above the last bound).
GROUP_BOUNDS = (0.0, 0.5)
GROUP_NAMES = ("none agree", "at most half agree", "more than half agree")
LEVELS = ("50", "68", "90", "95", "99")


def group_of(count: np.ndarray, views: int) -> np.ndarray:
    """Group [N] int64 of each agreeing count a [N] of ``views`` training views (``GROUP_BOUNDS``)."""
    return np.searchsorted(np.asarray(GROUP_BOUNDS), np.asarray(count, dtype=np.float64) / views, side="left")


def subset(renders: dict, keep: np.ndarray) -> dict:
    """``renders`` with every per-point array restricted to ``keep`` [N] (bool)."""
    n = keep.size
    return {k: (v[keep] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v) for k, v in renders.items()}


def subset_samples(samples, keep: np.ndarray):
    """The ``evaluation.DepthSamples`` ``samples`` at ``keep`` [N] (bool): gt, pred, stds, violation and
    block (no parts, no edge)."""
    return type(samples)(samples.gt[keep], samples.pred[keep], samples.std[keep], samples.std_raw[keep], {},
                         samples.violation[keep], samples.block[keep], None)


def scored(samples, groups: np.ndarray, fitted: list) -> dict:
    """Interval scores of ``samples`` judged by their group's cross-fitted maps; ``fitted`` [(map, folds)] per
    group (one entry: every point by the same map). Spearman of |err| against the calibrated std."""
    n = samples.gt.size
    std = np.zeros(n)
    fns = []
    for g, (m, folds) in enumerate(fitted):
        i = np.flatnonzero(groups == g) if len(fitted) > 1 else np.arange(n)
        if i.size == 0:
            continue
        std[i] = m.calibrated_std(samples.std_raw[i], samples.violation[i], samples.pred[i],
                                  parallax=None if samples.parallax is None else samples.parallax[i])
        fold = folds.fold_of(samples.block[i])
        fns.append((i, cross_fitted_depth_quantiles(samples.pred[i], samples.std_raw[i], fold, folds,
                                                    violation=samples.violation[i],
                                                    parallax=None if samples.parallax is None else samples.parallax[i])))

    def quantiles(t: np.ndarray) -> np.ndarray:
        out = np.zeros((n, np.asarray(t).size))
        for i, fn in fns:
            out[i] = fn(t)
        return out

    s = M.interval_sharpness(samples.gt, quantiles)
    names = [M.level_name(p) for p in s["levels"]]
    return {"coverage": dict(zip(names, s["coverage"])), "halfwidth_median_95": s["halfwidth_median_95"],
            "interval_score_95": s["interval_score_95"], "crps": s["crps"], "points": int(n),
            "spearman": float(spearmanr(np.abs(samples.gt - samples.pred), std).statistic)}


def validation_pool(scene: str, evals: Path, dataset, capture, ref) -> tuple:
    """The validation photos' SCORE points of ``scene`` where the render is opaque (``depth_samples``):
    (their pooled ``DepthSamples``, their capture point index [N], their agreeing views [N])."""
    pool, index, counts = [], [], []
    for sd, products, terms, blocks in validation_points(scene, evals, dataset, capture, ref):
        keep = sd.sample(products["opacity"]) > OPACITY_MASK
        pool.append(depth_samples({k: v for k, v in products.items() if k != "depth_edge"}, sparse=sd, blocks=blocks))
        index.append(sd.point_index[keep])
        counts.append(terms["count"][keep])
    return pool_depth_samples(pool), np.concatenate(index), np.concatenate(counts)


def analyse(scene: str, run: Path, evals: Path, arm: str) -> dict:
    """One run and arm: the scores of one map and of a map per group, and each group's own scores."""
    _, model, dataset = load_trained_model(run, device="cpu")
    ref = load_training_depth(run)
    if ref is None:
        raise SystemExit(f"{run}: no training_depth.npz (calibrate the run with the free-space check first)")
    T = len(ref.views)
    capture = load_capture_points(dataset)
    renders = depth_calibration_renders(model, dataset, points="held-out", free_space=ref, pair_points=arm)
    centres = camera_to_world(calibration_views(dataset)[0]).double()[:, :3, 3].numpy()[renders["view"]]
    X = rendered_points(centres, capture.xyz[renders["index"]], renders["depth"] + renders["err"], renders["depth"])
    cal_groups = group_of(agreeing_views(X, ref, tolerance=TOLERANCE)[0], T)
    samples, _, counts = validation_pool(scene, evals, dataset, capture, ref)
    groups = group_of(counts, T)
    one = [depth_map_and_folds(renders, capture, relative_floor=True, where=str(run))]
    per_group = [depth_map_and_folds(subset(renders, cal_groups == g), capture, relative_floor=True,
                                     where=f"{run} group {g}") for g in range(len(GROUP_NAMES))]
    out = {"one": scored(samples, groups, one), "grouped": scored(samples, groups, per_group), "groups": []}
    for g, (m, _) in enumerate(per_group):
        i = groups == g
        sub = subset_samples(samples, i)
        out["groups"].append({"calibration_points": int((cal_groups == g).sum()), "validation_points": int(i.sum()),
                              "rho": m.relative_floor, "beta": m.free_space_weight if m.free_space else 0.0,
                              "s68": m.std_scale, "one": scored(sub, np.zeros(i.sum(), int), one),
                              "own": scored(sub, np.zeros(i.sum(), int), [per_group[g]])})
    return out


def row(scene: str, arm: str, label: str, rows: list[dict]) -> str:
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in rows]):.1f}" for n in LEVELS)
    return (f"| {scene} | {arm} | {label} | {cov} | {100 * mean('halfwidth_median_95'):.1f}% | "
            f"{mean('interval_score_95'):.3f} | {mean('crps'):.4f} | {mean('spearman'):.3f} |")


def markdown(results: dict, seeds: list[int]) -> str:
    lines = ["# Depth maps fitted per agreement group", "",
             f"Today's S-NeRF (paper split, tables' budget, seed{'s' if len(seeds) > 1 else ''} "
             f"{', '.join(map(str, seeds))}), its validation photos' SCORE points (opacity > 0.5) scored as eval "
             "scores them (cross-fitted), by one map (today's, refitted from the same renders) or a map per agreement "
             f"group (a / T of the training views agreeing within {100 * TOLERANCE:g}% of the depth: 0, at most 1/2, "
             "more). "
             "Means over the seeds. Decides nothing.", "",
             "| scene | calibration points | maps | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | "
             "IS95 / depth | CRPS / depth | Spearman |err|-std |", "|---|---|---|---|---|---|---|---|"]
    for scene, arms in results.items():
        for arm, per_seed in arms.items():
            for variant in ("one", "grouped"):
                lines.append(row(scene, arm, "one (today's)" if variant == "one" else "per group",
                                 [r[variant] for r in per_seed]))
    lines += ["", "## Each group, judged by one map and by its own", "",
              "| scene | calibration points | group | points calibration / validation (seed sum) | maps | "
              "cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | Spearman |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for scene, arms in results.items():
        for arm, per_seed in arms.items():
            for g, name in enumerate(GROUP_NAMES):
                gs = [r["groups"][g] for r in per_seed]
                n = f"{sum(x['calibration_points'] for x in gs)} / {sum(x['validation_points'] for x in gs)}"
                for variant in ("one", "own"):
                    cells = row(scene, arm, variant, [x[variant] for x in gs]).split(" | ", 3)[3]
                    lines.append(f"| {scene} | {arm} | {name} | {n} | {variant} | {cells}")
    lines += ["", "Command: the module docstring of `benchmarks/studies/agreement_groups_analysis.py`."]
    return "\n".join(lines) + "\n"


def run_and_evals(runs: Path, seed: int, scene: str) -> tuple[Path, Path]:
    """(today's S-NeRF run of ``scene`` at ``seed`` under ``runs``, its validation renders' folder)."""
    return (runs / f"s{seed}" / "today" / scene / "snerf_default",
            runs / "validation" / f"s{seed}" / "today" / scene / "snerf_default")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/mondrian"))
    ap.add_argument("--work", type=Path, default=Path("runs/mondrian/groups"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/agreement_groups_analysis"))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[12, 13, 14])
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results: dict = {}
    for scene in args.scenes:
        for arm in args.arms:
            results.setdefault(scene, {})[arm] = [
                cached(args.work / f"s{seed}" / scene / f"{arm}.json",
                       lambda: analyse(scene, *run_and_evals(args.runs, seed, scene), arm)) for seed in args.seeds]
    write_study(args.out, {"results": results, "seeds": args.seeds, "tolerance": TOLERANCE,
                           "group_bounds": list(GROUP_BOUNDS)}, markdown(results, args.seeds))


if __name__ == "__main__":
    main()
