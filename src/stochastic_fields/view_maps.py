"""A rendered view's maps in the units every product uses (docs/definitions.md §1, §3).

The renderer returns ray-distance depths; products, scores and files use camera-z depth in scene
units: a depth (or standard deviation) along a ray times its ``z_scale`` (the ray direction's
camera-z component per unit length). ``depth_std`` is the total standard deviation (epistemic
+ termination spread, law of total variance). Rays that hit nothing report ``depth = far`` per
draw (see volume_rendering.expected_depth): depth is scored, exported and drawn only where the
opacity exceeds ``OPACITY_MASK``.
"""

from __future__ import annotations

import numpy as np
import torch

from .cameras import intrinsics_3x3

#: opacity above which a pixel counts as a surface hit for depth scores and products.
OPACITY_MASK = 0.5


def camera_z_maps(maps: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Renderer maps (ray distance) -> camera-z products, numpy float32: ``colour_mean``,
    ``colour_std`` [H, W, 3]; ``depth_mean``, ``depth_std`` (total), ``depth_std_epistemic``,
    ``depth_std_spread``, ``opacity``, ``num_draws`` (when rendered) [H, W]; ``depth_draws``
    [H, W, K] when kept."""
    z = maps["z_scale"].cpu().double()
    out = {
        "colour_mean": maps["colour_mean"].cpu().double(),
        "colour_std": maps["colour_var"].cpu().double().clamp_min(0).sqrt(),
        "depth_mean": maps["depth_mean"].cpu().double() * z,
        "depth_std": maps["depth_var_total"].cpu().double().clamp_min(0).sqrt() * z,
        "depth_std_epistemic": maps["depth_var_epistemic"].cpu().double().clamp_min(0).sqrt() * z,
        "depth_std_spread": maps["depth_var_spread"].cpu().double().clamp_min(0).sqrt() * z,
        "opacity": maps["opacity"].cpu().double(),
    }
    if "num_draws" in maps:
        out["num_draws"] = maps["num_draws"].cpu().double()
    if "depth_draws" in maps:
        out["depth_draws"] = maps["depth_draws"].cpu().double() * z[..., None]
    return {k: v.numpy().astype(np.float32) for k, v in out.items()}


def view_camera_arrays(dataset, view: int) -> dict[str, np.ndarray]:
    """The camera and units of a dataset view, stored next to its maps in every npz:
    ``intrinsics`` [3, 3] (pixel centres at +0.5), ``world_to_camera`` [4, 4] (OpenCV), ``near``,
    ``far`` (camera z), ``units`` and ``depth_kind``."""
    return {
        "intrinsics": intrinsics_3x3(dataset.cameras)[view].double().cpu().numpy(),
        "world_to_camera": dataset.cameras.extrinsics[view].double().cpu().numpy(),
        "near": np.float64(dataset.near[view]), "far": np.float64(dataset.far[view]),
        "units": np.str_("scene units"),
        "depth_kind": np.str_("camera_z; OpenCV camera, pixel (row i, col j) centre at (j + 0.5, i + 0.5)"),
    }


def draws_summary(num_draws: np.ndarray | torch.Tensor) -> dict[str, float | int]:
    """What K a render used: ``num_draws`` (int when every pixel got the same K, else the mean),
    ``num_draws_min`` and ``num_draws_max``, from a ``num_draws`` map."""
    k = np.asarray(num_draws.cpu() if isinstance(num_draws, torch.Tensor) else num_draws, dtype=np.float64)
    lo, hi = float(k.min()), float(k.max())
    return {"num_draws": int(lo) if lo == hi else float(k.mean()), "num_draws_min": int(lo), "num_draws_max": int(hi)}
