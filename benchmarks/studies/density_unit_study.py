"""Study 33: the grid's density counted per finest cell instead of per unit of length, judged by its
rule (docs/studies.md, fixed before the rows ran).

The question: the field's density is a number per unit of the capture's length, and the optimiser
moves the grid's values by about the same amount in any unit, so the same photos in another unit
train differently (the analysis "the scene's unit of length": the embedded scene with every length
times 10 scored 1.4-1.7 dB higher, its depth 38% closer). The candidate (``field.density_per
'cell'``) outputs relu(g) / L, L the finest cell's side (``SceneRegion.cell_length``), with the KL
priors scaled alike: the grid's value is the optical depth per finest cell, and training no longer
depends on the unit (tests/test_density_unit.py). One factor; everything else is the default.

Two stages, each with its own part of the rule:

* ``embedded``: validation scenes, not the demo's: the embedded scene generated with seeds 1, 2 and 3
  (study 32's validation scenes, the demo is seed 0), trained with the demo preset (S-NeRF, 10 of
  40 views, 2000 steps, training seed = scene seed), today's unit and the candidate's, scored on
  each scene's 30 test views by ``stochastic-fields eval``. Two runs at a time, one thread each::

      python benchmarks/studies/density_unit_study.py embedded --work runs/density_unit_study \\
          --out benchmarks/results/density_unit_study

* ``capture``: LLFF fern and flower with the capture split and the llff preset (its field lives in
  NDC, whose cells grow with depth), the capture bench's 10-minute budget, seed 0, two threads, the
  machine otherwise idle; today's row is the committed seed-0 row of the same bench on the same
  code (``benchmarks/results/capture_interval_seeds_occ``)::

      python benchmarks/capture_quality.py --methods snerf --marks 1 --threads 2 --seed 0 \\
          --set field.density_per=cell --work runs/density_unit_capture \\
          --out runs/density_unit_capture/bench
      python benchmarks/studies/depth_interval_seeds.py --run 0=runs/density_unit_capture \\
          --out runs/density_unit_capture/intervals
      python benchmarks/studies/density_unit_study.py capture \\
          --rows runs/density_unit_capture/intervals/results.json --out benchmarks/results/density_unit_study

Since study 35 changed ``loss.depth_relative_std`` to 0.03, the embedded rows train with
``PINNED_BEFORE_35`` (0.01, the value they ran with) and the capture rows need
``--set loss.depth_relative_std=0.01`` to be reproduced.

Resumable: a row whose ``eval/metrics.json`` exists is read, not re-run.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path


from stochastic_fields.data.synthetic import make_synthetic_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared report helpers
from study_helpers import (coverage_failures, pooled_scores, seed_means, train_and_eval,  # noqa: E402
                           validation_scenes_report)
from tables_cap_study import verdict_lines, write_study  # noqa: E402

SEEDS = (1, 2, 3)
ROWS = ("today (density per unit of length)", "candidate (density per finest cell)")
CANDIDATE_OPTIONS = ("--field.density_per", "cell")
RULE_LEVELS = (0.50, 0.68, 0.90, 0.95)
#: The rule, fixed before the rows ran. Embedded stage (means over seeds 1-3): PSNR at most
#: MAX_PSNR_LOSS_DB lower, depth abs-rel not higher, median 95% half-width not wider, every level
#: within COVERAGE_TOLERANCE of nominal or no further than today's. Capture stage (each of fern and
#: flower, seed 0, against today's seed-0 row): PSNR at most CAPTURE_MAX_PSNR_LOSS_DB lower, depth
#: abs-rel at most CAPTURE_MAX_ABS_REL_RISE higher, median 95% half-width at most
#: CAPTURE_MAX_BAND_RISE (of the depth) wider, the levels as above (the tolerances: about half the
#: spread of three seeds of today's rows).
MAX_PSNR_LOSS_DB = 0.1
COVERAGE_TOLERANCE = 0.05
CAPTURE_MAX_PSNR_LOSS_DB = 0.15
CAPTURE_MAX_ABS_REL_RISE = 0.003
CAPTURE_MAX_BAND_RISE = 0.01
#: The defaults studies 33-35 ran with that study 35 changed: each capture point's depth noise 1% of
#: its depth. Their rows train with it, so that their commands reproduce them.
PINNED_BEFORE_35: tuple[str, ...] = ("--loss.depth_relative_std", "0.01")
TODAY_CAPTURE_ROWS = Path(__file__).resolve().parents[1] / "results" / "capture_interval_seeds_occ" / "results.json"


def embedded_verdict(today: dict, candidate: dict) -> tuple[bool, list[str]]:
    failed = []
    if candidate["psnr"] < today["psnr"] - MAX_PSNR_LOSS_DB:
        failed.append(f"PSNR {today['psnr']:.2f} -> {candidate['psnr']:.2f} dB: more than {MAX_PSNR_LOSS_DB} dB lower")
    if candidate["abs_rel"] > today["abs_rel"]:
        failed.append(f"depth abs-rel {today['abs_rel']:.4f} -> {candidate['abs_rel']:.4f}: higher")
    if candidate["halfwidth_median_95"] > today["halfwidth_median_95"]:
        failed.append(f"median 95% half-width {100 * today['halfwidth_median_95']:.1f}% -> "
                      f"{100 * candidate['halfwidth_median_95']:.1f}%: wider")
    failed += coverage_failures(today, candidate, RULE_LEVELS, COVERAGE_TOLERANCE)
    return not failed, failed


#: Studies 34 and 35: the depth ranking (Spearman |err|-std) may fall at most this much (study 8's tolerance).
MAX_SPEARMAN_LOSS = 0.02


def spearman_failures(today: dict, candidate: dict) -> list[str]:
    """The depth-ranking check of studies 34 and 35: the candidate's mean Spearman at most
    ``MAX_SPEARMAN_LOSS`` below today's."""
    if candidate["spearman"] < today["spearman"] - MAX_SPEARMAN_LOSS:
        return [f"depth Spearman {today['spearman']:.3f} -> {candidate['spearman']:.3f}: more than "
                f"{MAX_SPEARMAN_LOSS} lower"]
    return []


def capture_verdict(today: dict, candidate: dict, scene: str) -> list[str]:
    failed = []
    if candidate["psnr"] < today["psnr"] - CAPTURE_MAX_PSNR_LOSS_DB:
        failed.append(f"{scene}: PSNR {today['psnr']:.2f} -> {candidate['psnr']:.2f} dB: more than "
                      f"{CAPTURE_MAX_PSNR_LOSS_DB} dB lower")
    if candidate["abs_rel"] > today["abs_rel"] + CAPTURE_MAX_ABS_REL_RISE:
        failed.append(f"{scene}: depth abs-rel {today['abs_rel']:.4f} -> {candidate['abs_rel']:.4f}: more than "
                      f"{CAPTURE_MAX_ABS_REL_RISE} higher")
    if candidate["halfwidth_median_95"] > today["halfwidth_median_95"] + CAPTURE_MAX_BAND_RISE:
        failed.append(f"{scene}: median 95% half-width {100 * today['halfwidth_median_95']:.1f}% -> "
                      f"{100 * candidate['halfwidth_median_95']:.1f}%: more than {100 * CAPTURE_MAX_BAND_RISE:.0f} "
                      "point wider")
    return failed + coverage_failures(today, candidate, RULE_LEVELS, COVERAGE_TOLERANCE, f"{scene}: ")


def table_row(label: str, r: dict) -> str:
    cov = "/".join(f"{100 * r[f'coverage_{c}']:.1f}" for c in (50, 68, 90, 95, 99))
    spearman = f" {r['spearman']:.3f} |" if "spearman" in r else " - |"
    return (f"| {label} | {r['psnr']:.2f} | {r['abs_rel']:.4f} | {cov} | {100 * r['halfwidth_median_95']:.1f}% | "
            f"{r['interval_score_95']:.3f} | {r['crps']:.4f} |{spearman}")


HEAD = ["| row | PSNR dB | depth abs-rel | cov 50/68/90/95/99 | median 95% half-width / depth | IS95 / depth | "
        "CRPS / depth | depth Spearman |", "|---|---|---|---|---|---|---|---|"]
RULE_TEXT = ("Rule (fixed before the rows ran): the candidate becomes the default if the embedded stage passes "
             f"(means over seeds 1-3: PSNR at most {MAX_PSNR_LOSS_DB} dB lower, depth abs-rel not higher, median 95% "
             f"half-width not wider, each of the 50/68.3/90/95% levels within {round(100 * COVERAGE_TOLERANCE)} points "
             "of nominal or no further than today's) and the capture stage passes (each of fern and flower, seed 0, "
             f"against today's seed-0 row: PSNR at most {CAPTURE_MAX_PSNR_LOSS_DB} dB lower, abs-rel at most "
             f"{CAPTURE_MAX_ABS_REL_RISE} higher, median 95% half-width at most {100 * CAPTURE_MAX_BAND_RISE:.0f} point "
             "wider, the levels as above). If only the embedded stage passes, the candidate becomes the default of "
             "object-centric scenes and the llff preset keeps the density per unit of length.")


def embedded_stage(args, *, study: int, title: str, script: str, labels: tuple[str, str],
                   options: tuple[str, ...], verdict, rule_text: str, pinned: tuple[str, ...] = PINNED_BEFORE_35
                   ) -> None:
    """A validation-scene stage (studies 33-35): today's row (label 0) and the candidate's (label 1,
    trained with the command-line ``options`` after ``pinned``) on each of ``SEEDS``, ``args.jobs``
    at a time, scored, their means judged by ``verdict(today, candidate) -> (taken, failed)``, and
    the report with ``rule_text`` written to ``args.out``/embedded. ``pinned``: the options both rows
    train with, the defaults of the day the study ran that a later study changed."""
    jobs = []
    for seed in SEEDS:
        scene = make_synthetic_scene(args.work / f"scene_s{seed}", seed=seed)
        for label in labels:
            candidate = label == labels[1]
            jobs.append((label, seed, scene, args.work / f"s{seed}" / ("candidate" if candidate else "today"), candidate))
    with ThreadPoolExecutor(args.jobs) as pool:
        results = list(pool.map(lambda j: pooled_scores(
            train_and_eval(j[2], j[3], j[1], options=pinned + (options if j[4] else ())), RULE_LEVELS), jobs))
    rows = {label: [r for (lab, *_), r in zip(jobs, results) if lab == label] for label in labels}
    means = {label: seed_means(rows[label]) for label in labels}
    taken, failed = verdict(means[labels[0]], means[labels[1]])
    lines = validation_scenes_report(title, script, labels, rows, means, SEEDS, HEAD, table_row)
    lines += verdict_lines(taken, failed) + ["", rule_text]
    write_study(args.out / "embedded", {"study": study, "stage": "embedded", "rows": rows, "means": means,
                                        "seeds": list(SEEDS), "taken": taken, "failed": failed},
                "\n".join(lines) + "\n")


def capture_rows(path: Path) -> dict:
    """{(scene, seed): row} of the capture-protocol rows of ``depth_interval_seeds.py``'s results.json."""
    return {(r["scene"], r["seed"]): r for r in json.loads(path.read_text())["rows"] if r["protocol"] == "capture"}


def capture_stage(*, study: int, title: str, intro: str, labels: tuple[str, str], today: Path, candidate: Path,
                  rule_text: str, out: Path) -> None:
    """A capture stage (studies 33-35): fern's and flower's seed-0 rows of ``today`` and
    ``candidate`` (``capture_rows`` files) in one table, each scene judged by ``capture_verdict``,
    the report (``intro`` under ``title``, then ``rule_text``) written to ``out``/capture."""
    rows_today, rows_candidate = capture_rows(today), capture_rows(candidate)
    failed, lines, rows = [], [title, "", intro, "", *HEAD], {}
    for scene in ("fern", "flower"):
        t, c = rows_today.get((scene, 0)), rows_candidate.get((scene, 0))
        if t is None or c is None:
            raise SystemExit(f"{today if t is None else candidate}: no capture row of {scene} seed 0")
        rows[scene] = {"today": t, "candidate": c}
        lines += [table_row(f"{scene}, {labels[0]} ({t['steps']} steps)", t),
                  table_row(f"{scene}, {labels[1]} ({c['steps']} steps)", c)]
        failed += capture_verdict(t, c, scene)
    lines += verdict_lines(not failed, failed) + ["", rule_text]
    write_study(out / "capture", {"study": study, "stage": "capture", "rows": rows, "taken": not failed,
                                  "failed": failed}, "\n".join(lines) + "\n")


#: The capture part of studies 34 and 35's rules (today's row trained beside the candidate's).
SIDE_BY_SIDE_CAPTURE_RULE = (
    "the capture stage passes (each of fern and flower, seed 0, against today's row trained beside it: PSNR at most "
    f"{CAPTURE_MAX_PSNR_LOSS_DB} dB lower, abs-rel at most {CAPTURE_MAX_ABS_REL_RISE} higher, median 95% half-width at "
    f"most {100 * CAPTURE_MAX_BAND_RISE:.0f} point wider, the levels as above).")


def side_by_side_intro(script: str) -> str:
    """The capture report's setup line of studies 34 and 35 (their rows trained side by side)."""
    return ("Capture split, llff preset, the capture bench's 10-minute budget, seed 0; today's row and the candidate's "
            f"trained side by side, one thread each. Command: the module docstring of `benchmarks/studies/{script}`.")


def stages_parser(doc: str, name: str, *, capture_today: bool) -> tuple[argparse.ArgumentParser, argparse.ArgumentParser]:
    """The command line of a two-stage study (studies 33-35): ``embedded`` (--work runs/``name``, --out
    benchmarks/results/``name``, --jobs) and ``capture`` (--rows, with ``capture_today`` --today too,
    --out). Returns (the parser, the embedded stage's sub-parser, for a study's own options)."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    sub = ap.add_subparsers(dest="stage", required=True)
    e = sub.add_parser("embedded", help="Train and score the validation scenes, today and the candidate.")
    e.add_argument("--work", type=Path, default=Path("runs") / name)
    e.add_argument("--out", type=Path, default=Path("benchmarks/results") / name)
    e.add_argument("--jobs", type=int, default=2, help="Rows trained at once (one thread each).")
    c = sub.add_parser("capture", help="Judge the candidate's capture-bench rows against today's.")
    if capture_today:
        c.add_argument("--today", type=Path, required=True, help="results.json of depth_interval_seeds.py on today's rows.")
    c.add_argument("--rows", type=Path, required=True, help="results.json of depth_interval_seeds.py on the candidate.")
    c.add_argument("--out", type=Path, default=Path("benchmarks/results") / name)
    return ap, e


def embedded(args) -> None:
    embedded_stage(args, study=33, title="Study 33, embedded stage: the density per finest cell",
                   script="density_unit_study.py", labels=ROWS, options=CANDIDATE_OPTIONS, verdict=embedded_verdict,
                   rule_text=RULE_TEXT)


def capture(args) -> None:
    capture_stage(study=33, title="# Study 33, capture stage: the density per finest cell on LLFF captures",
                  intro="Capture split, llff preset, the capture bench's 10-minute budget (two threads), seed 0; "
                        f"today's rows from `{TODAY_CAPTURE_ROWS.relative_to(TODAY_CAPTURE_ROWS.parents[3])}`. "
                        "Command: the module docstring of `benchmarks/studies/density_unit_study.py`.",
                  labels=ROWS, today=TODAY_CAPTURE_ROWS, candidate=args.rows, rule_text=RULE_TEXT, out=args.out)


def main() -> None:
    args = stages_parser(__doc__, "density_unit_study", capture_today=False)[0].parse_args()
    embedded(args) if args.stage == "embedded" else capture(args)


if __name__ == "__main__":
    main()
