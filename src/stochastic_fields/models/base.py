"""The protocol the trainer, evaluation and products use: every method (S-NeRF, its
ablations, the baselines) trains through ``training_loss`` and renders through
``render_view``, so all of them share one pipeline, split, budget and metrics."""

from __future__ import annotations

import abc

import torch
from torch import Tensor, nn

from ..depth_smoothness import expected_normalised_depth, patch_smoothness
from ..occlusion import expected_density, near_optical_depth
from ..rays import RayBundle
from ..samplers import sample_along_rays
from ..renderer import ChunkGenerators, RayRender, RenderOptions, RenderSettings
from ..fields.grid import GridField


#: Learning-rate multiplier of grid cells relative to network weights and priors.
GRID_LR_FACTOR = 10.0


class RadianceModel(nn.Module, abc.ABC):
    """A method that learns from pixels and renders colour/depth means and variances."""

    render_settings: RenderSettings
    #: Buffers that ``training_loss`` keeps as running maxima over the batches it saw; a
    #: data-parallel step takes their maximum over the ranks (``distributed.GradientReducer``).
    running_max_buffers: tuple[str, ...] = ()
    #: Whether the density this model renders is a mean field ``relu(mu)`` (False: S-NeRF's
    #: rectified normal, whose regularisers read its mean).
    mean_field_density: bool = True
    #: Fraction of the training schedule done (steps or the minutes budget, set by the trainer
    #: before each step); terms whose weight follows the schedule read it. 0 outside training.
    training_progress: float = 0.0
    #: Whether ``training_loss`` takes ``ray_weights`` [R] (each ray's weight in the colour
    #: likelihood) and leaves each ray's squared colour error in ``last_ray_errors`` [R]: what the
    #: error-guided ray sampler needs (``train.ray_sampling`` 'error', stochastic_fields.ray_sampling).
    accepts_ray_weights: bool = False
    #: Whether ``training_loss`` takes ``head_weights`` [R, M] (each ray's weight in each density
    #: head's likelihood, ``loss.head_bootstrap_keep``): S-NeRF.
    accepts_head_weights: bool = False
    last_ray_errors: Tensor | None = None

    @abc.abstractmethod
    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        """rays [R], target colours [R, 3] -> (scalar loss, logged scalars)."""

    @abc.abstractmethod
    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """rays [H, W] -> maps in ray-distance units (``renderer.render_chunked``: ``MAP_NAMES``,
        ``z_scale``, ``num_draws`` [H, W] = the K each pixel got, per-draw maps with
        ``options.keep_draws``). ``options``: this call's choices (default
        :meth:`default_render_options`); the model's ``render_settings`` are never changed."""

    def default_render_options(self) -> RenderOptions:
        """The options of a render that asks for nothing: the run's ``render`` settings."""
        return RenderOptions.from_settings(self.render_settings)

    def render_options(self, **changes) -> RenderOptions:
        """:meth:`default_render_options` with ``changes`` (``RenderOptions.with_changes``: names
        checked, values validated, None ignored)."""
        return self.default_render_options().with_changes(**changes)

    def add_occlusion(self, loss: Tensor, logs: dict[str, float], renders: list[RayRender]) -> Tensor:
        """``loss + lambda_occlusion * sum over renders of the mean near optical depth of their rays``
        (``stochastic_fields.occlusion``; ``loss`` unchanged at weight 0). ``renders``: the training
        renders (one per ensemble member), whose density is ``relu(mu)`` with ``mean_field_density``
        (else S-NeRF's rectified normal, by its mean). Logs ``occlusion``, the mean over renders."""
        cfg = self.loss_config
        if cfg.lambda_occlusion <= 0:
            return loss
        terms = []
        for out in renders:
            scale = None if self.mean_field_density else out.params.density_scale
            terms.append(near_optical_depth(out.params.density_loc, scale, out.samples,
                                            self.render_settings.spacing, cfg.occlusion_near_fraction).mean())
        total = torch.stack(terms).sum()
        logs["occlusion"] = float(total.detach()) / len(terms)
        return loss + cfg.lambda_occlusion * total

    def density_fields(self) -> list[nn.Module]:
        """Every field whose density this model renders (one; an ensemble's members)."""
        return [self.field]

    def add_smoothness(self, loss: Tensor, logs: dict[str, float], patches: RayBundle | None, *,
                       generator: torch.Generator | None = None) -> Tensor:
        """``loss + lambda_smoothness * sum over density_fields() of L_smooth`` of ``patches``
        [P, h, w] (``stochastic_fields.depth_smoothness``: dense stratified samples drawn with
        ``generator``, without empty-space skipping as the sparse-depth term, the expected density,
        the expected normalised depth per ray); ``loss``
        unchanged at weight 0 or without patches. Logs ``smoothness``, the mean over fields."""
        cfg = self.loss_config
        if patches is None or cfg.lambda_smoothness <= 0:
            return loss
        settings = self.render_settings
        samples = sample_along_rays(patches.reshape(-1), settings.num_samples, spacing=settings.spacing,
                                    stratified=True, generator=generator)
        terms = []
        for field in self.density_fields():
            loc, scale = field.density_params(samples.positions)  # [R, S] each
            density = expected_density(loc, None if self.mean_field_density else scale)
            depth = expected_normalised_depth(density, samples, settings.spacing, settings.quadrature)
            terms.append(patch_smoothness(depth.reshape(patches.shape)))
        total = torch.stack(terms).sum()
        logs["smoothness"] = float(total.detach()) / len(terms)
        return loss + cfg.lambda_smoothness * total

    def after_step(self, step: int) -> None:
        """Hook after each optimiser step (occupancy updates and similar)."""

    def param_groups(self, lr: float) -> list[dict]:
        """Optimiser parameter groups: grid cells (of every GridField inside) at
        ``GRID_LR_FACTOR * lr`` (each cell sees few rays per step) and marked ``sparse`` (their
        gradients are sparse, see ``optim.FieldOptimizer``), everything else at ``lr``. The colour's
        parameters are marked for ``train.adam_beta2_colour``: the grid group's ``colour_channels``
        (start, stop) of its tables' columns (where every grid has the same) and the dense group's
        ``colour_params`` (the grids' colour decoders)."""
        grids = [m for m in self.modules() if isinstance(m, GridField)]
        grid = [p for m in grids for p in m.levels.parameters()]
        ids = {id(p) for p in grid}
        rest = [p for p in self.parameters() if id(p) not in ids and p.requires_grad]
        colour_params = [p for m in grids if m.decoder_width > 0 for p in m.decoder.parameters() if p.requires_grad]
        layouts = {(m.colour_channels.start, m.colour_channels.stop) for m in grids}
        colour_channels = next(iter(layouts)) if len(layouts) == 1 else None
        groups = [{"params": grid, "lr": lr * GRID_LR_FACTOR, "sparse": True,
                   "colour_channels": colour_channels}] if grid else []
        return groups + [{"params": rest, "lr": lr, "colour_params": colour_params}]
