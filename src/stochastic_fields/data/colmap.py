"""COLMAP sparse models: full models through pycolmap, and a small reader for partial ones.

* :func:`read_colmap_model` reads a complete model (``cameras``, ``images``, ``points3D``, binary
  or text, as COLMAP and pycolmap write them) with pycolmap: registered images with their
  world-to-camera poses, cameras with their distortion, points with their tracks.
* :func:`read_cameras_binary` / :func:`read_points3d_binary` are kept for *partial* models:
  the LLFF scenes ship ``sparse/0`` with ``cameras.bin`` and ``points3D.bin`` but no
  ``images.bin``, which pycolmap's reader refuses ("... files do not exist"). Both readers return
  the same :class:`ColmapCamera` / :class:`ColmapPoints`, so everything downstream (sparse depth,
  scene bounds) has one code path.
* :func:`undistort_image` resamples a distorted photo to the pinhole camera with the same focal
  lengths, principal point and size, using pycolmap's camera models (exact, every COLMAP model).

Poses: COLMAP's ``cam_from_world`` is world-to-camera in the OpenCV convention (x right, y down,
z forward), the convention of this package, so no axis change is needed.

Binary layout read by hand (COLMAP docs, "Output format", binary; little-endian):

Layout (COLMAP docs, "Output format", binary; little-endian):

``cameras.bin``::

    uint64 num_cameras
    repeat: int32 camera_id, int32 model_id, uint64 width, uint64 height,
            float64 params[num_params(model_id)]

``points3D.bin``::

    uint64 num_points
    repeat: uint64 point3D_id, float64 xyz[3], uint8 rgb[3], float64 error,
            uint64 track_length, repeat track_length: (int32 image_id, int32 point2D_idx)

COLMAP pixel coordinates put pixel centres at +0.5 (the image spans [0, W] x [0, H]), the
convention this package uses for every camera.
"""

from __future__ import annotations

import functools
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .errors import DatasetError

#: COLMAP camera model id -> (name, number of parameters).
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}


@dataclass
class ColmapCamera:
    """One COLMAP camera: model name, image size and raw parameters (f/cx/cy first, as COLMAP)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [num_params] float64


@dataclass
class ColmapPoints:
    """COLMAP sparse points with their tracks in compressed (CSR) form.

    Shapes:
        ids: [P] uint64 point3D ids.
        xyz: [P, 3] float64 world positions.
        rgb: [P, 3] uint8 colours.
        error: [P] float64 mean reprojection error in pixels.
        track_offsets: [P + 1] int64; point p's track is entries
            ``track_offsets[p]:track_offsets[p + 1]`` of the two arrays below.
        track_image_ids: [T] int32 COLMAP image ids observing the points.
        track_point2d_idx: [T] int32 keypoint index within those images.
    """

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    track_offsets: np.ndarray
    track_image_ids: np.ndarray
    track_point2d_idx: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def track_lengths(self) -> np.ndarray:
        """[P] number of images that observe each point."""
        return np.diff(self.track_offsets)


def _read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read COLMAP file ({exc.strerror or exc})") from exc


def _unpack(fmt: str, data: bytes, offset: int, path: Path) -> tuple:
    try:
        return struct.unpack_from(fmt, data, offset)
    except struct.error as exc:
        raise DatasetError(path, f"truncated COLMAP binary file at byte {offset}") from exc


def read_cameras_binary(path: str | Path) -> dict[int, ColmapCamera]:
    """Read ``cameras.bin`` into ``{camera_id: ColmapCamera}``."""
    path = Path(path)
    data = _read_bytes(path)
    (num,) = _unpack("<Q", data, 0, path)
    offset = 8
    cameras: dict[int, ColmapCamera] = {}
    for _ in range(num):
        camera_id, model_id, width, height = _unpack("<iiQQ", data, offset, path)
        offset += 24
        if model_id not in CAMERA_MODELS:
            raise DatasetError(path, f"unknown COLMAP camera model id {model_id} for camera {camera_id}")
        name, num_params = CAMERA_MODELS[model_id]
        params = np.array(_unpack(f"<{num_params}d", data, offset, path), dtype=np.float64)
        offset += 8 * num_params
        cameras[camera_id] = ColmapCamera(camera_id, name, int(width), int(height), params)
    if offset != len(data):
        raise DatasetError(path, f"{len(data) - offset} trailing bytes after {num} cameras")
    return cameras


def read_points3d_binary(path: str | Path) -> ColmapPoints:
    """Read ``points3D.bin`` into :class:`ColmapPoints` (xyz, rgb, error, tracks)."""
    path = Path(path)
    data = _read_bytes(path)
    (num,) = _unpack("<Q", data, 0, path)
    offset = 8
    ids = np.empty(num, dtype=np.uint64)
    xyz = np.empty((num, 3), dtype=np.float64)
    rgb = np.empty((num, 3), dtype=np.uint8)
    error = np.empty(num, dtype=np.float64)
    track_offsets = np.zeros(num + 1, dtype=np.int64)
    tracks: list[np.ndarray] = []
    head = struct.Struct("<Q3d3BdQ")  # 8 + 24 + 3 + 8 + 8 = 51 bytes
    for p in range(num):
        try:
            fields = head.unpack_from(data, offset)
        except struct.error as exc:
            raise DatasetError(path, f"truncated COLMAP binary file at point {p} (byte {offset})") from exc
        offset += head.size
        ids[p] = fields[0]
        xyz[p] = fields[1:4]
        rgb[p] = fields[4:7]
        error[p] = fields[7]
        length = fields[8]
        end = offset + 8 * length
        if end > len(data):
            raise DatasetError(path, f"truncated track of point {p}: needs {length} entries")
        tracks.append(np.frombuffer(data, dtype="<i4", count=2 * length, offset=offset).reshape(length, 2))
        offset = end
        track_offsets[p + 1] = track_offsets[p] + length
    if offset != len(data):
        raise DatasetError(path, f"{len(data) - offset} trailing bytes after {num} points")
    track = np.concatenate(tracks, axis=0) if tracks else np.zeros((0, 2), dtype=np.int32)
    return ColmapPoints(
        ids=ids,
        xyz=xyz,
        rgb=rgb,
        error=error,
        track_offsets=track_offsets,
        track_image_ids=track[:, 0].astype(np.int32),
        track_point2d_idx=track[:, 1].astype(np.int32),
    )


# ---------------------------------------------------------------------- full models (pycolmap)
#: Camera models without distortion: images are used as they are.
PINHOLE_MODELS: tuple[str, ...] = ("SIMPLE_PINHOLE", "PINHOLE")
#: Where a COLMAP model is looked for under a scene folder, in this order (COLMAP's own layout,
#: ns-process-data's ``colmap/sparse/0``, a bare model folder).
MODEL_SUBFOLDERS: tuple[str, ...] = ("sparse/0", "sparse", "colmap/sparse/0", "colmap/sparse", ".")


@dataclass
class ColmapImage:
    """One registered COLMAP image.

    Attributes:
        image_id: COLMAP image id.
        name: file name relative to the image folder (as COLMAP stores it).
        camera_id: id of its camera in ``ColmapModel.cameras``.
        world_to_camera: [4, 4] float64 OpenCV world-to-camera (COLMAP's ``cam_from_world``).
    """

    image_id: int
    name: str
    camera_id: int
    world_to_camera: np.ndarray


@dataclass
class ColmapModel:
    """A complete COLMAP sparse model: registered images (sorted by name), cameras, points.

    ``points.track_image_ids`` refer to ``ColmapImage.image_id``; :meth:`visible_points` turns
    them into per-image point indices.
    """

    path: Path
    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points: ColmapPoints
    mean_reprojection_error: float

    def visible_points(self) -> list[np.ndarray]:
        """Per image of ``images`` (same order), the sorted indices of the points its track lists."""
        owner = np.repeat(np.arange(len(self.points)), self.points.track_lengths)
        order = np.argsort(self.points.track_image_ids, kind="stable")
        ids_sorted = self.points.track_image_ids[order]
        out = []
        for image in self.images:
            lo, hi = np.searchsorted(ids_sorted, [image.image_id, image.image_id + 1])
            out.append(np.unique(owner[order[lo:hi]]))
        return out


def _model_files_present(folder: Path) -> bool:
    return all((folder / f"{n}.bin").is_file() or (folder / f"{n}.txt").is_file()
               for n in ("cameras", "images", "points3D"))


def find_colmap_model(root: str | Path) -> Path | None:
    """The first folder of ``MODEL_SUBFOLDERS`` under ``root`` holding a complete model, or None."""
    root = Path(root)
    for sub in MODEL_SUBFOLDERS:
        folder = (root / sub) if sub != "." else root
        if folder.is_dir() and _model_files_present(folder):
            return folder
    return None


def world_to_camera(image) -> np.ndarray:
    """The world-to-camera matrix [4, 4] (OpenCV axes) of a posed pycolmap Image."""
    w2c = np.eye(4)
    w2c[:3] = image.cam_from_world().matrix()
    return w2c


def read_colmap_model(path: str | Path) -> ColmapModel:
    """Read a complete COLMAP model folder (binary or text) with pycolmap.

    Only registered images (those with a pose) are returned, sorted by name. DatasetError naming
    the folder if pycolmap cannot read it or it registers no image.
    """
    import pycolmap  # heavy optional dependency (pycolmap): loaded only when used

    path = Path(path)
    if not path.is_dir():
        raise DatasetError(path, "missing COLMAP model folder")
    if not _model_files_present(path):
        missing = [n for n in ("cameras", "images", "points3D")
                   if not ((path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file())]
        raise DatasetError(path, f"incomplete COLMAP model: no {', '.join(m + '.bin' for m in missing)}")
    try:
        rec = pycolmap.Reconstruction(path)
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with COLMAP's message
        raise DatasetError(path, f"pycolmap cannot read the COLMAP model ({type(exc).__name__}: {exc})") from exc
    cameras = {int(cid): ColmapCamera(int(cid), c.model.name, int(c.width), int(c.height),
                                      np.asarray(c.params, dtype=np.float64))
               for cid, c in rec.cameras.items()}
    images = []
    for iid, im in rec.images.items():
        if not im.has_pose:
            continue
        images.append(ColmapImage(int(iid), str(im.name), int(im.camera_id), world_to_camera(im)))
    if not images:
        raise DatasetError(path, "the COLMAP model has no registered image")
    images.sort(key=lambda im: im.name)
    pids = sorted(rec.points3D.keys())
    num = len(pids)
    xyz = np.empty((num, 3), dtype=np.float64)
    rgb = np.empty((num, 3), dtype=np.uint8)
    error = np.empty(num, dtype=np.float64)
    offsets = np.zeros(num + 1, dtype=np.int64)
    track: list[tuple[int, int]] = []
    for p, pid in enumerate(pids):
        point = rec.points3D[pid]
        xyz[p] = point.xyz
        rgb[p] = point.color
        error[p] = point.error
        elements = point.track.elements
        track.extend((int(e.image_id), int(e.point2D_idx)) for e in elements)
        offsets[p + 1] = offsets[p] + len(elements)
    track_arr = np.asarray(track, dtype=np.int64).reshape(-1, 2)
    points = ColmapPoints(ids=np.asarray(pids, dtype=np.uint64), xyz=xyz, rgb=rgb, error=error,
                          track_offsets=offsets, track_image_ids=track_arr[:, 0].astype(np.int32),
                          track_point2d_idx=track_arr[:, 1].astype(np.int32))
    return ColmapModel(path=path, cameras=cameras, images=images, points=points,
                       mean_reprojection_error=float(rec.compute_mean_reprojection_error()))


# ---------------------------------------------------------------------- camera models
def pycolmap_camera(camera: ColmapCamera):
    """The pycolmap.Camera of a :class:`ColmapCamera` (for projections and rescaling)."""
    import pycolmap  # heavy optional dependency (pycolmap): loaded only when used

    try:
        return pycolmap.Camera(model=camera.model, width=int(camera.width), height=int(camera.height),
                               params=[float(x) for x in camera.params])
    except Exception as exc:
        raise ValueError(f"camera {camera.camera_id}: not a valid COLMAP camera ({camera.model}, "
                         f"{camera.width}x{camera.height}, params {camera.params.tolist()}): {exc}") from exc


def rescale_camera(camera: ColmapCamera, width: int, height: int) -> ColmapCamera:
    """The same camera for images resized to ``width`` x ``height`` (focal lengths and principal
    point scale with the picture; distortion coefficients act on normalised coordinates and stay)."""
    if (width, height) == (camera.width, camera.height):
        return camera
    if camera.model == "PINHOLE":
        sx, sy = width / camera.width, height / camera.height
        params = camera.params * np.array([sx, sy, sx, sy])
        return ColmapCamera(camera.camera_id, camera.model, int(width), int(height), params)
    pc = pycolmap_camera(camera)
    pc.rescale(int(width), int(height))
    return ColmapCamera(camera.camera_id, camera.model, int(width), int(height), np.asarray(pc.params, dtype=np.float64))


def pinhole_intrinsics(camera: ColmapCamera) -> np.ndarray:
    """[3, 3] K of the camera's pinhole part (fx, fy, cx, cy; distortion left out)."""
    if camera.model == "PINHOLE":
        fx, fy, cx, cy = camera.params
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    pc = pycolmap_camera(camera)
    return np.array([[pc.focal_length_x, 0.0, pc.principal_point_x],
                     [0.0, pc.focal_length_y, pc.principal_point_y],
                     [0.0, 0.0, 1.0]])


def undistort_image(image: np.ndarray, camera: ColmapCamera) -> tuple[np.ndarray, np.ndarray]:
    """Resample a photo of a distorted camera to the undistorted pinhole camera.

    The pinhole camera keeps the image size and ``K = pinhole_intrinsics(camera)``. Each of its
    pixel centres ``(u, v)`` (at +0.5) is a ray ``((u - cx) / fx, (v - cy) / fy, 1)``; pycolmap's
    ``img_from_cam`` gives where the distorted camera sees that ray, and the photo is sampled
    there bicubically (Keys' cubic convolution, a = -0.75, as ``torch.nn.functional.grid_sample``
    and OpenCV's INTER_CUBIC; taps outside the photo take the nearest border pixel), the result
    clipped to the photo's value range. Bicubic rather than bilinear: the picture is resampled
    once more when a ray's colour is read at a continuous pixel position, and two bilinear steps
    blur it (fern, ``images_8``: the mean colour difference between the SfM points and the
    undistorted images at their projections is 0.108 bilinear, 0.097 bicubic; the distorted
    photos read at the distorted positions, no resampling at all, 0.091). Rays that leave the
    distorted image take its edge (a few pixels at the corners for typical phone lenses).

    Shapes: image [H, W, C] float32 -> ([H, W, C] float32, [3, 3] float64).
    """
    K = pinhole_intrinsics(camera)
    H, W = image.shape[:2]
    if (W, H) != (camera.width, camera.height):
        raise ValueError(f"camera {camera.camera_id} is {camera.width}x{camera.height} but the image is {W}x{H}")
    if camera.model in PINHOLE_MODELS:
        return image, K
    grid = _undistortion_grid(camera.model, int(W), int(H), tuple(float(x) for x in camera.params))
    src = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    out = F.grid_sample(src, grid[None], mode="bicubic", padding_mode="border", align_corners=False)
    out = out.clamp(float(src.min()), float(src.max()))
    return out[0].permute(1, 2, 0).contiguous().numpy(), K


@functools.lru_cache(maxsize=8)
def _undistortion_grid(model: str, W: int, H: int, params: tuple[float, ...]) -> torch.Tensor:
    """[H, W, 2] grid_sample coordinates (align_corners=False) of the distorted pixel each pinhole
    pixel centre sees; cached, as every frame of a capture usually shares one camera."""
    camera = ColmapCamera(0, model, W, H, np.asarray(params))
    K = pinhole_intrinsics(camera)
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
    uv = np.asarray(pycolmap_camera(camera).img_from_cam(rays, check_cheirality=False), dtype=np.float64)
    uv = uv.reshape(H, W, 2)
    grid = np.stack([uv[..., 0] / W * 2.0 - 1.0, uv[..., 1] / H * 2.0 - 1.0], axis=-1)
    return torch.from_numpy(grid).float()


def undistortion_shift(camera: ColmapCamera) -> tuple[float, float]:
    """How far :func:`undistort_image` moves the picture of a camera.

    Returns (largest distance in pixels between a pinhole pixel centre and the distorted pixel it
    samples, fraction of pinhole pixels whose sample lies outside the distorted image and so takes
    the nearest border pixel). (0, 0) for pinhole models.
    """
    if camera.model in PINHOLE_MODELS:
        return 0.0, 0.0
    W, H = int(camera.width), int(camera.height)
    grid = _undistortion_grid(camera.model, W, H, tuple(float(x) for x in camera.params)).double().numpy()
    src_u, src_v = (grid[..., 0] + 1.0) * W / 2.0, (grid[..., 1] + 1.0) * H / 2.0
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    shift = float(np.hypot(src_u - u, src_v - v).max())
    outside = (src_u < 0) | (src_u > W) | (src_v < 0) | (src_v > H)
    return shift, float(outside.mean())
