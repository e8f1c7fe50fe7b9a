"""Analysis (decides nothing): the depth intervals' coverage and width by how many training views observed each point.

Study 38 found that calibration views which render only the points both views of their pair observed fit a
map too narrow for paper-split fern's validation photos, and that fitting on the points either view observed
holds fern but widens every band. This asks where the shortfall lies: the validation photos' SCORE points are
grouped by how many training views' COLMAP tracks hold them (0, 1, 2, 3 or more), and each group is scored
as eval scores the pool (``evaluation.calibrated_depth_scores``: the run's map, cross-fitted over the SCORE
blocks). Inputs: study 37's today runs and their validation photos rendered by ``stochastic-fields eval
--views`` with per-view maps (``views/view_XXX.npz``). Command::

    # per run: stochastic-fields eval --run runs/colour_capacity_paper/sSEED/today/SCENE/snerf_default \\
    #     --views VALIDATION --quiet --out runs/visibility_analysis/sSEED/today/SCENE
    python benchmarks/studies/visibility_count_analysis.py --runs runs/colour_capacity_paper \\
        --evals runs/visibility_analysis --out benchmarks/results/visibility_count_analysis
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import write_study  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402

from stochastic_fields import metrics as M  # noqa: E402
from stochastic_fields.calibration import load_run_calibration  # noqa: E402
from stochastic_fields.capture_points import (block_keys, load_capture_points, restrict_sparse_depth,  # noqa: E402
                                              score_sparse_depth)
from stochastic_fields.evaluation import calibrated_depth_scores, depth_samples, pool_depth_samples  # noqa: E402
from stochastic_fields.config import load_config  # noqa: E402
from stochastic_fields.scenes import load_run_dataset  # noqa: E402

SEEDS = (12, 13, 14)
SCENES = ("fern", "flower")
#: Groups by the number of training views that observed a point (the last: that many or more).
GROUPS = (0, 1, 2, 3)


def group_name(g: int) -> str:
    return f"{g}+" if g == GROUPS[-1] else str(g)


def run_groups(run: Path, evals: Path, views: list[int]) -> dict[int, list]:
    """{group: [DepthSamples of each view]} of one run's validation photos (opacity above the mask, as eval)."""
    dataset = load_run_dataset(load_config(run / "config.json"), run)
    capture = load_capture_points(dataset)
    sparse = score_sparse_depth(dataset, views)
    train = [int(t) for t in dataset.train_indices]
    out: dict[int, list] = {g: [] for g in GROUPS}
    for v in views:
        sd = sparse[v]
        with np.load(evals / "views" / f"view_{v:03d}.npz") as f:
            products = {k: f[k] for k in f.files}
        count = sum(np.isin(sd.point_index, capture.visible[t]).astype(int) for t in train)
        blocks = block_keys(capture.xyz[sd.point_index], capture.xyz)
        for g in GROUPS:
            member = np.minimum(count, GROUPS[-1]) == g
            if not member.any():
                continue
            s = depth_samples(products, sparse=restrict_sparse_depth(sd, member), blocks=blocks[member])
            if s is not None and s.gt.size:
                out[g].append(s)
    return out


def scores(pool: list, calibration) -> dict:
    samples = pool_depth_samples(pool)
    s = calibrated_depth_scores(samples, calibration)
    iv = s["intervals"]
    rel = np.abs(samples.pred - samples.gt) / samples.gt
    return {"points": int(samples.gt.size), "abs_rel": float(np.mean(rel)),
            "coverage": {M.level_name(p): float(iv[f"coverage_{M.level_name(p)}"]) for p in M.INTERVAL_LEVELS},
            "halfwidth_median_95": float(iv["halfwidth_median_95"]), "interval_score_95": float(iv["interval_score_95"]),
            "crps": float(iv["crps"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/colour_capacity_paper"))
    ap.add_argument("--evals", type=Path, default=Path("runs/visibility_analysis"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/visibility_count_analysis"))
    args = ap.parse_args()
    rows: dict = {}
    for scene in SCENES:
        views = validation_views(scene)
        per_seed = []
        for seed in SEEDS:
            run = args.runs / f"s{seed}" / "today" / scene / "snerf_default"
            groups = run_groups(run, args.evals / f"s{seed}" / "today" / scene, views)
            cal = load_run_calibration(run)
            per_seed.append({g: scores(pool, cal) for g, pool in groups.items() if pool})
        rows[scene] = per_seed
    lines = ["# Coverage and width of the depth intervals by how many training views observed each point", "",
             "Study 37's today runs (paper split, decoder 32 / 8, seeds 12-14), their validation photos' SCORE points "
             "grouped by how many training views' COLMAP tracks hold them; each group scored as eval scores the pool "
             "(the run's map, cross-fitted). Means over the seeds (points: summed). Decides nothing.", "",
             "| scene | training views that observed the point | points | abs-rel | cov 50 / 68 / 90 / 95 / 99 | "
             "median 95% half-width | IS95 / depth | CRPS / depth |", "|---|---|---|---|---|---|---|---|"]
    for scene, per_seed in rows.items():
        for g in GROUPS:
            have = [r[g] for r in per_seed if g in r]
            if not have:
                continue
            mean = lambda key: float(np.mean([r[key] for r in have]))  # noqa: E731
            cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in have]):.1f}" for n in ("50", "68", "90", "95", "99"))
            lines.append(f"| {scene} | {group_name(g)} | {sum(r['points'] for r in have)} | {mean('abs_rel'):.4f} | {cov} | "
                         f"{100 * mean('halfwidth_median_95'):.1f}% | {mean('interval_score_95'):.3f} | {mean('crps'):.4f} |")
    lines += ["", "Command: the module docstring of `benchmarks/studies/visibility_count_analysis.py`."]
    write_study(args.out, {"rows": {s: [{group_name(g): r for g, r in seed.items()} for seed in v] for s, v in rows.items()},
                           "seeds": list(SEEDS)}, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
