"""The per-point observation noise (``loss.per_point_noise``, docs/definitions.md §4.7): the
likelihood with a per-draw variance against scipy, the rendered noise variance against a float64
loop and a Monte-Carlo estimate, dense against packed, gradients, the field heads, and a model
that trains and renders with it."""

from __future__ import annotations

import dataclasses
import math

import pytest
import scipy.stats
import torch
import torch.nn.functional as F

from stochastic_fields.data import load_dataset
from stochastic_fields.fields.base import FieldParams, inverse_softplus
from stochastic_fields.fields.grid import GridField
from stochastic_fields.fields.mlp import MLPField
from stochastic_fields.losses import gaussian_likelihood_nll
from stochastic_fields.models.registry import build_model
from stochastic_fields.scene_region import SceneRegion
from stochastic_fields.trainer import Trainer
from stochastic_fields.volume_rendering import trajectory_statistics, trajectory_statistics_packed


def _tiny_config(per_point_noise: bool = True):
    """The likelihood-noise tests' tiny S-NeRF, with or without the noise head."""
    from test_likelihood_noise import _tiny_snerf_config

    cfg = _tiny_snerf_config()
    cfg.loss.per_point_noise = per_point_noise
    return cfg


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    return load_dataset(tiny_scene)


def _weights(R: int, K: int, S: int, generator: torch.Generator) -> torch.Tensor:
    """Valid weights [R, K, S]: positive, each draw's sum below 1 (some rays nearly empty)."""
    w = torch.rand(R, K, S, generator=generator, dtype=torch.float64)
    return w / w.sum(-1, keepdim=True) * torch.rand(R, K, 1, generator=generator, dtype=torch.float64)


def _draws(R: int, K: int, S: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Generator]:
    """float64 weights [R, K, S], colours [R, K, S, 3], sample distances [R, S] and the generator."""
    g = torch.Generator().manual_seed(seed)
    w = _weights(R, K, S, g)
    rgb = torch.rand(R, K, S, 3, generator=g, dtype=torch.float64)
    t = torch.linspace(1.0, 4.0, S, dtype=torch.float64).expand(R, S).contiguous()
    return w, rgb, t, g


def test_likelihood_with_per_draw_variance_against_scipy():
    g = torch.Generator().manual_seed(0)
    colours = torch.rand(5, 4, 3, generator=g, dtype=torch.float64)
    target = torch.rand(5, 3, generator=g, dtype=torch.float64)
    std = torch.tensor([0.02, 0.1, 0.5], dtype=torch.float64)
    extra = torch.rand(5, 4, 3, generator=g, dtype=torch.float64) ** 4  # tiny to ~1
    ref = -scipy.stats.norm.logpdf(target.numpy()[:, None, :], colours.numpy(),
                                   (std ** 2 + extra).sqrt().numpy()).sum(-1).mean()
    assert float(gaussian_likelihood_nll(colours, target, std, extra)) == pytest.approx(ref, rel=1e-12)
    # no extra variance is the same as zeros
    assert float(gaussian_likelihood_nll(colours, target, std, torch.zeros_like(extra))) == pytest.approx(
        float(gaussian_likelihood_nll(colours, target, std)), rel=1e-12)


def test_likelihood_stays_finite_for_huge_noise_and_prefers_it_only_for_large_residuals():
    colours = torch.zeros(2, 1, 3, dtype=torch.float64)
    target = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=torch.float64)
    huge = torch.full((2, 1, 3), 1e6, dtype=torch.float64)
    assert math.isfinite(float(gaussian_likelihood_nll(colours, target, 0.05, huge)))
    # exact fit: extra noise only costs; residual 1: noise of about the residual beats none
    fit, miss = (gaussian_likelihood_nll(colours[i:i + 1], target[i:i + 1], 0.05, e[i:i + 1])
                 for i, e in ((0, torch.full((2, 1, 3), 0.5, dtype=torch.float64)),
                              (1, torch.full((2, 1, 3), 0.5, dtype=torch.float64))))
    assert float(fit) > float(gaussian_likelihood_nll(colours[:1], target[:1], 0.05))
    assert float(miss) < float(gaussian_likelihood_nll(colours[1:], target[1:], 0.05))


def test_rendered_noise_variance_against_a_float64_loop():
    R, K, S = 6, 5, 7
    w, rgb, t, g = _draws(R, K, S, 1)
    beta2 = torch.rand(R, S, generator=g, dtype=torch.float64) ** 2
    stats = trajectory_statistics(w, rgb, t, 5.0, observation_var=beta2)
    plain = trajectory_statistics(w, rgb, t, 5.0)
    for r in range(R):
        v = [sum(float(w[r, k, i]) * float(beta2[r, i]) for i in range(S)) for k in range(K)]
        for k in range(K):
            assert float(stats.colour_noise_var_draws[r, k, 0]) == pytest.approx(v[k], rel=1e-12)
        for c in range(3):
            draws = [float(plain.colour_draws[r, k, c]) for k in range(K)]
            mean = sum(draws) / K
            between = sum((d - mean) ** 2 for d in draws) / K
            assert float(stats.colour_var[r, c]) == pytest.approx(between + sum(v) / K, rel=1e-12)
    torch.testing.assert_close(stats.colour_mean, plain.colour_mean)  # the noise moves no mean


def test_rendered_noise_variance_matches_monte_carlo_pixels():
    """Pixels drawn as C_k + N(0, v_k) with k uniform have the rendered colour variance."""
    R, K, S = 3, 4, 6
    w, rgb, t, g = _draws(R, K, S, 2)
    beta2 = 0.05 * torch.rand(R, S, generator=g, dtype=torch.float64)
    stats = trajectory_statistics(w, rgb, t, 5.0, observation_var=beta2)
    n = 400_000
    k = torch.randint(0, K, (n,), generator=g)
    mean = stats.colour_draws[:, k]  # [R, n, 3]
    pixels = mean + stats.colour_noise_var_draws[:, k].sqrt() * torch.randn(R, n, 3, generator=g, dtype=torch.float64)
    mc_var = pixels.var(dim=1)
    torch.testing.assert_close(mc_var, stats.colour_var, rtol=0.02, atol=1e-5)


def test_packed_noise_variance_equals_dense():
    R, K, S = 4, 3, 5
    w, rgb, t, g = _draws(R, K, S, 3)
    beta2 = torch.rand(R, S, generator=g, dtype=torch.float64)
    dense = trajectory_statistics(w, rgb, t, 5.0, observation_var=beta2)
    ray_indices = torch.arange(R).repeat_interleave(S)
    packed = trajectory_statistics_packed(w.permute(1, 0, 2).reshape(K, R * S), rgb.permute(1, 0, 2, 3).reshape(K, R * S, 3),
                                          t.reshape(-1), ray_indices, R, 5.0, observation_var=beta2.reshape(-1))
    torch.testing.assert_close(packed.colour_noise_var_draws, dense.colour_noise_var_draws)
    torch.testing.assert_close(packed.colour_var, dense.colour_var)


def test_gradients_of_the_likelihood_through_the_noise_head_gradcheck():
    R, K, S = 3, 2, 4
    w, rgb, t, g = _draws(R, K, S, 4)
    target = torch.rand(R, 3, generator=g, dtype=torch.float64)
    raw = torch.randn(R, S, generator=g, dtype=torch.float64, requires_grad=True)
    log_std = torch.tensor([-3.0, -2.5, -2.0], dtype=torch.float64, requires_grad=True)

    def nll(raw_beta, log_sigma):
        stats = trajectory_statistics(w, rgb, t, 5.0, observation_var=F.softplus(raw_beta) ** 2)
        return gaussian_likelihood_nll(stats.colour_draws, target, log_sigma.exp(), stats.colour_noise_var_draws)

    assert torch.autograd.gradcheck(nll, (raw, log_std))


def test_field_params_with_and_without_noise_scale():
    base = FieldParams(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(2, 3, 3), torch.ones(2, 3, 3))
    assert base.map(lambda x: x[:1]).noise_scale is None
    assert base.reshape(6).density_loc.shape == (6,)
    noisy = FieldParams(base.density_loc, base.density_scale, base.rgb_loc, base.rgb_scale, torch.full((2, 3), 0.1))
    assert noisy.reshape(6).noise_scale.shape == (6,)
    assert FieldParams.cat([noisy, noisy]).noise_scale.shape == (4, 3)
    with pytest.raises(ValueError, match="noise_scale"):
        FieldParams.cat([base, noisy])


@pytest.mark.parametrize("make", [
    lambda region, head: GridField(region, (8, 8, 8), num_levels=2, noise_head=head),
    lambda region, head: GridField(region, (8, 8, 8), num_levels=2, decoder_width=0, noise_head=head),
    lambda region, head: MLPField(region, depth=2, width=16, head_width=8, noise_head=head),
])
def test_field_noise_heads_start_small_and_leave_the_other_outputs_alone(make):
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    torch.manual_seed(0)
    plain = make(region, False)
    torch.manual_seed(0)
    noisy = make(region, True)
    x = torch.rand(10, 3) * 1.6 - 0.8
    d = F.normalize(torch.randn(10, 3), dim=-1)
    assert plain(x, d).noise_scale is None
    out = noisy(x, d)
    assert out.noise_scale.shape == (10,) and bool((out.noise_scale > 0).all())
    from stochastic_fields.constants import NOISE_HEAD_INIT_STD

    if isinstance(noisy, GridField):  # grid: the value is the offset until trained
        torch.testing.assert_close(out.noise_scale, torch.full((10,), NOISE_HEAD_INIT_STD))
        with torch.no_grad():
            for level_plain, level_noisy in zip(plain.levels, noisy.levels):
                level_noisy[:, :-1].copy_(level_plain)
        ref = plain(x, d)
        for name in ("density_loc", "density_scale", "rgb_loc", "rgb_scale"):
            torch.testing.assert_close(getattr(noisy(x, d), name), getattr(ref, name))


def test_model_uses_the_head_only_when_its_field_has_one(dataset):
    from stochastic_fields.models.field_builder import build_field, fit_scene_region
    from stochastic_fields.models.snerf import SNeRF

    cfg = _tiny_config(per_point_noise=True)
    region = fit_scene_region(dataset, cfg)
    assert not SNeRF(build_field(cfg, region, dataset), region, cfg.render, cfg.loss).noise_head
    assert SNeRF(build_field(cfg, region, dataset, noise_head=True), region, cfg.render, cfg.loss).noise_head
    assert build_model(cfg, dataset).noise_head and not build_model(_tiny_config(False), dataset).noise_head


def test_noise_head_trains_and_its_variance_enters_the_predictive_colour_variance(dataset, tmp_path):
    cfg = _tiny_config(per_point_noise=True)
    cfg.train.iterations = 10  # the log is written every 10 steps
    start = [level.detach()[:, -1].clone() for level in build_model(cfg, dataset).field.levels]
    model = Trainer(cfg, tmp_path, dataset).train(progress=False)
    moved = [float((level.detach()[:, -1] - s).abs().max()) for level, s in zip(model.field.levels, start)]
    assert max(moved) > 0, "the noise channel gets gradient and is optimised"
    logs = [line for line in (tmp_path / "train_log.jsonl").read_text().splitlines() if "noise_head_rms" in line]
    assert logs, "training logs the rendered noise std"
    # a constant beta = b: the predictive colour variance is the epistemic one + sigma_n^2 + b^2 mean_k A_k
    b = 0.2
    with torch.no_grad():
        for level in model.field.levels:
            level[:, -1] = 0.0
        model.field.offset[-1] = inverse_softplus(b)
    model.eval()
    rays = dataset.rays(dataset.test_indices[0])[8:12, 8:14]
    predictive = model.render_view(rays, model.render_options(num_draws=6), generator=torch.Generator().manual_seed(5))
    epistemic_model = build_model(_with(cfg, "render.colour_variance", "epistemic"), dataset).eval()
    epistemic_model.load_state_dict(model.state_dict())
    epistemic = epistemic_model.render_view(rays, epistemic_model.render_options(num_draws=6),
                                            generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(predictive["colour_mean"], epistemic["colour_mean"])
    sigma2 = model.likelihood_std().detach() ** 2
    expected = epistemic["colour_var"] + sigma2 + (b ** 2 * predictive["opacity"])[..., None]
    torch.testing.assert_close(predictive["colour_var"], expected, rtol=1e-5, atol=1e-7)


def test_noise_head_run_resumes_from_its_checkpoint(dataset, tmp_path):
    from stochastic_fields.trainer import load_trained_model

    cfg = _tiny_config(per_point_noise=True)
    cfg.train.checkpoint_every = 3
    model = Trainer(cfg, tmp_path, dataset).train(progress=False)
    loaded = load_trained_model(tmp_path, dataset=dataset, device="cpu")[1]
    rays = dataset.rays(dataset.test_indices[0])[:4, :4]
    a = model.eval().render_view(rays, model.render_options(num_draws=4), generator=torch.Generator().manual_seed(0))
    b = loaded.eval().render_view(rays, loaded.render_options(num_draws=4), generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(a["colour_var"], b["colour_var"])


def _with(cfg, key: str, value):
    import copy

    from stochastic_fields.config import set_dotted

    out = copy.deepcopy(cfg)
    set_dotted(out, key, value)
    return out


def test_decoupled_likelihood_keeps_the_global_noise_gradient_on_colours():
    from stochastic_fields.losses import decoupled_likelihood_nll

    g = torch.Generator().manual_seed(6)
    colours = torch.rand(4, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(4, 3, generator=g, dtype=torch.float64)
    std = torch.tensor([0.05, 0.1, 0.2], dtype=torch.float64)
    extra = (torch.rand(4, 3, 3, generator=g, dtype=torch.float64) * 0.3).requires_grad_(True)
    decoupled = decoupled_likelihood_nll(colours, target, std, extra)
    (grad_c,) = torch.autograd.grad(decoupled, colours, retain_graph=True)
    plain = gaussian_likelihood_nll(colours, target, std)
    (ref_c,) = torch.autograd.grad(plain, colours)
    torch.testing.assert_close(grad_c, ref_c)  # (C - c) / sigma^2 / (R K), whatever the extra noise
    # the value: each term scaled by v / sigma^2
    var = std ** 2 + extra.detach()
    terms = 0.5 * (colours.detach() - target[:, None]) ** 2 / var + 0.5 * torch.log(2 * math.pi * var)
    assert float(decoupled.detach()) == pytest.approx(float((var / std ** 2 * terms).sum(-1).mean()), rel=1e-12)
    # the noise is stationary where v = residual^2, as with the plain likelihood
    resid2 = (colours.detach() - target[:, None]) ** 2
    at_residual = (resid2 - std ** 2).clamp_min(0.0).requires_grad_(True)  # v = max(r^2, sigma^2)
    (grad_v,) = torch.autograd.grad(decoupled_likelihood_nll(colours.detach(), target, std, at_residual), at_residual)
    fitted = resid2 > std ** 2
    assert float(grad_v[fitted].abs().max()) < 1e-12


def test_observation_noise_per_draw_dense_packed_and_rendered_agree(dataset):
    from stochastic_fields.renderer import observation_noise_per_draw, render_rays

    cfg = _tiny_config(per_point_noise=True)
    model = build_model(cfg, dataset).eval()
    with torch.no_grad():
        for level in model.field.levels:
            level[:, -1].uniform_(-1.0, 1.0, generator=torch.Generator().manual_seed(7))
    rays = dataset.rays(dataset.train_indices[0])[22:26, 30:34].flatten()  # the image centre: the solids
    # colours by draws: the pixel's variance given its trajectory is then the observation noise alone
    # (the Rao-Blackwellised estimator adds sum_i w_ik^2 Var[r_i] to it)
    by_draws = dataclasses.replace(model.render_settings, colour_estimator="draws")
    with torch.no_grad():
        dense = render_rays(model.field, rays, by_draws, num_draws=4, generator=torch.Generator().manual_seed(8))
        acc = dense.extras["weights"].sum(-1)  # [R, K]: most trajectories hold mass, so v is not trivially 0
        assert float((acc > 0.05).float().mean()) > 0.5
        v = observation_noise_per_draw(dense)
        torch.testing.assert_close(v, dense.stats.colour_noise_var_draws)  # predictive render composites it
        from stochastic_fields.renderer import pack_samples, render_samples_packed

        packed_samples = pack_samples(dense.samples, torch.ones(dense.samples.t_starts.shape, dtype=torch.bool))
        packed = render_samples_packed(dense.params.reshape(-1), packed_samples, model.render_settings, num_draws=4,
                                       noise=(torch.randn(4, packed_samples.ray_indices.numel(),
                                                          generator=torch.Generator().manual_seed(9)),
                                              torch.randn(4, packed_samples.ray_indices.numel(), 3,
                                                          generator=torch.Generator().manual_seed(10))))
        w = packed.extras["weights"]  # [K, N]
        beta2 = dense.params.noise_scale.reshape(-1) ** 2
        ref = torch.stack([torch.stack([(w[k, packed_samples.ray_indices == r] * beta2[packed_samples.ray_indices == r]).sum()
                                        for k in range(4)]) for r in range(len(rays))])
        torch.testing.assert_close(observation_noise_per_draw(packed)[..., 0], ref)


def test_runs_saved_before_the_head_load_without_it_and_keep_their_fingerprints():
    from stochastic_fields.config import ExperimentConfig, flatten, from_dict, saved_config, to_dict
    from stochastic_fields_bench.runner import semantic_options

    old = to_dict(ExperimentConfig())
    del old["loss"]["per_point_noise"], old["loss"]["noise_head_decoupled"]
    assert from_dict(ExperimentConfig, old).loss.per_point_noise  # a partial user config takes the default
    loaded = saved_config(old)  # a saved run lacking the keys was trained without the head
    assert not loaded.loss.per_point_noise and not loaded.loss.noise_head_decoupled
    assert "loss.per_point_noise" not in semantic_options(flatten(to_dict(loaded)))  # unchanged fingerprint
    assert semantic_options(flatten(to_dict(ExperimentConfig())))["loss.per_point_noise"] is True  # new default counts
    baseline = to_dict(ExperimentConfig(method="ensemble"))
    assert not any(k.startswith("loss.per_point") or k.startswith("loss.noise_head")
                   for k in semantic_options(flatten(baseline)))  # the baselines build no head
