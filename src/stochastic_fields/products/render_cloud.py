"""Offscreen pictures of point clouds coloured by uncertainty.

Backend: a matplotlib 3D scatter on the Agg canvas (no display, no GPU, deterministic), with
a colour bar labelled with the quantity and its units. Open3D's ``OffscreenRenderer`` needs
EGL/Vulkan, which headless CPU machines often lack (here it fails with "Failed to load vulkan
library"), and on some drivers it crashes the process instead of raising, so it is not used.

The view: points farther than the 0.5-99.5th percentile box (per axis, padded 5%) are left
out of the framing; at most ``max_points`` points are drawn (a fixed-seed subsample); equal
axis scale; matplotlib sorts the markers by depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io_utils import atomic_path
from .pointcloud import CloudArrays, uncertainty_range

#: Points drawn at most (a larger cloud is subsampled with a fixed seed).
MAX_POINTS_DRAWN: int = 80_000


def render_cloud_png(path: str | Path, cloud: CloudArrays, *, quantity: str = "depth_std",
                     value_range: tuple[float, float] | None = None, cmap: str = "viridis", title: str = "",
                     elev: float = 35.0, azim: float = -60.0, point_size: float | None = None,
                     max_points: int = MAX_POINTS_DRAWN, size_px: tuple[int, int] = (1200, 900),
                     seed: int = 0) -> Path:
    """Write a PNG of ``cloud`` coloured by attribute ``quantity`` (atomic). Returns the path.

    ``value_range`` defaults to :func:`~.pointcloud.uncertainty_range` (0 to the 99th
    percentile); ``point_size`` (matplotlib marker area in points^2) defaults to a value that
    keeps the cloud's coverage similar whatever the number of points.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if len(cloud) == 0:
        raise ValueError(f"render_cloud_png({path}): the cloud is empty")
    if quantity not in cloud.attributes:
        raise ValueError(f"render_cloud_png: no attribute {quantity!r}; have {sorted(cloud.attributes)}")
    rng = np.random.default_rng(seed)
    idx = np.arange(len(cloud))
    if len(cloud) > max_points:
        idx = np.sort(rng.choice(len(cloud), max_points, replace=False))
    pts = cloud.positions[idx]
    vals = cloud.attributes[quantity][idx].astype(np.float64)
    lo, hi = uncertainty_range(cloud.attributes[quantity]) if value_range is None else value_range
    box_lo, box_hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
    pad = 0.05 * (box_hi - box_lo)
    box_lo, box_hi = box_lo - pad, box_hi + pad
    inside = np.all((pts >= box_lo) & (pts <= box_hi), axis=1)
    pts, vals = pts[inside], vals[inside]
    if point_size is None:
        point_size = float(np.clip(6.0e4 / max(len(pts), 1), 0.3, 8.0))
    dpi = 150
    fig = plt.figure(figsize=(size_px[0] / dpi, size_px[1] / dpi), dpi=dpi)
    ax = fig.add_subplot(111, projection="3d")
    sc = ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=vals, cmap=cmap, vmin=lo, vmax=hi, s=point_size,
                    marker=".", linewidths=0, depthshade=False)
    ax.set_box_aspect(tuple(np.maximum(box_hi - box_lo, 1e-9 * max(float(np.max(box_hi - box_lo)), 1.0))))
    ax.set_xlim(box_lo[0], box_hi[0])
    ax.set_ylim(box_lo[1], box_hi[1])
    ax.set_zlim(box_lo[2], box_hi[2])
    ax.view_init(elev=elev, azim=azim)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_pane_color((0.96, 0.96, 0.96, 1.0))
        axis.set_tick_params(labelsize=6)
    units = cloud.metadata.get("units", "scene units")
    ax.set_xlabel(f"x [{units}]", fontsize=7)
    ax.set_ylabel(f"y [{units}]", fontsize=7)
    ax.set_zlabel(f"z [{units}]", fontsize=7)
    cb = fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12)
    cb.set_label(f"{quantity.replace('_', ' ')} [{units}]", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    ax.set_title(title or f"{len(cloud):,} points coloured by {quantity.replace('_', ' ')}", fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return Path(path)
