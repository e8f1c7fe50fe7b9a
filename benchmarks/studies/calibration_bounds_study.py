"""Study 12: the render bounds of the calibration views.

A calibration view sits between two training views; its near/far bounds come from theirs. Today it
takes the pair's widest (the nearer near, the farther far). The grid's renders depend on the bounds:
on flower, rendering a training view's own pixels with its pair's nearer near plane (3% nearer)
quadruples their depth error. The view then renders space that no training ray sampled. This
study fits the depth map (one factor per level, no floor) on the CALIBRATE points seen from the
calibration views with each choice of bounds (``calibration.BOUNDS_CHOICES``). It scores each map on
the SCORE points seen from the run's evaluated test views, overall and per tercile of raw sigma (as
``std_floor_study.py``). Beside that, with no test view, it compares each choice's calibration
renders with the renders of the same held-out (not FIT) capture points from the real photos that
neither trained nor are evaluated (COLMAP scenes). Those photos are the novel views the calibration
views stand in for.

    python benchmarks/studies/calibration_bounds_study.py --run fern/seed0=RUN ... \\
        --out benchmarks/results/uncertainty_study/calibration_bounds

The decision reads the means over a scene's seeds (docs/uncertainty.md, study 12, rule fixed before
this ran). Renders only. Torch on 1 thread. Writes ``study.json`` and ``study.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_helpers import LEVELS, begin_study, by_scene, distance, gap, scored_points, study_parser, tercile_rows, write_study  # noqa: E402

#: Study 12's tolerances (fixed with the rule): no scene's coverage distance or conditional gap may
#: grow by more than TOLERANCE, and the mean distance over scenes must fall by at least GAIN.
TOLERANCE: float = 0.02
GAIN: float = 0.02


def _render_summary(abs_err: np.ndarray, std: np.ndarray) -> dict:
    return {"points": int(len(abs_err)), "median_abs_err": float(np.median(abs_err)),
            "median_std": float(np.median(std)), "median_abs_z": float(np.median(abs_err / std))}


def photo_renders(model, dataset, points, evaluated: list[int], seed: int) -> dict | None:
    """The held-out capture points rendered from the photos that neither trained nor are evaluated
    (COLMAP tracks); None without COLMAP points or such photos."""
    import torch

    from stochastic_fields.calibration import render_at_points
    from stochastic_fields.capture_points import FIT, restrict_sparse_depth
    from stochastic_fields.sparse_depth import sparse_depth_for_dataset
    from stochastic_fields.view_maps import OPACITY_MASK

    others = [v for v in range(dataset.num_views) if v not in set(dataset.train_indices) | set(evaluated)]
    if points.colmap is None or not others:
        return None
    full = sparse_depth_for_dataset(dataset, others, points=points.colmap)
    sparse = {v: restrict_sparse_depth(sd, points.roles[sd.point_index] != FIT) for v, sd in full.items()}
    r = render_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse,
                         generator=torch.Generator().manual_seed(seed))
    keep = (r["opacity"] > OPACITY_MASK) & (r["depth_std"] > 0)
    return {"photos": others, **_render_summary(np.abs(r["gt"] - r["depth_mean"])[keep], r["depth_std"][keep])}


def study_run(run_dir: Path, *, seed: int = 0) -> dict:
    from stochastic_fields.calibration import BOUNDS_CHOICES, QuantileCalibration, depth_calibration_errors
    from stochastic_fields.capture_points import FIT, SCORE, block_roles, load_capture_points
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    points = load_capture_points(dataset)
    if points is None:
        raise ValueError(f"{run_dir}: the scene has no capture points")
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    scored = scored_points(run_dir, model, dataset, points, views, points.roles != FIT, seed)
    keep = (block_roles(scored["xyz"], points) if points.source == "synthetic" else scored["role"]) == SCORE
    s_err, s_std = scored["abs_err"][keep], scored["std"][keep]
    held = points.roles != FIT
    maps, renders = {}, {}
    for bounds in BOUNDS_CHOICES:
        err, std, source = depth_calibration_errors(model, dataset, seed=seed, bounds=bounds)
        maps[bounds] = QuantileCalibration.fit_errors(err, std, quantity="depth_std", source=source)
        every, every_std, _ = depth_calibration_errors(model, dataset, seed=seed, bounds=bounds, points="held-out")
        renders[bounds] = _render_summary(every, every_std)
    out = {"run": str(run_dir), "views": views, "held_out_points": int(held.sum()),
           "calibration_renders": renders, "photo_renders": photo_renders(model, dataset, points, views, seed),
           "scales": {b: m.scale_at(np.asarray(LEVELS)).tolist() for b, m in maps.items()}, "choices": {}}
    for bounds in BOUNDS_CHOICES[1:]:  # against today's (the first)
        rows = tercile_rows(s_err, s_std, maps[bounds], maps[BOUNDS_CHOICES[0]])
        out["choices"][bounds] = {"groups": rows,
                                  "distance": {"today": distance(rows[-1]["coverage_raw"]),
                                               "new": distance(rows[-1]["coverage"])},
                                  "gap": {"today": gap(rows, "coverage_raw"), "new": gap(rows, "coverage")}}
    return out


def decide(results: dict, choice: str) -> dict:
    """Study 12's rule for ``choice`` against today's bounds, on per-scene means over seeds."""
    scenes = {}
    for scene, seeds in by_scene(results["runs"]).items():
        runs = [r["choices"][choice] for r in seeds]
        mean = lambda key, which: float(np.mean([r[key][which] for r in runs]))  # noqa: E731
        scenes[scene] = {"seeds": len(runs),
                         "coverage_today": np.mean([r["groups"][-1]["coverage_raw"] for r in runs], axis=0).tolist(),
                         "coverage_new": np.mean([r["groups"][-1]["coverage"] for r in runs], axis=0).tolist(),
                         "distance_today": mean("distance", "today"), "distance_new": mean("distance", "new"),
                         "gap_today": mean("gap", "today"), "gap_new": mean("gap", "new")}
    worse = [s for s, m in scenes.items()
             if m["distance_new"] > m["distance_today"] + TOLERANCE or m["gap_new"] > m["gap_today"] + TOLERANCE]
    gain = float(np.mean([m["distance_today"] - m["distance_new"] for m in scenes.values()]))
    return {"choice": choice, "scenes": scenes, "worse_on": worse, "mean_distance_gain": gain,
            "taken": not worse and gain >= GAIN}


def _markdown(results: dict, command: str) -> str:
    lines = ["# Study 12: the render bounds of the calibration views", "", f"Command: `{command}`", "",
             "Maps (one factor per level) fitted on the CALIBRATE points seen from the calibration views with "
             "each choice of render bounds, scored on the SCORE points seen from the test views: share inside "
             f"the central {LEVELS[0]:.1%} / {LEVELS[1]:.0%} intervals. Distance: the largest |coverage - nominal|; "
             "gap: the spread of the 68% coverage over the terciles of raw sigma.", ""]
    for d in results["decisions"]:
        lines += [f"## Decision: {d['choice']} against widest (means over seeds)", "",
                  "| scene | seeds | widest 68 / 95 | new 68 / 95 | distance widest -> new | gap widest -> new |",
                  "|---|---|---|---|---|---|"]
        for scene, m in d["scenes"].items():
            lines.append(f"| {scene} | {m['seeds']} | {m['coverage_today'][0]:.3f} / {m['coverage_today'][1]:.3f} | "
                         f"{m['coverage_new'][0]:.3f} / {m['coverage_new'][1]:.3f} | {m['distance_today']:.3f} -> "
                         f"{m['distance_new']:.3f} | {m['gap_today']:.3f} -> {m['gap_new']:.3f} |")
        lines += ["", f"Mean distance gain over scenes: {d['mean_distance_gain']:+.3f} (rule: >= {GAIN}); scenes where "
                  f"distance or gap grew by more than {TOLERANCE}: {', '.join(d['worse_on']) or 'none'}. "
                  f"**{'Taken' if d['taken'] else 'Not taken'}.**", ""]
    lines += ["## Calibration renders against the real held-out photos (no test view)", "",
              "Every held-out (not FIT) capture point, rendered from the calibration views with each choice, and "
              "from the photos that neither trained nor are evaluated.", "",
              "| run | renders | points | median abs error | median std | median abs z |", "|---|---|---|---|---|---|"]
    for label, r in results["runs"].items():
        for name, m in list(r["calibration_renders"].items()) + [("photos", r["photo_renders"])]:
            if m is not None:
                lines.append(f"| {label} | {name} | {m['points']} | {m['median_abs_err']:.3g} | {m['median_std']:.3g} | "
                             f"{m['median_abs_z']:.2f} |")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "calibration_bounds", "Trained and evaluated S-NeRF (default) runs; labels SCENE/SEED.")
    args, runs, results = begin_study(p, argv, "calibration_bounds_study.py")
    from stochastic_fields.calibration import BOUNDS_CHOICES

    results["runs"] = {}
    for label, run_dir in runs.items():
        print(f"{label}: {run_dir}", flush=True)
        results["runs"][label] = r = study_run(run_dir, seed=args.seed)
        for choice, c in r["choices"].items():
            print(f"  {choice}: distance {c['distance']['today']:.3f} -> {c['distance']['new']:.3f}, "
                  f"gap {c['gap']['today']:.3f} -> {c['gap']['new']:.3f}", flush=True)
    results["decisions"] = [decide(results, choice) for choice in BOUNDS_CHOICES[1:]]
    text = _markdown(results, results["command"])
    write_study(args.out, results, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
