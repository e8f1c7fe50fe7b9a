"""``train.adam_beta2_colour``: Adam's second-moment decay for the colour's parameters apart.

The references: a table whose colour columns take their own decay equals, column by column, the
same steps with one decay for the whole table (each decay's run on its own columns), on the
compiled loop and the torch ops; the optimiser's groups put the grid's colour decoder and colour
channels (and only those) on the colour's decay; and a run with the option trains and resumes.
"""

from __future__ import annotations

import contextlib

import pytest
import torch
from conftest import tiny_cpu_config

from stochastic_fields import row_kernels
from stochastic_fields.data import load_dataset
from stochastic_fields.fields.grid import GridField
from stochastic_fields.fields.row_gather import gather_rows
from stochastic_fields.models.registry import build_model
from stochastic_fields.optim import FieldOptimizer, RowSparseAdam
from stochastic_fields.trainer import Trainer, make_optimizer

N, C, COLOUR = 30, 6, (2, 5)


def _steps(group_options: dict, *, torch_ops: bool, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Five lazy Adam steps of a [N, C] table on fixed gradients (duplicates, untouched rows)."""
    g = torch.Generator().manual_seed(3)
    table = torch.nn.Parameter(torch.randn(N, C, generator=g, dtype=dtype))
    opt = RowSparseAdam([{"params": [table], **group_options}], lr=0.05, eps=1e-8)
    with row_kernels.torch_ops_only() if torch_ops else contextlib.nullcontext():
        for s in range(5):
            idx = torch.randint(0, 15, (20, 8), generator=g) + s
            w = torch.rand(20, 8, generator=g, dtype=dtype)
            opt.zero_grad()
            (gather_rows(table, idx, w) * torch.randn(20, C, generator=g, dtype=dtype)).sum().backward()
            opt.step()
    return table.detach(), opt.state[table]["exp_avg_sq"]


@pytest.mark.parametrize("torch_ops", [True] + ([False] if row_kernels.numba is not None else []))
def test_colour_columns_take_their_own_decay_and_the_others_keep_theirs(torch_ops):
    mixed, mixed_v = _steps({"betas": (0.9, 0.999), "colour_channels": COLOUR, "colour_beta2": 0.99}, torch_ops=torch_ops)
    slow, slow_v = _steps({"betas": (0.9, 0.999)}, torch_ops=torch_ops)
    fast, fast_v = _steps({"betas": (0.9, 0.99)}, torch_ops=torch_ops)
    colour = torch.zeros(C, dtype=torch.bool)
    colour[COLOUR[0]:COLOUR[1]] = True
    tol = dict(rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(mixed[:, colour], fast[:, colour], **tol)
    torch.testing.assert_close(mixed[:, ~colour], slow[:, ~colour], **tol)
    torch.testing.assert_close(mixed_v[:, colour], fast_v[:, colour], **tol)
    torch.testing.assert_close(mixed_v[:, ~colour], slow_v[:, ~colour], **tol)
    assert not torch.allclose(slow[:, colour], fast[:, colour], rtol=1e-6, atol=0)  # the decays differ visibly


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_loop_with_per_channel_decay_matches_torch_ops(dtype):
    options = {"betas": (0.9, 0.999), "colour_channels": COLOUR, "colour_beta2": 0.95}
    ours, ours_v = _steps(options, torch_ops=False, dtype=dtype)
    ref, ref_v = _steps(options, torch_ops=True, dtype=dtype)
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-6, atol=2e-6)
    torch.testing.assert_close(ours, ref, **tol)
    torch.testing.assert_close(ours_v, ref_v, **tol)


def test_row_kernel_refuses_a_decay_list_of_the_wrong_length():
    x = torch.zeros(4, 3)
    with pytest.raises(ValueError):
        row_kernels.adam_touched_rows(x, torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4, 3),
                                      torch.ones(4, dtype=torch.bool), lr=0.1, betas=(0.9, (0.99, 0.999)),
                                      eps=1e-8, step=1)


def _model(tiny_scene, method: str = "snerf"):
    cfg = tiny_cpu_config(iterations=4)
    cfg.method = method
    return build_model(cfg, load_dataset(tiny_scene)), cfg


@pytest.mark.parametrize("method", ["snerf", "deterministic"])
def test_the_colour_decoder_and_channels_and_nothing_else_take_the_colour_decay(tiny_scene, method):
    model, cfg = _model(tiny_scene, method)
    grid = next(m for m in model.modules() if isinstance(m, GridField))
    assert grid.decoder_width > 0
    same = FieldOptimizer(model.param_groups(0.01), total_steps=10, final_factor=0.1, beta2=0.999, colour_beta2=0.999)
    assert len(same.param_groups) == 2  # equal decays: the model's own groups (older checkpoints load)
    assert all("colour_channels" not in g for g in same.param_groups)
    opt = FieldOptimizer(model.param_groups(0.01), total_steps=10, final_factor=0.1, beta2=0.999, colour_beta2=0.99)
    sparse, = [g for g in opt.param_groups if "colour_channels" in g]
    assert sparse["colour_channels"] == (grid.colour_channels.start, grid.colour_channels.stop)
    assert sparse["colour_beta2"] == 0.99 and sparse["betas"] == (0.9, 0.999)
    assert RowSparseAdam.channel_beta2(grid.levels[0], sparse) == tuple(
        0.99 if grid.colour_channels.start <= c < grid.colour_channels.stop else 0.999 for c in range(grid.num_channels))
    decoder = {id(p) for p in grid.decoder.parameters()}
    for g in opt.param_groups:
        if g is sparse:
            continue
        ids = {id(p) for p in g["params"]}
        assert ids <= decoder or not ids & decoder  # the decoder's parameters form a group of their own
        assert g["betas"] == ((0.9, 0.99) if ids <= decoder else (0.9, 0.999))
    assert sum(len(g["params"]) for g in opt.param_groups) == len([p for p in model.parameters() if p.requires_grad])


def test_a_run_with_the_colour_decay_trains_and_resumes(tiny_scene, tmp_path):
    cfg = tiny_cpu_config(iterations=4)
    cfg.train.adam_beta2_colour = 0.99
    dataset = load_dataset(tiny_scene)
    first = Trainer(cfg, tmp_path, dataset)
    first.train(progress=False, max_steps=2)
    assert len(first.optimizer.param_groups) == 3
    resumed = Trainer(cfg, tmp_path, dataset)
    resumed.train(progress=False)
    assert resumed.step == 4
    assert sorted(g["betas"][1] for g in resumed.optimizer.param_groups) == [0.99, 0.999, 0.999]
    for opt in (resumed.optimizer, make_optimizer(resumed.model, cfg)):  # the checkpoint's groups keep the option
        assert [g.get("colour_beta2") for g in opt.param_groups if "colour_channels" in g] == [0.99]


def test_a_run_saved_before_the_option_keeps_its_colour_decay_and_fingerprint():
    """A run saved before ``train.adam_beta2_colour`` existed gave its colour ``train.adam_beta2``: it
    loads with that, its fingerprint stays its own (study 47's 0.99 rows differ from a run at
    adam_beta2 0.99 with today's colour decay), and a default run's is unchanged."""
    from stochastic_fields.config import ExperimentConfig, saved_config, to_dict
    from stochastic_fields_bench.runner import config_fingerprint, semantic_options
    from stochastic_fields.config import flatten

    old = to_dict(ExperimentConfig())
    old["train"]["adam_beta2"] = 0.99
    del old["train"]["adam_beta2_colour"]
    loaded = saved_config(old)
    assert (loaded.train.adam_beta2, loaded.train.adam_beta2_colour) == (0.99, 0.99)
    assert semantic_options(flatten(old)) == semantic_options(flatten(to_dict(loaded)))
    today = ExperimentConfig()
    today.train.adam_beta2 = 0.99
    assert config_fingerprint(loaded) != config_fingerprint(today)
    default = to_dict(ExperimentConfig())
    del default["train"]["adam_beta2_colour"]
    assert semantic_options(flatten(default)) == semantic_options(flatten(to_dict(ExperimentConfig())))
    assert saved_config(default).train.adam_beta2_colour == 0.999
