"""What the renders-only studies share: reading the runs, rendering and standardising the scored
capture points, the options every study takes, coverage and distance of the intervals, and writing
``study.json`` / ``study.md`` with the command that reproduces them.

The study scripts beside this file import it by path (``sys.path`` holds the folder of the script
that runs); docs/studies.md is the research log they feed.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.special import ndtri
from scipy.stats import spearmanr

from stochastic_fields import metrics as M
from stochastic_fields.calibration import RunCalibration, render_at_points
from stochastic_fields.cameras import camera_to_world, intrinsics_3x3
from stochastic_fields.capture_points import SCORE, backproject_pixels, block_keys, depth_map_observes, restrict_sparse_depth
from stochastic_fields.evaluation import calibrated_depth_scores, pool_depth_samples
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.sparse_depth import project_sparse_depth, sparse_depth_for_dataset
from stochastic_fields.view_maps import OPACITY_MASK

#: Central levels scored.
LEVELS: tuple[float, float] = (0.6827, 0.95)
#: Share of the synthetic scene's evaluated surface pixels that are scored (seeded).
SYNTHETIC_PIXEL_SHARE: float = 0.1
#: Groups of the scored points by raw sigma: equal-count terciles.
STD_GROUPS: tuple[str, ...] = ("low sigma", "mid sigma", "high sigma")


def standardised_at_points(model, cameras, near, far, sparse, seed: int) -> dict[str, np.ndarray]:
    """|d - d*| / sigma [N], |d - d*| [N], sigma [N] and the point index [N] of each rendered point
    with opacity > mask."""

    r = render_at_points(model, cameras, near, far, sparse, generator=torch.Generator().manual_seed(seed))
    index = np.concatenate([sparse[v].point_index for v in sparse if len(sparse[v])] or [np.zeros(0, np.int64)])
    view = np.concatenate([np.full(len(sparse[v]), v) for v in sparse if len(sparse[v])] or [np.zeros(0, np.int64)])
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_std"]) & (r["depth_std"] > 0)
    abs_err = np.abs(r["gt"] - r["depth_mean"])[keep]
    return {"abs_z": abs_err / r["depth_std"][keep], "abs_err": abs_err, "std": r["depth_std"][keep],
            "index": index[keep], "view": view[keep], "gt": r["gt"][keep], "depth_mean": r["depth_mean"][keep]}


def scored_points(run_dir: Path, model, dataset, points, views: list[int], held: np.ndarray, seed: int):
    """Standardised errors at the evaluated test views with their points (world xyz), blocks and
    roles (SCORE for every synthetic pixel, as the tables score them all)."""

    if points.source == "synthetic":
        rng = np.random.default_rng(seed)
        K, c2w = intrinsics_3x3(dataset.cameras).double(), camera_to_world(dataset.cameras).double()
        xyz, visible, start = [], [np.zeros(0, np.int64) for _ in range(dataset.num_views)], 0
        for v in views:
            depth = dataset.depths[v].double()
            rows, cols = torch.nonzero(depth > 0, as_tuple=True)
            take = torch.from_numpy(rng.random(rows.numel()) < SYNTHETIC_PIXEL_SHARE)
            rows, cols = rows[take], cols[take]
            xyz.append(backproject_pixels(K[v], c2w[v], rows, cols, depth[rows, cols]).numpy())
            visible[v] = np.arange(start, start + len(rows))
            start += len(rows)
        xyz = np.concatenate(xyz)
        sparse = project_sparse_depth(dataset.cameras, xyz, views, visible=visible, visibility_name="test pixels")
        out = standardised_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse, seed)
        out["xyz"] = xyz[out["index"]]
        out["block"] = block_keys(out["xyz"], points.xyz)
        out["role"] = np.full(len(out["abs_z"]), SCORE)
        return out
    if points.colmap is not None:
        full = sparse_depth_for_dataset(dataset, views, points=points.colmap)
    else:
        full = project_sparse_depth(dataset.cameras, points.xyz, views, visible=points.visible,
                                    visibility_name=points.source)
    sparse = {v: restrict_sparse_depth(sd, held[sd.point_index]) for v, sd in full.items()}
    out = standardised_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse, seed)
    out["xyz"] = points.xyz[out["index"]]
    out["block"] = block_keys(out["xyz"], points.xyz)
    out["role"] = points.roles[out["index"]]
    return out


def photo_points(dataset, points, views: list[int], role: int) -> dict:
    """{view: SparseDepth} of the capture points of ``role`` that each of ``views`` observed: COLMAP
    tracks, or on a dense-depth scene the stand-in points its exact depth map shows
    (``capture_points.depth_map_observes``); one point per pixel, the nearest."""
    if points.colmap is not None:
        full = sparse_depth_for_dataset(dataset, views, points=points.colmap)
        return {v: restrict_sparse_depth(sd, points.roles[sd.point_index] == role) for v, sd in full.items()}
    visible = [np.zeros(0, np.int64) for _ in range(dataset.num_views)]
    for v in views:
        visible[v] = np.flatnonzero(depth_map_observes(dataset, points.xyz, v) & (points.roles == role))
    return project_sparse_depth(dataset.cameras, points.xyz, views, visible=visible, visibility_name="depth map")


def parse_runs(parser: argparse.ArgumentParser, items: list[str], required: str = "metrics.json") -> dict[str, Path]:
    """{scene: run folder} from ``--run SCENE=RUN_DIR`` items; a parser error names the item that
    is malformed or whose run lacks the file ``required`` (a path inside the run)."""
    runs = {}
    for item in items:
        scene, sep, path = item.partition("=")
        if not sep or not scene or not path:
            parser.error(f"--run expects SCENE=RUN_DIR, got {item!r}")
        if not (Path(path) / required).is_file():
            parser.error(f"--run {item}: {path} has no {required} (train and evaluate the run first)")
        runs[scene] = Path(path)
    return runs


def study_command(script: str, argv: list[str] | None) -> str:
    """The command that reproduces a study script's run with ``argv`` (None: this process's)."""
    return " ".join([f"python benchmarks/studies/{script}", *(shlex.quote(a) for a in (argv or sys.argv[1:]))])


def study_parser(doc: str, out_name: str, run_help: str, *, metavar: str = "SCENE/SEED=RUN_DIR",
                 seed_help: str = "Render seed (the draws).") -> argparse.ArgumentParser:
    """The options every renders-only study shares: ``--run`` (``metavar`` items, ``run_help``),
    ``--out`` (default ``benchmarks/results/uncertainty_study/OUT_NAME``) and ``--seed``."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", nargs="+", required=True, metavar=metavar, help=run_help)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/uncertainty_study") / out_name)
    p.add_argument("--seed", type=int, default=0, help=seed_help)
    return p


def cached(path: Path, compute) -> dict:
    """``compute()``'s result, written to ``path`` (JSON, atomically) the first time and read from it after:
    a study's per-run results, so that a stopped study resumes."""
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(compute(), indent=1))
    return json.loads(path.read_text())


def write_study(out: Path, results: dict, text: str, *, name: str = "study") -> None:
    """``OUT/NAME.json`` (``results``) and ``OUT/NAME.md`` (``text``), written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"{name}.json", json.dumps(results, indent=1))
    atomic_write_text(out / f"{name}.md", text)


def begin_study(parser: argparse.ArgumentParser, argv: list[str] | None, script: str
                ) -> tuple[argparse.Namespace, dict[str, Path], dict]:
    """What every renders-only study over ``--run LABEL=RUN_DIR`` starts with: parse ``argv``, put
    torch on 1 thread, read the runs (``parse_runs``). Returns (args, {label: run folder}, the
    results' header: the command that reproduces them, the levels, the thread count)."""
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    runs = parse_runs(parser, args.run)
    return args, runs, {"command": study_command(script, argv), "levels": list(LEVELS), "torch_threads": 1}


def labelled_run_results(parser: argparse.ArgumentParser, argv: list[str] | None, *, folders: int = 1
                         ) -> tuple[argparse.Namespace, list[tuple[str, list[Path]]], dict]:
    """What a renders-only analysis over ``--run SCENE:SEED=FOLDER[:FOLDER]`` items (``folders`` per
    item; the parser has ``--run`` with action "append" and ``--out``) starts with: parse ``argv``, put
    torch on 1 thread, create OUT and read back OUT/results.json (so a stopped analysis resumes;
    ``save_results`` writes it). Returns (args, [(label "SCENE:SEED", [folder, ...])], results); a
    parser error names a malformed item."""
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    saved = args.out / "results.json"
    runs = []
    for item in args.run:
        label, sep, paths = item.partition("=")
        parts = paths.split(":")
        if not sep or ":" not in label or len(parts) != folders or not all(parts):
            parser.error(f"--run {item!r}: expected SCENE:SEED=" + ":".join(["FOLDER"] * folders))
        runs.append((label, [Path(x) for x in parts]))
    return args, runs, (json.loads(saved.read_text()) if saved.is_file() else {})


def save_results(out: Path, results: dict) -> None:
    """``OUT/results.json``, atomically (``labelled_run_results`` reads it back)."""
    atomic_write_text(out / "results.json", json.dumps(results, indent=1))


def labelled_run_parser(doc: str, metavar: str = "SCENE:SEED=RUN") -> argparse.ArgumentParser:
    """The options of a renders-only analysis over labelled runs: ``--run`` (repeated, ``metavar``)
    and ``--out``."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar=metavar)
    p.add_argument("--out", type=Path, required=True)
    return p


def analyse_each(parser: argparse.ArgumentParser, argv: list[str] | None, analyse, report, line) -> int:
    """Run a one-folder-per-run analysis (``labelled_run_results``): ``analyse(label, folder)`` for
    each run not yet in OUT/results.json (saved after each, so a stopped analysis resumes), print
    ``line(label, result)``, then write OUT/study.md = ``report(results)``. Returns 0."""
    args, runs, results = labelled_run_results(parser, argv)
    for label, (folder,) in runs:
        if label not in results:
            results[label] = analyse(label, folder)
            save_results(args.out, results)
        print(f"{label}: {line(label, results[label])}")
    atomic_write_text(args.out / "study.md", report(results))
    return 0


def todays_std_on_photos(run: Path, scene: str) -> dict:
    """What the calibration-side analyses of a trained run start from. The run's model, dataset,
    capture points and training-view depths ("reference"; rendered when the run kept none); the
    calibration renders of every held-out point ("renders", ``depth_calibration_renders`` with the
    free-space check) with today's map refitted on them ("today") and the std it standardises,
    "c_cal" [M] = sqrt(sigma^2 + (beta e)^2 + (rho d)^2); and the rays through the validation photos'
    SCORE points (paper split: ``tables_cap_study.validation_views``; other splits: the run's held-out
    photos), rendered with seed 0 in ``render_at_points``' order: "render" (its dict), "keep" [N]
    (opacity > mask, finite depth, std > 0), "depth" [N] (rendered, the point's where not kept),
    "view" and "point" [N] (each ray's photo and capture point) and today's std "c" [N]."""
    from stochastic_fields.calibration import (_fit_depth_map, depth_calibration_renders,
                                               training_view_terms_at_points)
    from stochastic_fields.capture_points import load_capture_points, score_sparse_depth
    from stochastic_fields.free_space import load_training_depth, render_training_depth
    from stochastic_fields.trainer import load_trained_model
    from tables_cap_study import validation_views

    cfg, model, dataset = load_trained_model(run)
    reference = load_training_depth(run)
    if reference is None:
        reference = render_training_depth(model, dataset, progress=False)
    capture = load_capture_points(dataset)
    renders = depth_calibration_renders(model, dataset, points="held-out", free_space=reference)
    today, std_fit = _fit_depth_map(renders, floor=False, relative_floor=True)
    views = validation_views(scene) if cfg.data.split == "paper" else list(dataset.test_indices)
    sparse = score_sparse_depth(dataset, views)
    r = render_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse,
                         generator=torch.Generator().manual_seed(0))
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(r["depth_mean"]) & (r["depth_std"] > 0)
    depth = np.where(keep, r["depth_mean"], r["gt"])
    beta = today.free_space_weight if today.free_space else 0.0
    violation = training_view_terms_at_points(dataset.cameras, sparse, capture.xyz, r["gt"], depth, reference,
                                              free_space=True, parallax=False)[0]
    views_held = [v for v in sparse if len(sparse[v])]
    return {"model": model, "dataset": dataset, "capture": capture, "reference": reference, "renders": renders,
            "today": today, "c_cal": np.hypot(std_fit, today.relative_floor * renders["depth"]),
            "render": r, "keep": keep, "depth": depth,
            "view": np.concatenate([np.full(len(sparse[v]), v) for v in views_held]),
            "point": np.concatenate([sparse[v].point_index for v in views_held]),
            "c": np.hypot(np.hypot(r["depth_std"], beta * violation), today.relative_floor * r["depth_mean"])}


def interval_scores(iv: dict) -> dict[str, float]:
    """The scores the calibration-side analyses compare, from a ``metrics.interval_sharpness`` output:
    coverage at each level, the median 95% half-width, the 95% interval score and the CRPS (relative
    to depth), and each third of the bands' coverage at 68% and 95%."""
    groups = iv["width_groups"]["coverage"]
    out = {f"coverage_{M.level_name(p)}": c for p, c in zip(iv["levels"], iv["coverage"])}
    out.update({"halfwidth_median_95": iv["halfwidth_median_95"], "interval_score_95": iv["interval_score_95"],
                "crps": iv["crps"]})
    for name, g in (("narrowest", 0), ("middle", 1), ("widest", -1)):
        out[f"coverage_68_{name}_third"], out[f"coverage_95_{name}_third"] = groups[g][1], groups[g][3]
    return out


def coverage(abs_err: np.ndarray, std: np.ndarray, calibration, levels=LEVELS) -> np.ndarray:
    """Share of ``abs_err`` [N] inside the central intervals at ``levels`` [L] that render, eval and
    export draw from the map: |err| <= z_p calibrated_std(std) relative_scale(p), i.e.
    z_p s(p) sqrt(std^2 + floor^2). [L]."""
    levels = np.asarray(levels, np.float64)
    bound = ndtri((1.0 + levels) / 2.0) * calibration.relative_scale(levels)
    return (np.asarray(abs_err)[:, None] <= bound[None, :] * calibration.calibrated_std(std)[:, None]).mean(axis=0)


def tercile_rows(abs_err: np.ndarray, std: np.ndarray, floored, plain) -> list[dict]:
    """Per tercile of ``std`` (``STD_GROUPS``) and for all points: the points, the std range and the
    coverage with the ``floored`` map ("coverage") and the ``plain`` one ("coverage_raw", the name
    ``plots.plot_coverage_by_group`` reads)."""
    edges = np.quantile(std, [1.0 / 3.0, 2.0 / 3.0])
    group = np.digitize(std, edges)
    rows = []
    for g, name in list(enumerate(STD_GROUPS)) + [(None, "all")]:
        m = np.ones(len(std), bool) if g is None else group == g
        rows.append({"group": name, "points": int(m.sum()),
                     "std_range": [float(std[m].min()), float(std[m].max())] if m.any() else [np.nan, np.nan],
                     "coverage": coverage(abs_err[m], std[m], floored).tolist(),
                     "coverage_raw": coverage(abs_err[m], std[m], plain).tolist()})
    return rows


def distance(cov) -> float:
    """Coverage distance: the largest |coverage - nominal| over ``LEVELS``."""
    return float(np.max(np.abs(np.asarray(cov) - np.asarray(LEVELS))))


def gap(rows: list[dict], which: str) -> float:
    """Conditional gap at 68%: max - min of the terciles' ``which`` coverage."""
    vals = [r[which][0] for r in rows if r["group"] in STD_GROUPS]
    return float(max(vals) - min(vals))


def by_scene(runs: dict[str, dict]) -> dict[str, list[dict]]:
    """{SCENE/SEED label: result} -> {scene: [its seeds' results]}, in the given order."""
    out: dict[str, list[dict]] = {}
    for label, res in runs.items():
        out.setdefault(label.split("/")[0], []).append(res)
    return out


def train_and_eval(scene: Path, run: Path, seed: int, *, preset: str = "demo", products: bool = False,
                   options: tuple[str, ...] = ()) -> dict:
    """A run of ``preset`` on the scene folder ``scene`` (training seed ``seed``, one thread, the
    command-line ``options`` after the preset, e.g. ``("--field.density_per", "cell")``), scored
    on its test views by ``stochastic-fields eval`` into ``run``/eval (with the views' npz files when
    ``products``); its ``metrics.json``. Resumable: a run whose metrics exist is read, not re-run."""
    metrics = run / "eval" / "metrics.json"
    if not metrics.is_file():
        cli, env = [sys.executable, "-m", "stochastic_fields.cli"], {**os.environ, "OMP_NUM_THREADS": "1"}
        subprocess.run([*cli, "train", "--preset", preset, "--data.path", str(scene), "--train.seed", str(seed),
                        *options, "--out", str(run), "--quiet"], check=True, env=env, stdout=subprocess.DEVNULL)
        subprocess.run([*cli, "eval", "--run", str(run), *([] if products else ["--no-products"]), "--quiet",
                        "--out", str(run / "eval")], check=True, env=env, stdout=subprocess.DEVNULL)
    return json.loads(metrics.read_text())


def validation_scenes_report(title: str, script: str, labels: tuple[str, ...], rows: dict, means: dict,
                             seeds: tuple[int, ...], head: list[str], table_row) -> list[str]:
    """The report lines of a study on the embedded scene's validation seeds (the demo preset, the 30
    test views): its title, setup, the means over the seeds and the per-seed rows of every label in
    ``labels`` (``rows[label]`` one dict per seed, ``means[label]`` their mean), each formatted by
    ``table_row(label, row)`` under the table ``head``."""
    lines = [f"# {title}", "",
             f"Embedded scene generated with seeds {', '.join(map(str, seeds))} (validation scenes; the demo is seed 0), "
             "S-NeRF with the demo preset (10 of 40 views, 2000 steps), scored on each scene's 30 test views by "
             f"`stochastic-fields eval`. Command: the module docstring of `benchmarks/studies/{script}`.",
             "", "Means over the seeds:", "", *head]
    lines += [table_row(label, means[label]) for label in labels]
    lines += ["", "Per seed:", "", *head]
    for label in labels:
        lines += [table_row(f"{label}, seed {seed}", r) for seed, r in zip(seeds, rows[label])]
    return lines


def pooled_scores(metrics: dict, levels: tuple[float, ...]) -> dict:
    """The pooled scores a validation-scene study rules on, from an ``eval`` ``metrics.json``: PSNR,
    depth abs-rel and Spearman, coverage at ``levels`` and 99%, the median 95% half-width, the 95%
    interval score and the CRPS (widths and scores relative to the depth)."""
    intervals, depth = metrics["pooled"]["depth_intervals"], metrics["pooled"]["depth"]
    return {"psnr": metrics["summary"]["psnr"]["mean"], "abs_rel": depth["abs_rel"], "spearman": depth["spearman"],
            **{f"coverage_{round(100 * p)}": intervals[f"coverage_{round(100 * p)}"] for p in (*levels, 0.99)},
            "halfwidth_median_95": intervals["halfwidth_median_95"], "interval_score_95": intervals["interval_score_95"],
            "crps": intervals["crps"]}


def read_tables_method(path: Path, method: str, read, what: str) -> dict[str, dict]:
    """Per scene of an ``eval_tables.py`` ``tables.json``: ``read(row)`` of ``method``'s row, for the
    scenes that have one; a file that is not one, or a row without what ``read`` asks, stops with
    ``PATH: not an eval_tables.py tables.json with WHAT``."""
    try:
        per_scene = json.loads(Path(path).read_text())["per_scene"]
        return {scene: read(rows[method]) for scene, rows in per_scene.items() if method in rows}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not an eval_tables.py tables.json with {what} "
                         f"({type(exc).__name__}: {exc})") from exc


def seed_means(rows: list[dict]) -> dict:
    """The mean over seeds of every numeric entry of ``rows`` (one dict per seed)."""
    return {k: float(np.mean([r[k] for r in rows])) for k, v in rows[0].items() if isinstance(v, (int, float))}


def coverage_failures(today: dict, candidate: dict, levels: tuple[float, ...], tolerance: float,
                      where: str = "") -> list[str]:
    """A rule's coverage clause: each level p of ``levels`` whose candidate coverage lies more than
    ``tolerance`` from p and further from it than today's, as a failed check prefixed by ``where``."""
    failed = []
    for p in levels:
        key = f"coverage_{round(100 * p)}"
        off_c, off_t = abs(candidate[key] - p), abs(today[key] - p)
        if off_c > tolerance and off_c > off_t:
            failed.append(f"{where}{round(100 * p)}% coverage {100 * candidate[key]:.1f}: more than "
                          f"{round(100 * tolerance)} points from nominal and further than today's")
    return failed


def pooled_map_scores(depth_map, folds, ref, pool: list) -> dict:
    """The scores of a depth map (``calibration.QuantileCalibration`` with its cross-fitted ``folds``
    and training-view reference ``ref``) on a list of views' ``evaluation.DepthSamples``, as ``eval``
    pools them: coverage per level, the median 95% half-width, the 95% interval score and CRPS (all /
    depth), the point count, and the depth Spearman of |error| against the calibrated std pooled and
    averaged over the views (those with more than 10 points)."""
    cal = RunCalibration(depth=depth_map, points="held-out", training_depth=ref, depth_folds=folds)
    samples = pool_depth_samples(pool)
    iv = calibrated_depth_scores(samples, cal)["intervals"]

    def std_of(s):
        return depth_map.calibrated_std(s.std_raw, s.violation, s.pred, s.edge, parallax=s.parallax)

    per_view = [spearmanr(np.abs(s.pred - s.gt), std_of(s)).correlation for s in pool if s.gt.size > 10]
    return {"coverage": {M.level_name(p): float(iv[f"coverage_{M.level_name(p)}"]) for p in M.INTERVAL_LEVELS},
            "halfwidth_median_95": float(iv["halfwidth_median_95"]), "interval_score_95": float(iv["interval_score_95"]),
            "crps": float(iv["crps"]), "points": int(samples.gt.size),
            "spearman": float(spearmanr(np.abs(samples.pred - samples.gt), std_of(samples)).correlation),
            "spearman_per_view": float(np.mean(per_view))}
