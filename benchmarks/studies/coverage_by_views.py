"""Do the recalibrated depth intervals hold equally where few and many training views saw the surface?

The depth recalibration (``stochastic_fields.calibration``) is one map for a whole scene. A planner
would like its intervals to hold as well on a surface two training views matched as on one that
six did: coverage conditional on how well a point was observed, not only on average. This study
takes trained runs, renders the SCORE capture points from the run's evaluated test views (as
``calibration_split_study.py`` does: at the points' sub-pixel positions; on the synthetic scene a
seeded 10% of the test views' SCORE-block surface pixels), and groups them by how many training
views observe them (``capture_points.training_view_counts``: the COLMAP tracks, or the depth-map
test of the synthetic scene's stand-in points). Per group it reports the share inside the central
68% and 95% intervals with the run's stored map (``RUN/calibration.json``) and raw, and the
median standardised error |d - d*| / sigma.

    python benchmarks/studies/coverage_by_views.py --run fern=RUN flower=RUN synthetic=RUN \\
        --out benchmarks/results/uncertainty_study/coverage_by_views

Renders only (no training; test views choose nothing). Torch on 1 thread. Writes ``study.json``,
``study.md`` and ``coverage_by_views.png``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import LEVELS, begin_study, scored_points, study_parser, write_study  # noqa: E402

#: Groups of the training-view count: (label, lowest, highest).
GROUPS: tuple[tuple[str, int, int], ...] = (("0", 0, 0), ("1", 1, 1), ("2", 2, 2), ("3-4", 3, 4), ("5+", 5, 10**9))


def coverage_table(abs_z: np.ndarray, counts: np.ndarray, bounds: np.ndarray, raw_bounds: np.ndarray) -> list[dict]:
    """One row per non-empty group of ``GROUPS`` and one for all points: the number of points, the
    share with |z| <= each of ``bounds`` [L] (calibrated) and ``raw_bounds`` [L], and the median
    |z|. ``abs_z``, ``counts``: [N] standardised errors and training-view counts."""
    rows = []
    for label, lo, hi in GROUPS + (("all", 0, 10**9),):
        m = (counts >= lo) & (counts <= hi)
        if not m.any():
            continue
        z = abs_z[m]
        rows.append({"group": label, "points": int(m.sum()),
                     "coverage": (z[:, None] <= bounds[None, :]).mean(0).tolist(),
                     "coverage_raw": (z[:, None] <= raw_bounds[None, :]).mean(0).tolist(),
                     "median_abs_z": float(np.median(z))})
    return rows


def study_scene(run_dir: Path, *, seed: int = 0) -> dict:
    from scipy.special import ndtri

    from stochastic_fields.calibration import load_run_calibration
    from stochastic_fields.capture_points import (FIT, SCORE, block_roles, load_capture_points,
                                                  training_view_counts)
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    points = load_capture_points(dataset)
    if points is None:
        raise ValueError(f"{run_dir}: the scene has no capture points")
    calibration = load_run_calibration(run_dir)
    if calibration is None or calibration.depth is None:
        raise ValueError(f"{run_dir}: no depth calibration in calibration.json (run `stochastic-fields calibrate`)")
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    scored = scored_points(run_dir, model, dataset, points, views, points.roles != FIT, seed)
    if points.source == "synthetic":  # the tables score the pixels whose surface lies in a SCORE block
        keep = block_roles(scored["xyz"], points) == SCORE
        counts = training_view_counts(dataset, points, scored["xyz"][keep])
    else:
        keep = scored["role"] == SCORE
        counts = training_view_counts(dataset, points)[scored["index"][keep]]
    levels = np.asarray(LEVELS)
    raw_bounds = ndtri((1.0 + levels) / 2.0)
    bounds = calibration.depth.scale_at(levels) * raw_bounds
    return {"run": str(run_dir), "views": views, "train_views": [int(v) for v in dataset.train_indices],
            "source": points.source, "scales": calibration.depth.scale_at(levels).tolist(),
            "groups": coverage_table(scored["abs_z"][keep], counts, bounds, raw_bounds)}


def _markdown(results: dict, command: str) -> str:
    lines = ["# Recalibrated depth coverage by how many training views observe the point", "",
             f"Command: `{command}`", "",
             f"SCORE points seen from the test views, grouped by the number of training views that observe "
             f"them; share inside the central {LEVELS[0]:.1%} / {LEVELS[1]:.0%} intervals with the run's "
             "stored map (calibrated) and without it (raw), and the median |d - d*| / sigma (raw std).", ""]
    for scene, res in results["scenes"].items():
        lines += [f"## {scene}", "", f"Run `{res['run']}`, training views {res['train_views']}, test views "
                  f"{res['views']}; map s(68%) = {res['scales'][0]:.2f}, s(95%) = {res['scales'][1]:.2f}.", "",
                  "| training views | points | calibrated 68 | calibrated 95 | raw 68 | raw 95 | median abs z |",
                  "|---|---|---|---|---|---|---|"]
        for g in res["groups"]:
            lines.append(f"| {g['group']} | {g['points']} | {g['coverage'][0]:.3f} | {g['coverage'][1]:.3f} | "
                         f"{g['coverage_raw'][0]:.3f} | {g['coverage_raw'][1]:.3f} | {g['median_abs_z']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "coverage_by_views", "Trained, evaluated and calibrated runs, one per scene.", metavar="SCENE=RUN_DIR")
    args, runs, results = begin_study(p, argv, "coverage_by_views.py")
    from stochastic_fields.plots import plot_coverage_by_group

    results["scenes"] = {}
    for scene, run_dir in runs.items():
        print(f"{scene}: {run_dir}", flush=True)
        results["scenes"][scene] = study_scene(run_dir, seed=args.seed)
    text = _markdown(results, results["command"])
    write_study(args.out, results, text)
    plot_coverage_by_group({s: r["groups"] for s, r in results["scenes"].items()}, LEVELS,
                           args.out / "coverage_by_views.png", xlabel="training views observing the point",
                           title="Recalibrated depth coverage by how many training views observe the point")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
