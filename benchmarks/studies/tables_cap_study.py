"""Study 26: the tables' cell cap at the paper split (250k against the product's 2M), judged by its rule.

The rows are ``benchmarks/eval_tables.py`` runs (S-NeRF (default) and the deterministic NeRF, paper
split, seed 1, one thread), today's cap and the candidate's::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes SCENE --methods deterministic snerf_default \\
        --seed 1 --no-timing --out runs/cap_study/cap_250k
    (the same with --set field.grid_max_cells=2000000 --out runs/cap_study/cap_2M)

This script scores each run on its **validation views**, the paper split's held-out photos that the
tables do not score (``runner.scene_inputs`` gives the tables' four; the rest validate), with
``stochastic-fields eval --views`` (the user's path: PSNR, depth against the SCORE capture points
those photos see, intervals cross-fitted), then writes the table and the rule's verdict
(docs/studies.md, fixed before the rows ran) to ``--out``/README.md and ``results.json``::

    python benchmarks/studies/tables_cap_study.py --runs runs/cap_study --out benchmarks/results/tables_cap_study

The tables' own test-view scores (each run's metrics.json) are not read.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from stochastic_fields import metrics as M
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields_bench.budget import BenchmarkSettings
from stochastic_fields_bench.runner import load_stages, scene_inputs

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules
from relative_floor_study import COVERAGE_TOLERANCE, RULE_LEVELS  # noqa: E402  (issue 36's levels and tolerance)

#: The LLFF scenes, as eval_tables.py reads them.
DATA_ROOT = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "nerf_llff_data"
#: Row label -> the folder under --runs (today's first).
ROWS = {"250k (today)": "cap_250k", "2M (candidate)": "cap_2M"}
SCENES = ("fern", "flower")
METHODS = ("snerf_default", "deterministic")
#: Study 24's checks (S-NeRF): gain >= 0.2 dB PSNR or >= 0.005 abs-rel; lose <= 0.1 dB and <= 0.002.
MIN_PSNR_GAIN_DB, MIN_ABS_REL_GAIN, MAX_PSNR_LOSS_DB, MAX_ABS_REL_LOSS = 0.2, 0.005, 0.1, 0.002
#: The deterministic NeRF's PSNR may fall at most this much (the cap is every method's).
MAX_BASELINE_PSNR_LOSS_DB = 0.1
#: Issue 40's bound on the tables' budget: the candidate trains at most this many times as long.
MAX_TRAIN_RATIO = 2.0


def validation_views(scene: str) -> list[int]:
    """The paper split's held-out views the tables (CPU budget) do not score."""
    _, dataset, scored, _ = scene_inputs(scene, BenchmarkSettings(), DATA_ROOT, log=lambda _: None)
    return [v for v in dataset.test_indices if v not in set(scored)]


def score_run(run: Path, views: list[int], out: Path) -> dict:
    """``stochastic-fields eval`` on ``views`` (cached in ``out``): PSNR, depth abs-rel and intervals."""
    metrics = out / "metrics.json"
    if not metrics.is_file():
        cmd = [sys.executable, "-m", "stochastic_fields.cli", "eval", "--run", str(run), "--views",
               ",".join(map(str, views)), "--no-products", "--quiet", "--out", str(out)]
        subprocess.run(cmd, check=True)
    result = json.loads(metrics.read_text())
    depth = result.get("pooled", {}).get("depth") or {}
    intervals = result.get("pooled", {}).get("depth_intervals") or {}
    return {"psnr": result["summary"]["psnr"]["mean"], "ssim": result["summary"]["ssim"]["mean"],
            "abs_rel": depth.get("abs_rel"), "spearman": depth.get("spearman"), "points": depth.get("num_used"),
            "coverage": {M.level_name(p): intervals.get(f"coverage_{M.level_name(p)}") for p in M.INTERVAL_LEVELS},
            "halfwidth_median_95": intervals.get("halfwidth_median_95"),
            "interval_score_95": intervals.get("interval_score_95"), "crps": intervals.get("crps"),
            "train_s": load_stages(run)["train"]["train_s"], "views": len(views)}


def holds(coverage: float | None, level: float) -> bool:
    return coverage is not None and abs(coverage - level) <= COVERAGE_TOLERANCE


def scene_checks(scene: str, today: dict, candidate: dict) -> list[str]:
    """The failed checks of one scene, ``today`` and ``candidate`` holding each method's scores: S-NeRF
    gains 0.2 dB or 0.005 abs-rel and loses at most 0.1 dB and 0.002; its coverage stays within the
    tolerance at every rule level where today's is; the deterministic NeRF loses at most 0.1 dB."""
    failed = []
    t, c = today["snerf_default"], candidate["snerf_default"]
    dpsnr, dabs = c["psnr"] - t["psnr"], c["abs_rel"] - t["abs_rel"]
    if not (dpsnr >= MIN_PSNR_GAIN_DB or dabs <= -MIN_ABS_REL_GAIN):
        failed.append(f"{scene}: S-NeRF gains neither {MIN_PSNR_GAIN_DB} dB nor {MIN_ABS_REL_GAIN} abs-rel "
                      f"({dpsnr:+.2f} dB, {dabs:+.4f})")
    if dpsnr < -MAX_PSNR_LOSS_DB:
        failed.append(f"{scene}: S-NeRF PSNR {dpsnr:+.2f} dB")
    if dabs > MAX_ABS_REL_LOSS:
        failed.append(f"{scene}: S-NeRF abs-rel {dabs:+.4f}")
    for p in RULE_LEVELS:
        name = M.level_name(p)
        if holds(t["coverage"][name], p) and not holds(c["coverage"][name], p):
            failed.append(f"{scene}: {name}% coverage {100 * c['coverage'][name]:.1f}")
    if "deterministic" in today:  # a study without its rows takes an earlier study's check (study 43)
        td, cd = today["deterministic"], candidate["deterministic"]
        if cd["psnr"] - td["psnr"] < -MAX_BASELINE_PSNR_LOSS_DB:
            failed.append(f"{scene}: deterministic PSNR {cd['psnr'] - td['psnr']:+.2f} dB")
    return failed


def verdict(rows: dict) -> tuple[bool, list[str]]:
    """The rule: every check on both scenes (see the module docstring and docs/studies.md)."""
    today, cand = ROWS
    failed = []
    for scene in SCENES:
        failed += scene_checks(scene, rows[today][scene], rows[cand][scene])
        for m in METHODS:
            ratio = rows[cand][scene][m]["train_s"] / rows[today][scene][m]["train_s"]
            if ratio > MAX_TRAIN_RATIO:
                failed.append(f"{scene}: {m} trains {ratio:.2f}x as long")
    return not failed, failed


def fmt(x, spec: str) -> str:
    return "" if x is None else spec.format(x)


def table_head(factor: str) -> list[str]:
    """The header lines of a study's table of scored runs, ``factor`` naming the column of the row labels."""
    levels = " / ".join(M.level_name(p) for p in M.INTERVAL_LEVELS)
    return [f"| scene | method | {factor} | train s | PSNR | SSIM | depth abs-rel | depth Spearman | points | cov {levels} "
            "| median 95% half-width | IS95 / depth | CRPS / depth |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]


def table_row(scene: str, method: str, label: str, r: dict) -> str:
    """One scored run (``score_run``'s fields) as a row under ``table_head``; coverage for S-NeRF only."""
    def pct(x, spec: str = "{:.1f}") -> str:
        return fmt(None if x is None else 100 * x, spec)

    cov = " / ".join(pct(r["coverage"][M.level_name(p)]) for p in M.INTERVAL_LEVELS) if method == "snerf_default" else ""
    return (f"| {scene} | {method} | {label} | {r['train_s']:.0f} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
            f"{fmt(r['abs_rel'], '{:.4f}')} | {fmt(r['spearman'], '{:.3f}')} | {r['points']} | {cov} | "
            f"{pct(r['halfwidth_median_95'], '{:.1f}%')} | {fmt(r['interval_score_95'], '{:.3f}')} | "
            f"{fmt(r['crps'], '{:.4f}')} |")


def report(rows: dict, taken: bool, failed: list[str], views: dict) -> str:
    lines = ["# Study 26: the tables' cell cap at the paper split", "",
             "Paper split, seed 1, 1000 steps (the tables' CPU budget), one thread; scored on the validation views "
             f"(held-out photos the tables do not score: {', '.join(f'{s} {len(v)}' for s, v in views.items())}) "
             "with `stochastic-fields eval --views` (depth at the SCORE capture points they see; S-NeRF's intervals "
             "cross-fitted). Commands: the module docstring of `benchmarks/studies/tables_cap_study.py`.", "",
             *table_head("cap")]
    for scene in SCENES:
        for m in METHODS:
            for label in ROWS:
                lines.append(table_row(scene, m, label, rows[label][scene][m]))
    lines += verdict_lines(taken, failed)
    lines += ["", "How this was run: the row commands of the script's docstring (fern's two caps one after the other "
              "in one process, flower's in a second beside it, `OMP_NUM_THREADS=1`), then `python "
              "benchmarks/studies/tables_cap_study.py --runs runs/cap_study --out benchmarks/results/tables_cap_study` "
              "after the trainings. The decision and what it shows: docs/studies.md, study 26."]
    return "\n".join(lines) + "\n"


def verdict_lines(taken: bool, failed: list[str]) -> list[str]:
    """The rule's verdict and its failed checks, as report lines."""
    return ["", f"**Rule: {'taken' if taken else 'not taken'}.**" + ("" if taken else " Failed checks:"), "",
            *[f"- {f}" for f in failed]]


def write_study(out: Path, results: dict, text: str) -> None:
    """A study's ``results.json`` and ``README.md`` in ``out`` (written atomically), the report printed."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    atomic_write_text(out / "README.md", text)
    print(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=Path("runs/cap_study"), help="Folder holding cap_250k and cap_2M.")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/tables_cap_study"))
    args = ap.parse_args()
    views = {scene: validation_views(scene) for scene in SCENES}
    rows = {label: {scene: {m: score_run(args.runs / folder / scene / m, views[scene],
                                         args.runs / "validation" / folder / scene / m)
                            for m in METHODS} for scene in SCENES} for label, folder in ROWS.items()}
    taken, failed = verdict(rows)
    write_study(args.out, {"rows": rows, "validation_views": views, "taken": taken, "failed": failed},
                report(rows, taken, failed, views))


if __name__ == "__main__":
    main()
