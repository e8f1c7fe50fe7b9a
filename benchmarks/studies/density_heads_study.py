"""Study 52: density heads (``field.density_heads``) at the paper split, judged by its rule.

The rows are the tables' S-NeRF (default) row (``benchmarks/eval_tables.py``, paper split, fern and
flower) on seeds 0-2: today's (one head, study 51's ``tables_levels_5``) and the candidate's, the
same command with ``--set field.density_heads=M``::

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes fern flower --methods snerf_default \\
        --seed S --no-timing --quiet --set field.density_heads=4 --out runs/heads_4/seed_S

This script reads each side's ``tables.json`` (the columns of ``method_seeds.py``: the tables' own
per-view means and pooled intervals), takes the means over the seeds and writes the table and the
rule's verdict (docs/studies.md, fixed before any candidate row ran) to ``--out``/README.md and
``verdict.json``::

    python benchmarks/studies/density_heads_study.py \\
        --today benchmarks/results/grid_levels_study/tables_levels_5/seed_{0,1,2}/tables.json \\
        --candidate runs/heads_4/seed_{0,1,2}/tables.json --label "4 heads" --out benchmarks/results/density_heads_study/paper_verdict
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stochastic_fields.io_utils import atomic_write_text

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from method_seeds import COLUMNS  # noqa: E402
from study_helpers import read_tables_method, seed_means  # noqa: E402

METHOD = "snerf_default"
SCENES = ("fern", "flower")
#: The rule (written before any candidate row ran). Flower is the scene of issue 36's target 4.
MIN_FLOWER_RANKING_GAIN = 0.03
MAX_FERN_RANKING_LOSS = 0.01
MAX_PSNR_LOSS_DB = 0.2
MAX_ABS_REL_LOSS = 0.005
COVERAGE_POINTS = 5.0
LEVELS = (50, 68, 90, 95)
MAX_HALFWIDTH_GROWTH_POINTS = 1.0
MAX_SCORE_GROWTH = 0.05  # IS95 and CRPS: relative growth


def read_side(paths: list[Path]) -> dict[str, dict]:
    """{scene: the means over ``paths``' seeds of every column, with each seed's own under 'seeds'}."""
    per_seed = [read_tables_method(p, METHOD, lambda m: {name: float(read(m)) for name, _, read, *_ in COLUMNS},
                                   f"{METHOD}'s depth intervals") for p in paths]
    out = {}
    for scene in SCENES:
        rows = [s[scene] for s in per_seed if scene in s]
        if len(rows) != len(paths):
            raise SystemExit(f"{scene}: {len(rows)} of {len(paths)} tables.json hold a {METHOD} row")
        out[scene] = {**seed_means(rows), "seeds": rows}
    return out


def verdict(today: dict[str, dict], candidate: dict[str, dict]) -> dict:
    """The rule's checks on the seeds' means: each failed one as a line; taken if none failed."""
    failed = []
    gain = candidate["flower"]["depth_spearman"] - today["flower"]["depth_spearman"]
    if gain < MIN_FLOWER_RANKING_GAIN:
        failed.append(f"flower depth ranking {gain:+.3f} (at least +{MIN_FLOWER_RANKING_GAIN})")
    loss = today["fern"]["depth_spearman"] - candidate["fern"]["depth_spearman"]
    if loss > MAX_FERN_RANKING_LOSS:
        failed.append(f"fern depth ranking {-loss:+.3f} (falls at most {MAX_FERN_RANKING_LOSS})")
    for scene in SCENES:
        t, c = today[scene], candidate[scene]
        if t["psnr"] - c["psnr"] > MAX_PSNR_LOSS_DB:
            failed.append(f"{scene} PSNR {c['psnr'] - t['psnr']:+.2f} dB (falls at most {MAX_PSNR_LOSS_DB})")
        if c["depth_abs_rel"] - t["depth_abs_rel"] > MAX_ABS_REL_LOSS:
            failed.append(f"{scene} abs-rel {c['depth_abs_rel'] - t['depth_abs_rel']:+.4f} (rises at most {MAX_ABS_REL_LOSS})")
        for p in LEVELS:
            off_c, off_t = abs(c[f"coverage_{p}"] - p), abs(t[f"coverage_{p}"] - p)
            if off_c > COVERAGE_POINTS and off_c > off_t:
                failed.append(f"{scene} {p}% coverage {c[f'coverage_{p}']:.1f} (within {COVERAGE_POINTS:g} points, "
                              "or no farther than today's)")
        growth = c["halfwidth_median_95"] - t["halfwidth_median_95"]
        if growth > MAX_HALFWIDTH_GROWTH_POINTS:
            failed.append(f"{scene} median 95% half-width {growth:+.1f} points (grows at most {MAX_HALFWIDTH_GROWTH_POINTS:g})")
        for name in ("interval_score_95", "crps"):
            if c[name] > (1 + MAX_SCORE_GROWTH) * t[name]:
                failed.append(f"{scene} {name} x{c[name] / t[name]:.3f} (at most x{1 + MAX_SCORE_GROWTH:g})")
    return {"taken": not failed, "failed": failed}


def table(sides: dict[str, dict[str, dict]]) -> list[str]:
    head = ["scene", "setting", *(h for _, h, *_ in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene in SCENES:
        for label, side in sides.items():
            row = side[scene]
            lines.append("| " + " | ".join([scene, label, *(fmt.format(row[name]) for name, _, _, fmt, _ in COLUMNS)]) + " |")
    return lines


def seed_table(sides: dict[str, dict[str, dict]]) -> list[str]:
    lines = ["| scene | setting | seed | PSNR dB | depth abs-rel | depth Spearman | median 95% hw | IS95 / depth |",
             "|---|---|---|---|---|---|---|---|"]
    for scene in SCENES:
        for label, side in sides.items():
            for i, r in enumerate(side[scene]["seeds"]):
                lines.append(f"| {scene} | {label} | {i} | {r['psnr']:.2f} | {r['depth_abs_rel']:.4f} | "
                             f"{r['depth_spearman']:.3f} | {r['halfwidth_median_95']:.1f}% | {r['interval_score_95']:.3f} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--today", type=Path, nargs="+", required=True, help="today's tables.json, one per seed")
    ap.add_argument("--candidate", type=Path, nargs="+", required=True, help="the candidate's, the same seeds in order")
    ap.add_argument("--label", default="candidate", help="the candidate's name in the table")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if len(args.today) != len(args.candidate):
        ap.error(f"--today gives {len(args.today)} seeds, --candidate {len(args.candidate)}")
    today, candidate = read_side(args.today), read_side(args.candidate)
    result = verdict(today, candidate)
    sides = {"today (1 head)": today, args.label: candidate}
    command = ("python benchmarks/studies/density_heads_study.py --today " + " ".join(map(str, args.today))
               + " --candidate " + " ".join(map(str, args.candidate)) + f" --label '{args.label}' --out {args.out}")
    lines = [f"# Study 52: density heads at the paper split ({args.label})", "", f"Command: `{command}`", "",
             f"Means of {len(args.today)} seeds (the tables' S-NeRF (default) row; per-view means for PSNR, the "
             "rankings and abs-rel, intervals pooled over the SCORE points, relative to the depth):", "",
             *table(sides), "", "Each seed:", "", *seed_table(sides), "",
             f"Verdict: {'taken' if result['taken'] else 'not taken'}."]
    lines += [f"- failed: {f}" for f in result["failed"]]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "verdict.json", json.dumps({"today": today, "candidate": candidate, **result}, indent=2))
    atomic_write_text(args.out / "README.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
