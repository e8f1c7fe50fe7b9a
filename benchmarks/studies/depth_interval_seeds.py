"""The depth intervals of S-NeRF (default) on several seeds: coverage at every level, width, interval
score and CRPS, per seed and their mean (a measurement; it decides no default).

Each ``--run SEED=WORK`` names the ``--work`` folder of one ``benchmarks/capture_quality.py`` run
of S-NeRF (``--methods snerf``, the seed given there). Per scene the last evaluation of the run
(``eval_<steps>/metrics.json``: the validation photos' SfM points of the SCORE role, after the
recalibration ``train`` fits) is read; nothing is trained or rendered here.

    python benchmarks/studies/depth_interval_seeds.py --run 0=runs/capture_quality_parallax \\
        --run 1=runs/capture_interval_seeds/seed_1 --run 2=runs/capture_interval_seeds/seed_2 \\
        --tables 0=benchmarks/results/eval_tables/tables.json --tables 1=T1 ... --out benchmarks/results/depth_interval_seeds

``--evals SEED=FOLDER`` adds the same tables runs scored on the paper split's validation views (the
held-out photos the tables do not score), ``FOLDER/<scene>/metrics.json`` as
``paper_validation_views.py`` writes them.

``--tables SEED=TABLES_JSON`` adds the paper split: the S-NeRF (default) rows of a
``benchmarks/eval_tables.py`` run (``--seed SEED``; its test views' SCORE points, the map
cross-fitted), one ``tables.json`` per seed and scene or several scenes in one.

Issue 36's checks beside each mean, as study 20b states them (``relative_floor_study``): every level
of ``RULE_LEVELS`` within ``COVERAGE_TOLERANCE`` of nominal, and the median 95% half-width at most
``HALFWIDTH_TARGET_REAL`` of the depth.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from stochastic_fields import metrics as M
from stochastic_fields.io_utils import atomic_write_text

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared rules
from relative_floor_study import COVERAGE_TOLERANCE, HALFWIDTH_TARGET_REAL, RULE_LEVELS  # noqa: E402  (issue 36's checks)
from study_helpers import read_tables_method  # noqa: E402

#: Names of the central levels scored ("50", "68", ...), as metrics.json keys them.
LEVELS = tuple(M.level_name(p) for p in M.INTERVAL_LEVELS)
#: Columns of a row: (metrics.json key under pooled.depth_intervals, header, scale, format).
COLUMNS = ([(f"coverage_{p}", f"cov {p}", 100.0, "{:.1f}") for p in LEVELS]
           + [("halfwidth_median_68", "median 68% hw", 100.0, "{:.1f}%"),
              ("halfwidth_median_95", "median 95% hw", 100.0, "{:.1f}%"),
              ("halfwidth_p90_95", "p90 95% hw", 100.0, "{:.1f}%"),
              ("interval_score_68", "IS68 / depth", 1.0, "{:.3f}"),
              ("interval_score_95", "IS95 / depth", 1.0, "{:.3f}"),
              ("crps", "CRPS / depth", 1.0, "{:.4f}")])


def parse_run(text: str) -> tuple[int, Path]:
    seed, sep, path = text.partition("=")
    if not sep or not seed.strip().isdigit():
        raise argparse.ArgumentTypeError(f"--run expects SEED=WORK_FOLDER, got {text!r}")
    return int(seed), Path(path)


def read_eval_scores(metrics_file: Path) -> tuple[dict, dict]:
    """(the whole file, its pooled depth scores: abs_rel, points and the ``COLUMNS`` keys) of a
    ``stochastic-fields eval`` metrics.json (``evaluation.evaluate``'s, as the capture benchmark's
    marks and ``paper_validation_views.py`` write it); a file without pooled depth intervals is refused."""
    try:
        result = json.loads(Path(metrics_file).read_text())
        intervals, depth = result["pooled"]["depth_intervals"], result["pooled"]["depth"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{metrics_file}: not a stochastic-fields eval metrics.json with pooled depth intervals "
                         f"({type(exc).__name__}: {exc})") from exc
    return result, {"abs_rel": depth.get("abs_rel"), "points": depth.get("num_used"),
                    **{key: intervals.get(key) for key, *_ in COLUMNS}}


def read_row(work: Path, scene: str, seed: int) -> dict | None:
    """One seed's scores on ``scene`` from a capture benchmark's work folder, or None when the run
    is not finished there."""
    record = work / scene / "snerf" / "record.json"
    if not record.is_file():
        return None
    rec = json.loads(record.read_text())
    _, scores = read_eval_scores(work / scene / "snerf" / "run" / f"eval_{rec['steps']:06d}" / "metrics.json")
    last = rec["curve"][-1]
    return {"protocol": "capture", "scene": scene, "seed": seed, "steps": rec["steps"], "minutes": last["minutes"],
            "psnr": last["psnr"], **scores}


def read_table_rows(path: Path, seed: int) -> list[dict]:
    """The S-NeRF (default) rows, one per scene, of an ``eval_tables.py`` run's ``tables.json``."""
    def row(m: dict) -> dict:
        intervals = m["pooled"]["depth_intervals"]
        return {"psnr": m["psnr"], "abs_rel": m["depth"]["abs_rel"], "points": None,
                **{key: intervals.get(key) for key, *_ in COLUMNS}}

    found = read_tables_method(path, "snerf_default", row, "S-NeRF (default) depth intervals")
    return [{"protocol": "paper", "scene": scene, "seed": seed, "steps": "", **r} for scene, r in found.items()]


def read_eval_row(folder: Path, scene: str, seed: int) -> dict | None:
    """One seed's scores on ``scene`` from ``folder``/``scene``/metrics.json, a ``stochastic-fields eval``
    output (the paper split's validation views: ``paper_validation_views.py``), or None when absent."""
    path = Path(folder) / scene / "metrics.json"
    if not path.is_file():
        return None
    result, scores = read_eval_scores(path)
    try:
        psnr = result["summary"]["psnr"]["mean"]
    except (KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a stochastic-fields eval metrics.json (no summary PSNR: {exc})") from exc
    return {"protocol": "paper-val", "scene": scene, "seed": seed, "steps": "", "psnr": psnr, **scores}


def mean_row(rows: list[dict]) -> dict:
    keys = ["psnr", "abs_rel", *(key for key, *_ in COLUMNS)]
    return {key: float(np.mean([r[key] for r in rows])) for key in keys}


def checks(mean: dict) -> dict:
    """Issue 36's targets 1 and 2 on a mean row (study 20b's levels, tolerance and real-scene width
    target): offsets from nominal in points, keyed by the level in percent."""
    off = {int(M.level_name(p)): 100.0 * (mean[f"coverage_{M.level_name(p)}"] - p) for p in RULE_LEVELS}
    return {"levels_hold": all(abs(v) <= 100.0 * COVERAGE_TOLERANCE for v in off.values()),
            "level_offsets_points": off,
            "sharp": mean["halfwidth_median_95"] <= HALFWIDTH_TARGET_REAL}


def table(rows: list[dict]) -> list[str]:
    head = ["protocol", "scene", "seed", "steps", "PSNR dB", "abs-rel", *(h for _, h, *_ in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["protocol"], r["scene"], str(r["seed"]), str(r.get("steps", "")), f"{r['psnr']:.2f}", f"{r['abs_rel']:.4f}"]
        cells += [fmt.format(scale * r[key]) for key, _, scale, fmt in COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=parse_run, action="append", default=[], metavar="SEED=WORK",
                    help="A capture benchmark's --work folder of that seed (repeatable).")
    ap.add_argument("--tables", type=parse_run, action="append", default=[], metavar="SEED=TABLES_JSON",
                    help="An eval_tables.py run's tables.json of that seed (repeatable): the paper split's rows.")
    ap.add_argument("--evals", type=parse_run, action="append", default=[], metavar="SEED=FOLDER",
                    help="A folder of `stochastic-fields eval` outputs (FOLDER/<scene>/metrics.json) of that seed's "
                         "tables run on the paper split's validation views (paper_validation_views.py; repeatable).")
    ap.add_argument("--scenes", nargs="+", default=["fern", "flower"])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if not args.run and not args.tables and not args.evals:
        ap.error("give at least one --run, --tables or --evals")
    rows = []
    for scene in args.scenes:
        rows += [row for seed, work in args.run if (row := read_row(work, scene, seed)) is not None]
        rows += [row for seed, folder in args.evals if (row := read_eval_row(folder, scene, seed)) is not None]
    for seed, path in args.tables:
        rows += [row for row in read_table_rows(path, seed) if row["scene"] in args.scenes]
    rows.sort(key=lambda r: (r["protocol"], r["scene"], r["seed"]))
    means = {}
    for key in dict.fromkeys((r["protocol"], r["scene"]) for r in rows):
        found = [r for r in rows if (r["protocol"], r["scene"]) == key]
        mean = {**mean_row(found), "seeds": [r["seed"] for r in found]}
        means[f"{key[0]} {key[1]}"] = {**mean, "checks": checks(mean)}
    mean_rows = [{"protocol": name.split()[0], "scene": name.split()[1],
                  "seed": "mean of " + ", ".join(map(str, m["seeds"])), "steps": "", **m}
                 for name, m in means.items()]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "results.json", json.dumps({"rows": rows, "means": means}, indent=2))
    runs = " ".join([f"--run {seed}={work}" for seed, work in args.run]
                    + [f"--tables {seed}={path}" for seed, path in args.tables]
                    + [f"--evals {seed}={folder}" for seed, folder in args.evals])
    lines = ["# S-NeRF (default)'s depth intervals on several seeds", "",
             f"Command: `python benchmarks/studies/depth_interval_seeds.py {runs} --out {args.out}` "
             "(reads the runs of `benchmarks/capture_quality.py --methods snerf --seed SEED` and the tables of "
             "`benchmarks/eval_tables.py --methods snerf_default --seed SEED`; trains nothing).", "",
             "Capture: scored at the validation photos' SfM points of the SCORE role (every 8th photo validates), "
             "with the recalibration `train` fits. Paper: the tables' test views' SCORE points, the map "
             "cross-fitted. Paper-val: the same runs at the SCORE points of the paper split's other held-out "
             "photos (the validation views the tables do not score; `stochastic-fields eval --views`). "
             "Widths, interval scores and CRPS relative to the depth.", "",
             *table(rows + mean_rows), ""]
    for name, m in means.items():
        c = m["checks"]
        offsets = ", ".join(f"{p}%: {v:+.1f}" for p, v in c["level_offsets_points"].items())
        lines.append(f"- {name}: levels within {100 * COVERAGE_TOLERANCE:g} points of nominal: "
                     f"{'yes' if c['levels_hold'] else 'no'} ({offsets}); median 95% half-width "
                     f"{100 * m['halfwidth_median_95']:.1f}% (target {100 * HALFWIDTH_TARGET_REAL:g}%): "
                     f"{'met' if c['sharp'] else 'not met'}")
    atomic_write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
