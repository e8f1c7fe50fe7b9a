"""The protocol the trainer, evaluation and products use: every method (S-NeRF, its
ablations, the baselines) trains through ``training_loss`` and renders through
``render_view``, so all of them share one pipeline, split, budget and metrics."""

from __future__ import annotations

import abc

import torch
from torch import Tensor, nn

from ..rays import RayBundle
from ..renderer import RenderSettings


#: Learning-rate multiplier of grid cells relative to network weights and priors.
GRID_LR_FACTOR = 10.0


class RadianceModel(nn.Module, abc.ABC):
    """A method that learns from pixels and renders colour/depth means and variances."""

    render_settings: RenderSettings
    #: Buffers that ``training_loss`` keeps as running maxima over the batches it saw; a
    #: data-parallel step takes their maximum over the ranks (``distributed.GradientReducer``).
    running_max_buffers: tuple[str, ...] = ()

    @abc.abstractmethod
    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        """rays [R], target colours [R, 3] -> (scalar loss, logged scalars)."""

    @abc.abstractmethod
    def render_view(self, rays: RayBundle, *, num_draws: int | None = None,
                    generator: torch.Generator | None = None, keep_draws: bool = False,
                    progress: bool = False) -> dict[str, Tensor]:
        """rays [H, W] -> maps (see renderer.MAP_NAMES) in ray-distance units plus ``z_scale``."""

    def after_step(self, step: int) -> None:
        """Hook after each optimiser step (occupancy updates and similar)."""

    def param_groups(self, lr: float) -> list[dict]:
        """Optimiser parameter groups: grid cells (of every GridField inside) at
        ``GRID_LR_FACTOR * lr`` (each cell sees few rays per step) and marked ``sparse`` (their
        gradients are sparse, see ``optim.FieldOptimizer``), everything else at ``lr``."""
        from ..fields.grid import GridField

        grid = [p for m in self.modules() if isinstance(m, GridField) for p in m.levels.parameters()]
        ids = {id(p) for p in grid}
        rest = [p for p in self.parameters() if id(p) not in ids and p.requires_grad]
        groups = [{"params": grid, "lr": lr * GRID_LR_FACTOR, "sparse": True}] if grid else []
        return groups + [{"params": rest, "lr": lr}]
