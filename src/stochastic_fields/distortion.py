"""Distortion regulariser of Mip-NeRF 360 (Barron et al. 2022, Eq. 15), per trajectory.

For one ray's weights w_i on intervals [s_i, s_{i+1}] of the normalised ray coordinate s in [0, 1]
(midpoints m_i, widths d_i = s_{i+1} - s_i):

    L = sum_{i,j} w_i w_j |m_i - m_j|  +  1/3 sum_i w_i^2 d_i

The first term is small when the weight sits in one compact interval, the second when that
interval is short; a fog of small weights spread along the ray (floaters) pays for every pair.
With the samples sorted, sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i W_i - M_i), where
W_i = sum_{j<i} w_j and M_i = sum_{j<i} w_j m_j (exclusive prefix sums): O(S) per ray.

S-NeRF applies it to each sampled trajectory k (weights w_ik), so it acts on the draws of the
density distribution, not only its mean. ``s`` is the coordinate the samples were spaced
uniformly in (distance for ``linear`` spacing, disparity for ``disparity``), as in Mip-NeRF 360.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .rays import PackedRaySamples, RaySamples
from .samplers import Spacing
from .volume_rendering import exclusive_cumsum_packed


def normalised_coordinate(t: Tensor, near: Tensor, far: Tensor, spacing: Spacing) -> Tensor:
    """Ray distance t [..., S] -> s in [0, 1] [..., S], linear in the sampling coordinate.

    near/far broadcast against t (e.g. [R, 1] for dense samples, [N] for packed ones)."""
    if spacing == "linear":
        return (t - near) / (far - near)
    if spacing == "disparity":
        return (1.0 / t - 1.0 / near) / (1.0 / far - 1.0 / near)
    raise ValueError(f"spacing must be 'linear' or 'disparity', got {spacing!r}")


def sample_bounds(samples: RaySamples | PackedRaySamples) -> tuple[Tensor, Tensor]:
    """Each sample's ray near/far, shaped to broadcast against its t: [R, 1] each for dense samples,
    [N] each for packed ones."""
    rays = samples.rays
    if isinstance(samples, PackedRaySamples):
        return rays.near[samples.ray_indices], rays.far[samples.ray_indices]
    return rays.near[:, None], rays.far[:, None]


def distortion_loss(weights: Tensor, s_starts: Tensor, s_ends: Tensor) -> Tensor:
    """Distortion per ray and trajectory: weights [..., S], s_starts/s_ends broadcastable -> [...]."""
    mids = 0.5 * (s_starts + s_ends)
    widths = s_ends - s_starts
    w_prefix = torch.cumsum(weights, dim=-1) - weights  # exclusive: W_i
    wm = weights * mids
    wm_prefix = torch.cumsum(wm, dim=-1) - wm  # exclusive: M_i
    pairs = 2.0 * (weights * (mids * w_prefix - wm_prefix)).sum(-1)
    own = (weights ** 2 * widths).sum(-1) / 3.0
    return pairs + own


def distortion_loss_packed(weights: Tensor, s_starts: Tensor, s_ends: Tensor, ray_indices: Tensor,
                           num_rays: int) -> Tensor:
    """Packed distortion: weights [K, N] on samples [N] sorted by ray then s -> [K, R] (0 for empty rays).

    Skipped samples carry no weight, so a ray's packed loss equals its dense loss."""
    mids = 0.5 * (s_starts + s_ends)
    widths = s_ends - s_starts
    w_prefix = exclusive_cumsum_packed(weights, ray_indices, num_rays)
    wm = weights * mids
    wm_prefix = exclusive_cumsum_packed(wm, ray_indices, num_rays)
    per_sample = 2.0 * weights * (mids * w_prefix - wm_prefix) + weights ** 2 * widths / 3.0  # [K, N]
    out = torch.zeros(weights.shape[0], num_rays, dtype=weights.dtype, device=weights.device)
    return out.index_add_(1, ray_indices, per_sample)
