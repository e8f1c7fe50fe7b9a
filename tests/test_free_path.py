"""Free-path probabilities and the occupancy map against analytic cases (slab, empty space, wall),
and their files read back with the consumers' own libraries (numpy, pyoctomap)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from stochastic_fields.products.free_path import (free_probability, path_free_probability,
                                                  segment_free_probability, segment_optical_depths)
from stochastic_fields.products.occupancy_map import (blocking_threshold, occupancy_map, probability_density_exceeds,
                                                      read_occupancy_npz, write_occupancy_npz, write_octomap)
from stochastic_fields.scene_region import SceneRegion

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


class SlabField:
    """Density N(mu, s^2) before the ReLU inside the slab lo <= x < hi, empty (mu = -1e4) elsewhere."""

    def __init__(self, mu: float, s: float, lo: float = 1.0, hi: float = 2.0):
        self.mu, self.s, self.lo, self.hi = mu, s, lo, hi

    def density_params(self, points):
        inside = (points[..., 0] >= self.lo) & (points[..., 0] < self.hi)
        loc = torch.where(inside, torch.full_like(points[..., 0], self.mu), torch.full_like(points[..., 0], -1e4))
        return loc, torch.full_like(loc, self.s)


def _segments(device, n=3):
    starts = torch.tensor([[0.0, 0.0, 0.0]] * n, dtype=torch.float64, device=device)
    ends = torch.tensor([[3.0, 0.0, 0.0]] * n, dtype=torch.float64, device=device)
    return starts, ends


@pytest.mark.parametrize("device", DEVICES)
def test_empty_space_and_wall(device):
    starts, ends = _segments(device)
    g = torch.Generator(device=device).manual_seed(0)
    empty = segment_free_probability(SlabField(-1e4, 1.0), starts, ends, num_draws=64, step=0.05, generator=g)
    assert torch.all(empty.probability == 1) and torch.all(empty.stderr == 0)
    np.testing.assert_allclose(empty.transmittance_mean.cpu().numpy(), 1.0)
    assert empty.bound_95[0].item() == pytest.approx(3 / 64)  # rule of three at p = 1
    wall = segment_free_probability(SlabField(1e3, 1.0), starts, ends, num_draws=64, step=0.05, generator=g)
    assert torch.all(wall.probability == 0) and torch.all(wall.transmittance_mean < 1e-30)
    # a segment that stops before the wall is free, one that crosses it is not
    r = segment_free_probability(SlabField(1e3, 1.0), torch.zeros(2, 3, dtype=torch.float64, device=device),
                                 torch.tensor([[0.9, 0, 0], [1.5, 0, 0]], dtype=torch.float64, device=device),
                                 num_draws=16, step=0.05, generator=g)
    assert r.probability.tolist() == [1.0, 0.0]


@pytest.mark.parametrize("device", DEVICES)
def test_deterministic_slab_transmittance(device):
    """s -> 0: T = exp(-mu * L_inside) exactly (midpoints aligned with the slab faces)."""
    starts, ends = _segments(device)
    for mu, expect_free in ((0.5, True), (1.0, False)):  # exp(-0.5) = 0.61 > 0.5; exp(-1) = 0.37
        r = segment_free_probability(SlabField(mu, 1e-9), starts, ends, num_draws=8, step=0.1,
                                     generator=torch.Generator(device=device).manual_seed(1))
        np.testing.assert_allclose(r.transmittance.cpu().numpy(), math.exp(-mu), rtol=1e-6)
        assert torch.all(r.probability == float(expect_free))


@pytest.mark.parametrize("device", DEVICES)
def test_shared_noise_slab_matches_closed_form(device):
    """Shared eps: tau = relu(mu + s eps) L, free iff tau < -log(level):
    P = Phi((-log(level) / L - mu) / s)."""
    mu, s, L, level, K = 0.6, 0.4, 1.0, 0.5, 20000
    starts, ends = _segments(device, 1)
    r = segment_free_probability(SlabField(mu, s), starts, ends, num_draws=K, level=level, step=0.1,
                                 shared_noise=True, generator=torch.Generator(device=device).manual_seed(2))
    exact = stats.norm.cdf((-math.log(level) / L - mu) / s)
    p, se = r.probability.item(), r.stderr.item()
    assert se == pytest.approx(math.sqrt(exact * (1 - exact) / K), rel=0.05)
    assert abs(p - exact) < 4 * se, (p, exact, se)


@pytest.mark.parametrize("device", DEVICES)
def test_independent_noise_mean_transmittance_closed_form(device):
    """Independent eps per point: E[T] = prod_i E[exp(-delta relu(X_i))], with
    E[exp(-c relu(X))] = Phi(-mu/s) + exp(-c mu + c^2 s^2 / 2) Phi(mu/s - c s)."""
    mu, s, step, K = 0.8, 1.5, 0.1, 40000
    starts, ends = _segments(device, 1)
    tau, n = segment_optical_depths(SlabField(mu, s).density_params, starts, ends, num_draws=K, step=step,
                                    generator=torch.Generator(device=device).manual_seed(3))
    assert int(n[0]) == 30
    c = 3.0 / 30
    one = stats.norm.cdf(-mu / s) + math.exp(-c * mu + c * c * s * s / 2) * stats.norm.cdf(mu / s - c * s)
    exact = one ** 10  # 10 of the 30 midpoints lie in the slab [1, 2)
    T = torch.exp(-tau).cpu().numpy()
    assert abs(T.mean() - exact) < 4 * T.std() / math.sqrt(K)


def test_path_is_the_product_of_its_segments():
    field = SlabField(0.3, 0.2)
    way = torch.tensor([[0.0, 0, 0], [1.5, 0, 0], [2.5, 0, 0]], dtype=torch.float64)
    whole, parts = path_free_probability(field, way, num_draws=512, step=0.1, shared_noise=True,
                                         generator=torch.Generator().manual_seed(4))
    np.testing.assert_allclose(whole.transmittance[0].numpy(), parts.transmittance.prod(0).numpy(), rtol=1e-12)
    assert whole.probability.item() <= parts.probability.min().item()
    every = (parts.transmittance > 0.5).all(0).double().mean().item()
    assert whole.every_segment_free.item() == pytest.approx(every) and whole.probability.item() <= every
    # shared along the path: both segments of a draw saw the same eps, so their optical depths
    # scale with the lengths inside the slab (0.5 and 0.5)
    np.testing.assert_allclose(parts.transmittance[0].numpy(), parts.transmittance[1].numpy(), rtol=1e-12)


def test_free_probability_and_bad_input():
    p, se, bound = free_probability(torch.tensor([[0.9, 0.1, 0.7, 0.2]]), 0.5)
    assert p.item() == 0.5 and se.item() == pytest.approx(0.25) and bound.item() == pytest.approx(1.959963985 * 0.25)
    with pytest.raises(ValueError, match="must both be"):
        segment_free_probability(SlabField(0, 1), torch.zeros(2, 3), torch.zeros(3, 3), step=0.1)
    with pytest.raises(ValueError, match="step"):
        segment_free_probability(SlabField(0, 1), torch.zeros(2, 3), torch.ones(2, 3), step=0.0)
    with pytest.raises(ValueError, match="level"):
        segment_free_probability(SlabField(0, 1), torch.zeros(2, 3), torch.ones(2, 3), step=0.1, level=1.0)


# ----------------------------------------------------------------------------- occupancy
def test_probability_density_exceeds_against_sampling():
    mu = torch.tensor([-1.0, 0.0, 2.0], dtype=torch.float64)
    s = torch.tensor([0.5, 1.0, 3.0], dtype=torch.float64)
    tau = 0.7
    p = probability_density_exceeds(mu, s, tau)
    draws = torch.relu(mu + s * torch.randn(200000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64))
    mc = (draws > tau).double().mean(0)
    np.testing.assert_allclose(p.numpy(), mc.numpy(), atol=4e-3)
    np.testing.assert_allclose(p.numpy(), stats.norm.sf((tau - mu.numpy()) / s.numpy()), rtol=1e-12)
    assert blocking_threshold(0.1) == pytest.approx(math.log(2) / 0.1)


def test_occupancy_map_slab_npz_and_octomap(tmp_path):
    import pyoctomap

    region = SceneRegion("aabb", torch.tensor([[0.0, -0.5, -0.5], [3.0, 0.5, 0.5]]))
    field = SlabField(8.0, 4.0)
    voxel = 0.125
    occ = occupancy_map(field, region, voxel)
    tau = math.log(2) / voxel
    assert occ.shape == (24, 8, 8) and occ.inside_region.all()
    expect = stats.norm.sf((tau - 8.0) / 4.0)
    x = occ.centres()[:, 0]
    assert np.all((x >= 1.0) & (x < 2.0)) and len(x) == 8 * 8 * 8  # only the slab is listed (sparse)
    np.testing.assert_allclose(occ.probability, expect, rtol=1e-5)
    back = read_occupancy_npz(write_occupancy_npz(tmp_path / "occ.npz", occ))
    np.testing.assert_array_equal(back.indices, occ.indices)
    np.testing.assert_array_equal(back.inside_region, occ.inside_region)
    dense = back.dense()
    assert dense.shape == (24, 8, 8) and dense[0].max() == 0 and dense[10].min() == pytest.approx(expect, rel=1e-5)
    # OctoMap: the same probabilities at the voxel centres, read with pyoctomap
    occ.metres_per_unit = 2.0
    path = write_octomap(tmp_path / "occ.ot", occ)
    tree = pyoctomap.OcTree(0.1).read(str(path))
    assert tree.getResolution() == pytest.approx(voxel * 2.0)
    for centre in ([1.0625, 0.0625, 0.0625], [0.0625, 0.0625, 0.0625], [2.9375, -0.4375, 0.4375]):
        node = tree.search(np.asarray(centre) * 2.0)
        want = expect if 1.0 <= centre[0] < 2.0 else occ.min_probability
        assert node.getOccupancy() == pytest.approx(want, rel=1e-4)
    assert tree.getNumLeafNodes() < 24 * 8 * 8  # free space pruned into larger cells


def test_planner_goes_round_a_wall_through_its_gap():
    """A wall x in [1, 1.25) with a gap at y > 0.25: the plan passes the gap, its straight
    segments are free with probability 1, and a straight line through the wall is not."""
    from stochastic_fields.products.plan import plan_voxel_path, simplify_voxel_path

    class WallWithGap:
        def density_params(self, points):
            wall = (points[..., 0] >= 1.0) & (points[..., 0] < 1.25) & (points[..., 1] < 0.25)
            loc = torch.where(wall, torch.full_like(points[..., 0], 1e3), torch.full_like(points[..., 0], -1e3))
            return loc, torch.ones_like(loc)

    region = SceneRegion("aabb", torch.tensor([[0.0, -1.0, -0.25], [2.0, 1.0, 0.25]]))
    occ = occupancy_map(WallWithGap(), region, 0.125)
    start, goal = np.array([0.3, -0.8, 0.0]), np.array([1.8, -0.8, 0.0])
    vox, risk = plan_voxel_path(occ, start, goal)
    centres = occ.origin + (vox + 0.5) * occ.voxel_size
    assert risk < 1e-6 and centres[:, 1].max() > 0.25  # through the gap, no risk taken
    way = simplify_voxel_path(occ, vox)
    whole, parts = path_free_probability(WallWithGap(), torch.from_numpy(way), num_draws=32, step=0.05,
                                         generator=torch.Generator().manual_seed(0))
    assert whole.probability.item() == 1.0 and torch.all(parts.probability == 1)
    direct = segment_free_probability(WallWithGap(), torch.from_numpy(start)[None], torch.from_numpy(goal)[None],
                                      num_draws=32, step=0.05, generator=torch.Generator().manual_seed(0))
    assert direct.probability.item() == 0.0
    with pytest.raises(ValueError, match="outside the known region"):
        plan_voxel_path(occ, np.array([5.0, 0, 0]), goal)


def test_blocking_length_sets_the_threshold():
    """tau = log 2 / ell: a diffuse slab (density N(3, 0.5^2)) is not blocked at voxel scale
    (0.125 -> tau 5.5) but is for a 0.5-long crossing (tau 1.39)."""
    region = SceneRegion("aabb", torch.tensor([[0.0, -0.5, -0.5], [3.0, 0.5, 0.5]]))
    fine = occupancy_map(SlabField(3.0, 0.5), region, 0.125, min_probability=0.0)
    long = occupancy_map(SlabField(3.0, 0.5), region, 0.125, blocking_length=0.5)
    assert fine.density_threshold == pytest.approx(math.log(2) / 0.125)
    np.testing.assert_allclose(fine.probability[(fine.centres()[:, 0] >= 1) & (fine.centres()[:, 0] < 2)], stats.norm.sf((math.log(2) / 0.125 - 3.0) / 0.5), rtol=1e-5)
    np.testing.assert_allclose(long.probability, stats.norm.sf((math.log(2) / 0.5 - 3.0) / 0.5), rtol=1e-5)
    slab = (fine.centres()[:, 0] >= 1) & (fine.centres()[:, 0] < 2)
    assert fine.probability[slab].max() < 0.01 < 0.99 < long.probability.min()
    with pytest.raises(ValueError, match="blocking length"):
        blocking_threshold(0.0)
