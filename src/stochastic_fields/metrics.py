"""Evaluation metrics for predictive colour and depth distributions (docs/definitions.md §6).

Pure functions over tensors. Every input may be a ``torch.Tensor`` (any device) or anything
``numpy.asarray`` accepts; computation is in float64 on the input's device, results are Python
floats, small numpy arrays (curves) or small dataclasses. Each function states its convention;
``default_conventions()`` collects them for reports (``MetricReport``).

Shapes use the package's axis names: C colour channels, P pixels (flattened), L levels, F
removal fractions. ``[...]`` is any leading shape (for example ``[H, W]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import kornia
import numpy as np
import torch
from torch import Tensor

from .constants import DEPTH_NLL_VARIANCE_FLOOR, NLL_VARIANCE_FLOOR

ErrorMetric = Literal["rmse", "mae"]

#: 0.5 * log(2 pi): the constant of the Gaussian NLL, included in every NLL reported here.
HALF_LOG_2PI: float = 0.5 * math.log(2.0 * math.pi)

#: Number of removal fractions of the sparsification curves (docs/definitions.md §6): f = i / 100, i = 0..99.
DEFAULT_NUM_FRACTIONS: int = 100

#: Nominal levels of the calibration curve: 0.01, 0.02, ..., 0.99.
DEFAULT_CALIBRATION_LEVELS: np.ndarray = np.linspace(0.01, 0.99, 99)


# --------------------------------------------------------------------------------------------
# input handling
# --------------------------------------------------------------------------------------------


def _f64(x: Any, name: str) -> Tensor:
    """``x`` as a float64 tensor (same device if already a tensor)."""
    if isinstance(x, Tensor):
        return x.detach().to(torch.float64)
    try:
        return torch.as_tensor(np.asarray(x, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a tensor or array-like of numbers, got {type(x).__name__}") from exc


def _f64_all(**named: Any) -> list[Tensor]:
    """Convert every input with ``_f64`` onto the device of the first torch tensor among them."""
    device = next((x.device for x in named.values() if isinstance(x, Tensor)), torch.device("cpu"))
    return [_f64(x, name).to(device) for name, x in named.items()]


def _same_shape(**tensors: Tensor) -> None:
    shapes = {name: tuple(t.shape) for name, t in tensors.items()}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"shapes must match, got {shapes}")


def _finite(t: Tensor, name: str) -> None:
    bad = (~torch.isfinite(t)).sum().item()
    if bad:
        raise ValueError(f"{name} has {bad} non-finite values (of {t.numel()})")


def _mask_for(mask: Any, shape: torch.Size, device: torch.device, name: str = "mask") -> Tensor:
    """Boolean mask of ``shape``; ``None`` means all True. A mask of ``shape[:-1]`` is expanded."""
    if mask is None:
        return torch.ones(shape, dtype=torch.bool, device=device)
    m = mask.detach() if isinstance(mask, Tensor) else torch.as_tensor(np.asarray(mask))
    m = m.to(device=device)
    if m.dtype != torch.bool:
        raise TypeError(f"{name} must be boolean, got dtype {m.dtype}")
    if tuple(m.shape) == tuple(shape):
        return m
    if len(shape) >= 1 and tuple(m.shape) == tuple(shape[:-1]):
        return m[..., None].expand(shape)
    raise ValueError(f"{name} shape {tuple(m.shape)} matches neither {tuple(shape)} nor {tuple(shape[:-1])}")


# --------------------------------------------------------------------------------------------
# Gaussian NLL
# --------------------------------------------------------------------------------------------


def _nll_elements(gt: Tensor, mean: Tensor, var: Tensor, var_floor: float) -> Tensor:
    """Elementwise -log N(gt | mean, max(var, var_floor)), float64."""
    if not var_floor > 0:
        raise ValueError(f"var_floor must be > 0, got {var_floor}")
    _same_shape(gt=gt, mean=mean, var=var)
    for name, t in (("gt", gt), ("mean", mean), ("var", var)):
        _finite(t, name)
    if (var < 0).any():
        raise ValueError(f"var has negative values (min {var.min().item():.3g}); a variance is >= 0")
    v = var.clamp_min(var_floor)
    return HALF_LOG_2PI + 0.5 * torch.log(v) + 0.5 * (gt - mean) ** 2 / v


def gaussian_nll_per_pixel(gt: Any, mean: Any, var: Any, var_floor: float = NLL_VARIANCE_FLOOR) -> Tensor:
    """Per-pixel Gaussian NLL, averaged over channels.

    Formula (per channel value, natural log, nats):
        nll = 0.5 log(2 pi) + 0.5 log v + (gt - mean)^2 / (2 v),   v = max(var, var_floor)
    The 0.5 log(2 pi) ~ 0.919 term is included. A variance below ``var_floor`` is replaced by the
    floor (so it scores exactly as the floor does).

    Shapes:
        gt, mean, var: [..., C]  ->  returns [...] (float64, on the input's device).
    """
    g, m, v = _f64_all(gt=gt, mean=mean, var=var)
    if g.ndim == 0:
        raise ValueError("gt must have a channel axis [..., C]")
    return _nll_elements(g, m, v, var_floor).mean(dim=-1)


def gaussian_nll(gt: Any, mean: Any, var: Any, var_floor: float = NLL_VARIANCE_FLOOR, reduce: bool = True):
    """Gaussian NLL of the ground truth under the predicted per-channel Gaussians (docs/definitions.md §6).

    Convention: -log N(gt | mean, max(var, var_floor)) per channel value, including the
    0.5 log(2 pi) term, averaged over channels and pixels (nats per channel value; multiply by C
    for nats per pixel). ``var_floor`` defaults to ``constants.NLL_VARIANCE_FLOOR`` (8-bit
    quantisation noise, (1/255)^2 / 12).

    Shapes:
        gt, mean, var: [..., C].
    Returns:
        a float if ``reduce`` else the per-pixel tensor [...] (``gaussian_nll_per_pixel``).
    """
    per_pixel = gaussian_nll_per_pixel(gt, mean, var, var_floor)
    return float(per_pixel.mean().item()) if reduce else per_pixel


# --------------------------------------------------------------------------------------------
# correlation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CorrelationResult:
    """A correlation coefficient that knows whether it is defined.

    Attributes:
        value: the coefficient in [-1, 1], or NaN when undefined (never a silent number).
        defined: False when an input is constant (zero variance) or has fewer than 2 points.
        reason: why it is undefined (for example "constant uncertainty"), else None.
        n: number of pairs used.
    """

    value: float
    defined: bool
    reason: str | None
    n: int


def _correlation_inputs(x: Any, y: Any, x_name: str, y_name: str) -> tuple[Tensor, Tensor]:
    xt, yt = _f64(x, x_name).reshape(-1), _f64(y, y_name).reshape(-1)
    device = x.device if isinstance(x, Tensor) else yt.device  # the first tensor's device
    xt, yt = xt.to(device), yt.to(device)
    if xt.numel() != yt.numel():
        raise ValueError(f"{x_name} has {xt.numel()} values but {y_name} has {yt.numel()}")
    _finite(xt, x_name)
    _finite(yt, y_name)
    return xt, yt


def _undefined_reason(x: Tensor, y: Tensor, x_name: str, y_name: str) -> str | None:
    if x.numel() < 2:
        return f"fewer than 2 points (n={x.numel()})"
    constant = [name for name, t in ((x_name, x), (y_name, y)) if bool(t.max() == t.min())]
    if constant:
        return " and ".join(f"constant {name}" for name in constant)
    return None


def _pearson_core(x: Tensor, y: Tensor) -> float:
    dx, dy = x - x.mean(), y - y.mean()
    r = (dx * dy).sum() / torch.sqrt((dx * dx).sum() * (dy * dy).sum())
    return float(r.clamp(-1.0, 1.0).item())


def pearson(x: Any, y: Any, x_name: str = "x", y_name: str = "y") -> CorrelationResult:
    """Pearson correlation r = sum(dx dy) / sqrt(sum dx^2 sum dy^2), dx = x - mean(x), float64.

    Inputs are flattened. A constant input (max == min) gives ``defined=False``, value NaN and a
    reason naming it ("constant <y_name>"). Non-finite inputs raise ValueError.

    Shapes:
        x, y: any shapes with the same number of elements P.
    """
    return _correlation(x, y, x_name, y_name, ranked=False)


def average_ranks(x: Tensor) -> Tensor:
    """1-based ranks of ``x`` [P] with ties given their average rank (scipy.stats.rankdata 'average')."""
    sorted_x, order = torch.sort(x, stable=True)
    _, inverse, counts = torch.unique_consecutive(sorted_x, return_inverse=True, return_counts=True)
    ends = torch.cumsum(counts, 0).to(torch.float64)  # last 1-based position of each tie group
    starts = ends - counts.to(torch.float64) + 1.0  # first 1-based position
    group_rank = 0.5 * (starts + ends)
    ranks = torch.empty_like(x, dtype=torch.float64)
    ranks[order] = group_rank[inverse]
    return ranks


def spearman(x: Any, y: Any, x_name: str = "x", y_name: str = "y") -> CorrelationResult:
    """Spearman rank correlation: Pearson of the average ranks (ties share their mean rank).

    Same undefined-case convention as ``pearson``.

    Shapes:
        x, y: any shapes with the same number of elements P.
    """
    return _correlation(x, y, x_name, y_name, ranked=True)


def _correlation(x: Any, y: Any, x_name: str, y_name: str, *, ranked: bool) -> CorrelationResult:
    """Pearson of x and y (``ranked``: of their average ranks), undefined for a constant input."""
    xt, yt = _correlation_inputs(x, y, x_name, y_name)
    reason = _undefined_reason(xt, yt, x_name, y_name)
    if reason is not None:
        return CorrelationResult(float("nan"), False, reason, xt.numel())
    if ranked:
        xt, yt = average_ranks(xt), average_ranks(yt)
    return CorrelationResult(_pearson_core(xt, yt), True, None, xt.numel())


def pixel_mse(gt: Any, mean: Any) -> Tensor:
    """Per-pixel squared error averaged over channels: mean_c (gt - mean)^2. [..., C] -> [...]."""
    g, m = _f64_all(gt=gt, mean=mean)
    _same_shape(gt=g, mean=m)
    return ((g - m) ** 2).mean(dim=-1)


def pixel_uncertainty(var: Any) -> Tensor:
    """Per-pixel uncertainty: predicted variance averaged over channels. [..., C] -> [...]."""
    v = _f64(var, "var")
    if (v < 0).any():
        raise ValueError(f"var has negative values (min {v.min().item():.3g}); a variance is >= 0")
    return v.mean(dim=-1)


def mse_uncertainty_correlation(gt: Any, mean: Any, var: Any) -> dict[str, CorrelationResult]:
    """Correlation between per-pixel MSE and per-pixel uncertainty (the paper's Table 1 metric).

    Convention: MSE_p = mean_c (gt - mean)^2, U_p = mean_c var (raw predicted variance, no floor);
    Pearson (the paper's) and Spearman (rank, average ties) over all pixels. A constant uncertainty
    map (for example a deterministic NeRF) is reported undefined with reason "constant uncertainty".

    Shapes:
        gt, mean, var: [..., C].
    Returns:
        {"pearson": CorrelationResult, "spearman": CorrelationResult}
    """
    g, m, v = _f64_all(gt=gt, mean=mean, var=var)
    _same_shape(gt=g, mean=m, var=v)
    err, unc = pixel_mse(g, m), pixel_uncertainty(v)
    return {
        "pearson": pearson(err, unc, x_name="error", y_name="uncertainty"),
        "spearman": spearman(err, unc, x_name="error", y_name="uncertainty"),
    }


# --------------------------------------------------------------------------------------------
# sparsification and AUSE
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SparsificationResult:
    """Sparsification curves and the area between them (AUSE).

    Attributes:
        metric: "rmse" or "mae".
        fractions: [F] removed fractions i / F, i = 0..F-1.
        model: [F] metric on the pixels left after removing the most uncertain fraction.
        oracle: [F] the same when removing the largest errors first (lower bound).
        ause: trapezoid integral of (model - oracle) over ``fractions`` (>= 0).
        reference: the metric on all pixels (= model[0] = oracle[0]), the normaliser.
        model_normalised, oracle_normalised: [F] curves divided by ``reference``.
        ause_normalised: ause / reference (NaN when reference == 0: every error is zero).
        ause_max_normalised: the same integral with each curve divided by its own maximum (the
            convention of CF-NeRF, Bayes' Rays and FisherRF): trapz(model / max(model) - oracle /
            max(oracle)). It differs from ``ause_normalised`` only where removing the most
            uncertain pixels raises the error above its value on all pixels. NaN when every error is zero.
        num_pixels: P.
    """

    metric: str
    fractions: np.ndarray
    model: np.ndarray
    oracle: np.ndarray
    ause: float
    reference: float
    model_normalised: np.ndarray
    oracle_normalised: np.ndarray
    ause_normalised: float
    num_pixels: int
    ause_max_normalised: float = float("nan")


def _kept_metric_curve(abs_err: Tensor, key: Tensor, num_fractions: int, metric: ErrorMetric) -> Tensor:
    """[F] metric on the pixels remaining after removing the top-``key`` fraction i / F.

    Pixels are sorted by ``key`` descending with a stable sort (ties keep their input order);
    fraction i removes the first floor(i * P / F) of them.
    """
    p = abs_err.numel()
    order = torch.sort(key, descending=True, stable=True).indices
    e = abs_err[order]
    vals = e * e if metric == "rmse" else e
    suffix = torch.flip(torch.cumsum(torch.flip(vals, [0]), 0), [0])  # suffix[k] = sum_{j>=k} vals[j]
    i = torch.arange(num_fractions, device=abs_err.device)
    removed = (i * p) // num_fractions
    kept_mean = suffix[removed] / (p - removed).to(torch.float64)
    return torch.sqrt(kept_mean) if metric == "rmse" else kept_mean


def sparsification_curve(
    errors: Any,
    uncertainty: Any,
    num_fractions: int = DEFAULT_NUM_FRACTIONS,
    metric: ErrorMetric = "rmse",
) -> SparsificationResult:
    """Sparsification curve of a per-pixel uncertainty against the oracle, and AUSE.

    Convention: fractions f_i = i / F, i = 0..F-1 (F = ``num_fractions``, default 100, so f runs
    0..0.99). At f_i the floor(i P / F) most uncertain pixels are removed (stable sort: among equal
    uncertainties, earlier pixels go first) and the metric is computed on the rest:
        rmse = sqrt(mean_kept e^2),   mae = mean_kept |e|.
    The oracle removes the largest |e| first. AUSE = trapezoid integral over f of
    (model - oracle), on [0, (F-1)/F]. Normalised curves and AUSE divide by the metric on all
    pixels (the curves' value at f = 0).

    ``errors`` may be signed; magnitudes are used. For colour pass ``pixel_errors(gt, mean, metric)``
    so that the rmse curve is the RMSE over the kept pixels' channel values.

    Shapes:
        errors, uncertainty: [P] (any shapes with P elements; flattened).
    """
    if metric not in ("rmse", "mae"):
        raise ValueError(f"metric must be 'rmse' or 'mae', got {metric!r}")
    if not (isinstance(num_fractions, int) and num_fractions >= 2):
        raise ValueError(f"num_fractions must be an int >= 2, got {num_fractions!r}")
    e, u = (t.reshape(-1) for t in _f64_all(errors=errors, uncertainty=uncertainty))
    if e.numel() != u.numel():
        raise ValueError(f"errors has {e.numel()} values but uncertainty has {u.numel()}")
    if e.numel() == 0:
        raise ValueError("sparsification_curve needs at least one pixel, got 0")
    _finite(e, "errors")
    _finite(u, "uncertainty")
    abs_err = e.abs()

    model = _kept_metric_curve(abs_err, u, num_fractions, metric)
    oracle = _kept_metric_curve(abs_err, abs_err, num_fractions, metric)
    fractions = torch.arange(num_fractions, dtype=torch.float64, device=e.device) / num_fractions
    ause_value = float(torch.trapezoid(model - oracle, fractions).item())
    reference = float(model[0].item())
    if reference > 0:
        model_n, oracle_n, ause_n = model / reference, oracle / reference, ause_value / reference
        ause_max = float(torch.trapezoid(model / model.max() - oracle / oracle.max(), fractions).item())
    else:
        model_n = torch.full_like(model, float("nan"))
        oracle_n, ause_n, ause_max = model_n, float("nan"), float("nan")
    return SparsificationResult(
        metric=metric,
        fractions=fractions.cpu().numpy(),
        model=model.cpu().numpy(),
        oracle=oracle.cpu().numpy(),
        ause=ause_value,
        reference=reference,
        model_normalised=model_n.cpu().numpy(),
        oracle_normalised=oracle_n.cpu().numpy(),
        ause_normalised=float(ause_n),
        num_pixels=e.numel(),
        ause_max_normalised=ause_max,
    )


def ause(
    errors: Any,
    uncertainty: Any,
    num_fractions: int = DEFAULT_NUM_FRACTIONS,
    metric: ErrorMetric = "rmse",
    normalised: bool = False,
) -> float:
    """AUSE of ``sparsification_curve`` (normalised: divided by the metric on all pixels)."""
    res = sparsification_curve(errors, uncertainty, num_fractions, metric)
    return res.ause_normalised if normalised else res.ause


def pixel_errors(gt: Any, mean: Any, metric: ErrorMetric = "rmse") -> Tensor:
    """Per-pixel error magnitude for colour sparsification. [..., C] -> [...].

    rmse: sqrt(mean_c (gt - mean)^2) (so sqrt(mean over kept pixels of e^2) is the RMSE of their
    channel values); mae: mean_c |gt - mean|.
    """
    g, m = _f64_all(gt=gt, mean=mean)
    _same_shape(gt=g, mean=m)
    if metric == "rmse":
        return torch.sqrt(((g - m) ** 2).mean(dim=-1))
    if metric == "mae":
        return (g - m).abs().mean(dim=-1)
    raise ValueError(f"metric must be 'rmse' or 'mae', got {metric!r}")


def colour_sparsification(
    gt: Any, mean: Any, var: Any, metric: ErrorMetric = "rmse", num_fractions: int = DEFAULT_NUM_FRACTIONS
) -> SparsificationResult:
    """Colour sparsification: ``pixel_errors`` ranked by ``pixel_uncertainty`` (mean variance over C).

    Shapes:
        gt, mean, var: [..., C].
    """
    return sparsification_curve(pixel_errors(gt, mean, metric), pixel_uncertainty(var), num_fractions, metric)


def depth_sparsification(
    pred: Any,
    gt: Any,
    var: Any,
    mask: Any = None,
    metric: ErrorMetric = "rmse",
    num_fractions: int = DEFAULT_NUM_FRACTIONS,
) -> SparsificationResult:
    """Depth sparsification: |pred - gt| ranked by the predicted depth variance, on ``mask``.

    Shapes:
        pred, gt, var: [...]; mask: [...] bool (None: gt finite and > 0).
    """
    p, g, v = _f64_all(pred=pred, gt=gt, var=var)
    _same_shape(pred=p, gt=g, var=v)
    m = _depth_mask(g, mask)
    return sparsification_curve(p[m] - g[m], v[m], num_fractions, metric)


# --------------------------------------------------------------------------------------------
# calibration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationResult:
    """Coverage of central Gaussian intervals against their nominal level.

    Attributes:
        levels: [L] nominal levels p.
        coverage: [L] fraction of ground-truth values inside mean +- z_p std.
        auce: mean over levels of |coverage - p| (area under |coverage - p| on a uniform grid of
            levels, divided by its length).
        signed_gap: mean over levels of (coverage - p): < 0 overconfident (intervals too narrow),
            > 0 underconfident (too wide).
        num_values: number of (pooled) values.
    """

    levels: np.ndarray
    coverage: np.ndarray
    auce: float
    signed_gap: float
    num_values: int

    @property
    def verdict(self) -> str:
        """'overconfident', 'underconfident' or 'calibrated' (the sign of ``signed_gap``)."""
        if self.signed_gap < 0:
            return "overconfident"
        if self.signed_gap > 0:
            return "underconfident"
        return "calibrated"


def _levels_tensor(levels: Any, device: torch.device) -> Tensor:
    lv = _f64(DEFAULT_CALIBRATION_LEVELS if levels is None else levels, "levels").reshape(-1).to(device)
    if lv.numel() == 0 or not bool(((lv > 0) & (lv < 1)).all()):
        raise ValueError(f"levels must be non-empty and inside (0, 1), got {lv.cpu().numpy()}")
    return lv


def _coverage(abs_res: Tensor, std: Tensor, levels: Tensor, interval_scale: Any = None) -> Tensor:
    """[L] fraction of values with |res| <= z_p std m(p), z_p = Phi^-1((1 + p) / 2) = sqrt(2) erfinv(p),
    m(p) = ``interval_scale(levels)`` (a recalibrated interval, ``calibration.QuantileCalibration``) or 1."""
    # Normalised residual: 0 where res == 0 (inside every interval, even with std == 0),
    # +inf where std == 0 < |res| (inside none).
    u = torch.where(abs_res == 0, torch.zeros_like(abs_res), abs_res / std)
    u_sorted = torch.sort(u).values
    z = math.sqrt(2.0) * torch.erfinv(levels)
    if interval_scale is not None:
        z = z * torch.as_tensor(np.asarray(interval_scale(levels.cpu().numpy()), dtype=np.float64), device=z.device)
    inside = torch.searchsorted(u_sorted, z, right=True)
    return inside.to(torch.float64) / u.numel()


def calibration_curve(gt: Any, mean: Any, std: Any, levels: Any = None, mask: Any = None,
                      interval_scale: Any = None) -> CalibrationResult:
    """Calibration of Gaussian predictions: empirical coverage of central intervals (docs/definitions.md §6).

    Convention: for each nominal level p the central interval is mean +- z_p std with
    z_p = Phi^-1((1 + p) / 2), times ``interval_scale(p)`` when given (a recalibrated
    uncertainty's level-dependent multiplier, levels [L] numpy -> [L]);
    coverage(p) = fraction of gt with |gt - mean| <= z_p std, pooled
    over every value (all pixels and all channels for colour; masked pixels for depth).
    AUCE = mean_p |coverage(p) - p|. No variance floor is applied (pass a floored std if wanted).
    Default levels: 0.01, 0.02, ..., 0.99.

    Shapes:
        gt, mean, std: [...] (for colour [..., C]); mask: [...] or [...] without the last axis.
    """
    g, m, s = _f64_all(gt=gt, mean=mean, std=std)
    _same_shape(gt=g, mean=m, std=s)
    keep = _mask_for(mask, g.shape, g.device)
    g, m, s = g[keep], m[keep], s[keep]
    if g.numel() == 0:
        raise ValueError("calibration_curve needs at least one value, got 0 (empty input or mask)")
    for name, t in (("gt", g), ("mean", m), ("std", s)):
        _finite(t, name)
    if (s < 0).any():
        raise ValueError(f"std has negative values (min {s.min().item():.3g})")
    lv = _levels_tensor(levels, g.device)
    cov = _coverage((g - m).abs(), s, lv, interval_scale)
    gap = cov - lv
    return CalibrationResult(
        levels=lv.cpu().numpy(),
        coverage=cov.cpu().numpy(),
        auce=float(gap.abs().mean().item()),
        signed_gap=float(gap.mean().item()),
        num_values=g.numel(),
    )


def calibration_curve_per_channel(
    gt: Any, mean: Any, std: Any, levels: Any = None, mask: Any = None
) -> list[CalibrationResult]:
    """``calibration_curve`` for each channel of [..., C] inputs separately (mask: [...])."""
    g, m, s = _f64_all(gt=gt, mean=mean, std=std)
    _same_shape(gt=g, mean=m, std=s)
    if g.ndim == 0:
        raise ValueError("inputs must have a channel axis [..., C]")
    keep = _mask_for(mask, g.shape, g.device)
    return [calibration_curve(g[..., c], m[..., c], s[..., c], levels, keep[..., c]) for c in range(g.shape[-1])]


# --------------------------------------------------------------------------------------------
# image quality
# --------------------------------------------------------------------------------------------


def psnr(pred: Any, gt: Any, max_val: float = 1.0) -> float:
    """PSNR = 10 log10(max_val^2 / MSE), MSE pooled over every value (kornia.metrics.psnr).

    One image per call: for several views average the per-view values. Identical images give +inf.

    Shapes:
        pred, gt: same shape, for example [H, W, 3].
    """
    p, g = _f64_all(pred=pred, gt=gt)
    _same_shape(pred=p, gt=g)
    return float(kornia.metrics.psnr(p, g, max_val).item())


def ssim(pred: Any, gt: Any, window_size: int = 11, max_val: float = 1.0) -> float:
    """Mean SSIM (kornia.metrics.ssim: Gaussian window of ``window_size`` taps, sigma 1.5,
    reflect padding, c1 = (0.01 L)^2, c2 = (0.03 L)^2), averaged over pixels and channels.

    Shapes:
        pred, gt: [H, W, C] (channels last, as rendered) or [H, W].
    """
    p, g = _f64_all(pred=pred, gt=gt)
    _same_shape(pred=p, gt=g)
    if p.ndim == 2:
        p, g = p[..., None], g[..., None]
    if p.ndim != 3:
        raise ValueError(f"ssim expects [H, W, C] or [H, W] images, got shape {tuple(p.shape)}")
    to_bchw = lambda t: t.permute(2, 0, 1)[None]  # noqa: E731  [1, C, H, W]
    return float(kornia.metrics.ssim(to_bchw(p), to_bchw(g), window_size, max_val=max_val).mean().item())


# --------------------------------------------------------------------------------------------
# depth
# --------------------------------------------------------------------------------------------


def _depth_mask(gt: Tensor, mask: Any) -> Tensor:
    """Valid-pixel mask: given ``mask`` (must select only finite gt > 0), or gt finite and > 0."""
    if mask is None:
        m = torch.isfinite(gt) & (gt > 0)
    else:
        m = _mask_for(mask, gt.shape, gt.device)
        bad = (m & ~(torch.isfinite(gt) & (gt > 0))).sum().item()
        if bad:
            raise ValueError(f"mask selects {bad} pixels whose ground-truth depth is not finite and > 0")
    if not bool(m.any()):
        raise ValueError("no valid depth pixels (mask empty or no gt > 0)")
    return m


def depth_errors(pred: Any, gt: Any, mask: Any = None) -> dict[str, float]:
    """Depth errors on valid pixels (scene units).

    abs_rel = mean |pred - gt| / gt,  rmse = sqrt(mean (pred - gt)^2),  mae = mean |pred - gt|.

    Shapes:
        pred, gt: [...]; mask: [...] bool (None: gt finite and > 0).
    Returns:
        {"abs_rel", "rmse", "mae", "num_pixels"}.
    """
    p, g = _f64_all(pred=pred, gt=gt)
    _same_shape(pred=p, gt=g)
    m = _depth_mask(g, mask)
    p, g = p[m], g[m]
    _finite(p, "pred")
    d = p - g
    return {
        "abs_rel": float((d.abs() / g).mean().item()),
        "rmse": float(torch.sqrt((d * d).mean()).item()),
        "mae": float(d.abs().mean().item()),
        "num_pixels": int(g.numel()),
    }


def depth_nll(
    gt: Any, mean: Any, var: Any, mask: Any = None, var_floor: float = DEPTH_NLL_VARIANCE_FLOOR, reduce: bool = True
):
    """Gaussian NLL of ground-truth depth: -log N(gt | mean, max(var, var_floor)), 0.5 log(2 pi)
    included, averaged over valid pixels. ``var_floor`` is in scene units squared (default
    ``constants.DEPTH_NLL_VARIANCE_FLOOR``); the NLL depends on the scene's units.

    Shapes:
        gt, mean, var: [...]; mask: [...] bool (None: gt finite and > 0).
    Returns:
        a float, or (``reduce=False``) the per-pixel values [M] of the M valid pixels.
    """
    g, m, v = _f64_all(gt=gt, mean=mean, var=var)
    _same_shape(gt=g, mean=m, var=v)
    keep = _depth_mask(g, mask)
    per_pixel = _nll_elements(g[keep], m[keep], v[keep], var_floor)
    return float(per_pixel.mean().item()) if reduce else per_pixel


# --------------------------------------------------------------------------------------------
# interval sharpness: width, interval score and CRPS of a predictive distribution
# --------------------------------------------------------------------------------------------

#: Central levels whose coverage and width are reported (docs/definitions.md §6.7).
INTERVAL_LEVELS: tuple[float, ...] = (0.5, 0.682689492137086, 0.9, 0.95, 0.99)
#: Levels whose interval score is reported (one sigma and 95%).
INTERVAL_SCORE_LEVELS: tuple[float, ...] = (0.682689492137086, 0.95)
#: Quantile levels of the CRPS quadrature: the midpoints (j + 1/2) / CRPS_NUM_LEVELS.
CRPS_NUM_LEVELS: int = 99
#: Groups of equal size the scored values are sorted into by their relative half-width at
#: ``WIDTH_GROUP_LEVEL`` (narrowest first), each with its own coverage (docs/definitions.md §6.7).
WIDTH_GROUPS: int = 3
#: The level whose band width sorts the values into ``WIDTH_GROUPS`` (a planner's margin).
WIDTH_GROUP_LEVEL: float = 0.95
#: Names of the narrowest and the widest width group in the scalar keys (thirds: ``WIDTH_GROUPS`` = 3).
WIDTH_GROUP_NAMES: tuple[str, str] = ("narrowest_third", "widest_third")
#: Key of the narrowest group's largest relative half-width at ``WIDTH_GROUP_LEVEL``.
NARROWEST_WIDTH_KEY: str = "halfwidth_95_narrowest_third_max"


def crps_levels(num: int = CRPS_NUM_LEVELS) -> np.ndarray:
    """[Q] the quantile levels (j + 1/2) / Q, j = 0..Q-1, of ``crps_from_quantiles``."""
    return (np.arange(num, dtype=np.float64) + 0.5) / num


def level_name(level: float) -> str:
    """Key suffix of a central level: 0.95 -> "95", 0.6827 -> "68", 0.5 -> "50"."""
    return f"{int(math.floor(100.0 * float(level) + 1e-9))}"


def interval_score(gt: Any, lower: Any, upper: Any, level: float) -> Tensor:
    """Interval score of central intervals (Gneiting & Raftery 2007, Eq. 43), per value [N]:

        IS_a(l, u; y) = (u - l) + (2 / a) (l - y) 1{y < l} + (2 / a) (y - u) 1{y > u},  a = 1 - level.

    Negatively oriented (smaller is better) and proper for the (a/2, 1 - a/2) quantiles: the width
    is paid always, a miss by 2/a times its distance. Shapes: gt, lower, upper [N] (lower <= upper)."""
    g, lo, hi = _f64_all(gt=gt, lower=lower, upper=upper)
    _same_shape(gt=g, lower=lo, upper=hi)
    if not 0.0 < level < 1.0:
        raise ValueError(f"interval_score: level must lie in (0, 1), got {level}")
    a = 1.0 - level
    return (hi - lo) + (2.0 / a) * (lo - g).clamp_min(0) + (2.0 / a) * (g - hi).clamp_min(0)


def crps_from_quantiles(gt: Any, quantiles: Any, levels: Any = None) -> Tensor:
    """CRPS of predictive distributions given by their quantiles, per value [N]:

        CRPS(F, y) = 2 int_0^1 QS_t(F^-1(t), y) dt,   QS_t(q, y) = (1{y < q} - t) (q - y)

    (the pinball-loss form, Gneiting & Ranjan 2011), by the midpoint rule over ``levels`` [Q]
    (default ``crps_levels()``: Q midpoints of equal cells). Exact as Q grows; for a Gaussian the
    99-level rule is within 0.5% of the closed form (``gaussian_crps``, tested). Units of gt.
    Shapes: gt [N], quantiles [N, Q] (non-decreasing along Q)."""
    g, q = _f64_all(gt=gt, quantiles=quantiles)
    t = _f64(crps_levels() if levels is None else levels, "levels").to(g.device).reshape(1, -1)
    if q.ndim != 2 or q.shape[0] != g.reshape(-1).shape[0] or q.shape[1] != t.shape[1]:
        raise ValueError(f"crps_from_quantiles: quantiles must be [{g.numel()}, {t.shape[1]}], got {tuple(q.shape)}")
    y = g.reshape(-1, 1)
    return (2.0 * ((y < q).to(q.dtype) - t) * (q - y)).mean(dim=1)


def gaussian_crps(gt: Any, mean: Any, std: Any) -> Tensor:
    """Closed-form CRPS of N(mean, std^2) at gt, per value (Gneiting et al. 2005):
    std (z (2 Phi(z) - 1) + 2 phi(z) - 1 / sqrt(pi)), z = (gt - mean) / std (std > 0)."""
    g, m, s = _f64_all(gt=gt, mean=mean, std=std)
    _same_shape(gt=g, mean=m, std=s)
    z = (g - m) / s
    cdf = 0.5 * torch.erfc(-z / math.sqrt(2.0))
    pdf = torch.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    return s * (z * (2.0 * cdf - 1.0) + 2.0 * pdf - 1.0 / math.sqrt(math.pi))


def interval_sharpness(gt: Any, quantile_fn, levels: Sequence[float] = INTERVAL_LEVELS,
                       score_levels: Sequence[float] = INTERVAL_SCORE_LEVELS) -> dict[str, Any]:
    """Coverage, width, interval score and CRPS of predictive depth distributions at gt [N] (> 0);
    ``score_levels`` must be among ``levels``.

    ``quantile_fn(t)``: the predictive quantiles at levels t [Q] numpy -> [N, Q] (non-decreasing
    in t). The central interval at level p is [q((1 - p) / 2), q((1 + p) / 2)]. Everything is
    relative to the true depth y (scale-free, comparable over scenes):
        coverage_<p>            share of y inside the level-p interval,
        halfwidth_median_<p>    median over values of (upper - lower) / (2 y),
        halfwidth_p90_<p>       its 90th percentile,
        interval_score_<p>      mean of IS_(1-p)(lower, upper; y) / y (``interval_score``),
        crps                    mean of CRPS(F, y) / y (``crps_from_quantiles``),
    with "coverage", "halfwidth_median", "halfwidth_p90" also as lists over ``levels`` and
    "halfwidth" [N, L] the per-value relative half-widths (for histograms). Conditional on the
    width (``width_groups``): the values sorted by their relative half-width at ``WIDTH_GROUP_LEVEL``
    (known before the truth is) and cut into ``WIDTH_GROUPS`` groups of equal size (sizes differ by
    at most one; ties by input order), under "width_groups" each group's "coverage" [G, L], "halfwidth_median"
    [G] (at that level), "upper_edge" [G] (its largest half-width) and "num_values" [G]; and
        coverage_<p>_narrowest_third, coverage_<p>_widest_third     the first and last group's coverage,
        halfwidth_95_narrowest_third_max                           the first group's largest half-width
    (NaN with fewer values than groups), so a planner sees whether the narrow bands, the ones to act
    on, are honest too."""
    g = _f64(gt, "gt").reshape(-1)
    if g.numel() == 0 or not bool((torch.isfinite(g) & (g > 0)).all()):
        raise ValueError("interval_sharpness: needs at least one ground-truth depth, all finite and > 0")
    lv = np.asarray(levels, dtype=np.float64)
    at = [int(np.flatnonzero(np.isclose(lv, p))[0]) if np.isclose(lv, p).any() else -1 for p in score_levels]
    if min(at, default=0) < 0:
        raise ValueError(f"interval_sharpness: score levels {list(score_levels)} must be among the levels {lv.tolist()}")
    # one call for every level: a mixture's quantiles cost a bisection each call
    q = _f64(quantile_fn(np.concatenate([(1.0 - lv) / 2.0, (1.0 + lv) / 2.0, crps_levels()])), "quantiles")
    lo, hi, q_crps = q[:, :lv.size], q[:, lv.size:2 * lv.size], q[:, 2 * lv.size:]
    y = g.reshape(-1, 1)
    hit = (y >= lo) & (y <= hi)  # [N, L]
    inside = hit.to(torch.float64).mean(dim=0)
    half = (hi - lo) / (2.0 * y)
    out: dict[str, Any] = {"levels": lv.tolist(), "coverage": inside.tolist(),
                           "halfwidth_median": torch.quantile(half, 0.5, dim=0).tolist(),
                           "halfwidth_p90": torch.quantile(half, 0.9, dim=0).tolist(),
                           "halfwidth": half.cpu().numpy(), "num_values": int(g.numel())}
    for i, p in enumerate(lv):
        name = level_name(p)
        out[f"coverage_{name}"] = out["coverage"][i]
        out[f"halfwidth_median_{name}"] = out["halfwidth_median"][i]
        out[f"halfwidth_p90_{name}"] = out["halfwidth_p90"][i]
    for p, i in zip(score_levels, at):
        out[f"interval_score_{level_name(p)}"] = float((interval_score(g, lo[:, i], hi[:, i], p) / g).mean())
    out["crps"] = float((crps_from_quantiles(g, q_crps) / g).mean())
    out.update(_width_groups(hit.cpu().numpy(), half.cpu().numpy(), lv))
    return out


def _width_groups(inside: np.ndarray, half: np.ndarray, levels: np.ndarray) -> dict[str, Any]:
    """``interval_sharpness``' coverage per width group from ``inside`` [N, L] (bool) and the relative
    half-widths ``half`` [N, L] at ``levels`` [L] (its docstring)."""
    at = np.flatnonzero(np.isclose(levels, WIDTH_GROUP_LEVEL))
    if at.size == 0:
        return {}
    width = half[:, int(at[0])]
    groups = np.array_split(np.argsort(width, kind="stable"), WIDTH_GROUPS) if len(width) >= WIDTH_GROUPS else []
    upper = [float(width[g].max()) for g in groups]
    out: dict[str, Any] = {"width_groups": {
        "level": WIDTH_GROUP_LEVEL,
        "coverage": [inside[g].mean(axis=0).tolist() for g in groups],
        "halfwidth_median": [float(np.median(width[g])) for g in groups],
        "upper_edge": upper,
        "num_values": [int(g.size) for g in groups]},
        NARROWEST_WIDTH_KEY: upper[0] if groups else math.nan}
    for i, p in enumerate(levels):
        for name, g in zip(WIDTH_GROUP_NAMES, (0, -1)):
            out[f"coverage_{level_name(p)}_{name}"] = float(inside[groups[g], i].mean()) if groups else math.nan
    return out


def gaussian_quantiles(mean: Any, std: Any, levels: Any, interval_scale: Any = None) -> np.ndarray:
    """Quantiles [N, Q] at ``levels`` t [Q] of N(mean, std^2) [N], with central intervals widened by
    ``interval_scale(p)`` (a recalibrated std's level-dependent multiplier, ``calibration``):

        q(t) = mean + sign(t - 1/2) z_p std m(p),   p = |2 t - 1|, z_p = Phi^-1((1 + p) / 2),

    so that [q((1 - p) / 2), q((1 + p) / 2)] is the interval the coverage of ``calibration_curve``
    counts. m = 1 without a scale (the Gaussian's own quantiles)."""
    m = np.asarray(mean, dtype=np.float64).reshape(-1, 1)
    s = np.asarray(std, dtype=np.float64).reshape(-1, 1)
    t = np.asarray(levels, dtype=np.float64).reshape(1, -1)
    p = np.abs(2.0 * t - 1.0)
    z = math.sqrt(2.0) * torch.erfinv(torch.from_numpy(p)).numpy()
    if interval_scale is not None:
        z = z * np.asarray(interval_scale(p.reshape(-1)), dtype=np.float64).reshape(p.shape)
    return m + np.sign(t - 0.5) * z * s


#: Equal-width probability bins of ``event_reliability``.
EVENT_RELIABILITY_BINS: int = 10


def event_reliability(prob: Any, outcome: Any, num_bins: int = EVENT_RELIABILITY_BINS) -> dict[str, Any]:
    """How well probabilities of a yes/no event (for example "this segment is free") match what
    happened: prob [N] in [0, 1], outcome [N] in {0, 1}.

        brier        (1 / N) sum_i (p_i - o_i)^2            (0 is perfect; 0.25: always saying 1/2)
        ece          sum_b (n_b / N) |mean_b(p) - mean_b(o)|  (bins b: [0, 1/B), ..., [(B-1)/B, 1])
        accuracy     share of events with (p_i > 1/2) == o_i
    with the reliability curve per non-empty bin ("bin_prob", "bin_freq", "bin_count": mean
    probability, observed frequency, count) and the counts of confident answers (p < 0.05 or
    p > 0.95: "confident", and how many of them were wrong: "confident_wrong")."""
    p, o = (t.reshape(-1) for t in _f64_all(prob=prob, outcome=outcome))
    _same_shape(prob=p, outcome=o)
    if p.numel() == 0:
        raise ValueError("event_reliability: needs at least one event")
    if not bool(((p >= 0) & (p <= 1)).all()):
        raise ValueError("event_reliability: probabilities must lie in [0, 1]")
    if not bool(((o == 0) | (o == 1)).all()):
        raise ValueError("event_reliability: outcomes must be 0 or 1")
    if num_bins < 1:
        raise ValueError(f"event_reliability: num_bins must be >= 1, got {num_bins}")
    b = torch.clamp((p * num_bins).long(), max=num_bins - 1)
    count = torch.bincount(b, minlength=num_bins).to(torch.float64)
    sum_p = torch.zeros(num_bins, dtype=torch.float64, device=p.device).index_add_(0, b, p)
    sum_o = torch.zeros(num_bins, dtype=torch.float64, device=p.device).index_add_(0, b, o)
    used = count > 0
    bin_p, bin_o = sum_p[used] / count[used], sum_o[used] / count[used]
    confident = (p < 0.05) | (p > 0.95)
    return {"brier": float(((p - o) ** 2).mean()),
            "ece": float(((count[used] / p.numel()) * (bin_p - bin_o).abs()).sum()),
            "accuracy": float(((p > 0.5).to(torch.float64) == o).to(torch.float64).mean()),
            "bin_prob": bin_p.cpu().numpy(), "bin_freq": bin_o.cpu().numpy(), "bin_count": count[used].cpu().numpy(),
            "confident": int(confident.sum()), "confident_wrong": int((confident & ((p > 0.5).to(torch.float64) != o)).sum()),
            "events": int(p.numel())}


# --------------------------------------------------------------------------------------------
# reports
# --------------------------------------------------------------------------------------------


def default_conventions(num_fractions: int = DEFAULT_NUM_FRACTIONS, levels: Any = None) -> dict[str, str]:
    """The conventions behind every number in a report, as printable strings."""
    lv = np.asarray(DEFAULT_CALIBRATION_LEVELS if levels is None else levels, dtype=np.float64)
    return {
        "nll": "-log N(gt | mean, max(var, v_min)) per channel value, incl. 0.5 log(2 pi), "
        "mean over channels and pixels (nats)",
        "nll_variance_floor": f"{NLL_VARIANCE_FLOOR:.6g} (colour, (1/255)^2/12)",
        "depth_nll_variance_floor": f"{DEPTH_NLL_VARIANCE_FLOOR:.6g} (scene units^2)",
        "correlation": "per-pixel MSE (mean over channels) vs per-pixel variance (mean over channels, "
        "no floor); Pearson and Spearman (average ranks); undefined (NaN) for constant inputs",
        "ause_fractions": f"f = i/{num_fractions}, i = 0..{num_fractions - 1}; most uncertain removed first "
        "(stable sort); oracle removes largest errors first; trapezoid over f",
        "ause_normalisation": "curves and AUSE divided by the metric on all pixels (curve at f = 0)",
        "calibration": f"central intervals mean +- z_p std, {lv.size} levels {lv.min():.2f}..{lv.max():.2f}; "
        "AUCE = mean |coverage - p|; coverage < p is overconfident",
        "psnr_ssim": "kornia.metrics, max_val 1; SSIM Gaussian window 11 (sigma 1.5); "
        "per view, then mean over views",
        "view_mean": "report means are over views with a defined value; undefined values are counted",
    }


def _as_value(v: Any) -> float:
    if isinstance(v, CorrelationResult):
        return v.value
    if isinstance(v, SparsificationResult):
        return v.ause
    if isinstance(v, CalibrationResult):
        return v.auce
    if isinstance(v, Tensor):
        return float(v.item())
    return float(v)


@dataclass
class MetricReport:
    """Collects per-view metric values and summarises them with their conventions.

    ``add("view_003", psnr=31.2, nll=-1.4, pearson=CorrelationResult(...))`` appends one value per
    metric; correlation results contribute their ``value`` (NaN when undefined), sparsification
    results their AUSE, calibration results their AUCE. ``means()`` averages the finite values of
    each metric over views (NaN values, for example undefined correlations, are left out and
    counted in ``summary()``).
    """

    conventions: dict[str, str] = field(default_factory=default_conventions)
    views: list[str] = field(default_factory=list)
    per_view: dict[str, list[float]] = field(default_factory=dict)

    def add(self, view: str, **metrics: Any) -> None:
        """Record the metrics of one view. Every metric must be given for every view."""
        if self.views and set(metrics) != set(self.per_view):
            raise ValueError(
                f"view {view!r} has metrics {sorted(metrics)}, earlier views have {sorted(self.per_view)}"
            )
        self.views.append(view)
        for name, value in metrics.items():
            self.per_view.setdefault(name, []).append(_as_value(value))

    def means(self) -> dict[str, float]:
        """Mean over views of each metric, ignoring undefined (NaN) values (NaN if none is defined)."""
        out = {}
        for name, values in self.per_view.items():
            arr = np.asarray(values, dtype=np.float64)
            ok = ~np.isnan(arr)
            out[name] = float(arr[ok].mean()) if ok.any() else float("nan")
        return out

    def summary(self) -> dict[str, dict[str, float | int]]:
        """{metric: {"mean", "num_views", "num_undefined"}}."""
        means = self.means()
        return {
            name: {
                "mean": means[name],
                "num_views": len(values),
                "num_undefined": int(np.isnan(np.asarray(values, dtype=np.float64)).sum()),
            }
            for name, values in self.per_view.items()
        }

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: views, per-view lists, summary and conventions."""
        return {
            "views": list(self.views),
            "per_view": {k: list(v) for k, v in self.per_view.items()},
            "summary": self.summary(),
            "conventions": dict(self.conventions),
        }

    def format(self, title: str | None = None) -> str:
        """A printable table of means followed by the conventions."""
        lines = [title] if title else []
        for name, s in self.summary().items():
            undefined = f"  ({s['num_undefined']} undefined)" if s["num_undefined"] else ""
            lines.append(f"  {name:<24s} {s['mean']:>12.5g}  over {s['num_views']} views{undefined}")
        lines.append("  conventions:")
        lines.extend(f"    {k}: {v}" for k, v in self.conventions.items())
        return "\n".join(lines)


__all__: Sequence[str] = [
    "HALF_LOG_2PI",
    "DEFAULT_NUM_FRACTIONS",
    "DEFAULT_CALIBRATION_LEVELS",
    "gaussian_nll",
    "gaussian_nll_per_pixel",
    "CorrelationResult",
    "pearson",
    "spearman",
    "average_ranks",
    "pixel_mse",
    "pixel_uncertainty",
    "mse_uncertainty_correlation",
    "SparsificationResult",
    "sparsification_curve",
    "ause",
    "pixel_errors",
    "colour_sparsification",
    "depth_sparsification",
    "CalibrationResult",
    "calibration_curve",
    "calibration_curve_per_channel",
    "psnr",
    "ssim",
    "depth_errors",
    "depth_nll",
    "default_conventions",
    "MetricReport",
]
