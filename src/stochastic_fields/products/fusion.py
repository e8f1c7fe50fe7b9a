"""Fuse the point clouds of many views into one, by inverse-variance weighting per voxel.

Points are binned into cubic voxels of side ``voxel_size`` (key ``floor(x / voxel_size)``);
the points ``i`` of one voxel, with depth variances ``v_i`` (``depth_var``, floored at
PRODUCT_DEPTH_VARIANCE_FLOOR) and weights ``w_i = 1 / v_i``, become one point:

    x     = sum_i w_i x_i / sum_i w_i          (positions, and the same for rgb colours)
    var   = 1 / sum_i w_i                      (fused variance: independent Gaussian measurements)
    n     = normalize(sum_i w_i n_i)           (normals; if they cancel, the best point's normal)
    opacity, footprint, depth = weighted means;  confidence recomputed from sqrt(var) / depth
    count = number of points merged (int)
    cov   = sum_i w_i^2 Sigma_i / (sum_i w_i)^2  (if every point has cov_*: the covariance of the
            weighted mean above, for independent points)

Default voxel size: ``VOXEL_FOOTPRINTS`` times the median pixel footprint (``depth / f``) of
the input points, so a voxel holds about one pixel of each view that sees it.
"""

from __future__ import annotations

import numpy as np

from ..constants import PRODUCT_DEPTH_VARIANCE_FLOOR
from .pointcloud import COVARIANCE_NAMES, CloudArrays, confidence_from_std

#: Largest voxel index per axis: floor(x / voxel_size) stays exact in float64 and int64 far below it.
MAX_VOXEL_INDEX: float = 2.0**40
#: Default voxel side in median pixel footprints.
VOXEL_FOOTPRINTS: float = 1.0


def check_voxel_size(voxel_size: float, reach: float) -> None:
    """ValueError unless ``voxel_size`` is positive, finite and keeps the voxel index of every
    point within ``reach`` scene units of the origin below ``MAX_VOXEL_INDEX``."""
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be a positive number, got {voxel_size}")
    if reach / voxel_size >= MAX_VOXEL_INDEX:
        raise ValueError(f"voxel_size {voxel_size} is too small for a scene reaching {reach:.4g} units from the "
                         f"origin (voxel indices past {MAX_VOXEL_INDEX:.0e}); use >= {reach / MAX_VOXEL_INDEX:.3g}")


def default_voxel_size(cloud: CloudArrays) -> float:
    """``VOXEL_FOOTPRINTS * median(footprint)``; ValueError if the cloud has no footprint."""
    if "footprint" not in cloud.attributes or len(cloud) == 0:
        raise ValueError("default voxel size needs a non-empty cloud with a 'footprint' attribute; pass voxel_size")
    size = float(VOXEL_FOOTPRINTS * np.median(cloud.attributes["footprint"]))
    if not size > 0:
        raise ValueError(f"median pixel footprint is {size}; pass a positive voxel_size")
    return size


def _weighted_mean(values: np.ndarray, w: np.ndarray, inverse: np.ndarray, m: int, wsum: np.ndarray) -> np.ndarray:
    """Per-voxel sum_i w_i v_i / sum_i w_i for values [N] or [N, C]."""
    v = values.astype(np.float64)
    if v.ndim == 1:
        return np.bincount(inverse, weights=w * v, minlength=m) / wsum
    sums = [np.bincount(inverse, weights=w * v[:, c], minlength=m) for c in range(v.shape[1])]
    return np.stack(sums, 1) / wsum[:, None]


def fuse_clouds(clouds: list[CloudArrays] | CloudArrays, voxel_size: float | None = None) -> tuple[CloudArrays, dict]:
    """Fuse clouds (see module doc). Returns (fused cloud, report) where report holds
    ``input`` (points in), ``fused`` (points out), ``voxel_size``, ``max_count``."""
    cloud = clouds if isinstance(clouds, CloudArrays) else CloudArrays.concatenate(list(clouds))
    size = default_voxel_size(cloud) if voxel_size is None else float(voxel_size)
    if not (np.isfinite(size) and size > 0):
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    if len(cloud) == 0:
        return cloud, {"input": 0, "fused": 0, "voxel_size": size, "max_count": 0}
    if "depth_var" not in cloud.attributes:
        raise ValueError("fuse_clouds needs the per-point 'depth_var' attribute")
    check_voxel_size(size, float(np.abs(cloud.positions).max()))
    keys = np.floor(cloud.positions / size).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    m = len(first)
    w = 1.0 / np.maximum(cloud.attributes["depth_var"].astype(np.float64), PRODUCT_DEPTH_VARIANCE_FLOOR)
    wsum = np.bincount(inverse, weights=w, minlength=m)
    positions = _weighted_mean(cloud.positions, w, inverse, m, wsum)
    rgb = _weighted_mean(cloud.rgb, w, inverse, m, wsum).astype(np.float32)
    nsum = _weighted_mean(cloud.normals, w, inverse, m, wsum)
    nnorm = np.linalg.norm(nsum, axis=1, keepdims=True)
    best = np.zeros(m, dtype=np.int64)  # highest-weight point of each voxel
    order = np.lexsort((w, inverse))  # by voxel, then weight ascending: the last per voxel is the best
    inv_sorted = inverse[order]
    last = np.r_[inv_sorted[1:] != inv_sorted[:-1], True]
    best[inv_sorted[last]] = order[last]
    normals = np.where(nnorm > 0, nsum / np.where(nnorm > 0, nnorm, 1.0), cloud.normals[best]).astype(np.float32)
    var = 1.0 / wsum
    attrs: dict[str, np.ndarray] = {}
    a = cloud.attributes
    depth = _weighted_mean(a["depth"], w, inverse, m, wsum) if "depth" in a else None
    if depth is not None:
        attrs["depth"] = depth.astype(np.float32)
    attrs["depth_std"] = np.sqrt(var).astype(np.float32)
    attrs["depth_var"] = var.astype(np.float32)
    if depth is not None:
        attrs["confidence"] = confidence_from_std(np.sqrt(var), depth).astype(np.float32)
    for name in ("opacity", "footprint"):
        if name in a:
            attrs[name] = _weighted_mean(a[name], w, inverse, m, wsum).astype(np.float32)
    attrs["count"] = np.bincount(inverse, minlength=m).astype(np.int32)
    if all(n in a for n in COVARIANCE_NAMES):
        w2 = w * w / (wsum[inverse] ** 2)
        for n in COVARIANCE_NAMES:
            attrs[n] = np.bincount(inverse, weights=w2 * a[n].astype(np.float64), minlength=m).astype(np.float32)
    fused = CloudArrays(positions, normals, rgb, attrs, {**cloud.metadata, "voxel_size": size})
    return fused, {"input": len(cloud), "fused": m, "voxel_size": size, "max_count": int(attrs["count"].max())}
