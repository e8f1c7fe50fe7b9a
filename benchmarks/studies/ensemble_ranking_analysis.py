"""Analysis: the deep ensemble's depth ranking under study 39's objective (decides nothing).

Study 39's candidate (``field.grid_decoder_width`` 64, ``field.grid_feature_dim`` 16,
``loss.lambda_smoothness`` 60) lowers S-NeRF's flower depth Spearman (|error| against std) on the
validation photos. Issue 36 compares that ranking with the deep ensemble's, and the candidate would
train every method, so the comparison that matters is with the ensemble trained with the same
objective. The ensemble's rows (flower, paper split, the tables' budget, one thread, seeds 12-14, ARM
``today`` as is and ``wide_smooth`` with study 39's three settings)::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes flower --methods ensemble --seed SEED \\
        --no-timing --quiet [--set field.grid_decoder_width=64 --set field.grid_feature_dim=16 \\
        --set loss.lambda_smoothness=60] --out runs/ens_rank/sSEED/ARM

each scored on study 39's validation photos (``tables_cap_study.score_run``, cached in
``runs/ens_rank/validation/sSEED/ARM``), then::

    python benchmarks/studies/ensemble_ranking_analysis.py --runs runs/ens_rank \\
        --out benchmarks/results/ensemble_ranking_analysis

S-NeRF's and the deterministic NeRF's rows are study 39's committed results (same seeds, views and code).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules and scoring

from tables_cap_study import score_run, table_head, table_row, validation_views, write_study  # noqa: E402

SCENE = "flower"
#: Study 39's committed results: S-NeRF's and the deterministic NeRF's rows per seed.
STUDY_39 = Path(__file__).resolve().parents[1] / "results" / "wide_smooth_paper_study" / "results.json"
#: ARM folder -> study 39's row label of the same configuration.
ARMS = {"today": "32 / 8, 0 (today)", "wide_smooth": "64 / 16, 60 (candidate)"}
SEEDS = (12, 13, 14)
METHODS = ("snerf_default", "deterministic", "ensemble")


def mean_row(rows: list[dict]) -> dict:
    """The seed mean of the scores ``table_row`` prints (coverage per level included)."""
    def avg(key):
        values = [r[key] for r in rows if r[key] is not None]
        return statistics.fmean(values) if values else None

    out = {k: avg(k) for k in ("psnr", "ssim", "abs_rel", "spearman", "halfwidth_median_95", "interval_score_95",
                               "crps", "train_s")}
    out["points"] = round(statistics.fmean(r["points"] for r in rows))
    out["coverage"] = {level: statistics.fmean(r["coverage"][level] for r in rows) for level in rows[0]["coverage"]}
    return out


def collect(runs: Path, seeds: tuple[int, ...]) -> dict:
    """{arm: {method: [score per seed]}}: the ensemble's scored here, the others read from study 39."""
    study = json.loads(STUDY_39.read_text())
    missing = [s for s in seeds if s not in study["seeds"]]
    if missing:
        raise SystemExit(f"{STUDY_39}: study 39 has no rows for seeds {missing}")
    position = {s: study["seeds"].index(s) for s in seeds}
    views = validation_views(SCENE)
    rows = {}
    for arm, label in ARMS.items():
        rows[arm] = {m: [study["rows"][label][SCENE][m][position[s]] for s in seeds] for m in METHODS[:2]}
        rows[arm]["ensemble"] = [score_run(runs / f"s{s}" / arm / SCENE / "ensemble", views,
                                           runs / "validation" / f"s{s}" / arm / SCENE / "ensemble") for s in seeds]
    return rows


def report(rows: dict, seeds: tuple[int, ...]) -> tuple[str, dict]:
    means = {arm: {m: mean_row(rows[arm][m]) for m in METHODS} for arm in ARMS}
    lines = ["# Analysis: the deep ensemble's depth ranking under study 39's objective", "",
             f"Flower, paper split, the tables' budget, seeds {', '.join(map(str, seeds))}, scored on study 39's "
             "validation photos. Ensemble rows trained and scored here; S-NeRF's and the deterministic NeRF's are "
             "study 39's (`../wide_smooth_paper_study/`). Commands: the docstring of "
             "`benchmarks/studies/ensemble_ranking_analysis.py`.", "", "Means over the seeds:", "",
             *table_head("objective")]
    for m in METHODS:
        for arm, label in ARMS.items():
            lines.append(table_row(SCENE, m, label, means[arm][m]))
    lines += ["", "Depth Spearman per seed (today -> candidate):", "",
              "| method | " + " | ".join(f"seed {s}" for s in seeds) + " | mean |", "|---|" + "---|" * (len(seeds) + 1)]
    for m in METHODS:
        cells = [f"{a['spearman']:.3f} -> {b['spearman']:.3f}" for a, b in zip(rows["today"][m], rows["wide_smooth"][m])]
        lines.append(f"| {m} | " + " | ".join(cells) +
                     f" | {means['today'][m]['spearman']:.3f} -> {means['wide_smooth'][m]['spearman']:.3f} |")
    s, e = means["wide_smooth"]["snerf_default"]["spearman"], means["wide_smooth"]["ensemble"]["spearman"]
    outcome = ("at most S-NeRF's: the candidate does not lose issue 36's fourth target on flower"
               if e <= s else "above S-NeRF's: the candidate would lose issue 36's fourth target on flower")
    lines += ["", f"Under the candidate's objective the ensemble's mean depth Spearman is {e:.3f}, S-NeRF's {s:.3f}: "
              f"{outcome} (the consequence written before the rows, docs/studies.md)."]
    return "\n".join(lines) + "\n", means


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/ens_rank"), help="Folder holding sSEED/ARM/flower/ensemble.")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/ensemble_ranking_analysis"))
    args = ap.parse_args()
    seeds = tuple(args.seeds)
    rows = collect(args.runs, seeds)
    text, means = report(rows, seeds)
    write_study(args.out, {"seeds": list(seeds), "rows": rows, "means": means}, text)


if __name__ == "__main__":
    main()
