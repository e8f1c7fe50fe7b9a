"""Controlled study of S-NeRF's uncertainty on real and synthetic scenes: one factor at a time.

Each row is S-NeRF with the learned pixel noise (the tables' "S-NeRF + learned noise") with ONE
change, trained and scored by the same runner as the benchmark tables
(``stochastic_fields.eval.tables``: CPU budget, 1000 steps, 4 test views, seed 0), plus the deep
ensemble and the deterministic NeRF as references. Depth is scored on the SCORE capture points
only (``capture_points``); each S-NeRF row reports its depth intervals raw and recalibrated from
the CALIBRATE points (``calibration``), so the recalibration factor is measured on every row.
Test views choose nothing: the rows are fixed before the run.

    python benchmarks/uncertainty_study.py --out benchmarks/results/uncertainty_study

Resumable like the tables (finished stages are skipped). Writes ``study.md`` and ``study.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"

#: (row name, method of eval.tables.METHOD_SPECS, extra config overrides, what the row changes)
ROWS: tuple[tuple[str, str, tuple[tuple[str, object], ...], str], ...] = (
    ("base", "snerf_predictive", (), "S-NeRF + learned pixel noise, independent noise per point (the paper)"),
    ("shared_noise", "snerf_predictive", (("render.shared_noise", True),),
     "noise shared along each ray per draw (trajectory-consistent draws), training and rendering"),
    ("rao_blackwell", "snerf_predictive", (("render.colour_estimator", "rao_blackwell"),),
     "Rao-Blackwellised colour statistics at render time (less Monte-Carlo noise in the variance)"),
    ("depth", "snerf_predictive", (("loss.lambda_depth", 0.1),),
     "+ sparse-depth likelihood of the FIT capture points (weight 0.1)"),
    ("ensemble", "ensemble", (), "reference: deep ensemble of 5"),
    ("deterministic", "deterministic", (), "reference: deterministic NeRF"),
)

COLUMNS: tuple[tuple[str, str], ...] = (
    ("psnr", "PSNR"), ("nll", "NLL"), ("auce_colour", "AUCE"), ("spearman_mse_var", "Spearman MSE-var"),
    ("pooled_spearman", "Spearman pooled"), ("ause_rmse_normalised", "AUSE norm."),
    ("depth_abs_rel", "depth abs-rel"), ("depth_spearman", "depth Spearman"),
    ("cov68_raw", "cov68 raw"), ("cov95_raw", "cov95 raw"), ("cov68", "cov68 cal."), ("cov95", "cov95 cal."),
    ("depth_scale", "cal. x(68%)"), ("train_s", "train s"),
)


def _row_numbers(run_dir: Path) -> dict[str, float]:
    from stochastic_fields.eval.tables import load_method_result

    r = load_method_result(run_dir)
    m = r["metrics"]
    s = m["summary"]

    def mean(key: str) -> float:
        return s[key]["mean"] if key in s else math.nan

    pooled = m.get("pooled", {})
    depth = pooled.get("depth", {})
    raw = pooled.get("depth_raw", depth)
    cal = m.get("depth_calibration") or {}
    return {
        "psnr": mean("psnr"), "nll": mean("nll"), "auce_colour": mean("auce_colour"),
        "spearman_mse_var": mean("spearman_mse_var"), "pooled_spearman": pooled.get("spearman_mse_var", math.nan),
        "ause_rmse_normalised": mean("ause_rmse_normalised"),
        "depth_abs_rel": depth.get("abs_rel", math.nan), "depth_spearman": depth.get("spearman", math.nan),
        "cov68_raw": raw.get("coverage_68", math.nan), "cov95_raw": raw.get("coverage_95", math.nan),
        "cov68": depth.get("coverage_68", math.nan), "cov95": depth.get("coverage_95", math.nan),
        "depth_scale": (cal.get("depth") or {}).get("std_scale", math.nan),
        "depth_points": depth.get("num_used", math.nan),
        "train_s": r["stages"].get("train", {}).get("train_s", math.nan),
    }


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.0f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/uncertainty_study"))
    p.add_argument("--scenes", nargs="+", default=["synthetic", "fern", "flower"],
                   help="LLFF scene names under --data-root, folders, or 'synthetic' (the embedded scene, "
                        "generated into OUT/_scenes).")
    p.add_argument("--rows", nargs="+", default=[r[0] for r in ROWS], choices=[r[0] for r in ROWS])
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)

    import torch

    from stochastic_fields.eval.tables import BenchmarkSettings, run_scene

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    out = Path(args.out)
    scenes = []
    for scene in args.scenes:
        if scene == "synthetic":
            from stochastic_fields.data.synthetic import make_synthetic_scene

            path = out / "_scenes" / "synthetic"
            if not (path / "transforms.json").exists():
                make_synthetic_scene(path)
            scenes.append(str(path))
        else:
            scenes.append(scene)
    rows = [r for r in ROWS if r[0] in args.rows]
    for name, method, overrides, _ in rows:
        settings = BenchmarkSettings(timing=False, overrides=overrides)
        for scene in scenes:
            run_scene(scene, [method], out / name, settings, data_root=args.data_root, progress=not args.quiet)
    results: dict[str, dict[str, dict[str, float]]] = {}
    for name, method, _, _ in rows:
        for scene in scenes:
            run_dir = out / name / Path(scene).name / method
            if (run_dir / "metrics.json").exists():
                results.setdefault(Path(scene).name, {})[name] = _row_numbers(run_dir)
    command = "python benchmarks/uncertainty_study.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    lines = ["# Uncertainty study: one factor at a time", "", f"Command: `{command}`", "",
             "Rows (fixed before the run):", ""]
    lines += [f"- **{n}** ({m}): {why}" + (f"; overrides {dict(o)}" if o else "") for n, m, o, why in rows]
    lines += ["", "Columns: colour PSNR / NLL / AUCE / Spearman MSE-variance (per-view mean and pooled) / "
              "normalised AUSE-RMSE on the test views; depth abs-rel, Spearman |err|-std, and the share of "
              "SCORE capture points (synthetic: every test pixel with opacity > 0.5) inside the central "
              "68% / 95% intervals, raw and recalibrated (pooled); the recalibration factor at one sigma; "
              "training seconds (1 thread, machine shared with other work: compare within a column only).", ""]
    for scene, by_row in results.items():
        lines += [f"## {scene}", "", "| row | " + " | ".join(c[1] for c in COLUMNS) + " |",
                  "|---|" + "---|" * len(COLUMNS)]
        for name, nums in by_row.items():
            lines.append(f"| {name} | " + " | ".join(_fmt(nums[c[0]]) for c in COLUMNS) + " |")
        lines.append("")
    from stochastic_fields.io_utils import atomic_write_text

    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "study.md", "\n".join(lines))
    atomic_write_text(out / "study.json", json.dumps({"command": command, "results": results,
                                                      "wall_s_this_invocation": time.perf_counter() - t0},
                                                     indent=2, default=float))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
