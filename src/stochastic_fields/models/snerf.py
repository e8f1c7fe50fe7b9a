"""S-NeRF: a stochastic field trained by variational inference (docs/definitions.md §2-§4).

Empty-space skipping (``render_settings.skip_empty_space``): an ``OccupancyGrid`` over the scene
region's unit cube [-1, 1]^3 (``SceneRegion.to_unit``), so the same code serves box (aabb) and
forward-facing (ndc) regions; in NDC the cells are uniform in image space and disparity, like
the samples. After each optimiser step (``after_step``, every ``occupancy_update_every`` steps)
cells are refreshed from the per-sample optical-depth upper estimate

    tau_up(x) = relu(mu_a(x) + n s_a(x)) * delta(x)        n = render.occupancy_num_std (3)

(uncertain space is not empty: a cell whose density is uncertain stays occupied), where
``delta(x)`` is the length of one render interval at x: ``(far - near) / S`` for linear spacing,
``t^2 (1/near - 1/far) / S`` for disparity spacing (t: the distance from the reference camera in
NDC regions, the largest far bound otherwise; both measured on the training rays). A cell is
occupied where ``1 - exp(-tau_up) > render.occupancy_alpha_threshold`` (then dilated by one cell).
Training and rendering evaluate the field only at occupied samples (packed layout, alpha
compositing); the observed-ray KL is then taken over the kept samples.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ..adaptive import render_image_adaptive
from ..distortion import distortion_loss, distortion_loss_packed, normalised_coordinate, sample_bounds
from ..fields.base import StochasticField
from ..fields.grid import GridField
from ..losses import (LossConfig, Priors, decoupled_likelihood_nll, depth_weight, draw_weights, field_kl_means,
                      gaussian_likelihood_nll, termination_depth_nll)
from ..occupancy import OccupancyGrid, density_threshold, density_upper_estimate
from ..rays import PackedRaySamples, RayBundle, RaySamples
from ..renderer import (ChunkGenerators, ChunkRender, RayRender, RenderOptions, RenderSettings, colour_plan,
                        observation_noise_per_draw, render_any_samples, render_chunked, render_rays, skip_empty,
                        trajectory_weights)
from ..samplers import sample_along_rays
from ..scene_region import SceneRegion, random_unit_directions
from ..termination import with_depth_estimate
from .base import RadianceModel

UNIT_CUBE = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _allow_missing_occupancy(module, incompatible_keys) -> None:
    """Checkpoints written without skipping load into a model with it: the grid stays all-occupied
    (exact: nothing inside the region is skipped) until training updates it."""
    for key in list(incompatible_keys.missing_keys):
        if "occupancy." in key or key.endswith("interval_scale"):
            incompatible_keys.missing_keys.remove(key)


class SNeRF(RadianceModel):
    running_max_buffers = ("interval_scale",)  # the occupancy refresh reads it (absent without skipping)

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
        if loss.learn_likelihood_std:
            self.log_likelihood_std = nn.Parameter(torch.full((3,), math.log(loss.likelihood_std)))
        # the observation-noise head (§4.7) is used when the field has one (``loss.per_point_noise``
        # makes the builder add it: field_builder.build_field(..., noise_head=True))
        self.noise_head = bool(getattr(field, "noise_head", False))
        if render_settings.colour_variance not in ("epistemic", "predictive"):
            raise ValueError("render.colour_variance must be 'epistemic' or 'predictive', "
                             f"got {render_settings.colour_variance!r}")
        self.occupancy: OccupancyGrid | None = None
        if render_settings.skip_empty_space:
            if render_settings.quadrature != "alpha":
                raise ValueError("render.skip_empty_space needs render.quadrature='alpha' (the packed trapezoid "
                                 f"interpolates across skipped gaps), got {render_settings.quadrature!r}")
            self.occupancy = OccupancyGrid(UNIT_CUBE, render_settings.occupancy_resolution)
            # (c, t_max): interval length c (linear) or c * t^2 (disparity); 0 until a training batch sets it
            self.register_buffer("interval_scale", torch.zeros(2))
            self.register_load_state_dict_post_hook(_allow_missing_occupancy)

    def likelihood_std(self) -> Tensor:
        """[3] sigma_n per colour channel (learned or ``loss.likelihood_std``)."""
        if self.loss_config.learn_likelihood_std:
            return self.log_likelihood_std.exp()
        return torch.full((3,), self.loss_config.likelihood_std, device=self.priors.random_rgb_loc.device)

    # ------------------------------------------------------------------ empty-space skipping
    def occupied(self, positions: Tensor) -> Tensor:
        """[*B, 3] world points -> [*B] bool: inside the region in an occupied cell."""
        if self.occupancy is None:
            return torch.ones(positions.shape[:-1], dtype=torch.bool, device=positions.device)
        return self.occupancy.occupied(self.region.to_unit(positions))

    def _record_interval_scale(self, rays: RayBundle) -> None:
        S = self.render_settings.num_samples
        if self.render_settings.spacing == "linear":
            c = ((rays.far - rays.near) / S).max()
        else:
            c = ((1.0 / rays.near - 1.0 / rays.far) / S).max()
        self.interval_scale.copy_(torch.stack([torch.maximum(c, self.interval_scale[0]),
                                               torch.maximum(rays.far.max(), self.interval_scale[1])]))

    def interval_length(self, unit: Tensor) -> Tensor:
        """[P] length (ray distance) of one render interval at unit-cube points [P, 3] (see module doc)."""
        c, t_max = self.interval_scale.to(unit).unbind()
        if self.render_settings.spacing == "linear":
            return c.expand(unit.shape[:-1])
        if self.region.kind == "ndc":
            world = self.region.from_unit(unit)
            R, t = self.region.ref_w2c[:3, :3].to(unit), self.region.ref_w2c[:3, 3].to(unit)
            z = (world @ R.T + t)[..., 2].clamp_min(0.0)
            tan_x, tan_y, _ = self.region.ndc_scale.to(unit).unbind()
            # ray distance <= z / cos(corner angle): 1/cos^2 = 1 + tan_x^2 + tan_y^2 at the image corner
            return c * z ** 2 * (1.0 + tan_x ** 2 + tan_y ** 2)
        return (c * t_max ** 2).expand(unit.shape[:-1])

    def optical_depth_upper(self, unit: Tensor, num_std: float | None = None) -> Tensor:
        """[P] upper estimate relu(mu_a + n s_a) * delta of one interval's optical depth at unit points [P, 3]
        (n = ``num_std``, default ``render_settings.occupancy_num_std``)."""
        n = self.render_settings.occupancy_num_std if num_std is None else num_std
        upper = density_upper_estimate(self.field, n)
        return upper(self.region.from_unit(unit)) * self.interval_length(unit)

    def _occupancy_threshold(self, alpha_threshold: float | None = None) -> float:
        # optical depth of one interval (step 1: optical_depth_upper already multiplies by delta)
        alpha = self.render_settings.occupancy_alpha_threshold if alpha_threshold is None else alpha_threshold
        return density_threshold(1.0, alpha)

    @torch.no_grad()
    def rebuild_occupancy(self, passes: int = 4, seed: int = 0, *, num_std: float | None = None,
                          alpha_threshold: float | None = None) -> float:
        """Recompute the occupancy grid from the trained field: every cell evaluated at ``passes``
        jittered points, the maximum kept, occupied where the upper estimate with ``num_std`` gives
        an interval an opacity above ``alpha_threshold`` (defaults: the run's
        ``occupancy_num_std``, ``occupancy_alpha_threshold``). Returns the occupied fraction."""
        if self.occupancy is None or not bool(self.interval_scale[0] > 0):
            raise ValueError("rebuild_occupancy needs a model trained with render.skip_empty_space")
        self.occupancy.density_ema.zero_()
        gen = torch.Generator(device=self.occupancy.occupancy.device).manual_seed(seed)
        for _ in range(passes):
            self.occupancy.update(lambda unit: self.optical_depth_upper(unit, num_std), 0, decay=1.0,
                                  threshold=self._occupancy_threshold(alpha_threshold), warmup_steps=1,
                                  update_every_n_steps=1, generator=gen)
        return self.occupancy.occupied_fraction

    def after_step(self, step: int) -> None:
        """Refresh the occupancy grid (every ``occupancy_update_every`` steps; seeded by the step)."""
        if self.occupancy is None or not bool(self.interval_scale[0] > 0):
            return
        settings = self.render_settings
        gen = torch.Generator(device=self.occupancy.occupancy.device).manual_seed(int(step))
        self.occupancy.update(self.optical_depth_upper, step, threshold=self._occupancy_threshold(),
                              warmup_steps=settings.occupancy_warmup_steps,
                              update_every_n_steps=settings.occupancy_update_every, generator=gen)

    #: the trainer passes capture-point depth batches (``depth=``) to this model
    accepts_depth = True
    accepts_ray_weights = True
    #: ``training_loss`` takes each ray's density-head weights (``loss.head_bootstrap_keep``)
    accepts_head_weights = True
    #: the density is a rectified normal; its regularisers read its mean
    mean_field_density = False

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None,
                      depth: tuple[RayBundle, Tensor] | None = None,
                      ray_weights: Tensor | None = None,
                      head_weights: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
        """The variational loss (losses module doc) on a batch of rays [R] with colours [R, 3];
        ``depth``: capture-point rays [M] and their surface ray distances t* [M] for the
        sparse-depth likelihood (weighted by ``loss.lambda_depth``); ``ray_weights`` [R]: each ray's
        weight in the colour likelihood (the error-guided sampler's, stochastic_fields.ray_sampling);
        ``head_weights`` [R, M]: each ray's weight in each density head's colour likelihood
        (``loss.head_bootstrap_keep``, ``losses.bootstrap_head_weights``), applied to the draws of
        each head. Leaves each ray's squared colour error in ``last_ray_errors`` [R]."""
        cfg = self.loss_config
        if head_weights is not None:
            per_draw = draw_weights(head_weights, self.train_draws)
            ray_weights = per_draw if ray_weights is None else ray_weights[:, None] * per_draw
        settings = self.render_settings
        samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing, stratified=True,
                                    generator=generator)
        if self.occupancy is not None:
            with torch.no_grad():
                self._record_interval_scale(rays)
            samples = skip_empty(samples, self.occupied)
        positions, directions = samples.positions.reshape(-1, 3), samples.directions.reshape(-1, 3)
        n_ray = samples.t_starts.numel()
        # colours decoded only where a trajectory reaches (render.colour_min_transmittance): the draws
        # are fixed first, and the observed-ray KL's points picked first, so their colours are decoded
        plan = colour_plan(samples, settings, self.train_draws, colour_estimator=cfg.likelihood_estimator,
                           generator=generator)
        observed_pick = None
        if plan is not None and cfg.kl == "full" and 0 < cfg.observed_kl_samples < n_ray:
            observed_pick = torch.randperm(n_ray, generator=generator, device=positions.device)[:cfg.observed_kl_samples]
        use_random_kl = cfg.kl in ("fixed_prior", "full")
        if use_random_kl:
            # one field evaluation for ray samples and random KL points: one gradient pass over the grid
            pts = self.region.sample_stratified(cfg.random_points_per_axis, generator=generator)
            dirs = random_unit_directions(len(pts), generator=generator, device=pts.device)
            positions, directions = torch.cat([positions, pts]), torch.cat([directions, dirs])
        if plan is None:
            params_all = self.field(positions, directions)
        else:
            def colour_where(loc: Tensor, scale: Tensor, offsets: Tensor | None = None) -> Tensor:
                # [P] -> [P]: reached, picked or random
                need = plan.where(loc[:n_ray], scale[:n_ray], None if offsets is None else offsets[:n_ray])
                if observed_pick is not None:
                    need = need.index_fill(0, observed_pick, True)
                return torch.cat([need, need.new_ones(loc.shape[0] - n_ray)])

            params_all = self.field.forward_colour_where(positions, directions, colour_where)
        params = params_all.map(lambda t: t[:n_ray]).reshape(*samples.t_starts.shape)
        # drawn colours, or (Rao-Blackwellised) each draw's colour mean and variance given its density
        rao_blackwell = cfg.likelihood_estimator == "rao_blackwell"
        out = render_any_samples(params, samples, settings, num_draws=self.train_draws, generator=generator,
                                 colour_estimator=cfg.likelihood_estimator, observation_noise=False,
                                 noise=None if plan is None else plan.noise)
        colour_var = out.stats.colour_noise_var_draws if rao_blackwell else None  # [R, K, 3] sum_i w_ik^2 Var[r_i]
        sigma_n = self.likelihood_std()
        noise_var = None
        if self.noise_head:  # per-draw variance sigma_n^2 + sum_i w_ik beta_i^2 (§4.7)
            noise_var = observation_noise_per_draw(out, detach_weights=cfg.noise_head_decoupled)
        if noise_var is not None and cfg.noise_head_decoupled:
            nll = decoupled_likelihood_nll(out.stats.colour_draws, target, sigma_n, noise_var, colour_var, ray_weights)
        else:
            nll = gaussian_likelihood_nll(out.stats.colour_draws, target, sigma_n, noise_var, colour_var, ray_weights)
        square_error = (out.stats.colour_mean.detach() - target) ** 2  # [R, 3]
        self.last_ray_errors = square_error.sum(-1)
        loss = nll
        logs = {"nll": nll.item(), "mse": square_error.mean().item(),
                "field_evals_per_ray": n_ray / max(len(rays), 1)}
        if cfg.learn_likelihood_std:
            logs["likelihood_std"] = sigma_n.mean().item()
        if noise_var is not None:
            logs["noise_head_rms"] = noise_var.detach().mean().sqrt().item()
        kl_parts = []  # (log name, weight, params, prior): every KL term of the loss, evaluated in one batch
        unit = self.field.density_unit_factor()  # the priors are on the field's own density parameters
        if use_random_kl:
            kl_parts.append(("kl_random", cfg.lambda_random, params_all.map(lambda t: t[n_ray:]), self.priors.random(unit)))
        if cfg.kl == "full":
            obs = out.params.map(lambda t: t.reshape(-1, *t.shape[out.params.density_loc.dim():]))
            n_obs = cfg.observed_kl_samples
            if observed_pick is not None:
                obs = obs.map(lambda t: t[observed_pick])
            elif 0 < n_obs < obs.density_loc.shape[0]:
                pick = torch.randperm(obs.density_loc.shape[0], generator=generator, device=obs.density_loc.device)[:n_obs]
                obs = obs.map(lambda t: t[pick])
            kl_parts.append(("kl_observed", cfg.lambda_observed, obs, self.priors.observed(unit)))
        elif cfg.kl not in ("none", "fixed_prior"):
            raise ValueError(f"loss.kl must be 'none', 'fixed_prior' or 'full', got {cfg.kl!r}")
        kls = field_kl_means([(p, prior) for _, _, p, prior in kl_parts], estimator=cfg.kl_estimator,
                             mc_samples=cfg.kl_mc_samples, generator=generator)
        for (name, weight, _, _), kl in zip(kl_parts, kls):
            loss = loss + weight * kl
            logs[name] = kl.item()
        if cfg.lambda_distortion > 0:
            dist = self._distortion(out, samples)
            loss = loss + cfg.lambda_distortion * dist
            logs["distortion"] = dist.item()
        loss = self.add_occlusion(loss, logs, [out])
        if depth is not None and cfg.lambda_depth > 0:
            depth_nll = self._depth_nll(*depth, generator=generator)
            weight = depth_weight(cfg.lambda_depth, cfg.depth_final_factor, self.training_progress)
            loss = loss + weight * depth_nll
            logs["depth_nll"] = depth_nll.item()
            if cfg.depth_final_factor != 1.0:
                logs["depth_weight"] = weight
        if self.tv_weight > 0 and isinstance(self.field, GridField):
            tv = self.field.total_variation(generator=generator)
            loss = loss + self.tv_weight * tv
            logs["tv"] = tv.item()
        return loss, logs

    def depth_trajectories(self, rays: RayBundle, *, generator: torch.Generator | None
                           ) -> tuple[RaySamples, Tensor, Tensor, Tensor]:
        """What the depth likelihood reads on capture-point rays [M]: dense stratified samples (as
        the colour rays, without skipping), the field's density parameters there (``field.density_params``:
        no colour decoder, and on the grid a backward over 2 of its channels) and ``loss.depth_draws``
        trajectories (0: ``train_draws``) of the density alone (``trajectory_weights``; drawn with
        stopgrad(scale) unless ``loss.depth_trains_scale``). Returns
        (samples, density loc [M, S], density scale [M, S], weights [M, K, S])."""
        settings = self.render_settings
        samples = sample_along_rays(rays, settings.num_samples, spacing=settings.spacing, stratified=True,
                                    generator=generator)
        loc, scale, offsets = self.field.density_head_params(samples.positions)  # [M, S] each, offsets [M, S, H]
        num_draws = self.loss_config.depth_draws or self.train_draws
        drawn_scale = scale if self.loss_config.depth_trains_scale else scale.detach()
        weights = trajectory_weights(loc, drawn_scale, samples, settings, num_draws=num_draws, generator=generator,
                                     density_offsets=offsets)
        return samples, loc, scale, weights

    def _depth_nll(self, rays: RayBundle, target_t: Tensor, *, generator: torch.Generator | None) -> Tensor:
        """``termination_depth_nll`` of capture-point rays [M] at their surface distances [M], on the
        trajectories of ``depth_trajectories``."""
        samples, _, _, weights = self.depth_trajectories(rays, generator=generator)
        return termination_depth_nll(weights, samples.t_mids, samples.deltas, target_t,
                                     self.loss_config.depth_relative_std, self.loss_config.depth_likelihood,
                                     self.loss_config.depth_outlier_share)

    def _distortion(self, out: RayRender, samples: RaySamples | PackedRaySamples) -> Tensor:
        """Mean distortion over training rays and trajectories (stochastic_fields.distortion)."""
        spacing = self.render_settings.spacing
        near, far = sample_bounds(samples)
        s0 = normalised_coordinate(samples.t_starts, near, far, spacing)
        s1 = normalised_coordinate(samples.t_ends, near, far, spacing)
        if isinstance(samples, PackedRaySamples):
            return distortion_loss_packed(out.extras["weights"], s0, s1, samples.ray_indices, samples.num_rays).mean()
        return distortion_loss(out.extras["weights"], s0[:, None, :], s1[:, None, :]).mean()

    def _occupied_for(self, settings: RenderSettings):
        """The occupancy test of a render with ``settings``: the grid where one is kept and the
        quadrature is alpha (a trapezoid render evaluates every sample), else None."""
        return self.occupied if self.occupancy is not None and settings.quadrature == "alpha" else None

    @torch.no_grad()
    def render_chunk(self, rays: RayBundle, options: RenderOptions, *,
                     generator: torch.Generator | None = None) -> RayRender:
        """One chunk of rays [R] with ``options.num_draws`` trajectories, as ``render_view`` renders
        it (same samples, skipping and noise for the same generator): the notebook's pixel probe
        reads the samples, parameters and weights behind a pixel from it."""
        settings = options.settings_for(self.render_settings)
        out = render_rays(self.field, rays, settings, num_draws=options.num_draws, generator=generator,
                          occupied=self._occupied_for(settings))
        return with_depth_estimate(out, rays, settings.depth_estimate)

    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """Maps of ``rays`` [H, W] (``RadianceModel.render_view``): a fixed K, or adaptive K per chunk
        with ``options.adaptive_draws``. Empty space is skipped with the occupancy grid (alpha
        quadrature only: a trapezoid render evaluates every sample). With ``colour_variance =
        'predictive'`` the colour variance adds sigma_n^2 and, with a noise head, the mean over
        draws of sum_i w_ik beta_i^2 (law of total variance, docs/definitions.md §4.7)."""
        options = options or self.default_render_options()
        settings = options.settings_for(self.render_settings)
        if options.adaptive_draws:
            if settings.depth_estimate != "mean":
                raise ValueError(f"render.depth_estimate {settings.depth_estimate!r} needs a fixed K: adaptive draws "
                                 "render their trajectories in batches (render with adaptive_draws off)")
            maps = render_image_adaptive(self.field, rays, settings, generator=generator, keep_draws=options.keep_draws,
                                         progress=options.progress, occupied=self._occupied_for(settings))
        else:
            def chunk(r: RayBundle, gen: torch.Generator | None) -> ChunkRender:
                out = self.render_chunk(r, options, generator=gen)
                return ChunkRender(out.stats, options.num_draws, out.extras["field_evals"])

            maps = render_chunked(chunk, rays, options.chunk_rays, generator=generator, keep_draws=options.keep_draws,
                                  progress=options.progress)
        if settings.colour_variance == "predictive":
            # Var[c] = E_k Var[c | C_k] + Var_k C_k = sigma_n^2 + epistemic (law of total variance)
            maps["colour_var"] = maps["colour_var"] + self.likelihood_std().detach().to(maps["colour_var"]) ** 2
        return maps
