"""Fast CPU backend: a multi-resolution dense voxel grid with a tiny colour decoder.

Parameters live in L dense grids of increasing resolution over the scene region's unit cube
(level l has resolution ``base * 2^l`` per axis, up to the finest resolution chosen from the
image footprint). Each level is a table of cells ``[Z * Y * X, C]`` (channels last); the
trilinear interpolation of every level is summed:

    g(x) = sum_l sum_{8 corners j} w_j(u) G_l[idx_j(u)]      u = SceneRegion.to_unit(x)
    mu_a, raw_s_a = g_0(x), g_1(x)                           (density read straight from the grid)
    or, with a density unit k: mu_a = k g_0(x), s_a = k positive_scale(g_1(x))
    mu_c, raw_s_c = decoder([g_2..(x), PE(d)])               (view-dependent colour, 2-layer MLP)
    or, with ``concat_colour_levels``: decoder([g_{0,2..}(x), ..., g_{L-1,2..}(x), PE(d)]), each
    level's colour features its own inputs (instant-NGP's concatenation; the density stays summed)
    or, with ``decoder_width=0``: mu_c, raw_s_c = g_2..7(x)  (view-independent, no MLP)
    with ``noise_head``: beta(x) = softplus(g_last(x))      (observation-noise std, one more channel)
    with M density heads: o_h(x) = k (e_h(x) - mean_h' e_h'(x)) from M channels after g_1 (the
    colour features follow them); trajectory k draws its density around mu_a + o_{k mod M}

Density heads (``field.density_heads``, 2 by default, study 54): M alternative density fields around one
centre mu_a, each head a geometry of its own that the trajectories it draws must explain (the
likelihood is each trajectory's), sharing the colour features and the density scale, as a deep
ensemble's members would differ, inside one model: their channels start with independent noise
per cell (the deep ensemble's ``ENSEMBLE_GRID_DENSITY_NOISE`` rule), so the heads do not start equal.

Coarse to fine (``field.grid_coarse_to_fine``, a few-view regulariser): during training each level
may carry a weight a_l in [0, 1], g(x) = sum_l a_l g_l(x), set by the trainer from the training
progress (``coarse_to_fine_weights``): the coarse level alone first, the finer ones fading in, so
the early geometry is the smooth one that explains all views. A level of weight 0 is not read.
A loaded model reads every level at weight 1.

Density unit (``field.density_per``): the grid's values count density per unit of world length
(k = 1) or per finest cell (k = 1 / L, L = ``SceneRegion.cell_length`` of the finest level): the
rectified normal relu(N(mu, s^2)) scales with k (relu(k y) = k relu(y)), so with k = 1 / L the grid
value relu(g_0) is the optical depth per finest cell whatever the scene's unit, and the same photos
in metres or millimetres train the same cells. ``density_unit`` is a buffer: a saved model renders
with the unit it was trained with (checkpoints from before it: 1).

The corners are gathered with ``row_gather.gather_rows``, so a training step touches only the
cells its samples fall in: their gradients are summed per row (``RowGradient``) and the grid is
optimised with ``optim.RowSparseAdam`` (Adam moments updated only where a cell received gradient,
as instant-NGP does for its hash tables). ``torch.nn.functional.grid_sample`` gives the same
values (tested) but its backward writes a dense gradient of every cell, and a dense Adam then
updates all cells each step: at 2M cells that was 80% of a training step (benchmarks/).

Why a dense grid (measured in benchmarks/): on 2 CPU cores a trilinear gather of one level costs
about 50 ns per point (one fused ``embedding_bag`` over the 8 corner rows; the whole field with its
decoder about 250 ns), the paper's 8x256 MLP a few hundred times more; coarse
levels propagate gradients to unobserved cells quickly and the fine level adds detail.
A hash grid would save memory at high resolution but needs a hash per corner and resolves
collisions by training; the regions we model need at most a few million cells per level.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

import torch.nn.functional as F

from ..constants import NOISE_HEAD_INIT_STD, OUTSIDE_DENSITY_LOC, PARALLAX_PROBE_STEP
from ..scene_region import frustum_points, SceneRegion
from .base import FieldParams, StochasticField, inverse_positive_scale, inverse_softplus, positive_scale
from .encoding import PositionalEncoding
from .row_gather import gather_rows


def coarse_to_fine_weights(num_levels: int, progress: float, fraction: float) -> list[float]:
    """Per-level weights a_l at training ``progress`` in [0, 1]: level 0 always 1, level l >= 1

        a_l = clamp(progress / fraction * (L - 1) - (l - 1), 0, 1)

    i.e. the finer levels fade in one after the other, linearly, each over ``fraction / (L - 1)``
    of training, and all are 1 from ``progress = fraction`` on. ``fraction = 0``: all 1."""
    if num_levels < 1:
        raise ValueError(f"num_levels must be >= 1, got {num_levels}")
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"coarse-to-fine fraction must be in [0, 1], got {fraction}")
    if fraction == 0.0 or num_levels == 1:
        return [1.0] * num_levels
    ramp = min(max(float(progress), 0.0), 1.0) / fraction * (num_levels - 1)
    return [1.0] + [min(max(ramp - (level - 1), 0.0), 1.0) for level in range(1, num_levels)]


def level_resolutions(finest: tuple[int, int, int], num_levels: int) -> list[tuple[int, int, int]]:
    """Per-level (X, Y, Z) resolutions, halving from the finest, never below 4."""
    out = []
    for level in range(num_levels):
        div = 2 ** (num_levels - 1 - level)
        out.append(tuple(max(4, int(math.ceil(r / div))) for r in finest))
    return out


class GridField(StochasticField):
    def __init__(self, region: SceneRegion, resolution: tuple[int, int, int], *, num_levels: int = 3,
                 feature_dim: int = 8, decoder_width: int = 32, concat_colour_levels: bool = False,
                 direction_frequencies: int = 2,
                 init_density_loc: float = -1.0, init_std: float = 1.0, noise_head: bool = False,
                 density_unit: float = 1.0, density_heads: int = 1, head_init_std: float = 0.0):
        super().__init__()
        if density_heads < 1:
            raise ValueError(f"density_heads must be an integer >= 1, got {density_heads}")
        if not (math.isfinite(density_unit) and density_unit > 0):
            raise ValueError(f"density_unit must be a finite number > 0, got {density_unit}")
        #: k: world density = k * grid density (1: per unit of length; 1 / cell length: per cell)
        self.register_buffer("density_unit", torch.tensor(float(density_unit)))
        self.region = region
        self.resolution = tuple(int(r) for r in resolution)
        self.decoder_width = decoder_width
        colour_channels = feature_dim if decoder_width > 0 else 6
        #: M density heads: channels 2 .. 2 + M hold each head's raw offset (none for one head)
        self.density_heads = int(density_heads)
        heads = self.density_heads if self.density_heads > 1 else 0
        self.head_channels = slice(2, 2 + heads)
        #: what a density-only read gathers: the density's loc and scale, and the heads' offsets
        self.density_channels = slice(0, 2 + heads)
        self.colour_channels = slice(2 + heads, 2 + heads + colour_channels)
        self.noise_head = bool(noise_head)
        self.num_channels = 2 + heads + colour_channels + int(self.noise_head)
        self.level_shapes = level_resolutions(self.resolution, num_levels)  # (X, Y, Z) per level
        if concat_colour_levels and decoder_width == 0:
            raise ValueError("concat_colour_levels needs a colour decoder (decoder_width > 0)")
        #: the decoder reads each level's colour features (L F inputs), not their sum (F)
        self.concat_colour_levels = bool(concat_colour_levels)
        decoder_inputs = colour_channels * (num_levels if self.concat_colour_levels else 1)
        self.levels = nn.ParameterList()
        for rx, ry, rz in self.level_shapes:
            g = torch.zeros(rz * ry * rx, self.num_channels)  # cell (x, y, z) is row (z * Y + y) * X + x
            if decoder_width > 0:
                g[:, self.colour_channels] = 0.1 * torch.randn_like(g[:, self.colour_channels])
            if heads:  # independent per level: the summed std is head_init_std
                g[:, self.head_channels] = head_init_std / math.sqrt(num_levels) * torch.randn_like(g[:, self.head_channels])
            self.levels.append(nn.Parameter(g))
        #: per-level weights a_l (``coarse_to_fine_weights``) while training; None: every level at 1
        self.level_weights: list[float] | None = None
        raw_std = inverse_positive_scale(init_std)
        # Offsets added to the summed grid value: the field starts as a uniform, uncertain fog.
        offset = torch.zeros(self.num_channels)
        offset[0], offset[1] = init_density_loc, raw_std
        if decoder_width == 0:
            offset[self.colour_channels.start + 3:self.colour_channels.start + 6] = raw_std
        if self.noise_head:
            offset[-1] = inverse_softplus(NOISE_HEAD_INIT_STD)
        self.register_buffer("offset", offset)
        if decoder_width > 0:
            self.dir_enc = PositionalEncoding(direction_frequencies)
            self.decoder = nn.Sequential(
                nn.Linear(decoder_inputs + self.dir_enc.output_dim(3), decoder_width), nn.ReLU(),
                nn.Linear(decoder_width, 6),
            )
            with torch.no_grad():
                self.decoder[-1].bias[3:] = raw_std

    def density_unit_factor(self) -> Tensor:
        return self.density_unit

    def set_level_weights(self, weights: list[float] | None) -> None:
        """Weights a_l of the levels in g(x) = sum_l a_l g_l(x) (None: all 1)."""
        if weights is not None:
            if len(weights) != len(self.levels) or not all(0.0 <= float(a) <= 1.0 for a in weights):
                raise ValueError(f"level weights must be {len(self.levels)} numbers in [0, 1], got {weights}")
            weights = [float(a) for a in weights]
            if weights[0] == 0.0:
                raise ValueError("the coarsest level's weight must be > 0")
        self.level_weights = weights

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def _interpolate(self, unit: Tensor, channels: slice | None = None) -> Tensor:
        """unit [P, 3] in [-1, 1] -> [P, C] summed trilinear values of every level (plus offsets);
        ``channels``: only those, [P, c] (``_read``)."""
        return self._read(unit, channels)[0]

    def _read(self, unit: Tensor, channels: slice | None = None) -> tuple[Tensor, tuple[Tensor, ...] | None]:
        """unit [P, 3] in [-1, 1] -> (values [P, C]: the trilinear values of every level summed, plus
        offsets, or [P, c] of ``channels``; features: with ``concat_colour_levels`` and every channel
        read, each level's colour features, L x [P, F] (the decoder reads them side by side), else None).

        Points outside the cube read the border cells (their density is replaced in ``decode``).
        The cells' gradients go to each level's ``RowGradient`` (rows of the touched corners, only
        the asked-for ``channels``: a density-only read, as the depth likelihood's, back-propagates
        2 of the C channels)."""
        total, features = None, []
        concat = self.concat_colour_levels and channels is None
        weights = self.level_weights or [1.0] * len(self.levels)
        for table, shape, a in zip(self.levels, self.level_shapes, weights):
            if a == 0.0:  # a level not yet faded in (coarse to fine) is not read: its features are 0
                if concat:
                    width = self.colour_channels.stop - self.colour_channels.start
                    features.append(unit.new_zeros(unit.shape[0], width))
                continue
            idx, w = trilinear_corners(unit, shape)  # [P, 8], [P, 8]
            v = gather_rows(table, idx, w if a == 1.0 else w * a, channels=channels)  # [P, C] or [P, c]
            total = v if total is None else total + v
            if concat:
                features.append(v[:, self.colour_channels])
        off = self.offset if channels is None else self.offset[channels]
        return total + off.to(total), tuple(features) if concat else None

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints from before the density unit counted density per unit of length
        state_dict.setdefault(f"{prefix}density_unit", torch.tensor(1.0))
        # checkpoints from before the channels-last layout stored levels as [1, C, Z, Y, X]
        for i in range(len(self.levels)):
            key = f"{prefix}levels.{i}"
            t = state_dict.get(key)
            if t is not None and t.dim() == 5:
                state_dict[key] = t[0].permute(1, 2, 3, 0).reshape(-1, t.shape[1])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def describe(self) -> str:
        """One line for a user: the finest level's cells per axis (X x Y x Z of the unit cube), its
        total, the number of levels, and (``density_per='cell'``) the cell's side L."""
        x, y, z = self.resolution
        unit = float(self.density_unit)
        per = "" if unit == 1.0 else f", density per cell of side {1.0 / unit:.3g}"
        heads = "" if self.density_heads == 1 else f", {self.density_heads} density heads"
        return f"{x} x {y} x {z} cells at the finest of {len(self.level_shapes)} levels ({x * y * z / 1e6:.2f}M){per}{heads}"

    def forward(self, positions: Tensor, directions: Tensor) -> FieldParams:
        unit = self.region.to_unit(positions.reshape(-1, 3))
        values, features = self._read(unit)
        return self.decode(values, unit, directions, positions.shape[:-1], features=features)

    def forward_colour_where(self, positions: Tensor, directions: Tensor, colour_where) -> FieldParams:
        """``forward`` with the colour decoder run only at the points ``colour_where`` keeps (at a
        capture's end of training a fifth of them or fewer); the others get rgb_loc 0 and the scale
        of a raw 0 (``StochasticField.forward_colour_where``). Every channel is still read at every
        point in one gather: reading the colour channels apart at the kept points saved less (the
        extra gathers cost about what the rows' gradients saved: their cost is per row touched)."""
        unit = self.region.to_unit(positions.reshape(-1, 3))
        values, features = self._read(unit)
        return self.decode(values, unit, directions, positions.shape[:-1], colour_where=colour_where, features=features)

    def _density(self, values: Tensor, unit: Tensor) -> tuple[Tensor, Tensor]:
        """Grid values [P, >= 2] at unit points [P, 3] -> (density loc, density scale) [P]: k g_0
        inside the cube, ``OUTSIDE_DENSITY_LOC`` outside; k positive_scale(g_1)."""
        outside = ~(unit.abs() <= 1.0).all(-1)
        k = self.density_unit.to(values)
        loc = torch.where(outside, torch.full_like(values[:, 0], OUTSIDE_DENSITY_LOC), k * values[:, 0])
        return loc, k * positive_scale(values[:, 1])

    def _head_offsets(self, values: Tensor) -> Tensor | None:
        """Grid values [P, >= 2 + M] -> the heads' offsets [P, M], k (e_h - mean_h e_h) (None: one head).
        Outside the cube every head is empty as the centre (its loc is far below 0)."""
        if self.density_heads == 1:
            return None
        e = values[:, self.head_channels]
        return self.density_unit.to(values) * (e - e.mean(-1, keepdim=True))

    def _decode_colour(self, features: Tensor, directions: Tensor, hidden_transform=None) -> Tensor:
        """Colour features [P, F] and view directions [P, 3] -> [P, 6] (logit locs, raw scales)."""
        d = self.dir_enc(directions)
        hidden = torch.relu(self.decoder[0](torch.cat([features, d], dim=-1)))
        if hidden_transform is not None:
            hidden = hidden_transform(hidden)
        return self.decoder[-1](hidden)

    def decode(self, values: Tensor, unit: Tensor, directions: Tensor, batch: torch.Size,
               hidden_transform=None, colour_where=None, features: tuple[Tensor, ...] | None = None) -> FieldParams:
        """Grid values [P, C] at unit coordinates [P, 3] -> FieldParams [*batch].

        The decoder reads ``features`` (L x [P, F], ``_read``'s with ``concat_colour_levels``) side by
        side where given, else the values' colour channels. ``hidden_transform`` (e.g. dropout) is applied to the
        decoder's hidden layer; with ``colour_where`` (``forward_colour_where``) the decoder runs only
        at the points it keeps (the others: rgb_loc 0, the scale of a raw 0)."""
        density_loc, density_scale = self._density(values, unit)
        offsets = self._head_offsets(values)
        if self.decoder_width > 0:
            levels = (values[:, self.colour_channels],) if features is None else features
            dirs = directions.reshape(-1, 3)
            if colour_where is None:
                col = self._decode_colour(_side_by_side(levels), dirs, hidden_transform)
            else:
                dens = (density_loc.detach(), density_scale.detach()) + (() if offsets is None else (offsets.detach(),))
                keep = colour_where(*dens).nonzero().squeeze(1)  # [p]
                kept = _side_by_side([f[keep] for f in levels])  # the kept points' only: [p, L F]
                col = self._decode_colour(kept, dirs[keep], hidden_transform)
                col = col.new_zeros(values.shape[0], 6).index_copy(0, keep, col)
        else:  # colours are grid channels: nothing to save
            col = values[:, self.colour_channels]
        return FieldParams(
            density_loc=density_loc.reshape(batch),
            density_scale=density_scale.reshape(batch),
            rgb_loc=col[:, :3].reshape(*batch, 3),
            rgb_scale=positive_scale(col[:, 3:]).reshape(*batch, 3),
            noise_scale=F.softplus(values[:, -1]).reshape(batch) if self.noise_head else None,
            density_offsets=None if offsets is None else offsets.reshape(*batch, self.density_heads),
        )

    def density_params(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        loc, scale, _ = self.density_head_params(positions)
        return loc, scale

    def density_head_params(self, positions: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """``density_params`` and the heads' offsets [*B, M] (None with one head), in one read of
        the density channels (``density_channels``: loc and scale, and the heads' offsets)."""
        unit = self.region.to_unit(positions.reshape(-1, 3))
        values = self._interpolate(unit, self.density_channels)
        loc, scale = self._density(values, unit)
        offsets = self._head_offsets(values)
        batch = positions.shape[:-1]
        return (loc.reshape(batch), scale.reshape(batch),
                None if offsets is None else offsets.reshape(*batch, self.density_heads))

    def total_variation(self, num_cells: int = 4096, generator: torch.Generator | None = None) -> Tensor:
        """Mean squared difference between neighbouring cells, on a random subset of cells of
        every level (squared finite differences along x, y, z). Smooths the unobserved space the
        data leaves free."""
        losses = []
        for table, (X, Y, Z) in zip(self.levels, self.level_shapes):
            dev = table.device
            z = torch.randint(0, Z - 1, (num_cells,), generator=generator, device=dev)
            y = torch.randint(0, Y - 1, (num_cells,), generator=generator, device=dev)
            x = torch.randint(0, X - 1, (num_cells,), generator=generator, device=dev)
            centre = (z * Y + y) * X + x
            # one gather per level: the cells and their +z, +y, +x neighbours
            g = gather_rows(table, torch.cat([centre, centre + Y * X, centre + X, centre + 1]))
            c, nz, ny, nx = g.split(num_cells, dim=0)
            losses.append(((nz - c) ** 2 + (ny - c) ** 2 + (nx - c) ** 2).mean())
        return torch.stack(losses).sum()


def _side_by_side(parts: tuple[Tensor, ...] | list[Tensor]) -> Tensor:
    """L x [P, F] -> [P, L F]; one part is returned as it is (no copy)."""
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


#: [8, 3] (x, y, z) offsets of the 8 corners of a cell, corner j = x + 2 y + 4 z.
_CORNER_BITS = torch.tensor([[j & 1, (j >> 1) & 1, (j >> 2) & 1] for j in range(8)])


def trilinear_corners(unit: Tensor, shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """Corner rows and weights of trilinear interpolation in a cell table of ``shape`` (X, Y, Z).

    unit [P, 3] (x, y, z) in [-1, 1] (clamped: border padding) maps to the continuous cell
    coordinate ``p = (u + 1) / 2 * (R - 1)`` (cell centres at the cube's faces, as
    ``grid_sample(align_corners=True)``). Returns idx [P, 8] int64 rows ``(z * Y + y) * X + x`` and
    w [P, 8] weights ``prod_a (f_a if corner_a else 1 - f_a)``, ``f = p - floor(p)``; they sum to 1.
    Corner j = x + 2 y + 4 z: its row is the base corner's row plus a constant offset, and its
    weight the outer product of the per-axis weights (1 - f_a, f_a).
    """
    res = torch.tensor(shape, device=unit.device, dtype=unit.dtype)
    pos = (unit.clamp(-1.0, 1.0) + 1.0) * 0.5 * (res - 1)
    base = pos.detach().floor().clamp(max=res - 2)  # the last cell interpolates with f = 1
    frac = pos - base
    b = base.long()
    X, Y = shape[0], shape[1]
    row = (b[:, 2] * Y + b[:, 1]) * X + b[:, 0]  # [P]
    bits = _CORNER_BITS.to(unit.device)  # [8, 3]
    offsets = (bits[:, 2] * Y + bits[:, 1]) * X + bits[:, 0]  # [8]
    idx = row[:, None] + offsets[None]
    # outer product from columns: broadcasting [P, 2] against [P, 2] costs 6x more (tiny inner dims)
    fx, fy, fz = frac.unbind(dim=1)
    gx, gy, gz = 1 - fx, 1 - fy, 1 - fz
    zy = torch.stack([gz * gy, gz * fy, fz * gy, fz * fy], dim=1)  # [P, 4], column 2 z + y
    w = torch.stack([zy * gx[:, None], zy * fx[:, None]], dim=2).reshape(-1, 8)  # j = 4 z + 2 y + x
    return idx, w


def _capped(res: Tensor, max_cells: int, min_resolution: int) -> tuple[int, int, int]:
    """``res`` [3] per-axis cell counts, every axis scaled by one factor until at most ``max_cells``."""
    res = res.clamp_min(min_resolution)
    cells = float(res.prod())
    if cells > max_cells:
        res = torch.ceil(res * (max_cells / cells) ** (1.0 / 3.0)).clamp_min(min_resolution)
    return tuple(int(r) for r in res.tolist())


def _frustum_points_inside(region: SceneRegion, K: Tensor, w2c: Tensor, height: int, width: int, near: Tensor,
                           far: Tensor, caller: str) -> tuple[Tensor, Tensor]:
    """[V, P, 3] frustum points of every camera (``frustum_points``) and [V, P] whether inside the region."""
    V = w2c.shape[0]
    pts = frustum_points(K, w2c, height, width, near.reshape(-1).expand(V), far.reshape(-1).expand(V), grid=5, depths=8)
    inside = region.contains(pts)
    if not bool(inside.any()):
        raise ValueError(f"{caller}: no camera frustum point lies inside the scene region")
    return pts.reshape(V, -1, 3), inside.reshape(V, -1)


def resolution_from_footprint(region: SceneRegion, intrinsics: Tensor, w2c: Tensor, height: int, width: int,
                              near: Tensor, far: Tensor, *, pixels_per_voxel: float = 1.5,
                              max_cells: int = 2_000_000, min_resolution: int = 16) -> tuple[int, int, int]:
    """Finest grid resolution from what the images can resolve (``field.grid_resolution_rule``
    'footprint').

    A voxel should cover about ``pixels_per_voxel`` pixels where the cameras see it: the extent of
    the region in unit coordinates is measured against the unit-coordinate distance between the
    projections of neighbouring pixels, at the frustum points of every camera (median).
    Per axis of the unit cube, so a flat region gets few cells across its thin axis. The result
    is capped at ``max_cells`` cells (all axes scaled by the same factor).
    """
    K = intrinsics[:, :3, :3].float()
    per_view, inside = _frustum_points_inside(region, K, w2c, height, width, near, far, "resolution_from_footprint")
    # world length of one pixel footprint at each frustum point: camera depth / focal length
    fx = K[:, 0, 0]
    c2w = torch.linalg.inv(w2c.float())
    cam_z = ((per_view - c2w[:, None, :3, 3]) * c2w[:, None, :3, 2]).sum(-1)  # [V, P]
    footprint = (cam_z / fx[:, None])[inside]
    flat = per_view[inside]
    base = region.to_unit(flat)
    # per unit axis a: the largest change of u_a for a footprint-long step along any world axis
    steps = torch.eye(3, device=flat.device)[:, None, :] * footprint[None, :, None]  # [3, P, 3]
    du = (region.to_unit(flat[None] + steps) - base[None]).abs().amax(dim=0)  # [P, 3]
    pixel_unit = du.median(dim=0).values.clamp_min(1e-9)  # [3]
    return _capped(torch.ceil(2.0 / (pixel_unit * pixels_per_voxel)), max_cells, min_resolution)


def resolution_from_parallax(region: SceneRegion, intrinsics: Tensor, w2c: Tensor, height: int, width: int,
                             near: Tensor, far: Tensor, *, pixels_per_voxel: float = 1.5,
                             max_cells: int = 2_000_000, min_resolution: int = 16,
                             step: float = PARALLAX_PROBE_STEP) -> tuple[int, int, int]:
    """Finest grid resolution from how far the images see a step along each axis move
    (``field.grid_resolution_rule`` 'parallax').

    At each frustum point x inside the region (every camera's, as ``resolution_from_footprint``)
    and for each axis a of the unit cube, a step h e_a in unit coordinates moves the point's
    projection in training view v by m_v pixels. The view where it moves most is the one that
    resolves the axis there:

        n_a(x) = max_v m_v(x, a) / h        (pixels per unit of axis a; views that see x: in front,
                                             inside the image)
        res_a  = ceil(2 median_x n_a(x) / pixels_per_voxel)     (the unit cube spans 2)

    capped at ``max_cells`` as the footprint rule. Across the image axes this is the footprint
    rule (every view sees a lateral step move by about one footprint per pixel). Along a
    forward-facing capture's depth axis (NDC: the reference camera's rays, linear in disparity) it
    is parallax: a step that changes the disparity by d(1/z) moves the point by f |o| d(1/z) pixels
    in a camera at lateral offset o from the reference camera, z / |o| times less than a
    footprint-long lateral step; the footprint rule spent those cells on depth detail no photo
    resolves (LLFF fern: 452 depth cells by footprint, 83 by parallax, before the cap). Around an
    object some view sees every axis sideways, so no axis loses cells (the view that sees a point
    closest reads it: Blender lego within 1% of the footprint rule).
    """
    K = intrinsics[:, :3, :3].float()
    w2c = w2c.float()
    per_view, inside = _frustum_points_inside(region, K, w2c, height, width, near, far, "resolution_from_parallax")
    flat = per_view[inside]  # [P, 3]
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]

    # Not cameras.project_points / in_image: kornia's projection and in_image's open right and
    # bottom edges (the frustum points lie on them) moved the grid by one or two cells per axis on
    # the embedded scene and paper-split fern (measured), away from the grids study 24 measured.
    def project(x: Tensor) -> tuple[Tensor, Tensor]:  # [P, 3] -> pixels [V, P, 2], visible [V, P]
        cam = torch.einsum("vij,pj->vpi", R, x) + t[:, None]
        z = cam[..., 2]
        pix = torch.einsum("vij,vpj->vpi", K, cam)[..., :2] / z.clamp_min(1e-12)[..., None]
        seen = (z > 0) & (pix[..., 0] >= 0) & (pix[..., 0] <= width) & (pix[..., 1] >= 0) & (pix[..., 1] <= height)
        return pix, seen

    base_pix, seen = project(flat)
    unit = region.to_unit(flat)
    res = []
    for axis in range(3):
        moved = region.from_unit(unit + step * torch.eye(3, device=flat.device)[axis])
        pixels = (project(moved)[0] - base_pix).norm(dim=-1) / step  # [V, P]
        per_point = torch.where(seen, pixels, torch.zeros_like(pixels)).amax(dim=0)  # [P]
        res.append(2.0 * float(per_point.median()) / pixels_per_voxel)
    return _capped(torch.ceil(torch.tensor(res)), max_cells, min_resolution)


#: ``field.grid_resolution_rule`` -> the function that sizes the finest level.
RESOLUTION_RULES = {"footprint": resolution_from_footprint, "parallax": resolution_from_parallax}
