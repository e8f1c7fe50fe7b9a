"""Photos -> prepare -> train -> export, against the LLFF-posed run of the same budget (issue 17).

Runs (each step skipped when its output exists, so the script resumes):

    stochastic-fields prepare <fern>/images_8 (copied, no poses) --out OUT/scene
    stochastic-fields train --preset llff --train.iterations N --data.path OUT/scene     --out OUT/photos
    stochastic-fields train --preset llff --train.iterations N --data.path <fern>        --out OUT/llff
    stochastic-fields export --run OUT/<run> --views test --fuse --formats npz

and compares, on fern's test views (the same photos in both runs):

* the recovered cameras against LLFF's after a similarity alignment (Umeyama): centre error as a
  fraction of the largest distance between two cameras, rotation error in degrees;
* the exported depth maps: the photos run's depth times the alignment scale s against the LLFF
  run's, on pixels both render with opacity >= 0.5 (median and mean |relative difference|);
* each run against the SfM points of its own capture projected into the test views (sparse
  depth abs-rel; fern's LLFF points3D.bin for the LLFF run, the prepared model's for the other),
  and the photos run (times s) at LLFF's points;
* test PSNR of each run's exported colour mean against its own (undistorted) photos;
* the fused point clouds: the photos cloud mapped by (s, R, t) into LLFF's frame, median distance
  to the nearest LLFF point as a fraction of the median depth.

Usage: OMP_NUM_THREADS=1 python benchmarks/from_photos.py --out runs/from_photos [--iterations 300]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stochastic_fields.pose_alignment import pose_errors, similarity_align


#: Rendered colour mean in an exported view's npz.
COLOUR_KEY = "colour_mean"


def _cli(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "stochastic_fields.cli", *args], check=True)
    return time.perf_counter() - t0


def _sparse_abs_rel(dataset, export_dir: Path, views, scale: float = 1.0) -> float:
    """Mean |d - z| / z of a run's exported depth (times ``scale``) at the dataset's SfM points."""
    from stochastic_fields.sparse_depth import sparse_depth_for_dataset

    errs = []
    for v, sp in sparse_depth_for_dataset(dataset, views).items():
        npz = np.load(export_dir / "views" / f"view_{v:03d}.npz")
        d, op = sp.sample(npz["depth_mean"]) * scale, sp.sample(npz["opacity"])
        keep = op >= 0.5
        errs.append(np.abs(d[keep] - sp.depth[keep]) / sp.depth[keep])
    return float(np.mean(np.concatenate(errs)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fern", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
                    / "nerf_llff_data" / "fern")
    ap.add_argument("--out", type=Path, default=Path("runs/from_photos"))
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1, help="pycolmap threads")
    ap.add_argument("--noise-floor", action="store_true",
                    help="Also train the LLFF run with another seed: its depth difference to the first LLFF run is "
                         "what two runs of the same budget disagree by anyway.")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = args.out
    times: dict[str, float] = {}
    photos = out / "photos_in"
    if not photos.exists():
        shutil.copytree(args.fern / "images_8", photos)
    if not (out / "scene" / "transforms.json").exists():
        times["prepare"] = _cli("prepare", str(photos), "--out", str(out / "scene"), "--threads", str(args.threads),
                                "--quiet")
    runs = {"photos": (out / "scene", 0), "llff": (args.fern, 0)}
    if args.noise_floor:
        runs["llff_seed1"] = (args.fern, 1)
    for name, (data, seed) in runs.items():
        run = out / name
        if not (run / "checkpoint.pt").exists() or json.loads((run / "config.json").read_text())["train"]["iterations"] != args.iterations:
            # the paper's split, as when the committed results were made (the capture split is train's default now)
            times[f"train_{name}"] = _cli("train", "--preset", "llff", "--data.split", "paper",
                                          "--train.iterations", str(args.iterations),
                                          "--train.seed", str(seed), "--data.path", str(data), "--out", str(run),
                                          "--quiet")
        fuse = ["--fuse"] if seed == 0 else []
        if not (run / "export" / ("fused.ply" if fuse else "summary.json")).exists():
            times[f"export_{name}"] = _cli("export", "--run", str(run), "--views", "test", *fuse,
                                           "--formats", "npz", "--quiet")

    from scipy.spatial import cKDTree

    from stochastic_fields.cameras import camera_centres, camera_to_world
    from stochastic_fields.data import load_dataset

    import trimesh

    ours, llff = load_dataset(out / "scene"), load_dataset(args.fern)
    assert [p.name for p in ours.image_paths] == [p.name for p in llff.image_paths]
    ca, cb = camera_centres(ours.cameras).double().numpy(), camera_centres(llff.cameras).double().numpy()
    s, R, t = similarity_align(ca, cb)  # maps the photos run's depths and cloud into LLFF's frame below
    errors = pose_errors(*(camera_to_world(d.cameras).double().numpy() for d in (ours, llff)))
    centre_err, rot_err = errors["centre_error_max"], errors["rotation_error_max_deg"]

    views = list(llff.test_indices)

    def depth_difference(name: str, scale: float) -> dict:
        rel = []
        for v in views:
            a = np.load(out / name / "export" / "views" / f"view_{v:03d}.npz")
            b = np.load(out / "llff" / "export" / "views" / f"view_{v:03d}.npz")
            keep = (a["opacity"] >= 0.5) & (b["opacity"] >= 0.5)
            rel.append(np.abs(a["depth_mean"][keep] * scale - b["depth_mean"][keep]) / b["depth_mean"][keep])
        rel = np.concatenate(rel)
        return {"pixels": int(rel.size), "median_abs_rel": float(np.median(rel)), "mean_abs_rel": float(rel.mean()),
                "within_5pct": float((rel < 0.05).mean())}

    cloud_a = np.asarray(trimesh.load(out / "photos" / "export" / "fused.ply", process=False).vertices, dtype=np.float64)
    cloud_b = np.asarray(trimesh.load(out / "llff" / "export" / "fused.ply", process=False).vertices, dtype=np.float64)
    mapped = s * cloud_a @ R.T + t
    nn = cKDTree(cloud_b).query(mapped)[0]
    median_depth = float(np.median(np.concatenate([np.load(out / "llff" / "export" / "views" / f"view_{v:03d}.npz")
                                                   ["depth_mean"].ravel() for v in views])))
    psnr = {}
    for name, ds in (("photos", ours), ("llff", llff)):
        mse = [np.mean((np.load(out / name / "export" / "views" / f"view_{v:03d}.npz")[COLOUR_KEY]
                        - ds.images[v].numpy()) ** 2) for v in views]
        psnr[name] = float(np.mean([-10 * np.log10(m) for m in mse]))
    result = {
        "iterations": args.iterations,
        "registered": json.loads((out / "scene" / "prepare.json").read_text()),
        "alignment": {"scale": s, "centre_error_of_extent": centre_err, "rotation_error_deg": rot_err},
        "depth_photos_vs_llff": depth_difference("photos", s),
        "depth_llff_seed1_vs_llff": depth_difference("llff_seed1", 1.0) if args.noise_floor else None,
        "sparse_depth_abs_rel": {"photos": _sparse_abs_rel(ours, out / "photos" / "export", views),
                                 "llff": _sparse_abs_rel(llff, out / "llff" / "export", views),
                                 "photos_at_llff_points": _sparse_abs_rel(llff, out / "photos" / "export", views, s)},
        "fused_cloud": {"points_photos": int(len(cloud_a)), "points_llff": int(len(cloud_b)),
                        "median_nn_distance_rel_depth": float(np.median(nn) / median_depth)},
        "test_psnr_db": psnr,
        "seconds": {k: round(v, 1) for k, v in times.items()},
        "conventions": "depth = camera-z mean over K draws; photos-run depths times the similarity scale s "
                       "(camera centres, Umeyama) into LLFF units; pixels with opacity >= 0.5 in both runs",
    }
    (out / "comparison.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
