"""The Laplace density uncertainty (stochastic_fields.laplace) against autograd and a brute-force
Jacobian of every cell's log-density offset, in float64."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from stochastic_fields.distributions import RectifiedNormal
from stochastic_fields.fields.base import FieldParams
from stochastic_fields.laplace import (LaplaceDensity, cell_index, cell_runs, depth_variance_packed, fit_laplace_density,
                                       ray_derivatives)
from stochastic_fields.rays import RayBundle
from stochastic_fields.scene_region import SceneRegion



@pytest.fixture(autouse=True)
def _float64():
    """Every tensor of these tests in float64 (the references are exact to 1e-8)."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(before)


def _composite(tau, values, background=None):
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(tau[:, :1]), tau], 1), 1))
    w = trans[:, :-1] * (1 - torch.exp(-tau))
    out = (w[..., None] * values).sum(1)
    return out if background is None else out + trans[:, -1:] * background


def test_ray_derivatives_match_autograd():
    g = torch.Generator().manual_seed(0)
    tau = (torch.rand(5, 7, generator=g) * 2).requires_grad_()
    values = torch.rand(5, 7, 3, generator=g)
    bg = torch.tensor([0.2, 0.5, 0.9])
    composited, grad = ray_derivatives(tau.detach(), values, bg)
    ref = _composite(tau, values, bg)
    assert torch.allclose(composited, ref.detach(), atol=1e-12)
    for c in range(3):
        auto, = torch.autograd.grad(ref[:, c].sum(), tau, retain_graph=True)
        assert torch.allclose(grad[..., c], auto, atol=1e-12)


def _packed(tau):
    R, S = tau.shape
    return torch.arange(R).repeat_interleave(S)


def test_depth_variance_matches_autograd_including_empty_and_opaque_rays():
    """One cell per sample: V_r = sum_i (tau_i dD_r / d tau_i)^2 / P_i, dD / d tau by autograd."""
    g = torch.Generator().manual_seed(1)
    tau = torch.rand(4, 9, generator=g) * 3
    tau[1] = 0.0  # empty ray: no opacity, no variance
    tau[2, 3] = 80.0  # opaque: nothing behind sample 3 matters
    t = torch.sort(torch.rand(4, 9, generator=g) * 5 + 1, dim=1).values
    precision = torch.rand(36, generator=g) + 0.5
    cells = torch.arange(36).reshape(4, 9)
    tau_g = tau.clone().requires_grad_()
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros(4, 1), tau_g], 1), 1))
    w = trans[:, :-1] * (1 - torch.exp(-tau_g))
    depth_ref = (w * t).sum(1) / w.sum(1).clamp_min(1e-6)
    ref = torch.zeros(4)
    for r in (0, 2, 3):
        grad, = torch.autograd.grad(depth_ref[r], tau_g, retain_graph=True)
        ref[r] = ((tau[r] * grad[r]) ** 2 / precision[cells[r]]).sum()
    var = depth_variance_packed(tau.reshape(-1), t.reshape(-1), _packed(tau), 4, cells.reshape(-1), precision)
    assert torch.allclose(var, ref, rtol=1e-9, atol=1e-14)
    assert var[1] == 0.0 and torch.isfinite(var).all()


def test_depth_variance_sums_runs_and_ignores_skipped_empty_samples():
    """Samples of one cell add their J before squaring; dropping samples with tau = 0 (empty-space
    skipping) or outside every cell (cell -1 adds no J but still attenuates) changes nothing / what it should."""
    g = torch.Generator().manual_seed(2)
    tau = torch.rand(3, 8, generator=g) * 2
    tau[:, [1, 5]] = 0.0
    t = torch.sort(torch.rand(3, 8, generator=g) * 4 + 1, dim=1).values
    cells = torch.tensor([[0, 0, 1, 1, 1, 2, -1, 3]] * 3)
    precision = torch.tensor([1.0, 2.0, 0.5, 4.0])
    dense = depth_variance_packed(tau.reshape(-1), t.reshape(-1), _packed(tau), 3, cells.reshape(-1), precision)
    keep = (tau > 0).reshape(-1)
    skipped = depth_variance_packed(tau.reshape(-1)[keep], t.reshape(-1)[keep], _packed(tau)[keep], 3,
                                    cells.reshape(-1)[keep], precision)
    assert torch.allclose(skipped, dense, rtol=1e-12)
    rows = depth_variance_packed(tau.reshape(-1), t.reshape(-1), _packed(tau), 3, cells.reshape(-1), precision,
                                 samples_per_ray=8)
    assert torch.allclose(rows, dense, rtol=1e-12)  # the dense layout's plain cumulative sums
    one_cell = depth_variance_packed(tau.reshape(-1), t.reshape(-1), _packed(tau), 3, torch.zeros(24, dtype=torch.long),
                                     precision[:1])
    tau_g = tau.clone().requires_grad_()
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros(3, 1), tau_g], 1), 1))
    w = trans[:, :-1] * (1 - torch.exp(-tau_g))
    depth = (w * t).sum(1) / w.sum(1)
    for r in range(3):  # one cell over the whole ray: J = sum_i tau_i dD / d tau_i
        grad, = torch.autograd.grad(depth[r], tau_g, retain_graph=True)
        assert one_cell[r] == pytest.approx(float((tau[r] * grad[r]).sum()) ** 2, rel=1e-9)
    assert depth_variance_packed(torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long), 2,
                                 torch.zeros(0, dtype=torch.long), precision).tolist() == [0.0, 0.0]


def test_cell_runs_by_hand():
    cells = torch.tensor([[3, 3, 5, 5, 5, -1, 3]])
    values = torch.arange(1.0, 8.0).reshape(1, 7, 1)
    run_cell, sums = cell_runs(cells, values)
    assert run_cell.tolist() == [[3, 5, -1, 3, -1, -1, -1]]
    assert sums[0, :4, 0].tolist() == [3.0, 12.0, 6.0, 7.0]
    assert sums[0, 4:, 0].abs().sum() == 0


class _BlobField(torch.nn.Module):
    """An analytic field on the unit cube: a density bump and a colour that varies in space."""

    def __init__(self):
        super().__init__()
        self.region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))

    def density_params(self, positions):
        r2 = ((positions - torch.tensor([0.2, -0.1, 0.3])) ** 2).sum(-1)
        return 6.0 * torch.exp(-4.0 * r2) - 1.0, 0.3 + 0.1 * positions[..., 0].abs()

    def forward(self, positions, directions):
        loc, scale = self.density_params(positions)
        rgb = torch.stack([positions[..., 0], positions[..., 1] - positions[..., 2], positions[..., 2] * 2], -1)
        return FieldParams(loc, scale, rgb, torch.ones_like(rgb))


def _model(background=None):
    return SimpleNamespace(field=_BlobField(), likelihood_std=lambda: torch.tensor([0.05, 0.1, 0.2]),
                           render_settings=SimpleNamespace(num_samples=24, spacing="linear", background=background))


def _rays(n, seed):
    g = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, 0.0, -3.0]) + 0.3 * torch.randn(n, 3, generator=g)
    target = 0.6 * (torch.rand(n, 3, generator=g) - 0.5)
    d = torch.nn.functional.normalize(target - origins, dim=-1)
    return RayBundle(origins, d, torch.full((n,), 1.5), torch.full((n,), 4.5), 0.5 + 0.5 * torch.rand(n, generator=g))


def _brute_force(model, rays, resolution, delta):
    """Colours [R, 3] and depths [R] with every cell's density times exp(delta_c), differentiable in delta."""
    from stochastic_fields.samplers import sample_along_rays
    from stochastic_fields.distributions import RectifiedNormal
    s = sample_along_rays(rays, model.render_settings.num_samples, spacing="linear", stratified=False)
    pos = s.positions
    params = model.field(pos, rays.directions[:, None, :].expand_as(pos))
    dens = RectifiedNormal(params.density_loc, params.density_scale).mean
    cells = cell_index(model.field.region.to_unit(pos), resolution)
    factor = torch.where(cells >= 0, torch.exp(delta[cells.clamp_min(0)]), torch.ones_like(dens))
    tau = dens * factor * (s.t_ends - s.t_starts)
    bg = model.render_settings.background
    colour = _composite(tau, torch.sigmoid(params.rgb_loc), None if bg is None else torch.tensor(bg))
    trans = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(tau[:, :1]), tau], 1), 1))
    w = trans[:, :-1] * (1 - torch.exp(-tau))
    depth = (w * s.t_mids).sum(1) / w.sum(1).clamp_min(1e-6) * rays.z_scale
    return colour, depth


@pytest.mark.parametrize("background", [None, (1.0, 1.0, 1.0)])
def test_fit_and_depth_std_match_the_brute_force_jacobian(background):
    model, res, lam = _model(background), (3, 2, 4), 0.7
    train, test = _rays(40, 2), _rays(6, 3)
    fitted = fit_laplace_density(model, train, resolution=res, prior_precision=lam, max_rays=25, seed=4, chunk=7)
    nc = 3 * 2 * 4
    delta = torch.zeros(nc, requires_grad=True)
    pick = torch.randperm(40, generator=torch.Generator().manual_seed(4))[:25]
    colour, _ = _brute_force(model, train[pick], res, delta)
    fisher = torch.zeros(nc)
    noise = model.likelihood_std() ** 2
    for r in range(25):
        for c in range(3):
            j, = torch.autograd.grad(colour[r, c], delta, retain_graph=True)
            fisher += j ** 2 / noise[c]
    assert torch.allclose(fitted.precision, fisher * 40 / 25 + lam, rtol=1e-8, atol=1e-10)
    assert fitted.rays_used == 25
    _, depth = _brute_force(model, test, res, delta)
    var = torch.stack([(torch.autograd.grad(depth[r], delta, retain_graph=True)[0] ** 2 / fitted.precision).sum()
                       for r in range(6)])
    assert torch.allclose(fitted.depth_std(model, test, chunk=4), var.sqrt(), rtol=1e-8, atol=1e-12)


def test_std_from_a_renders_own_samples_matches_the_dense_pass():
    """The render's dense samples give depth_std's values; packed samples without those of zero density
    (what empty-space skipping drops when the density there is 0) give the same."""
    from stochastic_fields.renderer import pack_samples
    from stochastic_fields.samplers import sample_along_rays
    model, res = _model(), (3, 2, 4)
    fitted = fit_laplace_density(model, _rays(30, 6), resolution=res, prior_precision=0.5)
    rays = _rays(7, 7)
    s = sample_along_rays(rays, model.render_settings.num_samples, spacing="linear", stratified=False)
    loc, scale = model.field.density_params(s.positions)
    reference = fitted.depth_std(model, rays)
    assert torch.allclose(fitted.depth_std_of_samples(s, loc, scale, model.field.region), reference, rtol=1e-10)
    loc = torch.where(s.t_mids > 3.5, torch.full_like(loc, -50.0), loc)  # no density past t = 3.5: relu mean 0
    scale = torch.where(s.t_mids > 3.5, torch.full_like(scale, 1e-3), scale)
    zero = RectifiedNormal(loc, scale).mean == 0
    assert zero.any() and not zero.all()
    dense = fitted.depth_std_of_samples(s, loc, scale, model.field.region)
    packed = pack_samples(s, ~zero)
    keep = torch.nonzero(~zero, as_tuple=True)
    assert torch.allclose(fitted.depth_std_of_samples(packed, loc[keep], scale[keep], model.field.region), dense,
                          rtol=1e-12)


def test_unseen_cells_keep_the_prior_and_round_trip(tmp_path):
    model = _model()
    fitted = fit_laplace_density(model, _rays(10, 5), resolution=(4, 4, 4), prior_precision=2.0)
    assert fitted.precision.min() == pytest.approx(2.0)  # cells no ray crossed
    assert (fitted.precision > 2.0).any()
    fitted.save(tmp_path / "laplace.npz")
    back = LaplaceDensity.load(tmp_path / "laplace.npz")
    assert back.resolution == (4, 4, 4) and torch.equal(back.precision, fitted.precision)
    (tmp_path / "bad.npz").write_bytes(b"not a file")
    with pytest.raises(ValueError, match="bad.npz"):
        LaplaceDensity.load(tmp_path / "bad.npz")


def test_bad_arguments():
    with pytest.raises(ValueError, match="prior_precision"):
        fit_laplace_density(_model(), _rays(3, 0), prior_precision=0.0)
    with pytest.raises(ValueError, match="resolution"):
        fit_laplace_density(_model(), _rays(3, 0), resolution=(0, 2, 2))
