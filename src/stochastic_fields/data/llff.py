"""LLFF forward-facing scenes (``poses_bounds.npy`` + ``images_<factor>/`` + optional COLMAP model).

``poses_bounds.npy`` is [V, 17]: per view a row-major [3, 5] matrix (columns: the camera's
*down*, *right*, *back* axes in world coordinates, the camera centre, and ``(h, w, f)`` of the
full-resolution originals) followed by the near and far depth bounds. Views are the image files
in sorted order. Poses are converted to OpenCV at this boundary
(:func:`~stochastic_fields.cameras.llff_poses_to_opencv_w2c`).

Intrinsics: ``fx = fy = f * W / w`` (focal scaled by the image downsampling factor), principal
point at the image centre ``(W / 2, H / 2)`` with pixel centres at +0.5.

Lens distortion: ``poses_bounds.npy`` carries none, but the capture's COLMAP model
(``sparse/0/cameras.bin``) does (fern and flower: SIMPLE_RADIAL, k1 = 0.020 and 0.025, up to 3.7
and 3.9 pixels at the corners of ``images_8``). LLFF and NeRF ignore it; this loader (with
``undistort=True``, the default) resamples every image to the pinhole camera above with
:func:`~stochastic_fields.data.colmap.undistort_image` (the COLMAP loaders' implementation), the
COLMAP camera rescaled to the loaded size (:func:`~stochastic_fields.data.colmap.rescale_camera`).
The COLMAP focal length and principal point, so rescaled, must agree with LLFF's (within
``LLFF_COLMAP_FOCAL_RTOL`` and ``LLFF_COLMAP_CENTRE_TOL_PX``; fern and flower: to 1e-12, LLFF's
focal is COLMAP's), else a DatasetError names ``cameras.bin``. The image size and the intrinsics
stay as they are, so the SfM points (sparse depth, capture points), which are projected through
the dataset's pinhole cameras, land where the undistorted images show them. The price is a thin
band at the border whose rays leave the distorted photo and take its border pixel (fern: 0.5 to
3.7 pixels wide, 1.5% of the pixels); cropping it away would change the image size and the
principal point every LLFF number is measured with. The undistortion is computed in memory on
every load (nothing is written into the scene folder) and reported in ``SceneDataset.lens`` and a
warning. A model with several different cameras, which ``poses_bounds.npy``'s renamed images
cannot be matched to, is left distorted with a warning.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from ..cameras import llff_poses_to_opencv_w2c, make_cameras
from .colmap import (
    PINHOLE_MODELS,
    ColmapCamera,
    pinhole_intrinsics,
    read_cameras_binary,
    read_points3d_binary,
    rescale_camera,
    undistort_image,
    undistortion_shift,
)
from .dataset import (
    IMAGE_SUFFIXES,
    SceneDataset,
    fit_scene_aabb,
    read_image,
    split_every_indices,
    stack_images,
)
from .errors import DatasetError

#: Relative disagreement allowed between the width and height downsampling factors.
_ASPECT_TOLERANCE: float = 0.01


#: Tolerance on R^T R = I for the rotation block of a poses_bounds.npy row (float32 files from
#: COLMAP pass; a singular, scaled or sheared block does not).
LLFF_ROTATION_TOLERANCE: float = 1e-3
#: Relative disagreement allowed between poses_bounds.npy's focal and the COLMAP camera's, both
#: scaled to the loaded images (LLFF writes COLMAP's focal: fern and flower agree to 1e-12).
LLFF_COLMAP_FOCAL_RTOL: float = 1e-3
#: Disagreement (loaded-image pixels) allowed between the COLMAP principal point and LLFF's image centre.
LLFF_COLMAP_CENTRE_TOL_PX: float = 0.5

def read_poses_bounds(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(poses [V, 3, 5], bounds [V, 2]) from ``poses_bounds.npy``, validated.

    DatasetError naming the file for: unreadable file, shape other than [V, 17], non-finite
    values, near <= 0 or near >= far.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing poses_bounds.npy")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise DatasetError(path, f"unreadable array ({type(exc).__name__}: {exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise DatasetError(path, f"expected an array of shape [V, 17] (3x5 pose-hwf + near, far), got {arr.shape}")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise DatasetError(path, f"non-finite (NaN/inf) pose or bounds in rows {np.flatnonzero(bad).tolist()}")
    poses = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:17]
    bad = (bounds[:, 0] >= bounds[:, 1]) | (bounds[:, 0] <= 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError(path, f"need 0 < near < far, got near={bounds[i, 0]} far={bounds[i, 1]} in row {i}"
                           f" (rows {np.flatnonzero(bad).tolist()})")
    hwf = poses[:, :, 4]
    if (hwf <= 0).any():
        raise DatasetError(path, "hwf column (height, width, focal) must be positive")
    R = poses[:, :, :3]
    gram_err = np.abs(np.einsum("vji,vjk->vik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = (gram_err > LLFF_ROTATION_TOLERANCE) | (np.linalg.det(R) <= 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise DatasetError(path, f"row {i}: the 3x3 pose block must be a rotation (R^T R = I within "
                           f"{LLFF_ROTATION_TOLERANCE}, det R = 1), got {R[i].tolist()} (rows {np.flatnonzero(bad).tolist()})")
    return poses, bounds


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in sorted order; DatasetError if the folder is missing or empty."""
    if not folder.is_dir():
        raise DatasetError(folder, "missing image folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DatasetError(folder, f"no images ({'/'.join(IMAGE_SUFFIXES)}) in folder")
    return files


def load_llff(
    root: str | Path,
    *,
    images: str | int = 8,
    split_every: int = 5,
    load_points: bool = True,
    undistort: bool = True,
) -> SceneDataset:
    """Load an LLFF scene.

    Args:
        root: scene folder holding ``poses_bounds.npy``.
        images: image folder name (``"images_8"``) or downsampling factor (8 -> ``images_8``,
            1 -> ``images``).
        split_every: docs/definitions.md §7 split, train = ``index % split_every == 0``, test = the rest.
        load_points: read ``sparse/0/points3D.bin`` (if present) into ``points3d``; the points
            also bound the scene box.
        undistort: resample the images to the pinhole camera when ``sparse/0/cameras.bin``
            holds a distorted camera (module doc); False keeps them as they are (the numbers
            measured before this existed), still reporting the distortion.

    Returns:
        SceneDataset with OpenCV cameras, near/far from the file (camera-z), no depth maps,
        ``forward_facing=True``, ``lens`` describing the COLMAP lens distortion (None without one).
    """
    root = Path(root)
    poses_file = root / "poses_bounds.npy"
    poses, bounds = read_poses_bounds(poses_file)
    if isinstance(images, int):
        folder = root / ("images" if images == 1 else f"images_{images}")
    else:
        folder = root / images
    files = list_images(folder)
    if len(files) != poses.shape[0]:
        raise DatasetError(poses_file, f"{poses.shape[0]} poses but {len(files)} images in {folder}")
    arrays = [read_image(p)[..., :3] for p in files]
    imgs = stack_images(arrays, files)  # [V, H, W, 3]
    V, H, W = imgs.shape[:3]

    h0, w0, f0 = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
    scale_w, scale_h = W / w0, H / h0
    if np.any(np.abs(scale_w / scale_h - 1.0) > _ASPECT_TOLERANCE):
        raise DatasetError(folder, f"images are {W}x{H} but poses_bounds.npy says the originals are "
                           f"{w0[0]:.0f}x{h0[0]:.0f}: the aspect ratios differ")
    K = np.zeros((V, 3, 3))
    K[:, 0, 0] = f0 * scale_w
    K[:, 1, 1] = f0 * scale_w
    K[:, 0, 2] = W / 2.0
    K[:, 1, 2] = H / 2.0
    K[:, 2, 2] = 1.0
    lens = None
    camera = llff_colmap_camera(root, W, H)
    if camera is not None:
        if undistort:
            check_colmap_intrinsics(camera, K, root / "sparse" / "0" / "cameras.bin")
        shift, border = undistortion_shift(camera)
        lens = {"model": camera.model, "params": camera.params.tolist(), "width": W, "height": H,
                "max_shift_px": shift, "border_fraction": border, "undistorted": bool(undistort),
                "source": str(root / "sparse" / "0" / "cameras.bin")}
        what = (f"{lens['source']}: {camera.model} lens distortion (params at {W}x{H}: "
                f"{', '.join(f'{x:.6g}' for x in camera.params)}), up to {shift:.1f} px")
        if undistort:
            imgs = torch.stack([torch.from_numpy(undistort_image(im.numpy(), camera)[0]) for im in imgs])
            warnings.warn(f"{what}: images undistorted to the pinhole camera of poses_bounds.npy "
                          f"(same size; {border:.1%} of the pixels, at the border, see past the photo and "
                          "take its edge)", stacklevel=2)
        else:
            warnings.warn(f"{what}: images left distorted (undistort=False): pixels and the SfM points' "
                          "projections disagree by up to that much", stacklevel=2)
    w2c = llff_poses_to_opencv_w2c(torch.from_numpy(poses))
    cameras = make_cameras(torch.from_numpy(K).float(), w2c.float(), H, W)
    near = torch.from_numpy(bounds[:, 0]).float()
    far = torch.from_numpy(bounds[:, 1]).float()

    points = rgb = None
    points_file = root / "sparse" / "0" / "points3D.bin"
    if load_points and points_file.is_file():
        colmap = read_points3d_binary(points_file)
        points = torch.from_numpy(colmap.xyz).float()
        rgb = torch.from_numpy(colmap.rgb).float() / 255.0
    aabb = fit_scene_aabb(cameras, near, far, points, forward_facing=True)
    train, test = split_every_indices(V, split_every, poses_file)
    return SceneDataset(
        name=root.name,
        root=root,
        images=imgs,
        cameras=cameras,
        near=near,
        far=far,
        train_indices=train,
        test_indices=test,
        aabb=aabb,
        points3d=points,
        points3d_rgb=rgb,
        image_paths=files,
        forward_facing=True,
        lens=lens,
    )


def llff_colmap_camera(root: str | Path, width: int, height: int) -> ColmapCamera | None:
    """The distorted COLMAP camera of an LLFF capture rescaled to ``width`` x ``height``, or None.

    None when ``<root>/sparse/0/cameras.bin`` is absent, holds no camera or a pinhole one, or holds
    several different cameras (warned: ``poses_bounds.npy``'s renamed images cannot be matched to
    them).
    """
    path = Path(root) / "sparse" / "0" / "cameras.bin"
    if not path.is_file():
        return None
    cameras = list(read_cameras_binary(path).values())
    distinct = {(c.model, c.width, c.height, tuple(c.params.tolist())) for c in cameras}
    if len(distinct) > 1:
        warnings.warn(f"{path}: {len(distinct)} different cameras; the images of poses_bounds.npy cannot be "
                      "matched to them, so any lens distortion is left in the images", stacklevel=3)
        return None
    if not cameras or cameras[0].model in PINHOLE_MODELS:
        return None
    return rescale_camera(cameras[0], width, height)


def check_colmap_intrinsics(camera: ColmapCamera, K: np.ndarray, path: Path) -> None:
    """DatasetError naming ``path`` when the (rescaled) COLMAP camera's focal lengths or principal
    point disagree with the loader's pinhole ``K`` [V, 3, 3] in any view (module doc)."""
    Kc = pinhole_intrinsics(camera)
    K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    focal_err = max(np.abs(Kc[0, 0] / K[:, 0, 0] - 1.0).max(), np.abs(Kc[1, 1] / K[:, 1, 1] - 1.0).max())
    centre_err = max(np.abs(Kc[0, 2] - K[:, 0, 2]).max(), np.abs(Kc[1, 2] - K[:, 1, 2]).max())
    if focal_err > LLFF_COLMAP_FOCAL_RTOL or centre_err > LLFF_COLMAP_CENTRE_TOL_PX:
        raise DatasetError(path, f"the COLMAP camera at {camera.width}x{camera.height} (fx={Kc[0, 0]:.6g}, "
                           f"fy={Kc[1, 1]:.6g}, cx={Kc[0, 2]:.6g}, cy={Kc[1, 2]:.6g}) disagrees with "
                           f"poses_bounds.npy's (f={K[0, 0, 0]:.6g}, centre {K[0, 0, 2]:.6g}, {K[0, 1, 2]:.6g}) by "
                           f"{focal_err:.2g} in focal (tolerance {LLFF_COLMAP_FOCAL_RTOL:g}) and {centre_err:.2g} px "
                           f"in principal point (tolerance {LLFF_COLMAP_CENTRE_TOL_PX:g}): not this capture's "
                           "model? Load with undistort=False (option data.undistort false) to leave the images "
                           "distorted")
