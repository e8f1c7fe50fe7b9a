"""Analysis: which loss for prepare's final bundle adjustment (the models decide; the references score).

``prepare`` keeps the mapper's model as it comes out of pycolmap's incremental or global mapping,
whose last global bundle adjustment uses a squared loss. This applies one more global adjustment to
each mapped model with each loss below and scores the cameras against the known poses of the same
photos (``benchmarks/registration.py``'s ``score``: a similarity fitted on the camera centres, then
the largest and median centre and rotation errors). ``none`` is the mapped model as it was.

The models are the registration benchmark's prepared scenes of commit 722b82d (before
``prepare`` refined them), copied to ``runs/registration_raw_722b82d`` before the benchmark was run
again::

    OMP_NUM_THREADS=1 python benchmarks/studies/robust_refinement_analysis.py \\
        --models runs/registration_raw_722b82d --out benchmarks/results/robust_refinement_analysis

Blender lego's poses are exact; LLFF's ``poses_bounds.npy`` are COLMAP's own from the full-size photos,
a reference with errors of its own.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from registration import reference_cameras  # noqa: E402
from study_helpers import study_command, write_study  # noqa: E402

from stochastic_fields.data.colmap import world_to_camera  # noqa: E402
from stochastic_fields.data.prepare import bundle_adjust  # noqa: E402
from stochastic_fields.pose_alignment import pose_errors  # noqa: E402

#: (label, pycolmap loss name or None, scale in pixels): the losses Ceres offers through pycolmap.
LOSSES = (("none", None, None), ("squared", "TRIVIAL", 1.0), ("soft_l1 1px", "SOFT_L1", 1.0),
          ("cauchy 0.5px", "CAUCHY", 0.5), ("cauchy 1px", "CAUCHY", 1.0), ("cauchy 2px", "CAUCHY", 2.0),
          ("huber 1px", "HUBER", 1.0))


def camera_to_world(rec) -> tuple[list[str], np.ndarray]:
    """(image names, camera-to-world [N, 4, 4] in OpenCV axes) of a pycolmap Reconstruction's posed images."""
    images = [rec.images[image_id] for image_id in sorted(rec.reg_image_ids())]
    return [im.name for im in images], np.array([np.linalg.inv(world_to_camera(im)) for im in images])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, required=True, help="SCENE/LABEL/sparse/0 folders (registration's --work)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/robust_refinement_analysis"))
    args = ap.parse_args()
    import pycolmap

    rows = []
    for model in sorted(p.parent.parent for p in args.models.glob("*/*/sparse/0")):
        scene = model.parent.name
        index, reference = reference_cameras(scene)
        mapped = pycolmap.Reconstruction(model / "sparse" / "0")
        for label, loss, scale in LOSSES:
            t0 = time.perf_counter()
            rec = mapped if loss is None else bundle_adjust(mapped, loss, scale, num_threads=1)[0]
            names, poses = camera_to_world(rec)
            errors = pose_errors(poses, reference[[index[n] for n in names]])
            rows.append({"scene": scene, "model": model.name, "loss": label, "seconds": time.perf_counter() - t0,
                         "registered": len(names), "photos": len(index),
                         "reprojection_px": float(rec.compute_mean_reprojection_error()), **errors})
            print(f"{scene} {model.name} {label}: rotation max {errors['rotation_error_max_deg']:.3f}", flush=True)
    lines = ["# The loss of a final global bundle adjustment", "", f"Command: `{study_command(Path(__file__).name, sys.argv[1:])}`",
             "", "| scene | model | loss | registered | centre err max / median (% extent) | rotation err max / median (deg) | "
             "reproj. px |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['model']} | {r['loss']} | {r['registered']}/{r['photos']} | "
                     f"{100 * r['centre_error_max']:.2f} / "
                     f"{100 * r['centre_error_median']:.2f} | {r['rotation_error_max_deg']:.2f} / "
                     f"{r['rotation_error_median_deg']:.2f} | {r['reprojection_px']:.3f} |")
    whole = [r for r in rows if r["registered"] == r["photos"]]  # a mapping that placed 3 of 34 photos compares nothing
    worst = {label: max(r["rotation_error_max_deg"] for r in whole if r["loss"] == label) for label, _, _ in LOSSES}
    lines += ["", "Largest rotation error over the models that registered every photo, per loss: "
              + ", ".join(f"{k} {v:.2f} deg" for k, v in worst.items()), ""]
    scenes = sorted({r["scene"] for r in whole})
    lines += ["Per scene, the largest rotation error (degrees) over its models that registered every photo:", "",
              "| loss | " + " | ".join(scenes) + " |", "|---|" + "---|" * len(scenes)]
    for label, _, _ in LOSSES:
        lines.append(f"| {label} | " + " | ".join(
            f"{max(r['rotation_error_max_deg'] for r in whole if r['loss'] == label and r['scene'] == sc):.2f}"
            for sc in scenes) + " |")
    lines.append("")
    write_study(args.out, {"command": study_command(Path(__file__).name, sys.argv[1:]), "rows": rows, "worst_rotation_deg": worst},
                "\n".join(lines))


if __name__ == "__main__":
    main()
