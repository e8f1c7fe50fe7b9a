"""Cameras and rays (docs/definitions.md §1).

Every camera in the package is a kornia :class:`~kornia.geometry.camera.PinholeCamera` holding V
views: ``intrinsics`` [V, 4, 4] (top-left 3x3 block is ``K``), ``extrinsics`` [V, 4, 4]
world-to-camera ``[R | t]``, ``height`` and ``width`` [V].

Conventions:
    * Camera axes are OpenCV: x right, y down, z forward (the camera looks along +z).
    * Pixel coordinates (u, v) are continuous with the image spanning [0, W] x [0, H]; pixel
      (row i, column j) covers [j, j + 1] x [i, i + 1] and its centre is (j + 0.5, i + 0.5).
      A centred principal point is ``cx = W / 2``, ``cy = H / 2`` (COLMAP's convention; kornia's
      own docs use integer centres, but ``project``/``unproject`` only apply ``K``, so the
      numbers mean what our ``K`` means). The pixel a projected point falls in is
      ``floor(u), floor(v)``.
    * Depth is camera-z (``z_cam``). Ray distance ``t`` is along unit directions, and
      ``z_cam = t * z_scale`` with ``z_scale = cos(angle between ray and optical axis)``.
    * Loaders convert other conventions at the boundary (:func:`opengl_c2w_to_opencv_w2c`,
      :func:`llff_poses_to_opencv_w2c`); after that everything is OpenCV.
"""

from __future__ import annotations

from typing import Literal, Sequence

import torch
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.camera.perspective import unproject_points
from torch import Tensor

from .rays import RayBundle

#: How ``near``/``far`` passed to the ray generators are measured: ``"camera_z"`` (planes of
#: constant camera depth, as LLFF bounds and NeRF's near=2/far=6 with z-normalised directions)
#: or ``"ray_distance"`` (distance along each unit ray).
BoundsKind = Literal["camera_z", "ray_distance"]

# Axis flip between OpenGL camera axes (x right, y up, z back) and OpenCV (x right, y down,
# z forward): the same physical camera, with y and z negated.
_GL_TO_CV = (1.0, -1.0, -1.0)


# --------------------------------------------------------------------------- construction
def make_cameras(K: Tensor, world_to_camera: Tensor, height: int | Tensor, width: int | Tensor) -> PinholeCamera:
    """Build a batched kornia PinholeCamera.

    Args:
        K: [V, 3, 3] intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixel centres at +0.5).
        world_to_camera: [V, 4, 4] OpenCV extrinsics, ``x_cam = R x_world + t``.
        height, width: image size, an int (shared) or [V] tensor.

    Returns:
        PinholeCamera with intrinsics [V, 4, 4] (K embedded), extrinsics [V, 4, 4], height/width [V]
        in K's dtype and device.
    """
    K = torch.as_tensor(K)
    if K.ndim != 3 or K.shape[1:] != (3, 3):
        raise ValueError(f"make_cameras: K must be [V, 3, 3], got {tuple(K.shape)}")
    w2c = torch.as_tensor(world_to_camera).to(K)
    if w2c.shape != (K.shape[0], 4, 4):
        raise ValueError(f"make_cameras: world_to_camera must be [{K.shape[0]}, 4, 4], got {tuple(w2c.shape)}")
    if not torch.isfinite(K).all() or not torch.isfinite(w2c).all():
        raise ValueError("make_cameras: K and world_to_camera must be finite")
    V = K.shape[0]
    intrinsics = torch.eye(4, dtype=K.dtype, device=K.device).repeat(V, 1, 1)
    intrinsics[:, :3, :3] = K
    h = torch.as_tensor(height, dtype=K.dtype, device=K.device).reshape(-1).expand(V).clone()
    w = torch.as_tensor(width, dtype=K.dtype, device=K.device).reshape(-1).expand(V).clone()
    return PinholeCamera(intrinsics, w2c, h, w)


def invert_rigid(transform: Tensor) -> Tensor:
    """Inverse of rigid transforms [*, 4, 4]: ``[R | t]^-1 = [R^T | -R^T t]`` (exact, no LU)."""
    R = transform[..., :3, :3]
    t = transform[..., :3, 3:]
    out = torch.zeros_like(transform)
    Rt = R.transpose(-1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def opengl_c2w_to_opencv_w2c(c2w: Tensor) -> Tensor:
    """Blender/nerfstudio camera-to-world (OpenGL axes) -> OpenCV world-to-camera.

    OpenGL camera axes are x right, y up, z back (the camera looks along -z); OpenCV axes are
    x right, y down, z forward. The camera centre is unchanged and the rotation columns map as
    ``[x_cv, y_cv, z_cv] = [x_gl, -y_gl, -z_gl]``, i.e. ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``;
    the result is its rigid inverse.

    Shapes: c2w [V, 4, 4] (or [V, 3, 4]) -> [V, 4, 4].
    """
    c2w = torch.as_tensor(c2w)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"opengl_c2w_to_opencv_w2c: c2w must be [V, 4, 4] or [V, 3, 4], got {tuple(c2w.shape)}")
    full = torch.eye(4, dtype=c2w.dtype, device=c2w.device).repeat(c2w.shape[0], 1, 1)
    full[:, :3, :] = c2w[:, :3, :]
    flip = torch.tensor((*_GL_TO_CV, 1.0), dtype=c2w.dtype, device=c2w.device)
    return invert_rigid(full * flip)  # scales columns: c2w @ diag(flip)


def opencv_w2c_to_opengl_c2w(w2c: Tensor) -> Tensor:
    """Inverse of :func:`opengl_c2w_to_opencv_w2c`. Shapes: [V, 4, 4] -> [V, 4, 4]."""
    flip = torch.tensor((*_GL_TO_CV, 1.0), dtype=w2c.dtype, device=w2c.device)
    return invert_rigid(w2c) * flip


def llff_poses_to_opencv_w2c(poses: Tensor) -> Tensor:
    """LLFF ``poses_bounds.npy`` poses -> OpenCV world-to-camera.

    An LLFF pose is [3, 5]: columns 0..2 are the camera's *down*, *right* and *back* axes in
    world coordinates, column 3 the camera centre, column 4 ``(h, w, f)``. OpenCV camera axes
    are x right, y down, z forward, so ``c2w_cv = [col1, col0, -col2 | col3]``; the result is its
    rigid inverse. The hwf column is ignored here.

    Shapes: poses [V, 3, 5] (or [V, 3, 4]) -> [V, 4, 4].
    """
    poses = torch.as_tensor(poses)
    if poses.ndim != 3 or poses.shape[1] != 3 or poses.shape[2] not in (4, 5):
        raise ValueError(f"llff_poses_to_opencv_w2c: poses must be [V, 3, 5], got {tuple(poses.shape)}")
    c2w = torch.eye(4, dtype=poses.dtype, device=poses.device).repeat(poses.shape[0], 1, 1)
    c2w[:, :3, 0] = poses[:, :, 1]  # right
    c2w[:, :3, 1] = poses[:, :, 0]  # down
    c2w[:, :3, 2] = -poses[:, :, 2]  # forward = -back
    c2w[:, :3, 3] = poses[:, :, 3]
    return invert_rigid(c2w)


# --------------------------------------------------------------------------- queries
def camera_to_world(cameras: PinholeCamera) -> Tensor:
    """[V, 4, 4] OpenCV camera-to-world transforms (rigid inverse of the extrinsics)."""
    return invert_rigid(cameras.extrinsics)


def camera_centres(cameras: PinholeCamera) -> Tensor:
    """[V, 3] camera centres in world coordinates: ``c = -R^T t``."""
    return camera_to_world(cameras)[:, :3, 3]


def intrinsics_3x3(cameras: PinholeCamera) -> Tensor:
    """[V, 3, 3] the K matrices."""
    return cameras.intrinsics[:, :3, :3]


def image_size(cameras: PinholeCamera) -> tuple[int, int]:
    """(H, W) shared by all views; raises ValueError if the views differ in size."""
    h, w = cameras.height, cameras.width
    if not (torch.all(h == h[0]) and torch.all(w == w[0])):
        raise ValueError(f"views differ in size: heights {h.tolist()}, widths {w.tolist()}")
    return int(round(float(h[0]))), int(round(float(w[0])))


def select_cameras(cameras: PinholeCamera, indices: Sequence[int] | Tensor) -> PinholeCamera:
    """The PinholeCamera of the views ``indices`` (a copy, in that order)."""
    idx = torch.as_tensor(indices, dtype=torch.long, device=cameras.intrinsics.device).reshape(-1)
    return PinholeCamera(cameras.intrinsics[idx], cameras.extrinsics[idx], cameras.height[idx], cameras.width[idx])


def rescale_cameras(cameras: PinholeCamera, factor: float) -> PinholeCamera:
    """Cameras for images resized by ``factor`` (0.25 = four times smaller).

    With pixel centres at +0.5 the image edges scale with the picture, so ``fx, fy, cx, cy``
    all multiply by ``factor``; height and width become ``round(factor * size)``.
    """
    if factor <= 0:
        raise ValueError(f"rescale_cameras: factor must be positive, got {factor}")
    intr = cameras.intrinsics.clone()
    intr[:, :2, :3] = intr[:, :2, :3] * factor
    height = torch.round(cameras.height * factor)
    width = torch.round(cameras.width * factor)
    return PinholeCamera(intr, cameras.extrinsics, height, width)


def pixel_centres(height: int, width: int, *, device=None, dtype=torch.float32) -> Tensor:
    """[H, W, 2] (u, v) coordinates of pixel centres: ``(j + 0.5, i + 0.5)`` at row i, column j."""
    v = torch.arange(height, device=device, dtype=dtype) + 0.5
    u = torch.arange(width, device=device, dtype=dtype) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


# --------------------------------------------------------------------------- rays
def _per_view(value: float | Tensor, V: int, like: Tensor, name: str) -> Tensor:
    """[V] tensor from a float or a [V] / [1] / scalar tensor."""
    t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if t.ndim == 0 or t.numel() == 1:
        return t.reshape(1).expand(V)
    if t.shape != (V,):
        raise ValueError(f"{name} must be a float or a [{V}] tensor (one per view), got shape {tuple(t.shape)}")
    return t


def _rays_from_pixels(
    K: Tensor, c2w: Tensor, uv: Tensor, near: Tensor, far: Tensor, bounds: BoundsKind
) -> RayBundle:
    """Core ray generator.

    Shapes: K [B, 3, 3], c2w [B, 4, 4], uv [B, P, 2], near/far [B] -> RayBundle [B, P].

    The pixel is unprojected with kornia to the camera-frame point at z = 1,
    ``d_cam = ((u - cx) / fx, (v - cy) / fy, 1)``; ``z_scale = 1 / |d_cam|``, the world direction
    is ``R_c2w d_cam z_scale`` and the origin the camera centre.
    """
    if bounds not in ("camera_z", "ray_distance"):
        raise ValueError(f"bounds must be 'camera_z' or 'ray_distance', got {bounds!r}")
    ones = torch.ones_like(uv[..., :1])
    d_cam = unproject_points(uv, ones, K[:, None, :, :])  # [B, P, 3], z = 1
    norm = d_cam.norm(dim=-1)  # [B, P], >= 1
    z_scale = 1.0 / norm
    R = c2w[:, None, :3, :3]  # [B, 1, 3, 3]
    directions = (R @ (d_cam * z_scale[..., None])[..., None])[..., 0]  # [B, P, 3]
    origins = c2w[:, None, :3, 3].expand_as(directions)
    near_r = near[:, None].expand_as(z_scale)
    far_r = far[:, None].expand_as(z_scale)
    if bounds == "camera_z":
        near_r = near_r / z_scale
        far_r = far_r / z_scale
    return RayBundle(
        origins=origins.contiguous(),
        directions=directions,
        near=near_r.contiguous(),
        far=far_r.contiguous(),
        z_scale=z_scale,
    )


def generate_rays(
    cameras: PinholeCamera,
    near: float | Tensor,
    far: float | Tensor,
    pixels: Tensor | None = None,
    *,
    bounds: BoundsKind = "camera_z",
) -> RayBundle:
    """Rays through pixel centres of every view (or through given pixel coordinates).

    Args:
        cameras: V views.
        near, far: floats or [V] tensors (one per view), broadcast to every ray of that view.
            With ``bounds="camera_z"`` (default) they are camera depths, so each ray's
            ``near = near_z / z_scale`` (the segment between two planes of constant depth, as LLFF
            bounds mean); with ``"ray_distance"`` they are copied as they are.
        pixels: None for the full grid of pixel centres (all views must share H, W), or
            [V, P, 2] continuous (u, v) coordinates (centres are ``index + 0.5``).

    Returns:
        RayBundle of shape [V, H, W] (or [V, P]) with unit world directions and
        ``z_scale = cos(angle to the optical axis)``: ``camera_z = t * z_scale``.

    Memory: 36 bytes per ray in float32 (V=20 at 504x378 is about 140 MB); use
    :func:`generate_rays_for_view` to render view by view.
    """
    V = cameras.batch_size
    like = cameras.intrinsics
    near_v = _per_view(near, V, like, "near")
    far_v = _per_view(far, V, like, "far")
    K = intrinsics_3x3(cameras)
    c2w = camera_to_world(cameras)
    if pixels is None:
        H, W = image_size(cameras)
        uv = pixel_centres(H, W, device=like.device, dtype=like.dtype).reshape(1, H * W, 2).expand(V, -1, -1)
        return _rays_from_pixels(K, c2w, uv, near_v, far_v, bounds).reshape(V, H, W)
    pixels = torch.as_tensor(pixels).to(like)
    if pixels.ndim != 3 or pixels.shape[0] != V or pixels.shape[2] != 2:
        raise ValueError(f"generate_rays: pixels must be [{V}, P, 2] (u, v), got {tuple(pixels.shape)}")
    return _rays_from_pixels(K, c2w, pixels, near_v, far_v, bounds)


def generate_rays_for_view(
    cameras: PinholeCamera,
    view_index: int,
    near: float | Tensor,
    far: float | Tensor,
    *,
    bounds: BoundsKind = "camera_z",
) -> RayBundle:
    """Rays through every pixel centre of one view: RayBundle [H, W].

    ``near``/``far`` as in :func:`generate_rays` (floats, or [V] tensors indexed at the view).
    """
    V = cameras.batch_size
    if not -V <= view_index < V:
        raise IndexError(f"view_index {view_index} out of range for {V} views")
    view_index = view_index % V
    like = cameras.intrinsics
    near_v = _per_view(near, V, like, "near")[view_index : view_index + 1]
    far_v = _per_view(far, V, like, "far")[view_index : view_index + 1]
    one = select_cameras(cameras, [view_index])
    return generate_rays(one, near_v, far_v, bounds=bounds)[0]


def generate_rays_at(
    cameras: PinholeCamera,
    view_indices: Tensor,
    pixels: Tensor,
    near: float | Tensor,
    far: float | Tensor,
    *,
    bounds: BoundsKind = "camera_z",
) -> RayBundle:
    """Rays for a batch of (view, pixel) pairs, e.g. random training rays across views.

    Shapes: view_indices [R] int64, pixels [R, 2] continuous (u, v) -> RayBundle [R].
    ``near``/``far``: floats or [V] tensors (indexed by each ray's view).
    """
    V = cameras.batch_size
    like = cameras.intrinsics
    idx = torch.as_tensor(view_indices, dtype=torch.long, device=like.device).reshape(-1)
    pixels = torch.as_tensor(pixels).to(like)
    if pixels.shape != (idx.shape[0], 2):
        raise ValueError(f"generate_rays_at: pixels must be [{idx.shape[0]}, 2], got {tuple(pixels.shape)}")
    near_r = _per_view(near, V, like, "near")[idx]
    far_r = _per_view(far, V, like, "far")[idx]
    K = intrinsics_3x3(cameras)[idx]
    c2w = camera_to_world(cameras)[idx]
    return _rays_from_pixels(K, c2w, pixels[:, None, :], near_r, far_r, bounds)[:, 0]


# --------------------------------------------------------------------------- projection
def world_to_camera_points(cameras: PinholeCamera, points: Tensor) -> Tensor:
    """[V, P, 3] camera-frame coordinates of world points [P, 3]: ``R x + t``."""
    E = cameras.extrinsics
    points = torch.as_tensor(points).to(E)
    return points[None] @ E[:, :3, :3].transpose(1, 2) + E[:, None, :3, 3]


def project_points(cameras: PinholeCamera, points: Tensor) -> tuple[Tensor, Tensor]:
    """Project world points into every view with kornia.

    Shapes: points [P, 3] -> uv [V, P, 2] continuous pixel coordinates (pixel = floor(uv)),
    z [V, P] camera-z depth. Points with ``z <= 0`` lie behind the camera: their uv is
    meaningless, mask them with ``z > 0``.
    """
    points = torch.as_tensor(points).to(cameras.extrinsics)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"project_points: points must be [P, 3], got {tuple(points.shape)}")
    V = cameras.batch_size
    uv = cameras.project(points[None].expand(V, -1, -1))
    z = world_to_camera_points(cameras, points)[..., 2]
    return uv, z


def in_image(cameras: PinholeCamera, uv: Tensor, z: Tensor) -> Tensor:
    """[V, P] bool: in front of the camera and inside [0, W) x [0, H)."""
    H = cameras.height[:, None]
    W = cameras.width[:, None]
    return (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)


def backproject_depths(cameras: PinholeCamera, depths: Tensor, mask: Tensor | None = None) -> Tensor:
    """World points [N, 3] of camera-z depth maps [V, H, W] at pixel centres.

    ``x = c + t d`` with ray distance ``t = depth / z_scale``; pixels with ``mask`` False (default:
    ``depth > 0``) are dropped. Points come out view by view in row-major pixel order.
    """
    depths = torch.as_tensor(depths).to(cameras.extrinsics)
    V = cameras.batch_size
    H, W = image_size(cameras)
    if depths.shape != (V, H, W):
        raise ValueError(f"backproject_depths: depths must be [{V}, {H}, {W}], got {tuple(depths.shape)}")
    mask = depths > 0 if mask is None else torch.as_tensor(mask, dtype=torch.bool, device=depths.device)
    out = []
    for v in range(V):
        rays = generate_rays_for_view(cameras, v, 0.0, 1.0)
        m = mask[v]
        t = depths[v][m] / rays.z_scale[m]
        out.append(rays.origins[m] + t[:, None] * rays.directions[m])
    return torch.cat(out, dim=0)
