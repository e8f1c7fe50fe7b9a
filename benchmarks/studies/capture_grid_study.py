"""Studies 23 to 25, 36, 47 to 51 and 53: the grid's finest level, the samples along a ray, the colour's
capacity, Adam's second-moment decay, the colour levels, the rays' sampling, the grid's levels and its
density heads on a capture, each judged by its rule.

Each study's rows are runs of the capture benchmark (``benchmarks/capture_quality.py``, S-NeRF,
seed 1, the ten-minute schedule), today's setting and the candidate's (the commands are in
``STUDIES``, and in each row folder's README). This script reads their ``results.json`` and writes
the table and the rule's verdict (docs/studies.md; each rule fixed before its rows ran) to
``--out``/README.md and ``verdict.json``::

    python benchmarks/studies/capture_grid_study.py --study cells
    python benchmarks/studies/capture_grid_study.py --study resolution_rule
    python benchmarks/studies/capture_grid_study.py --study samples
    python benchmarks/studies/capture_grid_study.py --study colour_capacity
    python benchmarks/studies/capture_grid_study.py --study adam_beta2
    python benchmarks/studies/capture_grid_study.py --study adam_beta2_colour
    python benchmarks/studies/capture_grid_study.py --study colour_levels
    python benchmarks/studies/capture_grid_study.py --study colour_levels_minutes
    python benchmarks/studies/capture_grid_study.py --study error_sampling
    python benchmarks/studies/capture_grid_study.py --study grid_levels
    python benchmarks/studies/capture_grid_study.py --study density_heads

A row may be several runs (seeds): the rule then reads their means.

A study with ``paper_tables`` also checks the paper split: the candidate's S-NeRF (default) row of
``benchmarks/eval_tables.py`` (seed 0, or the means of several seeds' tables, the same ``--set``) against
today's committed rows.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import coverage_failures, read_tables_method, seed_means  # noqa: E402


class Study(NamedTuple):
    """One factor on the capture benchmark and its rule: the candidate is taken if on both scenes
    it gains ``min_psnr_gain_db`` of PSNR (or, where ``min_abs_rel_gain`` is set, lowers the depth
    abs-rel by that much instead), loses at most ``max_psnr_loss_db`` of PSNR (where set) and
    ``max_abs_rel_loss`` of abs-rel, keeps its recalibrated 68% and 95% coverage within
    ``coverage_points`` of nominal and trains at most ``max_minutes`` (None: the steps are fixed, the
    minutes not ruled); where ``paper_tables`` names (today's, the candidate's) ``tables.json``, its
    S-NeRF (default) row at the paper split also loses at most ``max_paper_psnr_loss_db`` of PSNR and
    ``max_paper_abs_rel_loss`` of abs-rel on each scene (each side may be several seeds' ``tables.json``:
    their means are ruled; with ``paper_levels`` the paper split's levels are ruled as the capture's); where ``step_costs`` names
    ``capture_step_cost.py`` outputs (under ``out``, one per scene), a step costs at most
    ``max_step_cost`` times today's on each scene.

    ``gain_on_mean``: the PSNR gain is asked of the mean over the scenes, not of each (each scene then
    loses at most ``max_psnr_loss_db``); ``levels``: the central levels (%) held within
    ``coverage_points`` of nominal (or, with ``level_as_far_as_today``, no farther than today's row
    misses them); where
    ``max_halfwidth_growth_points`` is set, the median 95% half-width / depth grows by at most that
    many points."""

    number: str
    title: str
    out: str
    rows: dict[str, str | tuple[str, ...]]  # label -> row folder(s) under out, one per seed (today's first)
    commands: tuple[str, ...]
    protocol: str
    min_psnr_gain_db: float | None = 0.2  # None: no gain asked, the captures need only hold
    min_abs_rel_gain: float | None = None
    max_psnr_loss_db: float | None = None
    max_abs_rel_loss: float = 0.002
    coverage_points: float = 5.0
    max_minutes: float | None = 11.0
    paper_tables: tuple[str | tuple[str, ...], str | tuple[str, ...]] | None = None
    max_paper_psnr_loss_db: float = 0.2
    max_paper_abs_rel_loss: float = 0.005
    paper_levels: bool = False
    gain_on_mean: bool = False
    levels: tuple[int, ...] = (68, 95)
    level_as_far_as_today: bool = False
    max_halfwidth_growth_points: float | None = None
    step_costs: tuple[str, ...] | None = None
    max_step_cost: float = 1.05


#: Nominal coverage (%) of each central level a study may rule on.
NOMINAL = {50: 50.0, 68: 68.27, 90: 90.0, 95: 95.0}


#: The rule of studies 47 to 51 (a seed's rows judged on the seeds' means): +0.1 dB on the mean of the captures, no
#: capture -0.05 dB, every level 50-95% held (no farther than today's where today's misses), bands at most 1 point wider.
SEED_MEANS_RULE = dict(min_psnr_gain_db=0.1, max_psnr_loss_db=0.05, max_minutes=None, gain_on_mean=True,
                       levels=(50, 68, 90, 95), level_as_far_as_today=True, max_halfwidth_growth_points=1.0)
#: Today's S-NeRF default row at the paper split, seeds 0-2 (the reference of studies 49b and 51).
TODAY_PAPER_SEEDS = ("benchmarks/results/adam_beta2_study/tables_0.999/tables.json",
                     "benchmarks/results/eval_tables_46b/seed_1/tables.json",
                     "benchmarks/results/eval_tables_46b/seed_2/tables.json")

#: The S-NeRF default row with five grid levels at the paper split, seeds 0-2 (study 51's candidate,
#: today's since; the reference of study 53).
LEVELS_5_PAPER_SEEDS = tuple(f"benchmarks/results/grid_levels_study/tables_levels_5/seed_{s}/tables.json" for s in range(3))


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
    "adam_beta2": Study(
        "47", "Adam's second-moment decay on a capture", "benchmarks/results/adam_beta2_study",
        {"today (0.999)": ("beta2_0.999/seed_3", "beta2_0.999/seed_4"),
         "candidate (0.99)": ("beta2_0.99/seed_3", "beta2_0.99/seed_4")},
        ("OMP_NUM_THREADS=2 python benchmarks/capture_quality.py --methods snerf --steps 3300 --marks 1 --threads 2 "
         "--quiet --seed S --out benchmarks/results/adam_beta2_study/beta2_0.999/seed_S "
         "--work runs/s47/beta2_0.999/seed_S (S = 3, 4)",
         "the same with --set train.adam_beta2=0.99 into beta2_0.99",
         "OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods snerf_default --seed 0 "
         "--no-timing --quiet --out runs/s47/tables_B [--set train.adam_beta2=0.99] (B = 0.999 on both scenes side by "
         "side, fern's 0.99 after fern's 0.999, flower's 0.99 last on two threads), then both scenes in one invocation, "
         "its tables.json and tables.md copied to benchmarks/results/adam_beta2_study/tables_B"),
        "S-NeRF default, capture split, seeds 3 and 4 (no study's), a schedule of 3300 steps (`--steps`) on two "
        "threads, one row at a time, a seed's two rows one after the other; the table's rows are the seeds' means",
        **SEED_MEANS_RULE,
        paper_tables=("benchmarks/results/adam_beta2_study/tables_0.999/tables.json",
                      "benchmarks/results/adam_beta2_study/tables_0.99/tables.json")),
    "adam_beta2_colour": Study(
        "48", "Adam's faster second-moment decay for the colour only", "benchmarks/results/adam_beta2_colour_study",
        {"today (0.999)": ("colour_0.999/seed_5", "colour_0.999/seed_6"),
         "candidate (colour 0.99)": ("colour_0.99/seed_5", "colour_0.99/seed_6")},
        ("OMP_NUM_THREADS=2 python benchmarks/capture_quality.py --methods snerf --steps 3300 --marks 1 --threads 2 "
         "--quiet --seed S --out benchmarks/results/adam_beta2_colour_study/colour_0.999/seed_S "
         "--work runs/s48/colour_0.999/seed_S (S = 5, 6; from the commit before the option existed)",
         "the same with --set train.adam_beta2_colour=0.99 into colour_0.99"),
        "S-NeRF default, capture split, seeds 5 and 6 (no study's), a schedule of 3300 steps (`--steps`) on two "
        "threads, one row at a time, today's rows first; the table's rows are the seeds' means",
        **SEED_MEANS_RULE),
    "colour_levels": Study(
        "49", "each grid level's colour features read apart", "benchmarks/results/colour_levels_study",
        {"today (sum)": ("today/seed_6", "today/seed_7"),
         "candidate (concat)": ("concat/seed_6", "concat/seed_7")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --steps 3300 --marks 1 --threads 1 "
         "--quiet --seed S --set field.grid_colour_levels=concat --out benchmarks/results/colour_levels_study/concat/seed_S "
         "--work runs/s70/concat/seed_S (S = 6, 7)",
         "the same without --set into today/seed_7 (today/seed_6 is study 48's colour_0.999/seed_6, the same computation)"),
        "S-NeRF default, capture split, seeds 6 and 7, a schedule of 3300 steps (`--steps`), two processes of one "
        "thread side by side; the table's rows are the seeds' means; the step's cost ruled apart "
        "(capture_step_cost.py)",
        **SEED_MEANS_RULE,
        step_costs=("step_cost_fern.json", "step_cost_flower.json")),
    "colour_levels_minutes": Study(
        "49b", "each grid level's colour features read apart, judged at ten minutes",
        "benchmarks/results/colour_levels_minutes_study",
        {"today (sum)": ("today/seed_9", "today/seed_10"),
         "candidate (concat)": ("concat/seed_9", "concat/seed_10")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --minutes 10 --marks 1 --threads 1 "
         "--quiet --seed S [--set field.grid_colour_levels=concat] --out "
         "benchmarks/results/colour_levels_minutes_study/{today,concat}/seed_S --work runs/s71/{today,concat}/seed_S "
         "(S = 9, then 10; a seed's two rows side by side)",
         "OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes fern flower --methods snerf_default --seed S "
         "--no-timing --quiet --set field.grid_colour_levels=concat --out runs/s71/tables_concat_seedS (S = 1, 2 side "
         "by side), its tables.json and tables.md copied to benchmarks/results/colour_levels_minutes_study/"
         "tables_concat/seed_S (seed 0: study 49's tables_concat)"),
        "S-NeRF default, capture split, seeds 9 and 10, ten minutes of training (train.minutes), a seed's two rows "
        "side by side on one thread each; the table's rows are the seeds' means",
        **SEED_MEANS_RULE,
        paper_tables=(TODAY_PAPER_SEEDS,
                      ("benchmarks/results/colour_levels_study/tables_concat/tables.json",
                       "benchmarks/results/colour_levels_minutes_study/tables_concat/seed_1/tables.json",
                       "benchmarks/results/colour_levels_minutes_study/tables_concat/seed_2/tables.json")),
        paper_levels=True),
    "grid_levels": Study(
        "51", "five grid levels instead of three, judged at ten minutes", "benchmarks/results/grid_levels_study",
        {"today (3 levels)": ("today/seed_35", "today/seed_36"),
         "candidate (5 levels)": ("levels_5/seed_35", "levels_5/seed_36")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --minutes 10 --marks 1 --threads 1 "
         "--quiet --seed S [--set field.grid_levels=5] --out benchmarks/results/grid_levels_study/{today,levels_5}/seed_S "
         "--work runs/s76/{today,levels_5}/seed_S (S = 35, then 36; a seed's two rows side by side)",
         "OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes fern flower --methods snerf_default --seed S "
         "--no-timing --quiet --set field.grid_levels=5 --out runs/s76/tables_levels_5_seedS (S = 0, 1, 2, two side "
         "by side), its tables.json and tables.md copied to benchmarks/results/grid_levels_study/tables_levels_5/seed_S"),
        "S-NeRF default, capture split, seeds 35 and 36 (no study's), ten minutes of training (train.minutes), a "
        "seed's two rows side by side on one thread each; the table's rows are the seeds' means",
        **SEED_MEANS_RULE,
        paper_tables=(TODAY_PAPER_SEEDS,
                      LEVELS_5_PAPER_SEEDS),
        paper_levels=True),
    "density_heads": Study(
        "53", "four density heads, judged at ten minutes", "benchmarks/results/density_heads_study",
        {"today (1 head)": ("today/seed_38", "today/seed_40"),
         "candidate (4 heads)": ("heads_4_capture/seed_38", "heads_4_capture/seed_40")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --minutes 10 --marks 1 --threads 1 "
         "--quiet --seed S [--set field.density_heads=4] --out "
         "benchmarks/results/density_heads_study/{today,heads_4_capture}/seed_S --work runs/s78/{today,heads_4}/seed_S "
         "(S = 38, then 40; a seed's two rows side by side)",
         "the paper split: study 52's rows (benchmarks/results/density_heads_study/heads_4/seed_S, S = 0, 1, 2)"),
        "S-NeRF default, capture split, seeds 38 and 40 (no study's), ten minutes of training (train.minutes), a "
        "seed's two rows side by side on one thread each; the table's rows are the seeds' means",
        **SEED_MEANS_RULE,
        paper_tables=(LEVELS_5_PAPER_SEEDS,
                      tuple(f"benchmarks/results/density_heads_study/heads_4/seed_{s}/tables.json" for s in range(3))),
        paper_levels=True),
    "density_heads_2": Study(
        "54", "two density heads for the paper split, with the captures held",
        "benchmarks/results/density_heads_study/capture_verdict_2",  # study 53's verdict is the folder's top
        {"today (1 head)": ("../today/seed_42", "../today/seed_44"),
         "candidate (2 heads)": ("../heads_2_capture/seed_42", "../heads_2_capture/seed_44")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --minutes 10 --marks 1 --threads 1 "
         "--quiet --seed S [--set field.density_heads=2] --out "
         "benchmarks/results/density_heads_study/{today,heads_2_capture}/seed_S --work runs/s79/{today,heads_2}/seed_S "
         "(S = 42, then 44; a seed's two rows side by side)",
         "the paper split: judged apart by density_heads_study.py --rule 54 (benchmarks/results/density_heads_study/"
         "paper_verdict_2)"),
        "S-NeRF default, capture split, seeds 42 and 44 (no study's), ten minutes of training (train.minutes), a "
        "seed's two rows side by side on one thread each; the table's rows are the seeds' means",
        **{**SEED_MEANS_RULE, "min_psnr_gain_db": None, "gain_on_mean": False}),
    "error_sampling": Study(
        "50", "training rays drawn by their blocks' colour error", "benchmarks/results/error_sampling_study",
        {"today (uniform)": ("today/seed_5", "today/seed_7"),
         "candidate (error-guided)": ("error/seed_5", "error/seed_7")},
        ("OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --scenes SCENE --methods snerf --steps 3300 --marks 1 "
         "--threads 1 --quiet --seed S --set train.ray_sampling=error --out runs/s74/error/seed_S/SCENE "
         "--work runs/s74/work/seed_S/SCENE (S = 7, then 5; a seed's two scenes side by side), then both scenes' "
         "work folders joined under one --work and the same command with --scenes fern flower (it reads the finished "
         "runs) into benchmarks/results/error_sampling_study/error/seed_S",
         "today/seed_5 is study 48's colour_0.999/seed_5, today/seed_7 study 49's today/seed_7: the same computation "
         "(with train.ray_sampling uniform a run is bit for bit the one before the option)",
         "OMP_NUM_THREADS=1 python benchmarks/studies/capture_step_cost.py --scene SCENE --set "
         "train.ray_sampling=error --out benchmarks/results/error_sampling_study/step_cost_SCENE.json (idle machine)"),
        "S-NeRF default, capture split, seeds 5 and 7, a schedule of 3300 steps (`--steps`), two processes of one "
        "thread side by side; the table's rows are the seeds' means; the step's cost ruled apart "
        "(capture_step_cost.py)",
        **SEED_MEANS_RULE,
        step_costs=("step_cost_fern.json", "step_cost_flower.json")),
}


def last_scores(results: dict) -> dict[str, dict]:
    """Per scene: the end of the schedule's scores, steps and minutes, and the recalibrated intervals."""
    out = {}
    for record in results["records"]:
        last, cal = record["curve"][-1], record.get("calibrated") or {}
        levels = cal.get("depth_intervals") or {}
        # study 23's rows were made when the benchmark probed its speed and fixed the steps
        out[record["scene"]] = {"steps": record.get("steps", record.get("iterations")),
                                "steps_per_s": record.get("steps_per_s", record.get("steps_per_s_probe")),
                                "minutes": last["minutes"], "psnr": last["psnr"], "ssim": last["ssim"],
                                "abs_rel": last["depth_abs_rel"], "coverage_68": cal.get("coverage_68"),
                                "coverage_95": cal.get("coverage_95"), "halfwidth_95": cal.get("halfwidth_median_95"),
                                **{f"coverage_{p}": levels.get(f"coverage_{p}") for p in (50, 90)},
                                "curve": [(c["minutes"], c["psnr"]) for c in record["curve"]]}
    return out


def mean_scores(runs: list[dict[str, dict]]) -> dict[str, dict]:
    """Per scene: the mean of several runs' ``last_scores`` (seeds; ``study_helpers.seed_means``) for the
    scenes every run has; a score no seed has stays None, the curve is the end of the schedule's mean."""
    out = {}
    for scene in sorted(set.intersection(*(set(r) for r in runs))):
        rows = [r[scene] for r in runs]
        mean = {key: None for key in rows[0] if key != "curve"} | seed_means(rows)
        out[scene] = {**mean, "curve": [(mean["minutes"], mean["psnr"])], "seeds": len(rows)}
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


def has_seeds(study: Study) -> bool:
    """Whether the study's rows are several seeds' runs (the rule then reads their means)."""
    return any(isinstance(folder, tuple) for folder in study.rows.values())


def read_rows(study: Study, out: Path) -> tuple[dict[str, dict], dict[str, dict[str, dict]]]:
    """Each row's scores (``row_scores``; the ``mean_scores`` of its seeds where it is several runs) and,
    per row of seeds, each seed folder's own scores (name -> ``row_scores``), every file read once."""
    def at(folder: str) -> Path:  # a row beside the verdict's folder ('../x') reads without the folder existing
        return Path(os.path.normpath(out / folder))

    rows, seeds = {}, {}
    for label, folder in study.rows.items():
        if isinstance(folder, tuple):
            seeds[label] = {Path(f).name: row_scores(at(f)) for f in folder}
            rows[label] = mean_scores(list(seeds[label].values()))
        else:
            rows[label] = row_scores(at(folder))
    return rows, seeds


def paper_scores(path: Path) -> dict[str, dict]:
    """Per scene: S-NeRF (default)'s PSNR and depth abs-rel in an ``eval_tables.py`` ``tables.json``, and
    the recalibrated depth coverage at each level of ``NOMINAL`` its pooled intervals report."""

    def read(m: dict) -> dict:
        scores = {"psnr": float(m["psnr"]), "abs_rel": float(m["depth"]["abs_rel"])}
        intervals = (m.get("pooled") or {}).get("depth_intervals") or {}
        scores.update({f"coverage_{p}": float(intervals[f"coverage_{p}"]) for p in NOMINAL
                       if intervals.get(f"coverage_{p}") is not None})
        return scores

    return read_tables_method(path, "snerf_default", read,
                              "S-NeRF (default) rows (run the study's tables command first)")


def paper_means(paths: str | tuple[str, ...]) -> dict[str, dict]:
    """``paper_scores`` of one ``tables.json`` or, per scene every file has, the means of several seeds'
    (each score every seed reports)."""
    per_seed = [paper_scores(Path(p)) for p in ((paths,) if isinstance(paths, str) else paths)]
    scenes = set.intersection(*(set(s) for s in per_seed))
    means = {}
    for scene in sorted(scenes):
        keys = set.intersection(*(set(s[scene]) for s in per_seed))
        means[scene] = {k: sum(s[scene][k] for s in per_seed) / len(per_seed) for k in sorted(keys)}
    return means


def step_cost_ratios(study: Study, out: Path) -> dict[str, float] | None:
    """Per scene: the candidate's step cost over today's in the study's ``capture_step_cost.py`` outputs."""
    if not study.step_costs:
        return None
    ratios = {}
    for name in study.step_costs:
        path = out / name
        if not path.is_file():
            raise SystemExit(f"{path}: no step-cost measurement (run the study's capture_step_cost.py command first)")
        result = json.loads(path.read_text())
        ratios[result["scene"]] = float(result["ratio"])
    return ratios


def verdict(study: Study, today: dict, candidate: dict,
            paper: tuple[dict, dict] | None = None, step_costs: dict[str, float] | None = None) -> dict:
    """Each scene's checks and whether the candidate passes on every scene; ``paper`` is (today's,
    the candidate's) ``paper_scores`` where the study checks the paper split, ``step_costs`` each
    scene's ``step_cost_ratios`` where it rules on a step's cost (a scene without one fails)."""
    scenes = {}
    for scene in sorted(set(today) & set(candidate)):
        a, b = today[scene], candidate[scene]
        psnr_gain, abs_rel_change = b["psnr"] - a["psnr"], b["abs_rel"] - a["abs_rel"]
        checks = {}
        if not study.gain_on_mean and study.min_psnr_gain_db is not None:  # a gain asked of each scene
            checks["gain"] = psnr_gain >= study.min_psnr_gain_db or (
                study.min_abs_rel_gain is not None and -abs_rel_change >= study.min_abs_rel_gain)
        checks.update({
            "psnr_kept": study.max_psnr_loss_db is None or psnr_gain >= -study.max_psnr_loss_db,
            "abs_rel": abs_rel_change <= study.max_abs_rel_loss,
            "coverage": coverage_held(study, a, b),
        })
        if study.max_minutes is not None:
            checks["minutes"] = b["minutes"] <= study.max_minutes
        if study.max_halfwidth_growth_points is not None:
            checks["halfwidth"] = (a["halfwidth_95"] is not None and b["halfwidth_95"] is not None and
                                   100 * (b["halfwidth_95"] - a["halfwidth_95"]) <= study.max_halfwidth_growth_points)
        if step_costs is not None:
            checks["step_cost"] = scene in step_costs and step_costs[scene] <= study.max_step_cost
        if paper is not None:
            p_today, p_cand = paper[0].get(scene), paper[1].get(scene)
            checks["paper_split"] = (p_today is not None and p_cand is not None
                                     and p_cand["psnr"] - p_today["psnr"] >= -study.max_paper_psnr_loss_db
                                     and p_cand["abs_rel"] - p_today["abs_rel"] <= study.max_paper_abs_rel_loss)
            if study.paper_levels:
                checks["paper_levels"] = (p_today is not None and p_cand is not None
                                          and coverage_held(study, p_today, p_cand))
        scenes[scene] = {"psnr_gain_db": psnr_gain, "abs_rel_change": abs_rel_change,
                         "checks": checks, "passes": all(checks.values())}
    both = {"fern", "flower"} <= set(scenes)
    out = {"scenes": scenes, "taken": both and all(s["passes"] for s in scenes.values())}
    if study.gain_on_mean:
        mean_gain = sum(s["psnr_gain_db"] for s in scenes.values()) / max(len(scenes), 1)
        out["mean_psnr_gain_db"] = mean_gain
        out["taken"] = out["taken"] and mean_gain >= study.min_psnr_gain_db
    return out


def coverage_held(study: Study, today: dict, candidate: dict) -> bool:
    """The candidate's recalibrated coverage at each of the study's levels within ``coverage_points`` of
    nominal (``study_helpers.coverage_failures``) or, with ``level_as_far_as_today``, no farther from it
    than today's; a row without coverage fails."""
    keys = [f"coverage_{p}" for p in study.levels]
    if any(candidate.get(key) is None for key in keys):
        return False
    nominal = {key: NOMINAL[p] / 100.0 for key, p in zip(keys, study.levels)}
    reference = {key: today.get(key) if today.get(key) is not None else nominal[key] for key in keys} \
        if study.level_as_far_as_today else nominal
    return not coverage_failures(reference, candidate, tuple(nominal.values()), study.coverage_points / 100.0)


def rule_text(study: Study) -> str:
    if study.min_psnr_gain_db is None:
        lead = (f"neither capture's PSNR falls by more than {study.max_psnr_loss_db} dB (no gain asked: the captures "
                f"need only hold)")
    elif study.gain_on_mean:
        lead = (f"its PSNR gain averaged over the two scenes is at least {study.min_psnr_gain_db} dB and on each "
                f"scene its PSNR at most {study.max_psnr_loss_db} dB below today's")
    else:
        lead = f"on both scenes its PSNR is at least {study.min_psnr_gain_db} dB above today's"
        if study.min_abs_rel_gain is not None:
            lead += f" or its depth abs-rel at least {study.min_abs_rel_gain} below"
        if study.max_psnr_loss_db is not None:
            lead += f", its PSNR at most {study.max_psnr_loss_db} dB below"
    levels = (f"recalibrated 68% and 95% coverage within {study.coverage_points:g} points of nominal"
              if study.levels == (68, 95) else
              f"recalibrated coverage at {', '.join(str(p) for p in study.levels)}% within {study.coverage_points:g} "
              f"points of nominal" + (" (a level today's misses, no farther)" if study.level_as_far_as_today else ""))
    width = (f", its median 95% half-width / depth at most {study.max_halfwidth_growth_points:g} point wider"
             if study.max_halfwidth_growth_points is not None else "")
    minutes = (f" and its training at most {study.max_minutes:g} minutes" if study.max_minutes is not None else "")
    minutes += (f" and a training step at most {study.max_step_cost:g}x today's" if study.step_costs else "")
    paper = (f" At the paper split (the tables' S-NeRF default row, {paper_seeds_text(study)}) its PSNR is at "
             f"most {study.max_paper_psnr_loss_db} dB and its depth abs-rel at most {study.max_paper_abs_rel_loss} "
             f"worse than today's on each scene" + (f", its {levels}" if study.paper_levels else "") + "."
             if study.paper_tables else "")
    seeds = " (on the means of the seeds)" if has_seeds(study) else ""
    return (f"Rule (fixed before the rows){seeds}: the candidate is taken if {lead}, "
            f"its depth abs-rel at most {study.max_abs_rel_loss} above, its {levels}{width}{minutes}.{paper}")


def paper_seeds_text(study: Study) -> str:
    """Which seeds the study's paper-split rows are: seed 0, or the means of several."""
    count = len(study.paper_tables[1]) if study.paper_tables and not isinstance(study.paper_tables[1], str) else 1
    return "seed 0" if count == 1 else f"the means of seeds 0-{count - 1}"


def score_table(study: Study, rows: dict[str, dict], caption: str | None) -> list[str]:
    """The markdown table of ``rows`` (label -> ``row_scores``), scene by scene, with every level the study rules."""
    levels = " / ".join(str(p) for p in study.levels)
    lines = [f"Rows: {caption}.", ""] if caption else []
    lines += [f"| scene | row | steps (steps/s) | minutes | PSNR dB (at half the schedule) | SSIM | depth abs-rel | "
              f"cov {levels} | median 95% half-width |", "|" + "---|" * 9]
    for scene in sorted({scene for scores in rows.values() for scene in scores}):
        for label, scores in rows.items():
            s = scores.get(scene)
            if s is None:
                continue
            half = s["curve"][0] if len(s["curve"]) > 1 else None
            half_text = f" ({half[1]:.2f} at {half[0]:.1f} min)" if half else ""
            cov = (" / ".join(f"{100 * s[f'coverage_{p}']:.1f}" for p in study.levels)
                   if all(s.get(f"coverage_{p}") is not None for p in study.levels) else "-")
            width = f"{100 * s['halfwidth_95']:.1f}%" if s["halfwidth_95"] is not None else "-"
            lines.append(f"| {scene} | {label} | {s['steps']:.0f} ({s['steps_per_s']:.2f}) | {s['minutes']:.1f} | "
                         f"{s['psnr']:.2f}{half_text} | {s['ssim']:.3f} | {s['abs_rel']:.4f} | {cov} | {width} |")
    return lines


def plot_seed_pairs(seeds: dict[str, dict[str, dict]], path: Path) -> None:
    """Per scene, each seed's PSNR, depth abs-rel and median 95% half-width under today's setting and the
    candidate's (``read_rows``' seeds: the two rows' labels -> seed folder -> scores, the seeds in the
    same order under both), a seed's two rows joined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (today_label, today), (cand_label, candidate) = seeds.items()
    # a row's seeds are listed in the same order under both settings (the study's folders)
    pairs = [(name, t, c) for (name, t), c in zip(today.items(), candidate.values())]
    scenes = sorted(set.intersection(*(set(t) & set(c) for _, t, c in pairs)))
    metrics = (("psnr", "PSNR dB", 1.0), ("abs_rel", "depth abs-rel", 1.0), ("halfwidth_95", "median 95% half-width / depth, %", 100.0))
    fig, axes = plt.subplots(len(scenes), len(metrics), figsize=(4 * len(metrics), 3.2 * len(scenes)), squeeze=False)
    for row, scene in zip(axes, scenes):
        for ax, (key, name, factor) in zip(row, metrics):
            for seed, t, c in pairs:
                if t[scene][key] is not None and c[scene][key] is not None:
                    ax.plot([0, 1], [factor * t[scene][key], factor * c[scene][key]], "o-", label=seed)
            ax.set_xticks([0, 1], [today_label, cand_label])
            ax.set_xlim(-0.4, 1.4)
            ax.set(title=f"{scene}: {name}")
            ax.grid(alpha=0.3)
        row[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--study", choices=sorted(STUDIES), required=True)
    ap.add_argument("--out", type=Path, default=None, help="Default: the study's results folder.")
    args = ap.parse_args()
    study = STUDIES[args.study]
    out = args.out or Path(study.out)
    rows, seeds = read_rows(study, out)
    (today_label, today), (cand_label, candidate) = rows.items()
    paper = tuple(paper_means(paths) for paths in study.paper_tables) if study.paper_tables else None
    costs = step_cost_ratios(study, out)
    v = verdict(study, today, candidate, paper, costs)
    out.mkdir(parents=True, exist_ok=True)
    (out / "verdict.json").write_text(json.dumps({"rows": rows, "paper_split": paper, "step_cost": costs,
                                                  "verdict": v}, indent=2) + "\n")
    lines = [f"# Study {study.number}: {study.title}", "",
             f"Rows: `benchmarks/capture_quality.py` ({study.protocol}); each row's own README in its folder:", ""]
    lines += [f"    {command}" for command in study.commands]
    lines += ["", f"Verdict: `python benchmarks/studies/capture_grid_study.py --study {args.study}`.", ""]
    lines += score_table(study, rows, "the means of the seeds" if seeds else None)
    for label, per_seed in seeds.items():  # each seed's row beside the means
        lines += ["", *score_table(study, {f"{label}, {name}": scores for name, scores in per_seed.items()},
                                   f"{label}, each seed")]
    if paper is not None:
        levels = " / ".join(str(p) for p in NOMINAL)
        lines += ["", f"Paper split (the tables' S-NeRF default row, {paper_seeds_text(study)}, its test views):", "",
                  f"| scene | row | PSNR dB | depth abs-rel | cov {levels} |", "|---|---|---|---|---|"]
        for scene in sorted(paper[0]):
            for label, scores in zip(rows, paper):
                if scene in scores:
                    s = scores[scene]
                    cov = (" / ".join(f"{100 * s[f'coverage_{p}']:.1f}" for p in NOMINAL)
                           if all(f"coverage_{p}" in s for p in NOMINAL) else "-")
                    lines.append(f"| {scene} | {label} | {s['psnr']:.2f} | {s['abs_rel']:.4f} | {cov} |")
    if costs is not None:
        lines += ["", "A training step's cost, the candidate over today's (`benchmarks/studies/capture_step_cost.py`, "
                  "interleaved in one process): " + ", ".join(f"{scene} {r:.3f}x" for scene, r in sorted(costs.items()))]
    lines += ["", rule_text(study), ""]
    for scene, s in v["scenes"].items():
        failed = [k for k, ok in s["checks"].items() if not ok]
        lines.append(f"- {scene}: PSNR {s['psnr_gain_db']:+.2f} dB, abs-rel {s['abs_rel_change']:+.4f}: "
                     + ("passes" if s["passes"] else "fails " + ", ".join(failed)))
    if "mean_psnr_gain_db" in v:
        lines.append(f"- PSNR gain averaged over the scenes: {v['mean_psnr_gain_db']:+.2f} dB "
                     f"(at least {study.min_psnr_gain_db} asked)")
    for scene in sorted({"fern", "flower"} - set(v["scenes"])):
        lines.append(f"- {scene}: no row of both settings (the rule needs it on every scene)")
    lines += ["", f"**{'Taken' if v['taken'] else 'Not taken'}.**", ""]
    if len(seeds) == 2:
        plot_seed_pairs(seeds, out / "seeds.png")
        lines += ["![each seed, both settings](seeds.png)", ""]
    (out / "README.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
