"""S-NeRF: a stochastic field trained by variational inference (SPEC 2-4)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..fields.base import StochasticField
from ..fields.grid import GridField
from ..losses import LossConfig, Priors, field_kl, gaussian_likelihood_nll
from ..rays import RayBundle
from ..renderer import RenderSettings, render_image, render_samples
from ..samplers import sample_along_rays
from ..scene_region import SceneRegion, random_unit_directions
from .base import RadianceModel


class SNeRF(RadianceModel):
    def __init__(self, field: StochasticField, region: SceneRegion, render_settings: RenderSettings,
                 loss: LossConfig, *, train_draws: int = 8, tv_weight: float = 0.0):
        super().__init__()
        self.field = field
        self.region = region
        self.priors = Priors()
        self.render_settings = render_settings
        self.loss_config = loss
        self.train_draws = train_draws
        self.tv_weight = tv_weight

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        cfg = self.loss_config
        settings = self.render_settings
        samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing, stratified=True,
                                    generator=generator)
        positions, directions = samples.positions.reshape(-1, 3), samples.directions.reshape(-1, 3)
        use_random_kl = cfg.kl in ("fixed_prior", "full")
        if use_random_kl:
            # one field evaluation for ray samples and random KL points: one gradient pass over the grid
            pts = self.region.sample_stratified(cfg.random_points_per_axis, generator=generator)
            dirs = random_unit_directions(len(pts), generator=generator, device=pts.device)
            positions, directions = torch.cat([positions, pts]), torch.cat([directions, dirs])
        params_all = self.field(positions, directions)
        n_ray = samples.t_starts.numel()
        params = params_all.map(lambda t: t[:n_ray]).reshape(*samples.t_starts.shape)
        out = render_samples(params, samples, settings, num_draws=self.train_draws, generator=generator)
        nll = gaussian_likelihood_nll(out.stats.colour_draws, target, cfg.likelihood_std)
        loss = nll
        logs = {"nll": nll.item(), "mse": ((out.stats.colour_mean.detach() - target) ** 2).mean().item()}
        if use_random_kl:
            kl_rand = field_kl(params_all.map(lambda t: t[n_ray:]), self.priors.random(), estimator=cfg.kl_estimator,
                               mc_samples=cfg.kl_mc_samples, generator=generator).mean()
            loss = loss + cfg.lambda_random * kl_rand
            logs["kl_random"] = kl_rand.item()
        if cfg.kl == "full":
            obs = out.params.map(lambda t: t.reshape(-1, *t.shape[2:]))
            n_obs = cfg.observed_kl_samples
            if 0 < n_obs < obs.density_loc.shape[0]:
                pick = torch.randperm(obs.density_loc.shape[0], generator=generator, device=obs.density_loc.device)[:n_obs]
                obs = obs.map(lambda t: t[pick])
            kl_obs = field_kl(obs, self.priors.observed(), estimator=cfg.kl_estimator,
                              mc_samples=cfg.kl_mc_samples, generator=generator).mean()
            loss = loss + cfg.lambda_observed * kl_obs
            logs["kl_observed"] = kl_obs.item()
        elif cfg.kl != "none":
            raise ValueError(f"loss.kl must be 'none', 'fixed_prior' or 'full', got {cfg.kl!r}")
        if self.tv_weight > 0 and isinstance(self.field, GridField):
            tv = self.field.total_variation(generator=generator)
            loss = loss + self.tv_weight * tv
            logs["tv"] = tv.item()
        return loss, logs

    def render_view(self, rays: RayBundle, *, num_draws: int | None = None,
                    generator: torch.Generator | None = None, keep_draws: bool = False,
                    progress: bool = False) -> dict[str, Tensor]:
        return render_image(self.field, rays, self.render_settings, num_draws=num_draws, generator=generator,
                            keep_draws=keep_draws, progress=progress)

    def param_groups(self, lr: float) -> list[dict]:
        if isinstance(self.field, GridField):
            grid = list(self.field.levels.parameters())
            grid_ids = {id(p) for p in grid}
            rest = [p for p in self.parameters() if id(p) not in grid_ids]
            return [{"params": grid, "lr": lr * 10.0}, {"params": rest, "lr": lr}]
        return super().param_groups(lr)
