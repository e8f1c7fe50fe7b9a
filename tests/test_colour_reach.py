"""Colours decoded only where a trajectory reaches (``render.colour_min_transmittance``): the kept
samples against a float64 loop, the bound on the composited colours and their gradients against
the full decode, the hard cases (an opaque first sample, no density at all, empty packed rays), and
a training step of S-NeRF and of the deterministic NeRF with the option on."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from stochastic_fields.constants import COLOUR_PLAN_MAX_PAIRS
from stochastic_fields.fields.grid import GridField
from stochastic_fields.fields.row_gather import row_gradient
from stochastic_fields.rays import RayBundle
from stochastic_fields.renderer import (RenderSettings, colour_plan, colour_reaching, pack_samples, render_any_samples,
                                        render_noise, render_rays)
from stochastic_fields.samplers import sample_along_rays
from stochastic_fields.scene_region import SceneRegion

TAU = 1e-3
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


def _field(seed: int = 0, *, noise_head: bool = True, density_shift: float = 0.0) -> GridField:
    torch.manual_seed(seed)
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (8, 7, 9), num_levels=2, decoder_width=8, feature_dim=4, noise_head=noise_head).double()
    with torch.no_grad():
        for table in field.levels:
            table.normal_(0.0, 1.0)
            table[:, 0] = table[:, 0] * 3.0 + density_shift  # some cells empty, some dense
    return field


def _rays(n: int = 48, seed: int = 1) -> RayBundle:
    g = torch.Generator().manual_seed(seed)
    origins = torch.zeros(n, 3, dtype=torch.float64)
    origins[:, 2] = -2.0
    directions = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.25
    directions[:, 2] = 1.0
    directions = directions / directions.norm(dim=-1, keepdim=True)
    ones = torch.ones(n, dtype=torch.float64)
    return RayBundle(origins, directions, 0.5 * ones, 3.5 * ones, ones)


def _settings(**changes) -> RenderSettings:
    """Every colour decoded unless ``changes`` set ``colour_min_transmittance``."""
    base = RenderSettings(num_samples=24, colour_estimator="draws", colour_min_transmittance=0.0)
    return dataclasses.replace(base, **changes)


def _reaching_loop(loc, scale, t_starts, t_ends, eps, tau):
    """The kept mask of ``colour_reaching``, one ray, trajectory and sample at a time (float64)."""
    R, S = loc.shape
    K = eps.shape[1]
    keep = torch.zeros(R, S, dtype=torch.bool)
    for r in range(R):
        for k in range(K):
            optical = 0.0
            for i in range(S):
                a = max(float(loc[r, i] + scale[r, i] * eps[r, k, i]), 0.0)
                if a > 0.0 and math.exp(-optical) >= tau:
                    keep[r, i] = True
                optical += a * float(t_ends[r, i] - t_starts[r, i])
    return keep


def test_kept_samples_match_a_float64_loop_dense_and_packed():
    field, settings = _field(), _settings()
    samples = sample_along_rays(_rays(12), settings.num_samples, stratified=True, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        loc, scale = field.density_params(samples.positions)
    eps = torch.randn(12, 5, settings.num_samples, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    kept = colour_reaching(loc, scale, samples, eps, TAU)
    expected = _reaching_loop(loc, scale, samples.t_starts, samples.t_ends, eps, TAU)
    assert torch.equal(kept, expected)
    assert 0 < int(kept.sum()) < kept.numel()  # the case is not trivial
    # packed: every sample kept by the occupancy test, eps laid out [K, N]
    packed = pack_samples(samples, torch.ones_like(kept))
    kept_packed = colour_reaching(loc.reshape(-1), scale.reshape(-1), packed, eps.permute(1, 0, 2).reshape(5, -1), TAU)
    assert torch.equal(kept_packed, expected.reshape(-1))
    # the mean field (deterministic render): eps = 0
    kept_mean = colour_reaching(loc, scale, samples, None, TAU)
    assert torch.equal(kept_mean, _reaching_loop(loc, scale, samples.t_starts, samples.t_ends,
                                                 torch.zeros(12, 1, settings.num_samples, dtype=torch.float64), TAU))


def test_all_kept_reads_exactly_what_forward_reads():
    field = _field()
    positions = torch.rand(300, 3, dtype=torch.float64) * 2.2 - 1.1  # some outside the cube
    directions = torch.nn.functional.normalize(torch.randn(300, 3, dtype=torch.float64), dim=-1)
    full = field(positions, directions)
    lazy = field.forward_colour_where(positions, directions, lambda loc, scale: torch.ones_like(loc, dtype=torch.bool))
    for name in ("density_loc", "density_scale", "rgb_loc", "rgb_scale", "noise_scale"):
        torch.testing.assert_close(getattr(lazy, name), getattr(full, name), rtol=0, atol=1e-14)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("layout", ["dense", "packed"])
@pytest.mark.parametrize("estimator", ["draws", "rao_blackwell"])
def test_composited_colours_within_tau_of_the_full_decode(layout, estimator, device):
    field = _field().to(device)
    settings = _settings(colour_min_transmittance=TAU, colour_estimator=estimator)
    samples = sample_along_rays(_rays().to(device), settings.num_samples, stratified=True,
                                generator=torch.Generator(device=device).manual_seed(4))
    if layout == "packed":  # drop a few samples, and every sample of ray 3 (an empty ray)
        keep = torch.rand(samples.t_starts.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64) > 0.2
        keep[3] = False
        samples = pack_samples(samples, keep.to(device))
    plan = colour_plan(samples, settings, 6, generator=torch.Generator(device=device).manual_seed(6))
    assert plan is not None and plan.noise is not None and plan.noise[0].device.type == device
    lazy_params = field.forward_colour_where(samples.positions, samples.directions, plan.where)
    full_params = field(samples.positions, samples.directions)
    lazy = render_any_samples(lazy_params, samples, settings, num_draws=6, noise=plan.noise)
    full = render_any_samples(full_params, samples, settings, num_draws=6, noise=plan.noise)
    kept = plan.where(full_params.density_loc.reshape(-1), full_params.density_scale.reshape(-1))
    assert 0.05 < float(kept.double().mean()) < 0.95  # some colours left out, some decoded
    # per trajectory and channel within tau; densities, depths and opacities unchanged
    assert float((lazy.stats.colour_draws - full.stats.colour_draws).detach().abs().max()) <= TAU
    torch.testing.assert_close(lazy.extras["weights"], full.extras["weights"], rtol=0, atol=0)
    torch.testing.assert_close(lazy.stats.depth_draws, full.stats.depth_draws, rtol=0, atol=0)


@pytest.mark.parametrize("heads", [1, 2])
@pytest.mark.parametrize("estimator", ["draws", "rao_blackwell"])
def test_a_render_reuses_the_plans_draws_bit_for_bit(estimator, heads):
    """Without autograd a dense render composites from the densities and transmittances the plan drew to
    find the reached samples (``ColourPlan.drawn``): the same maps bit for bit as drawing them again;
    with autograd (training) the plan keeps nothing."""
    torch.manual_seed(0)
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (8, 7, 9), num_levels=2, decoder_width=8, feature_dim=4, density_heads=heads).double()
    with torch.no_grad():
        for table in field.levels:
            table.normal_(0.0, 1.0)
            table[:, 0] *= 3.0
    settings = _settings(colour_min_transmittance=TAU, colour_estimator=estimator)
    samples = sample_along_rays(_rays(), settings.num_samples, stratified=True, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        plan = colour_plan(samples, settings, 6, generator=torch.Generator().manual_seed(6))
        params = field.forward_colour_where(samples.positions, samples.directions, plan.where)
        assert len(plan.drawn) == 2 and all(x.shape == (48, 6, 24) for x in plan.drawn)  # densities, transmittances
        reused = render_any_samples(params, samples, settings, num_draws=6, noise=plan.noise, drawn=plan.drawn)
        anew = render_any_samples(params, samples, settings, num_draws=6, noise=plan.noise)
    for name in ("colour_draws", "depth_draws", "spread_draws", "opacity_draws", "colour_var"):
        assert torch.equal(getattr(reused.stats, name), getattr(anew.stats, name)), name
    assert torch.equal(reused.extras["weights"], anew.extras["weights"])
    training_plan = colour_plan(samples, settings, 6, generator=torch.Generator().manual_seed(6))
    field.forward_colour_where(samples.positions, samples.directions, training_plan.where)
    assert training_plan.drawn is None


def test_gradients_within_the_bound_of_the_full_decode():
    """d (sum of colours) / d grid and decoder: the left-out samples' colours move the composited
    colour by less than tau, so every gradient changes by at most about tau times its scale."""
    settings = _settings(colour_min_transmittance=1e-6)
    samples = sample_along_rays(_rays(), settings.num_samples, stratified=True, generator=torch.Generator().manual_seed(7))
    grads = []
    for lazy in (False, True):
        field = _field()
        plan = colour_plan(samples, settings, 4, generator=torch.Generator().manual_seed(8))
        params = (field.forward_colour_where(samples.positions, samples.directions, plan.where) if lazy
                  else field(samples.positions, samples.directions))
        out = render_any_samples(params, samples, settings, num_draws=4, noise=plan.noise)
        (out.stats.colour_draws.sum() + out.stats.depth_draws.sum()).backward()
        # the grid tables keep their gradients as summed rows (RowGradient), the decoder as .grad
        grads.append({n: row_gradient(p).dense(p) if p.grad is None else p.grad.clone()
                      for n, p in field.named_parameters()})
    assert any(name.startswith("levels") for name in grads[0])
    for name, full in grads[0].items():
        assert float(full.abs().max()) > 0
        torch.testing.assert_close(grads[1][name], full, rtol=1e-4, atol=1e-5 * float(full.abs().max()))


def test_hard_cases_opaque_first_sample_and_no_density():
    settings = _settings(colour_min_transmittance=TAU)
    samples = sample_along_rays(_rays(8), settings.num_samples, stratified=False)
    shape = samples.t_starts.shape
    eps = (torch.zeros(8, 3, settings.num_samples, dtype=torch.float64),)
    # huge density everywhere: only the first sample of every ray is reached
    huge = torch.full(shape, 1e6, dtype=torch.float64)
    kept = colour_reaching(huge, torch.ones_like(huge), samples, eps[0], TAU)
    assert kept[:, 0].all() and not kept[:, 1:].any()
    # no density anywhere: no colour is needed, the render is the background alone
    none = torch.full(shape, -1e6, dtype=torch.float64)
    assert not colour_reaching(none, torch.ones_like(none), samples, eps[0], TAU).any()
    field = _field(density_shift=-1e3)
    out = render_rays(field, _rays(8), dataclasses.replace(settings, background=(0.2, 0.4, 0.6)), num_draws=3,
                      generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(out.stats.colour_mean, torch.tensor([[0.2, 0.4, 0.6]], dtype=torch.float64).expand(8, 3))


def test_off_or_trapezoid_decodes_every_colour():
    assert RenderSettings().colour_min_transmittance == 1e-4  # the default since study 46
    samples = sample_along_rays(_rays(4), 8, stratified=False)
    assert colour_plan(samples, _settings(), 4) is None
    assert colour_plan(samples, _settings(colour_min_transmittance=TAU, quadrature="trapezoid"), 4) is None
    plan = colour_plan(samples, _settings(colour_min_transmittance=TAU), 4, deterministic=True)
    assert plan.noise is None  # the mean field: nothing drawn
    # too many (sample, draw) pairs to draw at once: every colour decoded, the draw blocks bound memory
    K = COLOUR_PLAN_MAX_PAIRS // samples.t_starts.numel() + 1
    assert colour_plan(samples, _settings(colour_min_transmittance=TAU), K) is None
    assert colour_plan(samples, _settings(colour_min_transmittance=TAU), K - 1) is not None


def test_render_noise_shapes():
    settings = _settings()
    samples = sample_along_rays(_rays(5), settings.num_samples, stratified=False)
    eps_a, eps_c = render_noise(samples, 3, settings, colour=True)
    assert eps_a.shape == (5, 3, settings.num_samples) and eps_c.shape == (5, 3, settings.num_samples, 3)
    packed = pack_samples(samples, torch.rand(samples.t_starts.shape) > 0.5)
    eps_a, eps_c = render_noise(packed, 3, settings, colour=False)
    assert eps_a.shape == (3, packed.ray_indices.shape[0]) and eps_c is None
    shared = dataclasses.replace(settings, shared_noise=True)
    eps_a, eps_c = render_noise(packed, 3, shared, colour=True)  # one eps per ray and draw, gathered per sample
    for k in range(3):
        for r in packed.ray_indices.unique():
            assert eps_a[k, packed.ray_indices == r].unique().numel() == 1


@pytest.fixture(scope="module")
def tiny_dataset(tiny_scene):
    from stochastic_fields.data import load_dataset

    return load_dataset(tiny_scene)


def _tiny(method: str, tau: float):
    from test_baselines import tiny_config

    cfg = tiny_config(method)
    cfg.render.colour_min_transmittance = tau
    return cfg


def test_deterministic_nerf_loss_within_tau_of_the_full_decode(tiny_dataset):
    """The mean field draws nothing, so both renders see the same samples: the scaled squared error
    of colours within tau of each other differs by at most (2 |C - c| tau + tau^2) / (2 sigma^2)."""
    from stochastic_fields.models.registry import build_model

    losses = []
    for tau in (0.0, TAU):
        torch.manual_seed(0)
        model = build_model(_tiny("deterministic", tau), tiny_dataset)
        view = tiny_dataset.train_indices[0]
        rays = tiny_dataset.rays(view)[::4, ::4].flatten()
        target = tiny_dataset.images[view][::4, ::4].reshape(-1, 3)
        loss, _ = model.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(1))
        losses.append(float(loss.detach()))
    sigma = model.loss_config.likelihood_std
    assert abs(losses[1] - losses[0]) <= 3 * (2 * TAU + TAU ** 2) / (2 * sigma ** 2)


def test_snerf_trains_and_renders_with_the_option(tiny_dataset, tmp_path):
    from stochastic_fields.trainer import Trainer

    cfg = _tiny("snerf", TAU)
    cfg.train.iterations = 6
    model = Trainer(cfg, tmp_path, tiny_dataset).train(progress=False)
    assert all(torch.isfinite(p).all() for p in model.parameters())
    maps = model.render_view(tiny_dataset.rays(tiny_dataset.test_indices[0]),
                             generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(maps["colour_mean"]).all() and torch.isfinite(maps["depth_var_total"]).all()
