"""Adaptive K at render time: draw trajectories in batches until the variance estimates settle.

The field is evaluated once per chunk of rays; trajectories are then drawn from its parameters
in batches of ``b`` (draws are cheap given the parameters). After each batch the per-pixel
colour variance (mean over channels) ``v_c`` and total depth variance ``v_d`` are re-estimated
from all K draws so far, and drawing stops when both changed by less than ``rtol``:

    change(v) = sum_p |v_p(K) - v_p(K - b)| / sum_p max(v_p(K), v_floor)

(a relative L1 change over the chunk's pixels; single pixels are too noisy to test one by
one), or when ``K`` reaches ``max_draws``. Variances below the floors are what the metrics
cannot tell apart (``NLL_VARIANCE_FLOOR`` for colour, ``DEPTH_NLL_VARIANCE_FLOOR`` for depth):
if after the first batch the colour variance and the epistemic depth variance (variance of
D_k over draws) of every pixel of the chunk are below them, the draws are (nearly) identical
(a near-deterministic field, sigma -> 0), every estimate including the termination spread is
already exact, and drawing stops at K = b.

The K each chunk needed is returned as a map ``num_draws`` [H, W] (every pixel of a chunk shares
its chunk's K; the view's mean and max K follow from it).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .constants import DEPTH_NLL_VARIANCE_FLOOR, NLL_VARIANCE_FLOOR
from .fields.base import StochasticField
from .rays import RayBundle
from .renderer import MAP_NAMES, OccupiedFn, RenderSettings, render_any_samples, skip_empty
from .samplers import sample_along_rays
from .volume_rendering import TrajectoryStatistics, concatenate_draws


def relative_change(new: Tensor, old: Tensor, floor: float) -> float:
    """``sum |new - old| / sum max(new, floor)`` over all entries (see module doc)."""
    return float((new - old).abs().sum() / new.clamp_min(floor).sum())


def _colour_var(stats: TrajectoryStatistics) -> Tensor:
    return stats.colour_var.mean(dim=-1)  # [R]


def render_rays_adaptive(field: StochasticField, rays: RayBundle, settings: RenderSettings, *,
                         batch_draws: int | None = None, max_draws: int | None = None, rtol: float | None = None,
                         generator: torch.Generator | None = None,
                         occupied: OccupiedFn | None = None) -> tuple[TrajectoryStatistics, int, Tensor]:
    """Render rays [R] with adaptive K. Returns (statistics over the K draws, K, field evaluations [R]).

    Defaults come from ``settings.adaptive_*``.
    """
    b = settings.adaptive_batch_draws if batch_draws is None else batch_draws
    cap = settings.adaptive_max_draws if max_draws is None else max_draws
    tol = settings.adaptive_rtol if rtol is None else rtol
    if b < 1 or cap < b:
        raise ValueError(f"adaptive K needs 1 <= batch_draws <= max_draws, got batch_draws={b}, max_draws={cap}")
    if tol <= 0:
        raise ValueError(f"adaptive_rtol must be positive, got {tol}")
    samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing)
    samples = skip_empty(samples, occupied)
    params = field(samples.positions, samples.directions)
    first = render_any_samples(params, samples, settings, num_draws=b, generator=generator)

    def draw(k: int) -> TrajectoryStatistics:
        return render_any_samples(params, samples, settings, num_draws=k, generator=generator).stats

    parts: list[TrajectoryStatistics] = []
    stats: TrajectoryStatistics | None = None
    while True:
        parts.append(first.stats if not parts else draw(b))
        previous = stats
        stats = concatenate_draws(parts)
        K = b * len(parts)
        if K + b > cap:
            break
        cv = _colour_var(stats)
        if previous is None:
            # draws (nearly) identical: every estimate is already exact
            if bool((cv <= NLL_VARIANCE_FLOOR).all() and (stats.depth_var_epistemic <= DEPTH_NLL_VARIANCE_FLOOR).all()):
                break
            continue
        if (relative_change(cv, _colour_var(previous), NLL_VARIANCE_FLOOR) < tol
                and relative_change(stats.depth_var_total, previous.depth_var_total, DEPTH_NLL_VARIANCE_FLOOR) < tol):
            break
    return stats, K, first.extras["field_evals"]


@torch.no_grad()
def render_image_adaptive(field: StochasticField, rays: RayBundle, settings: RenderSettings, *,
                          batch_draws: int | None = None, max_draws: int | None = None, rtol: float | None = None,
                          generator: torch.Generator | None = None, keep_draws: bool = False,
                          progress: bool = False, occupied: OccupiedFn | None = None) -> dict[str, Tensor]:
    """``renderer.render_image`` with adaptive K per chunk of ``settings.chunk_rays`` rays.

    Returns the maps of ``render_image`` plus ``num_draws`` [H, W] (K of each pixel's chunk).
    With ``keep_draws``, per-draw maps
    are padded with NaN beyond each chunk's K to the largest K.
    """
    from tqdm.auto import tqdm

    shape = rays.shape
    flat = rays.flatten()
    out: dict[str, list[Tensor]] = {name: [] for name in (*MAP_NAMES, "field_evals_per_ray", "num_draws")}
    draws: dict[str, list[Tensor]] = {"depth_draws": [], "colour_draws": []}
    for start in tqdm(range(0, len(flat), settings.chunk_rays), desc="render (adaptive K)", disable=not progress,
                      leave=False):
        chunk = flat[start:start + settings.chunk_rays]
        stats, K, evals = render_rays_adaptive(field, chunk, settings, batch_draws=batch_draws, max_draws=max_draws,
                                               rtol=rtol, generator=generator, occupied=occupied)
        for name in MAP_NAMES:
            out[name].append(getattr(stats, name))
        out["field_evals_per_ray"].append(evals.to(stats.opacity.dtype))
        out["num_draws"].append(torch.full_like(stats.opacity, float(K)))
        if keep_draws:
            draws["depth_draws"].append(stats.depth_draws)
            draws["colour_draws"].append(stats.colour_draws)
    maps = {name: torch.cat(v).reshape(*shape, *torch.cat(v).shape[1:]) for name, v in out.items()}
    if keep_draws:
        k_max = max(d.shape[1] for d in draws["depth_draws"])
        for name, parts in draws.items():
            padded = [torch.nn.functional.pad(d, (0, 0) * (d.dim() - 2) + (0, k_max - d.shape[1]), value=float("nan"))
                      for d in parts]
            maps[name] = torch.cat(padded).reshape(*shape, *padded[0].shape[1:])
    maps["z_scale"] = rays.z_scale
    return maps
