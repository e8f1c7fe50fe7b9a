"""The Rao-Blackwellised colour estimator: tabulated logistic-normal moments against the float64
quadrature; per-draw conditional colour moments against float64 loops; the estimator against a
large Monte-Carlo render with drawn colours; packed = dense; adaptive K with it."""

from __future__ import annotations

import math

import pytest
import torch

from stochastic_fields.adaptive import render_rays_adaptive
from stochastic_fields.distributions import _logistic_normal_moments
from stochastic_fields.fields.base import FieldParams
from stochastic_fields.logistic_normal_table import logistic_normal_moments_tabulated
from stochastic_fields.renderer import (RenderSettings, colour_moments, pack_samples, render_samples,
                                        render_samples_packed)
from stochastic_fields.samplers import sample_along_rays
from stochastic_fields.volume_rendering import concatenate_draws, trajectory_statistics

from test_packed_render import BoxField, box_rays


# ------------------------------------------------------------------------- tabulated moments

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_table_matches_quadrature_over_the_working_range(dtype):
    gen = torch.Generator().manual_seed(3)
    n = 20000
    loc = (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1) * 20
    scale = torch.exp(torch.rand(n, generator=gen, dtype=torch.float64) * 16 - 8)  # 3e-4 .. 3e3
    mean_ref, var_ref = _logistic_normal_moments(loc, scale)
    mean, var = logistic_normal_moments_tabulated(loc.to(dtype), scale.to(dtype))
    assert mean.dtype == dtype and var.dtype == dtype
    assert (mean.double() - mean_ref).abs().max() < 5e-6
    assert (var.double() - var_ref).abs().max() < 5e-5
    relevant = var_ref > 1e-6  # NLL_VARIANCE_FLOOR ~ 1.3e-6
    assert ((var.double() - var_ref).abs() / var_ref)[relevant].max() < 2e-3


@pytest.mark.parametrize("loc, scale", [(0.0, 1e-6), (3.0, 1e-5), (-50.0, 1e-4), (50.0, 1e-3), (-12.0, 1e-2),
                                        (0.3, 1e3), (-40.0, 1e4), (45.0, 3e4), (-50.0, 3.0)])
def test_table_hard_cases(loc, scale):
    """Tiny scales (below the table: variance by the delta method), huge ones (above it), far tails."""
    l64, s64 = torch.tensor([loc], dtype=torch.float64), torch.tensor([scale], dtype=torch.float64)
    mean_ref, var_ref = _logistic_normal_moments(l64, s64)
    mean, var = logistic_normal_moments_tabulated(l64, s64)
    assert torch.isfinite(mean).all() and torch.isfinite(var).all() and (var >= 0).all()
    assert abs(float(mean - mean_ref)) < 5e-6
    assert abs(float(var - var_ref)) < 5e-5
    if float(var_ref) > 1e-30:  # relative accuracy holds down to tiny variances where s is small
        tol = 2e-3 if scale < 1.0 else 5e-2
        assert abs(float(var / var_ref) - 1.0) < tol, (float(var), float(var_ref))


def test_table_symmetry_and_gradients():
    loc = torch.linspace(-8, 8, 40, dtype=torch.float64, requires_grad=True)  # not 0: |loc| folds there
    scale = torch.full_like(loc, 0.7).requires_grad_(True)
    mean, var = logistic_normal_moments_tabulated(loc, scale)
    mean_neg, var_neg = logistic_normal_moments_tabulated(-loc, scale)
    torch.testing.assert_close(mean + mean_neg, torch.ones_like(mean), rtol=0, atol=1e-12)
    torch.testing.assert_close(var, var_neg, rtol=1e-12, atol=0)
    mean.sum().backward()
    assert torch.isfinite(loc.grad).all() and torch.isfinite(scale.grad).all()
    # d E[sigmoid(Y)] / d loc = E[sigmoid'(Y)]: the piecewise-bilinear table is within O(step) of it
    h = 1e-4
    fd = (_logistic_normal_moments(loc.detach() + h, scale.detach())[0]
          - _logistic_normal_moments(loc.detach() - h, scale.detach())[0]) / (2 * h)
    torch.testing.assert_close(loc.grad, fd, rtol=0, atol=2e-3)


# ------------------------------------------------------------------------- per-draw moments

def test_conditional_moments_match_a_float64_loop():
    gen = torch.Generator().manual_seed(0)
    R, K, S = 3, 5, 7
    w = torch.rand(R, K, S, generator=gen, dtype=torch.float64) / S
    loc = torch.randn(R, S, 3, generator=gen, dtype=torch.float64) * 2
    scale = torch.rand(R, S, 3, generator=gen, dtype=torch.float64) + 0.1
    m, v = _logistic_normal_moments(loc, scale)
    t = torch.linspace(1, 2, S, dtype=torch.float64).expand(R, 1, S)
    stats = trajectory_statistics(w, m, t, 3.0, background=0.5, rgb_var=v)
    for r in range(R):
        cond_means, cond_vars = [], []
        for k in range(K):
            acc = sum(float(w[r, k, i]) for i in range(S))
            cond_means.append([sum(float(w[r, k, i] * m[r, i, c]) for i in range(S)) + (1 - acc) * 0.5
                               for c in range(3)])
            cond_vars.append([sum(float(w[r, k, i] ** 2 * v[r, i, c]) for i in range(S)) for c in range(3)])
        for c in range(3):
            col = [cm[c] for cm in cond_means]
            mu = sum(col) / K
            between = sum((x - mu) ** 2 for x in col) / K
            within = sum(cv[c] for cv in cond_vars) / K
            assert math.isclose(float(stats.colour_mean[r, c]), mu, rel_tol=1e-12)
            assert math.isclose(float(stats.colour_var[r, c]), between + within, rel_tol=1e-12)


def _box_params(dtype=torch.float64):
    field, rays = BoxField(dtype), box_rays(4, dtype)
    samples = sample_along_rays(rays, 24)
    with torch.no_grad():
        params = field(samples.positions, samples.directions)
    return params, samples


def test_matches_drawn_colours_in_the_large_k_limit():
    """Both estimators target the same colour mean and variance: Rao-Blackwell at K = 4096 against
    drawn colours at K = 40000, compared within their Monte-Carlo standard errors."""
    params, samples = _box_params()
    params.density_scale = params.density_scale * 40.0  # make the density draws matter
    st = RenderSettings(num_samples=24, background=(1.0, 1.0, 1.0), skip_empty_space=False)
    k_rb, k_mc = 4096, 40000
    rb = render_samples(params, samples, st, num_draws=k_rb, colour_estimator="rao_blackwell",
                        generator=torch.Generator().manual_seed(1)).stats
    mc = render_samples(params, samples, st, num_draws=k_mc, colour_estimator="draws",
                        generator=torch.Generator().manual_seed(2)).stats
    assert (rb.colour_noise_var_draws is not None) and (mc.colour_noise_var_draws is None)
    between = rb.colour_var - rb.colour_noise_var_draws.mean(1)
    assert float(between.max()) > 1e-3  # the density draws do move the colour
    se_mean = (between / k_rb + mc.colour_var / k_mc).sqrt()
    assert ((rb.colour_mean - mc.colour_mean).abs() <= 5 * se_mean + 1e-9).all()
    # variance estimators: relative standard error ~ sqrt(2 / K) for near-Gaussian draws
    hit = mc.colour_var > 1e-4
    rel_se = math.sqrt(2 / k_rb + 2 / k_mc)
    ratio = rb.colour_var[hit] / mc.colour_var[hit]
    assert (ratio - 1).abs().max() < 6 * rel_se and abs(float(ratio.mean()) - 1) < 2 * rel_se
    # depth statistics come from the same density draws in both estimators
    torch.testing.assert_close(rb.depth_mean, mc.depth_mean, rtol=0, atol=2e-2)


@pytest.mark.parametrize("quadrature", ["alpha", "trapezoid"])
def test_deterministic_density_gives_the_exact_colour_variance_at_any_k(quadrature):
    """With (nearly) fixed densities every draw has the same weights: the estimator is exact,
    colour_var = sum_i w_i^2 Var[r_i], while drawn colours only approach it (either quadrature:
    alpha compositing folds the interval lengths into the density draws, the trapezoid does not)."""
    params, samples = _box_params()
    params.density_scale = torch.full_like(params.density_scale, 1e-12)
    st = RenderSettings(num_samples=24, skip_empty_space=False, quadrature=quadrature)
    stats = render_samples(params, samples, st, num_draws=2, colour_estimator="rao_blackwell").stats
    w = render_samples(params, samples, st, num_draws=1, deterministic=True).extras["weights"][:, 0]
    m, v = _logistic_normal_moments(params.rgb_loc, params.rgb_scale)
    torch.testing.assert_close(stats.colour_mean, (w[..., None] * m).sum(1), rtol=0, atol=2e-5)
    torch.testing.assert_close(stats.colour_var, (w[..., None] ** 2 * v).sum(1), rtol=5e-3, atol=1e-9)


@pytest.mark.parametrize("shared", [False, True])
def test_packed_and_dense_agree(shared):
    params, samples = _box_params()
    st = RenderSettings(num_samples=24, shared_noise=shared, background=(1.0, 1.0, 1.0),
                        colour_estimator="rao_blackwell")
    packed = pack_samples(samples, torch.ones_like(samples.t_starts, dtype=torch.bool))
    K, (R, S) = 6, samples.t_starts.shape
    gen = torch.Generator().manual_seed(5)
    if shared:
        dense = render_samples(params, samples, st, num_draws=K, generator=torch.Generator().manual_seed(5)).stats
        pk = render_samples_packed(params.reshape(-1), packed, st, num_draws=K,
                                   generator=torch.Generator().manual_seed(5)).stats
    else:
        eps = torch.randn(R, K, S, generator=gen, dtype=torch.float64)
        dense = render_samples(params, samples, st, num_draws=K, noise=(eps, None)).stats
        pk = render_samples_packed(params.reshape(-1), packed, st, num_draws=K,
                                   noise=(eps.permute(1, 0, 2).reshape(K, -1), None)).stats
    for name in ("colour_mean", "colour_var", "colour_noise_var_draws", "depth_mean", "depth_var_total"):
        torch.testing.assert_close(getattr(pk, name), getattr(dense, name), rtol=1e-10, atol=1e-12)


def test_blocks_and_given_moments_change_nothing(monkeypatch):
    from stochastic_fields import renderer

    params, samples = _box_params()
    st = RenderSettings(num_samples=24, colour_estimator="rao_blackwell")
    R, S = samples.t_starts.shape
    eps = torch.randn(R, 8, S, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    one = render_samples(params, samples, st, num_draws=8, noise=(eps, None)).stats
    monkeypatch.setattr(renderer, "DRAW_BLOCK_ELEMENTS", R * S * 3)  # blocks of 3, 3, 2 draws
    blocked = render_samples(params, samples, st, num_draws=8, noise=(eps, None),
                             colour_moments=colour_moments(params, st)).stats
    torch.testing.assert_close(blocked.colour_var, one.colour_var, rtol=1e-12, atol=0)
    torch.testing.assert_close(blocked.colour_noise_var_draws, one.colour_noise_var_draws, rtol=1e-12, atol=0)


def test_bad_estimator_and_mixed_concatenation_raise():
    params, samples = _box_params()
    with pytest.raises(ValueError, match="colour_estimator"):
        render_samples(params, samples, RenderSettings(num_samples=24), num_draws=2, colour_estimator="exact")
    rb = render_samples(params, samples, RenderSettings(num_samples=24), num_draws=2, colour_estimator="rao_blackwell")
    dr = render_samples(params, samples, RenderSettings(num_samples=24), num_draws=2, colour_estimator="draws")
    with pytest.raises(ValueError, match="Rao-Blackwellised"):
        concatenate_draws([rb.stats, dr.stats])
    assert colour_moments(params, RenderSettings(colour_estimator="draws")) is None
    assert colour_moments(params, RenderSettings()) is not None  # the default since study 7


def test_adaptive_k_stops_at_the_first_batch_when_only_colours_are_random():
    """Fixed densities: the conditional means do not vary over draws, so the first batch is exact
    (drawn colours would keep drawing: their variance over draws is far above the floor)."""
    field, rays = BoxField(), box_rays(4)

    class FixedDensity(torch.nn.Module):
        def forward(self, x, d):
            p = field(x, d)
            return FieldParams(p.density_loc, torch.full_like(p.density_scale, 1e-12), p.rgb_loc, p.rgb_scale)

    with torch.no_grad():
        rb = RenderSettings(num_samples=24, colour_estimator="rao_blackwell", adaptive_batch_draws=4)
        _, k_rb, _ = render_rays_adaptive(FixedDensity(), rays, rb, max_draws=64, rtol=1e-3)
        dr = RenderSettings(num_samples=24, adaptive_batch_draws=4, colour_estimator="draws")
        _, k_dr, _ = render_rays_adaptive(FixedDensity(), rays, dr, max_draws=64, rtol=1e-3)
    assert k_rb == 4 and k_dr > 4


def test_less_monte_carlo_noise_than_drawn_colours_at_equal_k():
    """The point of the estimator: over 24 seeds at K = 16, its colour mean and variance scatter
    less than those from drawn colours (law of total variance: only the density noise is left)."""
    params, samples = _box_params()
    params.density_scale = params.density_scale * 40.0
    st = RenderSettings(num_samples=24, background=(1.0, 1.0, 1.0))

    def scatter(estimator):
        runs = [render_samples(params, samples, st, num_draws=16, colour_estimator=estimator,
                               generator=torch.Generator().manual_seed(seed)).stats for seed in range(24)]
        means = torch.stack([r.colour_mean for r in runs])
        variances = torch.stack([r.colour_var for r in runs])
        return means.var(0).mean(), variances.var(0).mean()

    rb_mean, rb_var = scatter("rao_blackwell")
    dr_mean, dr_var = scatter("draws")
    assert rb_mean < 0.5 * dr_mean and rb_var < 0.5 * dr_var
