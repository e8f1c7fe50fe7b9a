"""Does density noise shared along each ray at render time rank the depth errors better? (decides nothing)

S-NeRF draws each sample's density noise independently (the paper's mean-field posterior), so along a
ray the K trajectories' expected depths average many independent draws and disagree little (docs/
uncertainty.md: the epistemic part is about 40 times smaller than the termination spread at observed
surfaces). Issue 36 names noise correlated along the ray as a factor. Study 1 trained with it
(``render.shared_noise``: one eps per ray and draw) and lost 1.5-2.7 dB. This asks the cheaper
question: on a model trained as today, do trajectories drawn with shared noise at render time, whose
whole ray's density rises or falls together (a floater with an uncertain density is there in one
trajectory and gone in the next), give a depth spread that ranks today's depth errors better?

For each run (today's S-NeRF at the tables' budget) and each of its paper split's validation photos
(``tables_cap_study.validation_views``: trained on by no run, scored by no table), the rays through
the photo's SCORE capture points are rendered twice with the same K and seed: independent noise
(today) and shared noise. The errors are today's (|independent mean - point depth|, opacity > 0.5);
each candidate std is ranked against them by Spearman per photo (raw stds, before any map):
today's total, the shared render's total and epistemic part, today's total plus the shared
epistemic variance, and the shift of the mean. The shared render's own depth error is reported too.

    python benchmarks/studies/shared_noise_ranking_analysis.py --run fern:12=RUN --run flower:12=RUN ... \
        --out benchmarks/results/shared_noise_ranking_analysis

RUN: a run folder of ``benchmarks/eval_tables.py --methods snerf_default --seed SEED`` (SCENE/snerf_default).
One torch thread. OUT/study.md and OUT/results.json hold the per-run and mean rows.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "benchmarks" / "studies"))

from stochastic_fields.capture_points import rays_through_points, score_sparse_depth  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402
from stochastic_fields.view_maps import OPACITY_MASK  # noqa: E402
from study_helpers import analyse_each, labelled_run_parser  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402

#: Candidate std (name, from the independent render "a" and the shared render "b": variance [N]).
CANDIDATES: tuple[tuple[str, object], ...] = (
    ("today: total (independent)", lambda a, b: a["depth_var_total"]),
    ("shared: total", lambda a, b: b["depth_var_total"]),
    ("shared: epistemic", lambda a, b: b["depth_var_epistemic"]),
    ("today's total + shared epistemic", lambda a, b: a["depth_var_total"] + b["depth_var_epistemic"]),
    ("mean shift, shared - independent", lambda a, b: (a["depth_mean"] - b["depth_mean"]) ** 2),
)


def render_points(model, dataset, sparse: dict, view: int, *, shared: bool, seed: int) -> dict[str, np.ndarray]:
    """Camera-z depth mean, variances (epistemic, total) and opacity [N] of the rays through ``view``'s
    SCORE points, with independent or shared noise (the model's own settings otherwise)."""
    model.render_settings = dataclasses.replace(model.render_settings, shared_noise=shared)
    rays, gt = rays_through_points(dataset.cameras, dataset.near, dataset.far, {view: sparse[view]})
    with torch.no_grad():
        maps = model.render_view(rays.reshape(1, len(gt)), model.render_options(),
                                 generator=torch.Generator().manual_seed(seed))
    z = maps["z_scale"].double().reshape(-1).numpy()
    out = {"gt": gt, "opacity": maps["opacity"].double().reshape(-1).numpy(),
           "depth_mean": maps["depth_mean"].double().reshape(-1).numpy() * z}
    for key in ("depth_var_epistemic", "depth_var_total"):
        out[key] = maps[key].double().reshape(-1).numpy() * z * z
    return out


def analyse_run(scene: str, run: Path, *, seed: int = 0) -> dict:
    """Per validation photo and mean over photos: each candidate's Spearman against today's errors,
    and the median relative error and epistemic std of both renders."""
    _, model, dataset = load_trained_model(run)
    views = validation_views(scene)
    sparse = score_sparse_depth(dataset, views)
    per_view: dict[str, list[float]] = {}
    for view in views:
        a = render_points(model, dataset, sparse, view, shared=False, seed=seed)
        b = render_points(model, dataset, sparse, view, shared=True, seed=seed)
        keep = (a["opacity"] > OPACITY_MASK) & np.isfinite(a["depth_mean"]) & np.isfinite(b["depth_mean"])
        err = np.abs(a["gt"] - a["depth_mean"])[keep]
        for name, variance in CANDIDATES:
            per_view.setdefault(name, []).append(float(spearmanr(err, np.sqrt(variance(a, b)[keep])).correlation))
        gt = a["gt"][keep]
        per_view.setdefault("median abs error / depth, independent", []).append(float(np.median(err / gt)))
        per_view.setdefault("median abs error / depth, shared", []).append(
            float(np.median(np.abs(b["gt"] - b["depth_mean"])[keep] / gt)))
        for label, r in (("independent", a), ("shared", b)):
            per_view.setdefault(f"median epistemic std / depth, {label}", []).append(
                float(np.median(np.sqrt(r["depth_var_epistemic"][keep]) / gt)))
        per_view.setdefault("points per photo", []).append(float(keep.sum()))
    return {"views": views, "per_view": per_view, "mean": {k: float(np.mean(v)) for k, v in per_view.items()}}


def report(results: dict[str, dict]) -> str:
    names = list(next(iter(results.values()))["mean"])
    lines = ["# Shared noise at render time: does its depth spread rank today's depth errors?", "",
             "Command: " + " ".join(["python benchmarks/studies/shared_noise_ranking_analysis.py"] + sys.argv[1:]), "",
             "Means over each run's validation photos (Spearman of |error| against the std, per photo, raw stds; "
             "errors and opacity mask from today's independent-noise render, K and seed the same for both renders).", "",
             "| quantity | " + " | ".join(results) + " |", "|---|" + "---|" * len(results)]
    for name in names:
        digits = 0 if name == "points per photo" else 4
        lines.append(f"| {name} | " + " | ".join(f"{r['mean'][name]:.{digits}f}" for r in results.values()) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return analyse_each(labelled_run_parser(__doc__, "SCENE:SEED=FOLDER"), argv,
                        lambda label, folder: analyse_run(label.split(":")[0], folder), report,
                        lambda label, result: ", ".join(f"{k} {v:.3f}" for k, v in result["mean"].items()
                                                        if k != "points per photo"))

if __name__ == "__main__":
    raise SystemExit(main())
