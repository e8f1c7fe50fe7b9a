"""Free-space probabilities for planners: P(depth > d) per pixel.

The predictive probability (``predictive_prob_depth_greater``; what ``export`` writes) comes from
the same per-pixel distribution as the exported depth bands, ``depth_std`` and the scores of
``eval``: symmetric about the depth mean d, with central interval d +- z_p m(p) sigma at level p
(sigma the recalibrated ``depth_std``, m the run's level map, ``calibration.relative_scale``; m = 1
without one: a Gaussian). So P(depth > d + z_p m(p) sigma) = (1 - p) / 2 exactly, and the share of
true depths whose P(depth > y) lies in [(1 - p) / 2, (1 + p) / 2] is the band's scored coverage.

The draws' probability (``prob_depth_greater``): for a pixel whose K draws have termination depths D_1..D_K (camera-z, scene units),

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

from typing import Callable, Sequence

import numpy as np
import torch
from scipy.special import ndtr, ndtri
from torch import Tensor

#: Central levels at which a level map is inverted (``central_level``): every 0.001 up to 0.99, then
#: 1 - 10^-2 ... 1 - 10^-9 in even log steps; beyond the last, the map's last multiplier (Gaussian tail).
CENTRAL_LEVEL_GRID: np.ndarray = np.concatenate([np.linspace(0.0, 0.99, 991), 1.0 - np.geomspace(1e-2, 1e-9, 120)[1:]])


def central_level(a: np.ndarray, band_multiplier: Callable[[float], float] | None = None) -> np.ndarray:
    """The central level p whose interval half-width is ``a`` standard deviations: the p with
    z_p m(p) = a, z_p = Phi^-1((1 + p) / 2), for a [...] >= 0 -> [...] in [0, 1). Without a
    multiplier m = 1 and p = 2 Phi(a) - 1; with one, by interpolation on ``CENTRAL_LEVEL_GRID``
    (z_p m(p) is non-decreasing for a fitted map) and the Gaussian tail with the last multiplier
    beyond it."""
    a = np.asarray(a, dtype=np.float64)
    if band_multiplier is None:
        return 2.0 * ndtr(a) - 1.0
    m = np.array([float(band_multiplier(float(p))) for p in CENTRAL_LEVEL_GRID])
    if not (np.isfinite(m).all() and (m > 0).all()):
        raise ValueError("central_level: the band multiplier must be finite and > 0")
    half = np.maximum.accumulate(ndtri((1.0 + CENTRAL_LEVEL_GRID) / 2.0) * m)
    tail = 2.0 * ndtr(a / m[-1]) - 1.0
    return np.where(a <= half[-1], np.interp(a, half, CENTRAL_LEVEL_GRID), np.maximum(tail, CENTRAL_LEVEL_GRID[-1]))


def predictive_prob_depth_greater(mean: np.ndarray, std: np.ndarray, d: np.ndarray | float,
                                  band_multiplier: Callable[[float], float] | None = None) -> np.ndarray:
    """P(depth > d) under the per-pixel predictive distribution (module doc): mean, std [...] (std
    >= 0; 0: all mass at the mean), d broadcastable -> [...] float64,

        P = (1 - sign(u) p(|u|)) / 2,   u = (d - mean) / std,   p = ``central_level``.

    Example (no multiplier): mean 2, std 0.1, d = 2.1645 -> 0.05."""
    mean, std = np.asarray(mean, dtype=np.float64), np.asarray(std, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    if (std < 0).any() or not np.isfinite(std).all():
        raise ValueError("predictive_prob_depth_greater: stds must be finite and >= 0")
    diff = d - mean
    point_mass = np.where(diff > 0, np.inf, np.where(diff < 0, -np.inf, 0.0))  # std 0: all mass at the mean
    u = np.where(std > 0, diff / np.where(std > 0, std, 1.0), point_mass)
    p = central_level(np.where(np.isfinite(u), np.abs(u), 0.0), band_multiplier)
    p = np.where(np.isinf(u), 1.0, np.where(u == 0, 0.0, p))
    return 0.5 * (1.0 - np.sign(u) * p)


def predictive_free_space_volume(mean: np.ndarray, std: np.ndarray, thresholds: Sequence[float],
                                 band_multiplier: Callable[[float], float] | None = None) -> np.ndarray:
    """``predictive_prob_depth_greater`` at every pixel of [H, W] maps for each threshold: -> [T, H, W]."""
    th = np.asarray(list(thresholds), dtype=np.float64)
    if th.ndim != 1 or th.size == 0:
        raise ValueError(f"predictive_free_space_volume: need a non-empty list of thresholds, got {list(thresholds)}")
    return np.stack([predictive_prob_depth_greater(mean, std, t, band_multiplier) for t in th])


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
