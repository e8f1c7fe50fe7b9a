"""Depth images as ROS and RGB-D tools read them (REP 118 / REP 117), with their std and camera.

REP 118 fixes two depth image encodings; we write both per view, with the matching std:

    <name>_depth_m.tiff       float32 camera-z depth in **metres**, NaN = invalid (REP 118 32FC1;
                              REP 117: NaN means "no return")
    <name>_depth_std_m.tiff   float32 total depth std in metres, NaN = invalid
    <name>_depth_mm.png       uint16 camera-z depth in **millimetres**, 0 = invalid (REP 118 16UC1)
    <name>_depth_std_mm.png   uint16 total depth std in millimetres, 0 = invalid
    <name>_camera_info.yaml   sensor_msgs/CameraInfo fields (K, D, R, P, width, height,
    <name>_camera_info.json   distortion_model) + the frame pose, the metric scale and its source

Metres: ``depth_m = depth_scene * metres_per_unit``. Scene units are metres only when somebody
says so: LLFF and structure-from-motion captures have an arbitrary scale, so the scale is an
input (``--metres-per-unit``, or a known distance between two camera centres, see
:func:`metres_per_unit_from_known_distance`) and is written into every file with its source.
Without a scale these files are not written (ValueError), never guessed.

16-bit millimetres: ``value = round(depth_m * 1000)``; 0 = invalid (opacity < min_opacity);
depths beyond 65.535 m cannot be represented and are written as 0 (counted in the metadata). A
valid std that rounds to 0 mm is written as 1 mm (0 would read as invalid).

Intrinsics convention: the project's K puts pixel centres at +0.5 (pixel (row i, col j) centre at
(u, v) = (j + 0.5, i + 0.5)). ROS CameraInfo, OpenCV and Open3D's ``PinholeCameraIntrinsic``
put pixel centres at integers ((u, v) = (j, i)), so the written cx, cy are ours minus 0.5
(``pixel_centre_convention`` in the metadata). Back-projecting pixel (i, j) with depth z:
``x = (j - cx) z / fx, y = (i - cy) z / fy``.

Open3D TSDF: :func:`integrate_tsdf_open3d` reads these files as they are (depth scale 1000 =
millimetres) into Open3D's tensor ``VoxelBlockGrid``. Open3D 0.20.0's legacy
``ScalableTSDFVolume`` integrates nothing (empty mesh, and an empty voxel cloud, even for a flat
plane; measured here) while the tensor route works in 0.19 and 0.20, so that is the route we use
and test.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import imageio.v3 as iio
import tifffile
import yaml

from ..io_utils import atomic_path, atomic_write_text
from .depth_maps import DepthProducts
from .export_options import MetricScale  # noqa: F401  (re-exported)

#: Millimetres per metre (REP 118 16UC1 depth is in millimetres).
MM_PER_METRE: float = 1000.0
#: Largest 16-bit value; 0 is reserved for "no depth".
UINT16_MAX: int = 65535
#: What the written intrinsics assume about pixel centres.
PIXEL_CENTRE_CONVENTION: str = (
    "integer: pixel (row i, column j) has its centre at (u, v) = (j, i), as in ROS CameraInfo, OpenCV "
    "and Open3D PinholeCameraIntrinsic; the project's own K (pixel centres at +0.5) has cx, cy larger by 0.5")
#: Truncation of the TSDF in voxels (Open3D's examples use 3-5).
TSDF_TRUNCATION_VOXELS: float = 4.0


def metres_per_unit_from_known_distance(world_to_camera: np.ndarray, i: int, j: int, metres: float) -> MetricScale:
    """Scale from a known distance: the centres of cameras ``i`` and ``j`` (world_to_camera [V, 4, 4])
    are ``metres`` apart. ``metres_per_unit = metres / |c_i - c_j|`` with ``c = -R^T t``."""
    w2c = np.asarray(world_to_camera, np.float64)
    V = w2c.shape[0]
    for k in (i, j):
        if not 0 <= k < V:
            raise ValueError(f"--known-distance: camera {k} out of range (the scene has {V} cameras, 0..{V - 1})")
    if i == j:
        raise ValueError(f"--known-distance needs two different cameras, got {i} and {j}")
    if not (math.isfinite(metres) and metres > 0):
        raise ValueError(f"--known-distance: the distance must be positive metres, got {metres}")
    centres = -np.einsum("vji,vj->vi", w2c[:, :3, :3], w2c[:, :3, 3])
    d = float(np.linalg.norm(centres[i] - centres[j]))
    if not d > 0:
        raise ValueError(f"--known-distance: cameras {i} and {j} share one centre; pick two cameras apart")
    return MetricScale(metres / d, f"known distance: camera centres {i} and {j} are {metres:g} m apart "
                                   f"({d:.6g} scene units)")


def ros_intrinsics(K: np.ndarray) -> np.ndarray:
    """[3, 3] project K (pixel centres at +0.5) -> [3, 3] K in the integer-centre convention
    (cx, cy minus 0.5). Example: cx = 32 for a 64-pixel-wide image -> 31.5."""
    out = np.asarray(K, np.float64).reshape(3, 3).copy()
    out[0, 2] -= 0.5
    out[1, 2] -= 0.5
    return out


def camera_info(products: DepthProducts, scale: MetricScale, *, frame_id: str, stamp_ns: int = 0) -> dict:
    """sensor_msgs/CameraInfo-like dict (row-major lists as in the message) plus the camera pose.

    ``K`` [9], ``D`` [5] zeros (``plumb_bob``: the renders are undistorted), ``R`` [9] identity,
    ``P`` [12] = [K | 0]; ``camera_to_world`` / ``world_to_camera`` [4][4] with translations in
    metres (OpenCV optical frame: x right, y down, z forward; REP 103 ``_optical`` frame).
    """
    K = ros_intrinsics(products.intrinsics)
    H, W = products.shape
    w2c = products.world_to_camera.copy()
    w2c[:3, 3] *= scale.metres_per_unit
    c2w = np.linalg.inv(w2c)
    P = np.concatenate([K, np.zeros((3, 1))], axis=1)
    return {
        "header": {"frame_id": frame_id, "stamp_ns": int(stamp_ns)},
        "width": int(W), "height": int(H),
        "distortion_model": "plumb_bob",
        "D": [0.0] * 5,
        "K": K.reshape(-1).tolist(),
        "R": np.eye(3).reshape(-1).tolist(),
        "P": P.reshape(-1).tolist(),
        "binning_x": 0, "binning_y": 0,
        "pixel_centre_convention": PIXEL_CENTRE_CONVENTION,
        "camera_to_world": c2w.tolist(),
        "world_to_camera": w2c.tolist(),
        "world_frame": "world",
        "units": "metres",
        "metres_per_unit": scale.metres_per_unit,
        "scale_source": scale.source,
        "depth_kind": "camera_z",
        "depth_images": {
            "float_metres": "32-bit float camera-z depth in metres, NaN = invalid (REP 118 32FC1)",
            "uint16_millimetres": "16-bit camera-z depth in millimetres, 0 = invalid (REP 118 16UC1)",
            "std": "total depth std (epistemic + termination spread) in the same units as its depth image",
        },
    }


def _yaml(info: dict) -> str:
    """CameraInfo YAML in the layout of ROS camera_calibration_parsers (plus our extra keys)."""
    K = info["K"]
    doc = {
        "image_width": info["width"], "image_height": info["height"], "camera_name": info["header"]["frame_id"],
        "camera_matrix": {"rows": 3, "cols": 3, "data": K},
        "distortion_model": info["distortion_model"],
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": info["D"]},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": info["R"]},
        "projection_matrix": {"rows": 3, "cols": 4, "data": info["P"]},
        **{k: info[k] for k in ("pixel_centre_convention", "camera_to_world", "world_to_camera", "world_frame",
                                "units", "metres_per_unit", "scale_source", "depth_kind")},
    }
    return yaml.safe_dump(doc, sort_keys=False)


def encode_uint16_mm(values_m: np.ndarray, valid: np.ndarray, *, min_value: int = 0) -> tuple[np.ndarray, int]:
    """[H, W] metres -> (uint16 millimetres, 0 where invalid or not representable; number of
    valid pixels beyond 65.535 m). ``min_value`` lifts valid values that round below it."""
    mm = np.asarray(values_m, np.float64) * MM_PER_METRE
    ok = np.asarray(valid, bool) & np.isfinite(mm) & (mm >= 0)
    r = np.round(np.where(ok, mm, 0.0))
    over = ok & (r > UINT16_MAX)
    ok &= ~over
    out = np.where(ok, np.clip(r, min_value, UINT16_MAX), 0).astype(np.uint16)
    return out, int(over.sum())


def write_ros_depth(views_dir: str | Path, name: str, products: DepthProducts, scale: MetricScale, *,
                    frame_id: str | None = None) -> list[Path]:
    """Write the REP 118 depth images, their std and the CameraInfo of one view (module doc).
    Returns the written paths (each atomic)."""
    views_dir = Path(views_dir)
    m = scale.metres_per_unit
    valid = products.valid
    depth_m = np.where(valid, products.depth_mean.astype(np.float64) * m, np.nan).astype(np.float32)
    std_m = np.where(valid, products.depth_std.astype(np.float64) * m, np.nan).astype(np.float32)
    depth_mm, over = encode_uint16_mm(depth_m, valid & (depth_m > 0), min_value=1)
    std_mm, _ = encode_uint16_mm(std_m, valid & (depth_mm > 0), min_value=1)
    info = camera_info(products, scale, frame_id=frame_id or f"{name}_optical")
    info["uint16_depth_beyond_range"] = over
    files = []
    for suffix, img, desc in (("depth_m", depth_m, "camera-z depth"), ("depth_std_m", std_m, "total depth std")):
        path = views_dir / f"{name}_{suffix}.tiff"
        meta = json.dumps({"quantity": desc, "units": "metres", "nodata": "nan", "depth_kind": "camera_z",
                           "metres_per_unit": m, "scale_source": scale.source,
                           "camera_info": f"{name}_camera_info.json"})
        with atomic_path(path) as tmp:
            tifffile.imwrite(tmp, img, photometric="minisblack", description=meta, metadata=None)
        files.append(path)
    for suffix, img in (("depth_mm", depth_mm), ("depth_std_mm", std_mm)):
        path = views_dir / f"{name}_{suffix}.png"
        with atomic_path(path) as tmp:
            iio.imwrite(tmp, img, extension=".png")
        files.append(path)
    js = views_dir / f"{name}_camera_info.json"
    atomic_write_text(js, json.dumps(info, indent=2))
    ym = views_dir / f"{name}_camera_info.yaml"
    atomic_write_text(ym, _yaml(info))
    return files + [js, ym]


def read_camera_info(path: str | Path) -> dict:
    """CameraInfo dict from a ``_camera_info.json`` written by :func:`write_ros_depth`."""
    return json.loads(Path(path).read_text())


# ------------------------------------------------------------------------------- Open3D TSDF
def integrate_tsdf_open3d(views: Sequence[tuple[Path, Path]], *, voxel_size: float,
                          max_std_mm: float | None = None, depth_max_m: float = 65.0,
                          std_images: Sequence[Path] | None = None):
    """TSDF mesh (``open3d.t.geometry.TriangleMesh``, world coordinates in metres) from exported
    ``(<name>_depth_mm.png, <name>_camera_info.json)`` pairs, read as they are: depth scale 1000,
    K and world_to_camera from the CameraInfo. With ``max_std_mm`` (and the matching
    ``<name>_depth_std_mm.png`` in ``std_images``), pixels whose std exceeds it are dropped first
    (confidence-masked integration).

    Open3D ``VoxelBlockGrid`` (tensor TSDF); truncation ``TSDF_TRUNCATION_VOXELS * voxel_size``;
    the mesh keeps voxels observed at least once (``weight_threshold`` below one frame's weight).
    """
    import open3d as o3d  # heavy optional dependency (Open3D): loaded only when used

    if max_std_mm is not None and (std_images is None or len(std_images) != len(views)):
        raise ValueError("integrate_tsdf_open3d: max_std_mm needs one std image per view")
    dev = o3d.core.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3d.core.float32, o3d.core.float32),
                                        attr_channels=((1), (1)), voxel_size=float(voxel_size), block_resolution=8,
                                        block_count=50_000, device=dev)
    for n, (depth_path, info_path) in enumerate(views):
        info = read_camera_info(info_path)
        depth = o3d.t.io.read_image(str(depth_path))
        if max_std_mm is not None:
            d = depth.as_tensor().numpy().copy()
            std = o3d.t.io.read_image(str(std_images[n])).as_tensor().numpy()
            d[std > max_std_mm] = 0
            depth = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(d)))
        K = o3d.core.Tensor(np.asarray(info["K"], np.float64).reshape(3, 3))
        E = o3d.core.Tensor(np.asarray(info["world_to_camera"], np.float64))
        blocks = vbg.compute_unique_block_coordinates(depth, K, E, MM_PER_METRE, depth_max_m, TSDF_TRUNCATION_VOXELS)
        vbg.integrate(blocks, depth, K, E, MM_PER_METRE, depth_max_m, TSDF_TRUNCATION_VOXELS)
    return vbg.extract_triangle_mesh(weight_threshold=0.5)
