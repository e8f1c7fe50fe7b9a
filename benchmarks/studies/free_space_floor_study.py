"""Studies 22 and 22b: the free-space check, and the calibration views' bounds, beside the
depth-proportional term (docs/studies.md, "Study 22", "Study 22b").

Question: today's map standardises the depth errors by sqrt(sigma^2 + (rho d)^2) (study 20b): the
depth-proportional term covers the points rendered on the wrong surface by widening every band in
proportion to the depth. The free-space check (``calibrate --free-space``; studies 13-13c) adds
e, how far the rendered point lies in front of a training view's rendered surface, which marks
many of those points one by one. Studies 13-13c judged the check before the term existed. Does
``sqrt(sigma^2 + e^2 + (rho d)^2)`` (rho refitted on the checked std, as ``calibrate --free-space``
fits it today) narrow the bands and keep every level, now that the term can carry what e misses?

Both maps are fitted as a user's run fits its map (every held-out capture point seen from the
virtual calibration views, 5 cross-fitted fold maps) and scored as ``eval`` scores them, on photos
no map and no training saw (study 20's protocol, ``relative_floor_study.scored_views``): the capture
split's held-out photos, the paper split's unused test photos, the embedded scene's unused views.
The check's reference is the training views' rendered depth (``free_space.render_training_depth``,
what ``calibrate --free-space`` stores), the violation of a scored point is that of its rendered
point (``free_space.rendered_points``), as ``eval`` computes it per pixel.

Study 22b asks the same of the calibration views' render bounds. They take their pair's widest
near/far bounds (``CALIBRATION_BOUNDS``); on flower that inflates their depth errors three- to
four-fold against real held-out photos (study 12: median relative error 0.17-0.22 against 0.05-0.06),
with the std, so a map of one factor per level did not care (study 12), but a std term in units of
the depth does: rho is fitted on the calibration views' relative errors (study 12b found the same for
the absolute std floor). Candidate: the same map (sigma, rho) fitted on calibration views rendered
with bounds interpolated at the view's fraction (``calibrate``'s ``bounds="interpolated"``).

Study 22c (``--study 22c``; rule written after 22b's seed-3 rows were seen, before any seed-2 run was
rendered with interpolated bounds): on seed 3 the interpolated bounds lost one check today passes by
0.4 points (capture flower's 90% level, 95.4%) and cut paper flower's median 95% band from 153% to
33% of the depth. The interpolated bounds alone are judged again, by the same rule unchanged, on the
seed-2 runs of study 21 (trained before this question was asked; their rows under today's map were
seen there, the candidate's never). The checked map is rendered and reported beside, deciding
nothing.

Study 22d (``--study 22d``; rule written after 22c's rows were seen, before any seed-4 run was
trained): on seeds 2 and 3 the check gave the narrowest bands and the best ranking on every real run
and held paper flower's 68% band, but over-covered the synthetic scene's centre by 14-17 points
(e > 0 at 81% of its scored points, at full weight). Candidate: the check with a weight beta,
sqrt(sigma^2 + (beta e)^2 + (rho d)^2), beta chosen from ``CHECK_WEIGHT_GRID`` with rho by the mean
CRPS / depth on the map's own points (``calibration.fit_check_weight``; beta = 0 is today's map, so a scene the
check does not help can keep it). Judged alone against today's by the same rule, on fresh seed-4
runs (the other rows reported beside).

Study 22e (``--study 22e``; rule written after 22d's seed-4 rows were seen, before the weighted check
was rendered on any seed-2 or seed-3 run): on seed 4 the weighted check failed study 20b's rule by
0.8 points on one level of one run (paper fern's 90%, 85.0%) while gaining three checks and cutting
the real runs' mean 95% interval score / depth from 1.58 to 1.19; a level's coverage moves by about
one point between seeds of the same default (docs/studies.md, "Analysis: the seed spread"), so a
one-seed rule decides such a margin by chance. The weighted check is judged again by study 20b's
rule applied to each run type's mean over seeds 2, 3 and 4 (coverage per level, median 95%
half-width, mean depth Spearman and 95% interval score / depth, each averaged over the three
seeds; seed 4's rows are 22d's, imported with ``--rows-from``), with one guard against an average
hiding a failure: on no single seed's run may a level that today's map holds within 5 points fall
more than 10 points from nominal. Only today's map, the checked one (which the weighted one needs)
and the weighted one are rendered.

Study 22f (``--study 22f``; rule written after 22e made the weighted check the default, before any
map was fitted on calibration views with interpolated bounds beside the check): studies 22b and
22c found that interpolated render bounds make the calibration views' depth errors like the photos'
(paper flower's fitting points err by a median 32% of their depth with the widest bounds, 10%
interpolated) and each lost one check by under a point on one seed; under today's map capture
flower's 50% and 68% bands over-cover by about 8 points on every seed, as a map fitted on errors
larger than the photos' would. Candidate: the calibration views rendered with interpolated bounds,
the weighted check and rho fitted on them as today. Judged against today's default (the weighted
check, widest bounds) by study 22e's rule: study 20b's checks on each run type's mean over seeds 2,
3 and 4, and 22e's guard. One render per bounds gives both the raw and the checked std. (A smoke
run of the script on seed 2's synthetic scene rendered that one row before this rule was committed:
beta = 0 and the same coverage as today's map, 52.8/71.8/91.0/96.9%.)

Rule (written before any run of the study was trained; study 20b's checks; 22b's added before any
seed-3 run was rendered, under the same rule). Per run: coverage at
each of 50, 68.3, 90 and 95% within 5 points of nominal (four checks), the median 95% half-width at
most 15% of the depth (5% on the synthetic scene), and the mean depth Spearman (|error| against the
calibrated std, per scored photo) no more than 0.02 below today's. A candidate becomes the default
(the check: ``DEPTH_FREE_SPACE``; the bounds: ``CALIBRATION_BOUNDS``) if, on every run, it passes
every check today passes, on the runs together it passes at least one check today fails, and the 95%
interval score / depth averaged over the real runs does not rise; if both pass, the one with the lower
mean interval score (their combination would be a study of its own). Runs: fresh seed-3 runs (nobody
has looked at them).

    OMP_NUM_THREADS=1 python benchmarks/studies/free_space_floor_study.py \\
        --run capture/fern=runs/capture_seed3/fern/snerf/run --run capture/flower=... \\
        --run paper/fern=runs/paper_seed3/fern/snerf_default --run paper/flower=... \\
        --run synthetic=runs/demo_seed3 --out benchmarks/results/free_space_floor_study
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stochastic_fields import metrics as M
from stochastic_fields.calibration import depth_calibration_renders, fit_check_weight
from stochastic_fields.cameras import camera_to_world
from stochastic_fields.capture_points import SCORE, block_keys, load_capture_points
from stochastic_fields.free_space import (checked_std, free_space_violation, render_training_depth,
                                          rendered_points)
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.plots import plot_interval_reliability
from stochastic_fields.trainer import load_trained_model

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from relative_floor_study import (RULE_LEVELS, decide_by_checks, interval_cells, score_map, scored_photo_renders,  # noqa: E402
                                  scored_views)

#: The maps: name -> (the calibration views' bounds, the std: "plain" sigma, "checked" sqrt(sigma^2 +
#: e^2), "weighted" sqrt(sigma^2 + (beta e)^2) with beta fitted, ``calibration.fit_check_weight``); all fit rho.
TODAY: str = "today (sigma, rho)"
CHECKED: str = "checked (sigma, e, rho)"
WEIGHTED: str = "weighted check (sigma, beta e, rho)"
INTERP_WEIGHTED: str = "interpolated bounds, weighted check (sigma, beta e, rho)"
CANDIDATES: dict[str, tuple[str, str]] = {TODAY: ("widest", "plain"),
                                          CHECKED: ("widest", "checked"),
                                          "interpolated bounds (sigma, rho)": ("interpolated", "plain"),
                                          WEIGHTED: ("widest", "weighted"),
                                          INTERP_WEIGHTED: ("interpolated", "weighted")}
RULE = ("per run: coverage at each of 50/68.3/90/95% within 5 points, median 95% half-width <= 15% (synthetic 5%), "
        "mean depth Spearman no more than 0.02 below today's; a candidate is taken if on every run it passes every "
        "check today passes, gains at least one, and the real runs' mean 95% interval score / depth does not rise; "
        "of two, the lower mean interval score")
RULE_22E = (RULE + "; study 22e reads each run type's mean over seeds 2, 3 and 4 (coverage per level, median 95% "
            "half-width, depth Spearman, IS95), and no single seed's level held within 5 points today may fall more "
            "than 10 points from nominal")


def collect(run_dir: Path, candidates=tuple(CANDIDATES)) -> dict:
    """The fitting points of ``candidates`` and the scored points of one run. One calibration render
    per bounds the candidates use, with the check (as ``calibrate --points held-out --free-space``):
    its raw std is the plain map's, the full violation the checked one's, and the weighted maps fit
    beta on it (``calibration.fit_check_weight``) as ``calibrate`` does; the scored points get the
    same std with their own violation."""
    cfg, model, dataset = load_trained_model(run_dir)
    capture = load_capture_points(dataset)
    t0 = time.perf_counter()
    ref = render_training_depth(model, dataset, progress=False)
    reference_s = time.perf_counter() - t0
    views = scored_views(dataset, cfg.data.split)
    r, index, view, keep = scored_photo_renders(model, dataset, capture, views)
    centres = camera_to_world(dataset.cameras).double()[:, :3, 3].numpy()[view[keep]]
    e = free_space_violation(rendered_points(centres, capture.xyz[index[keep]], r["gt"][keep], r["depth_mean"][keep]), ref)
    keys = block_keys(capture.xyz, capture.xyz)
    sigma = r["depth_std"][keep]
    renders = {bounds: depth_calibration_renders(model, dataset, points="held-out", bounds=bounds, free_space=ref)
               for bounds in dict.fromkeys(CANDIDATES[name][0] for name in candidates)}
    fit, betas, scored_std = {}, {}, {}
    for name in candidates:
        bounds, kind = CANDIDATES[name]
        f = renders[bounds]
        beta = {"plain": 0.0, "checked": 1.0}.get(kind)
        if beta is None:  # weighted
            beta = betas[name] = fit_check_weight(f["abs_err"], f["std_raw"], f["violation"], f["depth"])
        fit[name] = {"abs_err": f["abs_err"], "depth": f["depth"], "std": checked_std(f["std_raw"], beta * f["violation"]),
                     "keys": keys[f["index"]], "median_rel_err": float(np.median(f["abs_err"] / f["depth"]))}
        scored_std[name] = checked_std(sigma, beta * e)
    first = renders.get("widest", next(iter(renders.values())))
    return {"fit": fit, "score_blocks": keys[capture.roles == SCORE], "check_weight": betas.get(WEIGHTED),
            "check_weights": betas, "fit_violated": float((first["std"] > first["std_raw"] * (1 + 1e-9)).mean()),
            "scored": {"gt": r["gt"][keep], "pred": r["depth_mean"][keep], "std": scored_std, "violation": e,
                       "keys": keys[index[keep]], "view": view[keep]},
            "views": views, "reference_s": reference_s}


def evaluate_candidate(data: dict, name: str) -> tuple[dict, dict]:
    f, s = data["fit"][name], data["scored"]
    row, iv = score_map(f["abs_err"], f["std"], f["depth"], f["keys"], data["score_blocks"], s, s["std"][name])
    row.update({"fit_points": int(f["abs_err"].size), "fit_median_rel_err": f["median_rel_err"]})
    return row, iv


def violation_share(data: dict) -> dict:
    """How often the check fires, and whether it fires where the errors are large: the share of
    scored points with e > 0, and of those among the 10% largest relative errors."""
    s = data["scored"]
    rel = np.abs(s["gt"] - s["pred"]) / s["gt"]
    top = rel >= np.quantile(rel, 0.9)
    return {"scored_violated": float((s["violation"] > 0).mean()),
            "worst_decile_violated": float((s["violation"][top] > 0).mean()),
            "fit_violated": data["fit_violated"]}


#: The candidate study 22c judges (the others are reported beside it).
CANDIDATE_22C: str = "interpolated bounds (sigma, rho)"
#: What each study judges against today's (the other rows are reported beside, deciding nothing).
JUDGED: dict[str, list[str]] = {"22": [CHECKED, CANDIDATE_22C], "22c": [CANDIDATE_22C], "22d": [WEIGHTED],
                                 "22e": [WEIGHTED], "22f": [INTERP_WEIGHTED]}
#: The map each study judges against (22f: the default study 22e chose).
BASELINE: dict[str, str] = {"22f": WEIGHTED}
#: The maps each study renders (22e skips the interpolated bounds, which 22c decided).
RENDERED: dict[str, tuple[str, ...]] = {"22": tuple(CANDIDATES)[:4], "22c": tuple(CANDIDATES)[:4],
                                        "22d": tuple(CANDIDATES)[:4], "22e": (TODAY, CHECKED, WEIGHTED),
                                        "22f": (WEIGHTED, INTERP_WEIGHTED)}
#: Studies that read the means over seeds (22e's rule).
SEED_MEAN_STUDIES: tuple[str, ...] = ("22e", "22f")
#: Study 22e's guard: no single seed's level that today's map holds within 5 points may fall further
#: than this from nominal.
SINGLE_RUN_GUARD: float = 0.10
#: The row entries study 22e averages over seeds before study 20b's rule reads them.
AVERAGED: tuple[str, ...] = tuple(f"coverage_{M.level_name(p)}" for p in M.INTERVAL_LEVELS) + (
    "halfwidth_median_95", "spearman_mean", "interval_score_95")


def run_type(name: str) -> str:
    """'seed2/capture/fern' -> 'capture/fern' (study 22e names its runs by seed first)."""
    head, _, rest = name.partition("/")
    return rest if head.startswith("seed") and rest else name


def seed_means(runs: dict, names) -> dict:
    """{run type: {map: row of ``AVERAGED`` entries averaged over the type's seeds}}."""
    types: dict[str, list[str]] = {}
    for n in runs:
        types.setdefault(run_type(n), []).append(n)
    return {t: {c: {k: float(np.mean([runs[n][c][k] for n in members])) for k in AVERAGED} | {"seeds": len(members)}
                for c in names} for t, members in types.items()}


def single_run_guard(runs: dict, candidate: str, today: str = TODAY) -> list[str]:
    """Study 22e's guard: the levels a single run loses by more than ``SINGLE_RUN_GUARD``."""
    out = []
    for n, r in runs.items():
        for p in RULE_LEVELS:
            key = f"coverage_{M.level_name(p)}"
            if abs(r[today][key] - p) <= 0.05 and abs(r[candidate][key] - p) > SINGLE_RUN_GUARD:
                out.append(f"{n}: coverage {M.level_name(p)} {100 * r[candidate][key]:.1f}%")
    return out


def decide(runs: dict, study: str = "22") -> str:
    today = BASELINE.get(study, TODAY)
    if study not in SEED_MEAN_STUDIES:
        return decide_by_checks(runs, today, JUDGED[study])
    verdict = decide_by_checks(seed_means(runs, (today, *JUDGED[study])), today, JUDGED[study])
    broken = single_run_guard(runs, JUDGED[study][0], today)
    if broken and verdict.startswith("taken"):
        return "today's stays (the guard: " + "; ".join(broken) + "). " + verdict.split(". ", 1)[1]
    return verdict + (f" | guard: {'; '.join(broken)}" if broken else "")


def report(results: dict) -> str:
    names = "/".join(M.level_name(p) for p in M.INTERVAL_LEVELS)
    title = {"22c": "Study 22c: the calibration views' interpolated bounds, judged again on seed-2 runs",
             "22d": "Study 22d: the free-space check with a fitted weight",
             "22e": "Study 22e: the weighted free-space check judged on three seeds",
             "22f": "Study 22f: interpolated bounds beside the weighted free-space check"}.get(
        results.get("study"), "Studies 22 and 22b: the free-space check, and the calibration views' bounds, beside the "
                              "depth-proportional term")
    lines = [f"# {title}", "",
             f"Command: `{results['command']}`", "", f"Rule (written before the candidates were rendered on these runs): {results['rule']}", "",
             f"Decision: **{results['decision']}**", "",
             f"| run | map | points | fitting points (median relative error) | rho | coverage {names} | median 95% "
             "half-width / depth | p90 | IS 95% / depth | CRPS / depth | depth Spearman (mean over photos) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for run, r in results["runs"].items():
        for cand in (c for c in CANDIDATES if c in r):
            c = r[cand]
            lines.append(f"| {run} | {cand} | {c['points']} | {c['fit_points']} ({100 * c['fit_median_rel_err']:.1f}%) "
                         f"| {c['rho']:.3g} | {interval_cells(c)} |")
    if results.get("study") in SEED_MEAN_STUDIES:
        lines += ["", "Means over seeds 2, 3 and 4 (what the rule reads):", "",
                  f"| run | map | seeds | coverage {names} | median 95% half-width / depth | IS 95% / depth "
                  "| depth Spearman |", "|---|---|---|---|---|---|---|"]
        for run, r in seed_means(results["runs"], RENDERED[results["study"]]).items():
            for cand, c in r.items():
                cov = "/".join(f"{100 * c[f'coverage_{M.level_name(p)}']:.1f}" for p in M.INTERVAL_LEVELS)
                lines.append(f"| {run} | {cand} | {c['seeds']} | {cov} | {100 * c['halfwidth_median_95']:.1f}% "
                             f"| {c['interval_score_95']:.3f} | {c['spearman_mean']:.3f} |")
    lines += ["", "Where the check fires (share of points with a free-space violation e > 0):", "",
              "| run | fitting points | scored points | scored points among the 10% largest relative errors |",
              "|---|---|---|---|"]
    for run, r in results["runs"].items():
        v = r["violations"]
        lines.append(f"| {run} | {100 * v['fit_violated']:.1f}% | {100 * v['scored_violated']:.1f}% "
                     f"| {100 * v['worst_decile_violated']:.1f}% |")
    if any("check_weight" in r for r in results["runs"].values()):
        lines += ["", "Weight beta of the violation the weighted map fitted (0: today's map): " + ", ".join(
            f"{run} {r['check_weight']:.3g}" for run, r in results["runs"].items() if "check_weight" in r) + "."]
    lines += ["", "Cost: the training views' reference depth renders once per run (`reference_s` in results.json, "
              "one thread); a view's check then costs what `calibrate --free-space` documents."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="NAME=RUN")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--study", choices=tuple(JUDGED), default="22",
                   help="Whose rule decides: 22 and 22b judge the check and the interpolated bounds, 22c the "
                        "interpolated bounds alone, 22d the weighted check alone, 22e the weighted check on "
                        "the means over seeds.")
    p.add_argument("--rows-from", action="append", default=[], metavar="PREFIX=RESULTS_JSON",
                   help="Take the rows of another results.json under PREFIX/<its run name> (study 22e: "
                        "seed 4's rows from 22d) instead of rendering them again.")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {"command": "python benchmarks/studies/free_space_floor_study.py "
                                + " ".join(sys.argv[1:] if argv is None else argv),
                     "rule": RULE_22E if args.study in SEED_MEAN_STUDIES else RULE, "runs": {}}
    done = {}
    if (args.out / "results.json").is_file():  # resume: rows of the same run folders are kept
        done = json.loads((args.out / "results.json").read_text())["runs"]
    for spec in args.rows_from:
        prefix, path = spec.split("=", 1)
        for name, row in json.loads(Path(path).read_text())["runs"].items():
            results["runs"][f"{prefix}/{name}"] = {k: v for k, v in row.items() if k not in CANDIDATES
                                                   or k in RENDERED[args.study]}
    for spec in args.run:
        name, run = spec.split("=", 1)
        if done.get(name, {}).get("run") == run:
            results["runs"][name] = done[name]
            print(f"[{name}] kept from {args.out / 'results.json'}", flush=True)
            continue
        data = collect(Path(run), RENDERED[args.study])
        res, curves = {"run": run, "views": [int(v) for v in data["views"]], "violations": violation_share(data),
                       "reference_s": data["reference_s"], "check_weight": data["check_weight"],
                       "check_weights": data["check_weights"]}, {}
        for cand in RENDERED[args.study]:
            res[cand], curves[cand] = evaluate_candidate(data, cand)
            print(f"[{name}] {cand}: rho {res[cand]['rho']:.3g}, coverage "
                  + "/".join(f"{100 * x:.1f}" for x in res[cand]["coverage"])
                  + f", 95% half-width {100 * res[cand]['halfwidth_median_95']:.1f}%, "
                  f"IS95 {res[cand]['interval_score_95']:.3f}, Spearman {res[cand]['spearman_mean']:.3f}", flush=True)
        plot_interval_reliability(args.out / f"{name.replace('/', '_')}.png", curves, title=f"{name}: photos no map saw")
        results["runs"][name] = res
        atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    results["study"] = args.study
    results["decision"] = decide(results["runs"], args.study)
    atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "README.md", report(results))
    print(results["decision"])


if __name__ == "__main__":
    main()
