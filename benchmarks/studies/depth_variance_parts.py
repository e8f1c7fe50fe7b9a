"""Which part of S-NeRF's depth variance ranks depth errors (renders only; decides nothing).

S-NeRF's depth variance is the sum of two parts (law of total variance, docs/definitions.md §3.4):
the EPISTEMIC part Var_k D_k (the K trajectories' expected termination depths disagree) and the
SPREAD mean_k V_k (each trajectory's termination is spread along the ray). The scores rank depth
errors by the total. This re-scores trained runs exactly as the tables do (same test views, SCORE
capture points or the synthetic scene's SCORE-block pixels, opacity > 0.5, the run's stored
recalibration, render seed 0) and reports Spearman |error| vs the total std and vs each part's std
alone, per-view mean and pooled.

    python benchmarks/studies/depth_variance_parts.py --run fern=RUN --run flower=RUN2 ... --out OUT

Each ``--run`` is SCENE=FOLDER (SCENE: an LLFF scene under --data-root or a scene folder; FOLDER: a
trained S-NeRF run). Runs are re-scored into OUT/<scene>/<n> (resumable: a finished one is read
back); OUT/depth_variance_parts.md / .json hold the table.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"

#: (column, where in metrics.json): the total first, then each part.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("total", "depth/spearman", "depth"),
    ("epistemic", "depth_parts/spearman_epistemic", "depth_parts"),
    ("spread", "depth_parts/spearman_spread", "depth_parts"),
)


def part_spearmans(metrics: dict) -> dict[str, dict[str, float]]:
    """{"view_mean": {column: value}, "pooled": {column: value}} from an evaluation's metrics."""
    out: dict[str, dict[str, float]] = {"view_mean": {}, "pooled": {}}
    for column, key, pooled_group in COLUMNS:
        out["view_mean"][column] = float(metrics["summary"][key]["mean"])
        pooled = metrics["pooled"][pooled_group]
        out["pooled"][column] = float(pooled["spearman"] if pooled_group == "depth" else pooled[key.split("/", 1)[1]])
    return out


def parse_run(text: str) -> tuple[str, Path]:
    scene, sep, folder = text.partition("=")
    if not sep or not scene or not folder:
        raise ValueError(f"--run {text!r}: expected SCENE=FOLDER")
    return scene, Path(folder)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="SCENE=FOLDER")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    try:
        runs = [parse_run(r) for r in args.run]
    except ValueError as exc:
        p.error(str(exc))
    missing = [str(f) for _, f in runs if not (f / "config.json").is_file()]
    if missing:
        p.error(f"not a trained run (no config.json): {', '.join(missing)}")

    import torch

    from stochastic_fields.calibration import load_run_calibration
    from stochastic_fields.io_utils import atomic_write_text
    from stochastic_fields.trainer import load_trained_model
    from stochastic_fields_bench.budget import BenchmarkSettings
    from stochastic_fields_bench.runner import evaluate_run, scene_inputs

    torch.set_num_threads(1)
    rows: list[dict] = []
    inputs: dict[str, tuple] = {}
    for i, (scene, folder) in enumerate(runs):
        if scene not in inputs:
            inputs[scene] = scene_inputs(scene, BenchmarkSettings(), args.data_root, log=lambda _m: None)
        _, dataset, views, sparse = inputs[scene]
        out_dir = args.out / dataset.name / str(i)
        metrics_path = out_dir / "metrics.json"
        if not metrics_path.exists():
            _, model, _ = load_trained_model(folder, dataset=dataset)
            if not hasattr(model, "render_chunk"):
                p.error(f"{folder}: not an S-NeRF run (method {model.__class__.__name__})")
            evaluate_run(model, dataset, out_dir, views=views, sparse_depth=sparse, product_views=0,
                         progress=not args.quiet, calibration=load_run_calibration(folder))
        metrics = json.loads(metrics_path.read_text())
        rows.append({"scene": dataset.name, "run": str(folder), **part_spearmans(metrics)})

    command = "python benchmarks/studies/depth_variance_parts.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    names = [c[0] for c in COLUMNS]
    lines = ["# Which part of the depth variance ranks depth errors", "", f"Command: `{command}`", "",
             "Spearman |depth error| vs std: the total (what the scores use) and each part alone; "
             "per-view mean over the scored test views / pooled over them.", "",
             "| scene | run | " + " | ".join(f"{n} (views / pooled)" for n in names) + " |",
             "|---|---|" + "---|" * len(names)]
    for r in rows:
        lines.append(f"| {r['scene']} | `{r['run']}` | " + " | ".join(
            f"{r['view_mean'][n]:.3f} / {r['pooled'][n]:.3f}" for n in names) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "depth_variance_parts.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "depth_variance_parts.json", json.dumps({"command": command, "rows": rows}, indent=2))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
