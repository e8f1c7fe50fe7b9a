"""LLFF captures with lens distortion: the loader undistorts the images to the pinhole camera of
poses_bounds.npy using the COLMAP camera of ``sparse/0/cameras.bin`` (data/llff.py, module doc).

* A synthetic LLFF folder with a known SIMPLE_RADIAL camera: the loaded images equal a float64
  loop (the radial model by hand, Keys' bicubic by hand), the intrinsics stay LLFF's, a COLMAP
  camera that disagrees with poses_bounds.npy is refused naming cameras.bin.
* Real fern: the loader reports the distortion, and the SfM points land on the undistorted images
  better than on the distorted ones (colour at the projections, and the radial term that best
  explains where the points show).
"""

from __future__ import annotations

import math
import struct
import warnings

import imageio.v3 as iio
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from stochastic_fields.cameras import project_points, select_cameras
from stochastic_fields.data import DatasetError, load_llff, read_points3d_binary
from stochastic_fields.sparse_depth import track_visibility

# full-resolution camera of the synthetic capture; images_2 holds the photos at half size
FULL_W, FULL_H, FULL_F, K1 = 96, 72, 80.0, 0.08
SIMPLE_RADIAL_ID = 2


def _write_cameras(path, cameras):
    """Hand-pack cameras.bin: [(camera_id, model_id, width, height, params)]."""
    buf = struct.pack("<Q", len(cameras))
    for cid, model, w, h, params in cameras:
        buf += struct.pack(f"<iiQQ{len(params)}d", cid, model, w, h, *params)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf)


def _distorted_llff(root, *, n_views=3, focal_json=FULL_F, cameras=None):
    """LLFF folder: random images_2 photos (48x36), poses with hwf (72, 96, focal_json), and a
    SIMPLE_RADIAL cameras.bin (f 80, centre 48, 36, k1 0.08) at full resolution."""
    rng = np.random.default_rng(1)
    (root / "images_2").mkdir(parents=True)
    for i in range(n_views):
        iio.imwrite(root / "images_2" / f"image{i:03d}.png",
                    rng.integers(0, 256, (FULL_H // 2, FULL_W // 2, 3), dtype=np.uint8))
    poses = np.zeros((n_views, 17))
    for i in range(n_views):
        pose = np.zeros((3, 5))
        pose[:, :3] = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]
        pose[:, 3] = [0.1 * i, 0, 0]
        pose[:, 4] = [FULL_H, FULL_W, focal_json]
        poses[i, :15] = pose.ravel()
        poses[i, 15:] = [1.0, 10.0]
    np.save(root / "poses_bounds.npy", poses)
    if cameras is None:
        cameras = [(1, SIMPLE_RADIAL_ID, FULL_W, FULL_H, (FULL_F, FULL_W / 2, FULL_H / 2, K1))]
    _write_cameras(root / "sparse" / "0" / "cameras.bin", cameras)
    return root


def _keys(t: float, a: float = -0.75) -> float:
    """Keys' cubic convolution kernel (torch's and OpenCV's bicubic, a = -0.75)."""
    t = abs(t)
    if t <= 1:
        return (a + 2) * t ** 3 - (a + 3) * t ** 2 + 1
    if t < 2:
        return a * t ** 3 - 5 * a * t ** 2 + 8 * a * t - 4 * a
    return 0.0


def _reference_undistortion(photo: np.ndarray, f: float, cx: float, cy: float, k1: float):
    """Float64 loop: every pinhole pixel centre (u, v) -> normalised (x, y) -> SIMPLE_RADIAL
    ``(x, y) (1 + k1 r^2)`` -> distorted pixel -> bicubic sample (taps clamped to the photo),
    clipped to the photo's value range. Returns (image [H, W, 3], largest shift in pixels)."""
    H, W = photo.shape[:2]
    out = np.zeros_like(photo)
    shift = 0.0
    for i in range(H):
        for j in range(W):
            u, v = j + 0.5, i + 0.5
            x, y = (u - cx) / f, (v - cy) / f
            radial = 1.0 + k1 * (x * x + y * y)
            ud, vd = f * x * radial + cx, f * y * radial + cy
            shift = max(shift, math.hypot(ud - u, vd - v))
            sx, sy = ud - 0.5, vd - 0.5  # pixel-index coordinates
            x0, y0 = math.floor(sx), math.floor(sy)
            acc = np.zeros(3)
            for dy in range(-1, 3):
                wy = _keys(sy - (y0 + dy))
                yy = min(max(y0 + dy, 0), H - 1)
                for dx in range(-1, 3):
                    xx = min(max(x0 + dx, 0), W - 1)
                    acc += wy * _keys(sx - (x0 + dx)) * photo[yy, xx]
            out[i, j] = acc
    return np.clip(out, photo.min(), photo.max()), shift


def test_distorted_llff_images_equal_the_reference_undistortion(tmp_path):
    root = _distorted_llff(tmp_path / "scene")
    with pytest.warns(UserWarning, match=r"cameras\.bin: SIMPLE_RADIAL lens distortion.*images undistorted"):
        ds = load_llff(root, images=2)
    raw = load_llff(root, images=2, undistort=False)
    f, cx, cy = FULL_F / 2, FULL_W / 4, FULL_H / 4  # the camera at the loaded 48x36
    # the intrinsics are LLFF's (poses_bounds.npy's focal scaled, centred), undistorted or not
    for d in (ds, raw):
        np.testing.assert_allclose(d.cameras.fx.numpy(), f)
        np.testing.assert_allclose(d.cameras.cx.numpy(), cx)
        np.testing.assert_allclose(d.cameras.cy.numpy(), cy)
    assert ds.images.shape == raw.images.shape == (3, 36, 48, 3)
    for v in range(3):
        photo = iio.imread(root / "images_2" / f"image{v:03d}.png").astype(np.float64) / 255.0
        np.testing.assert_array_equal(raw.images[v].numpy(), photo.astype(np.float32))
        expected, shift = _reference_undistortion(photo, f, cx, cy, K1)
        np.testing.assert_allclose(ds.images[v].numpy(), expected, atol=1e-4)
    # the distortion is not a no-op here: the corner pixel centre (0.5, 0.5) is at r^2 =
    # (23.5^2 + 17.5^2) / 40^2 and moves by k1 r^3 f = 0.08 * r^3 * 40 = 1.2577 px
    assert shift == pytest.approx(0.08 * ((23.5 ** 2 + 17.5 ** 2) / 40 ** 2) ** 1.5 * 40, rel=1e-9)
    assert float((ds.images - raw.images).abs().mean()) > 0.05
    lens = ds.lens
    assert lens["model"] == "SIMPLE_RADIAL" and lens["undistorted"] and not raw.lens["undistorted"]
    np.testing.assert_allclose(lens["params"], [f, cx, cy, K1])  # focal and centre rescaled, k1 kept
    assert lens["max_shift_px"] == pytest.approx(shift, abs=1e-4)
    assert (lens["width"], lens["height"]) == (48, 36) and 0.0 < lens["border_fraction"] < 0.2
    # views and splits carry the report
    assert ds.test().lens == lens


def test_llff_without_distortion_is_left_alone(tmp_path):
    root = _distorted_llff(tmp_path / "pinhole",
                           cameras=[(1, 1, FULL_W, FULL_H, (FULL_F, FULL_F, FULL_W / 2, FULL_H / 2))])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = load_llff(root, images=2)
    assert ds.lens is None
    photo = iio.imread(root / "images_2" / "image000.png").astype(np.float32) / 255.0
    np.testing.assert_array_equal(ds.images[0].numpy(), photo)


def test_colmap_camera_that_disagrees_with_poses_bounds_is_refused(tmp_path):
    root = _distorted_llff(tmp_path / "other_focal", focal_json=FULL_F * 1.05)
    with pytest.raises(DatasetError, match=r"cameras\.bin.*disagrees with poses_bounds\.npy.*undistort=False"):
        load_llff(root, images=2)
    with pytest.warns(UserWarning, match="left distorted"):
        ds = load_llff(root, images=2, undistort=False)
    assert ds.lens["model"] == "SIMPLE_RADIAL" and not ds.lens["undistorted"]

    cams = [(1, SIMPLE_RADIAL_ID, FULL_W, FULL_H, (FULL_F, FULL_W / 2, FULL_H / 2, K1)),
            (2, SIMPLE_RADIAL_ID, FULL_W, FULL_H, (FULL_F, FULL_W / 2, FULL_H / 2, -K1))]
    root = _distorted_llff(tmp_path / "two_cameras", cameras=cams)
    with pytest.warns(UserWarning, match=r"cameras\.bin: 2 different cameras.*left in the images"):
        ds = load_llff(root, images=2)
    assert ds.lens is None


def test_undistort_option_is_checked_and_llff_only(tmp_path, tiny_scene):
    from stochastic_fields import config as C
    from stochastic_fields.scenes import load_run_dataset

    with pytest.raises(ValueError, match="undistort"):
        C.DataConfig(undistort="yes")
    cfg = C.ExperimentConfig()
    cfg.data.path = str(tiny_scene)
    cfg.data.undistort = False
    with pytest.raises(ValueError, match=r"data\.undistort=false applies to LLFF scenes"):
        load_run_dataset(cfg, tmp_path)
    root = _distorted_llff(tmp_path / "llff")
    cfg.data.path, cfg.data.images = str(root), "images_2"
    with pytest.warns(UserWarning, match="left distorted"):
        assert not load_run_dataset(cfg, tmp_path).lens["undistorted"]


# ------------------------------------------------------------------ real fern
#: Mean |image colour - COLMAP point colour| over fern's 41054 track observations, colour read
#: bilinearly at the pinhole projection (measured with this loader, images_8).
FERN_COLOUR_ERROR_UNDISTORTED = 0.0971
FERN_COLOUR_ERROR_DISTORTED = 0.1209
#: Radial terms tried when asking which one best explains where the points show.
RADIAL_GRID = np.round(np.arange(-0.01, 0.0351, 0.0025), 4)


def _fern_observations(ds, points):
    """Per view: pinhole projections [N, 2] of the points its COLMAP track lists, and their colours [N, 3]."""
    visible = track_visibility(points, ds.num_views)
    out = []
    for v in range(ds.num_views):
        cam = select_cameras(ds.cameras, [v])
        cam = type(cam)(cam.intrinsics.double(), cam.extrinsics.double(), cam.height.double(), cam.width.double())
        uv, _ = project_points(cam, torch.from_numpy(points.xyz[visible[v]]))
        out.append((uv[0].numpy(), points.rgb[visible[v]] / 255.0))
    return out


def _colour_error(ds, observations, k: float = 0.0) -> tuple[float, float]:
    """(mean colour error, mean pixel shift) when the projections are moved by a radial term
    ``(x, y) (1 + k r^2)`` before the image is read (k = 0: the projections as they are)."""
    f, cx, cy = float(ds.cameras.fx[0]), float(ds.cameras.cx[0]), float(ds.cameras.cy[0])
    errs, shifts = [], []
    for v, (uv, rgb) in enumerate(observations):
        x, y = (uv[:, 0] - cx) / f, (uv[:, 1] - cy) / f
        radial = 1.0 + k * (x * x + y * y)
        uvk = np.stack([f * x * radial + cx, f * y * radial + cy], -1)
        shifts.append(np.linalg.norm(uvk - uv, axis=1))
        grid = torch.from_numpy(np.stack([uvk[:, 0] / ds.width * 2 - 1, uvk[:, 1] / ds.height * 2 - 1], -1))
        colour = F.grid_sample(ds.images[v].permute(2, 0, 1)[None].double(), grid[None, None], align_corners=False,
                               padding_mode="border")[0, :, 0].T.numpy()
        errs.append(np.abs(colour - rgb).mean(1))
    return float(np.concatenate(errs).mean()), float(np.concatenate(shifts).mean())


def test_fern_is_undistorted_and_its_points_land_on_the_undistorted_images(shared_data):
    root = shared_data / "nerf_llff_data" / "fern"
    with pytest.warns(UserWarning, match=r"fern/sparse/0/cameras\.bin: SIMPLE_RADIAL lens distortion.*undistorted"):
        ds = load_llff(root, images="images_8")
    with pytest.warns(UserWarning, match="left distorted"):
        raw = load_llff(root, images="images_8", undistort=False)
    lens = ds.lens
    assert lens["model"] == "SIMPLE_RADIAL" and lens["undistorted"]
    f_llff = float(np.load(root / "poses_bounds.npy")[0, 14]) * 504 / 4032
    # COLMAP's focal scaled to images_8 is LLFF's (LLFF wrote it); centre at the image centre
    np.testing.assert_allclose(lens["params"][:3], [f_llff, 252.0, 189.0], rtol=1e-9)
    assert lens["params"][3] == pytest.approx(0.0197505, rel=1e-5)
    assert lens["max_shift_px"] == pytest.approx(3.69, abs=0.01)  # at the corners
    assert lens["border_fraction"] == pytest.approx(0.0155, abs=5e-4)

    points = read_points3d_binary(root / "sparse" / "0" / "points3D.bin")
    observations = _fern_observations(ds, points)  # same cameras in both datasets
    assert sum(len(o[0]) for o in observations) == 41054
    err_u, _ = _colour_error(ds, observations)
    err_d, _ = _colour_error(raw, observations)
    assert err_u == pytest.approx(FERN_COLOUR_ERROR_UNDISTORTED, abs=1e-3)
    assert err_d == pytest.approx(FERN_COLOUR_ERROR_DISTORTED, abs=1e-3)
    assert err_u < err_d - 0.02
    # in pixels: the radial term that best explains where the points show (least colour error) is
    # COLMAP's k1 on the distorted images, a mean reprojection error of 0.64 px; none on the
    # undistorted ones
    best = {}
    for name, d in (("undistorted", ds), ("distorted", raw)):
        scores = [_colour_error(d, observations, k) for k in RADIAL_GRID]
        i = int(np.argmin([s[0] for s in scores]))
        best[name] = (float(RADIAL_GRID[i]), scores[i][1])
    assert best["undistorted"][0] == 0.0 and best["undistorted"][1] < 1e-9, best
    assert best["distorted"][0] == pytest.approx(0.02), best
    assert best["distorted"][1] == pytest.approx(0.64, abs=0.01), best
