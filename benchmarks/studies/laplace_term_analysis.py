"""Analysis (decides nothing): a Laplace depth std from coarse cells of the trained density.

S-NeRF's depth std is almost all termination spread (study 34): its trajectories agree where the photos see
a surface, so a surface rendered in front of the true one often gets a small std. ``stochastic_fields.laplace``
measures what the training photos leave undetermined over regions of space instead: a diagonal Laplace
approximation of a log-density offset per coarse cell (32 x 32 x 32 over the field's unit cube, prior std 1,
the Fisher information of 65,536 training rays' colours), propagated to each ray's expected depth. This
measures, on study 37's today runs (paper split, seeds 12-14) and their validation photos, how that std
ranks the depth errors and what the depth map makes of it, in four arms, each map fitted on the same
calibration renders (the calibration views between the training views, as ``calibrate`` fits them) and
scored on the validation photos cross-fitted, as ``eval`` scores them:

* ``today``: the run's raw std sigma (the map refitted: free-space weight, rho, s(p));
* ``term``: sigma with the Laplace std as the map's extra term (the edge term's slot: gamma fitted by the
  CRPS, ``calibration.fit_edge_weight``);
* ``replace``: the Laplace std in place of sigma;
* ``sum``: sqrt(sigma^2 + l^2) in place of sigma.

The Laplace std l is put in sigma's units by one factor per run, median(sigma) / median(l) over the
calibration renders (no validation photo is read). On the synthetic validation scenes (exact depth) the
ranking alone: Spearman of |error| against each std per view, at 2,000 opaque pixels of each test view.
Seed 12's rows were explored first (grid sizes 16^3 to 128 x 128 x 32 and prior precisions 0.01 to 10^4 tried
there, with trilinear cells); 13 and 14 confirm them. Beside them (``--extra LABEL RUN EVALS``, scored at the
photos EVALS/views holds): study 39's candidate (``field.grid_decoder_width=64 field.grid_feature_dim=16
loss.lambda_smoothness=60``) at the paper split, seeds 12-14, and the capture split (seed 21, ten minutes on one
thread). Commands (inputs as ``agreement_groups_analysis.py`` lists them; the synthetic runs ``runs/synth/runS``
are study 39's ensemble analysis's; VALIDATION as there)::

    # study 39's candidate, SEED 12-14, SCENE fern / flower
    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods snerf_default --seed SEED \
        --no-timing --quiet --set field.grid_decoder_width=64 --set field.grid_feature_dim=16 \
        --set loss.lambda_smoothness=60 --out runs/laplace/sSEED/wide_smooth_SCENE
    stochastic-fields eval --run runs/laplace/sSEED/wide_smooth_SCENE/SCENE/snerf_default --views VALIDATION \
        --quiet --out runs/laplace/validation/sSEED/wide_smooth/SCENE/views_eval
    # the capture split
    OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --scenes SCENE --methods snerf --marks 1 --threads 1 \
        --seed 21 --quiet --work runs/laplace/capture --out runs/laplace/capture_report_SCENE
    stochastic-fields eval --run runs/laplace/capture/SCENE/snerf/run --quiet \
        --out runs/laplace/capture/SCENE/snerf/views_eval
    # the analysis (each --extra as above for every run), then one setting tried on every scene
    OMP_NUM_THREADS=1 python benchmarks/studies/laplace_term_analysis.py --runs runs/mondrian \
        --seeds 12 13 14 --synthetic runs/synth/run1 runs/synth/run2 \
        --extra wide_smooth_flower_s12 RUN EVALS ... --extra capture_fern_s21 RUN EVALS ... \
        --work runs/laplace/analysis --out benchmarks/results/laplace_term_analysis
    OMP_NUM_THREADS=1 python benchmarks/studies/laplace_term_analysis.py --runs runs/mondrian \
        --seeds 12 13 14 --synthetic runs/synth/run1 runs/synth/run2 --resolution 96 96 32 --prior 100 \
        --work runs/laplace/analysis_96 --out benchmarks/results/laplace_term_analysis/grid_96
    # the candidate on fresh seeds 15-17 (trained and evaluated as above), the --extra runs alone
    OMP_NUM_THREADS=1 python benchmarks/studies/laplace_term_analysis.py --seeds --scenes \
        --extra wide_smooth_SCENE_sSEED RUN EVALS ... (every SCENE and SEED) \
        --work runs/laplace/analysis_fresh --out benchmarks/results/laplace_term_analysis/fresh_seeds
    # today's default (wider colour branch, parallax term in every map): study 43's `wide` rows re-trained
    # (tables_steps_study.py's docstring, --study 43, --out runs/lap44/sSEED/today) and evaluated
    # (--out runs/lap44/validation/sSEED/today/SCENE/snerf_default), SEED 18-20; the synthetic runs as above
    OMP_NUM_THREADS=1 python benchmarks/studies/laplace_term_analysis.py --runs runs/lap44 --seeds 18 19 20 \
        --parallax-term --synthetic runs/synth/run1 runs/synth/run2 --work runs/lap44/analysis \
        --out benchmarks/results/laplace_term_analysis/today_default
"""

from __future__ import annotations

import argparse
import functools
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import cached, pooled_map_scores, write_study  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402

import stochastic_fields.calibration as calibration  # noqa: E402
from stochastic_fields.calibration import depth_calibration_renders, depth_map_and_folds  # noqa: E402
from stochastic_fields.cameras import generate_rays_for_view  # noqa: E402
from stochastic_fields.capture_points import (block_keys, load_capture_points, rays_through_points,  # noqa: E402
                                              score_sparse_depth)
from stochastic_fields.evaluation import depth_samples  # noqa: E402
from stochastic_fields.free_space import checked_std, load_training_depth, render_training_depth  # noqa: E402
from stochastic_fields.laplace import LAPLACE_PRIOR_PRECISION, LAPLACE_RESOLUTION, fit_laplace_density  # noqa: E402
from stochastic_fields.trainer import TrainingRays, load_trained_model  # noqa: E402
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402

SEEDS = (12, 13, 14)
SCENES = ("fern", "flower")
ARMS = ("today", "term", "replace", "sum")
LEVELS = ("50", "68", "90", "95", "99")
SYNTHETIC_PIXELS = 2000


#: The perturbation grid and prior of a run's fit (``--resolution``, ``--prior``; the module's defaults).
GRID = {"resolution": LAPLACE_RESOLUTION, "prior_precision": LAPLACE_PRIOR_PRECISION, "pair_points": "both",
        "parallax": False}


def laplace_for(model, dataset):
    """(the fitted LaplaceDensity, fit seconds) of a run."""
    t0 = time.perf_counter()
    rays = TrainingRays.from_dataset(dataset, torch.device("cpu")).rays
    return (fit_laplace_density(model, rays, resolution=GRID["resolution"], prior_precision=GRID["prior_precision"]),
            time.perf_counter() - t0)


def arm_scores(arm: str, renders: dict, lap_cal: np.ndarray, val: list, capture, ref, where: str) -> dict:
    """The validation photos' scores under ``arm``'s map (module doc)."""
    r = {k: v for k, v in renders.items() if k != "edge"}
    if arm == "term":
        r["edge"] = lap_cal
    elif arm in ("replace", "sum"):
        raw = lap_cal if arm == "replace" else np.hypot(renders["std_raw"], lap_cal)
        r.update(std_raw=raw, std=checked_std(raw, renders["violation"]))
    depth_map, folds = depth_map_and_folds(r, capture, relative_floor=True, where=where)
    pool = []
    for sd, products, lap, blocks in val:
        p = dict(products)
        if arm == "term":
            p["depth_edge"] = np.zeros_like(products["depth_mean"])
            p["depth_edge"][sd.rows, sd.cols] = lap
        elif arm in ("replace", "sum"):
            p["depth_std_raw"] = products["depth_std_raw"].copy()
            at = p["depth_std_raw"][sd.rows, sd.cols]
            p["depth_std_raw"][sd.rows, sd.cols] = lap if arm == "replace" else np.hypot(at, lap)
        pool.append(depth_samples(p, sparse=sd, blocks=blocks))
    return {**pooled_map_scores(depth_map, folds, ref, pool),
            "beta": depth_map.free_space_weight if depth_map.free_space else 0.0, "rho": depth_map.relative_floor,
            "gamma": depth_map.edge_weight}


def analyse(run: Path, evals: Path, views: list[int]) -> dict:
    """Every arm's scores of one run at ``views`` (rendered in ``evals/views``), with the Laplace fit's
    and a view's costs."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    laplace, fit_s = laplace_for(model, dataset)
    ref = load_training_depth(run)
    capture = load_capture_points(dataset)
    original = calibration.edge_at_points
    calibration.edge_at_points = lambda m, cams, near, far, sparse, depth, **_: laplace.depth_std(
        m, rays_through_points(cams, near, far, sparse)[0]).numpy()
    try:  # the calibration renders, with the Laplace std of their rays in the edge slot
        renders = depth_calibration_renders(model, dataset, points="held-out", free_space=ref, pair_points=GRID["pair_points"],
                                            edges=True, parallax=ref if GRID["parallax"] else None)
    finally:
        calibration.edge_at_points = original
    factor = float(np.median(renders["std_raw"]) / np.median(renders["edge"]))
    val = []
    for v, sd in score_sparse_depth(dataset, views).items():
        with np.load(evals / "views" / f"view_{v:03d}.npz") as f:
            products = {k: f[k] for k in f.files}
        rays = generate_rays_for_view(dataset.cameras, v, dataset.near, dataset.far)
        lap = laplace.depth_std(model, rays[torch.as_tensor(sd.rows), torch.as_tensor(sd.cols)]).numpy()
        val.append((sd, products, factor * lap, block_keys(capture.xyz[sd.point_index], capture.xyz)))
    out = {"arms": {arm: arm_scores(arm, renders, factor * renders["edge"], val, capture, ref, str(run)) for arm in ARMS},
           "factor": factor, "fit_s": fit_s}
    view = views[0]
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far).flatten()
    t0 = time.perf_counter()
    laplace.depth_std(model, rays)
    out["view_laplace_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    with torch.no_grad():
        model.render_view(generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far))
    out["view_render_s"] = time.perf_counter() - t0
    return out


def synthetic_test_pixels(run: Path, dataset):
    """For each test view v of a synthetic run: (v, its eval products, rows [P], cols [P], exact depth
    [H, W]) at ``SYNTHETIC_PIXELS`` opaque pixels of finite exact depth, drawn with one generator seeded 0."""
    rng = np.random.default_rng(0)
    for v in dataset.test_indices:
        with np.load(run / "eval" / "views" / f"view_{v:03d}.npz") as f:
            p = {k: f[k] for k in f.files}
        truth = np.asarray(dataset.depths[v])
        r, c = np.nonzero(np.isfinite(truth) & (truth > 0) & (p["opacity"] > OPACITY_MASK))
        pick = rng.choice(len(r), size=min(SYNTHETIC_PIXELS, len(r)), replace=False)
        yield v, p, r[pick], c[pick], truth


def analyse_synthetic(run: Path) -> dict:
    """Per test view of a synthetic run: Spearman of |error| against the calibrated std, the Laplace std and
    their sum (the run's map's scale, sigma's units by the median factor of each view's pixels)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    laplace, fit_s = laplace_for(model, dataset)
    rows = []
    for v, p, r, c, truth in synthetic_test_pixels(run, dataset):
        rays = generate_rays_for_view(dataset.cameras, v, dataset.near, dataset.far)[torch.as_tensor(r), torch.as_tensor(c)]
        lap = laplace.depth_std(model, rays).numpy()
        err = np.abs(p["depth_mean"][r, c] - truth[r, c])
        raw = p["depth_std_raw"][r, c]
        summed = np.hypot(raw, lap * np.median(raw) / np.median(lap))
        rows.append({"calibrated": spearmanr(err, p["depth_std"][r, c]).correlation,
                     "raw": spearmanr(err, raw).correlation, "laplace": spearmanr(err, lap).correlation,
                     "sum": spearmanr(err, summed).correlation})
    return {key: float(np.mean([row[key] for row in rows])) for key in rows[0]} | {"views": len(rows), "fit_s": fit_s}


def arm_row(label: str, arm: str, rows: list[dict]) -> str:
    """One table row: the means over ``rows`` of coverage, width, interval score, CRPS and rankings."""
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    cov = " / ".join(f"{100 * np.mean([r['coverage'][n] for r in rows]):.1f}" for n in LEVELS)
    return (f"| {label} | {arm} | {cov} | {100 * mean('halfwidth_median_95'):.1f}% | {mean('interval_score_95'):.3f} | "
            f"{mean('crps'):.4f} | {mean('spearman'):.3f} / {mean('spearman_per_view'):.3f} |")


#: The arms of an analysis that puts one more std term in the depth map's edge slot (``term_arm_results``).
TERM_ARMS = ("today", "term")


def run_with_reference(run: Path):
    """(model, dataset, training-view depths) of a trained run on the CPU: its stored training depths
    (``free_space.load_training_depth``), rendered when it kept none."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    ref = load_training_depth(run)
    return model, dataset, ref if ref is not None else render_training_depth(model, dataset, progress=False)


def renders_with_term(model, dataset, ref, term) -> tuple[dict, float]:
    """The calibration renders of today's map (held-out points, free-space check and parallax term of the
    training-view reference ``ref``) with ``term`` [N] of their points in the occlusion-edge slot ("edge"; a
    function called as ``calibration.edge_at_points`` is), and the factor median(sigma) / median(term) (over
    the points with a positive term) that puts the term in sigma's units."""
    original = calibration.edge_at_points
    calibration.edge_at_points = term
    try:
        renders = depth_calibration_renders(model, dataset, points="held-out", free_space=ref, edges=True, parallax=ref)
    finally:
        calibration.edge_at_points = original
    positive = renders["edge"] > 0
    return renders, float(np.median(renders["std_raw"]) / np.median(renders["edge"][positive]))


def term_arm_results(runs: Path, work: Path, seeds: list[int], scenes, analyse) -> dict:
    """{scene: {"arms": {arm: per-seed scores}, "extra": per-seed rest}} of a ``TERM_ARMS`` analysis
    (``seed_results`` over ``seeds``)."""
    views_of = functools.cache(validation_views)
    results: dict = {}
    for scene in scenes:
        per_seed = seed_results(runs, work, seeds, scene, analyse, views_of)
        results[scene] = {"arms": {arm: [s["arms"][arm] for s in per_seed] for arm in TERM_ARMS},
                          "extra": [{k: v for k, v in s.items() if k != "arms"} for s in per_seed]}
    return results


def term_arm_markdown(title: str, intro: str, results: dict, seeds: list[int], extra_columns: dict[str, object],
                      extra_said: str) -> list[str]:
    """The report's lines of a ``TERM_ARMS`` analysis: the seed means of both arms, then per seed the fitted
    gamma, each arm's width, IS95 and per-view ranking, and ``extra_columns`` {heading: cell(the seed's
    extra dict) -> str}, said in words by ``extra_said``."""
    lines = [f"# {title}", "", intro, "",
             "| scene | arm | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
             "depth Spearman pooled / per view |", "|---|---|---|---|---|---|---|"]
    for scene, res in results.items():
        lines += [arm_row(scene, arm, res["arms"][arm]) for arm in TERM_ARMS]
    lines += ["", "Per seed: the fitted weight gamma, the median 95% half-width, IS95 / depth and per-view Spearman of "
              f"each arm, {extra_said}:", "",
              f"| scene | seed | gamma | today | term | {' | '.join(extra_columns)} |",
              "|---|---|---|---|---|" + "---|" * len(extra_columns)]
    for scene, res in results.items():
        for seed, extra, today, term in zip(seeds, res["extra"], res["arms"]["today"], res["arms"]["term"]):
            cell = lambda r: f"{100 * r['halfwidth_median_95']:.1f}%, {r['interval_score_95']:.3f}, {r['spearman_per_view']:.3f}"  # noqa: E731
            extras = " | ".join(fmt(extra) for fmt in extra_columns.values())
            lines.append(f"| {scene} | {seed} | {term['gamma']:.3g} | {cell(today)} | {cell(term)} | {extras} |")
    return lines


def seed_groups(extra: dict) -> dict[str, list[str]]:
    """{label without its ``_sSEED`` suffix: the ``--extra`` labels of that group}, groups of two or more runs."""
    groups: dict[str, list[str]] = {}
    for label in extra:
        groups.setdefault(re.sub(r"_s\d+$", "", label), []).append(label)
    return {group: labels for group, labels in groups.items() if len(labels) > 1}


def markdown(results: dict, extra: dict, synthetic: dict, seeds: list[int], runs: Path) -> str:
    lines = ["# A Laplace depth std from coarse cells of the trained density", ""]
    if not results:
        lines += [f"Perturbation grid {' x '.join(map(str, GRID['resolution']))} cells, prior precision "
                  f"{GRID['prior_precision']:g}; calibration points seen by {GRID['pair_points']} view(s) of a pair; the "
                  "``--extra`` runs only. Decides nothing."]
        return _extra_markdown(lines, extra, synthetic)
    maps = "with the parallax term (today's map)" if GRID["parallax"] else "without the parallax term"
    lines += [f"The `today` runs of `{runs}` (paper split, seeds {', '.join(map(str, seeds))}), scored on their "
             "validation photos as eval scores them (cross-fitted); each arm's map fitted on the same calibration renders, "
             f"{maps}. Means over the seeds. Perturbation grid {' x '.join(map(str, GRID['resolution']))} cells, prior "
             f"precision {GRID['prior_precision']:g}. Decides nothing.", "",
             "| scene | arm | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
             "depth Spearman pooled / per view |", "|---|---|---|---|---|---|---|"]
    for scene, arms in results.items():
        lines += [arm_row(scene, arm, rows) for arm, rows in arms.items()]
    lines += ["", "Per seed (median 95% half-width, IS95 / depth, per-view Spearman):", "",
              "| scene | arm | " + " | ".join(f"seed {s}" for s in seeds) + " |", "|---|---|" + "---|" * len(seeds)]
    for scene, arms in results.items():
        for arm, rows in arms.items():
            cells = [f"{100 * r['halfwidth_median_95']:.1f}%, {r['interval_score_95']:.3f}, {r['spearman_per_view']:.3f}"
                     for r in rows]
            lines.append(f"| {scene} | {arm} | " + " | ".join(cells) + " |")
    return _extra_markdown(lines, extra, synthetic)


def _extra_markdown(lines: list[str], extra: dict, synthetic: dict) -> str:
    """``markdown``'s tables of the ``--extra`` runs (each, then the means of each seed group) and the synthetic scenes."""
    groups = seed_groups(extra)
    if groups:
        lines += ["", "Means over the seeds of each group of ``--extra`` runs (LABEL_sSEED):", "",
                  "| runs | arm | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
                  "depth Spearman pooled / per view |", "|---|---|---|---|---|---|---|"]
        for group, labels in groups.items():
            name = f"{group} ({', '.join(label[len(group) + 1:] for label in labels)})"
            lines += [arm_row(name, arm, [extra[label][arm][0] for label in labels]) for arm in ARMS]
    if extra:
        lines += ["", "Single runs (``--extra``): study 39's candidate at the paper split (its validation photos) and the "
                  "capture split (its validation photos); the same four maps.", "",
                  "| run | arm | cov 50 / 68 / 90 / 95 / 99 | median 95% half-width | IS95 / depth | CRPS / depth | "
                  "depth Spearman pooled / per view |", "|---|---|---|---|---|---|---|"]
        for label, arms in extra.items():
            lines += [arm_row(label, arm, rows) for arm, rows in arms.items()]
    if synthetic:
        lines += ["", "Synthetic validation scenes (demo preset, exact depth, 2,000 opaque pixels a test view): mean "
                  "per-view Spearman of |error| against each std.", "",
                  "| run | views | calibrated std (today) | raw sigma | Laplace std | sqrt(sigma^2 + l^2) |",
                  "|---|---|---|---|---|---|"]
        for label, s in synthetic.items():
            lines.append(f"| {label} | {s['views']} | {s['calibrated']:.3f} | {s['raw']:.3f} | {s['laplace']:.3f} | "
                         f"{s['sum']:.3f} |")
    return "\n".join(lines) + "\n\nCommand: the module docstring of `benchmarks/studies/laplace_term_analysis.py`.\n"


def seed_results(runs: Path, work: Path, seeds: list[int], scene: str, analyse, views_of) -> list[dict]:
    """Per seed, ``analyse(run, evals, views)`` of ``runs/sSEED/today/SCENE/snerf_default`` at the validation
    photos its eval rendered (``runs/validation/sSEED/today/SCENE/snerf_default``, the photos
    ``views_of(scene)``), cached in ``work/sSEED/SCENE.json``."""
    def one(seed: int) -> dict:
        return analyse(runs / f"s{seed}" / "today" / scene / "snerf_default",
                       runs / "validation" / f"s{seed}" / "today" / scene / "snerf_default", views_of(scene))
    return [cached(work / f"s{seed}" / f"{scene}.json", functools.partial(one, seed)) for seed in seeds]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/mondrian"))
    ap.add_argument("--seeds", nargs="*", type=int, default=list(SEEDS))
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=SCENES)
    ap.add_argument("--extra", nargs=3, action="append", default=[], metavar=("LABEL", "RUN", "EVALS"),
                    type=str, help="another run (a capture split's, a candidate's), scored at its eval folder's "
                                   "views (the run's validation photos)")
    ap.add_argument("--synthetic", nargs="*", type=Path, default=[], help="synthetic runs with RUN/eval/views")
    ap.add_argument("--resolution", type=int, nargs=3, default=list(LAPLACE_RESOLUTION), metavar=("X", "Y", "Z"))
    ap.add_argument("--prior", type=float, default=LAPLACE_PRIOR_PRECISION, help="prior precision lambda")
    ap.add_argument("--pair-points", choices=("both", "either"), default="both",
                    help="the calibration renders' points: seen by both views of a pair (calibrate's default) or either")
    ap.add_argument("--parallax-term", action="store_true",
                    help="every arm's map holds the parallax term (the default since study 42; the runs before it: without)")
    ap.add_argument("--work", type=Path, default=Path("runs/laplace/analysis"), help="per-run results (resumable)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/laplace_term_analysis"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    GRID.update(resolution=tuple(args.resolution), prior_precision=args.prior, pair_points=args.pair_points,
                parallax=args.parallax_term)
    args.extra = [(label, Path(run), Path(evals)) for label, run, evals in args.extra]
    cost_keys = ("factor", "fit_s", "view_laplace_s", "view_render_s")
    views_of = functools.cache(validation_views)  # a scene's photos, loaded once and only for a run not yet cached
    results: dict = {}
    costs: dict = {}
    for scene in args.scenes:
        per_seed = seed_results(args.runs, args.work, args.seeds, scene, analyse, views_of)
        results[scene] = {arm: [s["arms"][arm] for s in per_seed] for arm in ARMS}
        costs[scene] = [{k: s[k] for k in cost_keys} for s in per_seed]
    extra: dict = {}
    for label, run, evals in args.extra:
        views = sorted(int(f.stem.split("_")[1]) for f in (evals / "views").glob("view_*.npz"))
        done = cached(args.work / "extra" / f"{label}.json", lambda: analyse(run, evals, views))
        extra[label] = {arm: [done["arms"][arm]] for arm in ARMS}
        costs[label] = [{k: done[k] for k in cost_keys}]
    synthetic = {run.name: cached(args.work / "synthetic" / f"{run.name}.json", lambda: analyse_synthetic(run))
                 for run in args.synthetic}
    write_study(args.out, {"results": results, "extra": extra, "synthetic": synthetic, "costs": costs,
                           "seeds": args.seeds, "grid": dict(GRID)}, markdown(results, extra, synthetic, args.seeds, args.runs))

if __name__ == "__main__":
    main()
