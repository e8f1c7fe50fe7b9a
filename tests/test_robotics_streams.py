"""ROS 2 bag and rerun recording of an export, read back with rosbags and rerun-sdk; the planner
commands (occupancy, free-path) on a run folder; the camera in the eval npz."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_export import ExactDepthModel, run_dir  # noqa: F401  (fixture reused: a tiny-preset run folder)

from stochastic_fields.products.export import ExportOptions, dataset_view_specs, export_views

VIEWS = [1, 2]


@pytest.fixture(scope="module")
def dataset(tiny_scene):
    from stochastic_fields.data import load_dataset

    return load_dataset(tiny_scene)


@pytest.fixture(scope="module")
def export_dir(tiny_scene, dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    model = ExactDepthModel(tiny_scene / "scene.ply")
    opts = ExportOptions(formats=("npz",), metres_per_unit=0.5, fuse=True, progress=False)
    export_views(model, dataset_view_specs(dataset, VIEWS), out, opts)
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_rosbag_reads_back(tmp_path, export_dir, storage):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    from stochastic_fields.cli import main
    from stochastic_fields.products.pointcloud import read_ply

    bag = tmp_path / "bag"
    assert main(["rosbag", "--export", str(export_dir), "--out", str(bag), "--storage", storage]) == 0
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs: dict[str, list] = {}
    with Reader(bag) as reader:
        for conn, stamp, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append((stamp, ts.deserialize_cdr(raw, conn.msgtype)))
    assert {t: len(v) for t, v in msgs.items()} == {t: 2 for t in ("/camera/depth/image", "/camera/depth/std",
                                                                   "/camera/depth/camera_info", "/camera/color/image",
                                                                   "/camera/points", "/tf")}
    for k, v in enumerate(VIEWS):
        z = np.load(export_dir / "views" / f"view_{v:03d}.npz")
        stamp, img = msgs["/camera/depth/image"][k]
        assert stamp == k * 100_000_000 and img.encoding == "32FC1" and img.header.frame_id == f"view_{v:03d}_optical"
        depth = np.frombuffer(img.data, "<f4").reshape(img.height, img.width)
        valid = z["valid"]
        np.testing.assert_array_equal(depth[valid], (z["depth_mean"][valid].astype(np.float64) * 0.5).astype(np.float32))
        assert np.all(np.isnan(depth[~valid]))
        std = np.frombuffer(msgs["/camera/depth/std"][k][1].data, "<f4").reshape(img.height, img.width)
        np.testing.assert_allclose(std[valid], z["depth_std"][valid] * 0.5, rtol=1e-6)
        info = msgs["/camera/depth/camera_info"][k][1]
        K = np.asarray(info.k).reshape(3, 3)
        np.testing.assert_allclose(K[:2, 2], z["intrinsics"][:2, 2] - 0.5)
        assert info.width == img.width and info.distortion_model == "plumb_bob"
        colour = msgs["/camera/color/image"][k][1]
        assert colour.encoding == "rgb8" and len(colour.data) == 3 * img.width * img.height
        # the TF is the camera pose in metres: its translation is the camera centre * 0.5
        tf = msgs["/tf"][k][1].transforms[0]
        w2c = z["world_to_camera"]
        centre = -w2c[:3, :3].T @ w2c[:3, 3] * 0.5
        np.testing.assert_allclose([tf.transform.translation.x, tf.transform.translation.y,
                                    tf.transform.translation.z], centre, rtol=1e-6)
        from scipy.spatial.transform import Rotation

        r = tf.transform.rotation
        np.testing.assert_allclose(Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix(), w2c[:3, :3].T, atol=1e-6)
        # PointCloud2: fields and values equal the PLY's (metres)
        pc = msgs["/camera/points"][k][1]
        names = [f.name for f in pc.fields]
        assert names == ["x", "y", "z", "rgb", "depth_std", "confidence"] and all(f.datatype == 7 for f in pc.fields)
        rows = np.frombuffer(pc.data, "<f4").reshape(pc.width, len(names))
        cloud, _ = read_ply(export_dir / "clouds" / f"view_{v:03d}.ply")
        np.testing.assert_allclose(rows[:, :3], cloud.positions * 0.5, rtol=1e-6)
        np.testing.assert_allclose(rows[:, 4], cloud.attributes["depth_std"] * 0.5, rtol=1e-6)
        np.testing.assert_array_equal(rows[:, 5], cloud.attributes["confidence"].astype(np.float32))


def test_rosbag_needs_a_scale(tmp_path, tiny_scene, dataset, capsys):
    from stochastic_fields.cli import main

    out = tmp_path / "export"
    export_views(ExactDepthModel(tiny_scene / "scene.ply"), dataset_view_specs(dataset, [1]), out,
                 ExportOptions(formats=("npz",), progress=False))
    assert main(["rosbag", "--export", str(out), "--out", str(tmp_path / "bag")]) == 2
    assert "no metric scale" in capsys.readouterr().err
    assert main(["rosbag", "--export", str(tmp_path / "nothing"), "--out", str(tmp_path / "bag")]) == 2


def test_rerun_recording_reads_back(tmp_path, export_dir):
    from stochastic_fields.cli import main
    from stochastic_fields.products.pointcloud import read_ply
    from stochastic_fields.products.rerun_log import read_rerun_entities

    rrd = tmp_path / "run.rrd"
    assert main(["rerun", "--export", str(export_dir), "--out", str(rrd)]) == 0
    ents = read_rerun_entities(rrd)
    for v in VIEWS:
        base = f"/world/cameras/view_{v:03d}"
        assert {base, f"{base}/colour", f"{base}/depth", f"{base}/depth_std", f"/world/points/view_{v:03d}"} <= set(ents)
        pin = ents[base]
        cols = set().union(*(b.schema.names for b in pin))
        assert {"Pinhole:image_from_camera", "Transform3D:translation"} <= cols
        pts = ents[f"/world/points/view_{v:03d}"][0]
        conf = np.asarray(pts.column("confidence").to_pylist()[0], np.float32)
        cloud, _ = read_ply(export_dir / "clouds" / f"view_{v:03d}.ply")
        np.testing.assert_array_equal(conf, cloud.attributes["confidence"].astype(np.float32))
        pos = np.asarray(pts.column("Points3D:positions").to_pylist()[0], np.float32)
        np.testing.assert_allclose(pos, cloud.positions.astype(np.float32), rtol=1e-6)
        depth = ents[f"{base}/depth"][0]
        assert depth.column("DepthImage:meter").to_pylist()[0][0] == pytest.approx(2.0)  # 1 / metres_per_unit
    assert "/world/fused" in ents


# ----------------------------------------------------------------------------- planner commands on a run
def test_occupancy_and_free_path_commands(tmp_path, run_dir):  # noqa: F811
    from stochastic_fields.cli import main
    from stochastic_fields.products.occupancy_map import probability_density_exceeds, read_occupancy_npz
    from stochastic_fields.trainer import load_trained_model

    out = tmp_path / "occ"
    assert main(["occupancy", "--run", str(run_dir), "--out", str(out), "--max-cells", "40000", "--quiet"]) == 0
    occ = read_occupancy_npz(out / "occupancy.npz")
    meta = json.loads((out / "occupancy.json").read_text())
    assert (out / "occupancy.ot").is_file() and meta["voxel_size"] == pytest.approx(occ.voxel_size)
    assert np.prod(occ.shape) <= 40000 * 1.2
    _, model, _ = load_trained_model(run_dir, device="cpu")
    centres = torch.from_numpy(occ.centres()[:200]).float()
    with torch.no_grad():
        loc, scale, offsets = model.field.density_head_params(centres)  # the default's heads: their mixture
    assert offsets is not None
    p = probability_density_exceeds(loc.double(), scale.double(), occ.density_threshold, offsets.double())
    np.testing.assert_allclose(occ.probability[:200], p.float().numpy(), rtol=1e-4, atol=1e-6)
    # free-path: the CLI's answer equals the API's with the same seed and step
    lo, hi = occ.origin, occ.origin + np.asarray(occ.shape) * occ.voxel_size
    mid = (lo + hi) / 2
    q = {"segments": [[lo.tolist(), hi.tolist()], [mid.tolist(), (mid + 0.01).tolist()]],
         "path": [lo.tolist(), mid.tolist(), hi.tolist()]}
    (tmp_path / "q.json").write_text(json.dumps(q))
    assert main(["free-path", "--run", str(run_dir), "--queries", str(tmp_path / "q.json"), "--step", "0.05",
                 "--num-draws", "64", "--out", str(tmp_path / "a.json")]) == 0
    ans = json.loads((tmp_path / "a.json").read_text())
    from stochastic_fields.products.free_path import segment_free_probability

    seg = torch.tensor(q["segments"], dtype=torch.float64)
    ref = segment_free_probability(lambda x: model.field.density_head_params(x.float()), seg[:, 0], seg[:, 1],
                                   num_draws=64, step=0.05, shared_noise=model.render_settings.shared_noise,
                                   generator=torch.Generator().manual_seed(0))
    np.testing.assert_allclose(ans["segments"]["probability_free"], ref.probability.numpy())
    np.testing.assert_allclose(ans["segments"]["stderr"], ref.stderr.numpy())
    assert len(ans["path"]["segments"]["probability_free"]) == 2
    assert ans["path"]["whole"]["probability_free"][0] <= min(ans["path"]["segments"]["probability_free"])
    (tmp_path / "bad.json").write_text(json.dumps({"segments": [[1, 2, 3]]}))
    assert main(["free-path", "--run", str(run_dir), "--queries", str(tmp_path / "bad.json")]) == 2


def test_eval_npz_carries_camera_and_units(tmp_path, run_dir, dataset):  # noqa: F811
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.trainer import load_trained_model

    _, model, ds = load_trained_model(run_dir, device="cpu")
    evaluate(model, ds, tmp_path, views=[3], options=model.render_options(num_draws=2), progress=False)
    z = np.load(tmp_path / "views" / "view_003.npz")
    np.testing.assert_allclose(z["world_to_camera"], dataset.cameras.extrinsics[3].double().numpy())
    assert z["intrinsics"].shape == (3, 3) and str(z["units"]) == "scene units"
    assert float(z["far"]) == pytest.approx(float(dataset.far[3]))


def test_plan_path_example_runs(tmp_path, run_dir, monkeypatch, capsys):  # noqa: F811
    """examples/plan_path.py end to end on a run folder: prints the free-path probability of each
    segment and of the whole path, draws the picture."""
    import runpy
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "plan_path.py"
    png = tmp_path / "plan.png"
    monkeypatch.setattr(sys, "argv", [str(script), "--run", str(run_dir), "--start=-1.5,0,0.3", "--goal=1.5,0,0.3",
                                      "--num-draws", "16", "--png", str(png)])
    runpy.run_path(str(script), run_name="__main__")
    out = capsys.readouterr().out
    assert "segment 0:" in out and "whole path: P(transmittance > 0.5) =" in out and png.is_file()
