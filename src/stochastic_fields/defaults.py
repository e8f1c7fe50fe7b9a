"""The defaults and choices the command line shows, in one torch-free module.

``--help`` of every command reads them without loading the implementation behind the command
(torch, pycolmap, Open3D...); each implementation imports its own from here.
"""

from __future__ import annotations


# calibration
#: File of a run's calibration.
CALIBRATION_FILE = "calibration.json"
#: Which capture points a depth map may be fitted on (``--points``): "held-out", every point the
#: training did not fit (CALIBRATE and SCORE: three times the blocks, so the map sees most of the
#: scene's surfaces; the default, docs/uncertainty.md, studies 18 and 18b), scored independently by
#: its cross-fitted fold maps (``DepthFolds``); or "calibrate", the CALIBRATE role only (the SCORE
#: points then score the map itself; the protocol of studies 1 to 18).
CALIBRATION_POINTS: tuple[str, ...] = ("held-out", "calibrate")
DEFAULT_CALIBRATION_POINTS: str = "held-out"
#: Which capture points a calibration view (halfway between two training views) renders: "both", the
#: points both views of its pair observed (COLMAP tracks), or "either", those one of them observed
#: (docs/studies.md, study 38).
CALIBRATION_PAIR_POINTS: tuple[str, ...] = ("both", "either")
DEFAULT_CALIBRATION_PAIR_POINTS: str = "both"
#: Folds the SCORE blocks are dealt into when a map is fitted on them too (``DepthFolds``; study
#: 18's diagnostic: 5 folds).
CROSS_FIT_FOLDS: int = 5
#: Whether depth maps fit a std floor (``fit_std_floor``); docs/uncertainty.md, study 11.
DEPTH_STD_FLOOR: bool = False
#: Whether depth maps are fitted on the free-space-checked std sqrt(sigma^2 + (beta e)^2), beta fitted
#: with rho (``free_space``, ``calibration.fit_check_weight``; docs/uncertainty.md, studies 22d and 22e:
#: on the means over three seeds it keeps every check today's map passed, holds paper-split flower's
#: 68% and 90% bands and lowers the mean 95% interval score from 1.61 to 1.13; beta = 0 leaves a
#: scene the check does not help, the synthetic one, unchecked).
DEPTH_FREE_SPACE: bool = True
#: Whether depth maps fit a depth-proportional std term rho, depth_std = s sqrt(raw^2 + (rho d)^2)
#: (``calibration.fit_relative_floor``; docs/uncertainty.md, studies 20 and 20b: on fresh runs it
#: loses none of issue 36's checks and halves the mean 95% interval score; rho is fitted as 0 where
#: sigma already explains the errors).
DEPTH_RELATIVE_FLOOR: bool = True
#: Whether depth maps add an occlusion-edge term, depth_std = s sqrt(raw^2 + ... + (gamma Delta)^2), Delta
#: the range of the depths rendered within 2 pixels (``depth_edges``, ``calibration.fit_edge_weight``;
#: docs/studies.md, study 30: off, it lowers flower's 95% interval score but widens the median band).
DEPTH_EDGE_TERM: bool = False
#: Whether depth maps add the training views' parallax term, depth_std = s sqrt(raw^2 + ... +
#: (kappa d / max(sin theta_max, 0.01))^2), theta_max the widest angle between training views that see
#: the rendered point (``parallax``, ``calibration.fit_parallax_weight``; docs/studies.md, study 42: on,
#: the 95% interval score falls on every group, -3% to -11%, the depth ranking rises 0.02-0.05, every
#: level holds and the capture split's median 95% band narrows, 6.3 -> 5.6% and 13.9 -> 12.4%).
DEPTH_PARALLAX_TERM: bool = True

# free_space
#: File of a run's rendered training-view depths (``save_training_depth``).
TRAINING_DEPTH_FILE = "training_depth.npz"

# data/prepare
#: Default frames per second of footage kept from a video.
DEFAULT_VIDEO_FPS: float = 2.0
#: Default cap on the frames kept from a video.
DEFAULT_MAX_FRAMES: int = 300
#: Default fraction of the input images that must register.
DEFAULT_MIN_REGISTERED_FRACTION: float = 0.5
#: COLMAP camera models ``prepare`` offers, with the nerfstudio ``camera_model`` each is written as.
CAMERA_MODELS: dict[str, str] = {
    "SIMPLE_PINHOLE": "OPENCV", "PINHOLE": "OPENCV", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV",
    "OPENCV": "OPENCV", "SIMPLE_RADIAL_FISHEYE": "OPENCV_FISHEYE", "RADIAL_FISHEYE": "OPENCV_FISHEYE",
    "OPENCV_FISHEYE": "OPENCV_FISHEYE",
}
#: Mapping strategies, tried in this order until one registers every image (module doc).
MAPPING_STRATEGIES: tuple[str, ...] = ("incremental", "incremental-relaxed", "global")
#: Median triangulation angle (degrees) the initial pair needs in ``incremental-relaxed`` (COLMAP: 16).
RELAXED_INIT_MIN_TRI_ANGLE_DEG: float = 4.0
#: Scale (pixels) of the soft-L1 loss of the final global bundle adjustment (``refine_robust``): COLMAP's
#: incremental mapper uses soft L1 at 1 px in its local bundle adjustments, a squared loss in its global ones.
FINAL_BA_LOSS_SCALE_PX: float = 1.0

# products/occupancy_map
#: Opacity of one voxel crossing that counts as "blocked" for the default density threshold.
BLOCKED_OPACITY: float = 0.5
#: Pixels a voxel should span where the cameras see it (a voxel below one pixel is not resolved).
OCCUPANCY_PIXELS_PER_VOXEL: float = 2.0
#: Most voxels in the region (coarser voxels beyond this): 2M cells evaluate in seconds on a CPU.
OCCUPANCY_MAX_CELLS: int = 2_000_000

# products/free_path
#: Default transmittance level: a segment is free when more than half the light gets through.
FREE_TRANSMITTANCE_LEVEL: float = 0.5
#: Default number of density trajectories.
FREE_PATH_NUM_DRAWS: int = 256
#: Whether ``train`` and ``calibrate`` fit the free-path recalibration (products/free_path_calibration.py):
#: on by benchmarks/free_path_reliability.py's rule (mean ECE over the real runs 0.100 -> 0.033, Brier lower on each).
FREE_PATH_RECALIBRATION: bool = True

# products/rosbag
#: Seconds between the views' messages.
ROSBAG_PERIOD_S: float = 0.1

# products/rerun_log
#: Entity paths.
RERUN_CAMERAS: str = "world/cameras"
RERUN_POINTS: str = "world/points"

# products/next_view
#: Trajectories per pixel of the next-view score (a variance over draws). With 16, four seeds of
#: the draws move each candidate's score by 0.2-1.2% (std / mean; the one-sided tiny run of
#: tests/test_next_view.py, 15 candidates scoring 0.43-0.78 nats per pixel) and never its top pick.
NEXT_VIEW_NUM_DRAWS: int = 16
#: Pixels rendered per candidate (the intrinsics scaled down): the score is a mean over pixels.
NEXT_VIEW_MAX_PIXELS: int = 4096
#: Candidates shown in the contact sheet.
NEXT_VIEW_SHEET_ROWS: int = 4
