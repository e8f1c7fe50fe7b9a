"""Free-space probabilities for planners: P(depth > d) from the K depth trajectories.

For a pixel whose K draws have termination depths D_1..D_K (camera-z, scene units),

    P(depth > d) ~= (1 / K) * #{k : D_k > d}

the fraction of trajectories that end beyond d: the Monte-Carlo estimate, under the model's
distribution over scenes, of the probability that the segment of the pixel's ray up to camera
depth d is free. It takes the values {0, 1/K, ..., 1}, is non-increasing in d, and uses a
strict inequality (a draw ending exactly at d does not count as free beyond d). It describes
the epistemic part of the uncertainty (where each trajectory's expected surface is), not the
termination spread inside a trajectory.

Rays that hit nothing report D_k = far (volume_rendering.expected_depth), so their probability
is 1 up to the far bound and 0 beyond it: nothing is known past ``far``. A distance along the
ray ``t`` (not camera z) converts with ``d = t * z_scale`` (see cameras.py).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import Tensor


def prob_depth_greater(depth_draws: Tensor | np.ndarray, d: Tensor | np.ndarray | float) -> Tensor:
    """P(depth > d) as the fraction of draws beyond ``d``.

    Shapes: depth_draws [..., K]; d broadcastable to [...] -> [...] (float, in depth_draws' dtype).
    Example: draws [1, 2, 3, 4], d = 2.5 -> 0.5; d = 2 -> 0.5 (strict); d = 0 -> 1.
    """
    draws = torch.as_tensor(depth_draws)
    if draws.ndim < 1 or draws.shape[-1] < 1:
        raise ValueError(f"prob_depth_greater: depth_draws must be [..., K] with K >= 1, got {tuple(draws.shape)}")
    if not draws.is_floating_point():
        draws = draws.double()
    dist = torch.as_tensor(d, dtype=draws.dtype, device=draws.device)
    return (draws > dist[..., None]).to(draws.dtype).mean(dim=-1)


def pixel_free_space(depth_draws: Tensor | np.ndarray, row: int, col: int, d: float | Sequence[float]) -> Tensor:
    """P(depth > d) at one pixel (row, col) of a map of draws [H, W, K], for one distance or
    several (camera-z). Returns a scalar tensor or [D]."""
    draws = torch.as_tensor(depth_draws)
    if draws.ndim != 3:
        raise ValueError(f"pixel_free_space: depth_draws must be [H, W, K], got {tuple(draws.shape)}")
    H, W = draws.shape[:2]
    if not (0 <= row < H and 0 <= col < W):
        raise IndexError(f"pixel (row {row}, col {col}) outside the {H}x{W} image")
    return prob_depth_greater(draws[row, col], torch.as_tensor(d, dtype=torch.float64))


def free_space_volume(depth_draws: Tensor | np.ndarray, thresholds: Sequence[float]) -> Tensor:
    """P(depth > d_t) for every pixel and every threshold: [H, W, K], [T] -> [T, H, W]."""
    draws = torch.as_tensor(depth_draws)
    th = torch.as_tensor(list(thresholds), dtype=draws.dtype if draws.is_floating_point() else torch.float64)
    if th.ndim != 1 or th.numel() == 0:
        raise ValueError(f"free_space_volume: need a non-empty list of thresholds, got {list(thresholds)}")
    return torch.stack([prob_depth_greater(draws, float(t)) for t in th])
