"""From a field to K rendered trajectories per ray, and to full images in chunks.

    params = field(x_i, d)                          per sample i           [R, S]
    alpha_ik = relu(mu_a,i + s_a,i eps_ik)          K draws                [R, K, S]
    r_ikc = sigmoid(mu_c,i + s_c,i eps_ikc)                                [R, K, S, 3]
    w_ik = quadrature(alpha_k, t)                   alpha compositing or trapezoid
    C_k = sum_i w_ik r_ik,  D_k = sum_i w_ik t_i / sum_i w_ik
    colour mean/var, depth mean / epistemic var / termination spread over k (docs/definitions.md §3)

Noise: independent eps per point and draw (the paper), or shared along the ray per draw
(``shared_noise=True``: every trajectory is one consistent field realisation along the ray).
``deterministic=True`` uses eps = 0 (the mean field), for baselines without a distribution.

Empty-space skipping: ``render_rays(..., occupied=fn)`` keeps only the dense samples whose
midpoint ``fn(positions [R, S, 3]) -> [R, S] bool`` marks as occupied and renders the packed
(ragged) samples with ``volume_rendering``'s ``*_packed`` functions, alpha compositing only (the
packed trapezoid treats samples on both sides of a skipped gap as neighbours and is wrong
there, so that combination raises). A batch in which the grid skips less than
``PACK_MIN_SKIPPED_FRACTION`` of the samples stays dense (``skip_empty``): packing would cost
more than it saves. Every render records the field evaluations per ray
(``RayRender.extras["field_evals"]`` [R], ``render_image`` map ``field_evals_per_ray``).

Rao-Blackwellised colours (``colour_estimator="rao_blackwell"``): only the densities are drawn;
the colours enter through each sample's tabulated logistic-normal mean and variance
(``volume_rendering.trajectory_statistics`` with ``rgb_var``). Given noise ``(eps_a, eps_c)``
uses ``eps_a`` only (``eps_c`` may be None).

Packed and dense draws agree exactly for ``shared_noise=True``: the packed path draws the same
``[R, K, 1]`` noise as the dense one and gathers it per sample. With independent noise the
packed path draws ``[K, N]`` (one eps per kept sample); pass ``noise=`` to fix the draws.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field as dataclass_field
from typing import Callable, Literal

import torch
from torch import Tensor
from tqdm.auto import tqdm
import numpy as np

from .constants import COLOUR_PLAN_MAX_PAIRS, DRAW_BLOCK_ELEMENTS, PACK_MIN_SKIPPED_FRACTION
from .fields.base import FieldParams, StochasticField
from .logistic_normal_table import logistic_normal_moments_tabulated
from .rays import PackedRaySamples, RayBundle, RaySamples
from .samplers import sample_along_rays
from .settings import COLOUR_ESTIMATORS, RENDER_CHECKS, RenderSettings, Spacing  # noqa: F401  (re-exported)
from .validation import Checker, boolean, check_fields
from .volume_rendering import (LogitNormalColourDraws, TrajectoryStatistics, concatenate_draws,
                               exclusive_cumsum_packed, observation_noise, observation_noise_packed, render_weights,
                               render_weights_packed, trajectory_statistics, trajectory_statistics_packed,
                               transmittance_alpha, weights_alpha_from_optical_depth)
from . import draw_kernels

#: ``occupied(positions [R, S, 3]) -> [R, S] bool``: which dense samples to keep (empty-space skipping).
OccupiedFn = Callable[[Tensor], Tensor]


def dense_noise(num_rays: int, num_draws: int, num_samples: int, *, shared_noise: bool = False,
                generator: torch.Generator | None = None, device=None,
                dtype: torch.dtype = torch.float32, colour: bool = True) -> tuple[Tensor, Tensor | None]:
    """Standard-normal eps for the dense layout: ([R, K, S'], [R, K, S', 3]), S' = 1 when shared;
    the colour eps None without ``colour`` (Rao-Blackwellised colours draw none)."""
    s_axis = 1 if shared_noise else num_samples
    eps_a = torch.randn(num_rays, num_draws, s_axis, generator=generator, device=device, dtype=dtype)
    eps_c = torch.randn(num_rays, num_draws, s_axis, 3, generator=generator, device=device, dtype=dtype) \
        if colour else None
    return eps_a, eps_c


def gather_shared_noise(noise: tuple[Tensor, Tensor | None], ray_indices: Tensor) -> tuple[Tensor, Tensor | None]:
    """Dense shared eps ([R, K, 1], [R, K, 1, 3] or None) -> packed eps ([K, N], [K, N, 3] or None)
    of the samples' rays."""
    eps_a, eps_c = noise
    return eps_a[ray_indices, :, 0].T, None if eps_c is None else eps_c[ray_indices, :, 0].transpose(0, 1)


def draw_blocks(num_draws: int, pairs_per_draw: int) -> list[tuple[int, int]]:
    """(first draw, draws) of each block: at most ``DRAW_BLOCK_ELEMENTS`` (sample, draw) pairs per
    block and at least one draw. The renderers draw and composite block by block, so memory for
    temporaries does not grow with K (see constants)."""
    per_block = max(1, DRAW_BLOCK_ELEMENTS // max(pairs_per_draw, 1))
    return [(k0, min(per_block, num_draws - k0)) for k0 in range(0, num_draws, per_block)]


def draw_locs(density_loc: Tensor, density_offsets: Tensor | None, first_draw: int, num_draws: int, *,
              packed: bool) -> Tensor:
    """The density locs the draws first_draw .. first_draw + k - 1 draw around: mu_a + o_{j mod M}
    for draw j (``FieldParams.density_offsets``; None: mu_a for every draw). Dense: loc [R, S],
    offsets [R, S, M] -> [R, k, S] ([R, 1, S] without heads); packed: loc [N], offsets [N, M] ->
    [k, N] ([1, N] without heads)."""
    if density_offsets is None:
        return head_centres(density_loc, None, packed=packed)
    heads = torch.arange(first_draw, first_draw + num_draws, device=density_loc.device) % density_offsets.shape[-1]
    if packed:
        return density_loc[None] + density_offsets[:, heads].T
    return density_loc[:, None, :] + density_offsets[..., heads].permute(0, 2, 1)


def head_centres(density_loc: Tensor, density_offsets: Tensor | None, *, packed: bool) -> Tensor:
    """The M density heads' locs ``mu_a + o_h``: dense loc [R, S], offsets [R, S, M] -> [R, M, S]; packed
    loc [N], offsets [N, M] -> [M, N]; without heads (None) [R, 1, S] / [1, N]."""
    if density_offsets is None:
        return density_loc[None] if packed else density_loc[:, None, :]
    return density_loc[None] + density_offsets.T if packed else density_loc[:, None, :] + density_offsets.permute(0, 2, 1)


def drawn_density(density_loc: Tensor, density_scale: Tensor, density_offsets: Tensor | None, eps: Tensor,
                  first_draw: int = 0, *, packed: bool) -> Tensor:
    """The draws' densities ``relu(mu_a + o_{j mod M} + s_a eps_j)`` for draws j = first_draw .. first_draw
    + k - 1 (``draw_locs``). Dense: loc, scale [R, S], offsets [R, S, M] or None, eps [R, k, S'] (S' = S or
    1) -> [R, k, S]; packed: loc, scale [N], offsets [N, M] or None, eps [k, N] -> [k, N].

    With heads, a block that starts at a head-0 draw and holds whole rounds of the M heads (the
    renderers' blocks) broadcasts the M locs over [k / M, M] instead of gathering one loc per draw:
    the same values bit for bit, and about a third of the time on a dense chunk (a last-axis gather of
    [R, S, M] into [R, S, k] and its permuted add took 4 ms of a 2048-ray chunk on two threads)."""
    k = eps.shape[0] if packed else eps.shape[1]
    heads = 0 if density_offsets is None else density_offsets.shape[-1]
    if heads and first_draw % heads == 0 and k % heads == 0:
        centre = head_centres(density_loc, density_offsets, packed=packed)  # [M, N] / [R, M, S]
        if packed:
            drawn = centre[None] + density_scale[None, None] * eps.reshape(k // heads, heads, -1)
            return torch.relu(drawn).reshape(k, -1)
        drawn = centre[:, None] + density_scale[:, None, None, :] * eps.reshape(eps.shape[0], k // heads, heads, -1)
        return torch.relu(drawn).reshape(eps.shape[0], k, -1)
    loc = draw_locs(density_loc, density_offsets, first_draw, k, packed=packed)
    return torch.relu(loc + (density_scale[None] if packed else density_scale[:, None, :]) * eps)


def draw_trajectories(params: FieldParams, num_draws: int, *, shared_noise: bool = False,
                      deterministic: bool = False, generator: torch.Generator | None = None,
                      noise: tuple[Tensor, Tensor] | None = None, first_draw: int = 0) -> tuple[Tensor, Tensor]:
    """Reparameterised draws: params [R, S] -> density [R, K, S], rgb [R, K, S, 3].

    ``alpha = relu(mu_a + s_a eps_a)``, ``r = sigmoid(mu_c + s_c eps_c)``; ``noise`` fixes
    (eps_a [R, K, S], eps_c [R, K, S, 3]) (or S = 1 to share along rays) instead of drawing it.
    With density heads draw j (counted from ``first_draw``) draws around mu_a + o_{j mod M}
    (``draw_locs``); the deterministic draws are the centre's.
    """
    R, S = params.density_loc.shape
    dev, dt = params.density_loc.device, params.density_loc.dtype
    K = num_draws
    if deterministic:
        density = torch.relu(params.density_loc)[:, None, :].expand(R, K, S)
        rgb = torch.sigmoid(params.rgb_loc)[:, None].expand(R, K, S, 3)
        return density, rgb
    if noise is None:
        noise = dense_noise(R, K, S, shared_noise=shared_noise, generator=generator, device=dev, dtype=dt)
    eps_a, eps_c = noise
    density = drawn_density(params.density_loc, params.density_scale, params.density_offsets, eps_a, first_draw,
                            packed=False)
    rgb = torch.sigmoid(params.rgb_loc[:, None] + params.rgb_scale[:, None] * eps_c)
    return density, rgb


def draw_trajectories_packed(params: FieldParams, num_draws: int, ray_indices: Tensor, num_rays: int, *,
                             shared_noise: bool = False, deterministic: bool = False,
                             generator: torch.Generator | None = None,
                             noise: tuple[Tensor, Tensor] | None = None, first_draw: int = 0) -> tuple[Tensor, Tensor]:
    """Packed draws: params [N] -> density [K, N], rgb [K, N, 3] (draws axis first).

    Shared noise draws the dense layout's ``[R, K, 1]`` eps (same generator consumption as
    ``draw_trajectories``) and gathers it per sample, so both layouts give identical draws.
    ``noise`` fixes (eps_a [K, N], eps_c [K, N, 3]); density heads as ``draw_trajectories``.
    """
    N = params.density_loc.shape[0]
    dev, dt = params.density_loc.device, params.density_loc.dtype
    K = num_draws
    if deterministic:
        return (torch.relu(params.density_loc)[None].expand(K, N),
                torch.sigmoid(params.rgb_loc)[None].expand(K, N, 3))
    if noise is None:
        if shared_noise:
            noise = gather_shared_noise(dense_noise(num_rays, K, 1, shared_noise=True, generator=generator,
                                                    device=dev, dtype=dt), ray_indices)
        else:
            noise = (torch.randn(K, N, generator=generator, device=dev, dtype=dt),
                     torch.randn(K, N, 3, generator=generator, device=dev, dtype=dt))
    eps_a, eps_c = noise
    density = drawn_density(params.density_loc, params.density_scale, params.density_offsets, eps_a, first_draw,
                            packed=True)
    rgb = torch.sigmoid(params.rgb_loc[None] + params.rgb_scale[None] * eps_c)
    return density, rgb


@dataclass
class RayRender:
    """Result of rendering a batch of rays: statistics over K plus what produced them."""

    stats: TrajectoryStatistics
    params: FieldParams  # [R, S] dense or [N] packed
    samples: RaySamples | PackedRaySamples
    extras: dict = dataclass_field(default_factory=dict)
    """``weights`` ([R, K, S] dense, [K, N] packed) and ``field_evals`` [R] (samples evaluated per ray)."""


def _background(settings: RenderSettings, like: Tensor) -> Tensor | None:
    if settings.background is None:
        return None
    return torch.tensor(settings.background, device=like.device, dtype=like.dtype)


def _noise_block(noise: tuple[Tensor, Tensor | None], *index: slice) -> tuple[Tensor, Tensor | None]:
    """Both eps tensors indexed alike; the colour eps may be None (Rao-Blackwellised colours draw none)."""
    return noise[0][index], None if noise[1] is None else noise[1][index]


def check_colour_estimator(estimator: str) -> str:
    """``estimator`` if it is one of COLOUR_ESTIMATORS, else ValueError naming the value."""
    if estimator not in COLOUR_ESTIMATORS:
        raise ValueError(f"colour_estimator must be one of {COLOUR_ESTIMATORS}, got {estimator!r}")
    return estimator


def _use_rao_blackwell(settings: RenderSettings, colour_estimator: str | None, deterministic: bool) -> bool:
    estimator = check_colour_estimator(settings.colour_estimator if colour_estimator is None else colour_estimator)
    return estimator == "rao_blackwell" and not deterministic


def colour_moments(params: FieldParams, settings: RenderSettings) -> tuple[Tensor, Tensor] | None:
    """Per-sample colour means and variances ``(E[r_i], Var[r_i])`` (shaped like ``params.rgb_loc``)
    when ``settings`` renders Rao-Blackwellised colours, else None. Pass them as ``colour_moments=``
    to render the same parameters several times (adaptive K) without recomputing them."""
    if not _use_rao_blackwell(settings, None, False):
        return None
    return logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)


def reached_colour_moments(params: FieldParams, reached: Tensor) -> tuple[Tensor, Tensor]:
    """``colour_moments`` [R, S, 3] read from the table only at the samples a ``ColourPlan`` kept
    (``reached`` [R, S] bool): at a capture's end of training a sixth to a quarter of them. The others
    hold the field's placeholder colours (``forward_colour_where``), whose weight is below the plan's
    transmittance in every trajectory; they take the moments of the first of them (the grid field's
    placeholders are all one value, so its render is the full table read's to float rounding)."""
    loc, scale = params.rgb_loc.reshape(-1, 3), params.rgb_scale.reshape(-1, 3)
    keep = reached.reshape(-1)
    kept = keep.nonzero().squeeze(1)
    if kept.numel() == keep.numel():
        return logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)
    first_skipped = torch.argmin(keep.to(torch.uint8)).reshape(1)
    read = torch.cat([kept, first_skipped])
    mean, var = logistic_normal_moments_tabulated(loc[read], scale[read])
    full_mean = mean[-1:].expand(keep.numel(), 3).index_copy(0, kept, mean[:-1])
    full_var = var[-1:].expand(keep.numel(), 3).index_copy(0, kept, var[:-1])
    return full_mean.reshape(params.rgb_loc.shape), full_var.reshape(params.rgb_loc.shape)


def observation_variance(params: FieldParams, settings: RenderSettings,
                         observation_noise: bool | None = None) -> Tensor | None:
    """Per-sample observation-noise variance beta_i^2 (shaped like ``params.density_loc``) to
    composite into each draw's pixel variance, or None: when the field has no noise head, or
    ``observation_noise`` is False (None: only for ``colour_variance='predictive'``, where the
    rendered colour variance is the predictive one, docs/definitions.md §4.7)."""
    if params.noise_scale is None:
        return None
    if observation_noise is None:
        observation_noise = settings.colour_variance == "predictive"
    return params.noise_scale ** 2 if observation_noise else None


def observation_noise_per_draw(out: "RayRender", *, detach_weights: bool = False) -> Tensor:
    """[R, K, 3] v_k = sum_i w_ik beta_i^2 of a render whose field has a noise head (every
    channel), from its weights (detached with ``detach_weights``) and ``params.noise_scale``."""
    beta2 = out.params.noise_scale ** 2
    w = out.extras["weights"].detach() if detach_weights else out.extras["weights"]
    if isinstance(out.samples, PackedRaySamples):  # w [K, N]
        return observation_noise_packed(w, beta2, out.samples.ray_indices, out.samples.num_rays)
    return observation_noise(w, beta2)  # w [R, K, S], beta2 [R, S]


def _folded_optical_depth_params(params: FieldParams, samples: RaySamples) -> tuple[Tensor, Tensor]:
    """``(mu_a delta, s_a delta)`` [R, 1, S]: since ``relu(x) delta = relu(x delta)`` for delta > 0, a
    draw's optical depths are ``relu(mu_a delta + s_a delta eps)`` without a separate density tensor."""
    deltas = samples.t_ends - samples.t_starts
    return (params.density_loc * deltas)[:, None, :], (params.density_scale * deltas)[:, None, :]


#: Half dtypes: their 10-bit (float16) / 7-bit (bfloat16) mantissas lose transmittance products,
#: cumulative optical depths and depths of tens of scene units, so renders upcast them to float32.
HALF_DTYPES: tuple[torch.dtype, ...] = (torch.float16, torch.bfloat16)


def upcast_half(obj):
    """``obj`` (tensor, tuple, dataclass of them, or None) with float16/bfloat16 tensors as float32."""
    if isinstance(obj, Tensor):
        return obj.float() if obj.dtype in HALF_DTYPES else obj
    if isinstance(obj, tuple):
        return tuple(upcast_half(o) for o in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: upcast_half(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                                           if f.init})
    return obj


def render_samples(params: FieldParams, samples: RaySamples, settings: RenderSettings, *, num_draws: int,
                   deterministic: bool = False, generator: torch.Generator | None = None,
                   noise: tuple[Tensor, Tensor] | None = None, colour_estimator: str | None = None,
                   colour_moments: tuple[Tensor, Tensor] | None = None,
                   observation_noise: bool | None = None,
                   drawn: tuple[Tensor, Tensor] | None = None) -> RayRender:
    """K trajectories from field parameters already evaluated at ``samples`` ([R, S]).

    Draws are made and composited in blocks of ``draw_blocks(K, R * S)``; independent noise is
    drawn block by block (a seed gives the same draws as before blocking while K R S fits in one
    block), shared noise for all K at once (as the packed layout, which then agrees exactly).
    ``colour_estimator`` overrides ``settings.colour_estimator``; ``colour_moments`` gives the
    Rao-Blackwellised estimator's per-sample moments if already computed (``colour_moments()``).
    ``observation_noise``: add the noise head's per-draw variance (``observation_variance``).
    ``drawn``: (densities, transmittances) [R, K, S] of the K draws a ``ColourPlan`` already drew from
    ``noise`` (``ColourPlan.drawn``); without autograd the weights are composited from them, the same
    values bit for bit, instead of drawing them again (the Rao-Blackwellised render with density heads
    and drawn colours; the one-head Rao-Blackwellised render folds its optical depths and draws anew).
    float16/bfloat16 inputs are rendered in float32 (``upcast_half``); the statistics are float32.
    """
    params, samples, noise, colour_moments = upcast_half((params, samples, noise, colour_moments))
    obs_var = observation_variance(params, settings, observation_noise)
    R, S = samples.t_starts.shape
    dev, dt = params.density_loc.device, params.density_loc.dtype
    reuse = (drawn is not None and not deterministic and not torch.is_grad_enabled()
             and drawn[0].shape == (R, num_draws, S) and drawn[0].dtype == dt)
    rao_blackwell = _use_rao_blackwell(settings, colour_estimator, deterministic)
    if noise is None and settings.shared_noise and not deterministic:
        noise = dense_noise(R, num_draws, S, shared_noise=True, generator=generator, device=dev, dtype=dt)
    if rao_blackwell:  # [R, S, 3] each
        rgb_mean, rgb_var = colour_moments or logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)
        folded = _folded_optical_depth_params(params, samples) \
            if settings.quadrature == "alpha" and params.density_offsets is None else None
    blocks = [(0, num_draws)] if deterministic else draw_blocks(num_draws, R * S)
    parts, weights = [], []
    for k0, k in blocks:
        block_noise = None if noise is None else _noise_block(noise, slice(None), slice(k0, k0 + k))
        if rao_blackwell:
            eps_a = (torch.randn(R, k, S, generator=generator, device=dev, dtype=dt) if block_noise is None
                     else block_noise[0])
            if folded is not None:  # tau = relu(mu_a delta + s_a delta eps): two passes over [R, k, S]
                w = weights_alpha_from_optical_depth(torch.relu(torch.addcmul(*folded, eps_a)))
            elif reuse:
                w = _weights_from_drawn(drawn, samples, k0, k)
            else:
                w = trajectory_weights(params.density_loc, params.density_scale, samples, settings, num_draws=k,
                                       noise=eps_a, density_offsets=params.density_offsets, first_draw=k0)
            rgb, block_rgb_var = rgb_mean, rgb_var
        elif deterministic:
            density, rgb = draw_trajectories(params, k, deterministic=True)
            w = render_weights(density, samples.t_starts[:, None, :], samples.t_ends[:, None, :], settings.quadrature)
            block_rgb_var = None
        else:  # draw_trajectories' draws, the colours composited from their logits (one autograd node)
            eps_a, eps_c = block_noise if block_noise is not None else dense_noise(
                R, k, S, shared_noise=settings.shared_noise, generator=generator, device=dev, dtype=dt)
            w = _weights_from_drawn(drawn, samples, k0, k) if reuse else trajectory_weights(
                params.density_loc, params.density_scale, samples, settings, num_draws=k, noise=eps_a,
                density_offsets=params.density_offsets, first_draw=k0)
            rgb, block_rgb_var = LogitNormalColourDraws(params.rgb_loc, params.rgb_scale, eps_c), None
        parts.append(trajectory_statistics(w, rgb, samples.t_mids[:, None, :], samples.rays.far,
                                           background=_background(settings, w), rgb_var=block_rgb_var,
                                           observation_var=obs_var))
        weights.append(w)
    evals = torch.full((R,), S, device=dev, dtype=torch.long)
    return RayRender(stats=concatenate_draws(parts), params=params, samples=samples,
                     extras={"weights": torch.cat(weights, dim=1) if len(weights) > 1 else weights[0],
                             "field_evals": evals})


def _weights_from_drawn(drawn: tuple[Tensor, Tensor], samples: RaySamples, first_draw: int, num_draws: int) -> Tensor:
    """[R, k, S] alpha weights of draws first_draw .. + k - 1 from a plan's densities and transmittances:
    ``w = T (1 - exp(-a delta))``, computed as ``weights_alpha_from_optical_depth`` does without autograd
    (the same values bit for bit)."""
    density, transmittance = (x[:, first_draw:first_draw + num_draws] for x in drawn)
    tau = density * samples.deltas[:, None, :]
    return torch.neg(tau).expm1_().mul_(transmittance).neg_()


def trajectory_weights(density_loc: Tensor, density_scale: Tensor, samples: RaySamples, settings: RenderSettings, *,
                       num_draws: int, generator: torch.Generator | None = None, noise: Tensor | None = None,
                       density_offsets: Tensor | None = None, first_draw: int = 0) -> Tensor:
    """The compositing weights [R, K, S] of K density draws at dense ``samples`` from the density
    parameters alone (mu_a, s_a [R, S]; ``field.density_params``): what a loss on the termination
    distribution needs, without evaluating or drawing colours.
    ``alpha = relu(mu_a + s_a eps_a)`` with eps_a [R, K, S] (or [R, K, 1] with
    ``settings.shared_noise``) from ``generator``, or ``noise`` if given; the weights equal
    ``render_samples``' for the same eps_a. ``density_offsets`` [R, S, M]: the density heads' (draw j,
    counted from ``first_draw``, draws around mu_a + o_{j mod M}, ``draw_locs``)."""
    density_loc, density_scale, samples, density_offsets = upcast_half((density_loc, density_scale, samples,
                                                                        density_offsets))
    R, S = samples.t_starts.shape
    if noise is None:
        noise = torch.randn(R, num_draws, 1 if settings.shared_noise else S, generator=generator,
                            device=density_loc.device, dtype=density_loc.dtype)
    density = drawn_density(density_loc, density_scale, density_offsets, noise, first_draw, packed=False)
    return render_weights(density, samples.t_starts[:, None, :], samples.t_ends[:, None, :], settings.quadrature)


def render_samples_packed(params: FieldParams, samples: PackedRaySamples, settings: RenderSettings, *,
                          num_draws: int, deterministic: bool = False, generator: torch.Generator | None = None,
                          noise: tuple[Tensor, Tensor] | None = None, colour_estimator: str | None = None,
                          colour_moments: tuple[Tensor, Tensor] | None = None,
                          observation_noise: bool | None = None) -> RayRender:
    """K trajectories from field parameters evaluated at packed samples ([N]); alpha compositing only.

    Shapes: params [N]; returns statistics per ray [R, ...] like ``render_samples``. Blocks of
    draws, ``colour_estimator``, ``colour_moments`` and ``observation_noise`` as ``render_samples``
    (``draw_blocks(K, N)``).
    """
    if settings.quadrature != "alpha":
        raise ValueError(f"packed samples (empty-space skipping) need quadrature='alpha', got "
                         f"{settings.quadrature!r}: the packed trapezoid interpolates across skipped gaps")
    params, samples, noise, colour_moments = upcast_half((params, samples, noise, colour_moments))
    obs_var = observation_variance(params, settings, observation_noise)
    R, N = samples.num_rays, samples.ray_indices.shape[0]
    dev, dt = params.density_loc.device, params.density_loc.dtype
    rao_blackwell = _use_rao_blackwell(settings, colour_estimator, deterministic)
    shared = None
    if noise is None and settings.shared_noise and not deterministic:
        shared = dense_noise(R, num_draws, 1, shared_noise=True, generator=generator, device=dev, dtype=dt)
    if rao_blackwell:  # [N, 3] each
        rgb_mean, rgb_var = colour_moments or logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)
    blocks = [(0, num_draws)] if deterministic else draw_blocks(num_draws, N)
    parts, weights = [], []
    for k0, k in blocks:
        if shared is not None:
            block_noise = gather_shared_noise((shared[0][:, k0:k0 + k], shared[1][:, k0:k0 + k]), samples.ray_indices)
        else:
            block_noise = None if noise is None else _noise_block(noise, slice(k0, k0 + k))
        if rao_blackwell:
            eps_a = (torch.randn(k, N, generator=generator, device=dev, dtype=dt) if block_noise is None
                     else block_noise[0])
            density = drawn_density(params.density_loc, params.density_scale, params.density_offsets, eps_a, k0,
                                    packed=True)
            rgb, block_rgb_var = rgb_mean, rgb_var
        else:
            density, rgb = draw_trajectories_packed(params, k, samples.ray_indices, R,
                                                    shared_noise=settings.shared_noise, deterministic=deterministic,
                                                    generator=generator, noise=block_noise, first_draw=k0)
            block_rgb_var = None
        w = render_weights_packed(density, samples.t_starts, samples.t_ends, samples.ray_indices, R, "alpha")
        parts.append(trajectory_statistics_packed(w, rgb, samples.t_mids, samples.ray_indices, R, samples.rays.far,
                                                  background=_background(settings, w), rgb_var=block_rgb_var,
                                                  observation_var=obs_var))
        weights.append(w)
    evals = torch.bincount(samples.ray_indices, minlength=R)
    return RayRender(stats=concatenate_draws(parts), params=params, samples=samples,
                     extras={"weights": torch.cat(weights, dim=0) if len(weights) > 1 else weights[0],
                             "field_evals": evals})


def pack_samples(samples: RaySamples, keep: Tensor) -> PackedRaySamples:
    """Dense samples [R, S] and a mask [R, S] -> the kept samples, packed (ray-major, sorted by t)."""
    ray_indices, sample_indices = torch.nonzero(keep, as_tuple=True)
    return PackedRaySamples(rays=samples.rays, ray_indices=ray_indices,
                            t_starts=samples.t_starts[ray_indices, sample_indices],
                            t_ends=samples.t_ends[ray_indices, sample_indices])


@torch.no_grad()
def skip_empty(samples: RaySamples, occupied: OccupiedFn | None) -> RaySamples | PackedRaySamples:
    """The samples to evaluate: packed to the occupied ones when ``occupied`` skips at least
    ``PACK_MIN_SKIPPED_FRACTION`` of them, else the dense samples unchanged (packing would cost more
    than it saves)."""
    if occupied is None:
        return samples
    keep = occupied(samples.positions)
    if float(keep.float().mean()) > 1.0 - PACK_MIN_SKIPPED_FRACTION:
        return samples
    return pack_samples(samples, keep)


#: ``colour_where(density_loc [P], density_scale [P][, density_offsets [P, M]]) -> [P] bool``: which
#: of a field evaluation's points need their colour decoded (``StochasticField.forward_colour_where``;
#: a field with density heads passes their offsets as a third argument).
ColourWhereFn = Callable[..., Tensor]


def render_noise(samples: RaySamples | PackedRaySamples, num_draws: int, settings: RenderSettings, *,
                 colour: bool, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor | None]:
    """All K draws' eps of a render of ``samples`` at once, as ``render_any_samples(noise=...)`` takes them:
    dense (eps_a [R, K, S'], eps_c [R, K, S', 3]; S' = 1 with ``settings.shared_noise``), packed
    (eps_a [K, N], eps_c [K, N, 3]; shared noise drawn dense per ray and gathered per sample). The
    colour eps only with ``colour`` (drawn colours); else None (Rao-Blackwellised colours draw none)."""
    dev, dt = samples.t_starts.device, samples.t_starts.dtype
    if not isinstance(samples, PackedRaySamples):
        R, S = samples.t_starts.shape
        return dense_noise(R, num_draws, S, shared_noise=settings.shared_noise, generator=generator, device=dev,
                           dtype=dt, colour=colour)
    if settings.shared_noise:  # one eps per ray and draw, as the dense layout draws it
        return gather_shared_noise(dense_noise(samples.num_rays, num_draws, 1, shared_noise=True, generator=generator,
                                               device=dev, dtype=dt, colour=colour), samples.ray_indices)
    N = samples.ray_indices.shape[0]
    eps_a = torch.randn(num_draws, N, generator=generator, device=dev, dtype=dt)
    return eps_a, torch.randn(num_draws, N, 3, generator=generator, device=dev, dtype=dt) if colour else None


@torch.no_grad()
def colour_reaching(density_loc: Tensor, density_scale: Tensor, samples: RaySamples | PackedRaySamples,
                    eps_a: Tensor | None, min_transmittance: float, density_offsets: Tensor | None = None) -> Tensor:
    """Which samples' colours reach a pixel: some trajectory has density there and reaches it with
    transmittance at least ``min_transmittance`` (alpha compositing). [R, S] dense (density
    params [R, S], eps_a [R, K, S'] or None for the mean field), [N] packed (params [N], eps_a
    [K, N] or None).

        a_ik = relu(mu_a,i + s_a,i eps_ik),  T_ik = exp(-sum_{j<i} a_jk delta_j)
        kept: some k with a_ik > 0 and T_ik >= tau

    A sample without density in a trajectory has weight exactly 0 there, and its density's
    gradient through the ReLU is 0: its colour changes neither the colour nor a gradient. T falls
    along a ray, so the samples a trajectory leaves out for T < tau follow its first such sample
    i0, and their weights sum to at most T_i0k < tau: a colour composited without them (any values
    in [0, 1] in their place) is within tau of the full sum, per trajectory and channel, and the
    gradients change by as little (d C_k / d a_ik carries the factor T_ik). With density heads
    (``density_offsets`` [R, S, M] or [N, M]) draw k draws around its head's loc (``draw_locs``)."""
    if isinstance(samples, PackedRaySamples):
        eps = torch.zeros_like(density_loc)[None] if eps_a is None else eps_a  # [K, N]
        density = drawn_density(density_loc, density_scale, None if eps_a is None else density_offsets, eps, packed=True)
        tau = density * samples.deltas[None]
        transmittance = torch.exp(-exclusive_cumsum_packed(tau, samples.ray_indices, samples.num_rays))
        return ((density > 0) & (transmittance >= min_transmittance)).any(dim=0)
    return _reaching_dense(density_loc, density_scale, samples, eps_a, min_transmittance, density_offsets)[0]


@torch.no_grad()
def _reaching_dense(density_loc: Tensor, density_scale: Tensor, samples: RaySamples, eps_a: Tensor | None,
                    min_transmittance: float, density_offsets: Tensor | None = None
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """``colour_reaching`` on dense samples, with what it drew: (reached [R, S], the draws' densities
    [R, K, S] and transmittances T [R, K, S]), which a render without autograd reuses (``ColourPlan.drawn``)."""
    if eps_a is not None and draw_kernels.available(density_loc, density_scale, eps_a, samples.deltas):
        return draw_kernels.draw_reach(head_centres(density_loc, density_offsets, packed=False), density_scale, eps_a,
                                       samples.deltas, min_transmittance)
    eps = torch.zeros_like(density_loc)[:, None] if eps_a is None else eps_a  # [R, K, S']
    density = drawn_density(density_loc, density_scale, None if eps_a is None else density_offsets, eps, packed=False)
    transmittance = transmittance_alpha(density, samples.deltas[:, None, :])
    return ((density > 0) & (transmittance >= min_transmittance)).any(dim=1), density, transmittance


@dataclass
class ColourPlan:
    """The draws of a render fixed before its field evaluation, so the field decodes colours only
    at the samples some trajectory reaches (``settings.colour_min_transmittance``). ``noise``:
    what to pass to ``render_any_samples`` (None: deterministic); ``where``: the field's
    ``colour_where`` over the samples' flat points."""

    noise: tuple[Tensor, Tensor | None] | None
    where: ColourWhereFn
    #: What ``where`` drew on dense samples without autograd: the draws' (densities, transmittances)
    #: [R, K, S] (``render_samples(drawn=...)`` composites from them instead of drawing them again).
    drawn: tuple[Tensor, Tensor] | None = None
    #: Which samples ``where`` kept, [R, S] bool, on dense samples without autograd (``reached_colour_moments``).
    reached: Tensor | None = None


def colour_plan(samples: RaySamples | PackedRaySamples, settings: RenderSettings, num_draws: int, *,
                deterministic: bool = False, colour_estimator: str | None = None,
                generator: torch.Generator | None = None) -> ColourPlan | None:
    """A ``ColourPlan`` for a render of ``samples`` with these draws, or None when every colour is
    decoded (``colour_min_transmittance`` 0; the trapezoid quadrature, whose weights are not
    bounded by a transmittance; more than ``COLOUR_PLAN_MAX_PAIRS`` (sample, draw) pairs, whose
    noise drawn at once would outgrow the draw blocks). The draws are ``render_noise``'s, all K at once."""
    tau = settings.colour_min_transmittance
    if tau <= 0.0 or settings.quadrature != "alpha" or num_draws * samples.t_starts.numel() > COLOUR_PLAN_MAX_PAIRS:
        return None
    noise = None if deterministic else render_noise(
        samples, num_draws, settings, colour=not _use_rao_blackwell(settings, colour_estimator, deterministic),
        generator=generator)
    shape = samples.t_starts.shape

    def where(density_loc: Tensor, density_scale: Tensor, density_offsets: Tensor | None = None) -> Tensor:
        offsets = None if density_offsets is None else density_offsets.reshape(*shape, density_offsets.shape[-1])
        eps_a = None if noise is None else noise[0]
        if isinstance(samples, PackedRaySamples):
            return colour_reaching(density_loc, density_scale, samples, eps_a, tau, offsets)
        reach, *drawn = _reaching_dense(density_loc.reshape(shape), density_scale.reshape(shape), samples, eps_a, tau,
                                        offsets)
        if eps_a is not None and not torch.is_grad_enabled():  # a render: it composites these draws
            plan.drawn, plan.reached = tuple(drawn), reach
        return reach.reshape(-1)

    plan = ColourPlan(noise=noise, where=where)
    return plan


def render_any_samples(params: FieldParams, samples: RaySamples | PackedRaySamples, settings: RenderSettings, *,
                       num_draws: int, deterministic: bool = False, generator: torch.Generator | None = None,
                       noise: tuple[Tensor, Tensor] | None = None, colour_estimator: str | None = None,
                       colour_moments: tuple[Tensor, Tensor] | None = None,
                       observation_noise: bool | None = None,
                       drawn: tuple[Tensor, Tensor] | None = None) -> RayRender:
    """``render_samples`` or ``render_samples_packed``, whichever layout ``samples`` has (``drawn``: a
    plan's draws, which the dense layout reuses)."""
    kwargs = dict(num_draws=num_draws, deterministic=deterministic, generator=generator, noise=noise,
                  colour_estimator=colour_estimator, colour_moments=colour_moments, observation_noise=observation_noise)
    if isinstance(samples, PackedRaySamples):
        return render_samples_packed(params, samples, settings, **kwargs)
    return render_samples(params, samples, settings, drawn=drawn, **kwargs)


def render_rays(field: StochasticField, rays: RayBundle, settings: RenderSettings, *, num_draws: int | None = None,
                stratified: bool = False, deterministic: bool = False,
                generator: torch.Generator | None = None, occupied: OccupiedFn | None = None) -> RayRender:
    """Render rays [R] with K trajectories each (K = ``num_draws``, or ``settings.num_draws`` when
    None); with ``occupied`` only at samples it keeps (packed)."""
    K = settings.num_draws if num_draws is None else num_draws
    samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing,
                                stratified=stratified, generator=generator)
    samples = skip_empty(samples, occupied)
    plan = colour_plan(samples, settings, K, deterministic=deterministic, generator=generator)
    if plan is None:
        params = field(samples.positions, samples.directions)
    else:
        params = field.forward_colour_where(samples.positions, samples.directions, plan.where)
    moments = None
    if plan is not None and plan.reached is not None and _use_rao_blackwell(settings, None, deterministic):
        moments = reached_colour_moments(params, plan.reached)
    return render_any_samples(params, samples, settings, num_draws=K, deterministic=deterministic, generator=generator,
                              noise=None if plan is None else plan.noise, drawn=None if plan is None else plan.drawn,
                              colour_moments=moments)


MAP_NAMES = ("colour_mean", "colour_var", "depth_mean", "depth_var_epistemic", "depth_var_spread",
             "depth_var_total", "opacity")


# ----------------------------------------------------------------------------- per-call options
#: The RenderSettings fields a single render may choose (RenderOptions); the others (samples,
#: spacing, noise layout, background, the occupancy grid) are fixed when the model is trained.
PER_RENDER_FIELDS: tuple[str, ...] = ("num_draws", "quadrature", "chunk_rays", "colour_estimator", "adaptive_draws",
                                      "adaptive_batch_draws", "adaptive_max_draws", "adaptive_rtol", "adaptive_rule")


@dataclass(frozen=True)
class RenderOptions:
    """Choices of one render call, validated on construction (the ranges of ``RENDER_CHECKS``).

    Every caller (CLI, evaluation, export, notebook, benchmarks) passes one to
    ``RadianceModel.render_view``; nothing changes the model's own ``render_settings``.
    ``num_draws`` is the fixed K when ``adaptive_draws`` is False; with ``adaptive_draws`` K is
    chosen per chunk (``stochastic_fields.adaptive``) and ``num_draws`` is not used. Either way the
    rendered maps hold ``num_draws`` [H, W], the K each pixel actually got. Build them with
    ``model.render_options(**changes)`` (the model's defaults plus the changes) or
    :meth:`from_settings`.
    """

    num_draws: int = 8
    quadrature: Literal["alpha", "trapezoid"] = "alpha"
    chunk_rays: int = 2048
    colour_estimator: Literal["draws", "rao_blackwell"] = "rao_blackwell"
    adaptive_draws: bool = False
    adaptive_batch_draws: int = 8
    adaptive_max_draws: int = 128
    adaptive_rtol: float = 0.05
    adaptive_rule: Literal["precision", "change"] = "precision"
    keep_draws: bool = False
    """Also return the per-draw maps ``depth_draws`` [H, W, K] and ``colour_draws`` [H, W, K, 3]."""
    progress: bool = False
    """A progress bar over the chunks."""

    def __post_init__(self) -> None:
        check_fields(self, RENDER_OPTION_CHECKS)

    @classmethod
    def from_settings(cls, settings: RenderSettings, **changes) -> "RenderOptions":
        """``settings``' per-render fields, then :meth:`with_changes`."""
        return cls(**{name: getattr(settings, name) for name in PER_RENDER_FIELDS}).with_changes(**changes)

    def with_changes(self, **changes) -> "RenderOptions":
        """A copy with ``changes`` (validated; None values leave a field as it is). An explicit
        ``num_draws`` asks for that fixed K: it turns adaptive K off unless ``adaptive_draws`` is
        also given."""
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(changes) - set(names))
        if unknown:
            raise ValueError(f"unknown render option(s) {unknown}; choose from {names}")
        changes = {k: v for k, v in changes.items() if v is not None}
        if "num_draws" in changes and "adaptive_draws" not in changes:
            changes["adaptive_draws"] = False
        return dataclasses.replace(self, **changes)

    def settings_for(self, settings: RenderSettings) -> RenderSettings:
        """A copy of ``settings`` with this call's choices (``settings`` itself is not changed)."""
        return dataclasses.replace(settings, **{name: getattr(self, name) for name in PER_RENDER_FIELDS})


#: Declared range of every RenderOptions field.
RENDER_OPTION_CHECKS: dict[str, Checker] = {**{name: RENDER_CHECKS[name] for name in PER_RENDER_FIELDS},
                                            "keep_draws": boolean(), "progress": boolean()}


# ----------------------------------------------------------------------------- images in chunks
@dataclass
class ChunkRender:
    """What a per-chunk renderer returns to :func:`render_chunked` for rays [R]."""

    stats: TrajectoryStatistics
    num_draws: int
    """K of this chunk's statistics."""
    field_evals: Tensor | None = None
    """[R] field evaluations per ray, or None."""


#: A generator for the whole image, or one per chunk: ``chunk index -> generator``.
ChunkGenerators = Callable[[int], "torch.Generator | None"]


def chunk_seed(seed: int, view: int, chunk: int) -> int:
    """A 63-bit seed mixed from (seed, view, chunk) (numpy SeedSequence hashing)."""
    return int(np.random.SeedSequence((seed, view, chunk)).generate_state(1, dtype=np.uint64)[0] >> 1)


def seeded_chunks(seed: int, view: int, device: torch.device | str = "cpu") -> ChunkGenerators:
    """One generator per chunk of ``view``, seeded from (seed, view, chunk): a view's noise does not
    depend on which other views are rendered, in which order or on which process, and any chunk
    can be rendered again alone (the notebook's pixel probe). Every caller that renders dataset
    views (evaluation, export, notebook) seeds them this way."""
    return lambda chunk: torch.Generator(device=device).manual_seed(chunk_seed(seed, view, chunk))


@torch.no_grad()
def render_chunked(render_chunk: Callable[[RayBundle, "torch.Generator | None"], ChunkRender], rays: RayBundle,
                   chunk_rays: int, *, generator: "torch.Generator | ChunkGenerators | None" = None,
                   keep_draws: bool = False, progress: bool = False, desc: str = "render") -> dict[str, Tensor]:
    """The one loop that renders an image in chunks, for every model and every caller.

    ``render_chunk(rays [R], generator) -> ChunkRender`` renders ``chunk_rays`` rays at a time of
    ``rays`` [H, W]; ``generator`` is one generator for all chunks or a function of the chunk
    index (the notebook seeds each chunk on its own so that any chunk can be rendered again).

    Returns maps [H, W] / [H, W, 3] (``MAP_NAMES``, ray-distance units), ``z_scale`` [H, W],
    ``num_draws`` [H, W] (the K each pixel got), ``field_evals_per_ray`` [H, W] when the chunks
    report it, and with ``keep_draws`` ``depth_draws`` [H, W, K] and ``colour_draws``
    [H, W, K, 3], padded with NaN beyond a chunk's K to the largest K.
    """
    shape = rays.shape
    flat = rays.flatten()
    out: dict[str, list[Tensor]] = {name: [] for name in (*MAP_NAMES, "num_draws", "field_evals_per_ray")}
    draws: dict[str, list[Tensor]] = {"depth_draws": [], "colour_draws": []}
    starts = range(0, len(flat), chunk_rays)
    for index, start in enumerate(tqdm(starts, desc=desc, disable=not progress, leave=False)):
        gen = generator(index) if callable(generator) else generator
        chunk = render_chunk(flat[start:start + chunk_rays], gen)
        stats = chunk.stats
        for name in MAP_NAMES:
            out[name].append(getattr(stats, name))
        out["num_draws"].append(torch.full_like(stats.opacity, float(chunk.num_draws)))
        if chunk.field_evals is not None:
            out["field_evals_per_ray"].append(chunk.field_evals.to(stats.opacity.dtype))
        if keep_draws:
            draws["depth_draws"].append(stats.depth_draws)
            draws["colour_draws"].append(stats.colour_draws)
    if len(out["field_evals_per_ray"]) != len(out["opacity"]):
        del out["field_evals_per_ray"]
    maps = {}
    for name, parts in out.items():
        flat_map = torch.cat(parts)
        maps[name] = flat_map.reshape(*shape, *flat_map.shape[1:])
    if keep_draws:
        k_max = max(d.shape[1] for d in draws["depth_draws"])
        for name, parts in draws.items():
            padded = [torch.nn.functional.pad(d, (0, 0) * (d.dim() - 2) + (0, k_max - d.shape[1]), value=float("nan"))
                      for d in parts]
            flat_map = torch.cat(padded)
            maps[name] = flat_map.reshape(*shape, *flat_map.shape[1:])
    maps["z_scale"] = rays.z_scale
    return maps


@torch.no_grad()
def render_image(field: StochasticField, rays: RayBundle, settings: RenderSettings, *, num_draws: int | None = None,
                 deterministic: bool = False, generator: "torch.Generator | ChunkGenerators | None" = None,
                 keep_draws: bool = False, progress: bool = False, occupied: OccupiedFn | None = None
                 ) -> dict[str, Tensor]:
    """Render rays [H, W] with a fixed K (``num_draws``, or ``settings.num_draws`` when None) in
    chunks of ``settings.chunk_rays`` (:func:`render_chunked`; its maps, with
    ``field_evals_per_ray``). ``occupied``: empty-space skipping (see ``render_rays``)."""
    K = settings.num_draws if num_draws is None else num_draws

    def chunk(r: RayBundle, gen: torch.Generator | None) -> ChunkRender:
        out = render_rays(field, r, settings, num_draws=K, deterministic=deterministic, generator=gen,
                          occupied=occupied)
        return ChunkRender(out.stats, K, out.extras["field_evals"])

    return render_chunked(chunk, rays, settings.chunk_rays, generator=generator, keep_draws=keep_draws,
                          progress=progress)
