"""Offscreen pictures of point clouds coloured by uncertainty (numpy splatting + matplotlib).

Open3D's ``OffscreenRenderer`` needs EGL/Vulkan, which headless CPU machines often lack (here it
fails with "Failed to load vulkan library"; on some drivers it crashes the process instead of
raising), so clouds are drawn by a small software renderer that needs nothing but numpy:

* A virtual pinhole camera looks at the cloud's centre (per-axis median) from ``eye_direction``
  (default: ``elev``/``azim`` around ``up``), far enough for the 95th-percentile radius
  of the cloud to fill the field of view.
* Every point is splatted as a disk whose radius is its world size (``splat_size``, default
  the cloud's median ``footprint`` attribute, else 1/400 of the cloud's extent) projected to
  pixels, between 1 and ``MAX_SPLAT_RADIUS_PX``; a z-buffer keeps the nearest point per pixel.
* Colour = ``cmap((value - vmin) / (vmax - vmin))``, optionally shaded by the normals with a
  headlight (``ambient + (1 - ambient) |n . v|``) so shapes read in 3D; the colour bar shows the
  unshaded map with the quantity and units.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import matplotlib
import matplotlib.pyplot as plt

from ..io_utils import atomic_path
from .pointcloud import CloudArrays, uncertainty_range

#: Largest splat radius in pixels (bounds the work: candidates per point ~ pi r^2).
MAX_SPLAT_RADIUS_PX: int = 4
#: Light not coming from the headlight (0: pure Lambert, 1: no shading).
SHADING_AMBIENT: float = 0.55
#: Relative size below which a direction counts as degenerate (view axis parallel to ``up``;
#: a point in the camera's own plane): far above float64 round-off (~1e-16), far below any
#: meaningful angle or depth ratio in a picture.
DEGENERATE_FRACTION: float = 1e-9


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera [4, 4] at ``eye`` looking at ``target`` with image-up along ``up``."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < DEGENERATE_FRACTION:  # looking along up: any perpendicular will do
        right = np.cross(fwd, np.array([1.0, 0.0, 0.0]) if abs(fwd[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def splat(points: np.ndarray, colours: np.ndarray, world_to_camera: np.ndarray, focal: float, size: tuple[int, int],
          radius_world: np.ndarray | float, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Z-buffered disk splats: points [N, 3], colours [N, 3] in [0, 1] -> image [H, W, 3] float.

    Pinhole with the principal point at the image centre; a point of world radius r at camera
    depth z covers the pixels within ``clip(focal r / z, 1, MAX_SPLAT_RADIUS_PX)`` of its projection.
    """
    W, H = size
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = cam[:, 2]
    front = z > DEGENERATE_FRACTION * max(float(np.abs(z).max(initial=0.0)), 1.0)
    cam, z, colours = cam[front], z[front], colours[front]
    r_world = np.broadcast_to(np.asarray(radius_world, dtype=np.float64), front.shape)[front]
    u = focal * cam[:, 0] / z + W / 2.0
    v = focal * cam[:, 1] / z + H / 2.0
    r_px = np.clip(focal * r_world / z, 1.0, MAX_SPLAT_RADIUS_PX)
    R = MAX_SPLAT_RADIUS_PX
    offsets = [(dx, dy) for dy in range(-R, R + 1) for dx in range(-R, R + 1) if dx * dx + dy * dy <= R * R]
    pix, depth, src = [], [], []
    ui, vi = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    for dx, dy in offsets:
        ok = (dx * dx + dy * dy) <= r_px ** 2
        x, y = ui + dx, vi + dy
        ok &= (x >= 0) & (x < W) & (y >= 0) & (y < H)
        idx = np.flatnonzero(ok)
        pix.append(y[idx] * W + x[idx])
        depth.append(z[idx])
        src.append(idx)
    image = np.empty((H * W, 3))
    image[:] = background
    if pix:
        pix_a, depth_a, src_a = np.concatenate(pix), np.concatenate(depth), np.concatenate(src)
        order = np.lexsort((depth_a, pix_a))  # by pixel, nearest first
        pix_s = pix_a[order]
        first = np.r_[True, pix_s[1:] != pix_s[:-1]]
        image[pix_s[first]] = colours[src_a[order][first]]
    return image.reshape(H, W, 3)


def render_cloud_png(path: str | Path, cloud: CloudArrays, *, quantity: str = "depth_std",
                     value_range: tuple[float, float] | None = None, cmap: str = "viridis", title: str = "",
                     up=(0.0, 0.0, 1.0), eye_direction=None, elev: float = 30.0, azim: float = -60.0,
                     fov_deg: float = 40.0, splat_size: float | None = None, shade: bool = True,
                     size_px: tuple[int, int] = (1200, 900)) -> Path:
    """Write a PNG of ``cloud`` coloured by attribute ``quantity`` with a colour bar (atomic).

    ``value_range`` defaults to :func:`~.pointcloud.uncertainty_range` (0 to the 99th percentile).
    ``eye_direction``: world vector from the cloud's centre towards the eye; default from
    ``elev``/``azim`` (degrees) around ``up``. Returns the path.
    """
    matplotlib.use("Agg", force=False)
    if len(cloud) == 0:
        raise ValueError(f"render_cloud_png({path}): the cloud is empty")
    if quantity not in cloud.attributes:
        raise ValueError(f"render_cloud_png: no attribute {quantity!r}; have {sorted(cloud.attributes)}")
    pts = np.asarray(cloud.positions, dtype=np.float64)
    vals = cloud.attributes[quantity].astype(np.float64)
    lo, hi = uncertainty_range(vals) if value_range is None else (float(value_range[0]), float(value_range[1]))
    centre = np.median(pts, axis=0)
    radius = float(np.percentile(np.linalg.norm(pts - centre, axis=1), 95)) or 1.0
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    if eye_direction is None:
        a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        el, az = math.radians(elev), math.radians(azim)
        eye_dir = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up
    else:
        eye_dir = np.asarray(eye_direction, dtype=np.float64)
        eye_dir = eye_dir / np.linalg.norm(eye_dir)
    W, H = size_px
    fov = math.radians(fov_deg)
    dist = 1.05 * radius / math.sin(fov / 2.0)
    w2c = _look_at(centre + dist * eye_dir, centre, up)
    focal = 0.5 * min(W, H) / math.tan(fov / 2.0)
    if splat_size is None:
        fp = cloud.attributes.get("footprint")
        splat_size = float(np.median(fp)) if fp is not None and len(fp) else 2.0 * radius / 400.0
    colours = matplotlib.colormaps[cmap](np.clip((vals - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0))[:, :3]
    if shade:
        view = centre + dist * eye_dir - pts
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        lambert = np.abs(np.sum(np.asarray(cloud.normals, dtype=np.float64) * view, axis=1))
        colours = colours * (SHADING_AMBIENT + (1.0 - SHADING_AMBIENT) * lambert)[:, None]
    image = splat(pts, colours, w2c, focal, (W, H), 0.75 * splat_size)
    dpi = 150
    fig = plt.figure(figsize=(W / dpi + 1.6, H / dpi + 0.5), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, W / (W + 1.6 * dpi), H / (H + 0.5 * dpi)))
    ax.imshow(np.clip(image, 0.0, 1.0), interpolation="nearest")
    ax.set_axis_off()
    units = cloud.metadata.get("units", "scene units")
    cax = fig.add_axes((W / (W + 1.6 * dpi) + 0.02, 0.12, 0.025, 0.7))
    sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(lo, hi), cmap=cmap)
    cb = fig.colorbar(sm, cax=cax)
    cb.set_label(f"{quantity.replace('_', ' ')} [{units}]", fontsize=9)
    cb.ax.tick_params(labelsize=8)
    fig.suptitle(title or f"{len(cloud):,} points coloured by {quantity.replace('_', ' ')}", fontsize=10,
                 x=0.5 * W / (W + 1.6 * dpi), y=0.99)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)
