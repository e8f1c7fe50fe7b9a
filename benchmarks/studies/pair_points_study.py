"""Study 38: calibration views that render the capture points either view of their pair observed.

A calibration view sits halfway between two neighbouring training views; today it renders the held-out
capture points that *both* views observed (``calibration.pair_visible_points``), the points best seen
from the training views. The validation photos score every SCORE point they see. The candidate renders
the points *either* view observed. Calibration only: the runs are study 37's (paper split, seeds 12-14,
both arms), each S-NeRF run copied, recalibrated with the candidate (``calibrate_run``, today's other
settings) and scored on the same validation photos; today's rows are study 37's own scores.

Rule (fixed before the rows; docs/studies.md, study 38), on the seed means of today's field (decoder
32 / 8), both scenes:

1. every level at 50 / 68 / 90 / 95% that today's holds within 5 points stays within 5 points;
2. the mean distance from nominal over those four levels falls on at least one scene and grows by
   at most 0.5 points on the other;
3. the 95% interval score / depth and the CRPS / depth grow by at most 2% on each scene;
4. the depth Spearman (|error| against std) falls by at most 0.02 on each scene.

If taken, study 37 is judged again by its own rule with both of its arms recalibrated this way (the
deterministic NeRF's rows are unchanged: it has no map). Command (one thread, resumable)::

    OMP_NUM_THREADS=1 python benchmarks/studies/pair_points_study.py --arms today wide \
        --source runs/colour_capacity_paper --runs runs/pair_points --out benchmarks/results/pair_points_study

Study 39's candidate recalibrated the same way (after its verdict; decides nothing)::

    OMP_NUM_THREADS=1 python benchmarks/studies/pair_points_study.py --arms wide_smooth \
        --source runs/wide_smooth_paper --out benchmarks/results/wide_smooth_paper_study/either_calibration
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import write_study  # noqa: E402
from tables_cap_study import RULE_LEVELS, holds, score_run, validation_views  # noqa: E402
import tables_steps_study as steps  # noqa: E402

from stochastic_fields import calibration  # noqa: E402
from stochastic_fields import metrics as M  # noqa: E402

SEEDS = (12, 13, 14)
SCENES = ("fern", "flower")
MAX_DISTANCE_GROWTH = 0.005  # 0.5 points of coverage
MAX_SCORE_GROWTH = 0.02  # relative
MAX_SPEARMAN_LOSS = 0.02
#: The files a recalibrated copy needs (the trained weights and what eval reads besides the map).
COPIED = ("checkpoint.pt", "config.json", "stages.json", "train_log.jsonl", "curves.npz")


def recalibrated(source: Path, target: Path) -> Path:
    """``source`` run copied to ``target`` and calibrated there with the candidate's points (cached)."""
    if (target / calibration.CALIBRATION_FILE).is_file():
        return target
    target.mkdir(parents=True, exist_ok=True)
    for name in COPIED:
        if (source / name).is_file():
            shutil.copy2(source / name, target / name)
    calibration.calibrate_run(target, progress=False, pair_points="either")
    return target


def link(source: Path, target: Path) -> None:
    """``target`` a symlink to ``source`` (the rows the candidate does not change)."""
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        target.symlink_to(source.resolve(), target_is_directory=True)


def distance(coverage: dict) -> float:
    """Mean |coverage - nominal| over the rule's levels."""
    return statistics.fmean(abs(coverage[M.level_name(p)] - p) for p in RULE_LEVELS)


def verdict(today: dict, cand: dict) -> tuple[bool, list[str]]:
    """Study 38's rule (module doc) on the seed means of S-NeRF per scene ({scene: scores})."""
    failed, fell = [], []
    for scene in SCENES:
        t, c = today[scene], cand[scene]
        for p in RULE_LEVELS:
            n = M.level_name(p)
            if holds(t["coverage"][n], p) and not holds(c["coverage"][n], p):
                failed.append(f"{scene}: {n}% coverage {100 * c['coverage'][n]:.1f}")
        dt, dc = distance(t["coverage"]), distance(c["coverage"])
        fell.append(dc < dt)
        if dc > dt + MAX_DISTANCE_GROWTH:
            failed.append(f"{scene}: mean distance from nominal {100 * dc:.2f} against {100 * dt:.2f} points")
        for key in ("interval_score_95", "crps"):
            if c[key] > t[key] * (1 + MAX_SCORE_GROWTH):
                failed.append(f"{scene}: {key} {c[key]:.4f} against {t[key]:.4f}")
        if c["spearman"] < t["spearman"] - MAX_SPEARMAN_LOSS:
            failed.append(f"{scene}: depth Spearman {c['spearman']:.3f} against {t['spearman']:.3f}")
    if not any(fell):
        failed.append("the mean distance from nominal falls on no scene")
    return not failed, failed


#: The head of the tables ``row`` fills.
TABLE_HEAD = ("| scene | points of a calibration view, field | PSNR | depth abs-rel | depth Spearman | points scored | "
              "cov 50 / 68 / 90 / 95 / 99 | distance | median 95% half-width | IS95 / depth | CRPS / depth |",
              "|---|---|---|---|---|---|---|---|---|---|---|")


def row(scene: str, label: str, m: dict) -> str:
    cov = " / ".join(f"{100 * m['coverage'][n]:.1f}" for n in ("50", "68", "90", "95", "99"))
    return (f"| {scene} | {label} | {m['psnr']:.2f} | {m['abs_rel']:.4f} | {m['spearman']:.3f} | {m['points']} | {cov} | "
            f"{100 * distance(m['coverage']):.2f} | {100 * m['halfwidth_median_95']:.1f}% | {m['interval_score_95']:.3f} | "
            f"{m['crps']:.4f} |")


def write_study_39_either(args: argparse.Namespace, views: dict) -> None:
    """Study 39's candidate runs recalibrated with either-view points, beside their own maps and today's
    (study 37's today rows): ``--out`` study.md / study.json. Measured after study 39's verdict; decides
    nothing."""
    _, both = steps.scored_rows(args.source, steps.STUDIES[39].rows, SEEDS, views, methods=("snerf_default",))
    _, either = steps.scored_rows(args.runs, {"either": "wide_smooth"}, SEEDS, views, methods=("snerf_default",))
    rows = {"both, 32 / 8 / 0 (today)": both["32 / 8, 0 (today)"], "both, 64 / 16 / 60": both["64 / 16, 60 (candidate)"],
            "either, 64 / 16 / 60": either["either"]}
    lines = ["# Study 39's candidate with calibration views rendering the points either view of their pair observed", "",
             "Study 39's candidate runs (decoder 64, 16 features, depth smoothness 60; paper split, seeds 12-14) "
             "recalibrated with `--pair-points either` and scored on the validation photos, beside their own maps "
             "and today's rows. Measured after study 39's verdict: decides nothing. Means over the seeds.", "",
             *TABLE_HEAD]
    for scene in SCENES:
        for label, scenes in rows.items():
            lines.append(row(scene, label, scenes[scene]["snerf_default"]))
    lines += ["", "Command: `OMP_NUM_THREADS=1 python benchmarks/studies/pair_points_study.py --arms wide_smooth "
              "--source runs/wide_smooth_paper --out OUT` (fern and flower may run as two processes with `--scenes`, "
              "then once with both to write the table)."]
    write_study(args.out, {"rows": {k: {sc: v[sc]["snerf_default"] for sc in SCENES} for k, v in rows.items()},
                           "seeds": list(SEEDS)}, "\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arms", nargs="+", default=["today", "wide"], choices=["today", "wide", "wide_smooth"],
                    help="Study 37's arms (the study), or study 39's candidate (wide_smooth, with --source "
                         "runs/wide_smooth_paper: its recalibrated scores only, for docs/studies.md, study 39).")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--source", type=Path, default=Path("runs/colour_capacity_paper"), help="Study 37's runs.")
    ap.add_argument("--runs", type=Path, default=Path("runs/pair_points"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/pair_points_study"))
    args = ap.parse_args()
    views = {scene: validation_views(scene) for scene in SCENES}
    for arm in args.arms:  # the recalibrated copies and their scores, in study 37's folder layout
        for seed in SEEDS:
            for scene in args.scenes:
                src, _ = steps.run_folders(args.source, None, seed, arm, scene, "snerf_default")
                run, out = steps.run_folders(args.runs, None, seed, arm, scene, "snerf_default")
                score_run(recalibrated(src, run), views[scene], out)
                for a, b in zip(steps.run_folders(args.source, None, seed, arm, scene, "deterministic"),
                                steps.run_folders(args.runs, None, seed, arm, scene, "deterministic")):
                    link(a, b)
    if args.arms == ["wide_smooth"] and args.scenes == list(SCENES):
        write_study_39_either(args, views)
    if set(args.arms) != {"today", "wide"} or args.scenes != list(SCENES):
        return

    arms = {arm: arm for arm in args.arms}  # study 37's row folders
    _, today = steps.scored_rows(args.source, arms, SEEDS, views, methods=("snerf_default",))
    _, study37 = steps.scored_rows(args.runs, steps.STUDIES[37].rows, SEEDS, views)  # the candidate's maps
    rows = {"both (today)": {a: {s: today[a][s]["snerf_default"] for s in SCENES} for a in args.arms},
            "either (candidate)": {a: {s: study37[label][s]["snerf_default"] for s in SCENES}
                                   for label, a in steps.STUDIES[37].rows.items()}}
    taken, failed = verdict(rows["both (today)"]["today"], rows["either (candidate)"]["today"])
    taken37, failed37 = steps.verdict(study37, steps.STUDIES[37]) if taken else (None, [])
    lines = ["# Study 38: calibration views that render the points either view of their pair observed", "",
             "Study 37's runs (paper split, seeds 12-14, the tables' budget), each S-NeRF run recalibrated with the "
             "candidate and scored on the validation photos (fern 12, flower 23) with `stochastic-fields eval --views`. "
             "Means over the seeds; distance: mean |coverage - nominal| over 50/68/90/95%, in points.", "",
             *TABLE_HEAD]
    for scene in SCENES:
        for label, arms in rows.items():
            for arm in args.arms:
                lines.append(row(scene, f"{label}, {'32 / 8' if arm == 'today' else '64 / 16'}", arms[arm][scene]))
    lines += ["", f"**Rule (today's field): {'taken' if taken else 'not taken'}.**"]
    lines += [f"- {f}" for f in failed]
    if taken:
        lines += ["", f"**Study 37 judged again with these maps: {'taken' if taken37 else 'not taken'}.**"]
        lines += [f"- {f}" for f in failed37]
    lines += ["", "Command: the module docstring of `benchmarks/studies/pair_points_study.py`."]
    write_study(args.out, {"study": 38, "rows": rows, "taken": taken, "failed": failed,
                           "study_37_taken": taken37, "study_37_failed": failed37, "study_37_means": study37,
                           "seeds": list(SEEDS), "validation_views": views}, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
