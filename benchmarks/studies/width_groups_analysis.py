"""Are the narrow depth bands honest? Coverage by width, and a level map per width bin (decides nothing).

A planner acts on the narrow bands. Pooled coverage can hold while the narrowest bands miss and
the widest over-cover. Part 1 reads, from ``stochastic-fields eval`` on the paper split's validation
photos, the coverage of the narrowest and the widest third of the 95% bands (``metrics.
interval_sharpness``' width groups; cross-fitted as eval scores them). Part 2 asks whether a level map
per bin of the predicted relative width (Mondrian calibration on the std itself: the calibration
renders' terciles of c / d, c today's std sqrt(sigma^2 + (beta e)^2 + (rho d)^2), one s(p) per bin)
evens the coverage over the groups without widening the bands, and whether a smooth compression of
the widths does (std_a = d (c/d)^a m^(1-a), m the calibration renders' median c/d, a fitted like rho
by their mean CRPS / depth). Part 2 refits the arms, today's one map, the binned maps and the power,
from the same calibration renders (every held-out point, the calibration
views) and scores them on the validation photos' SCORE points without cross-fitting, so its
coverages are optimistic alike for both arms; the comparison between them is the point.

    python benchmarks/studies/width_groups_analysis.py --run fern:12=RUN:EVAL ... \
        --out benchmarks/results/width_groups_analysis

RUN: a run folder of ``benchmarks/eval_tables.py --methods snerf_default --seed SEED`` with its
calibration (SCENE/snerf_default); EVAL: the folder of ``stochastic-fields eval --run RUN --views
VALIDATION --no-products`` (``tables_cap_study.validation_views``). One torch thread; resumable.
``--no-bins`` reads part 1 only, for runs of another split (a capture run and its ``eval`` of the
validation photos: ``benchmarks/results/width_groups_analysis/capture``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "benchmarks" / "studies"))

from stochastic_fields import metrics as M  # noqa: E402
from stochastic_fields.calibration import QuantileCalibration, relative_crps  # noqa: E402
from study_helpers import (interval_scores, labelled_run_parser, labelled_run_results, save_results,  # noqa: E402
                           todays_std_on_photos)

#: Bins of the predicted relative width in part 2 (the width groups' count).
WIDTH_BINS: int = M.WIDTH_GROUPS
#: Exponents a of part 2's third arm (1: today's std).
POWER_GRID: tuple[float, ...] = tuple(np.round(np.linspace(0.2, 1.0, 17), 3))


def eval_width_groups(eval_dir: Path) -> dict[str, float]:
    """Part 1: the pooled interval scores of an eval's metrics.json, the width groups' among them."""
    iv = json.loads((eval_dir / "metrics.json").read_text())["pooled"]["depth_intervals"]
    return {k: float(v) for k, v in iv.items()}


def binned_maps(run: Path, scene: str) -> dict:
    """Part 2 for one run: today's one map and the maps per width bin, both fitted on the run's
    calibration renders, scored on the validation photos' SCORE points."""
    base = todays_std_on_photos(run, scene)
    renders, one, c_cal, keep = base["renders"], base["today"], base["c_cal"], base["keep"]
    gt, pred, c = base["render"]["gt"][keep], base["render"]["depth_mean"][keep], base["c"][keep]
    edges = np.quantile(c_cal / renders["depth"], np.linspace(0.0, 1.0, WIDTH_BINS + 1)[1:-1])
    cal_bin, val_bin = np.searchsorted(edges, c_cal / renders["depth"]), np.searchsorted(edges, c / pred)
    maps = [QuantileCalibration.fit(renders["abs_err"][cal_bin == b] / c_cal[cal_bin == b], quantity="depth_std")
            for b in range(WIDTH_BINS)]

    def binned(t: np.ndarray) -> np.ndarray:
        out = np.zeros((gt.size, np.size(t)))
        for b, m in enumerate(maps):
            i = val_bin == b
            out[i] = M.gaussian_quantiles(pred[i], m.std_scale * c[i], t, m.relative_scale)
        return out

    # a power of the relative width: std_a = d (c / d)^a m^(1 - a), m the calibration renders' median c / d, so a < 1
    # narrows the spread of the widths about m; a fitted by the mean CRPS / depth of the calibration renders
    m_cal = float(np.median(c_cal / renders["depth"]))

    def powered(c_: np.ndarray, d_: np.ndarray, a: float) -> np.ndarray:
        return d_ * (c_ / d_) ** a * m_cal ** (1.0 - a)

    a = float(min(POWER_GRID, key=lambda a_: relative_crps(renders["abs_err"], powered(c_cal, renders["depth"], a_),
                                                           renders["depth"], 0.0)))
    power = QuantileCalibration.fit(renders["abs_err"] / powered(c_cal, renders["depth"], a), quantity="depth_std")
    c_pow = powered(c, pred, a)
    return {"points": int(gt.size), "calibration_points": int(renders["abs_err"].size), "power": a,
            "bin_edges": edges.tolist(), "validation_share_per_bin": (np.bincount(val_bin, minlength=WIDTH_BINS)
                                                                      / gt.size).tolist(),
            "bin_scale_68": [m.std_scale for m in maps], "bin_scale_95": [float(m.scale_at(0.95)) for m in maps],
            "one map": interval_scores(M.interval_sharpness(
                gt, lambda t: M.gaussian_quantiles(pred, one.std_scale * c, t, one.relative_scale))),
            "maps per width bin": interval_scores(M.interval_sharpness(gt, binned)),
            "a power of the width": interval_scores(M.interval_sharpness(
                gt, lambda t: M.gaussian_quantiles(pred, power.std_scale * c_pow, t, power.relative_scale)))}


def mean_over(runs: list[dict], key: str) -> dict[str, float]:
    return {k: float(np.mean([r[key][k] for r in runs])) for k in runs[0][key]}


def report(results: dict[str, dict]) -> str:
    scenes = sorted({label.split(":")[0] for label in results})
    lines = ["# Are the narrow depth bands honest?", "",
             "Command: " + " ".join(["python benchmarks/studies/width_groups_analysis.py"] + sys.argv[1:]), "",
             "## Part 1: eval's width groups (cross-fitted; validation photos; mean over the runs)", "",
             "| scene | runs | cov 68 / 95 | narrowest third: cov 68 / 95, largest 95% half-width | widest third: cov 68 / 95 "
             "| median 95% half-width |", "|---|---|---|---|---|---|"]
    for scene in scenes:
        runs = [r["eval"] for label, r in results.items() if label.startswith(scene + ":")]
        m = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        lines.append(f"| {scene} | {len(runs)} | {100 * m['coverage_68']:.1f} / {100 * m['coverage_95']:.1f} | "
                     f"{100 * m['coverage_68_narrowest_third']:.1f} / {100 * m['coverage_95_narrowest_third']:.1f}, "
                     f"{100 * m['halfwidth_95_narrowest_third_max']:.1f}% | {100 * m['coverage_68_widest_third']:.1f} / "
                     f"{100 * m['coverage_95_widest_third']:.1f} | {100 * m['halfwidth_median_95']:.1f}% |")
    if not any("bins" in r for r in results.values()):
        return "\n".join(lines) + "\n"
    lines += ["", "## Part 2: one map against a map per width bin (same calibration renders; not cross-fitted)", "",
              "| scene | maps | cov 50 / 68 / 90 / 95 / 99 | narrowest / middle / widest third, cov 68 | "
              "narrowest / middle / widest third, cov 95 | median 95% half-width | IS95 / depth | CRPS / depth |",
              "|---|---|---|---|---|---|---|---|"]
    for scene in scenes:
        runs = [r["bins"] for label, r in results.items() if label.startswith(scene + ":") and "bins" in r]
        if not runs:
            continue
        for arm in ("one map", "maps per width bin", "a power of the width"):
            m = mean_over(runs, arm)
            cov = " / ".join(f"{100 * m[f'coverage_{n}']:.1f}" for n in ("50", "68", "90", "95", "99"))
            thirds = [" / ".join(f"{100 * m[f'coverage_{p}_{g}_third']:.1f}" for g in ("narrowest", "middle", "widest"))
                      for p in ("68", "95")]
            lines.append(f"| {scene} | {arm} | {cov} | {thirds[0]} | {thirds[1]} | {100 * m['halfwidth_median_95']:.1f}% | "
                         f"{m['interval_score_95']:.3f} | {m['crps']:.4f} |")
    fitted = [f"{label} {r['bins']['power']:g}" for label, r in results.items() if "power" in r.get("bins", {})]
    if fitted:
        lines += ["", "The power a fitted on each run's calibration renders: " + ", ".join(fitted) + "."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = labelled_run_parser(__doc__, "SCENE:SEED=RUN:EVAL")
    p.add_argument("--no-bins", action="store_true", help="part 1 only (no renders)")
    args, runs, results = labelled_run_results(p, argv, folders=2)
    for label, (run, eval_dir) in runs:
        entry = results.setdefault(label, {})
        entry["eval"] = eval_width_groups(eval_dir)
        if not args.no_bins and "bins" not in entry:  # resumable: a finished run is read back
            entry["bins"] = binned_maps(run, label.split(":")[0])
        save_results(args.out, results)
        print(f"{label}: done")
    (args.out / "study.md").write_text(report(results))
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
