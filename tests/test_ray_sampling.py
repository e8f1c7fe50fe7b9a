"""``train.ray_sampling`` 'error': the error map's blocks, its draw probabilities, likelihood
weights and updates against hand-computed values and large Monte-Carlo estimates; the weighted
likelihood against a float64 loop; a run with the sampler trains, checkpoints its map and resumes
it; methods without ray weights and data-parallel training are refused."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import tiny_cpu_config

from stochastic_fields.data import load_dataset
from stochastic_fields.losses import gaussian_likelihood_nll
from stochastic_fields.ray_sampling import UNVISITED_BLOCK_ERROR, ErrorMap, pixel_blocks
from stochastic_fields.trainer import Trainer, TrainingRays


def test_pixel_blocks_follow_the_flattened_views_rows_and_columns():
    blocks = pixel_blocks(2, 3, 5, 2).reshape(2, 3, 5)
    # 3 x 5 pixels in blocks of 2: 2 block rows x 3 block columns = 6 blocks a view
    expected_view = torch.tensor([[0, 0, 1, 1, 2], [0, 0, 1, 1, 2], [3, 3, 4, 4, 5]])
    assert torch.equal(blocks[0], expected_view)
    assert torch.equal(blocks[1], expected_view + 6)
    with pytest.raises(ValueError, match="block side"):
        pixel_blocks(1, 2, 2, 0)


def _map(errors, counts, *, uniform_share=0.25, correction=1.0) -> ErrorMap:
    labels = torch.cat([torch.full((n,), b) for b, n in enumerate(counts)])
    m = ErrorMap(labels[torch.randperm(len(labels), generator=torch.Generator().manual_seed(1))],
                 uniform_share=uniform_share, correction=correction)
    m.error = torch.tensor(errors, dtype=torch.float32)
    return m


def test_block_probabilities_by_hand():
    m = _map([1.0, 3.0, 0.0], [2, 1, 1], uniform_share=0.5)
    # mined part: e n = [2, 3, 0] / 5; uniform part: n / P = [2, 1, 1] / 4
    expected = 0.5 * torch.tensor([0.4, 0.6, 0.0]) + 0.5 * torch.tensor([0.5, 0.25, 0.25])
    torch.testing.assert_close(m.block_probabilities(), expected)
    m.error.zero_()  # nothing to mine: uniform over pixels
    torch.testing.assert_close(m.block_probabilities(), torch.tensor([0.5, 0.25, 0.25]))


def test_draws_follow_q_and_weights_make_the_mean_unbiased():
    errors, counts = [0.5, 0.01, 2.0, 0.1], [3, 5, 1, 7]
    m = _map(errors, counts, uniform_share=0.2, correction=1.0)
    n = 400_000
    idx, w = m.sample(n, torch.Generator().manual_seed(0))
    assert idx.min() >= 0 and idx.max() < m.num_pixels
    q_pixel = (m.block_probabilities() / m.counts)[m.block]  # [P] each pixel's probability
    freq = torch.bincount(idx, minlength=m.num_pixels).double() / n
    torch.testing.assert_close(freq, q_pixel.double(), atol=4 * math.sqrt(0.1 / n), rtol=0)
    f = torch.linspace(0, 1, m.num_pixels) ** 2  # any per-pixel value: the weighted draw mean is its uniform mean
    torch.testing.assert_close((f[idx] * w).mean(), f.mean(), atol=3e-3, rtol=0)
    assert w.mean().item() == pytest.approx(1.0, abs=1e-5)
    # alpha 0: no correction; alpha 1/2: the square root of the importance ratio, renormalised
    idx0, w0 = _map(errors, counts, correction=0.0).sample(10, torch.Generator().manual_seed(0))
    assert torch.equal(w0, torch.ones(10))
    half = _map(errors, counts, uniform_share=0.2, correction=0.5)
    idx_h, w_h = half.sample(1000, torch.Generator().manual_seed(2))
    ratio = (1.0 / (half.num_pixels * q_pixel[idx_h])) ** 0.5
    torch.testing.assert_close(w_h, (ratio / ratio.mean()).float())


def test_update_takes_each_visited_blocks_mean_and_leaves_the_others():
    m = ErrorMap(torch.tensor([7, 7, 9, 9, 9, 4]), uniform_share=0.25, correction=0.0)
    # dense labels follow sorted(unique): 4 -> 0, 7 -> 1, 9 -> 2
    m.update(torch.tensor([0, 1, 0, 2]), torch.tensor([0.1, 0.3, 0.2, 0.05]))
    torch.testing.assert_close(m.error, torch.tensor([UNVISITED_BLOCK_ERROR, 0.2, 0.05]))
    assert UNVISITED_BLOCK_ERROR > 3.0  # above any squared error of [0, 1] colours summed over 3 channels


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="uniform_share"):
        ErrorMap(torch.zeros(3, dtype=torch.long), uniform_share=1.5, correction=0.0)
    with pytest.raises(ValueError, match="correction"):
        ErrorMap(torch.zeros(3, dtype=torch.long), uniform_share=0.5, correction=-0.1)
    with pytest.raises(ValueError, match="at least one"):
        ErrorMap(torch.zeros(0, dtype=torch.long), uniform_share=0.5, correction=0.0)


def test_weighted_likelihood_against_a_float64_loop():
    g = torch.Generator().manual_seed(4)
    colours, target = torch.rand(5, 3, 3, generator=g, dtype=torch.float64), torch.rand(5, 3, generator=g, dtype=torch.float64)
    w = torch.rand(5, generator=g, dtype=torch.float64) + 0.5
    std = 0.2
    total = 0.0
    for r in range(5):
        per_ray = 0.0
        for k in range(3):
            for c in range(3):
                per_ray += 0.5 * (colours[r, k, c] - target[r, c]) ** 2 / std ** 2 + math.log(std) + 0.5 * math.log(2 * math.pi)
        total += w[r] * per_ray / 3
    got = gaussian_likelihood_nll(colours, target, std, ray_weights=w)
    assert got.item() == pytest.approx(total.item() / 5, rel=1e-12)
    torch.testing.assert_close(gaussian_likelihood_nll(colours, target, std, ray_weights=torch.ones(5, dtype=torch.float64)),
                               gaussian_likelihood_nll(colours, target, std))


def test_training_rays_blocks_follow_the_holdout_mask(tiny_scene):
    dataset = load_dataset(tiny_scene, split_every=5)
    plain = TrainingRays.from_dataset(dataset, torch.device("cpu"), error_block=4)
    held = TrainingRays.from_dataset(dataset, torch.device("cpu"), holdout_fraction=0.25, holdout_block=8, error_block=4)
    assert plain.blocks is not None and len(plain.blocks) == len(plain.colours)
    assert len(held.blocks) == len(held.colours) < len(plain.colours)
    assert TrainingRays.from_dataset(dataset, torch.device("cpu")).blocks is None


@pytest.mark.parametrize("method", ["snerf", "deterministic"])
def test_a_run_with_the_error_sampler_trains_checkpoints_and_resumes_its_map(tiny_scene, tmp_path, method):
    dataset = load_dataset(tiny_scene, split_every=5)
    cfg = tiny_cpu_config(4)
    cfg.method = method
    cfg.train.ray_sampling = "error"
    cfg.train.checkpoint_every = 2
    first = Trainer(cfg, tmp_path, dataset)
    first.train(progress=False, max_steps=2)
    visited = first.error_map.error < UNVISITED_BLOCK_ERROR
    assert 0 < int(visited.sum()) <= 2 * cfg.train.rays_per_batch
    resumed = Trainer(cfg, tmp_path, dataset)
    resumed.train(progress=False)
    assert resumed.step == 4
    # the resumed map starts where the first run's checkpoint left it, then sees more blocks
    assert int((resumed.error_map.error < UNVISITED_BLOCK_ERROR).sum()) >= int(visited.sum())
    reference = Trainer(cfg, tmp_path / "straight", dataset)
    reference.train(progress=False)
    torch.testing.assert_close(resumed.error_map.error, reference.error_map.error)


def test_methods_without_ray_weights_are_refused(tiny_scene, tmp_path):
    dataset = load_dataset(tiny_scene, split_every=5)
    cfg = tiny_cpu_config(2)
    cfg.method = "ensemble"
    cfg.train.ray_sampling = "error"
    with pytest.raises(ValueError, match="ray weights"):
        Trainer(cfg, tmp_path, dataset)
