"""The density heads' bootstrap of the training pixels (``loss.head_bootstrap_keep``)."""

from __future__ import annotations

import pytest
import torch

from stochastic_fields.losses import bootstrap_head_weights, draw_weights, gaussian_likelihood_nll


def test_bootstrap_weights_by_hand_and_in_the_mean():
    w = bootstrap_head_weights(400_000, 2, 0.5, torch.Generator().manual_seed(0))
    assert w.shape == (400_000, 2) and torch.all(w.sum(1) == 2)  # every pixel weighs what it weighs today
    both = (w == 1).all(1).float().mean()
    assert both == pytest.approx(0.25, abs=0.005)  # kept by both heads with chance 0.5^2
    # one head alone: 0.25 kept by it only + half of the 0.25 that no head kept
    assert (w[:, 0] == 2).float().mean() == pytest.approx(0.375, abs=0.005)
    assert w.mean(0) == pytest.approx(torch.ones(2), abs=0.01)  # each head's mean weight 1
    assert torch.equal(bootstrap_head_weights(5, 3, 1.0, torch.Generator()), torch.ones(5, 3))
    lone = bootstrap_head_weights(1000, 4, 1e-9, torch.Generator().manual_seed(1))  # no head keeps any pixel
    assert torch.all((lone == 4).sum(1) == 1) and torch.all((lone == 0).sum(1) == 3)


def test_draw_weights_follow_the_heads():
    head = torch.tensor([[2.0, 0.0], [1.0, 1.0]])
    assert torch.equal(draw_weights(head, 5), torch.tensor([[2.0, 0, 2, 0, 2], [1.0, 1, 1, 1, 1]]))


def test_likelihood_weighted_per_draw_by_hand():
    g = torch.Generator().manual_seed(0)
    colours, target = torch.rand(6, 4, 3, generator=g), torch.rand(6, 3, generator=g)
    w = torch.rand(6, 4, generator=g)
    per_draw = (0.5 * (colours - target[:, None]) ** 2 / 0.1 ** 2 + torch.log(torch.tensor(0.1))
                + 0.5 * torch.log(torch.tensor(2 * torch.pi))).sum(-1)  # [6, 4]
    got = gaussian_likelihood_nll(colours, target, 0.1, ray_weights=w)
    assert got == pytest.approx(float((per_draw * w).mean()), rel=1e-6)
    ones = gaussian_likelihood_nll(colours, target, 0.1, ray_weights=torch.ones(6, 4))
    assert ones == pytest.approx(float(gaussian_likelihood_nll(colours, target, 0.1)), rel=1e-6)


def _model_and_batch(tiny_scene, heads: int = 2):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.models.registry import build_model
    from test_baselines import tiny_config

    dataset = load_dataset(tiny_scene)
    cfg = tiny_config("snerf")
    cfg.field.density_heads = heads
    torch.manual_seed(0)
    model = build_model(cfg, dataset)
    view = dataset.train_indices[0]
    rays = dataset.rays(view)[::4, ::4].flatten()
    target = dataset.images[view][::4, ::4].reshape(-1, 3)
    return cfg, dataset, model, rays, target


def test_the_heads_likelihoods_split_linearly(tiny_scene):
    """With the same draws, giving every ray to head 0 and to head 1 in turn averages to giving it to both
    (the likelihood is linear in each draw's weight); all-ones weights are today's loss."""
    _, _, model, rays, target = _model_and_batch(tiny_scene)
    R = len(target)

    def nll(head_weights):
        _, logs = model.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(3),
                                      head_weights=head_weights)
        return logs["nll"]

    today = nll(None)
    assert nll(torch.ones(R, 2)) == pytest.approx(today, rel=1e-6)
    first, second = nll(torch.tensor([2.0, 0.0]).expand(R, 2)), nll(torch.tensor([0.0, 2.0]).expand(R, 2))
    assert (first + second) / 2 == pytest.approx(today, rel=1e-5)
    assert first != pytest.approx(second, rel=1e-6)  # the heads' draws differ


def test_trainer_bootstraps_the_heads_and_refuses_one_head(tiny_scene, tmp_path):
    from stochastic_fields.trainer import Trainer

    cfg, dataset, _, _, _ = _model_and_batch(tiny_scene)
    cfg.loss.head_bootstrap_keep = 0.5
    cfg.train.iterations = 3
    trainer = Trainer(cfg, tmp_path / "run", dataset)
    model = trainer.train(progress=False)
    table = trainer._head_table
    assert table is not None and table.shape[1] == 2 and torch.all(table.sum(1) == 2)
    again = Trainer(cfg, tmp_path / "again", dataset)
    again.train(progress=False)
    assert torch.equal(again._head_table, table)  # drawn from train.seed: the same after a restart
    maps = model.render_view(dataset.rays(dataset.test_indices[0]), generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(maps["depth_var_total"]).all()
    cfg.field.density_heads = 1
    with pytest.raises(ValueError, match="head_bootstrap_keep = 0.5 needs density heads"):
        Trainer(cfg, tmp_path / "one", dataset)
    with pytest.raises(ValueError, match="head_bootstrap_keep"):
        from stochastic_fields.settings import LossConfig
        LossConfig(head_bootstrap_keep=0.0)
