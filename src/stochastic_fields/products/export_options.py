"""What ``export`` is asked to write, checked before anything renders: the options, the point filter,
the metric scale and the quantile levels. numpy only, so that ``export --help`` answers at once
(``products.cli`` builds its options from :class:`ExportOptions`' defaults).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np


def check_quantile_levels(levels: Sequence[float]) -> np.ndarray:
    """[Q] float64 levels in the given order; ValueError naming the bad one if outside (0, 1)."""
    arr = np.asarray([float(q) for q in levels], dtype=np.float64)
    if arr.size == 0:
        raise ValueError("quantile levels: need at least one level in (0, 1)")
    bad = [float(q) for q in arr if not 0.0 < q < 1.0]
    if bad:
        raise ValueError(f"quantile levels must lie strictly between 0 and 1, got {bad}")
    return arr


@dataclass(frozen=True)
class MetricScale:
    """Metres per scene unit and where that number came from (written into every file)."""

    metres_per_unit: float
    source: str

    def __post_init__(self) -> None:
        if not (math.isfinite(self.metres_per_unit) and self.metres_per_unit > 0):
            raise ValueError(f"metres per scene unit must be a positive number, got {self.metres_per_unit}")


@dataclass
class PointFilter:
    """Which points to keep; None disables a test. Applied in this order:
    ``opacity >= min_opacity``, ``depth_std <= max_std``, ``depth_std / depth <= max_rel_std``,
    then the ``keep_fraction`` most confident of what is left (ties keep the earlier point)."""

    min_opacity: float | None = None
    max_std: float | None = None
    max_rel_std: float | None = None
    keep_fraction: float | None = None

    def __post_init__(self) -> None:
        for name in ("min_opacity", "max_std", "max_rel_std"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise ValueError(f"PointFilter.{name} must be a non-negative number, got {v}")
        if self.keep_fraction is not None and not 0.0 < self.keep_fraction <= 1.0:
            raise ValueError(f"PointFilter.keep_fraction must be in (0, 1], got {self.keep_fraction}")


FORMATS: tuple[str, ...] = ("npz", "png16", "tiff", "png", "ros")
#: Formats written when none are named ('ros' needs a metric scale, so it is asked for by name).
DEFAULT_FORMATS: tuple[str, ...] = ("npz", "png16", "tiff", "png")


@dataclass
class ExportOptions:
    """What ``export`` writes; every field is a CLI option (see products/cli.py)."""

    views: str = "test"
    """'test', 'train', 'all' or comma-separated dataset view indices; ignored with ``cameras``."""
    cameras: Path | None = None
    """JSON list of {"K": 3x3, "world_to_camera": 4x4, "width", "height"[, "near", "far", "name"]} (OpenCV)."""
    out: Path | None = None
    """Output folder (default: RUN/export)."""
    num_draws: int | None = None
    """K depth trajectories per pixel (default: the run's render.num_draws)."""
    formats: tuple[str, ...] = DEFAULT_FORMATS
    """Per-view map formats: npz, png16, tiff, png (colourised), ros (REP 118 metres/millimetres + CameraInfo)."""
    quantiles: tuple[float, ...] = (0.05, 0.95)
    """Depth quantile levels from the K draws."""
    min_opacity: float = 0.5
    """Pixels with lower accumulated opacity are invalid (no depth, no point)."""
    max_std: float | None = None
    """Drop points with total depth std above this (scene units)."""
    max_rel_std: float | None = None
    """Drop points with depth_std / depth above this."""
    keep_fraction: float | None = None
    """Keep only this fraction of each view's most confident points."""
    colour_by: str = "rgb"
    """PLY colours: 'rgb' (rendered colour) or 'uncertainty' (depth_std through a colour map)."""
    fuse: bool = False
    """Also write one fused cloud of all views."""
    voxel_size: float | None = None
    """Fusion voxel size (default: the median pixel footprint)."""
    free_space_thresholds: tuple[float, ...] = ()
    """Camera-z distances d for a per-view P(depth > d) volume [T, H, W]."""
    covariance: bool = False
    """Add per-point 3x3 covariances (cov_xx .. cov_zz) to the PLYs."""
    save_draws: bool = False
    """Store the [H, W, K] per-draw depths in the npz (for free-space queries at any distance)."""
    units: str = "scene units"
    """Name of the length unit written into every file."""
    metres_per_unit: float | None = None
    """Metres per scene unit (needed by the 'ros' format; written into every npz)."""
    known_distance: tuple[float, float, float] | None = None
    """(i, j, metres): dataset cameras i and j are this far apart; sets metres_per_unit."""
    scale_source: str | None = None
    """Where metres_per_unit came from (set by export_run for a known distance)."""
    seed: int = 0
    """Seed of the K draws."""
    raw_uncertainty: bool = False
    """Ignore the run's calibration.json (depth_std then is the raw total std; by default it is recalibrated, the raw one kept as depth_std_raw)."""
    device: str | None = None
    """auto, cpu or cuda (default: the run's)."""
    progress: bool = True
    """Show progress bars."""

    def validate(self) -> None:
        bad = [f for f in self.formats if f not in FORMATS]
        if bad:
            raise ValueError(f"unknown format(s) {bad}; choose from {list(FORMATS)}")
        check_quantile_levels(self.quantiles)
        if not 0.0 <= self.min_opacity <= 1.0:
            raise ValueError(f"min_opacity must be in [0, 1], got {self.min_opacity}")
        if self.colour_by not in ("rgb", "uncertainty"):
            raise ValueError(f"colour_by must be 'rgb' or 'uncertainty', got {self.colour_by!r}")
        if self.num_draws is not None and not 2 <= self.num_draws <= 4096:
            raise ValueError(f"num_draws must be in [2, 4096] for depth uncertainty, got {self.num_draws}")
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {self.voxel_size}")
        if any(not (math.isfinite(t) and t > 0) for t in self.free_space_thresholds):
            raise ValueError(
                f"free-space thresholds must be positive distances, got {list(self.free_space_thresholds)}")
        if self.metres_per_unit is not None and not (math.isfinite(self.metres_per_unit) and self.metres_per_unit > 0):
            raise ValueError(f"--metres-per-unit must be a positive number, got {self.metres_per_unit}")
        if self.metres_per_unit is not None and self.known_distance is not None and self.scale_source is None:
            raise ValueError("give either --metres-per-unit or --known-distance, not both")
        if "ros" in self.formats and self.metres_per_unit is None and self.known_distance is None:
            raise ValueError("--formats ros writes depth in metres: give --metres-per-unit or --known-distance "
                             "I,J,METRES (scene units are not metres for LLFF or structure-from-motion captures)")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not isinstance(self.units, str) or not 0 < len(self.units) <= 64 or not self.units.isprintable():
            raise ValueError(f"units must be 1-64 printable characters (it is written into file headers), "
                             f"got {self.units!r}")
        self.point_filter()

    def metric_scale(self) -> MetricScale | None:
        """The metric scale of the export, or None when unknown."""
        if self.metres_per_unit is None:
            return None
        return MetricScale(float(self.metres_per_unit), self.scale_source or "--metres-per-unit (given by the user)")

    def point_filter(self) -> PointFilter:
        return PointFilter(min_opacity=self.min_opacity, max_std=self.max_std, max_rel_std=self.max_rel_std,
                           keep_fraction=self.keep_fraction)
