"""A COLMAP capture: a sparse model (``sparse/0/*.bin``) and the images it was made from.

Layout (COLMAP's own, and what ``stochastic-fields prepare`` writes)::

    SCENE/images/<name>             the photos, names as COLMAP stores them
    SCENE/images_<d>/<name>         optional downscaled copies (d = 2, 4, 8)
    SCENE/sparse/0/{cameras,images,points3D}.bin   (or .txt; also colmap/sparse/0, sparse/)

Views are the registered images sorted by name. Poses are COLMAP's ``cam_from_world`` (OpenCV
already). Distorted cameras (SIMPLE_RADIAL, OPENCV, ...) are undistorted to the pinhole camera
with the same focal lengths and principal point (:func:`~.colmap.undistort_image`). Near/far and
the scene box come from the SfM points each view's track lists (:mod:`.capture`); the points and
their per-view visibility travel with the dataset for sparse-depth evaluation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..cameras import make_cameras
from .blender import _area_downscale
from .capture import bounds_from_points, is_forward_facing
from .colmap import ColmapModel, find_colmap_model, read_colmap_model, rescale_camera, undistort_image
from .dataset import SceneDataset, fit_scene_aabb, read_image, split_every_indices, stack_images
from .errors import DatasetError


def image_folder(root: Path, downscale: int) -> tuple[Path, int]:
    """(folder to read, remaining area-downscale factor): ``images_<d>`` when it exists, else ``images``."""
    if downscale > 1 and (root / f"images_{downscale}").is_dir():
        return root / f"images_{downscale}", 1
    return root / "images", downscale


def load_colmap(
    root: str | Path,
    *,
    downscale: int = 1,
    split_every: int = 5,
    model: str | Path | None = None,
    progress: bool = False,
) -> SceneDataset:
    """Load a COLMAP capture (module doc).

    Args:
        root: scene folder (holding ``images/`` and a model under ``sparse/0`` or similar).
        downscale: image downscale factor: reads ``images_<downscale>/`` if present, else
            area-averages ``images/``. Intrinsics follow the loaded size.
        split_every: views with ``index % split_every == 0`` train (docs/definitions.md §7).
        model: the model folder, if not one of the usual places under ``root``.
        progress: a progress bar over the images.
    """
    root = Path(root)
    if int(downscale) != downscale or downscale < 1:
        raise DatasetError(root, f"downscale must be a positive integer, got {downscale}")
    model_dir = Path(model) if model is not None else find_colmap_model(root)
    if model_dir is None:
        raise DatasetError(root, "no COLMAP model (cameras/images/points3D.bin under sparse/0, sparse or "
                           "colmap/sparse/0)")
    colmap = read_colmap_model(model_dir)
    folder, extra = image_folder(root, int(downscale))
    if not folder.is_dir():
        raise DatasetError(folder, f"missing image folder for the COLMAP model in {model_dir}")
    arrays, Ks, paths = [], [], []
    for image in tqdm(colmap.images, desc="images", disable=not progress, leave=False):
        path = folder / image.name
        if not path.is_file():
            raise DatasetError(path, f"missing image (registered in {model_dir})")
        photo = read_image(path)[..., :3]
        camera = rescale_camera(colmap.cameras[image.camera_id], photo.shape[1], photo.shape[0])
        photo, K = undistort_image(photo, camera)
        photo = _area_downscale(np.ascontiguousarray(photo), extra)
        K = K.copy()
        K[0] *= photo.shape[1] / camera.width
        K[1] *= photo.shape[0] / camera.height
        arrays.append(photo)
        Ks.append(K)
        paths.append(path)
    imgs = stack_images(arrays, paths)
    V, H, W = imgs.shape[:3]
    w2c = torch.from_numpy(np.stack([im.world_to_camera for im in colmap.images])).float()
    cameras = make_cameras(torch.from_numpy(np.stack(Ks)).float(), w2c, H, W)
    return _scene_from_model(root, colmap, imgs, cameras, paths, split_every, model_dir)


def _scene_from_model(root: Path, colmap: ColmapModel, imgs: torch.Tensor, cameras, paths: list[Path],
                      split_every: int, model_dir: Path) -> SceneDataset:
    visible = colmap.visible_points()
    xyz = colmap.points.xyz
    try:
        near, far = bounds_from_points(cameras, xyz, visible, track_lengths=colmap.points.track_lengths)
    except ValueError as exc:
        raise DatasetError(model_dir / "points3D.bin", str(exc)) from exc
    points = torch.from_numpy(xyz).float()
    forward = is_forward_facing(cameras, xyz)
    aabb = fit_scene_aabb(cameras, near, far, points, forward_facing=forward)
    train, test = split_every_indices(imgs.shape[0], split_every, model_dir)
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
        points3d_rgb=torch.from_numpy(colmap.points.rgb).float() / 255.0,
        image_paths=paths,
        forward_facing=forward,
        points3d_visible=visible,
        bounds_source="sfm_points",
    )
