"""Sparse depth ground truth from SfM (COLMAP) points, and depth scores against it (docs/definitions.md §6).

Real captures have no depth maps, but their COLMAP model holds the triangulated points in the
poses' world frame: LLFF ships ``sparse/0/points3D.bin``; COLMAP captures, prepared scenes and
nerfstudio captures carry them in the dataset (``points3d``, with ``points3d_visible`` from the
tracks), read once by the loader (:func:`sparse_depth_for_dataset` takes either). Projecting
them into a view gives real, sparse, camera-z depths at known pixels:

    (u, v), z = project(camera_v, X_p)       pixel = (floor(v), floor(u)), depth = z

Which points does view v see?
  * ``visibility="tracks"`` (default when it checks out): the points whose COLMAP track lists
    the view's image. A loaded capture knows them by image name. LLFF ships no ``images.bin``,
    so there image ids are matched to views by position: COLMAP numbers images 1..V in file-name order, and LLFF's
    ``poses_bounds.npy`` rows follow the same sorted names, hence image id = view + 1. The
    assumption is checked per view: at least ``TRACK_CHECK_INSIDE`` of the tracked points must
    project inside the image and in front of the camera (measured on fern and flower: 100%
    with id = view + 1, 93-99% with any other offset); otherwise we fall back to the z-buffer.
  * ``visibility="zbuffer"``: every point that projects inside the image in front of the camera
    (occluded points are only removed where they share a pixel with a nearer point).
In both modes several points falling into one pixel keep the nearest (the visible surface).

Scores (``sparse_depth_scores``) sample the rendered camera-z depth mean and standard
deviation at those pixels (nearest pixel centre: the pixel the point falls in) and keep points
where the rendered opacity exceeds ``opacity_mask`` (rays that hit nothing have depth ``far``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from torch import Tensor

from .cameras import in_image, project_points, select_cameras
from .constants import DEPTH_NLL_VARIANCE_FLOOR
from . import metrics as M
from .data.colmap import read_points3d_binary

Visibility = Literal["auto", "tracks", "zbuffer"]

#: Fraction of a view's tracked points that must project inside it for the image-id = view + 1
#: match to be trusted (see module doc; a wrong match drops to ~0.93 on flower).
TRACK_CHECK_INSIDE: float = 0.995

#: Nominal levels reported as single coverage numbers (1 and 2 standard deviations).
COVERAGE_LEVELS: tuple[float, float] = (0.682689492137086, 0.954499736103642)


@dataclass
class SparseDepth:
    """Ground-truth depth at the pixels where COLMAP points project into one view.

    Attributes:
        view: view index in the dataset.
        rows, cols: [M] int64 pixel row and column (``floor(v)``, ``floor(u)``).
        uv: [M, 2] float64 continuous pixel coordinates (u right, v down; pixel centres at +0.5).
        depth: [M] float64 camera-z depth (scene units).
        point_index: [M] int64 index of each point in the COLMAP point array.
        visibility: "tracks" or "zbuffer", how the points were selected.
        num_candidates: points that projected inside the image before the one-per-pixel rule.
    """

    view: int
    rows: np.ndarray
    cols: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    point_index: np.ndarray
    visibility: str
    num_candidates: int

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    def sample(self, image: np.ndarray | Tensor) -> np.ndarray:
        """Values of a map [H, W, ...] at the points' pixels -> [M, ...] (numpy float64)."""
        arr = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
        return arr[self.rows, self.cols].astype(np.float64)


def points_file(scene_root: str | Path) -> Path:
    """``<scene>/sparse/0/points3D.bin``."""
    return Path(scene_root) / "sparse" / "0" / "points3D.bin"


def track_visibility(points, num_views: int) -> list[np.ndarray] | None:
    """Per view, the indices of the points whose track lists image id ``view + 1``.

    ``points`` is a ``data.colmap.ColmapPoints``. Returns None when the image ids do not fit
    1..num_views (the id = view + 1 match cannot hold).
    """
    ids = points.track_image_ids
    if ids.size == 0 or ids.min() < 1 or ids.max() > num_views:
        return None
    owner = np.repeat(np.arange(len(points)), points.track_lengths)  # [T] point of each track entry
    return [np.unique(owner[ids == v + 1]) for v in range(num_views)]


def _float64_camera(cam):
    """The same kornia camera in float64 (projections of points ~100 units away stay exact to the pixel)."""
    return type(cam)(cam.intrinsics.double(), cam.extrinsics.double(), cam.height.double(), cam.width.double())


def _nearest_per_pixel(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, width: int) -> np.ndarray:
    """Indices (into the inputs) of the nearest point of every occupied pixel, sorted by pixel."""
    key = rows.astype(np.int64) * width + cols.astype(np.int64)
    order = np.lexsort((depth, key))  # by pixel, then by depth
    first = np.ones(order.size, dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    return order[first]


def project_sparse_depth(cameras, xyz: np.ndarray | Tensor, views: Sequence[int], *,
                         visible: list[np.ndarray] | None = None, visibility_name: str | None = None) -> dict[int, SparseDepth]:
    """Project world points [P, 3] into each of ``views`` of ``cameras`` (V kornia cameras).

    ``visible``: optional per-view arrays of candidate point indices (from ``track_visibility``);
    None uses every point. Points behind the camera or outside [0, W) x [0, H) are dropped;
    several points in one pixel keep the nearest.
    """
    xyz_t = torch.as_tensor(np.asarray(xyz), dtype=torch.float64)
    out: dict[int, SparseDepth] = {}
    for v in views:
        cam = select_cameras(cameras, [int(v)])
        cam64 = _float64_camera(cam)
        cand = np.arange(xyz_t.shape[0]) if visible is None else np.asarray(visible[v], dtype=np.int64)
        uv, z = project_points(cam64, xyz_t[torch.from_numpy(cand)])
        inside = in_image(cam64, uv, z)[0].numpy()
        uv_np, z_np, idx = uv[0].numpy()[inside], z[0].numpy()[inside], cand[inside]
        rows, cols = np.floor(uv_np[:, 1]).astype(np.int64), np.floor(uv_np[:, 0]).astype(np.int64)
        W = int(cam.width[0])
        keep = _nearest_per_pixel(rows, cols, z_np, W)
        out[int(v)] = SparseDepth(view=int(v), rows=rows[keep], cols=cols[keep], uv=uv_np[keep], depth=z_np[keep],
                                  point_index=idx[keep],
                                  visibility=visibility_name or ("tracks" if visible is not None else "zbuffer"),
                                  num_candidates=int(inside.sum()))
    return out


def sparse_depth_for_dataset(dataset, views: Sequence[int] | None = None, *, visibility: Visibility = "auto",
                             points=None) -> dict[int, SparseDepth]:
    """Sparse ground-truth depth of ``views`` (default: the test split) of a dataset with SfM points.

    Where the points come from, in this order: ``points`` (ColmapPoints) when given; the
    dataset's own ``points3d`` with ``points3d_visible`` (the tracks of a COLMAP capture or a
    prepared scene, read once by the loader); ``<dataset.root>/sparse/0/points3D.bin`` (LLFF,
    whose model has no images.bin); the dataset's ``points3d`` without tracks (a nerfstudio
    ``ply_file_path``: z-buffer only).
    ``visibility``: "tracks", "zbuffer" or "auto" (tracks when they are known and, for
    points3D.bin, the id = view + 1 match checks out for every requested view, else zbuffer).
    Raises FileNotFoundError naming the file if the scene has no SfM points.
    """
    views = list(dataset.test_indices) if views is None else [int(v) for v in views]
    if visibility not in ("auto", "tracks", "zbuffer"):
        raise ValueError(f"visibility must be 'auto', 'tracks' or 'zbuffer', got {visibility!r}")
    own_points = getattr(dataset, "points3d", None)
    own_visible = getattr(dataset, "points3d_visible", None)
    if points is None and own_points is not None and own_visible is not None:
        xyz = own_points.detach().double().cpu().numpy()
        return project_sparse_depth(dataset.cameras, xyz, views,
                                    visible=None if visibility == "zbuffer" else own_visible)
    if points is None:
        path = points_file(dataset.root)
        if not path.is_file():
            if own_points is not None:
                if visibility == "tracks":
                    raise ValueError(f"the SfM points of {dataset.root} have no tracks: use visibility='zbuffer'")
                return project_sparse_depth(dataset.cameras, own_points.detach().double().cpu().numpy(), views)
            raise FileNotFoundError(f"no COLMAP points for sparse depth: {path} does not exist")
        points = read_points3d_binary(path)
    visible = None
    if visibility in ("auto", "tracks"):
        visible = track_visibility(points, dataset.num_views)
        if visible is not None and not tracks_match_views(dataset.cameras, points.xyz, visible, views):
            visible = None
        if visible is None and visibility == "tracks":
            raise ValueError(f"COLMAP tracks of {points_file(dataset.root)} do not match the views by image id = view + 1")
    return project_sparse_depth(dataset.cameras, points.xyz, views, visible=visible)


def tracks_match_views(cameras, xyz: np.ndarray, visible: list[np.ndarray], views: Sequence[int]) -> bool:
    """True when, in every view, >= TRACK_CHECK_INSIDE of its tracked points project inside it."""
    xyz_t = torch.as_tensor(np.asarray(xyz), dtype=torch.float64)
    for v in views:
        if len(visible[v]) == 0:
            return False
        cam = select_cameras(cameras, [int(v)])
        cam64 = _float64_camera(cam)
        uv, z = project_points(cam64, xyz_t[torch.from_numpy(visible[v])])
        if float(in_image(cam64, uv, z).double().mean()) < TRACK_CHECK_INSIDE:
            return False
    return True


def paired_depth_scores(gt: np.ndarray, pred: np.ndarray, std: np.ndarray, *,
                        var_floor: float = DEPTH_NLL_VARIANCE_FLOOR, interval_scale=None) -> dict:
    """Depth scores of predictions at ground-truth samples (sparse points or masked dense pixels).

    ``interval_scale``: level-dependent multiplier of the central intervals (coverage, AUCE) of
    a recalibrated std (``calibration.QuantileCalibration.relative_scale``); None: Gaussian intervals.

    Shapes: gt, pred, std [M] (camera-z, scene units).
    Returns {"num_used", "abs_rel", "rmse", "mae", "nll", "ause_rmse", "ause_rmse_normalised",
    "pearson", "spearman" (CorrelationResult of |err| vs std), "coverage_68", "coverage_95",
    "auce", "calibration" (CalibrationResult or None), "sparsification" (SparsificationResult
    or None)}. With fewer than two samples every value is NaN (undefined, not a crash); with a
    constant std the correlations and the AUSE are undefined (a ranking by a constant is
    arbitrary).
    """
    gt, pred, std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (gt, pred, std))
    out: dict = {"num_used": int(gt.size)}
    names = ("abs_rel", "rmse", "mae", "nll", "ause_rmse", "ause_rmse_normalised", "coverage_68", "coverage_95", "auce")
    if gt.size < 2:
        out.update({k: math.nan for k in names})
        reason = f"fewer than 2 points (n={gt.size})"
        out["pearson"] = out["spearman"] = M.CorrelationResult(math.nan, False, reason, int(gt.size))
        out["calibration"] = out["sparsification"] = None
        return out
    err = M.depth_errors(pred, gt)
    abs_err = np.abs(pred - gt)
    cal = M.calibration_curve(gt, pred, std, interval_scale=interval_scale)
    cov = M.calibration_curve(gt, pred, std, levels=list(COVERAGE_LEVELS), interval_scale=interval_scale).coverage
    out.update({
        "abs_rel": err["abs_rel"], "rmse": err["rmse"], "mae": err["mae"],
        "nll": M.depth_nll(gt, pred, std ** 2, var_floor=var_floor),
        "pearson": M.pearson(abs_err, std, "|depth error|", "depth std"),
        "spearman": M.spearman(abs_err, std, "|depth error|", "depth std"),
        "coverage_68": float(cov[0]), "coverage_95": float(cov[1]), "auce": cal.auce, "calibration": cal,
    })
    if np.ptp(std) > 0:
        sp = M.sparsification_curve(pred - gt, std ** 2, metric="rmse")
        out.update(ause_rmse=sp.ause, ause_rmse_normalised=sp.ause_normalised, sparsification=sp)
    else:
        out.update(ause_rmse=math.nan, ause_rmse_normalised=math.nan, sparsification=None)
    return out


def sparse_depth_scores(depth_mean: np.ndarray | Tensor, depth_std: np.ndarray | Tensor, sparse: SparseDepth, *,
                        opacity: np.ndarray | Tensor | None = None, opacity_mask: float = 0.5,
                        var_floor: float = DEPTH_NLL_VARIANCE_FLOOR, interval_scale=None) -> dict:
    """``paired_depth_scores`` of rendered camera-z maps at the sparse points of one view.

    Points where the rendered ``opacity`` is not above ``opacity_mask`` are left out.
    Shapes: depth_mean, depth_std, opacity [H, W]. Adds "num_points" (before the mask).
    """
    d = sparse.sample(depth_mean)
    s = sparse.sample(depth_std)
    keep = np.isfinite(d) & np.isfinite(s)
    if opacity is not None:
        keep &= sparse.sample(opacity) > opacity_mask
    out = paired_depth_scores(sparse.depth[keep], d[keep], s[keep], var_floor=var_floor, interval_scale=interval_scale)
    out["num_points"] = len(sparse)
    return out


def sparse_depth_conventions() -> dict[str, str]:
    """Printable conventions of the sparse (COLMAP) depth scores."""
    return {
        "sparse_depth_gt": "COLMAP points3D projected into each test view (camera-z depth); visible points from "
        "COLMAP tracks (image id = view + 1, checked) or a z-buffer; one point per pixel (the nearest)",
        "sparse_depth_sampling": "rendered camera-z depth mean/std at the pixel the point falls in; points where "
        "the rendered opacity <= mask are left out",
        "sparse_depth_scores": "abs_rel = mean |d - z| / z, RMSE, depth NLL (floor "
        f"{DEPTH_NLL_VARIANCE_FLOOR:g} scene units^2), AUSE (RMSE, var ranking), Pearson/Spearman of |err| vs std, "
        "coverage of +-1 and +-2 std, AUCE",
    }
