"""Which photos train: the capture split (train's default) and the paper's split (``--preset paper``).

A user's capture trains on every photo but every 8th (``index % 8 == 0`` validates, LLFF's
convention); the benchmark tables keep the paper's protocol (``index % 5 == 0`` trains). Runs
saved before the option existed were trained with the paper's split and keep it.
"""

from __future__ import annotations

import json
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
