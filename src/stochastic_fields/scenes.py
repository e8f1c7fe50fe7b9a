"""Which dataset a run uses: a scene folder given by the user, or the embedded synthetic scene
generated into the run folder (no download)."""

from __future__ import annotations

from pathlib import Path

from .config import ExperimentConfig
from .data import detect_format, load_dataset
from .io_utils import check_no_symlinks

EMBEDDED_SCENE_DIR = "scene"


def scene_path(cfg: ExperimentConfig, run_dir: Path) -> Path:
    return Path(cfg.data.path) if cfg.data.path else Path(run_dir) / EMBEDDED_SCENE_DIR


def load_run_dataset(cfg: ExperimentConfig, run_dir: Path, *, generate: bool = True):
    """Load the run's dataset, split by ``cfg.data.split`` (:func:`apply_split`); generate the
    embedded synthetic scene first if needed."""
    path = scene_path(cfg, run_dir)
    if not cfg.data.path:
        check_no_symlinks(run_dir, EMBEDDED_SCENE_DIR)  # the scene is generated into the run folder
    if not cfg.data.path and not (path / "transforms.json").exists():
        if not generate:
            raise FileNotFoundError(f"the embedded scene is missing from {path}")
        from .data.synthetic import make_synthetic_scene  # heavy optional dependencies (Open3D, trimesh): only to generate the embedded scene

        make_synthetic_scene(path)
    if detect_format(path) == "llff":  # LLFF picks images_N; Blender/nerfstudio/COLMAP a downscale factor
        if cfg.data.downscale != 1:
            raise ValueError(f"option data.downscale={cfg.data.downscale} applies to Blender/nerfstudio scenes; "
                             f"{path} is an LLFF scene: choose its resolution with data.images (images_4, images_8)")
        return apply_split(load_dataset(path, images=cfg.data.images, split_every=cfg.data.split_every,
                                        undistort=cfg.data.undistort), cfg)
    if not cfg.data.undistort:
        raise ValueError(f"option data.undistort=false applies to LLFF scenes; {path} is a "
                         f"{detect_format(path)} capture, whose distorted cameras are always undistorted")
    return apply_split(load_dataset(path, split_every=cfg.data.split_every, downscale=cfg.data.downscale), cfg)


def apply_split(dataset, cfg: ExperimentConfig):
    """The run's split of a loaded dataset (``data.split``): 'paper' keeps the loader's
    ``index % split_every == 0`` training views; 'capture' holds out every ``holdout_every``-th view
    (index % holdout_every == 0) and trains on the rest; 'fewview' tests on the same views and trains on
    ``train_views`` of the rest, spread evenly (``data.dataset.few_view_indices``); 'views' trains the
    views of ``data.train_list`` and tests the rest. A split given by the scene's files
    (``dataset.split_source == "files"``) is kept either way."""
    if dataset.split_source == "files":
        return dataset
    if cfg.data.split == "capture":
        return dataset.hold_out_every(cfg.data.holdout_every)
    if cfg.data.split == "fewview":
        return dataset.few_views(cfg.data.train_views, cfg.data.holdout_every)
    if cfg.data.split == "views":
        return dataset.train_on([int(v) for v in cfg.data.train_list.split(",") if v.strip()])
    return dataset


def describe_split(dataset, cfg: ExperimentConfig) -> str:
    """One line: how many photos train and how many validate/test, and by which rule."""
    n_train, n_test = len(dataset.train_indices), len(dataset.test_indices)
    if dataset.split_source == "files":
        rule = "the scene's own train/test files"
    elif dataset.split_source == "few_views":
        rule = (f"few-view split: {n_train} of the photos not held out train, every {cfg.data.holdout_every}th "
                "tests (RegNeRF's protocol)")
    elif dataset.split_source == "views":
        rule = f"the views of data.train_list train: {cfg.data.train_list}"
    elif dataset.split_source == "holdout_every":
        rule = (f"capture split: every {cfg.data.holdout_every}th photo validates (index % {cfg.data.holdout_every} "
                "== 0); --preset paper for the paper's 20% split")
    else:
        rule = f"paper split: index % {cfg.data.split_every} == 0 trains"
    role = "validate" if dataset.split_source == "holdout_every" else "test"
    return f"{dataset.name}: {n_train} photos train, {n_test} {role} ({rule})"
