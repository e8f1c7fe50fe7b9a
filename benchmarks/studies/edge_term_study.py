"""Study 30: an occlusion-edge term in the depth map, judged by its rule (docs/studies.md, fixed before
the rows ran).

The runs are study 29's ``occ`` rows (S-NeRF (default) with today's llff preset, paper split, seeds 7, 8
and 9, fern 1000 steps and flower 1750), trained once. Today's row is each run as it stands: its
calibration.json (``stochastic-fields calibrate``'s defaults) and its scores on the validation views,
study 29's. The candidate's row copies each run (checkpoint, config, stages) into
``--work``/sSEED/SCENE/snerf_default, fits its calibration again with the edge term
(``stochastic-fields calibrate --run COPY --edge-term --no-free-path``: gamma fitted by the CRPS on the held-out
capture points, 0 where edges do not explain the errors) and scores it on the same validation views
with ``stochastic-fields eval --views`` (cached in ``--work``/validation)::

    OMP_NUM_THREADS=1 python benchmarks/studies/edge_term_study.py --runs runs/occlusion_study \\
        --work runs/edge_study --out benchmarks/results/edge_term_study

Nothing is trained: colour and depth means are the runs' own, so PSNR and abs-rel cannot move; the
rule reads the intervals and the ranking.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from stochastic_fields import metrics as M

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules and scoring
from tables_cap_study import (COVERAGE_TOLERANCE, RULE_LEVELS, SCENES, fmt, score_run, table_head,  # noqa: E402
                              table_row, validation_views, verdict_lines, write_study)
from tables_steps_study import seed_mean  # noqa: E402

SEEDS = (7, 8, 9)
METHOD = "snerf_default"
ROWS = ("today", "edge term (candidate)")
#: Files of a trained run the candidate's copy needs (its calibration is fitted again).
RUN_FILES = ("checkpoint.pt", "config.json", "stages.json", "train_log.jsonl")
#: The pooled depth Spearman may fall at most this much.
MAX_SPEARMAN_LOSS = 0.01
#: Scores that must not grow on either scene (key, name); one of the first two must fall on one scene.
SHARPNESS = (("halfwidth_median_95", "median 95% half-width"), ("interval_score_95", "95% interval score"),
             ("crps", "CRPS"))


def candidate_run(source: Path, copy: Path) -> Path:
    """``copy``, a copy of the trained ``source`` run calibrated with the edge term (skipped when done)."""
    if (copy / "calibration.json").is_file():
        return copy
    copy.mkdir(parents=True, exist_ok=True)
    for name in RUN_FILES:
        shutil.copy2(source / name, copy / name)
    subprocess.run([sys.executable, "-m", "stochastic_fields.cli", "calibrate", "--run", str(copy), "--edge-term",
                    "--no-free-path"], check=True)  # the scores read the depth map only
    return copy


def edge_weight(run: Path) -> float:
    """The gamma the run's depth map holds (0: none)."""
    return float(json.loads((run / "calibration.json").read_text())["depth"].get("edge_weight", 0.0))


def level_ok(today: float | None, candidate: float | None, p: float) -> bool:
    """Within the tolerance of nominal where today's is; elsewhere no farther from nominal than today's."""
    if candidate is None or today is None:
        return False
    if abs(today - p) <= COVERAGE_TOLERANCE:
        return abs(candidate - p) <= COVERAGE_TOLERANCE
    return abs(candidate - p) <= abs(today - p)


def verdict(means: dict) -> tuple[bool, list[str]]:
    """The rule on the seed means of each scene (docs/studies.md, study 30)."""
    today, cand = ROWS
    failed, sharper = [], False
    for scene in SCENES:
        t, c = means[today][scene], means[cand][scene]
        for p in RULE_LEVELS:
            name = M.level_name(p)
            if not level_ok(t["coverage"][name], c["coverage"][name], p):
                failed.append(f"{scene}: {name}% coverage {fmt(c['coverage'][name], '{:.3f}')} against "
                              f"{fmt(t['coverage'][name], '{:.3f}')}")
        for key, name in SHARPNESS:
            if c[key] > t[key]:
                failed.append(f"{scene}: {name} {c[key]:.4f} against {t[key]:.4f}")
        sharper |= any(c[key] < t[key] for key, _ in SHARPNESS[:2])
        if c["spearman"] < t["spearman"] - MAX_SPEARMAN_LOSS:
            failed.append(f"{scene}: depth Spearman {c['spearman']:.3f} against {t['spearman']:.3f}")
    if not sharper:
        failed.append("neither scene's median 95% half-width nor 95% interval score fell")
    return not failed, failed


def report(rows: dict, means: dict, weights: dict, taken: bool, failed: list[str], views: dict) -> str:
    lines = ["# Study 30: an occlusion-edge term in the depth map", "",
             f"Paper split, study 29's `occ` runs (S-NeRF (default), seeds {', '.join(map(str, SEEDS))}, fern 1000 "
             "steps, flower 1750), calibrated as today and with `--edge-term`; scored on the validation views "
             f"({', '.join(f'{s} {len(v)}' for s, v in views.items())}) with `stochastic-fields eval --views` "
             "(depth at the SCORE capture points they see; intervals cross-fitted). Command: the module docstring "
             "of `benchmarks/studies/edge_term_study.py`.", "",
             "Means over the seeds:", "", *table_head("depth map")]
    for scene in SCENES:
        for label in ROWS:
            lines.append(table_row(scene, METHOD, label, means[label][scene]))
    lines += ["", "Fitted edge weight gamma (each seed) and the median 95% half-width per seed:", "",
              "| scene | gamma | " + " | ".join(f"seed {s}: today / candidate" for s in SEEDS) + " |",
              "|---|---|" + "---|" * len(SEEDS)]
    for scene in SCENES:
        cells = [f"{100 * a['halfwidth_median_95']:.1f}% / {100 * b['halfwidth_median_95']:.1f}%"
                 for a, b in zip(rows[ROWS[0]][scene], rows[ROWS[1]][scene])]
        lines.append(f"| {scene} | {', '.join(f'{w:.3g}' for w in weights[scene])} | " + " | ".join(cells) + " |")
    lines += verdict_lines(taken, failed)
    lines += ["", "How this was run: the command of the script's docstring, one thread, beside other work (the "
              "calibration's cost is not a row). The decision and what it shows: docs/studies.md, study 30."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/occlusion_study"), help="Study 29's runs (sSEED/occ).")
    ap.add_argument("--work", type=Path, default=Path("runs/edge_study"), help="The candidate's copies and scores.")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/edge_term_study"))
    args = ap.parse_args()
    views = {scene: validation_views(scene) for scene in SCENES}
    rows = {label: {scene: [] for scene in SCENES} for label in ROWS}
    weights = {scene: [] for scene in SCENES}
    for seed in SEEDS:
        for scene in SCENES:
            source = args.runs / f"s{seed}" / "occ" / scene / METHOD
            rows[ROWS[0]][scene].append(
                score_run(source, views[scene], args.runs / "validation" / f"s{seed}" / "occ" / scene / METHOD))
            copy = candidate_run(source, args.work / f"s{seed}" / scene / METHOD)
            weights[scene].append(edge_weight(copy))
            rows[ROWS[1]][scene].append(
                score_run(copy, views[scene], args.work / "validation" / f"s{seed}" / scene / METHOD))
    means = {label: {scene: seed_mean(rows[label][scene]) for scene in SCENES} for label in ROWS}
    taken, failed = verdict(means)
    write_study(args.out, {"study": 30, "rows": rows, "means": means, "edge_weights": weights, "seeds": list(SEEDS),
                           "validation_views": views, "taken": taken, "failed": failed},
                report(rows, means, weights, taken, failed, views))


if __name__ == "__main__":
    main()
