"""Analysis (decides nothing): how narrow can honest depth intervals built on today's std be, if the map were
fitted on the validation photos' own points?

Every map so far was fitted on points rendered from calibration views, and the studies since 37 found those
points err unlike the photos' (``agreement_groups_analysis.py``). This asks what a perfect calibration set
would buy: the map (today's form: the free-space weight beta, rho and s(p) refitted,
``calibration.depth_map_and_folds``) fitted on the validation photos' SCORE points themselves, cross-fitted
over the SCORE blocks (each point judged by the fold map that did not see its block, so its levels hold by
construction up to the folds' differences). Its median 95% half-width is then the narrowest band today's
std can carry honestly: if it exceeds issue 36's 15%, no calibration data reaches the target and the std or
the model must change. Beside it: the same with a map per agreement group (``agreement_groups_analysis``),
and a band proportional to the depth alone (the std's ranking left out), which shows how much of the width
the std's ranking already saves. Today's map (calibration views) is the reference.

Inputs: ``agreement_groups_analysis.py``'s runs and validation renders. Command::

    OMP_NUM_THREADS=1 python benchmarks/studies/oracle_map_analysis.py --runs runs/mondrian --seeds 12 13 14 \\
        --work runs/mondrian/oracle --out benchmarks/results/oracle_map_analysis
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from agreement_groups_analysis import (GROUP_NAMES, LEVELS, TOLERANCE, group_of, run_and_evals,  # noqa: E402
                                       scored, subset, subset_samples, validation_pool)
from study_helpers import cached, write_study  # noqa: E402

from stochastic_fields.calibration import depth_map_and_folds, load_run_calibration  # noqa: E402
from stochastic_fields.capture_points import load_capture_points  # noqa: E402
from stochastic_fields.free_space import checked_std, load_training_depth  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402

SCENES = ("fern", "flower")
#: A raw std this small relative to the depth leaves the map's depth-proportional term alone.
NEGLIGIBLE_STD = 1e-6
VARIANTS = (("today", "today's map (calibration views)"),
            ("oracle", "today's form, fitted on the photos' points"),
            ("oracle_groups", "a map per agreement group, fitted on the photos' points"),
            ("oracle_depth_only", "rho x depth alone, fitted on the photos' points"))


def photo_renders(samples, index: np.ndarray) -> dict:
    """The validation points ``samples`` as ``depth_calibration_renders`` output (the checked std at full
    weight, the raw sigma, the violation, the capture point ``index`` [N]), like it only where the raw
    std is finite and > 0 (a few pixels render every draw at one depth)."""
    err = samples.gt - samples.pred
    renders = {"abs_err": np.abs(err), "err": err, "std": checked_std(samples.std_raw, samples.violation),
               "std_raw": samples.std_raw, "violation": samples.violation, "depth": samples.pred, "index": index,
               "view": np.zeros(index.size, np.int64), "source": "validation photos' SCORE points"}
    return subset(renders, np.isfinite(samples.std_raw) & (samples.std_raw > 0))


def _blind(samples):
    """``samples`` with sigma and the violation negligible: a map fitted on them is rho times the depth."""
    return type(samples)(samples.gt, samples.pred, samples.std, NEGLIGIBLE_STD * samples.pred, {},
                         np.zeros_like(samples.pred), samples.block, None)


def analyse(scene: str, run: Path, evals: Path) -> dict:
    """One run: the scores of each variant on the validation points, and each oracle map's fitted terms."""
    _, _, dataset = load_trained_model(run, device="cpu")
    ref = load_training_depth(run)
    capture = load_capture_points(dataset)
    samples, index, counts = validation_pool(scene, evals, dataset, capture, ref)
    groups = group_of(counts, len(ref.views))
    cal = load_run_calibration(run)
    fit = lambda r, where: depth_map_and_folds(r, capture, relative_floor=True, where=where)  # noqa: E731
    oracle = fit(photo_renders(samples, index), f"{run} oracle")
    per_group = [fit(photo_renders(subset_samples(samples, groups == g), index[groups == g]), f"{run} oracle group {g}")
                 for g in range(len(GROUP_NAMES))]
    blind = _blind(samples)
    depth_only = fit(photo_renders(blind, index), f"{run} depth only")
    variants = {"today": (samples, [(cal.depth, cal.depth_folds)]), "oracle": (samples, [oracle]),
                "oracle_groups": (samples, per_group), "oracle_depth_only": (blind, [depth_only])}
    out = {name: scored(s, groups, fitted) for name, (s, fitted) in variants.items()}
    out["terms"] = {name: {"rho": fitted[0][0].relative_floor,
                           "beta": fitted[0][0].free_space_weight if fitted[0][0].free_space else 0.0}
                    for name, (_, fitted) in variants.items() if len(fitted) == 1}
    return out


def markdown(results: dict, seeds: list[int]) -> str:
    lines = ["# How narrow can honest intervals on today's std be?", "",
             f"Today's S-NeRF (paper split, tables' budget, seed{'s' if len(seeds) > 1 else ''} "
             f"{', '.join(map(str, seeds))}), its validation photos' SCORE points (opacity > 0.5), each map "
             "cross-fitted over the SCORE blocks (a point is judged by the fold map that did not see its block). "
             f"Agreement groups as in `agreement_groups_analysis.py` (tau {100 * TOLERANCE:g}%). Means over the seeds. "
             "Decides nothing.", "",
             "| scene | map | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
             "Spearman |err|-std |", "|---|---|---|---|---|---|---|"]
    for scene, per_seed in results.items():
        for name, label in VARIANTS:
            rows = [r[name] for r in per_seed]
            mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
            cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in rows]):.1f}" for n in LEVELS)
            lines.append(f"| {scene} | {label} | {cov} | {100 * mean('halfwidth_median_95'):.1f}% | "
                         f"{mean('interval_score_95'):.3f} | {mean('crps'):.4f} | {mean('spearman'):.3f} |")
    lines += ["", "Fitted terms (per seed): " + "; ".join(
        f"{scene} {name} rho " + ", ".join(f"{r['terms'][name]['rho']:.3g}" for r in per_seed)
        + " beta " + ", ".join(f"{r['terms'][name]['beta']:.3g}" for r in per_seed)
        for scene, per_seed in results.items() for name in ("today", "oracle", "oracle_depth_only")) + ".",
              "", "Command: the module docstring of `benchmarks/studies/oracle_map_analysis.py`."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/mondrian"))
    ap.add_argument("--work", type=Path, default=Path("runs/mondrian/oracle"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/oracle_map_analysis"))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--seeds", nargs="+", type=int, default=[12, 13, 14])
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results: dict = {}
    for scene in args.scenes:
        results[scene] = [cached(args.work / f"s{seed}" / f"{scene}.json",
                                 lambda: analyse(scene, *run_and_evals(args.runs, seed, scene)))
                          for seed in args.seeds]
    write_study(args.out, {"results": results, "seeds": args.seeds}, markdown(results, args.seeds))


if __name__ == "__main__":
    main()
