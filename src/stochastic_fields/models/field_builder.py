"""The field and the modelled region of a method's model, from a config and a dataset."""

from __future__ import annotations

from ..cameras import image_size, intrinsics_3x3
from ..config import ExperimentConfig
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


def build_field(cfg: ExperimentConfig, region: SceneRegion, dataset, *, noise_head: bool = False) -> StochasticField:
    """The configured backend; ``noise_head``: with an observation-noise output (S-NeRF's
    ``loss.per_point_noise``)."""
    f = cfg.field
    if f.backend == "mlp":
        return MLPField(region, depth=f.mlp_depth, width=f.mlp_width, dropout=f.dropout, init_std=f.init_std,
                        noise_head=noise_head)
    if f.backend == "grid":
        H, W = image_size(dataset.cameras)
        idx = list(dataset.train_indices)
        finest_resolution = RESOLUTION_RULES[f.grid_resolution_rule]
        res = finest_resolution(region, intrinsics_3x3(dataset.cameras)[idx], dataset.cameras.extrinsics[idx],
                                H, W, dataset.near[idx], dataset.far[idx],
                                pixels_per_voxel=f.grid_pixels_per_voxel, max_cells=f.grid_max_cells)
        return GridField(region, res, num_levels=f.grid_levels, feature_dim=f.grid_feature_dim,
                         decoder_width=f.grid_decoder_width, init_density_loc=f.grid_init_density_loc,
                         init_std=f.init_std, noise_head=noise_head)
    raise ValueError(f"field.backend must be 'grid' or 'mlp', got {f.backend!r}")
