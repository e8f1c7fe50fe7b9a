"""Study 21: the termination mixture as the predictive depth distribution (docs/studies.md, "Study 21").

Question (issue 36, "the predictive distribution's shape"): the depth bands today are one Gaussian
per pixel (depth mean, total std with the depth-proportional term), widened per level by the level
map. The model itself defines another distribution: the mixture over the K trajectories of each
trajectory's termination distribution along the ray (``termination.py``), which has two modes where
a pixel's rays split their mass between two surfaces. Does it give bands that hold at every level
and are narrower?

Candidates, one factor at a time from today's:
- ``today``: the Gaussian with the depth-proportional term and the level map (the default map of
  ``calibrate``);
- ``termination + central map``: the termination mixture, its central intervals recalibrated
  (``predictive.CentralCalibration``: split conformal on |2 F(d*) - 1|, for a Gaussian the same
  as the level map): the shape changes, the kind of map does not;
- ``termination + PIT map``: the same mixture, its whole CDF recalibrated through its PIT values
  (``predictive.PitCalibration``, Kuleshov et al. 2018): the map changes too.

All three are fitted on the same renders (every held-out capture point seen from the calibration
views, as ``calibrate --points held-out``), cross-fitted with the same five folds of SCORE blocks,
and scored on the same renders of photos no map and no training saw (study 20's protocol: the
capture split's held-out photos, the paper split's unused test photos, the embedded scene's unused
views). Both the Gaussian and the mixture of a point come from one render of its ray (the same K
draws).

Rule (written before any run of this study was rendered; study 20b's checks): per run, coverage at
each of 50, 68.3, 90 and 95% within 5 points of nominal (four checks), the median 95% half-width at
most 15% of the depth (5% on the synthetic scene), and the mean depth Spearman (|error of the depth
mean| against the band's 68.3% half-width, per photo) no more than 0.02 below today's. A candidate
replaces today's distribution if on every run it passes every check today passes, on the runs
together it passes at least one check today fails, and the 95% interval score / depth averaged over
the real runs does not rise; of two such candidates the lower mean interval score wins.

    OMP_NUM_THREADS=1 python benchmarks/studies/termination_study.py \\
        --run capture/fern=RUN --run capture/flower=RUN --run paper/fern=RUN --run paper/flower=RUN \\
        --run synthetic=DEMO_RUN --out benchmarks/results/termination_study

Resumes: a run already in ``--out``'s results.json (same name, same folder) is kept, not re-rendered.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (QuantileCalibration, calibration_view_points,
                                          cross_fitted_depth_quantiles, fit_depth_folds)
from stochastic_fields.capture_points import SCORE, block_keys, load_capture_points, rays_through_points
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.plots import plot_interval_reliability
from stochastic_fields.predictive import PIT_CLIP, CentralCalibration, PitCalibration
from stochastic_fields.termination import TerminationMixture, render_termination
from stochastic_fields.trainer import load_trained_model
from stochastic_fields.view_maps import OPACITY_MASK

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import photo_points  # noqa: E402
from relative_floor_study import RULE_LEVELS, decide_by_checks, interval_cells, scored_views  # noqa: E402  (study 20b's checks)

TODAY = "today"
CANDIDATES: tuple[str, ...] = (TODAY, "termination + central map", "termination + PIT map")
#: The nominal 68.3% band whose half-width ranks the points (the depth Spearman check).
RANK_LEVEL: float = 0.682689492137086


def render_points(model, cameras, near, far, sparse: dict, seed: int) -> dict | None:
    """One render of the rays through ``sparse``'s points: gt, the Gaussian's mean/std/opacity, the
    termination mixture, the capture point and view of each ray."""
    found = rays_through_points(cameras, near, far, sparse)
    if found is None:
        return None
    rays, gt = found
    device = next(model.parameters()).device
    stats, mixture = render_termination(model, rays.to(device), generator=torch.Generator(device=device).manual_seed(seed))
    order = [v for v, sd in sparse.items() if len(sd)]
    return {"gt": np.asarray(gt, np.float64), **{k: v.cpu().numpy() for k, v in stats.items()}, "mixture": mixture,
            "index": np.concatenate([sparse[v].point_index for v in order]),
            "view": np.concatenate([np.full(len(sparse[v]), v) for v in order])}


def subset(r: dict, keep: np.ndarray) -> dict:
    return {**{n: v[keep] for n, v in r.items() if n != "mixture"},
            "mixture": r["mixture"].select(torch.from_numpy(keep).to(r["mixture"].t_starts.device))}


def collect(run_dir: Path) -> dict:
    cfg, model, dataset = load_trained_model(run_dir)
    capture = load_capture_points(dataset)
    cams, near, far, _, fit_sparse = calibration_view_points(dataset, capture, points="held-out")
    t0 = time.perf_counter()
    fit = render_points(model, cams, near, far, fit_sparse, seed=0)
    views = scored_views(dataset, cfg.data.split)
    scored = render_points(model, dataset.cameras, dataset.near, dataset.far,
                           photo_points(dataset, capture, views, SCORE), seed=0)
    render_s = time.perf_counter() - t0

    def valid(r):
        return (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_mean"]) & (r["depth_std"] > 0)

    keys = block_keys(capture.xyz, capture.xyz)
    fit, scored = subset(fit, valid(fit)), subset(scored, valid(scored))
    fit["keys"], scored["keys"] = keys[fit["index"]], keys[scored["index"]]
    for r in (fit, scored):
        r["pit"] = r["mixture"].cdf(torch.from_numpy(r["gt"])).cpu().numpy()
    return {"fit": fit, "scored": scored, "score_blocks": keys[capture.roles == SCORE], "views": views,
            "render_s": render_s, "num_draws": int(fit["mixture"].weights.shape[1])}


def outside_support(pit: np.ndarray) -> np.ndarray:
    """[N] bool: F(d*) within ``PIT_CLIP`` of 0 or 1 (``predictive.PIT_CLIP``)."""
    return (pit <= PIT_CLIP) | (pit >= 1.0 - PIT_CLIP)


def mixture_quantile_fn(mixture: TerminationMixture, maps, fold: np.ndarray):
    """t [Q] -> [N, Q]: each point's mixture quantiles at the levels its fold's map reads."""
    def quantiles(t: np.ndarray) -> np.ndarray:
        out = np.zeros((mixture.num_rays, np.asarray(t).size))
        for f, m in enumerate(maps):
            i = np.flatnonzero(fold == f)
            if i.size:
                levels = torch.from_numpy(m.quantile_levels(np.asarray(t)))
                out[i] = mixture.select(torch.from_numpy(i)).quantiles(levels).cpu().numpy()
        return out
    return quantiles


def evaluate_candidate(data: dict, name: str) -> tuple[dict, dict]:
    f, s = data["fit"], data["scored"]
    abs_err = np.abs(f["gt"] - f["depth_mean"])
    folds = fit_depth_folds(abs_err, f["depth_std"], f["keys"], data["score_blocks"], depth=f["depth_mean"])
    fold = folds.fold_of(s["keys"])
    t0 = time.perf_counter()
    if name == TODAY:
        run_map = QuantileCalibration.fit_errors(abs_err, f["depth_std"], quantity="depth_std", depth=f["depth_mean"])
        qfn = cross_fitted_depth_quantiles(s["depth_mean"], s["depth_std"], fold, folds)
        rank = run_map.calibrated_std(s["depth_std"], depth=s["depth_mean"])
        extra = {"rho": run_map.relative_floor, "s95": float(run_map.scale_at(0.95))}
    else:
        kind = CentralCalibration if "central" in name else PitCalibration
        fold_maps = [kind.fit(f["pit"][~np.isin(f["keys"], b)], source=f"outside fold {i}")
                     for i, b in enumerate(folds.blocks)]
        run_map = kind.fit(f["pit"], source="every held-out point")
        qfn = mixture_quantile_fn(s["mixture"], fold_maps, fold)
        band = s["mixture"].quantiles(torch.from_numpy(
            run_map.quantile_levels(np.array([(1 - RANK_LEVEL) / 2, (1 + RANK_LEVEL) / 2])))).cpu().numpy()
        rank = (band[:, 1] - band[:, 0]) / 2
        lv = np.array([(1 + p) / 2 for p in RULE_LEVELS])
        extra = {"raw_upper_levels": dict(zip([M.level_name(p) for p in RULE_LEVELS],
                                              run_map.quantile_levels(lv).tolist()))}
    iv = M.interval_sharpness(s["gt"], qfn)
    score_s = time.perf_counter() - t0
    err = np.abs(s["gt"] - s["depth_mean"])
    per_view = [float(spearmanr(err[s["view"] == v], rank[s["view"] == v])[0])
                for v in np.unique(s["view"]) if (s["view"] == v).sum() >= 10]
    row = {k: v for k, v in iv.items() if k != "halfwidth"}
    row.update(extra)
    row.update({"spearman_per_view": per_view, "spearman_mean": float(np.mean(per_view)),
                # truths where the mixture has no mass on one side (F(d*) is 0 or 1): no trajectory
                # terminates beyond (before) them, so no central interval of the mixture reaches them
                "outside_support": float(np.mean(outside_support(s["pit"]))),
                "outside_support_fit": float(np.mean(outside_support(f["pit"]))),
                "median_abs_rel": float(np.median(err / s["gt"])), "points": int(s["gt"].size),
                "fit_points": int(f["gt"].size), "score_s": score_s})
    return row, iv


def decide(runs: dict) -> str:
    return decide_by_checks(runs, TODAY, CANDIDATES[1:])


def report(results: dict) -> str:
    names = "/".join(M.level_name(p) for p in M.INTERVAL_LEVELS)
    lines = ["# Study 21: the termination mixture as the predictive depth distribution", "",
             f"Command: `{results['command']}`", "", f"Rule (written before any run was rendered): {results['rule']}", "",
             f"Decision: **{results['decision']}**", "",
             f"| run | distribution | points | coverage {names} | median 95% half-width / depth | p90 | IS 95% / depth "
             "| CRPS / depth | depth Spearman (mean over photos) |", "|---|---|---|---|---|---|---|---|---|"]
    support = []
    for run, r in results["runs"].items():
        for cand in CANDIDATES:
            c = r[cand]
            lines.append(f"| {run} | {cand} | {c['points']} | {interval_cells(c)} |")
        support.append(f"{run} {100 * r[TODAY]['outside_support']:.1f}% (fitting points "
                       f"{100 * r[TODAY]['outside_support_fit']:.1f}%)")
    lines += ["", "Scored points whose true depth lies where the termination mixture has no mass on one side "
              "(F(d*) = 0 or 1: every trajectory terminates before it, or none before it): " + ", ".join(support) + "."]
    lines += ["", "Cost per run (one thread): the renders of both point sets, then each candidate's fitting and "
              "scoring (`render_s`, `score_s` in results.json)."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="NAME=RUN")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    rule = ("per run: coverage at each of 50/68.3/90/95% within 5 points, median 95% half-width <= 15% (synthetic "
            "5%), mean depth Spearman no more than 0.02 below today's; a candidate is taken if on every run it passes "
            "every check today passes, gains at least one, and the real runs' mean 95% interval score does not rise; "
            "of two, the lower mean interval score")
    results: dict = {"command": "python benchmarks/studies/termination_study.py "
                     + " ".join(sys.argv[1:] if argv is None else argv), "rule": rule, "runs": {}}
    done = {}
    if (args.out / "results.json").exists():  # resume: a run already scored from the same folder is kept
        done = json.loads((args.out / "results.json").read_text()).get("runs", {})
    for spec in args.run:
        name, run = spec.split("=", 1)
        if done.get(name, {}).get("run") == str(Path(run).resolve()):
            results["runs"][name] = done[name]
            print(f"[{name}] scored before, kept", flush=True)
            continue
        data = collect(Path(run))
        res, curves = {"run": str(Path(run).resolve()), "views": [int(v) for v in data["views"]],
                       "render_s": data["render_s"],
                       "num_draws": data["num_draws"]}, {}
        for cand in CANDIDATES:
            res[cand], curves[cand] = evaluate_candidate(data, cand)
            print(f"[{name}] {cand}: coverage " + "/".join(f"{100 * x:.1f}" for x in res[cand]["coverage"])
                  + f", 95% half-width {100 * res[cand]['halfwidth_median_95']:.1f}%, IS95 "
                  f"{res[cand]['interval_score_95']:.3f}, CRPS {res[cand]['crps']:.4f}, Spearman "
                  f"{res[cand]['spearman_mean']:.3f}", flush=True)
        plot_interval_reliability(args.out / f"{name.replace('/', '_')}.png", curves, title=f"{name}: photos no map saw")
        results["runs"][name] = res
        atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    results["decision"] = decide(results["runs"])
    atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "README.md", report(results))
    print(results["decision"])


if __name__ == "__main__":
    main()
