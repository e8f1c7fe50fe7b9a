"""The free-space check: a rendered depth against what the training views saw (docs/uncertainty.md, study 13).

A training ray whose rendered surface lies at camera depth D_j(u) passed through empty space before
it: the colours of view j were fitted with that space empty. A depth rendered from any other view
puts a surface point X somewhere in the scene; if X projects into training view j at pixel u in
front of that surface, z_j(X) < D_j(u), the render claims a surface where view j saw none. The
violation

    e(X) = max_j max(0, D_j(u_j(X)) - z_j(X))

over the training views j in front of which X lies inside the image, at pixels with rendered
opacity above ``view_maps.OPACITY_MASK`` (a surface to compare with), is a distance in scene
units (camera z of view j). A point behind view j's surface (occluded there) or on it gives 0, so
occlusion raises nothing. It marks the errors S-NeRF's std misses most: floaters and surfaces
rendered in front of the true one with a small std (docs/uncertainty.md, studies 11 and 12).

The checked std adds it as an independent error component,

    sigma_checked = sqrt(sigma^2 + e^2),

which the depth recalibration then scales like any std (``calibration``). D_j is the model's own
rendered depth of training view j (``render_training_depth``; stored in the run as
``TRAINING_DEPTH_FILE``), not ground truth: a user's capture has none.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from .view_maps import OPACITY_MASK
from .cameras import intrinsics_3x3, invert_rigid
from .capture_points import backproject_pixels
from .io_utils import atomic_write
from .metrics import psnr as image_psnr
from .models.snerf import UNIT_CUBE
from .occupancy import OccupancyGrid
from .renderer import seeded_chunks
from .defaults import TRAINING_DEPTH_FILE  # noqa: F401  (defaults the command line shows)

#: Carving (``carve_free_space``): a training pixel carves only where its ray ended sharply, with
#: opacity above this ...
CARVE_MIN_OPACITY: float = 0.9
#: ... and a termination spread (std along the ray) below this share of its depth (a pixel that
#: mixes a thin foreground and the background has a broad one), ...
CARVE_MAX_SPREAD: float = 0.05
#: ... and a cell is carved when its centre lies in front of D - 3 spread - CARVE_MARGIN D.
CARVE_MARGIN: float = 0.05
#: Cells per axis of the occupancy grid built for carving a model that keeps none.
CARVE_RESOLUTION: int = 128


@dataclass
class TrainingDepth:
    """The model's rendered camera-z depth and opacity of the training views, with their cameras.

    Attributes:
        views: [T] dataset view indices.
        intrinsics: [T, 3, 3] float64 (pixel centres at +0.5).
        world_to_camera: [T, 4, 4] float64 (OpenCV).
        depth: [T, H, W] rendered camera-z depth mean (scene units).
        opacity: [T, H, W] rendered opacity.
        spread: [T, H, W] camera-z termination spread (std of where each draw's ray ends, mean over
            draws), or None (files written before it).
        psnr: [T] PSNR (dB) of each view's rendered colour mean against its photo (the pose check,
            ``pose_check``), or None (files written before it).
    """

    views: np.ndarray
    intrinsics: np.ndarray
    world_to_camera: np.ndarray
    depth: np.ndarray
    opacity: np.ndarray
    spread: np.ndarray | None = None
    psnr: np.ndarray | None = None

    def __post_init__(self) -> None:
        T = len(self.views)
        if T == 0:
            raise ValueError("training depth: no training view")
        if self.intrinsics.shape != (T, 3, 3) or self.world_to_camera.shape != (T, 4, 4):
            raise ValueError(f"training depth: cameras must be [{T}, 3, 3] and [{T}, 4, 4], got "
                             f"{self.intrinsics.shape} and {self.world_to_camera.shape}")
        if self.depth.ndim != 3 or self.depth.shape[0] != T or self.opacity.shape != self.depth.shape:
            raise ValueError(f"training depth: depth and opacity must both be [{T}, H, W], got "
                             f"{self.depth.shape} and {self.opacity.shape}")
        if self.spread is not None and self.spread.shape != self.depth.shape:
            raise ValueError(f"training depth: spread must be {self.depth.shape}, got {self.spread.shape}")
        if self.psnr is not None and self.psnr.shape != (T,):
            raise ValueError(f"training depth: psnr must be [{T}], got {self.psnr.shape}")
        for name in ("intrinsics", "world_to_camera", "depth", "opacity") + (() if self.spread is None else ("spread",)):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"training depth: {name} holds non-finite values")

    @property
    def centres(self) -> np.ndarray:
        """[T, 3] world positions of the training cameras (float64)."""
        return np.linalg.inv(self.world_to_camera)[:, :3, 3]


def render_training_depth(model, dataset, *, options=None, seed: int = 0, progress: bool = True) -> TrainingDepth:
    """Render every training view of ``dataset`` with ``model`` (``options``: the model's render
    options by default; draws seeded per view, as evaluation seeds them) and keep its camera-z
    depth mean, opacity, termination spread and the PSNR of its colour mean against the photo (None
    for a model that renders no colour)."""
    views = [int(v) for v in dataset.train_indices]
    device = next(model.parameters()).device
    depth, opacity, spread, psnr = [], [], [], []
    for v in tqdm(views, desc="render training views (free-space check, parallax, pose check)", disable=not progress, leave=False):
        with torch.no_grad():
            maps = model.render_view(dataset.rays(v).to(device), options, generator=seeded_chunks(seed, v, device))
        z = maps["z_scale"].double()
        depth.append((maps["depth_mean"].double() * z).cpu().numpy())  # camera z
        opacity.append(maps["opacity"].double().cpu().numpy())
        spread.append((maps["depth_var_spread"].double().clamp_min(0).sqrt() * z).cpu().numpy()
                      if "depth_var_spread" in maps else np.zeros_like(depth[-1]))
        if "colour_mean" in maps:  # a depth-only model (tests' stand-ins) has no colour to score
            psnr.append(image_psnr(maps["colour_mean"], dataset.images[v].to(device)))
    idx = torch.as_tensor(views)
    return TrainingDepth(np.asarray(views, np.int64), intrinsics_3x3(dataset.cameras)[idx].double().cpu().numpy(),
                         dataset.cameras.extrinsics[idx].double().cpu().numpy(),
                         np.stack(depth).astype(np.float32), np.stack(opacity).astype(np.float32),
                         np.stack(spread).astype(np.float32),
                         np.asarray(psnr, np.float64) if len(psnr) == len(views) else None)


def save_training_depth(run_dir: str | Path, ref: TrainingDepth) -> Path:
    """Write ``ref`` to ``RUN/TRAINING_DEPTH_FILE`` atomically."""
    path = Path(run_dir) / TRAINING_DEPTH_FILE

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, views=ref.views, intrinsics=ref.intrinsics, world_to_camera=ref.world_to_camera,
                                depth=ref.depth, opacity=ref.opacity,
                                **({} if ref.spread is None else {"spread": ref.spread}),
                                **({} if ref.psnr is None else {"psnr": ref.psnr}))

    atomic_write(path, write)
    return path


def load_training_depth(run_dir: str | Path) -> TrainingDepth | None:
    """The run's stored training-view depths, or None when it has none. ValueError naming the
    file when it is malformed (no pickles are read)."""
    path = Path(run_dir) / TRAINING_DEPTH_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in ("views", "intrinsics", "world_to_camera", "depth", "opacity")}
            spread = f["spread"].astype(np.float32) if "spread" in f.files else None
            psnr = f["psnr"].astype(np.float64) if "psnr" in f.files else None
        return TrainingDepth(data["views"].astype(np.int64), data["intrinsics"].astype(np.float64),
                             data["world_to_camera"].astype(np.float64), data["depth"].astype(np.float32),
                             data["opacity"].astype(np.float32), spread, psnr)
    except (OSError, KeyError, ValueError) as exc:
        raise ValueError(f"{path}: malformed training-view depths ({exc})") from exc


def look_up(X: np.ndarray, ref: TrainingDepth, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """World points ``X`` [N, 3] in training view ``t``: their camera z [N], whether they lie in front
    of the camera inside the image [N], and the row and column of their pixel [N] (0 where not)."""
    T, H, W = ref.depth.shape
    cam = X @ ref.world_to_camera[t, :3, :3].T + ref.world_to_camera[t, :3, 3]
    z = cam[:, 2]
    front = z > 0
    uv = cam[:, :2] / np.where(front, z, 1.0)[:, None] @ ref.intrinsics[t, :2, :2].T + ref.intrinsics[t, :2, 2]
    inside = front & np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    rows = np.clip(np.floor(np.where(inside, uv[:, 1], 0)).astype(np.int64), 0, H - 1)
    cols = np.clip(np.floor(np.where(inside, uv[:, 0], 0)).astype(np.int64), 0, W - 1)
    return z, inside, rows, cols


def opaque_surface(X: np.ndarray, ref: TrainingDepth, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points ``X`` [N, 3] (float64) against training view ``t``: their camera z [N], whether they
    fall inside its image in front of the camera on a pixel of opacity above ``OPACITY_MASK`` [N], and
    the camera-z depth the view rendered at that pixel [N] (float64; meaningless where not opaque)."""
    z, inside, rows, cols = look_up(X, ref, t)
    return z, inside & (ref.opacity[t][rows, cols] > OPACITY_MASK), ref.depth[t][rows, cols].astype(np.float64)


def free_space_violation(points: np.ndarray, ref: TrainingDepth, *, exclude: Sequence[int] = ()) -> np.ndarray:
    """e(X) [N] >= 0 of world points ``points`` [N, 3] (module doc): how far in front of a training
    view's rendered surface the point lies, the largest over the training views (0 where no view
    has it inside its image in front of the camera on an opaque pixel). ``exclude``: dataset views
    left out of the check (none by default)."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(X))
    for t in range(len(ref.views)):
        if int(ref.views[t]) in exclude:
            continue
        out = np.maximum(out, violation_in_view(*opaque_surface(X, ref, t)))
    return out


def violation_in_view(z: np.ndarray, opaque: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """max(0, D_j(u) - z_j(X)) [N] where the point is on an opaque pixel of view j, else 0: one view's
    share of the violation, of ``opaque_surface``'s camera z ``z``, mask ``opaque`` and ``surface`` [N]."""
    return np.where(opaque, np.maximum(surface - z, 0.0), 0.0)


def agreeing_views(points: np.ndarray, ref: TrainingDepth, *, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """How many training views render the surface a point lies on: for world points ``points`` [N, 3],
    the count [N] of training views that have the point inside their image in front of the camera
    on an opaque pixel (``view_maps.OPACITY_MASK``) with |z_j(X) - D_j(u_j(X))| <= ``tolerance``
    z_j(X), and the count [N] of views with it inside an opaque pixel at all (the first's
    denominator). A point in front of a view's surface (the free-space violation) or hidden behind it
    (occluded there) does not agree with that view. Used by the agreement analysis
    (docs/studies.md); ValueError for a ``tolerance`` that is not finite and > 0."""
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"agreeing views: the tolerance must be finite and > 0, got {tolerance}")
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    agree, seen = np.zeros(len(X), np.int64), np.zeros(len(X), np.int64)
    for t in range(len(ref.views)):
        z, opaque, surface = opaque_surface(X, ref, t)
        seen += opaque
        agree += opaque & (np.abs(z - surface) <= tolerance * z)
    return agree, seen


def rendered_points(centres: np.ndarray, points: np.ndarray, point_z: np.ndarray, rendered_z: np.ndarray) -> np.ndarray:
    """World points [N, 3] a render puts on the rays from camera ``centres`` [N, 3] through world
    ``points`` [N, 3] (camera-z depth ``point_z`` [N] > 0): at camera-z depth ``rendered_z`` [N] along
    the same ray, X = c + (p - c) rendered_z / point_z."""
    c = np.asarray(centres, dtype=np.float64)
    return c + (np.asarray(points, dtype=np.float64) - c) * (np.asarray(rendered_z, np.float64)
                                                             / np.asarray(point_z, np.float64))[:, None]


def violation_map(depth: np.ndarray, intrinsics: np.ndarray, world_to_camera: np.ndarray, ref: TrainingDepth,
                  *, mask: np.ndarray | None = None, exclude: Sequence[int] = ()) -> np.ndarray:
    """e [H, W] (float32) of a rendered camera-z ``depth`` map [H, W] of the camera ``intrinsics``
    [3, 3], ``world_to_camera`` [4, 4]: each pixel centre back-projected to its depth, then
    ``free_space_violation``; 0 where ``mask`` [H, W] is False (default: every pixel)."""
    return map_at_pixels(depth, intrinsics, world_to_camera, lambda X: free_space_violation(X, ref, exclude=exclude),
                         mask=mask)


def map_at_pixels(depth: np.ndarray, intrinsics: np.ndarray, world_to_camera: np.ndarray, value,
                  *, mask: np.ndarray | None = None) -> np.ndarray:
    """[H, W] (float32) ``value`` (world points [N, 3] -> [N]) of each pixel centre of a rendered
    camera-z ``depth`` map [H, W], back-projected to its depth with the camera ``intrinsics`` [3, 3],
    ``world_to_camera`` [4, 4]; 0 where ``mask`` [H, W] is False (default: every pixel)."""
    return maps_at_pixels(depth, intrinsics, world_to_camera, lambda X: (value(X),), mask=mask)[0]


def maps_at_pixels(depth: np.ndarray, intrinsics: np.ndarray, world_to_camera: np.ndarray, values,
                   *, mask: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """``map_at_pixels`` of several quantities from one back-projection: ``values`` maps world points
    [N, 3] to a tuple of [N] arrays (or None); returns a tuple of [H, W] float32 maps, 0 where ``mask``
    is False (None where ``values`` gave None)."""
    depth = torch.as_tensor(np.asarray(depth, dtype=np.float64))
    H, W = depth.shape
    rows, cols = torch.nonzero(torch.ones(H, W, dtype=torch.bool) if mask is None
                               else torch.as_tensor(np.asarray(mask, bool)), as_tuple=True)
    world = backproject_pixels(torch.as_tensor(np.asarray(intrinsics, np.float64)),
                               invert_rigid(torch.as_tensor(np.asarray(world_to_camera, np.float64))),
                               rows, cols, depth[rows, cols])
    at = (rows.numpy(), cols.numpy())

    def fill(v: np.ndarray) -> np.ndarray:
        out = np.zeros((H, W), np.float32)
        out[at] = v
        return out

    return tuple(None if v is None else fill(v) for v in values(world.numpy()))


def checked_std(std: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """sqrt(std^2 + e^2) (float64), the std with the free-space violation ``violation`` as an
    independent error component (module doc); same shapes."""
    return np.hypot(np.asarray(std, np.float64), np.asarray(violation, np.float64))


def carved_points(points: np.ndarray, ref: TrainingDepth, *, margin: float = CARVE_MARGIN,
                  max_spread: float = CARVE_MAX_SPREAD, min_opacity: float = CARVE_MIN_OPACITY) -> np.ndarray:
    """[N] bool: which world ``points`` [N, 3] lie clearly in the free space of a training view,
    z_j(X) < D_j(u) - 3 s_j(u) - margin D_j(u), at a pixel u whose ray ended sharply (opacity above
    ``min_opacity``, termination spread s_j below ``max_spread`` D_j). Needs ``ref.spread``."""
    if ref.spread is None:
        raise ValueError("carving needs the training views' termination spread (render_training_depth again)")
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(X), bool)
    for t in range(len(ref.views)):
        z, inside, rows, cols = look_up(X, ref, t)
        d = ref.depth[t][rows, cols].astype(np.float64)
        s = ref.spread[t][rows, cols].astype(np.float64)
        sharp = inside & (ref.opacity[t][rows, cols] > min_opacity) & (s < max_spread * d)
        out |= sharp & (z < d - 3.0 * s - margin * d)
    return out


def carve_free_space(model, ref: TrainingDepth, *, resolution: int = CARVE_RESOLUTION, **thresholds) -> float:
    """Empty the cells of ``model``'s occupancy grid (built all-occupied at ``resolution`` if it
    keeps none) whose centre ``carved_points`` marks, so renders skip them. Returns the share of
    the occupied cells carved."""
    if getattr(model, "occupancy", None) is None:
        device = next(model.parameters()).device
        model.occupancy = OccupancyGrid(UNIT_CUBE, resolution).to(device)
    grid = model.occupancy
    res = grid.resolution.tolist()
    ijk = torch.stack(torch.meshgrid(*[torch.arange(r, device=grid.aabb.device) for r in res], indexing="ij"), -1)
    unit = grid.aabb[0] + (ijk.reshape(-1, 3).to(grid.aabb.dtype) + 0.5) * grid.cell_size
    with torch.no_grad():
        world = model.region.from_unit(unit).double().cpu().numpy()
    occupied = grid.occupancy.reshape(-1)
    carve = torch.from_numpy(carved_points(world, ref, **thresholds)).to(occupied.device)
    before = int(occupied.sum())
    grid.occupancy.copy_((occupied & ~carve).reshape(res))
    return float((before - int(grid.occupancy.sum())) / max(before, 1))
