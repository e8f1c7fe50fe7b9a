"""The variational objective (docs/definitions.md §4, paper Eq. var_snerf):

    L = -1/(R K) sum_{r,k} log N(c_r | C_rk, sigma_n^2 I)                  (MC likelihood)
        [with a noise head: variance sigma_n^2 + sum_i w_rki beta_i^2 per draw, §4.7]
        + lambda_rand * mean_{x ~ region, d ~ sphere} KL(q(.|x,d) || p_rand)
        + lambda_obs  * mean_{x on training rays}     KL(q(.|x,d) || p_obs)
        [+ lambda_dist * mean_{r,k} distortion(w_rk)]                      (optional, off by default)
        [+ lambda_depth * termination_depth_nll(w, t*)]                    (capture points, FIT role)

with KL = KL_density (rectified normal) + sum_c KL_colour_c (logistic normal).
p_rand: learned means, std fixed at RANDOM_POINT_PRIOR_STD (10). p_obs: learned means and stds.
Ablations (paper Table 3): ``kl="none"`` (likelihood only), ``kl="fixed_prior"`` (random-point
KL only), ``kl="full"`` (both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from .constants import DEPTH_MIXTURE_WEIGHT_FLOOR, RANDOM_POINT_PRIOR_STD
from .distributions import (kl_logistic_normal, kl_logistic_normal_mc, kl_rectified_normal,
                            kl_rectified_normal_mc)
from .fields.base import FieldParams, inverse_positive_scale, positive_scale
from .settings import LOSS_CHECKS, LossConfig  # noqa: F401  (the loss settings, re-exported)



class Priors(nn.Module):
    """Learned prior parameters (scalars shared by every point of the scene)."""

    def __init__(self):
        super().__init__()
        self.random_density_loc = nn.Parameter(torch.tensor(0.0))
        self.random_rgb_loc = nn.Parameter(torch.zeros(3))
        self.observed_density_loc = nn.Parameter(torch.tensor(0.0))
        self.observed_rgb_loc = nn.Parameter(torch.zeros(3))
        self.observed_density_raw_scale = nn.Parameter(torch.tensor(inverse_positive_scale(1.0)))
        self.observed_rgb_raw_scale = nn.Parameter(torch.full((3,), inverse_positive_scale(1.0)))

    def random(self, density_unit: float | Tensor = 1.0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(density loc, density std, colour-logit locs, stds) of p_rand. ``density_unit``: the
        field's k (``StochasticField.density_unit_factor``): the density prior is k times the
        learned one, so KL(q || p) is that of the field's own density parameters (the KL of two
        rectified normals is unchanged when both scale by k)."""
        std = torch.tensor(RANDOM_POINT_PRIOR_STD, device=self.random_rgb_loc.device)
        return self.random_density_loc * density_unit, std * density_unit, self.random_rgb_loc, std.expand(3)

    def observed(self, density_unit: float | Tensor = 1.0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """p_obs, as ``random``."""
        return (self.observed_density_loc * density_unit, positive_scale(self.observed_density_raw_scale) * density_unit,
                self.observed_rgb_loc, positive_scale(self.observed_rgb_raw_scale))


def gaussian_likelihood_nll(colours: Tensor, target: Tensor, std: float | Tensor,
                            extra_variance: Tensor | None = None, colour_variance: Tensor | None = None,
                            ray_weights: Tensor | None = None) -> Tensor:
    """Mean over rays and draws of -log N(target | C_k, diag(v_k)), per pixel (3 channels summed),

        v_kc = std_c^2 + extra_variance_kc

    (``extra_variance``: a draw's observation noise from a field's noise head, §4.7; None = 0).
    With ``colour_variance`` W_k, ``colours`` are the draws' conditional means m_k = E[C_k | w_k]
    and the term is its expectation over the colours (Rao-Blackwellised):

        E[-log N(target | C_k, v_k) | w_k] = ((m_k - target)^2 + W_k) / (2 v_k) + log(2 pi v_k) / 2

    ``ray_weights`` [R] (None: all 1) weight each ray's term in the mean over rays (the error-guided
    sampler's likelihood weights, stochastic_fields.ray_sampling); [R, K] weight each ray's draws
    (the heads' bootstrap, ``draw_weights``).

    Shapes: colours [R, K, 3], target [R, 3], std a float or [3], extra_variance and
    colour_variance None or [R, K, 3] -> scalar.
    """
    std = torch.as_tensor(std, dtype=colours.dtype, device=colours.device).expand(3)
    sq = _expected_square_error(colours, target, colour_variance)  # [R, K, 3]
    if extra_variance is None:
        per_channel = 0.5 * sq / std ** 2 + torch.log(std) + 0.5 * math.log(2 * math.pi)
    else:
        var = std ** 2 + extra_variance
        per_channel = 0.5 * sq / var + 0.5 * torch.log(var) + 0.5 * math.log(2 * math.pi)
    return _ray_mean(per_channel.sum(-1), ray_weights)


def _ray_mean(per_draw: Tensor, ray_weights: Tensor | None) -> Tensor:
    """[R, K] -> scalar: the mean over draws and rays, each ray weighted by ``ray_weights`` [R], or
    each ray's draw by ``ray_weights`` [R, K] (None: 1)."""
    if ray_weights is None:
        return per_draw.mean()
    if ray_weights.dim() == 2:
        return (per_draw * ray_weights).mean()
    return (per_draw.mean(-1) * ray_weights).mean()


def bootstrap_head_weights(num_pixels: int, heads: int, keep: float, generator: torch.Generator) -> Tensor:
    """[N, M] each training pixel's weight in each density head's likelihood (``loss.head_bootstrap_keep``).

    Head h keeps pixel n with probability ``keep`` (independently); a pixel no head keeps is given
    to one head drawn uniformly. Then w_nh = M 1[h keeps n] / (number of heads keeping n): every
    pixel's weights sum to M (its weight in the loss is that of today's, where each is 1) and, by
    symmetry, each head's expected weight is 1. ``keep`` = 1: all ones."""
    kept = torch.rand(num_pixels, heads, generator=generator) < keep
    orphans = (~kept.any(1)).nonzero().squeeze(1)
    if len(orphans):
        kept[orphans, torch.randint(0, heads, (len(orphans),), generator=generator)] = True
    kept = kept.to(torch.float32)
    return heads * kept / kept.sum(1, keepdim=True)


def draw_weights(head_weights: Tensor, num_draws: int) -> Tensor:
    """[R, M] each ray's head weights -> [R, K] each draw's: draw k draws around head k mod M
    (``renderer.draw_locs``, training draws counted from 0)."""
    heads = torch.arange(num_draws, device=head_weights.device) % head_weights.shape[-1]
    return head_weights[:, heads]


def _expected_square_error(colours: Tensor, target: Tensor, colour_variance: Tensor | None) -> Tensor:
    """[R, K, 3] (C_k - c)^2, or (m_k - c)^2 + W_k: its expectation given the draw's weights."""
    sq = (colours - target[:, None, :]) ** 2
    return sq if colour_variance is None else sq + colour_variance


def decoupled_likelihood_nll(colours: Tensor, target: Tensor, std: Tensor, extra_variance: Tensor,
                             colour_variance: Tensor | None = None, ray_weights: Tensor | None = None) -> Tensor:
    """``gaussian_likelihood_nll`` with ``extra_variance`` whose terms are weighted by the
    detached ratio ``v_kc / std_c^2`` (v = std^2 + extra): the same value scaled per term, and
    gradients

        d/dC_k = (C_k - c) / std^2          (the global-noise likelihood's: the fit is not starved)
        d/d extra, d/d std: stationary where v = (C_k - c)^2, as the plain likelihood

    Pass ``extra_variance`` built from detached weights to keep the geometry's gradient that of
    the global-noise likelihood too (``loss.noise_head_decoupled``). ``colour_variance``: the
    Rao-Blackwellised form, as in ``gaussian_likelihood_nll`` (the weight depends on the draw's
    density only, so the expectation over colours passes through it); ``ray_weights`` as there.

    Shapes: colours [R, K, 3], target [R, 3], std [3], extra_variance and colour_variance [R, K, 3]
    (colour_variance optional) -> scalar.
    """
    std = torch.as_tensor(std, dtype=colours.dtype, device=colours.device).expand(3)
    var = std ** 2 + extra_variance
    sq = _expected_square_error(colours, target, colour_variance)
    per_channel = 0.5 * sq / var + 0.5 * torch.log(var) + 0.5 * math.log(2 * math.pi)
    return _ray_mean(((var / std ** 2).detach() * per_channel).sum(-1), ray_weights)


#: ``loss.depth_likelihood`` values: how ``termination_depth_nll`` combines a ray's trajectories.
DEPTH_LIKELIHOOD_FORMS: tuple[str, ...] = ("expected", "predictive")


def depth_weight(lambda_depth: float, final_factor: float, progress: float) -> float:
    """The sparse-depth likelihood's weight at a point of the schedule: lambda_depth * (1 - (1 - f) p)
    with f = ``loss.depth_final_factor`` and p = ``progress`` in [0, 1] (clamped): lambda_depth at the
    start, lambda_depth * f at the end, linear between."""
    p = min(max(float(progress), 0.0), 1.0)
    return lambda_depth * (1.0 - (1.0 - final_factor) * p)


def termination_depth_nll(weights: Tensor, t_mids: Tensor, deltas: Tensor, target_t: Tensor,
                          relative_std: float, form: str = "expected", outlier_share: float = 0.0) -> Tensor:
    """Negative log-likelihood of an observed surface at ray distance t* under the termination
    distributions of the K trajectories, with p_rk = sum_i w_rki N(t*_r | t_ri, s_ri^2),
    s_ri^2 = delta_ri^2 / 12 + (rho t*_r)^2 (each sample's weight spread over its bin, widened by the
    point's own depth noise rho t*):

        form 'expected':    -1/(R K) sum_{r,k} log p_rk          (the ELBO's expected log-likelihood)
        form 'predictive':  -1/R sum_r log (1/K sum_k p_rk)      (the predictive mixture's)

    By Jensen's inequality 'predictive' <= 'expected', equal for K = 1 or when every trajectory
    gives the point the same density. The mixture's mass is the ray's opacity, so a ray that misses
    the surface is penalised too. Weights below ``DEPTH_MIXTURE_WEIGHT_FLOOR`` count as that floor
    inside the log.

    ``outlier_share`` eps in [0, 1): a point may be an outlier of the structure from motion, placed
    anywhere on the ray's sampled range with equal density: p_rk is replaced by
    (1 - eps) p_rk + eps / L_r, L_r = sum_i delta_ri, so a point far from every trajectory's mass
    costs at most -log(eps / L_r) and pulls on the density with a weight that falls with its
    distance (a robust, heavy-tailed likelihood). eps = 0 is the formula above exactly.

    Shapes: weights [R, K, S], t_mids [R, S], deltas [R, S], target_t [R] -> scalar.
    """
    if form not in DEPTH_LIKELIHOOD_FORMS:
        raise ValueError(f"depth likelihood form must be one of {DEPTH_LIKELIHOOD_FORMS}, got {form!r}")
    if not 0.0 <= outlier_share < 1.0:
        raise ValueError(f"depth likelihood outlier share must be in [0, 1), got {outlier_share!r}")
    var = deltas ** 2 / 12.0 + (relative_std * target_t[:, None]) ** 2  # [R, S]
    log_normal = -0.5 * (target_t[:, None] - t_mids) ** 2 / var - 0.5 * torch.log(2 * math.pi * var)
    # log sum_i w_i N_i = m + log sum_i w_i exp(log N_i - m), m = max_i log N_i per ray: the
    # exponentials are taken once per ray [R, S] instead of per draw, and the sum is a matrix
    # product. Nothing overflows (every ratio <= 1) and the sum is >= the floor at the peak.
    peak = log_normal.amax(dim=-1, keepdim=True)  # [R, 1]
    ratio = torch.exp(log_normal - peak)  # [R, S]
    mixture = torch.matmul(weights.clamp_min(DEPTH_MIXTURE_WEIGHT_FLOOR), ratio[:, :, None])[..., 0]  # [R, K]
    if form == "predictive":  # log mean_k p_rk = peak + log mean_k mixture_rk (mixture_rk >= the floor)
        log_p = torch.log(mixture.mean(dim=-1)) + peak[:, 0]  # [R]
    else:
        log_p = torch.log(mixture) + peak  # [R, K]
    if outlier_share > 0.0:  # log((1 - eps) p + eps / L), one logaddexp: nothing overflows
        log_uniform = math.log(outlier_share) - torch.log(deltas.sum(dim=-1))  # [R]
        if form != "predictive":
            log_uniform = log_uniform[:, None]
        log_p = torch.logaddexp(log_p + math.log1p(-outlier_share), log_uniform)
    return -log_p.mean()


def field_kl(params: FieldParams, prior: tuple[Tensor, Tensor, Tensor, Tensor], *,
             estimator: str = "closed_form", mc_samples: int = 8,
             generator: torch.Generator | None = None) -> Tensor:
    """[*B] KL(q || p) per point: rectified-normal density KL + sum of the 3 colour-logit KLs.

    With density heads (``params.density_offsets`` [*B, M]) q's density is the equal mixture of
    the heads' rectified normals; its KL is bounded by the mean of theirs (KL is convex in q),
    which is the term: sum_h KL(q_h || p) / M >= KL(sum_h q_h / M || p), so the loss stays a bound."""
    d_loc, d_scale, c_loc, c_scale = prior
    loc, scale = params.density_loc, params.density_scale
    if params.density_offsets is not None:  # [*B, M]: each head's, the prior broadcast over them
        loc, scale = loc[..., None] + params.density_offsets, scale[..., None].expand_as(params.density_offsets)
        d_loc, d_scale = (torch.as_tensor(t, device=loc.device).unsqueeze(-1) for t in (d_loc, d_scale))
    if estimator == "closed_form":
        kd = kl_rectified_normal(loc, scale, d_loc, d_scale)
        kc = kl_logistic_normal(params.rgb_loc, params.rgb_scale, c_loc, c_scale).sum(-1)
    elif estimator == "monte_carlo":
        kd = kl_rectified_normal_mc(loc, scale, d_loc, d_scale,
                                    num_samples=mc_samples, generator=generator)
        kc = kl_logistic_normal_mc(params.rgb_loc, params.rgb_scale, c_loc, c_scale,
                                   num_samples=mc_samples, generator=generator).sum(-1)
    else:
        raise ValueError(f"kl_estimator must be 'closed_form' or 'monte_carlo', got {estimator!r}")
    if params.density_offsets is not None:
        kd = kd.mean(-1)
    return kd + kc


def field_kl_means(parts: list[tuple[FieldParams, tuple[Tensor, Tensor, Tensor, Tensor]]], *,
                   estimator: str = "closed_form", mc_samples: int = 8,
                   generator: torch.Generator | None = None) -> list[Tensor]:
    """``[field_kl(params_j, prior_j).mean() for each part]``, evaluated as one batch: the parts'
    points (params [N_j], rgb [N_j, 3]) concatenated, each prior broadcast to its own points.
    The KLs are about a hundred tensor operations on a few thousand points, dominated by their
    fixed cost per operation: one pass (and one backward) for the random-point and observed-sample
    KLs instead of two. The same value per point (Monte-Carlo KLs draw their noise for all points
    at once)."""
    if len(parts) <= 1:
        return [field_kl(p, prior, estimator=estimator, mc_samples=mc_samples, generator=generator).mean()
                for p, prior in parts]
    sizes = [p.density_loc.shape[0] for p, _ in parts]
    names = ("density_loc", "density_scale", "rgb_loc", "rgb_scale")
    heads = all(p.density_offsets is not None for p, _ in parts)
    joined = FieldParams(*(torch.cat([getattr(p, name) for p, _ in parts]) for name in names),
                         density_offsets=torch.cat([p.density_offsets for p, _ in parts]) if heads else None)
    prior = tuple(torch.cat([torch.as_tensor(pr[i], device=joined.density_loc.device).expand(n, *getattr(p, name).shape[1:])
                             for (p, pr), n in zip(parts, sizes)])
                  for i, name in enumerate(names))
    per_point = field_kl(joined, prior, estimator=estimator, mc_samples=mc_samples, generator=generator)
    return [part.mean() for part in per_point.split(sizes)]
