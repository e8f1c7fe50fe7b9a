"""Study 19: sharp depth intervals. Which predictive distribution and which calibration data give
intervals that hold at every level AND are narrow (docs/uncertainty.md, "Study 19")?

Renders only, on trained runs of the tables' runner (S-NeRF default and the deep ensemble, same
scene, same seed). For each run the capture points are rendered through a stencil of rays (the
point's own pixel and 8 directions at 2 and 4 pixels) from three sets of views:
- calibration views (halfway between neighbouring training views) with each choice of render
  bounds (widest, interpolated), CALIBRATE-role points only: what every candidate is fitted on;
- the unused photos (test photos the tables do not score), SCORE-role points: what the rule
  decides on (no scored test view is looked at to choose);
- the scored test views, SCORE-role points: what is reported.
Candidates, one factor at a time from today's (Gaussian, level map s(p), widest bounds):
recalibration of the whole CDF by its PIT values (predictive.PitCalibration), the calibration
views' bounds, and a neighbourhood mixture (predictive.neighbourhood_weights: the pixel's own
Gaussian keeps half the mass, the stencil's rays share the rest). Scores: metrics.interval_sharpness.

    python benchmarks/studies/depth_interval_study.py --run fern=RUNS/fern/snerf_default \\
        --run flower=RUNS/flower/snerf_default --ensemble fern=RUNS/fern/ensemble \\
        --ensemble flower=RUNS/flower/ensemble --out benchmarks/results/depth_interval_study
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (QuantileCalibration, calibration_views, pair_visible_points,
                                          render_at_points)
from stochastic_fields.capture_points import CALIBRATE, SCORE, load_capture_points, sparse_depth_for_role
from stochastic_fields.predictive import (PitCalibration, mixture_cdf, neighbourhood_weights,
                                          recalibrated_mixture_quantiles)
from stochastic_fields.sparse_depth import project_sparse_depth
from stochastic_fields.trainer import load_trained_model
from stochastic_fields.view_maps import OPACITY_MASK
from stochastic_fields_bench.budget import BenchmarkSettings, select_views

#: Stencil radii (pixels) and directions of the neighbourhood rays.
RADII: tuple[float, ...] = (2.0, 4.0)
DIRECTIONS: int = 8
#: The pixel's own share of a neighbourhood mixture.
CENTRE_WEIGHT: float = 0.5
#: Most unused-photo points rendered per scene (a seeded subsample beyond it).
MAX_UNUSED_POINTS: int = 8000
#: The rule, fixed before the unused photos were rendered: a candidate replaces today's only if its
#: coverage at 50, 68, 90 and 95% holds within COVERAGE_TOLERANCE of nominal on the unused photos of
#: every scene; among those the lowest mean 95% interval score / depth over the scenes wins.
COVERAGE_TOLERANCE: float = 0.05
RULE_LEVELS: tuple[float, ...] = (0.5, 0.682689492137086, 0.9, 0.95)


def stencil() -> np.ndarray:
    angles = np.arange(DIRECTIONS) * 2 * np.pi / DIRECTIONS
    rings = [np.stack([r * np.cos(angles), r * np.sin(angles)], 1) for r in RADII]
    return np.concatenate([np.zeros((1, 2))] + rings)


def render_stencil(model, cams, near, far, sparse: dict, seed: int = 0) -> dict[str, np.ndarray]:
    """Depth mean, total std and opacity [N, S] (and the points' depths "gt" [N]) at the stencil
    around every point of {view: SparseDepth}: each point repeated once per stencil offset, rendered
    by ``calibration.render_at_points``."""
    offsets = stencil()
    width, height = float(cams.width.reshape(-1)[0]), float(cams.height.reshape(-1)[0])
    moved = {}
    for v, sd in sparse.items():
        uv = (sd.uv[:, None, :] + offsets[None]).reshape(-1, 2)
        uv = np.stack([np.clip(uv[:, 0], 0.01, width - 0.01), np.clip(uv[:, 1], 0.01, height - 0.01)], 1)
        moved[v] = replace(sd, uv=uv, depth=np.repeat(sd.depth, len(offsets)))
    device = next(model.parameters()).device
    r = render_at_points(model, cams, near, far, moved, generator=torch.Generator(device=device).manual_seed(seed))
    if not len(r["gt"]):
        raise ValueError("no points to render")
    out = {k: r[k].reshape(-1, len(offsets)) for k in ("depth_mean", "depth_std", "opacity")}
    return {"gt": r["gt"].reshape(-1, len(offsets))[:, 0], "mean": out["depth_mean"], "std": out["depth_std"],
            "opacity": out["opacity"]}


def masked(r: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    keep = (r["opacity"][:, 0] > OPACITY_MASK) & (r["std"][:, 0] > 0) & np.isfinite(r["mean"][:, 0])
    return {k: v[keep] for k, v in r.items()}


def collect(run_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    """The renders of one run (module doc): {"cal_widest", "cal_interpolated", "unused", "test"}."""
    _, model, dataset = load_trained_model(run_dir)
    capture = load_capture_points(dataset)
    out = {}
    for bounds in ("widest", "interpolated"):
        cams, near, far, pairs = calibration_views(dataset, bounds=bounds)
        sparse = project_sparse_depth(cams, capture.xyz, range(len(pairs)), visible=pair_visible_points(
            capture, pairs, capture.roles == CALIBRATE), visibility_name="pair")
        out[f"cal_{bounds}"] = masked(render_stencil(model, cams, near, far, sparse))
    scored = select_views(list(dataset.test_indices), BenchmarkSettings())
    unused = [v for v in dataset.test_indices if v not in scored]
    for name, views in (("unused", unused), ("test", scored)):
        sparse = sparse_depth_for_role(dataset, capture, views, SCORE)
        r = masked(render_stencil(model, dataset.cameras, dataset.near, dataset.far, sparse))
        if name == "unused" and len(r["gt"]) > MAX_UNUSED_POINTS:
            keep = np.sort(np.random.default_rng(0).choice(len(r["gt"]), MAX_UNUSED_POINTS, replace=False))
            r = {k: v[keep] for k, v in r.items()}
        out[name] = r
    return out


def collect_cached(run_dir: Path, cache: Path) -> dict[str, dict[str, np.ndarray]]:
    """``collect``, stored in ``cache`` (npz) and read from it when present: a re-run (another scene
    added, the report rewritten) renders nothing twice."""
    if cache.is_file():
        with np.load(cache) as f:
            out: dict = {}
            for key in f.files:
                group, name = key.split("/", 1)
                out.setdefault(group, {})[name] = f[key]
            return out
    out = collect(run_dir)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **{f"{g}/{k}": v for g, r in out.items() for k, v in r.items()})
    tmp.replace(cache)
    return out


def components(r: dict[str, np.ndarray], shape: str):
    """(means, stds, weights) [N, M] of a candidate's distribution F."""
    if shape == "gaussian":
        return r["mean"][:, :1], r["std"][:, :1], np.ones((len(r["gt"]), 1))
    rays = {"neighbourhood r2": 1 + DIRECTIONS, "neighbourhood r4": 1 + 2 * DIRECTIONS}[shape]
    return (r["mean"][:, :rays], np.maximum(r["std"][:, :rays], 1e-9),
            neighbourhood_weights(r["opacity"][:, :rays], CENTRE_WEIGHT, OPACITY_MASK))


#: name -> (distribution F, recalibration, calibration bounds)
CANDIDATES: dict[str, tuple[str, str, str]] = {
    "today: Gaussian, s(p), widest": ("gaussian", "level map", "widest"),
    "Gaussian, s(p), interpolated": ("gaussian", "level map", "interpolated"),
    "Gaussian, PIT, widest": ("gaussian", "pit", "widest"),
    "Gaussian, PIT, interpolated": ("gaussian", "pit", "interpolated"),
    "neighbourhood r2, PIT, widest": ("neighbourhood r2", "pit", "widest"),
    "neighbourhood r2, PIT, interpolated": ("neighbourhood r2", "pit", "interpolated"),
    "neighbourhood r4, PIT, widest": ("neighbourhood r4", "pit", "widest"),
    "neighbourhood r4, PIT, interpolated": ("neighbourhood r4", "pit", "interpolated"),
}


def quantile_fn(data: dict, candidate: tuple[str, str, str], target: str):
    shape, recal, bounds = candidate
    cal = data[f"cal_{bounds}"]
    r = data[target]
    if recal == "level map":
        m = QuantileCalibration.fit_errors(np.abs(cal["mean"][:, 0] - cal["gt"]), cal["std"][:, 0], quantity="depth_std")
        return lambda t: M.gaussian_quantiles(r["mean"][:, 0], m.calibrated_std(r["std"][:, 0]), t, m.relative_scale)
    pit = PitCalibration.fit(mixture_cdf(cal["gt"], *components(cal, shape)))
    comps = components(r, shape)
    return lambda t: recalibrated_mixture_quantiles(t, *comps, pit)


def score(gt: np.ndarray, fn) -> dict:
    iv = M.interval_sharpness(gt, fn)
    return {k: v for k, v in iv.items() if k != "halfwidth"}, iv


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="SCENE=RUN", help="S-NeRF run of a scene.")
    p.add_argument("--ensemble", action="append", default=[], metavar="SCENE=RUN", help="Deep-ensemble run of a scene.")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    runs = dict(a.split("=", 1) for a in args.run)
    ensembles = dict(a.split("=", 1) for a in args.ensemble)
    results: dict = {"command": "python benchmarks/studies/depth_interval_study.py " + " ".join(sys.argv[1:] if argv is None else argv),
                     "rule": f"coverage at {[round(x, 3) for x in RULE_LEVELS]} within {COVERAGE_TOLERANCE} on the "
                             "unused photos of every scene; then the lowest mean 95% interval score / depth there",
                     "scenes": {}}
    from stochastic_fields.plots import plot_interval_reliability

    for scene, run in runs.items():
        data = collect_cached(Path(run), args.out / f"renders_{scene}_snerf.npz")
        res: dict = {"points": {k: int(len(v["gt"])) for k, v in data.items()}}
        curves = {}
        for name, cand in CANDIDATES.items():
            res[name] = {}
            for target in ("unused", "test"):
                res[name][target], iv = score(data[target]["gt"], quantile_fn(data, cand, target))
                if target == "test" and name in (next(iter(CANDIDATES)), "neighbourhood r4, PIT, interpolated"):
                    curves[name] = iv
            print(f"[{scene}] {name}: unused IS95 {res[name]['unused']['interval_score_95']:.3f}, test IS95 "
                  f"{res[name]['test']['interval_score_95']:.3f}", flush=True)
        if scene in ensembles:
            ens = collect_cached(Path(ensembles[scene]), args.out / f"renders_{scene}_ensemble.npz")
            for target in ("unused", "test"):
                r = ens[target]
                res.setdefault("D. Ens. (Gaussian, as the tables)", {})[target], iv = score(
                    r["gt"], lambda t, r=r: M.gaussian_quantiles(r["mean"][:, 0], r["std"][:, 0], t))
                res.setdefault("D. Ens., s(p), widest", {})[target], _ = score(
                    r["gt"], quantile_fn(ens, CANDIDATES["today: Gaussian, s(p), widest"], target))
            curves["D. Ens."] = iv
        plot_interval_reliability(args.out / f"{scene}_test.png", curves, title=f"{scene}: scored test views")
        results["scenes"][scene] = res
        (args.out / "results.json").write_text(json.dumps(results, indent=2))
    results["decision"] = decide(results["scenes"])
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    (args.out / "README.md").write_text(report(results))
    print(results["decision"])


def decide(scenes: dict) -> str:
    ok = []
    for name in CANDIDATES:
        holds = all(abs(s[name]["unused"][f"coverage_{M.level_name(p)}"] - p) <= COVERAGE_TOLERANCE
                    for s in scenes.values() for p in RULE_LEVELS)
        if holds:
            ok.append((float(np.mean([s[name]["unused"]["interval_score_95"] for s in scenes.values()])), name))
    if not ok:
        return "no candidate holds every level within the tolerance on the unused photos: today's stays"
    best = min(ok)[1]
    return f"{best} (lowest mean 95% interval score / depth among {len(ok)} candidates that hold)"


def report(results: dict) -> str:
    lines = ["# Study 19: sharp depth intervals", "", f"Command: `{results['command']}`", "",
             f"Rule (fixed before the unused photos were rendered): {results['rule']}.", "",
             f"Decision: **{results['decision']}**", ""]
    names = [M.level_name(p) for p in M.INTERVAL_LEVELS]
    for scene, res in results["scenes"].items():
        lines += [f"## {scene} (points: {res['points']})", ""]
        for target in ("unused", "test"):
            lines += [f"### {'unused photos (decides)' if target == 'unused' else 'scored test views (reported)'}", "",
                      "| candidate | coverage " + "/".join(names) + " | median 95% half-width / depth | p90 | "
                      "IS 68% / depth | IS 95% / depth | CRPS / depth |", "|---|---|---|---|---|---|---|"]
            for name, r in res.items():
                if name == "points":
                    continue
                s = r[target]
                lines.append(f"| {name} | " + "/".join(f"{100 * s[f'coverage_{n}']:.1f}" for n in names)
                             + f" | {100 * s['halfwidth_median_95']:.1f}% | {100 * s['halfwidth_p90_95']:.0f}% | "
                             f"{s['interval_score_68']:.3f} | {s['interval_score_95']:.3f} | {s['crps']:.4f} |")
            lines.append("")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
