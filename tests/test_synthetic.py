"""The synthetic scene: depths, colours and poses checked against independent mesh ray casts."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pytest
import torch
import trimesh

from stochastic_fields.cameras import backproject_depths, generate_rays
from stochastic_fields.data import load_dataset, make_synthetic_scene
from stochastic_fields.data.synthetic import AMBIENT, BACKGROUND, LIGHT_DIRECTION, ring_cameras


@pytest.fixture(scope="module")
def scene(tiny_scene):
    ds = load_dataset(tiny_scene)
    meta = json.loads((tiny_scene / "transforms.json").read_text())
    mesh = trimesh.load(tiny_scene / "scene.ply", process=False)
    return ds, meta, mesh


def test_files_and_loaded_shapes(tiny_scene, scene):
    ds, meta, mesh = scene
    assert (tiny_scene / "scene.ply").is_file() and len(meta["frames"]) == 20
    assert sorted(p.name for p in tiny_scene.iterdir()) == ["depth", "images", "scene.ply", "transforms.json"]
    assert not [p for p in tiny_scene.rglob(".*")]  # no temporary files left behind
    assert ds.images.shape == (20, 48, 64, 3) and ds.depths.shape == (20, 48, 64)
    assert ds.train_indices == [0, 5, 10, 15]  # the file's split_every hint
    assert ds.background == tuple(BACKGROUND)
    frac = float(ds.depth_mask.float().mean())
    assert 0.3 < frac < 0.99  # both surface and background are in view
    # background pixels are exactly white, surfaces are not
    miss = ~ds.depth_mask
    assert torch.all(ds.images[miss] == 1.0)
    assert float(ds.images[ds.depth_mask].mean()) < 0.9
    torch.testing.assert_close(ds.aabb, torch.tensor(meta["aabb"], dtype=torch.float32))
    assert float(ds.near[0]) == pytest.approx(meta["near"]) and float(ds.far[0]) == pytest.approx(meta["far"])
    assert float(ds.depths[ds.depth_mask].min()) > meta["near"] and float(ds.depths.max()) < meta["far"]


def test_backprojected_depth_lies_on_the_mesh(scene):
    ds, meta, mesh = scene
    pts = backproject_depths(ds.cameras, ds.depths)  # via generate_rays: origin + depth / z_scale * dir
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    dist = rc.compute_distance(o3d.core.Tensor(pts.numpy().astype(np.float32))).numpy()
    assert pts.shape[0] == int(ds.depth_mask.sum())
    assert float(np.max(dist)) < 1e-4, np.max(dist)
    # and the points sit inside the aabb hint, the ground (z = 0) 5% of the box's largest extent
    # (the ground's 4 units) above the box's floor: inside the field, not on its face
    assert bool(torch.all((pts >= ds.aabb[0]) & (pts <= ds.aabb[1])))
    lo, hi = mesh.bounds
    assert float(ds.aabb[0, 2]) == pytest.approx(lo[2] - 0.05 * max(hi - lo), abs=1e-6)
    torch.testing.assert_close(ds.aabb[1] - ds.aabb[0], torch.tensor(hi - lo + 0.1 * max(hi - lo), dtype=torch.float32))


def _reference_rays_from_json(meta, views, rows, cols):
    """Independent pinhole rays from the json alone: K from fl/cx/cy, OpenGL c2w (y up, z back)."""
    o, d, zdir = [], [], []
    for v, i, j in zip(views, rows, cols):
        c2w = np.asarray(meta["frames"][v]["transform_matrix"])
        x = (j + 0.5 - meta["cx"]) / meta["fl_x"]
        y = (i + 0.5 - meta["cy"]) / meta["fl_y"]
        d_gl = np.array([x, -y, -1.0])  # OpenGL camera: image down = -y, forward = -z
        world = c2w[:3, :3] @ d_gl
        o.append(c2w[:3, 3])
        d.append(world / np.linalg.norm(world))
        zdir.append(-c2w[:3, 2])  # optical axis in world
    return np.array(o), np.array(d), np.array(zdir)


def moller_trumbore(o, d, tris):
    """Naive float64 first hits of rays o, d [n, 3] on triangles [F, 3, 3]: (t [n] inf on miss, face [n])."""
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    p = np.cross(d[:, None, :], e2[None])  # [n, F, 3]
    det = np.sum(e1[None] * p, -1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o[:, None, :] - v0[None]
    u = np.sum(s * p, -1) * inv
    q = np.cross(s, e1[None])
    v = np.sum(d[:, None, :] * q, -1) * inv
    t = np.sum(e2[None] * q, -1) * inv
    valid = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(valid, t, np.inf)
    return t.min(1), t.argmin(1)


def test_depth_and_colour_match_independent_raycast(tiny_scene, scene):
    ds, meta, mesh = scene
    rng = np.random.default_rng(1)
    n = 300
    views, rows, cols = rng.integers(0, 20, n), rng.integers(0, 48, n), rng.integers(0, 64, n)
    o, d, axis = _reference_rays_from_json(meta, views, rows, cols)
    t, face = moller_trumbore(o, d, np.asarray(mesh.triangles, dtype=np.float64))
    hit = np.isfinite(t)
    depth_ref = np.where(hit, np.where(hit, t, 0.0) * np.sum(d * axis, 1), 0.0)  # camera-z of the hit
    depth = ds.depths[views, rows, cols].numpy()
    # grazing rays may disagree between the two ray casters; they are rare
    agree_hit = (depth > 0) == hit
    assert agree_hit.mean() > 0.98
    both = hit & (depth > 0)
    np.testing.assert_allclose(depth[both], depth_ref[both], rtol=1e-4, atol=1e-4)
    # colour = face albedo * (ambient + (1 - ambient) max(0, n.l)), normal turned to the camera
    normals = mesh.face_normals[face[both]]
    normals = np.where(np.sum(normals * d[both], 1, keepdims=True) > 0, -normals, normals)
    light = np.asarray(LIGHT_DIRECTION) / np.linalg.norm(LIGHT_DIRECTION)
    albedo = mesh.visual.face_colors[face[both], :3] / 255.0
    rgb_ref = albedo * (AMBIENT + (1 - AMBIENT) * np.clip(normals @ light, 0, None))[:, None]
    png = np.stack([iio.imread(tiny_scene / meta["frames"][v]["file_path"]) for v in range(20)]) / 255.0
    rgb = png[views[both], rows[both], cols[both]]
    same_face = np.abs(rgb - rgb_ref).max(1) <= 0.5 / 255 + 1e-9  # 8-bit rounding
    assert same_face.mean() > 0.97  # the rest: rays that hit a neighbouring face at an edge
    missed = ~hit & (depth == 0)
    np.testing.assert_allclose(png[views[missed], rows[missed], cols[missed]], 1.0)


def test_pose_round_trip(scene):
    ds, meta, mesh = scene
    K, w2c = ring_cameras(20, 64, 48, seed=meta["seed"])
    torch.testing.assert_close(ds.cameras.extrinsics, w2c.float(), rtol=0, atol=1e-6)
    torch.testing.assert_close(ds.cameras.intrinsics[:, :3, :3], K.float())
    # every camera looks at the scene centre: its optical-axis ray passes within a hair of it
    rays = generate_rays(ds.cameras, 1.0, 2.0, pixels=torch.tensor([[[32.0, 24.0]]]).expand(20, 1, 2))
    centre = torch.tensor([0.0, 0.0, 0.3])
    to_c = centre - rays.origins[:, 0]
    closest = to_c - (to_c * rays.directions[:, 0]).sum(-1, keepdim=True) * rays.directions[:, 0]
    assert float(closest.norm(dim=-1).max()) < 1e-5
    assert bool(torch.all(rays.origins[:, 0, 2] > 0.3))  # upper hemisphere


def test_seed_determinism_and_cli(tmp_path, load_script):
    a = make_synthetic_scene(tmp_path / "a", num_views=3, width=16, height=12, seed=2)
    b = make_synthetic_scene(tmp_path / "b", num_views=3, width=16, height=12, seed=2)
    c = make_synthetic_scene(tmp_path / "c", num_views=3, width=16, height=12, seed=3)
    def png(root):
        return (root / "images" / "frame_001.png").read_bytes()

    assert png(a) == png(b) and png(a) != png(c)
    cli = load_script("data_tools/make_synthetic_scene.py")
    out = cli.main([str(tmp_path / "cli"), "--num-views", "5", "--width", "20", "--height", "10"])
    ds = load_dataset(out)
    assert ds.images.shape == (5, 10, 20, 3) and ds.train_indices == [0] and ds.test_indices == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="num_views"):
        make_synthetic_scene(tmp_path / "bad", num_views=1)
    # field of view of the default cameras: 55 degrees horizontally
    meta = json.loads((out / "transforms.json").read_text())
    assert 2 * math.degrees(math.atan(0.5 * 20 / meta["fl_x"])) == pytest.approx(55.0)
