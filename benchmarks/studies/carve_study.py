"""Study 14: does carving the training views' free space out of a trained model improve its renders?

Study 13 found renders putting surfaces where the training views saw empty space (floaters).
``free_space.carve_free_space`` empties the occupancy cells that lie clearly in front of a
training view's sharply ended surface, so renders skip them (no retraining). This study
re-evaluates each run twice, as the tables evaluate it (its scored test views, SCORE capture
points or the synthetic scene's SCORE-block pixels, the depth map refitted on the CALIBRATE points
of the same model): *plain* (today) and *carved*.

    python benchmarks/studies/carve_study.py --run fern/0=RUN flower/0=RUN ... --out OUT
    python benchmarks/studies/carve_study.py --run ... --merge OUT_A OUT_B --out OUT   # runs made in parts
    python benchmarks/studies/carve_study.py --check --run ... --out OUT   # study 15: carved, then checked

With ``--check`` (study 15) the carved arm also checks free space: the training views are rendered
again from the carved model and the depth map is fitted on, and applies, the checked std
(``calibrate --free-space``).

Labels are SCENE/SEED; the decision reads the means over a scene's seeds (docs/uncertainty.md,
study 14, where the rule was fixed before this ran). Renders only. Torch on 1 thread. Writes
``study.json`` and ``study.md``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from study_helpers import LEVELS, begin_study, by_scene, study_parser, write_study  # noqa: E402

#: Study 14's tolerances (fixed with the rule; study 8's): PSNR may drop by at most this (dB), ...
PSNR_TOLERANCE: float = 0.2
#: ... colour NLL rise by at most this, ...
NLL_TOLERANCE: float = 0.05
#: ... colour and per-view depth Spearman fall by at most this, and the coverage distance grow by
#: at most this.
RANK_TOLERANCE: float = 0.02
#: What the rule reads: (key, direction: +1 higher is better, -1 lower is better).
MEASURES: tuple[tuple[str, int], ...] = (("psnr", 1), ("nll", -1), ("colour_spearman", 1), ("depth_abs_rel", -1),
                                         ("depth_spearman_view", 1), ("distance", -1))


def scores(metrics: dict) -> dict[str, float]:
    """The ruled numbers of an ``evaluate`` result (per-view means and pooled depth, as the tables)."""
    s, depth = metrics["summary"], metrics["pooled"].get("depth", {})
    cov = [depth.get("coverage_68", math.nan), depth.get("coverage_95", math.nan)]
    return {"psnr": s["psnr"]["mean"], "nll": s["nll"]["mean"], "colour_spearman": s["spearman_mse_var"]["mean"],
            "depth_abs_rel": depth.get("abs_rel", math.nan), "depth_spearman_view": s["depth/spearman"]["mean"],
            "depth_spearman_pooled": depth.get("spearman", math.nan), "coverage": cov,
            "distance": float(max(abs(c - n) for c, n in zip(cov, LEVELS)))}


def study_run(run_dir: Path, out: Path, *, seed: int = 0, check: bool = False) -> dict:
    from stochastic_fields.calibration import RunCalibration, fit_depth_calibration
    from stochastic_fields.capture_points import SCORE, load_capture_points, sparse_depth_for_role
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.free_space import carve_free_space, render_training_depth
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    views = [int(name.split("_")[-1]) for name in read_json(run_dir / "metrics.json", "metrics")["views"]]
    sparse = None
    if getattr(dataset, "depths", None) is None:
        sparse = sparse_depth_for_role(dataset, load_capture_points(dataset), views, SCORE)
    ref = render_training_depth(model, dataset, seed=seed, progress=False)
    result = {"run": str(run_dir), "views": views}
    for name in ("plain", "carved"):
        reference = None
        if name == "carved":
            result["carved_share"] = carve_free_space(model, ref)
            if check:  # the check against the carved model's own training renders
                reference = render_training_depth(model, dataset, seed=seed, progress=False)
        cal = RunCalibration(depth=fit_depth_calibration(model, dataset, seed=seed, free_space=reference),
                             training_depth=reference)
        metrics = evaluate(model, dataset, out / name, views=views, seed=seed, sparse_depth=sparse, product_views=1,
                           calibration=cal, progress=False)
        result[name] = {**scores(metrics), "depth_scale": cal.depth.std_scale}
    return result


def decide(results: dict) -> dict:
    """Study 14's rule on the per-scene means over seeds (docs/uncertainty.md)."""
    scenes = {}
    for scene, runs in by_scene(results["runs"]).items():
        m = {"seeds": len(runs)}
        for which in ("plain", "carved"):
            for key, _ in MEASURES + (("depth_spearman_pooled", 1),):
                m[f"{key}_{which}"] = float(np.mean([r[which][key] for r in runs]))
            m[f"coverage_{which}"] = np.mean([r[which]["coverage"] for r in runs], axis=0).tolist()
        scenes[scene] = m
    tolerance = {"psnr": PSNR_TOLERANCE, "nll": NLL_TOLERANCE, "colour_spearman": RANK_TOLERANCE,
                 "depth_spearman_view": RANK_TOLERANCE, "distance": RANK_TOLERANCE, "depth_abs_rel": 0.0}
    failed = {}
    for scene, m in scenes.items():
        bad = [key for key, sign in MEASURES
               if sign * (m[f"{key}_carved"] - m[f"{key}_plain"]) < -tolerance[key]
               or (key == "depth_abs_rel" and not m["depth_abs_rel_carved"] < m["depth_abs_rel_plain"])]
        if bad:
            failed[scene] = bad
    return {"scenes": scenes, "failed": failed, "taken": not failed}


def _markdown(results: dict) -> str:
    d = results["decision"]
    title = ("Study 15: carving, then the free-space check" if "--check" in results["command"]
             else "Study 14: carving the training views' free space")
    lines = [f"# {title}", "", f"Command: `{results['command']}`", "",
             "Each run evaluated as the tables evaluate it (its test views, SCORE points; the depth map refitted on "
             "the CALIBRATE points of the same model), *plain* (today) and *carved* (occupancy cells clearly in "
             "front of a training view's sharply ended surface emptied"
             + ("; then the depth map fitted on, and applying, the free-space-checked std against the carved "
                "model's training renders" if "--check" in results["command"] else "")
             + "). Means over seeds, plain -> carved.", "",
             "| scene | seeds | PSNR | colour NLL | colour Spearman | depth abs-rel | depth Spearman per view | "
             "coverage 68 / 95 | distance |", "|---|---|---|---|---|---|---|---|---|"]
    for scene, m in d["scenes"].items():
        def pair(key: str) -> str:
            return f"{m[key + '_plain']:.3f} -> {m[key + '_carved']:.3f}"
        lines.append(f"| {scene} | {m['seeds']} | {pair('psnr')} | {pair('nll')} | {pair('colour_spearman')} | "
                     f"{pair('depth_abs_rel')} | {pair('depth_spearman_view')} | "
                     f"{m['coverage_plain'][0]:.3f} / {m['coverage_plain'][1]:.3f} -> "
                     f"{m['coverage_carved'][0]:.3f} / {m['coverage_carved'][1]:.3f} | {pair('distance')} |")
    lines += ["", "Failed: " + ("; ".join(f"{s}: {', '.join(k)}" for s, k in d["failed"].items()) or "nothing")
              + f". **{'Taken' if d['taken'] else 'Not taken'}.**", "", "## Per run", "",
              "| run | carved share of occupied cells | PSNR | depth abs-rel | depth Spearman per view | coverage 68 / 95 |",
              "|---|---|---|---|---|---|"]
    for label, r in results["runs"].items():
        p, c = r["plain"], r["carved"]
        lines.append(f"| {label} | {r['carved_share']:.2f} | {p['psnr']:.2f} -> {c['psnr']:.2f} | "
                     f"{p['depth_abs_rel']:.3f} -> {c['depth_abs_rel']:.3f} | {p['depth_spearman_view']:.3f} -> "
                     f"{c['depth_spearman_view']:.3f} | {p['coverage'][0]:.3f} / {p['coverage'][1]:.3f} -> "
                     f"{c['coverage'][0]:.3f} / {c['coverage'][1]:.3f} |")
    lines += ["", "Runs: " + "; ".join(f"{k}: `{r['run']}`" for k, r in results["runs"].items()), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "carve", "Trained and evaluated S-NeRF (default) runs; labels SCENE/SEED.")
    p.add_argument("--work", type=Path, default=None, help="Where the evaluations go (default: OUT/work).")
    p.add_argument("--check", action="store_true",
                   help="Study 15: the carved arm also fits and applies the free-space-checked depth map.")
    p.add_argument("--merge", nargs="*", type=Path, default=[],
                   help="Decide over the runs of these earlier outputs (their study.json) instead of running.")
    args, runs, results = begin_study(p, argv, "carve_study.py")
    from stochastic_fields.io_utils import read_json

    work = args.work or args.out / "work"
    results["runs"] = {}
    if args.merge:
        parts = [read_json(d / "study.json", "study results") for d in args.merge]
        results["parts"] = [part["command"] for part in parts]
        runs = {}
        for part in parts:
            results["runs"].update(part["runs"])
    for label, run_dir in runs.items():
        print(f"{label}: {run_dir}", flush=True)
        results["runs"][label] = r = study_run(run_dir, work / label.replace("/", "_"), seed=args.seed,
                                               check=args.check)
        print(f"  carved {r['carved_share']:.2f}; PSNR {r['plain']['psnr']:.2f} -> {r['carved']['psnr']:.2f}, abs-rel "
              f"{r['plain']['depth_abs_rel']:.3f} -> {r['carved']['depth_abs_rel']:.3f}", flush=True)
    results["decision"] = decide(results)
    text = _markdown(results)
    write_study(args.out, results, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
