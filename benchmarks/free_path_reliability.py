"""Are the free-space answers honest? P(segment free) against what the held-out photos show.

A planner asks ``free-path`` whether a straight segment is free, and reads P(depth > d) from the
pixels ``export`` writes. Both are probabilities of the same kind of event, and on a pixel's own ray
they are the probability of the same event: the segment from the ray's near point to camera depth
d is free exactly when the pixel's surface lies beyond d. This benchmark asks them that question
where the answer is known.

For every run, a sample of the capture points of the SCORE role seen from the run's test photos
(photos no training and no map saw; at most ``--points`` per run, seeded), at true camera depth y
along the photo's pixel ray, and each margin m of ``--margins``:
- the segment to camera depth (1 - m) y is free (outcome 1: the photo sees the point, so nothing
  stands in front of it),
- the segment to (1 + m) y is blocked (outcome 0: it runs through the surface the point lies on).
Each segment gets two answers:
- *pixel*: P(depth > d) of the pixel's recalibrated predictive distribution (the run's
  calibration.json; what ``export --free-space-thresholds`` writes,
  ``products.free_space.predictive_prob_depth_greater``);
- *free-path*: the share of K density trajectories whose transmittance along the segment exceeds
  the level (``products.free_path.segment_free_probability``, the ``free-path`` command's answer,
  with its default draws, level and step).
Scored by ``metrics.event_reliability`` (Brier score, expected calibration error, accuracy, the
confident answers that were wrong), with their mean absolute disagreement on the same segments.
Segments that would start beyond their end (y (1 - m) below the near plane) are left out. Where the
run has a free-path map (``products.free_path_calibration``: isotonic, fitted on the calibration
views' held-out points, never on these photos), its answer is scored too.

Rule for the map (written before any map was fitted on a real run): ``free-path`` reports the
recalibrated answer by default, and ``train`` and ``calibrate`` fit the map, only if on every real
run the recalibrated answers' pooled Brier score is at most the model's + 0.005, and the pooled ECE,
averaged over the real runs, falls by at least a quarter.

    OMP_NUM_THREADS=1 python benchmarks/free_path_reliability.py --run capture/fern=RUN ... \\
        --out benchmarks/results/free_path_reliability
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stochastic_fields import metrics as M
from stochastic_fields.calibration import (edge_at_points, load_run_calibration, render_at_points,
                                           training_view_terms_at_points)
from stochastic_fields.capture_points import SCORE, load_capture_points, rays_through_points
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.plots import plot_event_reliability
from stochastic_fields.products.free_path import (FREE_PATH_NUM_DRAWS, FREE_TRANSMITTANCE_LEVEL, FloatField,
                                                  default_step, segment_free_probability)
from stochastic_fields.products.free_path_calibration import (FREE_PATH_CALIBRATION_MARGINS, known_segments,
                                                             load_free_path_calibration, subsample_points)
from stochastic_fields.products.free_space import predictive_prob_depth_greater
from stochastic_fields.products.occupancy_map import blocking_threshold, probability_density_exceeds, run_voxel_size
from stochastic_fields.trainer import load_trained_model
from stochastic_fields.view_maps import OPACITY_MASK

sys.path.insert(0, str(Path(__file__).resolve().parent / "studies"))
from study_helpers import photo_points  # noqa: E402

#: Most scored points per run.
MAX_POINTS: int = 1500


def measure(run_dir: Path, *, margins, limit: int, seed: int) -> dict:
    cfg, model, dataset = load_trained_model(run_dir)
    if not hasattr(model, "field"):
        raise ValueError(f"{run_dir}: free-path needs an S-NeRF run (a stochastic field)")
    calibration = load_run_calibration(run_dir)
    depth_map = None if calibration is None else calibration.depth
    path_map = load_free_path_calibration(run_dir)
    capture = load_capture_points(dataset)
    if capture is None:
        raise ValueError(f"{run_dir}: the scene has no capture points to score free space on")
    views = list(dataset.test_indices)
    sparse = subsample_points(photo_points(dataset, capture, views, SCORE), limit, seed)
    rays, gt = rays_through_points(dataset.cameras, dataset.near, dataset.far, sparse)  # the segments' rays
    r = render_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse,
                         generator=torch.Generator().manual_seed(seed))
    z = rays.z_scale.double().reshape(-1).numpy()
    mean, raw = r["depth_mean"], r["depth_std"]
    keep = (r["opacity"] > OPACITY_MASK) & np.isfinite(mean) & (raw > 0)
    violation = parallax = None
    if depth_map is not None:  # each pixel's violation and parallax angle, as export computes them (one pass)
        violation, parallax = training_view_terms_at_points(dataset.cameras, sparse, capture.xyz, r["gt"],
                                                            np.where(keep, mean, r["gt"]), calibration.training_depth,
                                                            free_space=depth_map.free_space,
                                                            parallax=depth_map.parallax_weight > 0.0)
    edge = None
    if depth_map is not None and depth_map.edge_weight > 0.0:  # each pixel's edge size, as export computes it
        edge = edge_at_points(model, dataset.cameras, dataset.near, dataset.far, sparse, mean, seed=seed)
    std = raw if depth_map is None else depth_map.calibrated_std(raw, violation, depth=mean, edge=edge,
                                                                 parallax=parallax)
    multiplier = None if depth_map is None else (lambda level: float(depth_map.relative_scale(level)))
    step = default_step(model, dataset)
    field = FloatField(model.field)
    shared = model.render_settings.shared_noise
    out = {"run": str(run_dir), "split": cfg.data.split, "views": views, "step": step, "shared_noise": bool(shared),
           "num_draws": FREE_PATH_NUM_DRAWS, "level": FREE_TRANSMITTANCE_LEVEL, "calibrated": depth_map is not None,
           "free_path_calibrated": path_map is not None, "points": int(keep.sum()), "margins": {}}
    t0 = time.perf_counter()
    pooled: dict[str, tuple[list, list]] = {}
    for m in margins:
        seg = known_segments(rays, torch.from_numpy(gt), [m])
        ok = keep[seg["ray"].numpy()]
        i, d, outcome = seg["ray"].numpy()[ok], seg["depth"].numpy()[ok], seg["outcome"].numpy()[ok]
        path = segment_free_probability(field, seg["starts"][ok], seg["ends"][ok], step=step, shared_noise=shared,
                                        generator=torch.Generator().manual_seed(seed))
        answers = {"pixel": predictive_prob_depth_greater(mean[i], std[i], d, multiplier),
                   "free-path (model)": path.probability.numpy()}
        if path_map is not None:
            answers["free-path (recalibrated)"] = path_map(answers["free-path (model)"])
        row = {k: {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv)
                   for kk, vv in M.event_reliability(p, outcome).items()} for k, p in answers.items()}
        row["disagreement"] = {k: float(np.mean(np.abs(answers["pixel"] - p))) for k, p in answers.items() if k != "pixel"}
        row["segments"] = int(len(d))
        out["margins"][str(m)] = row
        for k, p in answers.items():
            pooled.setdefault(k, ([], []))
            pooled[k][0].append(p)
            pooled[k][1].append(outcome)
    out["occupancy"] = voxel_events(model, dataset, rays.origins.double(), rays.directions.double(),
                                    torch.from_numpy(gt / z), margins)
    out["seconds"] = time.perf_counter() - t0
    out["pooled"] = {k: M.event_reliability(np.concatenate(p), np.concatenate(o)) for k, (p, o) in pooled.items()}
    return out


def voxel_events(model, dataset, origins, dirs, t_true, margins) -> dict:
    """The occupancy map's answers (``occupancy``'s default voxel size and threshold, P at the voxel
    centre) for the voxel holding each point (outcome 1, a surface passes through it) and the voxel
    at (1 - m) of the way to it (outcome 0), where that voxel lies inside the region and at least
    two voxels from the point's own (Chebyshev distance of their indices)."""
    vs = run_voxel_size(model, dataset)
    tau = blocking_threshold(vs)
    point = origins + t_true[:, None] * dirs
    key_point = torch.floor(point / vs)
    keys, outcome = [key_point], [torch.ones(len(point), dtype=torch.float64)]
    for m in margins:
        key = torch.floor((origins + (1.0 - m) * t_true[:, None] * dirs) / vs)
        apart = (key - key_point).abs().amax(-1) >= 2
        keys.append(key[apart])
        outcome.append(torch.zeros(int(apart.sum()), dtype=torch.float64))
    centres = (torch.cat(keys) + 0.5) * vs
    outcome = torch.cat(outcome)
    inside = model.region.contains(centres.float())
    with torch.no_grad():
        loc, scale = model.field.density_params(centres[inside].float())
    p = probability_density_exceeds(loc.double(), scale.double(), tau).numpy()
    r = M.event_reliability(p, outcome[inside].numpy())
    r = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
    r.update(voxel_size=vs, density_threshold=tau, occupied=int(outcome[inside].sum()),
             free=int((outcome[inside] == 0).sum()))
    return r


#: The rule for the free-path map (module doc).
BRIER_SLACK: float = 0.005
ECE_GAIN: float = 0.25


def decide(results: dict) -> str:
    """The module doc's rule over the real runs (names not starting with "synthetic")."""
    real = {n: r["pooled"] for n, r in results["runs"].items() if not n.startswith("synthetic")}
    missing = [n for n, a in real.items() if "free-path (recalibrated)" not in a]
    if not real or missing:
        return "undecided: runs without a free-path map: " + ", ".join(missing or ["no real run"])
    worse = [f"{n}: Brier {a['free-path (model)']['brier']:.3f} -> {a['free-path (recalibrated)']['brier']:.3f}"
             for n, a in real.items()
             if a["free-path (recalibrated)"]["brier"] > a["free-path (model)"]["brier"] + BRIER_SLACK]
    ece_model = float(np.mean([a["free-path (model)"]["ece"] for a in real.values()]))
    ece_cal = float(np.mean([a["free-path (recalibrated)"]["ece"] for a in real.values()]))
    fails = worse + ([f"mean ECE falls only {ece_model:.3f} -> {ece_cal:.3f}"] if ece_cal > (1 - ECE_GAIN) * ece_model else [])
    verdict = "not taken: " + "; ".join(fails) if fails else "taken: the recalibrated answer is free-path's default"
    return f"{verdict} (mean ECE over the real runs {ece_model:.3f} -> {ece_cal:.3f})"


def report(results: dict) -> str:
    lines = ["# Free-space answers against the held-out photos", "", f"Command: `{results['command']}`", "",
             f"Rule for the free-path map (written before any map was fitted on a real run): on every real run the "
             f"recalibrated answers' pooled Brier score at most the model's + {BRIER_SLACK}, and the pooled ECE, averaged "
             f"over the real runs, down by at least {ECE_GAIN:.0%}. Decision: **{decide(results)}**", "",
             "Segments from a test photo's pixel ray's near point to (1 - m) times the true depth of a capture point of "
             "the SCORE role (free) and to (1 + m) times it (blocked); *pixel*: P(depth > d) of the recalibrated "
             "per-pixel distribution (`export`'s); *free-path (model)*: the share of density trajectories whose "
             "transmittance exceeds the level; *free-path (recalibrated)*: what `free-path` reports with the run's "
             "free_path_calibration.json (fitted on calibration views, never on these photos). Brier score (0 perfect, 0.25 a coin), ECE "
             "(10 bins), accuracy at 1/2, confident answers (P < 5% or > 95%) that were wrong. Each run's map was fitted "
             "before this benchmark ran, by `products.free_path_calibration.fit_free_path_calibration` (what `calibrate "
             "--free-path` and `train` call).", "",
             "| run | margin m | segments | answer | Brier / ECE / accuracy | confident answers wrong | mean "
             "disagreement with the pixel's |", "|---|---|---|---|---|---|---|"]
    for name, r in results["runs"].items():
        for m, row in r["margins"].items():
            for answer in (k for k in row if k not in ("segments", "disagreement")):
                a = row[answer]
                dis = row["disagreement"].get(answer)
                lines.append(f"| {name} | {float(m):.0%} | {row['segments']} | {answer} | {a['brier']:.3f} / "
                             f"{a['ece']:.3f} / {a['accuracy']:.3f} | {a['confident_wrong']} of {a['confident']} | "
                             + ("-" if dis is None else f"{dis:.3f}") + " |")
    lines += ["", "Pooled over the margins:", "", "| run | answer | Brier | ECE | confident answers wrong |",
              "|---|---|---|---|---|"]
    for name, r in results["runs"].items():
        for answer, a in r["pooled"].items():
            lines.append(f"| {name} | {answer} | {a['brier']:.3f} | {a['ece']:.3f} | {a['confident_wrong']} of "
                         f"{a['confident']} |")
    lines += ["", "The occupancy map's answers (`occupancy`'s default voxel size and density threshold, P(density > "
              "threshold) at the voxel centre): the voxel holding each scored point (occupied) and the voxels at (1 - m) "
              "of the way to it (free; only those inside the region and two or more voxels from the point's). Its "
              "reliability depends on that mix of occupied and free voxels, which is the benchmark's choice:", "",
              "| run | voxel size | occupied / free voxels | Brier / ECE / accuracy | confident wrong |", "|---|---|---|---|---|"]
    for name, r in results["runs"].items():
        o = r["occupancy"]
        lines.append(f"| {name} | {o['voxel_size']:.4g} | {o['occupied']} / {o['free']} | {o['brier']:.3f} / "
                     f"{o['ece']:.3f} / {o['accuracy']:.3f} | {o['confident_wrong']} of {o['confident']} |")
    lines += ["", "Runs: " + "; ".join(f"{k}: `{r['run']}` ({r['split']} split, {r['points']} points, step "
                                      f"{r['step']:.4g}, K = {r['num_draws']}, {r['seconds']:.0f} s)"
                                      for k, r in results["runs"].items()), ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="NAME=RUN")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--margins", nargs="+", type=float, default=list(FREE_PATH_CALIBRATION_MARGINS))
    p.add_argument("--points", type=int, default=MAX_POINTS, help="Most scored points per run.")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads.")
    p.add_argument("--report-only", action="store_true", help="Only write README.md again from OUT/results.json.")
    args = p.parse_args(argv)
    if args.report_only:
        atomic_write_text(args.out / "README.md", report(json.loads((args.out / "results.json").read_text())))
        return
    if not all(0.0 < m < 1.0 for m in args.margins):
        p.error(f"--margins must lie in (0, 1), got {args.margins}")
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results: dict = {"command": "python benchmarks/free_path_reliability.py " + " ".join(sys.argv[1:] if argv is None else argv),
                     "threads": args.threads, "runs": {}}
    for spec in args.run:
        name, run = spec.split("=", 1)
        r = measure(Path(run), margins=args.margins, limit=args.points, seed=args.seed)
        plot_event_reliability(args.out / f"{name.replace('/', '_')}.png", {**r["pooled"], "occupancy": r["occupancy"]},
                               title=f"{name}: is the segment free? (test photos, margins pooled)")
        r["pooled"] = {k: {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv) for kk, vv in v.items()}
                       for k, v in r["pooled"].items()}
        results["runs"][name] = r
        print(f"[{name}] " + "; ".join(f"{k} Brier {a['brier']:.3f} ECE {a['ece']:.3f}" for k, a in r["pooled"].items()),
              flush=True)
        atomic_write_text(args.out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(args.out / "README.md", report(results))


if __name__ == "__main__":
    main()
