"""A Laplace approximation of the trained density over coarse cells of space (post hoc).

S-NeRF's variational posterior gives every sample its own density noise; the noise of a ray's
samples is independent, so it averages out along the ray, and where the training photos see a
surface the density's scale is a few hundredths of its location (studies 34 and the analysis
after it, docs/studies.md): the K trajectories end at the same depth, and the depth std is almost
all termination spread. What the photos leave undetermined over a *region* (a floater no other
view refutes, a surface seen from one side) is a perturbation shared by every sample in it. This
module measures it with a diagonal Laplace approximation, as Bayes' Rays (Goli et al., CVPR 2024)
does for a deformation field, here for the density itself.

**Perturbation.** A coarse grid of ``resolution`` = (X, Y, Z) cells over the field's unit cube
(``SceneRegion.to_unit``); cell c scales the mean density of every point inside it,
``sigma(x) = E[relu(Y(x))] exp(delta_c)``, piecewise constant (a sample lies in one cell; a ray
crosses a cell in one run of consecutive samples). Samples outside the unit cube belong to no cell.

**Derivatives** (alpha quadrature, one ray, samples i = 1..S, optical depths tau_i = sigma_i
dt_i, transmittance T_i = exp(-sum_{j<i} tau_j), weights w_i = T_i (1 - exp(-tau_i)), final
transmittance T_{S+1}, opacity O = 1 - T_{S+1}), d tau_i / d delta_c = tau_i for i in c:

    dC / d tau_i = T_{i+1} c_i - sum_{j>i} w_j c_j - T_{S+1} b             (colour, background b)
    dD / d tau_i = (T_{i+1} t_i - sum_{j>i} w_j t_j - D T_{S+1}) / O        (D = sum_i w_i t_i / O)

so ``J_c = sum_{i in c} tau_i d/d tau_i`` is a sum over the ray's run of samples in c.

**Posterior.** With the colour likelihood N(C_r | c_r, sigma_n^2) of the training rays and a prior
delta_c ~ N(0, 1 / lambda), the Gauss-Newton Hessian's diagonal gives each cell the precision

    P_c = lambda + (N / M) sum_{r in M sampled rays} sum_ch (dC_r,ch / d delta_c)^2 / sigma_n,ch^2

(``fit_laplace_density``: M of the N training pixels, scaled to all of them), and a ray's expected
depth the linearised variance ``V_r = sum_c (dD_r / d delta_c)^2 / P_c`` (``LaplaceDensity.depth_std``,
in camera-z units: the ray distance times ``RayBundle.z_scale``). A cell no training ray passes
through keeps the prior's variance 1 / lambda; one many rays see with sensitivity gets a small one.
The mean density, the colour at the logits' mean (sigmoid(mu_c)) and dense samples (the model's
``num_samples`` and spacing, not stratified, nothing skipped) define the linearisation point.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from .constants import OPACITY_EPS
from .distributions import RectifiedNormal
from .io_utils import atomic_write
from .rays import PackedRaySamples, RayBundle, RaySamples
from .samplers import sample_along_rays
from .volume_rendering import exclusive_cumsum_packed, weights_alpha_from_optical_depth

#: Cells per axis of the perturbation grid (x, y, z of the field's unit cube).
LAPLACE_RESOLUTION: tuple[int, int, int] = (32, 32, 32)
#: Prior precision lambda of a cell's log-density offset (prior std 1: a factor e either way).
LAPLACE_PRIOR_PRECISION: float = 1.0
#: Training rays the Fisher information is summed over (a random subset, scaled to every pixel).
LAPLACE_FIT_RAYS: int = 65536
#: Rays per chunk of the fit and of ``depth_std``.
LAPLACE_CHUNK: int = 1024


def ray_derivatives(tau: Tensor, values: Tensor, background: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(composited values [R, C], their derivatives d/d tau_i [R, S, C]) of ``values`` [R, S, C]
    composited with optical depths ``tau`` [R, S] (module doc: ``T_{i+1} v_i - sum_{j>i} w_j v_j
    - T_{S+1} b``; ``background`` [C] or None)."""
    w = weights_alpha_from_optical_depth(tau)[..., None]  # [R, S, 1]
    after_i = torch.exp(-torch.cumsum(tau, dim=1))[..., None]  # T_{i+1} [R, S, 1]; its last is T_{S+1}
    wv = w * values
    composited = wv.sum(1)
    later = torch.flip(torch.cumsum(torch.flip(wv, [1]), dim=1), [1]) - wv  # sum_{j>i} w_j v_j, from the far end
    grad = after_i * values - later
    if background is not None:
        composited = composited + after_i[:, -1] * background
        grad = grad - after_i[:, -1:] * background
    return composited, grad


def depth_variance_packed(tau: Tensor, t_mids: Tensor, ray_indices: Tensor, num_rays: int, cells: Tensor,
                          precision: Tensor, *, samples_per_ray: int | None = None) -> Tensor:
    """V_r = sum_c J_rc^2 / P_c [R] of the opacity-normalised expected depth (ray-distance units, module doc)
    from packed samples: optical depths ``tau`` [N], distances ``t_mids`` [N], ``ray_indices`` [N] (sorted,
    each ray's samples in order of t), ``cells`` [N] (``cell_index``; -1: no cell) and the cells' precisions
    ``precision`` [C]; computed in float64.

    ``J_rc = sum_{i in c} tau_i dD_r / d tau_i`` with ``dD / d tau_i = (T_{i+1} t_i - sum_{j>i} w_j t_j - D
    T_{S+1}) / O``. A ray crosses a (convex) cell in one run of consecutive samples, so (ray, cell) pairs are
    runs of the packed order. Samples left out of the packing with tau = 0 change nothing: an
    empty-space-skipping render gives the variance of its dense samples. ``samples_per_ray``: every ray
    has that many samples (the dense layout flattened), whose per-ray sums are then plain cumulative sums."""
    R, C = int(num_rays), precision.shape[0]
    tau, t = tau.double(), t_mids.double()
    if tau.numel() == 0:
        return torch.zeros(R, dtype=torch.float64, device=tau.device)

    def exclusive(x: Tensor) -> Tensor:  # sum_{j<i, same ray} x_j
        if samples_per_ray is None:
            return exclusive_cumsum_packed(x, ray_indices, R)
        rows = x.reshape(R, samples_per_ray)
        return (torch.cumsum(rows, dim=1) - rows).reshape(-1)

    before = torch.exp(-exclusive(tau))  # T_i
    after = before * torch.exp(-tau)  # T_{i+1}
    wt = before * -torch.expm1(-tau) * t
    numerator = torch.zeros(R, dtype=torch.float64, device=tau.device).index_add_(0, ray_indices, wt)
    total = torch.zeros_like(numerator).index_add_(0, ray_indices, tau)
    final, o = torch.exp(-total), (-torch.expm1(-total)).clamp_min(OPACITY_EPS)
    depth = numerator / o
    later = numerator[ray_indices] - exclusive(wt) - wt  # sum_{j>i} w_j t_j
    per_sample = tau * (after * t - later - (depth * final)[ray_indices]) / o[ray_indices]
    seen = cells >= 0
    keys, run = torch.unique_consecutive(ray_indices[seen] * C + cells[seen], return_inverse=True)
    J = torch.zeros(keys.shape[0], dtype=torch.float64, device=tau.device).index_add_(0, run, per_sample[seen])
    var = J ** 2 / precision.to(tau.device, torch.float64)[keys % C]
    return torch.zeros_like(numerator).index_add_(0, keys // C, var)


def cell_runs(cells: Tensor, per_sample: Tensor) -> tuple[Tensor, Tensor]:
    """Sums of ``per_sample`` [R, S, C] over each ray's runs of consecutive samples in one cell.

    ``cells`` [R, S] int64, -1 for a sample in no cell. Returns (cell of each run [R, S], -1 where
    there is no run; the run's sums [R, S, C]): run k of ray r in slot k (a ray has at most S runs)."""
    R, S = cells.shape
    start = torch.ones_like(cells, dtype=torch.bool)
    start[:, 1:] = cells[:, 1:] != cells[:, :-1]
    run = torch.cumsum(start.long(), dim=1) - 1  # [R, S] run slot of each sample
    sums = torch.zeros_like(per_sample).scatter_add_(1, run[..., None].expand_as(per_sample), per_sample)
    run_cell = torch.full_like(cells, -1).scatter_(1, run, cells)
    return run_cell, sums


def cell_index(unit: Tensor, resolution: tuple[int, int, int]) -> Tensor:
    """Cell index [*B] of unit-cube points [*B, 3] on a grid of ``resolution`` (X, Y, Z) cells (x
    fastest), -1 outside the cube."""
    res = torch.tensor(resolution, device=unit.device)
    ijk = torch.minimum(((unit + 1.0) * 0.5 * res).floor().long().clamp(min=0), res - 1)
    X, Y, _ = resolution
    idx = (ijk[..., 2] * Y + ijk[..., 1]) * X + ijk[..., 0]
    return torch.where((unit.abs() <= 1.0).all(-1), idx, torch.full_like(idx, -1))


@dataclass
class LaplaceDensity:
    """The cells' posterior precisions P_c [X Y Z] (module doc), on the grid ``resolution``."""

    resolution: tuple[int, int, int]
    precision: Tensor
    prior_precision: float
    rays_used: int

    def depth_std(self, model, rays: RayBundle, *, chunk: int = LAPLACE_CHUNK) -> Tensor:
        """sqrt(V_r) [R] of flat ``rays`` [R] in camera-z units (module doc)."""
        settings, out = model.render_settings, []
        for start in range(0, rays.origins.shape[0], chunk):
            samples = sample_along_rays(rays[start:start + chunk], settings.num_samples, spacing=settings.spacing,
                                        stratified=False)
            with torch.no_grad():
                loc, scale = model.field.density_params(samples.positions)
            out.append(self.depth_std_of_samples(samples, loc.double(), scale.double(), model.field.region))
        return torch.cat(out) if out else torch.zeros(0, device=rays.origins.device)

    def depth_std_of_samples(self, samples: RaySamples | PackedRaySamples, density_loc: Tensor, density_scale: Tensor,
                             region) -> Tensor:
        """sqrt(V_r) [R] in camera-z units from a render's own samples (dense [R, S] or packed [N]) and the
        density parameters the render evaluated there (same layout; the linearisation point E[relu(Y)] is
        computed in their precision, the derivatives in float64): ``depth_std`` on dense samples, equal to it
        when the render skipped nothing or only samples of zero density; ``region``: the field's
        ``SceneRegion``. Costs no field evaluation."""
        if isinstance(samples, PackedRaySamples):
            ray_indices, n, S = samples.ray_indices, samples.num_rays, None
        else:
            n, S = samples.t_starts.shape
            ray_indices = torch.arange(n, device=samples.t_starts.device).repeat_interleave(S)
        tau, cells = _optical_depth_and_cells(samples, density_loc, density_scale, region, self.resolution)
        var = depth_variance_packed(tau.reshape(-1), samples.t_mids.reshape(-1), ray_indices, n, cells.reshape(-1),
                                    self.precision, samples_per_ray=S)
        return var.sqrt() * samples.rays.z_scale.double()

    def save(self, path: Path) -> None:
        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, resolution=np.asarray(self.resolution), precision=self.precision.cpu().numpy(),
                         prior_precision=self.prior_precision, rays_used=self.rays_used)

        atomic_write(path, write)

    @staticmethod
    def load(path: Path) -> "LaplaceDensity":
        try:
            with np.load(Path(path), allow_pickle=False) as f:
                res = tuple(int(v) for v in f["resolution"])
                precision = torch.from_numpy(f["precision"])
                prior, used = float(f["prior_precision"]), int(f["rays_used"])
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a readable Laplace density file ({exc})") from None
        if len(res) != 3 or precision.shape != (res[0] * res[1] * res[2],) or not bool((precision > 0).all()):
            raise ValueError(f"{path}: not a Laplace density file (resolution {res}, precision "
                             f"{tuple(precision.shape)}, all > 0 needed)")
        return LaplaceDensity(res, precision, prior, used)


def _linearisation(model, rays: RayBundle, resolution: tuple[int, int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """(tau [R, S], colours [R, S, 3], cells [R, S]) of the mean field on dense samples of ``rays``
    (module doc), in float64: what the fit's colour derivatives need."""
    settings = model.render_settings
    samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing, stratified=False)
    positions = samples.positions
    with torch.no_grad():
        params = model.field(positions, rays.directions[:, None, :].expand_as(positions))
    tau, cells = _optical_depth_and_cells(samples, params.density_loc.double(), params.density_scale.double(),
                                          model.field.region, resolution)
    return tau, torch.sigmoid(params.rgb_loc).double(), cells


def _optical_depth_and_cells(samples: RaySamples | PackedRaySamples, density_loc: Tensor, density_scale: Tensor,
                             region, resolution: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """(tau, cells), each in ``samples``' layout ([R, S] or [N]): the optical depth E[relu(Y)] dt (float64;
    the mean computed in the parameters' precision) and the perturbation cell of each sample (module doc)."""
    density = RectifiedNormal(density_loc, density_scale).mean.double()
    tau = density * (samples.t_ends - samples.t_starts).double()
    positions = samples.positions
    unit = region.to_unit(positions.reshape(-1, 3)).reshape(positions.shape)
    return tau, cell_index(unit, resolution)


def fit_laplace_density(model, rays: RayBundle, *, resolution: tuple[int, int, int] = LAPLACE_RESOLUTION,
                        prior_precision: float = LAPLACE_PRIOR_PRECISION, max_rays: int = LAPLACE_FIT_RAYS,
                        seed: int = 0, chunk: int = LAPLACE_CHUNK, progress: bool = False) -> LaplaceDensity:
    """The cells' precisions P_c from the training ``rays`` [N] (flat; module doc): the Fisher
    information of the colour likelihood (the model's ``likelihood_std``) summed over ``max_rays`` of
    them drawn with ``seed`` (all when fewer), times N / M, plus ``prior_precision``."""
    if not prior_precision > 0:
        raise ValueError(f"prior_precision must be > 0, got {prior_precision}")
    if len(resolution) != 3 or min(resolution) < 1:
        raise ValueError(f"resolution must be three cell counts >= 1, got {resolution}")
    n = rays.origins.shape[0]
    if n == 0:
        raise ValueError("fit_laplace_density needs at least one training ray")
    device = rays.origins.device
    m = min(n, int(max_rays))
    pick = torch.randperm(n, generator=torch.Generator().manual_seed(seed))[:m].to(device)
    noise_var = (model.likelihood_std().detach().double().reshape(-1) ** 2).expand(3).to(device)
    background = model.render_settings.background
    bg = None if background is None else torch.tensor(background, dtype=torch.float64, device=device)
    resolution = tuple(int(v) for v in resolution)
    fisher = torch.zeros(resolution[0] * resolution[1] * resolution[2], dtype=torch.float64, device=device)
    for start in tqdm(range(0, m, chunk), desc="laplace: training rays", disable=not progress, leave=False):
        r = rays[pick[start:start + chunk]]
        tau, rgb, cells = _linearisation(model, r, resolution)
        _, d_colour = ray_derivatives(tau, rgb, bg)
        run_cell, J = cell_runs(cells, tau[..., None] * d_colour)
        seen = run_cell >= 0
        fisher.index_add_(0, run_cell[seen], (J[seen] ** 2 / noise_var).sum(-1))
    precision = fisher * (n / m) + float(prior_precision)
    return LaplaceDensity(resolution, precision, float(prior_precision), m)
