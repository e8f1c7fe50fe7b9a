"""Compare two sets of camera poses of the same photos up to a similarity (scale, rotation, shift).

Structure from motion recovers poses in a frame of its own choosing: any similarity
``x -> s R x + t`` of the world gives the same images. Recovered poses are therefore scored after
the similarity that best maps their camera centres onto the reference ones (Umeyama 1991):

    (s, R, t) = argmin sum_i |s R c_i + t - c'_i|^2,

then per camera the centre error ``|s R c_i + t - c'_i|`` as a fraction of the reference capture's
extent (the largest distance between two of its cameras), and the rotation error, the angle of
``(R R_i)^T R'_i`` with ``R_i`` the camera-to-world rotations, read as
``atan2(|A - A^T|_F / (2 sqrt 2), (tr A - 1) / 2)``: ``acos((tr - 1) / 2)`` alone loses the small
angles (a float32 pose's rounding of 1e-7 in the trace reads as 0.03 degrees).
"""

from __future__ import annotations

import numpy as np


def similarity_align(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama (1991): (s, R [3, 3], t [3]) minimising sum |s R src_i + t - dst_i|^2; src, dst [N, 3], N >= 3."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need two [N, 3] point sets with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (xs ** 2).sum(1).mean())
    return s, R, mu_d - s * R @ mu_s


def _same_cameras(c2w, c2w_ref) -> tuple[np.ndarray, np.ndarray]:
    """Both pose sets as float64 arrays; ValueError when they hold different numbers of cameras."""
    c2w, c2w_ref = np.asarray(c2w, dtype=np.float64), np.asarray(c2w_ref, dtype=np.float64)
    if c2w.shape[0] != c2w_ref.shape[0]:
        raise ValueError(f"need the same cameras in both, got {c2w.shape[0]} and {c2w_ref.shape[0]}")
    return c2w, c2w_ref


def camera_errors(c2w: np.ndarray, c2w_ref: np.ndarray,
                  similarity: tuple[float, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per camera, the centre error [N] (fraction of the reference's extent) and the rotation error
    [N] (degrees) of camera-to-world poses [N, 3|4, 4] against the reference's after ``similarity``
    (s, R, t) (module doc)."""
    c2w, c2w_ref = _same_cameras(c2w, c2w_ref)
    s, R, t = similarity
    centres_ref = c2w_ref[:, :3, 3]
    extent = float(np.linalg.norm(centres_ref[:, None] - centres_ref[None], axis=-1).max())
    centre = np.linalg.norm(s * c2w[:, :3, 3] @ R.T + t - centres_ref, axis=1) / extent
    relative = np.einsum("ij,njk->nik", R, c2w[:, :3, :3]).transpose(0, 2, 1) @ c2w_ref[:, :3, :3]
    cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0
    sin = np.linalg.norm(relative - relative.transpose(0, 2, 1), axis=(1, 2)) / (2.0 * np.sqrt(2.0))
    return centre, np.degrees(np.arctan2(sin, cos))


def pose_errors(c2w: np.ndarray, c2w_ref: np.ndarray) -> dict[str, float]:
    """Centre and rotation errors of camera-to-world poses [N, 3|4, 4] against the reference's after
    the similarity fitted on all camera centres (module doc).

    Returns scale, centre_error_max / centre_error_median (fractions of the reference's extent) and
    rotation_error_max_deg / rotation_error_median_deg.
    """
    c2w, c2w_ref = _same_cameras(c2w, c2w_ref)
    similarity = similarity_align(c2w[:, :3, 3], c2w_ref[:, :3, 3])
    centre, angle = camera_errors(c2w, c2w_ref, similarity)
    return {"scale": similarity[0], "centre_error_max": float(centre.max()), "centre_error_median": float(np.median(centre)),
            "rotation_error_max_deg": float(angle.max()), "rotation_error_median_deg": float(np.median(angle))}
