"""Empty-space skipping: packed (ragged) and dense layouts give the same colours, depths,
variances and gradients, at the renderer level and through the S-NeRF model (every cell
occupied; and after an occupancy update where the skipped samples carry zero weight)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from stochastic_fields.constants import PACK_MIN_SKIPPED_FRACTION
from stochastic_fields.fields.base import FieldParams, StochasticField
from stochastic_fields.losses import LossConfig
from stochastic_fields.models.snerf import SNeRF
from stochastic_fields.rays import RayBundle
from stochastic_fields import renderer
from stochastic_fields.renderer import (MAP_NAMES, RenderSettings, pack_samples, render_rays, render_samples,
                                        render_samples_packed)
from stochastic_fields.samplers import sample_along_rays
from stochastic_fields.scene_region import SceneRegion

STAT_NAMES = ("colour_mean", "colour_var", "depth_mean", "depth_var_epistemic", "depth_var_spread",
              "depth_var_total", "opacity", "colour_draws", "depth_draws")
HALF_WIDTH = 0.4  # the dense box of the test field, in world = unit coordinates


class BoxField(StochasticField):
    """Known field with learnable parameters: dense inside the box |x|_inf < 0.4, exactly empty outside.

    density_loc = gain * 40 (0.4 - |x|_inf) (+ a learnable offset), density_scale = 0.05 * gain,
    colour logits from a linear map of (x, d). Outside ~|x|_inf > 0.45 every draw within 1e3
    standard deviations is exactly zero density (relu), so skipping there is exact.
    """

    def __init__(self, dtype=torch.float64):
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.gain = nn.Parameter(torch.tensor(1.0, dtype=dtype))
        self.colour = nn.Linear(6, 6, dtype=dtype)
        with torch.no_grad():
            self.colour.weight.copy_(torch.randn(6, 6, generator=gen, dtype=dtype))
        self.register_buffer("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=dtype))

    def forward(self, positions, directions):
        h = HALF_WIDTH - positions.abs().amax(dim=-1)
        col = self.colour(torch.cat([positions, directions], dim=-1))
        return FieldParams(density_loc=self.gain * 40.0 * h, density_scale=0.05 * self.gain.expand_as(h),
                           rgb_loc=col[..., :3], rgb_scale=nn.functional.softplus(col[..., 3:]))


def box_rays(n_side: int = 6, dtype=torch.float64) -> RayBundle:
    """Rays from (0, 0, -3) through [-0.5, 0.5]^2 on z = 0, near/far keeping them inside [-1, 1]^3."""
    s = torch.linspace(-0.5, 0.5, n_side, dtype=dtype)
    targets = torch.stack(torch.meshgrid(s, s, indexing="ij") + (torch.zeros(n_side, n_side, dtype=dtype),), -1)
    targets = targets.reshape(-1, 3)
    origins = torch.tensor([0.0, 0.0, -3.0], dtype=dtype).expand_as(targets).clone()
    d = targets - origins
    d = d / d.norm(dim=-1, keepdim=True)
    n = len(d)
    return RayBundle(origins, d, torch.full((n,), 2.2, dtype=dtype), torch.full((n,), 3.8, dtype=dtype),
                     torch.ones(n, dtype=dtype))


def settings(**kw) -> RenderSettings:
    base = dict(num_samples=24, num_draws=4, background=(1.0, 1.0, 1.0), shared_noise=True, skip_empty_space=True,
                occupancy_resolution=8)
    base.update(kw)
    return RenderSettings(**base)


def grads(module: nn.Module) -> list[torch.Tensor]:
    return [p.grad.clone() for p in module.parameters() if p.grad is not None]


# ------------------------------------------------------------------------- renderer level


def box_scene(shared: bool):
    """(field, settings, dense samples [R, S], the same samples packed with every one kept, noise generator)."""
    st = settings(shared_noise=shared)
    samples = sample_along_rays(box_rays(), st.num_samples, stratified=True, generator=torch.Generator().manual_seed(1))
    packed = pack_samples(samples, torch.ones(samples.t_starts.shape, dtype=torch.bool))
    return BoxField(), st, samples, packed, torch.Generator().manual_seed(2)


@pytest.mark.parametrize("shared", [True, False])
def test_packed_equals_dense_with_every_sample_kept(shared):
    field, st, samples, packed, gen = box_scene(shared)
    R, S, K = *samples.t_starts.shape, 5
    eps_a = torch.randn(R, K, 1 if shared else S, generator=gen, dtype=torch.float64)
    eps_c = torch.randn(R, K, 1 if shared else S, 3, generator=gen, dtype=torch.float64)
    si = torch.arange(len(packed.ray_indices)) % S
    pa = eps_a[packed.ray_indices, :, 0 if shared else si].T if shared else eps_a[packed.ray_indices, :, si].T
    pc = (eps_c[packed.ray_indices, :, 0] if shared else eps_c[packed.ray_indices, :, si]).transpose(0, 1)

    dense = render_samples(field(samples.positions, samples.directions), samples, st, num_draws=K,
                           noise=(eps_a, eps_c)).stats
    loss_d = dense.colour_mean.sum() + dense.depth_mean.sum() + dense.colour_var.sum() + dense.depth_var_total.sum()
    loss_d.backward()
    g_dense = grads(field)
    field.zero_grad()
    pk = render_samples_packed(field(packed.positions, packed.directions), packed, st, num_draws=K,
                               noise=(pa, pc)).stats
    loss_p = pk.colour_mean.sum() + pk.depth_mean.sum() + pk.colour_var.sum() + pk.depth_var_total.sum()
    loss_p.backward()
    for name in STAT_NAMES:
        torch.testing.assert_close(getattr(pk, name), getattr(dense, name), rtol=1e-10, atol=1e-12, msg=name)
    for a, b in zip(grads(field), g_dense):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    assert float(dense.opacity.detach().max()) > 0.5  # the box is hit: the comparison is not of empty rays


def test_batch_packs_only_when_enough_samples_are_skipped():
    field, rays, st = BoxField(), box_rays(), settings(shared_noise=False)
    R, S, K = len(rays), st.num_samples, st.num_draws
    plain = render_rays(field, rays, st, generator=torch.Generator().manual_seed(4))

    def keep_all_but(count):
        def occupied(x):
            keep = torch.ones(x.shape[:-1], dtype=torch.bool)
            keep.view(-1)[:count] = False
            return keep
        return occupied

    few = int(PACK_MIN_SKIPPED_FRACTION * R * S) - 1  # just under the fraction: stays dense
    dense = render_rays(field, rays, st, generator=torch.Generator().manual_seed(4), occupied=keep_all_but(few))
    assert dense.extras["weights"].shape == plain.extras["weights"].shape == (R, K, S)
    for name in STAT_NAMES:  # same layout, same draws: identical to rendering without an occupancy grid
        assert torch.equal(getattr(dense.stats, name), getattr(plain.stats, name)), name
    assert torch.all(dense.extras["field_evals"] == S)  # every sample was evaluated

    enough = int(PACK_MIN_SKIPPED_FRACTION * R * S) + 1
    packed = render_rays(field, rays, st, generator=torch.Generator().manual_seed(4), occupied=keep_all_but(enough))
    assert packed.extras["weights"].shape == (K, R * S - enough)
    assert int(packed.extras["field_evals"].sum()) == R * S - enough


def test_packed_trapezoid_is_refused():
    rays = box_rays(2)
    samples = sample_along_rays(rays, 8)
    packed = pack_samples(samples, torch.ones(4, 8, dtype=torch.bool))
    params = BoxField()(packed.positions, packed.directions)
    with pytest.raises(ValueError, match="quadrature='alpha'"):
        render_samples_packed(params, packed, settings(quadrature="trapezoid"), num_draws=2)
    with pytest.raises(ValueError, match="skip_empty_space"):
        SNeRF(BoxField(), SceneRegion("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3])),
              settings(quadrature="trapezoid"), LossConfig())


# ------------------------------------------------------------------------- through the model


def make_models(loss: LossConfig) -> tuple[SNeRF, SNeRF, BoxField]:
    field = BoxField()
    region = SceneRegion("aabb", torch.tensor([[-1.0] * 3, [1.0] * 3]))
    dense = SNeRF(field, region, settings(skip_empty_space=False), loss, train_draws=3).double()
    skip = SNeRF(field, region, settings(), loss, train_draws=3).double()
    return dense, skip, field


def loss_and_grads(model: SNeRF, field: BoxField, rays, target):
    field.zero_grad()
    loss, logs = model.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(7))
    loss.backward()
    return loss.detach(), grads(field), logs


def test_model_all_cells_occupied_equals_dense_model():
    # nothing skipped: the skipping model keeps the dense layout (no packing) and must agree
    dense, skip, field = make_models(LossConfig(kl="full", random_points_per_axis=3, observed_kl_samples=50))
    rays = box_rays()
    target = torch.rand(len(rays), 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert skip.occupancy.occupied_fraction == 1.0
    l_d, g_d, logs_d = loss_and_grads(dense, field, rays, target)
    l_s, g_s, logs_s = loss_and_grads(skip, field, rays, target)
    assert logs_s["field_evals_per_ray"] == logs_d["field_evals_per_ray"] == 24
    torch.testing.assert_close(l_s, l_d, rtol=1e-10, atol=0)
    for a, b in zip(g_s, g_d):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_model_packed_equals_dense_after_occupancy_update(monkeypatch):
    # pack whatever the grid skips (the default packs only batches worth it: see renderer.skip_empty)
    monkeypatch.setattr(renderer, "PACK_MIN_SKIPPED_FRACTION", 0.0)
    # observed-ray KL runs over the kept samples only, so compare the likelihood and random-point KL
    dense, skip, field = make_models(LossConfig(kl="fixed_prior", random_points_per_axis=3))
    rays = box_rays()
    target = torch.rand(len(rays), 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    skip.training_loss(rays, target, step=0)  # records the render interval length
    skip.after_step(0)
    occ = skip.occupancy.occupancy
    # the box |x| < 0.4 spans the central cells of the 8^3 grid (cells of 0.25); dilation adds one ring
    assert 0.05 < skip.occupancy.occupied_fraction < 0.5
    assert bool(occ[3:5, 3:5, 3:5].all()) and not bool(occ[0].any()) and not bool(occ[:, :, 7].any())

    l_d, g_d, logs_d = loss_and_grads(dense, field, rays, target)
    l_s, g_s, logs_s = loss_and_grads(skip, field, rays, target)
    assert logs_s["field_evals_per_ray"] < 0.95 * logs_d["field_evals_per_ray"]  # samples were skipped
    torch.testing.assert_close(l_s, l_d, rtol=1e-10, atol=0)
    for a, b in zip(g_s, g_d):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)

    maps_d = dense.render_view(rays.reshape(6, 6), generator=torch.Generator().manual_seed(5))
    maps_s = skip.render_view(rays.reshape(6, 6), generator=torch.Generator().manual_seed(5))
    for name in MAP_NAMES:
        torch.testing.assert_close(maps_s[name], maps_d[name], rtol=1e-10, atol=1e-12, msg=name)
    assert float(maps_s["field_evals_per_ray"].mean()) < 0.95 * float(maps_d["field_evals_per_ray"].mean())
    assert float(maps_d["opacity"].max()) > 0.5


def test_checkpoint_without_occupancy_loads_into_skipping_model():
    dense, skip, _ = make_models(LossConfig(kl="none"))
    state = dense.state_dict()
    assert not any("occupancy" in k for k in state)
    skip.load_state_dict(state)  # strict: only the occupancy buffers may be missing
    assert skip.occupancy.occupied_fraction == 1.0
    with pytest.raises(RuntimeError, match="Missing key"):
        skip.load_state_dict({k: v for k, v in state.items() if not k.startswith("field.colour")})


@pytest.mark.parametrize("shared", [False, True])
def test_draw_blocks_give_the_same_render_and_gradients_as_one_block(monkeypatch, shared):
    """K = 7 draws in blocks of 2 (2, 2, 2, 1) equal one block of 7: statistics, weights and
    gradients, dense and packed; with shared noise also from the generator (drawn for all K at once)."""
    field, st, samples, packed, gen = box_scene(shared)
    R, S, K = *samples.t_starts.shape, 7
    noise = (torch.randn(R, K, 1 if shared else S, generator=gen, dtype=torch.float64),
             torch.randn(R, K, 1 if shared else S, 3, generator=gen, dtype=torch.float64))
    packed_noise = (torch.randn(K, len(packed.ray_indices), generator=gen, dtype=torch.float64),
                    torch.randn(K, len(packed.ray_indices), 3, generator=gen, dtype=torch.float64))

    def run(render, smp, **kw):
        field.zero_grad()
        out = render(field(smp.positions, smp.directions), smp, st, num_draws=K, **kw)
        (out.stats.colour_var.sum() + out.stats.depth_var_total.sum() + out.stats.colour_mean.sum()).backward()
        return out, grads(field)

    cases = [(render_samples, samples, {"noise": noise}), (render_samples_packed, packed, {"noise": packed_noise})]
    if shared:
        cases += [(render_samples, samples, {"generator": "seed"}), (render_samples_packed, packed, {"generator": "seed"})]
    for render, smp, kw in cases:
        results = []
        for block in (10 ** 9, 2 * (S * R)):
            monkeypatch.setattr(renderer, "DRAW_BLOCK_ELEMENTS", block)
            call = {"generator": torch.Generator().manual_seed(3)} if kw.get("generator") == "seed" else kw
            results.append(run(render, smp, **call))
        assert len(renderer.draw_blocks(K, S * R)) == 4  # the second render really was blocked
        (one, g_one), (blocked, g_blocked) = results
        for name in STAT_NAMES:
            torch.testing.assert_close(getattr(blocked.stats, name), getattr(one.stats, name), rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(blocked.extras["weights"], one.extras["weights"], rtol=0, atol=0)
        for a, b in zip(g_blocked, g_one):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-13)


def test_draw_blocks_cover_every_draw_once():
    assert renderer.draw_blocks(7, renderer.DRAW_BLOCK_ELEMENTS // 2) == [(0, 2), (2, 2), (4, 2), (6, 1)]
    assert renderer.draw_blocks(3, renderer.DRAW_BLOCK_ELEMENTS * 5) == [(0, 1), (1, 1), (2, 1)]
    assert renderer.draw_blocks(16, 1) == [(0, 16)]
