"""Do depth errors grow with how far a view looks from the training views, and do the calibration
renders' points see the same errors as the test views'?

Study 33's analysis left an inference to check: the recalibration fitted on the views halfway
between training views over-covers the test views of sharp (per-cell) runs, as if the halfway
views erred more than the test views. For each run, at the capture points the map is fitted on
(held-out roles seen from the calibration views) and at the scored test-view points (as
``coverage_by_views.py``), it computes each rendered point's view angle: the smallest angle
between the rendering ray and the ray from any training camera to the same rendered point
(degrees). It reports, per bin of that angle (sextiles of both sets together), the median and 90th
percentile of |d - d*| / d and the coverage of the run's 68% and 95% intervals (the map's full std:
sqrt(sigma^2 + (beta e)^2 + (rho d)^2)), for the calibration points, the test points as the tables
score them (on the synthetic scene: its pixels) and the test views' SCORE capture points (the map's
kind of points) apart.

    python benchmarks/studies/error_by_view_angle.py --run today/1=RUN cell/1=RUN ... \\
        --out benchmarks/results/density_unit_study/error_by_view_angle

Renders only; decides nothing. Torch on 1 thread.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from scipy.special import ndtri

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import (parse_runs, photo_points, scored_points, standardised_at_points,  # noqa: E402
                           study_command, study_parser, write_study)

LEVELS = (0.6827, 0.95)
BINS = 6


def view_angles(points: np.ndarray, centres: np.ndarray, train_centres: np.ndarray) -> np.ndarray:
    """[N] degrees: for each point [N, 3] seen from its camera centre [N, 3], the smallest angle
    between that ray and the ray from any of the training centres [T, 3] to the point."""
    a = points - centres
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = points[:, None] - train_centres[None]
    b /= np.linalg.norm(b, axis=2, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.einsum("nc,ntc->nt", a, b).max(axis=1), -1.0, 1.0)))


def full_std(cal, sigma: np.ndarray, violation: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The map's std before s(p): sqrt(sigma^2 + (beta e)^2 + (rho d)^2) (no std floor or edge term)."""
    beta = cal.free_space_weight if cal.free_space else 0.0
    return np.sqrt(sigma ** 2 + (beta * violation) ** 2 + (cal.relative_floor * depth) ** 2)


def binned(angle, err, depth, std, bounds, edges) -> list[dict]:
    rel, z = np.abs(err) / depth, np.abs(err) / std
    which = np.clip(np.digitize(angle, edges[1:-1]), 0, len(edges) - 2)
    rows = []
    for i in range(len(edges) - 1):
        m = which == i
        if m.sum() == 0:
            continue
        rows.append({"angle": [float(edges[i]), float(edges[i + 1])], "points": int(m.sum()),
                     "rel_median": float(np.median(rel[m])), "rel_p90": float(np.quantile(rel[m], 0.9)),
                     "coverage": [float(np.mean(z[m] <= b)) for b in bounds]})
    rows.append({"angle": "all", "points": int(len(z)), "angle_median": float(np.median(angle)),
                 "rel_median": float(np.median(rel)), "rel_p90": float(np.quantile(rel, 0.9)),
                 "coverage": [float(np.mean(z <= b)) for b in bounds]})
    return rows


def study_run(run_dir: Path, seed: int) -> dict:
    from stochastic_fields.calibration import calibration_views, depth_calibration_renders, load_run_calibration
    from stochastic_fields.cameras import camera_to_world
    from stochastic_fields.capture_points import FIT, SCORE, block_roles, load_capture_points
    from stochastic_fields.free_space import free_space_violation, rendered_points
    from stochastic_fields.io_utils import read_json
    from stochastic_fields.trainer import load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    calibration = load_run_calibration(run_dir)
    cal, ref = calibration.depth, calibration.training_depth
    capture = load_capture_points(dataset)
    centres_all = camera_to_world(dataset.cameras).double()[:, :3, 3].numpy()
    train_centres = centres_all[np.asarray(dataset.train_indices)]
    bounds = cal.scale_at(np.asarray(LEVELS)) * ndtri((1.0 + np.asarray(LEVELS)) / 2.0)

    def measured(centres, xyz, gt, depth, sigma, violation=None) -> dict:
        """Angles, errors, depths and the map's full std of points ``xyz`` rendered from ``centres``
        at camera z ``depth`` (truth ``gt``), raw std ``sigma`` (the free-space violation computed
        when not given)."""
        X = rendered_points(centres, xyz, gt, depth)
        if violation is None:
            violation = free_space_violation(X, ref) if ref is not None else np.zeros(len(X))
        return {"angle": view_angles(X, centres, train_centres), "err": gt - depth, "depth": depth,
                "std": full_std(cal, sigma, violation, depth)}

    # the calibration renders: held-out capture points seen from the halfway views, as the map is fitted
    fit = depth_calibration_renders(model, dataset, seed=seed, points="held-out", free_space=ref)
    fit_centres = camera_to_world(calibration_views(dataset)[0]).double()[:, :3, 3].numpy()[fit["view"]]
    cal_set = measured(fit_centres, capture.xyz[fit["index"]], fit["depth"] + fit["err"], fit["depth"],
                       fit.get("std_raw", fit["std"]), fit.get("violation", np.zeros(len(fit["err"]))))
    # the test views' scored points (as the tables score them)
    test_views = [int(name.split("_")[-1]) for name in read_json(run_dir / "eval" / "metrics.json", "metrics")["views"]]
    s = scored_points(run_dir, model, dataset, capture, test_views, capture.roles != FIT, seed)
    scored = (block_roles(s["xyz"], capture) == SCORE) if capture.source == "synthetic" else capture.roles[s["index"]] == SCORE
    test_set = measured(centres_all[s["view"]][scored], s["xyz"][scored], s["gt"][scored], s["depth_mean"][scored],
                        s["std"][scored])
    # the test views' SCORE capture points (the map's kind of points; on LLFF the same as "test")
    q = standardised_at_points(model, dataset.cameras, dataset.near, dataset.far,
                               photo_points(dataset, capture, test_views, SCORE), seed)
    point_set = measured(centres_all[q["view"]], capture.xyz[q["index"]], q["gt"], q["depth_mean"], q["std"])
    edges = np.quantile(np.concatenate([cal_set["angle"], test_set["angle"]]), np.linspace(0.0, 1.0, BINS + 1))
    return {"run": str(run_dir), "relative_floor": cal.relative_floor,
            "free_space_weight": cal.free_space_weight if cal.free_space else 0.0,
            **{name: binned(x["angle"], x["err"], x["depth"], x["std"], bounds, edges)
               for name, x in (("calibration", cal_set), ("test", test_set), ("test points", point_set))}}


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "error_by_view_angle", "Trained, evaluated and calibrated runs.", metavar="LABEL=RUN_DIR")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    runs = parse_runs(p, args.run, required="eval/metrics.json")
    command = study_command("error_by_view_angle.py", argv)
    results = {"command": command, "levels": list(LEVELS), "torch_threads": 1, "runs": {}}
    lines = ["# Depth errors by the view angle to the nearest training ray", "", f"Command: `{command}`", "",
             "Per run: the map's rho and beta; per angle bin (degrees, sextiles of both point sets), the points, "
             "median / 90th percentile of |d - d*| / d, and the coverage of the run's 68% / 95% intervals, at the "
             "calibration renders' points (views halfway between training views), at the test views' scored points "
             "(as the tables score them: on the synthetic scene its pixels) and at the test views' SCORE capture points.", ""]
    for label, run in runs.items():
        print(f"{label}: {run}", flush=True)
        res = results["runs"][label] = study_run(run, args.seed)
        lines += [f"## {label}", "", f"Run `{res['run']}`: rho {res['relative_floor']:.4f}, beta {res['free_space_weight']:.3f}.", "",
                  "| points | angle (deg) | n | median rel err | p90 rel err | cov 68 | cov 95 |", "|---|---|---|---|---|---|---|"]
        for name in ("calibration", "test", "test points"):
            for row in res[name]:
                angle = (f"all (median {row['angle_median']:.1f})" if row["angle"] == "all"
                         else f"{row['angle'][0]:.1f}-{row['angle'][1]:.1f}")
                lines.append(f"| {name} | {angle} | {row['points']} | {100 * row['rel_median']:.2f}% | "
                             f"{100 * row['rel_p90']:.2f}% | {100 * row['coverage'][0]:.1f} | {100 * row['coverage'][1]:.1f} |")
        lines.append("")
    text = "\n".join(lines)
    write_study(args.out, results, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
