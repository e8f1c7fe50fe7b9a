"""Study 27: twice the tables' training steps at the paper split (1000 against 2000), judged by its rule.

The rows are ``benchmarks/eval_tables.py`` runs (S-NeRF (default) and the deterministic NeRF, paper
split, one thread), seeds 1, 2 and 3, today's steps and the candidate's::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods deterministic snerf_default \\
        --seed SEED --iterations STEPS --no-timing --quiet --out runs/steps_study/sSEED/STEPS

Seed 1 at 1000 steps is study 26's 250k row (``--seed1-runs``: ``runs/cap_study/cap_250k``, trained by
the same code and command). Each run is scored on its **validation views** as study 26 scores them
(``tables_cap_study.score_run``: ``stochastic-fields eval --views`` on the paper split's held-out
photos the tables do not score), and the rule (docs/studies.md, fixed before the rows ran) is applied
to the means over the seeds::

    python benchmarks/studies/tables_steps_study.py --out benchmarks/results/tables_steps_study

The tables' own test-view scores (each run's metrics.json) are not read.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules and scoring
from tables_cap_study import (METHODS, SCENES, fmt, scene_checks, score_run, table_head, table_row,  # noqa: E402
                              validation_views, verdict_lines, write_study)

#: Row label -> training steps (today's first).
ROWS = {"1000 (today)": 1000, "2000 (candidate)": 2000}
SEEDS = (1, 2, 3)
#: What each score's seed mean is taken of (None where a run has none: the deterministic NeRF's intervals).
MEAN_KEYS = ("psnr", "ssim", "abs_rel", "spearman", "halfwidth_median_95", "interval_score_95", "crps", "train_s")


def run_folders(runs: Path, seed1_runs: Path, seed: int, steps: int, scene: str, method: str) -> tuple[Path, Path]:
    """(run folder, its validation scores' folder): seed 1's 1000-step rows are study 26's."""
    if seed == 1 and steps == 1000:
        return seed1_runs / scene / method, seed1_runs.parent / "validation" / seed1_runs.name / scene / method
    return runs / f"s{seed}" / str(steps) / scene / method, runs / "validation" / f"s{seed}" / str(steps) / scene / method


def seed_mean(per_seed: list[dict]) -> dict:
    """The mean over seeds of each score (coverage per level); None where any seed lacks it."""
    out = {}
    for key in MEAN_KEYS:
        values = [r[key] for r in per_seed]
        out[key] = None if any(v is None for v in values) else statistics.fmean(values)
    out["coverage"] = {}
    for name in per_seed[0]["coverage"]:
        values = [r["coverage"][name] for r in per_seed]
        out["coverage"][name] = None if any(v is None for v in values) else statistics.fmean(values)
    out["points"] = round(statistics.fmean(r["points"] or 0 for r in per_seed))  # per seed
    return out


def verdict(means: dict) -> tuple[bool, list[str]]:
    """The rule on the seed means: study 26's checks on both scenes (docs/studies.md, study 27)."""
    today, cand = ROWS
    failed = [f for scene in SCENES for f in scene_checks(scene, means[today][scene], means[cand][scene])]
    return not failed, failed


def report(rows: dict, means: dict, taken: bool, failed: list[str], views: dict) -> str:
    lines = ["# Study 27: twice the tables' training steps at the paper split", "",
             f"Paper split, seeds {', '.join(map(str, SEEDS))}, the tables' CPU budget (250k cells) at 1000 and 2000 "
             "steps, one thread; scored on the validation views (held-out photos the tables do not score: "
             f"{', '.join(f'{s} {len(v)}' for s, v in views.items())}) with `stochastic-fields eval --views` (depth "
             "at the SCORE capture points they see; S-NeRF's intervals cross-fitted). Commands: the module "
             "docstring of `benchmarks/studies/tables_steps_study.py`.", "",
             "Means over the seeds:", "",
             *table_head("steps")]
    for scene in SCENES:
        for m in METHODS:
            for label in ROWS:
                lines.append(table_row(scene, m, label, means[label][scene][m]))
    lines += ["", "Each seed (PSNR dB / depth abs-rel / train s):", "",
              "| scene | method | steps | " + " | ".join(f"seed {s}" for s in SEEDS) + " |",
              "|---|---|---|" + "---|" * len(SEEDS)]
    for scene in SCENES:
        for m in METHODS:
            for label in ROWS:
                cells = [f"{r['psnr']:.2f} / {fmt(r['abs_rel'], '{:.4f}')} / {r['train_s']:.0f}"
                         for r in rows[label][scene][m]]
                lines.append(f"| {scene} | {m} | {label} | " + " | ".join(cells) + " |")
    lines += verdict_lines(taken, failed)
    lines += ["", "How this was run: the row commands of the script's docstring, fern's one after the other in "
              "one shell chain and flower's in a second beside it (`OMP_NUM_THREADS=1`; flower's seed-3 rows in two "
              "processes once fern's chain had ended), each run scored on its "
              "validation views right after its training. Other work shared the machine during some 2000-step rows, "
              "so the training seconds are not a clean cost (the cost is the steps: twice). Then `python "
              "benchmarks/studies/tables_steps_study.py "
              "--out benchmarks/results/tables_steps_study`. The decision and what it shows: docs/studies.md, study 27."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/steps_study"), help="Folder holding sSEED/STEPS.")
    ap.add_argument("--seed1-runs", type=Path, default=Path("runs/cap_study/cap_250k"),
                    help="Study 26's 250k runs: seed 1 at 1000 steps.")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/tables_steps_study"))
    args = ap.parse_args()
    views = {scene: validation_views(scene) for scene in SCENES}

    def score(seed: int, steps: int, scene: str, method: str) -> dict:
        run, scores = run_folders(args.runs, args.seed1_runs, seed, steps, scene, method)
        return score_run(run, views[scene], scores)

    rows = {label: {scene: {m: [score(seed, steps, scene, m) for seed in SEEDS] for m in METHODS} for scene in SCENES}
            for label, steps in ROWS.items()}
    means = {label: {scene: {m: seed_mean(rows[label][scene][m]) for m in METHODS} for scene in SCENES} for label in ROWS}
    taken, failed = verdict(means)
    write_study(args.out, {"rows": rows, "means": means, "seeds": list(SEEDS), "validation_views": views,
                           "taken": taken, "failed": failed}, report(rows, means, taken, failed, views))

if __name__ == "__main__":
    main()
