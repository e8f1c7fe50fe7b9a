"""Build a method's model from a config and a dataset (one place that knows every method)."""

from __future__ import annotations

import copy
import dataclasses
from typing import Callable

import torch

from ..config import METHOD_NAMES, ExperimentConfig
from ..settings import RenderSettings
from ..scene_region import SceneRegion
from .base import RadianceModel
from .baselines import BASELINE_BUILDERS
from .field_builder import build_field, fit_scene_region
from .snerf import SNeRF


def build_snerf(cfg: ExperimentConfig, dataset, region: SceneRegion, *,
                grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    field = build_field(cfg, region, dataset, noise_head=cfg.loss.per_point_noise, grid_resolution=grid_resolution)
    return SNeRF(field, region, cfg.render, cfg.loss,
                 train_draws=cfg.train.train_draws, tv_weight=cfg.train.tv_weight)


#: method name -> builder(cfg, dataset, region, *, grid_resolution=None), for every name of ``config.METHOD_NAMES``.
METHODS: dict[str, Callable[..., RadianceModel]] = {
    "snerf": build_snerf, **BASELINE_BUILDERS}
if tuple(METHODS) != METHOD_NAMES:
    raise ImportError(f"config.METHOD_NAMES {METHOD_NAMES} and the builders {tuple(METHODS)} disagree")


def scene_render_settings(render: RenderSettings, dataset) -> RenderSettings:
    """``render`` with its background resolved for ``dataset``: ``render.background`` None means the
    scene's own, ``dataset.background`` (a Blender or nerfstudio file's ``"background"``, white for
    RGBA photos: the colour the loader composited the photos on), and none (black, no compositing)
    for a scene without one (LLFF, COLMAP, RGB photos). A colour given in the config wins."""
    background = getattr(dataset, "background", None)
    if render.background is not None or background is None:
        return render
    return dataclasses.replace(render, background=tuple(float(c) for c in background))


def build_model(cfg: ExperimentConfig, dataset, region: SceneRegion | None = None, *,
                grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    """The configured method's model; ``grid_resolution``: a saved run's finest grid level
    (``field_builder.trained_grid_resolution``) instead of sizing it from the training views. The
    model composites the scene's background (``scene_render_settings``) unless the config names one."""
    if cfg.method not in METHODS:
        raise ValueError(f"unknown method {cfg.method!r}; choose from {sorted(METHODS)}")
    region = fit_scene_region(dataset, cfg) if region is None else region
    render = scene_render_settings(cfg.render, dataset)
    if render is not cfg.render:
        cfg = copy.copy(cfg)
        cfg.render = render
    return METHODS[cfg.method](cfg, dataset, region, grid_resolution=grid_resolution)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for but no CUDA device is available (use auto or cpu)")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}") from exc
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s) present")
    return dev
