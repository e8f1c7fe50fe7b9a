"""Build a method's model from a config and a dataset (one place that knows every method)."""

from __future__ import annotations

from typing import Callable

import torch

from ..config import ExperimentConfig
from ..fields.base import StochasticField
from ..fields.grid import GridField, resolution_from_footprint
from ..fields.mlp import MLPField
from ..scene_region import SceneRegion, fit_region
from .base import RadianceModel
from .snerf import SNeRF


def fit_scene_region(dataset, cfg: ExperimentConfig) -> SceneRegion:
    """The modelled region from the dataset's cameras, near/far and sparse points."""
    from ..cameras import image_size, intrinsics_3x3

    H, W = image_size(dataset.cameras)
    return fit_region(intrinsics_3x3(dataset.cameras), dataset.cameras.extrinsics, H, W, dataset.near, dataset.far,
                      forward_facing=bool(getattr(dataset, "forward_facing", False)),
                      aabb=dataset.aabb)


def build_field(cfg: ExperimentConfig, region: SceneRegion, dataset) -> StochasticField:
    f = cfg.field
    if f.backend == "mlp":
        return MLPField(region, depth=f.mlp_depth, width=f.mlp_width, dropout=f.dropout, init_std=f.init_std)
    if f.backend == "grid":
        from ..cameras import image_size, intrinsics_3x3

        H, W = image_size(dataset.cameras)
        idx = list(dataset.train_indices)
        res = resolution_from_footprint(region, intrinsics_3x3(dataset.cameras)[idx], dataset.cameras.extrinsics[idx],
                                        H, W, dataset.near[idx], dataset.far[idx],
                                        pixels_per_voxel=f.grid_pixels_per_voxel, max_cells=f.grid_max_cells)
        return GridField(region, res, num_levels=f.grid_levels, feature_dim=f.grid_feature_dim,
                         decoder_width=f.grid_decoder_width, init_density_loc=f.grid_init_density_loc,
                         init_std=f.init_std)
    raise ValueError(f"field.backend must be 'grid' or 'mlp', got {f.backend!r}")


def build_snerf(cfg: ExperimentConfig, dataset, region: SceneRegion) -> RadianceModel:
    return SNeRF(build_field(cfg, region, dataset), region, cfg.render, cfg.loss,
                 train_draws=cfg.train.train_draws, tv_weight=cfg.train.tv_weight)


#: method name -> builder(cfg, dataset, region). Baselines register themselves here.
METHODS: dict[str, Callable[[ExperimentConfig, object, SceneRegion], RadianceModel]] = {"snerf": build_snerf}


def build_model(cfg: ExperimentConfig, dataset, region: SceneRegion | None = None) -> RadianceModel:
    if cfg.method not in METHODS:
        raise ValueError(f"unknown method {cfg.method!r}; choose from {sorted(METHODS)}")
    region = fit_scene_region(dataset, cfg) if region is None else region
    return METHODS[cfg.method](cfg, dataset, region)


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


# --------------------------------------------------------------------------- baselines (SPEC 5)
# Registered last: models.baselines imports build_field from this module lazily.
from .baselines import BASELINE_BUILDERS as _BASELINE_BUILDERS  # noqa: E402

METHODS.update(_BASELINE_BUILDERS)
