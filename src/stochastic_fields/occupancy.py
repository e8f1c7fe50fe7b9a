"""Occupancy grid for empty-space skipping (the idea of nerfacc's ``estimators/occ_grid.py``).

A regular grid over an axis-aligned box keeps, per cell, an exponential moving maximum of a
density upper estimate (``density_ema``) and a boolean ``occupancy``. Sampling takes the dense
samples between near and far and keeps only those whose midpoint lies in an occupied cell
inside the box, returning packed samples for the ``*_packed`` renderers of
``volume_rendering``.

Why skipping is exact with alpha compositing: a skipped sample has (estimated) density ~0, so
its weight ``T_i (1 - exp(-a_i delta_i))`` and its optical depth are ~0; removing it changes
neither the transmittance nor any other weight. (The trapezoid rule treats consecutive packed
samples as neighbours and would interpolate across skipped gaps; use alpha compositing.)

Occupied means: the density upper estimate ``a`` implies a per-sample opacity
``1 - exp(-a * step_size)`` above ``constants.OCCUPANCY_ALPHA_THRESHOLD``, i.e.
``a > -log(1 - OCCUPANCY_ALPHA_THRESHOLD) / step_size``.

Updates evaluate one jittered point per cell, so a cell that only grazes a surface can be
missed by its own point; the binary grid is therefore dilated by ``dilation`` cells (default
1) after thresholding. With this margin, surfaces whose radius of curvature spans a few cells
are covered (tested on a sphere of radius 8 cells); features thinner than a cell can still be
missed by point sampling, as with any occupancy grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .constants import OCCUPANCY_ALPHA_THRESHOLD, OCCUPANCY_UPPER_NUM_STD
from .fields.base import StochasticField
from .rays import PackedRaySamples, RayBundle
from .samplers import Spacing, sample_along_rays

DensityFn = Callable[[Tensor], Tensor]


def density_threshold(step_size: float, alpha_threshold: float = OCCUPANCY_ALPHA_THRESHOLD) -> float:
    """Density above which one sample of length ``step_size`` has opacity above ``alpha_threshold``.

    ``1 - exp(-a * step) > alpha  <=>  a > -log(1 - alpha) / step``.
    """
    if step_size <= 0:
        raise ValueError(f"step_size must be positive, got {step_size}")
    if not 0.0 < alpha_threshold < 1.0:
        raise ValueError(f"alpha_threshold must lie in (0, 1), got {alpha_threshold}")
    return -math.log1p(-alpha_threshold) / step_size


def density_upper_estimate(field: StochasticField, num_std: float = OCCUPANCY_UPPER_NUM_STD) -> DensityFn:
    """A ``density_fn`` for ``OccupancyGrid.update``: the high quantile ``relu(mu_a + num_std s_a)``.

    The density is ``relu(mu_a + s_a eps)``; a draw exceeds this value with probability
    ``1 - Phi(num_std)`` (0.13% for 3), so cells below it are empty for almost every draw. With
    density heads (``FieldParams.density_offsets``) mu_a is the highest head's loc.
    """

    def density_fn(points: Tensor) -> Tensor:  # [P, 3] -> [P]
        loc, scale, offsets = field.density_head_params(points)
        if offsets is not None:  # density heads: the highest head's
            loc = loc + offsets.amax(-1)
        return torch.relu(loc + num_std * scale)

    return density_fn


class OccupancyGrid(nn.Module):
    """Binary occupancy over a box, updated from a density upper estimate.

    Buffers:
        aabb: [2, 3] min and max corners (world coordinates, scene units).
        resolution: [3] int64 cells per axis (X, Y, Z).
        occupancy: [X, Y, Z] bool; True where samples must be kept. All True at construction,
            so nothing is skipped before the first update.
        density_ema: [X, Y, Z] exponential moving maximum of the density upper estimate.
    """

    aabb: Tensor
    resolution: Tensor
    occupancy: Tensor
    density_ema: Tensor

    def __init__(self, aabb: Tensor | Sequence[Sequence[float]], resolution: int | Sequence[int] = 128):
        super().__init__()
        aabb_t = torch.as_tensor(aabb, dtype=torch.float32)
        if aabb_t.shape != (2, 3) or not bool(torch.all(aabb_t[1] > aabb_t[0])):
            raise ValueError(f"aabb must be [2, 3] with max > min per axis, got {aabb_t.tolist()}")
        res = [resolution] * 3 if isinstance(resolution, int) else list(resolution)
        if len(res) != 3 or any(int(r) < 1 for r in res):
            raise ValueError(f"resolution must be a positive int or three positive ints, got {resolution!r}")
        res = [int(r) for r in res]
        self.register_buffer("aabb", aabb_t.clone())
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.long))
        self.register_buffer("occupancy", torch.ones(res, dtype=torch.bool))
        self.register_buffer("density_ema", torch.zeros(res, dtype=torch.float32))

    # ------------------------------------------------------------------------------ geometry
    @property
    def num_cells(self) -> int:
        return self.occupancy.numel()

    @property
    def cell_size(self) -> Tensor:
        """[3] edge lengths of one cell."""
        return (self.aabb[1] - self.aabb[0]) / self.resolution.to(self.aabb.dtype)

    @property
    def occupied_fraction(self) -> float:
        """Fraction of cells marked occupied."""
        return float(self.occupancy.float().mean())

    def cell_indices(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Cells of ``points`` [*B, 3]: (flat cell index [*B] int64, inside-the-box mask [*B] bool).

        A point on the max face belongs to the last cell; points outside get index 0 and
        ``inside = False``.
        """
        lo, hi = self.aabb[0].to(points), self.aabb[1].to(points)
        inside = ((points >= lo) & (points <= hi)).all(dim=-1)
        res = self.resolution.to(points.device)
        ijk = torch.floor((points - lo) / (hi - lo) * res.to(points.dtype)).long()
        ijk = torch.minimum(ijk.clamp_min(0), res - 1)
        flat = (ijk[..., 0] * res[1] + ijk[..., 1]) * res[2] + ijk[..., 2]
        return torch.where(inside, flat, torch.zeros_like(flat)), inside

    def occupied(self, points: Tensor) -> Tensor:
        """[*B] bool: the point lies inside the box in an occupied cell."""
        flat, inside = self.cell_indices(points)
        return inside & self.occupancy.reshape(-1)[flat]

    def _cell_points(self, flat_indices: Tensor, generator: torch.Generator | None) -> Tensor:
        """[P, 3] one uniformly jittered point inside each listed cell."""
        res = self.resolution
        ijk = torch.stack(
            [flat_indices // (res[1] * res[2]), (flat_indices // res[2]) % res[1], flat_indices % res[2]], dim=-1
        )
        jitter = torch.rand(ijk.shape, generator=generator, device=ijk.device, dtype=self.aabb.dtype)
        return self.aabb[0] + (ijk.to(self.aabb.dtype) + jitter) * self.cell_size

    # ------------------------------------------------------------------------------ updates
    def mark_all_occupied(self) -> None:
        """Keep every sample inside the box (e.g. before training or to disable skipping)."""
        self.occupancy.fill_(True)

    @torch.no_grad()
    def update(
        self,
        density_fn: DensityFn,
        step: int,
        *,
        decay: float = 0.95,
        threshold: float | None = None,
        step_size: float | None = None,
        warmup_steps: int = 256,
        update_every_n_steps: int = 16,
        dilation: int = 1,
        chunk_size: int = 65536,
        generator: torch.Generator | None = None,
    ) -> bool:
        """Refresh the grid from ``density_fn(points [P, 3]) -> density upper estimate [P]``.

        Runs only when ``step % update_every_n_steps == 0`` (returns whether it ran). During
        warm-up (``step < warmup_steps``) every cell is evaluated; afterwards a random quarter
        of all cells plus as many random occupied cells (nerfacc's schedule). For each
        evaluated cell, at one jittered point:

            density_ema = max(decay * density_ema, density_fn(point))
            occupancy   = dilate(density_ema > threshold, dilation cells)

        Args:
            density_fn: density upper estimate, e.g. ``density_upper_estimate(field)``.
            step: the training step.
            decay: EMA factor in (0, 1]; a cell stays occupied for about
                log(ema / threshold) / -log(decay) updates after its density vanishes.
            threshold: density threshold; default ``density_threshold(step_size)``.
            step_size: render step size (ray distance per sample) behind the default threshold;
                default: the smallest cell edge.
            warmup_steps, update_every_n_steps: schedule as above.
            dilation: cells of binary dilation after thresholding (0 disables).
            chunk_size: points per ``density_fn`` call.
            generator: for the jitter and the cell subsets.
        """
        if update_every_n_steps < 1:
            raise ValueError(f"update_every_n_steps must be >= 1, got {update_every_n_steps}")
        if not 0.0 < decay <= 1.0:
            raise ValueError(f"decay must lie in (0, 1], got {decay}")
        if dilation < 0:
            raise ValueError(f"dilation must be >= 0, got {dilation}")
        if step % update_every_n_steps != 0:
            return False
        if threshold is None:
            threshold = density_threshold(float(self.cell_size.min()) if step_size is None else step_size)

        device = self.occupancy.device
        if step < warmup_steps:
            indices = torch.arange(self.num_cells, device=device)
        else:
            count = max(self.num_cells // 4, 1)
            uniform = torch.randint(self.num_cells, (count,), generator=generator, device=device)
            occupied = torch.nonzero(self.occupancy.reshape(-1)).squeeze(-1)
            if occupied.numel() > 0:
                pick = torch.randint(occupied.numel(), (count,), generator=generator, device=device)
                uniform = torch.cat([uniform, occupied[pick]])
            indices = uniform

        points = self._cell_points(indices, generator)
        density = torch.cat([density_fn(chunk).reshape(-1) for chunk in points.split(chunk_size)])
        if density.shape[0] != indices.shape[0]:
            raise ValueError(
                f"density_fn must return one value per point: got {density.shape[0]} for {indices.shape[0]} points"
            )

        ema = self.density_ema.reshape(-1).clone()
        ema[indices] = ema[indices] * decay
        ema.scatter_reduce_(0, indices, density.to(ema.dtype), reduce="amax")
        self.density_ema.copy_(ema.reshape(self.density_ema.shape))

        occupied_cells = (self.density_ema > threshold).to(torch.float32)
        if dilation > 0:
            size = 2 * dilation + 1
            occupied_cells = F.max_pool3d(occupied_cells[None, None], size, stride=1, padding=dilation)[0, 0]
        self.occupancy.copy_(occupied_cells > 0)
        return True

    # ------------------------------------------------------------------------------ sampling
    @torch.no_grad()
    def sample(
        self,
        rays: RayBundle,
        num_samples_per_ray: int,
        *,
        stratified: bool = False,
        generator: torch.Generator | None = None,
        spacing: Spacing = "linear",
    ) -> PackedRaySamples:
        """Dense samples between near and far, keeping those whose midpoint is in an occupied cell.

        The dense samples are exactly ``samplers.sample_along_rays`` (same jitter for the same
        generator state), so with every cell occupied and the rays inside the box the packed
        samples are the dense ones. Rays may end up with no samples.

        Shapes:
            rays: [R]. Returns ``PackedRaySamples`` with ray_indices, t_starts, t_ends [N],
            samples of each ray contiguous and sorted by distance.
        """
        if len(rays.shape) != 1:
            raise ValueError(f"rays must be a flat bundle [R], got shape {tuple(rays.shape)}; call .flatten()")
        dense = sample_along_rays(
            rays, num_samples_per_ray, spacing=spacing, stratified=stratified, generator=generator
        )
        keep = self.occupied(dense.positions)  # [R, S]
        ray_indices, sample_indices = torch.nonzero(keep, as_tuple=True)  # row-major: sorted by ray, then t
        return PackedRaySamples(
            rays=rays,
            ray_indices=ray_indices,
            t_starts=dense.t_starts[ray_indices, sample_indices],
            t_ends=dense.t_ends[ray_indices, sample_indices],
        )

    def extra_repr(self) -> str:
        return f"aabb={self.aabb.tolist()}, resolution={self.resolution.tolist()}"
