"""benchmarks/registration.py scores a prepared scene against the known cameras of its photos: a scene
whose poses are the known ones moved by a similarity scores zero, and a known perturbation of one
camera is measured (LLFF and Blender references alike)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench(load_script):
    return load_script("benchmarks/registration.py")


def _rotation_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_object_scene_scores_its_own_poses_up_to_a_similarity(bench, shared_data, tmp_path):
    """Ten of lego's training renders with their transforms_train.json poses moved by a similarity
    (scale 2.5, a rotation, a shift), written as a prepared scene's transforms.json (OpenGL
    camera-to-world, nerfstudio layout): every error is ~0; one camera turned by 0.8 degrees about
    its own axis reads 0.8 degrees."""
    source = json.loads((shared_data / "nerf_synthetic" / "lego" / "transforms_train.json").read_text())
    assert bench.photo_folder("lego").resolve() == (shared_data / "nerf_synthetic" / "lego" / "train").resolve()
    s, R, t = 2.5, _rotation_z(30.0) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), np.array([0.3, -1.0, 2.0])
    frames = []
    (tmp_path / "images").mkdir()
    for frame in source["frames"][::10]:
        name = frame["file_path"].split("/")[-1] + ".png"
        (tmp_path / "images" / name).symlink_to(shared_data / "nerf_synthetic" / "lego" / "train" / name)
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        moved = np.eye(4)
        moved[:3, :3], moved[:3, 3] = R @ c2w[:3, :3], s * R @ c2w[:3, 3] + t
        frames.append({"file_path": f"images/{name}", "transform_matrix": moved.tolist()})
    focal = 0.5 * 800 / math.tan(0.5 * source["camera_angle_x"])
    scene = {"fl_x": focal, "fl_y": focal, "cx": 400.0, "cy": 400.0, "w": 800, "h": 800, "near": 2.0, "far": 6.0,
             "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(scene))
    errors = bench.score(tmp_path, "lego")
    assert errors["centre_error_max"] < 1e-6 and errors["rotation_error_max_deg"] < 1e-4
    assert errors["scale"] == pytest.approx(1 / 2.5, rel=1e-6)
    turned = np.asarray(frames[3]["transform_matrix"])
    turned[:3, :3] = turned[:3, :3] @ _rotation_z(0.8)  # about the camera's own optical axis
    frames[3]["transform_matrix"] = turned.tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(scene))
    errors = bench.score(tmp_path, "lego")
    assert errors["rotation_error_max_deg"] == pytest.approx(0.8, abs=1e-4) and errors["centre_error_max"] < 1e-6
