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

try:  # a declared dependency; the numpy pair loop stands in where it is missing
    import numba
except ImportError:  # pragma: no cover - exercised only on machines without numba
    numba = None

from .constants import PARALLAX_MIN_SIN
from .free_space import TrainingDepth, map_at_pixels, maps_at_pixels, opaque_surface, violation_in_view

#: A training view sees a point X unless the surface it rendered at X's pixel lies nearer than
#: (1 - SEE_TOLERANCE) of X's camera z (a point behind that surface is hidden from it).
SEE_TOLERANCE: float = 0.05


def parallax_angle(points: np.ndarray, ref: TrainingDepth, *, tolerance: float = SEE_TOLERANCE
                   ) -> tuple[np.ndarray, np.ndarray]:
    """theta_max [N] (degrees, in [0, 90]) of world ``points`` [N, 3] over the training views of
    ``ref`` that see them (module doc), and how many views see each [N] int64."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    sees = views_seeing(X, ref, tolerance=tolerance)
    return angle_of_cosine(widest_cosine(X, ref.centres, sees)), sees.sum(axis=1).astype(np.int64)


def views_seeing(points: np.ndarray, ref: TrainingDepth, *, tolerance: float = SEE_TOLERANCE) -> np.ndarray:
    """[N, T] bool: which training views of ``ref`` see each world point of ``points`` [N, 3] (module
    doc: inside the image, in front of the camera, on an opaque pixel, not behind its rendered
    surface by more than ``tolerance`` of the point's camera z)."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    sees = np.zeros((len(ref.views), len(X)), bool)
    for t in range(len(ref.views)):
        sees[t] = sees_in_view(*opaque_surface(X, ref, t), tolerance=tolerance)
    return np.ascontiguousarray(sees.T)


def sees_in_view(z: np.ndarray, opaque: np.ndarray, surface: np.ndarray, *, tolerance: float = SEE_TOLERANCE
                 ) -> np.ndarray:
    """[N] bool: whether one training view sees each point (module doc), of ``opaque_surface``'s camera
    z ``z``, mask ``opaque`` and rendered ``surface`` [N]."""
    return opaque & (surface >= z * (1.0 - tolerance))


def training_view_terms(points: np.ndarray, ref: TrainingDepth, *, free_space: bool, parallax: bool,
                        tolerance: float = SEE_TOLERANCE) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The free-space violation e [N] (``free_space.free_space_violation``; None unless ``free_space``)
    and the parallax angle theta_max [N] in degrees (``parallax_angle``; None unless ``parallax``) of
    world ``points`` [N, 3], from one projection of the points into each training view of ``ref``
    (the two terms read the same rendered surface there)."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    violation = np.zeros(len(X)) if free_space else None
    sees = np.zeros((len(ref.views), len(X)), bool) if parallax else None
    if free_space or parallax:
        for t in range(len(ref.views)):
            surface = opaque_surface(X, ref, t)
            if free_space:
                violation = np.maximum(violation, violation_in_view(*surface))
            if parallax:
                sees[t] = sees_in_view(*surface, tolerance=tolerance)
    angle = angle_of_cosine(widest_cosine(X, ref.centres, np.ascontiguousarray(sees.T))) if parallax else None
    return violation, angle


def training_view_maps(depth: np.ndarray, intrinsics: np.ndarray, world_to_camera: np.ndarray, ref: TrainingDepth,
                       *, free_space: bool, parallax: bool, mask: np.ndarray | None = None
                       ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The free-space violation map e [H, W] (``free_space.violation_map``; None unless ``free_space``)
    and the parallax map theta_max [H, W] (``parallax_map``; None unless ``parallax``), float32, of a
    rendered camera-z ``depth`` map [H, W] of the camera ``intrinsics`` [3, 3], ``world_to_camera``
    [4, 4]: one back-projection of the pixels and one projection into each training view for both
    (``training_view_terms``); 0 where ``mask`` [H, W] is False (default: every pixel)."""
    if not (free_space or parallax):
        return None, None
    return maps_at_pixels(depth, intrinsics, world_to_camera,
                          lambda X: training_view_terms(X, ref, free_space=free_space, parallax=parallax), mask=mask)


def angle_of_cosine(cos_min: np.ndarray) -> np.ndarray:
    """theta_max [N] in degrees of its cosine [N], clipped to [0, 90] (sin is what the term uses)."""
    return np.degrees(np.arccos(np.clip(cos_min, 0.0, 1.0)))


def widest_cosine_loop(points: np.ndarray, centres: np.ndarray, sees: np.ndarray) -> np.ndarray:
    """cos theta_max [N]: the smallest u_i . u_j over pairs i < j of the views that both see point n
    (1 where fewer than two see it), u_t = (c_t - X_n) / |c_t - X_n|, of world ``points`` X [N, 3],
    camera ``centres`` c [T, 3] and ``sees`` [N, T] (bool); float64. numpy, one pass over the points
    per pair of views: the reference of the compiled ``widest_cosine``."""
    rays = centres[:, None, :] - points[None, :, :]  # [T, N, 3]: each view's rays contiguous
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), np.finfo(np.float64).tiny)
    by_view = np.ascontiguousarray(np.asarray(sees, bool).T)  # [T, N]
    cos_min = np.ones(len(points))
    for i in range(len(centres)):
        for j in range(i + 1, len(centres)):
            both = by_view[i] & by_view[j]
            if both.any():
                cos_min = np.where(both, np.minimum(cos_min, np.einsum("nk,nk->n", rays[i], rays[j])), cos_min)
    return cos_min


def _widest_cosine(points: np.ndarray, centres: np.ndarray, sees: np.ndarray) -> np.ndarray:
    """``widest_cosine_loop``'s values one point at a time: the unit rays of the views that see it,
    then its pairs (compiled by numba: no [N, T, 3] rays in memory, T^2 / 2 multiply-adds a point)."""
    N, T = sees.shape
    out = np.ones(N)
    rays = np.empty((T, 3))
    tiny = np.finfo(np.float64).tiny
    for n in range(N):
        k = 0
        for t in range(T):
            if sees[n, t]:
                u0 = centres[t, 0] - points[n, 0]
                u1 = centres[t, 1] - points[n, 1]
                u2 = centres[t, 2] - points[n, 2]
                norm = max(np.sqrt(u0 * u0 + u1 * u1 + u2 * u2), tiny)
                rays[k, 0], rays[k, 1], rays[k, 2] = u0 / norm, u1 / norm, u2 / norm
                k += 1
        best = 1.0
        for a in range(k):
            for b in range(a + 1, k):
                c = rays[a, 0] * rays[b, 0] + rays[a, 1] * rays[b, 1] + rays[a, 2] * rays[b, 2]
                if c < best:
                    best = c
        out[n] = best
    return out


widest_cosine = numba.njit(cache=True, nogil=True)(_widest_cosine) if numba is not None else widest_cosine_loop


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
