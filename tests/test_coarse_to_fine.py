"""Coarse to fine on the grid backend (``field.grid_coarse_to_fine``): the level-weight schedule by
hand, the weighted field against a per-level reference sum, the gradients of a faded level, and the
trainer's use of it (finer levels untouched at the start, every level read by the trained model)."""

from __future__ import annotations

import pytest
import torch

from stochastic_fields.fields.grid import GridField, coarse_to_fine_weights
from stochastic_fields.fields.row_gather import row_gradient
from stochastic_fields.scene_region import SceneRegion


def _field(num_levels: int = 3, seed: int = 0) -> GridField:
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (9, 7, 8), num_levels=num_levels, decoder_width=0).double()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for level in field.levels:
            level.copy_(torch.randn(level.shape, generator=g, dtype=torch.float64))
    return field


def _points(n: int = 200, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1


@pytest.mark.parametrize("progress, expected", [
    (0.0, [1.0, 0.0, 0.0]),
    (0.125, [1.0, 0.5, 0.0]),   # level 1 halfway through its window [0, 0.25]
    (0.25, [1.0, 1.0, 0.0]),
    (0.375, [1.0, 1.0, 0.5]),   # level 2 halfway through [0.25, 0.5]
    (0.5, [1.0, 1.0, 1.0]),
    (0.9, [1.0, 1.0, 1.0]),
    (1.7, [1.0, 1.0, 1.0]),     # clamped
    (-0.3, [1.0, 0.0, 0.0]),
])
def test_schedule_by_hand(progress, expected):
    assert coarse_to_fine_weights(3, progress, 0.5) == pytest.approx(expected, abs=1e-12)


def test_schedule_edge_cases():
    assert coarse_to_fine_weights(3, 0.0, 0.0) == [1.0, 1.0, 1.0]  # off
    assert coarse_to_fine_weights(1, 0.0, 0.5) == [1.0]
    # four levels over the whole run: windows of a third each
    assert coarse_to_fine_weights(4, 0.5, 1.0) == pytest.approx([1.0, 1.0, 0.5, 0.0])
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="fraction"):
            coarse_to_fine_weights(3, 0.5, bad)


def test_weighted_levels_equal_the_weighted_sum_of_single_levels():
    field, unit = _field(), _points()
    offset = field.offset
    single = []  # each level alone: zero the others
    for keep in range(3):
        f = _field()
        with torch.no_grad():
            for i, level in enumerate(f.levels):
                if i != keep:
                    level.zero_()
        single.append(f._interpolate(unit) - offset)
    weights = [1.0, 0.3, 0.0]
    field.set_level_weights(weights)
    expected = offset + sum(a * s for a, s in zip(weights, single))
    torch.testing.assert_close(field._interpolate(unit), expected, rtol=1e-12, atol=1e-12)
    with torch.no_grad():  # the sliced read of some channels agrees
        torch.testing.assert_close(field._interpolate(unit, slice(0, 2)), expected[:, :2], rtol=1e-12, atol=1e-12)
    field.set_level_weights(None)
    torch.testing.assert_close(field._interpolate(unit), offset + sum(single), rtol=1e-12, atol=1e-12)


def _level_gradients(weights: list[float], unit: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Dense gradients of sum v^2 for every level, and v [P, C], with the given level weights."""
    field = _field()
    field.set_level_weights(weights)
    value = field._interpolate(unit)
    value.pow(2).sum().backward()
    return [row_gradient(level).dense(level) for level in field.levels], value.detach()


def test_a_faded_level_gets_a_scaled_gradient_and_an_unread_one_none():
    unit = _points()
    full, _ = _level_gradients([1.0, 1.0, 1.0], unit)
    faded, value = _level_gradients([1.0, 0.25, 0.0], unit)
    assert faded[2].abs().max() == 0  # level 2 not read
    assert full[1].abs().max() > 0
    # by hand: d/dG_1 sum_p v_p^2 = sum_p 2 v_p * 0.25 * w_pj at level 1's corners, i.e. the gradient
    # of sum_p <g_1(x_p), 2 * 0.25 * v_p> with g_1 level 1 alone
    ref = _field()
    with torch.no_grad():
        ref.levels[0].zero_()
        ref.levels[2].zero_()
    ref.offset.zero_()
    (ref._interpolate(unit) * (2 * 0.25 * value)).sum().backward()
    torch.testing.assert_close(faded[1], row_gradient(ref.levels[1]).dense(ref.levels[1]), rtol=1e-10, atol=1e-12)


def test_level_weights_are_checked():
    field = _field()
    with pytest.raises(ValueError, match="3 numbers"):
        field.set_level_weights([1.0, 0.5])
    with pytest.raises(ValueError, match="3 numbers"):
        field.set_level_weights([1.0, 2.0, 0.0])
    with pytest.raises(ValueError, match="coarsest"):
        field.set_level_weights([0.0, 1.0, 1.0])


def test_config_rejects_coarse_to_fine_without_a_grid():
    from stochastic_fields.config import preset, validate_experiment
    from stochastic_fields.validation import ConfigError

    cfg = preset("tiny")
    cfg.field.backend = "mlp"
    cfg.field.grid_coarse_to_fine = 0.5
    with pytest.raises(ConfigError, match="field.grid_coarse_to_fine"):
        validate_experiment(cfg)


def test_trainer_fades_levels_in_and_the_trained_model_reads_all(tiny_scene, tmp_path):
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    cfg.train.iterations = 8
    cfg.train.rays_per_batch = 64
    cfg.train.device = "cpu"
    cfg.train.tv_weight = 0.0  # the TV term touches every level; without it only read levels move
    cfg.field.grid_max_cells = 8 ** 3
    cfg.field.grid_coarse_to_fine = 1.0
    cfg.field.grid_levels = 3  # the weights asserted below are three levels'
    cfg.loss.lambda_random = 0.0  # the priors read the field too; keep to the pixels' reads
    cfg.loss.lambda_observed = 0.0
    trainer = Trainer(cfg, tmp_path, load_dataset(tiny_scene))
    grid = trainer.model.field
    before = [level.detach().clone() for level in grid.levels]
    seen = []
    original = grid._interpolate

    def spy(unit, channels=None):
        seen.append(list(grid.level_weights) if grid.level_weights is not None else None)
        return original(unit, channels)

    grid._interpolate = spy
    trainer.train(progress=False, max_steps=1)  # progress 0: level 0 only
    assert seen and all(w == [1.0, 0.0, 0.0] for w in seen)
    assert not torch.equal(grid.levels[0].detach(), before[0])
    for i in (1, 2):
        torch.testing.assert_close(grid.levels[i].detach(), before[i], rtol=0, atol=0)
    assert grid.level_weights is None  # after training: every level read
    seen.clear()
    trainer.train(progress=False, max_steps=3)  # steps 1..3 of 8: progress 1/8, 2/8, 3/8 of a full-run fade
    assert seen[-1] == pytest.approx(coarse_to_fine_weights(3, 3 / 8, 1.0))
    assert grid.level_weights is None
