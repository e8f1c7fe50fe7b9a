"""Tables 1-5 (json and markdown) and the sparsification / calibration plots, built from the
files of finished runs alone."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from stochastic_fields import metrics as M
from stochastic_fields.evaluation import INTERVAL_KEYS
from stochastic_fields.plots import plot_calibration, plot_sparsification

from .budget import TABLE_CONVENTIONS, BenchmarkSettings
from .methods import DEFAULT_METHODS, METHOD_SPECS, PAPER_TABLE1, PAPER_TABLE2, PAPER_TABLE3, TABLE1_METHODS, TABLE3_METHODS


def _unpack(data, prefix: str, cls):
    kwargs = {}
    for f in dataclasses.fields(cls):
        v = data[f"{prefix}.{f.name}"]
        kwargs[f.name] = v if v.ndim else v.item()
    return cls(**kwargs)


def _summary(result: dict, key: str) -> dict[str, Any]:
    """{"mean", "num_views", "num_undefined"} of a per-view metric (NaN mean when absent)."""
    s = result["metrics"]["summary"].get(key)
    if s is None:
        return {"mean": math.nan, "num_views": 0, "num_undefined": 0}
    return s


def _mean(values: Sequence[float]) -> float:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(vals)) if vals else math.nan


def _scene_row(result: dict) -> dict[str, Any]:
    """The numbers of one method on one scene that the tables use."""
    metrics = result["metrics"]
    pooled = metrics.get("pooled", {})
    keys = ("nll", "pearson_mse_var", "spearman_mse_var", "psnr", "ssim", "ause_rmse", "ause_rmse_normalised",
            "ause_mae", "ause_mae_normalised", "ause_rmse_max_normalised", "ause_mae_max_normalised", "auce_colour",
            "calibration_gap_colour", "render_s")
    row = {k: _summary(result, k)["mean"] for k in keys}
    row["correlation_undefined_views"] = _summary(result, "pearson_mse_var")["num_undefined"]
    row["num_views"] = _summary(result, "nll")["num_views"]
    row["pooled"] = {k: v for k, v in pooled.items() if k != "depth"}
    depth_keys = ("abs_rel", "rmse", "nll", "ause_rmse", "ause_rmse_normalised", "pearson", "spearman", "coverage_68",
                  "coverage_95", "auce", "num_used")
    if metrics.get("depth_source"):
        row["depth"] = {k: _summary(result, f"depth/{k}")["mean"] for k in depth_keys}
        row["depth"]["source"] = metrics["depth_source"]
        row["depth"]["pooled"] = pooled.get("depth", {})
        row["depth"]["intervals"] = pooled.get("depth_intervals", {})  # metrics.json before them: none
    stages = result["stages"]
    train = stages.get("train", {})
    row["train_s"] = train.get("train_s", math.nan)
    row["steps"] = train.get("steps")
    row["num_parameters"] = train.get("num_parameters")
    row["num_draws"] = metrics.get("num_draws")
    timing = result.get("timing") or {}
    row["timing"] = timing
    return row


def build_tables(results: dict[str, dict[str, dict]], *, methods: Sequence[str] | None = None,
                 settings: BenchmarkSettings | None = None, command: str | None = None) -> dict[str, Any]:
    """All tables as one JSON-ready dict from {scene: {method: result}}."""
    scenes = list(results)
    present = [m for m in (methods or DEFAULT_METHODS) if any(m in results[s] for s in scenes)]
    rows = {s: {m: _scene_row(results[s][m]) for m in present if m in results[s]} for s in scenes}

    def per_scene(m: str, getter) -> dict[str, float]:
        vals = {s: getter(rows[s][m]) for s in scenes if m in rows[s]}
        vals["average"] = _mean(list(vals.values()))
        return vals

    table1 = {}
    for m in [m for m in TABLE1_METHODS if m in present]:
        table1[m] = {
            "label": METHOD_SPECS[m].label,
            "nll": per_scene(m, lambda r: r["nll"]),
            "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
            "spearman": per_scene(m, lambda r: r["spearman_mse_var"]),
            "pooled_pearson": per_scene(m, lambda r: r["pooled"].get("pearson_mse_var", math.nan)),
            "pooled_spearman": per_scene(m, lambda r: r["pooled"].get("spearman_mse_var", math.nan)),
            "correlation_undefined_views": {s: rows[s][m]["correlation_undefined_views"] for s in scenes if m in rows[s]},
            "paper": {s: PAPER_TABLE1.get(s, {}).get(m) for s in scenes},
        }
    ref = "deterministic" if "deterministic" in present else None
    table2 = {}
    for m in present:
        render = per_scene(m, lambda r: r["timing"].get("render_s", math.nan))
        train = per_scene(m, lambda r: r["train_s"])
        entry = {"label": METHOD_SPECS[m].label, "render_s": render, "train_s": train,
                 "rays_per_s": per_scene(m, lambda r: r["timing"].get("rays_per_s", math.nan)),
                 "num_draws": next((rows[s][m]["num_draws"] for s in scenes if m in rows[s]), None),
                 "peak_rss_mib": per_scene(m, lambda r: r["timing"].get("process_peak_rss_mib", math.nan)),
                 "psnr": per_scene(m, lambda r: r["psnr"]), "nll": per_scene(m, lambda r: r["nll"]),
                 "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
                 "depth_abs_rel": per_scene(m, lambda r: r.get("depth", {}).get("abs_rel", math.nan)),
                 "paper_render_s": PAPER_TABLE2.get(m)}
        if ref is not None:
            ref_render = per_scene(ref, lambda r: r["timing"].get("render_s", math.nan))
            ref_train = per_scene(ref, lambda r: r["train_s"])
            for key, num, den in (("render_ratio", render, ref_render), ("train_ratio", train, ref_train)):
                ratios = {s: num[s] / den[s] if den.get(s) else math.nan for s in scenes if s in num}
                ratios["average"] = _mean(list(ratios.values()))  # mean of the per-scene ratios
                entry[key] = ratios
        table2[m] = entry
    table3 = {}
    for m in [m for m in TABLE3_METHODS if m in present]:
        table3[m] = {"label": METHOD_SPECS[m].label, "nll": per_scene(m, lambda r: r["nll"]),
                     "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
                     "spearman": per_scene(m, lambda r: r["spearman_mse_var"]),
                     "psnr": per_scene(m, lambda r: r["psnr"]), "ause_rmse": per_scene(m, lambda r: r["ause_rmse"]),
                     "auce": per_scene(m, lambda r: r["auce_colour"]),
                     "paper": {s: PAPER_TABLE3.get(s, {}).get(m) for s in scenes}}
    quality = {m: {"label": METHOD_SPECS[m].label,
                   **{k: per_scene(m, lambda r, k=k: r[k]) for k in ("psnr", "ssim", "ause_rmse", "ause_rmse_normalised",
                                                                  "ause_mae", "ause_mae_normalised",
                                                                  "ause_rmse_max_normalised", "ause_mae_max_normalised",
                                                                  "nll", "auce_colour", "calibration_gap_colour")}}
               for m in present}
    depth = {m: {"label": METHOD_SPECS[m].label,
                 **{k: per_scene(m, lambda r, k=k: r.get("depth", {}).get(k, math.nan))
                    for k in ("abs_rel", "rmse", "nll", "ause_rmse", "ause_rmse_normalised", "pearson", "spearman",
                              "coverage_68", "coverage_95", "auce", "num_used")}}
             for m in present}
    intervals = {m: {"label": METHOD_SPECS[m].label,
                     **{k: per_scene(m, lambda r, k=k: r.get("depth", {}).get("intervals", {}).get(k, math.nan))
                        for k in INTERVAL_KEYS}}
                 for m in present}
    depth_sources = sorted({rows[s][m]["depth"]["source"] for s in scenes for m in rows[s] if "depth" in rows[s][m]})
    any_result = next(iter(next(iter(results.values())).values())) if results else None
    conventions = dict(any_result["metrics"]["conventions"]) if any_result else M.default_conventions()
    conventions.update(TABLE_CONVENTIONS)
    conventions.update({
        "view_means": "table entries are means over test views of per-view values; 'average' is the mean over scenes",
        "pooled": "pooled_* entries score every test pixel of a scene at once",
        "timing": "median wall time of repeated full renders of the first test view after an untimed warm-up "
                  "chunk, this machine, same run; ratios are to the deterministic NeRF",
        "paper_figures": "the paper's numbers are context only: their NLL convention and hardware are not ours",
        "same_pipeline": "every method renders the same dense samples (render.skip_empty_space and "
                         "render.adaptive_draws off unless overridden; the baselines never use them)",
    })
    budget = None
    if any_result:
        cfg = any_result["config"]
        budget = {"iterations": cfg["train"]["iterations"], "rays_per_batch": cfg["train"]["rays_per_batch"],
                  "backend": cfg["field"]["backend"], "num_samples": cfg["render"]["num_samples"],
                  "snerf_num_draws": _snerf_num_draws(rows), "images": cfg["data"]["images"],
                  "split_every": cfg["data"]["split_every"], "seed": cfg["train"]["seed"],
                  "grid_max_cells": cfg["field"]["grid_max_cells"]}
    return {"scenes": scenes, "methods": present, "budget": budget, "command": command,
            "protocol": settings.describe_protocol() if settings else None,
            "settings": dataclasses.asdict(settings) if settings else None, "table1": table1, "table2": table2,
            "table3": table3, "quality": quality, "depth": depth, "depth_intervals": intervals,
            "depth_sources": depth_sources,
            "per_scene": rows, "conventions": conventions}


def _snerf_num_draws(rows: dict[str, dict[str, dict]]) -> int | None:
    """K that S-NeRF's scores were rendered with (its metrics, the default S-NeRF column first); a
    baseline's config.json may keep the K of the day it was trained, which its renders ignore."""
    methods = sorted({m for by in rows.values() for m in by}, key=lambda m: (m != "snerf_default", m))
    for m in methods:
        for by in rows.values():
            if m in by and m.startswith("snerf") and by[m].get("num_draws") is not None:
                return by[m]["num_draws"]
    return None


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and math.isnan(v):
        return "undef."
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if abs(v) >= 1e4:
        return f"{v:.3g}"
    return f"{v:.{digits}f}"


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def format_markdown(tables: dict[str, Any]) -> str:
    """The tables as Markdown, with the budget, the command and the conventions."""
    scenes = tables["scenes"]
    cols = scenes + (["average"] if len(scenes) > 1 else [])
    L: list[str] = ["# Uncertainty benchmark: S-NeRF against the paper's baselines", ""]
    if tables.get("command"):
        L += ["Command: `" + tables["command"] + "`", ""]
    if tables.get("budget"):
        L += ["Budget (every method): " + ", ".join(f"{k}={v}" for k, v in tables["budget"].items()), ""]
    if tables.get("protocol"):
        L += ["Split: " + tables["protocol"], ""]
    if tables["table1"]:
        L += ["## Table 1: NLL and MSE-uncertainty correlation (paper's figures in brackets)", ""]
        header = ["method"] + [f"NLL {s}" for s in cols] + [f"Pearson {s}" for s in cols] + [f"Spearman {s}" for s in cols]
        rows = []
        for m, e in tables["table1"].items():
            def cell(kind: str, s: str, idx: int) -> str:
                paper = e["paper"].get(s) if s != "average" else None
                text = _fmt(e[kind][s])
                return text + (f" [{paper[idx]:.2f}]" if paper else "")
            rows.append([e["label"]] + [cell("nll", s, 0) for s in cols] + [cell("pearson", s, 1) for s in cols]
                        + [_fmt(e["spearman"][s]) for s in cols])
        L += _md_table(header, rows) + [""]
        L += ["Pooled over all test pixels of a scene: " + "; ".join(
            f"{e['label']}: Pearson " + ", ".join(f"{s} {_fmt(e['pooled_pearson'][s])}" for s in scenes)
            + ", Spearman " + ", ".join(f"{s} {_fmt(e['pooled_spearman'][s])}" for s in scenes)
            for e in tables["table1"].values()), ""]
    if tables["table2"]:
        L += ["## Table 2: cost against what it buys (one full test view, this machine)", ""]
        header = ["method", "K"] + [f"render s {s}" for s in scenes] + ["render x NeRF", "rays/s", "train s",
                                                                         "train x NeRF", "peak RSS MiB", "PSNR",
                                                                         "NLL", "Pearson", "depth abs-rel",
                                                                         "paper render s"]
        rows = []
        for m, e in tables["table2"].items():
            avg = "average" if len(scenes) > 1 else scenes[0]
            rows.append([e["label"], _fmt(e["num_draws"])] + [_fmt(e["render_s"][s], 2) for s in scenes]
                        + [_fmt(e.get("render_ratio", {}).get(avg, math.nan), 2), _fmt(e["rays_per_s"][avg], 0),
                           _fmt(e["train_s"][avg], 0), _fmt(e.get("train_ratio", {}).get(avg, math.nan), 2),
                           _fmt(e["peak_rss_mib"][avg], 0), _fmt(e["psnr"][avg], 2), _fmt(e["nll"][avg]),
                           _fmt(e["pearson"][avg]), _fmt(e["depth_abs_rel"][avg]),
                           _fmt(e["paper_render_s"], 2)])
        L += _md_table(header, rows) + [""]
    if tables["table3"]:
        L += ["## Table 3: ablation of the KL terms (paper's figures in brackets)", ""]
        header = ["variant"] + [f"NLL {s}" for s in cols] + [f"Pearson {s}" for s in cols] + [
            f"Spearman {s}" for s in cols] + [f"PSNR {s}" for s in cols]
        rows = []
        for m, e in tables["table3"].items():
            def cell3(kind: str, s: str, idx: int) -> str:
                paper = e["paper"].get(s) if s != "average" else None
                return _fmt(e[kind][s]) + (f" [{paper[idx]:.2f}]" if paper else "")
            rows.append([e["label"]] + [cell3("nll", s, 0) for s in cols] + [cell3("pearson", s, 1) for s in cols]
                        + [_fmt(e["spearman"][s]) for s in cols] + [_fmt(e["psnr"][s], 2) for s in cols])
        L += _md_table(header, rows) + [""]
    L += ["## Table 4: image quality, sparsification and calibration (colour)", ""]
    L += ["AUSE norm.: ours (docs/definitions.md §6.3); AUSE max-norm.: each sparsification curve divided by its "
          "own maximum (the CF-NeRF / Bayes' Rays / FisherRF convention), the column to set beside published numbers.", ""]
    header = ["method", "scene", "PSNR", "SSIM", "AUSE RMSE", "AUSE RMSE norm.", "AUSE RMSE max-norm.", "AUSE MAE",
              "AUSE MAE norm.", "AUSE MAE max-norm.", "NLL", "AUCE", "coverage gap"]
    rows = [[e["label"], s] + [_fmt(e[k][s], 2 if k == "psnr" else 4) for k in
                               ("psnr", "ssim", "ause_rmse", "ause_rmse_normalised", "ause_rmse_max_normalised",
                                "ause_mae", "ause_mae_normalised", "ause_mae_max_normalised", "nll", "auce_colour",
                                "calibration_gap_colour")]
            for e in tables["quality"].values() for s in cols]
    L += _md_table(header, rows) + [""]
    if tables["depth_sources"]:
        L += [f"## Table 5: depth against {', '.join(tables['depth_sources'])} ground truth (camera-z, scene units)", ""]
        header = ["method", "scene", "abs-rel", "RMSE", "depth NLL", "AUSE RMSE", "AUSE norm.", "Pearson |err|-std",
                  "Spearman |err|-std", "cov. 68%", "cov. 95%", "AUCE", "points"]
        rows = [[e["label"], s] + [_fmt(e[k][s], 4) for k in ("abs_rel", "rmse", "nll", "ause_rmse",
                                                             "ause_rmse_normalised", "pearson", "spearman",
                                                             "coverage_68", "coverage_95", "auce")]
                + [_fmt(e["num_used"][s], 0)] for e in tables["depth"].values() for s in cols]
        L += _md_table(header, rows) + [""]
        if any(math.isfinite(v) for e in tables.get("depth_intervals", {}).values()
               for k, per in e.items() if k != "label" for v in per.values()):
            names = [M.level_name(p) for p in M.INTERVAL_LEVELS]
            L += ["## Table 6: depth intervals, coverage and width per level (pooled over the scored depths)", "",
                  "Half-widths, interval scores (Gneiting & Raftery 2007) and CRPS are relative to the true depth "
                  "(docs/definitions.md §6.7); S-NeRF (default) is cross-fitted as in Table 5. The narrowest third: "
                  "the third of the scored depths with the narrowest 95% bands, the ones a planner acts on.", ""]
            narrow = M.WIDTH_GROUP_NAMES[0]  # the third of the depths with the narrowest 95% bands
            header = (["method", "scene"] + [f"cov. {n}%" for n in names] + [f"median half-width {n}%" for n in names[1:4]]
                      + ["p90 half-width 95%", "IS 68%", "IS 95%", "CRPS", "narrowest third: cov. 68%", "cov. 95%",
                         "its widest half-width 95%"])
            keys = ([f"coverage_{n}" for n in names] + [f"halfwidth_median_{n}" for n in names[1:4]]
                    + ["halfwidth_p90_95", "interval_score_68", "interval_score_95", "crps", f"coverage_68_{narrow}",
                       f"coverage_95_{narrow}", M.NARROWEST_WIDTH_KEY])
            rows = [[e["label"], s] + [_fmt(e[k][s], 3) for k in keys] for e in tables["depth_intervals"].values()
                    for s in cols]
            L += _md_table(header, rows) + [""]
    L += ["## Conventions", ""] + [f"- **{k}**: {v}" for k, v in tables["conventions"].items()] + [""]
    return "\n".join(L)


def write_plots(results: dict[str, dict[str, dict]], plot_dir: Path) -> list[Path]:
    """Per scene: colour sparsification (RMSE, normalised) and calibration plots for the Table-1
    methods and for the ablation, plus depth plots where depth ground truth exists."""
    written = []
    groups = {"": TABLE1_METHODS, "ablation_": TABLE3_METHODS}
    for scene, by_method in results.items():
        for prefix, group in groups.items():
            members = [m for m in group if m in by_method]
            if not members:
                continue
            label = lambda m: METHOD_SPECS[m].label  # noqa: E731
            for kind, stem, cls, plot in (
                ("colour_sparsification_rmse", "sparsification_rmse", M.SparsificationResult, plot_sparsification),
                ("colour_calibration", "calibration_colour", M.CalibrationResult, plot_calibration),
                ("depth_sparsification_rmse", "sparsification_depth", M.SparsificationResult, plot_sparsification),
                ("depth_calibration", "calibration_depth", M.CalibrationResult, plot_calibration),
            ):
                curves = {label(m): _unpack(by_method[m]["curves"], kind, cls) for m in members
                          if f"{kind}.auce" in by_method[m]["curves"] or f"{kind}.ause" in by_method[m]["curves"]}
                if not curves:
                    continue
                path = Path(plot_dir) / f"{scene}_{prefix}{stem}.png"
                title = f"{scene}: {stem.replace('_', ' ')} ({'ablation' if prefix else 'methods'})"
                written.append(plot(curves, path, title=title))
    return written
