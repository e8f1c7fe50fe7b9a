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


def _look_at(centre: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes) at ``centre`` looking at the origin, z up."""
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    M = np.eye(4)
    M[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    M[:3, 3] = centre
    return M


def test_turned_cameras_are_found_after_a_fit_on_the_others(load_script):
    """Twelve cameras on a ring around an object, moved by a similarity; two of them put on the other
    side of the object, looking back at it (turned 180 degrees about the vertical): those two are
    reported, about 180 degrees and 100% of the extent off, the ten others not."""
    script = load_script("benchmarks/registration_consistency.py")
    angles = np.radians(np.arange(12) * 30.0)
    ref = np.stack([_look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 1.0])) for a in angles])
    ours = ref.copy()
    for i in (2, 7):  # mirrored through the vertical axis
        ours[i] = _look_at(ref[i, :3, 3] * np.array([-1.0, -1.0, 1.0]))
    s, R, t = 0.7, _rotation_z(40.0), np.array([1.0, 2.0, -0.5])
    moved = ours.copy()
    moved[:, :3, :3] = R @ ours[:, :3, :3]
    moved[:, :3, 3] = s * ours[:, :3, 3] @ R.T + t
    turned = script.turned_cameras([f"c{i}" for i in range(12)], moved, ref)
    assert sorted(turned) == ["c2", "c7"]
    for centre, angle in turned.values():
        assert angle == pytest.approx(180.0, abs=1e-6) and centre == pytest.approx(1.0, abs=1e-6)


def test_sampson_distance_of_a_match_off_its_epipolar_line(load_script):
    """Second camera one unit along +x, no rotation: E = [t]x, epipolar lines are the image rows.
    A match one unit of normalised height off its row lies 1 / sqrt(2) from it in Sampson's first-order
    distance (the error split between the two points); a match on its row, 0."""
    script = load_script("benchmarks/registration_consistency.py")
    E = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # [t]x R with t = (1, 0, 0), R = I
    p1 = np.array([[0.2, 0.1, 1.0], [0.2, 0.1, 1.0]])
    p2 = np.array([[-0.3, 0.1, 1.0], [-0.3, 1.1, 1.0]])
    np.testing.assert_allclose(script.sampson_distance(E, p1, p2), [0.0, 1 / math.sqrt(2)], atol=1e-12)
