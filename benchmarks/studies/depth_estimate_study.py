"""Study 50: the depth map's point estimate, the predictive mixture's median instead of its mean
(docs/studies.md, "Study 50").

``render.depth_estimate`` "median" renders each pixel's depth as F^-1(1/2) of its predictive
mixture (``termination.median_depth``) instead of the mean over the K trajectories' expected
termination depths. It changes no training: each trained run is scored twice, once per arm, by the
product's own path. For each arm the run's files are copied to ``--work/NAME/ARM`` with
``render.depth_estimate`` set in its config.json, recalibrated as ``train`` does
(``calibration.calibrate_run``: the map is fitted on the errors of the estimate that arm renders),
and its photos no training and no map saw are scored by ``evaluation.evaluate`` with that
calibration (the capture split's validation photos; the paper split's held-out photos the tables do
not score, ``relative_floor_study.scored_views``), at their SCORE capture points, as ``eval`` does.

    OMP_NUM_THREADS=1 python benchmarks/studies/depth_estimate_study.py \\
        --run capture/fern/s42=RUN --run capture/flower/s42=RUN --run paper/fern/s42=RUN ... \\
        --work runs/depth_estimate_study --out benchmarks/results/depth_estimate_study

Each (run, arm) is written to ``--work`` as it finishes and read back on a re-run (resumes);
``--out`` gets results.json and README.md (rows, group means and the rule's verdict).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from stochastic_fields.calibration import calibrate_run
from stochastic_fields.capture_points import score_sparse_depth
from stochastic_fields.evaluation import evaluate
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.trainer import load_trained_model

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from relative_floor_study import scored_views  # noqa: E402

ARMS: tuple[str, ...] = ("mean", "median")
#: The files of a trained run an arm needs (the calibration is re-fitted per arm).
RUN_FILES: tuple[str, ...] = ("config.json", "checkpoint.pt")
LEVELS: tuple[str, ...] = ("50", "68", "90", "95")
NOMINAL: dict[str, float] = {"50": 50.0, "68": 68.27, "90": 90.0, "95": 95.0}
#: The rule's limits (docs/studies.md, "Study 50"; written before any row).
ABS_REL_RISE: float = 0.002
LEVEL_TOLERANCE: float = 5.0
BAND_GROWTH_POINTS: float = 0.5
CRPS_RISE: float = 0.01
SPEARMAN_FALL: float = 0.02
RENDER_COST: float = 1.15


def arm_dir(work: Path, name: str, arm: str, run: Path) -> Path:
    """The arm's copy of ``run`` with ``render.depth_estimate`` = ``arm`` in its config.json."""
    out = work / name / arm
    out.mkdir(parents=True, exist_ok=True)
    for f in RUN_FILES:
        if not (out / f).exists():
            shutil.copy2(run / f, out / f)
    cfg = json.loads((run / "config.json").read_text())
    cfg.setdefault("render", {})["depth_estimate"] = arm
    atomic_write_text(out / "config.json", json.dumps(cfg, indent=2))
    return out


def score_arm(work: Path, name: str, arm: str, run: Path) -> dict:
    record = work / name / arm / "record.json"
    if record.exists():
        return json.loads(record.read_text())
    run_dir = arm_dir(work, name, arm, run)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cfg, model, dataset = load_trained_model(run_dir)
    assert model.render_settings.depth_estimate == arm, "the arm's config.json did not reach the model"
    views = scored_views(dataset, cfg.data.split)
    t0 = time.perf_counter()
    calibration = calibrate_run(run_dir, model=model, dataset=dataset, progress=False)
    calibrate_s = time.perf_counter() - t0
    with torch.no_grad():
        result = evaluate(model, dataset, run_dir / "eval", views=views, sparse_depth=score_sparse_depth(dataset, views),
                          product_views=0, progress=False, calibration=calibration)
    pooled, summary = result["pooled"], result["summary"]
    iv = pooled["depth_intervals"]
    out = {"run": str(run), "arm": arm, "views": views, "psnr": summary["psnr"]["mean"],
           "abs_rel": pooled["depth"]["abs_rel"], "points": pooled["depth"]["num_used"],
           "spearman": summary["depth/spearman"]["mean"],
           **{f"coverage_{p}": 100.0 * iv[f"coverage_{p}"] for p in LEVELS + ("99",)},
           "band_95": 100.0 * iv["halfwidth_median_95"], "is_95": iv["interval_score_95"], "crps": iv["crps"],
           "render_s_per_view": result["render_s_per_view"], "calibrate_s": calibrate_s}
    atomic_write_text(record, json.dumps(out, indent=2))
    return out


def group_of(name: str) -> str:
    """'capture/fern/s42' -> 'capture/fern'."""
    return "/".join(name.split("/")[:2])


def means(rows: dict) -> dict:
    """{group: {arm: {metric: mean over the group's runs}}}."""
    groups: dict = {}
    for name, arms in rows.items():
        groups.setdefault(group_of(name), []).append(arms)
    record = next(iter(rows.values()))["mean"]
    keys = [k for k, v in record.items() if isinstance(v, float)]
    return {g: {arm: {k: float(np.mean([r[arm][k] for r in runs])) for k in keys} for arm in ARMS}
            for g, runs in groups.items()}


def level_ok(value: float, today: float, nominal: float) -> bool:
    """Within the tolerance of nominal, or (where today's misses) no farther from nominal than today's."""
    return abs(value - nominal) <= LEVEL_TOLERANCE or abs(value - nominal) <= abs(today - nominal)


def verdict(groups: dict) -> dict:
    """The rule (module doc, docs/studies.md) on the group means: every check per group, then the taken flag."""
    fails = []
    for g, arms in groups.items():
        old, new = arms["mean"], arms["median"]
        if new["abs_rel"] > old["abs_rel"] + ABS_REL_RISE:
            fails.append(f"{g}: abs-rel {old['abs_rel']:.4f} -> {new['abs_rel']:.4f}")
        for p in LEVELS:
            if not level_ok(new[f"coverage_{p}"], old[f"coverage_{p}"], NOMINAL[p]):
                fails.append(f"{g}: {p}% level {new[f'coverage_{p}']:.1f}")
        if new["band_95"] > old["band_95"] + BAND_GROWTH_POINTS:
            fails.append(f"{g}: median 95% band {old['band_95']:.1f} -> {new['band_95']:.1f}%")
        if new["is_95"] > old["is_95"]:
            fails.append(f"{g}: IS95 {old['is_95']:.3f} -> {new['is_95']:.3f}")
        if new["crps"] > old["crps"] * (1.0 + CRPS_RISE):
            fails.append(f"{g}: CRPS {old['crps']:.4f} -> {new['crps']:.4f}")
        if new["spearman"] < old["spearman"] - SPEARMAN_FALL:
            fails.append(f"{g}: depth Spearman {old['spearman']:.3f} -> {new['spearman']:.3f}")
        if new["render_s_per_view"] > RENDER_COST * old["render_s_per_view"]:
            fails.append(f"{g}: render {new['render_s_per_view'] / old['render_s_per_view']:.2f}x")
    mean_old = float(np.mean([a["mean"]["abs_rel"] for a in groups.values()]))
    mean_new = float(np.mean([a["median"]["abs_rel"] for a in groups.values()]))
    if mean_new >= mean_old:
        fails.append(f"mean abs-rel over the groups does not fall ({mean_old:.4f} -> {mean_new:.4f})")
    return {"taken": not fails, "fails": fails, "mean_abs_rel": [mean_old, mean_new]}


def markdown(rows: dict, groups: dict, decision: dict, command: str) -> str:
    head = ("| run | estimate | PSNR | abs-rel | 50 / 68 / 90 / 95 / 99% | median 95% half-width | IS95 / depth | "
            "CRPS / depth | depth Spearman | render s / view |")
    lines = ["# Study 50: the depth map's point estimate, the predictive mixture's median against its mean", "",
             "Command:", "", f"    {command}", "", head, "|---|---|---|---|---|---|---|---|---|---|"]

    def row(label, arm, r):
        cov = " / ".join(f"{r[f'coverage_{p}']:.1f}" for p in LEVELS + ("99",))
        return (f"| {label} | {arm} | {r['psnr']:.2f} | {r['abs_rel']:.4f} | {cov} | {r['band_95']:.1f}% | "
                f"{r['is_95']:.3f} | {r['crps']:.4f} | {r['spearman']:.3f} | {r['render_s_per_view']:.2f} |")
    for name, arms in rows.items():
        lines += [row(name, arm, arms[arm]) for arm in ARMS]
    lines += ["", "Means per group (the rule reads these):", "", head, "|---|---|---|---|---|---|---|---|---|---|"]
    for g, arms in groups.items():
        lines += [row(g, arm, arms[arm]) for arm in ARMS]
    lines += ["", f"Verdict: **{'taken' if decision['taken'] else 'not taken'}**" +
              ("" if decision["taken"] else " (" + "; ".join(decision["fails"]) + ")") +
              f"; mean abs-rel over the groups {decision['mean_abs_rel'][0]:.4f} -> {decision['mean_abs_rel'][1]:.4f}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="append", required=True, metavar="SPLIT/SCENE/SEED=RUN_DIR")
    ap.add_argument("--work", type=Path, default=Path("runs/depth_estimate_study"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    rows = {}
    for item in args.run:
        name, sep, path = item.partition("=")
        if not sep or name.count("/") != 2:
            ap.error(f"--run expects SPLIT/SCENE/SEED=RUN_DIR, got {item!r}")
        rows[name] = {arm: score_arm(args.work, name, arm, Path(path)) for arm in ARMS}
        print(name, {arm: (round(r["abs_rel"], 4), round(r["band_95"], 1), round(r["is_95"], 3)) for arm, r in rows[name].items()},
              flush=True)
    groups = means(rows)
    decision = verdict(groups)
    command = "OMP_NUM_THREADS=1 python benchmarks/studies/depth_estimate_study.py " + \
        " ".join(f"--run {r}" for r in args.run) + f" --work {args.work} --out {args.out}"
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "results.json", json.dumps({"rows": rows, "groups": groups, "verdict": decision}, indent=2))
    atomic_write_text(args.out / "README.md", markdown(rows, groups, decision, command))
    print(json.dumps(decision, indent=1))


if __name__ == "__main__":
    main()
