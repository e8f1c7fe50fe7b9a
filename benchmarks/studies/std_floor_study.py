"""Study 11: does a depth std floor make the recalibrated intervals hold at every level of sigma?

The depth map (``stochastic_fields.calibration``) scales the raw std sigma by one factor per level.
On the calibration points of the real scenes the most confident renders hold the largest
standardised errors (a surface rendered in the wrong place with a tiny sigma), so one factor is
too wide where sigma is large and too narrow where it is small, and a set of points' coverage
depends on its mix of sigmas. The floored map standardises by sqrt(sigma^2 + tau^2) instead
(``calibration.fit_std_floor``). This study fits both maps on the same CALIBRATE renders (the
calibration views, as ``stochastic-fields calibrate`` does) and scores both on the SCORE points seen
from the run's evaluated test views (``study_helpers.scored_points``; on the synthetic
scene a seeded 10% of the test views' surface pixels in SCORE blocks), overall and per tercile of
the scored points' raw sigma.

    python benchmarks/studies/std_floor_study.py --run fern/seed0=RUN flower/seed0=RUN ... \\
        --out benchmarks/results/uncertainty_study/std_floor

Labels are SCENE/SEED; the decision reads the means over a scene's seeds (docs/uncertainty.md,
study 11, where the rule was fixed before this ran). Renders only (no training). Torch on 1 thread.
Writes ``study.json``, ``study.md`` and ``coverage_by_std.png``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import (LEVELS, STD_GROUPS, begin_study, by_scene, coverage, distance, gap,  # noqa: E402,F401
                    scored_points, study_parser, tercile_rows, write_study)

#: Study 11's tolerances (fixed with the rule): coverage distance and conditional gap may grow by
#: at most this much on any scene (study 8's coverage tolerance) ...
TOLERANCE: float = 0.02
#: ... and the conditional gap must fall by at least this much on the mean over scenes.
GAP_GAIN: float = 0.05


def study_run(run_dir: Path, *, seed: int = 0, bounds: str | None = None) -> dict:
    from scipy.stats import spearmanr

    from stochastic_fields.calibration import QuantileCalibration, depth_calibration_errors
    from stochastic_fields.capture_points import FIT, SCORE, block_roles, load_capture_points
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    points = load_capture_points(dataset)
    if points is None:
        raise ValueError(f"{run_dir}: the scene has no capture points")
    err, std, source = depth_calibration_errors(model, dataset, seed=seed,
                                                **({} if bounds is None else {"bounds": bounds}))
    plain = QuantileCalibration.fit_errors(err, std, quantity="depth_std", floor=False, source=source)
    floored = QuantileCalibration.fit_errors(err, std, quantity="depth_std", floor=True, source=source)
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    scored = scored_points(run_dir, model, dataset, points, views, points.roles != FIT, seed)
    keep = (block_roles(scored["xyz"], points) if points.source == "synthetic" else scored["role"]) == SCORE
    s_err, s_std = scored["abs_err"][keep], scored["std"][keep]
    rows = tercile_rows(s_err, s_std, floored, plain)
    return {"run": str(run_dir), "views": views, "calibration_points": int(len(err)), "source": source,
            "floor": floored.floor, "median_calibration_std": float(np.median(std)),
            "scales_plain": plain.scale_at(np.asarray(LEVELS)).tolist(),
            "scales_floored": floored.scale_at(np.asarray(LEVELS)).tolist(),
            "calibration_trend": float(spearmanr(std, err / std)[0]),
            "scored_trend": {"plain": float(spearmanr(s_std, s_err / s_std)[0]),
                             "floored": float(spearmanr(s_std, s_err / np.hypot(s_std, floored.floor))[0])},
            "groups": rows,
            "distance": {"plain": distance(rows[-1]["coverage_raw"]), "floored": distance(rows[-1]["coverage"])},
            "gap": {"plain": gap(rows, "coverage_raw"), "floored": gap(rows, "coverage")}}


def decide(results: dict) -> dict:
    """Study 11's rule on the per-scene means over seeds (module doc; docs/uncertainty.md)."""
    scenes = {}
    for scene, runs in by_scene(results["runs"]).items():
        mean = lambda key, which: float(np.mean([r[key][which] for r in runs]))  # noqa: E731
        scenes[scene] = {"seeds": len(runs),
                         "coverage_plain": np.mean([r["groups"][-1]["coverage_raw"] for r in runs], axis=0).tolist(),
                         "coverage_floored": np.mean([r["groups"][-1]["coverage"] for r in runs], axis=0).tolist(),
                         "distance_plain": mean("distance", "plain"), "distance_floored": mean("distance", "floored"),
                         "gap_plain": mean("gap", "plain"), "gap_floored": mean("gap", "floored"),
                         "floor_fitted": sum(r["floor"] > 0 for r in runs)}
    worse = [s for s, m in scenes.items()
             if m["distance_floored"] > m["distance_plain"] + TOLERANCE or m["gap_floored"] > m["gap_plain"] + TOLERANCE]
    gain = float(np.mean([m["gap_plain"] - m["gap_floored"] for m in scenes.values()]))
    return {"scenes": scenes, "worse_on": worse, "mean_gap_gain": gain,
            "taken": not worse and gain >= GAP_GAIN}


def _markdown(results: dict, command: str) -> str:
    d = results["decision"]
    lines = ["# Study 11: the depth std floor", "", f"Command: `{command}`", "",
             "Both maps fitted on the same CALIBRATE renders (calibration views), scored on the SCORE points "
             f"seen from the test views: share inside the central {LEVELS[0]:.1%} / {LEVELS[1]:.0%} intervals. "
             "*plain*: today's map (one factor per level); *floored*: the factors on |err| / sqrt(sigma^2 + tau^2). "
             "Distance: the largest |coverage - nominal|; gap: the spread of the 68% coverage over the terciles "
             "of raw sigma.", "",
             "## Decision (means over seeds)", "",
             "| scene | seeds | floor fitted | plain 68 / 95 | floored 68 / 95 | distance plain -> floored | "
             "gap plain -> floored |", "|---|---|---|---|---|---|---|"]
    for scene, m in d["scenes"].items():
        lines.append(f"| {scene} | {m['seeds']} | {m['floor_fitted']} | {m['coverage_plain'][0]:.3f} / "
                     f"{m['coverage_plain'][1]:.3f} | {m['coverage_floored'][0]:.3f} / {m['coverage_floored'][1]:.3f} | "
                     f"{m['distance_plain']:.3f} -> {m['distance_floored']:.3f} | "
                     f"{m['gap_plain']:.3f} -> {m['gap_floored']:.3f} |")
    lines += ["", f"Mean gap gain over scenes: {d['mean_gap_gain']:+.3f} (rule: >= {GAP_GAIN}); scenes where "
              f"distance or gap grew by more than {TOLERANCE}: {', '.join(d['worse_on']) or 'none'}. "
              f"**{'Taken' if d['taken'] else 'Not taken'}.**", "", "## Per run", ""]
    for label, r in results["runs"].items():
        lines += [f"### {label}", "", f"Run `{r['run']}`, test views {r['views']}; {r['source']}; floor tau = "
                  f"{r['floor']:.4g} (median calibration sigma {r['median_calibration_std']:.4g}); Spearman(sigma, |z|) "
                  f"on the calibration points {r['calibration_trend']:+.3f}, on the scored points "
                  f"{r['scored_trend']['plain']:+.3f} -> {r['scored_trend']['floored']:+.3f} with the floor.", "",
                  "| group | points | sigma range | floored 68 | floored 95 | plain 68 | plain 95 |",
                  "|---|---|---|---|---|---|---|"]
        for g in r["groups"]:
            lines.append(f"| {g['group']} | {g['points']} | {g['std_range'][0]:.3g} - {g['std_range'][1]:.3g} | "
                         f"{g['coverage'][0]:.3f} | {g['coverage'][1]:.3f} | {g['coverage_raw'][0]:.3f} | "
                         f"{g['coverage_raw'][1]:.3f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from stochastic_fields.calibration import BOUNDS_CHOICES

    p = study_parser(__doc__, "std_floor", "Trained and evaluated S-NeRF (default) runs; labels SCENE/SEED.")
    p.add_argument("--bounds", choices=BOUNDS_CHOICES, default=None,
                   help="Calibration views' render bounds of both maps' fit (default: CALIBRATION_BOUNDS).")
    args, runs, results = begin_study(p, argv, "std_floor_study.py")
    from stochastic_fields.plots import plot_coverage_by_group

    results["runs"] = {}
    for label, run_dir in runs.items():
        print(f"{label}: {run_dir}", flush=True)
        results["runs"][label] = r = study_run(run_dir, seed=args.seed, bounds=args.bounds)
        print(f"  tau {r['floor']:.4g}, distance {r['distance']['plain']:.3f} -> {r['distance']['floored']:.3f}, "
              f"gap {r['gap']['plain']:.3f} -> {r['gap']['floored']:.3f}", flush=True)
    results["decision"] = decide(results)
    text = _markdown(results, results["command"])
    write_study(args.out, results, text)
    first = {}
    for label, r in results["runs"].items():  # one panel per scene: its first seed
        first.setdefault(label.split("/")[0], r["groups"])
    plot_coverage_by_group(first, LEVELS, args.out / "coverage_by_std.png", xlabel="scored points by raw sigma",
                           title="Recalibrated depth coverage by raw sigma: floored map against one factor per level",
                           series=("floored", "plain"))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
