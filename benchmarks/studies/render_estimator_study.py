"""Study 7: how S-NeRF renders its statistics (renders only, no training).

The colour estimator (drawn colours or Rao-Blackwellised, docs/design.md) and the number of
trajectories K are render-time choices: the trained field is the same. Every row re-renders the same
trained S-NeRF runs with its options, refits the depth recalibration with them (the map fits the std
of the K and estimator it is fitted with), scores the tables' test views and times one full view
interleaved with the deterministic NeRF in this one process (``--timing-repeats`` passes over
[deterministic, row 1, row 2, ...]; median per row). The rows and the rule are fixed before the run
(docs/uncertainty.md, study 7).

    python benchmarks/studies/render_estimator_study.py --snerf-runs RUNS --deterministic-runs DET --out OUT \\
        --scenes synthetic fern flower

``RUNS/<scene>/snerf_default`` and ``DET/<scene>/deterministic`` are run folders of the tables'
runner (``benchmarks/eval_tables.py`` or ``benchmarks/studies/uncertainty_study.py``). Each row's scores go
to ``OUT/<row>/<scene>/metrics.json`` (skipped when present: the study resumes), the timings to
``OUT/timing_<scene>.json``, the table to ``OUT/study.md`` / ``study.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "src"))  # run from a checkout

from stochastic_fields.calibration import RunCalibration, fit_depth_calibration  # noqa: E402
from stochastic_fields.evaluation import evaluate  # noqa: E402
from stochastic_fields.io_utils import atomic_write_text  # noqa: E402
from stochastic_fields.trainer import load_trained_model  # noqa: E402
from stochastic_fields_bench.budget import BenchmarkSettings  # noqa: E402
from stochastic_fields_bench.runner import TABLE_CONVENTIONS, scene_inputs, time_renders_interleaved  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"

#: (name, render options, why): fixed before the run. Every row names both options, so a row
#: renders the same whatever render defaults the stored runs were saved with (the runs of the
#: study had drawn colours and K = 16; study 7 made rb8 the default).
ROWS: tuple[tuple[str, dict, str], ...] = (
    ("drawn16", {"colour_estimator": "draws", "num_draws": 16}, "the default before this study: drawn colours, K = 16"),
    ("rb16", {"colour_estimator": "rao_blackwell", "num_draws": 16}, "Rao-Blackwellised colours, K = 16"),
    ("drawn8", {"colour_estimator": "draws", "num_draws": 8}, "drawn colours, K = 8"),
    ("rb8", {"colour_estimator": "rao_blackwell", "num_draws": 8}, "Rao-Blackwellised colours, K = 8"),
)

#: (column, key in metrics.json's summary or pooled, format)
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("PSNR", "summary/psnr", "{:.3f}"),
    ("colour NLL", "summary/nll", "{:.3f}"),
    ("colour AUCE", "summary/auce_colour", "{:.3f}"),
    ("colour Spearman", "summary/spearman_mse_var", "{:.3f}"),
    ("colour AUSE norm.", "summary/ause_rmse_normalised", "{:.3f}"),
    ("depth Spearman", "summary/depth/spearman", "{:.3f}"),
    ("depth cov68 cal.", "pooled/depth/coverage_68", "{:.3f}"),
    ("depth cov95 cal.", "pooled/depth/coverage_95", "{:.3f}"),
    ("depth NLL", "summary/depth/nll", "{:.3f}"),
)


def _value(metrics: dict, key: str) -> float:
    kind, name = key.split("/", 1)
    if kind == "summary":
        return float(metrics["summary"][name]["mean"])
    node = metrics["pooled"]
    for part in name.split("/"):
        node = node[part]
    return float(node)


def run_scene(scene: str, args) -> dict:
    _, dataset, views, sparse = scene_inputs(scene, BenchmarkSettings(), args.data_root)
    name = dataset.name
    _, snerf, _ = load_trained_model(args.snerf_runs / name / "snerf_default", dataset=dataset)
    _, det, _ = load_trained_model(args.deterministic_runs / name / "deterministic", dataset=dataset)
    out: dict = {"views": views, "rows": {}}
    for row, changes, _ in ROWS:
        run_out = args.out / row / name
        metrics_path = run_out / "metrics.json"
        if not metrics_path.exists():
            options = snerf.render_options(**changes)
            t0 = time.perf_counter()
            depth_map = fit_depth_calibration(snerf, dataset, seed=0, options=options)
            calibration = RunCalibration(depth=depth_map)
            evaluate(snerf, dataset, run_out, views=views, options=options, seed=0, sparse_depth=sparse,
                     product_views=0, calibration=calibration, conventions=TABLE_CONVENTIONS,
                     progress=not args.quiet)
            print(f"[{name}/{row}] calibrated (x{depth_map.std_scale:.3g}) and scored in "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
        out["rows"][row] = json.loads(metrics_path.read_text())
    timing_path = args.out / f"timing_{name}.json"
    if not timing_path.exists():
        out_t = time_interleaved(det, snerf, dataset, views[0], args.timing_repeats)
        atomic_write_text(timing_path, json.dumps(out_t, indent=2))
    out["timing"] = json.loads(timing_path.read_text())
    return out


def time_interleaved(det, snerf, dataset, view: int, repeats: int) -> dict:
    """Median wall time of one full render of ``view`` per variant, the variants interleaved
    (deterministic, then every row) ``repeats`` times after an untimed warm-up chunk each."""
    rays = dataset.rays(view)
    variants = {"deterministic": (det, det.default_render_options())}
    variants.update({row: (snerf, snerf.render_options(**changes)) for row, changes, _ in ROWS})
    warm = rays.flatten()[:2048].reshape(1, -1)
    for model, options in variants.values():
        with torch.no_grad():
            model.render_view(warm, options, generator=torch.Generator().manual_seed(0))
    times = time_renders_interleaved(variants, rays, repeats)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"view": int(view), "repeats": repeats, "torch_threads": torch.get_num_threads(), "seconds": times,
            "median_s": med, "ratio_to_deterministic": {k: med[k] / med["deterministic"] for k in med}}


def table(results: dict, command: str) -> str:
    lines = ["# Study 7: how S-NeRF renders its statistics (renders only)", "",
             f"Command: `{command}`", "", "Rows (fixed before the run):", ""]
    lines += [f"- **{r}**: {why}" for r, _, why in ROWS]
    lines += ["", "Scores as the tables' (4 test views, depth on the SCORE points / SCORE blocks, recalibrated "
              "with a map refitted with the row's options; per-view means unless pooled). Render: one full "
              "test view, median of the interleaved passes, 1 thread, ratio to the deterministic NeRF "
              "rendered in the same passes.", ""]
    for scene, res in results.items():
        lines += [f"## {scene}", "", "| row | " + " | ".join(c for c, _, _ in COLUMNS) + " | render s | render x NeRF |",
                  "|---|" + "---|" * (len(COLUMNS) + 2)]
        t = res["timing"]
        for row, _, _ in ROWS:
            m = res["rows"][row]
            cells = [fmt.format(_value(m, key)) for _, key, fmt in COLUMNS]
            lines.append(f"| {row} | " + " | ".join(cells) + f" | {t['median_s'][row]:.2f} | "
                         f"{t['ratio_to_deterministic'][row]:.2f} |")
        lines += ["", f"Deterministic NeRF: {t['median_s']['deterministic']:.2f} s per view ({t['repeats']} passes).", ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--snerf-runs", type=Path, required=True, help="RUNS with RUNS/<scene>/snerf_default")
    p.add_argument("--deterministic-runs", type=Path, required=True, help="DET with DET/<scene>/deterministic")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--scenes", nargs="+", default=["synthetic", "fern", "flower"])
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT,
                   help="where LLFF scene names are looked up; other scenes are given as folders")
    p.add_argument("--timing-repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (stated in the timings)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    for scene in args.scenes:
        results[Path(scene).name] = run_scene(scene, args)
    command = "python benchmarks/studies/render_estimator_study.py " + " ".join(sys.argv[1:] if argv is None else argv)
    atomic_write_text(args.out / "study.json", json.dumps({"command": command, "results": results}, indent=1,
                                                          default=float))
    atomic_write_text(args.out / "study.md", table(results, command))
    print((args.out / "study.md").read_text())


if __name__ == "__main__":
    main()
