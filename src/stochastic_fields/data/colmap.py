"""A small reader for COLMAP's binary sparse model (``cameras.bin``, ``points3D.bin``).

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

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
