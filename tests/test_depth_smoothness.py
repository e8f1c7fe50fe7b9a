"""Unseen-view depth smoothness (stochastic_fields.depth_smoothness, virtual_views.PatchSampler, the
trainer's term): the expected normalised depth against closed forms and a float64 loop, the patch
loss by hand, gradcheck, hard densities, the patches' cameras and pixels, and the term each model and
the trainer add."""

from __future__ import annotations

import copy
import math

import pytest
from conftest import rays_along_z
import torch

from stochastic_fields.depth_smoothness import expected_normalised_depth, patch_smoothness
from stochastic_fields.losses import LossConfig
from stochastic_fields.samplers import sample_along_rays




def naive_depth(density, t0, t1, near, far, spacing):
    """sum_i w_i m_i + (1 - sum_i w_i) by a loop: alpha compositing, m the midpoint's normalised coordinate."""
    trans, total, mass = 1.0, 0.0, 0.0
    for d, a, b in zip(density.tolist(), t0.tolist(), t1.tolist()):
        alpha = 1.0 - math.exp(-d * (b - a))
        w = trans * alpha
        mid = 0.5 * (a + b)
        m = (mid - near) / (far - near) if spacing == "linear" else (1 / mid - 1 / near) / (1 / far - 1 / near)
        total += w * m
        mass += w
        trans *= 1.0 - alpha
    return total + (1.0 - mass)


@pytest.mark.parametrize("spacing", ["linear", "disparity"])
def test_expected_depth_matches_a_loop_over_samples(spacing):
    g = torch.Generator().manual_seed(0)
    rays = rays_along_z([0.5, 1.0, 2.0], [4.0, 100.0, 3.0])
    samples = sample_along_rays(rays, 24, spacing=spacing, stratified=True, generator=g)
    density = torch.rand(3, 24, generator=g, dtype=torch.float64) * 3
    got = expected_normalised_depth(density, samples, spacing)
    for r in range(3):
        ref = naive_depth(density[r], samples.t_starts[r], samples.t_ends[r], float(rays.near[r]),
                          float(rays.far[r]), spacing)
        assert got[r].item() == pytest.approx(ref, rel=1e-12)


def test_empty_ray_ends_at_the_far_bound_and_an_opaque_slab_at_its_sample():
    """Zero density: d = 1 (no division by a zero opacity). An opaque slab (1e6) on the 3rd of 4 linear
    samples on [0, 4]: all the weight there, d = its midpoint's coordinate 2.5 / 4; a huge density stays finite."""
    rays = rays_along_z([0.0 + 1e-9, 0.0 + 1e-9], [4.0, 4.0])
    samples = sample_along_rays(rays, 4, spacing="linear")
    density = torch.zeros(2, 4, dtype=torch.float64)
    density[1, 2] = 1e6
    d = expected_normalised_depth(density, samples, "linear")
    assert d[0].item() == pytest.approx(1.0, abs=1e-12)
    assert d[1].item() == pytest.approx(2.5 / 4.0, abs=1e-6)
    density[1, 2] = 1e30
    assert torch.isfinite(expected_normalised_depth(density, samples, "linear")).all()


def test_uniform_density_has_the_closed_form_depth():
    """Constant density s on [0, L], linear spacing, many samples: E[t] / L with the far remainder,
    d = (1 - exp(-sL)) / (sL) in the limit of fine samples (integral of exp(-st) s t / L plus exp(-sL))."""
    s, L = 0.7, 3.0
    rays = rays_along_z([1e-12], [L])
    samples = sample_along_rays(rays, 20000, spacing="linear")
    d = expected_normalised_depth(torch.full((1, 20000), s, dtype=torch.float64), samples, "linear")
    assert d.item() == pytest.approx((1.0 - math.exp(-s * L)) / (s * L), rel=1e-4)


def test_patch_smoothness_by_hand():
    """A 2x3 patch [[0, 1, 3], [2, 2, 2]]: the pixels with a right and a lower neighbour are (0,0) and
    (0,1): (0-1)^2 + (0-2)^2 = 5 and (1-3)^2 + (1-2)^2 = 5, mean 5; a constant patch: 0."""
    depth = torch.tensor([[[0.0, 1.0, 3.0], [2.0, 2.0, 2.0]]], dtype=torch.float64)
    assert patch_smoothness(depth).item() == pytest.approx(5.0)
    assert patch_smoothness(torch.full((3, 4, 4), 0.3)).item() == 0.0
    with pytest.raises(ValueError, match="h, w >= 2"):
        patch_smoothness(torch.zeros(2, 1, 4))


def test_gradcheck_through_depth_and_patch():
    g = torch.Generator().manual_seed(1)
    rays = rays_along_z([1.0] * 4, [5.0] * 4)
    samples = sample_along_rays(rays, 6, spacing="disparity", stratified=True, generator=g)
    density = (torch.rand(4, 6, generator=g, dtype=torch.float64) * 2).requires_grad_(True)

    def f(x):
        return patch_smoothness(expected_normalised_depth(x, samples, "disparity").reshape(1, 2, 2))

    assert torch.autograd.gradcheck(f, (density,))


def test_loss_config_rejects_bad_values():
    with pytest.raises(ValueError, match="lambda_smoothness"):
        LossConfig(lambda_smoothness=-1.0)
    with pytest.raises(ValueError, match="smoothness_patch_size"):
        LossConfig(smoothness_patch_size=1)
    with pytest.raises(ValueError, match="smoothness_patches"):
        LossConfig(smoothness_patches=0)


def test_patches_lie_in_the_image_through_virtual_cameras(tiny_scene):
    """Every patch: size x size rays one pixel apart (re-projected through its camera), inside the image,
    from a camera of the pool (between two training views); the same generator state gives the same
    patches."""
    from stochastic_fields.cameras import camera_centres, project_points, select_cameras
    from stochastic_fields.data import load_dataset
    from stochastic_fields.virtual_views import PATCH_FRACTIONS, PatchSampler

    ds = load_dataset(tiny_scene, split_every=5)
    sampler = PatchSampler.for_dataset(ds)
    assert sampler.num_cameras % len(PATCH_FRACTIONS) == 0 and sampler.num_cameras > 0
    patches = sampler.sample(5, 4, torch.Generator().manual_seed(3))
    assert patches.shape == (5, 4, 4)
    again = sampler.sample(5, 4, torch.Generator().manual_seed(3))
    torch.testing.assert_close(again.origins, patches.origins)
    torch.testing.assert_close(again.directions, patches.directions)
    pool = camera_centres(sampler.cameras)
    for p in range(5):
        centre = patches.origins[p, 0, 0]
        k = int((pool - centre).norm(dim=1).argmin())
        assert float((pool[k] - centre).norm()) < 1e-5
        cam = select_cameras(sampler.cameras, [k])
        pts = (patches.origins[p] + patches.directions[p] * 2.0).reshape(-1, 3)
        uv, z = project_points(cam, pts)
        uv = uv.reshape(4, 4, 2)
        assert (z > 0).all()
        torch.testing.assert_close(uv[:, 1:, 0] - uv[:, :-1, 0], torch.ones(4, 3), atol=1e-3, rtol=0)
        torch.testing.assert_close(uv[1:, :, 1] - uv[:-1, :, 1], torch.ones(3, 4), atol=1e-3, rtol=0)
        assert (uv[..., 0] >= 0).all() and (uv[..., 0] <= ds.width).all()
        assert (uv[..., 1] >= 0).all() and (uv[..., 1] <= ds.height).all()
    with pytest.raises(ValueError, match="does not fit"):
        sampler.sample(1, 1000, torch.Generator())


def test_one_training_view_has_no_patch_pool(tiny_scene):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.virtual_views import PatchSampler

    ds = load_dataset(tiny_scene, split_every=20)
    assert len(ds.train_indices) == 1
    assert PatchSampler.for_dataset(ds) is None


@pytest.mark.parametrize("method", ["snerf", "deterministic", "ensemble"])
def test_models_add_the_weighted_term(method, tiny_scene):
    """The term is lambda times the logged smoothness (summed over ensemble members); weight 0 or no
    patches leaves the loss as it is."""
    from test_baselines import tiny_config

    from stochastic_fields.data import load_dataset
    from stochastic_fields.models.registry import build_model
    from stochastic_fields.virtual_views import PatchSampler

    dataset = load_dataset(tiny_scene)
    cfg = copy.deepcopy(tiny_config(method))
    cfg.loss.lambda_smoothness = 2.0
    torch.manual_seed(0)
    model = build_model(cfg, dataset)
    patches = PatchSampler.for_dataset(dataset).sample(3, 4, torch.Generator().manual_seed(0))
    base = torch.tensor(1.5, dtype=torch.float32)
    logs: dict = {}
    out = model.add_smoothness(base, logs, patches, generator=torch.Generator().manual_seed(1))
    members = len(model.members) if method == "ensemble" else 1
    assert logs["smoothness"] > 0
    torch.testing.assert_close(out, base + 2.0 * members * logs["smoothness"], rtol=1e-5, atol=1e-6)
    assert model.add_smoothness(base, {}, None) is base
    cfg0 = copy.deepcopy(cfg)
    cfg0.loss.lambda_smoothness = 0.0
    off = build_model(cfg0, dataset)
    assert off.add_smoothness(base, {}, patches) is base


def test_snerf_reads_the_expected_density(tiny_scene):
    """S-NeRF's term equals the one computed by hand from the field's (loc, scale) through the rectified
    normal's mean, with the same stratified samples."""
    from test_baselines import tiny_config

    from stochastic_fields.data import load_dataset
    from stochastic_fields.models.registry import build_model
    from stochastic_fields.occlusion import expected_density
    from stochastic_fields.virtual_views import PatchSampler

    dataset = load_dataset(tiny_scene)
    cfg = copy.deepcopy(tiny_config("snerf"))
    cfg.loss.lambda_smoothness = 1.0
    torch.manual_seed(0)
    model = build_model(cfg, dataset)
    patches = PatchSampler.for_dataset(dataset).sample(2, 3, torch.Generator().manual_seed(0))
    logs: dict = {}
    model.add_smoothness(torch.tensor(0.0), logs, patches, generator=torch.Generator().manual_seed(4))
    s = model.render_settings
    samples = sample_along_rays(patches.reshape(-1), s.num_samples, spacing=s.spacing, stratified=True,
                                generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        loc, scale = model.field.density_params(samples.positions)
        depth = expected_normalised_depth(expected_density(loc, scale), samples, s.spacing, s.quadrature)
    assert logs["smoothness"] == pytest.approx(patch_smoothness(depth.reshape(2, 3, 3)).item(), rel=1e-5)


def test_trainer_adds_the_term_and_leaves_the_batches_alone(tiny_scene, tmp_path):
    """With the term on, the trainer logs it, and the colour batches are the ones drawn without it (the
    patches have their own generators, seeded by the step: the same at every call for a step)."""
    from test_baselines import tiny_config

    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    dataset = load_dataset(tiny_scene)
    cfg = copy.deepcopy(tiny_config("snerf"))
    cfg.train.iterations = 10  # the log keeps every 10th step
    cfg.train.checkpoint_every = 0
    cfg.train.eval_every = 0
    cfg.loss.lambda_smoothness = 1.0
    on = Trainer(cfg, tmp_path / "on", dataset)
    a, b = on.smoothness_generators(), on.smoothness_generators()
    assert torch.equal(torch.rand(3, generator=a[0]), torch.rand(3, generator=b[0]))
    on.train(progress=False)
    cfg_off = copy.deepcopy(cfg)
    cfg_off.loss.lambda_smoothness = 0.0
    off = Trainer(cfg_off, tmp_path / "off", dataset)
    off.train(progress=False)
    assert torch.equal(on.generator.get_state(), off.generator.get_state())
    import json
    on_log = [json.loads(line) for line in (tmp_path / "on" / "train_log.jsonl").read_text().splitlines()]
    off_log = [json.loads(line) for line in (tmp_path / "off" / "train_log.jsonl").read_text().splitlines()]
    assert on_log and all(r["smoothness"] > 0 for r in on_log)
    assert off_log and all("smoothness" not in r for r in off_log)
