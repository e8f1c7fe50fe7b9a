"""The field and the modelled region of a method's model, from a config and a dataset."""

from __future__ import annotations

from torch import nn

from ..cameras import image_size, intrinsics_3x3
from ..config import ExperimentConfig
from ..constants import ENSEMBLE_GRID_DENSITY_NOISE
from ..fields.base import StochasticField
from ..fields.grid import GridField, RESOLUTION_RULES
from ..fields.mlp import MLPField
from ..scene_region import SceneRegion, fit_region


def fit_scene_region(dataset, cfg: ExperimentConfig) -> SceneRegion:
    """The modelled region from the dataset's cameras, near/far and sparse points."""
    H, W = image_size(dataset.cameras)
    return fit_region(intrinsics_3x3(dataset.cameras), dataset.cameras.extrinsics, H, W, dataset.near, dataset.far,
                      forward_facing=bool(getattr(dataset, "forward_facing", False)),
                      aabb=dataset.aabb)


def finest_grid_resolution(cfg: ExperimentConfig, region: SceneRegion, dataset) -> tuple[int, int, int]:
    """Cells per axis of the grid's finest level, from the dataset's training views by
    ``field.grid_resolution_rule`` under ``field.grid_max_cells``."""
    f = cfg.field
    H, W = image_size(dataset.cameras)
    idx = list(dataset.train_indices)
    rule = RESOLUTION_RULES[f.grid_resolution_rule]
    return rule(region, intrinsics_3x3(dataset.cameras)[idx], dataset.cameras.extrinsics[idx], H, W,
                dataset.near[idx], dataset.far[idx], pixels_per_voxel=f.grid_pixels_per_voxel,
                max_cells=f.grid_max_cells)


def grid_field(model: nn.Module) -> GridField | None:
    """The model's (first) grid field, or None for a model without one; every member of an
    ensemble has the same shape."""
    return next((m for m in model.modules() if isinstance(m, GridField)), None)


def trained_grid_resolution(model: nn.Module) -> tuple[int, int, int] | None:
    """The finest level's cells per axis of the model's grid field, or None for a model without
    one. Stored in the checkpoint, so a saved run rebuilds the grid it was trained with whatever
    views or sizing code load it."""
    grid = grid_field(model)
    return None if grid is None else grid.resolution


def build_field(cfg: ExperimentConfig, region: SceneRegion, dataset, *, noise_head: bool = False,
                grid_resolution: tuple[int, int, int] | None = None) -> StochasticField:
    """The configured backend; ``noise_head``: with an observation-noise output (S-NeRF's
    ``loss.per_point_noise``); ``grid_resolution``: the finest level's cells per axis (a saved
    run's), instead of sizing it from the dataset's training views."""
    f = cfg.field
    if f.backend == "mlp":  # one density field: field.density_heads is the grid's
        return MLPField(region, depth=f.mlp_depth, width=f.mlp_width, dropout=f.dropout, init_std=f.init_std,
                        noise_head=noise_head)
    if f.backend == "grid":
        res = finest_grid_resolution(cfg, region, dataset) if grid_resolution is None else grid_resolution
        unit = 1.0 / region.cell_length(res) if f.density_per == "cell" else 1.0
        return GridField(region, res, num_levels=f.grid_levels, feature_dim=f.grid_feature_dim,
                         decoder_width=f.grid_decoder_width,
                         concat_colour_levels=f.grid_colour_levels == "concat", init_density_loc=f.grid_init_density_loc,
                         init_std=f.init_std, noise_head=noise_head, density_unit=unit,
                         density_heads=f.density_heads,
                         head_init_std=ENSEMBLE_GRID_DENSITY_NOISE * abs(f.grid_init_density_loc))
    raise ValueError(f"field.backend must be 'grid' or 'mlp', got {f.backend!r}")
