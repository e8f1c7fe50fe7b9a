"""Occupancy with probabilities for planners: a voxel map of P(occupied) over the scene region.

(Not the renderer's empty-space-skipping grid in ``occupancy.py``: that one is a conservative
bitfield for sampling; this one is a product with calibrated-as-the-model probabilities.)

Per voxel centre x the field gives the rectified normal ``alpha = relu(mu(x) + s(x) eps)``, so
for a density threshold tau >= 0 (closed form, no sampling):

    P(alpha(x) > tau) = P(mu + s eps > tau) = Phi((mu - tau) / s)

The default threshold asks "would a straight crossing of length ell through density like this
be blocked": opacity ``1 - exp(-alpha ell) >= blocked_opacity`` (default 0.5), i.e.

    tau = -log(1 - blocked_opacity) / ell,    ell = blocking_length (default: the voxel size).

A field whose surfaces are thinner than a voxel passes the voxel-size test; a diffuse one (a
briefly trained model spreads a surface over several voxels with densities of a few per unit)
does not, and needs the planner's own length (robot size, clearance) as ``blocking_length``.

Resolution: from the images' footprint (the world length one pixel covers at the frustum points
inside the region, median over views: depth / focal length), times ``pixels_per_voxel``, and
coarsened until the region holds at most ``max_cells`` voxels. The grid is aligned to multiples of
the voxel size (OctoMap keys), so the npz and the ``.ot`` file index the same cells.

Storage is sparse: voxels with ``P >= min_probability`` are listed with their probability; a
voxel inside the region that is not listed has ``P < min_probability`` (free); voxels outside the
region are unknown (``inside_region`` mask, bit-packed). Files:

* npz (:func:`write_occupancy_npz`): ``indices`` [N, 3] int32 (i, j, k), ``probability`` [N]
  float32, ``origin`` [3] (world corner of voxel (0, 0, 0)), ``voxel_size``, ``shape`` [3],
  ``inside_region`` (packed bits of the [X, Y, Z] mask), ``frame``, ``units``,
  ``metres_per_unit``, ``density_threshold``, ``min_probability``, ``conventions``.
* OctoMap ``.ot`` (:func:`write_octomap`, via pyoctomap): every voxel inside the region is a node
  whose log-odds is ``log(P / (1 - P))`` with P clamped to [min_probability, 1 - OCTOMAP_CLAMP]
  (free voxels share the floor value, so OctoMap prunes them into large cells); coordinates in
  metres when a metric scale is known, otherwise in scene units (written in the npz).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..fields.base import density_reader
from ..io_utils import atomic_path, atomic_write_text
from ..cameras import image_size, intrinsics_3x3
from ..scene_region import frustum_points
from ..trainer import load_trained_model
from ..defaults import (BLOCKED_OPACITY, OCCUPANCY_MAX_CELLS, OCCUPANCY_PIXELS_PER_VOXEL)  # noqa: F401  (defaults the command line shows)

#: Voxels with a lower probability are not listed (they are free).
OCCUPANCY_MIN_PROBABILITY: float = 1e-3
#: OctoMap clamping: probabilities in (0, 1) are kept up to this distance from 0 and 1.
OCTOMAP_CLAMP: float = 1e-6
#: Points per chunk of field evaluations.
OCCUPANCY_CHUNK: int = 65_536


def probability_density_exceeds(density_loc: Tensor, density_scale: Tensor, threshold: float,
                                density_offsets: Tensor | None = None) -> Tensor:
    """P(relu(mu + s eps) > tau) = Phi((mu - tau) / s) for tau >= 0. Shapes [...] -> [...].
    Example: mu = 1, s = 1, tau = 1 -> 0.5; mu = 0, s = 1, tau = 1.645 -> 0.05.
    With density heads (``density_offsets`` [..., M]) the density is their equal mixture:
    mean_h Phi((mu + o_h - tau) / s)."""
    if not threshold >= 0:
        raise ValueError(f"density threshold must be >= 0, got {threshold}")
    if density_offsets is not None:
        return torch.special.ndtr((density_loc[..., None] + density_offsets - threshold)
                                  / density_scale[..., None]).mean(-1)
    return torch.special.ndtr((density_loc - threshold) / density_scale)


def blocking_threshold(length: float, blocked_opacity: float = BLOCKED_OPACITY) -> float:
    """Density tau above which one straight crossing of ``length`` has opacity >= ``blocked_opacity``:
    ``tau = -log(1 - blocked_opacity) / length`` (log(2) / length for 0.5)."""
    if not 0.0 < blocked_opacity < 1.0:
        raise ValueError(f"blocked_opacity must lie in (0, 1), got {blocked_opacity}")
    if not (length > 0 and math.isfinite(length)):
        raise ValueError(f"blocking length must be a positive length, got {length}")
    return -math.log1p(-blocked_opacity) / length


def region_world_bounds(region) -> tuple[np.ndarray, np.ndarray]:
    """World AABB ([3], [3]) of a SceneRegion: its unit cube's 8 corners mapped to the world (the
    NDC box of a forward-facing scene is a frustum, the convex hull of its corners)."""
    corners = torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    world = region.from_unit(corners.to(region.box.device)).double().cpu().numpy()
    return world.min(0), world.max(0)


def footprint_voxel_size(region, intrinsics: Tensor, w2c: Tensor, height: int, width: int, near: Tensor, far: Tensor,
                         *, pixels_per_voxel: float = OCCUPANCY_PIXELS_PER_VOXEL,
                         max_cells: int = OCCUPANCY_MAX_CELLS) -> float:
    """Cubic voxel size from the images' footprint (module doc), coarsened to ``max_cells``."""
    K = intrinsics[:, :3, :3].float()
    V = w2c.shape[0]
    pts = frustum_points(K, w2c, height, width, near.reshape(-1).expand(V), far.reshape(-1).expand(V), grid=5, depths=8)
    per_view = pts.reshape(V, -1, 3)
    c2w = torch.linalg.inv(w2c.float())
    cam_z = ((per_view - c2w[:, None, :3, 3]) * c2w[:, None, :3, 2]).sum(-1)  # [V, P]
    footprint = (cam_z / K[:, 0, 0][:, None]).reshape(-1)
    inside = region.contains(per_view.reshape(-1, 3))
    if not bool(inside.any()):
        raise ValueError("occupancy: no camera frustum point lies inside the scene region")
    size = float(footprint[inside].median()) * pixels_per_voxel
    lo, hi = region_world_bounds(region)
    cells = float(np.prod(np.ceil((hi - lo) / size)))
    if cells > max_cells:
        size *= (cells / max_cells) ** (1.0 / 3.0)
    return size


@dataclass
class OccupancyMap:
    """A sparse voxel map of P(occupied) (module doc). Arrays are numpy.

    Attributes:
        indices: [N, 3] int32 voxel indices (i, j, k) of the listed voxels (P >= min_probability).
        probability: [N] float32 P(density > density_threshold) at their centres.
        origin: [3] float64 world corner of voxel (0, 0, 0) (a multiple of voxel_size).
        voxel_size: edge length (scene units).
        shape: (X, Y, Z).
        inside_region: [X, Y, Z] bool, voxel centre inside the modelled region (else unknown).
        density_threshold: tau; min_probability: listing floor.
        frame, units, metres_per_unit: world frame name, unit name, metres per unit (None = unknown).
    """

    indices: np.ndarray
    probability: np.ndarray
    origin: np.ndarray
    voxel_size: float
    shape: tuple[int, int, int]
    inside_region: np.ndarray
    density_threshold: float
    min_probability: float = OCCUPANCY_MIN_PROBABILITY
    frame: str = "world"
    units: str = "scene units"
    metres_per_unit: float | None = None

    def centres(self) -> np.ndarray:
        """[N, 3] world centres of the listed voxels."""
        return self.origin + (self.indices.astype(np.float64) + 0.5) * self.voxel_size

    def dense(self, unknown: float = math.nan) -> np.ndarray:
        """[X, Y, Z] float32 probabilities: listed values, 0 for free voxels inside the region
        (P < min_probability), ``unknown`` outside it."""
        out = np.where(self.inside_region, 0.0, unknown).astype(np.float32)
        out[tuple(self.indices.T)] = self.probability
        return out

    def index_of(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] world points -> [N, 3] int voxel indices (may be outside the grid)."""
        return np.floor((np.asarray(points, np.float64) - self.origin) / self.voxel_size).astype(np.int64)


@torch.no_grad()
def occupancy_map(field, region, voxel_size: float, *, density_threshold: float | None = None,
                  blocked_opacity: float = BLOCKED_OPACITY, blocking_length: float | None = None,
                  min_probability: float = OCCUPANCY_MIN_PROBABILITY, chunk: int = OCCUPANCY_CHUNK,
                  progress: bool = False) -> OccupancyMap:
    """Evaluate P(occupied) at the centres of a grid over ``region`` (module doc).

    Args:
        field: anything with ``density_params(points [N, 3]) -> (loc [N], scale [N])`` (world points);
            a field's ``density_head_params`` where it has one (density heads: their mixture).
        region: a SceneRegion (its world AABB is gridded; voxels whose centre is outside are unknown).
        voxel_size: edge length; the origin is floor(lo / voxel_size) * voxel_size.
        density_threshold: tau (default: :func:`blocking_threshold` of ``blocking_length``,
            itself defaulting to ``voxel_size``).
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel size must be positive, got {voxel_size}")
    if density_threshold is None:
        tau = blocking_threshold(blocking_length if blocking_length is not None else voxel_size, blocked_opacity)
    else:
        tau = float(density_threshold)
    lo, hi = region_world_bounds(region)
    origin = np.floor(lo / voxel_size) * voxel_size
    shape = tuple(int(n) for n in np.maximum(np.ceil((hi - origin) / voxel_size).astype(int), 1))
    X, Y, Z = shape
    device = region.box.device
    total = X * Y * Z
    inside = np.zeros(total, bool)
    keep_idx, keep_p = [], []
    o = torch.as_tensor(origin, dtype=torch.float64, device=device)
    read = density_reader(field)
    for start in tqdm(range(0, total, chunk), desc="occupancy", disable=not progress, dynamic_ncols=True):
        flat = torch.arange(start, min(start + chunk, total), device=device)
        ijk = torch.stack([flat // (Y * Z), (flat // Z) % Y, flat % Z], dim=-1)
        centres = (o + (ijk.double() + 0.5) * voxel_size).float()
        ins = region.contains(centres)
        inside[start:start + len(flat)] = ins.cpu().numpy()
        if not bool(ins.any()):
            continue
        loc, scale, offsets = read(centres[ins])
        p = probability_density_exceeds(loc.double(), scale.double(), tau,
                                        None if offsets is None else offsets.double())
        sel = p >= min_probability
        keep_idx.append(ijk[ins][sel].cpu().numpy().astype(np.int32))
        keep_p.append(p[sel].float().cpu().numpy())
    indices = np.concatenate(keep_idx) if keep_idx else np.zeros((0, 3), np.int32)
    prob = np.concatenate(keep_p) if keep_p else np.zeros(0, np.float32)
    return OccupancyMap(indices, prob, origin, float(voxel_size), shape, inside.reshape(shape), tau, min_probability)


OCCUPANCY_CONVENTIONS: str = (
    "probability[n] = P(density > density_threshold) at the centre origin + (indices[n] + 0.5) * voxel_size "
    "(rectified normal, closed form Phi((mu - tau) / s)); density_threshold = -log(1 - blocked_opacity) / "
    "blocking_length (default 0.5 and the voxel size): a straight crossing of that length through such density is "
    "blocked with opacity >= blocked_opacity; voxels inside the region "
    "(inside_region, np.unpackbits(...)[:X*Y*Z].reshape(shape)) that are not listed have P < min_probability; "
    "voxels outside it are unknown; coordinates in the world frame, scene units (x metres_per_unit = metres)")


def write_occupancy_npz(path: str | Path, occ: OccupancyMap) -> Path:
    """Write an :class:`OccupancyMap` as npz (module doc; atomic)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, indices=occ.indices.astype(np.int32), probability=occ.probability.astype(np.float32),
                origin=np.asarray(occ.origin, np.float64), voxel_size=np.float64(occ.voxel_size),
                shape=np.asarray(occ.shape, np.int64), inside_region=np.packbits(occ.inside_region.reshape(-1)),
                density_threshold=np.float64(occ.density_threshold), min_probability=np.float64(occ.min_probability),
                frame=np.str_(occ.frame), units=np.str_(occ.units),
                metres_per_unit=np.float64(np.nan if occ.metres_per_unit is None else occ.metres_per_unit),
                conventions=np.str_(OCCUPANCY_CONVENTIONS))
    return path


def read_occupancy_npz(path: str | Path) -> OccupancyMap:
    """An :class:`OccupancyMap` from :func:`write_occupancy_npz`'s file."""
    z = np.load(Path(path))
    shape = tuple(int(s) for s in z["shape"])
    inside = np.unpackbits(z["inside_region"])[: int(np.prod(shape))].astype(bool).reshape(shape)
    mpu = float(z["metres_per_unit"])
    return OccupancyMap(z["indices"], z["probability"], z["origin"], float(z["voxel_size"]), shape, inside,
                        float(z["density_threshold"]), float(z["min_probability"]), str(z["frame"]), str(z["units"]),
                        None if math.isnan(mpu) else mpu)


def write_octomap(path: str | Path, occ: OccupancyMap) -> Path:
    """Write an OctoMap ``.ot`` (full probabilities, pyoctomap; module doc). Resolution and
    coordinates in metres when ``occ.metres_per_unit`` is known, else scene units. Atomic."""
    import pyoctomap  # heavy optional dependency (pyoctomap): loaded only when used

    path = Path(path)
    if path.suffix != ".ot":
        raise ValueError(f"OctoMap file {path} must end in .ot (the full-probability format)")
    s = occ.metres_per_unit or 1.0
    tree = pyoctomap.OcTree(occ.voxel_size * s)
    tree.setClampingThresMin(OCTOMAP_CLAMP)
    tree.setClampingThresMax(1.0 - OCTOMAP_CLAMP)
    p = occ.dense(unknown=math.nan).reshape(-1)
    X, Y, Z = occ.shape
    flat = np.flatnonzero(occ.inside_region.reshape(-1))
    ijk = np.stack([flat // (Y * Z), (flat // Z) % Y, flat % Z], axis=-1)
    centres = (occ.origin + (ijk + 0.5) * occ.voxel_size) * s
    prob = np.clip(np.maximum(p[flat].astype(np.float64), occ.min_probability), OCTOMAP_CLAMP, 1 - OCTOMAP_CLAMP)
    log_odds = np.log(prob) - np.log1p(-prob)
    for c, lo in zip(centres, log_odds.tolist()):
        tree.updateNode(c, float(lo), lazy_eval=False)  # not lazy: equal siblings are pruned as they fill
    with atomic_path(path) as tmp:
        if not tree.write(str(tmp)):
            raise OSError(f"pyoctomap could not write {path}")
    return path


def occupancy_metadata(occ: OccupancyMap) -> dict:
    """Summary numbers of a map (for summary.json / the CLI)."""
    inside = int(occ.inside_region.sum())
    return {"voxel_size": occ.voxel_size, "shape": list(occ.shape), "origin": np.asarray(occ.origin).tolist(),
            "voxels_inside_region": inside, "voxels_listed": int(len(occ.probability)),
            "voxels_p_above_0.5": int((occ.probability > 0.5).sum()), "density_threshold": occ.density_threshold,
            "min_probability": occ.min_probability, "units": occ.units, "metres_per_unit": occ.metres_per_unit}


def require_stochastic_field(model, run: str | Path, product: str) -> None:
    """ValueError naming ``run`` and its model unless it is an S-NeRF run (a stochastic field and its
    region): ``product`` (occupancy maps, free-path answers) integrate the field's random density,
    which the baselines do not have."""
    if not hasattr(model, "region") or not hasattr(model, "field"):
        raise ValueError(f"{run}: {product} need an S-NeRF run (a stochastic field and its region); "
                         f"this one is {type(model).__name__}")


def run_voxel_size(model, dataset, *, pixels_per_voxel: float = OCCUPANCY_PIXELS_PER_VOXEL,
                   max_cells: int = OCCUPANCY_MAX_CELLS) -> float:
    """The voxel size of a run's occupancy map when none is given: ``footprint_voxel_size`` of the
    dataset's cameras and bounds over the model's region."""
    H, W = image_size(dataset.cameras)
    dev = model.region.box.device
    return footprint_voxel_size(model.region, intrinsics_3x3(dataset.cameras).to(dev),
                                dataset.cameras.extrinsics.to(dev), H, W, dataset.near.to(dev),
                                dataset.far.to(dev), pixels_per_voxel=pixels_per_voxel, max_cells=max_cells)


def occupancy_from_run(run_dir: str | Path, out: str | Path, *, voxel_size: float | None = None,
                       pixels_per_voxel: float = OCCUPANCY_PIXELS_PER_VOXEL, max_cells: int = OCCUPANCY_MAX_CELLS,
                       blocked_opacity: float = BLOCKED_OPACITY, blocking_length: float | None = None,
                       density_threshold: float | None = None, metres_per_unit: float | None = None,
                       octomap: bool = True, device: str | None = None, progress: bool = True) -> dict:
    """``stochastic-fields occupancy``: the occupancy map of a trained run into folder ``out``
    (``occupancy.npz``, ``occupancy.ot``, ``occupancy.json``). Returns the metadata."""
    _, model, dataset = load_trained_model(Path(run_dir), device=device)
    require_stochastic_field(model, run_dir, "occupancy maps")
    if voxel_size is None:
        voxel_size = run_voxel_size(model, dataset, pixels_per_voxel=pixels_per_voxel, max_cells=max_cells)
    occ = occupancy_map(model.field, model.region, voxel_size, blocked_opacity=blocked_opacity,
                        blocking_length=blocking_length, density_threshold=density_threshold, progress=progress)
    occ.metres_per_unit = metres_per_unit
    out = Path(out)
    files = [write_occupancy_npz(out / "occupancy.npz", occ)]
    if octomap:
        files.append(write_octomap(out / "occupancy.ot", occ))
    meta = occupancy_metadata(occ)
    meta["files"] = [p.name for p in files]
    atomic_write_text(out / "occupancy.json", json.dumps(meta, indent=2))
    return meta
