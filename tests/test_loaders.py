"""Loaders: real LLFF/Blender data (conventions checked with COLMAP points), the COLMAP reader
against hand-packed files, and DatasetError on broken copies written into tmp_path."""

from __future__ import annotations

import json
import math
import struct

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from stochastic_fields.cameras import in_image, make_cameras, project_points
from stochastic_fields.data import (
    DatasetError,
    SceneDataset,
    detect_format,
    fit_scene_aabb,
    pad_box,
    load_blender,
    load_dataset,
    load_llff,
    read_cameras_binary,
    read_points3d_binary,
)


# ------------------------------------------------------------------ COLMAP reader
def _write_points(path, points):
    """Hand-pack points3D.bin following the documented layout."""
    buf = struct.pack("<Q", len(points))
    for pid, xyz, rgb, err, track in points:
        buf += struct.pack("<Q3d3Bd", pid, *xyz, *rgb, err) + struct.pack("<Q", len(track))
        for image_id, idx in track:
            buf += struct.pack("<ii", image_id, idx)
    path.write_bytes(buf)


def test_colmap_reader_hand_packed(tmp_path):
    pts = [
        (7, (1.0, -2.0, 3.5), (10, 20, 30), 0.25, [(1, 4), (3, 9)]),
        (9, (0.0, 0.5, -1e6), (255, 0, 128), 1.5, []),
        (11, (2.0, 2.0, 2.0), (1, 2, 3), 0.0, [(2, 0), (5, 1), (8, 77)]),
    ]
    _write_points(tmp_path / "points3D.bin", pts)
    out = read_points3d_binary(tmp_path / "points3D.bin")
    assert len(out) == 3
    np.testing.assert_array_equal(out.ids, [7, 9, 11])
    np.testing.assert_array_equal(out.xyz, [p[1] for p in pts])
    np.testing.assert_array_equal(out.rgb, [p[2] for p in pts])
    np.testing.assert_array_equal(out.error, [0.25, 1.5, 0.0])
    np.testing.assert_array_equal(out.track_lengths, [2, 0, 3])
    np.testing.assert_array_equal(out.track_image_ids, [1, 3, 2, 5, 8])
    np.testing.assert_array_equal(out.track_point2d_idx, [4, 9, 0, 1, 77])

    cams = struct.pack("<Q", 2) + struct.pack("<iiQQ4d", 1, 1, 640, 480, 500.0, 510.0, 320.0, 240.0)
    cams += struct.pack("<iiQQ3d", 2, 0, 100, 50, 80.0, 50.0, 25.0)
    (tmp_path / "cameras.bin").write_bytes(cams)
    c = read_cameras_binary(tmp_path / "cameras.bin")
    assert c[1].model == "PINHOLE" and (c[1].width, c[1].height) == (640, 480)
    np.testing.assert_array_equal(c[1].params, [500.0, 510.0, 320.0, 240.0])
    assert c[2].model == "SIMPLE_PINHOLE" and c[2].params.tolist() == [80.0, 50.0, 25.0]

    (tmp_path / "short.bin").write_bytes((tmp_path / "points3D.bin").read_bytes()[:-5])
    with pytest.raises(DatasetError, match="short.bin"):
        read_points3d_binary(tmp_path / "short.bin")
    with pytest.raises(DatasetError, match="missing.bin"):
        read_cameras_binary(tmp_path / "missing.bin")


# ------------------------------------------------------------------ LLFF fern
@pytest.fixture(scope="module")
def fern(shared_data):
    return load_llff(shared_data / "nerf_llff_data" / "fern", images="images_8")


@pytest.mark.parametrize("images,shape", [("images_8", (378, 504)), (16, (189, 252))])
def test_fern_loads(shared_data, images, shape):
    ds = load_dataset(shared_data / "nerf_llff_data" / "fern", images=images)
    H, W = shape
    assert isinstance(ds, SceneDataset) and ds.forward_facing
    assert ds.images.shape == (20, H, W, 3) and ds.images.dtype == torch.float32
    assert 0.0 <= float(ds.images.min()) and float(ds.images.max()) <= 1.0
    assert ds.train_indices == [0, 5, 10, 15]
    assert ds.test_indices == [i for i in range(20) if i % 5]
    raw = np.load(shared_data / "nerf_llff_data" / "fern" / "poses_bounds.npy")
    np.testing.assert_allclose(ds.near.numpy(), raw[:, 15], rtol=1e-6)
    np.testing.assert_allclose(ds.far.numpy(), raw[:, 16], rtol=1e-6)
    f = raw[0, 14] * W / raw[0, 9]  # focal of the 4032-wide originals, scaled
    np.testing.assert_allclose(ds.cameras.fx.numpy(), f, rtol=1e-6)
    np.testing.assert_allclose(ds.cameras.cx.numpy(), W / 2)
    np.testing.assert_allclose(ds.cameras.cy.numpy(), H / 2)
    assert ds.points3d is not None and ds.points3d.shape[1] == 3
    assert ds.aabb.shape == (2, 3) and bool(torch.all(ds.aabb[1] > ds.aabb[0]))


def test_fern_colmap_camera_matches_poses(shared_data):
    cams = read_cameras_binary(shared_data / "nerf_llff_data" / "fern" / "sparse" / "0" / "cameras.bin")
    raw = np.load(shared_data / "nerf_llff_data" / "fern" / "poses_bounds.npy")
    (cam,) = cams.values()
    assert (cam.height, cam.width) == (raw[0, 4], raw[0, 9])
    np.testing.assert_allclose(cam.params[0], raw[0, 14], rtol=1e-6)  # same focal
    np.testing.assert_allclose(cam.params[1:3], [cam.width / 2, cam.height / 2])  # half-pixel centred


def _colour_errors(ds: SceneDataset, cams, shift=(0, 0)):
    """Median |image colour at projected pixel - COLMAP rgb| per view, and a shuffled baseline."""
    uv, z = project_points(cams, ds.points3d)
    vis = in_image(cams, uv, z)
    gen = torch.Generator().manual_seed(0)
    errs, shuffled = [], []
    for v in range(ds.num_views):
        px = uv[v][vis[v]].floor().long() + torch.tensor(shift)
        px[:, 0] = px[:, 0].clamp(0, ds.width - 1)
        px[:, 1] = px[:, 1].clamp(0, ds.height - 1)
        colour = ds.images[v][px[:, 1], px[:, 0]]
        ref = ds.points3d_rgb[vis[v]]
        errs.append(float((colour - ref).abs().mean(-1).median()))
        perm = torch.randperm(len(ref), generator=gen)
        shuffled.append(float((colour - ref[perm]).abs().mean(-1).median()))
    return np.array(errs), np.array(shuffled)


def test_fern_conventions_with_colmap_points(fern):
    """The real check of docs/definitions.md §1: COLMAP points land in frame, in front, between
    near/far, on the right pixels."""
    uv, z = project_points(fern.cameras, fern.points3d)
    assert float((z > 0).float().mean()) > 0.9
    assert float(in_image(fern.cameras, uv, z).float().mean(1).min()) > 0.9
    median_z = z.median(dim=1).values
    assert bool(torch.all((median_z > fern.near) & (median_z < fern.far))), (median_z, fern.near, fern.far)
    errs, shuffled = _colour_errors(fern, fern.cameras)
    assert np.all(errs < 0.5 * shuffled), (errs, shuffled)
    # a few pixels off is measurably worse: the projection hits the right pixels, not just the frame
    off, _ = _colour_errors(fern, fern.cameras, shift=(5, 5))
    assert np.all(errs < off), (errs, off)
    # the fitted scene box holds the bulk of the sparse points
    inside = torch.all((fern.points3d >= fern.aabb[0]) & (fern.points3d <= fern.aabb[1]), dim=1)
    assert float(inside.float().mean()) > 0.95


def test_fern_check_fails_with_wrong_axes(fern):
    """Negative control: reading LLFF columns as [right, down, back] puts the points elsewhere."""
    raw = np.load(fern.root / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    c2w = np.tile(np.eye(4), (20, 1, 1))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = raw[:, :, 0], raw[:, :, 1], -raw[:, :, 2], raw[:, :, 3]
    wrong = make_cameras(fern.cameras.intrinsics[:, :3, :3], torch.from_numpy(np.linalg.inv(c2w)).float(),
                         fern.height, fern.width)
    errs, _ = _colour_errors(fern, fern.cameras)
    uv, z = project_points(wrong, fern.points3d)
    frac = float(in_image(wrong, uv, z).float().mean())
    if frac > 0.5:  # if many still land in frame, their colours must disagree
        werrs, _ = _colour_errors(fern, wrong)
        assert np.median(werrs) > 1.5 * np.median(errs)


# ------------------------------------------------------------------ Blender lego
def test_lego_train_json_downscaled(shared_data):
    path = shared_data / "nerf_synthetic" / "lego" / "transforms_train.json"
    ds = load_dataset(path, downscale=8, frame_stride=10)
    meta = json.loads(path.read_text())
    assert ds.images.shape == (10, 100, 100, 3)
    assert ds.background == (1.0, 1.0, 1.0)
    assert ds.train_indices == [0, 5] and len(ds.test_indices) == 8
    f = 0.5 * 100 / math.tan(0.5 * meta["camera_angle_x"])
    np.testing.assert_allclose(ds.cameras.fx.numpy(), f, rtol=1e-6)
    # OpenGL -> OpenCV: every camera looks at the scene origin, which projects to the image centre
    uv, z = project_points(ds.cameras, torch.zeros(1, 3))
    assert bool(torch.all(z > 0))
    np.testing.assert_allclose(uv[:, 0].numpy(), 50.0, atol=1.0)
    # the centre camera ray distance matches the json's camera position
    centres = np.array([f_["transform_matrix"] for f_ in meta["frames"][::10]])[:, :3, 3]
    np.testing.assert_allclose(z[:, 0].numpy(), np.linalg.norm(centres, axis=1), rtol=1e-3)
    # composited on white: the corners of every view are background
    np.testing.assert_allclose(ds.images[:, 0, 0].numpy(), 1.0, atol=1e-6)
    # the object-centric box holds the origin and stays well inside the cameras' ring
    assert bool(torch.all(ds.aabb[0] < 0) and torch.all(ds.aabb[1] > 0))
    assert float(ds.aabb.abs().max()) < 3.0


def test_lego_folder_uses_split_files(shared_data):
    ds = load_blender(shared_data / "nerf_synthetic" / "lego", downscale=16, frame_stride=25)
    assert ds.images.shape == (4 + 1, 50, 50, 3)
    assert ds.train_indices == [0, 1, 2, 3] and ds.test_indices == [4]
    assert detect_format(shared_data / "nerf_synthetic" / "lego") == "blender"
    assert detect_format(shared_data / "nerf_llff_data" / "fern") == "llff"


# ------------------------------------------------------------------ SceneDataset
def test_dataset_subset_split_and_rays(tiny_scene):
    ds = load_dataset(tiny_scene)
    assert ds.train_indices == [0, 5, 10, 15]
    sub = ds.subset([5, 6, 0])
    assert sub.num_views == 3 and sub.train_indices == [0, 2] and sub.test_indices == [1]
    torch.testing.assert_close(sub.images[1], ds.images[6])
    torch.testing.assert_close(sub.cameras.extrinsics[2], ds.cameras.extrinsics[0])
    assert sub.depths is not None and torch.equal(sub.depths[0], ds.depths[5])
    assert sub.image_paths[0] == ds.image_paths[5]
    tr = ds.train()
    assert tr.num_views == 4 and tr.test_indices == [] and tr.train_indices == [0, 1, 2, 3]
    re = ds.split_every(4)
    assert re.train_indices == [0, 4, 8, 12, 16]
    with pytest.raises(DatasetError, match="no test view"):
        ds.split_every(1)
    rays = ds.rays(3)
    assert rays.shape == (ds.height, ds.width)
    torch.testing.assert_close(rays.near * rays.z_scale, ds.near[3].expand(ds.height, ds.width))


def test_fit_scene_aabb_modes(tiny_scene):
    ds = load_dataset(tiny_scene)
    pts = torch.tensor([[0.0, 0, 0.3]]) + 0.1 * torch.randn(1000, 3, generator=torch.Generator().manual_seed(0))
    pts[:5] = torch.tensor([50.0, 50.0, 50.0])  # outliers (0.5%) the percentiles must ignore
    box = fit_scene_aabb(ds.cameras, ds.near, ds.far, pts)
    assert float((box[1] - box[0]).max()) < 1.0
    assert bool(torch.all(box[0] < torch.tensor([0.0, 0, 0.3])) and torch.all(box[1] > torch.tensor([0.0, 0, 0.3])))
    covis = fit_scene_aabb(ds.cameras, ds.near, ds.far)  # no points: region most views see
    frusta = fit_scene_aabb(ds.cameras, ds.near, ds.far, forward_facing=True)
    assert bool(torch.all(covis[0] >= frusta[0]) and torch.all(covis[1] <= frusta[1]))
    assert float((covis[1] - covis[0]).prod()) < 0.5 * float((frusta[1] - frusta[0]).prod())
    objects = torch.tensor([[-1.1, -1.1, 0.0], [1.1, 1.1, 0.8]])  # the solids of the scene
    assert bool(torch.all(covis[0] <= objects[0]) and torch.all(covis[1] >= objects[1]))
    with pytest.raises(ValueError, match="far > near"):
        fit_scene_aabb(ds.cameras, 2.0, 1.0)


def test_pad_box_hand_values():
    lo, hi = torch.tensor([-2.0, -1.0, 0.0]), torch.tensor([2.0, 1.0, 0.5])
    torch.testing.assert_close(pad_box(lo, hi, 0.05), torch.tensor([[-2.2, -1.2, -0.2], [2.2, 1.2, 0.7]]))
    torch.testing.assert_close(pad_box(lo, hi, 0.05, isotropic=False),
                               torch.tensor([[-2.2, -1.1, -0.025], [2.2, 1.1, 0.525]]))


def test_object_box_keeps_a_floor_inside(tiny_scene):
    """A floor of points at z = 0 (2 x 2) under a small object (0.4 high): the object-centric box
    pads z by 5% of the largest extent (0.1), the forward-facing box by 5% of z's own (0.02)."""
    ds = load_dataset(tiny_scene)
    g = torch.Generator().manual_seed(0)
    floor = torch.rand(800, 3, generator=g) * torch.tensor([2.0, 2.0, 0.0]) - torch.tensor([1.0, 1.0, 0.0])
    floor[:2, :2] = torch.tensor([[-1.0, -1.0], [1.0, 1.0]])  # the floor's corners: x and y span exactly 2
    thing = torch.rand(200, 3, generator=g) * torch.tensor([0.5, 0.5, 0.4])
    thing[0, 2] = 0.4
    pts = torch.cat([floor, thing])
    frusta = fit_scene_aabb(ds.cameras, ds.near, ds.far, forward_facing=True)
    assert float(frusta[0, 2]) < -0.1 and float(frusta[1, 2]) > 0.5  # the clip leaves these boxes whole
    box = fit_scene_aabb(ds.cameras, ds.near, ds.far, pts, percentiles=(0.0, 100.0))
    torch.testing.assert_close(box, torch.tensor([[-1.1, -1.1, -0.1], [1.1, 1.1, 0.5]]), atol=1e-6, rtol=0)
    forward = fit_scene_aabb(ds.cameras, ds.near, ds.far, pts, percentiles=(0.0, 100.0), forward_facing=True)
    torch.testing.assert_close(forward[:, 2], torch.tensor([-0.02, 0.42]), atol=1e-6, rtol=0)


# ------------------------------------------------------------------ broken inputs
def _write_llff(root, n_views=3, n_images=None, H=6, W=8, poses=None):
    """A tiny valid LLFF scene (random images) unless told otherwise."""
    (root / "images_8").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n_views if n_images is None else n_images):
        iio.imwrite(root / "images_8" / f"image{i:03d}.png", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    if poses is None:
        poses = np.zeros((n_views, 17))
        for i in range(n_views):
            pose = np.zeros((3, 5))
            pose[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]  # down=y, right=x, back=-z
            pose[:, 3] = [0.1 * i, 0, 0]
            pose[:, 4] = [H * 8, W * 8, 40.0]
            poses[i, :15] = pose.ravel()
            poses[i, 15:] = [1.0, 10.0]
    np.save(root / "poses_bounds.npy", poses)
    return root


def test_llff_tiny_valid_scene(tmp_path):
    ds = load_dataset(_write_llff(tmp_path / "ok", n_views=6), split_every=3)
    assert ds.images.shape == (6, 6, 8, 3) and ds.train_indices == [0, 3]
    np.testing.assert_allclose(ds.cameras.fx.numpy(), 40.0 / 8)


def test_llff_errors_name_the_file(tmp_path):
    root = _write_llff(tmp_path / "count", n_views=3, n_images=2)
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*3 poses but 2 images"):
        load_llff(root)

    root = _write_llff(tmp_path / "nan")
    arr = np.load(root / "poses_bounds.npy")
    arr[1, 3] = np.nan
    np.save(root / "poses_bounds.npy", arr)
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*NaN.*\[1\]"):
        load_llff(root)

    root = _write_llff(tmp_path / "bounds")
    arr = np.load(root / "poses_bounds.npy")
    arr[2, 15:] = [5.0, 5.0]
    np.save(root / "poses_bounds.npy", arr)
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*near < far.*row 2"):
        load_llff(root)

    root = _write_llff(tmp_path / "shape", poses=np.zeros((3, 15)))
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*shape \[V, 17\]"):
        load_llff(root)

    root = _write_llff(tmp_path / "split", n_views=3)
    assert load_llff(root, split_every=5).test_indices == [1, 2]
    with pytest.raises(DatasetError, match=r"poses_bounds\.npy.*no test view"):
        load_llff(root, split_every=1)


def test_llff_unreadable_and_missing_images(tmp_path):
    root = _write_llff(tmp_path / "bad")
    (root / "images_8" / "image001.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"image001\.png.*unreadable"):
        load_llff(root)
    root = _write_llff(tmp_path / "nofolder")
    with pytest.raises(DatasetError, match=r"images_16.*missing image folder"):
        load_llff(root, images=16)
    with pytest.raises(DatasetError, match="unknown dataset format"):
        load_dataset(tmp_path)


def _write_blender(root, frames=2, H=4, W=5):
    (root / "train").mkdir(parents=True, exist_ok=True)
    meta = {"camera_angle_x": 0.8, "frames": []}
    for i in range(frames):
        rgba = np.full((H, W, 4), 255, dtype=np.uint8)
        rgba[..., 3] = 0  # fully transparent -> white after compositing
        iio.imwrite(root / "train" / f"r_{i}.png", rgba)
        c2w = np.eye(4)
        c2w[2, 3] = 4.0 + i
        meta["frames"].append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
    (root / "transforms.json").write_text(json.dumps(meta))
    return root, meta


def test_blender_errors_name_the_file(tmp_path):
    root, meta = _write_blender(tmp_path / "ok", frames=3)
    ds = load_dataset(root, split_every=2)
    assert ds.images.shape == (3, 4, 5, 3) and torch.all(ds.images == 1.0)
    assert ds.near.tolist() == [2.0] * 3  # Blender default bounds without hints

    (root / "train" / "r_1.png").unlink()
    with pytest.raises(DatasetError, match=r"r_1.*missing image"):
        load_dataset(root)

    root, meta = _write_blender(tmp_path / "nan")
    meta["frames"][1]["transform_matrix"][0][3] = float("nan")
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json.*frame 1.*NaN"):
        load_dataset(root)

    root, meta = _write_blender(tmp_path / "shape")
    meta["frames"][0]["transform_matrix"] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json.*frame 0.*4x4"):
        load_dataset(root)

    root, meta = _write_blender(tmp_path / "bounds")
    meta.update(near=3.0, far=3.0)
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"transforms\.json.*near < far"):
        load_dataset(root)

    root, meta = _write_blender(tmp_path / "split", frames=2)
    with pytest.raises(DatasetError, match=r"transforms\.json.*no test view"):
        load_dataset(root, split_every=1)

    root, meta = _write_blender(tmp_path / "depth")
    for i, fr in enumerate(meta["frames"]):
        np.save(root / f"d{i}.npy", np.ones((3, 3), np.float32))
        fr["depth_file_path"] = f"d{i}.npy"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"d0\.npy.*depth map shape"):
        load_dataset(root)
