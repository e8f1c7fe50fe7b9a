"""Analysis: does the scene's unit of length change what S-NeRF reconstructs? (docs/studies.md,
"Analysis: the scene's unit of length"; renders and trainings, decides nothing).

The same photos in other units: the embedded scene generated with a seed (``--seeds``), then copied
with every length multiplied by each ``--scales`` factor (camera centres, near/far and the box hint
of ``transforms.json``, the depth maps; images and intrinsics untouched), so the copies differ only
in the number that measures a metre. Each copy trains with the demo preset (S-NeRF, 10 of 40
views, 2000 steps, training seed = scene seed) and is scored by ``stochastic-fields eval`` on its
30 test views; relative depth metrics do not depend on the unit, so the rows should agree. Beside
them: the median signed depth error (rendered - true, relative) on the ground and on the solids,
and the median peak of the mean-field density relu(mu) along rays through the solids, in 1 / the
scene's unit of length and per finest-level cell. Two runs at a time, one thread each::

    python benchmarks/studies/scene_scale_study.py --seeds 1 2 --scales 1 10 \\
        --work runs/scene_scale_study --out benchmarks/results/scene_scale_study
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from stochastic_fields.cameras import generate_rays, select_cameras
from stochastic_fields.data.synthetic import make_synthetic_scene
from stochastic_fields.trainer import load_trained_model

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared report helpers
from study_helpers import train_and_eval  # noqa: E402
from tables_cap_study import write_study  # noqa: E402

#: Ground pixels: true surface within this height of z = 0 (the ground plane), in the scene's units / scale.
GROUND_HEIGHT = 1e-3
#: Rays per view through the solids whose density profile is read (seeded).
PROFILE_RAYS = 100
#: The profile's half-length around the true depth and its number of points.
PROFILE_HALF_LENGTH, PROFILE_POINTS = 0.4, 801


def scaled_scene(base: Path, out: Path, scale: float) -> Path:
    """A copy of the generated scene ``base`` with every length times ``scale`` (atomic json last)."""
    if (out / "transforms.json").is_file():
        return out
    (out / "depth").mkdir(parents=True, exist_ok=True)
    if not (out / "images").exists():
        os.symlink((base / "images").resolve(), out / "images")
    meta = json.loads((base / "transforms.json").read_text())
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        c2w[:3, 3] *= scale
        frame["transform_matrix"] = c2w.tolist()
        np.save(out / frame["depth_file_path"], np.load(base / frame["depth_file_path"]) * np.float32(scale),
                allow_pickle=False)
    meta["near"], meta["far"] = meta["near"] * scale, meta["far"] * scale
    meta["aabb"] = (np.asarray(meta["aabb"]) * scale).tolist()
    tmp = out / "transforms.json.tmp"
    tmp.write_text(json.dumps(meta, indent=1))
    tmp.replace(out / "transforms.json")
    return out


def train_and_score(scene: Path, run: Path, seed: int) -> dict:
    m = train_and_eval(scene, run, seed, products=True)  # the views' npz files: the signed errors read them
    intervals = m["pooled"]["depth_intervals"]
    return {"psnr": m["summary"]["psnr"]["mean"], "abs_rel": m["pooled"]["depth"]["abs_rel"],
            "coverage": [intervals[f"coverage_{c}"] for c in (50, 68, 90, 95, 99)],
            "halfwidth_median_95": intervals["halfwidth_median_95"], "spearman": m["pooled"]["depth"]["spearman"]}


def signed_errors(run: Path, ds, scale: float) -> dict:
    """Median relative signed error (rendered - true) on the ground and on the solids, test views
    of the run's dataset ``ds``."""
    out = {"ground": [], "solids": []}
    for v in ds.test_indices:
        npz = np.load(run / "eval" / "views" / f"view_{v:03d}.npz")
        gt = ds.depths[v].numpy()
        rays = generate_rays(select_cameras(ds.cameras, [v]), ds.near[v], ds.far[v])
        points = (rays.origins + rays.directions / rays.z_scale[..., None] * torch.from_numpy(gt)[None, ..., None])[0]
        keep = (gt > 0) & (npz["opacity"] > 0.5)
        rel = (npz["depth_mean"] - gt) / np.where(gt > 0, gt, 1.0)
        ground = np.abs(points[..., 2].numpy()) < GROUND_HEIGHT * scale
        out["ground"].append(rel[keep & ground])
        out["solids"].append(rel[keep & ~ground])
    return {k: float(np.median(np.concatenate(v))) for k, v in out.items()}


def peak_density(model, ds, scale: float, seed: int) -> dict:
    """Median over rays through the solids of the peak of relu(mu) within PROFILE_HALF_LENGTH x scale
    of the true depth: per unit of length and per finest cell (times the cell's mean side)."""
    rng = np.random.default_rng(seed)
    peaks = []
    for v in ds.test_indices[:5]:
        gt = ds.depths[v].reshape(-1)
        rays = generate_rays(select_cameras(ds.cameras, [v]), ds.near[v], ds.far[v])
        o, d = rays.origins.reshape(-1, 3).float(), (rays.directions / rays.z_scale[..., None]).reshape(-1, 3).float()
        surface = o + d * gt[:, None]
        solids = np.flatnonzero((gt > 0).numpy() & (surface[:, 2].numpy() > 0.05 * scale))
        for i in rng.choice(solids, min(PROFILE_RAYS, len(solids)), replace=False):
            t = torch.linspace(float(gt[i]) - PROFILE_HALF_LENGTH * scale, float(gt[i]) + PROFILE_HALF_LENGTH * scale,
                               PROFILE_POINTS)
            with torch.no_grad():
                loc, _ = model.field.density_params(o[i][None] + d[i][None] * t[:, None])
            peaks.append(float(torch.relu(loc).max()))
    box = model.field.region.box
    cell = float(((box[1] - box[0]) / torch.tensor(model.field.resolution, dtype=box.dtype)).mean())
    return {"per_unit": float(np.median(peaks)), "per_cell": float(np.median(peaks)) * cell}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 10.0])
    ap.add_argument("--work", type=Path, default=Path("runs/scene_scale_study"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/scene_scale_study"))
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    jobs = []
    for seed in args.seeds:
        base = make_synthetic_scene(args.work / f"s{seed}" / "generated", seed=seed)
        for scale in args.scales:
            scene = scaled_scene(base, args.work / f"s{seed}" / f"x{scale:g}" / "scene", scale)
            jobs.append((seed, scale, scene, args.work / f"s{seed}" / f"x{scale:g}" / "run"))
    with ThreadPoolExecutor(args.jobs) as pool:
        scores = list(pool.map(lambda j: train_and_score(j[2], j[3], j[0]), jobs))
    rows = []
    for (seed, scale, _, run), s in zip(jobs, scores):
        _, model, ds = load_trained_model(run)  # once per row: both readings use it
        rows.append({"seed": seed, "scale": scale, **s, "median_signed": signed_errors(run, ds, scale),
                     "peak_density": peak_density(model, ds, scale, seed)})
    lines = ["# Analysis: the scene's unit of length", "",
             "The embedded scene (seeds " + ", ".join(map(str, args.seeds)) + ") with every length multiplied by a "
             "factor, S-NeRF with the demo preset, scored on the 30 test views. Command: the module docstring of "
             "`benchmarks/studies/scene_scale_study.py`.", "",
             "| seed | lengths x | PSNR dB | depth abs-rel | cov 50/68/90/95/99 | median 95% half-width / depth | "
             "depth Spearman | median signed error: ground / solids | peak density: per unit / per cell |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cov = "/".join(f"{100 * c:.1f}" for c in r["coverage"])
        lines.append(f"| {r['seed']} | {r['scale']:g} | {r['psnr']:.2f} | {r['abs_rel']:.4f} | {cov} | "
                     f"{100 * r['halfwidth_median_95']:.1f}% | {r['spearman']:.3f} | "
                     f"{100 * r['median_signed']['ground']:+.1f}% / {100 * r['median_signed']['solids']:+.1f}% | "
                     f"{r['peak_density']['per_unit']:.3g} / {r['peak_density']['per_cell']:.3g} |")
    write_study(args.out, {"rows": rows, "seeds": args.seeds, "scales": args.scales}, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
