"""Cameras and rays against float64 hand-written pinhole references and hand-made cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stochastic_fields.cameras import (
    backproject_depths,
    camera_centres,
    camera_to_world,
    generate_rays,
    generate_rays_at,
    generate_rays_for_view,
    in_image,
    llff_poses_to_opencv_w2c,
    make_cameras,
    opencv_w2c_to_opengl_c2w,
    opengl_c2w_to_opencv_w2c,
    pixel_centres,
    project_points,
    rescale_cameras,
    select_cameras,
)


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """[n, 3, 3] proper rotations (QR of Gaussian matrices, sign-fixed)."""
    A = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    Q, R = torch.linalg.qr(A)
    Q = Q * torch.sign(torch.diagonal(R, dim1=-2, dim2=-1))[:, None, :]
    det = torch.det(Q)
    Q[:, :, 0] *= det[:, None]
    return Q


def random_setup(V=3, H=7, W=9, dtype=torch.float64, seed=0):
    """Random K (fx != fy, off-centre principal point), random OpenCV w2c, as float64 numpy too."""
    gen = torch.Generator().manual_seed(seed)
    K = torch.zeros(V, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = 5 + 10 * torch.rand(V, generator=gen, dtype=torch.float64)
    K[:, 1, 1] = 5 + 10 * torch.rand(V, generator=gen, dtype=torch.float64)
    K[:, 0, 2] = W / 2 + torch.randn(V, generator=gen, dtype=torch.float64)
    K[:, 1, 2] = H / 2 + torch.randn(V, generator=gen, dtype=torch.float64)
    K[:, 2, 2] = 1
    R = random_rotations(V, gen)
    t = torch.randn(V, 3, generator=gen, dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = t
    cams = make_cameras(K.to(dtype), w2c.to(dtype), H, W)
    return cams, K.numpy(), w2c.numpy()


def reference_rays(K: np.ndarray, w2c: np.ndarray, H: int, W: int):
    """Naive float64 loops: origins, unit directions, z_scale per pixel centre, [V, H, W, ...]."""
    V = K.shape[0]
    o = np.zeros((V, H, W, 3))
    d = np.zeros((V, H, W, 3))
    zs = np.zeros((V, H, W))
    for v in range(V):
        R, t = w2c[v, :3, :3], w2c[v, :3, 3]
        centre = -R.T @ t
        Kinv = np.linalg.inv(K[v])
        for i in range(H):
            for j in range(W):
                dc = Kinv @ np.array([j + 0.5, i + 0.5, 1.0])
                dc /= np.linalg.norm(dc)
                o[v, i, j] = centre
                d[v, i, j] = R.T @ dc
                zs[v, i, j] = dc[2]
    return o, d, zs


# ------------------------------------------------------------------ construction
def test_make_cameras_embeds_K_and_validates():
    cams, K, w2c = random_setup()
    assert cams.intrinsics.shape == (3, 4, 4) and cams.extrinsics.shape == (3, 4, 4)
    np.testing.assert_allclose(cams.intrinsics[:, :3, :3].numpy(), K)
    np.testing.assert_allclose(cams.intrinsics[:, 3, 3].numpy(), 1.0)
    assert cams.height.tolist() == [7, 7, 7] and cams.width.tolist() == [9, 9, 9]
    with pytest.raises(ValueError, match="K must be"):
        make_cameras(torch.eye(3), torch.eye(4)[None], 4, 4)
    with pytest.raises(ValueError, match="world_to_camera must be"):
        make_cameras(torch.eye(3)[None], torch.eye(4)[None].repeat(2, 1, 1), 4, 4)
    bad = torch.eye(4)[None].clone()
    bad[0, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        make_cameras(torch.eye(3)[None], bad, 4, 4)


def test_camera_centres_and_c2w():
    cams, K, w2c = random_setup(V=4)
    for v in range(4):
        ref = -w2c[v, :3, :3].T @ w2c[v, :3, 3]
        np.testing.assert_allclose(camera_centres(cams)[v].numpy(), ref, atol=1e-12)
        np.testing.assert_allclose(camera_to_world(cams)[v].numpy(), np.linalg.inv(w2c[v]), atol=1e-12)


# ------------------------------------------------------------------ conventions
def test_opengl_to_opencv_hand_case():
    """Identity OpenGL camera at the origin looks along world -z with world +y up."""
    c2w = torch.eye(4, dtype=torch.float64)[None]
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    K = torch.tensor([[[10.0, 0, 5], [0, 10.0, 4], [0, 0, 1]]], dtype=torch.float64)
    cams = make_cameras(K, w2c, 8, 10)
    pts = torch.tensor([[0.0, 0, -2], [1.0, 0, -2], [0.0, 1, -2], [0.0, 0, 2]], dtype=torch.float64)
    uv, z = project_points(cams, pts)
    np.testing.assert_allclose(z[0].numpy(), [2, 2, 2, -2])
    np.testing.assert_allclose(uv[0, 0].numpy(), [5, 4])  # straight ahead -> principal point
    np.testing.assert_allclose(uv[0, 1].numpy(), [10, 4])  # world +x -> image right
    np.testing.assert_allclose(uv[0, 2].numpy(), [5, -1])  # world +y (up) -> image up (smaller v)
    assert not bool(in_image(cams, uv, z)[0, 3])  # behind the camera


def test_opengl_opencv_round_trip():
    gen = torch.Generator().manual_seed(3)
    c2w = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    c2w[:, :3, :3] = random_rotations(5, gen)
    c2w[:, :3, 3] = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    back = opencv_w2c_to_opengl_c2w(opengl_c2w_to_opencv_w2c(c2w))
    torch.testing.assert_close(back, c2w, rtol=0, atol=1e-12)
    # same centre, viewing direction flipped: OpenCV +z is OpenGL -z
    cv_c2w = torch.linalg.inv(opengl_c2w_to_opencv_w2c(c2w))
    torch.testing.assert_close(cv_c2w[:, :3, 3], c2w[:, :3, 3], rtol=0, atol=1e-12)
    torch.testing.assert_close(cv_c2w[:, :3, 2], -c2w[:, :3, 2], rtol=0, atol=1e-12)
    torch.testing.assert_close(cv_c2w[:, :3, 1], -c2w[:, :3, 1], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="c2w must be"):
        opengl_c2w_to_opencv_w2c(torch.eye(4))


def test_llff_columns_down_right_back():
    """Build an LLFF pose from known OpenCV axes; points ahead/right/below land where they should."""
    gen = torch.Generator().manual_seed(1)
    R = random_rotations(2, gen)  # columns: right, down, forward (OpenCV c2w)
    centre = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    right, down, fwd = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    hwf = torch.tensor([30.0, 40.0, 35.0], dtype=torch.float64).expand(2, 3)
    poses = torch.stack([down, right, -fwd, centre, hwf], dim=-1)  # [2, 3, 5]
    w2c = llff_poses_to_opencv_w2c(poses)
    ref = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    ref[:, :3, :3] = R.transpose(1, 2)
    ref[:, :3, 3] = -(R.transpose(1, 2) @ centre[..., None])[..., 0]
    torch.testing.assert_close(w2c, ref, rtol=0, atol=1e-12)
    K = torch.tensor([[35.0, 0, 20], [0, 35.0, 15], [0, 0, 1]], dtype=torch.float64).expand(2, 3, 3)
    cams = make_cameras(K, w2c, 30, 40)
    for v in range(2):
        pts = torch.stack([centre[v] + 2 * fwd[v], centre[v] + 2 * fwd[v] + 0.5 * right[v],
                           centre[v] + 2 * fwd[v] + 0.5 * down[v]])
        uv, z = project_points(select_cameras(cams, [v]), pts)
        np.testing.assert_allclose(uv[0].numpy(), [[20, 15], [20 + 35 * 0.25, 15], [20, 15 + 35 * 0.25]], atol=1e-10)
        np.testing.assert_allclose(z[0].numpy(), [2, 2, 2], atol=1e-12)
    with pytest.raises(ValueError, match="poses must be"):
        llff_poses_to_opencv_w2c(torch.zeros(2, 5, 3))


# ------------------------------------------------------------------ rays
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_generate_rays_matches_naive_reference(dtype, tol):
    cams, K, w2c = random_setup(dtype=dtype)
    rays = generate_rays(cams, 0.5, torch.tensor([2.0, 3.0, 4.0]))
    assert rays.shape == (3, 7, 9) and rays.origins.dtype == dtype
    o, d, zs = reference_rays(K, w2c, 7, 9)
    np.testing.assert_allclose(rays.origins.double().numpy(), o, atol=tol * 10)
    np.testing.assert_allclose(rays.directions.double().numpy(), d, atol=tol)
    np.testing.assert_allclose(rays.z_scale.double().numpy(), zs, atol=tol)
    # camera_z bounds: planes of constant depth -> ray distances depth / z_scale
    np.testing.assert_allclose(rays.near.double().numpy(), 0.5 / zs, rtol=tol * 10)
    far_ref = np.array([2.0, 3.0, 4.0])[:, None, None] / zs
    np.testing.assert_allclose(rays.far.double().numpy(), far_ref, rtol=tol * 10)


def test_ray_distance_bounds_are_copied_and_points_reproject():
    cams, K, w2c = random_setup()
    rays = generate_rays(cams, 1.0, 3.0, bounds="ray_distance")
    assert torch.all(rays.near == 1.0) and torch.all(rays.far == 3.0)
    # a point at distance t along each ray projects back onto its own pixel centre, z = t z_scale
    t = 2.5
    pts = rays.origins + t * rays.directions  # [V, H, W, 3]
    for v in range(3):
        uv, z = project_points(select_cameras(cams, [v]), pts[v].reshape(-1, 3))
        centres = pixel_centres(7, 9, dtype=torch.float64).reshape(-1, 2)
        np.testing.assert_allclose(uv[0].numpy(), centres.numpy(), atol=1e-9)
        np.testing.assert_allclose(z[0].numpy(), (t * rays.z_scale[v]).reshape(-1).numpy(), atol=1e-12)
    with pytest.raises(ValueError, match="bounds must be"):
        generate_rays(cams, 1.0, 3.0, bounds="metres")
    with pytest.raises(ValueError, match="near must be"):
        generate_rays(cams, torch.ones(2), 3.0)


def test_wide_angle_corner_rays():
    """A 170-degree field of view: corner rays nearly perpendicular to the axis stay exact."""
    W = H = 4
    f = 0.5 * W / math.tan(math.radians(85))
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]], dtype=torch.float64)
    cams = make_cameras(K, torch.eye(4, dtype=torch.float64)[None], H, W)
    rays = generate_rays(cams, 1.0, 2.0)
    _, d, zs = reference_rays(K.numpy(), np.eye(4)[None], H, W)
    np.testing.assert_allclose(rays.directions.numpy(), d, atol=1e-14)
    np.testing.assert_allclose(rays.z_scale.numpy(), zs, rtol=1e-12)
    assert float(rays.z_scale.min()) < 0.1
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(1, H, W, dtype=torch.float64))


def test_view_and_batch_generators_agree_with_full_bundle():
    cams, K, w2c = random_setup(V=4)
    near, far = torch.tensor([0.1, 0.2, 0.3, 0.4]), torch.tensor([1.0, 2.0, 3.0, 4.0])
    full = generate_rays(cams, near, far)
    for v in (0, 2, -1):
        one = generate_rays_for_view(cams, v, near, far)
        assert one.shape == (7, 9)
        for name in ("origins", "directions", "near", "far", "z_scale"):
            torch.testing.assert_close(getattr(one, name), getattr(full[v], name), rtol=0, atol=0)
    views = torch.tensor([3, 0, 1, 3])
    rows, cols = torch.tensor([0, 6, 3, 2]), torch.tensor([8, 0, 4, 1])
    uv = torch.stack([cols + 0.5, rows + 0.5], dim=-1).double()
    batch = generate_rays_at(cams, views, uv, near, far)
    assert batch.shape == (4,)
    for name in ("origins", "directions", "near", "far", "z_scale"):
        torch.testing.assert_close(getattr(batch, name), getattr(full, name)[views, rows, cols], rtol=0, atol=1e-14)
    explicit = generate_rays(cams, near, far, pixels=uv[None].expand(4, -1, -1))
    torch.testing.assert_close(explicit.directions[3], full.directions[3, rows, cols], rtol=0, atol=1e-14)
    with pytest.raises(IndexError):
        generate_rays_for_view(cams, 4, near, far)


def test_rescale_cameras_scales_projections():
    cams, K, w2c = random_setup(H=8, W=10)
    pts = torch.randn(5, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 0.0])
    uv, z = project_points(cams, pts)
    half = rescale_cameras(cams, 0.5)
    uv2, z2 = project_points(half, pts)
    torch.testing.assert_close(uv2, uv * 0.5, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(z2, z)
    assert half.height.tolist() == [4, 4, 4] and half.width.tolist() == [5, 5, 5]


def test_backproject_depths_round_trip():
    cams, K, w2c = random_setup(V=2, H=5, W=6)
    gen = torch.Generator().manual_seed(5)
    depth = 0.5 + 3 * torch.rand(2, 5, 6, generator=gen, dtype=torch.float64)
    depth[0, 1, 2] = 0.0  # no surface: dropped
    pts = backproject_depths(cams, depth)
    assert pts.shape == (2 * 30 - 1, 3)
    uv, z = project_points(select_cameras(cams, [1]), pts[29:])
    np.testing.assert_allclose(z[0].numpy(), depth[1].reshape(-1).numpy(), rtol=1e-12)
    centres = pixel_centres(5, 6, dtype=torch.float64).reshape(-1, 2)
    np.testing.assert_allclose(uv[0].numpy(), centres.numpy(), atol=1e-9)
