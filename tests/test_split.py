"""Which photos train: the capture split (train's default) and the paper's split (``--preset paper``).

A user's capture trains on every photo but every 8th (``index % 8 == 0`` validates, LLFF's
convention); the benchmark tables keep the paper's protocol (``index % 5 == 0`` trains). Runs
saved before the option existed were trained with the paper's split and keep it.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import pytest

from stochastic_fields import config as C
from stochastic_fields.data import DatasetError, load_dataset
from stochastic_fields.data.dataset import holdout_every_indices, split_every_indices
from stochastic_fields.scenes import apply_split, describe_split, load_run_dataset


def test_holdout_every_indices_follow_the_llff_convention():
    train, test = holdout_every_indices(17, 8, "scene")
    assert test == [0, 8, 16] and train == [i for i in range(17) if i not in (0, 8, 16)]
    assert holdout_every_indices(3, 8, "scene") == ([1, 2], [0])
    with pytest.raises(DatasetError, match="scene: the split leaves no training view"):
        holdout_every_indices(1, 8, "scene")
    with pytest.raises(DatasetError, match="holdout_every must be >= 2, got 1"):
        holdout_every_indices(10, 1, "scene")
    assert split_every_indices(17, 5, "scene")[0] == [0, 5, 10, 15]


def test_capture_is_the_default_and_paper_is_a_preset():
    assert C.ExperimentConfig().data.split == "capture" and C.ExperimentConfig().data.holdout_every == 8
    paper = C.preset("paper")
    assert (paper.data.split, paper.data.split_every) == ("paper", 5)
    for name in ("demo", "tiny"):  # the embedded scene's presets keep the split their numbers were made with
        assert (C.preset(name).data.split, C.preset(name).data.split_every) == ("paper", 4)
    with pytest.raises(ValueError, match=r"data\.split.*'capture', 'paper'.*'all'"):
        C.from_dict(C.ExperimentConfig, {"data": {"split": "all"}})
    with pytest.raises(ValueError, match=r"data\.holdout_every"):
        C.from_dict(C.ExperimentConfig, {"data": {"holdout_every": 1}})


def test_a_run_saved_before_the_option_keeps_the_paper_split(tmp_path):
    saved = C.to_dict(C.ExperimentConfig())
    del saved["data"]["split"], saved["data"]["holdout_every"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    assert C.load_config(tmp_path / "config.json").data.split == "paper"


def test_load_run_dataset_splits_an_llff_capture_by_the_config(shared_data, tmp_path):
    fern = shared_data / "nerf_llff_data" / "fern"
    cfg = C.preset("llff")
    cfg.data.path = str(fern)
    capture = load_run_dataset(cfg, tmp_path)
    assert capture.test_indices == [0, 8, 16] and len(capture.train_indices) == 17
    assert describe_split(capture, cfg).startswith("fern: 17 photos train, 3 validate (capture split: every 8th")
    cfg.data.split = "paper"
    paper = load_run_dataset(cfg, tmp_path)
    assert paper.train_indices == [0, 5, 10, 15] and len(paper.test_indices) == 16
    assert describe_split(paper, cfg) == "fern: 4 photos train, 16 test (paper split: index % 5 == 0 trains)"


def test_a_split_given_by_the_scene_files_is_kept(tiny_scene, tmp_path):
    dataset = load_dataset(tiny_scene)
    cfg = C.ExperimentConfig()
    assert apply_split(dataset, cfg).test_indices == [i for i in range(20) if i % 8 == 0]
    given = replace(dataset, split_source="files")
    assert apply_split(given, cfg) is given
    assert "the scene's own train/test files" in describe_split(given, cfg)


@pytest.mark.slow
def test_train_prints_the_split_and_eval_scores_depth_at_the_capture_points(shared_data, tmp_path, capsys):
    """A user's LLFF capture: train says how many photos train and validate; eval scores depth at
    the capture's own SfM points of the SCORE role, the same points the benchmark scores."""
    from stochastic_fields.capture_points import score_sparse_depth
    from stochastic_fields.cli import main

    fern, run = shared_data / "nerf_llff_data" / "fern", tmp_path / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fern's lens-distortion notice
        assert main(["train", "--preset", "tiny", "--data.split", "capture", "--data.path", str(fern),
                     "--train.iterations", "10", "--out", str(run), "--quiet"]) in (0, None)
        printed = capsys.readouterr().out
        assert "fern: 17 photos train, 3 validate (capture split: every 8th photo validates" in printed
        # fern's 17 photos: the depth axis gets the cells its parallax resolves (docs/design.md)
        assert "grid: 246 x 177 x 47 cells at the finest of 5 levels (2.05M), 2 density heads, sized by the parallax rule" in printed
        assert main(["eval", "--run", str(run), "--views", "8", "--no-products", "--quiet"]) in (0, None)
        printed = capsys.readouterr().out
        metrics = json.loads((run / "metrics.json").read_text())
        expected = score_sparse_depth(load_run_dataset(C.load_config(run / "config.json"), run), [8])[8]
    assert metrics["depth_source"] == "sparse" and metrics["views"] == ["view_008"]
    used = metrics["pooled"]["depth"]["num_used"]
    assert 0 < used <= len(expected.depth)
    assert f"over {used} SfM points (SCORE role)" in printed and "pooled depth: abs-rel " in printed
    assert "depth intervals 50/68/90/95/99%: coverage" in printed


def test_few_view_split_follows_regnerf_protocol():
    """Every 8th view tests; n of the rest, spread evenly by round(linspace(0, R-1, n)) with Python's
    half-to-even rounding (RegNeRF's code), train. Worked by hand for fern (20 views) and flower (34)."""
    from stochastic_fields.data.dataset import few_view_indices

    assert few_view_indices(20, 3, 8, "fern") == ([1, 10, 19], [0, 8, 16])
    assert few_view_indices(20, 6, 8, "fern") == ([1, 4, 7, 12, 15, 19], [0, 8, 16])  # positions 0 3 6 10 13 16
    assert few_view_indices(34, 3, 8, "flower") == ([1, 17, 33], [0, 8, 16, 24, 32])
    # 9 views of flower: positions 0, 3.5, 7, 10.5, 14, 17.5, 21, 24.5, 28 round half to even
    assert few_view_indices(34, 9, 8, "flower")[0] == [1, 5, 9, 12, 17, 21, 25, 28, 33]
    with pytest.raises(DatasetError, match=r"fern: few-view split: train_views must be between 1 and the 17"):
        few_view_indices(20, 18, 8, "fern")


def test_few_view_split_is_a_named_option(shared_data, tmp_path):
    fern = shared_data / "nerf_llff_data" / "fern"
    cfg = C.preset("llff")
    cfg.data.path, cfg.data.split, cfg.data.train_views = str(fern), "fewview", 3
    dataset = load_run_dataset(cfg, tmp_path)
    assert (dataset.train_indices, dataset.test_indices) == ([1, 10, 19], [0, 8, 16])
    assert describe_split(dataset, cfg).startswith("fern: 3 photos train, 3 test (few-view split")
    with pytest.raises(ValueError, match=r"data\.split.*'fewview'"):
        C.from_dict(C.ExperimentConfig, {"data": {"split": "few"}})
