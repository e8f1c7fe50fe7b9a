"""A rerun recording (``.rrd``, rerun-sdk) of an export: images, depth with std, the confident
point cloud with its confidence values, and the camera frusta.

``stochastic-fields rerun --export OUT --out run.rrd`` reads the export folder (as the rosbag
command does) and logs, on the timeline ``view`` (one step per view):

    world/cameras/<name>                 Transform3D (camera-to-world, OpenCV axes) + Pinhole (frustum;
                                         rerun's pinhole has pixel centres at +0.5 like ours, so K as is)
    world/cameras/<name>/colour          Image, rendered colour mean
    world/cameras/<name>/depth           DepthImage, camera-z depth (meter = 1 / metres_per_unit when a
                                         scale is known, else 1: one "meter" per scene unit), 0 = invalid
    world/cameras/<name>/depth_std       DepthImage, total depth std in the depth's units
    world/points/<name>                  Points3D of the view's exported cloud (world, scene units)
                                         coloured by confidence, with AnyValues confidence and depth_std

and, static, ``world/fused`` when the export has ``fused.ply``. Coordinates are scene units
(rerun has no unit; ``world`` carries a TextDocument with the units and scale).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import matplotlib

from .rosbag import load_export
from .pointcloud import read_ply
from ..defaults import RERUN_CAMERAS, RERUN_POINTS  # noqa: F401  (defaults the command line shows)


def _confidence_colours(conf: np.ndarray) -> np.ndarray:
    return (matplotlib.colormaps["viridis"](np.clip(conf, 0, 1))[:, :3] * 255).astype(np.uint8)


def write_rerun(export_dir: str | Path, out: str | Path, *, application_id: str = "stochastic-fields") -> dict:
    """Write the recording (module doc) to ``out`` (.rrd). Returns {entity: rows logged}."""
    import rerun as rr  # heavy optional dependency (rerun-sdk): loaded only when used

    views = load_export(export_dir)
    out = Path(out)
    if out.suffix != ".rrd":
        raise ValueError(f"rerun output {out} must end in .rrd")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    rec = rr.RecordingStream(application_id)
    rec.save(str(tmp))
    logged: dict[str, int] = {}
    first = views[0].products()
    mpu = first.metres_per_unit
    rec.log("world", rr.TextDocument(f"units: {first.units}; metres per unit: "
                                     f"{mpu if mpu is not None else 'unknown'} ({first.scale_source}); "
                                     "depth is camera-z; OpenCV camera axes"), static=True)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    for v, view in enumerate(views):
        p = view.products()
        rec.set_time("view", sequence=v)
        base = f"{RERUN_CAMERAS}/{view.name}"
        c2w = np.linalg.inv(p.world_to_camera)
        H, W = p.shape
        rec.log(base, rr.Transform3D(translation=c2w[:3, 3], mat3x3=c2w[:3, :3]))
        rec.log(base, rr.Pinhole(image_from_camera=p.intrinsics, resolution=[W, H],
                                 camera_xyz=rr.ViewCoordinates.RDF))
        rec.log(f"{base}/colour", rr.Image(np.clip(np.round(p.colour_mean * 255), 0, 255).astype(np.uint8)))
        meter = 1.0 / p.metres_per_unit if p.metres_per_unit else 1.0
        for key, arr in (("depth", p.depth_mean), ("depth_std", p.depth_std)):
            img = np.where(p.valid, arr, 0.0).astype(np.float32)
            rec.log(f"{base}/{key}", rr.DepthImage(img, meter=meter))
        for ent in (base, f"{base}/colour", f"{base}/depth", f"{base}/depth_std"):
            logged[ent] = logged.get(ent, 0) + 1
        if view.cloud is not None and len(view.cloud):
            conf = view.cloud.attributes["confidence"].astype(np.float32)
            ent = f"{RERUN_POINTS}/{view.name}"
            rec.log(ent, rr.Points3D(view.cloud.positions, colors=_confidence_colours(conf)),
                    rr.AnyValues(confidence=conf, depth_std=view.cloud.attributes["depth_std"].astype(np.float32)))
            logged[ent] = len(conf)
    fused = Path(export_dir) / "fused.ply"
    if fused.is_file():
        cloud, _ = read_ply(fused)
        conf = cloud.attributes["confidence"].astype(np.float32)
        rec.log("world/fused", rr.Points3D(cloud.positions, colors=_confidence_colours(conf)),
                rr.AnyValues(confidence=conf, depth_std=cloud.attributes["depth_std"].astype(np.float32)), static=True)
        logged["world/fused"] = len(conf)
    rec.flush()
    rec.disconnect()
    del rec
    tmp.replace(out)
    return logged


def read_rerun_entities(path: str | Path) -> dict[str, list]:
    """{entity path: [pyarrow RecordBatch, ...]} of a recording (rerun.chunk.RrdReader)."""
    from rerun.chunk import RrdReader  # heavy optional dependency (rerun-sdk): loaded only when used

    out: dict[str, list] = {}
    for chunk in RrdReader(str(path)).stream():
        out.setdefault(str(chunk.entity_path), []).append(chunk.to_record_batch())
    return out


# ------------------------------------------------------------------------------- CLI


def run(args) -> None:
    logged = write_rerun(args.export, args.out)
    points = sum(n for e, n in logged.items() if e.startswith(RERUN_POINTS) or e == "world/fused")
    print(f"wrote rerun recording {args.out}: {len([e for e in logged if e.startswith(RERUN_CAMERAS) and e.count('/') == 2])} cameras, "
          f"{points} points (open with `rerun {args.out}`)")
