"""Pixels held out of training and the colour recalibration fitted on them (holdout.py, calibration.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stochastic_fields.calibration import (CALIBRATION_LEVELS, QuantileCalibration, RunCalibration, apply_calibration,
                                           fit_colour_calibration, load_run_calibration, save_run_calibration)
from stochastic_fields.holdout import holdout_mask
from stochastic_fields.rays import RayBundle


# ------------------------------------------------------------------ the mask
def test_mask_holds_out_whole_blocks_in_the_asked_share():
    h, w, block = 64, 96, 16  # 4 x 6 = 24 blocks
    m = holdout_mask(h, w, 3, fraction=0.25, block=block)
    assert m.shape == (h, w) and m.dtype == bool
    per_block = m.reshape(h // block, block, w // block, block).transpose(0, 2, 1, 3).reshape(-1, block * block)
    assert set(per_block.mean(axis=1).tolist()) <= {0.0, 1.0}  # every block all in or all out
    assert int(per_block.all(axis=1).sum()) == 6  # round(0.25 * 24)


def test_mask_is_fixed_by_view_and_options_alone():
    a = holdout_mask(50, 70, 2, fraction=0.2, block=8)
    assert np.array_equal(a, holdout_mask(50, 70, 2, fraction=0.2, block=8))
    assert not np.array_equal(a, holdout_mask(50, 70, 7, fraction=0.2, block=8))


def test_mask_edges_and_bad_options():
    assert not holdout_mask(10, 10, 0, fraction=0.0, block=4).any()
    # ragged edge blocks (10 = 4 + 4 + 2): at least one block for a small positive share
    assert holdout_mask(10, 10, 0, fraction=0.01, block=4).sum() >= 4
    for kwargs in ({"fraction": -0.1, "block": 4}, {"fraction": 1.0, "block": 4}, {"fraction": 0.1, "block": 0}):
        with pytest.raises(ValueError):
            holdout_mask(10, 10, 0, **kwargs)
    with pytest.raises(ValueError, match="empty"):
        holdout_mask(0, 10, 0, fraction=0.1, block=4)


def test_training_rays_leave_the_held_out_pixels_out(tiny_scene):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.holdout import holdout_masks
    from stochastic_fields.trainer import TrainingRays

    ds = load_dataset(tiny_scene, split_every=5)
    full = TrainingRays.from_dataset(ds, torch.device("cpu"))
    kept = TrainingRays.from_dataset(ds, torch.device("cpu"), holdout_fraction=0.2, holdout_block=8)
    masks = holdout_masks(ds, list(ds.train_indices), fraction=0.2, block=8)
    assert len(kept.colours) == len(full.colours) - int(masks.sum())
    keep = torch.from_numpy(~masks.reshape(-1))
    torch.testing.assert_close(kept.colours, full.colours[keep], rtol=0, atol=0)
    torch.testing.assert_close(kept.rays.directions, full.rays.directions[keep], rtol=0, atol=0)


# ------------------------------------------------------------------ the colour map
class _PixelDataset:
    """Two 'training views' of 40 x 50 pixels whose rays carry (view, row, column) in their origins."""

    def __init__(self, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        self.images = torch.rand(2, 40, 50, 3, generator=g)
        self.train_indices = [0, 1]

    def rays(self, v: int) -> RayBundle:
        rows, cols = torch.meshgrid(torch.arange(40.0), torch.arange(50.0), indexing="ij")
        origins = torch.stack([torch.full_like(rows, float(v)), rows, cols], dim=-1)
        ones = torch.ones(40, 50)
        return RayBundle(origins, torch.nn.functional.normalize(torch.ones(40, 50, 3), dim=-1), ones, 2 * ones, ones)


class _MiscalibratedModel(torch.nn.Module):
    """Renders each ray's true colour plus N(0, (true_scale * std)^2) noise and reports variance std^2:
    a colour std too small by ``true_scale``."""

    def __init__(self, dataset: _PixelDataset, std: float, true_scale: float):
        super().__init__()
        self.dummy = torch.nn.Parameter(torch.zeros(1))
        self.dataset, self.std, self.true_scale = dataset, std, true_scale

    def render_view(self, rays: RayBundle, generator=None):
        o = rays.origins.long()
        gt = self.dataset.images[o[..., 0], o[..., 1], o[..., 2]].double()
        noise = torch.randn(gt.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        return {"colour_mean": gt + self.true_scale * self.std * noise,
                "colour_var": torch.full_like(gt, self.std ** 2)}


@pytest.mark.parametrize("true_scale", [0.5, 3.0])
def test_colour_map_recovers_a_known_miscalibration(true_scale):
    ds = _PixelDataset()
    model = _MiscalibratedModel(ds, std=0.02, true_scale=true_scale)
    cal = fit_colour_calibration(model, ds, fraction=0.3, block=5)
    assert cal.quantity == "colour_std"
    n_pixels = sum(int(holdout_mask(40, 50, v, fraction=0.3, block=5).sum()) for v in (0, 1))
    assert cal.num_samples == 3 * n_pixels  # every channel value of every held-out pixel
    # Gaussian errors: s(p) = true_scale at every level, up to the sampling error of ~1400 values
    np.testing.assert_allclose(cal.std_scale, true_scale, rtol=0.06)
    np.testing.assert_allclose(cal.scale_at(np.array([0.5, 0.9])), true_scale, rtol=0.08)


def test_colour_map_needs_held_out_pixels():
    ds = _PixelDataset()
    with pytest.raises(ValueError, match="holdout_fraction"):
        fit_colour_calibration(_MiscalibratedModel(ds, 0.02, 1.0), ds, fraction=0.0, block=5)


def test_apply_calibration_scales_colour_and_keeps_the_raw_std(tmp_path):
    scales = np.full(len(CALIBRATION_LEVELS), 2.5)
    cal = RunCalibration(colour=QuantileCalibration("colour_std", CALIBRATION_LEVELS, scales, 100, "test"))
    products = {"colour_std": np.full((2, 2, 3), 0.1, np.float32), "depth_std": np.ones((2, 2), np.float32)}
    out = apply_calibration(products, cal)
    np.testing.assert_allclose(out["colour_std"], 0.25, rtol=1e-6)
    assert out["colour_std"].dtype == np.float32
    assert out["colour_std_raw"] is products["colour_std"]
    assert out["depth_std"] is products["depth_std"] and "depth_std_raw" not in out  # no depth map: untouched
    # stored and read back; a file written before colour maps existed reads with none
    save_run_calibration(tmp_path, cal)
    back = load_run_calibration(tmp_path)
    assert back.depth is None and back.colour.std_scale == pytest.approx(2.5)
    (tmp_path / "calibration.json").write_text(json.dumps({"depth": None, "points": "calibrate"}))
    assert load_run_calibration(tmp_path).colour is None


@pytest.mark.slow
def test_a_run_with_held_out_pixels_fits_and_applies_the_colour_map(tiny_scene, tmp_path):
    from stochastic_fields.calibration import calibrate_run
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    cfg.train.iterations = 30
    cfg.train.rays_per_batch = 128
    cfg.render.num_samples = 24
    cfg.train.holdout_fraction = 0.2
    cfg.train.holdout_block = 8
    ds = load_dataset(tiny_scene, split_every=5)
    model = Trainer(cfg, tmp_path, ds).train(progress=False)
    cal = calibrate_run(tmp_path, model=model, dataset=ds)
    assert cal.colour is not None and "held out from training" in cal.colour.source
    assert load_run_calibration(tmp_path).colour.std_scale == pytest.approx(cal.colour.std_scale)
    result = evaluate(model, ds, tmp_path / "eval", views=[ds.test_indices[0]], progress=False, calibration=cal)
    assert len(result["per_view"]["nll_raw"]) == 1 and len(result["per_view"]["auce_colour_raw"]) == 1
    assert "colour_calibration" in result["conventions"]
