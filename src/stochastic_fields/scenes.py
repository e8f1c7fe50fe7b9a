"""Which dataset a run uses: a scene folder given by the user, or the embedded synthetic scene
generated into the run folder (no download)."""

from __future__ import annotations

from pathlib import Path

from .config import ExperimentConfig

EMBEDDED_SCENE_DIR = "scene"


def scene_path(cfg: ExperimentConfig, run_dir: Path) -> Path:
    return Path(cfg.data.path) if cfg.data.path else Path(run_dir) / EMBEDDED_SCENE_DIR


def load_run_dataset(cfg: ExperimentConfig, run_dir: Path, *, generate: bool = True):
    """Load the run's dataset; generate the embedded synthetic scene first if needed."""
    from .data import detect_format, load_dataset

    path = scene_path(cfg, run_dir)
    if not cfg.data.path:
        from .io_utils import check_no_symlinks

        check_no_symlinks(run_dir, EMBEDDED_SCENE_DIR)  # the scene is generated into the run folder
    if not cfg.data.path and not (path / "transforms.json").exists():
        if not generate:
            raise FileNotFoundError(f"the embedded scene is missing from {path}")
        from .data.synthetic import make_synthetic_scene

        make_synthetic_scene(path)
    if detect_format(path) == "llff":  # LLFF picks images_N; Blender/nerfstudio/COLMAP a downscale factor
        if cfg.data.downscale != 1:
            raise ValueError(f"option data.downscale={cfg.data.downscale} applies to Blender/nerfstudio scenes; "
                             f"{path} is an LLFF scene: choose its resolution with data.images (images_4, images_8)")
        return load_dataset(path, images=cfg.data.images, split_every=cfg.data.split_every,
                            undistort=cfg.data.undistort)
    if not cfg.data.undistort:
        raise ValueError(f"option data.undistort=false applies to LLFF scenes; {path} is a "
                         f"{detect_format(path)} capture, whose distorted cameras are always undistorted")
    return load_dataset(path, split_every=cfg.data.split_every, downscale=cfg.data.downscale)
