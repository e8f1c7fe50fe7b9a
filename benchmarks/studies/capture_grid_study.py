"""Studies 23 to 25 and 36: the grid's finest level, the samples along a ray and the colour's capacity on a
capture, each judged by its rule.

Each study's rows are runs of the capture benchmark (``benchmarks/capture_quality.py``, S-NeRF,
seed 1, the ten-minute schedule), today's setting and the candidate's (the commands are in
``STUDIES``, and in each row folder's README). This script reads their ``results.json`` and writes
the table and the rule's verdict (docs/studies.md; each rule fixed before its rows ran) to
``--out``/README.md and ``verdict.json``::

    python benchmarks/studies/capture_grid_study.py --study cells
    python benchmarks/studies/capture_grid_study.py --study resolution_rule
    python benchmarks/studies/capture_grid_study.py --study samples
    python benchmarks/studies/capture_grid_study.py --study colour_capacity

A study with ``paper_tables`` also checks the paper split: the candidate's S-NeRF (default) row of
``benchmarks/eval_tables.py`` (seed 0, the same ``--set``) against today's committed row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import read_tables_method  # noqa: E402


class Study(NamedTuple):
    """One factor on the capture benchmark and its rule: the candidate is taken if on both scenes
    it gains ``min_psnr_gain_db`` of PSNR (or, where ``min_abs_rel_gain`` is set, lowers the depth
    abs-rel by that much instead), loses at most ``max_psnr_loss_db`` of PSNR (where set) and
    ``max_abs_rel_loss`` of abs-rel, keeps its recalibrated 68% and 95% coverage within
    ``coverage_points`` of nominal and trains at most ``max_minutes``; where ``paper_tables`` names
    (today's, the candidate's) ``tables.json``, its S-NeRF (default) row at the paper split also loses at
    most ``max_paper_psnr_loss_db`` of PSNR and ``max_paper_abs_rel_loss`` of abs-rel on each scene."""

    number: str
    title: str
    out: str
    rows: dict[str, str]  # label -> row folder under out (today's first)
    commands: tuple[str, ...]
    protocol: str
    min_psnr_gain_db: float = 0.2
    min_abs_rel_gain: float | None = None
    max_psnr_loss_db: float | None = None
    max_abs_rel_loss: float = 0.002
    coverage_points: float = 5.0
    max_minutes: float = 11.0
    paper_tables: tuple[str, str] | None = None
    max_paper_psnr_loss_db: float = 0.2
    max_paper_abs_rel_loss: float = 0.005


STUDIES = {
    "cells": Study(
        "23", "the finest grid level's cell cap on a capture", "benchmarks/results/grid_cells_study",
        {"today (2M cells)": "cells_2M", "candidate (8M cells)": "cells_8M"},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --seed 1 --marks 0.5 1 "
         "--out benchmarks/results/grid_cells_study/cells_2M --work runs/grid_cells/cells_2M",
         "the same with --set field.grid_max_cells=8000000 into cells_8M"),
        "S-NeRF default, capture split, seed 1, the probed ten-minute schedule (steps/s: the probe's), one thread, the two rows of "
        "a scene side by side"),
    "resolution_rule": Study(
        "24", "the grid's depth cells sized by parallax", "benchmarks/results/resolution_rule_study",
        {"today (footprint)": "footprint", "candidate (parallax)": "parallax"},
        tuple(f"OMP_NUM_THREADS=2 python benchmarks/capture_quality.py --methods snerf --scenes {scene} --seed 1 "
              f"--threads 2 --marks 0.5 1 --out benchmarks/results/resolution_rule_study/{rule} "
              f"--work runs/resolution_rule/{rule} --set field.grid_resolution_rule={rule}"
              for scene in ("fern", "flower") for rule in ("footprint", "parallax")),
        "S-NeRF default, capture split, seed 1, ten minutes of training (train.minutes) on two threads, "
        "one row at a time, the two rows of a scene one after the other",
        min_abs_rel_gain=0.005, max_psnr_loss_db=0.1),
    "samples": Study(
        "25", "a sample per depth cell of the parallax grid", "benchmarks/results/samples_study",
        {"today (64 samples)": "samples_64", "candidate (a sample per depth cell)": "samples_per_depth_cell"},
        tuple(f"OMP_NUM_THREADS=2 python benchmarks/capture_quality.py --methods snerf --scenes {scene} --seed 1 "
              f"--threads 2 --marks 0.5 1 --out benchmarks/results/samples_study/{row}/capture_{scene} "
              f"--work runs/samples_study/{row}" + (f" --set render.num_samples={samples}" if samples else "")
              for scene, depth_cells in (("fern", 47), ("flower", 42)) for row, samples in
              (("samples_64", None), ("samples_per_depth_cell", depth_cells))),
        "S-NeRF default, capture split, seed 1, ten minutes of training (train.minutes) on two threads, "
        "one row at a time, the two rows of a scene one after the other; the candidate's samples per ray are "
        "the finest grid level's depth cells on each capture (fern 246 x 177 x 47, flower 266 x 182 x 42)",
        min_abs_rel_gain=0.005, max_psnr_loss_db=0.1),
    "colour_capacity": Study(
        "36", "the colour branch's capacity on a capture", "benchmarks/results/colour_capacity_study",
        {"today (decoder 32, 8 features)": "today", "candidate (decoder 64, 16 features)": "wide_colour"},
        tuple(f"OMP_NUM_THREADS=2 python benchmarks/capture_quality.py --methods snerf --scenes {scene} --seed 11 "
              f"--threads 2 --minutes 10 --marks 1 --quiet --out benchmarks/results/colour_capacity_study/{row}/capture_{scene} "
              f"--work runs/colour_capacity/{row}" + sets
              for scene in ("fern", "flower") for row, sets in
              (("today", ""), ("wide_colour", " --set field.grid_decoder_width=64 --set field.grid_feature_dim=16")))
        + ("OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods snerf_default --seed 0 "
           "--no-timing --quiet --out runs/colour_capacity/tables --set field.grid_decoder_width=64 "
           "--set field.grid_feature_dim=16 (fern and flower side by side), then both scenes in one invocation "
           "(the same --out: it reuses the runs and writes the tables), its tables.json and tables.md copied to "
           "benchmarks/results/colour_capacity_study/tables",),
        "S-NeRF default, capture split, training seed 11 (no study's), ten minutes of training (train.minutes) on "
        "two threads, one row at a time on the otherwise idle machine, the two rows of a scene one after the other",
        paper_tables=("benchmarks/results/eval_tables_35/tables.json",
                      "benchmarks/results/colour_capacity_study/tables/tables.json")),
}


def last_scores(results: dict) -> dict[str, dict]:
    """Per scene: the end of the schedule's scores, steps and minutes, and the recalibrated intervals."""
    out = {}
    for record in results["records"]:
        last, cal = record["curve"][-1], record.get("calibrated") or {}
        # study 23's rows were made when the benchmark probed its speed and fixed the steps
        out[record["scene"]] = {"steps": record.get("steps", record.get("iterations")),
                                "steps_per_s": record.get("steps_per_s", record.get("steps_per_s_probe")),
                                "minutes": last["minutes"], "psnr": last["psnr"], "ssim": last["ssim"],
                                "abs_rel": last["depth_abs_rel"], "coverage_68": cal.get("coverage_68"),
                                "coverage_95": cal.get("coverage_95"), "halfwidth_95": cal.get("halfwidth_median_95"),
                                "curve": [(c["minutes"], c["psnr"]) for c in record["curve"]]}
    return out


def row_scores(folder: Path) -> dict[str, dict]:
    """``last_scores`` of a row's ``results.json``, or merged over its per-scene sub-folders'
    (a row whose setting differs per scene writes one capture-benchmark output per scene)."""
    files = [folder / "results.json"] if (folder / "results.json").is_file() else sorted(folder.glob("*/results.json"))
    if not files:
        raise SystemExit(f"{folder}: no results.json (run the row's command first)")
    scores = {}
    for path in files:
        scores.update(last_scores(json.loads(path.read_text())))
    return scores


def paper_scores(path: Path) -> dict[str, dict]:
    """Per scene: S-NeRF (default)'s PSNR and depth abs-rel in an ``eval_tables.py`` ``tables.json``."""
    return read_tables_method(path, "snerf_default",
                              lambda m: {"psnr": float(m["psnr"]), "abs_rel": float(m["depth"]["abs_rel"])},
                              "S-NeRF (default) rows (run the study's tables command first)")


def verdict(study: Study, today: dict, candidate: dict,
            paper: tuple[dict, dict] | None = None) -> dict:
    """Each scene's checks and whether the candidate passes on every scene; ``paper`` is (today's,
    the candidate's) ``paper_scores`` where the study checks the paper split."""
    scenes = {}
    for scene in sorted(set(today) & set(candidate)):
        a, b = today[scene], candidate[scene]
        psnr_gain, abs_rel_change = b["psnr"] - a["psnr"], b["abs_rel"] - a["abs_rel"]
        gains = psnr_gain >= study.min_psnr_gain_db or (
            study.min_abs_rel_gain is not None and -abs_rel_change >= study.min_abs_rel_gain)
        checks = {
            "gain": gains,
            "psnr_kept": study.max_psnr_loss_db is None or psnr_gain >= -study.max_psnr_loss_db,
            "abs_rel": abs_rel_change <= study.max_abs_rel_loss,
            "coverage": (b["coverage_68"] is not None
                         and abs(100 * b["coverage_68"] - 68.27) <= study.coverage_points
                         and abs(100 * b["coverage_95"] - 95.0) <= study.coverage_points),
            "minutes": b["minutes"] <= study.max_minutes,
        }
        if paper is not None:
            p_today, p_cand = paper[0].get(scene), paper[1].get(scene)
            checks["paper_split"] = (p_today is not None and p_cand is not None
                                     and p_cand["psnr"] - p_today["psnr"] >= -study.max_paper_psnr_loss_db
                                     and p_cand["abs_rel"] - p_today["abs_rel"] <= study.max_paper_abs_rel_loss)
        scenes[scene] = {"psnr_gain_db": psnr_gain, "abs_rel_change": abs_rel_change,
                         "checks": checks, "passes": all(checks.values())}
    return {"scenes": scenes, "taken": {"fern", "flower"} <= set(scenes) and all(s["passes"] for s in scenes.values())}


def rule_text(study: Study) -> str:
    gain = f"its PSNR is at least {study.min_psnr_gain_db} dB above today's"
    if study.min_abs_rel_gain is not None:
        gain += f" or its depth abs-rel at least {study.min_abs_rel_gain} below"
    if study.max_psnr_loss_db is not None:
        gain += f", its PSNR at most {study.max_psnr_loss_db} dB below"
    paper = (f" At the paper split (the tables' S-NeRF default row, seed 0) its PSNR is at most "
             f"{study.max_paper_psnr_loss_db} dB and its depth abs-rel at most {study.max_paper_abs_rel_loss} "
             f"worse than today's on each scene." if study.paper_tables else "")
    return (f"Rule (fixed before the rows): the candidate is taken if on both scenes {gain}, "
            f"its depth abs-rel at most {study.max_abs_rel_loss} above, its "
            f"recalibrated 68% and 95% coverage within {study.coverage_points:g} points of nominal and its "
            f"training at most {study.max_minutes:g} minutes.{paper}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--study", choices=sorted(STUDIES), required=True)
    ap.add_argument("--out", type=Path, default=None, help="Default: the study's results folder.")
    args = ap.parse_args()
    study = STUDIES[args.study]
    out = args.out or Path(study.out)
    rows = {label: row_scores(out / folder) for label, folder in study.rows.items()}
    (today_label, today), (cand_label, candidate) = rows.items()
    paper = tuple(paper_scores(Path(path)) for path in study.paper_tables) if study.paper_tables else None
    v = verdict(study, today, candidate, paper)
    (out / "verdict.json").write_text(json.dumps({"rows": rows, "paper_split": paper, "verdict": v}, indent=2) + "\n")
    lines = [f"# Study {study.number}: {study.title}", "",
             f"Rows: `benchmarks/capture_quality.py` ({study.protocol}); each row's own README in its folder:", ""]
    lines += [f"    {command}" for command in study.commands]
    lines += ["", f"Verdict: `python benchmarks/studies/capture_grid_study.py --study {args.study}`.", "",
              "| scene | row | steps (steps/s) | minutes | PSNR dB (at half the schedule) | SSIM | depth abs-rel | "
              "cov 68 / 95 | median 95% half-width |", "|" + "---|" * 9]
    for scene in sorted(today):
        for label, scores in rows.items():
            s = scores.get(scene)
            if s is None:
                continue
            half = s["curve"][0] if len(s["curve"]) > 1 else None
            half_text = f" ({half[1]:.2f} at {half[0]:.1f} min)" if half else ""
            cov = (f"{100 * s['coverage_68']:.1f} / {100 * s['coverage_95']:.1f}" if s["coverage_68"] is not None else "-")
            width = f"{100 * s['halfwidth_95']:.1f}%" if s["halfwidth_95"] is not None else "-"
            lines.append(f"| {scene} | {label} | {s['steps']} ({s['steps_per_s']:.2f}) | {s['minutes']:.1f} | "
                         f"{s['psnr']:.2f}{half_text} | {s['ssim']:.3f} | {s['abs_rel']:.4f} | {cov} | {width} |")
    if paper is not None:
        lines += ["", "Paper split (the tables' S-NeRF default row, seed 0, its four test views):", "",
                  "| scene | row | PSNR dB | depth abs-rel |", "|---|---|---|---|"]
        for scene in sorted(paper[0]):
            for label, scores in zip(rows, paper):
                if scene in scores:
                    lines.append(f"| {scene} | {label} | {scores[scene]['psnr']:.2f} | {scores[scene]['abs_rel']:.4f} |")
    lines += ["", rule_text(study), ""]
    for scene, s in v["scenes"].items():
        failed = [k for k, ok in s["checks"].items() if not ok]
        lines.append(f"- {scene}: PSNR {s['psnr_gain_db']:+.2f} dB, abs-rel {s['abs_rel_change']:+.4f}: "
                     + ("passes" if s["passes"] else "fails " + ", ".join(failed)))
    for scene in sorted({"fern", "flower"} - set(v["scenes"])):
        lines.append(f"- {scene}: no row of both settings (the rule needs it on every scene)")
    lines += ["", f"**{'Taken' if v['taken'] else 'Not taken'}.**", ""]
    (out / "README.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
