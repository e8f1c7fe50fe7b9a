"""Study 23: the finest grid level's cell cap on a capture, judged by its rule.

The rows are two runs of the capture benchmark (``benchmarks/capture_quality.py``, S-NeRF, seed 1,
the two rows of a scene side by side), today's cap and the candidate's::

    OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --seed 1 --marks 0.5 1 \\
        --out benchmarks/results/grid_cells_study/cells_2M --work runs/grid_cells/cells_2M
    OMP_NUM_THREADS=1 python benchmarks/capture_quality.py --methods snerf --seed 1 --marks 0.5 1 \\
        --out benchmarks/results/grid_cells_study/cells_8M --work runs/grid_cells/cells_8M \\
        --set field.grid_max_cells=8000000

This script reads their ``results.json`` and writes the table and the rule's verdict
(docs/studies.md, study 23; fixed before the rows ran) to ``--out``/README.md and ``verdict.json``.

    python benchmarks/studies/grid_cells_study.py --out benchmarks/results/grid_cells_study
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

#: The rule: PSNR gain (dB) at least, depth abs-rel loss at most, coverage within (points) of
#: nominal at 68 and 95%, training minutes at most.
MIN_PSNR_GAIN_DB, MAX_ABS_REL_LOSS, COVERAGE_POINTS, MAX_MINUTES = 0.2, 0.002, 5.0, 11.0
ROWS = {"today (2M cells)": "cells_2M", "candidate (8M cells)": "cells_8M"}


def last_scores(results: dict) -> dict[str, dict]:
    """Per scene: the end of the schedule's scores, steps and minutes, and the recalibrated intervals."""
    out = {}
    for record in results["records"]:
        last, cal = record["curve"][-1], record.get("calibrated") or {}
        # the study's rows were made when the benchmark probed its speed and fixed the steps
        out[record["scene"]] = {"steps": record.get("steps", record.get("iterations")),
                                "steps_per_s": record.get("steps_per_s", record.get("steps_per_s_probe")),
                                "minutes": last["minutes"], "psnr": last["psnr"], "ssim": last["ssim"],
                                "abs_rel": last["depth_abs_rel"], "coverage_68": cal.get("coverage_68"),
                                "coverage_95": cal.get("coverage_95"), "halfwidth_95": cal.get("halfwidth_median_95"),
                                "curve": [(c["minutes"], c["psnr"]) for c in record["curve"]]}
    return out


def verdict(today: dict, candidate: dict) -> dict:
    """Each scene's checks and whether the candidate passes on every scene."""
    scenes = {}
    for scene in sorted(set(today) & set(candidate)):
        a, b = today[scene], candidate[scene]
        checks = {
            "psnr_gain": b["psnr"] - a["psnr"] >= MIN_PSNR_GAIN_DB,
            "abs_rel": b["abs_rel"] <= a["abs_rel"] + MAX_ABS_REL_LOSS,
            "coverage": (b["coverage_68"] is not None
                         and abs(100 * b["coverage_68"] - 68.27) <= COVERAGE_POINTS
                         and abs(100 * b["coverage_95"] - 95.0) <= COVERAGE_POINTS),
            "minutes": b["minutes"] <= MAX_MINUTES,
        }
        scenes[scene] = {"psnr_gain_db": b["psnr"] - a["psnr"], "abs_rel_change": b["abs_rel"] - a["abs_rel"],
                         "checks": checks, "passes": all(checks.values())}
    return {"scenes": scenes, "taken": {"fern", "flower"} <= set(scenes) and all(s["passes"] for s in scenes.values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/grid_cells_study"))
    args = ap.parse_args()
    rows = {label: last_scores(json.loads((args.out / folder / "results.json").read_text()))
            for label, folder in ROWS.items()}
    (today_label, today), (cand_label, candidate) = rows.items()
    v = verdict(today, candidate)
    (args.out / "verdict.json").write_text(json.dumps({"rows": rows, "verdict": v}, indent=2) + "\n")
    lines = ["# Study 23: the finest grid level's cell cap on a capture", "",
             "Rows: `benchmarks/capture_quality.py` (S-NeRF default, capture split, seed 1, the probed "
             "ten-minute schedule, one thread, the two rows of a scene side by side); commands in "
             "`benchmarks/studies/grid_cells_study.py`, each row's own README in its folder. Verdict: "
             "`python benchmarks/studies/grid_cells_study.py --out benchmarks/results/grid_cells_study`.", "",
             "| scene | row | steps (steps/s of the speed probe) | minutes | PSNR dB (at half the schedule) | SSIM | depth abs-rel | "
             "cov 68 / 95 | median 95% half-width |", "|" + "---|" * 9]
    for scene in sorted(today):
        for label, scores in rows.items():
            s = scores.get(scene)
            if s is None:
                continue
            half = s["curve"][0] if len(s["curve"]) > 1 else None
            half_text = f" ({half[1]:.2f} at {half[0]:.1f} min)" if half else ""
            cov = (f"{100 * s['coverage_68']:.1f} / {100 * s['coverage_95']:.1f}" if s["coverage_68"] is not None else "-")
            width = f"{100 * s['halfwidth_95']:.1f}%" if s["halfwidth_95"] is not None else "-"
            lines.append(f"| {scene} | {label} | {s['steps']} ({s['steps_per_s']:.2f}) | {s['minutes']:.1f} | "
                         f"{s['psnr']:.2f}{half_text} | {s['ssim']:.3f} | {s['abs_rel']:.4f} | {cov} | {width} |")
    lines += ["", f"Rule (fixed before the rows): the candidate is taken if on both scenes its PSNR is at least "
              f"{MIN_PSNR_GAIN_DB} dB above today's, its depth abs-rel at most {MAX_ABS_REL_LOSS} above, its 68% "
              f"and 95% coverage within {COVERAGE_POINTS:g} points of nominal and its training at most "
              f"{MAX_MINUTES:g} minutes.", ""]
    for scene, s in v["scenes"].items():
        failed = [k for k, ok in s["checks"].items() if not ok]
        lines.append(f"- {scene}: PSNR {s['psnr_gain_db']:+.2f} dB, abs-rel {s['abs_rel_change']:+.4f}: "
                     + ("passes" if s["passes"] else "fails " + ", ".join(failed)))
    for scene in sorted({"fern", "flower"} - set(v["scenes"])):
        lines.append(f"- {scene}: no row of both caps (the rule needs it on every scene)")
    lines += ["", f"**{'Taken' if v['taken'] else 'Not taken'}.**", ""]
    (args.out / "README.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
