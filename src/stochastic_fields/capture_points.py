"""The capture's own 3D points as sparse depth, split by blocks of space into three roles.

A user of their own capture has no ground-truth depth, but structure-from-motion leaves
triangulated surface points (COLMAP ``points3D.bin``). They serve three jobs that must not see
each other's data (docs/uncertainty.md, "Independence"):

* ``FIT``: a depth likelihood term during training (``loss.lambda_depth``),
* ``CALIBRATE``: fitting the depth-uncertainty recalibration (``stochastic_fields.calibration``),
* ``SCORE``: depth scores of the test views, and nothing else.

Neighbouring points share their errors (the same surface, the same grid cells), so the split is
by **blocks of space**, not point by point: the robust extent of the points (their
``SPLIT_EXTENT_PERCENTILES``, per axis) is cut into ``SPLIT_BLOCKS_PER_AXIS^3`` blocks, the
occupied blocks are shuffled with ``SPLIT_SEED``, and walked in that order giving each block
wholly to one role until that role holds its ``SPLIT_FRACTIONS`` share of the points. Points
outside the extent join the block they are clamped into. The split is a function of the points
alone (not of the run's options), so training, calibration and evaluation always agree on it.

Scenes without SfM points but with dense depth (the embedded synthetic scene) get stand-in
capture points: a seeded ``SYNTHETIC_POINTS_FRACTION`` of every training view's surface pixels,
back-projected, observed by every training view whose depth map agrees with them
(``synthetic_capture_points``). They play the part of SfM points (surface points
seen from training views). Test views are scored on their exact dense depth, but only at the
pixels whose surface lies in a SCORE block (``dense_depth_score_mask``), as the sparse scenes are
scored on the SCORE points only: the FIT blocks' surfaces trained the depth likelihood and the
CALIBRATE blocks' fitted the recalibration.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import torch
from .cameras import camera_to_world, generate_rays_at, in_image, intrinsics_3x3, project_points, select_cameras
from .data.colmap import read_points3d_binary
from .sparse_depth import points_file, project_sparse_depth, sparse_depth_for_dataset, track_visibility

#: Roles of a capture point.
FIT, CALIBRATE, SCORE = 0, 1, 2
ROLE_NAMES: dict[int, str] = {FIT: "fit", CALIBRATE: "calibrate", SCORE: "score"}

#: Role of a point in a block of space that holds no capture point (no role: nothing trained or fitted there).
NO_ROLE = -1
#: Blocks per axis of the spatial split (6^3 = 216 blocks; fern's points occupy about 70 of them).
SPLIT_BLOCKS_PER_AXIS: int = 6
#: Share of the points per role (fit, calibrate, score).
SPLIT_FRACTIONS: tuple[float, float, float] = (0.4, 0.2, 0.4)
#: Seed of the block shuffle.
SPLIT_SEED: int = 0
#: Percentiles of the point coordinates that bound the block grid (outliers are clamped in).
SPLIT_EXTENT_PERCENTILES: tuple[float, float] = (1.0, 99.0)
#: Fraction of a training view's surface pixels taken as stand-in capture points (dense-depth scenes).
SYNTHETIC_POINTS_FRACTION: float = 0.02
#: A training view observes a stand-in point when its depth map at the point's pixel is within this
#: relative distance of the point's depth (a z-test: the pixel's surface is the point's, not an occluder).
SYNTHETIC_VISIBILITY_RTOL: float = 0.02


def block_keys(xyz: np.ndarray, reference: np.ndarray, *,
               blocks_per_axis: int = SPLIT_BLOCKS_PER_AXIS) -> np.ndarray:
    """Block of space of every point ``xyz`` [N, 3] -> [N] int64 key, on the split's grid over the
    ``reference`` points' [P, 3] robust extent (``SPLIT_EXTENT_PERCENTILES`` per axis, cut into
    ``blocks_per_axis``^3 blocks; points outside join the block they are clamped into). With the
    capture points as reference, any other point (a test pixel back-projected) gets the block the
    split would give it."""
    n = int(blocks_per_axis)
    if n < 1:
        raise ValueError(f"blocks_per_axis must be >= 1, got {blocks_per_axis}")
    reference = np.asarray(reference, dtype=np.float64)
    lo, hi = np.percentile(reference, SPLIT_EXTENT_PERCENTILES, axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    cell = np.clip(np.floor((np.asarray(xyz, dtype=np.float64) - lo) / span * n), 0, n - 1).astype(np.int64)
    return (cell[:, 0] * n + cell[:, 1]) * n + cell[:, 2]


def block_roles(xyz: np.ndarray, capture: "CapturePoints") -> np.ndarray:
    """Role of the block of space each point ``xyz`` [N, 3] falls in, on the split of ``capture``'s
    points (``block_keys`` over their extent; every block belongs wholly to one role) -> [N] int8:
    FIT, CALIBRATE, SCORE, or ``NO_ROLE`` for a block that holds no capture point."""
    keys = block_keys(capture.xyz, capture.xyz)
    blocks, first = np.unique(keys, return_index=True)
    query = block_keys(np.asarray(xyz, dtype=np.float64).reshape(-1, 3), capture.xyz)
    pos = np.clip(np.searchsorted(blocks, query), 0, len(blocks) - 1)
    return np.where(blocks[pos] == query, capture.roles[first[pos]], NO_ROLE).astype(np.int8)


def _dense_surface_points(dataset, view: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """The pixels of ``view``'s exact depth map with a surface (depth > 0): rows [N], cols [N] and
    their back-projected world points [N, 3] (float64)."""
    depth = dataset.depths[view].double()
    rows, cols = torch.nonzero(depth > 0, as_tuple=True)
    xyz = backproject_pixels(intrinsics_3x3(dataset.cameras)[view], camera_to_world(dataset.cameras)[view],
                             rows, cols, depth[rows, cols])
    return rows, cols, xyz.numpy()


def dense_depth_score_mask(dataset, capture: "CapturePoints", view: int) -> np.ndarray:
    """[H, W] bool: the pixels of ``view``'s exact depth map (``dataset.depths``, > 0 on a surface)
    whose surface point, back-projected, lies in a SCORE block of ``capture``'s split: the dense
    counterpart of scoring the SCORE capture points only (module doc)."""
    rows, cols, xyz = _dense_surface_points(dataset, view)
    mask = np.zeros(tuple(dataset.depths[view].shape), dtype=bool)
    if len(xyz):
        mask[rows.numpy(), cols.numpy()] = block_roles(xyz, capture) == SCORE
    return mask


def dense_depth_block_keys(dataset, capture: "CapturePoints", view: int) -> np.ndarray:
    """[H, W] int64: the block of space (``block_keys`` on ``capture``'s split) of each pixel's
    surface point in ``view``'s exact depth map; -1 where there is no surface."""
    rows, cols, xyz = _dense_surface_points(dataset, view)
    keys = np.full(tuple(dataset.depths[view].shape), -1, dtype=np.int64)
    if len(xyz):
        keys[rows.numpy(), cols.numpy()] = block_keys(xyz, capture.xyz)
    return keys


def split_points_by_blocks(xyz: np.ndarray, *, blocks_per_axis: int = SPLIT_BLOCKS_PER_AXIS,
                           fractions: Sequence[float] = SPLIT_FRACTIONS, seed: int = SPLIT_SEED) -> np.ndarray:
    """Role (FIT, CALIBRATE or SCORE) of every point [P, 3] -> [P] int8, by blocks of space (module doc).

    Every block goes wholly to one role. Raises ValueError for an empty or non-finite point set,
    fractions that are negative or do not sum to 1, or fewer than 1 block per axis.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] == 0:
        raise ValueError(f"split_points_by_blocks needs points [P, 3] with P > 0, got shape {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise ValueError("split_points_by_blocks: points contain NaN or inf")
    frac = np.asarray(fractions, dtype=np.float64)
    if frac.shape != (3,) or (frac < 0).any() or abs(frac.sum() - 1.0) > 1e-9:
        raise ValueError(f"fractions must be three non-negative shares summing to 1, got {tuple(fractions)}")
    if blocks_per_axis < 1:
        raise ValueError(f"blocks_per_axis must be >= 1, got {blocks_per_axis}")
    key = block_keys(xyz, xyz, blocks_per_axis=blocks_per_axis)
    blocks, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    order = np.random.default_rng(seed).permutation(len(blocks))
    # walk the shuffled blocks: a block joins the first role whose share is not yet filled
    targets = np.cumsum(frac) * xyz.shape[0]
    block_role = np.empty(len(blocks), dtype=np.int8)
    filled = 0
    for b in order:
        role = int(np.searchsorted(targets, filled, side="right"))
        block_role[b] = min(role, 2)
        filled += counts[b]
    return block_role[inverse]


@dataclass
class CapturePoints:
    """The capture's surface points and their roles.

    Attributes:
        xyz: [P, 3] float64 world points.
        roles: [P] int8 FIT / CALIBRATE / SCORE.
        source: "colmap" (structure from motion, with tracks), "sfm" (points without tracks)
            or "synthetic" (stand-in, see module doc).
        visible: per view, the indices of the points the view observed (COLMAP tracks, or the
            view a stand-in point came from); None: decide by a z-buffer.
        colmap: the ColmapPoints when read from COLMAP (tracks), else None.
    """

    xyz: np.ndarray
    roles: np.ndarray
    source: str
    visible: list[np.ndarray] | None = None
    colmap: object | None = None

    def counts(self) -> dict[str, int]:
        return {name: int((self.roles == r).sum()) for r, name in ROLE_NAMES.items()}


def backproject_pixels(K: torch.Tensor, c2w: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
                       z: torch.Tensor) -> torch.Tensor:
    """World points [N, 3] (float64) of pixel centres (``rows``, ``cols`` [N]) at camera-z depths
    ``z`` [N], for one camera: intrinsics ``K`` [3, 3], camera-to-world ``c2w`` [4, 4] (OpenCV
    axes): X = R K^-1 (u + 1/2, v + 1/2, 1)^T z + t."""
    K, c2w, z = K.double(), c2w.double(), z.double()
    uv1 = torch.stack([cols.double() + 0.5, rows.double() + 0.5, torch.ones_like(z)], dim=-1)
    cam = torch.linalg.solve(K, uv1.T).T * z[:, None]
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def depth_map_observes(dataset, xyz: np.ndarray | torch.Tensor, view: int, *,
                       rtol: float = SYNTHETIC_VISIBILITY_RTOL) -> np.ndarray:
    """[P] bool: which world points ``xyz`` [P, 3] view ``view`` of a dense-depth dataset observes.

    A point is observed when it projects inside the image in front of the camera and the view's
    depth map at its pixel is within ``rtol`` (relative) of the point's camera depth: the pixel's
    surface is the point's, not an occluder (the track of a stand-in point)."""
    points = torch.as_tensor(np.asarray(xyz), dtype=torch.float64)
    cam = select_cameras(dataset.cameras, [int(view)])
    cam64 = type(cam)(cam.intrinsics.double(), cam.extrinsics.double(), cam.height.double(), cam.width.double())
    uv, zc = project_points(cam64, points)
    inside = in_image(cam64, uv, zc)[0]
    rows = uv[0, :, 1].floor().long().clamp(0, dataset.height - 1)
    cols = uv[0, :, 0].floor().long().clamp(0, dataset.width - 1)
    surface = dataset.depths[int(view)].double()[rows, cols]
    return (inside & (surface > 0) & ((surface - zc[0]).abs() <= rtol * zc[0])).numpy()


def synthetic_capture_points(dataset, *, fraction: float = SYNTHETIC_POINTS_FRACTION,
                             seed: int = SPLIT_SEED) -> tuple[np.ndarray, list[np.ndarray]]:
    """Stand-in SfM points of a dense-depth scene: a seeded ``fraction`` of every training view's
    surface pixels, back-projected at the pixel centre. Returns (xyz [P, 3], per-view visible point
    indices): as a COLMAP track, a training view observes a point when ``depth_map_observes`` says
    so (test views observe none)."""
    if dataset.depths is None:
        raise ValueError(f"{dataset.root}: no dense depth to take stand-in capture points from")
    rng = np.random.default_rng(seed)
    K = intrinsics_3x3(dataset.cameras).double()
    c2w = camera_to_world(dataset.cameras).double()
    xyz = []
    for v in dataset.train_indices:
        depth = dataset.depths[v].double()
        rows, cols = torch.nonzero(depth > 0, as_tuple=True)
        take = torch.from_numpy(rng.random(rows.numel()) < fraction)
        rows, cols = rows[take], cols[take]
        xyz.append(backproject_pixels(K[v], c2w[v], rows, cols, depth[rows, cols]))
    if not xyz:
        return np.zeros((0, 3)), [np.zeros(0, dtype=np.int64) for _ in range(dataset.num_views)]
    points = torch.cat(xyz).numpy()
    visible = [np.zeros(0, dtype=np.int64) for _ in range(dataset.num_views)]
    for v in dataset.train_indices:
        visible[v] = np.flatnonzero(depth_map_observes(dataset, points, v)).astype(np.int64)
    return points, visible


def training_view_counts(dataset, capture: "CapturePoints", xyz: np.ndarray | None = None) -> np.ndarray:
    """[P] int: how many training views observe each point: the capture points' own tracks
    (``capture.visible``), or for other points ``xyz`` [P, 3] of a dense-depth scene the depth-map
    test of ``depth_map_observes``. Raises ValueError when neither is known."""
    if xyz is None:
        if capture.visible is None:
            raise ValueError(f"{dataset.root}: the capture points have no tracks to count training views from")
        counts = np.zeros(len(capture.xyz), dtype=np.int64)
        for v in dataset.train_indices:
            counts[capture.visible[v]] += 1
        return counts
    if getattr(dataset, "depths", None) is None:
        raise ValueError(f"{dataset.root}: no dense depth to test which training views observe the points")
    counts = np.zeros(len(xyz), dtype=np.int64)
    for v in dataset.train_indices:
        counts += depth_map_observes(dataset, xyz, v)
    return counts


def load_capture_points(dataset) -> CapturePoints | None:
    """The capture points of a dataset, or None. In this order: the loader's own SfM points with
    their tracks (``dataset.points3d`` / ``points3d_visible``: a COLMAP capture or a prepared
    scene); ``<root>/sparse/0/points3D.bin`` (LLFF, tracks matched by image id = view + 1);
    the loader's points without tracks (z-buffer); stand-in points of a dense-depth scene.
    Roles from ``split_points_by_blocks``."""
    own = getattr(dataset, "points3d", None)
    own_visible = getattr(dataset, "points3d_visible", None)
    if own is not None and own_visible is not None and len(own):
        xyz = own.detach().double().cpu().numpy()
        return CapturePoints(xyz, split_points_by_blocks(xyz), "colmap", list(own_visible))
    path = points_file(dataset.root)
    if path.is_file():
        pts = read_points3d_binary(path)
        if len(pts.xyz) == 0:
            return None
        visible = track_visibility(pts, dataset.num_views)
        return CapturePoints(pts.xyz, split_points_by_blocks(pts.xyz), "colmap", visible, pts)
    if own is not None and len(own):
        xyz = own.detach().double().cpu().numpy()
        return CapturePoints(xyz, split_points_by_blocks(xyz), "sfm", None)
    if getattr(dataset, "depths", None) is not None:
        xyz, visible = synthetic_capture_points(dataset)
        if len(xyz) == 0:
            return None
        return CapturePoints(xyz, split_points_by_blocks(xyz), "synthetic", visible)
    return None


def sparse_depth_for_role(dataset, points: CapturePoints, views: Sequence[int], role: int) -> dict:
    """{view: SparseDepth} of the points of one ``role`` in ``views`` (nearest point per pixel).

    COLMAP points use their tracks when the image-id match checks out for these views
    (``sparse_depth.sparse_depth_for_dataset``), stand-in points the view they came from;
    otherwise a z-buffer."""
    views = [int(v) for v in views]
    if points.colmap is not None:
        full = sparse_depth_for_dataset(dataset, views, points=points.colmap)
    else:
        full = project_sparse_depth(dataset.cameras, points.xyz, views, visible=points.visible,
                                    visibility_name=points.source)
    return {v: restrict_sparse_depth(sd, points.roles[sd.point_index] == role) for v, sd in full.items()}


def score_sparse_depth(dataset, views: Sequence[int]) -> dict | None:
    """What scores the depth of ``views`` of a scene without exact depth maps: {view: SparseDepth}
    of its SCORE capture points (``sparse_depth_for_role``), or None when the scene has exact depth
    maps (they score instead) or no SfM points. The one rule eval and the benchmark runner use."""
    if getattr(dataset, "depths", None) is not None:
        return None
    points = load_capture_points(dataset)
    return None if points is None else sparse_depth_for_role(dataset, points, views, SCORE)


def restrict_sparse_depth(sd, keep: np.ndarray):
    """A SparseDepth with only the entries where ``keep`` [M] is True."""
    keep = np.asarray(keep, dtype=bool)
    return replace(sd, rows=sd.rows[keep], cols=sd.cols[keep], uv=sd.uv[keep], depth=sd.depth[keep],
                   point_index=sd.point_index[keep])


def rays_through_points(cameras, near, far, sparse: dict):
    """Rays through the pixels (continuous uv) of {view: SparseDepth} of ``cameras`` (bounds
    ``near``/``far``: floats or [V]) and the points' camera-z depths: (RayBundle [N], [N] float64).
    None when no view holds a point."""
    views = [v for v, sd in sparse.items() if len(sd)]
    if not views:
        return None
    idx = torch.cat([torch.full((len(sparse[v]),), v, dtype=torch.long) for v in views])
    uv = torch.cat([torch.from_numpy(sparse[v].uv) for v in views]).float()
    depth = np.concatenate([sparse[v].depth for v in views])
    return generate_rays_at(cameras, idx, uv, near, far), depth
