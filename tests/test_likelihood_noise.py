"""S-NeRF's likelihood noise sigma_n: the Gaussian pixel likelihood against scipy, learning
sigma_n, and the predictive colour variance (epistemic + sigma_n^2)."""

from __future__ import annotations


import pytest
import scipy.stats
import torch

from stochastic_fields.config import preset
from stochastic_fields.data import load_dataset
from stochastic_fields.losses import gaussian_likelihood_nll
from stochastic_fields.models.registry import build_model
from stochastic_fields.trainer import Trainer


def _tiny_snerf_config():
    cfg = preset("tiny")
    cfg.train.iterations = 3
    cfg.train.rays_per_batch = 64
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    cfg.render.num_samples = 16
    cfg.field.grid_max_cells = 16 ** 3
    cfg.field.grid_levels = 2
    return cfg


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    return load_dataset(tiny_scene)


def test_gaussian_likelihood_nll_per_channel_std_against_scipy():
    g = torch.Generator().manual_seed(0)
    colours = torch.rand(5, 4, 3, generator=g, dtype=torch.float64)
    target = torch.rand(5, 3, generator=g, dtype=torch.float64)
    std = torch.tensor([0.02, 0.1, 0.5], dtype=torch.float64)
    ref = -scipy.stats.norm.logpdf(target.numpy()[:, None, :], colours.numpy(), std.numpy()).sum(-1).mean()
    assert float(gaussian_likelihood_nll(colours, target, std)) == pytest.approx(ref, rel=1e-12)
    # a float std is the same as that std in every channel
    ref1 = -scipy.stats.norm.logpdf(target.numpy()[:, None, :], colours.numpy(), 0.05).sum(-1).mean()
    assert float(gaussian_likelihood_nll(colours, target, 0.05)) == pytest.approx(ref1, rel=1e-12)


def test_learned_noise_gets_gradient_and_moves_towards_the_residual(dataset, tmp_path):
    cfg = _tiny_snerf_config()
    cfg.loss.learn_likelihood_std = True
    cfg.loss.likelihood_std = 0.01  # far below the residual of an untrained field
    trainer = Trainer(cfg, tmp_path, dataset)
    start = trainer.model.likelihood_std().detach().clone()
    torch.testing.assert_close(start, torch.full((3,), 0.01))
    model = trainer.train(progress=False)
    assert (model.likelihood_std().detach() > start).all()  # d NLL / d log sigma < 0 while residual > sigma


def test_predictive_colour_variance_adds_sigma_n_squared(dataset):
    cfg = _tiny_snerf_config()
    cfg.loss.learn_likelihood_std = True
    cfg.loss.per_point_noise = False  # the head's part: tests/test_noise_head.py
    cfg.render.colour_variance = "epistemic"
    model = build_model(cfg, dataset).eval()
    with torch.no_grad():
        model.log_likelihood_std.copy_(torch.log(torch.tensor([0.1, 0.2, 0.3])))
    rays = dataset.rays(dataset.test_indices[0])[10:14, 10:15]
    epistemic = model.render_view(rays, model.render_options(num_draws=8), generator=torch.Generator().manual_seed(3))
    cfg.render.colour_variance = "predictive"
    same = build_model(cfg, dataset).eval()
    same.load_state_dict(model.state_dict())
    predictive = same.render_view(rays, same.render_options(num_draws=8), generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(predictive["colour_mean"], epistemic["colour_mean"])
    torch.testing.assert_close(predictive["colour_var"] - epistemic["colour_var"],
                               torch.tensor([0.01, 0.04, 0.09]).expand_as(epistemic["colour_var"]))


def test_bad_colour_variance_setting_is_rejected(dataset):
    cfg = _tiny_snerf_config()
    cfg.render.colour_variance = "aleatoric"
    with pytest.raises(ValueError, match="colour_variance.*aleatoric"):
        build_model(cfg, dataset)


def test_rebuild_occupancy_skips_more_with_a_looser_criterion(dataset, tmp_path):
    cfg = _tiny_snerf_config()
    cfg.render.skip_empty_space = True
    cfg.train.iterations = 20
    model = Trainer(cfg, tmp_path, dataset).train(progress=False)
    fractions = [model.rebuild_occupancy(num_std=num_std, alpha_threshold=alpha)
                 for num_std, alpha in ((3.0, 1e-4), (1.0, 1e-2), (-3.0, 0.5))]
    assert fractions[0] >= fractions[1] >= fractions[2]
    # relu(mu - 3 s) * delta with opacity above 0.5: a 20-step field is nowhere that sure
    assert fractions[2] == 0.0
    assert model.rebuild_occupancy(num_std=1e3, alpha_threshold=1e-4) == 1.0  # everything uncertain enough


@pytest.mark.parametrize("decoupled", [False, True])
def test_rao_blackwell_likelihood_is_the_colour_draws_expectation(decoupled):
    """With fixed density draws, the Rao-Blackwellised pixel NLL (each draw's colour mean and
    sum_i w_ik^2 Var[r_i] from the renderer) equals the mean of the drawn-colour NLL over 20000
    colour draws (float64; within 4 Monte-Carlo standard errors), for the plain and the decoupled
    likelihood with a noise head's per-draw variance."""
    from stochastic_fields.fields.base import FieldParams
    from stochastic_fields.losses import decoupled_likelihood_nll
    from stochastic_fields.rays import RayBundle
    from stochastic_fields.renderer import RenderSettings, render_samples
    from stochastic_fields.samplers import sample_along_rays

    R, S, K, M = 3, 10, 2, 20000
    g = torch.Generator().manual_seed(0)
    rays = RayBundle(torch.zeros(R, 3, dtype=torch.float64),
                     torch.nn.functional.normalize(torch.randn(R, 3, generator=g, dtype=torch.float64), dim=-1),
                     torch.full((R,), 0.5, dtype=torch.float64), torch.full((R,), 4.0, dtype=torch.float64),
                     torch.ones(R, dtype=torch.float64))
    samples = sample_along_rays(rays, S)
    params = FieldParams(torch.randn(R, S, generator=g, dtype=torch.float64),
                         torch.rand(R, S, generator=g, dtype=torch.float64) + 0.1,
                         2.0 * torch.randn(R, S, 3, generator=g, dtype=torch.float64),
                         2.0 * torch.rand(R, S, 3, generator=g, dtype=torch.float64) + 0.05)
    st = RenderSettings(num_samples=S)
    target = torch.rand(R, 3, generator=g, dtype=torch.float64)
    std = torch.tensor([0.05, 0.1, 0.2], dtype=torch.float64)
    extra = torch.rand(R, K, 3, generator=g, dtype=torch.float64) * 0.01
    eps_a = torch.randn(R, K, S, generator=g, dtype=torch.float64)

    def nll(colours, colour_var=None):
        if decoupled:
            return decoupled_likelihood_nll(colours, target, std, extra, colour_var)
        return gaussian_likelihood_nll(colours, target, std, extra, colour_var)

    rb = render_samples(params, samples, st, num_draws=K, noise=(eps_a, torch.zeros(R, K, S, 3, dtype=torch.float64)),
                        colour_estimator="rao_blackwell", observation_noise=False)
    got = float(nll(rb.stats.colour_draws, rb.stats.colour_noise_var_draws))
    # the same density draws M times, each with its own colour draws: [R, M K, S]
    eps_c = torch.randn(R, M * K, S, 3, generator=g, dtype=torch.float64)
    drawn = render_samples(params, samples, st, num_draws=M * K, noise=(eps_a.repeat(1, M, 1), eps_c),
                           colour_estimator="draws", observation_noise=False)
    per_draw = torch.stack([nll(drawn.stats.colour_draws[:, m * K:(m + 1) * K]) for m in range(0, M, 1)])
    ref, se = float(per_draw.mean()), float(per_draw.std() / M ** 0.5)
    assert abs(got - ref) < 4 * se + 1e-4 * abs(ref)
    # the colour variance term is what the draws add: without it the NLL is too small
    assert float(nll(rb.stats.colour_draws)) < ref - 10 * se


def test_rao_blackwell_training_loss_reaches_the_colour_scales_and_trains(dataset, tmp_path):
    """With loss.likelihood_estimator='rao_blackwell' the likelihood alone (KL, depth and TV off)
    gives the colour scales a gradient (through sum_i w_ik^2 Var[r_i]: no colour is drawn), and
    training lowers the pixel error."""
    import json

    cfg = _tiny_snerf_config()
    cfg.loss.likelihood_estimator = "rao_blackwell"
    cfg.loss.kl = "none"
    cfg.loss.lambda_depth = 0.0
    cfg.train.tv_weight = 0.0
    model = build_model(cfg, dataset)
    g = torch.Generator().manual_seed(0)
    from stochastic_fields.trainer import TrainingRays

    rays, target = TrainingRays.from_dataset(dataset, torch.device("cpu")).batch(64, g)
    loss, _ = model.training_loss(rays, target, step=0, generator=g)
    loss.backward()
    scale_grad = model.field.decoder[-1].bias.grad[3:]
    assert torch.isfinite(loss) and torch.isfinite(scale_grad).all() and scale_grad.abs().min() > 0

    cfg.train.iterations = 30
    Trainer(cfg, tmp_path, dataset).train(progress=False)
    log = [json.loads(line) for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in log)
    assert log[-1]["mse"] < log[0]["mse"]
