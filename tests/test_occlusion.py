"""Occlusion regulariser (stochastic_fields.occlusion): the near optical depth against a float64 loop
over samples, packed = dense, hand values, hard densities, the rectified-normal mean against scipy,
gradients only where the mask is, and the term each model's training loss adds."""

from __future__ import annotations

import copy
import math

import pytest
from conftest import rays_along_z
import scipy.stats
import torch

from stochastic_fields.losses import LossConfig
from stochastic_fields.occlusion import expected_density, near_optical_depth
from stochastic_fields.renderer import pack_samples
from stochastic_fields.samplers import sample_along_rays




def naive(density, t0, t1, near, far, spacing, fraction):
    """sum over samples whose midpoint's sampling coordinate is below ``fraction`` of sigma * delta, by a loop."""
    total = 0.0
    for d, a, b in zip(density.tolist(), t0.tolist(), t1.tolist()):
        m = 0.5 * (a + b)
        s = (m - near) / (far - near) if spacing == "linear" else (1 / m - 1 / near) / (1 / far - 1 / near)
        if s < fraction:
            total += d * (b - a)
    return total


@pytest.mark.parametrize("spacing", ["linear", "disparity"])
@pytest.mark.parametrize("fraction", [0.25, 0.5, 1.0])
def test_matches_a_loop_over_samples(spacing, fraction):
    g = torch.Generator().manual_seed(0)
    rays = rays_along_z([0.5, 1.0, 2.0], [4.0, 100.0, 3.0])
    samples = sample_along_rays(rays, 24, spacing=spacing, stratified=True, generator=g)
    density = torch.rand(3, 24, generator=g, dtype=torch.float64) * 5
    got = near_optical_depth(density, None, samples, spacing, fraction)
    for r in range(3):
        ref = naive(density[r], samples.t_starts[r], samples.t_ends[r], float(rays.near[r]), float(rays.far[r]),
                    spacing, fraction)
        assert got[r].item() == pytest.approx(ref, rel=1e-12)


def test_hand_values():
    """Unit density on [1, 5], 4 linear samples: the first quarter is the sample [1, 2] (optical depth 1);
    all of the ray is 4; on 64 disparity samples from 1 to 100 the first 16 end at 1 / (1 - 0.25 * 0.99)."""
    rays = rays_along_z([1.0], [5.0])
    samples = sample_along_rays(rays, 4, spacing="linear")
    ones = torch.ones(1, 4, dtype=torch.float64)
    assert near_optical_depth(ones, None, samples, "linear", 0.25).item() == pytest.approx(1.0)
    assert near_optical_depth(ones, None, samples, "linear", 1.0).item() == pytest.approx(4.0)
    assert near_optical_depth(torch.zeros(1, 4, dtype=torch.float64), None, samples, "linear", 1.0).item() == 0.0
    rays = rays_along_z([1.0], [100.0])
    samples = sample_along_rays(rays, 64, spacing="disparity")
    got = near_optical_depth(torch.ones(1, 64, dtype=torch.float64), None, samples, "disparity", 0.25).item()
    assert got == pytest.approx(1.0 / (1.0 - 0.25 * 0.99) - 1.0, rel=1e-12)


def test_huge_densities_stay_finite_and_exact():
    rays = rays_along_z([1.0], [5.0])
    samples = sample_along_rays(rays, 4, spacing="linear")
    density = torch.tensor([[1e30, 0.0, 1e30, 1e30]], dtype=torch.float32)
    got = near_optical_depth(density, None, samples, "linear", 0.5).item()
    assert math.isfinite(got) and got == pytest.approx(1e30, rel=1e-6)  # only the first sample counts


def test_packed_equals_dense_when_skipped_samples_are_empty():
    g = torch.Generator().manual_seed(1)
    rays = rays_along_z([0.5, 1.0, 2.0, 1.5], [4.0, 100.0, 3.0, 9.0])
    samples = sample_along_rays(rays, 16, spacing="disparity", stratified=True, generator=g)
    keep = torch.rand(4, 16, generator=g) > 0.5
    keep[1] = False  # a ray with nothing kept
    density = torch.rand(4, 16, generator=g, dtype=torch.float64) * keep
    packed = pack_samples(samples, keep)
    got = near_optical_depth(density[keep], None, packed, "disparity", 0.25)
    torch.testing.assert_close(got, near_optical_depth(density, None, samples, "disparity", 0.25), rtol=1e-12, atol=0)
    assert got[1].item() == 0.0


def test_gradient_reaches_only_the_near_samples():
    rays = rays_along_z([1.0, 2.0], [5.0, 6.0])
    samples = sample_along_rays(rays, 8, spacing="linear")
    density = torch.rand(2, 8, generator=torch.Generator().manual_seed(2), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d: near_optical_depth(d, None, samples, "linear", 0.25), (density,))
    near_optical_depth(density, None, samples, "linear", 0.25).sum().backward()
    torch.testing.assert_close(density.grad[:, :2], samples.deltas[:, :2])  # 2 of 8 samples are the near quarter
    assert torch.all(density.grad[:, 2:] == 0)


def test_rectified_normal_density_matches_its_mean_on_every_sample():
    """With a scale the term is the loop over samples of the rectified normal's mean (computed on all
    samples, then restricted); gradients reach loc and scale of the near samples only."""
    g = torch.Generator().manual_seed(3)
    rays = rays_along_z([0.5, 2.0], [40.0, 3.0])
    samples = sample_along_rays(rays, 16, spacing="disparity", stratified=True, generator=g)
    loc = (torch.randn(2, 16, generator=g, dtype=torch.float64) * 3).requires_grad_()
    scale = (torch.rand(2, 16, generator=g, dtype=torch.float64) + 0.05).requires_grad_()
    got = near_optical_depth(loc, scale, samples, "disparity", 0.25)
    mean = expected_density(loc, scale).detach()
    for r in range(2):
        ref = naive(mean[r], samples.t_starts[r], samples.t_ends[r], float(rays.near[r]), float(rays.far[r]),
                    "disparity", 0.25)
        assert got[r].item() == pytest.approx(ref, rel=1e-12)
    assert torch.autograd.gradcheck(lambda a, b: near_optical_depth(a, b, samples, "disparity", 0.25), (loc, scale))
    got.sum().backward()
    m = (1 / samples.t_mids - 1 / rays.near[:, None]) / (1 / rays.far[:, None] - 1 / rays.near[:, None])
    near = (m < 0.25).double()
    a, b = loc.detach().clone().requires_grad_(), scale.detach().clone().requires_grad_()
    (expected_density(a, b) * samples.deltas * near).sum().backward()  # every sample's mean, far ones weighted 0
    torch.testing.assert_close(loc.grad, a.grad, rtol=1e-12, atol=0)
    torch.testing.assert_close(scale.grad, b.grad, rtol=1e-12, atol=0)
    assert torch.all(loc.grad[near == 0] == 0) and torch.all(scale.grad[near == 0] == 0) and near.sum() > 0


@pytest.mark.parametrize("fraction", [0.0, -0.1, 1.5])
def test_rejects_a_fraction_outside_0_1(fraction):
    samples = sample_along_rays(rays_along_z([1.0], [2.0]), 4)
    with pytest.raises(ValueError, match="near_fraction"):
        near_optical_depth(torch.ones(1, 4), None, samples, "linear", fraction)
    if fraction <= 0 or fraction > 1:
        with pytest.raises(ValueError, match="occlusion_near_fraction"):
            LossConfig(occlusion_near_fraction=fraction)


def test_loss_config_rejects_a_negative_weight():
    with pytest.raises(ValueError, match="lambda_occlusion"):
        LossConfig(lambda_occlusion=-1.0)


@pytest.mark.parametrize("loc,scale", [(0.7, 0.3), (-2.0, 0.5), (3.0, 1e-4), (-40.0, 1.0), (0.0, 2.0)])
def test_expected_density_is_the_rectified_normal_mean(loc, scale):
    # E[max(0, Y)] = P(Y > 0) E[Y | Y > 0], the truncated normal's mean from scipy
    ref = scipy.stats.norm.sf(0.0, loc, scale) * scipy.stats.truncnorm.mean(-loc / scale, math.inf, loc, scale)
    got = expected_density(torch.tensor([loc], dtype=torch.float64), torch.tensor([scale], dtype=torch.float64))
    assert got.item() == pytest.approx(ref, rel=1e-7, abs=1e-300)
    assert expected_density(torch.tensor([loc]), None).item() == pytest.approx(max(loc, 0.0))


@pytest.mark.parametrize("method", ["snerf", "deterministic", "ensemble"])
def test_training_loss_adds_the_weighted_term(method, tiny_scene):
    """Same generator, same field: the regularised loss is the plain loss plus lambda times the logged
    term (summed over ensemble members); weight 0 logs nothing."""
    from test_baselines import tiny_config

    from stochastic_fields.data import load_dataset
    from stochastic_fields.models.registry import build_model

    dataset = load_dataset(tiny_scene)
    cfg = tiny_config(method)
    torch.manual_seed(0)
    plain = build_model(cfg, dataset)
    cfg = copy.deepcopy(cfg)  # the models keep their LossConfig
    cfg.loss.lambda_occlusion = 0.5
    reg = build_model(cfg, dataset)
    reg.load_state_dict(plain.state_dict())
    rays = dataset.rays(dataset.train_indices[0])[::6, ::6].flatten()
    target = dataset.images[dataset.train_indices[0]][::6, ::6].reshape(-1, 3)
    l0, logs0 = plain.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(5))
    l1, logs1 = reg.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(5))
    assert "occlusion" not in logs0
    assert logs1["occlusion"] > 0
    members = len(reg.members) if method == "ensemble" else 1
    torch.testing.assert_close(l1, l0 + 0.5 * members * logs1["occlusion"], rtol=1e-5, atol=1e-5)


def test_llff_preset_trains_with_it_and_the_paper_rows_without():
    """Study 29: the llff preset (forward-facing scenes) sets 0.1; the package default and the paper S-NeRF rows
    (the paper's objective) keep 0, every other method of the tables takes the preset's."""
    from stochastic_fields.config import ExperimentConfig, preset
    from stochastic_fields_bench.methods import METHOD_SPECS

    assert preset("llff").loss.lambda_occlusion == 0.1 and ExperimentConfig().loss.lambda_occlusion == 0.0
    for name, spec in METHOD_SPECS.items():
        paper = name in ("snerf", "snerf_predictive", "snerf_kl_none", "snerf_kl_fixed_prior")
        assert (("loss.lambda_occlusion", 0.0) in spec.overrides) == paper, name
