"""Block keys of the spatial split, pixel back-projection, the re-split coverage of the depth
recalibration and calibration views at several fractions (docs/uncertainty.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from stochastic_fields.calibration import ONE_SIGMA_LEVEL, calibration_views, resplit_coverage
from stochastic_fields.capture_points import (SPLIT_BLOCKS_PER_AXIS, backproject_pixels, block_keys,
                                              split_points_by_blocks)


def test_block_keys_give_every_split_block_one_role():
    """The split hands whole blocks out: every key of block_keys holds one role only, and points
    outside the reference extent are clamped into the border blocks."""
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(3000, 3)) * [1.0, 2.0, 0.5]
    keys = block_keys(xyz, xyz)
    roles = split_points_by_blocks(xyz)
    assert keys.min() >= 0 and keys.max() < SPLIT_BLOCKS_PER_AXIS ** 3
    for k in np.unique(keys):
        assert len(np.unique(roles[keys == k])) == 1
    far = np.array([[100.0, 100.0, 100.0], [-100.0, -100.0, -100.0]])
    n = SPLIT_BLOCKS_PER_AXIS
    assert block_keys(far, xyz).tolist() == [n ** 3 - 1, 0]
    with pytest.raises(ValueError, match="blocks_per_axis"):
        block_keys(xyz, xyz, blocks_per_axis=0)


def test_backproject_pixels_round_trips_through_the_camera():
    """X = R K^-1 (u+1/2, v+1/2, 1) z + t, checked by projecting X back with the world-to-camera matrix."""
    K = torch.tensor([[50.0, 0.0, 31.5], [0.0, 55.0, 23.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    angle = 0.3
    R = torch.tensor([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]])
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3], c2w[:3, 3] = R, torch.tensor([1.0, -2.0, 0.5])
    rows, cols = torch.tensor([0, 10, 47]), torch.tensor([0, 33, 63])
    z = torch.tensor([1.0, 2.5, 7.0], dtype=torch.float64)
    X = backproject_pixels(K, c2w, rows, cols, z)
    w2c = torch.linalg.inv(c2w)
    cam = X @ w2c[:3, :3].T + w2c[:3, 3]
    torch.testing.assert_close(cam[:, 2], z)
    uv = (cam @ K.T)[:, :2] / cam[:, 2:]
    torch.testing.assert_close(uv, torch.stack([cols + 0.5, rows + 0.5], -1).double())


def test_resplit_coverage_two_blocks_by_hand():
    """Block 0 holds |z| = 1, block 1 holds |z| = 3, equal counts, share 1/2: each re-split
    calibrates on one block and scores the other, so coverage is exactly 0 (fitted on block 0:
    every scored 3 > 1) or 1 (fitted on block 1), at every level."""
    cal_z = np.r_[np.full(100, 1.0), np.full(100, 3.0)]
    cal_b = np.r_[np.zeros(100, int), np.ones(100, int)]
    score_z = np.r_[np.full(80, 1.0), np.full(80, 3.0)]
    score_b = np.r_[np.zeros(80, int), np.ones(80, int)]
    cov = resplit_coverage(cal_z, cal_b, score_z, score_b, np.array([0, 1]), np.array([100, 100]),
                           share=0.5, num_splits=50, seed=3)
    assert cov.shape == (50, 2)
    assert set(np.unique(cov).tolist()) <= {0.0, 1.0}
    assert np.array_equal(cov[:, 0], cov[:, 1])
    assert 0 < cov[:, 0].sum() < 50  # both orders were drawn


def test_resplit_coverage_is_nominal_for_exchangeable_blocks_and_spreads_for_heterogeneous_ones():
    """Errors |N(0, c^2)| with one scale c everywhere: the expected coverage is the nominal level
    (here within 0.01 over 100 re-splits of 60 blocks) whatever c, with a small spread. Scales that
    differ by block leave the mean near nominal but widen the spread several times."""
    rng = np.random.default_rng(0)
    B, per = 60, 300
    blocks = np.arange(B)
    blk = np.repeat(blocks, per)

    def draw(scale_per_block):
        return np.abs(rng.normal(size=B * per)) * np.repeat(scale_per_block, per)

    same = np.full(B, 2.7)
    cov = resplit_coverage(draw(same), blk, draw(same), blk, blocks, np.full(B, per), share=1 / 3,
                           num_splits=100, seed=0)
    np.testing.assert_allclose(cov.mean(0), [ONE_SIGMA_LEVEL, 0.95], atol=0.01)
    mixed = np.exp(rng.normal(scale=0.6, size=B))
    cov_mixed = resplit_coverage(draw(mixed), blk, draw(mixed), blk, blocks, np.full(B, per), share=1 / 3,
                                 num_splits=100, seed=0)
    assert cov_mixed[:, 0].std() > 3 * cov[:, 0].std()
    assert abs(cov_mixed[:, 0].mean() - ONE_SIGMA_LEVEL) < 0.05


def test_resplit_coverage_matches_scipy_quantiles_for_one_split():
    """With share close to 1 every block but the last calibrates; the coverage then equals the
    share of scored |z| below the calibration errors' empirical quantiles (numpy 'linear')."""
    rng = np.random.default_rng(1)
    cal_z = np.abs(rng.standard_t(3, size=400))
    cal_b = np.repeat(np.arange(4), 100)
    score_z = np.abs(rng.standard_t(3, size=50))
    score_b = np.full(50, 7)  # a block that never calibrates
    cov = resplit_coverage(cal_z, cal_b, score_z, score_b, np.arange(4), np.full(4, 100), share=0.99,
                           levels=(0.5, 0.9), num_splits=3)
    q = stats.mstats.mquantiles(cal_z, [0.5, 0.9], alphap=1, betap=1)  # = numpy's linear quantile
    np.testing.assert_allclose(cov, np.tile([(score_z <= q[0]).mean(), (score_z <= q[1]).mean()], (3, 1)))


def test_resplit_coverage_rejects_bad_input():
    with pytest.raises(ValueError, match="share"):
        resplit_coverage(np.ones(60), np.zeros(60), np.ones(3), np.ones(3), np.array([0]), np.array([60]), share=1.0)
    with pytest.raises(ValueError, match="equal shapes"):
        resplit_coverage(np.ones(60), np.zeros(59), np.ones(3), np.ones(3), np.array([0]), np.array([60]), share=0.5)


def test_calibration_views_at_several_fractions_and_neighbours(tiny_scene):
    """Each pair gets one camera per fraction f: rotation at geodesic angle f * a_ij from the first
    view, centre on the arc at the interpolated distance from the scene centre; with 2 neighbours
    the pairs are a superset of the 1-neighbour pairs. Fractions outside (0, 1) are refused."""
    from scipy.spatial.transform import Rotation

    from stochastic_fields.cameras import camera_centres
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene, split_every=5)
    fractions = (0.25, 0.5, 0.75)
    cams, near, far, pairs = calibration_views(ds, neighbours=2, fractions=fractions)
    _, _, _, pairs1 = calibration_views(ds)
    assert set(pairs1) <= set(pairs) and len(pairs) == len(fractions) * len(set(pairs))
    centres = camera_centres(ds.cameras).double()
    o = ds.aabb.double().mean(0)
    R_all = ds.cameras.extrinsics.double()[:, :3, :3].numpy()
    for p, (i, j) in enumerate(pairs):
        f = fractions[p % len(fractions)]
        R = cams.extrinsics.double()[p, :3, :3].numpy()
        a_i = (Rotation.from_matrix(R) * Rotation.from_matrix(R_all[i]).inv()).magnitude()
        a_ij = (Rotation.from_matrix(R_all[j]) * Rotation.from_matrix(R_all[i]).inv()).magnitude()
        assert a_i == pytest.approx(f * a_ij, abs=1e-5)
        ci, cj = centres[i] - o, centres[j] - o
        direction = (1 - f) * ci + f * cj
        expected = o + direction / direction.norm() * ((1 - f) * ci.norm() + f * cj.norm())
        torch.testing.assert_close(camera_centres(cams).double()[p], expected, atol=1e-4, rtol=0)
    for bad in [(0.0,), (1.0,), ()]:
        with pytest.raises(ValueError, match="fractions"):
            calibration_views(ds, fractions=bad)
    with pytest.raises(ValueError, match="neighbours"):
        calibration_views(ds, neighbours=0)


def test_plot_resplit_coverage_writes_a_png_and_refuses_nothing_to_plot(tmp_path):
    from stochastic_fields.plots import plot_resplit_coverage

    rng = np.random.default_rng(0)
    cov = {"a": rng.uniform(0.5, 1.0, size=(40, 2)), "b": rng.uniform(0.5, 1.0, size=(40, 2))}
    path = plot_resplit_coverage(cov, {"a": [0.7, 0.96], "b": [0.6, 0.9]}, (ONE_SIGMA_LEVEL, 0.95),
                                 tmp_path / "sub" / "resplit.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]
    with pytest.raises(ValueError, match="at least one scene"):
        plot_resplit_coverage({}, {}, (0.5,), tmp_path / "x.png")


def test_pair_visible_points_both_or_either():
    """A calibration view renders the kept points both views of its pair observed, or either's (study 38)."""
    from types import SimpleNamespace

    from stochastic_fields.calibration import pair_visible_points

    capture = SimpleNamespace(xyz=np.zeros((6, 3)), visible=[np.array([0, 1, 2]), np.array([2, 3, 4]), np.array([5])])
    keep = np.array([True, True, True, False, True, True])
    assert [list(v) for v in pair_visible_points(capture, [(0, 1)], keep)] == [[2]]
    assert [list(v) for v in pair_visible_points(capture, [(0, 1), (1, 2)], keep, pair_points="either")] == \
        [[0, 1, 2, 4], [2, 4, 5]]
    no_tracks = SimpleNamespace(xyz=np.zeros((3, 3)), visible=None)
    assert [list(v) for v in pair_visible_points(no_tracks, [(0, 1)], np.array([True, False, True]),
                                                 pair_points="either")] == [[0, 2]]
    with pytest.raises(ValueError, match="pair points"):
        pair_visible_points(capture, [(0, 1)], keep, pair_points="any")


def test_calibration_renders_more_points_with_either_view(tmp_path):
    """``pair_points="either"`` renders more points than "both" where a pair's views saw different points
    (a pixel keeps its nearest point, so a both-point may give way to a nearer either-point); the map's
    source says which points it was fitted on, and ``calibrate_run`` fits on them."""
    from stochastic_fields.calibration import calibrate_run, depth_calibration_renders

    from conftest import train_tiny_synthetic_run

    model, ds = train_tiny_synthetic_run(tmp_path)
    both = depth_calibration_renders(model, ds, points="held-out")
    either = depth_calibration_renders(model, ds, points="held-out", pair_points="either")
    pairs_both = set(zip(both["view"].tolist(), both["index"].tolist()))
    pairs_either = set(zip(either["view"].tolist(), either["index"].tolist()))
    shared = pairs_both & pairs_either
    assert len(pairs_either) > len(pairs_both) and len(shared) >= 0.9 * len(pairs_both)
    assert "either view of the pair" in either["source"] and "either view" not in both["source"]
    cal = calibrate_run(tmp_path, model=model, dataset=ds, free_space=False, progress=False, pair_points="either")
    assert "either view of the pair" in cal.depth.source
