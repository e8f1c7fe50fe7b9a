"""How well each prepared registration of an object's photos agrees with the photos' own verified matches.

A registration can place a few cameras in a mirrored pose and still report every photo registered
at a small reprojection error (docs/capture.md: lego on two threads). This script asks whether the
verified matches could tell: for each prepared scene it reads the COLMAP model, scores its cameras
against the known ones (``pose_alignment``; the turned cameras after a similarity refitted without
them, ``turned_cameras``, so that they do not bend it), and counts the
inlier matches of every verified two-view geometry in ``--database`` whose epipolar distance under
the scene's own relative pose exceeds ``--pixels`` (both scenes judged against the same matches).

    .venv/bin/python benchmarks/registration_consistency.py --object lego \\
        --scene mirrored=/tmp/lego/ex2 --scene right=/tmp/lego/raw --database /tmp/lego/ex2/colmap/database.db

Prints, per scene: the cameras more than 5 degrees or 5% of the extent off, and the contradicted
inliers in all and for each of those cameras. Decides nothing; docs/capture.md quotes one run.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

from stochastic_fields.pose_alignment import camera_errors, pose_errors, similarity_align

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/registration.py, beside this script
from registration import reference_cameras  # noqa: E402

#: A camera this far off (degrees, or fraction of the extent) counts as turned.
TURNED_DEG, TURNED_CENTRE = 5.0, 0.05
#: The similarity is fitted again on the cameras within this many times the median centre error.
FIT_SPREAD = 2.5


def world_to_camera(image) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) of a registered pycolmap image: x_cam = R x_world + t."""
    pose = image.cam_from_world()
    return pose.rotation.matrix(), np.asarray(pose.translation)


def read_cameras(scene: Path):
    """(pycolmap.Reconstruction, names [N], camera-to-world [N, 4, 4] OpenCV) of a prepared scene."""
    import pycolmap

    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model if model.is_dir() else scene / "sparse"))
    names, c2w = [], []
    for im in rec.images.values():
        R, t = world_to_camera(im)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R.T, -R.T @ t
        names.append(im.name)
        c2w.append(M)
    return rec, names, np.asarray(c2w)


def turned_cameras(names: list[str], c2w: np.ndarray, ref: np.ndarray) -> dict[str, tuple[float, float]]:
    """{name: (centre error / extent, rotation error degrees)} of the cameras off by more than the
    thresholds, after a similarity fitted on the others (five passes keeping the cameras within
    ``FIT_SPREAD`` times the median centre error of the cameras kept before)."""
    keep = np.ones(len(names), bool)
    for _ in range(5):
        similarity = similarity_align(c2w[keep, :3, 3], ref[keep, :3, 3])
        centre, angle = camera_errors(c2w, ref, similarity)
        keep = centre <= FIT_SPREAD * np.median(centre[keep]) + 1e-9
    return {n: (float(centre[i]), float(angle[i])) for i, n in enumerate(names)
            if angle[i] > TURNED_DEG or centre[i] > TURNED_CENTRE}


def sampson_distance(E: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Sampson distance [N] of matches p1 -> p2 ([N, 3] homogeneous normalised image points) to the
    essential matrix E [3, 3] (x2^T E x1 = 0): (p2^T E p1)^2 / (|(E p1)_xy|^2 + |(E^T p2)_xy|^2),
    square-rooted; times the focal length, pixels."""
    Ep1, Etp2 = p1 @ E.T, p2 @ E
    num = np.einsum("ij,ij->i", p2, Ep1) ** 2
    return np.sqrt(num / (Ep1[:, 0] ** 2 + Ep1[:, 1] ** 2 + Etp2[:, 0] ** 2 + Etp2[:, 1] ** 2))


def contradicted_inliers(rec, database: Path, pixels: float) -> tuple[collections.Counter, collections.Counter]:
    """({image: verified inliers with a registered partner}, {image: those whose epipolar distance
    under ``rec``'s relative pose exceeds ``pixels``}), each pair counted for both its images."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        name_of = {im.image_id: im.name for im in db.read_all_images()}
        images = {im.name: im for im in rec.images.values()}
        normalised = {}

        def rays(image_id: int):
            name = name_of[image_id]
            if name not in normalised:
                cam = rec.cameras[images[name].camera_id]
                xy = cam.cam_from_img(db.read_keypoints(image_id)[:, :2])
                normalised[name] = (np.c_[xy, np.ones(len(xy))], cam.mean_focal_length())
            return normalised[name]

        total, contradicted = collections.Counter(), collections.Counter()
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            i1, i2 = pycolmap.pair_id_to_image_pair(pair_id)
            n1, n2 = name_of[i1], name_of[i2]
            matches = np.asarray(geometry.inlier_matches)
            if n1 not in images or n2 not in images or len(matches) == 0:
                continue
            (R1, t1), (R2, t2) = world_to_camera(images[n1]), world_to_camera(images[n2])
            R = R2 @ R1.T
            t = t2 - R @ t1
            E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
            (x1, f), (x2, _) = rays(i1), rays(i2)
            bad = int((sampson_distance(E, x1[matches[:, 0]], x2[matches[:, 1]]) * f > pixels).sum())
            for n in (n1, n2):
                total[n] += len(matches)
                contradicted[n] += bad
        return total, contradicted
    finally:
        db.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="lego", help="Blender scene whose transforms_train.json holds the true cameras.")
    ap.add_argument("--scene", action="append", required=True, metavar="LABEL=SCENE", help="A prepared scene.")
    ap.add_argument("--database", type=Path, required=True, help="COLMAP database whose verified matches judge every scene.")
    ap.add_argument("--pixels", type=float, default=4.0, help="Epipolar (Sampson) distance that contradicts a match.")
    args = ap.parse_args()
    index, ref = reference_cameras(args.object)
    results = {}
    for item in args.scene:
        label, _, path = item.partition("=")
        rec, names, c2w = read_cameras(Path(path))
        true = ref[[index[n] for n in names]]
        results[label] = (pose_errors(c2w, true), turned_cameras(names, c2w, true),
                          *contradicted_inliers(rec, args.database, args.pixels))
    watched = sorted({name for _, turned, _, _ in results.values() for name in turned})
    for label, (errors, turned, total, bad) in results.items():
        all_total, all_bad = sum(total.values()) // 2, sum(bad.values()) // 2
        print(f"{label}: rotation error max {errors['rotation_error_max_deg']:.2f} degrees, {len(turned)} cameras "
              f"turned; contradicted inliers {all_bad} of {all_total} ({100 * all_bad / max(all_total, 1):.2f}%)")
        for name in watched:
            where = (f"turned {turned[name][1]:.1f} degrees, centre {100 * turned[name][0]:.0f}% of the extent off"
                     if name in turned else "placed right")
            print(f"  {name} ({where}): its inliers contradicted {bad[name]} of {total[name]} "
                  f"({100 * bad[name] / max(total[name], 1):.1f}%)")

if __name__ == "__main__":
    main()
