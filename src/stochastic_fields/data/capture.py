"""What a posed capture's sparse SfM points say about its scene: per-view depth bounds and shape.

Bounds follow LLFF's ``imgs2poses`` (the rule behind every ``poses_bounds.npy``): a view's near
and far planes are the 0.1th and 99.9th percentiles of the camera-z depths of the SfM points
that view observes,

    near_v = percentile_0.1{ z_v(X_p) : p in track of v, z > 0 }
    far_v  = percentile_99.9{ ... }

so a COLMAP model, a prepared capture and an LLFF scene of the same photos get the same bounds
(up to the SfM's arbitrary scale). Where tracks are known only points seen by at least
``MIN_TRACK_LENGTH`` images count: two-view triangulations are the least certain in depth, and
with the few hundred points per view of a small capture the 0.1th percentile is the nearest
point, so one bad triangulation would set near (fern from its ``images_8`` photos: one view's
near fell to 0.64x LLFF's with two-view points, 1.01x without). A view that observes fewer than
``MIN_POINTS_PER_VIEW`` points takes the smallest near and largest far of the other views.

Forward-facing (LLFF-like, modelled in NDC) or not: every optical axis within
``FORWARD_FACING_MAX_ANGLE_DEG`` of the mean axis, and every SfM point in front of the mean
camera.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from kornia.geometry.camera import PinholeCamera

from ..cameras import camera_to_world, project_points, select_cameras

#: Fraction of the SfM points that must lie in front of the mean camera for a forward-facing capture
#: (a few stray triangulations behind it are tolerated).
FORWARD_FACING_MIN_FRONT: float = 0.99
#: Percentiles of the visible points' depths that give near and far (LLFF's imgs2poses).
NEAR_PERCENTILE: float = 0.1
FAR_PERCENTILE: float = 99.9
#: Points observed by fewer images than this are left out of the bounds (module doc).
MIN_TRACK_LENGTH: int = 3
#: Fewer observed points than this and a view's own percentiles are not trusted.
MIN_POINTS_PER_VIEW: int = 10
#: A capture is forward-facing when every optical axis lies within this angle of the mean axis
#: (LLFF fern: at most 6 degrees; an object orbit spans 180 degrees and more).
FORWARD_FACING_MAX_ANGLE_DEG: float = 30.0


def visible_points_by_projection(cameras: PinholeCamera, xyz: np.ndarray) -> list[np.ndarray]:
    """Per view, indices of the points that project inside the image in front of the camera.

    The fallback when no tracks say which view saw which point (a nerfstudio ``sparse_pc.ply``).
    Occluded points are kept, so bounds from this set are a little wider than from tracks.
    """
    xyz_t = torch.as_tensor(np.asarray(xyz), dtype=torch.float64)
    out = []
    for v in range(cameras.batch_size):
        cam = select_cameras(cameras, [v])
        cam64 = type(cam)(cam.intrinsics.double(), cam.extrinsics.double(), cam.height.double(), cam.width.double())
        uv, z = project_points(cam64, xyz_t)
        W, H = float(cam.width[0]), float(cam.height[0])
        inside = (z[0] > 0) & (uv[0, :, 0] >= 0) & (uv[0, :, 0] < W) & (uv[0, :, 1] >= 0) & (uv[0, :, 1] < H)
        out.append(np.flatnonzero(inside.numpy()))
    return out


def bounds_from_points(cameras: PinholeCamera, xyz: np.ndarray, visible: list[np.ndarray], *,
                       track_lengths: np.ndarray | None = None,
                       what: str = "SfM points") -> tuple[torch.Tensor, torch.Tensor]:
    """(near [V], far [V]) camera-z bounds from the points each view observes (module doc).

    ``track_lengths`` [P]: images per point, when known; points below ``MIN_TRACK_LENGTH`` are
    left out. Raises ValueError if no view observes ``MIN_POINTS_PER_VIEW`` points in front of it.
    """
    V = cameras.batch_size
    xyz64 = np.asarray(xyz, dtype=np.float64)
    if track_lengths is not None:
        reliable = np.asarray(track_lengths) >= MIN_TRACK_LENGTH
        visible = [np.asarray(idx, dtype=np.int64)[reliable[np.asarray(idx, dtype=np.int64)]] for idx in visible]
    w2c = cameras.extrinsics.double().cpu().numpy()  # [V, 4, 4]
    near = np.full(V, np.nan)
    far = np.full(V, np.nan)
    for v in range(V):
        idx = np.asarray(visible[v], dtype=np.int64)
        if idx.size == 0:
            continue
        z = xyz64[idx] @ w2c[v, 2, :3] + w2c[v, 2, 3]
        z = z[z > 0]
        if z.size < MIN_POINTS_PER_VIEW:
            continue
        near[v], far[v] = np.percentile(z, NEAR_PERCENTILE), np.percentile(z, FAR_PERCENTILE)
    ok = np.isfinite(near) & (far > near)
    if not ok.any():
        raise ValueError(f"no view observes {MIN_POINTS_PER_VIEW} or more {what} in front of it: "
                         "cannot derive near/far")
    near[~ok], far[~ok] = near[ok].min(), far[ok].max()
    return torch.from_numpy(near).float(), torch.from_numpy(far).float()


def is_forward_facing(cameras: PinholeCamera, xyz: np.ndarray | None = None) -> bool:
    """True for LLFF-like captures: all optical axes within ``FORWARD_FACING_MAX_ANGLE_DEG`` of
    their mean, and (given points [P, 3]) ``FORWARD_FACING_MIN_FRONT`` of the points in front of
    the mean camera."""
    c2w = camera_to_world(cameras).double()
    axes = c2w[:, :3, 2]  # OpenCV z = viewing direction, [V, 3]
    mean = axes.mean(0)
    if float(mean.norm()) < 1e-6:
        return False
    mean = mean / mean.norm()
    cos = (axes @ mean).clamp(-1.0, 1.0)
    if float(cos.min()) < math.cos(math.radians(FORWARD_FACING_MAX_ANGLE_DEG)):
        return False
    if xyz is not None and len(xyz) > 0:
        centre = c2w[:, :3, 3].mean(0)
        depth = (torch.as_tensor(np.asarray(xyz), dtype=torch.float64) - centre) @ mean
        return float((depth > 0).double().mean()) >= FORWARD_FACING_MIN_FRONT
    return True
