"""Blender / nerfstudio scenes described by ``transforms*.json``.

Each frame has ``file_path`` (relative to the json, with or without extension) and
``transform_matrix``, an OpenGL camera-to-world matrix (camera x right, y up, z back),
converted to OpenCV at this boundary
(:func:`~stochastic_fields.cameras.opengl_c2w_to_opencv_w2c`).

Intrinsics, top level or per frame: ``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` (nerfstudio;
pixel centres at +0.5) or ``camera_angle_x`` (Blender: ``fx = fy = W / (2 tan(angle_x / 2))``,
principal point at the image centre). Lens distortion as ns-process-data writes it
(``camera_model`` OPENCV with ``k1 k2 k3 p1 p2``, OPENCV_FISHEYE with ``k1..k4``, top level or per
frame) is removed: each photo is resampled to the pinhole camera with the same ``fl_x fl_y cx cy``
and size (:func:`~stochastic_fields.data.colmap.undistort_image`).

Downscaling (``downscale=d``): when ``images_<d>/`` sits beside the frames' ``images/`` folder
(nerfstudio's layout, and what ``stochastic-fields prepare`` writes) those files are read;
otherwise the full images are area-averaged.

RGBA images are composited on white (or on a top-level ``"background": [r, g, b]``) and
``background`` records it; for RGB images that key states the background they show. An optional per-frame
``depth_file_path`` loads camera-z depth into ``depths`` (``.npy`` float32 in scene units, 0 =
no surface, as our synthetic scenes write; or a 16-bit PNG times ``depth_unit_scale_factor``,
nerfstudio's convention, default 1e-3).

Optional top-level hints written by :mod:`~stochastic_fields.data.synthetic`: ``near``, ``far``
(camera-z), ``aabb`` ([2, 3]), ``split_every``.

Scene bounds without near/far hints come from the capture's SfM points, as LLFF's do
(:mod:`~stochastic_fields.data.capture`): a COLMAP model beside the json (``sparse/0``,
``colmap/sparse/0``; its points mapped by the json's ``applied_transform``, the tracks give each
view's points by image name), else the json's ``ply_file_path`` point cloud (already in the
json's frame; each view's points by projection). The points also become ``points3d`` for sparse
depth. Without hints or points the Blender convention near = 2, far = 6 is used, with a warning
that it is a guess.

Splits: a folder with ``transforms_train.json`` and ``transforms_test.json`` loads both, and
the files give the split; a single json (``transforms.json`` or one named file) is split with
``split_every`` (the file's own ``split_every`` hint wins when the caller passes none). The
dataset's ``split_source`` says which (``"files"`` or ``"split_every"``): a run's capture split
(``data.split``) re-splits the second only.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
import imageio.v3 as iio

from ..cameras import backproject_depths, make_cameras, opengl_c2w_to_opencv_w2c
from .capture import bounds_from_points, is_forward_facing, visible_points_by_projection
from .colmap import ColmapCamera, find_colmap_model, read_colmap_model, rescale_camera, undistort_image
from .dataset import (
    IMAGE_SUFFIXES,
    SceneDataset,
    check_split,
    fit_scene_aabb,
    read_image,
    split_every_indices,
    stack_images,
)
from .errors import DatasetError

#: near/far (camera-z) of the original Blender scenes, used when the json gives no hints.
BLENDER_NEAR: float = 2.0
BLENDER_FAR: float = 6.0
#: Scene-units per unit of 16-bit PNG depth when the json gives no ``depth_unit_scale_factor``.
DEFAULT_DEPTH_UNIT_SCALE: float = 1e-3
#: At most this many back-projected depth points are used to fit the scene box.
_MAX_AABB_POINTS: int = 200_000

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


#: Tolerance on R^T R = I for a frame's camera-to-world rotation: poses written with 4-5
#: significant digits pass, a scaled, sheared or singular matrix does not.
POSE_ROTATION_TOLERANCE: float = 1e-3


def _number(json_path: Path, where: str, key: str, value: Any, *, positive: bool = False) -> float:
    """``float(value)`` for a JSON number, else DatasetError naming the file, the key and the value."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)) \
            or (positive and not float(value) > 0):
        raise DatasetError(json_path, f"{where}{key!r} must be a finite{' positive' if positive else ''} number, "
                           f"got {value!r}")
    return float(value)


def _read_json(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise DatasetError(path, "missing transforms file")
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(path, f"unreadable JSON ({exc})") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise DatasetError(path, "expected a JSON object with a non-empty 'frames' list")
    return meta


def _resolve_file(json_path: Path, rel: str, what: str) -> Path:
    """The file ``rel`` names (relative to the json's folder), trying image suffixes if it has none."""
    base = json_path.parent / rel
    if base.is_file():
        return base
    for suffix in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES):
        cand = base.with_name(base.name + suffix)
        if cand.is_file():
            return cand
    raise DatasetError(base, f"missing {what} (listed in {json_path.name})")


def _frame_pose(json_path: Path, index: int, frame: dict[str, Any]) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise DatasetError(json_path, f"frame {index} has no transform_matrix")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DatasetError(json_path, f"frame {index}: transform_matrix is not numeric ({exc})") from exc
    if m.shape not in ((4, 4), (3, 4)):
        raise DatasetError(json_path, f"frame {index}: transform_matrix must be 4x4 or 3x4, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise DatasetError(json_path, f"frame {index}: transform_matrix has NaN/inf entries")
    R = m[:3, :3]
    if (m.shape == (4, 4) and not np.allclose(m[3], [0, 0, 0, 1])) or np.linalg.det(R) <= 0 \
            or not np.allclose(R.T @ R, np.eye(3), atol=POSE_ROTATION_TOLERANCE):
        raise DatasetError(json_path, f"frame {index}: transform_matrix must be a rigid camera-to-world transform "
                           f"[[R, t], [0, 0, 0, 1]] with R a rotation (R^T R = I within {POSE_ROTATION_TOLERANCE}, "
                           f"det R = 1), got {m.tolist()}")
    full = np.eye(4)
    full[:3] = m[:3]
    return full


#: nerfstudio ``camera_model`` names of perspective cameras (radial-tangential distortion).
_PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
#: nerfstudio ``camera_model`` names of fisheye cameras (k1..k4, equidistant).
_FISHEYE_MODELS = ("OPENCV_FISHEYE",)


def _frame_camera(json_path: Path, meta: dict, frame: dict, index: int, H: int, W: int) -> ColmapCamera:
    """The frame's camera at the full image size H x W, as a COLMAP camera model.

    PINHOLE when every distortion coefficient is zero; else OPENCV (k1 k2 p1 p2), FULL_OPENCV
    (with k3) or OPENCV_FISHEYE (k1..k4), following ``camera_model``.
    """

    def get(key: str):
        return frame.get(key, meta.get(key))

    where = f"frame {index}: "

    def num(key: str, positive: bool = False) -> float | None:
        value = get(key)
        return None if value is None else _number(json_path, where, key, value, positive=positive)

    w, h = num("w", True), num("h", True)
    if (w is not None and w != W) or (h is not None and h != H):
        raise DatasetError(json_path, f"frame {index}: json says {get('w')}x{get('h')} but the image is {W}x{H}")
    fl_x, fl_y = num("fl_x"), num("fl_y")
    for key, size, axis in (("camera_angle_x", W, "x"), ("camera_angle_y", H, "y")):
        angle = num(key)
        if angle is None or (fl_x if axis == "x" else fl_y) is not None:
            continue
        if not 0.0 < angle < math.pi:
            raise DatasetError(json_path, f"{where}{key!r} must be a field of view in radians in (0, pi), got {angle}")
        focal = 0.5 * size / math.tan(0.5 * angle)
        fl_x, fl_y = (focal, fl_y) if axis == "x" else (fl_x, focal)
    if fl_x is None and fl_y is None:
        raise DatasetError(json_path, "no focal length: need fl_x/fl_y or camera_angle_x")
    fl_x = float(fl_y if fl_x is None else fl_x)
    fl_y = float(fl_x if fl_y is None else fl_y)
    cx = num("cx") if get("cx") is not None else W / 2.0
    cy = num("cy") if get("cy") is not None else H / 2.0
    if not all(math.isfinite(x) for x in (fl_x, fl_y, cx, cy)) or fl_x <= 0 or fl_y <= 0:
        raise DatasetError(json_path, f"frame {index}: bad intrinsics fl_x={fl_x} fl_y={fl_y} cx={cx} cy={cy}")
    dist = {}
    for key in _DISTORTION_KEYS:
        value = get(key)
        try:
            dist[key] = 0.0 if value is None else float(value)
        except (TypeError, ValueError):
            raise DatasetError(json_path, f"frame {index}: distortion {key}={value!r} is not a number") from None
        if not math.isfinite(dist[key]):
            raise DatasetError(json_path, f"frame {index}: distortion {key}={value} is not finite")
    model = str(get("camera_model") or "OPENCV").upper()
    pinhole = [fl_x, fl_y, cx, cy]
    if model in _FISHEYE_MODELS:
        if dist["p1"] or dist["p2"]:
            raise DatasetError(json_path, f"frame {index}: OPENCV_FISHEYE has no tangential terms, got "
                               f"p1={dist['p1']} p2={dist['p2']}")
        return ColmapCamera(index, "OPENCV_FISHEYE", W, H,
                            np.array(pinhole + [dist["k1"], dist["k2"], dist["k3"], dist["k4"]]))
    if model not in _PERSPECTIVE_MODELS:
        raise DatasetError(json_path, f"frame {index}: camera_model {model!r} is not supported (use one of "
                           f"{', '.join(_PERSPECTIVE_MODELS + _FISHEYE_MODELS)})")
    if dist["k4"]:
        raise DatasetError(json_path, f"frame {index}: k4={dist['k4']} on a perspective camera is not supported "
                           "(only OPENCV_FISHEYE has k4)")
    if not any(dist.values()):
        return ColmapCamera(index, "PINHOLE", W, H, np.array(pinhole))
    if dist["k3"]:
        return ColmapCamera(index, "FULL_OPENCV", W, H, np.array(
            pinhole + [dist["k1"], dist["k2"], dist["p1"], dist["p2"], dist["k3"], 0.0, 0.0, 0.0]))
    return ColmapCamera(index, "OPENCV", W, H, np.array(pinhole + [dist["k1"], dist["k2"], dist["p1"], dist["p2"]]))


def _downscaled_file(json_path: Path, path: Path, factor: int) -> Path | None:
    """``<json dir>/<first folder>_<factor>/<rest>`` for ``path`` under the json's folder, if it exists."""
    if factor <= 1:
        return None
    try:
        rel = path.relative_to(json_path.parent)
    except ValueError:
        return None
    if len(rel.parts) < 2:
        return None
    cand = json_path.parent / f"{rel.parts[0]}_{factor}" / Path(*rel.parts[1:])
    return cand if cand.is_file() else None


def _image_size(path: Path) -> tuple[int, int]:
    """(H, W) of an image file without decoding all of it."""
    try:
        shape = iio.improps(path).shape
    except Exception as exc:
        raise DatasetError(path, f"unreadable image ({type(exc).__name__}: {exc})") from exc
    return int(shape[0]), int(shape[1])


def _read_depth(path: Path, scale: float) -> np.ndarray:
    """[H, W] float32 camera-z depth, 0 = no surface."""
    if path.suffix == ".npy":
        try:
            depth = np.load(path, allow_pickle=False)
        except Exception as exc:
            raise DatasetError(path, f"unreadable depth array ({type(exc).__name__}: {exc})") from exc
        depth = np.asarray(depth, dtype=np.float32)
    elif path.suffix.lower() == ".png":
        raw = iio.imread(path)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(path, f"depth PNG must be single-channel 16-bit, got {raw.dtype} {raw.shape}")
        depth = raw.astype(np.float32) * scale
    else:
        raise DatasetError(path, "unsupported depth format (use .npy float32 or 16-bit .png)")
    if depth.ndim != 2:
        raise DatasetError(path, f"depth map must be [H, W], got shape {depth.shape}")
    if not np.isfinite(depth).all() or (depth < 0).any():
        raise DatasetError(path, "depth map has NaN/inf or negative values")
    return depth


def _area_downscale(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, C] -> [round(H / f), round(W / f), C] by area averaging (identity for f = 1)."""
    if factor == 1:
        return image
    H, W = image.shape[:2]
    size = (max(1, round(H / factor)), max(1, round(W / factor)))
    x = torch.from_numpy(image).permute(2, 0, 1)[None]
    return F.interpolate(x, size=size, mode="area")[0].permute(1, 2, 0).contiguous().numpy()


def _load_frames(json_path: Path, meta: dict, want_depth: bool, downscale: int, frame_stride: int):
    """Load the frames of one json (every ``frame_stride``-th), composited and downscaled.

    Returns images [V, H, W, 3], K [V, 3, 3] at the loaded size, c2w_gl [V, 4, 4], depths
    [V, H, W] or None, image paths, background.
    """
    frames = meta["frames"][::frame_stride]
    background = meta.get("background")
    if background is not None:
        try:
            background = tuple(float(c) for c in background)
        except (TypeError, ValueError):
            background = ()
        if len(background) != 3:
            raise DatasetError(json_path, f"'background' must be 3 numbers, got {meta['background']}")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(json_path, f"frame {i} must be a JSON object, got {frame!r}")
    has_depth = [("depth_file_path" in f) for f in frames]
    want_depth = want_depth and any(has_depth)
    if want_depth and not all(has_depth):
        raise DatasetError(json_path, "some frames have depth_file_path and others not")
    if want_depth and downscale > 1:
        raise DatasetError(json_path, f"downscale={downscale} with depth maps: area-averaging mixes surfaces; "
                           "render the scene at the wanted size or pass load_depth=False")
    depth_scale = _number(json_path, "", "depth_unit_scale_factor",
                          meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT_SCALE), positive=True)
    arrays, paths, Ks, poses, depths = [], [], [], [], []
    for i, frame in enumerate(frames):
        if "file_path" not in frame:
            raise DatasetError(json_path, f"frame {i} has no file_path")
        path = _resolve_file(json_path, str(frame["file_path"]), "image")
        poses.append(_frame_pose(json_path, i, frame))
        small = _downscaled_file(json_path, path, downscale)
        image = read_image(small or path)
        H0, W0 = _image_size(path) if small is not None else image.shape[:2]
        camera = _frame_camera(json_path, meta, frame, i, H0, W0)
        if image.shape[-1] == 4:
            background = background or (1.0, 1.0, 1.0)
            alpha = image[..., 3:]
            image = image[..., :3] * alpha + (1.0 - alpha) * np.asarray(background, dtype=np.float32)
        image = np.ascontiguousarray(image[..., :3])
        camera = rescale_camera(camera, image.shape[1], image.shape[0])
        image, K = undistort_image(image, camera)
        image = _area_downscale(image, 1 if small is not None else downscale)
        H, W = image.shape[:2]
        K = K.copy()
        K[0] *= W / camera.width
        K[1] *= H / camera.height
        if small is not None:
            path = small
        if want_depth:
            dpath = json_path.parent / str(frame["depth_file_path"])
            if not dpath.is_file():
                raise DatasetError(dpath, f"missing depth map (listed in {json_path.name})")
            d = _read_depth(dpath, depth_scale)
            if d.shape != (H, W):
                raise DatasetError(dpath, f"depth map shape {d.shape} differs from image shape {(H, W)}")
            depths.append(d)
        arrays.append(image)
        paths.append(path)
        Ks.append(K)
    imgs = stack_images(arrays, paths)
    depth_t = torch.from_numpy(np.stack(depths)) if want_depth else None
    return imgs, np.stack(Ks), np.stack(poses), depth_t, paths, background


def _json_files(path: Path) -> list[tuple[Path, str]]:
    """[(json file, split name)] to load for a folder or a file."""
    if path.is_file():
        return [(path, "all")]
    train, test = path / "transforms_train.json", path / "transforms_test.json"
    if train.is_file() and test.is_file():
        return [(train, "train"), (test, "test")]
    single = path / "transforms.json"
    if single.is_file():
        return [(single, "all")]
    raise DatasetError(path, "no transforms.json or transforms_train.json + transforms_test.json in folder")


def _hint(path: Path, metas: list[dict], key: str):
    values = [m[key] for m in metas if key in m]
    return values[0] if values else None


def load_blender(
    path: str | Path,
    *,
    downscale: int = 1,
    split_every: int | None = None,
    near: float | None = None,
    far: float | None = None,
    load_depth: bool = True,
    frame_stride: int = 1,
) -> SceneDataset:
    """Load a Blender/nerfstudio scene.

    Args:
        path: a folder (``transforms_train.json`` + ``transforms_test.json``, or
            ``transforms.json``) or a single json file.
        downscale: integer area-resize factor for the images (e.g. 8: lego 800 -> 100); the
            intrinsics scale with the picture. Depth maps cannot be area-averaged without mixing
            surfaces, so ``downscale > 1`` with depth maps present raises (render smaller instead,
            or pass ``load_depth=False``).
        split_every: split of a single json (train = ``index % split_every == 0``); default:
            the file's ``split_every`` hint, else 5.
        near, far: camera-z bounds; default the file's hints, else from the capture's SfM
            points (module doc), else 2 and 6 (Blender) with a warning.
        load_depth: read ``depth_file_path`` maps when frames list them.
        frame_stride: load every n-th frame of each json only (quick looks, tests); the split
            is then made among the loaded frames.

    Returns:
        SceneDataset (OpenCV cameras; ``forward_facing`` True only for an SfM capture whose
        cameras all look one way, :func:`~stochastic_fields.data.capture.is_forward_facing`).
    """
    path = Path(path)
    if int(downscale) != downscale or downscale < 1:
        raise DatasetError(path, f"downscale must be a positive integer, got {downscale}")
    files = _json_files(path)
    metas = [_read_json(f) for f, _ in files]
    if int(frame_stride) != frame_stride or frame_stride < 1:
        raise DatasetError(path, f"frame_stride must be a positive integer, got {frame_stride}")
    loaded = [_load_frames(f, m, load_depth, int(downscale), int(frame_stride)) for (f, _), m in zip(files, metas)]
    first = files[0][0]
    shapes = {tuple(x[0].shape[1:3]) for x in loaded}
    if len(shapes) > 1:
        raise DatasetError(files[-1][0], f"image sizes differ between split files: {sorted(shapes)}")
    imgs = torch.cat([x[0] for x in loaded])
    K = torch.from_numpy(np.concatenate([x[1] for x in loaded])).float()
    c2w_gl = torch.from_numpy(np.concatenate([x[2] for x in loaded]))
    has_depth = [x[3] is not None for x in loaded]
    if any(has_depth) and not all(has_depth):
        raise DatasetError(first, "depth maps are listed in some split files but not others")
    depths = torch.cat([x[3] for x in loaded]) if all(has_depth) else None
    paths = [p for x in loaded for p in x[4]]
    backgrounds = {x[5] for x in loaded}
    background = loaded[0][5] if len(backgrounds) == 1 else (1.0, 1.0, 1.0)

    V, H, W = imgs.shape[:3]

    near_v = near if near is not None else _hint(first, metas, "near")
    far_v = far if far is not None else _hint(first, metas, "far")
    if (near_v is None) != (far_v is None):
        raise DatasetError(first, f"give both near and far or neither, got near={near_v} far={far_v}")
    if near_v is not None:
        near_v, far_v = _number(first, "", "near", near_v), _number(first, "", "far", far_v)
        if not (0 < near_v < far_v) or not math.isfinite(far_v):
            raise DatasetError(first, f"need 0 < near < far, got near={near_v} far={far_v}")

    if files[0][1] == "all":
        hint = _hint(first, metas, "split_every")
        if hint is not None and (isinstance(hint, bool) or not isinstance(hint, int) or hint < 1):
            raise DatasetError(first, f"'split_every' must be a positive integer, got {hint!r}")
        every = split_every if split_every is not None else (hint or 5)
        train, test = split_every_indices(V, every, first)
    else:
        n_train = loaded[0][0].shape[0]
        train, test = list(range(n_train)), list(range(n_train, V))
        check_split(train, test, path)

    w2c = opengl_c2w_to_opencv_w2c(c2w_gl).float()
    cameras = make_cameras(K, w2c, H, W)
    depth_mask = None if depths is None else depths > 0
    sparse = _sparse_points(first, metas[0], cameras, paths)
    forward_facing = False
    if near_v is not None:
        near_t, far_t, bounds_source = torch.full((V,), near_v), torch.full((V,), far_v), "file"
    elif sparse is not None:
        try:
            near_t, far_t = bounds_from_points(cameras, sparse[0], sparse[1], track_lengths=sparse[5],
                                               what=f"SfM points ({sparse[2]})")
        except ValueError as exc:
            raise DatasetError(sparse[2], str(exc)) from exc
        bounds_source = "sfm_points"
        forward_facing = is_forward_facing(cameras, sparse[0])
    else:
        if _hint(first, metas, "camera_angle_x") is None:  # Blender's own files: near 2 / far 6 is their convention
            warnings.warn(f"{first}: no near/far in the json and no SfM points (COLMAP model or ply_file_path) "
                          f"beside it: guessing the Blender bounds near={BLENDER_NEAR:g}, far={BLENDER_FAR:g}. "
                          "Pass near/far (json keys) if the scene lies elsewhere.", UserWarning, stacklevel=2)
        near_t, far_t, bounds_source = torch.full((V,), BLENDER_NEAR), torch.full((V,), BLENDER_FAR), "default"

    aabb_hint = _hint(first, metas, "aabb")
    if aabb_hint is not None:
        try:
            aabb = torch.as_tensor(aabb_hint, dtype=torch.float32)
        except (TypeError, ValueError, RuntimeError):
            aabb = torch.zeros(0)
        if aabb.shape != (2, 3) or not bool(torch.isfinite(aabb).all()) or not bool(torch.all(aabb[1] > aabb[0])):
            raise DatasetError(first, f"'aabb' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {aabb_hint}")
    else:
        pts = None
        if depths is not None:
            pts = backproject_depths(cameras, depths, depth_mask)
            if pts.shape[0] > _MAX_AABB_POINTS:
                step = math.ceil(pts.shape[0] / _MAX_AABB_POINTS)
                pts = pts[::step]
        elif sparse is not None:
            pts = torch.from_numpy(sparse[0]).float()
        aabb = fit_scene_aabb(cameras, near_t, far_t, pts, forward_facing=forward_facing)

    root = path if path.is_dir() else path.parent
    return SceneDataset(
        name=root.name,
        root=root,
        images=imgs,
        cameras=cameras,
        near=near_t,
        far=far_t,
        train_indices=train,
        test_indices=test,
        aabb=aabb,
        depths=depths,
        depth_mask=depth_mask,
        background=background,
        image_paths=paths,
        forward_facing=forward_facing,
        points3d=None if sparse is None else torch.from_numpy(sparse[0]).float(),
        points3d_rgb=None if sparse is None else torch.from_numpy(sparse[3]).float() / 255.0,
        points3d_visible=None if sparse is None or not sparse[4] else sparse[1],
        bounds_source=bounds_source,
        split_source="split_every" if files[0][1] == "all" else "files",
    )


def _applied_transform(json_path: Path, meta: dict) -> np.ndarray:
    """[4, 4] map from the COLMAP world to the json's world (``applied_transform``, identity if absent)."""
    A = np.eye(4)
    if meta.get("applied_transform") is not None:
        try:
            m = np.asarray(meta["applied_transform"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise DatasetError(json_path, f"applied_transform is not numeric ({exc})") from exc
        if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
            raise DatasetError(json_path, f"applied_transform must be a finite 3x4 or 4x4 matrix, got shape {m.shape}")
        A[:3] = m[:3]
    return A


def _sparse_points(json_path: Path, meta: dict, cameras, paths: list[Path]):
    """(xyz [P, 3] float64, per-view point indices, source file, rgb [P, 3] uint8, from_tracks,
    track lengths [P] or None) of the capture's SfM points in the json's world frame, or None (module
    doc: COLMAP model, else ply_file_path). ``from_tracks``: the per-view indices are COLMAP tracks,
    not projections."""
    folder = json_path.parent
    model_dir = find_colmap_model(folder)
    if model_dir is not None:
        model = read_colmap_model(model_dir)
        A = _applied_transform(json_path, meta)
        xyz = model.points.xyz @ A[:3, :3].T + A[:3, 3]
        by_name = {Path(im.name).name: v for v, im in enumerate(model.images)}
        per_image = model.visible_points()
        names = [p.name for p in paths]
        tracks = all(n in by_name for n in names)
        visible = [per_image[by_name[n]] for n in names] if tracks else visible_points_by_projection(cameras, xyz)
        return xyz, visible, model_dir, model.points.rgb, tracks, model.points.track_lengths
    ply = meta.get("ply_file_path")
    if ply:
        ply_path = folder / str(ply)
        if not ply_path.is_file():
            raise DatasetError(ply_path, f"missing point cloud (ply_file_path in {json_path.name})")
        import trimesh  # heavy optional dependency (trimesh, about 1 s to import): only for a scene's point-cloud PLY

        try:
            cloud = trimesh.load(ply_path, process=False)
            xyz = np.asarray(cloud.vertices, dtype=np.float64)
        except Exception as exc:
            raise DatasetError(ply_path, f"unreadable point cloud ({type(exc).__name__}: {exc})") from exc
        colours = getattr(getattr(cloud, "visual", None), "vertex_colors", None)
        rgb = (np.asarray(colours)[:, :3].astype(np.uint8) if colours is not None and len(colours) == len(xyz)
               else np.full((len(xyz), 3), 128, dtype=np.uint8))
        return xyz, visible_points_by_projection(cameras, xyz), ply_path, rgb, False, None
    return None
