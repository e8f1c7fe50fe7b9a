"""Post-hoc recalibration of S-NeRF's depth uncertainty from the capture's own points.

The rendered depth standard deviation sigma ranks errors but its scale (and the shape of the
error distribution) need not match what happens on real scenes. Quantile recalibration
(Kuleshov et al. 2018) fixes this with data a user has: the capture points that training did not
fit (``capture_points``: structure-from-motion points split by blocks of space; by default the
CALIBRATE and SCORE roles, ``CALIBRATION_POINTS``), rendered from calibration views: virtual
cameras halfway between neighbouring training views (novel viewpoints, as the test views are,
made without them; ``calibration_views``). A map fitted on the SCORE points too is scored on them
by its cross-fitted fold maps (``DepthFolds``), each fitted without the blocks it judges.

With standardised errors |z| = |d - d*| / sigma on those points and z_p = Phi^-1((1 + p) / 2),
the map stores, for nominal central levels p,

    s(p) = Q_p(|z|) / z_p                       (Q_p: empirical p-quantile)

so that the interval ``d +- s(p) z_p sigma`` holds the fitted points at rate p. Applied:

    sigma_cal = s(p1) sigma,  p1 = Phi(1) - Phi(-1) = 0.6827   (the calibrated one-sigma std)
    interval at level p:  d +- z_p sigma_cal * s(p) / s(p1)    (``relative_scale``)

A Gaussian error model with the right scale gives s(p) constant; heavier or lighter tails give
an s(p) that rises or falls with p. The raw sigma stays available (``depth_std_raw``).

A depth map may also hold a depth-proportional term rho (``fit_relative_floor``, ``DEPTH_RELATIVE_FLOOR``):
the errors are standardised by sqrt(sigma^2 + (rho d)^2), d the rendered depth, and

    sigma_cal = s(p1) sqrt(sigma^2 + (rho d)^2)

A pixel rendered on the wrong surface with a tiny sigma has an error that is a fraction of its
depth, not a multiple of its sigma: without rho, the few such pixels set s(95%) for every pixel
(x100 on flower), with rho their standardised error is bounded by about |err| / (rho d).
rho is the grid value that minimises the mean CRPS / depth of the fitted distribution on the
fitting points (a proper score: it pays for width and for misses at every level at once);
docs/uncertainty.md, study 20.

A depth map may also hold an occlusion-edge term gamma (``fit_edge_weight``, ``DEPTH_EDGE_TERM``):
the errors are standardised by sqrt(sigma^2 + (gamma Delta)^2 + ...), Delta the range of the depths
rendered around the pixel (``depth_edges``): a pixel beside an occlusion edge may render the other
surface, an error about the size of the step there whatever its own ray's std says.

A depth map may also hold a parallax term kappa (``fit_parallax_weight``, ``DEPTH_PARALLAX_TERM``): the
errors are standardised by sqrt(sigma^2 + ... + (kappa d / max(sin theta, PARALLAX_MIN_SIN))^2), theta the
widest angle between the training views that see the rendered point (``parallax``): a surface the
photos saw with little parallax is placed less surely than its std says.

A map may also hold a std floor tau (``fit_std_floor``; depth only, ``DEPTH_STD_FLOOR``): the
errors are standardised by sqrt(sigma^2 + tau^2) instead of sigma, and

    sigma_cal = s(p1) sqrt(sigma^2 + tau^2)

tau is the smallest value for which the standardised errors carry no trend in sigma (their
Spearman correlation with sigma is zero): without it the most confident renders hold the largest
standardised errors (a surface rendered in the wrong place with a tiny std), one scale fitted to
all of them is too wide where sigma is large and too narrow where it is small, and the coverage of
a set of points depends on its mix of sigmas. sigma_cal is increasing in sigma, so rankings
(Spearman, AUSE) are unchanged by it.

The colour std gets the same kind of map when the run held pixel blocks of its training views out
of training (``train.holdout_fraction``, ``holdout``): |z| = |c - c*| / sigma_c per channel value
of the held-out pixels, rendered from their own (training) cameras; applied as for depth
(``colour_std`` calibrated, ``colour_std_raw`` kept). docs/uncertainty.md states the protocols
and their limits.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.special import ndtri
from scipy.stats import spearmanr
from . import metrics as M
from .cameras import camera_to_world
from .capture_points import CALIBRATE, SCORE, block_keys, load_capture_points, rays_through_points
from .config import load_config
from .constants import DEPTH_NLL_VARIANCE_FLOOR
from .holdout import holdout_masks
from .io_utils import atomic_write_text, read_json
from .sparse_depth import COVERAGE_LEVELS, project_sparse_depth
from .trainer import load_trained_model
from .virtual_views import BOUNDS_CHOICES, views_between  # noqa: F401 (BOUNDS_CHOICES: studies read it here)
from .view_maps import OPACITY_MASK
from .defaults import (CALIBRATION_FILE, CALIBRATION_PAIR_POINTS, CALIBRATION_POINTS, CROSS_FIT_FOLDS,  # noqa: F401
                       DEFAULT_CALIBRATION_PAIR_POINTS, DEFAULT_CALIBRATION_POINTS, DEPTH_EDGE_TERM, DEPTH_FREE_SPACE,
                       DEPTH_PARALLAX_TERM, DEPTH_RELATIVE_FLOOR, DEPTH_STD_FLOOR)  # (defaults the command line shows)
from .depth_edges import edge_range_at_points, edge_range_map
from .free_space import (TRAINING_DEPTH_FILE, checked_std, load_training_depth,
                         render_training_depth, rendered_points, save_training_depth)
from .parallax import parallax_term, training_view_maps, training_view_terms
from .pose_check import check_photo_fit, load_training_fit, photo_names, save_training_fit

#: Central level of +-1 standard deviation: Phi(1) - Phi(-1).
ONE_SIGMA_LEVEL: float = 0.682689492137086
#: Levels at which a map is fitted: 0.01, 0.02, ..., 0.99.
CALIBRATION_LEVELS: np.ndarray = np.round(np.arange(1, 100) / 100.0, 2)
#: Fewest standardised errors a map may be fitted on (below it the quantiles are noise).
MIN_CALIBRATION_SAMPLES: int = 50
#: Smallest scale a fitted map may hold (a map of zeros would claim certainty).
MIN_CALIBRATION_SCALE: float = 1e-3
#: Seed of the deal of the SCORE blocks into folds (``DepthFolds``; study 18's diagnostic: seed 0).
CROSS_FIT_SEED: int = 0
#: Relative precision of the fitted std floor (bisection in log tau stops there).
STD_FLOOR_RTOL: float = 1e-4
#: A floor is fitted only when the standardised errors fall with sigma at this one-sided significance
#: (Spearman test): sampling noise alone must not put a floor under a std that needs none.
STD_FLOOR_SIGNIFICANCE: float = 0.05
#: Largest std floor tried, in multiples of the largest raw std (beyond it the std is ~constant).
STD_FLOOR_MAX_RATIO: float = 100.0
#: Values of the depth-proportional term rho tried by ``fit_relative_floor``: 0 and 48 values
#: spaced evenly in log from 0.1% to 100% of the depth (neighbours 15% apart).
RELATIVE_FLOOR_GRID: np.ndarray = np.concatenate([[0.0], np.geomspace(1e-3, 1.0, 48)])
#: Weights beta of the free-space violation a checked depth map tries (``fit_check_weight``): 0 (the
#: unchecked map) and 12 log-spaced values to 1 (the full check); studies 22d and 22e.
CHECK_WEIGHT_GRID: np.ndarray = np.concatenate([[0.0], np.geomspace(0.03, 1.0, 12)])
#: Weights gamma of the occlusion-edge size Delta an edge-term depth map tries (``fit_edge_weight``): 0
#: (no term) and 12 log-spaced values from 0.05 to 2 (the depth error anatomy measured 0.25 to 1).
EDGE_WEIGHT_GRID: np.ndarray = np.concatenate([[0.0], np.geomspace(0.05, 2.0, 12)])
#: Weights kappa of the parallax term d / max(sin theta, PARALLAX_MIN_SIN) a parallax depth map tries
#: (``fit_parallax_weight``): 0 (no term) and 31 log-spaced values from 1e-6 to 0.1 (the research log's
#: analysis fitted 3e-4 to 3e-3 on LLFF).
PARALLAX_WEIGHT_GRID: np.ndarray = np.concatenate([[0.0], np.geomspace(1e-6, 0.1, 31)])
#: What the calibration renders' source says of a checked std (the fit names the weight it chose).
CHECKED_SOURCE: str = ", std checked against the training views' free space"


@dataclass
class QuantileCalibration:
    """Quantile recalibration of one quantity's standard deviation (module doc).

    Attributes:
        quantity: what it calibrates (e.g. "depth_std", camera-z).
        levels: [L] nominal central levels in (0, 1), increasing.
        scales: [L] s(p) at those levels (> 0; s(p) z_p is non-decreasing in p).
        num_samples: standardised errors it was fitted on.
        source: the data it was fitted on, in words.
        floor: the std floor tau (units of the quantity; 0: none): errors are standardised by
            sqrt(sigma^2 + tau^2) (module doc, ``fit_std_floor``).
        free_space: the map was fitted on (and applies to) the free-space-checked std
            sqrt(sigma^2 + (beta e)^2), e the rendered point's violation of the training views' free
            space (``free_space``; depth only) and beta ``free_space_weight``.
        relative_floor: the depth-proportional term rho (0: none): errors are standardised by
            sqrt(sigma^2 + tau^2 + (rho d)^2), d the rendered depth (module doc,
            ``fit_relative_floor``; depth only).
        free_space_weight: beta, the weight of the free-space violation in a ``free_space`` map
            (``fit_check_weight``; files without it: 1, the full check).
        edge_weight: gamma, the weight of the occlusion-edge size Delta (``depth_edges``; 0: no term,
            files without it): errors are standardised by sqrt(sigma^2 + ... + (gamma Delta)^2)
            (``fit_edge_weight``; depth only).
        parallax_weight: kappa, the weight of the parallax term d / max(sin theta, PARALLAX_MIN_SIN),
            theta the widest angle between training views that see the rendered point (``parallax``;
            0: no term, files without it): errors are standardised by sqrt(sigma^2 + ... + (kappa d /
            max(sin theta, PARALLAX_MIN_SIN))^2) (``fit_parallax_weight``; depth only).
    """

    quantity: str
    levels: np.ndarray
    scales: np.ndarray
    num_samples: int
    source: str = ""
    floor: float = 0.0
    free_space: bool = False
    relative_floor: float = 0.0
    free_space_weight: float = 1.0
    edge_weight: float = 0.0
    parallax_weight: float = 0.0

    @property
    def needs_training_depth(self) -> bool:
        """Whether applying the map needs the training views' rendered depths (``free_space.TrainingDepth``):
        a free-space check or a parallax term."""
        return self.free_space or self.parallax_weight > 0.0

    @classmethod
    def fit(cls, abs_z: np.ndarray, *, quantity: str, source: str = "",
            levels: np.ndarray = CALIBRATION_LEVELS) -> "QuantileCalibration":
        """Fit s(p) = Q_p(|z|) / z_p on standardised errors ``abs_z`` [N] (finite, >= 0).

        Raises ValueError for fewer than ``MIN_CALIBRATION_SAMPLES`` values or non-finite ones."""
        z = np.asarray(abs_z, dtype=np.float64).reshape(-1)
        if z.size < MIN_CALIBRATION_SAMPLES:
            raise ValueError(f"calibration of {quantity} needs at least {MIN_CALIBRATION_SAMPLES} standardised "
                             f"errors, got {z.size} ({source})")
        if not np.isfinite(z).all() or (z < 0).any():
            raise ValueError(f"calibration of {quantity}: standardised errors must be finite and >= 0")
        levels = np.asarray(levels, dtype=np.float64)
        q = np.quantile(z, levels)  # non-decreasing in p
        scales = np.maximum(q / ndtri((1.0 + levels) / 2.0), MIN_CALIBRATION_SCALE)
        return cls(quantity, levels, scales, int(z.size), source)

    @classmethod
    def fit_errors(cls, abs_err: np.ndarray, std: np.ndarray, *, quantity: str, source: str = "",
                   floor: bool = False, depth: np.ndarray | None = None,
                   levels: np.ndarray = CALIBRATION_LEVELS) -> "QuantileCalibration":
        """Fit on absolute errors ``abs_err`` [N] and raw stds ``std`` [N] (> 0): with ``floor``, first
        the std floor tau (``fit_std_floor``); with the rendered depths ``depth`` [N] (> 0), then the
        depth-proportional term rho (``fit_relative_floor``); then s(p) on
        |err| / sqrt(std^2 + tau^2 + (rho depth)^2) (``fit``)."""
        abs_err, std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (abs_err, std))
        if abs_err.shape != std.shape:
            raise ValueError(f"calibration of {quantity}: {abs_err.size} errors but {std.size} stds")
        if not (np.isfinite(std).all() and (std > 0).all()):
            raise ValueError(f"calibration of {quantity}: stds must be finite and > 0")
        tau = fit_std_floor(abs_err, std) if floor and abs_err.size >= MIN_CALIBRATION_SAMPLES else 0.0
        std = np.hypot(std, tau)
        rho = 0.0
        if depth is not None:
            depth = np.asarray(depth, dtype=np.float64).reshape(-1)
            if depth.shape != std.shape or not (np.isfinite(depth).all() and (depth > 0).all()):
                raise ValueError(f"calibration of {quantity}: needs one finite depth > 0 per error, got {depth.size} "
                                 f"depths for {std.size} errors")
            if abs_err.size >= MIN_CALIBRATION_SAMPLES:
                rho = fit_relative_floor(abs_err, std, depth)
            std = np.hypot(std, rho * depth)
        out = cls.fit(abs_err / std, quantity=quantity, source=source, levels=levels)
        out.floor, out.relative_floor = float(tau), float(rho)
        return out

    def calibrated_std(self, raw: np.ndarray, violation: np.ndarray | None = None,
                       depth: np.ndarray | None = None, edge: np.ndarray | None = None,
                       parallax: np.ndarray | None = None) -> np.ndarray:
        """s(0.6827) sqrt(raw^2 + floor^2 [+ (beta violation)^2] [+ (gamma edge)^2]
        [+ (kappa depth / max(sin parallax, PARALLAX_MIN_SIN))^2] [+ (relative_floor depth)^2]) in float64:
        the calibrated one-sigma std of raw stds [...]; a ``free_space`` map needs the free-space
        ``violation`` [...], a map with an ``edge_weight`` the occlusion-edge size ``edge`` [...]
        (``depth_edges``), a map with a ``parallax_weight`` the parallax angle ``parallax`` [...]
        (degrees, ``parallax``) and the rendered ``depth``, a map with a ``relative_floor`` the
        rendered ``depth`` [...] (same shape)."""
        std = np.hypot(np.asarray(raw, dtype=np.float64), self.floor)
        if self.free_space:
            if violation is None:
                raise ValueError(f"the {self.quantity} map was fitted on the free-space-checked std: it needs each "
                                 "pixel's free-space violation (free_space.violation_map)")
            std = np.hypot(std, self.free_space_weight * np.asarray(violation, dtype=np.float64))
        if self.edge_weight > 0.0:
            if edge is None:
                raise ValueError(f"the {self.quantity} map has an occlusion-edge term: it needs each pixel's edge size "
                                 "(depth_edges.edge_range_map)")
            std = np.hypot(std, self.edge_weight * np.asarray(edge, dtype=np.float64))
        if self.parallax_weight > 0.0:
            if parallax is None or depth is None:
                raise ValueError(f"the {self.quantity} map has a parallax term: it needs each pixel's parallax angle "
                                 "(parallax.parallax_map) and rendered depth")
            std = np.hypot(std, self.parallax_weight * parallax_term(parallax, depth))
        if self.relative_floor > 0.0:
            if depth is None:
                raise ValueError(f"the {self.quantity} map has a depth-proportional term: it needs each pixel's "
                                 "rendered depth")
            std = np.hypot(std, self.relative_floor * np.asarray(depth, dtype=np.float64))
        return self.std_scale * std

    def scale_at(self, p: float | np.ndarray) -> np.ndarray:
        """s(p), linear between fitted levels, constant beyond the first and last."""
        return np.interp(np.asarray(p, dtype=np.float64), self.levels, self.scales)

    @property
    def std_scale(self) -> float:
        """s(0.6827): the factor from the raw to the calibrated one-sigma std."""
        return float(self.scale_at(ONE_SIGMA_LEVEL))

    def relative_scale(self, p: float | np.ndarray) -> np.ndarray:
        """s(p) / s(0.6827): the interval multiplier at level p for the *calibrated* std."""
        return self.scale_at(p) / self.std_scale

    def to_dict(self) -> dict[str, Any]:
        return {"quantity": self.quantity, "levels": self.levels.tolist(), "scales": self.scales.tolist(),
                "num_samples": self.num_samples, "source": self.source, "std_scale": self.std_scale,
                "floor": self.floor, "free_space": self.free_space, "relative_floor": self.relative_floor,
                "free_space_weight": self.free_space_weight, "edge_weight": self.edge_weight,
                "parallax_weight": self.parallax_weight}

    @classmethod
    def from_dict(cls, data: dict, *, where: str = "calibration") -> "QuantileCalibration":
        try:
            levels = np.asarray(data["levels"], dtype=np.float64)
            scales = np.asarray(data["scales"], dtype=np.float64)
            out = cls(str(data["quantity"]), levels, scales, int(data["num_samples"]), str(data.get("source", "")),
                      float(data.get("floor", 0.0)),  # files written before the floor: none
                      data.get("free_space", False),  # ... before the free-space check: none
                      float(data.get("relative_floor", 0.0)),  # ... before the depth-proportional term: none
                      float(data.get("free_space_weight", 1.0)),  # ... before the check's weight: the full check
                      float(data.get("edge_weight", 0.0)),  # ... before the edge term: none
                      float(data.get("parallax_weight", 0.0)))  # ... before the parallax term: none
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: malformed quantile calibration ({exc!r})") from exc
        if not isinstance(out.free_space, bool):
            raise ValueError(f"{where}: free_space must be true or false, got {out.free_space!r}")
        if not (math.isfinite(out.floor) and out.floor >= 0.0):
            raise ValueError(f"{where}: the std floor must be finite and >= 0, got {out.floor}")
        _check_weight(out.free_space_weight, where)
        _edge_weight(out.edge_weight, where)
        _parallax_weight(out.parallax_weight, where)
        if not (math.isfinite(out.relative_floor) and out.relative_floor >= 0.0):
            raise ValueError(f"{where}: the depth-proportional term must be finite and >= 0, got {out.relative_floor}")
        if (levels.ndim != 1 or levels.shape != scales.shape or levels.size == 0 or not np.isfinite(levels).all()
                or not np.isfinite(scales).all() or (levels <= 0).any() or (levels >= 1).any()
                or (np.diff(levels) <= 0).any() or (scales <= 0).any()):
            raise ValueError(f"{where}: levels must increase inside (0, 1) and scales be positive and finite, "
                             f"with one scale per level")
        return out


@dataclass
class DepthFolds:
    """Cross-fitted fold maps that score a depth map fitted on the SCORE capture points too
    (``points="held-out"``) without letting it judge the points it saw.

    The SCORE role's blocks of space (``capture_points.block_keys``) are dealt into folds; fold f's
    map is fitted, like the run's map, on every held-out calibration render whose point lies outside
    fold f's blocks. A scored depth whose surface lies in a block of fold f is judged by map f
    (``cross_fitted_depth_scores``): no map sees the block of a point it scores. Each fold map is
    fitted on about (1 - 1 / (3 folds)) of the held-out points, so the scores estimate how the run's
    map (fitted on all of them) holds on surfaces it did not see. Render, export and every ranking
    score use the run's map; only the scores of its intervals (coverage, AUCE, NLL) use the folds.

    Attributes:
        blocks: per fold, its block keys [B_f] int64.
        maps: per fold, its map.
        seed: seed of the deal.
    """

    blocks: list[np.ndarray]
    maps: list[QuantileCalibration]
    seed: int = CROSS_FIT_SEED

    def fold_of(self, keys: np.ndarray) -> np.ndarray:
        """Fold of each block key [N] -> [N] int64 (-1: a block in no fold)."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        out = np.full(keys.shape, -1, dtype=np.int64)
        for f, blocks in enumerate(self.blocks):
            out[np.isin(keys, blocks)] = f
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "blocks": [b.tolist() for b in self.blocks], "maps": [m.to_dict() for m in self.maps]}

    @classmethod
    def from_dict(cls, data: dict, *, where: str) -> "DepthFolds":
        try:
            blocks = [np.asarray(b, dtype=np.int64).reshape(-1) for b in data["blocks"]]
            maps = [QuantileCalibration.from_dict(m, where=f"{where}: fold {f}") for f, m in enumerate(data["maps"])]
            seed = int(data.get("seed", CROSS_FIT_SEED))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, ValueError) and str(exc).startswith(where):
                raise
            raise ValueError(f"{where}: malformed depth folds ({exc!r})") from exc
        if not blocks or len(blocks) != len(maps):
            raise ValueError(f"{where}: depth folds need one map per fold, got {len(blocks)} folds and {len(maps)} maps")
        every = np.concatenate(blocks)
        if len(np.unique(every)) != len(every):
            raise ValueError(f"{where}: a block belongs to more than one fold")
        return cls(blocks, maps, seed)


def fit_depth_folds(abs_err: np.ndarray, std: np.ndarray, keys: np.ndarray, score_blocks: np.ndarray, *,
                    folds: int = CROSS_FIT_FOLDS, seed: int = CROSS_FIT_SEED, floor: bool = False,
                    depth: np.ndarray | None = None, source: str = "") -> DepthFolds:
    """``DepthFolds`` from the held-out calibration renders: absolute errors ``abs_err`` [N], their
    stds ``std`` [N] (> 0) and the block key of each point ``keys`` [N]; ``score_blocks`` [B]: the
    SCORE role's block keys, shuffled (``seed``) and dealt round-robin into ``folds`` folds; fold f's
    map is fitted (``QuantileCalibration.fit_errors``, ``floor`` and the rendered ``depth`` [N] for
    a depth-proportional term as the run's map) on the renders outside fold f's blocks. ValueError for fewer than 2 folds or blocks, or a fold map with too few
    points."""
    score_blocks = np.unique(np.asarray(score_blocks, dtype=np.int64))
    if folds < 2 or len(score_blocks) < 2:
        raise ValueError(f"cross-fitting needs at least 2 folds and 2 SCORE blocks, got {folds} folds and "
                         f"{len(score_blocks)} blocks")
    order = np.random.default_rng(seed).permutation(score_blocks)
    blocks = [np.sort(order[f::folds]) for f in range(min(folds, len(order)))]
    keys = np.asarray(keys, dtype=np.int64)
    maps = []
    for f, b in enumerate(blocks):
        out = ~np.isin(keys, b)
        maps.append(QuantileCalibration.fit_errors(abs_err[out], std[out], quantity="depth_std", floor=floor,
                                                   depth=None if depth is None else np.asarray(depth)[out],
                                                   source=f"{source}, outside fold {f}'s {len(b)} SCORE blocks"))
    return DepthFolds(blocks, maps, seed)


def cross_fitted_depth_scores(gt: np.ndarray, pred: np.ndarray, raw_std: np.ndarray, fold: np.ndarray,
                              folds: DepthFolds, *, violation: np.ndarray | None = None,
                              var_floor: float | None = None, coverage_levels=None,
                              edge: np.ndarray | None = None, parallax: np.ndarray | None = None) -> dict[str, Any]:
    """The interval scores of depths judged by their folds' maps (``DepthFolds``): each depth i of
    fold f = ``fold`` [N] gets std_i = map_f.calibrated_std(raw_std_i, violation_i) and the interval
    at level p pred_i +- z_p std_i s_f(p) / s_f(0.6827). ``raw_std`` [N]: the raw total std;
    ``violation`` [N]: each depth's free-space violation, which maps fitted with the free-space
    check need (``QuantileCalibration.calibrated_std``); ``edge`` [N]: each depth's occlusion-edge size,
    which maps with an edge term need; ``parallax`` [N]: each depth's parallax angle, which maps with a
    parallax term need. Pooled over the folds:
    {"nll": mean Gaussian NLL (``metrics.depth_nll``), "coverage_68", "coverage_95", "coverage" (at
    ``coverage_levels`` [L], default ``sparse_depth.COVERAGE_LEVELS``: +-1 and +-2 std; the first two
    are "coverage_68" and "coverage_95"), "auce", "calibration": ``metrics.CalibrationResult`` at the
    default levels}. ValueError when a depth lies in no fold."""
    gt, pred, raw_std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (gt, pred, raw_std))
    violation = None if violation is None else np.asarray(violation, dtype=np.float64).reshape(-1)
    edge = None if edge is None else np.asarray(edge, dtype=np.float64).reshape(-1)
    parallax = None if parallax is None else np.asarray(parallax, dtype=np.float64).reshape(-1)
    fold = np.asarray(fold, dtype=np.int64).reshape(-1)
    if (fold < 0).any() or (fold >= len(folds.maps)).any():
        raise ValueError(f"cross-fitted depth scores: {int(((fold < 0) | (fold >= len(folds.maps))).sum())} of "
                         f"{fold.size} depths lie in no fold's SCORE blocks")
    floor = DEPTH_NLL_VARIANCE_FLOOR if var_floor is None else var_floor
    levels = M.DEFAULT_CALIBRATION_LEVELS
    coverage_levels = list(COVERAGE_LEVELS if coverage_levels is None else coverage_levels)
    inside, inside_cov, nll_sum = np.zeros(len(levels)), np.zeros(len(coverage_levels)), 0.0
    for f, m in enumerate(folds.maps):
        i = fold == f
        if not i.any():
            continue
        std = m.calibrated_std(raw_std[i], None if violation is None else violation[i], pred[i],
                               None if edge is None else edge[i], None if parallax is None else parallax[i])
        inside += M.calibration_curve(gt[i], pred[i], std, interval_scale=m.relative_scale).coverage * i.sum()
        inside_cov += M.calibration_curve(gt[i], pred[i], std, levels=coverage_levels,
                                          interval_scale=m.relative_scale).coverage * i.sum()
        nll_sum += M.depth_nll(gt[i], pred[i], std ** 2, var_floor=floor) * int(i.sum())
    n = max(1, gt.size)
    cov = inside / n
    curve = M.CalibrationResult(levels=np.asarray(levels), coverage=cov, auce=float(np.abs(cov - levels).mean()),
                                signed_gap=float((cov - levels).mean()), num_values=int(gt.size))
    return {"nll": nll_sum / n, "coverage_68": float(inside_cov[0] / n), "coverage_95": float(inside_cov[1] / n),
            "coverage": (inside_cov / n).tolist(), "auce": curve.auce, "calibration": curve}


def cross_fitted_depth_quantiles(pred: np.ndarray, raw_std: np.ndarray, fold: np.ndarray, folds: DepthFolds, *,
                                 violation: np.ndarray | None = None, edge: np.ndarray | None = None,
                                 parallax: np.ndarray | None = None):
    """The predictive quantile function of depths judged by their folds' maps: t [Q] -> [N, Q], depth i
    of fold f = ``fold`` [N] getting ``metrics.gaussian_quantiles`` of (pred_i, map_f's calibrated
    std of raw_std_i, map_f's interval scale): the distribution whose intervals
    ``cross_fitted_depth_scores`` counts, for the width, interval score and CRPS
    (``metrics.interval_sharpness``). ValueError when a depth lies in no fold."""
    pred, raw_std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (pred, raw_std))
    fold = np.asarray(fold, dtype=np.int64).reshape(-1)
    if (fold < 0).any() or (fold >= len(folds.maps)).any():
        raise ValueError(f"cross-fitted depth quantiles: {int(((fold < 0) | (fold >= len(folds.maps))).sum())} of "
                         f"{fold.size} depths lie in no fold's SCORE blocks")
    stds = np.zeros_like(raw_std)
    for f, m in enumerate(folds.maps):
        i = fold == f
        if i.any():
            stds[i] = m.calibrated_std(raw_std[i], None if violation is None else np.asarray(violation)[i], pred[i],
                                       None if edge is None else np.asarray(edge)[i],
                                       None if parallax is None else np.asarray(parallax)[i])

    def quantiles(levels: np.ndarray) -> np.ndarray:
        out = np.zeros((pred.size, np.asarray(levels).size))
        for f, m in enumerate(folds.maps):
            i = fold == f
            if i.any():
                out[i] = M.gaussian_quantiles(pred[i], stds[i], levels, m.relative_scale)
        return out

    return quantiles


def fit_std_floor(abs_err: np.ndarray, std: np.ndarray) -> float:
    """The std floor tau >= 0 of ``abs_err`` [N] against raw stds ``std`` [N] (> 0): the smallest
    tau for which Spearman(std, |err| / sqrt(std^2 + tau^2)) = 0, i.e. the standardised errors
    carry no trend in sigma.

    At tau = 0 the correlation is Spearman(std, |z|); as tau grows it tends to Spearman(std, |err|).
    0 unless the first is negative at one-sided significance ``STD_FLOOR_SIGNIFICANCE`` (no
    over-confident low stds to lift, or too few errors to tell); ``STD_FLOOR_MAX_RATIO``
    times the largest std when even the second is < 0 (the std does not rank the errors at all: the
    map is then ~one constant std); otherwise the root, by bisection in log tau to ``STD_FLOOR_RTOL``.
    Constant stds or errors (Spearman undefined) give 0."""
    abs_err, std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (abs_err, std))
    if abs_err.shape != std.shape or abs_err.size < 3:
        raise ValueError(f"fit_std_floor: needs >= 3 paired errors and stds, got {abs_err.size} and {std.size}")
    if not (np.isfinite(abs_err).all() and (abs_err >= 0).all() and np.isfinite(std).all() and (std > 0).all()):
        raise ValueError("fit_std_floor: errors must be finite and >= 0, stds finite and > 0")

    def trend(tau: float) -> float:
        with warnings.catch_warnings():  # constant input: Spearman undefined, read as no trend
            warnings.simplefilter("ignore")
            rho = spearmanr(std, abs_err / np.hypot(std, tau))[0]
        return 0.0 if not np.isfinite(rho) else float(rho)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        at_zero = spearmanr(std, abs_err / std, alternative="less")
    if not (np.isfinite(at_zero.pvalue) and at_zero.pvalue < STD_FLOOR_SIGNIFICANCE):
        return 0.0
    lo, hi = float(std.min()) * 1e-6, float(std.max()) * STD_FLOOR_MAX_RATIO
    if trend(hi) < 0.0:
        return hi
    while hi / lo > 1.0 + STD_FLOOR_RTOL:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if trend(mid) < 0.0 else (lo, mid)
    return hi


def fit_relative_floor(abs_err: np.ndarray, std: np.ndarray, depth: np.ndarray,
                       grid: np.ndarray = RELATIVE_FLOOR_GRID) -> float:
    """The depth-proportional term rho of ``abs_err`` [N] against stds ``std`` [N] (> 0) at rendered
    depths ``depth`` [N] (> 0): the value of ``grid`` with the smallest ``relative_crps`` (ties go to
    the smaller rho, 0 first)."""
    abs_err, std, depth = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (abs_err, std, depth))
    if not (abs_err.shape == std.shape == depth.shape) or abs_err.size < 3:
        raise ValueError(f"fit_relative_floor: needs >= 3 paired errors, stds and depths, got {abs_err.size}, "
                         f"{std.size} and {depth.size}")
    if not (np.isfinite(abs_err).all() and (abs_err >= 0).all() and np.isfinite(std).all() and (std > 0).all()
            and np.isfinite(depth).all() and (depth > 0).all()):
        raise ValueError("fit_relative_floor: errors must be finite and >= 0, stds and depths finite and > 0")
    grid = np.asarray(grid, dtype=np.float64)
    return float(grid[int(np.argmin([relative_crps(abs_err, std, depth, rho) for rho in grid]))])


def relative_crps(abs_err: np.ndarray, std: np.ndarray, depth: np.ndarray, rho: float) -> float:
    """The mean CRPS / depth that the level map fitted on these points gives them with the term rho:

        mean_i CRPS(F_i, y_i) / d_i,   F_i symmetric about d_i with central half-width
        h_i(p) = Q_p(z) sqrt(std_i^2 + (rho d_i)^2) at level p,  z = |err| / sqrt(std^2 + (rho d)^2)

    (Q_p the empirical p-quantile), the CRPS in its quantile form at ``metrics.crps_levels()``
    (``metrics.crps_from_quantiles``). The CRPS of a symmetric distribution depends on |y - d|
    only, so ``abs_err`` [N] suffices. ``std``, ``depth`` [N] (> 0)."""
    t = M.crps_levels()
    total = np.hypot(std, rho * depth)
    half = np.quantile(abs_err / total, np.abs(2.0 * t - 1.0))  # [Q] in units of each point's total std
    q_minus_y = np.sign(t - 0.5)[None, :] * half[None, :] * total[:, None] - abs_err[:, None]  # y = d + |err|
    crps = 2.0 * (((q_minus_y > 0).astype(np.float64) - t[None, :]) * q_minus_y).mean(axis=1)
    return float((crps / depth).mean())


def _edge_weight(weight: float, where: str) -> float:
    """``weight`` when it is a valid occlusion-edge weight (finite, >= 0); ValueError naming ``where``."""
    if not (math.isfinite(weight) and weight >= 0.0):
        raise ValueError(f"{where}: the occlusion-edge weight must be finite and >= 0, got {weight}")
    return weight


def _parallax_weight(weight: float, where: str) -> float:
    """``weight`` when it is a valid parallax-term weight (finite, >= 0); ValueError naming ``where``."""
    if not (math.isfinite(weight) and weight >= 0.0):
        raise ValueError(f"{where}: the parallax term's weight must be finite and >= 0, got {weight}")
    return weight


def _check_weight(weight: float, where: str) -> float:
    """``weight`` when it is a valid free-space check weight (finite, >= 0); ValueError naming ``where``."""
    if not (math.isfinite(weight) and weight >= 0.0):
        raise ValueError(f"{where}: the free-space check's weight must be finite and >= 0, got {weight}")
    return weight


def fit_check_weight(abs_err: np.ndarray, sigma: np.ndarray, violation: np.ndarray, depth: np.ndarray,
                     grid: np.ndarray = CHECK_WEIGHT_GRID) -> float:
    """The weight beta of the free-space violation (studies 22d, 22e): the value of ``grid`` whose std
    sqrt(sigma^2 + (beta e)^2), with the depth-proportional term rho fitted on it
    (``fit_relative_floor``), gives the smallest mean CRPS / depth (``relative_crps``) on these points;
    ties go to the smaller beta (0 first: a scene the check does not help keeps the unchecked map).
    ``abs_err`` [N] (>= 0), ``sigma`` [N] (> 0), ``violation`` e [N] (>= 0), ``depth`` [N] (> 0)."""
    return _fit_term_weight(abs_err, sigma, violation, depth, grid, "fit_check_weight", "violation")


def fit_edge_weight(abs_err: np.ndarray, std: np.ndarray, edge: np.ndarray, depth: np.ndarray,
                    grid: np.ndarray = EDGE_WEIGHT_GRID) -> float:
    """The weight gamma of the occlusion-edge size (study 30): the value of ``grid`` whose std
    sqrt(std^2 + (gamma Delta)^2), with rho fitted on it (``fit_relative_floor``), gives the smallest
    mean CRPS / depth (``relative_crps``) on these points; ties go to the smaller gamma (0 first: no
    term where edges do not explain the errors). ``abs_err`` [N] (>= 0), ``std`` [N] (> 0; the
    checked std where the map checks free space), ``edge`` Delta [N] (>= 0), ``depth`` [N] (> 0)."""
    return _fit_term_weight(abs_err, std, edge, depth, grid, "fit_edge_weight", "edge size")


def fit_parallax_weight(abs_err: np.ndarray, std: np.ndarray, angle: np.ndarray, depth: np.ndarray,
                        grid: np.ndarray = PARALLAX_WEIGHT_GRID) -> float:
    """The weight kappa of the parallax term (``parallax``): the value of ``grid`` whose std
    sqrt(std^2 + (kappa d / max(sin theta, PARALLAX_MIN_SIN))^2), with rho fitted on it
    (``fit_relative_floor``), gives the smallest mean CRPS / depth (``relative_crps``) on these points;
    ties go to the smaller kappa (0 first: no term where the parallax does not explain the errors).
    ``abs_err`` [N] (>= 0), ``std`` [N] (> 0; with the map's other terms), ``angle`` theta [N]
    (degrees, >= 0), ``depth`` d [N] (> 0)."""
    angle, depth = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (angle, depth))
    if angle.shape != depth.shape or not (np.isfinite(angle).all() and (angle >= 0).all()):
        raise ValueError(f"fit_parallax_weight: needs one finite parallax angle >= 0 per depth, got {angle.size} for "
                         f"{depth.size}")
    return _fit_term_weight(abs_err, std, parallax_term(angle, depth), depth, grid, "fit_parallax_weight",
                            "parallax term")


def _fit_term_weight(abs_err: np.ndarray, std: np.ndarray, term: np.ndarray, depth: np.ndarray, grid: np.ndarray,
                     name: str, what: str) -> float:
    """The value w of ``grid`` whose std sqrt(std^2 + (w term)^2), rho fitted on it, has the smallest
    ``relative_crps`` (the first on ties); ``name`` and ``what`` name the caller and the term in errors."""
    abs_err, std, term, depth = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (abs_err, std, term, depth))
    if term.shape != std.shape or not (np.isfinite(term).all() and (term >= 0).all()):
        raise ValueError(f"{name}: needs one finite {what} >= 0 per std, got {term.size} for {std.size}")
    grid = np.asarray(grid, dtype=np.float64)
    scores = []
    for w in grid:
        total = np.hypot(std, w * term)
        scores.append(relative_crps(abs_err, total, depth, fit_relative_floor(abs_err, total, depth)))
    return float(grid[int(np.argmin(scores))])


def standardised_errors(gt: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """|gt - mean| / std over the entries with a finite, positive std: [N] -> [N'] float64."""
    gt, mean, std = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (gt, mean, std))
    keep = np.isfinite(gt) & np.isfinite(mean) & np.isfinite(std) & (std > 0)
    return np.abs(gt[keep] - mean[keep]) / std[keep]


def resplit_coverage(cal_abs_z: np.ndarray, cal_blocks: np.ndarray, score_abs_z: np.ndarray,
                     score_blocks: np.ndarray, blocks: np.ndarray, block_counts: np.ndarray, *,
                     share: float, levels=(ONE_SIGMA_LEVEL, 0.95), num_splits: int = 200,
                     seed: int = 0) -> np.ndarray:
    """Coverage of quantile recalibration over random re-splits of held-out blocks of space.

    One re-split shuffles ``blocks`` [B] (with ``block_counts`` [B] points each) and hands them,
    whole, to calibration until it holds ``share`` of the points (as ``split_points_by_blocks``);
    the map is fitted on the calibration errors ``cal_abs_z`` [N] whose ``cal_blocks`` [N] were
    drawn (``QuantileCalibration.fit``) and scored on the errors ``score_abs_z`` [M] of the other
    blocks: coverage at level p = share of those |z| <= s(p) z_p. The spread over re-splits is how
    far one split's coverage can fall from the procedure's expected coverage by the luck of which
    blocks calibrate; with exchangeable blocks the expected coverage is the nominal level.
    Re-splits with fewer than ``MIN_CALIBRATION_SAMPLES`` calibration errors or no scored error
    are skipped. Returns [num_splits', L] coverages."""
    cal_abs_z, cal_blocks = np.asarray(cal_abs_z, np.float64), np.asarray(cal_blocks)
    score_abs_z, score_blocks = np.asarray(score_abs_z, np.float64), np.asarray(score_blocks)
    blocks, block_counts = np.asarray(blocks), np.asarray(block_counts, np.float64)
    if cal_abs_z.shape != cal_blocks.shape or score_abs_z.shape != score_blocks.shape or blocks.shape != block_counts.shape:
        raise ValueError("resplit_coverage: errors and their blocks, and blocks and their counts, must have equal shapes")
    if not 0.0 < share < 1.0:
        raise ValueError(f"resplit_coverage: share must lie strictly between 0 and 1, got {share}")
    levels = np.asarray(levels, dtype=np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(int(num_splits)):
        order = rng.permutation(len(blocks))
        before = np.cumsum(block_counts[order]) - block_counts[order]  # points handed out before each block
        chosen = blocks[order][before < share * block_counts.sum()]
        fit_z = cal_abs_z[np.isin(cal_blocks, chosen)]
        scored = score_abs_z[~np.isin(score_blocks, chosen)]
        if fit_z.size < MIN_CALIBRATION_SAMPLES or scored.size == 0:
            continue
        cal = QuantileCalibration.fit(fit_z, quantity="depth_std", levels=levels)
        bound = cal.scales * ndtri((1.0 + levels) / 2.0)
        out.append((scored[:, None] <= bound[None, :]).mean(axis=0))
    return np.asarray(out, dtype=np.float64).reshape(-1, len(levels))


# --------------------------------------------------------------------------------------------
# a run's calibration
# --------------------------------------------------------------------------------------------


def render_at_points(model, cameras, near, far, sparse: dict, *,
                     generator: torch.Generator | None = None, options=None) -> dict[str, np.ndarray]:
    """Render the rays through the pixels of {view: SparseDepth} (continuous uv) of ``cameras``
    (bounds ``near``/``far``: floats or [V]) with the render ``options`` (default: the model's):
    camera-z depth mean, total std and opacity [N], with the points' depths [N] as "gt" (float64)."""
    found = rays_through_points(cameras, near, far, sparse)
    if found is None:
        return {k: np.zeros(0) for k in ("gt", "depth_mean", "depth_std", "opacity")}
    rays, gt = found
    device = next(model.parameters()).device
    rays = rays.to(device)
    with torch.no_grad():
        maps = model.render_view(rays.reshape(1, len(gt)), options, generator=generator)
    z = maps["z_scale"].double().cpu().reshape(-1)
    return {"gt": gt,
            "depth_mean": (maps["depth_mean"].double().cpu().reshape(-1) * z).numpy(),
            "depth_std": (maps["depth_var_total"].double().cpu().clamp_min(0).sqrt().reshape(-1) * z).numpy(),
            "opacity": maps["opacity"].double().cpu().reshape(-1).numpy()}


def edge_at_points(model, cameras, near, far, sparse: dict, depth: np.ndarray, *, seed: int = 0,
                   options=None) -> np.ndarray:
    """The occlusion-edge size Delta [N] (``depth_edges.edge_range_at_points``) of the rays
    ``render_at_points`` rendered for ``sparse`` (same arguments, its ray order), whose rendered
    depths are ``depth`` [N]: the 8 neighbouring rays of each are rendered with the generator seeded
    ``seed`` (as the centre's)."""
    views = [v for v, sd in sparse.items() if len(sd)]
    if not views:
        return np.zeros(0)
    sizes = [len(sparse[v]) for v in views]
    uv = np.concatenate([sparse[v].uv for v in views])
    device = next(model.parameters()).device

    def render_depth(moved: np.ndarray) -> np.ndarray:
        parts = np.split(moved, np.cumsum(sizes)[:-1])
        shifted = {v: replace(sparse[v], uv=part.astype(sparse[v].uv.dtype)) for v, part in zip(views, parts)}
        return render_at_points(model, cameras, near, far, shifted, options=options,
                                generator=torch.Generator(device=device).manual_seed(seed))["depth_mean"]

    width, height = (np.concatenate([np.full(n, float(size.reshape(-1)[v])) for v, n in zip(views, sizes)])
                     for size in (cameras.width, cameras.height))
    return edge_range_at_points(render_depth, uv, depth, width, height)


#: Nearest training neighbours each training view is paired with for calibration views.
CALIBRATION_NEIGHBOURS: int = 1
#: Where calibration views sit along each pair's arc (0: the first view, 1: the second).
CALIBRATION_FRACTIONS: tuple[float, ...] = (0.5,)
#: A calibration view's render bounds from its pair's: "widest" (the nearer near, the farther far)
#: or "interpolated" (both at the view's fraction). The grid's renders depend on the bounds (on
#: flower a 3% nearer near plane quadruples the depth error of a training view's own pixels):
#: docs/uncertainty.md, study 12.
CALIBRATION_BOUNDS: str = "widest"


def calibration_views(dataset, *, neighbours: int = CALIBRATION_NEIGHBOURS,
                      fractions: tuple[float, ...] = CALIBRATION_FRACTIONS, bounds: str = CALIBRATION_BOUNDS
                      ) -> tuple[object, torch.Tensor, torch.Tensor, list[tuple[int, int]]]:
    """Virtual cameras between each training view and its ``neighbours`` nearest other training
    views, at each of ``fractions`` of the way (default: halfway between nearest neighbours), with
    the pair's widest or interpolated bounds (``bounds``, ``CALIBRATION_BOUNDS``):
    ``virtual_views.views_between``. Novel viewpoints among the training ones, like the test views a
    user renders, made without any test view. Returns (cameras [P], near [P], far [P], the (i, j)
    view pair of each camera), the pairs (i < j) sorted and each pair's fractions in the given order."""
    return views_between(dataset, neighbours=neighbours, fractions=fractions, bounds=bounds,
                         what="calibration views")


def pair_visible_points(capture, pairs: list[tuple[int, int]], keep: np.ndarray, *,
                        pair_points: str = DEFAULT_CALIBRATION_PAIR_POINTS) -> list[np.ndarray]:
    """Per calibration view of ``pairs`` (i, j), the indices of the capture points with ``keep``
    [P] that both views i and j observed (``pair_points`` "both") or one of them ("either"; COLMAP
    tracks; every kept point when the capture has no visibility; ``defaults.CALIBRATION_PAIR_POINTS``,
    docs/studies.md, study 38). ValueError for an unknown ``pair_points``."""
    if pair_points not in CALIBRATION_PAIR_POINTS:
        raise ValueError(f"calibration pair points must be one of {CALIBRATION_PAIR_POINTS}, got {pair_points!r}")
    join = np.intersect1d if pair_points == "both" else np.union1d
    out = []
    for i, j in pairs:
        seen = (np.arange(len(capture.xyz)) if capture.visible is None
                else join(capture.visible[i], capture.visible[j]))
        out.append(seen[keep[seen]])
    return out


def depth_calibration_errors(model, dataset, *, seed: int = 0, opacity_mask: float | None = None,
                             points: str = "calibrate", options=None, bounds: str = CALIBRATION_BOUNDS,
                             free_space=None) -> tuple[np.ndarray, np.ndarray, str]:
    """``depth_calibration_renders`` (same arguments) as (absolute errors [N], stds [N], source)."""
    r = depth_calibration_renders(model, dataset, seed=seed, opacity_mask=opacity_mask, points=points,
                                  options=options, bounds=bounds, free_space=free_space)
    return r["abs_err"], r["std"], r["source"]


def calibration_view_points(dataset, capture, *, points: str = "calibrate", bounds: str = CALIBRATION_BOUNDS,
                            pair_points: str = DEFAULT_CALIBRATION_PAIR_POINTS):
    """The calibration views (``calibration_views``) and the capture points a depth map is fitted on
    in each ({view: SparseDepth}): the CALIBRATE role (``points="held-out"``: CALIBRATE and SCORE)
    that both views of the view's pair observed (``pair_points`` "either": one of them,
    ``pair_visible_points``). Returns (cameras, near, far, pairs, sparse)."""
    cams, near, far, pairs = calibration_views(dataset, bounds=bounds)
    role = np.isin(capture.roles, [CALIBRATE] if points == "calibrate" else [CALIBRATE, SCORE])
    sparse = project_sparse_depth(cams, capture.xyz, range(len(pairs)), visible=pair_visible_points(capture, pairs, role, pair_points=pair_points),
                                  visibility_name="pair")
    return cams, near, far, pairs, sparse


def training_view_terms_at_points(cameras, sparse: dict, xyz: np.ndarray, gt: np.ndarray, depth: np.ndarray,
                                  reference, *, free_space: bool, parallax: bool
                                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The free-space violation e [N] (``free_space.free_space_violation``; None unless ``free_space``)
    and the parallax angle theta_max [N] in degrees (``parallax.parallax_angle``; None unless
    ``parallax``) against the training views of ``reference`` (a ``free_space.TrainingDepth``) of the
    points ``render_at_points`` rendered for ``sparse`` ({view: SparseDepth} of ``cameras``, in its
    ray order): on each view's ray through capture point ``xyz[point_index]`` [P, 3], whose camera z is
    ``gt`` [N], the point at the rendered camera z ``depth`` [N] (finite;
    ``free_space.rendered_points``). One projection into each training view serves both terms
    (``parallax.training_view_terms``)."""
    if not (free_space or parallax):
        return None, None
    return training_view_terms(rendered_points_of(cameras, sparse, xyz, gt, depth), reference,
                               free_space=free_space, parallax=parallax)


def rendered_points_of(cameras, sparse: dict, xyz: np.ndarray, gt: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points [N, 3] ``render_at_points`` put for ``sparse`` ({view: SparseDepth} of ``cameras``,
    in its ray order): on each view's ray through capture point ``xyz[point_index]`` [P, 3], whose
    camera z is ``gt`` [N], the point at the rendered camera z ``depth`` [N]
    (``free_space.rendered_points``)."""
    views = [v for v, sd in sparse.items() if len(sd)]
    if not views:
        return np.zeros((0, 3))
    centres = camera_to_world(cameras).double()[:, :3, 3].numpy()[np.concatenate(
        [np.full(len(sparse[v]), v) for v in views])]
    index = np.concatenate([sparse[v].point_index for v in views])
    return rendered_points(centres, np.asarray(xyz)[index], gt, depth)


def depth_calibration_renders(model, dataset, *, seed: int = 0, opacity_mask: float | None = None,
                              points: str = "calibrate", options=None, bounds: str = CALIBRATION_BOUNDS,
                              free_space=None, edges: bool = False,
                              pair_points: str = DEFAULT_CALIBRATION_PAIR_POINTS, parallax=None) -> dict[str, Any]:
    """What a depth map is fitted on: the absolute camera-z errors "abs_err" [N] (signed, true minus
    rendered: "err") and raw total stds
    "std" [N] (> 0), with the capture point of each ("index" [N] int64), its calibration view ("view"
    [N], an index of ``calibration_views``), the rendered depth ("depth" [N]) and the data in words ("source"), at the CALIBRATE capture points (``points="held-out"``: CALIBRATE and SCORE, see
    ``CALIBRATION_POINTS``) seen from the calibration views (``calibration_views``: halfway between
    neighbouring training views; a point counts when both views of the pair observed it, or one of
    them with ``pair_points`` "either": ``pair_visible_points``), at pixels
    with rendered opacity above ``opacity_mask`` (as the depth scores), rendered with ``options``
    (default: the model's; a map fits the std of the K and estimator it is fitted with, so fit it
    with the options the run will render with; ``bounds``: the views' render bounds,
    ``calibration_views``); with ``free_space`` (``free_space.TrainingDepth``) "std" holds the
    checked ones at full weight, sqrt(sigma^2 + e^2) with e the rendered point's free-space violation
    (``free_space.checked_std``), "std_raw" the raw sigma and "violation" e [N]; with ``edges``,
    "edge" [N] holds each point's occlusion-edge size (``edge_at_points``: 8 more renders); with
    ``parallax`` (``free_space.TrainingDepth``), "parallax" [N] each rendered point's parallax angle
    (``training_view_terms_at_points``, degrees; one projection into each training view serves both
    terms, so when both are asked they must be the same reference).
    ValueError when the scene has no capture points, for an unknown ``points``, or for two different
    training-view references."""
    if points not in CALIBRATION_POINTS:
        raise ValueError(f"calibration points must be one of {CALIBRATION_POINTS}, got {points!r}")
    if free_space is not None and parallax is not None and parallax is not free_space:
        raise ValueError("the free-space check and the parallax term read one training-view reference: pass the "
                         "same free_space.TrainingDepth as both (got two different ones)")
    mask = OPACITY_MASK if opacity_mask is None else opacity_mask
    capture = load_capture_points(dataset)
    if capture is None:
        raise ValueError(f"{dataset.root}: no capture points (sparse/0/points3D.bin or dense depth) to calibrate on")
    cams, near, far, pairs, sparse = calibration_view_points(dataset, capture, points=points, bounds=bounds,
                                                             pair_points=pair_points)
    device = next(model.parameters()).device
    r = render_at_points(model, cams, near, far, sparse, generator=torch.Generator(device=device).manual_seed(seed),
                         options=options)
    keep = (r["opacity"] > mask) & np.isfinite(r["depth_mean"]) & np.isfinite(r["depth_std"]) & (r["depth_std"] > 0)
    roles = "calibrate role" if points == "calibrate" else "calibrate and score roles"
    source = (f"{int(keep.sum())} {capture.source} points of the {roles} seen from {len(pairs)} views halfway "
              f"between neighbouring training views{'' if pair_points == 'both' else ' (points either view of the pair observed)'}"
              f" (opacity > {mask})")
    std = sigma = r["depth_std"]
    violation = angle = None
    views = [v for v, sd in sparse.items() if len(sd)]  # the order of render_at_points' rays
    index = np.concatenate([sparse[v].point_index for v in views] or [np.zeros(0, np.int64)])
    at = np.where(keep, r["depth_mean"], r["gt"])  # where each kept ray's render put its point
    reference = free_space if free_space is not None else parallax  # one, when both are asked (checked above)
    if reference is not None:
        violation, angle = training_view_terms_at_points(cams, sparse, capture.xyz, r["gt"], at, reference,
                                                         free_space=free_space is not None and len(std) > 0,
                                                         parallax=parallax is not None)
    if violation is not None:
        std = checked_std(sigma, violation)
        source += CHECKED_SOURCE
    err = r["gt"][keep] - r["depth_mean"][keep]
    view = np.concatenate([np.full(len(sparse[v]), v) for v in views] or [np.zeros(0, np.int64)])
    out = {"abs_err": np.abs(err), "err": err, "std": std[keep], "index": index[keep], "view": view[keep],
           "depth": r["depth_mean"][keep], "source": source}
    if violation is not None:
        out.update({"std_raw": sigma[keep], "violation": violation[keep]})
    if edges:
        out["edge"] = edge_at_points(model, cams, near, far, sparse, r["depth_mean"], seed=seed, options=options)[keep]
    if angle is not None:
        out["parallax"] = angle[keep]
    return out


def fit_depth_calibration(model, dataset, *, seed: int = 0, opacity_mask: float | None = None,
                          points: str = "calibrate", options=None, floor: bool = DEPTH_STD_FLOOR,
                          free_space=None, relative_floor: bool = DEPTH_RELATIVE_FLOOR,
                          check_weight: float | None = None, edges: bool = DEPTH_EDGE_TERM,
                          edge_weight: float | None = None, parallax=None,
                          parallax_weight: float | None = None) -> QuantileCalibration:
    """The depth map fitted on ``depth_calibration_errors`` (same arguments, the default bounds);
    with ``floor``, a std floor first (``fit_std_floor``); with ``free_space``
    (``free_space.TrainingDepth``), on the free-space-checked std (the map's ``free_space``); with
    ``relative_floor``, a depth-proportional term (``fit_relative_floor``); ``check_weight``: the
    free-space violation's weight (None: fitted, ``fit_check_weight``); with ``edges``, an
    occlusion-edge term weighted ``edge_weight`` (None: fitted, ``fit_edge_weight``); with ``parallax``
    (``free_space.TrainingDepth``), a parallax term weighted ``parallax_weight`` (None: fitted,
    ``fit_parallax_weight``). ValueError when the scene has no capture points or too few of those
    roles, or for an unknown ``points``."""
    r = depth_calibration_renders(model, dataset, seed=seed, opacity_mask=opacity_mask, points=points,
                                  options=options, free_space=free_space, edges=edges, parallax=parallax)
    return _fit_depth_map(r, floor=floor, relative_floor=relative_floor, check_weight=check_weight,
                          edge_weight=edge_weight, parallax_weight=parallax_weight)[0]


def _add_term(std: np.ndarray, source: str, weight: float, term: np.ndarray, name: str) -> tuple[np.ndarray, str]:
    """sqrt(std^2 + (weight term)^2) [N] and ``source`` with the term's weight said (``name``)."""
    return np.hypot(std, weight * term), source + (f", {name} weight {weight:.3g}" if weight > 0.0
                                                   else f", the {name} fitted with weight 0 (none)")


def _fit_depth_map(renders: dict[str, Any], *, floor: bool, relative_floor: bool,
                   check_weight: float | None = None, edge_weight: float | None = None,
                   parallax_weight: float | None = None) -> tuple[QuantileCalibration, np.ndarray]:
    """The depth map of ``depth_calibration_renders``' output and the stds [N] it was fitted on. Renders
    with the free-space check (a "violation" entry) weigh it by ``check_weight``, or when None by the
    weight beta ``fit_check_weight`` fits (with rho when ``relative_floor``; without the term, the
    full check); a weight of 0 leaves an unchecked map. Renders with edge sizes (an "edge" entry)
    then add the edge term weighted ``edge_weight``, or when None by the gamma ``fit_edge_weight``
    fits on the checked std (without rho: no term); a weight of 0 leaves a map without it. Renders with
    parallax angles (a "parallax" entry) then add the parallax term weighted ``parallax_weight``, or
    when None by the kappa ``fit_parallax_weight`` fits on the std so far (without rho: no term)."""
    weight = 1.0 if check_weight is None else _check_weight(float(check_weight), "check_weight")
    std, source, checked = renders["std"], renders["source"], "violation" in renders
    if checked:
        if check_weight is None and relative_floor and renders["abs_err"].size >= MIN_CALIBRATION_SAMPLES:
            weight = fit_check_weight(renders["abs_err"], renders["std_raw"], renders["violation"], renders["depth"])
        std = checked_std(renders["std_raw"], weight * renders["violation"])
        source = source.replace(CHECKED_SOURCE, f"{CHECKED_SOURCE} (weight {weight:.3g})" if weight > 0.0
                                else ", the free-space check fitted with weight 0 (std unchecked)")
    fits = relative_floor and renders["abs_err"].size >= MIN_CALIBRATION_SAMPLES  # a weight is fitted with rho only
    gamma = kappa = 0.0
    if "edge" in renders:
        gamma = (_edge_weight(float(edge_weight), "edge_weight") if edge_weight is not None
                 else fit_edge_weight(renders["abs_err"], std, renders["edge"], renders["depth"]) if fits else 0.0)
        std, source = _add_term(std, source, gamma, renders["edge"], "occlusion-edge term")
    if "parallax" in renders:
        kappa = (_parallax_weight(float(parallax_weight), "parallax_weight") if parallax_weight is not None
                 else fit_parallax_weight(renders["abs_err"], std, renders["parallax"], renders["depth"]) if fits
                 else 0.0)
        std, source = _add_term(std, source, kappa, parallax_term(renders["parallax"], renders["depth"]),
                                "parallax term")
    out = QuantileCalibration.fit_errors(renders["abs_err"], std, quantity="depth_std", floor=floor,
                                         depth=renders["depth"] if relative_floor else None, source=source)
    if checked and weight > 0.0:  # a weight of 0 leaves the unchecked map (free_space False, weight 1)
        out.free_space, out.free_space_weight = True, weight
    out.edge_weight, out.parallax_weight = gamma, kappa
    return out, std


def fit_depth_calibration_and_folds(model, dataset, *, seed: int = 0, points: str = DEFAULT_CALIBRATION_POINTS,
                                    options=None, floor: bool = DEPTH_STD_FLOOR, free_space=None,
                                    relative_floor: bool = DEPTH_RELATIVE_FLOOR, check_weight: float | None = None,
                                    folds: int = CROSS_FIT_FOLDS, edges: bool = DEPTH_EDGE_TERM,
                                    edge_weight: float | None = None,
                                    pair_points: str = DEFAULT_CALIBRATION_PAIR_POINTS, parallax=None,
                                    parallax_weight: float | None = None
                                    ) -> tuple[QuantileCalibration, DepthFolds | None]:
    """The depth map (as ``fit_depth_calibration``) and, when it is fitted on the SCORE points too
    (``points="held-out"``), its cross-fitted ``DepthFolds`` from the same renders (``pair_points``:
    ``depth_calibration_renders``); None otherwise,
    or with a warning when the scene has too few SCORE blocks or points to fit them. ValueError as
    ``fit_depth_calibration``."""
    r = depth_calibration_renders(model, dataset, seed=seed, points=points, options=options, free_space=free_space,
                                  edges=edges, pair_points=pair_points, parallax=parallax)
    return depth_map_and_folds(r, load_capture_points(dataset) if points != "calibrate" else None, floor=floor,
                               relative_floor=relative_floor, check_weight=check_weight, edge_weight=edge_weight,
                               parallax_weight=parallax_weight, folds=folds, where=str(dataset.root))


def depth_map_and_folds(renders: dict[str, Any], capture=None, *, floor: bool = DEPTH_STD_FLOOR,
                        relative_floor: bool = DEPTH_RELATIVE_FLOOR, check_weight: float | None = None,
                        edge_weight: float | None = None, parallax_weight: float | None = None,
                        folds: int = CROSS_FIT_FOLDS, where: str = "capture"
                        ) -> tuple[QuantileCalibration, DepthFolds | None]:
    """The depth map of ``depth_calibration_renders``' output ``renders`` (its free-space check and
    edge term weighted as ``_fit_depth_map`` fits them) and, with the scene's ``capture`` points
    (held-out renders: CALIBRATE and SCORE), its cross-fitted ``DepthFolds``: None without
    ``capture``, or with a warning naming ``where`` when the scene has too few SCORE blocks."""
    out, std = _fit_depth_map(renders, floor=floor, relative_floor=relative_floor, check_weight=check_weight,
                              edge_weight=edge_weight, parallax_weight=parallax_weight)
    if capture is None:
        return out, None
    keys = block_keys(capture.xyz, capture.xyz)
    try:
        folded = fit_depth_folds(renders["abs_err"], std, keys[renders["index"]], keys[capture.roles == SCORE],
                                 folds=folds, floor=floor, depth=renders["depth"] if relative_floor else None,
                                 source=out.source)
    except ValueError as exc:  # a scene too small to cross-fit: the map stands, its scores are not independent
        warnings.warn(f"{where}: the depth map's cross-fitted folds were not fitted ({exc}); depth interval "
                      "scores on the SCORE points will not be independent", stacklevel=2)
        return out, None
    for m in folded.maps:  # the weights the run's map chose; each fold's own s(p) and rho
        m.free_space, m.free_space_weight, m.edge_weight = out.free_space, out.free_space_weight, out.edge_weight
        m.parallax_weight = out.parallax_weight
    return out, folded


def fit_colour_calibration(model, dataset, *, fraction: float, block: int, seed: int = 0) -> QuantileCalibration:
    """Fit the colour map on the pixels of the training views held out from training
    (``holdout.holdout_mask`` with the run's ``fraction`` and ``block``), rendered from their own
    cameras: |z| = |c - c*| / sigma_c over every channel value with a positive std.
    ValueError when nothing was held out (``fraction`` 0) or too few values remain."""
    if fraction <= 0:
        raise ValueError("colour calibration needs pixels held out from training (train.holdout_fraction > 0)")
    views = list(dataset.train_indices)
    masks = holdout_masks(dataset, views, fraction=fraction, block=block)
    device = next(model.parameters()).device
    generator = torch.Generator(device=device).manual_seed(seed)
    errors, pixels = [], 0
    for v, mask in zip(views, masks):
        keep = torch.from_numpy(mask)
        rays = dataset.rays(v)[keep]
        with torch.no_grad():
            maps = model.render_view(rays.reshape(1, len(rays)).to(device), generator=generator)
        std = maps["colour_var"].double().cpu().clamp_min(0).sqrt().reshape(-1, 3).numpy()
        mean = maps["colour_mean"].double().cpu().reshape(-1, 3).numpy()
        gt = dataset.images[v][keep].double().numpy()
        errors.append(standardised_errors(gt, mean, std))
        pixels += int(mask.sum())
    z = np.concatenate(errors)
    return QuantileCalibration.fit(z, quantity="colour_std",
                                   source=f"{len(z)} channel values of {pixels} pixels held out from training in "
                                          f"{block}-pixel blocks ({fraction:g} of the blocks) of {len(views)} "
                                          "training views")


@dataclass
class RunCalibration:
    """What a run stores in ``calibration.json``: one map per calibrated quantity (depth, colour;
    None where not fitted) and the capture points the depth map was fitted on
    (``CALIBRATION_POINTS``; files without it: "calibrate")."""

    depth: QuantileCalibration | None = None
    points: str = "calibrate"
    colour: QuantileCalibration | None = None
    training_depth: Any = None
    """The training views' rendered depths (``free_space.TrainingDepth``) a ``free_space`` depth map
    checks against and a parallax term measures the parallax with, stored beside calibration.json
    (``free_space.TRAINING_DEPTH_FILE``)."""
    depth_folds: DepthFolds | None = None
    """The depth map's cross-fitted fold maps (``points="held-out"``): what its interval scores use."""

    @property
    def saw_score_points(self) -> bool:
        """Whether the SCORE points were fitted on."""
        return self.points != "calibrate"

    @property
    def independent_depth_scores(self) -> bool:
        """Whether depth scores on the SCORE points are an independent test: the map never saw them,
        or its cross-fitted folds judge them."""
        return not self.saw_score_points or self.depth_folds is not None

    def to_dict(self) -> dict[str, Any]:
        return {"depth": None if self.depth is None else self.depth.to_dict(), "points": self.points,
                "colour": None if self.colour is None else self.colour.to_dict(),
                "depth_folds": None if self.depth_folds is None else self.depth_folds.to_dict()}

    @classmethod
    def from_dict(cls, data: dict, *, where: str) -> "RunCalibration":
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a JSON object, got {type(data).__name__}")
        points = data.get("points", "calibrate")
        if points not in CALIBRATION_POINTS:
            raise ValueError(f"{where}: points must be one of {CALIBRATION_POINTS}, got {points!r}")
        depth, colour, folds = data.get("depth"), data.get("colour"), data.get("depth_folds")
        if folds is not None and not isinstance(folds, dict):
            raise ValueError(f"{where}: depth_folds must be a JSON object, got {type(folds).__name__}")
        return cls(depth=None if depth is None else QuantileCalibration.from_dict(depth, where=f"{where}: depth"),
                   points=points,
                   colour=None if colour is None else QuantileCalibration.from_dict(colour, where=f"{where}: colour"),
                   depth_folds=None if folds is None else DepthFolds.from_dict(folds, where=f"{where}: depth_folds"))


def save_run_calibration(run_dir: str | Path, calibration: RunCalibration) -> Path:
    path = Path(run_dir) / CALIBRATION_FILE
    atomic_write_text(path, json.dumps(calibration.to_dict(), indent=2))
    return path


def load_run_calibration(run_dir: str | Path) -> RunCalibration | None:
    """The run's calibration.json, or None when it has none. ValueError (naming the file) if malformed."""
    path = Path(run_dir) / CALIBRATION_FILE
    if not path.is_file():
        return None
    out = RunCalibration.from_dict(read_json(path, "calibration"), where=str(path))
    if out.depth is not None and out.depth.needs_training_depth:
        out.training_depth = load_training_depth(run_dir)
        if out.training_depth is None:
            raise ValueError(f"{path}: the depth map checks free space or has a parallax term, but "
                             f"{Path(run_dir) / TRAINING_DEPTH_FILE} is missing (run `stochastic-fields calibrate "
                             f"--run {run_dir}` again)")
    return out


def calibrate_run(run_dir: str | Path, *, device: str | None = None, seed: int = 0, model=None,
                  dataset=None, points: str = DEFAULT_CALIBRATION_POINTS, floor: bool = DEPTH_STD_FLOOR,
                  free_space: bool = DEPTH_FREE_SPACE, relative_floor: bool = DEPTH_RELATIVE_FLOOR,
                  check_weight: float | None = None, progress: bool = True, edges: bool = DEPTH_EDGE_TERM,
                  edge_weight: float | None = None,
                  pair_points: str = DEFAULT_CALIBRATION_PAIR_POINTS, parallax: bool = DEPTH_PARALLAX_TERM,
                  parallax_weight: float | None = None) -> RunCalibration:
    """Fit the run's calibration and write ``RUN/calibration.json``: the depth map from its capture
    points (``points``: ``CALIBRATION_POINTS``; "held-out" adds the cross-fitted ``DepthFolds``
    that score it) and, when the run held pixels out of training
    (``train.holdout_fraction`` > 0 in its config.json), the colour map from them; ``floor``: whether
    the depth map fits a std floor (``fit_std_floor``); ``free_space``: whether it is fitted on the
    free-space-checked std (the training views are rendered once, and stored as
    ``free_space.TRAINING_DEPTH_FILE`` before calibration.json when the map keeps the check, and
    their PSNR with the pose check's verdict as ``pose_check.TRAINING_FIT_FILE``;
    ``progress``: a bar over them), weighted by ``check_weight`` (None: fitted,
    ``fit_check_weight``; a fitted 0 leaves the map unchecked); ``relative_floor``: whether
    it fits a depth-proportional term (``fit_relative_floor``); ``edges``: whether it adds an
    occlusion-edge term (``depth_edges``) weighted ``edge_weight`` (None: fitted, ``fit_edge_weight``;
    a fitted 0 leaves it out); ``parallax``: whether it adds the training views' parallax term
    (``parallax``; the training views are rendered as for the check) weighted ``parallax_weight``
    (None: fitted, ``fit_parallax_weight``; a fitted 0 leaves it out); ``pair_points``: which
    capture points a calibration view renders (``pair_visible_points``). ValueError (the depth fit's reason) when neither can be fitted; a depth
    fit that fails beside a colour one leaves depth raw."""
    if model is None:
        cfg, model, dataset = load_trained_model(Path(run_dir), dataset=dataset, device=device)
    else:
        cfg = load_config(Path(run_dir) / "config.json")
    colour = None
    if cfg.train.holdout_fraction > 0:
        colour = fit_colour_calibration(model, dataset, fraction=cfg.train.holdout_fraction,
                                        block=cfg.train.holdout_block, seed=seed)
    reference = (render_training_depth(model, dataset, seed=seed, progress=progress) if free_space or parallax
                 else None)
    if reference is not None and reference.psnr is not None:  # the same renders check the training photos' poses (pose_check)
        save_training_fit(run_dir, check_photo_fit(photo_names(dataset, reference.views), reference.psnr))
    try:
        depth, folds = fit_depth_calibration_and_folds(model, dataset, seed=seed, points=points, floor=floor,
                                                       free_space=reference if free_space else None,
                                                       relative_floor=relative_floor,
                                                       check_weight=check_weight, edges=edges,
                                                       edge_weight=edge_weight, pair_points=pair_points,
                                                       parallax=reference if parallax else None,
                                                       parallax_weight=parallax_weight)
    except ValueError:
        if colour is None:
            raise
        depth = folds = None
    if depth is not None and depth.needs_training_depth:  # fitted weights of 0 leave the map without them: no file
        save_training_depth(run_dir, reference)  # before the calibration.json that names it
    calibration = RunCalibration(depth=depth, points=points, colour=colour,
                                 training_depth=None if depth is None or not depth.needs_training_depth else reference,
                                 depth_folds=folds)
    save_run_calibration(run_dir, calibration)
    return calibration


def describe(calibration: RunCalibration) -> str:
    """A few lines for people: the fitted factors at 68% and 95%."""
    parts = [f"{name} std: {_std_formula(m)}{m.std_scale:.3g} "
             f"(one sigma, 68.3%), x{float(m.scale_at(0.95)):.3g} at 95% [{m.source}]"
             for name, m in (("depth", calibration.depth), ("colour", calibration.colour)) if m is not None]
    if calibration.depth_folds is not None:
        scales = [m.std_scale for m in calibration.depth_folds.maps]
        parts.append(f"depth interval scores cross-fitted over {len(scales)} folds of the SCORE blocks "
                     f"(fold factors x{min(scales):.3g} to x{max(scales):.3g})")
    return "; ".join(parts) if parts else "no calibrated quantity"


def _std_formula(m: QuantileCalibration) -> str:
    check = ("free-space violation^2" if m.free_space_weight == 1.0
             else f"({m.free_space_weight:.3g} free-space violation)^2")
    terms = (["raw^2"] + ([f"{m.floor:.3g}^2"] if m.floor else []) + ([check] if m.free_space else [])
             + ([f"({m.edge_weight:.3g} edge size)^2"] if m.edge_weight else [])
             + ([f"({m.parallax_weight:.3g} depth / sin parallax)^2"] if m.parallax_weight else [])
             + ([f"({m.relative_floor:.3g} depth)^2"] if m.relative_floor else []))
    return "x" if len(terms) == 1 else f"sqrt({' + '.join(terms)}) x"


def apply_calibration(products: dict[str, np.ndarray], calibration: RunCalibration | None,
                      camera: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Camera-z products (``view_maps.camera_z_maps``) with ``depth_std`` and ``colour_std``
    calibrated where the run has their maps (``QuantileCalibration.calibrated_std``, in float64,
    stored in the raw one's dtype), the raw ones kept as ``depth_std_raw`` and ``colour_std_raw``.
    A ``free_space`` depth map also adds ``depth_free_space`` [H, W], each pixel's free-space
    violation (as ``free_space.violation_map`` at pixels with opacity above ``OPACITY_MASK``), which
    needs the view's ``camera`` (intrinsics [3, 3], OpenCV world-to-camera [4, 4]); a depth map with
    an occlusion-edge term adds ``depth_edge`` [H, W], each pixel's edge size
    (``depth_edges.edge_range_map`` of ``depth_mean``); a depth map with a parallax term adds
    ``depth_parallax`` [H, W], each pixel's parallax angle in degrees (as ``parallax.parallax_map`` at
    pixels with opacity above ``OPACITY_MASK``; the view's ``camera`` too); both from one projection of
    the pixels into each training view (``parallax.training_view_maps``). Returns a new dict (unchanged entries where a
    map is missing)."""
    out = dict(products)
    if calibration is None:
        return out
    violation = parallax = None
    if calibration.depth is not None and calibration.depth.needs_training_depth and "depth_std" in products:
        if camera is None or calibration.training_depth is None:
            raise ValueError("the depth map checks free space or has a parallax term: applying it needs the view's "
                             "camera and the run's training-view depths (load the calibration with "
                             "load_run_calibration)")
        # one projection of the pixels into each training view serves both terms
        violation, parallax = training_view_maps(products["depth_mean"], camera[0], camera[1],
                                                 calibration.training_depth, free_space=calibration.depth.free_space,
                                                 parallax=calibration.depth.parallax_weight > 0.0,
                                                 mask=products["opacity"] > OPACITY_MASK)
        if parallax is not None:
            out["depth_parallax"] = parallax
        if violation is not None:
            out["depth_free_space"] = violation
    edge = None
    if calibration.depth is not None and calibration.depth.edge_weight > 0.0 and "depth_std" in products:
        edge = np.nan_to_num(edge_range_map(products["depth_mean"]), nan=0.0).astype(products["depth_std"].dtype)
        out["depth_edge"] = edge
    for key, cal in (("depth_std", calibration.depth), ("colour_std", calibration.colour)):
        if cal is not None and key in products:
            raw = products[key]
            extra = violation if key == "depth_std" else None
            depth = products.get("depth_mean") if key == "depth_std" else None
            std = cal.calibrated_std(raw, extra, depth, edge if key == "depth_std" else None,
                                     parallax if key == "depth_std" else None)
            out.update({f"{key}_raw": raw, key: std.astype(raw.dtype)})
    return out


# --------------------------------------------------------------------------------------------
# ``stochastic-fields calibrate``
# --------------------------------------------------------------------------------------------


def run(args) -> None:
    cal = calibrate_run(Path(args.run), device=args.device, seed=args.seed, points=args.points,
                        floor=args.std_floor, free_space=args.free_space, relative_floor=args.relative_floor,
                        check_weight=args.free_space_weight, edges=args.edge_term, edge_weight=args.edge_weight,
                        pair_points=args.pair_points, parallax=args.parallax_term,
                        parallax_weight=args.parallax_weight)
    print(f"calibrated {args.run}: {describe(cal)}")
    print(f"written: {Path(args.run) / CALIBRATION_FILE} (render, eval and export apply it; raw stds as depth_std_raw "
          "and colour_std_raw)")
    if cal.training_depth is not None:
        print(f"written: {Path(args.run) / TRAINING_DEPTH_FILE} (the training views' rendered depths the free-space "
              "check compares with and the parallax term measures with; each view's violation is written as "
              "depth_free_space, its parallax angle as depth_parallax)")
    fit = load_training_fit(args.run) if args.free_space or args.parallax_term else None
    if fit is not None:
        print(fit.summary())
