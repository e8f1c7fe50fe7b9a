"""``stochastic-fields export``: depth-uncertainty products of a trained run for a set of cameras.

For each camera (dataset views, or a ``cameras.json`` of intrinsics/poses), render K depth
trajectories and write (every file atomically, so an interrupted export leaves complete files
or none; the whole folder is written beside OUT as ``.OUT.partial-*`` and swapped in when
complete, so OUT is always one finished export, never a mix of an old and an interrupted one;
``summary.json`` marks a finished export):

    OUT/views/<name>.npz                 all maps, float32, + intrinsics/pose/units/K (depth_maps.write_npz)
    OUT/views/<name>_depth_mean.png/.json 16-bit depth + scale sidecar (also _depth_std, _depth_q<p>)
    OUT/views/<name>.tiff                float32 pages, NaN where invalid
    OUT/views/<name>_depth_vis.png       colourised depth mean/std with colour bars
    OUT/views/<name>_free_space.npz      P(depth > d) [T, H, W] for --free-space-thresholds (the
                                         bands' predictive distribution; the draws' fraction beside it)
    OUT/views/<name>_depth_m.tiff, _depth_mm.png, _depth_std_*, _camera_info.yaml/.json
                                         REP 118 depth in metres/millimetres (format 'ros', ros_depth.py)
    OUT/clouds/<name>.ply                filtered point cloud of the view (pointcloud.write_ply)
    OUT/fused.ply, OUT/fused_cloud.png   inverse-variance fusion of all views (--fuse)
    OUT/summary.json                     counts per stage, files, colour mapping, ground-truth checks

Ground-truth checks (when the scene has them): mean unsigned distance of the exported points to
the scene's ``scene.ply`` surface (Open3D ``RaycastingScene.compute_distance``), for all points
and for the 50% most confident; calibration of the depth intervals against ground-truth
camera-z depth over pixels that are valid and have a ground truth: Gaussian intervals
``mean +- z * depth_std`` (total std) and empirical draw-quantile intervals.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import trimesh

from ..cameras import generate_rays_for_view, intrinsics_3x3, make_cameras
from ..data.dataset import parse_views
from ..distributed import map_sharded
from ..renderer import seeded_chunks
from ..io_utils import atomic_folder, atomic_path, atomic_write_text, check_file_name, read_json
from .depth_maps import (CONVENTIONS, DepthProducts, check_quantile_levels, compute_depth_products,
                         draw_quantiles, quantile_name, write_colourised, write_npz, write_png16, write_tiff)
from .free_space import free_space_volume, predictive_free_space_volume
from .fusion import check_voxel_size, fuse_clouds
from .pointcloud import (CloudArrays, PointFilter, cloud_from_products, filter_cloud, most_confident,
                         uncertainty_range, write_ply)
from .render_cloud import render_cloud_png
from .ros_depth import metres_per_unit_from_known_distance, MetricScale, write_ros_depth
from ..calibration import load_run_calibration
from ..trainer import load_trained_model
from .export_options import DEFAULT_FORMATS, FORMATS, ExportOptions  # noqa: F401  (re-exported)

#: Tolerance on R^T R = I for a user's world_to_camera: poses typed or exported with 5-6
#: significant digits pass, a scaled or sheared matrix (off by 1e-2 or more) does not.
ROTATION_TOLERANCE: float = 1e-4
#: Central interval levels checked against ground truth, and their Gaussian half-widths in std.
CALIBRATION_LEVELS: dict[str, tuple[float, float]] = {"68": (0.682689492, 1.0), "90": (0.9, 1.644853627),
                                                      "95": (0.95, 1.959963985)}


@dataclass
class ViewSpec:
    """One camera to export: name, K [3, 3], world_to_camera [4, 4], size, camera-z bounds,
    and the ground-truth depth [H, W] (0 = none) when known."""

    name: str
    intrinsics: np.ndarray
    world_to_camera: np.ndarray
    height: int
    width: int
    near: float
    far: float
    gt_depth: np.ndarray | None = field(default=None, repr=False)
    index: int = 0
    """The view's index in its source (dataset view, or entry of the cameras file): seeds its noise."""


# ------------------------------------------------------------------------------- inputs
def _matrix(path: Path, i: int, cam: dict, key: str, shape: tuple[int, int]) -> np.ndarray:
    if key not in cam:
        raise ValueError(f"{path}: camera {i} has no {key!r} (need K, world_to_camera, width, height)")
    try:
        arr = np.asarray(cam[key], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: camera {i}: {key!r} is not a numeric matrix: {cam[key]!r}") from exc
    if arr.shape != shape:
        raise ValueError(f"{path}: camera {i}: {key!r} must be {shape[0]}x{shape[1]}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{path}: camera {i}: {key!r} has non-finite values: {arr.tolist()}")
    return arr


def load_cameras_json(path: str | Path, *, default_near: float, default_far: float) -> list[ViewSpec]:
    """Cameras from a JSON file: a list (or ``{"cameras": [...]}``) of objects with ``K`` (3x3,
    OpenCV, pixel centres at +0.5), ``world_to_camera`` (4x4 OpenCV, rigid), ``width``,
    ``height``, optional ``near``/``far`` (camera-z; default: the run's bounds) and ``name``.
    Raises FileNotFoundError / ValueError naming the file, the camera and the bad value."""
    path = Path(path)
    data = read_json(path, "cameras file")
    if isinstance(data, dict) and "cameras" in data:
        data = data["cameras"]
    if not isinstance(data, list) or not data:
        raise ValueError(f"{path}: expected a non-empty list of cameras, got {type(data).__name__}")
    specs = []
    for i, cam in enumerate(data):
        if not isinstance(cam, dict):
            raise ValueError(f"{path}: camera {i} must be an object, got {cam!r}")
        K = _matrix(path, i, cam, "K", (3, 3))
        w2c = _matrix(path, i, cam, "world_to_camera", (4, 4))
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[0, 1] == 0 and np.allclose(K[2], [0, 0, 1])):
            raise ValueError(f"{path}: camera {i}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                             f"got {K.tolist()}")
        R = w2c[:3, :3]
        if not np.allclose(w2c[3], [0, 0, 0, 1]) or not np.allclose(R.T @ R, np.eye(3), atol=ROTATION_TOLERANCE) \
                or np.linalg.det(R) <= 0:
            raise ValueError(f"{path}: camera {i}: world_to_camera must be a rigid transform [[R, t], [0, 0, 0, 1]] "
                             f"with R a rotation, got {w2c.tolist()}")
        size = {}
        for key in ("width", "height"):
            v = cam.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or int(v) < 1:
                raise ValueError(f"{path}: camera {i}: {key!r} must be a positive integer, got {v!r}")
            size[key] = int(v)
        try:
            near = float(cam.get("near", default_near))
            far = float(cam.get("far", default_far))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: camera {i}: 'near'/'far' must be numbers, got near={cam.get('near')!r} "
                             f"far={cam.get('far')!r}") from exc
        if not (0 < near < far and math.isfinite(far)):
            raise ValueError(f"{path}: camera {i}: need 0 < near < far, got near={near} far={far}")
        name = cam.get("name", f"cam_{i:03d}")
        check_file_name(name, f"{path}: camera {i}: 'name'")
        specs.append(ViewSpec(name, K, w2c, size["height"], size["width"], near, far, index=i))
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: camera names must be unique, got {names}")
    return specs


def dataset_view_specs(dataset, views: Sequence[int]) -> list[ViewSpec]:
    """ViewSpecs of dataset views (with ground-truth depth when the dataset has it)."""
    K = intrinsics_3x3(dataset.cameras).double().cpu().numpy()
    w2c = dataset.cameras.extrinsics.double().cpu().numpy()
    specs = []
    for v in views:
        gt = dataset.depths[v].numpy() if getattr(dataset, "depths", None) is not None else None
        specs.append(ViewSpec(f"view_{v:03d}", K[v], w2c[v], dataset.height, dataset.width, float(dataset.near[v]),
                              float(dataset.far[v]), gt, index=int(v)))
    return specs


# ------------------------------------------------------------------------------- rendering
def render_products(model, spec: ViewSpec, opts: ExportOptions, calibration=None) -> DepthProducts:
    """Render one camera with K draws and return its depth products (draws kept; ``calibration``:
    the run's depth recalibration, see ``compute_depth_products``). Noise: ``seeded_chunks(opts.seed,
    spec.index)``, as evaluation and the notebook seed a dataset view."""
    device = next(model.parameters()).device
    cams = make_cameras(torch.from_numpy(spec.intrinsics).float()[None],
                        torch.from_numpy(spec.world_to_camera).float()[None], spec.height, spec.width)
    rays = generate_rays_for_view(cams, 0, spec.near, spec.far).to(device)
    maps = model.render_view(rays, model.render_options(num_draws=opts.num_draws, keep_draws=True),
                             generator=seeded_chunks(opts.seed, spec.index, device))
    return compute_depth_products(maps, intrinsics_3x3(cams)[0].double().numpy(), cams.extrinsics[0].double().numpy(),
                                  near=spec.near, far=spec.far, quantiles=opts.quantiles,
                                  min_opacity=opts.min_opacity, units=opts.units, keep_draws=True,
                                  calibration=calibration)


def write_view_files(out_dir: Path, name: str, products: DepthProducts, opts: ExportOptions) -> list[Path]:
    """Write the per-view map files of ``opts.formats`` (+ free-space volume). Returns the paths."""
    views_dir = out_dir / "views"
    files: list[Path] = []
    scale = opts.metric_scale()
    if scale is not None:
        products.metres_per_unit, products.scale_source = scale.metres_per_unit, scale.source
    if "npz" in opts.formats:
        files.append(write_npz(views_dir / f"{name}.npz", products, include_draws=opts.save_draws))
    if "png16" in opts.formats:
        maps = products.maps()
        for qname in ["depth_mean", "depth_std"] + [quantile_name(float(q)) for q in products.quantile_levels]:
            files.extend(write_png16(views_dir / f"{name}_{qname}.png", maps[qname], products.valid,
                                     max_depth=products.far, units=products.units, quantity=qname))
    if "tiff" in opts.formats:
        files.append(write_tiff(views_dir / f"{name}.tiff", products))
    if "ros" in opts.formats:
        files.extend(write_ros_depth(views_dir, name, products, scale))
    if "png" in opts.formats:
        files.append(write_colourised(views_dir / f"{name}_depth_vis.png", products, title=name))
    if opts.free_space_thresholds:
        vol = predictive_free_space_volume(products.depth_mean, products.depth_std, opts.free_space_thresholds,
                                           products.band_multiplier).astype(np.float32)
        draws = free_space_volume(torch.from_numpy(products.depth_draws), opts.free_space_thresholds).float().numpy()
        path = views_dir / f"{name}_free_space.npz"
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, prob_depth_greater=vol, prob_depth_greater_draws=draws,
                                    thresholds=np.asarray(opts.free_space_thresholds, np.float32),
                                    num_draws=np.int64(products.num_draws), units=np.str_(products.units),
                                    intrinsics=products.intrinsics, world_to_camera=products.world_to_camera,
                                    conventions=np.str_("prob_depth_greater[t, i, j] = P(camera-z depth at pixel (i, j) "
                                                        "> thresholds[t]) under the predictive distribution of the "
                                                        "depth bands and depth_std (symmetric about depth_mean, central "
                                                        "level-p interval depth_mean +- z_p m(p) depth_std, m the run's "
                                                        "level map; 1 - the band's (1 + p) / 2 quantile); "
                                                        "prob_depth_greater_draws = the fraction of the K draws' "
                                                        "expected depths beyond it (epistemic part only); "
                                                        + CONVENTIONS))
        files.append(path)
    return files


# ------------------------------------------------------------------------------- ground truth
class CalibrationAccumulator:
    """Pools (gt, mean, std, draw quantiles) over the valid pixels with a ground truth."""

    QUANTILE_LEVELS = (0.158655254, 0.841344746, 0.025, 0.975)  # central 68.27% and 95% draw intervals

    def __init__(self) -> None:
        self.rows: list[np.ndarray] = []
        self.num_gt = 0
        self.num_valid = 0
        self.band_multiplier = None  # m(p) of a recalibrated run (DepthProducts.band_multiplier), else None

    def add(self, products: DepthProducts, gt_depth: np.ndarray | None) -> None:
        if gt_depth is None:
            return
        has_gt = gt_depth > 0
        self.num_gt += int(has_gt.sum())
        self.num_valid += int(products.valid.sum())
        m = has_gt & products.valid
        self.band_multiplier = products.band_multiplier
        if not m.any():
            return
        q = draw_quantiles(torch.from_numpy(products.depth_draws[m]).double(), self.QUANTILE_LEVELS).numpy()  # [4, P]
        self.rows.append(np.stack([gt_depth[m], products.depth_mean[m], products.depth_std[m], *q]).astype(np.float64))

    def merge(self, other: "CalibrationAccumulator") -> None:
        """Append ``other``'s pixels after this one's (views pooled in order; ``band_multiplier`` is not merged)."""
        self.rows.extend(other.rows)
        self.num_gt += other.num_gt
        self.num_valid += other.num_valid

    def summary(self) -> dict | None:
        if not self.rows:
            return None
        gt, mean, std, q16, q84, q025, q975 = np.concatenate(self.rows, axis=1)
        err = np.abs(mean - gt)
        out = {
            "num_pixels": int(gt.size),
            "fraction_of_gt_pixels_valid": gt.size / max(self.num_gt, 1),
            "fraction_of_valid_pixels_with_gt": gt.size / max(self.num_valid, 1),
            "depth_abs_error_mean": float(err.mean()),
            "depth_abs_error_median": float(np.median(err)),
            "depth_std_mean": float(std.mean()),
            "gaussian_total_std": {},
            "draw_quantiles": {
                "68": float(np.mean((gt >= q16) & (gt <= q84))),
                "95": float(np.mean((gt >= q025) & (gt <= q975))),
            },
            "convention": "fraction of ground-truth camera-z depths inside the central interval, over pixels with "
                          "opacity >= min_opacity and a ground truth; gaussian_total_std: |mean - gt| <= z * m(p) * depth_std "
                          "(z = 1 for 68.27%, 1.645 for 90% (the exported depth_band90), 1.96 for 95%; m(p) = 1, or "
                          "s(p)/s(0.683) of a recalibrated run); draw_quantiles: empirical quantiles of the K draws "
                          "(15.87-84.13% and 2.5-97.5%), which cover only the epistemic part",
        }
        for key, (level, z) in CALIBRATION_LEVELS.items():
            m = 1.0 if self.band_multiplier is None else float(self.band_multiplier(level))
            out["gaussian_total_std"][key] = float(np.mean(err <= z * m * std))
        return out


def surface_distances(points: np.ndarray, mesh_path: str | Path) -> np.ndarray:
    """Unsigned distance [N] of world points [N, 3] to the triangle mesh in ``mesh_path``
    (Open3D RaycastingScene.compute_distance, float32)."""
    import open3d as o3d  # heavy optional dependency (Open3D): loaded only when used
    try:
        mesh = trimesh.load(str(mesh_path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises bare exceptions for damaged files ("PLY is unexpected length!")
        raise ValueError(f"{mesh_path}: cannot read the ground-truth mesh ({type(exc).__name__}: {exc})") from exc
    if not hasattr(mesh, "faces") or len(mesh.faces) == 0:
        raise ValueError(f"{mesh_path}: the ground-truth mesh has no triangles")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    if len(points) == 0:
        return np.zeros(0)
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy().astype(np.float64)


def surface_report(cloud: CloudArrays, mesh_path: Path) -> dict:
    """Mean/median distance of the points to the surface, for all and the 50% most confident
    (and, for comparison, the 50% with the smallest depth_std)."""
    dist = surface_distances(cloud.positions, mesh_path)
    if dist.size == 0:
        return {"num_points": 0}
    conf_half = most_confident(cloud.attributes["confidence"], 0.5)
    std_half = most_confident(-cloud.attributes["depth_std"].astype(np.float64), 0.5)
    return {
        "mesh": str(mesh_path),
        "num_points": int(dist.size),
        "mean": float(dist.mean()),
        "median": float(np.median(dist)),
        "most_confident_50_mean": float(dist[conf_half].mean()),
        "least_confident_50_mean": float(dist[~conf_half].mean()) if (~conf_half).any() else math.nan,
        "smallest_std_50_mean": float(dist[std_half].mean()),
        "units": cloud.metadata.get("units", "scene units"),
    }


def picture_viewpoint(specs: Sequence[ViewSpec], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(up, eye direction) for the cloud picture: up is the cameras' mean up axis (OpenCV -y in
    world), the eye looks from the first camera's side of the cloud's centre."""
    R = np.stack([s.world_to_camera[:3, :3] for s in specs])
    up = -R[:, 1, :].mean(0)  # camera y points down; row 1 of R is that axis in world
    c0 = -R[0].T @ specs[0].world_to_camera[:3, 3]
    eye = c0 - np.median(points, axis=0)
    if np.linalg.norm(up) < ROTATION_TOLERANCE or not np.linalg.norm(eye) > 0:  # cameras' up axes cancel
        return np.array([0.0, 0.0, 1.0]), None
    return up / np.linalg.norm(up), eye


# ------------------------------------------------------------------------------- driver
def export_run(run_dir: str | Path, opts: ExportOptions, *, distributed=None) -> dict:
    """Export the products of a trained run (see the module doc). Returns the summary it saves.
    ``distributed``: this rank's ``distributed.DistContext`` (see ``export_views``); the model is
    loaded on the rank's device."""
    opts.validate()
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run folder {run_dir} does not exist")
    device = opts.device if distributed is None else str(distributed.device)
    cfg, model, dataset = load_trained_model(run_dir, device=device)
    if opts.known_distance is not None:
        i, j, metres = opts.known_distance
        if i != int(i) or j != int(j):
            raise ValueError(f"--known-distance: camera indices must be integers, got {i}, {j}")
        known = metres_per_unit_from_known_distance(dataset.cameras.extrinsics.double().cpu().numpy(), int(i), int(j),
                                                    float(metres))
        opts.metres_per_unit, opts.scale_source = known.metres_per_unit, known.source
    if opts.cameras is not None:
        specs = load_cameras_json(opts.cameras, default_near=float(dataset.near.min()),
                                  default_far=float(dataset.far.max()))
    else:
        views = parse_views(opts.views, dataset.num_views, dataset.train_indices, dataset.test_indices)
        specs = dataset_view_specs(dataset, views)
    if opts.voxel_size is not None:  # against the scene's extent, before any render
        reach = max(float(dataset.aabb.abs().max()), float(dataset.cameras.extrinsics[:, :3, 3].abs().max()))
        check_voxel_size(opts.voxel_size, reach)
    out = Path(opts.out) if opts.out is not None else run_dir / "export"
    mesh_path = Path(dataset.root) / "scene.ply"
    calibration = None if opts.raw_uncertainty else load_run_calibration(run_dir)
    return export_views(model, specs, out, opts, mesh_path=mesh_path if mesh_path.is_file() else None,
                        run_name=str(run_dir), calibration=calibration, distributed=distributed)


#: Entries an export folder holds: a non-empty folder with anything else is not replaced.
EXPORT_ENTRIES: frozenset[str] = frozenset({"views", "clouds", "fused.ply", "fused_cloud.png", "summary.json"})


def is_export_folder(path: Path) -> bool:
    """True for a folder holding only what an export writes (a previous or interrupted export)."""
    return all(p.name in EXPORT_ENTRIES or p.name.startswith(".") for p in Path(path).iterdir())


def export_views(model, specs: Sequence[ViewSpec], out: Path, opts: ExportOptions, *, mesh_path: Path | None = None,
                 run_name: str = "", calibration=None, distributed=None) -> dict:
    """Render, write and summarise ``specs`` into ``out`` (see the module doc): the files go to a
    fresh folder beside ``out`` that replaces it when complete (``io_utils.atomic_folder``); an
    existing ``out`` that holds anything but a previous export is refused. ``calibration``: the
    run's depth recalibration (``compute_depth_products``), or None.

    ``distributed``: a ``distributed.DistContext`` (one rank of a torchrun launch). Rank 0 opens
    the temporary folder and broadcasts its path (or its refusal, raised on every rank); rank r
    renders positions r, r + W, ... of ``specs`` and writes their per-view files into that folder
    itself (one folder for all ranks: a shared file system across hosts); the clouds, calibration
    rows and counts are gathered to rank 0, which writes the clouds, the fused cloud and
    summary.json and swaps the folder in; every rank then returns rank 0's summary. A rank that
    fails makes the others raise ``DistributedError`` before the swap: ``out`` is left as it was
    (a ``.OUT.partial-*`` left by a rank still writing is removed by the next export).
    """
    opts.validate()
    if "ros" in opts.formats and opts.metres_per_unit is None:
        raise ValueError("export_views: --known-distance is resolved against the dataset's cameras by export_run; "
                         "pass metres_per_unit here")
    for spec in specs:
        check_file_name(spec.name, "view name")
    ctx = distributed
    if ctx is None:
        with atomic_folder(out, replaceable=is_export_folder, option="--out") as work:
            return _export_views_into(model, specs, work, opts, mesh_path=mesh_path, run_name=run_name,
                                      calibration=calibration)
    what = "export's temporary folder from rank 0"
    summary = None
    if ctx.is_main:
        try:
            folder = atomic_folder(out, replaceable=is_export_folder, option="--out")
            work = folder.__enter__()
        except (ValueError, OSError) as exc:  # refused on every rank
            ctx.broadcast_object(exc, what=what)
            raise
        with contextlib.ExitStack() as stack:
            stack.push(folder.__exit__)  # removes the folder on an error, swaps it in on success
            ctx.broadcast_object(str(work), what=what)
            summary = _export_views_into(model, specs, work, opts, mesh_path=mesh_path, run_name=run_name,
                                         calibration=calibration, distributed=ctx)
    else:
        work = ctx.broadcast_object(None, what=what)
        if isinstance(work, BaseException):
            raise type(work)(*work.args)
        _export_views_into(model, specs, Path(work), opts, mesh_path=mesh_path, run_name=run_name,
                           calibration=calibration, distributed=ctx)
    # after rank 0's swap: its summary (or its failure) ends every rank's call
    return ctx.broadcast_object(summary, what="export's summary from rank 0 after the folder swap")


def _export_view(model, spec: ViewSpec, index: int, out: Path, opts: ExportOptions, flt: PointFilter,
                 calibration) -> dict:
    """Render and write one camera (position ``index`` in the export): its files, filtered cloud,
    pixel counts and calibration rows (numpy only: sent between ranks as is)."""
    products = render_products(model, spec, opts, calibration)
    files = write_view_files(out, spec.name, products, opts)
    calib = CalibrationAccumulator()
    calib.add(products, spec.gt_depth)
    calib.band_multiplier = None  # the run's, set by the caller (a closure does not travel between ranks)
    cloud = cloud_from_products(products, view=index, covariance=opts.covariance)  # valid pixels
    kept, counts = filter_cloud(cloud, flt)
    counts = {"pixels": int(products.valid.size), **counts}  # input = opacity >= min_opacity
    return {"position": index, "files": files, "calibration": calib, "cloud": kept, "counts": counts,
            "num_draws": products.num_draws}


def _export_views_into(model, specs: Sequence[ViewSpec], out: Path, opts: ExportOptions, *,
                       mesh_path: Path | None, run_name: str, calibration=None, distributed=None) -> dict | None:
    """The export into the folder ``out``; with ``distributed``, this rank's share of ``specs``
    (positions rank::W), then rank 0 assembles (returns the summary) and the others return None."""
    out = Path(out)
    flt = opts.point_filter()
    ctx = distributed
    records = map_sharded(lambda i: _export_view(model, specs[i], i, out, opts, flt, calibration), len(specs), ctx,
                          what="export's per-view clouds and counts to rank 0", desc="export", progress=opts.progress)
    if records is None:
        return None
    calib = CalibrationAccumulator()
    depth_cal = None if calibration is None else calibration.depth
    calib.band_multiplier = None if depth_cal is None else (lambda level: float(depth_cal.relative_scale(level)))
    clouds: list[CloudArrays] = []
    per_view: dict[str, dict] = {}
    files: list[Path] = []
    num_draws = None
    for spec, rec in zip(specs, records):  # in the order of ``specs``, whichever rank rendered them
        num_draws = rec["num_draws"]
        files += rec["files"]
        calib.merge(rec["calibration"])
        per_view[spec.name] = {"counts": rec["counts"], "view_index_in_clouds": rec["position"]}
        clouds.append(rec["cloud"])
    all_points = CloudArrays.concatenate(clouds)
    colour_range = None
    if opts.colour_by == "uncertainty":
        colour_range = uncertainty_range(all_points.attributes.get("depth_std", np.zeros(0)))
    mapping = {}
    for spec, kept in zip(specs, clouds):
        path = out / "clouds" / f"{spec.name}.ply"
        mapping = write_ply(path, kept, opts.colour_by, value_range=colour_range,
                            comments=[f"view {spec.name}", f"units {opts.units}"])
        files.append(path)
    totals = {
        "pixels": sum(v["counts"]["pixels"] for v in per_view.values()),
        "after_opacity": sum(v["counts"]["input"] for v in per_view.values()),
        "after_filters": len(all_points),
    }
    summary: dict = {
        "run": run_name,
        "views": [s.name for s in specs],
        "num_draws": num_draws,
        "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(opts).items()},
        "units": opts.units,
        "metres_per_unit": opts.metres_per_unit,
        "scale_source": opts.metric_scale().source if opts.metric_scale() else "unknown",
        "conventions": CONVENTIONS,
        "depth_calibration": None if calibration is None else calibration.to_dict(),
        "colour_mapping": mapping,
        "per_view": per_view,
    }
    fused = None
    if opts.fuse and len(all_points):
        fused, report = fuse_clouds(all_points, opts.voxel_size)
        totals["after_fusion"] = report["fused"]
        summary["fusion"] = report
        fused_mapping = write_ply(out / "fused.ply", fused, opts.colour_by, value_range=colour_range,
                                  comments=["fused", f"units {opts.units}"])
        summary["fused_colour_mapping"] = fused_mapping
        files.append(out / "fused.ply")
        up, eye = picture_viewpoint(specs, fused.positions)
        files.append(render_cloud_png(out / "fused_cloud.png", fused, value_range=colour_range, up=up,
                                      eye_direction=eye,
                                      title=f"fused cloud, {len(fused):,} points, coloured by depth std"))
    summary["counts"] = totals
    gt: dict = {}
    if mesh_path is not None and len(all_points):
        gt["surface_distance"] = surface_report(all_points, mesh_path)
        if fused is not None:
            gt["surface_distance_fused"] = surface_report(fused, mesh_path)
    cal = calib.summary()
    if cal is not None:
        gt["calibration"] = cal
    if gt:
        summary["ground_truth"] = gt
    summary["files"] = sorted(str(p.relative_to(out)) for p in files)
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, default=float))
    return summary
