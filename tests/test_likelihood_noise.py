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
