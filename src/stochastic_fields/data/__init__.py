"""Datasets: LLFF, Blender/nerfstudio and COLMAP loaders, COLMAP readers and the embedded synthetic scene.

Every loader returns a :class:`SceneDataset` with OpenCV cameras (docs/definitions.md §1) and raises
:class:`DatasetError` (naming the file) on bad input.
"""

from .blender import load_blender
from .colmap import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    ColmapPoints,
    find_colmap_model,
    read_cameras_binary,
    read_colmap_model,
    read_points3d_binary,
)
from .colmap_scene import load_colmap
from .dataset import SceneDataset, fit_scene_aabb, pad_box
from .loading import detect_format, load_dataset
from .errors import DatasetError
from .llff import load_llff
from .synthetic import make_synthetic_scene

__all__ = [
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "ColmapPoints",
    "DatasetError",
    "SceneDataset",
    "detect_format",
    "find_colmap_model",
    "fit_scene_aabb",
    "pad_box",
    "load_blender",
    "load_colmap",
    "load_dataset",
    "load_llff",
    "make_synthetic_scene",
    "read_cameras_binary",
    "read_colmap_model",
    "read_points3d_binary",
]
