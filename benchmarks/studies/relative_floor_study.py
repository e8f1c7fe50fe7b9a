"""Study 20: a depth-proportional std term under the depth map (docs/studies.md, "Study 20").

Question: does standardising the depth errors by sqrt(sigma^2 + (rho d)^2) instead of sigma
(``calibration.fit_relative_floor``; rho fitted on the map's own points by the mean CRPS / depth)
make the 95% bands narrow while every level still holds?

Both maps are fitted as a user's run fits its map (``calibrate --points held-out``: every held-out
capture point seen from the virtual calibration views, 5 cross-fitted fold maps) and scored as
``eval`` scores them (each point by the fold map that did not see its block), on photos no map and
no training saw:
- capture-split runs (``benchmarks/capture_quality.py``: every 8th photo held out, the rest train):
  the held-out photos' SCORE points;
- paper-split runs (the tables' runner; every 5th photo trains): the SCORE points of the *unused*
  photos (test photos the tables do not score; study 18c's protocol);
- the embedded synthetic scene (``stochastic-fields demo``): the same, on its unused views.

Rule (fixed before any scored point was looked at): the term becomes the default of ``calibrate``,
``train`` and ``demo`` only if, on every run,
1. coverage at 50, 68.3, 90 and 95% lies within 5 points of nominal, or no farther from nominal
   than without the term;
2. the mean depth Spearman(|err|, calibrated std) over the scored photos falls by at most 0.02;
and the 95% interval score / depth, averaged over the real runs, falls by at least 25%.

Study 20b (``--study 20b``; rule written after study 20's seed-0 rows were seen, judged on seed-1
runs nobody had looked at): per run, the checks are issue 36's targets as they apply to one run:
coverage at each of 50, 68.3, 90 and 95% within 5 points of nominal (four checks), the median 95%
half-width at most 15% of the depth (5% on the synthetic scene), and the mean depth Spearman no
more than 0.02 below today's. The term becomes the default if, on every run, it passes every check
today passes, on the runs together it passes at least one check today fails, and the 95% interval
score / depth averaged over the real runs does not rise.

    OMP_NUM_THREADS=1 python benchmarks/studies/relative_floor_study.py \\
        --run capture/fern=runs/capture_quality/fern/snerf/run --run capture/flower=... \\
        --run paper/fern=RUNS/fern/snerf_default --run paper/flower=... --run synthetic=DEMO_RUN \\
        --out benchmarks/results/relative_floor_study
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (QuantileCalibration, cross_fitted_depth_quantiles,
                                          depth_calibration_renders, fit_depth_folds, render_at_points)
from stochastic_fields.capture_points import SCORE, block_keys, load_capture_points
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.plots import plot_interval_reliability
from stochastic_fields.trainer import load_trained_model
from stochastic_fields.view_maps import OPACITY_MASK
from stochastic_fields_bench.budget import BenchmarkSettings, select_views

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import photo_points  # noqa: E402

#: The rule (module doc), fixed before any scored point was looked at.
COVERAGE_TOLERANCE: float = 0.05
RULE_LEVELS: tuple[float, ...] = (0.5, 0.682689492137086, 0.9, 0.95)
SPEARMAN_TOLERANCE: float = 0.02
INTERVAL_SCORE_GAIN: float = 0.25
#: Study 20b's width targets (issue 36, target 2): median 95% half-width / depth.
HALFWIDTH_TARGET_REAL: float = 0.15
HALFWIDTH_TARGET_SYNTHETIC: float = 0.05
#: The candidates: name -> whether the map fits the depth-proportional term.
CANDIDATES: dict[str, bool] = {"today (sigma)": False, "sqrt(sigma^2 + (rho d)^2)": True}


def scored_views(dataset, split: str) -> list[int]:
    """Photos that neither train nor are scored by the tables: all held-out photos of a capture
    ``split`` (the tables do not run on it), the unused test photos of a paper split."""
    test = list(dataset.test_indices)
    if split == "capture":
        return test
    scored = set(select_views(test, BenchmarkSettings()))
    return [v for v in test if v not in scored]


def scored_photo_renders(model, dataset, capture, views: list[int]) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    """Render the SCORE points the photos ``views`` observed (seed 0): (``render_at_points``' maps,
    each point's capture index [N], its view [N], the mask [N] of renders the scores keep: opacity
    above ``OPACITY_MASK``, a finite depth and a positive std)."""
    sparse = photo_points(dataset, capture, views, SCORE)
    r = render_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse,
                         generator=torch.Generator().manual_seed(0))
    order = [v for v, sd in sparse.items() if len(sd)]
    index = np.concatenate([sparse[v].point_index for v in order])
    view = np.concatenate([np.full(len(sparse[v]), v) for v in order])
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_mean"]) & (r["depth_std"] > 0)
    return r, index, view, keep


def collect(run_dir: Path) -> dict:
    """The fitting renders (as ``calibrate --points held-out``) and the scored points of one run."""
    cfg, model, dataset = load_trained_model(run_dir)
    capture = load_capture_points(dataset)
    fit = depth_calibration_renders(model, dataset, points="held-out")
    views = scored_views(dataset, cfg.data.split)
    r, index, view, keep = scored_photo_renders(model, dataset, capture, views)
    keys = block_keys(capture.xyz, capture.xyz)
    return {"fit": {k: fit[k] for k in ("abs_err", "std", "depth")}, "fit_keys": keys[fit["index"]],
            "score_blocks": keys[capture.roles == SCORE],
            "scored": {"gt": r["gt"][keep], "pred": r["depth_mean"][keep], "std": r["depth_std"][keep],
                       "keys": keys[index[keep]], "view": view[keep]},
            "views": views}


def score_map(abs_err, fit_std, fit_depth, fit_keys, score_blocks, scored: dict, std) -> tuple[dict, dict]:
    """Fit a depth map (and its 5 cross-fitted fold maps) on errors ``abs_err`` with stds ``fit_std``
    (``fit_depth``: the rendered depths for a depth-proportional term, None for none) and score it on
    the photos' points ``scored`` with their stds ``std`` as ``eval`` does: (row, interval output)."""
    run_map = QuantileCalibration.fit_errors(abs_err, fit_std, quantity="depth_std", depth=fit_depth)
    folds = fit_depth_folds(abs_err, fit_std, fit_keys, score_blocks, depth=fit_depth)
    s = scored
    iv = M.interval_sharpness(s["gt"], cross_fitted_depth_quantiles(s["pred"], std, folds.fold_of(s["keys"]), folds))
    calibrated = run_map.calibrated_std(std, depth=s["pred"])
    err = np.abs(s["gt"] - s["pred"])
    per_view = [float(spearmanr(err[s["view"] == v], calibrated[s["view"] == v])[0])
                for v in np.unique(s["view"]) if (s["view"] == v).sum() >= 10]
    row = {k: v for k, v in iv.items() if k != "halfwidth"}
    row.update({"rho": run_map.relative_floor, "rho_folds": [m.relative_floor for m in folds.maps],
                "s68": run_map.std_scale, "s95": float(run_map.scale_at(0.95)),
                "spearman_per_view": per_view, "spearman_mean": float(np.mean(per_view)),
                "median_abs_rel": float(np.median(err / s["gt"])), "points": int(s["gt"].size)})
    return row, iv


def evaluate_candidate(data: dict, relative: bool) -> tuple[dict, dict]:
    f, s = data["fit"], data["scored"]
    return score_map(f["abs_err"], f["std"], f["depth"] if relative else None, data["fit_keys"],
                     data["score_blocks"], s, s["std"])


def decide(runs: dict) -> str:
    today, cand = CANDIDATES
    fails = []
    for name, r in runs.items():
        for p in RULE_LEVELS:
            key = f"coverage_{M.level_name(p)}"
            gap_new, gap_old = abs(r[cand][key] - p), abs(r[today][key] - p)
            if gap_new > COVERAGE_TOLERANCE and gap_new > gap_old + 1e-12:
                fails.append(f"{name}: coverage at {p:.3f} {100 * r[cand][key]:.1f}%")
        drop = r[today]["spearman_mean"] - r[cand]["spearman_mean"]
        if drop > SPEARMAN_TOLERANCE:
            fails.append(f"{name}: depth Spearman falls by {drop:.3f}")
    real = [n for n in runs if not n.startswith("synthetic")]
    old = np.mean([runs[n][today]["interval_score_95"] for n in real])
    new = np.mean([runs[n][cand]["interval_score_95"] for n in real])
    if new > (1.0 - INTERVAL_SCORE_GAIN) * old:
        fails.append(f"the mean 95% interval score / depth falls only from {old:.3f} to {new:.3f}")
    if fails:
        return "not taken: " + "; ".join(fails)
    return f"taken: every run holds, mean 95% interval score / depth {old:.3f} -> {new:.3f}"


def checks(name: str, row: dict, today: dict) -> dict[str, bool]:
    """Study 20b's checks of one run's row (module doc)."""
    out = {f"coverage {M.level_name(p)}": abs(row[f"coverage_{M.level_name(p)}"] - p) <= COVERAGE_TOLERANCE
           for p in RULE_LEVELS}
    target = HALFWIDTH_TARGET_SYNTHETIC if name.startswith("synthetic") else HALFWIDTH_TARGET_REAL
    out["95% half-width"] = row["halfwidth_median_95"] <= target
    out["depth Spearman"] = today["spearman_mean"] - row["spearman_mean"] <= SPEARMAN_TOLERANCE
    return out


def decide_by_checks(runs: dict, today: str, candidates) -> str:
    """Study 20b's rule (module doc) for each of ``candidates`` against ``today`` over {run: {name:
    row}}: taken if on every run it passes every check today passes, passes at least one check today
    fails, and the real runs' mean 95% interval score / depth does not rise; of several, the lowest
    mean interval score. Studies 21 and 22 judge by it too."""
    real = [n for n in runs if not n.startswith("synthetic")]
    is_today = float(np.mean([runs[n][today]["interval_score_95"] for n in real]))
    verdicts, winners = [], []
    for cand in candidates:
        lost, gained = [], []
        for name, r in runs.items():
            old, new = checks(name, r[today], r[today]), checks(name, r[cand], r[today])
            lost += [f"{name}: {c}" for c in old if old[c] and not new[c]]
            gained += [f"{name}: {c}" for c in old if new[c] and not old[c]]
        is_new = float(np.mean([runs[n][cand]["interval_score_95"] for n in real]))
        fails = [f"loses {c}" for c in lost] + ([] if gained else ["gains no check"])
        if is_new > is_today:
            fails.append(f"mean 95% interval score / depth rises {is_today:.3f} -> {is_new:.3f}")
        if fails:
            verdicts.append(f"{cand}: not taken ({'; '.join(fails)})")
        else:
            winners.append((is_new, cand))
            verdicts.append(f"{cand}: passes (gains {', '.join(gained)}; mean IS95 {is_today:.3f} -> {is_new:.3f})")
    head = f"taken: {min(winners)[1]}" if winners else "today's stays"
    return head + ". " + " | ".join(verdicts)


def decide_20b(runs: dict) -> str:
    today, cand = CANDIDATES
    return decide_by_checks(runs, today, [cand])


def interval_cells(c: dict) -> str:
    """A row's table cells: coverage per level, median and p90 95% half-width, IS95, CRPS, Spearman."""
    cov = "/".join(f"{100 * x:.1f}" for x in c["coverage"])
    return (f"{cov} | {100 * c['halfwidth_median_95']:.1f}% | {100 * c['halfwidth_p90_95']:.0f}% "
            f"| {c['interval_score_95']:.3f} | {c['crps']:.4f} | {c['spearman_mean']:.3f}")


def report(results: dict) -> str:
    names = "/".join(M.level_name(p) for p in M.INTERVAL_LEVELS)
    lines = [f"# Study {results.get('study', '20')}: a depth-proportional std term", "", f"Command: `{results['command']}`", "",
             f"Rule (fixed before any scored point was looked at): {results['rule']}", "",
             f"Decision: **{results['decision']}**", "",
             f"| run | map | points | rho | coverage {names} | median 95% half-width / depth | p90 | IS 95% / depth "
             "| CRPS / depth | depth Spearman (mean over photos) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for run, r in results["runs"].items():
        for cand in CANDIDATES:
            c = r[cand]
            lines.append(f"| {run} | {cand} | {c['points']} | {c['rho']:.3g} | {interval_cells(c)} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="NAME=RUN")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--study", choices=("20", "20b"), default="20", help="Whose rule decides (module doc).")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    rule_20b = ("per run: coverage at each of 50/68.3/90/95% within 5 points, median 95% half-width <= 15% "
                "(synthetic 5%), mean depth Spearman no more than 0.02 below today's; taken if on every run it passes "
                "every check today passes, gains at least one, and the real runs' mean 95% interval score does not rise")
    results: dict = {"command": "python benchmarks/studies/relative_floor_study.py " + " ".join(sys.argv[1:] if argv is None else argv),
                     "study": args.study,
                     "rule": rule_20b if args.study == "20b" else f"on every run, coverage at {[round(x, 3) for x in RULE_LEVELS]} within {COVERAGE_TOLERANCE} "
                             f"of nominal or no farther than today's, and the mean depth Spearman falls by at most "
                             f"{SPEARMAN_TOLERANCE}; the mean 95% interval score / depth over the real runs falls by at "
                             f"least {INTERVAL_SCORE_GAIN:.0%}", "runs": {}}
    for spec in args.run:
        name, run = spec.split("=", 1)
        data = collect(Path(run))
        res, curves = {"views": [int(v) for v in data["views"]]}, {}
        for cand, relative in CANDIDATES.items():
            res[cand], curves[cand] = evaluate_candidate(data, relative)
            print(f"[{name}] {cand}: rho {res[cand]['rho']:.3g}, coverage "
                  + "/".join(f"{100 * x:.1f}" for x in res[cand]["coverage"])
                  + f", 95% half-width {100 * res[cand]['halfwidth_median_95']:.1f}%, IS95 {res[cand]['interval_score_95']:.3f}",
                  flush=True)
        plot_interval_reliability(args.out / f"{name.replace('/', '_')}.png", curves, title=f"{name}: photos no map saw")
        results["runs"][name] = res
        atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    results["decision"] = (decide if args.study == "20" else decide_20b)(results["runs"])
    atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "README.md", report(results))
    print(results["decision"])


if __name__ == "__main__":
    main()
