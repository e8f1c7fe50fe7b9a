"""The paper's baselines (Table 1, docs/definitions.md §5) as real ``RadianceModel``s.

Every baseline uses the configured field backend (``field.backend``: the same backbone as
S-NeRF), the same samplers, quadrature, background and chunked rendering, and trains through
the same ``Trainer`` (same budget, split, seeds). None of them models a distribution over
fields, so all of them render the *mean field* (``draw_trajectories(deterministic=True)``:
density relu(mu_a), colour sigmoid(mu_c); the field's scale outputs are unused, except NeRF-W's,
which reads the colour-scale head as its beta).

Methods (registry names):

* ``deterministic``: one field, K = 1, Gaussian likelihood with S-NeRF's noise scale
  ``loss.likelihood_std`` (= MSE / (2 sigma_n^2) + const). It has no uncertainty: its colour
  variance is exactly zero (NLL is scored at the metric's variance floor, correlations are
  undefined). Its depth variance is the termination spread of its single trajectory (the
  epistemic part is zero).
* ``mc_dropout``: one field with dropout (rate ``field.dropout``, ``DEFAULT_DROPOUT_RATE`` when
  the config says 0). MLP backend: dropout after the odd trunk layers (``MLPField``). Grid
  backend: dropout on the interpolated grid features (every channel, before the density
  read-out and the colour decoder: the grid plays the MLP trunk's role) and on the colour
  decoder's hidden layer (``GridDropoutField``). Trained with dropout on; renders P passes
  (default ``DEFAULT_MC_DROPOUT_PASSES`` = 5, ``num_draws`` overrides) with dropout on; colour
  mean/variance, depth mean, epistemic depth variance across passes, spread averaged.
* ``ensemble``: M = ``DEFAULT_ENSEMBLE_SIZE`` (5) independently initialised deterministic
  fields trained together on the same batches (sum of their likelihoods); moments across
  members as for MC-Dropout.
* ``nerfw``: NeRF-W-style uncertainty without appearance/transient embeddings. Per point
  ``beta_ic = softplus(raw_ic)`` from the colour-scale head (per channel), rendered as an extra
  channel ``v_rc = sum_i w_i beta_ic^2 + beta_min^2`` (``constants.NERFW_BETA_MIN``) and
  trained with the Gaussian NLL ``sum_c [0.5 (c_c - C_c)^2 / v_c + 0.5 log v_c] + const``
  (NeRF-W's transient-density sparsity term has no counterpart without a transient field and is
  left out). Predicted colour variance = ``v``; depth as the deterministic NeRF.

Dropout masks are drawn from the generator the caller passes (the trainer's draw generator,
the evaluation seed), so training and renders are reproducible (``SeededDropout``).

Grid backend and deterministic draws: relu(mu_a) has zero gradient where mu_a < 0, and the grid
starts every cell at ``field.grid_init_density_loc`` (-1 by default, chosen for S-NeRF's random
draws). Deterministic methods therefore start the grid at the *same mean density* S-NeRF starts
from, ``E[relu(N(mu_0, s_0^2))] = mu_0 Phi(mu_0/s_0) + s_0 phi(mu_0/s_0)`` (0.083 for
mu_0 = -1, s_0 = 1), so their density can learn (``deterministic_density_init``). Ensemble
members on the grid also get independent density-cell noise (``ENSEMBLE_GRID_DENSITY_NOISE``)
since the grid's density cells otherwise start identical in every member.
"""

from __future__ import annotations

import contextlib
import copy
import math
from dataclasses import replace
from typing import Callable, Iterator

import torch
from torch import Tensor, nn

from ..constants import ENSEMBLE_GRID_DENSITY_NOISE, FIELD_STD_FLOOR, NERFW_BETA_MIN
from ..fields.base import FieldParams, StochasticField
from ..fields.grid import GridField
from ..losses import LossConfig, gaussian_likelihood_nll
from ..rays import RayBundle
from ..renderer import ChunkGenerators, ChunkRender, RenderOptions, RenderSettings, RayRender, render_chunked, render_rays
from ..volume_rendering import TrajectoryStatistics, accumulate, statistics_from_draws
from .base import RadianceModel
from .field_builder import build_field

#: Dropout rate of ``mc_dropout`` when ``field.dropout`` is 0 (the common MC-Dropout choice).
DEFAULT_DROPOUT_RATE: float = 0.2
#: Stochastic forward passes of MC-Dropout at render time (the paper: 5).
DEFAULT_MC_DROPOUT_PASSES: int = 5
#: Members of the deep ensemble (the paper: 5).
DEFAULT_ENSEMBLE_SIZE: int = 5


# --------------------------------------------------------------------------------------------
# dropout with an explicit generator
# --------------------------------------------------------------------------------------------


class SeededDropout(nn.Module):
    """Inverted dropout ``x * m / (1 - p)``, ``m ~ Bernoulli(1 - p)`` elementwise.

    Active while the module is in training mode or ``always_on`` is set (MC-Dropout renders).
    Masks come from ``generator`` (set by the owning model for the duration of a call; None:
    torch's global generator), so runs are reproducible and resumable.

    Shapes: x [*B] -> [*B].
    """

    def __init__(self, p: float):
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"dropout rate must be in [0, 1), got {p}")
        self.p = float(p)
        self.generator: torch.Generator | None = None
        self.always_on = False

    def forward(self, x: Tensor) -> Tensor:
        if self.p == 0.0 or not (self.training or self.always_on):
            return x
        keep = torch.rand(x.shape, generator=self.generator, device=x.device, dtype=x.dtype) >= self.p
        return x * keep / (1.0 - self.p)

    def extra_repr(self) -> str:
        return f"p={self.p}"


@contextlib.contextmanager
def dropout_control(module: nn.Module, generator: torch.Generator | None, *, always_on: bool | None = None) -> Iterator[None]:
    """Set the generator (and optionally ``always_on``) of every ``SeededDropout`` in ``module``
    for the duration of the block; restore them afterwards."""
    layers = [m for m in module.modules() if isinstance(m, SeededDropout)]
    saved = [(m.generator, m.always_on) for m in layers]
    for m in layers:
        m.generator = generator
        if always_on is not None:
            m.always_on = always_on
    try:
        yield
    finally:
        for m, (g, on) in zip(layers, saved):
            m.generator, m.always_on = g, on


class GridDropoutField(StochasticField):
    """A ``GridField`` with MC-Dropout: dropout on the interpolated features and on the colour
    decoder's hidden layer.

        v = dropout(g(x))                              all grid channels [P, 2 + F]
                                                       (and each level's features, dropped alike,
                                                       with ``concat_colour_levels``)
        mu_a = v_0 (outside the region: OUTSIDE_DENSITY_LOC)
        mu_c, raw_s_c = W_2 dropout(relu(W_1 [v_2.., PE(d)]))   (decoder_width > 0)

    Zeroing a negative mu_a keeps the point empty (relu(0) = 0): dropout never creates density
    in empty space. Parameters are those of the wrapped grid (its state-dict keys get the
    ``grid.`` prefix).
    """

    def __init__(self, grid: GridField, p: float):
        super().__init__()
        self.grid = grid
        self.feature_dropout = SeededDropout(p)
        self.hidden_dropout = SeededDropout(p)

    def forward(self, positions: Tensor, directions: Tensor) -> FieldParams:
        g = self.grid
        batch = positions.shape[:-1]
        unit = g.region.to_unit(positions.reshape(-1, 3))
        values, features = g._read(unit)  # [P, C], L x [P, F] or None
        values = self.feature_dropout(values)
        features = None if features is None else tuple(self.feature_dropout(f) for f in features)
        return g.decode(values, unit, directions, batch, hidden_transform=self.hidden_dropout, features=features)

    def density_params(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """Without dropout (occupancy-style queries want the mean field)."""
        return self.grid.density_params(positions)


# --------------------------------------------------------------------------------------------
# rendering helpers
# --------------------------------------------------------------------------------------------


def render_mean_field(field: StochasticField, rays: RayBundle, settings: RenderSettings, *, stratified: bool = False,
                      generator: torch.Generator | None = None) -> RayRender:
    """One trajectory of the mean field (eps = 0) per ray: rays [R] -> stats with K = 1."""
    return render_rays(field, rays, settings, num_draws=1, stratified=stratified, deterministic=True,
                       generator=generator)


def stack_draws(parts: list[TrajectoryStatistics]) -> TrajectoryStatistics:
    """Moments over the union of the draws of several renders of the same rays.

    Each part has per-draw fields [R, K_j, ...]; the result treats all sum_j K_j trajectories
    (dropout passes, ensemble members) as the draws: colour mean/variance, depth mean, epistemic
    variance Var D_k, spread E V_k, total = their sum.
    """
    return statistics_from_draws(torch.cat([p.colour_draws for p in parts], dim=1),
                                 torch.cat([p.depth_draws for p in parts], dim=1),
                                 torch.cat([p.spread_draws for p in parts], dim=1),
                                 torch.cat([p.opacity_draws for p in parts], dim=1))


def grid_total_variation(module: nn.Module, generator: torch.Generator | None) -> Tensor | None:
    """Sum of ``GridField.total_variation`` over every grid inside ``module`` (None: no grid)."""
    grids = [m for m in module.modules() if isinstance(m, GridField)]
    if not grids:
        return None
    return torch.stack([g.total_variation(generator=generator) for g in grids]).sum()


class _MeanFieldModel(RadianceModel):
    """Shared parts: settings, the grid TV term and the grid learning rates (as S-NeRF)."""

    def __init__(self, render_settings: RenderSettings, loss: LossConfig, *, tv_weight: float):
        super().__init__()
        self.render_settings = render_settings
        self.loss_config = loss
        self.tv_weight = tv_weight

    @property
    def trajectories(self) -> int | None:
        """K of every render (1, or the ensemble's M), or None where a render may choose it
        (MC-Dropout's passes)."""
        return 1

    def default_num_draws(self) -> int:
        """K of a render that asks for nothing."""
        return int(self.trajectories)

    def default_render_options(self) -> RenderOptions:
        """The run's render settings with this method's K and no adaptive K (one field pass per draw)."""
        return RenderOptions.from_settings(self.render_settings, num_draws=self.default_num_draws(),
                                           adaptive_draws=False)

    def render_options(self, **changes) -> RenderOptions:
        """As ``RadianceModel.render_options``; a K other than a fixed-K method's own, or adaptive K,
        is a ValueError naming the method."""
        name = type(self).__name__
        k = changes.get("num_draws")
        if k is not None and self.trajectories is not None and int(k) != self.trajectories:
            raise ValueError(f"{name} renders {self.trajectories} trajectory(ies) per ray; num_draws={k} cannot apply")
        if changes.get("adaptive_draws"):
            raise ValueError(f"{name} has no adaptive K (adaptive_draws applies to S-NeRF)")
        return super().render_options(**changes)

    def _render_chunks(self, chunk, rays: RayBundle, options: RenderOptions | None,
                       generator: "torch.Generator | ChunkGenerators | None") -> dict[str, Tensor]:
        """``renderer.render_chunked`` with this model's chunk renderer ``chunk(rays, generator, K)``."""
        options = options or self.default_render_options()
        K = self.trajectories or options.num_draws
        settings = options.settings_for(self.render_settings)
        return render_chunked(lambda r, g: chunk(r, g, K, settings), rays, options.chunk_rays, generator=generator,
                              keep_draws=options.keep_draws, progress=options.progress)

    def _regularise(self, loss: Tensor, logs: dict[str, float], generator: torch.Generator | None,
                    renders: list[RayRender]) -> Tensor:
        """``loss`` plus the occlusion term of the training ``renders`` and the grid TV term."""
        loss = self.add_occlusion(loss, logs, renders)
        if self.tv_weight > 0:
            tv = grid_total_variation(self, generator)
            if tv is not None:
                logs["tv"] = float(tv.detach())
                return loss + self.tv_weight * tv
        return loss

    def _likelihood_loss(self, out: RayRender, target: Tensor, generator: torch.Generator | None,
                         ray_weights: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
        """The Gaussian pixel likelihood (same sigma_n as S-NeRF) of the training render ``out``
        (each ray weighted by ``ray_weights`` [R], None: 1) plus the regularisers (``_regularise``);
        each ray's squared colour error is left in ``last_ray_errors``."""
        stats = out.stats
        nll = gaussian_likelihood_nll(stats.colour_draws, target, self.loss_config.likelihood_std,
                                      ray_weights=ray_weights)
        square_error = (stats.colour_mean.detach() - target) ** 2  # [R, 3]
        self.last_ray_errors = square_error.sum(-1)
        logs = {"nll": float(nll.detach()), "mse": float(square_error.mean())}
        return self._regularise(nll, logs, generator, [out]), logs


# --------------------------------------------------------------------------------------------
# the baselines
# --------------------------------------------------------------------------------------------


class DeterministicNeRF(_MeanFieldModel):
    """A deterministic NeRF on the configured backbone: K = 1, colour variance 0."""

    accepts_ray_weights = True

    def __init__(self, field: StochasticField, render_settings: RenderSettings, loss: LossConfig, *,
                 tv_weight: float = 0.0):
        super().__init__(render_settings, loss, tv_weight=tv_weight)
        self.field = field

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None,
                      ray_weights: Tensor | None = None) -> tuple[Tensor, dict[str, float]]:
        out = render_mean_field(self.field, rays, self.render_settings, stratified=True, generator=generator)
        return self._likelihood_loss(out, target, generator, ray_weights)

    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """One trajectory of the mean field per ray (K = 1)."""
        def chunk(r: RayBundle, gen, K: int, settings: RenderSettings) -> ChunkRender:
            out = render_mean_field(self.field, r, settings, generator=gen)
            return ChunkRender(out.stats, 1, out.extras["field_evals"])

        return self._render_chunks(chunk, rays, options, generator)


class MCDropoutNeRF(_MeanFieldModel):
    """MC-Dropout: trained with dropout on, rendered as P stochastic passes with dropout on."""

    def __init__(self, field: StochasticField, render_settings: RenderSettings, loss: LossConfig, *,
                 passes: int = DEFAULT_MC_DROPOUT_PASSES, tv_weight: float = 0.0):
        super().__init__(render_settings, loss, tv_weight=tv_weight)
        if not any(isinstance(m, SeededDropout) for m in field.modules()):
            raise ValueError("MCDropoutNeRF needs a field with SeededDropout layers (see build_mc_dropout)")
        if passes < 1:
            raise ValueError(f"MC-Dropout needs at least one pass, got passes={passes}")
        self.field = field
        self.passes = passes

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        with dropout_control(self, generator, always_on=True):
            out = render_mean_field(self.field, rays, self.render_settings, stratified=True, generator=generator)
        return self._likelihood_loss(out, target, generator)

    @property
    def trajectories(self) -> int | None:
        return None  # the passes P are a render option (num_draws)

    def default_num_draws(self) -> int:
        return self.passes

    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """``options.num_draws`` dropout passes P per ray (default ``self.passes``)."""
        def chunk(r: RayBundle, gen, K: int, settings: RenderSettings) -> ChunkRender:
            with dropout_control(self, gen, always_on=True):  # the dropout masks draw from the chunk's generator
                outs = [render_mean_field(self.field, r, settings, generator=gen) for _ in range(K)]
            return ChunkRender(stack_draws([o.stats for o in outs]), K, sum(o.extras["field_evals"] for o in outs))

        return self._render_chunks(chunk, rays, options, generator)


class DeepEnsemble(_MeanFieldModel):
    """M independently initialised mean fields trained on the same batches; moments across members."""

    def __init__(self, fields: list[StochasticField], render_settings: RenderSettings, loss: LossConfig, *,
                 tv_weight: float = 0.0):
        if len(fields) < 1:
            raise ValueError("an ensemble needs at least one member")
        super().__init__(render_settings, loss, tv_weight=tv_weight)
        self.members = nn.ModuleList(fields)

    def density_fields(self) -> list[nn.Module]:
        """Every member's field (each renders its own density)."""
        return list(self.members)

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        """Sum over members of each member's Gaussian likelihood NLL (members are independent:
        the sum's gradient w.r.t. a member is that member's own gradient)."""
        nlls, mses, outs = [], [], []
        for field in self.members:
            out = render_mean_field(field, rays, self.render_settings, stratified=True, generator=generator)
            outs.append(out)
            nlls.append(gaussian_likelihood_nll(out.stats.colour_draws, target, self.loss_config.likelihood_std))
            mses.append(float(((out.stats.colour_mean.detach() - target) ** 2).mean()))
        loss = torch.stack(nlls).sum()
        logs = {"nll": float(loss.detach()) / len(nlls), "mse": sum(mses) / len(mses)}
        return self._regularise(loss, logs, generator, outs), logs

    @property
    def trajectories(self) -> int | None:
        return len(self.members)

    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """The draws are the M members' mean-field renders (K = M)."""
        def chunk(r: RayBundle, gen, K: int, settings: RenderSettings) -> ChunkRender:
            outs = [render_mean_field(f, r, settings, generator=gen) for f in self.members]
            return ChunkRender(stack_draws([o.stats for o in outs]), K, sum(o.extras["field_evals"] for o in outs))

        return self._render_chunks(chunk, rays, options, generator)


def nerfw_point_variance(params: FieldParams) -> Tensor:
    """Per-point, per-channel beta_i^2 from the colour-scale head: params [*B] -> [*B, 3].

    ``beta = softplus(raw) = rgb_scale - FIELD_STD_FLOOR`` (``rgb_scale`` is softplus(raw) + floor);
    clamped at 0 against rounding.
    """
    return (params.rgb_scale - FIELD_STD_FLOOR).clamp_min(0.0) ** 2


def nerfw_ray_variance(weights: Tensor, point_variance: Tensor, beta_min: float = NERFW_BETA_MIN) -> Tensor:
    """The rendered variance channel: ``v_rc = sum_i w_i beta_ic^2 + beta_min^2``.

    Shapes: weights [R, S], point_variance [R, S, 3] -> [R, 3].
    """
    return accumulate(weights, point_variance) + beta_min ** 2


def gaussian_nll_learned_variance(colour: Tensor, target: Tensor, variance: Tensor) -> Tensor:
    """Mean over rays of ``sum_c [0.5 (C_c - c_c)^2 / v_c + 0.5 log v_c + 0.5 log 2 pi]``.

    Shapes: colour, target, variance [R, 3] -> scalar.
    """
    per = 0.5 * (colour - target) ** 2 / variance + 0.5 * torch.log(variance) + 0.5 * math.log(2 * math.pi)
    return per.sum(-1).mean()


class NeRFWUncertainty(_MeanFieldModel):
    """NeRF-W-style uncertainty: a per-point variance rendered as an extra channel, Gaussian NLL."""

    def __init__(self, field: StochasticField, render_settings: RenderSettings, loss: LossConfig, *,
                 beta_min: float = NERFW_BETA_MIN, tv_weight: float = 0.0):
        super().__init__(render_settings, loss, tv_weight=tv_weight)
        if not beta_min > 0:
            raise ValueError(f"beta_min must be > 0, got {beta_min}")
        self.field = field
        self.beta_min = float(beta_min)

    def _render(self, rays: RayBundle, *, stratified: bool, generator: torch.Generator | None,
                settings: RenderSettings | None = None) -> tuple[RayRender, Tensor]:
        """(the render, with K = 1; its rendered variance [R, 3]); ``settings`` default: the model's."""
        out = render_mean_field(self.field, rays, settings or self.render_settings, stratified=stratified,
                                generator=generator)
        weights = out.extras["weights"][:, 0]  # [R, S]
        var = nerfw_ray_variance(weights, nerfw_point_variance(out.params), self.beta_min)
        return out, var

    def training_loss(self, rays: RayBundle, target: Tensor, *, step: int,
                      generator: torch.Generator | None = None) -> tuple[Tensor, dict[str, float]]:
        out, var = self._render(rays, stratified=True, generator=generator)
        stats = out.stats
        nll = gaussian_nll_learned_variance(stats.colour_mean, target, var)
        logs = {"nll": float(nll.detach()), "mse": float(((stats.colour_mean.detach() - target) ** 2).mean()),
                "beta_rms": float(var.detach().mean().sqrt())}
        return self._regularise(nll, logs, generator, [out]), logs

    def render_view(self, rays: RayBundle, options: RenderOptions | None = None, *,
                    generator: "torch.Generator | ChunkGenerators | None" = None) -> dict[str, Tensor]:
        """One trajectory (K = 1); ``colour_var`` is the rendered variance."""
        def chunk(r: RayBundle, gen, K: int, settings: RenderSettings) -> ChunkRender:
            out, var = self._render(r, stratified=False, generator=gen, settings=settings)
            return ChunkRender(replace(out.stats, colour_var=var), 1)

        return self._render_chunks(chunk, rays, options, generator)


# --------------------------------------------------------------------------------------------
# builders (registered in models.registry.METHODS)
# --------------------------------------------------------------------------------------------


def mean_relu(loc: float, scale: float) -> float:
    """E[relu(X)], X ~ N(loc, scale^2): ``loc Phi(loc/scale) + scale phi(loc/scale)``."""
    z = loc / scale
    Phi = 0.5 * math.erfc(-z / math.sqrt(2.0))
    phi = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    return loc * Phi + scale * phi


def deterministic_density_init(cfg):
    """A copy of ``cfg`` whose grid starts at S-NeRF's initial *mean* density (see module doc), with
    one density field (``field.density_heads`` 1: the heads are alternatives for S-NeRF's trajectories
    to draw; a baseline's deterministic passes read the centre only, and the heads would be idle channels)."""
    cfg = copy.deepcopy(cfg)
    cfg.field.density_heads = 1
    if cfg.field.backend == "grid":
        cfg.field.grid_init_density_loc = mean_relu(cfg.field.grid_init_density_loc, cfg.field.init_std)
    return cfg


def _build_field(cfg, dataset, region, grid_resolution: tuple[int, int, int] | None):
    return build_field(cfg, region, dataset, grid_resolution=grid_resolution)


def build_deterministic(cfg, dataset, region, *, grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    c = deterministic_density_init(cfg)
    return DeterministicNeRF(_build_field(c, dataset, region, grid_resolution), cfg.render, cfg.loss, tv_weight=cfg.train.tv_weight)


def build_mc_dropout(cfg, dataset, region, *, passes: int = DEFAULT_MC_DROPOUT_PASSES,
                     grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    c = deterministic_density_init(cfg)
    rate = c.field.dropout if c.field.dropout > 0 else DEFAULT_DROPOUT_RATE
    c.field.dropout = rate
    field = _build_field(c, dataset, region, grid_resolution)
    if isinstance(field, GridField):
        field = GridDropoutField(field, rate)
    elif isinstance(getattr(field, "dropout", None), nn.Dropout):
        field.dropout = SeededDropout(rate)  # MLPField: dropout after the odd trunk layers
    else:
        raise ValueError(f"mc_dropout does not know where to put dropout in a {type(field).__name__}")
    return MCDropoutNeRF(field, cfg.render, cfg.loss, passes=passes, tv_weight=cfg.train.tv_weight)


def build_ensemble(cfg, dataset, region, *, members: int = DEFAULT_ENSEMBLE_SIZE,
                   grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    c = deterministic_density_init(cfg)
    fields = []
    for _ in range(members):
        field = _build_field(c, dataset, region, grid_resolution)  # each draws its own initial weights
        if isinstance(field, GridField):
            noise = ENSEMBLE_GRID_DENSITY_NOISE * abs(c.field.grid_init_density_loc) / math.sqrt(len(field.levels))
            with torch.no_grad():
                for level in field.levels:  # independent per level: the summed std is noise * sqrt(L)
                    level[:, 0].add_(noise * torch.randn_like(level[:, 0]))
        fields.append(field)
    return DeepEnsemble(fields, cfg.render, cfg.loss, tv_weight=cfg.train.tv_weight)


def build_nerfw(cfg, dataset, region, *, grid_resolution: tuple[int, int, int] | None = None) -> RadianceModel:
    c = deterministic_density_init(cfg)
    return NeRFWUncertainty(_build_field(c, dataset, region, grid_resolution), cfg.render, cfg.loss, tv_weight=cfg.train.tv_weight)


#: Registry entries: method name -> builder(cfg, dataset, region, *, grid_resolution=None).
BASELINE_BUILDERS: dict[str, Callable] = {
    "deterministic": build_deterministic,
    "mc_dropout": build_mc_dropout,
    "ensemble": build_ensemble,
    "nerfw": build_nerfw,
}
