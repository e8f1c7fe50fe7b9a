"""COLMAP captures, nerfstudio distortion and SfM-derived bounds (issue 17).

References: a COLMAP model written by hand in COLMAP's text format from the synthetic scene's
exact cameras and depth maps (so poses, visibility and depths are known), the OPENCV distortion
polynomial written out in numpy, and LLFF's percentile rule evaluated in a float64 loop.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import warnings

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from stochastic_fields.cameras import intrinsics_3x3, make_cameras, opencv_w2c_to_opengl_c2w
from stochastic_fields.data import DatasetError, detect_format, load_dataset, read_colmap_model
from stochastic_fields.data.capture import FAR_PERCENTILE, MIN_TRACK_LENGTH, NEAR_PERCENTILE, is_forward_facing
from stochastic_fields.data.colmap import ColmapCamera, pycolmap_camera, undistort_image
from stochastic_fields.data.prepare import CAMERA_MODELS, nerfstudio_intrinsics
from stochastic_fields.sparse_depth import sparse_depth_for_dataset

POINTS_PER_VIEW = 60


def _synthetic_sfm(ds, seed: int = 0):
    """Points back-projected from the depth maps at random pixels, and their true tracks.

    A point's track: every view where it projects inside the image, in front, and its depth agrees
    with that view's depth map to 0.5% (it is the visible surface there). Returns xyz [P, 3],
    tracks (list of [(view, u, v)]).
    """
    rng = np.random.default_rng(seed)
    K = intrinsics_3x3(ds.cameras).double().numpy()
    w2c = ds.cameras.extrinsics.double().numpy()
    depth = ds.depths.double().numpy()
    V, H, W = depth.shape
    xyz = []
    for v in range(V):
        rows, cols = np.nonzero(depth[v] > 0)
        pick = rng.choice(rows.size, POINTS_PER_VIEW, replace=False)
        r, c = rows[pick], cols[pick]
        z = depth[v][r, c]
        cam = np.stack([(c + 0.5 - K[v, 0, 2]) / K[v, 0, 0] * z, (r + 0.5 - K[v, 1, 2]) / K[v, 1, 1] * z, z], -1)
        c2w = np.linalg.inv(w2c[v])
        xyz.append(cam @ c2w[:3, :3].T + c2w[:3, 3])
    xyz = np.concatenate(xyz)
    tracks = []
    for p in xyz:
        track = []
        for v in range(V):
            c = w2c[v, :3, :3] @ p + w2c[v, :3, 3]
            if c[2] <= 0:
                continue
            u, vv = K[v, 0, 0] * c[0] / c[2] + K[v, 0, 2], K[v, 1, 1] * c[1] / c[2] + K[v, 1, 2]
            if not (0 <= u < W and 0 <= vv < H):
                continue
            d = depth[v][int(vv), int(u)]
            if d > 0 and abs(d - c[2]) < 0.005 * c[2]:
                track.append((v, u, vv))
        tracks.append(track)
    return xyz, tracks


def _f(x) -> str:
    """A number as COLMAP's text format wants it (full precision, no numpy repr)."""
    return repr(float(x))


def _write_colmap_text(folder, ds, xyz, tracks, *, camera_line: str | None = None):
    """COLMAP text model (cameras.txt, images.txt, points3D.txt) of the dataset's cameras."""
    folder.mkdir(parents=True, exist_ok=True)
    K = intrinsics_3x3(ds.cameras).double().numpy()[0]
    cam = camera_line or f"1 PINHOLE {ds.width} {ds.height} {_f(K[0, 0])} {_f(K[1, 1])} {_f(K[0, 2])} {_f(K[1, 2])}"
    (folder / "cameras.txt").write_text(f"# cameras\n{cam}\n")
    obs = {v: [] for v in range(ds.num_views)}  # view -> [(u, v, point id)]
    for pid, track in enumerate(tracks, start=1):
        for v, u, vv in track:
            obs[v].append((u, vv, pid))
    lines = ["# images"]
    w2c = ds.cameras.extrinsics.double().numpy()
    index_in_image = {}
    # image ids deliberately not view + 1 (reversed): the loader must match by name
    for v in range(ds.num_views):
        image_id = ds.num_views - v
        qx, qy, qz, qw = Rotation.from_matrix(w2c[v, :3, :3]).as_quat()
        t = w2c[v, :3, 3]
        lines.append(f"{image_id} {_f(qw)} {_f(qx)} {_f(qy)} {_f(qz)} {_f(t[0])} {_f(t[1])} {_f(t[2])} 1 frame_{v:03d}.png")
        lines.append(" ".join(f"{_f(u)} {_f(vv)} {pid}" for u, vv, pid in obs[v]))
        for k, (_, _, pid) in enumerate(obs[v]):
            index_in_image[(pid, v)] = (image_id, k)
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    pts = ["# points"]
    for pid, (p, track) in enumerate(zip(xyz, tracks), start=1):
        elems = " ".join(f"{index_in_image[(pid, v)][0]} {index_in_image[(pid, v)][1]}" for v, _, _ in track)
        pts.append(f"{pid} {_f(p[0])} {_f(p[1])} {_f(p[2])} 128 128 128 0.5 {elems}")
    (folder / "points3D.txt").write_text("\n".join(pts) + "\n")


def _percentile_bounds(ds, xyz, tracks):
    """LLFF's rule in a float64 loop: per view, 0.1/99.9 percentiles of the z of its tracked points
    that at least MIN_TRACK_LENGTH views see."""
    w2c = ds.cameras.extrinsics.double().numpy()
    near, far = [], []
    for v in range(ds.num_views):
        z = [float(w2c[v, 2, :3] @ p + w2c[v, 2, 3]) for p, tr in zip(xyz, tracks)
             if any(t[0] == v for t in tr) and len(tr) >= MIN_TRACK_LENGTH]
        near.append(np.percentile(z, NEAR_PERCENTILE))
        far.append(np.percentile(z, FAR_PERCENTILE))
    return np.array(near), np.array(far)


@pytest.fixture(scope="module")
def colmap_capture(tiny_scene, tmp_path_factory):
    """The tiny synthetic scene as a COLMAP capture: images/ + sparse/0 text model, no other file."""
    ds = load_dataset(tiny_scene)
    xyz, tracks = _synthetic_sfm(ds)
    keep = [i for i, t in enumerate(tracks) if len(t) >= 2]
    xyz, tracks = xyz[keep], [tracks[i] for i in keep]
    root = tmp_path_factory.mktemp("colmap_capture")
    shutil.copytree(tiny_scene / "images", root / "images")
    _write_colmap_text(root / "sparse" / "0", ds, xyz, tracks)
    return root, ds, xyz, tracks


def test_colmap_capture_loads_with_poses_bounds_and_tracks(colmap_capture):
    root, ref, xyz, tracks = colmap_capture
    assert detect_format(root) == "colmap"
    ds = load_dataset(root)
    assert ds.num_views == ref.num_views and ds.bounds_source == "sfm_points"
    torch.testing.assert_close(ds.cameras.extrinsics, ref.cameras.extrinsics.float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(ds.cameras.intrinsics, ref.cameras.intrinsics.float(), atol=1e-4, rtol=0)
    torch.testing.assert_close(ds.images, ref.images)  # pinhole: the photos as they are
    near, far = _percentile_bounds(ref, xyz, tracks)
    np.testing.assert_allclose(ds.near.numpy(), near, rtol=1e-5)
    np.testing.assert_allclose(ds.far.numpy(), far, rtol=1e-5)
    for v in range(ds.num_views):
        expected = [i for i, tr in enumerate(tracks) if any(t[0] == v for t in tr)]
        assert ds.points3d_visible[v].tolist() == expected
    assert not ds.forward_facing  # a ring of cameras around the objects
    # sparse depth through the loader's tracks: each point's own camera-z, and the depth map at its
    # pixel to the 0.5% the tracks were built with (the surface's slope within one pixel)
    sparse = sparse_depth_for_dataset(ds, [1, 7])
    w2c = ref.cameras.extrinsics.double().numpy()
    for v, s in sparse.items():
        assert s.visibility == "tracks" and len(s) > 20
        assert set(s.point_index.tolist()) <= set(ds.points3d_visible[v].tolist())
        np.testing.assert_allclose(s.depth, xyz[s.point_index] @ w2c[v, 2, :3] + w2c[v, 2, 3], rtol=1e-6)
        np.testing.assert_allclose(s.depth, ref.depths[v].double().numpy()[s.rows, s.cols], rtol=0.0051)
    sub = ds.subset([3, 1])
    assert sub.points3d_visible[0].tolist() == ds.points3d_visible[3].tolist()


def test_colmap_reader_matches_hand_written_model(colmap_capture):
    root, ref, xyz, tracks = colmap_capture
    model = read_colmap_model(root / "sparse" / "0")
    assert [im.name for im in model.images] == [f"frame_{v:03d}.png" for v in range(ref.num_views)]
    np.testing.assert_allclose(model.points.xyz, xyz, rtol=0, atol=1e-12)
    assert model.points.track_lengths.tolist() == [len(t) for t in tracks]


def test_photos_without_poses_point_to_prepare(tmp_path, colmap_capture):
    root = colmap_capture[0]
    shutil.copytree(root / "images", tmp_path / "photos")
    with pytest.raises(DatasetError, match=r"photos.*unknown dataset format.*photos holds 20 photos.*stochastic-fields prepare"):
        load_dataset(tmp_path / "photos")
    (tmp_path / "broken" / "sparse" / "0").mkdir(parents=True)
    shutil.copy(root / "sparse" / "0" / "cameras.txt", tmp_path / "broken" / "sparse" / "0")
    from stochastic_fields.data import load_colmap

    with pytest.raises(DatasetError, match=r"broken.*no COLMAP model"):
        load_colmap(tmp_path / "broken")
    with pytest.raises(DatasetError, match=r"0.*incomplete COLMAP model: no images.bin, points3D.bin"):
        read_colmap_model(tmp_path / "broken" / "sparse" / "0")
    # a registered image whose file is missing is named
    shutil.copytree(root, tmp_path / "missing")
    (tmp_path / "missing" / "images" / "frame_004.png").unlink()
    with pytest.raises(DatasetError, match=r"frame_004\.png.*missing image"):
        load_dataset(tmp_path / "missing")


def _opencv_distort(x, y, k1, k2, p1, p2):
    """OpenCV's radial-tangential model on normalised coordinates (written out)."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def test_undistort_image_samples_the_distorted_photo_at_the_model(tmp_path):
    H, W = 60, 80
    fx, fy, cx, cy = 70.0, 72.0, 41.0, 29.5
    k1, k2, p1, p2 = 0.05, -0.01, 0.002, -0.001
    camera = ColmapCamera(1, "OPENCV", W, H, np.array([fx, fy, cx, cy, k1, k2, p1, p2]))

    def photo(u, v):  # a smooth picture in distorted pixel coordinates, 3 channels
        return np.stack([0.5 + 0.4 * np.sin(u / 7.0), 0.5 + 0.4 * np.cos(v / 9.0), 0.5 + 0.3 * np.sin((u + v) / 11.0)], -1)

    vv, uu = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    out, K = undistort_image(photo(uu, vv).astype(np.float32), camera)
    np.testing.assert_allclose(K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    xd, yd = _opencv_distort((uu - cx) / fx, (vv - cy) / fy, k1, k2, p1, p2)
    ud, vd = fx * xd + cx, fy * yd + cy
    inside = (ud > 2) & (ud < W - 2) & (vd > 2) & (vd < H - 2)  # the cubic's taps reach 2 px
    assert inside.mean() > 0.8
    # Keys' cubic with a = -0.75 reproduces linear functions but not quadratics: on these sinusoids
    # its error, measured against the float64 picture, is at most 2.8e-3 (tests/test_llff_distortion.py
    # checks the sampling itself exactly against a float64 loop)
    np.testing.assert_allclose(out[inside], photo(ud, vd)[inside], atol=3.5e-3)
    # and the distortion is not ignored: the undistorted picture differs from the photo
    # (by ten times the tolerance above; measured 0.042)
    assert np.abs(out[inside] - photo(uu, vv)[inside]).max() > 10 * 3.5e-3


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
def test_nerfstudio_intrinsics_describe_the_same_camera(model, tmp_path):
    """Every prepare camera model written as nerfstudio keys and read back projects identically."""
    from stochastic_fields.data.blender import _frame_camera

    import pycolmap

    rng = np.random.default_rng(1)

    cam = pycolmap.Camera.create_from_model_name(1, model, 70.0, 80, 60)
    params = np.asarray(cam.params, dtype=np.float64)
    extra = list(cam.extra_params_idxs())
    params[extra] = rng.uniform(-0.05, 0.05, len(extra))
    original = ColmapCamera(1, model, 80, 60, params)
    keys = nerfstudio_intrinsics(original)
    json_path = tmp_path / "transforms.json"
    back = _frame_camera(json_path, keys, {}, 0, 60, 80)
    rays = np.concatenate([rng.uniform(-0.5, 0.5, (50, 2)), np.ones((50, 1))], axis=1)
    a = pycolmap_camera(original).img_from_cam(rays)
    b = pycolmap_camera(back).img_from_cam(rays)
    np.testing.assert_allclose(b, a, atol=1e-9)


def _nerfstudio_json(root, ds, **extra):
    K = intrinsics_3x3(ds.cameras).double().numpy()[0]
    c2w = opencv_w2c_to_opengl_c2w(ds.cameras.extrinsics.double()).numpy()
    meta = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
            "w": ds.width, "h": ds.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": [{"file_path": f"images/frame_{v:03d}.png", "transform_matrix": c2w[v].tolist()}
                       for v in range(ds.num_views)]}
    meta.update(extra)
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def test_nerfstudio_distortion_is_undistorted_not_refused(colmap_capture, tmp_path):
    src, ref, _, _ = colmap_capture
    root = tmp_path / "ns"
    shutil.copytree(src, root)
    meta = _nerfstudio_json(root, ref, k1=0.02)
    ds = load_dataset(root)
    camera = ColmapCamera(0, "OPENCV", ref.width, ref.height,
                          np.array([meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], 0.02, 0.0, 0.0, 0.0]))
    expected, _ = undistort_image(ref.images[2].numpy(), camera)
    np.testing.assert_allclose(ds.images[2].numpy(), expected, atol=1e-6)
    torch.testing.assert_close(ds.cameras.intrinsics, ref.cameras.intrinsics.float(), atol=1e-4, rtol=0)
    # a per-frame override wins over the top level
    meta["frames"][1]["k1"] = 0.0
    (root / "transforms.json").write_text(json.dumps(meta))
    torch.testing.assert_close(load_dataset(root).images[1], ref.images[1])
    for bad, match in (({"k4": 0.1}, r"transforms\.json.*frame 0.*k4"),
                       ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, r"transforms\.json.*OPENCV_FISHEYE.*tangential"),
                       ({"camera_model": "EQUIRECTANGULAR"}, r"transforms\.json.*EQUIRECTANGULAR.*not supported"),
                       ({"k1": "x"}, r"transforms\.json.*k1='x'")):
        _nerfstudio_json(root, ref, **bad)
        with pytest.raises(DatasetError, match=match):
            load_dataset(root)


def test_nerfstudio_bounds_come_from_the_sfm_points(colmap_capture, tmp_path):
    src, ref, xyz, tracks = colmap_capture
    near, far = _percentile_bounds(ref, xyz, tracks)
    # ns-process-data's layout: colmap/sparse/0, poses and points moved by applied_transform
    root = tmp_path / "ns"
    (root / "colmap").mkdir(parents=True)
    shutil.copytree(src / "images", root / "images")
    shutil.copytree(src / "sparse", root / "colmap" / "sparse")
    A = np.eye(4)
    A[:3, :3] = Rotation.from_euler("xyz", [90, 0, 180], degrees=True).as_matrix()
    A[:3, 3] = [1.0, -2.0, 0.5]
    w2c_moved = ref.cameras.extrinsics.double() @ torch.from_numpy(np.linalg.inv(A))  # world' = A world
    moved = dataclasses.replace(ref, cameras=make_cameras(ref.cameras.intrinsics[:, :3, :3].double(), w2c_moved,
                                                          ref.height, ref.width))
    _nerfstudio_json(root, moved, applied_transform=A[:3].tolist())
    ds = load_dataset(root)
    assert ds.bounds_source == "sfm_points"
    np.testing.assert_allclose(ds.near.numpy(), near, rtol=1e-4)
    np.testing.assert_allclose(ds.far.numpy(), far, rtol=1e-4)
    np.testing.assert_allclose(ds.points3d.double().numpy(), xyz @ A[:3, :3].T + A[:3, 3], atol=1e-5)
    assert [len(v) for v in ds.points3d_visible] == [sum(any(t[0] == v for t in tr) for tr in tracks)
                                                      for v in range(ref.num_views)]

    # only a ply_file_path (no tracks): bounds from the points that project into each view
    from stochastic_fields.data.prepare import write_points_ply

    root2 = tmp_path / "ply"
    shutil.copytree(src / "images", root2 / "images")
    write_points_ply(root2 / "sparse_pc.ply", xyz, np.full((len(xyz), 3), 200, np.uint8))
    _nerfstudio_json(root2, ref, ply_file_path="sparse_pc.ply")
    ds2 = load_dataset(root2)
    assert ds2.bounds_source == "sfm_points" and ds2.points3d_visible is None
    w2c = ref.cameras.extrinsics.double().numpy()
    K = intrinsics_3x3(ref.cameras).double().numpy()
    for v in (0, 9):
        cam = xyz @ w2c[v, :3, :3].T + w2c[v, :3, 3]
        u = K[v, 0, 0] * cam[:, 0] / cam[:, 2] + K[v, 0, 2]
        vv = K[v, 1, 1] * cam[:, 1] / cam[:, 2] + K[v, 1, 2]
        z = cam[(cam[:, 2] > 0) & (u >= 0) & (u < ref.width) & (vv >= 0) & (vv < ref.height), 2]
        assert ds2.near[v].item() == pytest.approx(np.percentile(z, NEAR_PERCENTILE), rel=1e-5)
        assert ds2.far[v].item() == pytest.approx(np.percentile(z, FAR_PERCENTILE), rel=1e-5)
    assert sparse_depth_for_dataset(ds2, [1])[1].visibility == "zbuffer"

    # neither near/far nor points: the loader says it guesses
    root3 = tmp_path / "none"
    shutil.copytree(src / "images", root3 / "images")
    _nerfstudio_json(root3, ref)
    with pytest.warns(UserWarning, match=r"transforms\.json.*guessing the Blender bounds near=2, far=6"):
        ds3 = load_dataset(root3)
    assert ds3.bounds_source == "default"
    _nerfstudio_json(root3, ref, near=0.5, far=9.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_dataset(root3).near.tolist() == [0.5] * ref.num_views


def test_forward_facing_test_on_llff_and_ring(shared_data, colmap_capture):
    fern = load_dataset(shared_data / "nerf_llff_data" / "fern", images=16, load_points=False)
    assert is_forward_facing(fern.cameras)
    assert not is_forward_facing(colmap_capture[1].cameras)


def test_capture_points_of_a_colmap_capture_use_its_tracks(colmap_capture):
    """The uncertainty tools read the loader's own SfM points and tracks (image ids need not be
    view + 1): each view's FIT/CALIBRATE/SCORE sparse depth is the tracked points of that role."""
    from stochastic_fields.capture_points import FIT, SCORE, load_capture_points, sparse_depth_for_role

    ds = load_dataset(colmap_capture[0])
    pts = load_capture_points(ds)
    assert pts.source == "colmap" and len(pts.xyz) == len(ds.points3d)
    for role in (FIT, SCORE):
        per_view = sparse_depth_for_role(ds, pts, ds.train_indices, role)
        for v, sd in per_view.items():
            assert len(sd) > 0
            assert set(sd.point_index) <= set(ds.points3d_visible[v])
            assert (pts.roles[sd.point_index] == role).all()
