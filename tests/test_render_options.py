"""Per-call render options and the one chunked render loop: options are validated once and never
change a model's settings, an explicit K means a fixed K, fixed-K baselines refuse another K,
every render reports the K it used, and the evaluation loop states that K (adaptive included)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from stochastic_fields.config import preset
from stochastic_fields.data import load_dataset
from stochastic_fields.evaluation import evaluate
from stochastic_fields.models.registry import build_model
from stochastic_fields.renderer import (MAP_NAMES, ChunkRender, RenderOptions, RenderSettings, render_chunked,
                                        seeded_chunks)
from stochastic_fields.trainer import Trainer
from stochastic_fields.validation import ConfigError
from stochastic_fields.volume_rendering import statistics_from_draws


def _config(method: str = "snerf"):
    cfg = preset("tiny")
    cfg.method = method
    cfg.train.iterations = 12
    cfg.train.rays_per_batch = 64
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    cfg.render.num_samples = 16
    cfg.render.num_draws = 4
    cfg.render.chunk_rays = 7  # several chunks per patch, the last one short
    cfg.field.grid_max_cells = 16 ** 3
    cfg.field.grid_levels = 2
    return cfg


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    return load_dataset(tiny_scene)


@pytest.fixture(scope="module")
def snerf(dataset, tmp_path_factory):
    return Trainer(_config(), tmp_path_factory.mktemp("snerf"), dataset).train(progress=False).eval()


def _patch(dataset):
    return dataset.rays(dataset.test_indices[0])[8:13, 10:16]  # [5, 6]


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------------------ options
def test_options_are_validated_with_the_settings_ranges():
    with pytest.raises(ConfigError, match="num_draws"):
        RenderOptions(num_draws=0)
    with pytest.raises(ConfigError, match="quadrature"):
        RenderOptions(quadrature="simpson")
    with pytest.raises(ConfigError, match="keep_draws"):
        RenderOptions(keep_draws="yes")
    with pytest.raises(ValueError, match="unknown render option.*num_samples"):
        RenderOptions().with_changes(num_samples=8)  # fixed at training, not a per-call choice


def test_an_explicit_k_is_a_fixed_k():
    adaptive = RenderSettings(adaptive_draws=True, num_draws=6)
    assert RenderOptions.from_settings(adaptive).adaptive_draws is True
    fixed = RenderOptions.from_settings(adaptive, num_draws=12)
    assert (fixed.adaptive_draws, fixed.num_draws) == (False, 12)
    both = RenderOptions.from_settings(adaptive, num_draws=12, adaptive_draws=True)
    assert both.adaptive_draws is True
    assert RenderOptions.from_settings(adaptive, num_draws=None).adaptive_draws is True  # None: nothing asked


def test_rendering_never_changes_the_models_settings(snerf, dataset):
    before = dataclasses.asdict(snerf.render_settings)
    for changes in ({"quadrature": "trapezoid"}, {"colour_estimator": "rao_blackwell"}, {"num_draws": 3},
                    {"adaptive_draws": True, "adaptive_max_draws": 8}, {"chunk_rays": 3, "keep_draws": True}):
        snerf.render_view(_patch(dataset), snerf.render_options(**changes), generator=_gen())
    assert dataclasses.asdict(snerf.render_settings) == before


def test_options_reach_the_render(snerf, dataset):
    rays = _patch(dataset)
    maps = snerf.render_view(rays, snerf.render_options(num_draws=3, keep_draws=True), generator=_gen())
    assert maps["depth_draws"].shape == (5, 6, 3) and (maps["num_draws"] == 3).all()
    # the trapezoid cannot skip empty space: every sample is evaluated; alpha skips some here
    trap = snerf.render_view(rays, snerf.render_options(quadrature="trapezoid"), generator=_gen())
    alpha = snerf.render_view(rays, snerf.render_options(), generator=_gen())
    assert (trap["field_evals_per_ray"] == 16).all()
    assert float(alpha["field_evals_per_ray"].mean()) < 16


# ------------------------------------------------------------------------------ the chunk loop
def test_render_chunked_gives_chunk_generators_and_pads_varying_k():
    from stochastic_fields.rays import RayBundle

    bundle = RayBundle(origins=torch.zeros(2, 5, 3), directions=torch.tensor([0.0, 0.0, 1.0]).expand(2, 5, 3),
                       near=torch.ones(2, 5), far=torch.full((2, 5), 3.0), z_scale=torch.ones(2, 5))
    seen = []

    def chunk(r, gen):
        seen.append((len(r), gen.initial_seed()))
        K = 2 if len(seen) == 1 else 3  # the first chunk has K = 2, the others 3 (as adaptive K would)
        draws = torch.rand(len(r), K, generator=gen)
        stats = statistics_from_draws(draws[..., None].expand(-1, -1, 3), draws, torch.zeros_like(draws),
                                      torch.ones_like(draws))
        return ChunkRender(stats, K, torch.full((len(r),), 7))

    maps = render_chunked(chunk, bundle, 4, generator=lambda i: torch.Generator().manual_seed(100 + i),
                          keep_draws=True)
    assert seen == [(4, 100), (4, 101), (2, 102)]
    assert maps["num_draws"].flatten().tolist() == [2.0] * 4 + [3.0] * 6
    assert torch.isnan(maps["depth_draws"].reshape(10, 3)[:4, 2]).all()  # padded beyond the chunk's K
    assert not torch.isnan(maps["depth_draws"].reshape(10, 3)[4:]).any()
    assert (maps["field_evals_per_ray"] == 7).all()
    assert set(MAP_NAMES) <= set(maps) and maps["colour_mean"].shape == (2, 5, 3)


# ------------------------------------------------------------------------------ baselines
@pytest.mark.parametrize("method, k", [("deterministic", 1), ("ensemble", 5), ("nerfw", 1)])
def test_fixed_k_baselines_refuse_another_k(method, k, dataset):
    model = build_model(_config(method), dataset).eval()
    assert model.default_render_options().num_draws == k
    assert model.render_options(num_draws=k).num_draws == k
    with pytest.raises(ValueError, match=f"renders {k} trajectory.*num_draws=8"):
        model.render_options(num_draws=8)
    with pytest.raises(ValueError, match="adaptive"):
        model.render_options(adaptive_draws=True)
    maps = model.render_view(_patch(dataset), generator=_gen())
    assert (maps["num_draws"] == k).all()


def test_mc_dropout_passes_are_a_render_option(dataset):
    model = build_model(_config("mc_dropout"), dataset).eval()
    assert model.default_render_options().num_draws == model.passes
    maps = model.render_view(_patch(dataset), model.render_options(num_draws=3, keep_draws=True), generator=_gen())
    assert maps["colour_draws"].shape[2] == 3 and (maps["num_draws"] == 3).all()


# ------------------------------------------------------------------------------ evaluation
@pytest.mark.slow
def test_evaluation_reports_the_k_it_rendered(snerf, dataset, tmp_path):
    views = list(dataset.test_indices)[:2]
    options = snerf.render_options(adaptive_draws=True, adaptive_batch_draws=2, adaptive_max_draws=8,
                                   adaptive_rtol=0.5)
    result = evaluate(snerf, dataset, tmp_path, views=views, options=options, product_views=0, progress=False)
    # the same renders by hand, each view's chunks seeded from (seed, view, chunk) as the loop seeds them
    ks = np.concatenate([snerf.render_view(dataset.rays(v), options, generator=seeded_chunks(0, v))["num_draws"]
                         .reshape(-1).numpy() for v in views])
    assert result["num_draws_min"] == int(ks.min()) and result["num_draws_max"] == int(ks.max())
    assert result["num_draws"] == (int(ks[0]) if ks.min() == ks.max() else pytest.approx(ks.mean()))
    assert 2 <= ks.min() <= ks.max() <= 8
    assert result["render_options"]["adaptive_draws"] is True
    fixed = evaluate(snerf, dataset, tmp_path / "k3", views=views, options=snerf.render_options(num_draws=3),
                     product_views=0, progress=False)
    assert (fixed["num_draws"], fixed["num_draws_min"], fixed["num_draws_max"]) == (3, 3, 3)
    assert fixed["summary"]["num_draws"]["mean"] == 3


def test_a_views_maps_do_not_depend_on_the_other_views(snerf, dataset, tmp_path):
    """Per-(view, chunk) seeds: a view scored alone or after others gets the same draws."""
    a, b = list(dataset.test_indices)[:2]
    both = evaluate(snerf, dataset, tmp_path / "both", views=[a, b], product_views=2, progress=False)
    alone = evaluate(snerf, dataset, tmp_path / "alone", views=[b], product_views=1, progress=False)
    for name, values in alone["per_view"].items():
        if name != "render_s":
            np.testing.assert_equal(values[0], both["per_view"][name][1], err_msg=name)
    with np.load(tmp_path / "both" / "views" / f"view_{b:03d}.npz") as x, \
            np.load(tmp_path / "alone" / "views" / f"view_{b:03d}.npz") as y:
        np.testing.assert_array_equal(x["depth_std"], y["depth_std"])


def test_options_default_to_the_settings_defaults():
    """RenderOptions mirrors RenderSettings' per-render fields: same defaults (same ranges by construction)."""
    from stochastic_fields.renderer import PER_RENDER_FIELDS, RENDER_CHECKS, RENDER_OPTION_CHECKS

    assert RenderOptions() == RenderOptions.from_settings(RenderSettings())
    assert {f.name for f in dataclasses.fields(RenderOptions)} == set(PER_RENDER_FIELDS) | {"keep_draws", "progress"}
    assert all(RENDER_OPTION_CHECKS[n] is RENDER_CHECKS[n] for n in PER_RENDER_FIELDS)


@pytest.mark.parametrize("method", ["snerf", "deterministic", "ensemble"])
def test_a_model_composites_the_scenes_background_unless_the_config_names_one(method, dataset):
    """render.background None: the scene's own (the tiny scene's transforms.json says white, the colour
    its photos show where rays miss), so an object capture trains against the background its photos
    have; a colour in the config wins; a scene without one (LLFF, COLMAP, RGB photos) stays black."""
    assert dataset.background == (1.0, 1.0, 1.0)
    cfg = _config(method)
    cfg.render.background = None
    assert build_model(cfg, dataset).render_settings.background == (1.0, 1.0, 1.0)
    assert cfg.render.background is None  # the config itself (config.json) is not changed
    cfg.render.background = (0.0, 0.0, 0.0)
    assert build_model(cfg, dataset).render_settings.background == (0.0, 0.0, 0.0)
    cfg.render.background = None
    assert build_model(cfg, dataclasses.replace(dataset, background=None)).render_settings.background is None
    # and it reaches the pixels: rays turned away from the scene (the cameras stand outside its region)
    # see nothing and render the background
    model = build_model(cfg, dataset).eval()
    patch = _patch(dataset)
    away = dataclasses.replace(patch, directions=-patch.directions)
    with torch.no_grad():
        miss = model.render_view(away, model.render_options(), generator=_gen())
    torch.testing.assert_close(miss["colour_mean"], torch.ones_like(miss["colour_mean"]), atol=1e-4, rtol=0)
    torch.testing.assert_close(miss["opacity"], torch.zeros_like(miss["opacity"]), atol=1e-4, rtol=0)
