"""Fast logistic-normal moments from a table, for rendering with the Rao-Blackwellised colour
estimator (``RenderSettings.colour_estimator = "rao_blackwell"``).

For ``R = sigmoid(Y)``, ``Y ~ N(loc, s^2)``, the mean and variance have no closed form;
``distributions._logistic_normal_moments`` integrates them to float64 round-off, at ~3.6 us a
value. A render needs them at every sample and channel (~4e5 values per 2048-ray chunk), so
this module tabulates them once per process (from that quadrature) and reads them by bilinear
interpolation with ``torch.nn.functional.grid_sample`` (~9 ns a value on 2 CPU cores).

Coordinates make the tabulated functions smooth and bounded:

    fold       m(-loc, s) = 1 - m(loc, s),  v(-loc, s) = v(loc, s)       (table loc <= 0)
    a        = |loc| / sqrt(1 + pi s^2 / 8)      MacKay's probit-scaled location
    table 0  = m(-a) - sigmoid(-a)                MacKay's approximation sigmoid(-a) is exact as
                                                  s -> 0 and within 0.02 elsewhere; the table
                                                  holds the small, smooth remainder
    table 1  = log v                              ~ 2 log s + log sigmoid'(loc)^2 for small s:
                                                  linear in log s, so relative accuracy holds
                                                  down to variances ~1e-30

over ``a`` in [0, LOGISTIC_TABLE_A_MAX] and ``log s`` in ``LOGISTIC_TABLE_LOG_SCALE_RANGE``
(accuracy and the treatment outside the table: see those constants).
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import Tensor

from .constants import (LOGISTIC_TABLE_A_MAX, LOGISTIC_TABLE_A_STEP, LOGISTIC_TABLE_LOG_SCALE_RANGE,
                        LOGISTIC_TABLE_LOG_SCALE_STEP)
from .distributions import _logistic_normal_moments

__all__ = ["logistic_normal_moments_tabulated", "mackay_location"]

_TABLE_BUILD_BATCH = 32768  # values per quadrature call while building (bounds its [B, 64] temporaries)


def mackay_location(loc: Tensor, scale: Tensor) -> Tensor:
    """``a = |loc| / sqrt(1 + pi scale^2 / 8)``, the table's first coordinate. Shapes broadcast."""
    return loc.abs() * torch.rsqrt(1.0 + (math.pi / 8.0) * scale * scale)


def _grid_size() -> tuple[int, int]:
    lo, hi = LOGISTIC_TABLE_LOG_SCALE_RANGE
    return (round(LOGISTIC_TABLE_A_MAX / LOGISTIC_TABLE_A_STEP) + 1,
            round((hi - lo) / LOGISTIC_TABLE_LOG_SCALE_STEP) + 1)


@lru_cache(maxsize=None)
def _table_float64() -> Tensor:
    """[1, 2, n_log_scale, n_a] (grid_sample's [N, C, H, W]): channel 0 the mean's remainder
    ``m(-a, s) - sigmoid(-a)``, channel 1 ``log v``; float64, built once (~1 s)."""
    n_a, n_s = _grid_size()
    lo, hi = LOGISTIC_TABLE_LOG_SCALE_RANGE
    a = torch.linspace(0.0, LOGISTIC_TABLE_A_MAX, n_a, dtype=torch.float64)
    scale = torch.linspace(lo, hi, n_s, dtype=torch.float64).exp()[:, None].expand(n_s, n_a).reshape(-1)
    loc = -(a[None, :] * torch.sqrt(1.0 + (math.pi / 8.0) * scale.reshape(n_s, n_a) ** 2)).reshape(-1)
    means, variances = [], []
    for start in range(0, loc.numel(), _TABLE_BUILD_BATCH):
        m, v = _logistic_normal_moments(loc[start:start + _TABLE_BUILD_BATCH],
                                        scale[start:start + _TABLE_BUILD_BATCH])
        means.append(m)
        variances.append(v)
    remainder = torch.cat(means).reshape(n_s, n_a) - torch.sigmoid(-a)[None, :]
    log_var = torch.cat(variances).reshape(n_s, n_a).log()
    return torch.stack([remainder, log_var])[None]


@lru_cache(maxsize=8)
def _table(device: torch.device, dtype: torch.dtype) -> Tensor:
    return _table_float64().to(device=device, dtype=dtype)


def logistic_normal_moments_tabulated(loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """``E[sigmoid(Y)]`` and ``Var[sigmoid(Y)]`` for ``Y ~ N(loc, scale^2)``, read from the table.

    Shapes: ``loc``, ``scale`` broadcast to ``[*B]``; returns two ``[*B]`` tensors on their
    device and dtype. Differentiable (piecewise-bilinear in the table coordinates). Scales must be
    positive (the fields guarantee it). Accuracy: see ``constants.LOGISTIC_TABLE_A_MAX``.
    float16/bfloat16 inputs are read in float32 (autocast disabled) and the results cast back.
    """
    loc, scale = torch.broadcast_tensors(loc, scale)
    if loc.dtype in (torch.float16, torch.bfloat16) or scale.dtype in (torch.float16, torch.bfloat16):
        # half mantissas cannot hold the table's coordinates or exp(log v): read in float32
        # (autocast off), return in the input dtype
        with torch.autocast(device_type=loc.device.type, enabled=False):
            mean, variance = logistic_normal_moments_tabulated(loc.float(), scale.float())
        return mean.to(loc.dtype), variance.to(loc.dtype)
    table = _table(loc.device, loc.dtype)
    lo, hi = LOGISTIC_TABLE_LOG_SCALE_RANGE
    a = mackay_location(loc, scale)
    log_scale = torch.log(scale)
    grid_x = a * (2.0 / LOGISTIC_TABLE_A_MAX) - 1.0
    grid_y = (log_scale - lo) * (2.0 / (hi - lo)) - 1.0
    grid = torch.stack([grid_x, grid_y], dim=-1).reshape(1, 1, -1, 2)
    read = F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, 0]
    remainder, log_var = read[0].reshape(loc.shape), read[1].reshape(loc.shape)
    folded_mean = torch.sigmoid(-a) + remainder
    mean = torch.where(loc > 0, 1.0 - folded_mean, folded_mean)
    variance = torch.exp(log_var + 2.0 * (log_scale - lo).clamp_max(0.0))
    return mean, variance
