"""Analysis: the deep ensemble's depth ranking under study 39's objective (decides nothing).

Study 39's candidate (``field.grid_decoder_width`` 64, ``field.grid_feature_dim`` 16,
``loss.lambda_smoothness`` 60) lowers S-NeRF's flower depth Spearman (|error| against std) on the
validation photos. Issue 36 compares that ranking with the deep ensemble's, and the candidate would
train every method, so the comparison that matters is with the ensemble trained with the same
objective. The ensemble's rows (flower, paper split, the tables' budget, one thread, ARM ``wide_smooth``
with study 39's three settings, ARM ``today`` as is; seed 12, ``--seeds`` takes more)::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes flower --methods ensemble --seed SEED \\
        --no-timing --quiet [--set field.grid_decoder_width=64 --set field.grid_feature_dim=16 \\
        --set loss.lambda_smoothness=60] --out runs/ens_rank/sSEED/ARM

each scored on study 39's validation photos (``tables_cap_study.score_run``, cached in
``runs/ens_rank/validation/sSEED/ARM``), then::

    python benchmarks/studies/ensemble_ranking_analysis.py --runs runs/ens_rank \\
        --out benchmarks/results/ensemble_ranking_analysis

S-NeRF's and the deterministic NeRF's rows are study 39's committed results (same seeds, views and code).

**The synthetic scene** (issue 36 compares the same ranking there; the ensemble's last measurement
predates study 32's box). The synthetic validation scenes of seeds 1 and 2 (``make_synthetic_scene(path,
seed=S)``), both methods trained with the ``demo`` preset and evaluated
on the scene's test views::

    stochastic-fields train --preset demo [--method ensemble] --data.path runs/synth/sceneS \
        --train.seed S --out RUN --quiet
    stochastic-fields eval --run RUN --quiet --out RUN/eval

with RUN ``runs/synth/runS`` for S-NeRF and ``runs/ens_rank/synth/runS`` for the ensemble
(``--synthetic-snerf`` and ``--synthetic-ensemble``). Each eval folder gives both the scores (its
metrics.json) and the per-view maps the cross-ranking reads (each method's std against the other's errors).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules and scoring

from tables_cap_study import score_run, table_head, table_row, validation_views, write_study  # noqa: E402
from tables_steps_study import seed_mean  # noqa: E402

from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402

SCENE = "flower"
#: Study 39's committed results: S-NeRF's and the deterministic NeRF's rows per seed.
STUDY_39 = Path(__file__).resolve().parents[1] / "results" / "wide_smooth_paper_study" / "results.json"
#: ARM folder -> study 39's row label of the same configuration.
ARMS = {"today": "32 / 8, 0 (today)", "wide_smooth": "64 / 16, 60 (candidate)"}
SEEDS = (12,)
#: Seeds whose ensemble also trained under today's objective (the pair that shows how far it moves).
TODAY_SEEDS = (12,)
METHODS = ("snerf_default", "deterministic", "ensemble")


def collect(runs: Path, seeds: tuple[int, ...], today_seeds: tuple[int, ...]) -> dict:
    """{arm: {method: {seed: score}}}: the ensemble's scored here (today's objective on ``today_seeds``
    only), S-NeRF's and the deterministic NeRF's read from study 39."""
    study = json.loads(STUDY_39.read_text())
    missing = [s for s in seeds if s not in study["seeds"]]
    if missing:
        raise SystemExit(f"{STUDY_39}: study 39 has no rows for seeds {missing}")
    position = {s: study["seeds"].index(s) for s in seeds}
    views = validation_views(SCENE)
    rows = {}
    for arm, label in ARMS.items():
        rows[arm] = {m: {s: study["rows"][label][SCENE][m][position[s]] for s in seeds} for m in METHODS[:2]}
        rows[arm]["ensemble"] = {s: score_run(runs / f"s{s}" / arm / SCENE / "ensemble", views,
                                              runs / "validation" / f"s{s}" / arm / SCENE / "ensemble")
                                 for s in (today_seeds if arm == "today" else seeds)}
    return rows


def synthetic_scores(run: Path) -> dict:
    """Depth ranking and accuracy of one synthetic run's ``eval`` (its metrics.json)."""
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    summary, depth = metrics["summary"], metrics["pooled"]["depth"]
    return {"psnr": summary["psnr"]["mean"], "abs_rel": depth["abs_rel"], "points": depth["num_used"],
            "spearman_views": summary["depth/spearman"]["mean"], "spearman_pooled": depth["spearman"],
            "coverage_68": depth["coverage_68"], "coverage_95": depth["coverage_95"]}


def synthetic_lines(rows: dict, seeds: tuple[int, ...]) -> list[str]:
    """The synthetic validation scenes' table, ``rows``: {seed: {method: synthetic_scores}}."""
    lines = ["", "## The synthetic validation scenes (demo preset, every test view, exact depth)", "",
             "| scene seed | method | PSNR | depth abs-rel | depth Spearman (views) | pooled | cov 68 / 95 | pixels |",
             "|---|---|---|---|---|---|---|---|"]
    for s in seeds:
        for m, r in rows[s].items():
            lines.append(f"| {s} | {m} | {r['psnr']:.2f} | {r['abs_rel']:.4f} | {r['spearman_views']:.3f} | "
                         f"{r['spearman_pooled']:.3f} | {100 * r['coverage_68']:.1f} / {100 * r['coverage_95']:.1f} | "
                         f"{r['points']} |")
    mean = {m: statistics.fmean(rows[s][m]["spearman_views"] for s in seeds) for m in ("snerf_default", "ensemble")}
    return lines + ["", f"Mean depth Spearman per view: S-NeRF {mean['snerf_default']:.3f}, "
                        f"ensemble {mean['ensemble']:.3f}."]


def cross_ranking(snerf_views: Path, ensemble_views: Path, depths: Path) -> dict:
    """Mean over the views of Spearman(|error of A|, std of B) for A, B in (S-NeRF, ensemble), on the
    pixels both render with opacity > ``OPACITY_MASK`` and the exact depth is positive: does each
    method's std rank the other's errors? Also each method's error against the other's."""
    pairs = {}
    for path in sorted(snerf_views.glob("view_*.npz")):
        view = int(path.stem.split("_")[1])
        s, e = np.load(path), np.load(ensemble_views / path.name)
        gt = np.load(depths / f"frame_{view:03d}.npy")
        keep = (s["opacity"] > OPACITY_MASK) & (e["opacity"] > OPACITY_MASK) & np.isfinite(gt) & (gt > 0)
        err = {"snerf_default": np.abs(s["depth_mean"] - gt)[keep], "ensemble": np.abs(e["depth_mean"] - gt)[keep]}
        std = {"snerf_default": s["depth_std"][keep], "ensemble": e["depth_std"][keep]}
        for a in err:
            for b in std:
                pairs.setdefault(f"{a} error ~ {b} std", []).append(spearmanr(err[a], std[b]).statistic)
        pairs.setdefault("snerf_default error ~ ensemble error", []).append(spearmanr(*err.values()).statistic)
    return {k: float(np.nanmean(v)) for k, v in pairs.items()} | {"views": len(next(iter(pairs.values())))}


def cross_lines(cross: dict, seed: int) -> list[str]:
    rows = [f"| {k.split(' ~ ')[0]} | {k.split(' ~ ')[1]} | {v:.3f} |" for k, v in cross.items() if k != "views"]
    return ["", f"Each method's std against the other's errors (scene seed {seed}, mean over {cross['views']} views of "
            "the Spearman on the pixels both render opaque, |error| against the exact depth):", "",
            "| errors of | ranked by | Spearman |", "|---|---|---|", *rows]


def with_int_seeds(rows: dict) -> dict:
    """``rows`` as read back from results.json (JSON turns the seed keys into strings)."""
    return {k: with_int_seeds(v) if isinstance(v, dict) and k not in ("coverage",) else v
            for k, v in ((int(k) if isinstance(k, str) and k.isdigit() else k, v) for k, v in rows.items())}


def full_report(results: dict) -> str:
    """README.md from results.json's content: the flower table, then the synthetic one if measured."""
    text = report(results["rows"], tuple(results["seeds"]))
    if "synthetic" in results:
        text += "\n".join(synthetic_lines(results["synthetic"], tuple(results["synthetic_seeds"]))) + "\n"
    for seed, cross in results.get("cross_ranking", {}).items():
        text += "\n".join(cross_lines(cross, seed)) + "\n"
    return text


def seed_means(rows: dict) -> dict:
    """{arm: {method: the mean over the seeds that row has}}."""
    return {arm: {m: seed_mean(list(rows[arm][m].values())) for m in METHODS} for arm in ARMS}


def report(rows: dict, seeds: tuple[int, ...]) -> str:
    means = seed_means(rows)
    today_seeds = sorted(rows["today"]["ensemble"])
    lines = ["# Analysis: the deep ensemble's depth ranking under study 39's objective", "",
             f"Flower, paper split, the tables' budget, seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}, "
             "scored on study 39's "
             "validation photos. Ensemble rows trained and scored here (today's objective on seed "
             f"{', '.join(map(str, today_seeds))} only); S-NeRF's and the deterministic NeRF's are study 39's "
             "(`../wide_smooth_paper_study/`). Commands: the docstring of "
             "`benchmarks/studies/ensemble_ranking_analysis.py`.", "", "Means over the seeds each row has:", "",
             *table_head("objective")]
    for m in METHODS:
        for arm, label in ARMS.items():
            lines.append(table_row(SCENE, m, label, means[arm][m]))
    lines += ["", "Depth Spearman per seed (today -> candidate):", "",
              "| method | " + " | ".join(f"seed {s}" for s in seeds) + " | mean |", "|---|" + "---|" * (len(seeds) + 1)]
    for m in METHODS:
        def cell(s):
            before = rows["today"][m].get(s)
            return f"{'-' if before is None else format(before['spearman'], '.3f')} -> {rows['wide_smooth'][m][s]['spearman']:.3f}"
        lines.append(f"| {m} | " + " | ".join(cell(s) for s in seeds) +
                     f" | {means['today'][m]['spearman']:.3f} -> {means['wide_smooth'][m]['spearman']:.3f} |")
    s, e = means["wide_smooth"]["snerf_default"]["spearman"], means["wide_smooth"]["ensemble"]["spearman"]
    outcome = ("at most S-NeRF's, so the candidate does not lose issue 36's fourth target on flower"
               if e <= s else "above S-NeRF's, so the candidate would lose issue 36's fourth target on flower")
    lines += ["", f"Under the candidate's objective the ensemble's mean depth Spearman is {e:.3f}, S-NeRF's {s:.3f}: "
              f"{outcome} (the consequence written before the rows, docs/studies.md)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/ens_rank"), help="Folder holding sSEED/ARM/flower/ensemble.")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--today-seeds", type=int, nargs="*", default=list(TODAY_SEEDS),
                    help="Seeds with an ensemble row under today's objective (context; the candidate's decides).")
    ap.add_argument("--synthetic-snerf", type=Path, default=Path("runs/synth"), help="Folder of S-NeRF's runS.")
    ap.add_argument("--synthetic-ensemble", type=Path, default=Path("runs/ens_rank/synth"),
                    help="Folder of the ensemble's runS.")
    ap.add_argument("--synthetic-seeds", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/ensemble_ranking_analysis"))
    args = ap.parse_args()
    seeds = tuple(args.seeds)
    rows = collect(args.runs, seeds, tuple(args.today_seeds))
    results = {"seeds": list(seeds), "rows": rows, "means": seed_means(rows)}
    if args.synthetic_seeds:
        results["synthetic_seeds"] = list(args.synthetic_seeds)
        results["synthetic"] = {s: {"snerf_default": synthetic_scores(args.synthetic_snerf / f"run{s}"),
                                    "ensemble": synthetic_scores(args.synthetic_ensemble / f"run{s}")}
                                for s in args.synthetic_seeds}
        results["cross_ranking"] = {s: cross_ranking(args.synthetic_snerf / f"run{s}" / "eval" / "views",
                                                     args.synthetic_ensemble / f"run{s}" / "eval" / "views",
                                                     args.synthetic_snerf / f"scene{s}" / "depth")
                                    for s in args.synthetic_seeds}
    write_study(args.out, results, full_report(results))


if __name__ == "__main__":
    main()
