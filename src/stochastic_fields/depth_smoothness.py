"""Depth smoothness of patches rendered from unseen viewpoints (after RegNeRF, Niemeyer et al.
CVPR 2022): a few-view regulariser against geometry that explains the training photos but breaks
up when seen from between them.

Each training step renders P patches of h x w neighbouring pixels from virtual cameras between
neighbouring training views (``virtual_views.PatchSampler``), with the expected density E[sigma]
(``occlusion.expected_density``: S-NeRF's rectified-normal mean, a mean field's ``relu(mu)``).
Per ray, with the weights w_i of E[sigma] (the run's quadrature) and the normalised coordinates
m_i in [0, 1] of the sample midpoints (linear in the sampling coordinate, disparity on LLFF:
``distortion.normalised_coordinate``), the expected normalised depth is

    d = sum_i w_i m_i + (1 - sum_i w_i) * 1

(the mass that does not terminate ends at the far bound, so an empty ray has d = 1 and the term
needs no division by the opacity). The patch loss is the mean over the patches' pixels of the
squared differences with the right and lower neighbours (RegNeRF's total variation, Eq. 3):

    L_smooth = mean_{p, u < w, v < h} (d_{p,v,u} - d_{p,v,u+1})^2 + (d_{p,v,u} - d_{p,v+1,u})^2

In the normalised coordinate a depth step counts the same at every distance and on every scene
(in disparity it is the step in NDC depth RegNeRF penalises on LLFF).
"""

from __future__ import annotations

from torch import Tensor

from .distortion import normalised_coordinate
from .rays import RaySamples
from .samplers import Spacing
from .volume_rendering import render_weights


def expected_normalised_depth(density: Tensor, samples: RaySamples, spacing: Spacing,
                              quadrature: str = "alpha") -> Tensor:
    """d = sum_i w_i m_i + (1 - sum_i w_i) per ray: density [R, S] on dense ``samples`` [R, S]
    -> [R] in [0, 1] (module doc)."""
    weights = render_weights(density, samples.t_starts, samples.t_ends, quadrature)
    m = normalised_coordinate(samples.t_mids, samples.rays.near[:, None], samples.rays.far[:, None], spacing)
    return (weights * m).sum(-1) + (1.0 - weights.sum(-1))


def patch_smoothness(depth: Tensor) -> Tensor:
    """L_smooth of patches' depths [P, h, w] (h, w >= 2): the mean over the [P, h-1, w-1] pixels
    that have both a right and a lower neighbour of the two squared differences' sum (module doc)."""
    if depth.ndim != 3 or depth.shape[1] < 2 or depth.shape[2] < 2:
        raise ValueError(f"patch_smoothness needs depths [P, h, w] with h, w >= 2, got {tuple(depth.shape)}")
    centre = depth[:, :-1, :-1]
    return ((centre - depth[:, :-1, 1:]) ** 2 + (centre - depth[:, 1:, :-1]) ** 2).mean()
