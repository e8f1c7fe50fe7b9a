"""Point clouds with per-point depth uncertainty, from per-view depth products.

Every valid pixel (``opacity >= min_opacity``) becomes one world point:

    x_cam = depth * ((u - cx) / fx, (v - cy) / fy, 1)      (kornia unproject_points, pixel centres)
    x_world = R^T (x_cam - t)                               (kornia transform_points, camera-to-world)

Per-point attributes (float32 unless noted):

* ``depth``: camera-z mean depth of the pixel in its view [units].
* ``depth_std``: total camera-z depth std (epistemic + termination spread) [units];
  ``depth_var`` = depth_std^2 [units^2].
* ``confidence`` in (0, 1]: ``exp(-(depth_std / depth) / CONFIDENCE_REL_STD_SCALE)``, a
  decreasing function of the *relative* std, so near and far points are ranked on the same
  footing (a pixel's footprint and typical depth error grow with depth). 1 = no spread;
  1/e when the std is CONFIDENCE_REL_STD_SCALE (5%) of the depth.
* ``opacity``: accumulated opacity of the pixel's ray (probability it hits a surface).
* ``footprint``: lateral size of the pixel at that depth, ``depth / sqrt(fx fy)`` [units].
* ``view``, ``row``, ``col`` (int32): the pixel the point came from.
* optional ``cov_xx, cov_xy, ..., cov_zz`` (9 floats, row-major 3x3, world frame) [units^2]:
  ``Sigma = var_t d d^T + s_lat^2 (I - d d^T)`` with ``d`` the unit ray direction,
  ``var_t = (depth_std / z_scale)^2`` the variance along the ray (ray distance) and
  ``s_lat^2 = footprint^2 / 12`` the variance of a uniform position across one pixel.

Normals come from the depth map: the cross product of the horizontal and vertical differences
of neighbouring back-projected points, each taken on the side (forward or backward) whose
neighbour is valid and closer, so normals do not smear across depth edges; pixels without a
valid neighbour on an axis get the direction towards the camera. Normals point towards the
camera (``n . (c - x) >= 0``).

Files: binary little-endian PLY written with numpy (:func:`write_ply`): ``x y z`` float,
``nx ny nz`` float, ``red green blue`` uchar, then the attributes above by name. Open3D
(``o3d.t.io.read_point_cloud``), trimesh and common viewers read it with every attribute.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from kornia.geometry.camera.perspective import unproject_points
from kornia.geometry.linalg import transform_points
import matplotlib

from ..cameras import invert_rigid, pixel_centres
from ..io_utils import atomic_path
from .depth_maps import DepthProducts
from .export_options import PointFilter  # noqa: F401  (re-exported)

#: Relative depth std at which ``confidence`` = 1/e (see module doc).
CONFIDENCE_REL_STD_SCALE: float = 0.05
#: Perceptual colour map for colouring by uncertainty.
UNCERTAINTY_CMAP: str = "viridis"
#: Names of the 9 covariance attributes (row-major 3x3, world axes).
COVARIANCE_NAMES: tuple[str, ...] = tuple(f"cov_{a}{b}" for a in "xyz" for b in "xyz")
#: Integer attributes (written as PLY ``int``).
INT_ATTRIBUTES: frozenset[str] = frozenset({"view", "row", "col", "count"})

ColourBy = Literal["rgb", "uncertainty"]


@dataclass
class CloudArrays:
    """A point cloud in numpy: positions [N, 3] float64 (world), normals [N, 3] float32,
    rgb [N, 3] float32 in [0, 1] (rendered colour), attributes name -> [N] (float32 or int32),
    metadata (units, colour mapping, ...)."""

    positions: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def select(self, mask_or_index: np.ndarray) -> "CloudArrays":
        """The points at a bool mask [N] or index array."""
        m = np.asarray(mask_or_index)
        return replace(self, positions=self.positions[m], normals=self.normals[m], rgb=self.rgb[m],
                       attributes={k: v[m] for k, v in self.attributes.items()}, metadata=dict(self.metadata))

    @staticmethod
    def concatenate(clouds: Sequence["CloudArrays"]) -> "CloudArrays":
        """One cloud holding all points; attributes present in every cloud are kept."""
        if not clouds:
            return empty_cloud()
        keys = [k for k in clouds[0].attributes if all(k in c.attributes for c in clouds)]
        return CloudArrays(
            positions=np.concatenate([c.positions for c in clouds]),
            normals=np.concatenate([c.normals for c in clouds]),
            rgb=np.concatenate([c.rgb for c in clouds]),
            attributes={k: np.concatenate([c.attributes[k] for c in clouds]) for k in keys},
            metadata=dict(clouds[0].metadata),
        )


def empty_cloud() -> CloudArrays:
    return CloudArrays(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), {}, {})


# ------------------------------------------------------------------------------- geometry
def backproject_map(depth: torch.Tensor | np.ndarray, intrinsics, world_to_camera) -> torch.Tensor:
    """World points of every pixel centre of a camera-z depth map with kornia.

    Shapes: depth [H, W], intrinsics [3, 3], world_to_camera [4, 4] -> [H, W, 3] (float64).
    """
    depth = torch.as_tensor(np.asarray(depth), dtype=torch.float64)
    if depth.ndim != 2:
        raise ValueError(f"backproject_map: depth must be [H, W], got {tuple(depth.shape)}")
    K = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float64)
    w2c = torch.as_tensor(np.asarray(world_to_camera), dtype=torch.float64)
    if K.shape != (3, 3) or w2c.shape != (4, 4):
        raise ValueError(f"backproject_map: intrinsics must be [3, 3] and world_to_camera [4, 4], "
                         f"got {tuple(K.shape)} and {tuple(w2c.shape)}")
    H, W = depth.shape
    uv = pixel_centres(H, W, dtype=torch.float64)  # [H, W, 2]
    cam = unproject_points(uv.reshape(-1, 2), depth.reshape(-1, 1), K[None])  # [HW, 3], z = depth
    world = transform_points(invert_rigid(w2c)[None], cam[None])[0]
    return world.reshape(H, W, 3)


def _one_sided(points: torch.Tensor, valid: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Difference to the neighbour along ``dim`` (forward or backward, whichever is valid and
    nearer): ([H, W, 3] difference in the +dim direction, [H, W] bool ok)."""
    fwd = torch.zeros_like(points)
    bwd = torch.zeros_like(points)
    ok_f = torch.zeros_like(valid)
    ok_b = torch.zeros_like(valid)
    n = points.shape[dim]
    a = [slice(None)] * 2
    b = [slice(None)] * 2
    a[dim], b[dim] = slice(0, n - 1), slice(1, n)
    a, b = tuple(a), tuple(b)
    diff = points[b] - points[a]  # x[i+1] - x[i]
    both = valid[a] & valid[b]
    fwd[a], ok_f[a] = diff, both  # at i: x[i+1] - x[i]
    bwd[b], ok_b[b] = diff, both  # at i+1: x[i+1] - x[i]
    use_b = ok_b & (~ok_f | (bwd.norm(dim=-1) < fwd.norm(dim=-1)))
    out = torch.where(use_b[..., None], bwd, fwd)
    return out, (ok_f | ok_b) & valid


def depth_map_normals(points: torch.Tensor, valid: torch.Tensor, camera_centre: torch.Tensor) -> torch.Tensor:
    """Unit normals [H, W, 3] of back-projected points [H, W, 3] (see module doc).

    ``n = normalize(dx x dy)`` with dx, dy the column/row differences, flipped so that
    ``n . (c - x) >= 0``; pixels without a valid neighbour on either axis (or a degenerate
    cross product) get ``normalize(c - x)``.
    """
    dx, okx = _one_sided(points, valid, 1)
    dy, oky = _one_sided(points, valid, 0)
    n = torch.cross(dx, dy, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    to_cam = camera_centre.to(points) - points
    to_cam = to_cam / to_cam.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(points.dtype).tiny)
    good = okx & oky & (norm[..., 0] > 0)
    n = torch.where(good[..., None], n / norm.clamp_min(torch.finfo(points.dtype).tiny), to_cam)
    flip = (n * to_cam).sum(-1, keepdim=True) < 0
    return torch.where(flip, -n, n)


def confidence_from_std(depth_std: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``exp(-(std / depth) / CONFIDENCE_REL_STD_SCALE)`` in (0, 1] (see module doc)."""
    depth = np.asarray(depth, dtype=np.float64)
    rel = np.asarray(depth_std, dtype=np.float64) / np.where(depth > 0, depth, np.inf)
    return np.exp(-rel / CONFIDENCE_REL_STD_SCALE)


def point_covariances(directions: np.ndarray, var_ray: np.ndarray, var_lateral: np.ndarray) -> np.ndarray:
    """``Sigma = var_ray d d^T + var_lateral (I - d d^T)``: directions [N, 3] (unit), variances
    [N] -> [N, 3, 3] (symmetric, eigenvalues var_ray once and var_lateral twice)."""
    d = np.asarray(directions, dtype=np.float64)
    ddT = d[:, :, None] * d[:, None, :]
    eye = np.eye(3)[None]
    return var_ray[:, None, None] * ddT + var_lateral[:, None, None] * (eye - ddT)


# ------------------------------------------------------------------------------- construction
def cloud_from_products(products: DepthProducts, *, view: int = 0, mask: np.ndarray | None = None,
                        covariance: bool = False) -> CloudArrays:
    """One point per pixel of ``mask`` (default ``products.valid``), row-major order.

    Positions from the mean depth; attributes and (optionally) covariances as in the module doc.
    """
    mask = products.valid if mask is None else np.asarray(mask, bool)
    depth = torch.from_numpy(products.depth_mean.astype(np.float64))
    valid_t = torch.from_numpy(mask)
    pts = backproject_map(depth, products.intrinsics, products.world_to_camera)  # [H, W, 3]
    centre = invert_rigid(torch.from_numpy(products.world_to_camera))[:3, 3]
    normals = depth_map_normals(pts, valid_t, centre)
    rows, cols = np.nonzero(mask)
    z = products.depth_mean[mask].astype(np.float64)
    std = products.depth_std[mask].astype(np.float64)
    fx, fy = products.intrinsics[0, 0], products.intrinsics[1, 1]
    footprint = z / math.sqrt(fx * fy)
    attrs = {
        "depth": z.astype(np.float32),
        "depth_std": std.astype(np.float32),
        "depth_var": (std ** 2).astype(np.float32),
        "confidence": confidence_from_std(std, z).astype(np.float32),
        "opacity": products.opacity[mask].astype(np.float32),
        "footprint": footprint.astype(np.float32),
        "view": np.full(rows.shape, view, dtype=np.int32),
        "row": rows.astype(np.int32),
        "col": cols.astype(np.int32),
    }
    positions = pts.numpy()[mask]
    if covariance:
        centre_np = centre.numpy()
        ray = positions - centre_np
        dist = np.linalg.norm(ray, axis=-1)
        d = ray / np.where(dist > 0, dist, 1.0)[:, None]
        z_scale = np.where(dist > 0, z / np.where(dist > 0, dist, 1.0), 1.0)  # cos(angle to the axis)
        cov = point_covariances(d, (std / z_scale) ** 2, footprint ** 2 / 12.0).reshape(-1, 9)
        for k, name in enumerate(COVARIANCE_NAMES):
            attrs[name] = cov[:, k].astype(np.float32)
    return CloudArrays(
        positions=positions,
        normals=normals.numpy()[mask].astype(np.float32),
        rgb=products.colour_mean[mask].astype(np.float32),
        attributes=attrs,
        metadata={"units": products.units},
    )


# ------------------------------------------------------------------------------- filters


def most_confident(confidence: np.ndarray, fraction: float) -> np.ndarray:
    """Bool mask [N] of the ``ceil(fraction N)`` highest-confidence points (stable ties)."""
    n = len(confidence)
    keep_n = int(math.ceil(fraction * n))
    order = np.argsort(-np.asarray(confidence, dtype=np.float64), kind="stable")
    mask = np.zeros(n, dtype=bool)
    mask[order[:keep_n]] = True
    return mask


def filter_cloud(cloud: CloudArrays, flt: PointFilter) -> tuple[CloudArrays, dict[str, int]]:
    """(kept cloud, counts after each stage: input, opacity, std, rel_std, keep_fraction)."""
    a = cloud.attributes
    keep = np.ones(len(cloud), dtype=bool)
    counts = {"input": len(cloud)}
    if flt.min_opacity is not None:
        keep &= a["opacity"] >= flt.min_opacity
    counts["opacity"] = int(keep.sum())
    if flt.max_std is not None:
        keep &= a["depth_std"] <= flt.max_std
    counts["std"] = int(keep.sum())
    if flt.max_rel_std is not None:
        keep &= a["depth_std"] <= flt.max_rel_std * a["depth"]
    counts["rel_std"] = int(keep.sum())
    if flt.keep_fraction is not None:
        idx = np.flatnonzero(keep)
        sub = most_confident(a["confidence"][idx], flt.keep_fraction)
        keep = np.zeros_like(keep)
        keep[idx[sub]] = True
    counts["keep_fraction"] = int(keep.sum())
    return cloud.select(keep), counts


# ------------------------------------------------------------------------------- colours
def uncertainty_range(values: np.ndarray) -> tuple[float, float]:
    """Colour-map range of an uncertainty: [0, 99th percentile] (0, 1 when empty)."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0.0, 1.0
    hi = float(np.percentile(values, 99))
    return 0.0, hi if hi > 0 else 1.0


def point_colours(cloud: CloudArrays, colour_by: ColourBy = "rgb", *, value_range: tuple[float, float] | None = None,
                  quantity: str = "depth_std", cmap: str = UNCERTAINTY_CMAP) -> tuple[np.ndarray, dict]:
    """(uint8 colours [N, 3], mapping description). ``rgb``: the rendered colour;
    ``uncertainty``: ``cmap((value - vmin) / (vmax - vmin))`` of ``quantity`` clipped to the range
    (default :func:`uncertainty_range`). The description records what was mapped and how."""
    if colour_by == "rgb":
        rgb = np.clip(np.asarray(cloud.rgb, dtype=np.float64), 0.0, 1.0)
        return (rgb * 255.0 + 0.5).astype(np.uint8), {"colour_by": "rgb"}
    if colour_by != "uncertainty":
        raise ValueError(f"colour_by must be 'rgb' or 'uncertainty', got {colour_by!r}")
    if quantity not in cloud.attributes:
        raise ValueError(f"cannot colour by {quantity!r}: the cloud has {sorted(cloud.attributes)}")
    values = cloud.attributes[quantity].astype(np.float64)
    lo, hi = uncertainty_range(values) if value_range is None else (float(value_range[0]), float(value_range[1]))
    if not hi > lo:
        raise ValueError(f"colour range must have vmax > vmin, got ({lo}, {hi})")
    rgba = matplotlib.colormaps[cmap](np.clip((values - lo) / (hi - lo), 0.0, 1.0))
    desc = {"colour_by": "uncertainty", "quantity": quantity, "cmap": cmap, "vmin": lo, "vmax": hi,
            "units": cloud.metadata.get("units", "scene units"), "clipped": True}
    return (rgba[:, :3] * 255.0 + 0.5).astype(np.uint8), desc


# ------------------------------------------------------------------------------- open3d / PLY
def to_open3d(cloud: CloudArrays, colour_by: ColourBy = "rgb", *, value_range: tuple[float, float] | None = None):
    """``open3d.t.geometry.PointCloud`` with positions (float32), normals, uint8 colors and every
    attribute as an [N, 1] tensor."""
    import open3d as o3d  # heavy optional dependency (Open3D): loaded only when used

    colours, _ = point_colours(cloud, colour_by, value_range=value_range)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(cloud.positions.astype(np.float32))
    pc.point.normals = o3d.core.Tensor(cloud.normals.astype(np.float32))
    pc.point.colors = o3d.core.Tensor(colours)
    for name, values in cloud.attributes.items():
        pc.point[name] = o3d.core.Tensor(np.ascontiguousarray(values.reshape(-1, 1)))
    return pc


def _ply_type(dtype: np.dtype) -> tuple[str, str]:
    if dtype == np.uint8:
        return "uchar", "u1"
    if np.issubdtype(dtype, np.integer):
        return "int", "<i4"
    return "float", "<f4"


def write_ply(path: str | Path, cloud: CloudArrays, colour_by: ColourBy = "rgb", *,
              value_range: tuple[float, float] | None = None, comments: Sequence[str] = ()) -> dict:
    """Binary little-endian PLY (atomic). Returns the colour mapping description, which is also
    written as header comments (``comment colour_by=... vmin=... vmax=...``)."""
    colours, desc = point_colours(cloud, colour_by, value_range=value_range)
    columns: list[tuple[str, np.ndarray]] = [("x", cloud.positions[:, 0]), ("y", cloud.positions[:, 1]),
                                             ("z", cloud.positions[:, 2]), ("nx", cloud.normals[:, 0]),
                                             ("ny", cloud.normals[:, 1]), ("nz", cloud.normals[:, 2]),
                                             ("red", colours[:, 0]), ("green", colours[:, 1]), ("blue", colours[:, 2])]
    for name, values in cloud.attributes.items():
        if not name.isidentifier():
            raise ValueError(f"PLY attribute name {name!r} must be an identifier")
        values = np.asarray(values)
        if values.shape != (len(cloud),):
            raise ValueError(f"attribute {name!r} has shape {values.shape}, expected ({len(cloud)},)")
        if name in INT_ATTRIBUTES:
            values = values.astype(np.int32)
        columns.append((name, values))
    dtype = []
    header = ["ply", "format binary_little_endian 1.0", "comment written by stochastic-fields"]
    header += [f"comment {k}={v}" for k, v in desc.items()]
    header += [f"comment {c}" for c in comments]
    header.append(f"element vertex {len(cloud)}")
    for name, values in columns:
        ply_t, np_t = _ply_type(np.asarray(values).dtype) if name not in ("red", "green", "blue") else ("uchar", "u1")
        dtype.append((name, np_t))
        header.append(f"property {ply_t} {name}")
    header.append("end_header")
    data = np.empty(len(cloud), dtype=dtype)
    for name, values in columns:
        data[name] = values
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            fh.write(data.tobytes())
    return desc


def read_ply(path: str | Path) -> tuple[CloudArrays, np.ndarray]:
    """(cloud, uint8 colours [N, 3]) read back with Open3D (attributes as [N] arrays)."""
    import open3d as o3d  # heavy optional dependency (Open3D): loaded only when used

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    pc = o3d.t.io.read_point_cloud(str(path))
    n = pc.point.positions.shape[0]
    attrs = {}
    for name in pc.point:
        if name in ("positions", "normals", "colors"):
            continue
        attrs[name] = pc.point[name].numpy().reshape(n)
    positions = pc.point.positions.numpy().astype(np.float64)
    normals = pc.point.normals.numpy() if "normals" in pc.point else np.zeros((n, 3), np.float32)
    colours = pc.point.colors.numpy() if "colors" in pc.point else np.zeros((n, 3), np.uint8)
    rgb = colours.astype(np.float32) / 255.0 if colours.dtype == np.uint8 else colours.astype(np.float32)
    return CloudArrays(positions, normals, rgb, attrs, {}), colours
