"""The pose check: training photos the field fits far worse than the others (pose_check)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stochastic_fields.pose_check import (POSE_CHECK_MIN_GAP_DB, POSE_CHECK_MIN_VIEWS, TRAINING_FIT_FILE,
                                          check_photo_fit, load_training_fit, photo_names, save_training_fit)


def _names(n: int) -> list[str]:
    return [f"r_{i}.png" for i in range(n)]


def test_flags_the_photos_far_below_the_median_worst_first():
    psnr = [25.0, 25.5, 24.5, 25.2, 24.8, 25.1, 24.9, 15.0, 25.3, 13.9, 24.6]
    fit = check_photo_fit(_names(len(psnr)), psnr)
    # by hand: median 24.9 (of 11); |psnr - 24.9| sorted: 0, .1, .1, .2, .3, .3, .4, .6, ... -> MAD 0.3
    assert fit.median_db == pytest.approx(24.9)
    assert fit.threshold_db == pytest.approx(24.9 - max(3.5 * 1.4826 * 0.3, 3.0))
    assert fit.flagged == (9, 7)  # 13.9 dB before 15.0 dB
    line = fit.summary()
    assert "2 of 11 training photos" in line and line.index("r_9.png 13.9 dB") < line.index("r_7.png 15.0 dB")
    assert "prepare the capture again" in line


def test_a_wide_spread_raises_the_bar_by_the_modified_z_score():
    from scipy import stats

    psnr = 25.0 + 2.0 * stats.norm.ppf((np.arange(400) + 0.5) / 400)  # normal quantiles, std 2 dB: MAD 1.35
    psnr[[100, 200, 300]] = [20.5, 19.5, 10.0]  # 4.5 and 5.5 dB under are within 3.5 sigma (7 dB); 15 dB is not
    fit = check_photo_fit(_names(400), psnr)
    mad = np.median(np.abs(psnr - np.median(psnr)))
    assert fit.threshold_db == pytest.approx(np.median(psnr) - 3.5 * 1.4826 * mad)
    assert 0 < np.median(psnr) - fit.threshold_db - 7.0 < 0.5
    assert fit.flagged == (300,)


def test_photos_that_fit_alike_flag_nothing_within_the_least_gap():
    psnr = [25.00, 25.01, 24.99, 25.02, 24.98, 25.00, 25.01, 24.99, 25.0 - POSE_CHECK_MIN_GAP_DB + 0.1]
    fit = check_photo_fit(_names(len(psnr)), psnr)  # z far below -3.5, but 2.9 dB only
    assert fit.flagged == () and fit.threshold_db == pytest.approx(25.0 - POSE_CHECK_MIN_GAP_DB)
    assert "fit alike" in fit.summary()
    psnr[-1] = 25.0 - POSE_CHECK_MIN_GAP_DB - 0.1
    assert check_photo_fit(_names(len(psnr)), psnr).flagged == (len(psnr) - 1,)


def test_too_few_photos_or_exact_renders():
    few = check_photo_fit(_names(POSE_CHECK_MIN_VIEWS - 1), [25.0] * (POSE_CHECK_MIN_VIEWS - 2) + [5.0])
    assert few.flagged == () and "skipped" in few.summary()
    exact = check_photo_fit(_names(9), [np.inf] * 3 + [30.0] * 5 + [10.0])  # +inf: an exact render
    assert exact.median_db == 30.0 and exact.flagged == (8,)
    assert check_photo_fit([], []).flagged == ()
    with pytest.raises(ValueError, match="3 names for 2"):
        check_photo_fit(_names(3), [1.0, 2.0])
    with pytest.raises(ValueError, match="r_1.png is NaN"):
        check_photo_fit(_names(9), [25.0, np.nan] + [25.0] * 7)


def test_the_summary_lists_a_few_and_counts_the_rest():
    psnr = [25.0] * 30 + [10.0 + 0.1 * i for i in range(12)]
    line = check_photo_fit(_names(42), psnr).summary()
    assert "12 of 42" in line and "and 4 more" in line and "r_30.png 10.0 dB" in line and "r_41.png" not in line


def test_file_round_trip_and_a_malformed_file(tmp_path):
    assert load_training_fit(tmp_path) is None
    fit = check_photo_fit(_names(10), [25.0] * 9 + [12.0])
    assert save_training_fit(tmp_path, fit) == tmp_path / TRAINING_FIT_FILE
    stored = json.loads((tmp_path / TRAINING_FIT_FILE).read_text())
    assert stored["flagged"] == ["r_9.png"] and stored["psnr_db"]["r_9.png"] == 12.0
    back = load_training_fit(tmp_path)
    assert back.names == fit.names and back.flagged == fit.flagged
    np.testing.assert_array_equal(back.psnr, fit.psnr)
    (tmp_path / TRAINING_FIT_FILE).write_text('{"psnr_db": {"r_0.png": "dark"}}')
    with pytest.raises(ValueError, match=f"{TRAINING_FIT_FILE}: malformed"):
        load_training_fit(tmp_path)


def test_photo_names_fall_back_to_view_numbers():
    class WithPaths:
        image_paths = ["/a/b/r_3.png", "/a/b/r_4.png"]

    class Without:
        image_paths: list = []

    assert photo_names(WithPaths(), [1, 0]) == ["r_4.png", "r_3.png"]
    assert photo_names(Without(), [7]) == ["view_007"]


@pytest.mark.slow
def test_training_renders_score_each_photo_as_eval_does(tmp_path):
    """render_training_depth's PSNR per training view equals metrics.psnr of the model's render; a
    training photo swapped for another view's (its colours disagree with its camera) falls by more
    than the check's least gap."""
    import torch

    from stochastic_fields.free_space import render_training_depth
    from stochastic_fields.metrics import psnr
    from stochastic_fields.renderer import seeded_chunks

    from conftest import train_tiny_synthetic_run

    model, ds = train_tiny_synthetic_run(tmp_path)
    ref = render_training_depth(model, ds, progress=False)
    v = int(ds.train_indices[1])
    with torch.no_grad():
        maps = model.render_view(ds.rays(v), None, generator=seeded_chunks(0, v, torch.device("cpu")))
    assert ref.psnr.shape == (len(ds.train_indices),)
    assert ref.psnr[1] == pytest.approx(psnr(maps["colour_mean"], ds.images[v]), abs=1e-9)
    w = int(ds.train_indices[2])
    ds.images[v] = ds.images[w].clone()  # view v's camera, view w's photo
    swapped = render_training_depth(model, ds, progress=False)
    assert ref.psnr[1] - swapped.psnr[1] > POSE_CHECK_MIN_GAP_DB
    np.testing.assert_array_equal(np.delete(swapped.psnr, 1), np.delete(ref.psnr, 1))


def test_eval_checks_training_and_validation_photos_each_as_a_group(capsys):
    """``eval``: the training photos against each other, the validation photos against each other."""
    from stochastic_fields.cli import _print_pose_check
    from stochastic_fields.pose_check import check_view_groups, view_groups_record

    class Capture:
        image_paths = [f"/photos/p{i}.jpg" for i in range(40)]
        train_indices = [i for i in range(40) if i % 4]  # 30 training photos, 10 validate

    views = list(range(40))
    psnr = [25.0 + 0.1 * (i % 3) for i in views]
    psnr[5] = 14.0  # a training photo far below the others
    psnr[8] = 5.0  # a validation photo far below the others
    _print_pose_check({"pose_check": view_groups_record(Capture(), views, psnr)})  # as evaluate records it
    training, validation = capsys.readouterr().out.strip().splitlines()
    assert "1 of 30 training photos" in training and "p5.jpg 14.0 dB" in training and "p8.jpg" not in training
    assert "1 of 10 validation photos" in validation and "p8.jpg 5.0 dB" in validation
    psnr[9] = float("nan")  # an undefined PSNR is not checked
    training, validation = check_view_groups(Capture(), views, psnr)
    assert len(training.names) == 29 and "p9.jpg" not in training.names and validation.group == "validation"
    _print_pose_check({"pose_check": view_groups_record(Capture(), [0, 4, 8], [25.0, 25.0, 5.0])})  # validation only
    assert capsys.readouterr().out.strip() == "pose check: skipped (3 validation photos, it compares 8 or more)"
