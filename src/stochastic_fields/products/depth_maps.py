"""Per-view depth products from K depth trajectories, and the files they are written to.

Every product is **camera-z depth in scene units** (docs/definitions.md §1): the renderer's ray distances are
multiplied by ``z_scale`` (:func:`stochastic_fields.view_maps.camera_z_maps`). Per pixel, with
``D_k`` the camera-z termination depth of draw k (k = 1..K):

    depth_mean          = mean_k D_k
    depth_std_epistemic = sqrt(var_k D_k)                       (spread of the K trajectories)
    depth_std_spread    = sqrt(mean_k sum_i w_ik (z_i - D_k)^2)  (termination spread inside a draw)
    depth_std           = sqrt(epistemic^2 + spread^2)           (total, law of total variance)
    opacity             = mean_k sum_i w_ik                     (probability the ray hits something)
    depth_draw_q<p>     = empirical q-quantile of {D_k}          (see :func:`draw_quantiles`)
    depth_band<L>_lower = depth_mean - z_L m(L) depth_std,  depth_band<L>_upper = depth_mean + z_L m(L) depth_std
                          (central L% band, z_L = Phi^-1((1 + L) / 2); m(L) = 1, a normal with the total
                          variance, or the run's recalibration s(L) / s(0.683))

With a recalibrated run (``RUN/calibration.json``, ``stochastic_fields.calibration``)
``depth_std`` is the recalibrated std ``s(0.683) x`` the total std above, which stays available as
``depth_std_raw``.

The draw quantiles come from the K draws' expected depths only, so they describe the epistemic
part of the uncertainty (where each trajectory's expected surface is), not the termination
spread; they are named ``depth_draw_q<p>`` for that reason and are **not** a predictive band (on
the demo run the 5-95% draw interval holds the true depth for 1.2% of pixels). The predictive
band that holds its level is ``depth_band<L>_lower/upper`` from the total variance; its coverage
is tested on the synthetic scene (tests/test_ros_depth.py) and reported by ``export`` when the
scene has ground truth.

Rays that hit nothing report ``D_k = far`` (volume_rendering.expected_depth); ``valid`` marks
pixels with ``opacity >= min_opacity``. File writers (all atomic: temporary file + ``os.replace``):

* :func:`write_npz`: every map as float32, plus intrinsics, pose, units, K and conventions.
* :func:`write_png16`: 16-bit PNG, ``depth = value * scale``, 0 = invalid, scale in a JSON
  sidecar ``<name>.json`` (the common RGB-D convention).
* :func:`write_tiff`: float32 multi-page TIFF, one page per map, NaN where invalid, page names
  in the ImageDescription (JSON).
* :func:`write_colourised`: a PNG for people: depth mean and total std with colour bars.
"""

from __future__ import annotations

import json
from statistics import NormalDist
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
import imageio.v3 as iio
import matplotlib
import matplotlib.pyplot as plt
import tifffile

from ..calibration import apply_calibration
from ..view_maps import camera_z_maps
from ..io_utils import atomic_path, atomic_write_text
from .export_options import check_quantile_levels  # noqa: F401  (re-exported)

#: Colour range (relative) given to a constant map so matplotlib can draw it.
FLAT_MAP_RANGE: float = 1e-3
#: Largest value of a 16-bit PNG; 0 is reserved for "no depth".
PNG16_MAX: int = 65535
#: Levels of the predictive depth bands written next to the maps (central 90%).
BAND_LEVELS: tuple[float, ...] = (0.9,)

#: What every file states about its numbers.
CONVENTIONS: str = (
    "camera-z depth (distance along the optical axis, not along the ray) in scene units; "
    "OpenCV camera (x right, y down, z forward), pixel (row i, column j) has its centre at "
    "(u, v) = (j + 0.5, i + 0.5); world_to_camera maps world points to camera points, "
    "x_cam = R x_world + t; depth_std is the total std (epistemic + termination spread, law of "
    "total variance); depth_draw_q<p> (and depth_quantiles) are empirical quantiles of the K per-draw "
    "expected depths (linear interpolation between order statistics, numpy's default 'linear' method): "
    "epistemic only, not a predictive band; depth_band<L>_lower/upper = depth_mean -/+ z depth_std with "
    "z = Phi^-1((1 + L/100) / 2), the central L% band of a normal with the total variance; valid = "
    "opacity >= min_opacity; rays that hit nothing report depth = far per draw"
)


@dataclass
class DepthProducts:
    """Depth products of one view (numpy; maps [H, W] float32 unless noted).

    Attributes:
        depth_mean, depth_std, depth_std_epistemic, depth_std_spread, opacity: see module doc.
        depth_quantiles: [Q, H, W] camera-z depth quantiles at ``quantile_levels``.
        quantile_levels: [Q] levels in (0, 1), ascending.
        colour_mean: [H, W, 3] mean rendered colour in [0, 1].
        valid: [H, W] bool, ``opacity >= min_opacity``.
        intrinsics: [3, 3] float64 K (OpenCV, pixel centres at +0.5).
        world_to_camera: [4, 4] float64 OpenCV extrinsics.
        num_draws: K.
        near, far: camera-z bounds the view was rendered between.
        units: name of the length unit ("scene units" unless the scene says more).
        min_opacity: threshold behind ``valid``.
        depth_draws: [H, W, K] camera-z depth of each draw, or None.
        colour_std: [H, W, 3] std of the rendered colour over the draws, or None.
        band_levels: levels L of the predictive bands ``depth_band<L>_lower/upper`` (see module doc).
        depth_std_raw: the total std before recalibration (``depth_std`` is recalibrated), or None.
        band_multiplier: m(L) of the bands (recalibration), or None (1).
        metres_per_unit: metres per scene unit when known (``--metres-per-unit`` or a known
            distance), else None; ``scale_source`` says where it came from.
    """

    depth_mean: np.ndarray
    depth_std: np.ndarray
    depth_std_epistemic: np.ndarray
    depth_std_spread: np.ndarray
    opacity: np.ndarray
    depth_quantiles: np.ndarray
    quantile_levels: np.ndarray
    colour_mean: np.ndarray
    valid: np.ndarray
    intrinsics: np.ndarray
    world_to_camera: np.ndarray
    num_draws: int
    near: float
    far: float
    units: str = "scene units"
    min_opacity: float = 0.5
    depth_draws: np.ndarray | None = field(default=None, repr=False)
    colour_std: np.ndarray | None = field(default=None, repr=False)
    band_levels: tuple[float, ...] = BAND_LEVELS
    metres_per_unit: float | None = None
    scale_source: str = "unknown: scene units are not known to be metres"
    depth_std_raw: np.ndarray | None = field(default=None, repr=False)
    band_multiplier: Callable[[float], float] | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.depth_mean.shape)  # type: ignore[return-value]

    def quantile_map(self, level: float) -> np.ndarray:
        """[H, W] the quantile map at ``level`` (must be one of ``quantile_levels``)."""
        idx = np.flatnonzero(np.isclose(self.quantile_levels, level))
        if idx.size == 0:
            raise KeyError(f"quantile {level} not exported; have {self.quantile_levels.tolist()}")
        return self.depth_quantiles[idx[0]]

    def maps(self) -> dict[str, np.ndarray]:
        """Named [H, W] float32 maps, quantiles as ``depth_q<percent>`` (see :func:`quantile_name`)."""
        out = {
            "depth_mean": self.depth_mean,
            "depth_std": self.depth_std,
            "depth_std_epistemic": self.depth_std_epistemic,
            "depth_std_spread": self.depth_std_spread,
            "opacity": self.opacity,
        }
        if self.depth_std_raw is not None:
            out["depth_std_raw"] = self.depth_std_raw
        for level, q in zip(self.quantile_levels, self.depth_quantiles):
            out[quantile_name(float(level))] = q
        for level in self.band_levels:
            m = 1.0 if self.band_multiplier is None else float(self.band_multiplier(level))
            lower, upper = gaussian_band(self.depth_mean, self.depth_std * m, level)
            out[band_name(level, "lower")] = lower
            out[band_name(level, "upper")] = upper
        return out


def quantile_name(level: float) -> str:
    """File/array name of a draw-quantile map: 0.05 -> ``depth_draw_q5``, 0.95 -> ``depth_draw_q95``,
    0.025 -> ``depth_draw_q2p5`` (percent, '.' written as 'p'). "draw": a quantile of the K
    draws' expected depths (epistemic), not of the predictive depth distribution."""
    return "depth_draw_q" + f"{level * 100:g}".replace(".", "p")


def band_name(level: float, side: str) -> str:
    """Name of a predictive band map: (0.9, 'lower') -> ``depth_band90_lower``."""
    return "depth_band" + f"{level * 100:g}".replace(".", "p") + f"_{side}"


def gaussian_band(mean: np.ndarray, std: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """Central ``level`` band of N(mean, std^2): ``mean -/+ z std``, ``z = Phi^-1((1 + level) / 2)``
    (1.645 for 0.9). Shapes: [...] -> ([...], [...]) float32. Example: mean 2, std 0.1, 0.9 ->
    (1.8355, 2.1645)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"band level must lie strictly between 0 and 1, got {level}")
    z = NormalDist().inv_cdf(0.5 * (1.0 + level))
    mean = np.asarray(mean, np.float64)
    std = np.asarray(std, np.float64)
    return (mean - z * std).astype(np.float32), (mean + z * std).astype(np.float32)


# ------------------------------------------------------------------------------- estimators
def draw_quantiles(draws: torch.Tensor, levels: Sequence[float]) -> torch.Tensor:
    """Empirical quantiles of K draws: [..., K] -> [Q, ...] (levels in the given order).

    Linear interpolation between order statistics (Hyndman & Fan type 7, numpy's default
    ``method="linear"``, same as ``torch.quantile``): with the sorted draws ``x_(0) <= ... <=
    x_(K-1)`` and ``h = q (K - 1)``,

        Q(q) = x_(floor h) + (h - floor h) (x_(floor h + 1) - x_(floor h)).

    Implemented with one sort (no element-count limit, unlike ``torch.quantile``).
    Example: draws [1, 2, 3, 4], q = 0.25 -> h = 0.75 -> 1.75.
    """
    lv = check_quantile_levels(levels)
    K = draws.shape[-1]
    if K < 1:
        raise ValueError("draw_quantiles: need at least one draw")
    s = torch.sort(draws, dim=-1).values  # [..., K]
    h = torch.as_tensor(lv, dtype=torch.float64) * (K - 1)
    lo = torch.floor(h).long().clamp(0, K - 1)
    hi = (lo + 1).clamp(max=K - 1)
    frac = (h - lo.double()).to(draws.dtype).to(draws.device)  # [Q]
    x_lo = s[..., lo.to(draws.device)]  # [..., Q]
    x_hi = s[..., hi.to(draws.device)]
    q = x_lo + frac * (x_hi - x_lo)
    return torch.movedim(q, -1, 0)


def compute_depth_products(maps: dict[str, torch.Tensor], intrinsics: np.ndarray, world_to_camera: np.ndarray, *,
                           near: float, far: float, quantiles: Sequence[float] = (0.05, 0.95),
                           min_opacity: float = 0.5, units: str = "scene units",
                           keep_draws: bool = False, calibration=None) -> DepthProducts:
    """Depth products of one view from the renderer's maps.

    Args:
        maps: ``render_view(..., keep_draws=True)`` output (ray distance, [H, W] maps, ``z_scale``
            [H, W], ``depth_draws`` [H, W, K]).
        intrinsics: [3, 3]; world_to_camera: [4, 4] (stored with the products).
        near, far: the view's camera-z bounds.
        quantiles: levels in (0, 1) of :func:`draw_quantiles`.
        min_opacity: pixels with lower opacity are not ``valid``.
        keep_draws: keep the [H, W, K] camera-z draws (needed for free-space queries).
        calibration: the run's ``calibration.RunCalibration`` (recalibrated ``depth_std`` and
            bands, raw std kept as ``depth_std_raw``), or None.
    """
    if "depth_draws" not in maps:
        raise ValueError("compute_depth_products needs per-draw depths: render with keep_draws=True")
    levels = np.unique(check_quantile_levels(quantiles))  # ascending, no duplicates
    z = apply_calibration(camera_z_maps(maps), calibration,  # camera-z numpy float32
                          camera=(np.asarray(intrinsics, np.float64), np.asarray(world_to_camera, np.float64)))
    depth_cal = None if calibration is None else calibration.depth
    draws = torch.from_numpy(z["depth_draws"]).double()  # [H, W, K]
    q = draw_quantiles(draws, levels).float().numpy()  # [Q, H, W]
    return DepthProducts(
        depth_mean=z["depth_mean"],
        depth_std=z["depth_std"],
        depth_std_epistemic=z["depth_std_epistemic"],
        depth_std_spread=z["depth_std_spread"],
        opacity=z["opacity"],
        depth_quantiles=q,
        quantile_levels=levels,
        colour_mean=z["colour_mean"],
        valid=z["opacity"] >= min_opacity,
        intrinsics=np.asarray(intrinsics, dtype=np.float64).reshape(3, 3),
        world_to_camera=np.asarray(world_to_camera, dtype=np.float64).reshape(4, 4),
        num_draws=int(draws.shape[-1]),
        near=float(near),
        far=float(far),
        units=units,
        min_opacity=float(min_opacity),
        depth_draws=z["depth_draws"] if keep_draws else None,
        colour_std=z.get("colour_std"),
        depth_std_raw=z.get("depth_std_raw"),
        band_multiplier=None if depth_cal is None else (lambda level: float(depth_cal.relative_scale(level))),
    )


# ------------------------------------------------------------------------------- writers
def write_npz(path: str | Path, products: DepthProducts, *, include_draws: bool = False) -> Path:
    """One ``.npz`` per view (atomic). Arrays: every map of :meth:`DepthProducts.maps` (float32
    [H, W]), ``depth_quantiles`` [Q, H, W], ``quantile_levels`` [Q], ``colour_mean`` [H, W, 3],
    ``colour_std`` [H, W, 3] (when rendered), ``valid`` [H, W] bool, ``intrinsics`` [3, 3] and
    ``world_to_camera`` [4, 4] (float64), ``num_draws``, ``near``, ``far``, ``min_opacity``,
    ``units``, ``metres_per_unit`` (NaN when unknown), ``scale_source``, ``band_levels`` and
    ``conventions``; ``depth_draws`` [H, W, K] when ``include_draws``."""
    path = Path(path)
    arrays = {k: np.asarray(v, dtype=np.float32) for k, v in products.maps().items()}
    arrays.update(
        depth_quantiles=products.depth_quantiles.astype(np.float32),
        quantile_levels=products.quantile_levels.astype(np.float32),
        colour_mean=products.colour_mean.astype(np.float32),
        valid=products.valid.astype(bool),
        intrinsics=products.intrinsics.astype(np.float64),
        world_to_camera=products.world_to_camera.astype(np.float64),
        num_draws=np.int64(products.num_draws),
        near=np.float64(products.near),
        far=np.float64(products.far),
        min_opacity=np.float64(products.min_opacity),
        units=np.str_(products.units),
        metres_per_unit=np.float64(np.nan if products.metres_per_unit is None else products.metres_per_unit),
        scale_source=np.str_(products.scale_source),
        band_levels=np.asarray(products.band_levels, np.float32),
        conventions=np.str_(CONVENTIONS),
    )
    if products.colour_std is not None:
        arrays["colour_std"] = products.colour_std.astype(np.float32)
    if include_draws:
        if products.depth_draws is None:
            raise ValueError(f"write_npz({path}): include_draws=True but the products hold no draws")
        arrays["depth_draws"] = products.depth_draws.astype(np.float32)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


def png16_scale(max_depth: float) -> float:
    """Depth per 16-bit step so that ``max_depth`` (the far bound) maps to the top of the range:
    ``scale = max_depth / 65535``; quantisation error is at most ``scale / 2``."""
    if not np.isfinite(max_depth) or max_depth <= 0:
        raise ValueError(f"png16 scale: max depth must be positive and finite, got {max_depth}")
    return float(max_depth) / PNG16_MAX


def encode_png16(depth: np.ndarray, valid: np.ndarray, scale: float) -> np.ndarray:
    """[H, W] float depth -> uint16 ``round(depth / scale)``, clipped to [1, 65535] where valid
    (depth > 0), 0 elsewhere."""
    depth = np.asarray(depth, dtype=np.float64)
    ok = np.asarray(valid, bool) & np.isfinite(depth) & (depth > 0)
    value = np.clip(np.round(np.where(ok, depth, 0.0) / scale), 1, PNG16_MAX)
    return np.where(ok, value, 0).astype(np.uint16)


def write_png16(path: str | Path, depth: np.ndarray, valid: np.ndarray, *, max_depth: float, units: str,
                quantity: str = "depth_mean") -> tuple[Path, Path]:
    """16-bit PNG ``path`` plus JSON sidecar ``path.with_suffix('.json')`` (both atomic).

    Sidecar: ``{"scale", "formula": "depth = value * scale", "invalid_value": 0, "units",
    "depth_kind": "camera_z", "quantity", "image"}``.
    """
    path = Path(path)
    scale = png16_scale(max_depth)
    img = encode_png16(depth, valid, scale)
    sidecar = path.with_suffix(".json")
    meta = {"image": path.name, "quantity": quantity, "scale": scale, "formula": "depth = value * scale",
            "invalid_value": 0, "units": units, "depth_kind": "camera_z", "max_depth": float(max_depth),
            "conventions": CONVENTIONS}
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, img, extension=".png")
    atomic_write_text(sidecar, json.dumps(meta, indent=2))
    return path, sidecar


def read_png16(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W] float64, valid [H, W] bool) from a PNG written by :func:`write_png16`."""
    path = Path(path)
    sidecar = path.with_suffix(".json")
    if not sidecar.is_file():
        raise FileNotFoundError(f"{path}: missing scale sidecar {sidecar}")
    scale = float(json.loads(sidecar.read_text())["scale"])
    img = iio.imread(path)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise ValueError(f"{path}: expected a single-channel 16-bit PNG, got {img.dtype} {img.shape}")
    return img.astype(np.float64) * scale, img > 0


def write_tiff(path: str | Path, products: DepthProducts) -> Path:
    """Float32 multi-page TIFF [C, H, W] (atomic): pages are the maps of
    :meth:`DepthProducts.maps` in that order, NaN where not ``valid`` (opacity is kept
    everywhere). The ImageDescription is JSON: ``{"pages": [...], "units", "nodata": "nan",
    "conventions", "min_opacity"}``."""
    path = Path(path)
    maps = products.maps()
    names = list(maps)
    stack = np.stack([np.where(products.valid | (n == "opacity"), maps[n], np.nan) for n in names]).astype(np.float32)
    desc = json.dumps({"pages": names, "units": products.units, "nodata": "nan", "depth_kind": "camera_z",
                       "min_opacity": products.min_opacity, "conventions": CONVENTIONS})
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, stack, photometric="minisblack", description=desc, metadata=None)
    return path


def read_tiff(path: str | Path) -> dict[str, np.ndarray]:
    """Maps by name from a TIFF written by :func:`write_tiff`."""
    with tifffile.TiffFile(path) as tf:
        desc = json.loads(tf.pages[0].description)
        data = tf.asarray()
    return {name: data[i] for i, name in enumerate(desc["pages"])}


def write_colourised(path: str | Path, products: DepthProducts, *, title: str = "") -> Path:
    """PNG for people (atomic): depth mean (turbo) and total std (magma) side by side, each with
    a colour bar labelled with its units; invalid pixels grey. Ranges: 1st-99th percentile of
    the valid pixels (std from 0)."""
    matplotlib.use("Agg", force=False)
    path = Path(path)
    H, W = products.shape
    valid = products.valid
    panels = (("depth mean (camera z)", products.depth_mean, "turbo", None),
              ("depth std (total)", products.depth_std, "magma", 0.0))
    aspect = W / max(H, 1)
    fig, axes = plt.subplots(1, 2, figsize=(2 * 3.6 * aspect + 1.6, 3.6 + 0.6), dpi=110, constrained_layout=True)
    for ax, (label, values, cmap, vmin) in zip(axes, panels):
        vals = values[valid]
        lo = float(np.percentile(vals, 1)) if vals.size and vmin is None else (vmin or 0.0)
        hi = float(np.percentile(vals, 99)) if vals.size else 1.0
        if hi <= lo:
            hi = lo + max(abs(lo), 1.0) * FLAT_MAP_RANGE
        cm = matplotlib.colormaps[cmap].with_extremes(bad=(0.6, 0.6, 0.6))
        im = ax.imshow(np.ma.masked_array(values, ~valid), cmap=cm, vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.set_label(f"{label.split(' (')[0]} [{products.units}]", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(f"{title}  (K={products.num_draws}, grey: opacity < {products.min_opacity:g})", fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
