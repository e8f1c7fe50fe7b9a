"""S-NeRF (default) against the deep ensemble on several seeds of the paper tables: issue 36's
targets 3 (interval score and CRPS at most the ensemble's) and 4 (colour and depth rankings at least
the ensemble's) judged on the seeds' means and seed by seed (a measurement; it decides no default).

Each ``--rows SEED:METHOD=TABLES_JSON`` names the ``tables.json`` of a ``benchmarks/eval_tables.py``
run (``--seed SEED``) that holds ``METHOD``'s rows; one file may serve several methods and a seed's
methods may come from different files (a row re-run after a default changed), so each row says
where it is read. Nothing is trained or rendered here::

    python benchmarks/studies/method_seeds.py \\
        --rows 0:snerf_default=benchmarks/results/eval_tables_35/tables.json \\
        --rows 0:ensemble=benchmarks/results/eval_tables/tables.json \\
        --rows 1:snerf_default=benchmarks/results/eval_tables_35/seed_1/tables.json \\
        --rows 1:ensemble=benchmarks/results/eval_tables_35/seed_1/tables.json ... \\
        --out benchmarks/results/method_seeds_35

The scores are the tables' own: per-view means over the scored test views for PSNR, the Spearman
columns and abs-rel; the interval columns pooled over the test views' SCORE points (S-NeRF's map
cross-fitted), relative to the depth.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stochastic_fields.io_utils import atomic_write_text

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import read_tables_method, seed_means  # noqa: E402

#: The methods compared: the candidate first, the reference second.
CANDIDATE, REFERENCE = "snerf_default", "ensemble"
#: Columns: (name, header, reader of a tables.json method row, format, which way is better).
COLUMNS = (
    ("psnr", "PSNR dB", lambda m: m["psnr"], "{:.2f}", "higher"),
    ("colour_spearman", "colour Spearman", lambda m: m["spearman_mse_var"], "{:.3f}", "higher"),
    ("ause_rmse_normalised", "AUSE-RMSE norm.", lambda m: m["ause_rmse_normalised"], "{:.3f}", "lower"),
    ("depth_abs_rel", "depth abs-rel", lambda m: m["depth"]["abs_rel"], "{:.4f}", "lower"),
    ("depth_spearman", "depth Spearman", lambda m: m["depth"]["spearman"], "{:.3f}", "higher"),
    *((f"coverage_{p}", f"cov {p}", lambda m, p=p: 100.0 * m["pooled"]["depth_intervals"][f"coverage_{p}"], "{:.1f}", None)
      for p in (50, 68, 90, 95)),
    ("halfwidth_median_95", "median 95% hw",
     lambda m: 100.0 * m["pooled"]["depth_intervals"]["halfwidth_median_95"], "{:.1f}%", "lower"),
    ("interval_score_95", "IS95 / depth", lambda m: m["pooled"]["depth_intervals"]["interval_score_95"], "{:.3f}", "lower"),
    ("crps", "CRPS / depth", lambda m: m["pooled"]["depth_intervals"]["crps"], "{:.4f}", "lower"),
)
#: Which way each column is better ("higher", "lower"; None: not compared).
DIRECTION = {name: direction for name, *_, direction in COLUMNS}
#: Issue 36's comparisons with the ensemble: target -> the columns it names.
TARGETS = {"3 (interval score, CRPS)": ("interval_score_95", "crps"),
           "4 (rankings)": ("colour_spearman", "ause_rmse_normalised", "depth_spearman")}


def parse_rows(text: str) -> tuple[int, str, Path]:
    """``SEED:METHOD=TABLES_JSON`` -> (seed, method, path)."""
    key, sep, path = text.partition("=")
    seed, colon, method = key.partition(":")
    if not sep or not colon or not seed.strip().isdigit() or not method or not path:
        raise argparse.ArgumentTypeError(f"--rows expects SEED:METHOD=TABLES_JSON, got {text!r}")
    return int(seed), method, Path(path)


def read_rows(path: Path, seed: int, method: str, scenes: list[str]) -> list[dict]:
    """``method``'s row of each of ``scenes`` that ``path`` (an eval_tables.py tables.json) holds."""
    found = read_tables_method(path, method, lambda m: {name: float(read(m)) for name, _, read, *_ in COLUMNS},
                               f"{method}'s depth intervals")
    return [{"scene": scene, "seed": seed, "method": method, **found[scene]} for scene in scenes if scene in found]


def better_or_equal(column: str, candidate: float, reference: float) -> bool:
    """Whether ``candidate`` is at least as good as ``reference`` in ``column``'s direction."""
    return candidate >= reference if DIRECTION[column] == "higher" else candidate <= reference


def comparisons(rows: list[dict], scene: str) -> dict:
    """Per column of ``TARGETS``: the candidate's and the reference's means on ``scene``, whether the
    means meet the target, and on how many of the seeds both methods have the candidate is as good."""
    by = {(r["method"], r["seed"]): r for r in rows if r["scene"] == scene}
    seeds = sorted({s for (m, s) in by if m == CANDIDATE} & {s for (m, s) in by if m == REFERENCE})
    if not seeds:
        return {}
    cand = seed_means([by[(CANDIDATE, s)] for s in seeds])
    ref = seed_means([by[(REFERENCE, s)] for s in seeds])
    out = {"seeds": seeds}
    for columns in TARGETS.values():
        for column in columns:
            out[column] = {"candidate": cand[column], "reference": ref[column],
                           "met_on_means": better_or_equal(column, cand[column], ref[column]),
                           "seeds_met": sum(better_or_equal(column, by[(CANDIDATE, s)][column], by[(REFERENCE, s)][column])
                                            for s in seeds)}
    return out


def table(rows: list[dict]) -> list[str]:
    head = ["scene", "method", "seed", *(h for _, h, *_ in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join([r["scene"], r["method"], str(r["seed"]),
                                        *(fmt.format(r[name]) for name, _, _, fmt, _ in COLUMNS)]) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=parse_rows, action="append", required=True, metavar="SEED:METHOD=TABLES_JSON",
                    help="Where a seed's rows of a method are read (repeatable).")
    ap.add_argument("--scenes", nargs="+", default=["fern", "flower"])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = [row for seed, method, path in args.rows for row in read_rows(path, seed, method, args.scenes)]
    keys = [(r["scene"], r["method"], r["seed"]) for r in rows]
    if len(set(keys)) != len(keys):
        raise SystemExit("two --rows give the same scene, method and seed: " + ", ".join(
            f"{k[0]} {k[1]} seed {k[2]}" for k in dict.fromkeys(k for k in keys if keys.count(k) > 1)))
    rows.sort(key=lambda r: (r["scene"], r["method"] != CANDIDATE, r["method"], r["seed"]))
    means = []
    for scene, method in dict.fromkeys((r["scene"], r["method"]) for r in rows):
        found = [r for r in rows if (r["scene"], r["method"]) == (scene, method)]
        mean = seed_means(found)  # the seed column itself averaged too: replaced by the seeds' list
        means.append({"scene": scene, "method": method, **mean,
                      "seed": "mean of " + ", ".join(str(r["seed"]) for r in found)})
    verdicts = {scene: comparisons(rows, scene) for scene in args.scenes}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "results.json", json.dumps({"rows": rows, "means": means, "comparisons": verdicts},
                                                            indent=2))
    command = " ".join(f"--rows {seed}:{method}={path}" for seed, method, path in args.rows)
    lines = [f"# {CANDIDATE} against the {REFERENCE} on several seeds of the paper tables", "",
             f"Command: `python benchmarks/studies/method_seeds.py {command} --out {args.out}` (reads the tables of "
             "`benchmarks/eval_tables.py --seed SEED`; trains nothing). Per-view means over the test views for "
             "PSNR, the Spearman columns, AUSE and abs-rel; intervals pooled over their SCORE points, relative "
             "to the depth.", "", *table(rows + means), ""]
    for scene, verdict in verdicts.items():
        if not verdict:
            continue
        for target, columns in TARGETS.items():
            parts = [f"{name} {v['candidate']:.4g} against {v['reference']:.4g}: "
                     f"{'met' if v['met_on_means'] else 'not met'} on the means, on {v['seeds_met']} of "
                     f"{len(verdict['seeds'])} seeds" for name in columns for v in [verdict[name]]]
            lines.append(f"- {scene}, issue 36 target {target}: " + "; ".join(parts))
    atomic_write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
