"""Tests for the occupancy grid: coverage of a known density, packed == dense rendering, schedules."""

from __future__ import annotations

import math

import pytest
import torch

from stochastic_fields import volume_rendering as vr
from stochastic_fields.constants import OCCUPANCY_ALPHA_THRESHOLD
from stochastic_fields.fields.base import FieldParams, StochasticField
from stochastic_fields.occupancy import OccupancyGrid, density_threshold, density_upper_estimate
from stochastic_fields.rays import RayBundle
from stochastic_fields.samplers import sample_along_rays

UNIT_BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
CENTRE = torch.tensor([0.1, -0.05, 0.07])
RADIUS = 0.5
SPHERE_DENSITY = 10.0


def sphere_density(points: torch.Tensor) -> torch.Tensor:
    """Density 10 inside a ball of radius 0.5 (8 cells of a 32^3 grid on [-1, 1]^3), 0 elsewhere."""
    return SPHERE_DENSITY * ((points - CENTRE).norm(dim=-1) <= RADIUS).to(points.dtype)


def radiance(points: torch.Tensor) -> torch.Tensor:
    """[*B, 3] a smooth colour that varies over the sphere, so colours test which samples were kept."""
    return torch.sigmoid(torch.stack([3 * points[..., 0], 2 * points[..., 1] + 1, points[..., 2] - points[..., 0]], -1))


def camera_rays(num_side: int = 12, origin=(0.0, 0.0, -3.0), near=1.0, far=5.0) -> RayBundle:
    """Rays from one origin through a grid of targets on the z = 0 plane spanning [-0.9, 0.9]^2."""
    s = torch.linspace(-0.9, 0.9, num_side)
    targets = torch.stack(torch.meshgrid(s, s, indexing="ij") + (torch.zeros(num_side, num_side),), -1).reshape(-1, 3)
    origins = torch.tensor(origin).expand_as(targets).clone()
    directions = targets - origins
    directions = directions / directions.norm(dim=-1, keepdim=True)
    n = targets.shape[0]
    return RayBundle(origins, directions, torch.full((n,), near), torch.full((n,), far), torch.ones(n))


def intersecting_cells(grid: OccupancyGrid) -> torch.Tensor:
    """[X, Y, Z] bool: the cell box intersects the ball (closest point of the box within the radius)."""
    res = grid.resolution.tolist()
    idx = torch.stack(torch.meshgrid(*(torch.arange(r) for r in res), indexing="ij"), -1).float()
    lo = grid.aabb[0] + idx * grid.cell_size
    closest = torch.maximum(torch.minimum(CENTRE, lo + grid.cell_size), lo)
    return (closest - CENTRE).norm(dim=-1) <= RADIUS


# ----------------------------------------------------------------------------- geometry


def test_cell_indices_match_loop_on_anisotropic_grid():
    grid = OccupancyGrid([[0.0, -2.0, 1.0], [4.0, 1.0, 2.0]], (4, 3, 2))
    gen = torch.Generator().manual_seed(0)
    points = torch.rand(200, 3, generator=gen) * torch.tensor([5.0, 4.0, 1.6]) + torch.tensor([-0.5, -2.5, 0.8])
    flat, inside = grid.cell_indices(points)
    for p, f, ins in zip(points.tolist(), flat.tolist(), inside.tolist()):
        expected_inside = 0.0 <= p[0] <= 4.0 and -2.0 <= p[1] <= 1.0 and 1.0 <= p[2] <= 2.0
        assert ins == expected_inside
        if ins:
            i, j, k = min(int(p[0] // 1.0), 3), min(int((p[1] + 2.0) // 1.0), 2), min(int((p[2] - 1.0) // 0.5), 1)
            assert f == (i * 3 + j) * 2 + k
    # the max corner belongs to the last cell
    flat, inside = grid.cell_indices(torch.tensor([[4.0, 1.0, 2.0]]))
    assert inside.item() and flat.item() == grid.num_cells - 1


def test_bad_construction_and_arguments_raise():
    with pytest.raises(ValueError, match="max > min"):
        OccupancyGrid([[0, 0, 0], [1, 0, 1]], 4)
    with pytest.raises(ValueError, match="resolution"):
        OccupancyGrid(UNIT_BOX, (4, 0, 4))
    grid = OccupancyGrid(UNIT_BOX, 4)
    with pytest.raises(ValueError, match="decay"):
        grid.update(sphere_density, 0, decay=1.5)
    with pytest.raises(ValueError, match="flat bundle"):
        grid.sample(camera_rays(2).reshape(2, 2), 8)
    with pytest.raises(ValueError, match="one value per point"):
        grid.update(lambda p: torch.zeros(3), 0)
    with pytest.raises(ValueError, match="step_size"):
        density_threshold(0.0)


# ----------------------------------------------------------------------------- updates


def test_default_threshold_is_the_named_alpha():
    step = 0.01
    thr = density_threshold(step)
    assert -math.expm1(-thr * step) == pytest.approx(OCCUPANCY_ALPHA_THRESHOLD, rel=1e-12)
    grid = OccupancyGrid(UNIT_BOX, 8)
    grid.update(lambda p: torch.full(p.shape[:1], 0.99 * thr), 0, step_size=step)
    assert grid.occupied_fraction == 0.0
    grid.update(lambda p: torch.full(p.shape[:1], 1.01 * thr), 0, step_size=step, decay=1.0)
    assert grid.occupied_fraction == 1.0


def test_warmup_evaluates_every_cell_once_at_jittered_points():
    grid = OccupancyGrid([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]], (6, 3, 4))
    seen = []

    def record(points):
        seen.append(points)
        return torch.zeros(points.shape[0])

    assert grid.update(record, 0, warmup_steps=10, chunk_size=7, generator=torch.Generator().manual_seed(1))
    points = torch.cat(seen)
    flat, inside = grid.cell_indices(points)
    assert bool(inside.all())
    assert torch.equal(flat, torch.arange(grid.num_cells))
    centres = grid.aabb[0] + (torch.stack(torch.meshgrid(*(torch.arange(r) for r in (6, 3, 4)), indexing="ij"), -1)
                              .reshape(-1, 3) + 0.5) * grid.cell_size
    assert (points - centres).abs().max() > 0.1 * grid.cell_size.min()  # jittered, not at the centres


def test_schedule_and_moving_maximum():
    grid = OccupancyGrid(UNIT_BOX, 8)
    calls = []

    def constant(value):
        def fn(points):
            calls.append(points.shape[0])
            return torch.full(points.shape[:1], value)
        return fn

    gen = torch.Generator().manual_seed(2)
    assert not grid.update(constant(5.0), 3, update_every_n_steps=4, warmup_steps=8)
    assert calls == []
    assert grid.update(constant(5.0), 4, update_every_n_steps=4, warmup_steps=8, generator=gen)
    assert calls == [512] and torch.equal(grid.density_ema, torch.full((8, 8, 8), 5.0))
    # after warm-up: a quarter of the cells at random plus as many occupied ones, decayed then maxed
    assert grid.update(constant(0.0), 8, update_every_n_steps=4, warmup_steps=8, decay=0.9, generator=gen)
    assert calls[-1] == 2 * 128
    torch.testing.assert_close(grid.density_ema.unique(), torch.tensor([4.5, 5.0]))
    touched = (grid.density_ema < 5.0).sum().item()
    assert 128 <= touched <= 256
    # a larger density wins over the decayed maximum
    grid.update(constant(7.0), 12, update_every_n_steps=4, warmup_steps=100, decay=0.9, generator=gen)
    assert torch.equal(grid.density_ema, torch.full((8, 8, 8), 7.0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_update_covers_every_cell_intersecting_the_sphere(seed):
    grid = OccupancyGrid(UNIT_BOX, 32)
    grid.update(sphere_density, 0, generator=torch.Generator().manual_seed(seed))
    must = intersecting_cells(grid)
    assert bool(grid.occupancy[must].all())
    # and nothing far from it: every occupied cell is within dilation (1 cell) of the ball
    res = grid.resolution.tolist()
    idx = torch.stack(torch.meshgrid(*(torch.arange(r) for r in res), indexing="ij"), -1).float()
    centres = grid.aabb[0] + (idx + 0.5) * grid.cell_size
    reach = RADIUS + 1.5 * math.sqrt(3.0) * grid.cell_size[0]
    assert bool(((centres - CENTRE).norm(dim=-1)[grid.occupancy] <= reach).all())
    assert grid.occupied_fraction < 1.5 * must.float().mean().item()


def test_without_dilation_point_sampling_misses_grazing_cells():
    """Why dilation is on by default: one jittered point per cell misses cells that graze the sphere."""
    grid = OccupancyGrid(UNIT_BOX, 32)
    grid.update(sphere_density, 0, dilation=0, generator=torch.Generator().manual_seed(0))
    missed = (intersecting_cells(grid) & ~grid.occupancy).sum().item()
    assert missed > 100


def test_density_upper_estimate_uses_high_quantile():
    class Linear(StochasticField):
        def __init__(self):
            super().__init__()
            self.register_buffer("aabb", torch.tensor(UNIT_BOX))

        def forward(self, positions, directions):
            shape = positions.shape[:-1]
            return FieldParams(positions[..., 0], torch.full(shape, 0.5), torch.zeros(*shape, 3), torch.ones(*shape, 3))

    fn = density_upper_estimate(Linear(), num_std=2.0)
    points = torch.tensor([[-3.0, 0, 0], [-1.0, 0, 0], [0.5, 0, 0]])
    torch.testing.assert_close(fn(points), torch.tensor([0.0, 0.0, 1.5]))


def test_state_dict_round_trip():
    grid = OccupancyGrid(UNIT_BOX, (8, 4, 2))
    grid.update(sphere_density, 0, generator=torch.Generator().manual_seed(3))
    other = OccupancyGrid(UNIT_BOX, (8, 4, 2))
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.occupancy, grid.occupancy) and torch.equal(other.density_ema, grid.density_ema)


# ----------------------------------------------------------------------------- sampling


def test_all_occupied_packed_equals_dense_sampling():
    grid = OccupancyGrid(UNIT_BOX, 16)
    grid.mark_all_occupied()
    rays = camera_rays(5, origin=(0.0, 0.0, -0.95), near=0.05, far=1.2)  # every sample inside the box
    assert bool((sample_along_rays(rays, 24).positions.abs() < 1.0).all())
    packed = grid.sample(rays, 24, stratified=True, generator=torch.Generator().manual_seed(4))
    dense = sample_along_rays(rays, 24, stratified=True, generator=torch.Generator().manual_seed(4))
    assert torch.equal(packed.ray_indices, torch.arange(len(rays)).repeat_interleave(24))
    assert torch.equal(packed.t_starts, dense.t_starts.reshape(-1))
    assert torch.equal(packed.t_ends, dense.t_ends.reshape(-1))


def test_samples_outside_the_box_are_dropped():
    grid = OccupancyGrid(UNIT_BOX, 8)
    grid.mark_all_occupied()
    rays = camera_rays(4)  # from z = -3: the first samples lie outside the box
    packed = grid.sample(rays, 64)
    dense = sample_along_rays(rays, 64)
    inside = ((dense.positions.abs() <= 1.0).all(-1))
    assert packed.ray_indices.numel() == int(inside.sum())
    assert torch.equal(packed.t_starts, dense.t_starts[inside])
    assert bool((packed.ray_indices[1:] >= packed.ray_indices[:-1]).all())


def render_packed(packed, density_scales, background):
    points = packed.positions
    density = density_scales[:, None] * sphere_density(points)  # [K, N]
    rgb = radiance(points).expand(len(density_scales), -1, -1)  # [K, N, 3]
    w = vr.weights_alpha_packed(density, packed.t_starts, packed.t_ends, packed.ray_indices, packed.num_rays)
    return vr.trajectory_statistics_packed(w, rgb, packed.t_mids, packed.ray_indices, packed.num_rays,
                                           packed.rays.far, background)


def render_dense(samples, density_scales, background):
    points = samples.positions  # [R, S, 3]
    density = density_scales[None, :, None] * sphere_density(points)[:, None, :]  # [R, K, S]
    rgb = radiance(points)[:, None].expand(-1, len(density_scales), -1, -1)  # [R, K, S, 3]
    w = vr.weights_alpha(density, samples.t_starts[:, None], samples.t_ends[:, None])
    return vr.trajectory_statistics(w, rgb, samples.t_mids, samples.rays.far, background)


def test_sphere_packed_rendering_equals_dense_with_far_fewer_samples():
    grid = OccupancyGrid(UNIT_BOX, 32)
    grid.update(sphere_density, 0, step_size=4.0 / 256, generator=torch.Generator().manual_seed(5))
    rays = camera_rays(12)
    scales = torch.tensor([1.0, 0.3])  # two "draws" with different densities
    background = torch.tensor([0.9, 0.8, 0.7])
    packed = grid.sample(rays, 256, stratified=True, generator=torch.Generator().manual_seed(6))
    dense = sample_along_rays(rays, 256, stratified=True, generator=torch.Generator().manual_seed(6))
    assert packed.ray_indices.numel() < 0.15 * dense.t_starts.numel()

    ours, ref = render_packed(packed, scales, background), render_dense(dense, scales, background)
    assert ref.opacity_draws[:, 0].max() > 0.99 and (ref.opacity < 1e-6).any()  # rays that hit and rays that miss
    counts = torch.bincount(packed.ray_indices, minlength=len(rays))
    assert (counts == 0).any()  # some rays keep no samples at all
    for key in ("colour_draws", "depth_draws", "opacity_draws", "colour_var", "depth_var_total", "depth_var_spread"):
        torch.testing.assert_close(getattr(ours, key), getattr(ref, key), rtol=1e-5, atol=1e-6, msg=key)
    assert torch.equal(ours.depth_draws[counts == 0], rays.far[counts == 0, None].expand(-1, 2))


def test_empty_grid_gives_empty_rays():
    grid = OccupancyGrid(UNIT_BOX, 8)
    grid.update(lambda p: torch.zeros(p.shape[0]), 0)
    assert grid.occupied_fraction == 0.0
    rays = camera_rays(3)
    packed = grid.sample(rays, 32, stratified=True, generator=torch.Generator().manual_seed(7))
    assert packed.ray_indices.numel() == 0 and packed.t_starts.shape == (0,)
    background = torch.tensor([0.2, 0.4, 0.6])
    stats = render_packed(packed, torch.tensor([1.0, 2.0]), background)
    assert torch.equal(stats.opacity, torch.zeros(9))
    assert torch.equal(stats.depth_mean, rays.far)
    assert torch.equal(stats.colour_mean, background.expand(9, 3))
    assert torch.equal(stats.depth_var_total, torch.zeros(9))
