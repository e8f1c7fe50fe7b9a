"""``stochastic-fields prepare``: from a folder of photos or a video to a posed scene, with pycolmap.

Stages (each with a progress bar):

1. Input. A folder of photos (png/jpg, one size) is copied to ``SCENE/images/``; a video is
   split into frames at ``fps`` frames per second of footage: from each window of
   ``video_fps / fps`` consecutive frames the sharpest (largest variance of the Laplacian) is
   kept, so the frames are both sharp and spread out; at most ``max_frames`` are kept. Photos
   named in ``exclude`` are left out (not read, copied, matched or mapped; a video's frames are left
   out by preparing its scene again from ``SCENE/images``).
2. Structure from motion with pycolmap (COLMAP's SIFT features, exhaustive matching for photos
   (``match_every_pair``: pair lists, a progress bar over the pairs) or sequential matching for
   video frames; one shared camera; CPU, or CUDA where pycolmap is built
   with it). Mapping tries the strategies of :data:`MAPPING_STRATEGIES` in order, on the same
   features and matches, and stops at the first that registers every image (else the one that
   registered most is kept):

   - ``incremental``: COLMAP's incremental mapper with its default options. Its initial image pair
     must triangulate its points at a median angle of 16 degrees (COLMAP halves the thresholds
     twice when no pair qualifies).
   - ``incremental-relaxed``: the same mapper whose initial pair needs only
     :data:`RELAXED_INIT_MIN_TRI_ANGLE_DEG` degrees. A forward-facing capture taken from one spot
     (LLFF's flower: 34 photos with 1300-2300 verified matches each) has no pair that wide, and the
     default mapper then registers no image at all.
   - ``global``: pycolmap's global mapper (GLOMAP): rotation averaging then global positioning,
     no initial pair.

   The largest reconstruction of the chosen strategy is kept; ``prepare.json`` records every
   strategy tried and how many images it registered.

   Then one global bundle adjustment of that reconstruction with a robust loss
   (``refine_robust``: soft L1 at :data:`FINAL_BA_LOSS_SCALE_PX` pixels, the loss of COLMAP's local
   adjustments; the mappers end on a squared loss, which lets a few mismatched observations pull a
   camera). On Blender lego's 100 renders (exact poses) the largest rotation error falls from 0.50
   to 0.35 degrees and the largest centre error from 0.35% to 0.21-0.23% of the extent (seeds
   0-2); docs/capture.md has the measurements on LLFF's scenes. ``prepare.json`` records the
   reprojection error before and after.
3. Output, next to the images::

       SCENE/sparse/0/{cameras,images,points3D}.bin   COLMAP model (+ rigs/frames.bin of COLMAP 3.12+)
       SCENE/transforms.json     nerfstudio-style: intrinsics incl. distortion, OpenGL poses, file_path
       SCENE/sparse_pc.ply       the SfM points (nerfstudio's ply_file_path)
       SCENE/images_2, images_4, images_8   area-downscaled copies
       SCENE/colmap/database.db  features and matches (COLMAP's database)
       SCENE/prepare.json        what was done: counts, reprojection error, timings, failures,
                                 the photos left out, the SHA-256 of the photos the database holds

The transforms.json poses are in the COLMAP model's world frame (``applied_transform`` is the
identity), so its loader finds the model beside it and takes the points, their tracks and
near/far from there (docs/capture.md).

Bad input raises :class:`~stochastic_fields.data.errors.DatasetError` naming the file: no
images, unreadable photos or frames, a video that cannot be decoded, photos of different sizes,
or fewer registered images than ``min_registered`` (a summary of the reasons, the first
:data:`FAILURES_LISTED` failed images, and the whole list in a JSON file of the system's temporary
folder that the message names). Every stage writes into a hidden staging folder beside ``SCENE``,
moved into ``SCENE`` only when all succeeded: after any error or an interruption ``SCENE`` is as it
was before the command (not created if it did not exist).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm
import imageio.v3 as iio

from ..io_utils import atomic_path, atomic_write, atomic_write_text
from .colmap import ColmapCamera, read_colmap_model
from .dataset import IMAGE_SUFFIXES, read_image
from .errors import DatasetError
from ..cameras import opencv_w2c_to_opengl_c2w
from .blender import _area_downscale
from ..defaults import (CAMERA_MODELS, DEFAULT_MAX_FRAMES, DEFAULT_MIN_REGISTERED_FRACTION, DEFAULT_VIDEO_FPS,
                        FINAL_BA_LOSS_SCALE_PX, MAPPING_STRATEGIES, RELAXED_INIT_MIN_TRI_ANGLE_DEG)  # noqa: F401  (defaults the command line shows)

#: Video files ``prepare`` splits into frames (decoded with imageio's PyAV plugin).
VIDEO_SUFFIXES: tuple[str, ...] = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
#: Downscaled copies written next to ``images/`` (``images_<d>``), as LLFF and nerfstudio do.
DOWNSCALE_FACTORS: tuple[int, ...] = (2, 4, 8)
#: Fewer registered images than this and no radiance field can be trained.
MIN_REGISTERED_IMAGES: int = 3
#: Fewer SIFT features than this in an image is reported as the likely reason it failed.
FEW_FEATURES: int = 100
#: Failed images named in a registration error (the rest are counted, and listed in the file it names).
FAILURES_LISTED: int = 3
#: Image pairs matched per pycolmap call by ``match_every_pair``: a progress step (about 17 s on
#: two threads at lego's 3500 SIFT features a photo; 15 pairs a second, as ``match_exhaustive``).
MATCH_PAIRS_PER_CALL: int = 256
#: pycolmap's glog level while it runs (3 = fatal only: its INFO lines would bury the progress bars, and a
#: strategy that fails is reported in prepare's own summary and error).
PYCOLMAP_LOG_LEVEL: int = 3


@dataclass
class PrepareResult:
    """What ``prepare`` did (also written to ``SCENE/prepare.json``); ``database_photos``: {name:
    ``file_digest``} of the photos whose features and matches ``SCENE/colmap/database.db`` holds."""

    scene_dir: str
    num_images: int
    num_registered: int
    num_points: int
    mean_reprojection_error_px: float
    camera_model: str
    failed: dict[str, str] = field(default_factory=dict)
    timings_s: dict[str, float] = field(default_factory=dict)
    mapping: str = "incremental"
    mapping_attempts: dict[str, int] = field(default_factory=dict)
    matcher: str = ""
    excluded: list[str] = field(default_factory=list)
    database_photos: dict[str, str] = field(default_factory=dict)
    refinement: dict = field(default_factory=dict)

    def summary(self) -> str:
        lines = [f"registered {self.num_registered}/{self.num_images} images, {self.num_points} points, "
                 f"mean reprojection error {self.mean_reprojection_error_px:.3f} px ({self.camera_model})",
                 "mapping: " + mapping_report(self.mapping, self.mapping_attempts, self.num_images),
                 *([f"refinement: robust ({self.refinement['loss']}, {self.refinement['scale_px']:g} px) bundle "
                    f"adjustment, reprojection error {self.refinement['reprojection_before_px']:.3f} -> "
                    f"{self.refinement['reprojection_after_px']:.3f} px"] if self.refinement.get("applied") else []),
                 "time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.timings_s.items())]
        lines += [f"  not registered: {name}: {why}" for name, why in self.failed.items()]
        if self.excluded:
            lines.append(f"left out ({len(self.excluded)}, --exclude): " + ", ".join(self.excluded))
        return "\n".join(lines)


def mapping_report(chosen: str, attempts: dict[str, int], num_images: int) -> str:
    """One line: the strategy kept and what each tried registered, e.g.
    ``incremental-relaxed (incremental 0/34, incremental-relaxed 34/34)``."""
    tried = ", ".join(f"{name} {n}/{num_images}" for name, n in attempts.items())
    return f"{chosen} ({tried})" if len(attempts) > 1 else f"{chosen} ({tried or 'not run'})"


def failure_summary(failed: dict[str, str], listed: int = FAILURES_LISTED) -> str:
    """The reasons counted by kind, then the first ``listed`` images with theirs."""
    kinds: dict[str, int] = {}
    for why in failed.values():
        kind = why.split(":")[0]  # every reason of _failure_reasons reads "kind: detail"
        kinds[kind] = kinds.get(kind, 0) + 1
    counts = "; ".join(f"{n} x {kind}" for kind, n in sorted(kinds.items(), key=lambda kv: -kv[1]))
    first = "; ".join(f"{name}: {why}" for name, why in list(failed.items())[:listed])
    more = f" (and {len(failed) - listed} more)" if len(failed) > listed else ""
    return f"{counts}. For example {first}{more}"


# ---------------------------------------------------------------------- input
def sharpness(image: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image [H, W, C] or [H, W] (any range).

    Blur removes high frequencies, so a blurred frame of the same scene scores lower.
    """
    g = np.asarray(image, dtype=np.float64)
    if g.ndim == 3:
        g = g[..., :3].mean(axis=-1)
    lap = 4.0 * g[1:-1, 1:-1] - g[:-2, 1:-1] - g[2:, 1:-1] - g[1:-1, :-2] - g[1:-1, 2:]
    return float(lap.var()) if lap.size else 0.0


def _write_png(path: Path, image: np.ndarray) -> None:
    atomic_write(path, lambda tmp: iio.imwrite(tmp, image, extension=".png"))


def extract_video_frames(video: str | Path, out_dir: str | Path, *, fps: float = DEFAULT_VIDEO_FPS,
                         max_frames: int = DEFAULT_MAX_FRAMES, progress: bool = True) -> list[Path]:
    """Split a video into sharp, spread-out PNG frames ``out_dir/frame_00001.png, ...`` (module doc).

    The window length is ``max(round(video_fps / fps), ceil(num_frames / max_frames))`` frames;
    the sharpest frame of each window is kept. DatasetError naming the video if it cannot be
    opened or decoded, or yields no frame.
    """
    video, out_dir = Path(video), Path(out_dir)
    if not video.is_file():
        raise DatasetError(video, "missing video file")
    if not fps > 0 or int(max_frames) < 1:
        raise ValueError(f"need fps > 0 and max_frames >= 1, got fps={fps} max_frames={max_frames}")
    try:
        meta = iio.immeta(video, plugin="pyav")
    except Exception as exc:
        raise DatasetError(video, f"cannot open the video ({type(exc).__name__}: {exc}); convert it to H.264 MP4, "
                           "or extract the frames yourself and pass their folder") from exc
    video_fps = float(meta.get("fps") or 0.0)
    duration = float(meta.get("duration") or 0.0)
    total = int(round(video_fps * duration)) if video_fps > 0 and duration > 0 else None
    window = max(1, round(video_fps / fps)) if video_fps > 0 else 1
    if total:
        window = max(window, math.ceil(total / int(max_frames)))
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    best, best_score, index = None, -1.0, -1
    bar = tqdm(total=total, desc=f"frames of {video.name}", unit="frame", disable=not progress)
    try:
        for index, frame in enumerate(iio.imiter(video, plugin="pyav")):
            bar.update(1)
            score = sharpness(frame)
            if score > best_score:
                best, best_score = frame, score
            if (index + 1) % window == 0:
                written.append(out_dir / f"frame_{len(written) + 1:05d}.png")
                _write_png(written[-1], np.ascontiguousarray(best[..., :3]))
                best, best_score = None, -1.0
    except Exception as exc:
        raise DatasetError(video, f"cannot decode the video at frame {index + 1} ({type(exc).__name__}: {exc}; "
                           f"codec {meta.get('codec', 'unknown')})") from exc
    finally:
        bar.close()
    if best is not None:
        written.append(out_dir / f"frame_{len(written) + 1:05d}.png")
        _write_png(written[-1], np.ascontiguousarray(best[..., :3]))
    if not written:
        raise DatasetError(video, f"the video yielded no frame (codec {meta.get('codec', 'unknown')})")
    if len(written) > max_frames:  # the duration was unknown or wrong: thin out evenly
        keep = set(np.linspace(0, len(written) - 1, int(max_frames)).round().astype(int).tolist())
        for i, p in enumerate(written):
            if i not in keep:
                p.unlink()
        written = [p for i, p in enumerate(written) if i in keep]
    return written


def collect_photos(folder: str | Path, out_dir: str | Path, *, exclude=(), progress: bool = True) -> list[Path]:
    """Check the photos of ``folder`` (readable, one size) and copy them into ``out_dir``; the photos
    named in ``exclude`` are left as they are (not read, not copied).

    Returns the copies, sorted by name. DatasetError naming the folder when it holds no photo or
    ``exclude`` names one it does not hold, or naming the photo that cannot be read or whose size
    differs from the first.
    """
    folder, out_dir = Path(folder), Path(out_dir)
    if not folder.is_dir():
        raise DatasetError(folder, "missing photo folder")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    skip = set(exclude)
    unknown = sorted(skip - {p.name for p in photos})
    if unknown:
        raise DatasetError(folder, f"--exclude names {', '.join(repr(n) for n in unknown[:FAILURES_LISTED])}"
                           f"{' and more' if len(unknown) > FAILURES_LISTED else ''}, not among its "
                           f"{len(photos)} photos (give file names, as the pose check prints them)")
    photos = [p for p in photos if p.name not in skip]
    if not photos:
        others = sorted(p.name for p in folder.iterdir())[:5]
        raise DatasetError(folder, f"no images ({'/'.join(IMAGE_SUFFIXES)}) in the folder"
                           + (f" (it holds {', '.join(others)}...)" if others else " (it is empty)"))
    out_dir.mkdir(parents=True, exist_ok=True)
    size = None
    copies = []
    for photo in tqdm(photos, desc="photos", unit="img", disable=not progress):
        try:
            shape = iio.improps(photo).shape
            iio.imread(photo)  # decode once: a truncated file fails here, not inside COLMAP
        except Exception as exc:
            raise DatasetError(photo, f"unreadable image ({type(exc).__name__}: {exc})") from exc
        if size is None:
            size = shape[:2]
        elif shape[:2] != size:
            raise DatasetError(photo, f"image size {shape[1]}x{shape[0]} differs from {size[1]}x{size[0]} of "
                               f"{photos[0].name}: one capture, one camera size")
        target = out_dir / photo.name
        if photo.resolve() != target.resolve():
            with atomic_path(target) as tmp:
                shutil.copyfile(photo, tmp)
        copies.append(target)
    return copies


# ---------------------------------------------------------------------- structure from motion
def _device(name: str):
    import pycolmap  # heavy optional dependency (pycolmap): loaded only when used

    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {name!r}")
    if name == "cuda" and not pycolmap.has_cuda:
        raise ValueError("device 'cuda' asked for, but this pycolmap is built without CUDA "
                         "(install a CUDA build of pycolmap, or use --device cpu)")
    return getattr(pycolmap.Device, name)


def _failure_reasons(database: Path, names: list[str], registered: set[str], min_matches: int) -> dict[str, str]:
    """Why each image of ``names`` not in ``registered`` failed, from the database's counts.

    Each reason reads ``"<kind>: <detail>"``; the kinds are ``not imported by COLMAP``, ``few SIFT
    features``, ``too few matches`` and ``not placed by the mapper``.
    """
    import pycolmap  # heavy optional dependency (pycolmap): loaded only when used

    db = pycolmap.Database.open(database)
    try:
        ids = {im.name: int(im.image_id) for im in db.read_all_images()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        best: dict[int, int] = {}
        partners: dict[int, int] = {}
        for pid, n in zip(pair_ids, inliers):
            for iid in pycolmap.pair_id_to_image_pair(int(pid)):
                best[iid] = max(best.get(iid, 0), int(n))
                if n >= min_matches:
                    partners[iid] = partners.get(iid, 0) + 1
        reasons = {}
        for name in names:
            if name in registered:
                continue
            iid = ids.get(name)
            if iid is None:
                reasons[name] = "not imported by COLMAP: unreadable for it"
                continue
            feats = int(db.num_keypoints_for_image(iid))
            if feats < FEW_FEATURES:
                reasons[name] = f"few SIFT features: only {feats} (blurred, dark or textureless?)"
            elif partners.get(iid, 0) == 0:
                reasons[name] = (f"too few matches: no other image shares {min_matches} geometrically verified "
                                 f"matches with it (best {best.get(iid, 0)}; {feats} features)")
            else:
                reasons[name] = (f"not placed by the mapper: {partners[iid]} images share >= {min_matches} "
                                 f"verified matches with it (best {best.get(iid, 0)})")
        return reasons
    finally:
        db.close()


def map_images(database: Path, image_dir: Path, out: Path, strategy: str, *, names: list[str],
               num_threads: int = -1, seed: int = 0, progress: bool = True) -> dict:
    """One mapping strategy of :data:`MAPPING_STRATEGIES` on the database's features and matches of
    the images ``names`` (a database may hold others: photos left out with ``exclude``).

    Writes its models under ``out`` (emptied first) and returns pycolmap's {index: Reconstruction}.
    """
    import pycolmap  # heavy optional dependency, loaded only when prepare runs

    if strategy not in MAPPING_STRATEGIES:
        raise ValueError(f"mapping strategy must be one of {', '.join(MAPPING_STRATEGIES)}, got {strategy!r}")
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    pycolmap.set_random_seed(int(seed))
    if strategy == "global":
        options = pycolmap.GlobalPipelineOptions()
        options.num_threads = int(num_threads)
        options.random_seed = int(seed)
        options.image_names = list(names)
        return pycolmap.global_mapping(database, image_dir, out, options=options)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = int(num_threads)
    options.random_seed = int(seed)
    options.image_names = list(names)
    if strategy == "incremental-relaxed":
        options.mapper.init_min_tri_angle = RELAXED_INIT_MIN_TRI_ANGLE_DEG
    bar = tqdm(total=len(names), desc=f"registering ({strategy})", unit="img", disable=not progress, leave=False)
    try:
        return pycolmap.incremental_mapping(database, image_dir, out, options=options,
                                            initial_image_pair_callback=lambda: bar.update(2),
                                            next_image_callback=lambda: bar.update(1))
    finally:
        bar.close()


def bundle_adjust(rec, loss: str, loss_scale_px: float, *, num_threads: int = -1) -> tuple[object, bool]:
    """One global bundle adjustment of a copy of the pycolmap Reconstruction ``rec`` (cameras, poses,
    points; the principal point held, as the mappers hold it; the gauge of pycolmap.bundle_adjustment)
    with Ceres's ``loss`` (a ``pycolmap.LossFunctionType`` name: TRIVIAL, SOFT_L1, CAUCHY, HUBER) at
    ``loss_scale_px``. Returns (the adjusted copy, whether Ceres reports a usable solution)."""
    import pycolmap  # heavy optional dependency, loaded only when prepare runs

    if not loss_scale_px > 0:
        raise ValueError(f"loss_scale_px must be > 0, got {loss_scale_px}")
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_principal_point = False
    options.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, loss)
    options.ceres.loss_function_scale = float(loss_scale_px)
    options.ceres.solver_options.num_threads = int(num_threads)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjusted = pycolmap.Reconstruction(rec)
    summary = pycolmap.create_default_bundle_adjuster(options, config, adjusted).solve()
    adjusted.update_point_3d_errors()
    return adjusted, bool(summary.is_solution_usable())


def refine_robust(rec, *, num_threads: int = -1, loss_scale_px: float = FINAL_BA_LOSS_SCALE_PX) -> tuple[object, dict]:
    """``bundle_adjust`` of ``rec`` with the soft-L1 loss ``rho(s) = 2 b^2 (sqrt(1 + s / b^2) - 1)`` of
    each squared reprojection error s (b = ``loss_scale_px``): quadratic below b pixels, linear above,
    so a mismatched observation pulls with a bounded force (module doc). Returns (the refined copy, or
    ``rec`` itself where Ceres reports no usable solution; a report: the loss, its scale, the mean
    reprojection error before and after in pixels, ``applied``)."""
    refined, usable = bundle_adjust(rec, "SOFT_L1", loss_scale_px, num_threads=num_threads)
    before, after = float(rec.compute_mean_reprojection_error()), float(refined.compute_mean_reprojection_error())
    applied = usable and math.isfinite(after)
    report = {"loss": "soft_l1", "scale_px": float(loss_scale_px), "reprojection_before_px": before,
              "reprojection_after_px": after if applied else before, "applied": applied}
    return (refined if applied else rec), report


def match_every_pair(database: Path, names: list[str], matching, device, *, progress: bool = True) -> None:
    """Exhaustive matching of ``names`` (every pair once), :data:`MATCH_PAIRS_PER_CALL` pairs per
    pycolmap call (``match_image_pairs`` on a pair list), so that a bar counts the pairs and Ctrl-C
    lands between calls: the same matches as one ``match_exhaustive`` call, verified with RANSAC draws
    in another order. Names with white space cannot be written to COLMAP's pair list: then one
    ``match_exhaustive``."""
    import pycolmap  # heavy optional dependency, loaded only when prepare runs

    if any(any(c.isspace() for c in name) for name in names):
        pycolmap.match_exhaustive(database, matching_options=matching, device=device)
        return
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    bar = tqdm(total=len(pairs), desc="matching every pair", unit="pair", disable=not progress, leave=False)
    with tempfile.TemporaryDirectory(prefix="prepare-pairs-") as tmp:
        listing = Path(tmp) / "pairs.txt"
        for start in range(0, len(pairs), MATCH_PAIRS_PER_CALL):
            block = pairs[start:start + MATCH_PAIRS_PER_CALL]
            listing.write_text("".join(f"{a} {b}\n" for a, b in block))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(listing)
            pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing, device=device)
            bar.update(len(block))
    bar.close()


def run_sfm(image_dir: Path, work_dir: Path, names: list[str], *, camera_model: str = "SIMPLE_RADIAL",
            matcher: str = "exhaustive", mapping: str = "auto", num_threads: int = -1, device: str = "auto",
            seed: int = 0, reuse_database: Path | None = None, progress: bool = True):
    """Features, matches and mapping with pycolmap (module doc, stage 2); ``reuse_database``: a
    database that already holds the features and matches of every image of ``names`` (copied, and
    only the mapping runs).

    ``mapping`` is one strategy of :data:`MAPPING_STRATEGIES`, or ``"auto"``: each in turn until one
    registers every image. Returns (the largest pycolmap.Reconstruction of the strategy kept, or
    None; the database path; per-stage seconds; the strategy kept; {strategy tried: images it
    registered}).
    """
    import pycolmap  # heavy optional dependency, loaded only when prepare runs

    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    if matcher not in ("exhaustive", "sequential"):
        raise ValueError(f"matcher must be 'exhaustive' or 'sequential', got {matcher!r}")
    if mapping != "auto" and mapping not in MAPPING_STRATEGIES:
        raise ValueError(f"mapping must be 'auto' or one of {', '.join(MAPPING_STRATEGIES)}, got {mapping!r}")
    dev = _device(device)
    work_dir.mkdir(parents=True, exist_ok=True)
    database = work_dir / "database.db"
    if database.exists():
        database.unlink()  # a new run: COLMAP would otherwise add to the old features
    if reuse_database is not None:
        shutil.copyfile(reuse_database, database)
    pycolmap.set_random_seed(int(seed))
    timings: dict[str, float] = {}
    strategies = MAPPING_STRATEGIES if mapping == "auto" else (mapping,)
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = PYCOLMAP_LOG_LEVEL
    stages = tqdm(total=3, desc="SfM", unit="stage", disable=not progress)
    try:
        if reuse_database is not None:
            stages.update(2)
            timings["features and matches reused"] = 0.0
            return _map_strategies(database, image_dir, work_dir, names, strategies, num_threads=num_threads,
                                   seed=seed, progress=progress, stages=stages, timings=timings)
        t0 = time.perf_counter()
        stages.set_postfix_str("features")
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = int(num_threads)
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=dev)
        timings["features"] = time.perf_counter() - t0
        stages.update(1)

        t0 = time.perf_counter()
        stages.set_postfix_str(f"{matcher} matching")
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = int(num_threads)
        if matcher == "exhaustive":
            match_every_pair(database, names, matching, dev, progress=progress)
        else:
            pycolmap.match_sequential(database, matching_options=matching, device=dev)
        timings["matching"] = time.perf_counter() - t0
        stages.update(1)
        return _map_strategies(database, image_dir, work_dir, names, strategies, num_threads=num_threads,
                               seed=seed, progress=progress, stages=stages, timings=timings)
    finally:
        stages.close()
        pycolmap.logging.minloglevel = old_level


def _map_strategies(database: Path, image_dir: Path, work_dir: Path, names: list[str], strategies, *,
                    num_threads: int, seed: int, progress: bool, stages, timings: dict[str, float]):
    """``run_sfm``'s mapping stage: each strategy in turn until one registers every image."""
    attempts: dict[str, int] = {}
    best, best_strategy = None, strategies[0]
    t0 = time.perf_counter()
    for strategy in strategies:
        stages.set_postfix_str(f"{strategy} mapping")
        recs = map_images(database, image_dir, work_dir / "sparse", strategy, names=names,
                          num_threads=num_threads, seed=seed, progress=progress)
        rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
        attempts[strategy] = rec.num_reg_images() if rec is not None else 0
        if rec is not None and (best is None or attempts[strategy] > best.num_reg_images()):
            best, best_strategy = rec, strategy
        if attempts[strategy] == len(names):
            break
    timings["mapping"] = time.perf_counter() - t0
    stages.update(1)
    return best, database, timings, best_strategy, attempts


# ---------------------------------------------------------------------- output
def nerfstudio_intrinsics(camera: ColmapCamera) -> dict:
    """nerfstudio's intrinsics keys (``camera_model``, ``fl_x fl_y cx cy w h``, ``k1 k2 [k3 k4] p1 p2``)
    of a COLMAP camera of :data:`CAMERA_MODELS`."""
    p = [float(x) for x in camera.params]
    model = camera.model
    if model not in CAMERA_MODELS:
        raise ValueError(f"camera model {model} cannot be written as nerfstudio intrinsics")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        fx = fy = p[0]
        cx, cy, extra = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, extra = p[0], p[1], p[2], p[3], p[4:]
    out = {"camera_model": CAMERA_MODELS[model], "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
           "w": int(camera.width), "h": int(camera.height)}
    if CAMERA_MODELS[model] == "OPENCV":
        k = extra[:2] + [0.0] * (2 - len(extra[:2]))
        pp = extra[2:4] if model == "OPENCV" else [0.0, 0.0]
        out.update(k1=k[0], k2=k[1], p1=pp[0], p2=pp[1])
    else:
        k = extra + [0.0] * (4 - len(extra))
        out.update(k1=k[0], k2=k[1], k3=k[2], k4=k[3])
    return out


def write_transforms(model_dir: Path, scene_dir: Path, image_folder: str = "images") -> Path:
    """``scene_dir/transforms.json`` from the COLMAP model in ``model_dir`` (OpenGL camera-to-world)."""
    model = read_colmap_model(model_dir)
    cams = {cid: nerfstudio_intrinsics(c) for cid, c in model.cameras.items()}
    used = sorted({im.camera_id for im in model.images})
    meta: dict = dict(cams[used[0]]) if len(used) == 1 else {}
    frames = []
    for im in model.images:
        c2w = opencv_w2c_to_opengl_c2w(torch.from_numpy(im.world_to_camera)[None])[0].numpy()
        frame = {"file_path": f"{image_folder}/{im.name}", "transform_matrix": c2w.tolist(),
                 "colmap_im_id": im.image_id}
        if len(used) > 1:
            frame.update(cams[im.camera_id])
        frames.append(frame)
    meta.update({"applied_transform": np.eye(4)[:3].tolist(), "ply_file_path": "sparse_pc.ply", "frames": frames})
    path = scene_dir / "transforms.json"
    atomic_write_text(path, json.dumps(meta, indent=2))
    return path


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with ``x y z`` (float) and ``red green blue`` (uchar)."""
    rows = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rows["x"], rows["y"], rows["z"] = (np.asarray(xyz, dtype=np.float32)[:, k] for k in range(3))
    rows["red"], rows["green"], rows["blue"] = (np.asarray(rgb, dtype=np.uint8)[:, k] for k in range(3))
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rows.tobytes())

    atomic_write(path, write)


def area_downscale_rgba(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, C] float in [0, 1] (C = 3, or 4 with straight alpha) -> area-averaged copy.

    RGB is averaged as is. RGBA is averaged premultiplied (a c and a, then c = mean(a c) / mean(a)
    where mean(a) > 0, 0 elsewhere), so that the small copy composited on any background b,
    c' a' + (1 - a') b, equals the area average of the full-size image composited on b: what the
    loaders do with RGBA (``blender._load_frames``). Averaging the straight colours would bleed the
    colour hidden under a = 0 (often black) into the object's border."""
    if image.shape[-1] != 4:
        return _area_downscale(np.ascontiguousarray(image), factor)
    alpha = image[..., 3:]
    small = _area_downscale(np.ascontiguousarray(np.concatenate([image[..., :3] * alpha, alpha], -1)), factor)
    a = small[..., 3:]
    rgb = np.where(a > 0, small[..., :3] / np.maximum(a, 1e-12), 0.0)
    return np.concatenate([np.clip(rgb, 0.0, 1.0), a], -1)


def write_downscaled(images: list[Path], scene_dir: Path, factors=DOWNSCALE_FACTORS, *, progress: bool = True) -> None:
    """Area-downscaled copies ``scene_dir/images_<d>/<name>`` of each image, in its own format.

    The file name is kept so that ``images_<d>/<name>`` mirrors ``images/<name>`` (nerfstudio's
    rule, which the loaders follow). Sizes: ``round(H / d) x round(W / d)``. An RGBA photo (a
    masked object) keeps its alpha, averaged premultiplied (``area_downscale_rgba``), so every
    size composites on the scene's background alike.
    """
    for path in tqdm(images, desc="downscaling", unit="img", disable=not progress):
        image = read_image(path)
        for d in factors:
            small = np.clip(area_downscale_rgba(image, int(d)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
            target = scene_dir / f"images_{d}" / path.name
            atomic_write(target, lambda tmp, a=small, ext=path.suffix.lower(): iio.imwrite(tmp, a, extension=ext))


def _nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists."""
    path = path.absolute()
    while not path.exists():
        path = path.parent
    return path


def publish_scene(staging: Path, scene_dir: Path) -> None:
    """Move every entry of ``staging`` into ``scene_dir`` (created if needed), each replacing the
    entry of that name, ``transforms.json`` and ``prepare.json`` last (their presence says the
    scene is complete); ``staging`` is removed."""
    scene_dir.mkdir(parents=True, exist_ok=True)
    order = {"transforms.json": 1, "prepare.json": 2}  # every other entry 0: first
    for entry in sorted(staging.iterdir(), key=lambda p: order.get(p.name, 0)):
        target = scene_dir / entry.name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
        os.replace(entry, target)
    staging.rmdir()


def prepare(source: str | Path, scene_dir: str | Path, *, camera_model: str = "SIMPLE_RADIAL",
            matcher: str | None = None, mapping: str = "auto", num_threads: int = -1, device: str = "auto",
            fps: float = DEFAULT_VIDEO_FPS,
            max_frames: int = DEFAULT_MAX_FRAMES, min_registered_fraction: float = DEFAULT_MIN_REGISTERED_FRACTION,
            downscale_factors=DOWNSCALE_FACTORS, seed: int = 0, exclude=(), progress: bool = True) -> PrepareResult:
    """Photos folder or video -> posed scene folder (module doc). Returns what was done.

    ``exclude``: names of photos left out of the reconstruction (for example those the pose check
    of ``train`` or ``eval`` flagged, ``pose_check``); DatasetError naming one that is not among
    the photos. Prepared in place with ``exclude``, the features and matches of the scene's last
    prepare are reused when its photos are unchanged (``reusable_database``): only the mapping runs.

    The scene is built in a hidden staging folder beside ``scene_dir`` and moved into it only when
    every stage succeeded (``publish_scene``): on bad input, a capture that does not register or an
    interruption, ``scene_dir`` is left as it was (not created if it did not exist). Photos already
    in ``scene_dir/images`` are prepared in place (not copied)."""
    source, scene_dir = Path(source), Path(scene_dir)
    if not source.exists():
        raise DatasetError(source, "input does not exist (give a folder of photos or a video file)")
    if not 0.0 <= min_registered_fraction <= 1.0:
        raise ValueError(f"min_registered_fraction must be in [0, 1], got {min_registered_fraction}")
    if scene_dir.exists() and not scene_dir.is_dir():
        raise DatasetError(scene_dir, "exists and is not a folder: give --out a folder to write the scene into")
    if source.is_file():
        if source.suffix.lower() not in VIDEO_SUFFIXES:
            raise DatasetError(source, f"not a video ({'/'.join(VIDEO_SUFFIXES)}) nor a folder of photos")
        if (scene_dir / "images").is_dir() and any((scene_dir / "images").iterdir()):
            raise DatasetError(scene_dir / "images", "already holds images: prepare a video into a new folder")
    staging = Path(tempfile.mkdtemp(prefix=f".{scene_dir.name}.prepare-", dir=_nearest_existing(scene_dir.parent)))
    try:
        result = _prepare_into(staging, source, scene_dir, camera_model=camera_model, matcher=matcher,
                               mapping=mapping, num_threads=num_threads, device=device, fps=fps,
                               max_frames=max_frames, min_registered_fraction=min_registered_fraction,
                               downscale_factors=downscale_factors, seed=seed, exclude=exclude,
                               progress=progress)
        publish_scene(staging, scene_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return result


def _prepare_into(staging: Path, source: Path, scene_dir: Path, *, camera_model: str, matcher: str | None,
                  mapping: str, num_threads: int, device: str, fps: float, max_frames: int,
                  min_registered_fraction: float, downscale_factors, seed: int, exclude, progress: bool) -> PrepareResult:
    """``prepare``'s stages, every file written into ``staging`` (the scene's layout); photos
    already in ``scene_dir/images`` are read where they are."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    in_place = source.is_dir() and source.resolve() == (scene_dir / "images").resolve()
    image_dir = source if in_place else staging / "images"
    excluded = sorted(set(exclude))
    if source.is_file():
        if excluded:
            raise DatasetError(source, "--exclude names photos of a folder: prepare the video, then "
                               "prepare SCENE/images --out SCENE --exclude ...")
        images = extract_video_frames(source, image_dir, fps=fps, max_frames=max_frames, progress=progress)
        timings["frames"] = time.perf_counter() - t_start
        matcher = matcher or "sequential"
    else:
        images = collect_photos(source, image_dir, exclude=excluded, progress=progress)
        timings["photos"] = time.perf_counter() - t_start
        matcher = matcher or "exhaustive"
    names = [p.name for p in images]
    digests = {p.name: file_digest(p) for p in images}
    reuse = reusable_database(scene_dir, digests, camera_model, matcher) if in_place and excluded else None
    if reuse is not None:
        digests = reuse[1]  # the copied database holds these photos' features (the left-out ones too)
    if len(names) < MIN_REGISTERED_IMAGES:
        raise DatasetError(source, f"only {len(names)} images: structure from motion needs at least "
                           f"{MIN_REGISTERED_IMAGES}, and a radiance field many more")
    rec, database, sfm_times, strategy, attempts = run_sfm(
        image_dir, staging / "colmap", names, camera_model=camera_model, matcher=matcher, mapping=mapping,
        num_threads=num_threads, device=device, seed=seed, reuse_database=None if reuse is None else reuse[0],
        progress=progress)
    timings.update(sfm_times)
    registered = {rec.images[i].name for i in rec.reg_image_ids()} if rec is not None else set()
    import pycolmap  # heavy optional dependency (pycolmap): loaded only when used

    failed = _failure_reasons(database, names, registered,
                              int(pycolmap.TwoViewGeometryOptions().min_num_inliers))
    need = max(MIN_REGISTERED_IMAGES, math.ceil(min_registered_fraction * len(names)))
    if len(registered) < need:
        listing = write_failure_listing(scene_dir, {"mapping_attempts": attempts, "failed": failed})
        raise DatasetError(source, f"only {len(registered)} of {len(names)} images registered (need {need}; "
                           f"mapping tried: {mapping_report(strategy, attempts, len(names))}). Not registered: "
                           f"{failure_summary(failed)}. Every image and its reason: {listing} "
                           f"({scene_dir} left as it was)")
    t0 = time.perf_counter()
    rec, refinement = refine_robust(rec, num_threads=num_threads)
    timings["refinement"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    model_dir = staging / "sparse" / "0"
    model_dir.mkdir(parents=True)
    rec.write(model_dir)
    shutil.rmtree(staging / "colmap" / "sparse", ignore_errors=True)  # the mapper's own copy
    model = read_colmap_model(model_dir)
    write_transforms(model_dir, staging)
    write_points_ply(staging / "sparse_pc.ply", model.points.xyz, model.points.rgb)
    write_downscaled([image_dir / im.name for im in model.images], staging, downscale_factors, progress=progress)
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    camera = next(iter(model.cameras.values()))
    result = PrepareResult(scene_dir=str(scene_dir), num_images=len(names), num_registered=len(model.images),
                           num_points=len(model.points), mean_reprojection_error_px=model.mean_reprojection_error,
                           camera_model=camera.model, failed=failed,
                           timings_s={k: round(v, 2) for k, v in timings.items()}, mapping=strategy,
                           mapping_attempts=attempts, matcher=matcher, excluded=excluded, database_photos=digests,
                           refinement=refinement)
    atomic_write_text(staging / "prepare.json", json.dumps(asdict(result), indent=2))
    return result


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (hex): whether a photo is the one a database's features came from."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def reusable_database(scene_dir: Path, digests: dict[str, str], camera_model: str,
                      matcher: str) -> tuple[Path, dict[str, str]] | None:
    """(``scene_dir/colmap/database.db``, its photos' digests) when the scene's last prepare (its
    prepare.json) extracted and matched every photo of ``digests`` ({name: ``file_digest``}) as it
    is now, with the same camera model and matcher; else None (extracted and matched again)."""
    database, record = scene_dir / "colmap" / "database.db", scene_dir / "prepare.json"
    if not (database.is_file() and record.is_file()):
        return None
    try:
        last = json.loads(record.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(last, dict) or last.get("camera_model") != camera_model or last.get("matcher") != matcher:
        return None
    held = last.get("database_photos")
    if not isinstance(held, dict) or any(held.get(name) != d for name, d in digests.items()):
        return None
    return database, held


def write_failure_listing(scene_dir: Path, listing: dict) -> Path:
    """Every image that did not register and its reason, as JSON in the system's temporary folder
    (``scene_dir`` is left as it was), named after the scene; returns the file."""
    fd, name = tempfile.mkstemp(prefix=f"prepare-{scene_dir.name}-failures-", suffix=".json")
    with os.fdopen(fd, "w") as f:  # a new file of its own: nothing to replace atomically
        f.write(json.dumps(listing, indent=2))
    return Path(name)


# ---------------------------------------------------------------------- CLI


def run(args: argparse.Namespace) -> None:
    if args.threads == 0 or args.threads < -1:
        raise ValueError(f"--threads must be -1 (all cores) or >= 1, got {args.threads}")
    result = prepare(args.source, args.out, camera_model=args.camera_model, matcher=args.matcher,
                     mapping=args.mapping, num_threads=args.threads, device=args.device, fps=args.fps, max_frames=args.max_frames,
                     min_registered_fraction=args.min_registered, seed=args.seed,
                     exclude=[n.strip() for n in args.exclude.split(",") if n.strip()], progress=not args.quiet)
    print(result.summary())
    print(f"scene: {args.out} (train with: stochastic-fields train --data.path {args.out} --out RUN)")
