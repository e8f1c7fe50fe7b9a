"""``stochastic-fields prepare``: photos or a video -> pycolmap SfM -> a scene folder (issue 17).

The fern test is the reference: its 20 ``images_8`` photos, without their poses, must all
register, and after a similarity alignment the recovered cameras must agree with LLFF's
``poses_bounds.npy`` (camera centres within 2% of the capture's extent, rotations within 2 degrees).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from stochastic_fields.cameras import camera_centres, camera_to_world
from stochastic_fields.data import DatasetError, load_dataset
from stochastic_fields.data.colmap import world_to_camera
from stochastic_fields.data.prepare import (FAILURES_LISTED, area_downscale_rgba, extract_video_frames,
                                               failure_summary, mapping_report, prepare, refine_robust, sharpness,
                                               write_downscaled)
from stochastic_fields.pose_alignment import pose_errors, similarity_align

#: Threads for pycolmap in tests (the test machine has 2 cores shared with other work).
THREADS = 1


def test_similarity_align_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(12, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))
    s, R_hat, t = similarity_align(src, 2.5 * src @ R.T + [1.0, -2.0, 3.0])
    assert s == pytest.approx(2.5, rel=1e-12)
    np.testing.assert_allclose(R_hat, R, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-12)


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues: the rotation by ``degrees`` about ``axis``."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def test_pose_errors_are_zero_up_to_a_similarity_and_measure_a_known_perturbation():
    rng = np.random.default_rng(1)
    ref = np.tile(np.eye(4), (6, 1, 1))
    for i in range(6):
        ref[i, :3, :3] = _rotation(rng.normal(size=3), rng.uniform(0, 90))
        ref[i, :3, 3] = rng.normal(size=3)
    Rs, s, t = _rotation([1.0, 2.0, 0.5], 40.0), 0.3, np.array([2.0, -1.0, 0.5])
    ours = ref.copy()  # the same cameras in another frame: x -> (Rs^T (x - t)) / s
    ours[:, :3, :3] = Rs.T @ ref[:, :3, :3]
    ours[:, :3, 3] = (ref[:, :3, 3] - t) @ Rs / s
    exact = pose_errors(ours, ref)
    assert exact["scale"] == pytest.approx(s, rel=1e-12)
    assert exact["centre_error_max"] < 1e-12 and exact["rotation_error_max_deg"] < 1e-5
    # poses stored in float32 (as the loaders keep them) still read ~0, not acos's 0.03-degree floor
    assert pose_errors(ours.astype(np.float32), ref.astype(np.float32))["rotation_error_max_deg"] < 1e-3
    turned = ours.copy()
    turned[4, :3, :3] = turned[4, :3, :3] @ _rotation([1.0, 0.0, 0.0], 179.5)  # near the half turn too
    assert pose_errors(turned, ref)["rotation_error_max_deg"] == pytest.approx(179.5, rel=1e-9)
    ours[2, :3, :3] = ours[2, :3, :3] @ _rotation([0.0, 1.0, 1.0], 0.3)  # one camera turned by 0.3 degrees
    assert pose_errors(ours, ref)["rotation_error_max_deg"] == pytest.approx(0.3, rel=1e-6)
    assert pose_errors(ours, ref)["centre_error_max"] < 1e-12
    with pytest.raises(ValueError, match="same cameras"):
        pose_errors(ours[:5], ref)


def test_sharpness_ranks_blur_below_the_original():
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(40, 50, 3))
    blurred = (image + np.roll(image, 1, 0) + np.roll(image, 1, 1) + np.roll(image, (1, 1), (0, 1))) / 4
    assert sharpness(blurred) < 0.5 * sharpness(image)
    # a linear ramp has zero Laplacian: variance exactly 0
    ramp = np.add.outer(np.arange(30.0), np.arange(20.0))
    assert sharpness(ramp) == pytest.approx(0.0, abs=1e-20)


def _pattern(i: int, H: int = 96, W: int = 128) -> np.ndarray:
    """A textured frame that shifts with i (uint8 RGB)."""
    rng = np.random.default_rng(100)
    base = rng.uniform(0, 255, size=(H // 8, W // 8 + 16, 3))
    big = np.kron(base, np.ones((8, 8, 1)))
    return np.ascontiguousarray(big[:, 2 * i: 2 * i + W]).astype(np.uint8)


def test_video_frames_are_the_sharpest_of_each_window(tmp_path):
    """20 frames at 10 fps, fps=2 -> windows of 5; in each window one frame is sharp, the rest blurred."""
    frames = []
    sharp_index = [1, 8, 12, 19]  # one per window of 5
    for i in range(20):
        f = _pattern(i).astype(np.float64)
        if i not in sharp_index:
            for _ in range(3):
                f = (f + np.roll(f, 1, 0) + np.roll(f, 1, 1) + np.roll(f, (1, 1), (0, 1))) / 4
        frames.append(np.round(f).astype(np.uint8))
    video = tmp_path / "walk.mp4"
    iio.imwrite(video, np.stack(frames), plugin="pyav", codec="libx264", fps=10)
    out = extract_video_frames(video, tmp_path / "frames", fps=2.0, progress=False)
    assert [p.name for p in out] == [f"frame_{k:05d}.png" for k in range(1, 5)]
    decoded = list(iio.imiter(video, plugin="pyav"))
    for path, want in zip(out, sharp_index):
        got = iio.imread(path).astype(np.float64)
        errors = [np.abs(got - d.astype(np.float64)).mean() for d in decoded]
        assert int(np.argmin(errors)) == want and errors[want] == 0.0
    # a cap on the number of frames widens the windows: 20 frames, at most 2 kept
    assert len(extract_video_frames(video, tmp_path / "two", fps=10.0, max_frames=2, progress=False)) == 2


def test_bad_input_is_named(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty: no images .* \(it is empty\)"):
        prepare(tmp_path / "empty", tmp_path / "s1", progress=False)
    with pytest.raises(DatasetError, match=r"nothing_here: input does not exist"):
        prepare(tmp_path / "nothing_here", tmp_path / "s2", progress=False)
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        iio.imwrite(photos / f"p{i}.png", _pattern(i))
    (photos / "p1.png").write_bytes(b"\x89PNG broken")
    kept = tmp_path / "kept"  # an --out that holds a user's file: left as it was
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match=r"p1\.png: unreadable image"):
        prepare(photos, kept, progress=False)
    iio.imwrite(photos / "p1.png", _pattern(1)[:80])
    with pytest.raises(DatasetError, match=r"p1\.png: image size 128x80 differs from 128x96 of p0\.png"):
        prepare(photos, tmp_path / "s4", progress=False)
    assert [p.name for p in kept.iterdir()] == ["notes.txt"] and (kept / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "s4").exists() and not any(p.name.startswith(".") for p in tmp_path.iterdir())
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(DatasetError, match=r"a_file: exists and is not a folder"):
        prepare(photos, tmp_path / "a_file", progress=False)
    (photos / "p1.png").unlink()
    with pytest.raises(DatasetError, match=r"photos: only 2 images"):
        prepare(photos, tmp_path / "s5", progress=False)
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200))
    with pytest.raises(DatasetError, match=r"clip\.mp4: cannot open the video"):
        prepare(video, tmp_path / "s6", progress=False)
    with pytest.raises(DatasetError, match=r"notes\.txt: not a video"):
        (tmp_path / "notes.txt").write_text("hi")
        prepare(tmp_path / "notes.txt", tmp_path / "s7", progress=False)


def test_unmatchable_photos_fail_with_reasons(tmp_path):
    """Independent noise images share no geometry: nothing registers, whatever the mapping strategy.

    The error counts the reasons, names at most FAILURES_LISTED images, and points at a file with
    every image and its reason.
    """
    photos = tmp_path / "noise"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(5):
        iio.imwrite(photos / f"n{i}.png", rng.integers(0, 256, size=(96, 128, 3), dtype=np.uint8))
    with pytest.raises(DatasetError) as info:
        prepare(photos, tmp_path / "new" / "scene", num_threads=THREADS, progress=False)
    msg = str(info.value)
    assert "noise: only 0 of 5 images registered (need 3; mapping tried: incremental (incremental 0/5, " \
           "incremental-relaxed 0/5, global 0/5))" in msg
    assert sum(f"n{i}.png: " in msg for i in range(5)) == FAILURES_LISTED == 3
    assert "(and 2 more)" in msg and ("5 x too few matches" in msg or "5 x few SIFT features" in msg)
    # --out is left as it was (here: not created, nor its parent), and no staging folder stays behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]
    assert f"{tmp_path / 'new' / 'scene'} left as it was" in msg
    listing_path = Path(re.search(r"Every image and its reason: (\S+\.json)", msg).group(1))
    assert listing_path.name.startswith("prepare-scene-failures-")
    listing = json.loads(listing_path.read_text())
    listing_path.unlink()
    assert sorted(listing["failed"]) == [f"n{i}.png" for i in range(5)]
    assert listing["mapping_attempts"] == {"incremental": 0, "incremental-relaxed": 0, "global": 0}
    assert all(why.startswith(("too few matches: ", "few SIFT features: ")) for why in listing["failed"].values())


def test_downscaled_rgba_copies_composite_like_the_full_size_photo(tmp_path):
    """A masked object (RGBA, black under a = 0): images_<d> keeps the alpha, averaged premultiplied,
    so the small copy composited on white (as the loaders composite) is the area average of the
    full-size photo composited on white, to 8-bit rounding; straight averaging bleeds the black
    under a = 0 into the border (checked to fail by 0.2 here). RGB photos stay RGB."""
    rng = np.random.default_rng(0)
    H, W = 48, 64
    alpha = np.zeros((H, W))
    alpha[10:38, 12:50] = 1.0
    alpha[10:38, 11] = alpha[9, 12:50] = 0.5  # a soft edge
    rgb = rng.uniform(0.2, 1.0, size=(H, W, 3)) * (alpha[..., None] > 0)
    photo = np.concatenate([rgb, alpha[..., None]], -1)
    iio.imwrite(tmp_path / "obj.png", np.round(photo * 255).astype(np.uint8))
    iio.imwrite(tmp_path / "plain.png", np.round(rgb * 255).astype(np.uint8))
    write_downscaled([tmp_path / "obj.png", tmp_path / "plain.png"], tmp_path / "scene", factors=(2, 4), progress=False)
    exact = np.round(photo * 255) / 255
    on_white = exact[..., :3] * exact[..., 3:] + (1 - exact[..., 3:])
    for d in (2, 4):
        small = iio.imread(tmp_path / "scene" / f"images_{d}" / "obj.png").astype(np.float64) / 255
        assert small.shape == (H // d, W // d, 4)
        composited = small[..., :3] * small[..., 3:] + (1 - small[..., 3:])
        want = on_white.reshape(H // d, d, W // d, d, 3).mean(axis=(1, 3))
        assert np.abs(composited - want).max() < 1.5 / 255
        straight = exact.reshape(H // d, d, W // d, d, 4).mean(axis=(1, 3))
        assert np.abs(straight[..., :3] * straight[..., 3:] + 1 - straight[..., 3:] - want).max() > 0.1
        assert iio.imread(tmp_path / "scene" / f"images_{d}" / "plain.png").shape == (H // d, W // d, 3)
    assert np.array_equal(area_downscale_rgba(rgb, 1), rgb)


def test_failure_summary_counts_kinds_and_lists_a_few():
    failed = {"a.png": "too few matches: x", "b.png": "few SIFT features: only 3", "c.png": "too few matches: y",
              "d.png": "too few matches: z"}
    assert failure_summary(failed, listed=2) == ("3 x too few matches; 1 x few SIFT features. For example a.png: too "
                                                 "few matches: x; b.png: few SIFT features: only 3 (and 2 more)")
    assert mapping_report("global", {"incremental": 0, "global": 7}, 8) == "global (incremental 0/8, global 7/8)"


def _textured_planes(camera_x: float, H: int = 120, W: int = 160, focal: float = 150.0) -> np.ndarray:
    """A pinhole view (OpenCV axes, looking down +z) from (camera_x, 0, 0) of two textured planes:
    a wall at z = 8 and a card at z = 5 (x in [-1.5, 1], y in [-1.2, 1.2]). uint8 RGB [H, W, 3]."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    dx, dy = (u + 0.5 - W / 2) / focal, (v + 0.5 - H / 2) / focal
    image, nearest = np.zeros((H, W, 3)), np.full((H, W), np.inf)
    for seed, z, half_size, rect in ((1, 8.0, 8.0, None), (2, 5.0, 3.0, (-1.5, 1.0, -1.2, 1.2))):
        rng = np.random.default_rng(seed)
        texture = np.kron(rng.uniform(0, 1, size=(64, 64, 3)), np.ones((4, 4, 1)))
        for _ in range(2):  # blur the blocks into blobs SIFT finds at several scales
            texture = (texture + np.roll(texture, 1, 0) + np.roll(texture, 1, 1) + np.roll(texture, (1, 1), (0, 1))) / 4
        x, y = camera_x + dx * z, dy * z
        hit = z < nearest
        if rect is not None:
            hit &= (x > rect[0]) & (x < rect[1]) & (y > rect[2]) & (y < rect[3])
        n = texture.shape[0]
        tu = np.clip((x / half_size * 0.5 + 0.5) * (n - 1), 0, n - 1).astype(int)
        tv = np.clip((y / half_size * 0.5 + 0.5) * (n - 1), 0, n - 1).astype(int)
        image[hit], nearest[hit] = texture[tv[hit], tu[hit]], z
    return (image * 255).round().astype(np.uint8)


def test_small_baseline_capture_registers_through_the_fallback(tmp_path):
    """Eight views along a 0.3-unit line of a scene 5-8 units away: the widest pair sees its points
    at about 2.6 degrees, below what COLMAP's default initial pair accepts even after its own two
    halvings of 16 degrees, so the default mapper does not register them all; the relaxed initial
    pair does, and prepare says so."""
    photos = tmp_path / "walk"
    photos.mkdir()
    for i, x in enumerate(np.linspace(-0.15, 0.15, 8)):
        iio.imwrite(photos / f"v{i}.png", _textured_planes(float(x)))
    with pytest.raises(DatasetError, match=r"only \d of 8 images registered .*mapping tried: incremental "
                                           r"\(incremental \d/8\)"):
        prepare(photos, tmp_path / "default_only", mapping="incremental", num_threads=THREADS, progress=False)
    result = prepare(photos, tmp_path / "scene", num_threads=THREADS, progress=False)
    assert result.num_registered == 8 and result.mapping == "incremental-relaxed"
    assert list(result.mapping_attempts) == ["incremental", "incremental-relaxed"]
    assert result.mapping_attempts["incremental"] < 8 and result.mapping_attempts["incremental-relaxed"] == 8
    assert "mapping: incremental-relaxed (incremental " in result.summary()
    recorded = json.loads((tmp_path / "scene" / "prepare.json").read_text())
    assert recorded["mapping"] == "incremental-relaxed" and recorded["mapping_attempts"] == result.mapping_attempts
    # the recovered centres lie on one line, evenly spaced, as the views were taken (within 3% of the
    # 0.3-unit line: the texture is looked up at the nearest texel, so the views are not exact projections)
    centres = camera_centres(load_dataset(tmp_path / "scene").cameras).double().numpy()
    s, R, t = similarity_align(centres, np.stack([np.linspace(-0.15, 0.15, 8), np.zeros(8), np.zeros(8)], 1))
    aligned = s * centres @ R.T + t
    assert np.abs(aligned[:, 0] - np.linspace(-0.15, 0.15, 8)).max() < 0.03 * 0.3
    assert np.abs(aligned[:, 1:]).max() < 0.03 * 0.3
    # prepared again in place (the photos already in SCENE/images): the outputs are replaced, the
    # photos and the user's own files stay, and nothing is left beside the scene
    (tmp_path / "scene" / "notes.txt").write_text("mine")
    (tmp_path / "scene" / "transforms.json").write_text("stale")
    photos_before = {p.name: p.read_bytes() for p in (tmp_path / "scene" / "images").iterdir()}
    again = prepare(tmp_path / "scene" / "images", tmp_path / "scene", mapping="incremental-relaxed",
                    num_threads=THREADS, progress=False)
    assert again.num_registered == 8 and again.timings_s.get("photos") is not None
    assert {p.name: p.read_bytes() for p in (tmp_path / "scene" / "images").iterdir()} == photos_before
    assert (tmp_path / "scene" / "notes.txt").read_text() == "mine"
    assert camera_centres(load_dataset(tmp_path / "scene").cameras).shape == (8, 3)  # transforms.json rewritten
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene", "walk"]


def test_photos_left_out_reuse_the_last_features_and_matches_in_place(tmp_path, monkeypatch):
    """--exclude: the named photos are left out of the reconstruction; prepared in place, the last
    prepare's features and matches are reused while the photos are the ones they came from (only
    the mapping runs), and extracted again once a photo changed; an unknown name is refused, the
    scene left as it was; from another folder a left-out photo is not copied."""
    import pycolmap

    photos = tmp_path / "walk"
    photos.mkdir()
    for i, x in enumerate(np.linspace(-0.15, 0.15, 8)):
        iio.imwrite(photos / f"v{i}.png", _textured_planes(float(x)))
    scene = tmp_path / "scene"
    first = prepare(photos, scene, num_threads=THREADS, progress=False)
    assert first.num_registered == 8 and first.matcher == "exhaustive" and len(first.database_photos) == 8
    extracted = []
    real_extract = pycolmap.extract_features
    monkeypatch.setattr(pycolmap, "extract_features", lambda *a, **k: (extracted.append(1), real_extract(*a, **k)))

    def frames():
        return sorted(Path(f["file_path"]).name for f in json.loads((scene / "transforms.json").read_text())["frames"])

    again = prepare(scene / "images", scene, exclude=["v3.png"], num_threads=THREADS, progress=False)
    assert not extracted and "features and matches reused" in again.timings_s and "matching" not in again.timings_s
    assert again.num_images == 7 and again.num_registered == 7 and again.excluded == ["v3.png"]
    assert frames() == [f"v{i}.png" for i in range(8) if i != 3] and (scene / "images" / "v3.png").is_file()
    assert "left out (1, --exclude): v3.png" in again.summary()
    assert json.loads((scene / "prepare.json").read_text())["database_photos"] == first.database_photos
    twice = prepare(scene / "images", scene, exclude=["v7.png", "v3.png"], num_threads=THREADS, progress=False)
    assert not extracted and twice.num_registered == 6 and twice.excluded == ["v3.png", "v7.png"]

    before = {p.name: p.read_bytes() for p in scene.iterdir() if p.is_file()}
    with pytest.raises(DatasetError, match=r"--exclude names 'v9.png', not among its 8 photos"):
        prepare(scene / "images", scene, exclude=["v9.png"], num_threads=THREADS, progress=False)
    assert {p.name: p.read_bytes() for p in scene.iterdir() if p.is_file()} == before

    iio.imwrite(scene / "images" / "v0.png", _textured_planes(-0.16))  # a photo changed since
    changed = prepare(scene / "images", scene, exclude=["v3.png"], num_threads=THREADS, progress=False)
    assert extracted and "matching" in changed.timings_s and changed.num_registered == 7

    (photos / "v8.png").write_bytes(b"not a png")  # a broken photo left out is not even read
    elsewhere = prepare(photos, tmp_path / "other", exclude=["v7.png", "v8.png"], num_threads=THREADS, progress=False)
    assert elsewhere.num_images == 7 and not (tmp_path / "other" / "images" / "v7.png").exists()
    assert not (tmp_path / "other" / "images" / "v8.png").exists()


def test_matching_every_pair_in_blocks_gives_exhaustive_matching(tmp_path, monkeypatch):
    """match_every_pair (pair lists of MATCH_PAIRS_PER_CALL pairs, a progress bar over them) stores the
    same matches as one match_exhaustive call, here 28 pairs in 6 lists of at most 5, and verifies the
    same pairs with the same geometry; the verification's RANSAC draws in another order, so the inlier
    counts agree to 1% (two exhaustive runs on two threads differ by 0.5% between themselves)."""
    import sqlite3

    import pycolmap

    from stochastic_fields.data import prepare as prep

    photos = tmp_path / "walk"
    photos.mkdir()
    for i, x in enumerate(np.linspace(-0.15, 0.15, 8)):
        iio.imwrite(photos / f"v{i}.png", _textured_planes(float(x)))
    names = sorted(p.name for p in photos.iterdir())
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = THREADS
    stored = {}
    for how in ("exhaustive", "blocks"):
        database = tmp_path / f"{how}.db"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = THREADS
        pycolmap.extract_features(database, photos, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        pycolmap.set_random_seed(0)  # the verification's RANSAC, as prepare seeds it
        if how == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            monkeypatch.setattr(prep, "MATCH_PAIRS_PER_CALL", 5)
            calls = []
            real = pycolmap.match_image_pairs
            monkeypatch.setattr(pycolmap, "match_image_pairs",
                                lambda *a, **k: (calls.append(Path(k["pairing_options"].match_list_path).read_text()),
                                                 real(*a, **k)))
            prep.match_every_pair(database, names, matching, pycolmap.Device.cpu, progress=False)
            assert len(calls) == 6 and sum(len(c.splitlines()) for c in calls) == 28  # 5 + 5 + 5 + 5 + 5 + 3
        with sqlite3.connect(database) as db:
            stored[how] = (db.execute("select pair_id, rows, data from matches order by pair_id").fetchall(),
                           db.execute("select pair_id, rows, config from two_view_geometries order by pair_id").fetchall())
    assert len(stored["exhaustive"][0]) == 28 and stored["blocks"][0] == stored["exhaustive"][0]
    verified = {how: {pair: (rows, config) for pair, rows, config in stored[how][1]} for how in stored}
    assert verified["blocks"].keys() == verified["exhaustive"].keys()
    assert all(verified["blocks"][k][1] == verified["exhaustive"][k][1] for k in verified["blocks"])
    inliers = {how: sum(rows for rows, _ in verified[how].values()) for how in verified}
    assert inliers["exhaustive"] > 1000 and abs(inliers["blocks"] - inliers["exhaustive"]) < 0.01 * inliers["exhaustive"]


@pytest.mark.slow
def test_fern_photos_without_poses_recover_llff_cameras(shared_data, tmp_path):
    fern = shared_data / "nerf_llff_data" / "fern"
    photos = tmp_path / "photos"
    shutil.copytree(fern / "images_8", photos)  # the photos only: no poses, no COLMAP model
    # plus one photo of something else (smooth noise: many features, none shared with fern)
    rng = np.random.default_rng(0)
    other = np.kron(rng.integers(0, 256, size=(63, 84, 3)), np.ones((6, 6, 1))).astype(np.uint8)
    iio.imwrite(photos / "zz_other.png", other)
    result = prepare(photos, tmp_path / "scene", num_threads=THREADS, progress=False)
    assert result.num_images == 21 and result.num_registered == 20
    assert list(result.failed) == ["zz_other.png"] and "too few matches" in result.failed["zz_other.png"]
    assert 0 < result.mean_reprojection_error_px < 1.5
    refinement = result.refinement  # the robust adjustment ran on the mapped model and is what was written
    assert refinement["applied"] and refinement["loss"] == "soft_l1"
    assert result.mean_reprojection_error_px == pytest.approx(refinement["reprojection_after_px"], rel=1e-6)
    assert refinement["reprojection_after_px"] < refinement["reprojection_before_px"]
    assert "refinement: robust (soft_l1, 1 px) bundle adjustment" in result.summary()
    scene = tmp_path / "scene"
    for rel in ("sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin", "transforms.json",
                "sparse_pc.ply", "prepare.json", "images_2/image000.png", "images_8/image019.png"):
        assert (scene / rel).is_file(), rel
    assert iio.improps(scene / "images_4" / "image000.png").shape[:2] == (94, 126)  # round(378/4), round(504/4)
    assert not (scene / "images_2" / "zz_other.png").exists()  # only registered images are kept downscaled
    meta = json.loads((scene / "transforms.json").read_text())
    assert len(meta["frames"]) == 20 and meta["camera_model"] == "OPENCV" and meta["w"] == 504

    ours = load_dataset(scene)  # through transforms.json, with the model beside it
    llff = load_dataset(fern)
    assert ours.bounds_source == "sfm_points" and ours.forward_facing and ours.points3d_visible is not None
    ca, cb = camera_centres(ours.cameras).double().numpy(), camera_centres(llff.cameras).double().numpy()
    s, R, t = similarity_align(ca, cb)
    extent = max(np.linalg.norm(a - b) for a in cb for b in cb)  # largest distance between two cameras
    centre_err = np.linalg.norm(s * ca @ R.T + t - cb, axis=1)
    assert centre_err.max() < 0.02 * extent, (centre_err.max(), extent)
    Ra = camera_to_world(ours.cameras).double().numpy()[:, :3, :3]
    Rb = camera_to_world(llff.cameras).double().numpy()[:, :3, :3]
    cos = [(np.trace((R @ Ra[i]).T @ Rb[i]) - 1) / 2 for i in range(20)]
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0
    # the bounds follow LLFF's rule: scaled into LLFF's frame, the medians agree within 10%
    assert float(np.median(ours.near.numpy() * s / llff.near.numpy())) == pytest.approx(1.0, abs=0.1)
    assert float(np.median(ours.far.numpy() * s / llff.far.numpy())) == pytest.approx(1.0, abs=0.1)
    # the same folder also loads as a bare COLMAP capture (model + images)
    (scene / "transforms.json").unlink()
    bare = load_dataset(scene)
    torch.testing.assert_close(bare.cameras.extrinsics, ours.cameras.extrinsics, atol=1e-5, rtol=0)
    torch.testing.assert_close(bare.near, ours.near)


def test_prepare_is_a_cli_command(tmp_path, capsys):
    from stochastic_fields.cli import build_parser, main

    args = build_parser().parse_args(["prepare", str(tmp_path / "in"), "--out", str(tmp_path / "s"), "--threads", "1"])
    assert args.command == "prepare" and args.threads == 1 and args.camera_model == "SIMPLE_RADIAL"
    assert main(["prepare", str(tmp_path / "in"), "--out", str(tmp_path / "s"), "--quiet"]) == 2
    assert f"{tmp_path / 'in'}: input does not exist" in capsys.readouterr().err


def _synthetic_reconstruction(outlier_fraction: float, seed: int = 0):
    """(exact pycolmap Reconstruction of 12 views of 300 points, a copy with 0.5 px noise on every
    observation, its poses perturbed by 0.3 degrees and 2% of the scene, and ``outlier_fraction`` of
    the observations moved by N(0, 15 px): mismatches that survived verification)."""
    pycolmap = pytest.importorskip("pycolmap")
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_cameras_per_rig, options.num_frames_per_rig = 1, 1, 12
    options.num_points3D, options.num_points2D_without_point3D = 300, 0
    pycolmap.set_random_seed(seed)
    exact = pycolmap.synthesize_dataset(options)
    noisy = pycolmap.Reconstruction(exact)
    noise = pycolmap.SyntheticNoiseOptions()
    noise.point2D_stddev, noise.rig_from_world_rotation_stddev, noise.rig_from_world_translation_stddev = 0.5, 0.3, 0.02
    pycolmap.synthesize_noise(noise, noisy)
    rng = np.random.default_rng(seed)
    for image_id in noisy.reg_image_ids():
        points = noisy.images[image_id].points2D
        for k in range(len(points)):
            if points[k].has_point3D() and rng.random() < outlier_fraction:
                moved = points[k]
                moved.xy = moved.xy + rng.normal(0.0, 15.0, 2)
                points[k] = moved
    return exact, noisy


def _camera_to_world(rec) -> np.ndarray:
    """Camera-to-world [N, 4, 4] of a pycolmap Reconstruction's posed images, by image id."""
    return np.array([np.linalg.inv(world_to_camera(rec.images[i])) for i in sorted(rec.reg_image_ids())])


def _squared_loss_adjustment(rec):
    """A copy of ``rec`` after pycolmap's global bundle adjustment with its default squared loss."""
    import pycolmap

    adjusted = pycolmap.Reconstruction(rec)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.solver_options.num_threads = THREADS
    pycolmap.bundle_adjustment(adjusted, options)
    return adjusted


def test_robust_refinement_resists_mismatched_observations():
    """5% of the observations 15 px off: a squared-loss bundle adjustment (the mappers' last one)
    leaves the cameras a quarter of a degree off; the soft-L1 one comes within a twentieth."""
    pytest.importorskip("pycolmap")
    exact, noisy = _synthetic_reconstruction(0.05)
    squared = _squared_loss_adjustment(noisy)
    refined, report = refine_robust(noisy, num_threads=THREADS)
    truth = _camera_to_world(exact)
    plain_err = pose_errors(_camera_to_world(squared), truth)
    robust_err = pose_errors(_camera_to_world(refined), truth)
    assert plain_err["rotation_error_max_deg"] > 0.15
    assert robust_err["rotation_error_max_deg"] < plain_err["rotation_error_max_deg"] / 3
    assert robust_err["rotation_error_max_deg"] < 0.08 and robust_err["centre_error_max"] < 1e-3
    assert report["applied"] and report["loss"] == "soft_l1" and report["scale_px"] == 1.0
    assert report["reprojection_before_px"] == pytest.approx(noisy.compute_mean_reprojection_error())
    assert report["reprojection_after_px"] < report["reprojection_before_px"]
    camera = next(iter(refined.cameras.values()))
    np.testing.assert_allclose(camera.params[1:3], next(iter(noisy.cameras.values())).params[1:3])  # principal point held
    np.testing.assert_allclose(_camera_to_world(noisy), _camera_to_world(_synthetic_reconstruction(0.05)[1]))  # input untouched


def test_robust_refinement_matches_squared_loss_without_outliers():
    """Gaussian 0.5 px noise only (every residual inside the soft-L1 loss's quadratic core): both
    adjustments land on the same cameras to a hundredth of a degree."""
    pytest.importorskip("pycolmap")
    exact, noisy = _synthetic_reconstruction(0.0)
    squared = _squared_loss_adjustment(noisy)
    refined, _ = refine_robust(noisy, num_threads=THREADS)
    truth = _camera_to_world(exact)
    a, b = pose_errors(_camera_to_world(squared), truth), pose_errors(_camera_to_world(refined), truth)
    assert b["rotation_error_max_deg"] == pytest.approx(a["rotation_error_max_deg"], abs=0.01)
    assert b["rotation_error_max_deg"] < 0.1


def test_robust_refinement_rejects_a_bad_scale():
    pycolmap = pytest.importorskip("pycolmap")
    with pytest.raises(ValueError, match="loss_scale_px"):
        refine_robust(pycolmap.Reconstruction(), loss_scale_px=0.0)
