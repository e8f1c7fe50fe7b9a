"""Turn maps into images people can look at (perceptual colour maps, shared ranges)."""

from __future__ import annotations

import numpy as np
import matplotlib


def colourise(values: np.ndarray, *, cmap: str = "viridis", vmin: float | None = None, vmax: float | None = None,
              mask: np.ndarray | None = None, invalid_rgb=(0, 0, 0)) -> tuple[np.ndarray, float, float]:
    """[H, W] float -> ([H, W, 3] uint8, vmin, vmax). Range defaults to the 1st-99th percentiles of
    the valid values, so a few outliers do not wash the map out. Invalid pixels (``~mask`` or
    non-finite) get ``invalid_rgb``."""
    values = np.asarray(values, dtype=np.float64)
    valid = np.isfinite(values) if mask is None else (np.asarray(mask, bool) & np.isfinite(values))
    if valid.any():
        lo = float(np.percentile(values[valid], 1)) if vmin is None else vmin
        hi = float(np.percentile(values[valid], 99)) if vmax is None else vmax
    else:
        lo, hi = 0.0, 1.0
    if hi <= lo:
        hi = lo + 1e-12
    norm = np.clip((values - lo) / (hi - lo), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](np.where(valid, norm, 0.0))
    rgb = (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)
    rgb[~valid] = np.asarray(invalid_rgb, dtype=np.uint8)
    return rgb, lo, hi


def to_uint8_rgb(colour: np.ndarray) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8."""
    return (np.clip(np.asarray(colour, dtype=np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
