"""``field.grid_colour_levels``: the colour decoder reading each grid level's colour features apart.

References: the concatenated inputs equal each level's own trilinear read (torch's grid_sample) side
by side, with the density and noise channels still summed over the levels; gradients reach every
level's table as dense autograd gives them (float64) and gradcheck passes on a tiny field; a level
not yet faded in (coarse to fine) reads zeros; 'sum' is today's field; a run with the option trains,
resumes and refuses a field without a decoder.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from conftest import grid_sample_read, tiny_cpu_config

from stochastic_fields.config import validate_experiment
from stochastic_fields.data import load_dataset
from stochastic_fields.fields.grid import GridField
from stochastic_fields.scene_region import SceneRegion
from stochastic_fields.trainer import Trainer
from stochastic_fields.validation import ConfigError

FINEST, LEVELS, FEATURES = (6, 5, 8), 3, 4


def _field(concat: bool, *, seed: int = 0, noise_head: bool = True) -> GridField:
    torch.manual_seed(seed)
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, FINEST, num_levels=LEVELS, feature_dim=FEATURES, decoder_width=8,
                      concat_colour_levels=concat, noise_head=noise_head).double()
    with torch.no_grad():  # every channel of every level non-zero, so a swapped level or channel shows
        for table in field.levels:
            table.copy_(torch.randn_like(table))
    return field


def _points(n: int = 50) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    return torch.rand(n, 3, generator=g, dtype=torch.float64) * 2.2 - 1.1


def test_concatenated_inputs_are_each_levels_own_read_and_the_density_is_summed():
    field, unit = _field(True), _points()
    reads = [grid_sample_read(t.detach(), s, unit) for t, s in zip(field.levels, field.level_shapes)]  # L x [P, C]
    values, levels = field._read(unit)
    features = torch.cat(levels, dim=1)
    assert features.shape == (unit.shape[0], LEVELS * FEATURES)
    assert field.decoder[0].in_features == LEVELS * FEATURES + field.dir_enc.output_dim(3)
    torch.testing.assert_close(features, torch.cat([r[:, field.colour_channels] for r in reads], dim=1),
                               rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(values, sum(reads) + field.offset, rtol=1e-12, atol=1e-12)  # density, noise summed
    # a density-only read is the summed one, with no features
    only, none = field._read(unit, slice(0, 2))
    assert none is None
    torch.testing.assert_close(only, values[:, :2], rtol=1e-12, atol=1e-12)


def test_sum_is_todays_field():
    field, unit = _field(False), _points()
    reads = [grid_sample_read(t.detach(), s, unit) for t, s in zip(field.levels, field.level_shapes)]
    values, features = field._read(unit)
    assert features is None
    torch.testing.assert_close(values, sum(reads) + field.offset, rtol=1e-12, atol=1e-12)
    assert field.decoder[0].in_features == FEATURES + field.dir_enc.output_dim(3)


def test_gradients_reach_each_level_as_dense_autograd_gives_them():
    field, unit = _field(True), _points(40)
    dirs = F.normalize(torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)), dim=-1)
    out = field(unit, dirs)
    loss = (out.rgb_loc ** 2).sum() + out.density_loc.sum() + out.noise_scale.sum()
    loss.backward()
    dense = [t.detach().clone().requires_grad_(True) for t in field.levels]
    reads = [grid_sample_read(t, s, unit) for t, s in zip(dense, field.level_shapes)]
    colour = field.colour_channels
    ref = field.decode(sum(reads) + field.offset, unit, dirs, torch.Size([40]),
                       features=tuple(r[:, colour] for r in reads))
    ((ref.rgb_loc ** 2).sum() + ref.density_loc.sum() + ref.noise_scale.sum()).backward()
    for table, reference in zip(field.levels, dense):
        got = table.row_gradient.dense(table) if table.grad is None else table.grad
        torch.testing.assert_close(got, reference.grad, rtol=1e-10, atol=1e-12)
        assert reference.grad[:, colour].abs().sum() > 0  # every level's colour features receive gradient


def test_colour_gradcheck_through_the_concatenated_levels():
    field, unit = _field(True, noise_head=False), _points(6)
    dirs = F.normalize(torch.ones(6, 3, dtype=torch.float64), dim=-1)
    tables = [t.detach().clone().requires_grad_(True) for t in field.levels]

    def rgb(*levels):
        reads = [grid_sample_read(t, s, unit) for t, s in zip(levels, field.level_shapes)]
        features = tuple(r[:, field.colour_channels] for r in reads)
        return field.decode(sum(reads) + field.offset, unit, dirs, torch.Size([6]), features=features).rgb_loc

    assert torch.autograd.gradcheck(rgb, tuple(tables), eps=1e-6, atol=1e-7)


def test_a_level_not_yet_faded_in_reads_zero_features():
    field, unit = _field(True), _points()
    field.set_level_weights([1.0, 0.5, 0.0])
    features = torch.cat(field._read(unit)[1], dim=1)
    last = features[:, 2 * FEATURES:]
    assert torch.equal(last, torch.zeros_like(last))
    half = grid_sample_read(field.levels[1].detach(), field.level_shapes[1], unit)[:, field.colour_channels] * 0.5
    torch.testing.assert_close(features[:, FEATURES:2 * FEATURES], half, rtol=1e-12, atol=1e-12)


def test_concat_needs_a_colour_decoder():
    cfg = tiny_cpu_config(iterations=2)
    cfg.field.grid_colour_levels = "concat"
    cfg.field.grid_decoder_width = 0
    with pytest.raises(ConfigError, match="grid_colour_levels"):
        validate_experiment(cfg)
    with pytest.raises(ValueError, match="decoder"):
        GridField(SceneRegion("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3])), (4, 4, 4), decoder_width=0,
                  concat_colour_levels=True)


def test_a_run_with_concatenated_levels_trains_and_resumes(tiny_scene, tmp_path):
    cfg = tiny_cpu_config(iterations=4)
    cfg.field.grid_colour_levels = "concat"
    dataset = load_dataset(tiny_scene)
    first = Trainer(cfg, tmp_path, dataset)
    first.train(progress=False, max_steps=2)
    levels = len(first.model.field.levels)
    assert first.model.field.decoder[0].in_features == levels * cfg.field.grid_feature_dim + 15
    resumed = Trainer(cfg, tmp_path, dataset)
    resumed.train(progress=False)
    assert resumed.step == 4
    for a, b in zip(first.model.state_dict().values(), resumed.model.state_dict().values()):
        assert a.shape == b.shape


def test_mc_dropout_drops_each_levels_features():
    from stochastic_fields.models.baselines import GridDropoutField, dropout_control

    field, unit = _field(True), _points(30)
    dirs = F.normalize(torch.ones(30, 3, dtype=torch.float64), dim=-1)
    wrapped = GridDropoutField(field, 0.5).double()
    wrapped.eval()
    mean = wrapped(unit, dirs)  # dropout off: the field itself
    torch.testing.assert_close(mean.rgb_loc, field(unit, dirs).rgb_loc, rtol=1e-12, atol=1e-12)
    seen = []
    handle = field.decoder[0].register_forward_hook(lambda m, inp, out: seen.append(inp[0]))
    with dropout_control(wrapped, torch.Generator().manual_seed(0), always_on=True):
        wrapped(unit, dirs)
    handle.remove()
    features = seen[0][:, :LEVELS * FEATURES]
    kept = features != 0
    assert 0.3 < kept.double().mean() < 0.7  # about half of every level's features dropped
    torch.testing.assert_close(features[kept], 2.0 * torch.cat(field._read(unit)[1], dim=1)[kept], rtol=1e-12, atol=1e-12)
