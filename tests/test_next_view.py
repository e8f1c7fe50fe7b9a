"""next-view: the information score against hand-computed values, the coverage test of the greedy
batch, and the known answer: a scene seen from one side only ranks the unseen side first."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from stochastic_fields.cli import main
from stochastic_fields.products.export import ViewSpec
from stochastic_fields.products.pointcloud import backproject_map
from stochastic_fields.products.next_view import (CandidateMaps, greedy_batch, information_gain,
                                                  render_scale, scaled_camera, seen_by)

#: The known-answer scene: a ring of 20 cameras; the even views of the first half train.
TRAINED = (0, 2, 4, 6, 8)
SEEN_SIDE = (1, 3, 5, 7)  # between training views
UNSEEN_SIDE = (11, 12, 13, 14, 15, 16, 17)  # three or more ring steps from every training view


def test_information_gain_hand_computed():
    # two draws per channel: colours 0.2 / 0.4 -> e = 0.01; predictive var 0.01 + n with n = 0.0025
    draws = torch.tensor([[[0.2, 0.5, 0.5], [0.4, 0.5, 0.5]]])  # [1, K=2, 3]
    var = torch.tensor([[0.0125, 0.0025, 0.0025]])
    info, e = information_gain(draws, var)
    assert e[0].tolist() == pytest.approx([0.01, 0.0, 0.0], abs=1e-9)
    assert float(info[0]) == pytest.approx(0.5 * math.log(1 + 0.01 / 0.0025), rel=1e-6)  # 0.5 log 5


def test_information_gain_hard_cases():
    # identical draws and no noise left: zero information, not NaN; huge disagreement: finite
    draws = torch.full((4, 8, 3), 0.3)
    info, _ = information_gain(draws, torch.zeros(4, 3))
    assert torch.all(info == 0)
    wild = torch.rand(4, 8, 3, generator=torch.Generator().manual_seed(0))
    e = wild.double().var(dim=1, unbiased=False)
    info, _ = information_gain(wild, e.float())  # predictive var == epistemic: noise at the floor
    assert torch.all(torch.isfinite(info)) and torch.all(info > 0)


def test_scaled_camera_and_back_projection_round_trip():
    K = np.array([[100.0, 0, 32.0], [0, 100.0, 24.0], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1, -0.2, 0.5]
    spec = ViewSpec("a", K, w2c, 48, 64, 0.1, 10.0)
    s = render_scale(48, 64, 768)
    Ks, h, w = scaled_camera(spec, s)
    assert (h, w) == (24, 32) and Ks[0, 0] == pytest.approx(50.0) and Ks[0, 2] == pytest.approx(16.0)
    assert render_scale(48, 64, 10**6) == 1.0
    depth = np.full((h, w), 2.0)
    pts = backproject_map(depth, Ks, w2c).reshape(-1, 3).numpy()
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    assert np.allclose(cam[:, 2], 2.0)
    uv = cam @ Ks.T
    assert np.allclose(uv[:, 0] / uv[:, 2], np.tile(np.arange(w) + 0.5, h))


def _maps(spec: ViewSpec, depth: float, info: float, size=(6, 8)) -> CandidateMaps:
    K, h, w = scaled_camera(spec, size[0] / spec.height)
    d = np.full((h, w), depth, np.float32)
    return CandidateMaps(spec=spec, render_intrinsics=K, render_size=(h, w), information=np.full((h, w), info),
                         colour_mean=np.zeros((h, w, 3)), colour_std_epistemic=np.zeros((h, w)), depth_mean=d,
                         depth_std=d * 0.1, opacity=np.ones((h, w)), valid=np.ones((h, w), bool),
                         points=backproject_map(d, K, spec.world_to_camera).reshape(-1, 3).numpy())


def test_seen_by_and_greedy_batch_skip_a_near_duplicate():
    K = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]])
    a = np.eye(4)
    b = np.eye(4)
    b[0, 3] = 1e-3  # a's twin, one millimetre aside
    c = np.eye(4)
    c[:3, :3] = np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])  # looking the other way
    cands = [_maps(ViewSpec("a", K, a, 48, 64, 0.1, 10), 2.0, 1.0),
             _maps(ViewSpec("b", K, b, 48, 64, 0.1, 10), 2.0, 0.99),
             _maps(ViewSpec("c", K, c, 48, 64, 0.1, 10), 2.0, 0.5)]
    assert seen_by(cands[1].points, cands[0]).mean() > 0.8  # the twin's surface lies in a's view
    assert not seen_by(cands[2].points, cands[0]).any()  # behind a's camera
    occluded = cands[0].points * 2.0  # twice as far along a's rays: behind a's surface at depth 2
    assert not seen_by(occluded, cands[0]).any()
    picks = greedy_batch(cands, 2)
    assert [i for i, _ in picks] == [0, 2]  # the twin gives almost nothing once a is picked
    assert picks[1][1]["fraction_new_pixels"] == 1.0
    with pytest.raises(ValueError, match="--count"):
        greedy_batch(cands, 4)


@pytest.fixture(scope="module")
def one_sided_run(tmp_path_factory, tiny_scene) -> Path:
    """The tiny ring scene trained from the even views of one half only (the 'views' split)."""
    out = tmp_path_factory.mktemp("next_view") / "run"
    assert main(["train", "--preset", "tiny", "--data.path", str(tiny_scene), "--data.split", "views",
                 "--data.train_list", ",".join(map(str, TRAINED)), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.slow
def test_the_unseen_side_ranks_first(one_sided_run, tiny_scene, tmp_path):
    out = tmp_path / "nv"
    assert main(["next-view", "--run", str(one_sided_run), "--candidates-from", str(tiny_scene), "--count", "3",
                 "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "next_views.json").read_text())
    score = {r["index"]: r["score"] for r in result["ranked"]}
    assert set(score) == set(range(20)) - set(TRAINED)
    assert result["ranked"][0]["index"] in UNSEEN_SIDE
    assert min(score[v] for v in UNSEEN_SIDE) > max(score[v] for v in SEEN_SIDE)
    picks = [r["index"] for r in result["batch"]]
    assert len(set(picks)) == 3 and all(p in UNSEEN_SIDE or p in (9, 10, 18, 19) for p in picks)
    assert (out / "next_views.png").stat().st_size > 0
    first = result["batch"][0]
    assert np.allclose(np.linalg.inv(np.array(first["world_to_camera"])), np.array(first["camera_to_world"]))


@pytest.mark.slow
def test_candidates_file_and_bad_input(one_sided_run, tiny_scene, tmp_path, capsys):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.cameras import intrinsics_3x3

    ds = load_dataset(tiny_scene)
    K = intrinsics_3x3(ds.cameras)[13].tolist()
    w2c = ds.cameras.extrinsics[13].tolist()
    cam = {"K": K, "world_to_camera": w2c, "width": ds.width, "height": ds.height}
    w2c_seen = ds.cameras.extrinsics[3].tolist()
    good = tmp_path / "cands.json"
    good.write_text(json.dumps([{**cam, "name": "u1"}, {**cam, "name": "u2"},
                                {**cam, "world_to_camera": w2c_seen, "name": "s"}]))
    out = tmp_path / "nv"
    assert main(["next-view", "--run", str(one_sided_run), "--candidates", str(good), "--count", "2",
                 "--out", str(out), "--quiet"]) == 0
    batch = [r["name"] for r in json.loads((out / "next_views.json").read_text())["batch"]]
    assert batch[0] in ("u1", "u2") and batch[1] == "s"  # the twin of the first pick sees nothing new

    def fails(text: str | None, match: str, *extra: str) -> None:
        bad = tmp_path / "bad.json"
        if text is not None:
            bad.write_text(text)
        argv = ["next-view", "--run", str(one_sided_run), "--quiet", *extra]
        argv += [] if "--candidates-from" in extra else ["--candidates", str(bad)]
        capsys.readouterr()
        assert main(argv) != 0
        err = capsys.readouterr().err
        assert match in err and (text is None or str(bad) in err), err

    fails("[]", "non-empty list")
    sheared = np.array(w2c)
    sheared[0, 0] *= 1.5
    fails(json.dumps([{**cam, "world_to_camera": sheared.tolist()}]), "rotation")
    fails(json.dumps([{**cam, "K": [[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]]}]), "non-finite")
    fails(json.dumps([cam]), "--count 2", "--count", "2")
    fails(None, "trained on", "--candidates-from", str(tmp_path))


def test_views_split(tiny_scene, capsys):
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.errors import DatasetError
    from stochastic_fields.scenes import apply_split, describe_split

    cfg = preset("tiny")
    cfg.data.split, cfg.data.train_list = "views", "3, 1,17"
    ds = apply_split(load_dataset(tiny_scene), cfg)
    assert ds.train_indices == [1, 3, 17] and ds.test_indices == [v for v in range(20) if v not in (1, 3, 17)]
    assert "1, 3" not in describe_split(ds, cfg) and "3 photos train" in describe_split(ds, cfg)
    for bad in ("", "1,1", "20"):
        cfg.data.train_list = bad
        with pytest.raises(DatasetError, match="train"):
            apply_split(load_dataset(tiny_scene), cfg)
    assert main(["train", "--data.split", "views", "--data.train_list", "0;5", "--out", str(tiny_scene / "x")]) != 0
    assert "data.train_list: must be empty or comma-separated integers >= 0, got '0;5'" in capsys.readouterr().err


@pytest.mark.slow
def test_next_view_loop_example(one_sided_run, tiny_scene, monkeypatch, capsys):
    """examples/next_view_loop.py: two rounds, retraining on the chosen photo between them; each
    round prints a pose on the unseen side, and the second round no longer offers the first pick."""
    import runpy
    import sys

    script = Path(__file__).resolve().parents[1] / "examples" / "next_view_loop.py"
    monkeypatch.setattr(sys, "argv", [str(script), "--run", str(one_sided_run), "--candidates-from", str(tiny_scene),
                                      "--rounds", "2", "--retrain-steps", "20"])
    runpy.run_path(str(script), run_name="__main__")
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("round ")]
    picks = [int(ln.split("view_")[1][:3]) for ln in lines]
    assert len(picks) == 2 and picks[0] != picks[1] and picks[0] in UNSEEN_SIDE
    assert "camera-to-world rotation" in lines[0]
    retrained = Path(f"{one_sided_run}_next1")
    assert json.loads((retrained / "config.json").read_text())["data"]["train_list"] == \
        ",".join(map(str, sorted(set(TRAINED) | {picks[0]})))
