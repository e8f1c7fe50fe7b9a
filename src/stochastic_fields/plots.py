"""Plots of sparsification and calibration curves (one line per method) and of coverage over
random block re-splits, saved as PNG.

Uses matplotlib's Agg canvas directly (no pyplot, no global backend switch), so it works headless
and never touches a user's interactive backend. Files are written atomically: the figure goes to
a temporary file in the target directory, then ``os.replace`` moves it into place, so a reader
never sees a half-written PNG.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import CalibrationResult, SparsificationResult


def _save_atomic(fig: Figure, path: str | os.PathLike, dpi: int) -> Path:
    """Render ``fig`` to PNG at ``path`` through a temporary file and ``os.replace``."""
    target = Path(path)
    if target.suffix.lower() != ".png":
        raise ValueError(f"plot path must end in .png, got {str(target)!r}")
    target.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=".png.tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fig.savefig(fh, format="png", dpi=dpi)
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return target


def plot_sparsification(
    curves: Mapping[str, SparsificationResult],
    path: str | os.PathLike,
    normalised: bool = True,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
    """Plot each method's sparsification curve (solid) and its oracle (dashed, same colour).

    Args:
        curves: method name -> ``SparsificationResult``.
        path: output ``.png`` (parent directories are created).
        normalised: plot curves divided by the metric on all pixels (the AUSE convention).
    Returns:
        the written path.
    """
    if not curves:
        raise ValueError("plot_sparsification needs at least one curve")
    metrics = {r.metric for r in curves.values()}
    if len(metrics) != 1:
        raise ValueError(f"all curves must use the same metric, got {sorted(metrics)}")
    metric = metrics.pop().upper()
    fig = Figure(figsize=(6.0, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    for i, (name, r) in enumerate(curves.items()):
        colour = f"C{i % 10}"
        model = r.model_normalised if normalised else r.model
        oracle = r.oracle_normalised if normalised else r.oracle
        area = r.ause_normalised if normalised else r.ause
        ax.plot(r.fractions, model, color=colour, label=f"{name} (AUSE {area:.4g})")
        ax.plot(r.fractions, oracle, color=colour, linestyle="--", label=f"{name} oracle")
    ax.set_xlabel("fraction of pixels removed (most uncertain first)")
    ax.set_ylabel(f"{metric} of remaining pixels" + (f" / {metric} of all pixels" if normalised else ""))
    ax.set_title(title or f"Sparsification ({metric})")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    return _save_atomic(fig, path, dpi)


def calibration_figure(curves: Mapping[str, CalibrationResult], title: str | None = None) -> Figure:
    """Empirical coverage against nominal level per method, with the ideal diagonal (a Figure)."""
    if not curves:
        raise ValueError("calibration_figure needs at least one curve")
    fig = Figure(figsize=(5.0, 5.0))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0.0, 1.0], [0.0, 1.0], color="0.5", linestyle=":", label="ideal")
    for i, (name, r) in enumerate(curves.items()):
        ax.plot(r.levels, r.coverage, color=f"C{i % 10}", label=f"{name} (AUCE {r.auce:.3f}, {r.verdict})")
    ax.set_xlabel("nominal level p of the central interval")
    ax.set_ylabel("empirical coverage")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_title(title or "Calibration")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    fig.tight_layout()
    return fig


def plot_calibration(
    curves: Mapping[str, CalibrationResult],
    path: str | os.PathLike,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
    """Write :func:`calibration_figure` to ``path`` (``.png``, parent directories created, atomic).

    Returns:
        the written path.
    """
    if not curves:
        raise ValueError("plot_calibration needs at least one curve")
    return _save_atomic(calibration_figure(curves, title), path, dpi)


def interval_reliability_figure(intervals: Mapping[str, Mapping], title: str | None = None) -> Figure:
    """Left: coverage of the central intervals against their nominal level (reliability diagram),
    with the narrowest and the widest third of the bands' own coverage where the result has
    ``width_groups``; right: the distribution of their 95% half-widths relative to depth
    (sharpness), per name, from ``metrics.interval_sharpness`` outputs {name: result} (a Figure)."""
    if not intervals:
        raise ValueError("interval_reliability_figure needs at least one result")
    fig = Figure(figsize=(10.0, 4.5))
    ax, bx = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ax.plot([0.0, 1.0], [0.0, 1.0], color="0.5", linestyle=":", label="ideal")
    for i, (name, r) in enumerate(intervals.items()):
        levels = np.asarray(r["levels"])
        ax.plot(levels, r["coverage"], "o-", color=f"C{i % 10}", label=name)
        groups = r.get("width_groups") or {}
        if len(groups.get("coverage", [])) >= 2:  # the narrowest and the widest bands' own coverage
            for g, style, which in ((0, "--", "narrowest"), (-1, ":", "widest")):
                ax.plot(levels, groups["coverage"][g], style, color=f"C{i % 10}", alpha=0.8,
                        label=f"{name}, {which} third of the {100 * groups['level']:.0f}% bands "
                              f"(median {100 * groups['halfwidth_median'][g]:.0f}%)")
        at95 = int(np.argmin(np.abs(levels - 0.95)))
        half = np.asarray(r["halfwidth"])[:, at95]
        half = half[np.isfinite(half) & (half > 0)]
        if half.size:
            bins = np.logspace(np.log10(max(half.min(), 1e-4)), np.log10(max(half.max(), 2e-4)), 40)
            bx.hist(half, bins=bins, histtype="step", color=f"C{i % 10}",
                    label=f"{name}: median {100 * np.median(half):.0f}%")
    ax.set_xlabel("nominal level of the central interval")
    ax.set_ylabel("share of true depths inside")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    ax.set_title("reliability")
    bx.axvline(0.15, color="0.5", linestyle=":")
    bx.set_xscale("log")
    bx.set_xlabel("95% half-width / true depth")
    bx.set_ylabel("values")
    bx.set_title("sharpness")
    bx.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_interval_reliability(path: str | os.PathLike, intervals: Mapping, title: str | None = None,
                              dpi: int = 110) -> Path:
    """Write ``interval_reliability_figure`` to ``path`` (atomic); ``intervals``: one
    ``metrics.interval_sharpness`` output, or {name: output}."""
    if "levels" in intervals:
        intervals = {"depth": intervals}
    return _save_atomic(interval_reliability_figure(intervals, title), path, dpi)


def event_reliability_figure(results: Mapping[str, Mapping], title: str | None = None) -> Figure:
    """Reliability diagram of yes/no probabilities: the observed frequency against the mean
    probability per bin, one line per name, from ``metrics.event_reliability`` outputs {name:
    result}, marker area by the bin's count; the legend gives each Brier score and ECE (a Figure)."""
    if not results:
        raise ValueError("event_reliability_figure needs at least one result")
    fig = Figure(figsize=(5.5, 5.0))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0.0, 1.0], [0.0, 1.0], color="0.5", linestyle=":", label="ideal")
    for i, (name, r) in enumerate(results.items()):
        count = np.asarray(r["bin_count"], dtype=np.float64)
        ax.plot(r["bin_prob"], r["bin_freq"], "-", color=f"C{i % 10}",
                label=f"{name}: Brier {r['brier']:.3f}, ECE {r['ece']:.3f}")
        ax.scatter(r["bin_prob"], r["bin_freq"], s=10 + 200 * count / count.sum(), color=f"C{i % 10}")
    ax.set_xlabel("stated probability")
    ax.set_ylabel("observed frequency")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", loc="upper left")
    if title:
        ax.set_title(title, fontsize="medium")
    fig.tight_layout()
    return fig


def plot_event_reliability(path: str | os.PathLike, results: Mapping[str, Mapping], title: str | None = None,
                           dpi: int = 110) -> Path:
    """Write ``event_reliability_figure`` to ``path`` (atomic)."""
    return _save_atomic(event_reliability_figure(results, title), path, dpi)


def plot_resplit_coverage(
    coverages: Mapping[str, np.ndarray],
    today: Mapping[str, Sequence[float]],
    levels: Sequence[float],
    path: str | os.PathLike,
    tolerance: float = 0.05,
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """Histograms of the recalibrated depth coverage over random block re-splits, one panel per
    scene (columns) and level (rows), with the nominal level +- ``tolerance`` shaded and the
    committed split's coverage dashed.

    Args:
        coverages: scene -> [splits, L] coverages (``calibration.resplit_coverage``).
        today: scene -> [L] coverage of the committed split.
        levels: [L] nominal central levels.
    Returns:
        the written path.
    """
    if not coverages:
        raise ValueError("plot_resplit_coverage needs at least one scene")
    scenes = list(coverages)
    fig = Figure(figsize=(4.0 * len(scenes), 3.2 * len(levels)))
    for c, scene in enumerate(scenes):
        cov = np.asarray(coverages[scene], dtype=np.float64).reshape(-1, len(levels))
        for r, level in enumerate(levels):
            ax = fig.add_subplot(len(levels), len(scenes), r * len(scenes) + c + 1)
            ax.axvspan(level - tolerance, level + tolerance, color="tab:green", alpha=0.15,
                       label=f"nominal +- {tolerance * 100:.0f} points")
            ax.hist(cov[:, r], bins=30, color="tab:blue", alpha=0.8, label=f"{len(cov)} random re-splits")
            ax.axvline(level, color="tab:green")
            ax.axvline(float(today[scene][r]), color="tab:red", linestyle="--", label="committed split")
            ax.set_title(f"{scene}: {level:.0%} interval")
            ax.set_xlabel("share of scored depths inside")
            if r == 0 and c == 0:
                ax.legend(fontsize="x-small")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save_atomic(fig, path, dpi)


def plot_coverage_by_group(
    groups: Mapping[str, Sequence[Mapping]],
    levels: Sequence[float],
    path: str | os.PathLike,
    tolerance: float = 0.05,
    xlabel: str = "group",
    title: str | None = None,
    dpi: int = 110,
    series: tuple[str, str] = ("recalibrated", "raw"),
) -> Path:
    """Interval coverage per group of points, one panel per scene: bars for each level (calibrated
    solid, raw hatched), the nominal level +- ``tolerance`` shaded, each group's point count on top.

    Args:
        groups: scene -> rows with "group" (label), "points", "coverage" [L], "coverage_raw" [L]
            (``benchmarks/studies/coverage_by_views.coverage_table``).
        levels: [L] nominal central levels.
        series: legend names of "coverage" and "coverage_raw".
    Returns:
        the written path.
    """
    if not groups:
        raise ValueError("plot_coverage_by_group needs at least one scene")
    scenes = list(groups)
    fig = Figure(figsize=(4.6 * len(scenes), 3.6))
    colours = ("tab:blue", "tab:orange", "tab:purple", "tab:brown")
    width = 0.8 / (2 * len(levels))
    for c, scene in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), c + 1)
        rows = list(groups[scene])
        x = np.arange(len(rows))
        for j, level in enumerate(levels):
            colour = colours[j % len(colours)]
            ax.axhspan(level - tolerance, level + tolerance, color=colour, alpha=0.08)
            ax.axhline(level, color=colour, linewidth=0.8)
            cal = [float(r["coverage"][j]) for r in rows]
            raw = [float(r["coverage_raw"][j]) for r in rows]
            ax.bar(x + (2 * j - len(levels)) * width + width / 2, cal, width, color=colour,
                   label=f"{level:.0%} {series[0]}")
            ax.bar(x + (2 * j + 1 - len(levels)) * width + width / 2, raw, width, color="none",
                   edgecolor=colour, hatch="//", label=f"{level:.0%} {series[1]}")
        for i, r in enumerate(rows):
            ax.text(i, 1.02, str(r["points"]), ha="center", va="bottom", fontsize="x-small")
        ax.set_xticks(x, [str(r["group"]) for r in rows])
        ax.set_ylim(0.0, 1.1)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("share of scored depths inside")
        ax.set_title(scene)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2 * len(levels), fontsize="small")
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    return _save_atomic(fig, path, dpi)


def plot_rule_margins(
    margins: Mapping[str, Mapping[str, Mapping[str, float]]],
    path: str | os.PathLike,
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """A study's rule at a glance: one panel per scene, for each ruled metric one bar per row of its
    change in tolerances (> 0 better, <= -1 fails the rule; failing bars drawn red-edged).

    Args:
        margins: scene -> row -> metric -> signed change / |tolerance|
            (``benchmarks/studies/uncertainty_study.rule_margins``).
    Returns:
        the written path.
    """
    if not margins:
        raise ValueError("plot_rule_margins needs at least one scene")
    scenes = list(margins)
    rows = list(dict.fromkeys(r for scene in scenes for r in margins[scene]))
    metrics = list(dict.fromkeys(m for scene in scenes for r in margins[scene].values() for m in r))
    fig = Figure(figsize=(4.8 * len(scenes), 3.8))
    colours = ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")
    width = 0.8 / max(len(rows), 1)
    x = np.arange(len(metrics))
    for c, scene in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), c + 1, sharey=fig.axes[0] if c else None)
        ax.axhspan(-1.0, 1.0, color="0.5", alpha=0.08)
        ax.axhline(-1.0, color="tab:red", linewidth=0.8, linestyle="--")
        ax.axhline(0.0, color="0.3", linewidth=0.6)
        for j, row in enumerate(rows):
            values = [float(margins[scene].get(row, {}).get(m, np.nan)) for m in metrics]
            edges = ["tab:red" if v <= -1.0 else colours[j % len(colours)] for v in values]
            ax.bar(x + (j - (len(rows) - 1) / 2) * width, values, width, color=colours[j % len(colours)],
                   edgecolor=edges, linewidth=1.5, label=row)
        ax.set_xticks(x, metrics, rotation=30, ha="right", fontsize="small")
        ax.set_ylabel("change / tolerance (> 0 better)")
        ax.set_title(scene)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(rows), fontsize="small")
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    return _save_atomic(fig, path, dpi)


def plot_step_times(
    end_steps: Sequence[int],
    step_s: Mapping[str, Sequence[float]],
    labels: Mapping[str, str],
    path: str | os.PathLike,
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """Training step time (ms) against the training step, one line per method
    (``benchmarks/studies/train_cost.py``: each point a chunk of steps, at the chunk's last step).

    Args:
        end_steps: [C] the last step of each chunk.
        step_s: method -> [C] seconds per step in each chunk.
        labels: method -> legend label.
    Returns:
        the written path.
    """
    if not step_s:
        raise ValueError("plot_step_times needs at least one method")
    fig = Figure(figsize=(7.0, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    for method, seconds in step_s.items():
        if len(seconds) != len(end_steps):
            raise ValueError(f"{method}: {len(seconds)} step times for {len(end_steps)} chunks")
        ax.plot(list(end_steps), [1e3 * float(t) for t in seconds], marker=".", label=labels.get(method, method))
    ax.set_xlabel("training step (end of chunk)")
    ax.set_ylabel("ms per step")
    ax.set_ylim(bottom=0)
    if title:
        ax.set_title(title, fontsize="small")
    ax.legend(fontsize="small")
    fig.tight_layout()
    return _save_atomic(fig, path, dpi)


def view_panels_figure(photo: np.ndarray, maps: Mapping[str, np.ndarray], title: str | None = None) -> Figure:
    """One view side by side: the photo [H, W, 3], the rendered colour mean, the depth mean and the
    depth std relative to depth (``maps`` of a render/eval ``view_XXX.npz``: ``colour_mean``,
    ``depth_mean``, ``depth_std``, ``opacity``), each map with its colour bar; pixels with
    opacity below 0.5 are grey in the depth panels."""
    valid = np.asarray(maps["opacity"]) >= 0.5
    depth = np.where(valid, maps["depth_mean"], np.nan)
    relative = np.where(valid, np.asarray(maps["depth_std"]) / np.maximum(np.asarray(maps["depth_mean"]), 1e-12),
                        np.nan)
    fig = Figure(figsize=(16, 3.6))
    axes = fig.subplots(1, 4)
    panels = [("photo", np.clip(photo, 0, 1), None), ("rendered colour (mean of K)", np.clip(maps["colour_mean"], 0, 1), None),
              ("depth mean (camera z)", depth, "viridis"), ("depth std / depth", relative, "magma")]
    for ax, (name, image, cmap) in zip(axes, panels):
        if cmap is None:
            ax.imshow(image)
        else:
            finite = image[np.isfinite(image)]
            lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
            shown = ax.imshow(image, cmap=cmap, vmin=lo, vmax=hi)
            shown.cmap.set_bad("0.6")
            fig.colorbar(shown, ax=ax, fraction=0.035, pad=0.02)
        ax.set_title(name, fontsize=10)
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return fig


def plot_view_panels(path: str | os.PathLike, photo: np.ndarray, maps: Mapping[str, np.ndarray],
                     title: str | None = None, dpi: int = 90) -> Path:
    """:func:`view_panels_figure` saved as a PNG (atomically)."""
    return _save_atomic(view_panels_figure(photo, maps, title), path, dpi)
