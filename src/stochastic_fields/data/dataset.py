"""The in-memory multi-view scene every loader returns, its scene box, and format autodetection.

Conventions (docs/definitions.md §1): cameras are OpenCV (x right, y down, z forward), pixel centres at +0.5,
``near``/``far``/``depths`` are camera-z depths in the scene's own units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera
from torch import Tensor

from ..cameras import (
    camera_to_world,
    generate_rays_for_view,
    image_size,
    intrinsics_3x3,
    select_cameras,
)
from ..rays import RayBundle
from .errors import DatasetError

#: Default training split (docs/definitions.md §7): views with ``index % 5 == 0`` train, the rest test.
DEFAULT_SPLIT_EVERY: int = 5
#: Views processed together when counting covisibility in :func:`fit_scene_aabb`.
_VIEWS_PER_CHUNK: int = 16


@dataclass
class SceneDataset:
    """A multi-view scene: images, cameras, depth bounds and the views' split.

    Attributes:
        name: scene name (folder name).
        root: folder the scene was read from.
        images: [V, H, W, 3] float32 in [0, 1] (RGBA composited on ``background``).
        cameras: V kornia PinholeCameras (OpenCV, world-to-camera extrinsics).
        near, far: [V] float32 camera-z bounds per view (scene units); rays get them via
            ``generate_rays(..., bounds="camera_z")``.
        train_indices, test_indices: view indices of the split.
        aabb: [2, 3] float32 scene box (lower, upper corner), see :func:`fit_scene_aabb`.
        depths: [V, H, W] float32 camera-z metric depth, 0 where no surface; or None.
        depth_mask: [V, H, W] bool, True where ``depths`` holds a surface; or None.
        background: RGB in [0, 1] that empty pixels show (white for Blender RGBA); or None.
        points3d: [P, 3] float32 sparse world points (COLMAP) or None.
        points3d_rgb: [P, 3] float32 in [0, 1], their colours, or None.
        points3d_visible: per view, int64 indices into ``points3d`` of the points that view
            observes (from the SfM tracks, or by projection when a capture has no tracks); or
            None (LLFF: ``sparse_depth`` reads the tracks from ``points3D.bin``).
        bounds_source: where near/far came from: "file" (poses_bounds.npy, json keys), "sfm_points"
            (the capture's SfM points) or "default" (Blender's near 2 / far 6, guessed).
        image_paths: source file of each view.
        forward_facing: True for LLFF-style captures (all cameras look the same way).
        lens: LLFF only: the lens distortion of the capture's COLMAP camera at the loaded size
            ({"model", "params", "width", "height", "max_shift_px", "border_fraction",
            "undistorted", "source"}), or None when it has none (``data.llff``).
    """

    name: str
    root: Path
    images: Tensor
    cameras: PinholeCamera
    near: Tensor
    far: Tensor
    train_indices: list[int]
    test_indices: list[int]
    aabb: Tensor
    depths: Tensor | None = None
    depth_mask: Tensor | None = None
    background: tuple[float, float, float] | None = None
    points3d: Tensor | None = None
    points3d_rgb: Tensor | None = None
    image_paths: list[Path] = field(default_factory=list)
    forward_facing: bool = False
    points3d_visible: list[np.ndarray] | None = None
    bounds_source: str = "file"
    lens: dict | None = None
    split_source: str = "split_every"

    # ------------------------------------------------------------------ sizes
    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def __len__(self) -> int:
        return self.num_views

    # ------------------------------------------------------------------ rays
    def rays(self, view: int) -> RayBundle:
        """RayBundle [H, W] through the pixel centres of one view, bounded by its near/far planes."""
        return generate_rays_for_view(self.cameras, view, self.near, self.far, bounds="camera_z")

    # ------------------------------------------------------------------ splits
    def subset(self, indices: Sequence[int]) -> "SceneDataset":
        """The views ``indices`` (in that order) as a new dataset.

        Train/test membership is kept: ``train_indices`` of the result are the positions in
        ``indices`` of views that were training views here (same for test).
        """
        idx = [int(i) % self.num_views for i in indices]
        for i in indices:
            if not -self.num_views <= int(i) < self.num_views:
                raise IndexError(f"view {i} out of range for {self.num_views} views of {self.name}")
        train, test = set(self.train_indices), set(self.test_indices)
        t_idx = torch.as_tensor(idx, dtype=torch.long)
        return replace(
            self,
            images=self.images[t_idx],
            cameras=select_cameras(self.cameras, idx),
            near=self.near[t_idx],
            far=self.far[t_idx],
            depths=None if self.depths is None else self.depths[t_idx],
            depth_mask=None if self.depth_mask is None else self.depth_mask[t_idx],
            image_paths=[self.image_paths[i] for i in idx] if self.image_paths else [],
            points3d_visible=None if self.points3d_visible is None else [self.points3d_visible[i] for i in idx],
            train_indices=[k for k, i in enumerate(idx) if i in train],
            test_indices=[k for k, i in enumerate(idx) if i in test],
        )

    def train(self) -> "SceneDataset":
        """The training views only."""
        return self.subset(self.train_indices)

    def test(self) -> "SceneDataset":
        """The test views only."""
        return self.subset(self.test_indices)

    def split_every(self, n: int) -> "SceneDataset":
        """Re-split: views with ``index % n == 0`` train, the rest test (docs/definitions.md §7 uses n = 5)."""
        train, test = split_every_indices(self.num_views, n, self.root)
        return replace(self, train_indices=train, test_indices=test, split_source="split_every")

    def few_views(self, train_views: int, holdout_every: int = 8) -> "SceneDataset":
        """Re-split by the few-view protocol (:func:`few_view_indices`): every ``holdout_every``-th view
        tests, ``train_views`` of the others train, the rest are left out."""
        train, test = few_view_indices(self.num_views, train_views, holdout_every, self.root)
        return replace(self, train_indices=train, test_indices=test, split_source="few_views")

    def train_on(self, views: Sequence[int]) -> "SceneDataset":
        """Re-split: the listed ``views`` train, every other view tests. DatasetError if the list is
        empty, repeats a view or names one outside the scene."""
        views = [int(v) for v in views]
        if not views:
            raise DatasetError(self.root, "the 'views' split needs at least one training view (data.train_list)")
        bad = [v for v in views if not 0 <= v < self.num_views]
        if bad or len(set(views)) != len(views):
            raise DatasetError(self.root, f"data.train_list must name distinct views in [0, {self.num_views - 1}], "
                               f"got {views}")
        keep = set(views)
        return replace(self, train_indices=sorted(keep), test_indices=[v for v in range(self.num_views) if v not in keep],
                       split_source="views")

    def hold_out_every(self, n: int) -> "SceneDataset":
        """Re-split for a capture: views with ``index % n == 0`` validate (test), the rest train."""
        train, test = holdout_every_indices(self.num_views, n, self.root)
        return replace(self, train_indices=train, test_indices=test, split_source="holdout_every")


def parse_views(spec: str, num_views: int, train: Sequence[int], test: Sequence[int]) -> list[int]:
    """'test' | 'train' | 'all' | '1,2,3' -> indices; ValueError for bad tokens or out of range."""
    spec = (spec or "test").strip()
    if spec == "test":
        return list(test)
    if spec == "train":
        return list(train)
    if spec == "all":
        return list(range(num_views))
    try:
        views = [int(v) for v in spec.split(",") if v.strip()]
    except ValueError as exc:
        raise ValueError(f"--views must be 'test', 'train', 'all' or comma-separated indices, got {spec!r}") from exc
    if not views:
        raise ValueError(f"--views {spec!r} names no view")
    if len(set(views)) != len(views):
        raise ValueError(f"--views {spec!r} names a view more than once")
    bad = [v for v in views if not 0 <= v < num_views]
    if bad:
        raise ValueError(f"--views {bad} out of range: the scene has {num_views} views (0..{num_views - 1})")
    return views


def _every_nth(num_views: int, n: int) -> tuple[list[int], list[int]]:
    """(views with ``index % n == 0``, the rest)."""
    return [i for i in range(num_views) if i % n == 0], [i for i in range(num_views) if i % n != 0]


def split_every_indices(num_views: int, n: int, path: str | Path) -> tuple[list[int], list[int]]:
    """(train, test) indices with train = ``index % n == 0``; DatasetError if either is empty."""
    if int(n) < 1:
        raise DatasetError(path, f"split_every must be >= 1, got {n}")
    train, test = _every_nth(num_views, int(n))
    check_split(train, test, path)
    return train, test


def holdout_every_indices(num_views: int, n: int, path: str | Path) -> tuple[list[int], list[int]]:
    """(train, test) indices with test = ``index % n == 0`` (LLFF's convention with n = 8: views 0, 8,
    16, ... validate); DatasetError if either is empty."""
    if int(n) < 2:
        raise DatasetError(path, f"holdout_every must be >= 2, got {n}")
    test, train = _every_nth(num_views, int(n))
    check_split(train, test, path)
    return train, test


def few_view_indices(num_views: int, train_views: int, holdout_every: int, path: str | Path
                     ) -> tuple[list[int], list[int]]:
    """The few-view protocol of RegNeRF (Niemeyer et al. 2022), used by FreeNeRF, SparseNeRF, FSGS and
    others on LLFF: views with ``index % holdout_every == 0`` test (every 8th); ``train_views`` of the
    others, spread evenly, train: the rest's positions ``round(linspace(0, R - 1, train_views))``
    with Python's ``round`` (half to even), as RegNeRF's code picks them. The views neither train nor
    test are left out. DatasetError if the split is impossible."""
    if int(holdout_every) < 2:
        raise DatasetError(path, f"holdout_every must be >= 2, got {holdout_every}")
    test, rest = _every_nth(num_views, int(holdout_every))
    if not 1 <= int(train_views) <= len(rest):
        raise DatasetError(path, f"few-view split: train_views must be between 1 and the {len(rest)} views that are "
                           f"not held out, got {train_views}")
    positions = [round(float(x)) for x in np.linspace(0, len(rest) - 1, int(train_views))]
    train = [rest[k] for k in positions]
    check_split(train, test, path)
    return train, test


def check_split(train: Sequence[int], test: Sequence[int], path: str | Path) -> None:
    """DatasetError naming ``path`` if the split leaves no training or no test view."""
    if len(train) == 0:
        raise DatasetError(path, "the split leaves no training view")
    if len(test) == 0:
        raise DatasetError(path, f"the split leaves no test view ({len(train)} views, all training)")


# ---------------------------------------------------------------------- scene box
def frustum_corners(cameras: PinholeCamera, near: Tensor, far: Tensor) -> Tensor:
    """[V, 8, 3] world corners of each view's frustum between its near and far depth planes."""
    V = cameras.batch_size
    H, W = image_size(cameras)
    like = cameras.intrinsics
    uv = torch.tensor([[0.0, 0.0], [W, 0.0], [0.0, H], [W, H]], dtype=like.dtype, device=like.device)
    K = intrinsics_3x3(cameras)
    d_cam = torch.cat([(uv[None] - K[:, None, :2, 2]) / torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None],
                       torch.ones(V, 4, 1, dtype=like.dtype, device=like.device)], dim=-1)  # [V, 4, 3], z = 1
    z = torch.stack([near, far], dim=1).to(like)  # [V, 2]
    cam = (d_cam[:, None, :, :] * z[:, :, None, None]).reshape(V, 8, 3)
    c2w = camera_to_world(cameras)
    return cam @ c2w[:, :3, :3].transpose(1, 2) + c2w[:, None, :3, 3]


def pad_box(lo: Tensor, hi: Tensor, padding: float, *, isotropic: bool = True) -> Tensor:
    """[2, 3] box ``lo``/``hi`` [3] grown on every side by ``padding`` x the box's largest extent
    (``isotropic``), or x each axis's own extent.

    An object-centric box is the field's region, so it pads isotropically: a flat axis (a floor,
    the embedded scene's z from the ground at 0 to 0.8) padded by its own extent leaves the floor on
    the box's face, with no density below it, and the grid fills the space above the floor to make
    it opaque (the ground rendered 3% of the depth in front of the truth: docs/studies.md, study
    32)."""
    extent = hi - lo
    pad = extent.max() * padding if isotropic else extent * padding
    return torch.stack([lo - pad, hi + pad])


def _robust_box(points: Tensor, percentiles: tuple[float, float], padding: float, *, isotropic: bool) -> Tensor:
    """[2, 3] per-axis percentile box of points [P, 3], padded (``pad_box``)."""
    p = points.double()
    q = torch.tensor([percentiles[0] / 100.0, percentiles[1] / 100.0], dtype=p.dtype)
    lo_hi = torch.quantile(p, q, dim=0)  # [2, 3]
    return pad_box(lo_hi[0], lo_hi[1], padding, isotropic=isotropic).float()


def _intersect(a: Tensor, b: Tensor) -> Tensor:
    box = torch.stack([torch.maximum(a[0], b[0]), torch.minimum(a[1], b[1])])
    if not bool(torch.all(box[1] > box[0])):
        return a  # disjoint: the points disagree with the frusta, keep the camera-derived box
    return box


def fit_scene_aabb(
    cameras: PinholeCamera,
    near: Tensor | float,
    far: Tensor | float,
    points: Tensor | None = None,
    *,
    forward_facing: bool = False,
    percentiles: tuple[float, float] = (1.0, 99.0),
    padding: float = 0.05,
    min_view_fraction: float = 0.5,
    grid: int = 32,
) -> Tensor:
    """The scene box [2, 3] (lower, upper corner), fitted from cameras, near/far and points.

    The choice:
      * Nothing outside the union of the frusta (between each view's near and far depth planes)
        can be seen, so the box never exceeds the AABB of the frustum corners.
      * With ``points`` (COLMAP sparse points, or surface points back-projected from depth maps):
        the per-axis ``percentiles`` box of the points (so a few outliers do not inflate it),
        padded by ``padding`` x its largest extent on every axis (``pad_box``; forward-facing
        scenes, whose field lives in NDC, by each axis's own extent), intersected with the frusta
        box. This is the choice for forward-facing LLFF scenes, whose frusta reach far behind the
        content.
      * Bounded scenes without points: the AABB of the *covisible* volume, grid points of the
        frusta box that at least ``min_view_fraction`` of the views see (inside the image and
        between near and far), padded by one grid cell plus ``padding`` x its largest extent. For
        cameras ringed around an object this is the region around the object, not the cameras' ring.
      * Forward-facing without points: the frusta box.

    Shapes: near/far floats or [V]; points [P, 3].
    """
    V = cameras.batch_size
    like = cameras.extrinsics
    near_v = torch.as_tensor(near, dtype=like.dtype, device=like.device).reshape(-1).expand(V)
    far_v = torch.as_tensor(far, dtype=like.dtype, device=like.device).reshape(-1).expand(V)
    if not bool(torch.all(far_v > near_v)):
        raise ValueError(f"fit_scene_aabb: need far > near for every view, "
                         f"got near={near_v.tolist()} far={far_v.tolist()}")
    corners = frustum_corners(cameras, near_v, far_v).reshape(-1, 3)
    frusta_box = torch.stack([corners.min(0).values, corners.max(0).values]).float().cpu()
    if points is not None and len(points) > 0:
        box = _robust_box(torch.as_tensor(points).float().cpu(), percentiles, padding, isotropic=not forward_facing)
        return _intersect(frusta_box, box)
    if forward_facing:
        return frusta_box
    # covisible volume on a grid inside the frusta box
    axes = [torch.linspace(float(frusta_box[0, k]), float(frusta_box[1, k]), grid, dtype=like.dtype) for k in range(3)]
    gx, gy, gz = torch.meshgrid(*axes, indexing="ij")
    pts = torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3).to(like.device)
    counts = torch.zeros(pts.shape[0], dtype=torch.long, device=like.device)
    K = intrinsics_3x3(cameras)
    E = cameras.extrinsics
    for start in range(0, V, _VIEWS_PER_CHUNK):  # a few views at a time: memory O(chunk * grid^3)
        sl = slice(start, start + _VIEWS_PER_CHUNK)
        cam = pts[None] @ E[sl, :3, :3].transpose(1, 2) + E[sl, None, :3, 3]  # [v, G, 3]
        z = cam[..., 2]
        safe_z = torch.where(z > 0, z, torch.ones_like(z))
        u = K[sl, None, 0, 0] * cam[..., 0] / safe_z + K[sl, None, 0, 2]
        v = K[sl, None, 1, 1] * cam[..., 1] / safe_z + K[sl, None, 1, 2]
        seen = (z >= near_v[sl, None]) & (z <= far_v[sl, None]) & (z > 0)
        seen &= (u >= 0) & (u < cameras.width[sl, None]) & (v >= 0) & (v < cameras.height[sl, None])
        counts += seen.long().sum(0)
    need = max(1, math.ceil(min_view_fraction * V))
    keep = pts[counts >= need].cpu()
    if keep.shape[0] == 0:
        return frusta_box
    cell = (frusta_box[1] - frusta_box[0]) / (grid - 1)
    lo, hi = keep.min(0).values.float() - cell, keep.max(0).values.float() + cell
    return _intersect(frusta_box, pad_box(lo, hi, padding))


# ---------------------------------------------------------------------- image files
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")


def read_image(path: str | Path) -> np.ndarray:
    """[H, W, C] float32 in [0, 1] (C = 3 or 4) from an 8- or 16-bit image file.

    Raises DatasetError naming the file if it is missing, unreadable or not RGB(A).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing image")
    try:
        img = iio.imread(path)
    except Exception as exc:  # imageio raises many types for corrupt files
        raise DatasetError(path, f"unreadable image ({type(exc).__name__}: {exc})") from exc
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise DatasetError(path, f"expected an RGB or RGBA image, got array of shape {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if np.issubdtype(img.dtype, np.floating):
        return img.astype(np.float32)
    raise DatasetError(path, f"unsupported image dtype {img.dtype}")


def stack_images(arrays: list[np.ndarray], paths: list[Path]) -> Tensor:
    """[V, H, W, C] float32 tensor; DatasetError naming the first image whose size differs."""
    shape = arrays[0].shape
    for a, p in zip(arrays, paths):
        if a.shape != shape:
            raise DatasetError(p, f"image shape {a.shape} differs from {shape} of {paths[0].name}")
    return torch.from_numpy(np.stack(arrays, axis=0))
