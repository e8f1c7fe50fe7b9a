"""The termination mixture (``termination.py``) against closed forms, scipy and the renderer, and the
central-interval recalibration (``predictive.CentralCalibration``) against hand counts."""

from __future__ import annotations

import dataclasses
import math
import tempfile

import numpy as np
import pytest
import scipy.optimize
import scipy.stats
import torch

from stochastic_fields.config import preset, validate_experiment
from stochastic_fields.validation import ConfigError
from stochastic_fields.data import load_dataset
from stochastic_fields.data.synthetic import make_synthetic_scene
from stochastic_fields.cameras import generate_rays_for_view
from stochastic_fields.models.registry import build_model
from stochastic_fields.predictive import CentralCalibration
from stochastic_fields.rays import PackedRaySamples, RayBundle, RaySamples
from stochastic_fields.renderer import RayRender
from stochastic_fields.termination import (TerminationMixture, median_depth, render_termination, termination_mixture,
                                          with_depth_estimate)
from stochastic_fields.volume_rendering import render_weights, statistics_from_draws

#: Two slabs of constant density on one ray (ray distance): (start, end, density).
SLABS = ((1.0, 2.0, 0.7), (3.0, 3.5, 2.5))
FAR = 5.0


def _slab_cdf(t: float, slabs=SLABS) -> float:
    """Exact termination CDF of piecewise-constant density given termination:
    (1 - exp(-int_0^t a)) / (1 - exp(-int_0^far a)), 1 at far."""
    if t >= FAR:
        return 1.0
    tau = sum(a * min(max(t - s, 0.0), e - s) for s, e, a in slabs)
    return -math.expm1(-tau) / -math.expm1(-sum(a * (e - s) for s, e, a in slabs))


def _slab_ray(slabs=SLABS, n: int = 50) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Intervals on [0.5, 4.5] whose edges include the slabs' (n per unit), float64, and each
    interval's density."""
    edges = torch.unique(torch.cat([torch.linspace(0.5, 4.5, int(4 * n) + 1, dtype=torch.float64),
                                    torch.tensor([v for s, e, _ in slabs for v in (s, e)], dtype=torch.float64)]))
    starts, ends = edges[:-1], edges[1:]
    mids = 0.5 * (starts + ends)
    density = torch.zeros_like(mids)
    for s, e, a in slabs:
        density = torch.where((mids > s) & (mids < e), torch.full_like(mids, a), density)
    return starts, ends, density


def _mixture(densities: list[torch.Tensor], starts, ends, z_scale: float = 1.0) -> TerminationMixture:
    w = torch.stack([render_weights(d, starts, ends, "alpha") for d in densities])  # [K, S]
    return TerminationMixture(starts[None], ends[None], w[None], torch.tensor([FAR], dtype=torch.float64),
                              torch.tensor([z_scale], dtype=torch.float64))


def test_two_slabs_cdf_survival_and_quantiles_are_the_closed_form():
    starts, ends, density = _slab_ray()
    m = _mixture([density], starts, ends)
    t = torch.tensor([[0.2, 1.0, 1.3, 1.999, 2.5, 3.1, 3.25, 3.5, 4.9, 5.0, 6.0]], dtype=torch.float64)
    exact = torch.tensor([[_slab_cdf(float(x)) for x in t[0]]], dtype=torch.float64)
    assert torch.allclose(m.cdf(t), exact, atol=1e-12, rtol=0)
    assert torch.allclose(m.survival(t), 1 - exact, atol=1e-12, rtol=0)  # the expected transmittance
    levels = torch.tensor([0.01, 0.2, 0.5, 0.55, 0.85, 0.999], dtype=torch.float64)
    q = m.quantiles(levels)[0]
    for level, value in zip(levels.tolist(), q.tolist()):
        root = scipy.optimize.brentq(lambda x: _slab_cdf(x) - level, 0.5, 4.5, xtol=1e-14)
        assert value == pytest.approx(root, abs=1e-10)
    assert float(m.cdf(torch.tensor([4.9], dtype=torch.float64))) == pytest.approx(1.0, abs=1e-12)  # given termination


def test_a_mixture_of_trajectories_matches_its_average_cdf_and_scipy_quantiles():
    starts, ends, d1 = _slab_ray()
    near_slab = ((1.0, 2.0, 3.0),)
    d2 = torch.zeros_like(d1)
    mids = 0.5 * (starts + ends)
    d2 = torch.where((mids > 1.0) & (mids < 2.0), torch.full_like(mids, 3.0), d2)
    m = _mixture([d1, d2], starts, ends, z_scale=0.8)  # camera z = 0.8 x ray distance

    def F(z: float) -> float:
        t = z / 0.8
        return 0.5 * (_slab_cdf(t) + _slab_cdf(t, near_slab))

    z = torch.linspace(0.5, 3.9, 37, dtype=torch.float64)[None]
    assert torch.allclose(m.cdf(z), torch.tensor([[F(float(v)) for v in z[0]]], dtype=torch.float64), atol=1e-12)
    levels = np.array([0.05, 0.3, 0.5, 0.7, 0.9])
    q = m.quantiles(torch.from_numpy(levels))[0].numpy()
    roots = [scipy.optimize.brentq(lambda x: F(x) - p, 0.4, 3.9, xtol=1e-14) for p in levels]
    np.testing.assert_allclose(q, roots, atol=1e-10)
    # two modes: the 68% band of the mixture reaches both surfaces, each trajectory's alone does not
    assert F(1.6) > 0.5 and F(3.0 * 0.8) < 0.9


def test_packed_samples_with_skipped_intervals_give_the_dense_distribution():
    starts, ends, density = _slab_ray()
    dense_w = render_weights(density, starts, ends, "alpha")[None, None]  # [1, 1, S]
    rays = RayBundle(origins=torch.zeros(1, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]),
                     near=torch.tensor([0.5]), far=torch.tensor([FAR]), z_scale=torch.ones(1))
    dense = termination_mixture(RaySamples(rays, starts[None].float(), ends[None].float()), dense_w.float(), rays)
    keep = density > 0  # the empty intervals are skipped
    packed = PackedRaySamples(rays=rays, ray_indices=torch.zeros(int(keep.sum()), dtype=torch.long),
                              t_starts=starts[keep].float(), t_ends=ends[keep].float())
    pm = termination_mixture(packed, dense_w[0, :, keep].float(), rays)
    z = torch.linspace(0.3, 5.5, 53, dtype=torch.float64)[None]
    assert torch.allclose(pm.cdf(z), dense.cdf(z), atol=1e-6)
    lv = torch.tensor([0.1, 0.5, 0.8], dtype=torch.float64)
    assert torch.allclose(pm.quantiles(lv), dense.quantiles(lv), atol=1e-5)


def test_an_opaque_interval_and_an_empty_ray():
    starts = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    ends = torch.tensor([2.0, 3.0, 4.0], dtype=torch.float64)
    w = torch.tensor([[[0.0, 1.0, 0.0]], [[0.0, 0.0, 0.0]]], dtype=torch.float64)  # [R=2, K=1, S]
    m = TerminationMixture(starts.expand(2, -1), ends.expand(2, -1), w, torch.full((2,), FAR, dtype=torch.float64),
                           torch.ones(2, dtype=torch.float64))
    F = m.cdf(torch.tensor([[2.0, 2.0 + 1e-9, 4.9], [2.0, 2.5, 4.9]], dtype=torch.float64))
    assert F.tolist() == [[0.0, 1.0, 1.0], [0.0, 0.0, 0.0]]  # an opaque surface stops every ray at its front
    q = m.quantiles(torch.tensor([0.5], dtype=torch.float64))
    assert float(q[0, 0]) == pytest.approx(2.0, abs=1e-12) and float(q[1, 0]) == FAR  # nothing hit: far
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        m.quantiles(torch.tensor([1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="weights"):
        TerminationMixture(starts[None], ends[None], w[0], torch.ones(1), torch.ones(1))


def _tiny_config():
    """The tiny preset on a 16-sample grid of two levels, on the CPU."""
    cfg = preset("tiny")
    cfg.train.device, cfg.render.num_samples = "cpu", 16
    cfg.field.grid_max_cells, cfg.field.grid_levels = 16 ** 3, 2
    return cfg


def _untrained_model(cfg, tmp: str):
    """(dataset, an untrained model of ``cfg``) on a 16 x 12 synthetic scene of six views in ``tmp``."""
    dataset = load_dataset(make_synthetic_scene(tmp, num_views=6, width=16, height=12, seed=0))
    return dataset, build_model(cfg, dataset).eval()


def test_render_termination_holds_the_renders_draws():
    cfg = _tiny_config()
    with tempfile.TemporaryDirectory() as tmp:
        dataset, model = _untrained_model(cfg, tmp)
        rays = generate_rays_for_view(dataset.cameras, 0, float(dataset.near[0]), float(dataset.far[0])).reshape(-1)
        options = model.render_options(num_draws=4, chunk_rays=50)
        stats, m = render_termination(model, rays, options, generator=torch.Generator().manual_seed(0))
    assert m.num_rays == len(rays) == stats["depth_mean"].shape[0] and m.weights.shape[1] == 4
    # the weights are the render's (their mass is its opacity); the CDF is 0 before near, and just
    # before far it is the share of trajectories that hit something (the others sit at far)
    torch.testing.assert_close(m.weights.sum(-1).mean(-1), stats["opacity"], atol=1e-5, rtol=0)
    hit = (m.weights.sum(-1) >= 1e-6).double().mean(-1)
    torch.testing.assert_close(m.cdf(m.far * m.z_scale * (1 - 1e-9)), hit, atol=1e-6, rtol=0)
    near_z = rays.near.double() * rays.z_scale.double() * 0.99
    assert float(m.cdf(near_z).abs().max()) == 0.0
    assert bool((m.cdf(m.far * m.z_scale) == 1).all())
    # the mixture's mean (exact inside each interval) is the rendered depth mean up to the sample spacing
    levels = torch.linspace(0.0005, 0.9995, 1000, dtype=torch.float64)
    mean = m.quantiles(levels).mean(1)
    spacing = ((m.t_ends - m.t_starts).max(1).values * m.z_scale)
    assert bool(((mean - stats["depth_mean"]).abs() <= spacing + 1e-3).all())


def test_central_calibration_by_hand_and_its_gaussian_case():
    u = np.array([0.5, 0.6, 0.9, 0.1, 0.75] * 20)  # scores |2u - 1|: 0, 0.2, 0.8, 0.8, 0.5
    cal = CentralCalibration.fit(u, levels=np.array([0.0, 0.5, 0.9]))
    # conformal ranks ceil(101 p) of 100 sorted scores (20 each of 0, 0.2, 0.5, 0.8, 0.8)
    assert cal.raw_levels.tolist() == pytest.approx([0.0, 0.5, 0.8])
    assert cal.quantile_levels(np.array([0.25, 0.75, 0.5])).tolist() == pytest.approx([0.25, 0.75, 0.5])
    # a Gaussian whose errors are twice its std: the raw central level of nominal p is 2 Phi(2 z_p) - 1
    rng = np.random.default_rng(0)
    err = 2.0 * rng.standard_normal(200_000)
    cal = CentralCalibration.fit(scipy.stats.norm.cdf(err))
    for p in (0.5, 0.683, 0.9, 0.95):
        t = cal.quantile_levels(np.array([(1 + p) / 2]))[0]
        assert scipy.stats.norm.ppf(t) == pytest.approx(2.0 * scipy.stats.norm.ppf((1 + p) / 2), rel=0.02)
    # held-out coverage of the recalibrated band is the nominal level
    test = 2.0 * rng.standard_normal(100_000)
    hi = scipy.stats.norm.ppf(cal.quantile_levels(np.array([0.975]))[0])
    assert np.mean(np.abs(test) <= hi) == pytest.approx(0.95, abs=0.005)
    with pytest.raises(ValueError, match="at least"):
        CentralCalibration.fit(np.array([0.5] * 3))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        CentralCalibration.fit(np.array([1.5] * 60))


def test_termination_study_rule_by_hand(load_script):
    study = load_script("benchmarks/studies/termination_study.py")
    levels = ("50", "68", "90", "95")

    def row(cov, width, is95, rho=0.8):
        return {**{f"coverage_{n}": c for n, c in zip(levels, cov)}, "halfwidth_median_95": width,
                "interval_score_95": is95, "spearman_mean": rho}

    honest = (0.5, 0.683, 0.9, 0.95)
    runs = {"capture/fern": {"today": row(honest, 0.20, 1.0), "termination + central map": row(honest, 0.12, 0.8),
                             "termination + PIT map": row((0.40, 0.6, 0.9, 0.95), 0.10, 0.7)},
            "synthetic": {"today": row(honest, 0.04, 0.2), "termination + central map": row(honest, 0.04, 0.2),
                          "termination + PIT map": row(honest, 0.04, 0.2, rho=0.7)}}
    decision = study.decide(runs)
    # central: gains capture fern's width check, loses nothing, IS falls -> taken; PIT loses checks
    assert decision.startswith("taken: termination + central map")
    assert "capture/fern: coverage 50" in decision and "synthetic: depth Spearman" in decision
    runs["capture/fern"]["termination + central map"]["interval_score_95"] = 1.1  # now its IS rises
    assert study.decide(runs).startswith("today's stays")


def test_study_22c_judges_only_the_interpolated_bounds(load_script):
    study = load_script("benchmarks/studies/free_space_floor_study.py")
    levels = ("50", "68", "90", "95")

    def row(cov, width, is95):
        return {**{f"coverage_{n}": c for n, c in zip(levels, cov)}, "halfwidth_median_95": width,
                "interval_score_95": is95, "spearman_mean": 0.7}

    honest, wide = (0.5, 0.683, 0.9, 0.95), (0.8, 0.9, 0.97, 0.99)
    runs = {"paper/flower": {study.TODAY: row(wide, 1.5, 4.0), "checked (sigma, e, rho)": row(honest, 0.2, 1.0),
                             study.CANDIDATE_22C: row(honest, 0.3, 1.5)},
            "synthetic": {study.TODAY: row(honest, 0.04, 0.2), "checked (sigma, e, rho)": row(wide, 0.04, 0.2),
                          study.CANDIDATE_22C: row(honest, 0.04, 0.2)}}
    assert study.decide(runs, "22c").startswith(f"taken: {study.CANDIDATE_22C}")
    assert "checked" not in study.decide(runs, "22c")  # reported beside, never judged
    both = study.decide(runs, "22")  # study 22 judges both: the check loses the synthetic centre
    assert both.startswith(f"taken: {study.CANDIDATE_22C}") and "checked (sigma, e, rho): not taken" in both


def test_study_22d_check_weight_follows_the_errors(load_script):
    study = load_script("benchmarks/studies/free_space_floor_study.py")
    rng = np.random.default_rng(0)
    n = 4000
    sigma, depth = np.full(n, 1.0), np.full(n, 100.0)
    e = rng.exponential(3.0, n) * (rng.random(n) < 0.3)  # a violation at 30% of the points
    explained = np.abs(rng.normal(size=n)) * np.hypot(sigma, e)  # errors as large as e says
    assert study.fit_check_weight(explained, sigma, e, depth) == pytest.approx(1.0)
    unrelated = np.abs(rng.normal(size=n)) * sigma  # e (now large) says nothing about these errors
    assert study.fit_check_weight(unrelated, sigma, 30.0 * e, depth) == 0.0


def test_study_22e_reads_seed_means_and_guards_single_seeds(load_script):
    """Study 22e's rule by hand: a candidate that misses paper fern's 90% level on one seed by under a
    point but holds it on the mean over seeds is taken; the same candidate with one seed's level 12
    points off nominal is stopped by the guard; 22f judges against the weighted map."""
    study = load_script("benchmarks/studies/free_space_floor_study.py")
    levels = ("50", "68", "90", "95", "99")

    def row(cov, width=0.1, is95=1.0, spearman=0.7):
        return {**{f"coverage_{n}": c for n, c in zip(levels, (*cov, 0.99))}, "halfwidth_median_95": width,
                "interval_score_95": is95, "spearman_mean": spearman}

    honest, wide = (0.5, 0.683, 0.9, 0.95), (0.8, 0.9, 0.97, 0.99)
    runs = {}
    for seed, fern90 in ((2, 0.846), (3, 0.872), (4, 0.857)):  # the candidate's paper fern 90% per seed
        runs[f"seed{seed}/paper/fern"] = {study.TODAY: row((0.5, 0.683, 0.86, 0.95), 0.2, 1.5),
                                         study.WEIGHTED: row((0.5, 0.683, fern90, 0.95), 0.2, 1.4)}
        runs[f"seed{seed}/paper/flower"] = {study.TODAY: row(wide, 1.0, 3.0), study.WEIGHTED: row(honest, 0.2, 1.4)}
        runs[f"seed{seed}/synthetic"] = {study.TODAY: row(honest, 0.04, 0.2), study.WEIGHTED: row(honest, 0.04, 0.2)}
    assert study.run_type("seed2/paper/fern") == "paper/fern" and study.run_type("synthetic") == "synthetic"
    means = study.seed_means(runs, (study.TODAY, study.WEIGHTED))
    assert means["paper/fern"][study.WEIGHTED]["coverage_90"] == pytest.approx((0.846 + 0.872 + 0.857) / 3)
    assert study.decide(runs, "22d").startswith("today's stays")  # one seed at a time: 84.6% loses the level
    assert study.decide(runs, "22e").startswith("taken: " + study.WEIGHTED)
    runs["seed3/synthetic"][study.WEIGHTED] = row((0.5, 0.563, 0.9, 0.95), 0.04, 0.2)  # 12 points under at 68%
    runs["seed2/synthetic"][study.WEIGHTED] = row((0.5, 0.773, 0.9, 0.95), 0.04, 0.2)  # 9 over: the mean holds
    verdict = study.decide(runs, "22e")
    assert verdict.startswith("today's stays (the guard: seed3/synthetic: coverage 68 56.3%)")
    for r in runs.values():  # 22f: the weighted map is today's; a copy of it gains nothing
        r[study.INTERP_WEIGHTED] = dict(r[study.WEIGHTED])
    assert "gains no check" in study.decide(runs, "22f")


def test_median_depth_is_the_mixtures_half_quantile_in_ray_distance():
    starts, ends, d1 = _slab_ray()
    mids = 0.5 * (starts + ends)
    d2 = torch.where((mids > 1.0) & (mids < 2.0), torch.full_like(mids, 3.0), torch.zeros_like(mids))
    w = torch.stack([render_weights(d, starts, ends, "alpha") for d in (d1, d2)])  # [K, S]
    rays = RayBundle(origins=torch.zeros(1, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]),
                     near=torch.tensor([0.5]), far=torch.tensor([FAR]), z_scale=torch.tensor([0.8]))
    samples = RaySamples(rays, starts[None], ends[None])
    near_slab = ((1.0, 2.0, 3.0),)
    root = scipy.optimize.brentq(lambda t: 0.5 * (_slab_cdf(t) + _slab_cdf(t, near_slab)) - 0.5, 0.5, 4.5, xtol=1e-14)
    median = median_depth(samples, w[None], rays)  # ray distance, not camera z
    assert median.dtype == torch.float64 and float(median[0]) == pytest.approx(root, abs=1e-10)
    # a render's stats take it as the depth map ("median"), or keep the mean ("mean")
    stats = statistics_from_draws(torch.zeros(1, 2, 3), (w * mids).sum(-1)[None] / w.sum(-1)[None],
                                  torch.zeros(1, 2), w.sum(-1)[None])
    out = RayRender(stats=stats, params=None, samples=samples, extras={"weights": w[None]})
    assert with_depth_estimate(out, rays, "mean") is out
    moved = with_depth_estimate(out, rays, "median")
    assert float(moved.stats.depth_mean[0]) == pytest.approx(root, abs=1e-10)
    assert torch.equal(moved.stats.depth_var_total, stats.depth_var_total)  # the spread stays about the mean
    with pytest.raises(ValueError, match="'mean' or 'median'"):
        with_depth_estimate(out, rays, "mode")


def test_the_median_option_reaches_every_render_and_refuses_adaptive_draws():
    cfg = _tiny_config()
    with tempfile.TemporaryDirectory() as tmp:
        dataset, model = _untrained_model(cfg, tmp)
        rays = generate_rays_for_view(dataset.cameras, 0, float(dataset.near[0]), float(dataset.far[0]))
        options = model.render_options(num_draws=4, chunk_rays=50)
        mean_maps = model.render_view(rays, options, generator=torch.Generator().manual_seed(0))
        _, m = render_termination(model, rays.reshape(-1), options, generator=torch.Generator().manual_seed(0))
        model.render_settings = dataclasses.replace(model.render_settings, depth_estimate="median")
        maps = model.render_view(rays, options, generator=torch.Generator().manual_seed(0))
        half = m.quantiles(torch.tensor([0.5], dtype=torch.float64))[:, 0]  # camera z
        torch.testing.assert_close((maps["depth_mean"] * maps["z_scale"]).reshape(-1).double(), half,
                                   atol=1e-4, rtol=1e-5)
        torch.testing.assert_close(maps["depth_var_total"], mean_maps["depth_var_total"])
        assert not torch.allclose(maps["depth_mean"], mean_maps["depth_mean"])
        with pytest.raises(ValueError, match="fixed K"):
            model.render_view(rays, model.render_options(adaptive_draws=True))
    cfg.render.depth_estimate, cfg.render.adaptive_draws = "median", True
    with pytest.raises(ConfigError, match="render.depth_estimate"):
        validate_experiment(cfg)
