"""Occlusion edges of a rendered depth map: the range of the depths rendered around each pixel.

A pixel near an occlusion edge can render the near surface while the truth is the far one (or the
reverse); its error is then about the depth step there, whatever the std of its own ray says.
The edge size

    Delta(u) = max_{o in O} d(u + r o) - min_{o in O} d(u + r o),   O = {-1, 0, 1}^2

(d the rendered depth mean, r = ``EDGE_RADIUS_PX`` pixels, neighbours outside the image left out)
measures that step. A depth map may add it to the std as an independent term (``calibration``'s
edge weight gamma): depth_std = s sqrt(... + (gamma Delta)^2). The same definition serves whole
maps (``edge_range_map``: neighbouring pixel centres) and single rays (``edge_range_at_points``:
rays through the point's pixel position moved by r o), so the intervals a user exports and the
ones the calibration is fitted and scored on agree (docs/uncertainty.md, study 30).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

#: Pixels between a pixel and the neighbours its edge size looks at (the depth error anatomy's stencil).
EDGE_RADIUS_PX: int = 2


def neighbour_offsets(radius: float = EDGE_RADIUS_PX) -> list[tuple[float, float]]:
    """The 8 offsets (du, dv) of the 3 x 3 stencil with step ``radius`` pixels, the centre left out."""
    return [(du * radius, dv * radius) for dv in (-1, 0, 1) for du in (-1, 0, 1) if (du, dv) != (0, 0)]


def edge_range_map(depth: np.ndarray, radius: int = EDGE_RADIUS_PX) -> np.ndarray:
    """Delta [H, W] (float64) of a depth map [H, W]: max - min of the depths at the pixel and its 8
    neighbours ``radius`` pixels away (those inside the image). Non-finite depths are left out; a
    pixel whose stencil holds none gets NaN."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"edge_range_map: expected a depth map [H, W], got shape {depth.shape}")
    if int(radius) != radius or radius < 1:
        raise ValueError(f"edge_range_map: radius must be a whole number of pixels >= 1, got {radius}")
    radius = int(radius)
    h, w = depth.shape
    padded = np.full((h + 2 * radius, w + 2 * radius), np.nan)
    padded[radius:radius + h, radius:radius + w] = np.where(np.isfinite(depth), depth, np.nan)
    hi = np.full((h, w), -np.inf)
    lo = np.full((h, w), np.inf)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            window = padded[radius + dv * radius:radius + dv * radius + h, radius + du * radius:radius + du * radius + w]
            hi = np.fmax(hi, window)
            lo = np.fmin(lo, window)
    out = hi - lo
    out[~np.isfinite(out)] = np.nan
    return out


def edge_range_at_points(render_depth: Callable[[np.ndarray], np.ndarray], uv: np.ndarray, depth: np.ndarray,
                         width: float | np.ndarray, height: float | np.ndarray,
                         radius: float = EDGE_RADIUS_PX) -> np.ndarray:
    """Delta [N] of single rays: ``depth`` [N] rendered through the pixel positions ``uv`` [N, 2]
    (continuous, u right, v down, the image [0, width) x [0, height), sizes scalars or [N]) and ``render_depth(uv')`` [N]
    the depths rendered through the positions ``uv'`` [N, 2] = ``uv`` moved by each of the 8
    ``neighbour_offsets``; neighbours outside the image and non-finite depths are left out (as
    ``edge_range_map``)."""
    uv = np.asarray(uv, dtype=np.float64)
    centre = np.asarray(depth, dtype=np.float64).reshape(-1)
    if uv.shape != (centre.size, 2):
        raise ValueError(f"edge_range_at_points: expected uv [{centre.size}, 2], got {uv.shape}")
    hi = np.where(np.isfinite(centre), centre, -np.inf)
    lo = np.where(np.isfinite(centre), centre, np.inf)
    for du, dv in neighbour_offsets(radius):
        moved = uv + np.array([du, dv])
        inside = (moved[:, 0] >= 0) & (moved[:, 0] < width) & (moved[:, 1] >= 0) & (moved[:, 1] < height)
        d = np.asarray(render_depth(moved), dtype=np.float64).reshape(-1)
        if d.shape != centre.shape:
            raise ValueError(f"edge_range_at_points: render_depth gave {d.size} depths for {centre.size} rays")
        ok = inside & np.isfinite(d)
        hi = np.where(ok, np.maximum(hi, d), hi)
        lo = np.where(ok, np.minimum(lo, d), lo)
    out = hi - lo
    out[~np.isfinite(out)] = np.nan
    return out
