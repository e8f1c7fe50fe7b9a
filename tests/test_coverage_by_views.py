"""Which training views observe a point (tracks, or the depth-map test of dense-depth scenes) and the
coverage-by-group table and plot of benchmarks/studies/coverage_by_views.py (docs/uncertainty.md)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stochastic_fields.capture_points import (CapturePoints, backproject_pixels, depth_map_observes,
                                              load_capture_points, training_view_counts)


def test_training_view_counts_from_tracks_by_hand():
    """Counts over the training views only: a test view's track entries do not count."""
    xyz = np.zeros((4, 3))
    visible = [np.array([0, 1]), np.array([1, 2]), np.array([0, 1, 2, 3]), np.array([1])]
    capture = CapturePoints(xyz, np.zeros(4, np.int8), "colmap", visible)
    dataset = SimpleNamespace(train_indices=[0, 1, 3], root="scene")
    assert training_view_counts(dataset, capture).tolist() == [1, 3, 1, 0]
    with pytest.raises(ValueError, match="no tracks"):
        training_view_counts(dataset, CapturePoints(xyz, np.zeros(4, np.int8), "sfm", None))
    with pytest.raises(ValueError, match="no dense depth"):
        training_view_counts(SimpleNamespace(train_indices=[0], root="scene", depths=None), capture, xyz)


def test_depth_map_observes_surface_points_and_not_occluded_or_outside_ones(tiny_scene):
    """A training view's own back-projected surface pixel is observed by that view; the same point
    pushed 10% further along the view's ray (behind the surface) is not, nor is a point behind the
    camera. The stand-in points' tracks are exactly the depth-map test, and every stand-in point is
    observed by the view it came from at least."""
    from stochastic_fields.cameras import camera_to_world, intrinsics_3x3
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene)
    v = ds.train_indices[1]
    K, c2w = intrinsics_3x3(ds.cameras).double()[v], camera_to_world(ds.cameras).double()[v]
    depth = ds.depths[v].double()
    rows, cols = torch.nonzero(depth > 0, as_tuple=True)
    rows, cols = rows[::50], cols[::50]
    surface = backproject_pixels(K, c2w, rows, cols, depth[rows, cols])
    behind = backproject_pixels(K, c2w, rows, cols, 1.1 * depth[rows, cols])
    at_back = c2w[:3, 3] - 5.0 * c2w[:3, 2]  # 5 units behind the camera, on its axis
    assert depth_map_observes(ds, surface.numpy(), v).all()
    assert not depth_map_observes(ds, behind.numpy(), v).any()
    assert not depth_map_observes(ds, at_back[None].numpy(), v).any()

    capture = load_capture_points(ds)
    from_tracks = training_view_counts(ds, capture)
    assert np.array_equal(from_tracks, training_view_counts(ds, capture, capture.xyz))
    assert from_tracks.min() >= 1 and from_tracks.max() <= len(ds.train_indices)


def test_coverage_table_by_hand_and_its_plot(tmp_path, load_script):
    """Shares inside the bounds per group, by hand; empty groups are left out; 'all' pools every point."""
    script = load_script("benchmarks/studies/coverage_by_views.py")
    abs_z = np.array([0.5, 1.5, 2.5, 0.2, 3.0, 0.9])
    counts = np.array([0, 0, 0, 2, 2, 7])
    rows = script.coverage_table(abs_z, counts, bounds=np.array([1.0, 2.0]), raw_bounds=np.array([0.6, 2.6]))
    assert [r["group"] for r in rows] == ["0", "2", "5+", "all"]
    by = {r["group"]: r for r in rows}
    assert by["0"]["points"] == 3 and by["0"]["coverage"] == pytest.approx([1 / 3, 2 / 3])
    assert by["0"]["coverage_raw"] == pytest.approx([1 / 3, 1.0])
    assert by["2"]["coverage"] == pytest.approx([0.5, 0.5]) and by["2"]["median_abs_z"] == pytest.approx(1.6)
    assert by["5+"]["coverage"] == pytest.approx([1.0, 1.0]) and by["5+"]["coverage_raw"] == pytest.approx([0.0, 1.0])
    assert by["all"]["points"] == 6 and by["all"]["coverage"] == pytest.approx([3 / 6, 4 / 6])

    from stochastic_fields.plots import plot_coverage_by_group

    path = plot_coverage_by_group({"a": rows, "b": rows[:2]}, (0.6827, 0.95), tmp_path / "c.png", title="t")
    assert path.is_file() and path.stat().st_size > 1000
    with pytest.raises(ValueError, match="at least one scene"):
        plot_coverage_by_group({}, (0.6827, 0.95), tmp_path / "d.png")
