"""Study 13: does the free-space check make the depth std rank errors and the intervals hold?

S-NeRF's depth std misses its worst errors: surfaces rendered in front of the true one with a
small std (docs/uncertainty.md, studies 11 and 12). A training view that saw past such a point
contradicts it. The checked std sqrt(sigma^2 + e^2) adds the point's free-space violation e
against the training views' rendered depth (``stochastic_fields.free_space``). This study fits
the depth map (one factor per level) on the CALIBRATE renders of the calibration views twice,
on sigma (*plain*, today) and on the checked std (*checked*), and scores both on the SCORE points
seen from the run's evaluated test views (``study_helpers.scored_points``): depth
Spearman |err| against the std per test view (mean) and pooled, and the coverage of the central
68% / 95% intervals. ``--reference`` runs (the deep ensemble) are scored the same way, reported
beside, deciding nothing.

    python benchmarks/studies/free_space_study.py --run fern/seed0=RUN flower/seed0=RUN ... \\
        --reference fern=ENSEMBLE_RUN ... --out benchmarks/results/uncertainty_study/free_space

Labels are SCENE/SEED; the decision reads the means over a scene's seeds (docs/uncertainty.md,
study 13, where the rule was fixed before this ran). Renders only (no training). Torch on 1 thread.
Writes ``study.json``, ``study.md`` and ``coverage_by_seed.png`` (``--plot-only``: the figure again
from ``OUT/study.json``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import LEVELS, begin_study, by_scene, coverage, distance, scored_points, study_parser, write_study  # noqa: E402

#: Study 13's tolerances (fixed with the rule): on no scene may the per-view or pooled depth
#: Spearman fall by more than this, nor the coverage distance grow by more (study 8's) ...
TOLERANCE: float = 0.02
#: ... and the per-view depth Spearman must rise by at least this much on the mean over scenes.
SPEARMAN_GAIN: float = 0.02


def spearman_scores(abs_err: np.ndarray, std: np.ndarray, view: np.ndarray) -> dict[str, float]:
    """Spearman |err| [N] against ``std`` [N]: mean over ``view`` [N] groups, and pooled."""
    from scipy.stats import spearmanr

    per_view = [spearmanr(abs_err[view == v], std[view == v])[0] for v in np.unique(view) if (view == v).sum() > 2]
    return {"per_view": float(np.mean(per_view)), "pooled": float(spearmanr(abs_err, std)[0])}


def cross_fitted_coverage(renders: dict, scored: dict, capture, *, floor: bool = False) -> list[float]:
    """Coverage at ``LEVELS`` of the ``scored`` points ("gt", "depth_mean", "std" [N], "xyz" [N, 3]) by
    the cross-fitted fold maps (``calibration.fit_depth_folds``, as eval scores a held-out map) of the
    held-out calibration ``renders`` (``calibration.depth_calibration_renders``), scored as eval
    does (``calibration.cross_fitted_depth_scores``)."""
    from stochastic_fields.calibration import cross_fitted_depth_scores, fit_depth_folds
    from stochastic_fields.capture_points import SCORE, block_keys

    keys = block_keys(capture.xyz, capture.xyz)
    folds = fit_depth_folds(renders["abs_err"], renders["std"], keys[renders["index"]], keys[capture.roles == SCORE],
                            floor=floor)
    fold = folds.fold_of(block_keys(scored["xyz"], capture.xyz))
    return cross_fitted_depth_scores(scored["gt"], scored["depth_mean"], scored["std"], fold, folds,
                                     coverage_levels=LEVELS)["coverage"]


def study_run(run_dir: Path, *, seed: int = 0, fit: bool = True, fit_points: str = "calibrate") -> dict:
    """Both maps of one run (``fit``: False for a reference run, scored raw and checked only), fitted
    on the ``fit_points`` of ``calibration.CALIBRATION_POINTS``; "held-out" maps are scored
    cross-fitted (``cross_fitted_coverage``)."""
    from stochastic_fields.calibration import QuantileCalibration, depth_calibration_errors, depth_calibration_renders
    from stochastic_fields.cameras import camera_to_world
    from stochastic_fields.capture_points import FIT, SCORE, block_roles, load_capture_points
    from stochastic_fields.free_space import checked_std, free_space_violation, render_training_depth, rendered_points
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    points = load_capture_points(dataset)
    if points is None:
        raise ValueError(f"{run_dir}: the scene has no capture points")
    ref = render_training_depth(model, dataset, seed=seed, progress=False)
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    scored = scored_points(run_dir, model, dataset, points, views, points.roles != FIT, seed)
    keep = (block_roles(scored["xyz"], points) if points.source == "synthetic" else scored["role"]) == SCORE
    s = {k: v[keep] for k, v in scored.items() if isinstance(v, np.ndarray) and len(v) == len(keep)}
    centres = camera_to_world(dataset.cameras).double()[:, :3, 3].numpy()[s["view"]]
    e = free_space_violation(rendered_points(centres, s["xyz"], s["gt"], s["depth_mean"]), ref)
    std_checked = checked_std(s["std"], e)
    out = {"run": str(run_dir), "views": views, "scored_points": int(len(e)),
           "share_violated": float((e > 0).mean()), "median_violation": float(np.median(e)),
           "median_std": float(np.median(s["std"])),
           "spearman": {"plain": spearman_scores(s["abs_err"], s["std"], s["view"]),
                        "checked": spearman_scores(s["abs_err"], std_checked, s["view"])}}
    if fit and fit_points == "held-out":
        r = depth_calibration_renders(model, dataset, seed=seed, points=fit_points)
        r_c = depth_calibration_renders(model, dataset, seed=seed, points=fit_points, free_space=ref)
        err, std, source, err_c, std_c = r["abs_err"], r["std"], r["source"], r_c["abs_err"], r_c["std"]
        cov = {"plain": cross_fitted_coverage(r, s, points),
               "checked": cross_fitted_coverage(r_c, {**s, "std": std_checked}, points)}
    elif fit:
        err, std, source = depth_calibration_errors(model, dataset, seed=seed)
        err_c, std_c, _ = depth_calibration_errors(model, dataset, seed=seed, free_space=ref)
    if fit:
        plain = QuantileCalibration.fit_errors(err, std, quantity="depth_std", source=source)
        checked = QuantileCalibration.fit_errors(err_c, std_c, quantity="depth_std", source=source)
        if fit_points != "held-out":
            cov = {"plain": coverage(s["abs_err"], s["std"], plain).tolist(),
                   "checked": coverage(s["abs_err"], std_checked, checked).tolist()}
        out.update(calibration_points=int(len(err)), source=source, coverage=cov,
                   distance={k: distance(v) for k, v in cov.items()},
                   scales={"plain": plain.scale_at(np.asarray(LEVELS)).tolist(),
                           "checked": checked.scale_at(np.asarray(LEVELS)).tolist()})
    return out


def decide(results: dict) -> dict:
    """Study 13's rule on the per-scene means over seeds (module doc; docs/uncertainty.md)."""
    scenes = {}
    for scene, runs in by_scene(results["runs"]).items():
        m = {"seeds": len(runs)}
        for which in ("plain", "checked"):
            for kind in ("per_view", "pooled"):
                m[f"spearman_{kind}_{which}"] = float(np.mean([r["spearman"][which][kind] for r in runs]))
            m[f"coverage_{which}"] = np.mean([r["coverage"][which] for r in runs], axis=0).tolist()
            m[f"distance_{which}"] = float(np.mean([r["distance"][which] for r in runs]))
        scenes[scene] = m
    worse = [s for s, m in scenes.items()
             if m["spearman_per_view_checked"] < m["spearman_per_view_plain"] - TOLERANCE
             or m["spearman_pooled_checked"] < m["spearman_pooled_plain"] - TOLERANCE
             or m["distance_checked"] > m["distance_plain"] + TOLERANCE]
    gain = float(np.mean([m["spearman_per_view_checked"] - m["spearman_per_view_plain"] for m in scenes.values()]))
    return {"scenes": scenes, "worse_on": worse, "mean_spearman_gain": gain,
            "taken": not worse and gain >= SPEARMAN_GAIN}


def _markdown(results: dict) -> str:
    d = results["decision"]
    lines = ["# Study 13: the free-space check", "", f"Command: `{results['command']}`", "",
             ("Both maps fitted on the same CALIBRATE renders (calibration views), scored on the SCORE points seen "
              "from the test views." if results.get("points", "calibrate") == "calibrate" else
              "Both maps fitted on the same renders of every held-out (CALIBRATE and SCORE) point (calibration "
              "views), scored cross-fitted on the SCORE points seen from the test views (5 folds of the SCORE "
              "blocks, each judged by maps fitted without them).") + " *plain*: today's std sigma; *checked*: sqrt(sigma^2 + e^2), e the rendered "
             "point's free-space violation against the training views' rendered depth. Spearman |err| against "
             f"the std per test view (mean) and pooled; coverage of the central {LEVELS[0]:.1%} / {LEVELS[1]:.0%} "
             "intervals; distance: the largest |coverage - nominal|.", "",
             "## Decision (means over seeds)", "",
             "| scene | seeds | Spearman per view plain -> checked | pooled plain -> checked | coverage plain 68 / 95 | "
             "coverage checked 68 / 95 | distance plain -> checked |", "|---|---|---|---|---|---|---|"]
    for scene, m in d["scenes"].items():
        lines.append(f"| {scene} | {m['seeds']} | {m['spearman_per_view_plain']:.3f} -> {m['spearman_per_view_checked']:.3f} "
                     f"| {m['spearman_pooled_plain']:.3f} -> {m['spearman_pooled_checked']:.3f} | "
                     f"{m['coverage_plain'][0]:.3f} / {m['coverage_plain'][1]:.3f} | "
                     f"{m['coverage_checked'][0]:.3f} / {m['coverage_checked'][1]:.3f} | "
                     f"{m['distance_plain']:.3f} -> {m['distance_checked']:.3f} |")
    lines += ["", f"Mean per-view Spearman gain over scenes: {d['mean_spearman_gain']:+.3f} (rule: >= {SPEARMAN_GAIN}); "
              f"scenes outside the tolerances ({TOLERANCE}): {', '.join(d['worse_on']) or 'none'}. "
              f"**{'Taken' if d['taken'] else 'Not taken'}.**", "", "## Per run", "",
              "| run | scored points | violated share | median e / median sigma | Spearman per view plain -> checked | "
              "pooled plain -> checked | coverage plain 68 / 95 | coverage checked 68 / 95 |",
              "|---|---|---|---|---|---|---|---|"]
    for label, r in list(results["runs"].items()) + [(f"{k} (reference)", v) for k, v in results["references"].items()]:
        sp = r["spearman"]
        cov = r.get("coverage")
        lines.append(f"| {label} | {r['scored_points']} | {r['share_violated']:.2f} | {r['median_violation']:.3g} / "
                     f"{r['median_std']:.3g} | {sp['plain']['per_view']:.3f} -> {sp['checked']['per_view']:.3f} | "
                     f"{sp['plain']['pooled']:.3f} -> {sp['checked']['pooled']:.3f} | "
                     + (f"{cov['plain'][0]:.3f} / {cov['plain'][1]:.3f} | {cov['checked'][0]:.3f} / {cov['checked'][1]:.3f} |"
                        if cov else "- | - |"))
    lines += ["", "Runs: " + "; ".join(f"{k}: `{r['run']}`, test views {r['views']}" for k, r in
                                      list(results["runs"].items()) + list(results["references"].items())), ""]
    return "\n".join(lines)


def coverage_groups(results: dict) -> dict[str, list[dict]]:
    """{scene: one row per seed run} with the checked map's coverage as "coverage" and the plain
    map's as "coverage_raw" (the rows ``plots.plot_coverage_by_group`` draws)."""
    return {scene: [{"group": f"seed {r['label'].split('/')[-1]}", "points": r["scored_points"],
                     "coverage": r["coverage"]["checked"], "coverage_raw": r["coverage"]["plain"]} for r in runs]
            for scene, runs in by_scene({k: {**v, "label": k} for k, v in results["runs"].items()}).items()}


def plot(results: dict, path: Path) -> Path:
    from stochastic_fields.plots import plot_coverage_by_group

    return plot_coverage_by_group(coverage_groups(results), LEVELS, path, xlabel="run",
                                  title="Depth interval coverage on the SCORE points: free-space-checked map "
                                        "against today's", series=("checked", "plain"))


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "free_space", "Trained and evaluated S-NeRF (default) runs; labels SCENE/SEED.")
    p.add_argument("--reference", nargs="*", default=[], metavar="SCENE=RUN_DIR",
                   help="Reference runs (the deep ensemble), scored raw and checked, deciding nothing.")
    p.add_argument("--plot-only", action="store_true", help="Only draw the figure again from OUT/study.json.")
    p.add_argument("--points", choices=("calibrate", "held-out"), default="calibrate",
                   help="Fit both maps on the CALIBRATE points (studies 13 and 13b) or on every held-out point, "
                        "scored cross-fitted (study 13c, today's protocol).")
    args, runs, results = begin_study(p, argv, "free_space_study.py")
    results["points"] = args.points
    if args.plot_only:
        from stochastic_fields.io_utils import read_json

        print(plot(read_json(args.out / "study.json", "study results"), args.out / "coverage_by_seed.png"))
        return 0
    from study_helpers import parse_runs


    references = parse_runs(p, args.reference) if args.reference else {}
    results["runs"], results["references"] = {}, {}
    for label, run_dir in runs.items():
        print(f"{label}: {run_dir}", flush=True)
        results["runs"][label] = r = study_run(run_dir, seed=args.seed, fit_points=args.points)
        print(f"  Spearman per view {r['spearman']['plain']['per_view']:.3f} -> {r['spearman']['checked']['per_view']:.3f}, "
              f"distance {r['distance']['plain']:.3f} -> {r['distance']['checked']:.3f}", flush=True)
    for label, run_dir in references.items():
        print(f"{label} (reference): {run_dir}", flush=True)
        results["references"][label] = study_run(run_dir, seed=args.seed, fit=False)
    results["decision"] = decide(results)
    text = _markdown(results)
    write_study(args.out, results, text)
    plot(results, args.out / "coverage_by_seed.png")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
