"""Study 18: the depth map fitted on real held-out photos instead of the virtual calibration views.

Today's map (``calibration.fit_depth_calibration``) is fitted on the CALIBRATE capture points seen
from virtual views halfway between neighbouring training views. A user could instead hold real
photos out of training. At the CPU budget the benchmark scenes have such photos for free: the
views that neither train nor are scored. This study fits the map (one factor per level) on the
CALIBRATE points seen from them (*photos*), and from each one alone (*one photo*, at least
``MIN_PHOTO_POINTS`` points), and scores every map on the SCORE points seen from the run's
evaluated test views (``study_helpers.scored_points``), beside today's (*views*).

    python benchmarks/studies/photo_calibration_study.py --run fern/seed0=RUN flower/seed0=RUN ... \\
        --out benchmarks/results/uncertainty_study/photo_calibration

Labels are SCENE/SEED; the decision reads the means over a scene's seeds (docs/uncertainty.md,
study 18, rule fixed before this ran). Renders only. Torch on 1 thread. Writes ``study.json``,
``study.md`` and ``coverage_by_seed.png`` (``--plot-only``: the figure again from ``OUT/study.json``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_helpers import (LEVELS, begin_study, by_scene, coverage, distance, photo_points, scored_points,  # noqa: E402
                           study_parser, write_study)

#: Study 18's rule (study 12's): no scene's coverage distance may grow by more than TOLERANCE, and the
#: mean distance over the scenes must fall by at least GAIN.
TOLERANCE: float = 0.02
GAIN: float = 0.02
#: A single photo's map is reported only when the photo holds at least this many calibration points.
MIN_PHOTO_POINTS: int = 100
#: Folds of the SCORE blocks in the cross-fitted diagnostic (``cross_fitted_coverage``).
CROSS_FOLDS: int = 5
#: ``--sensitivity``: the fold counts and deal seeds the virtual views' cross-fitted coverage is
#: also computed with (is 5 folds, seed 0 a lucky deal?).
SENSITIVITY_FOLDS: tuple[int, ...] = (3, 5, 10)
SENSITIVITY_SEEDS: tuple[int, ...] = (0, 1, 2, 3, 4)


def unused_views(dataset, evaluated: list[int]) -> list[int]:
    """The views that neither train nor are evaluated, in order."""
    used = set(int(v) for v in dataset.train_indices) | set(int(v) for v in evaluated)
    return [v for v in range(dataset.num_views) if v not in used]


def rendered_errors(model, cameras, near, far, sparse: dict, seed: int) -> dict[str, np.ndarray]:
    """"abs_err" |d - d*| [N], raw "std" sigma [N], "view" [N], capture "index" [N], "gt" d* and
    "depth_mean" d [N] of each point of
    {view: SparseDepth} rendered from ``cameras`` (bounds ``near``/``far``), opacity above the scores'
    mask."""
    import torch

    from stochastic_fields.calibration import render_at_points
    from stochastic_fields.view_maps import OPACITY_MASK

    r = render_at_points(model, cameras, near, far, sparse, generator=torch.Generator().manual_seed(seed))
    filled = [v for v, sd in sparse.items() if len(sd)]
    view = np.concatenate([np.full(len(sparse[v]), v) for v in filled] or [np.zeros(0, np.int64)])
    index = np.concatenate([sparse[v].point_index for v in filled] or [np.zeros(0, np.int64)])
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_std"]) & (r["depth_std"] > 0)
    return {"abs_err": np.abs(r["gt"] - r["depth_mean"])[keep], "std": r["depth_std"][keep], "view": view[keep],
            "index": index[keep], "gt": r["gt"][keep], "depth_mean": r["depth_mean"][keep]}


def photo_errors(model, dataset, sparse: dict, seed: int) -> dict[str, np.ndarray]:
    """``rendered_errors`` of {view: SparseDepth} of the dataset's photos, each with its own bounds."""
    return rendered_errors(model, dataset.cameras, dataset.near, dataset.far, sparse, seed)


def cross_fitted_coverage(scored: dict[str, np.ndarray], fitting: dict[str, np.ndarray], *,
                          folds: int = CROSS_FOLDS, seed: int = 0) -> list[float]:
    """Coverage [L] of the ``scored`` points ("abs_err", "std", "block" [N]) when each is judged by a
    map fitted on the ``fitting`` points ("abs_err", "std", "block" [M]) outside its fold: the
    scored points' blocks are shuffled (``seed``) and dealt into ``folds`` folds; fold f's points
    are scored with the map of every fitting point whose block is not in fold f. No map sees the
    block of a point it scores. (Eval's ``calibration.DepthFolds`` deal the SCORE role's blocks,
    seen or not by the test views, so the two deals differ; study 18b and the sensitivity study
    measured how little a deal matters.)"""
    from stochastic_fields.calibration import QuantileCalibration

    blocks = np.random.default_rng(seed).permutation(np.unique(scored["block"]))
    inside = np.zeros(len(LEVELS))
    for f in range(folds):
        held = blocks[f::folds]
        m_s, m_f = np.isin(scored["block"], held), ~np.isin(fitting["block"], held)
        if not m_s.any():
            continue
        fitted = QuantileCalibration.fit_errors(fitting["abs_err"][m_f], fitting["std"][m_f], quantity="depth_std")
        inside += coverage(scored["abs_err"][m_s], scored["std"][m_s], fitted) * m_s.sum()
    return (inside / len(scored["block"])).tolist()


def photo_validation(model, dataset, points, photos: list[int], seed: int, calibrate_map, held_out: dict) -> dict:
    """Study 18c: the coverage at ``LEVELS`` of the SCORE-role points seen from the unused ``photos``
    (no test view) by ``calibrate_map`` (fitted on the CALIBRATE points, "calibrate") and by the map of
    the ``held_out`` renders (``calibration.depth_calibration_renders(points="held-out")``) scored with
    its cross-fitted folds as eval scores it ("held-out")."""
    from stochastic_fields.calibration import cross_fitted_depth_scores, fit_depth_folds
    from stochastic_fields.capture_points import SCORE, block_keys

    scored = photo_errors(model, dataset, photo_points(dataset, points, photos, SCORE), seed)
    keys = block_keys(points.xyz, points.xyz)
    folds = fit_depth_folds(held_out["abs_err"], held_out["std"], keys[held_out["index"]], keys[points.roles == SCORE])
    held = cross_fitted_depth_scores(scored["gt"], scored["depth_mean"], scored["std"], folds.fold_of(keys[scored["index"]]),
                                     folds, coverage_levels=LEVELS)
    cov = {"calibrate": coverage(scored["abs_err"], scored["std"], calibrate_map).tolist(), "held-out": held["coverage"]}
    return {"scored_points": int(len(scored["gt"])), "coverage": cov, "distance": {k: distance(c) for k, c in cov.items()}}


def study_run(run_dir: Path, *, seed: int = 0, sensitivity: bool = False, validate: bool = False) -> dict:
    from stochastic_fields.calibration import QuantileCalibration, depth_calibration_errors, depth_calibration_renders
    from stochastic_fields.capture_points import CALIBRATE, FIT, SCORE, block_keys, block_roles, load_capture_points
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    points = load_capture_points(dataset)
    if points is None:
        raise ValueError(f"{run_dir}: the scene has no capture points")
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    photos = unused_views(dataset, views)
    if not photos:
        raise ValueError(f"{run_dir}: every view trains or is evaluated; no photo is left to calibrate on")
    scored = scored_points(run_dir, model, dataset, points, views, points.roles != FIT, seed)
    keep = (block_roles(scored["xyz"], points) if points.source == "synthetic" else scored["role"]) == SCORE
    s_err, s_std = scored["abs_err"][keep], scored["std"][keep]

    def fit(err, std, source):
        return QuantileCalibration.fit_errors(err, std, quantity="depth_std", source=source)

    err_v, std_v, source = depth_calibration_errors(model, dataset, seed=seed)
    cal = photo_errors(model, dataset, photo_points(dataset, points, photos, CALIBRATE), seed)
    err_p, std_p, view_p = cal["abs_err"], cal["std"], cal["view"]
    sco = photo_errors(model, dataset, photo_points(dataset, points, photos, SCORE), seed)
    err_d, std_d = sco["abs_err"], sco["std"]
    maps = {"views": fit(err_v, std_v, source),
            "photos": fit(err_p, std_p, f"{len(err_p)} calibrate-role points seen from {len(photos)} unused photos"),
            "photos_score_blocks": fit(err_d, std_d, f"{len(err_d)} score-role points seen from {len(photos)} unused photos")}
    out = {"run": str(run_dir), "views": views, "photos": photos, "scored_points": int(keep.sum()),
           "calibration_points": {"views": int(len(err_v)), "photos": int(len(err_p)),
                                  "photos_score_blocks": int(len(err_d))},
           "median_abs_z": {"views": float(np.median(err_v / std_v)), "photos": float(np.median(err_p / std_p)),
                            "scored": float(np.median(s_err / s_std))},
           "scales": {name: m.scale_at(np.asarray(LEVELS)).tolist() for name, m in maps.items()},
           "coverage": {name: coverage(s_err, s_std, m).tolist() for name, m in maps.items()}}
    out["distance"] = {name: distance(c) for name, c in out["coverage"].items()}
    single = {}
    for v in photos:
        m = view_p == v
        if m.sum() >= MIN_PHOTO_POINTS:
            c = coverage(s_err, s_std, fit(err_p[m], std_p[m], f"photo {v}"))
            single[int(v)] = {"points": int(m.sum()), "coverage": c.tolist(), "distance": distance(c)}
    out["one_photo"] = single
    # the cross-fitted diagnostic: every held-out (CALIBRATE or SCORE) point outside the scored fold
    key = block_keys(points.xyz, points.xyz)
    scored_blocks = {"abs_err": s_err, "std": s_std, "block": scored["block"][keep]}
    fitting = {"photos": {k: np.concatenate([cal[k], sco[k]]) for k in ("abs_err", "std", "index")},
               "views": depth_calibration_renders(model, dataset, seed=seed, points="held-out")}
    out["cross_fitted"] = {name: cross_fitted_coverage(scored_blocks, {**f, "block": key[f["index"]]}, seed=seed)
                           for name, f in fitting.items()}
    if validate:
        out["photo_validation"] = photo_validation(model, dataset, points, photos, seed, maps["views"], fitting["views"])
    if sensitivity:
        views = {**fitting["views"], "block": key[fitting["views"]["index"]]}
        out["cross_fitted_sensitivity"] = {
            str(folds): [cross_fitted_coverage(scored_blocks, views, folds=folds, seed=deal) for deal in SENSITIVITY_SEEDS]
            for folds in SENSITIVITY_FOLDS}
    return out


def decide(results: dict) -> dict:
    """Study 18's rule: *photos* against *views* on per-scene means over seeds."""
    scenes = {}
    for scene, seeds in by_scene(results["runs"]).items():
        mean = lambda f: np.mean([f(r) for r in seeds], axis=0)  # noqa: E731
        one = [p for r in seeds for p in r["one_photo"].values()]
        scenes[scene] = {"seeds": len(seeds),
                         "coverage_views": mean(lambda r: r["coverage"]["views"]).tolist(),
                         "coverage_photos": mean(lambda r: r["coverage"]["photos"]).tolist(),
                         "distance_views": float(mean(lambda r: r["distance"]["views"])),
                         "distance_photos": float(mean(lambda r: r["distance"]["photos"])),
                         "coverage_photos_score_blocks": mean(lambda r: r["coverage"]["photos_score_blocks"]).tolist(),
                         "distance_photos_score_blocks": float(mean(lambda r: r["distance"]["photos_score_blocks"])),
                         "coverage_cross_fitted": {k: mean(lambda r: r["cross_fitted"][k]).tolist()
                                                   for k in ("views", "photos")},
                         "one_photo_maps": len(one),
                         "one_photo_distance_mean": float(np.mean([p["distance"] for p in one])) if one else None,
                         "one_photo_distance_range": [float(min(p["distance"] for p in one)),
                                                      float(max(p["distance"] for p in one))] if one else None}
    worse = [s for s, m in scenes.items() if m["distance_photos"] > m["distance_views"] + TOLERANCE]
    gain = float(np.mean([m["distance_views"] - m["distance_photos"] for m in scenes.values()]))
    return {"scenes": scenes, "worse_on": worse, "mean_distance_gain": gain, "passes": not worse and gain >= GAIN}


def decide_validation(results: dict) -> dict:
    """Study 18c's rule: the held-out map against the CALIBRATE-only map on the unused photos'
    SCORE points, per-scene means over seeds (docs/uncertainty.md)."""
    scenes = {}
    for scene, seeds in by_scene(results["runs"]).items():
        v = [r["photo_validation"] for r in seeds]
        scenes[scene] = {"seeds": len(v), "points": int(np.mean([x["scored_points"] for x in v])),
                         **{f"coverage_{k}": np.mean([x["coverage"][k] for x in v], axis=0).tolist()
                            for k in ("calibrate", "held-out")},
                         **{f"distance_{k}": float(np.mean([x["distance"][k] for x in v])) for k in ("calibrate", "held-out")}}
    worse = [s for s, m in scenes.items() if m["distance_held-out"] > m["distance_calibrate"] + TOLERANCE]
    gain = float(np.mean([m["distance_calibrate"] - m["distance_held-out"] for m in scenes.values()]))
    return {"scenes": scenes, "worse_on": worse, "mean_distance_gain": gain, "passes": not worse and gain >= GAIN}


def _markdown(results: dict) -> str:
    d = results["decision"]
    lines = ["# Study 18: the depth map fitted on real held-out photos", "", f"Command: `{results['command']}`", "",
             "Maps (one factor per level) fitted on the CALIBRATE capture points seen from the virtual calibration "
             "views (*views*, today) or from the photos that neither train nor are scored (*photos*), scored on the "
             f"SCORE points seen from the test views: share inside the central {LEVELS[0]:.1%} / {LEVELS[1]:.0%} "
             "intervals. Distance: the larger |coverage - nominal| of the two levels.", "",
             "## Per run", "",
             "| run | photos | calibration points views / photos | median abs z views / photos / scored | "
             "s(68%) views / photos | coverage views | coverage photos | one photo: maps, mean distance |",
             "|---|---|---|---|---|---|---|---|"]
    for label, r in results["runs"].items():
        one = list(r["one_photo"].values())
        one_txt = f"{len(one)}, {np.mean([p['distance'] for p in one]):.3f}" if one else "0, -"
        cv, cp = r["coverage"]["views"], r["coverage"]["photos"]
        lines.append(f"| {label} | {len(r['photos'])} | {r['calibration_points']['views']} / "
                     f"{r['calibration_points']['photos']} | {r['median_abs_z']['views']:.2f} / "
                     f"{r['median_abs_z']['photos']:.2f} / {r['median_abs_z']['scored']:.2f} | "
                     f"{r['scales']['views'][0]:.2f} / {r['scales']['photos'][0]:.2f} | "
                     f"{cv[0]:.3f} / {cv[1]:.3f} | {cp[0]:.3f} / {cp[1]:.3f} | {one_txt} |")
    lines += ["", "## Decision (means over seeds)", "",
              "| scene | seeds | views 68 / 95 | photos 68 / 95 | distance views -> photos | one photo: distance mean (range) |",
              "|---|---|---|---|---|---|"]
    for scene, m in d["scenes"].items():
        one = (f"{m['one_photo_distance_mean']:.3f} ({m['one_photo_distance_range'][0]:.3f}-"
               f"{m['one_photo_distance_range'][1]:.3f}, {m['one_photo_maps']} maps)" if m["one_photo_maps"] else "-")
        lines.append(f"| {scene} | {m['seeds']} | {m['coverage_views'][0]:.3f} / {m['coverage_views'][1]:.3f} | "
                     f"{m['coverage_photos'][0]:.3f} / {m['coverage_photos'][1]:.3f} | {m['distance_views']:.3f} -> "
                     f"{m['distance_photos']:.3f} | {one} |")
    lines += ["", "Diagnostic, deciding nothing (added after the rows above were seen): the map fitted on the "
              "SCORE-role points seen from the same unused photos, i.e. on the scored surfaces from other "
              "viewpoints. It is not independent of the scores; it separates the viewpoints from the blocks.", "",
              "| scene | photos, CALIBRATE blocks: 68 / 95 | photos, SCORE blocks: 68 / 95 | distance |", "|---|---|---|---|"]
    for scene, m in d["scenes"].items():
        cs = m["coverage_photos_score_blocks"]
        lines.append(f"| {scene} | {m['coverage_photos'][0]:.3f} / {m['coverage_photos'][1]:.3f} | {cs[0]:.3f} / "
                     f"{cs[1]:.3f} | {m['distance_photos']:.3f} -> {m['distance_photos_score_blocks']:.3f} |")
    lines += ["", f"Diagnostic, deciding nothing (added after the rows above were seen): cross-fitted maps. The "
              f"SCORE blocks are dealt into {CROSS_FOLDS} folds; each fold's test-view points are judged by the map "
              "of every held-out (CALIBRATE or SCORE) point outside the fold, seen from the virtual views or the "
              "photos. Independent per point (no map sees the block it scores); each map fits about 90% of the "
              "held-out blocks, as `calibrate --points held-out` does for a user.", "",
              "| scene | virtual views, cross-fitted: 68 / 95 | photos, cross-fitted: 68 / 95 |", "|---|---|---|"]
    for scene, m in d["scenes"].items():
        cv, cp = m["coverage_cross_fitted"]["views"], m["coverage_cross_fitted"]["photos"]
        lines.append(f"| {scene} | {cv[0]:.3f} / {cv[1]:.3f} | {cp[0]:.3f} / {cp[1]:.3f} |")
    if all("cross_fitted_sensitivity" in r for r in results["runs"].values()):
        lines += ["", "Sensitivity, deciding nothing: the virtual views' cross-fitted coverage with "
                  f"{', '.join(map(str, SENSITIVITY_FOLDS))} folds, each dealt with seeds "
                  f"{', '.join(map(str, SENSITIVITY_SEEDS))}; mean over the runs of a scene, and the range over "
                  "runs and deals.", "", "| scene | folds | 68%: mean (range) | 95%: mean (range) |", "|---|---|---|---|"]
        for scene, seeds in by_scene(results["runs"]).items():
            for folds in SENSITIVITY_FOLDS:
                c = np.array([cov for r in seeds for cov in r["cross_fitted_sensitivity"][str(folds)]])
                lines.append(f"| {scene} | {folds} | {c[:, 0].mean():.3f} ({c[:, 0].min():.3f}-{c[:, 0].max():.3f}) | "
                             f"{c[:, 1].mean():.3f} ({c[:, 1].min():.3f}-{c[:, 1].max():.3f}) |")
    if "validation" in results:
        v = results["validation"]
        lines += ["", "## Study 18c: the default judged on the unused photos (no test view)", "",
                  "SCORE-role points seen from the photos that neither train nor are scored. *calibrate*: the map "
                  "fitted on the CALIBRATE points; *held-out*: the map fitted on every held-out point, scored with "
                  "its cross-fitted folds as eval does. Means over seeds.", "",
                  "| scene | seeds | points | calibrate 68 / 95 | held-out 68 / 95 | distance calibrate -> held-out |",
                  "|---|---|---|---|---|---|"]
        for scene, m in v["scenes"].items():
            a, b = m["coverage_calibrate"], m["coverage_held-out"]
            lines.append(f"| {scene} | {m['seeds']} | {m['points']} | {a[0]:.3f} / {a[1]:.3f} | {b[0]:.3f} / {b[1]:.3f} | "
                         f"{m['distance_calibrate']:.3f} -> {m['distance_held-out']:.3f} |")
        lines += ["", f"Mean distance gain: {v['mean_distance_gain']:+.3f} (rule: >= {GAIN}); scenes worse by more than "
                  f"{TOLERANCE}: {', '.join(v['worse_on']) or 'none'}. The held-out default "
                  f"**{'stands' if v['passes'] else 'is reverted'}**."]
    verdict = ("**passes**: the next study trains without the held-out photos" if d["passes"]
               else "**fails**: real photos calibrate no better than the virtual views")
    lines += ["", f"Mean distance gain over scenes: {d['mean_distance_gain']:+.3f} (rule: >= {GAIN}); scenes where "
              f"the distance grows by more than {TOLERANCE}: {', '.join(d['worse_on']) or 'none'}. Verdict: {verdict}.", ""]
    return "\n".join(lines)


def coverage_groups(results: dict) -> dict[str, list[dict]]:
    """{scene: [{"group": seed label, "coverage_raw": views' coverage, "coverage": photos'}]}, the
    rows ``plots.plot_coverage_by_group`` draws."""
    return {scene: [{"group": f"seed {r['label']}", "points": r["scored_points"], "coverage_raw": r["coverage"]["views"],
                     "coverage": r["coverage"]["photos"]} for r in seeds]
            for scene, seeds in by_scene(results["runs"]).items()}


def plot(results: dict, path: Path) -> Path:
    from stochastic_fields.plots import plot_coverage_by_group

    return plot_coverage_by_group(coverage_groups(results), LEVELS, path, xlabel="run", series=("held-out photos", "virtual views"),
                                  title="Depth interval coverage on the SCORE points: map fitted on held-out photos "
                                        "against today's")


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "photo_calibration", "Trained and evaluated runs (S-NeRF default), labelled SCENE/SEED.")
    p.add_argument("--plot-only", action="store_true", help="Only draw the figure again from OUT/study.json.")
    p.add_argument("--validate", action="store_true",
                   help="Study 18c: judge the held-out map against the CALIBRATE-only map on the unused photos only.")
    p.add_argument("--sensitivity", action="store_true",
                   help="Also compute the virtual views' cross-fitted coverage for other fold counts and deal seeds.")
    args, runs, results = begin_study(p, argv, "photo_calibration_study.py")
    if args.plot_only:
        from stochastic_fields.io_utils import read_json

        print(f"written: {plot(read_json(args.out / 'study.json', 'study results'), args.out / 'coverage_by_seed.png')}")
        return 0
    results["runs"] = {}
    for label, run_dir in runs.items():
        print(f"{label}: {run_dir}", flush=True)
        results["runs"][label] = {"label": label.split("/")[-1],
                                  **study_run(run_dir, seed=args.seed, sensitivity=args.sensitivity,
                                              validate=args.validate)}
    results["decision"] = decide(results)
    if args.validate:
        results["validation"] = decide_validation(results)
    write_study(args.out, results, _markdown(results))
    print(_markdown(results))
    print(f"written: {plot(results, args.out / 'coverage_by_seed.png')}, {args.out / 'study.json'}, study.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
