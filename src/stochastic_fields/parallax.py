"""The training views' parallax at a rendered point, and the depth-std term it gives (docs/uncertainty.md).

Two photos that see a surface point X along rays meeting at the angle theta resolve its depth to
about d / (f sin theta) per pixel of image error (d the depth, f the focal length in pixels): a
surface the training photos saw with little parallax is placed less surely than one they saw
from far apart, whatever the model's own std says. S-NeRF's std does not know theta; the research
log's analyses found the model errs most where theta is small (docs/studies.md, "which points the
narrow bands miss" and "a depth-std term from the training views' parallax").

For a rendered point X (a pixel's ray at its rendered depth) the training views that *see* X are
those with X inside their image, in front of the camera, on a pixel with rendered opacity above
``view_maps.OPACITY_MASK`` whose rendered surface is not nearer than (1 - ``SEE_TOLERANCE``) z_j(X)
(X not hidden behind what view j rendered there; ``free_space.TrainingDepth``). The parallax angle

    theta_max(X) = max over pairs (i, j) of views that see X of angle(c_i - X, c_j - X)

(c the camera centres; 0 when fewer than two views see X; angles above 90 degrees count as 90: sin
is what the term uses) is written per pixel as ``depth_parallax`` (degrees). The depth
recalibration may add the term

    kappa d / max(sin theta_max, PARALLAX_MIN_SIN)

to the std in quadrature (``calibration``, ``parallax_term``), kappa fitted on the calibration
points like the other terms' weights.
"""

from __future__ import annotations

import numpy as np

from .constants import PARALLAX_MIN_SIN
from .free_space import TrainingDepth, look_up, map_at_pixels
from .view_maps import OPACITY_MASK

#: A training view sees a point X unless the surface it rendered at X's pixel lies nearer than
#: (1 - SEE_TOLERANCE) of X's camera z (a point behind that surface is hidden from it).
SEE_TOLERANCE: float = 0.05


def parallax_angle(points: np.ndarray, ref: TrainingDepth, *, tolerance: float = SEE_TOLERANCE
                   ) -> tuple[np.ndarray, np.ndarray]:
    """theta_max [N] (degrees, in [0, 90]) of world ``points`` [N, 3] over the training views of
    ``ref`` that see them (module doc), and how many views see each [N] int64."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centres = np.linalg.inv(ref.world_to_camera)[:, :3, 3]
    sees, rays = [], []
    for t in range(len(ref.views)):
        z, inside, rows, cols = look_up(X, ref, t)
        surface = ref.depth[t][rows, cols].astype(np.float64)
        sees.append(inside & (ref.opacity[t][rows, cols] > OPACITY_MASK) & (surface >= z * (1.0 - tolerance)))
        u = centres[t][None] - X
        rays.append(u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), np.finfo(np.float64).tiny))
    cos_min = np.ones(len(X))
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            both = sees[i] & sees[j]
            if both.any():
                cos_min = np.where(both, np.minimum(cos_min, np.einsum("nk,nk->n", rays[i], rays[j])), cos_min)
    angle = np.degrees(np.arccos(np.clip(cos_min, 0.0, 1.0)))
    return angle, np.sum(sees, axis=0).astype(np.int64) if sees else np.zeros(len(X), np.int64)


def parallax_map(depth: np.ndarray, intrinsics: np.ndarray, world_to_camera: np.ndarray, ref: TrainingDepth,
                 *, mask: np.ndarray | None = None) -> np.ndarray:
    """theta_max [H, W] (degrees, float32) of a rendered camera-z ``depth`` map [H, W] of the camera
    ``intrinsics`` [3, 3], ``world_to_camera`` [4, 4] (``parallax_angle`` of each pixel centre
    back-projected to its depth); 0 where ``mask`` [H, W] is False (default: every pixel)."""
    return map_at_pixels(depth, intrinsics, world_to_camera, lambda X: parallax_angle(X, ref)[0], mask=mask)


def parallax_term(angle: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """d / max(sin theta, ``PARALLAX_MIN_SIN``) (float64): the term kappa scales (module doc), of the
    parallax angle ``angle`` (degrees) and the rendered ``depth`` (same shapes)."""
    sin = np.sin(np.radians(np.asarray(angle, dtype=np.float64)))
    return np.asarray(depth, dtype=np.float64) / np.maximum(sin, PARALLAX_MIN_SIN)
