"""``stochastic-fields prepare``: photos or a video -> camera poses (pycolmap) -> a scene folder (``data.prepare``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

import argparse

from ..defaults import CAMERA_MODELS, DEFAULT_MAX_FRAMES, DEFAULT_MIN_REGISTERED_FRACTION, DEFAULT_VIDEO_FPS, MAPPING_STRATEGIES, RELAXED_INIT_MIN_TRI_ANGLE_DEG


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Recover camera poses and intrinsics of a folder of photos or a video with pycolmap and "
                     "write a scene folder that `stochastic-fields train --data.path` reads (docs/capture.md).")
    p.add_argument("source", help="A folder of photos (png/jpg, one size) or a video file (mp4, mov, ...).")
    p.add_argument("--out", required=True, help="Scene folder to write (images/, sparse/0/, transforms.json, ...).")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=tuple(CAMERA_MODELS),
                   help="COLMAP camera model shared by all images (default SIMPLE_RADIAL: one focal length and "
                        "one radial term; OPENCV for stronger lens distortion, OPENCV_FISHEYE for fisheyes).")
    p.add_argument("--matcher", default=None, choices=("exhaustive", "sequential"),
                   help="Feature matching: every pair (default for photos) or neighbours in order (default for video).")
    p.add_argument("--mapping", default="auto", choices=("auto",) + MAPPING_STRATEGIES,
                   help="SfM mapping: auto (default) tries incremental, then incremental-relaxed (an initial pair "
                        f"needing {RELAXED_INIT_MIN_TRI_ANGLE_DEG:g} instead of 16 degrees of triangulation angle, for "
                        "captures taken from one spot), then global (GLOMAP), until one registers every image.")
    p.add_argument("--fps", type=float, default=DEFAULT_VIDEO_FPS,
                   help="Video only: frames kept per second of footage (the sharpest of each window).")
    p.add_argument("--max-frames", type=int, default=DEFAULT_MAX_FRAMES, help="Video only: at most this many frames.")
    p.add_argument("--threads", type=int, default=-1, help="CPU threads for pycolmap (-1: all cores).")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"),
                   help="SIFT extraction/matching device (auto: CUDA when pycolmap is built with it).")
    p.add_argument("--min-registered", type=float, default=DEFAULT_MIN_REGISTERED_FRACTION,
                   help="Fail when fewer than this fraction of the images register (default 0.5).")
    p.add_argument("--seed", type=int, default=0, help="Random seed of COLMAP's RANSAC and mapper.")
    p.add_argument("--exclude", default="",
                   help="Photos to leave out, comma-separated file names (e.g. those the pose check of train or "
                        "eval flagged). Prepared in place (SOURCE is SCENE/images) the last prepare's features and "
                        "matches are reused when the photos are unchanged: only the mapping runs.")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")


def run(args) -> None:
    from ..data.prepare import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
