"""Occlusion regulariser near the cameras (after FreeNeRF's, Yang et al. CVPR 2023): the expected
optical depth a training ray accumulates in the first part of its sampled range.

With few training views a NeRF can explain a photo by a surface floating just in front of the
camera that the other views never see (a "wall" at the near bound); such pixels render on the
wrong surface with a small spread, the failure that widens the calibrated depth intervals
(docs/uncertainty.md, "Wide bands are wrong surfaces"). For one ray with samples on intervals
[t_i, t_{i+1}] (widths delta_i), normalised coordinates m_i in [0, 1] of their midpoints (linear in
the sampling coordinate, ``distortion.normalised_coordinate``) and expected densities
E[sigma_i]:

    L_occ = sum_{i: m_i < f} E[sigma_i] delta_i

the expected optical depth of the near fraction f of the ray (f = 1/4 of 64 disparity-spaced
samples covers the ray from the near bound to about 1.3x it on the paper's LLFF bounds).
``exp(-L_occ)`` bounds the ray's expected transmittance through that part from below (Jensen), so
the term is small exactly when the near part of every training ray stays empty. E[sigma] is
evaluated on the near samples only (a quarter of them by default: the rectified normal's mean is
the costly part of the term). FreeNeRF penalises
the raw density of the first M samples; the optical depth is the same idea in units that do not
depend on the ray's length or on the sample count.

``E[sigma]`` is the rectified normal's mean ``mu Phi(mu/s) + s phi(mu/s)`` for S-NeRF's density
distribution and ``relu(mu)`` for a mean field (``expected_density``). Samples the occupancy
grid skipped are absent from packed samples and add nothing (they render empty).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .distortion import normalised_coordinate, sample_bounds
from .distributions import RectifiedNormal
from .rays import PackedRaySamples, RaySamples
from .samplers import Spacing


def expected_density(density_loc: Tensor, density_scale: Tensor | None) -> Tensor:
    """E[sigma] per sample [...]: ``RectifiedNormal(loc, scale).mean``, or ``relu(loc)`` for a
    mean field (``density_scale`` None)."""
    if density_scale is None:
        return torch.relu(density_loc)
    return RectifiedNormal(density_loc, density_scale, validate=False).mean


def near_optical_depth(density_loc: Tensor, density_scale: Tensor | None, samples: RaySamples | PackedRaySamples,
                       spacing: Spacing, near_fraction: float) -> Tensor:
    """Per ray, the expected optical depth ``sum_{i: m_i < f} E[sigma_i] delta_i`` of the samples whose
    midpoint lies in the near fraction ``f`` of the ray's sampled range, ``E[sigma_i]`` the
    ``expected_density`` of ``density_loc`` and ``density_scale`` (None: a mean field, ``relu(loc)``)
    evaluated on those samples only: [R, S] (dense) or [N] (packed) -> [R] (0 for rays with no
    sample there)."""
    if not 0.0 < near_fraction <= 1.0:
        raise ValueError(f"near_fraction must be in (0, 1], got {near_fraction}")
    near, far = sample_bounds(samples)
    near_part = normalised_coordinate(samples.t_mids, near, far, spacing) < near_fraction
    if isinstance(samples, PackedRaySamples):
        ray_index, num_rays = samples.ray_indices, samples.num_rays
    else:
        num_rays = near_part.shape[0]
        ray_index = torch.arange(num_rays, device=near_part.device)[:, None].expand_as(near_part)
    scale = None if density_scale is None else density_scale[near_part]
    per_sample = expected_density(density_loc[near_part], scale) * samples.deltas[near_part]
    out = torch.zeros(num_rays, dtype=per_sample.dtype, device=per_sample.device)
    return out.index_add_(0, ray_index[near_part], per_sample)
