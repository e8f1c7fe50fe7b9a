"""Study 32: the scene box padded by a share of its largest extent, judged by its rule (docs/studies.md,
fixed before the rows ran).

The question: an object-centric scene's box (``SceneDataset.aabb``, the grid's region) is padded by 5%
of each axis's own extent. A flat axis (a floor: the embedded scene's z runs from the ground at 0 to
the objects' tops at 0.8) then gets 0.04 of padding, one cell of the finest level, and the floor sits
on the box's face: below it is outside the field (no density), so the grid cannot make it opaque in
its one layer of cells and fills the space above it instead. The candidate pads every axis by 5% of
the box's largest extent (0.2 on every axis of the embedded scene).

Validation scenes, not the demo's: the embedded scene generated with seeds 1, 2 and 3 (the same
solids, other ring phases, so other photos, other ground and face colours; the demo is seed 0).
Each is written twice, identical but for the ``aabb`` hint of ``transforms.json`` (today's rule and
the candidate's, both computed here from ``scene.ply``'s bounds, so the rows do not depend on the
code version), and trained with the demo preset (S-NeRF, 10 of 40 views, 2000 steps, training seed =
scene seed), then scored on its 30 test views by ``stochastic-fields eval`` (exact depth at the SCORE
blocks' pixels, intervals cross-fitted). Two runs at a time, one thread each::

    python benchmarks/studies/box_padding_study.py --work runs/box_padding_study \\
        --out benchmarks/results/box_padding_study

Resumable: a row whose ``eval/metrics.json`` exists is read, not re-run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import trimesh

from stochastic_fields.data.synthetic import make_synthetic_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared report helpers
from study_helpers import (coverage_failures, pooled_scores, seed_means, train_and_eval,  # noqa: E402
                           validation_scenes_report)
from tables_cap_study import verdict_lines, write_study  # noqa: E402

SEEDS = (1, 2, 3)
PADDING = 0.05
ROWS = ("today (each axis by its own extent)", "candidate (every axis by the largest extent)")
#: The rule, fixed before the rows ran (means over the seeds).
MIN_ABS_REL_GAIN = 0.005
MAX_PSNR_LOSS_DB = 0.1
COVERAGE_TOLERANCE = 0.05
RULE_LEVELS = (0.50, 0.68, 0.90, 0.95)


def padded_box(lo: np.ndarray, hi: np.ndarray, isotropic: bool) -> list[list[float]]:
    """[[lo], [hi]] padded by PADDING x each axis's extent (today) or x the largest extent (candidate)."""
    extent = hi - lo
    pad = PADDING * (np.full(3, extent.max()) if isotropic else extent)
    return [(lo - pad).tolist(), (hi + pad).tolist()]


def write_scenes(work: Path, seed: int) -> dict[str, Path]:
    """The seed's scene, twice: {row label: folder}, differing only in the aabb hint."""
    base = make_synthetic_scene(work / f"scene_s{seed}" / "generated", seed=seed)
    bounds = trimesh.load(base / "scene.ply", process=False).bounds
    folders = {}
    for label, isotropic in zip(ROWS, (False, True)):
        folder = work / f"scene_s{seed}" / ("candidate" if isotropic else "today")
        if not (folder / "transforms.json").is_file():
            folder.mkdir(parents=True, exist_ok=True)
            for sub in ("images", "depth"):
                if not (folder / sub).exists():
                    os.symlink((base / sub).resolve(), folder / sub)
            (folder / "scene.ply").write_bytes((base / "scene.ply").read_bytes())
            meta = json.loads((base / "transforms.json").read_text())
            meta["aabb"] = padded_box(bounds[0], bounds[1], isotropic)
            tmp = folder / "transforms.json.tmp"
            tmp.write_text(json.dumps(meta, indent=1))
            tmp.replace(folder / "transforms.json")
        folders[label] = folder
    return folders


def run_row(scene: Path, run: Path, seed: int) -> dict:
    """Train (demo preset) and score one row; the pooled metrics it needs, and the row's box."""
    return {**pooled_scores(train_and_eval(scene, run, seed), RULE_LEVELS),
            "aabb": json.loads((scene / "transforms.json").read_text())["aabb"]}


def verdict(today: dict, candidate: dict) -> tuple[bool, list[str]]:
    failed = []
    if candidate["abs_rel"] > today["abs_rel"] - MIN_ABS_REL_GAIN:
        failed.append(f"depth abs-rel {today['abs_rel']:.4f} -> {candidate['abs_rel']:.4f}: not {MIN_ABS_REL_GAIN} lower")
    if candidate["psnr"] < today["psnr"] - MAX_PSNR_LOSS_DB:
        failed.append(f"PSNR {today['psnr']:.2f} -> {candidate['psnr']:.2f} dB: more than {MAX_PSNR_LOSS_DB} dB lower")
    if candidate["halfwidth_median_95"] > today["halfwidth_median_95"]:
        failed.append(f"median 95% half-width {100 * today['halfwidth_median_95']:.1f}% -> "
                      f"{100 * candidate['halfwidth_median_95']:.1f}%: wider")
    failed += coverage_failures(today, candidate, RULE_LEVELS, COVERAGE_TOLERANCE)
    return not failed, failed


def table_row(label: str, r: dict) -> str:
    cov = "/".join(f"{100 * r[f'coverage_{c}']:.1f}" for c in (50, 68, 90, 95, 99))
    return (f"| {label} | {r['psnr']:.2f} | {r['abs_rel']:.4f} | {cov} | {100 * r['halfwidth_median_95']:.1f}% | "
            f"{r['interval_score_95']:.3f} | {r['crps']:.4f} | {r['spearman']:.3f} |")


def report(rows: dict, means: dict, taken: bool, failed: list[str]) -> str:
    head = ["| row | PSNR dB | depth abs-rel | cov 50/68/90/95/99 | median 95% half-width / depth | IS95 / depth | "
            "CRPS / depth | depth Spearman |", "|---|---|---|---|---|---|---|---|"]
    lines = validation_scenes_report("Study 32: the scene box padded by a share of its largest extent",
                                     "box_padding_study.py", ROWS, rows, means, SEEDS, head, table_row)
    lines += ["", "Boxes (seed 1): " + "; ".join(f"{label}: {rows[label][0]['aabb']}" for label in ROWS)]
    lines += verdict_lines(taken, failed)
    lines += ["", "Rule (fixed before the rows): the candidate is taken if, on the means over the seeds, its depth "
              f"abs-rel is at least {MIN_ABS_REL_GAIN} lower, its PSNR at most {MAX_PSNR_LOSS_DB} dB lower, its median "
              "95% half-width not wider, and each of the 50/68/90/95% levels within "
              f"{round(100 * COVERAGE_TOLERANCE)} points of nominal or no further from it than today's."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("runs/box_padding_study"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/box_padding_study"))
    ap.add_argument("--jobs", type=int, default=2, help="Rows trained at once (one thread each).")
    args = ap.parse_args()
    jobs = []
    for seed in SEEDS:
        scenes = write_scenes(args.work, seed)
        for label in ROWS:
            tag = "candidate" if label == ROWS[1] else "today"
            jobs.append((label, seed, scenes[label], args.work / f"s{seed}" / tag))
    with ThreadPoolExecutor(args.jobs) as pool:
        results = list(pool.map(lambda j: run_row(j[2], j[3], j[1]), jobs))
    rows = {label: [r for (lab, *_), r in zip(jobs, results) if lab == label] for label in ROWS}
    means = {label: seed_means(rows[label]) for label in ROWS}
    taken, failed = verdict(means[ROWS[0]], means[ROWS[1]])
    write_study(args.out, {"study": 32, "rows": rows, "means": means, "seeds": list(SEEDS), "taken": taken,
                           "failed": failed}, report(rows, means, taken, failed))


if __name__ == "__main__":
    main()
