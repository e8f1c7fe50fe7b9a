"""Where along each ray the field is evaluated (dense layout).

Bins between near and far, spaced linearly in distance (bounded scenes) or linearly in
disparity 1/t (forward-facing scenes, where the far bound is large). During training the bin
edges are jittered inside their own bin (stratified sampling, the paper's appendix): each
interior edge e_i moves uniformly in [b_i - D/2, b_i + D/2], so edges stay ordered.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from .rays import RayBundle, RaySamples
from .settings import Spacing



def bin_edges(near: Tensor, far: Tensor, num_samples: int, spacing: Spacing = "linear") -> Tensor:
    """[R, S + 1] bin edges from near [R] to far [R]."""
    s = torch.linspace(0.0, 1.0, num_samples + 1, device=near.device, dtype=near.dtype)
    if spacing == "linear":
        return near[:, None] * (1.0 - s) + far[:, None] * s
    if spacing == "disparity":
        return 1.0 / ((1.0 / near[:, None]) * (1.0 - s) + (1.0 / far[:, None]) * s)
    raise ValueError(f"spacing must be 'linear' or 'disparity', got {spacing!r}")


def sample_along_rays(rays: RayBundle, num_samples: int, *, spacing: Spacing = "linear",
                      stratified: bool = False, generator: torch.Generator | None = None) -> RaySamples:
    """Dense samples: rays [R] -> RaySamples with t_starts/t_ends [R, S]."""
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    edges = bin_edges(rays.near, rays.far, num_samples, spacing)
    if stratified and num_samples > 1:
        width = edges[:, 1:] - edges[:, :-1]  # [R, S]
        half_lo = 0.5 * width[:, :-1]
        half_hi = 0.5 * width[:, 1:]
        u = torch.rand(edges[:, 1:-1].shape, generator=generator, device=edges.device, dtype=edges.dtype)
        interior = edges[:, 1:-1] - half_lo + u * (half_lo + half_hi)
        edges = torch.cat([edges[:, :1], interior, edges[:, -1:]], dim=1)
    return RaySamples(rays=rays, t_starts=edges[:, :-1], t_ends=edges[:, 1:])
