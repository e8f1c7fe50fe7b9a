"""The compiled draws of a render's colour plan (``draw_kernels.draw_reach``) against the torch ops (bit for
bit) and a float64 loop, and the colour moments a render reads only where its plan keeps a sample
(``reached_colour_moments``)."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch

from stochastic_fields import draw_kernels, row_kernels
from stochastic_fields.fields.grid import GridField
from stochastic_fields.logistic_normal_table import logistic_normal_moments_tabulated
from stochastic_fields.rays import RayBundle
from stochastic_fields.renderer import RenderSettings, _reaching_dense, reached_colour_moments, render_rays
from stochastic_fields.scene_region import SceneRegion

needs_numba = pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")


def _draws(dtype, M, shared, R=37, K=6, S=29, seed=0):
    g = torch.Generator().manual_seed(seed)
    loc = torch.randn(R, S, generator=g, dtype=dtype) * 3.0
    offsets = torch.randn(R, S, M, generator=g, dtype=dtype) if M > 1 else None
    scale = torch.rand(R, S, generator=g, dtype=dtype) + 0.05
    eps = torch.randn(R, K, 1 if shared else S, generator=g, dtype=dtype)
    deltas = torch.rand(R, S, generator=g, dtype=dtype) * 0.3
    loc[0] = -50.0  # a ray with no density in any draw: nothing reached
    loc[1, 0] = 1e6  # opaque at its first sample: only that one reached
    scale[2] = 1e-12  # (nearly) no noise: every draw its head's mean field
    deltas[3, 5:] = 0.0  # zero-length intervals: no optical depth
    return loc, offsets, scale, eps, SimpleNamespace(deltas=deltas)


@needs_numba
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("M", [1, 2, 3])
@pytest.mark.parametrize("shared", [False, True])
def test_draw_reach_is_the_torch_ops_bit_for_bit(dtype, M, shared):
    loc, offsets, scale, eps, samples = _draws(dtype, M, shared)
    fast = _reaching_dense(loc, scale, samples, eps, 1e-4, offsets)
    with row_kernels.torch_ops_only():
        ref = _reaching_dense(loc, scale, samples, eps, 1e-4, offsets)
    for a, b, name in zip(fast, ref, ("reached", "density", "transmittance")):
        assert a.dtype == b.dtype and torch.equal(a, b), name
    reached, density, transmittance = fast
    assert not reached[0].any() and reached[1].tolist() == [True] + [False] * (reached.shape[1] - 1)
    assert transmittance[1, :, 1:].eq(0.0).all() and transmittance[:, :, 0].eq(1.0).all()


@needs_numba
def test_draw_reach_against_a_loop():
    """One ray, draw and sample at a time, float64: relu(mu + o_(k mod M) + s eps), T = exp(-sum_{j<i})."""
    loc, offsets, scale, eps, samples = _draws(torch.float64, 2, False, R=5, K=4, S=9, seed=4)
    reached, density, transmittance = _reaching_dense(loc, scale, samples, eps, 1e-3, offsets)
    R, K, S = density.shape
    for r in range(R):
        for k in range(K):
            optical = 0.0
            for i in range(S):
                a = max(float(loc[r, i] + offsets[r, i, k % 2] + scale[r, i] * eps[r, k, i]), 0.0)
                assert float(density[r, k, i]) == pytest.approx(a, rel=1e-12, abs=1e-300)
                assert float(transmittance[r, k, i]) == pytest.approx(math.exp(-optical), rel=1e-12, abs=1e-300)
                optical += a * float(samples.deltas[r, i])
        want = [any(float(density[r, k, i]) > 0 and float(transmittance[r, k, i]) >= 1e-3 for k in range(K))
                for i in range(S)]
        assert reached[r].tolist() == want


@needs_numba
def test_draw_reach_checks_shapes_and_runs_without_autograd_only():
    loc, offsets, scale, eps, samples = _draws(torch.float32, 2, False)
    with pytest.raises(ValueError, match="draw_reach"):
        draw_kernels.draw_reach(loc[:, None], scale[:, :3], eps, samples.deltas, 1e-4)
    assert not draw_kernels.available(loc)  # autograd on
    with torch.no_grad():
        assert draw_kernels.available(loc, eps)
        assert not draw_kernels.available(loc, eps.double())  # mixed float dtypes
        with row_kernels.torch_ops_only():
            assert not draw_kernels.available(loc)


def _field() -> GridField:
    torch.manual_seed(0)
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (8, 7, 9), num_levels=2, decoder_width=8, feature_dim=4, noise_head=True,
                      density_heads=2, head_init_std=0.5)
    with torch.no_grad():
        for table in field.levels:
            table.normal_(0.0, 1.0)
            table[:, 0] = table[:, 0] * 3.0 + 0.5
    return field.eval()


def _rays(n: int = 64) -> RayBundle:
    g = torch.Generator().manual_seed(1)
    origins = torch.zeros(n, 3)
    origins[:, 2] = -2.0
    directions = torch.randn(n, 3, generator=g) * 0.25
    directions[:, 2] = 1.0
    directions = directions / directions.norm(dim=-1, keepdim=True)
    ones = torch.ones(n)
    return RayBundle(origins, directions, 0.5 * ones, 3.5 * ones, ones)


def test_colour_moments_read_only_where_kept():
    field = _field()
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        params = field(torch.randn(10, 6, 3, generator=g), torch.randn(10, 6, 3, generator=g))
        reached = torch.rand(10, 6, generator=g) < 0.3
        reached[0, 0], reached[0, 1] = True, False
        mean, var = reached_colour_moments(params, reached)
        full_mean, full_var = logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)
        torch.testing.assert_close(mean[reached], full_mean[reached], rtol=1e-6, atol=1e-7)
        torch.testing.assert_close(var[reached], full_var[reached], rtol=1e-6, atol=1e-7)
        first = (~reached).reshape(-1).nonzero()[0, 0]
        skipped_mean = full_mean.reshape(-1, 3)[first].expand(int((~reached).sum()), 3)
        torch.testing.assert_close(mean[~reached], skipped_mean, rtol=1e-6, atol=1e-7)
        every = reached_colour_moments(params, torch.ones_like(reached))
        assert torch.equal(every[0], full_mean) and torch.equal(every[1], full_var)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_render_with_its_plan_matches_every_colour_decoded(compiled):
    """The render that reads colour moments where its plan keeps a sample (its draws compiled with numba,
    else the torch ops) against the one that decodes every colour: within the plan's transmittance."""
    field, rays = _field(), _rays()
    tau = 1e-4
    base = RenderSettings(num_samples=32, num_draws=8, colour_estimator="rao_blackwell", colour_min_transmittance=0.0)
    planned = dataclasses.replace(base, colour_min_transmittance=tau)
    ctx = row_kernels.torch_ops_only() if not compiled else torch.no_grad()
    with torch.no_grad(), ctx:
        full = render_rays(field, rays, base, generator=torch.Generator().manual_seed(5))
        fast = render_rays(field, rays, planned, generator=torch.Generator().manual_seed(5))
    assert 0.0 < float((fast.params.rgb_scale != full.params.rgb_scale).any(-1).float().mean()) < 1.0
    for name in ("colour_mean", "colour_var", "depth_mean", "depth_var_total", "opacity"):
        torch.testing.assert_close(getattr(fast.stats, name), getattr(full.stats, name), rtol=0, atol=8 * tau,
                                   msg=name)
    torch.testing.assert_close(fast.extras["weights"], full.extras["weights"], rtol=1e-6, atol=1e-7)
