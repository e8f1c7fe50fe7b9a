"""Pixels of the training views held out from training, to recalibrate the colour uncertainty.

A user's capture has no test views with known answers, but its training photos have pixels the
model need not see. ``train.holdout_fraction`` of each training view's pixel blocks
(``train.holdout_block`` x ``train.holdout_block`` pixels, the image cut into a grid from its top-left
corner; the last row and column of blocks may be smaller) are left out of the training rays;
after training, the colour std is recalibrated on them (``calibration.fit_colour_calibration``).

Blocks rather than single pixels: a held-out pixel whose neighbours trained is nearly a training
pixel (the grid's cells span several pixels), so its error would understate a novel view's. The
choice depends on the image size, the view index, the fraction and the block size alone (a fixed
seed, ``HOLDOUT_SEED``), never on the run's seed: every method and every run of a scene holds out
the same pixels. Each view holds out round(fraction x blocks) blocks, at least one when the
fraction is positive. docs/uncertainty.md ("Colour recalibration") states the protocol and its limits.
"""

from __future__ import annotations

import numpy as np

#: Seed of the held-out block choice (fixed: the same pixels for every run of a scene).
HOLDOUT_SEED: int = 20_261_123


def holdout_mask(height: int, width: int, view: int, *, fraction: float, block: int) -> np.ndarray:
    """[H, W] bool: True at the pixels of view ``view`` held out from training (module doc).

    All False for ``fraction`` 0. ValueError for a fraction outside [0, 1), a block < 1 or an
    empty image."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"holdout fraction must lie in [0, 1), got {fraction}")
    if block < 1:
        raise ValueError(f"holdout block must be at least 1 pixel, got {block}")
    if height < 1 or width < 1:
        raise ValueError(f"holdout mask of an empty image ({height} x {width})")
    mask = np.zeros((height, width), dtype=bool)
    if fraction == 0.0:
        return mask
    rows, cols = -(-height // block), -(-width // block)
    count = max(1, int(round(fraction * rows * cols)))
    rng = np.random.default_rng([HOLDOUT_SEED, int(view)])
    for b in rng.choice(rows * cols, size=count, replace=False):
        r, c = divmod(int(b), cols)
        mask[r * block:(r + 1) * block, c * block:(c + 1) * block] = True
    return mask


def holdout_masks(dataset, views, *, fraction: float, block: int) -> np.ndarray:
    """[V, H, W] bool masks of ``views`` of a dataset (images [N, H, W, 3])."""
    height, width = int(dataset.images.shape[1]), int(dataset.images.shape[2])
    return np.stack([holdout_mask(height, width, int(v), fraction=fraction, block=block) for v in views])
