"""Baselines (docs/definitions.md §5): every method trains and renders through the shared pipeline; their
uncertainties are checked against independent computations (numpy moments over the draws,
float64 loops over samples, torch.distributions, scipy quadrature)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.integrate
import scipy.stats
import torch

from stochastic_fields.config import preset
from stochastic_fields.constants import FIELD_STD_FLOOR, NERFW_BETA_MIN, NLL_VARIANCE_FLOOR
from stochastic_fields.data import load_dataset
from stochastic_fields import metrics as M
from stochastic_fields.evaluation import score_view
from stochastic_fields.view_maps import camera_z_maps
from stochastic_fields.fields.grid import GridField
from stochastic_fields.losses import gaussian_likelihood_nll
from stochastic_fields.models import baselines as B
from stochastic_fields.models.registry import METHODS, build_model, fit_scene_region
from stochastic_fields.renderer import MAP_NAMES, render_rays
from stochastic_fields.trainer import Trainer, load_trained_model

BASELINES = ("deterministic", "mc_dropout", "ensemble", "nerfw")
#: trajectories per rendered pixel: 1, dropout passes, members, 1
EXPECTED_K = {"deterministic": 1, "mc_dropout": B.DEFAULT_MC_DROPOUT_PASSES, "ensemble": B.DEFAULT_ENSEMBLE_SIZE,
              "nerfw": 1}


def tiny_config(method: str, backend: str = "grid"):
    """Seconds on 2 CPU cores: a 16^3 two-level grid (or a 2 x 32 MLP), 16 samples, 64 rays."""
    cfg = preset("tiny")
    cfg.method = method
    cfg.train.iterations = 3
    cfg.train.rays_per_batch = 64
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    cfg.render.num_samples = 16
    cfg.render.chunk_rays = 256
    cfg.field.backend = backend
    cfg.field.grid_max_cells = 16 ** 3
    cfg.field.grid_levels = 2
    cfg.field.mlp_depth = 2
    cfg.field.mlp_width = 32
    return cfg


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    return load_dataset(tiny_scene)


@pytest.fixture(scope="module")
def patch_rays(dataset):
    """[8, 10] rays of the first test view, crossing the scene's objects and the background."""
    return dataset.rays(dataset.test_indices[0])[20:28, 27:37]


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    """Each baseline trained 3 steps through the Trainer: {method: (run_dir, model)}."""
    out = {}
    for method in BASELINES:
        run_dir = tmp_path_factory.mktemp(method)
        model = Trainer(tiny_config(method), run_dir, dataset).train(progress=False)
        out[method] = (run_dir, model)
    return out


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------------ pipeline


def test_baselines_are_registered():
    assert set(BASELINES) <= set(METHODS)


@pytest.mark.parametrize("method", BASELINES)
def test_method_trains_and_renders_maps(method, trained, patch_rays, dataset):
    run_dir, model = trained[method]
    assert (run_dir / "checkpoint.pt").is_file()
    assert model.default_render_options().num_draws == EXPECTED_K[method]
    maps = model.render_view(patch_rays, model.render_options(keep_draws=True), generator=_gen(0))
    H, W = patch_rays.shape
    K = EXPECTED_K[method]
    expected = {name: (H, W, 3) if name.startswith("colour") else (H, W) for name in MAP_NAMES}
    expected.update(z_scale=(H, W), num_draws=(H, W), depth_draws=(H, W, K), colour_draws=(H, W, K, 3))
    if method != "nerfw":
        expected["field_evals_per_ray"] = (H, W)
    assert {k: tuple(v.shape) for k, v in maps.items()} == expected
    assert (maps["num_draws"] == K).all()  # the K each pixel got, as reports state it
    for name, value in maps.items():
        assert torch.isfinite(value).all(), name
    for name in ("colour_var", "depth_var_epistemic", "depth_var_spread", "depth_var_total"):
        assert (maps[name] >= 0).all(), name
    # the moments are those of the kept draws (population variance over K), computed with numpy
    draws = maps["colour_draws"].double().numpy()
    assert np.allclose(maps["colour_mean"].numpy(), draws.mean(axis=2), atol=1e-6)
    if method != "nerfw":  # NeRF-W's variance is its rendered channel, not a spread of draws
        assert np.allclose(maps["colour_var"].numpy(), draws.var(axis=2), atol=1e-7)
    depth = maps["depth_draws"].double().numpy()
    assert np.allclose(maps["depth_var_epistemic"].numpy(), depth.var(axis=2), rtol=1e-4, atol=1e-6)
    assert torch.allclose(maps["depth_var_total"], maps["depth_var_epistemic"] + maps["depth_var_spread"])


@pytest.mark.parametrize("method", BASELINES)
def test_checkpoint_round_trip_renders_identically(method, trained, patch_rays, dataset):
    run_dir, model = trained[method]
    _, loaded, _ = load_trained_model(run_dir, dataset=dataset, device="cpu")
    assert type(loaded) is type(model)
    a = model.render_view(patch_rays, generator=_gen(3))
    b = loaded.render_view(patch_rays, generator=_gen(3))
    for name in MAP_NAMES:
        assert torch.equal(a[name], b[name]), name


def test_training_changes_parameters(dataset, tmp_path):
    """3 optimiser steps move the density cells of a deterministic grid (relu is alive)."""
    cfg = tiny_config("deterministic")
    torch.manual_seed(cfg.train.seed)
    fresh = build_model(cfg, dataset)
    trainer = Trainer(cfg, tmp_path, dataset)
    model = trainer.train(progress=False)
    before = fresh.field.levels[0][:, 0]
    after = model.field.levels[0][:, 0]
    assert not torch.equal(before, after)


# ------------------------------------------------------------------------------ deterministic


def test_deterministic_has_zero_variance_and_undefined_correlation(trained, dataset):
    _, model = trained["deterministic"]
    v = dataset.test_indices[0]
    maps = model.render_view(dataset.rays(v), generator=_gen())
    assert torch.count_nonzero(maps["colour_var"]) == 0
    assert torch.count_nonzero(maps["depth_var_epistemic"]) == 0
    products = camera_z_maps(maps)
    gt = dataset.images[v].numpy()
    corr = M.mse_uncertainty_correlation(gt, products["colour_mean"], products["colour_std"] ** 2)
    assert not corr["pearson"].defined and not corr["spearman"].defined
    assert "constant uncertainty" in corr["pearson"].reason
    scores = score_view(products, gt, None)
    assert not scores["pearson_mse_var"].defined and math.isnan(scores["pearson_mse_var"].value)
    assert not scores["spearman_mse_var"].defined
    # NLL at the documented floor, against scipy
    mean = products["colour_mean"].astype(np.float64)
    ref = -scipy.stats.norm.logpdf(gt.astype(np.float64), loc=mean, scale=math.sqrt(NLL_VARIANCE_FLOOR)).mean()
    assert scores["nll"] == pytest.approx(ref, rel=1e-9)


def test_deterministic_loss_is_scaled_mse(dataset):
    """Gaussian likelihood with sigma_n: 0.5 |c - C|^2 / sigma^2 + 3 log sigma + 1.5 log 2 pi."""
    cfg = tiny_config("deterministic")
    cfg.train.tv_weight = 0.0
    model = build_model(cfg, dataset)
    rays = dataset.rays(dataset.train_indices[0])[::8, ::8].flatten()
    target = dataset.images[dataset.train_indices[0]][::8, ::8].reshape(-1, 3)
    loss, logs = model.training_loss(rays, target, step=0, generator=_gen(1))
    out = B.render_mean_field(model.field, rays, model.render_settings, stratified=True, generator=_gen(1))
    sigma = cfg.loss.likelihood_std
    sq = ((out.stats.colour_mean.double() - target.double()) ** 2).sum(-1)
    ref = (0.5 * sq / sigma ** 2 + 3 * math.log(sigma) + 1.5 * math.log(2 * math.pi)).mean().detach()
    assert logs["nll"] == pytest.approx(float(ref), rel=1e-5)
    assert float(loss.detach()) == pytest.approx(float(ref), rel=1e-5)


def test_deterministic_grid_starts_at_snerf_mean_density(dataset):
    cfg = tiny_config("deterministic")
    assert cfg.field.grid_init_density_loc < 0  # S-NeRF's default: a dead ReLU for eps = 0
    model = build_model(cfg, dataset)
    mu0, s0 = cfg.field.grid_init_density_loc, cfg.field.init_std
    expected = scipy.integrate.quad(lambda x: max(x, 0.0) * scipy.stats.norm.pdf(x, mu0, s0), -20, 20)[0]
    assert B.mean_relu(mu0, s0) == pytest.approx(expected, rel=1e-9)
    assert float(model.field.offset[0]) == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("loc,scale", [(-1.0, 1.0), (0.0, 1.0), (2.5, 0.3), (-6.0, 1.0)])
def test_mean_relu_against_quadrature(loc, scale):
    ref = scipy.integrate.quad(lambda x: x * scipy.stats.norm.pdf(x, loc, scale), 0, loc + 30 * scale)[0]
    assert B.mean_relu(loc, scale) == pytest.approx(ref, rel=1e-8, abs=1e-15)


# ------------------------------------------------------------------------------- MC-Dropout


def test_seeded_dropout_statistics_and_reproducibility():
    layer = B.SeededDropout(0.2)
    x = torch.ones(200_000)
    layer.eval()
    assert torch.equal(layer(x), x)
    layer.train()
    layer.generator = _gen(5)
    y = layer(x)
    dropped = float((y == 0).double().mean())
    # binomial(n, 0.2): 5 standard deviations
    assert abs(dropped - 0.2) < 5 * math.sqrt(0.2 * 0.8 / x.numel())
    assert torch.allclose(y[y != 0], torch.full_like(y[y != 0], 1 / 0.8))
    layer.generator = _gen(5)
    assert torch.equal(layer(x), y)
    with pytest.raises(ValueError, match="dropout rate"):
        B.SeededDropout(1.0)


def test_grid_dropout_field_equals_grid_when_dropout_is_off(dataset):
    cfg = tiny_config("mc_dropout")
    model = build_model(cfg, dataset)
    wrapper = model.field
    assert isinstance(wrapper, B.GridDropoutField)
    wrapper.eval()
    pts = torch.rand(50, 3, generator=_gen(2)) * 2 - 1
    pts = wrapper.grid.region.from_unit(pts * 0.9)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=_gen(3)), dim=-1)
    a, b = wrapper(pts, dirs), wrapper.grid(pts, dirs)
    for name in ("density_loc", "density_scale", "rgb_loc", "rgb_scale"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    with B.dropout_control(wrapper, _gen(4), always_on=True):
        c = wrapper(pts, dirs)
    assert not torch.equal(c.rgb_loc, b.rgb_loc)


@pytest.mark.parametrize("backend", ["grid", "mlp"])
def test_mc_dropout_passes_differ_and_are_seeded(backend, dataset, patch_rays):
    cfg = tiny_config("mc_dropout", backend)
    model = build_model(cfg, dataset).eval()
    drops = [m for m in model.modules() if isinstance(m, B.SeededDropout)]
    assert drops and all(m.p == B.DEFAULT_DROPOUT_RATE for m in drops)
    maps = model.render_view(patch_rays, model.render_options(keep_draws=True), generator=_gen(0))
    draws = maps["colour_draws"]  # [H, W, P, 3]
    assert draws.shape[2] == B.DEFAULT_MC_DROPOUT_PASSES
    assert not torch.equal(draws[:, :, 0], draws[:, :, 1])
    assert float(maps["colour_var"].max()) > 0
    again = model.render_view(patch_rays, generator=_gen(0))
    other = model.render_view(patch_rays, generator=_gen(1))
    assert torch.equal(maps["colour_var"], again["colour_var"])
    assert not torch.equal(maps["colour_var"], other["colour_var"])
    # rendering leaves the model in eval mode with dropout off: the field is deterministic again
    assert all(not m.always_on for m in drops)
    three = model.render_view(patch_rays, model.render_options(num_draws=3, keep_draws=True), generator=_gen(0))
    assert three["colour_draws"].shape[2] == 3


def test_mc_dropout_respects_configured_rate(dataset):
    cfg = tiny_config("mc_dropout", "mlp")
    cfg.field.dropout = 0.35
    model = build_model(cfg, dataset)
    assert {m.p for m in model.modules() if isinstance(m, B.SeededDropout)} == {0.35}
    assert not any(isinstance(m, torch.nn.Dropout) for m in model.modules())


# --------------------------------------------------------------------------------- ensemble


def test_ensemble_members_differ(trained, patch_rays):
    _, model = trained["ensemble"]
    assert len(model.members) == B.DEFAULT_ENSEMBLE_SIZE
    d0 = model.members[0].levels[0][:, 0]
    assert all(not torch.equal(d0, m.levels[0][:, 0]) for m in model.members[1:])
    maps = model.render_view(patch_rays, model.render_options(keep_draws=True))
    draws = maps["colour_draws"]
    for j in range(1, B.DEFAULT_ENSEMBLE_SIZE):
        assert not torch.allclose(draws[:, :, 0], draws[:, :, j])
    # variance across members equals the variance of each member rendered on its own
    solo = torch.stack([B.render_mean_field(f, patch_rays.flatten(), model.render_settings).stats.colour_mean
                        for f in model.members], dim=1).double()  # [R, M, 3]
    ref = solo.var(dim=1, unbiased=False).reshape(maps["colour_var"].shape)
    assert torch.allclose(maps["colour_var"].double(), ref, atol=1e-7)


def test_ensemble_loss_is_sum_of_member_losses(dataset):
    cfg = tiny_config("ensemble")
    cfg.train.tv_weight = 0.0
    model = build_model(cfg, dataset)
    rays = dataset.rays(dataset.train_indices[0])[::6, ::6].flatten()
    target = dataset.images[dataset.train_indices[0]][::6, ::6].reshape(-1, 3)
    loss, _ = model.training_loss(rays, target, step=0, generator=_gen(7))
    g = _gen(7)  # the members consume the generator in order
    ref = sum(gaussian_likelihood_nll(B.render_mean_field(f, rays, model.render_settings, stratified=True,
                                                          generator=g).stats.colour_draws, target,
                                      cfg.loss.likelihood_std) for f in model.members)
    assert float(loss.detach()) == pytest.approx(float(ref.detach()), rel=1e-6)


# ----------------------------------------------------------------------------------- NeRF-W


def test_nerfw_variance_channel_against_float64_loop(trained, patch_rays):
    _, model = trained["nerfw"]
    rays = patch_rays.flatten()
    maps = model.render_view(patch_rays)
    var = maps["colour_var"].reshape(-1, 3)
    assert (var >= NERFW_BETA_MIN ** 2 * (1 - 1e-6)).all()  # beta > 0: never below beta_min^2
    with torch.no_grad():
        out = render_rays(model.field, rays, model.render_settings, num_draws=1, deterministic=True)
    w = out.extras["weights"][:, 0].double()  # [R, S]
    beta = (out.params.rgb_scale.double() - FIELD_STD_FLOOR)  # softplus(raw) [R, S, 3]
    ref = torch.empty(len(rays), 3, dtype=torch.float64)
    for r in range(len(rays)):
        for c in range(3):
            ref[r, c] = sum(float(w[r, i]) * float(beta[r, i, c]) ** 2 for i in range(w.shape[1])) + NERFW_BETA_MIN ** 2
    assert torch.allclose(var.double(), ref, rtol=1e-5, atol=1e-9)


def test_nerfw_loss_is_gaussian_nll(dataset):
    cfg = tiny_config("nerfw")
    cfg.train.tv_weight = 0.0
    model = build_model(cfg, dataset)
    rays = dataset.rays(dataset.train_indices[0])[::6, ::6].flatten()
    target = dataset.images[dataset.train_indices[0]][::6, ::6].reshape(-1, 3)
    loss, logs = model.training_loss(rays, target, step=0, generator=_gen(8))
    out, var = model._render(rays, stratified=True, generator=_gen(8))
    stats = out.stats
    ref = -torch.distributions.Normal(stats.colour_mean.double(), var.double().sqrt()).log_prob(target.double())
    assert float(loss.detach()) == pytest.approx(float(ref.sum(-1).mean().detach()), rel=1e-5)
    assert logs["beta_rms"] > NERFW_BETA_MIN


def test_nerfw_nll_gradcheck():
    g = _gen(11)
    colour = torch.rand(4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(4, 3, generator=g, dtype=torch.float64)
    var = (0.01 + torch.rand(4, 3, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda c, v: B.gaussian_nll_learned_variance(c, target, v), (colour, var))


def test_region_is_shared_by_all_methods(dataset):
    """Same backbone: every method models the same region with the same grid resolution."""
    region = fit_scene_region(dataset, tiny_config("snerf"))
    resolutions = set()
    for method in ("snerf",) + BASELINES:
        model = METHODS[method](tiny_config(method), dataset, region)
        resolutions |= {g.resolution for g in model.modules() if isinstance(g, GridField)}
    assert len(resolutions) == 1
