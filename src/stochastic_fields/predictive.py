"""Per-pixel predictive depth distributions beyond one Gaussian: Gaussian mixtures and their
recalibration through the probability integral transform (docs/uncertainty.md, "Sharp intervals").

A pixel's predictive distribution is a mixture of M Gaussians (weights pi_m >= 0 summing to one,
means mu_m, stds s_m > 0):

    F(d) = sum_m pi_m Phi((d - mu_m) / s_m)

One component is today's Gaussian (depth mean, total std); K components N(D_k, spread) are the K
trajectories (their mixture has the same mean and total variance, by the law of total variance);
the components of a pixel's neighbours model a surface seen a few pixels off (an occlusion edge).

PIT recalibration (Kuleshov et al. 2018): on held-out points the values u_i = F_i(d*_i) would be
uniform if F were calibrated. ``PitCalibration`` stores their empirical quantiles Q_u(t); the
recalibrated distribution is G = R o F with R the empirical CDF of u, so its quantile at level t
is F^-1(Q_u(t)). The guarantee: for points exchangeable with the fitted ones, the recalibrated
level-t quantile lies above the truth at rate t (up to the O(1/n) of the empirical quantile); it
says nothing about which pixels get the width, which is the distribution F's job.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import ndtr

#: PIT values are kept inside [PIT_CLIP, 1 - PIT_CLIP]: a truth beyond every component's
#: reach (u = 0 or 1 in float64) would otherwise ask for an infinite quantile. 1e-12 is 7 stds of a
#: Gaussian, well inside float64's resolution of 1 - u (1.1e-16).
PIT_CLIP: float = 1e-12
#: Bisection steps of ``mixture_quantiles``: the bracket of 24 stds halves each step, so 60 steps
#: leave 24 s 2^-60, below float64 resolution.
QUANTILE_BISECTION_STEPS: int = 60
#: Half-width of the quantile bracket in component stds (beyond it a Gaussian has < 1e-126 mass).
QUANTILE_BRACKET_STDS: float = 24.0
#: Smallest PIT values a recalibration is fitted on.
MIN_PIT_SAMPLES: int = 50


def check_mixture(means: np.ndarray, stds: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, ...]:
    """The components as float64 [N, M] each; ValueError for mismatched shapes, stds <= 0, negative
    weights or weights that do not sum to one per value."""
    mu, s, w = (np.asarray(a, dtype=np.float64) for a in (means, stds, weights))
    if mu.ndim != 2 or mu.shape != s.shape or mu.shape != w.shape:
        raise ValueError(f"mixture: means, stds and weights must be [N, M] alike, got {mu.shape}, {s.shape}, {w.shape}")
    if not (np.isfinite(mu).all() and np.isfinite(s).all() and (s > 0).all()):
        raise ValueError("mixture: means must be finite and stds finite and > 0")
    if (w < 0).any() or not np.allclose(w.sum(axis=1), 1.0, atol=1e-9):
        raise ValueError("mixture: weights must be >= 0 and sum to one per value")
    return mu, s, w


def mixture_cdf(x: np.ndarray, means: np.ndarray, stds: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """F(x) of each value's mixture: x [N] or [N, Q], components [N, M] -> [N] or [N, Q]."""
    mu, s, w = check_mixture(means, stds, weights)
    x = np.asarray(x, dtype=np.float64)
    flat = x.ndim == 1
    x2 = x[:, None] if flat else x
    out = (w[:, None, :] * ndtr((x2[..., None] - mu[:, None, :]) / s[:, None, :])).sum(-1)
    return out[:, 0] if flat else out


def mixture_quantiles(levels: np.ndarray, means: np.ndarray, stds: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """F^-1(t) of each value's mixture by bisection: levels [Q] (shared) or [N, Q] in (0, 1),
    components [N, M] -> [N, Q] float64. The bracket is [min mu - 24 s, max mu + 24 s]."""
    mu, s, w = check_mixture(means, stds, weights)
    t = np.asarray(levels, dtype=np.float64)
    t = np.broadcast_to(t.reshape(1, -1) if t.ndim == 1 else t, (mu.shape[0], t.shape[-1]))
    if not ((t > 0) & (t < 1)).all():
        raise ValueError("mixture quantiles: levels must lie strictly between 0 and 1")
    lo = np.broadcast_to((mu - QUANTILE_BRACKET_STDS * s).min(1, keepdims=True), t.shape).copy()
    hi = np.broadcast_to((mu + QUANTILE_BRACKET_STDS * s).max(1, keepdims=True), t.shape).copy()
    for _ in range(QUANTILE_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        below = mixture_cdf(mid, mu, s, w) < t
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def checked_pit(pit: np.ndarray, what: str, source: str) -> np.ndarray:
    """PIT values [N] as float64; ValueError for fewer than ``MIN_PIT_SAMPLES`` or values outside [0, 1]."""
    u = np.asarray(pit, dtype=np.float64).reshape(-1)
    if u.size < MIN_PIT_SAMPLES:
        raise ValueError(f"{what} needs at least {MIN_PIT_SAMPLES} values, got {u.size} ({source})")
    if not (np.isfinite(u).all() and (u >= 0).all() and (u <= 1).all()):
        raise ValueError(f"{what}: PIT values must lie in [0, 1]")
    return u


@dataclass
class PitCalibration:
    """Recalibration of predictive CDFs by their PIT values (module doc): the empirical quantiles
    ``pit_quantiles`` [L] of u = F(d*) at ``levels`` [L] (increasing in (0, 1)); ``quantile_levels(t)``
    maps a nominal level t to the level of F to read, Q_u(t) (linear between fitted levels)."""

    levels: np.ndarray
    pit_quantiles: np.ndarray
    num_samples: int
    source: str = ""

    @classmethod
    def fit(cls, pit: np.ndarray, *, source: str = "", levels: np.ndarray | None = None) -> "PitCalibration":
        """Fit on PIT values [N] in [0, 1]; ValueError for fewer than ``MIN_PIT_SAMPLES`` or values
        outside [0, 1]. Default levels: 0.0005 and 0.001 ... 0.999 and 0.9995."""
        u = checked_pit(pit, "PIT recalibration", source)
        lv = (np.concatenate([[5e-4], np.arange(1, 1000) / 1000.0, [1 - 5e-4]]) if levels is None
              else np.asarray(levels, dtype=np.float64))
        q = np.quantile(np.clip(u, PIT_CLIP, 1.0 - PIT_CLIP), lv)
        return cls(lv, np.maximum.accumulate(q), int(u.size), source)

    def quantile_levels(self, t: np.ndarray) -> np.ndarray:
        """Q_u(t) for nominal levels t (any shape), clipped to [PIT_CLIP, 1 - PIT_CLIP]."""
        return np.clip(np.interp(np.asarray(t, dtype=np.float64), self.levels, self.pit_quantiles),
                       PIT_CLIP, 1.0 - PIT_CLIP)

    def to_dict(self) -> dict[str, Any]:
        return {"levels": self.levels.tolist(), "pit_quantiles": self.pit_quantiles.tolist(),
                "num_samples": self.num_samples, "source": self.source}


@dataclass
class CentralCalibration:
    """Recalibration of the central intervals of any predictive CDF F (split conformal prediction,
    Vovk et al. 2005; Romano et al. 2019 for quantile bands): on held-out points the conformity
    score of a truth d* is c = |2 F(d*) - 1|, the smallest central level whose interval
    [F^-1((1 - c) / 2), F^-1((1 + c) / 2)] holds it. For a nominal central level p the raw level is
    r(p) = the ceil((n + 1) p)-th smallest of the n scores (``raw_levels`` at ``levels``, linear
    between them), and the band is F's central interval at r(p). Guarantee: a point exchangeable
    with the fitted ones lies inside with probability >= p (< p + 1 / (n + 1) without ties). For a
    Gaussian F = N(mu, sigma^2) it is the level map of ``calibration.QuantileCalibration``:
    z_((1 + r) / 2) = s(p) z_((1 + p) / 2). Unlike ``PitCalibration`` it keeps each band central
    (equal mass outside on both sides), so it moves one number per level, as the level map does."""

    levels: np.ndarray
    raw_levels: np.ndarray
    num_samples: int
    source: str = ""

    @classmethod
    def fit(cls, pit: np.ndarray, *, source: str = "", levels: np.ndarray | None = None) -> "CentralCalibration":
        """Fit on PIT values u = F(d*) [N] in [0, 1]; ValueError for fewer than ``MIN_PIT_SAMPLES``
        or values outside [0, 1]. Default levels: 0, 0.001, ..., 0.999 and 0.9995."""
        u = checked_pit(pit, "central recalibration", source)
        lv = (np.concatenate([np.arange(0, 1000) / 1000.0, [1 - 5e-4]]) if levels is None
              else np.asarray(levels, dtype=np.float64))
        c = np.sort(np.abs(2.0 * u - 1.0))
        n = c.size
        rank = np.clip(np.ceil((n + 1) * lv).astype(np.int64), 1, n)  # the conformal rank, 1-based
        return cls(lv, np.maximum.accumulate(c[rank - 1]), int(n), source)

    def quantile_levels(self, t: np.ndarray) -> np.ndarray:
        """The levels of F to read for nominal quantile levels t (any shape): 1/2 +- r(|2t - 1|) / 2,
        clipped to [PIT_CLIP, 1 - PIT_CLIP]."""
        t = np.asarray(t, dtype=np.float64)
        r = np.interp(np.abs(2.0 * t - 1.0), self.levels, self.raw_levels)
        return np.clip(0.5 + np.sign(t - 0.5) * r / 2.0, PIT_CLIP, 1.0 - PIT_CLIP)

    def to_dict(self) -> dict[str, Any]:
        return {"levels": self.levels.tolist(), "raw_levels": self.raw_levels.tolist(),
                "num_samples": self.num_samples, "source": self.source}


def recalibrated_mixture_quantiles(levels: np.ndarray, means: np.ndarray, stds: np.ndarray, weights: np.ndarray,
                                   pit: PitCalibration | None) -> np.ndarray:
    """Quantiles [N, Q] of R o F at nominal ``levels`` [Q]: F^-1(Q_u(t)) (``pit`` None: F^-1(t))."""
    t = np.asarray(levels, dtype=np.float64)
    return mixture_quantiles(t if pit is None else pit.quantile_levels(t), means, stds, weights)


def neighbourhood_weights(opacity: np.ndarray, centre_weight: float, opacity_mask: float) -> np.ndarray:
    """Mixture weights [N, S] over a stencil of S rays per value (the first the pixel's own): the
    pixel keeps ``centre_weight``, its neighbours share the rest equally, neighbours whose rendered
    ``opacity`` [N, S] is not above ``opacity_mask`` get none (renormalised)."""
    op = np.asarray(opacity, dtype=np.float64)
    if op.ndim != 2 or op.shape[1] < 1:
        raise ValueError(f"neighbourhood weights: opacity must be [N, S], got {op.shape}")
    if not 0.0 < centre_weight <= 1.0:
        raise ValueError(f"neighbourhood weights: the centre weight must lie in (0, 1], got {centre_weight}")
    s = op.shape[1]
    w = np.full(op.shape, (1.0 - centre_weight) / max(1, s - 1))
    w[:, 0] = centre_weight
    w = np.where(op > opacity_mask, w, 0.0)
    w[:, 0] = np.where(w.sum(1) > 0, w[:, 0], 1.0)
    return w / w.sum(1, keepdims=True)
