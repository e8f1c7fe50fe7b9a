"""A ROS 2 bag of an export, written with the pure-Python ``rosbags`` (no ROS installation).

``stochastic-fields rosbag --export OUT --out BAG`` reads an export folder (``views/<name>.npz``
and, when present, ``clouds/<name>.ply``) and writes one message per view and topic, view v at
``t = v * period`` (default 0.1 s), storage MCAP (or sqlite3), ROS 2 Humble message definitions:

    /camera/depth/image           sensor_msgs/Image 32FC1, camera-z depth in metres, NaN = invalid (REP 118)
    /camera/depth/std             sensor_msgs/Image 32FC1, total depth std in metres, NaN = invalid
    /camera/depth/camera_info     sensor_msgs/CameraInfo (K, P with integer pixel centres, see ros_depth)
    /camera/color/image           sensor_msgs/Image rgb8, the rendered colour mean
    /camera/points                sensor_msgs/PointCloud2 in the world frame (metres): x y z float32,
                                  rgb float32 (packed), depth_std float32 (metres), confidence float32
    /tf                           tf2_msgs/TFMessage world -> <name>_optical (the camera pose, metres)

Metres need a scale: the npz's ``metres_per_unit`` (written by ``export --metres-per-unit``) or
``--metres-per-unit`` here; none -> ValueError. Frames: image messages carry
``frame_id = <name>_optical`` (REP 103 optical frame: x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .depth_maps import DepthProducts
from .ros_depth import MetricScale, camera_info
from .pointcloud import read_ply
from ..defaults import ROSBAG_PERIOD_S  # noqa: F401  (defaults the command line shows)

#: PointCloud2 datatype code for FLOAT32 (sensor_msgs/PointField).
POINTFIELD_FLOAT32: int = 7
#: PointCloud2 fields written (all float32).
CLOUD_FIELDS: tuple[str, ...] = ("x", "y", "z", "rgb", "depth_std", "confidence")
TOPICS = {"depth": "/camera/depth/image", "std": "/camera/depth/std", "info": "/camera/depth/camera_info",
          "colour": "/camera/color/image", "points": "/camera/points", "tf": "/tf"}


@dataclass
class ExportedView:
    """One view of an export folder: its npz arrays and (optionally) its point cloud."""

    name: str
    arrays: dict
    cloud: object | None  # pointcloud.CloudArrays
    colours: np.ndarray | None = None  # [N, 3] uint8 as the PLY stores them

    def products(self) -> DepthProducts:
        """A DepthProducts holding what the bag and the recording need (from the npz)."""
        z = self.arrays
        mpu = float(z["metres_per_unit"]) if "metres_per_unit" in z else math.nan
        return DepthProducts(
            depth_mean=z["depth_mean"], depth_std=z["depth_std"], depth_std_epistemic=z["depth_std_epistemic"],
            depth_std_spread=z["depth_std_spread"], opacity=z["opacity"], depth_quantiles=z["depth_quantiles"],
            quantile_levels=z["quantile_levels"], colour_mean=z["colour_mean"], valid=z["valid"],
            intrinsics=z["intrinsics"], world_to_camera=z["world_to_camera"], num_draws=int(z["num_draws"]),
            near=float(z["near"]), far=float(z["far"]), units=str(z["units"]), min_opacity=float(z["min_opacity"]),
            colour_std=z.get("colour_std"), metres_per_unit=None if math.isnan(mpu) else mpu,
            scale_source=str(z["scale_source"]) if "scale_source" in z else "unknown")


def load_export(export_dir: str | Path) -> list[ExportedView]:
    """The views of an export folder, sorted by name (npz files other than ``*_free_space.npz``)."""
    export_dir = Path(export_dir)
    vdir = export_dir / "views"
    paths = sorted(p for p in vdir.glob("*.npz") if not p.name.endswith("_free_space.npz")) if vdir.is_dir() else []
    if not paths:
        raise FileNotFoundError(f"{export_dir}: no views/*.npz (run `stochastic-fields export` with the npz format)")
    out = []
    for p in paths:
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        if "intrinsics" not in arrays:
            raise ValueError(f"{p}: not an export npz (no intrinsics)")
        ply = export_dir / "clouds" / f"{p.stem}.ply"
        cloud, colours = read_ply(ply) if ply.is_file() else (None, None)
        out.append(ExportedView(p.stem, arrays, cloud, colours))
    return out


def resolve_scale(view: ExportedView, metres_per_unit: float | None) -> MetricScale:
    """The metric scale of a view: the option if given, else the npz's; ValueError if neither."""
    if metres_per_unit is not None:
        return MetricScale(float(metres_per_unit), "--metres-per-unit (given by the user)")
    mpu = float(view.arrays.get("metres_per_unit", math.nan))
    if math.isnan(mpu):
        raise ValueError(f"view {view.name}: the export has no metric scale; give --metres-per-unit (scene units "
                         "are not metres for LLFF or structure-from-motion captures)")
    return MetricScale(mpu, str(view.arrays.get("scale_source", "export")))


def pack_rgb_float(rgb: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 -> [N] float32 whose bits are 0x00RRGGBB (PCL / RViz ``rgb`` field)."""
    rgb = np.asarray(rgb, np.uint32)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).astype(np.uint32).view(np.float32)


def cloud_array(view: ExportedView, scale: MetricScale) -> np.ndarray:
    """[N, 6] float32 rows (x, y, z in metres, rgb packed, depth_std in metres, confidence)."""
    c = view.cloud
    if c is None or len(c) == 0:
        return np.zeros((0, len(CLOUD_FIELDS)), np.float32)
    m = scale.metres_per_unit
    rgb = view.colours if view.colours is not None else np.clip(np.round(c.rgb * 255), 0, 255).astype(np.uint8)
    return np.column_stack([c.positions * m, pack_rgb_float(rgb), c.attributes["depth_std"] * m,
                            c.attributes["confidence"]]).astype(np.float32)


def write_rosbag(export_dir: str | Path, out: str | Path, *, metres_per_unit: float | None = None,
                 period_s: float = ROSBAG_PERIOD_S, storage: str = "mcap") -> dict:
    """Write the bag (module doc). ``out`` must not exist (rosbags refuses to overwrite).
    Returns {topic: message count}."""
    from rosbags.rosbag2 import StoragePlugin, Writer  # heavy optional dependency (rosbags): loaded only when used
    from rosbags.typesys import Stores, get_typestore  # heavy optional dependency (rosbags): loaded only when used

    views = load_export(export_dir)
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists; rosbag output must be a new folder")
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise ValueError(f"--storage must be 'mcap' or 'sqlite3', got {storage!r}")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Image, Info, Cloud = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"], T["sensor_msgs/msg/PointCloud2"]
    Field, Header, Time = T["sensor_msgs/msg/PointField"], T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    ROI, TFM = T["sensor_msgs/msg/RegionOfInterest"], T["tf2_msgs/msg/TFMessage"]
    TS, Tr = T["geometry_msgs/msg/TransformStamped"], T["geometry_msgs/msg/Transform"]
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    counts = {t: 0 for t in TOPICS.values()}
    out.parent.mkdir(parents=True, exist_ok=True)
    with Writer(out, version=9, storage_plugin=plugin) as w:
        conns = {
            TOPICS["depth"]: w.add_connection(TOPICS["depth"], Image.__msgtype__, typestore=ts),
            TOPICS["std"]: w.add_connection(TOPICS["std"], Image.__msgtype__, typestore=ts),
            TOPICS["info"]: w.add_connection(TOPICS["info"], Info.__msgtype__, typestore=ts),
            TOPICS["colour"]: w.add_connection(TOPICS["colour"], Image.__msgtype__, typestore=ts),
            TOPICS["points"]: w.add_connection(TOPICS["points"], Cloud.__msgtype__, typestore=ts),
            TOPICS["tf"]: w.add_connection(TOPICS["tf"], TFM.__msgtype__, typestore=ts),
        }

        def put(topic, msg, stamp_ns):
            w.write(conns[topic], stamp_ns, ts.serialize_cdr(msg, msg.__msgtype__))
            counts[topic] += 1

        for v, view in enumerate(views):
            scale = resolve_scale(view, metres_per_unit)
            p = view.products()
            stamp_ns = int(round(v * period_s * 1e9))
            frame = f"{view.name}_optical"
            hdr = Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame)
            H, W = p.shape
            m = scale.metres_per_unit
            for topic, arr in ((TOPICS["depth"], p.depth_mean), (TOPICS["std"], p.depth_std)):
                img = np.where(p.valid, arr.astype(np.float64) * m, np.nan).astype("<f4")
                put(topic, Image(header=hdr, height=H, width=W, encoding="32FC1", is_bigendian=0, step=4 * W,
                                 data=np.ascontiguousarray(img).view(np.uint8).reshape(-1)), stamp_ns)
            rgb = np.clip(np.round(p.colour_mean * 255), 0, 255).astype(np.uint8)
            put(TOPICS["colour"], Image(header=hdr, height=H, width=W, encoding="rgb8", is_bigendian=0, step=3 * W,
                                        data=rgb.reshape(-1)), stamp_ns)
            info = camera_info(p, scale, frame_id=frame, stamp_ns=stamp_ns)
            put(TOPICS["info"], Info(header=hdr, height=H, width=W, distortion_model=info["distortion_model"],
                                     d=np.asarray(info["D"], np.float64), k=np.asarray(info["K"], np.float64),
                                     r=np.asarray(info["R"], np.float64), p=np.asarray(info["P"], np.float64),
                                     binning_x=0, binning_y=0,
                                     roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)), stamp_ns)
            c2w = np.asarray(info["camera_to_world"])
            qx, qy, qz, qw = _quaternion(c2w[:3, :3])
            tf = TS(header=Header(stamp=hdr.stamp, frame_id="world"), child_frame_id=frame,
                    transform=Tr(translation=V3(x=float(c2w[0, 3]), y=float(c2w[1, 3]), z=float(c2w[2, 3])),
                                 rotation=Q(x=qx, y=qy, z=qz, w=qw)))
            put(TOPICS["tf"], TFM(transforms=[tf]), stamp_ns)
            rows = cloud_array(view, scale)
            fields = [Field(name=n, offset=4 * i, datatype=POINTFIELD_FLOAT32, count=1) for i, n in enumerate(CLOUD_FIELDS)]
            put(TOPICS["points"], Cloud(header=Header(stamp=hdr.stamp, frame_id="world"), height=1, width=len(rows),
                                        fields=fields, is_bigendian=False, point_step=4 * len(CLOUD_FIELDS),
                                        row_step=4 * len(CLOUD_FIELDS) * len(rows),
                                        data=np.ascontiguousarray(rows.astype("<f4")).view(np.uint8).reshape(-1),
                                        is_dense=True), stamp_ns)
    return counts


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) unit quaternion of a rotation matrix [3, 3] (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = ((R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s)
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        q = (v[0], v[1], v[2], (R[k, j] - R[j, k]) / s)
    n = math.sqrt(sum(x * x for x in q))
    return tuple(float(x / n) for x in q)  # type: ignore[return-value]


# ------------------------------------------------------------------------------- CLI


def run(args) -> None:
    try:
        counts = write_rosbag(args.export, args.out, metres_per_unit=args.metres_per_unit, period_s=args.period,
                              storage=args.storage)
    except FileExistsError as exc:
        raise ValueError(str(exc)) from exc
    print(f"wrote ROS 2 bag {args.out}: " + ", ".join(f"{t} x{n}" for t, n in counts.items()))
