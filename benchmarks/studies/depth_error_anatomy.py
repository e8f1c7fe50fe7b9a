"""Where S-NeRF's large depth errors are, and what each kind of interval makes of them (renders only;
decides nothing).

The depth intervals hold, but their 95% bands stay wider than issue 36's 15% of the depth on most
real runs. This measures what the wide tails are made of, on photos no training saw:

1. **Size and side.** The share of points whose relative error |d - d*| / d* exceeds 5, 15 and 30%,
   and of those the share rendered IN FRONT of the truth (d < d*); per third of the true depths;
   how many depths render at the view's near bound (``NEAR_BOUND_FACTOR``), against how many true
   depths lie there.
2. **Occlusion edges.** Each point's ray and its 8 neighbours ``NEIGHBOUR_RADIUS_PX`` pixels away
   (a 3 x 3 stencil) are rendered; Delta = max - min of their 9 rendered depths. A large error
   "at an edge" has Delta >= half its error: a ray that close renders a surface that far away.
3. **What an edge term would buy.** The intervals of a symmetric level map (s(p) = Q_p(|err| / s))
   on s = the run's total std sqrt(sigma^2 + (beta e)^2 + (rho d)^2) and on
   sqrt(s^2 + (gamma Delta)^2) for ``EDGE_WEIGHTS``, each map fitted OUT OF FOLD on the same points
   (the run's five cross-fitting folds): the same footing for every row, the run's own map aside.
4. **Which side the calibration sees.** The product's intervals (the run's cross-fitted fold maps,
   as ``eval`` scores them) against intervals from the SIGNED standardised errors of the same
   calibration renders: [d + Q_{(1-p)/2}(t) s, d + Q_{(1+p)/2}(t) s], t = (d* - d) / s, each fold's
   quantiles from the renders outside its blocks (as the fold maps are fitted).

Points: the SCORE capture points (``capture_points.score_sparse_depth``) seen from photos no
training saw and no table scores (``run_views``: on the paper split the held-out photos beside the
tables' four; on the capture split its validation photos). Rays through the points' exact pixel positions (``calibration.render_at_points``,
render seed 0), opacity > 0.5. Every interval is scored by ``metrics.interval_sharpness``.

    python benchmarks/studies/depth_error_anatomy.py --run paper/fern=RUN --run capture/flower=RUN ... --out OUT

``--run LABEL=FOLDER``: a trained, calibrated S-NeRF run of a scene with SfM points (LABEL names the
row). Each run's record (with every point's signed error) is kept in ``--work`` (default OUT/runs;
resumable); OUT/README.md, OUT/anatomy.json and OUT/signed_errors.png are rewritten after each.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

#: How far (pixels) the neighbours of a point's ray are (the 3 x 3 stencil's step).
NEIGHBOUR_RADIUS_PX: float = 2.0
#: Relative-error sizes that count as large.
ERROR_SIZES: tuple[float, ...] = (0.05, 0.15, 0.30)
#: The size the edge and tercile columns use.
LARGE_ERROR: float = 0.15
#: A rendered depth "at the near bound": below this multiple of the view's near bound.
NEAR_BOUND_FACTOR: float = 1.25
#: The size of an in-front error whose share at the near bound is reported.
FAR_ERROR: float = 0.30
#: Weights gamma of the edge term in section 3.
EDGE_WEIGHTS: tuple[float, ...] = (0.25, 0.5, 1.0)
#: Render seed (as the tables).
SEED: int = 0


def neighbour_offsets(radius: float) -> list[tuple[float, float]]:
    """The 8 (du, dv) pixel offsets of the 3 x 3 stencil of step ``radius`` around a point."""
    return [(du * radius, dv * radius) for dv in (-1, 0, 1) for du in (-1, 0, 1) if (du, dv) != (0, 0)]


def error_sides(gt: np.ndarray, pred: np.ndarray, sizes=ERROR_SIZES, large: float = LARGE_ERROR) -> dict:
    """Size and side of the relative errors (pred - gt) / gt of gt, pred [N] (> 0): per size, the
    share of points beyond it and the share of those in front (pred < gt); per third of the true
    depths (nearest first), the median signed error, the share beyond ``large`` and its share in front."""
    gt, pred = np.asarray(gt, dtype=np.float64), np.asarray(pred, dtype=np.float64)
    rel = (pred - gt) / gt
    big = np.abs(rel)

    def front(mask):
        return float(np.mean(rel[mask] < 0)) if mask.any() else float("nan")

    out = {"num_points": int(gt.size), "median_abs": float(np.median(big)), "p90_abs": float(np.quantile(big, 0.9)),
           "sizes": [{"size": s, "share": float(np.mean(big > s)), "in_front": front(big > s)} for s in sizes]}
    edges = np.quantile(gt, [1 / 3, 2 / 3])
    third = np.digitize(gt, edges, right=True)
    out["thirds"] = [{"median_signed": float(np.median(rel[third == k])), "share_large": float(np.mean(big[third == k] > large)),
                      "in_front": front((third == k) & (big > large))} for k in range(3)]
    return out


def front_depth_ratio(signed_rel, large: float = LARGE_ERROR) -> float:
    """Median rendered / true depth (1 + rel) over the errors ``signed_rel`` [N] ((d - d*) / d*)
    beyond ``large`` in front of the truth; nan without any."""
    rel = np.asarray(signed_rel, dtype=np.float64)
    front = rel[rel < -large]
    return float(np.median(1.0 + front)) if front.size else float("nan")


def near_bound_shares(gt: np.ndarray, pred: np.ndarray, near: np.ndarray, factor: float = NEAR_BOUND_FACTOR,
                      size: float = FAR_ERROR) -> dict:
    """How many depths render at the near bound (pred < ``factor`` x the view's ``near`` [N]): the
    share of the in-front errors beyond ``size`` (relative), of every point, and of the true depths
    that lie there (what the scene puts there)."""
    gt, pred, near = (np.asarray(a, dtype=np.float64) for a in (gt, pred, near))
    at_near = pred < factor * near
    front = (pred - gt) / gt < -size
    return {"front_errors": float(np.mean(at_near[front])) if front.any() else float("nan"),
            "rendered": float(np.mean(at_near)), "true": float(np.mean(gt < factor * near))}


def edge_shares(gt: np.ndarray, pred: np.ndarray, delta: np.ndarray, std: np.ndarray, large: float = LARGE_ERROR) -> dict:
    """Where the large errors are against the neighbours' depth range ``delta`` [N]: the share of
    errors beyond ``large`` (relative) with delta >= half the error, the share of the other points
    with delta / gt > ``large``, and the Spearman of |error| with delta and with the run's ``std``."""
    from scipy.stats import spearmanr

    gt, pred, delta, std = (np.asarray(a, dtype=np.float64) for a in (gt, pred, delta, std))
    err = np.abs(pred - gt)
    big = err / gt > large
    return {"large_at_edge": float(np.mean(delta[big] >= 0.5 * err[big])) if big.any() else float("nan"),
            "others_wide_range": float(np.mean(delta[~big] / gt[~big] > large)) if (~big).any() else float("nan"),
            "spearman_delta": float(spearmanr(err, delta)[0]), "spearman_std": float(spearmanr(err, std)[0])}


def out_of_fold_level_quantiles(pred: np.ndarray, abs_err: np.ndarray, std: np.ndarray, fold: np.ndarray):
    """The quantile function t [Q] -> [N, Q] of the symmetric level map fitted out of fold: point i of
    fold f gets q(t) = pred_i + sign(t - 1/2) Q_p(|err| / std over the points of the other folds) std_i,
    p = |2t - 1|. ``fold`` [N] >= 0; each fold needs points outside it."""
    pred, abs_err, std = (np.asarray(a, dtype=np.float64) for a in (pred, abs_err, std))
    fold = np.asarray(fold)

    def quantiles(levels):
        t = np.asarray(levels, dtype=np.float64).reshape(1, -1)
        out = np.zeros((pred.size, t.size))
        for f in np.unique(fold):
            i = fold == f
            z = np.quantile(abs_err[~i] / std[~i], np.abs(2.0 * t.reshape(-1) - 1.0))
            out[i] = pred[i, None] + np.sign(t - 0.5) * z[None, :] * std[i, None]
        return out

    return quantiles


def signed_fold_quantiles(pred: np.ndarray, std: np.ndarray, fold: np.ndarray, t_outside: dict):
    """The quantile function t [Q] -> [N, Q] from signed standardised calibration errors: point i of
    fold f gets pred_i + Q_t(t_outside[f]) std_i (``std`` [N]: each point's total std under its own
    fold's map; ``t_outside[f]``: the signed errors (true - rendered) / std of the calibration renders
    outside fold f's blocks)."""
    pred, std = np.asarray(pred, dtype=np.float64), np.asarray(std, dtype=np.float64)
    fold = np.asarray(fold)

    def quantiles(levels):
        t = np.asarray(levels, dtype=np.float64).reshape(-1)
        out = np.zeros((pred.size, t.size))
        for f, signed in t_outside.items():
            i = fold == f
            out[i] = pred[i, None] + np.quantile(signed, t)[None, :] * std[i, None]
        return out

    return quantiles


def interval_row(gt: np.ndarray, quantile_fn, abs_err: np.ndarray | None = None) -> dict:
    """``metrics.interval_sharpness`` of a quantile function (without its per-point widths), with the
    Spearman of the absolute errors ``abs_err`` [N] against the level-68.3% half-width (both in depth
    units, as the depth Spearman of the tables)."""
    from scipy.stats import spearmanr

    from stochastic_fields import metrics as M

    scores = M.interval_sharpness(gt, quantile_fn)
    half = scores.pop("halfwidth")
    out = {k: v for k, v in scores.items() if not isinstance(v, np.ndarray)}
    if abs_err is not None:
        lv = np.asarray(scores["levels"])
        width = half[:, int(np.argmin(np.abs(lv - 0.6827)))] * np.asarray(gt, dtype=np.float64)  # in depth units
        out["spearman"] = float(spearmanr(abs_err, width)[0])
    return out


def run_views(dataset, split: str) -> tuple[list[int], str]:
    """The photos scored here and their name: on the paper split (``split``), the held-out photos the
    tables do not score (``budget.select_views`` at the CPU budget picks the tables'); on any other
    split, its held-out photos (the capture split's validation photos)."""
    from stochastic_fields_bench.budget import BenchmarkSettings, select_views

    held_out = sorted(dataset.test_indices)
    if split == "paper":
        scored = set(select_views(held_out, BenchmarkSettings()))
        return [v for v in held_out if v not in scored], "held-out photos the tables do not score"
    return held_out, "validation photos"


def anatomy_of_run(folder: Path, *, radius: float = NEIGHBOUR_RADIUS_PX, seed: int = SEED) -> dict:
    """Sections 1-4 of the module doc for one trained, calibrated run."""
    import torch

    from stochastic_fields.calibration import cross_fitted_depth_quantiles, depth_calibration_renders, \
        load_run_calibration, render_at_points, training_view_terms_at_points
    from stochastic_fields.capture_points import block_keys, load_capture_points, score_sparse_depth
    from stochastic_fields.view_maps import OPACITY_MASK
    from stochastic_fields.trainer import load_trained_model

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cfg, model, dataset = load_trained_model(folder)
    calibration = load_run_calibration(folder)
    if calibration is None or calibration.depth is None or calibration.depth_folds is None:
        raise SystemExit(f"{folder}: no cross-fitted depth calibration (calibration.json with folds); run "
                         f"`stochastic-fields calibrate --run {folder}` first")
    views, which = run_views(dataset, cfg.data.split)
    sparse = score_sparse_depth(dataset, views)
    if sparse is None or not any(len(sd) for sd in sparse.values()):
        raise SystemExit(f"{folder}: its scene has no SCORE capture points in the {which} {views}")
    sparse = {v: sd for v, sd in sparse.items() if len(sd)}

    def render(points):
        return render_at_points(model, dataset.cameras, dataset.near, dataset.far, points,
                                generator=torch.Generator(device=next(model.parameters()).device).manual_seed(seed))

    centre = render(sparse)
    near_of_view = np.broadcast_to(np.asarray(dataset.near, dtype=np.float64).reshape(-1), (dataset.num_views,))
    near = np.concatenate([np.full(len(sd), near_of_view[v]) for v, sd in sparse.items()])
    ranges = [centre["depth_mean"]]
    for du, dv in neighbour_offsets(radius):
        moved = {v: replace(sd, uv=sd.uv + np.array([du, dv], dtype=sd.uv.dtype)) for v, sd in sparse.items()}
        ranges.append(render(moved)["depth_mean"])
    ranges = np.stack(ranges)
    delta = np.nanmax(ranges, axis=0) - np.nanmin(ranges, axis=0)
    capture = load_capture_points(dataset)
    index = np.concatenate([sd.point_index for sd in sparse.values()])
    maps, folds = calibration.depth, calibration.depth_folds
    rendered = np.where(np.isfinite(centre["depth_mean"]), centre["depth_mean"], centre["gt"])
    # the map's free-space and parallax terms at the same rendered points (the product's std), in one pass
    violation, parallax = training_view_terms_at_points(dataset.cameras, sparse, capture.xyz, centre["gt"], rendered,
                                                        calibration.training_depth, free_space=maps.free_space,
                                                        parallax=maps.parallax_weight > 0.0)
    keep = (centre["opacity"] > OPACITY_MASK) & np.isfinite(centre["depth_mean"]) & np.isfinite(delta) \
        & (centre["depth_std"] > 0)
    gt, pred, raw, delta = centre["gt"][keep], centre["depth_mean"][keep], centre["depth_std"][keep], delta[keep]
    near = near[keep]
    e = None if violation is None else violation[keep]
    angle = None if parallax is None else parallax[keep]
    keys = block_keys(capture.xyz, capture.xyz)
    fold = folds.fold_of(keys[index[keep]])
    if (fold < 0).any():
        raise SystemExit(f"{folder}: {int((fold < 0).sum())} SCORE points lie in no fold of its calibration")
    total = np.zeros_like(raw)  # each point's total std under its own fold's map (before the level map)
    for f, m in enumerate(folds.maps):
        i = fold == f
        total[i] = m.calibrated_std(raw[i], None if e is None else e[i], pred[i],
                                    parallax=None if angle is None else angle[i]) / m.std_scale
    abs_err = np.abs(pred - gt)
    product = cross_fitted_depth_quantiles(pred, raw, fold, folds, violation=e, parallax=angle)
    # the calibration renders, signed, as the run's map was fitted on them
    cal = depth_calibration_renders(model, dataset, seed=seed, points=calibration.points,
                                    free_space=calibration.training_depth if maps.free_space else None,
                                    parallax=calibration.training_depth if parallax is not None else None)
    cal_fold = folds.fold_of(keys[cal["index"]])
    t_outside = {}
    for f, m in enumerate(folds.maps):
        out = cal_fold != f
        s = m.calibrated_std(cal.get("std_raw", cal["std"])[out], None if not maps.free_space else cal["violation"][out],
                             cal["depth"][out], parallax=cal["parallax"][out] if "parallax" in cal else None
                             ) / m.std_scale
        t_outside[f] = cal["err"][out] / s
    edge_rows = {"run's std s": interval_row(gt, out_of_fold_level_quantiles(pred, abs_err, total, fold), abs_err)}
    for gamma in EDGE_WEIGHTS:
        std = np.hypot(total, gamma * delta)
        edge_rows[f"sqrt(s^2 + ({gamma:g} Delta)^2)"] = interval_row(
            gt, out_of_fold_level_quantiles(pred, abs_err, std, fold), abs_err)
    return {"folder": str(folder), "views": views, "which": which, "steps": _steps(folder),
            "train_views": len(dataset.train_indices), "radius_px": radius,
            "map": {"rho": maps.relative_floor, "beta": maps.free_space_weight if maps.free_space else 0.0},
            "sides": error_sides(gt, pred), "near_bound": near_bound_shares(gt, pred, near),
            "edges": edge_shares(gt, pred, delta, total),
            "edge_term": edge_rows,
            "calibration": {"product (symmetric level map)": interval_row(gt, product, abs_err),
                            "signed calibration errors": interval_row(gt, signed_fold_quantiles(pred, total, fold, t_outside), abs_err),
                            "calibration_t_quantiles": np.quantile(np.concatenate(list(t_outside.values())),
                                                                   [0.025, 0.25, 0.5, 0.75, 0.975]).tolist(),
                            "calibration_points": int(cal["err"].size)},
            "signed_rel": ((pred - gt) / gt).tolist()}


def _steps(folder: Path) -> int | None:
    """The run's last logged training step (the log keeps every 10th, so up to 9 short of the last)."""
    from stochastic_fields.trainer import LOG_NAME

    log = Path(folder) / LOG_NAME
    if not log.is_file():
        return None
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    return int(json.loads(lines[-1])["step"]) if lines else None


def pct(x: float) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.1f}%"


def interval_cells(row: dict) -> list[str]:
    cov = " / ".join(f"{100 * c:.1f}" for c in row["coverage"][:4])
    return [cov, pct(row["halfwidth_median_95"]), f"{row['interval_score_95']:.3f}", f"{row['crps']:.4f}",
            f"{row.get('spearman', float('nan')):.3f}"]


def report(records: dict[str, dict], command: str) -> str:
    lines = ["# Where the large depth errors are", "",
             f"Command: `{command}`", "",
             "Renders only; decides nothing (docs/studies.md, \"Analysis: where the large depth errors are\"). "
             "Points: SCORE capture points seen from photos no training saw and no table scores (paper split: "
             "the held-out photos beside the tables' four; capture split: its validation photos), rays through "
             "their exact pixels, opacity > 0.5. Errors relative "
             "to the true depth; \"in front\": rendered nearer than the truth.", "",
             "## 1. Size and side", "",
             "| run | last logged step | points | median / p90 abs-rel | > 5% (in front) | > 15% (in front) | > 30% (in front) "
             "| rendered / true, > 15% in front | near third: median signed, > 15% (in front) | middle third | far third |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, r in records.items():
        s = r["sides"]
        sizes = [f"{pct(z['share'])} ({pct(z['in_front'])})" for z in s["sizes"]]
        thirds = [f"{100 * t['median_signed']:+.1f}%, {pct(t['share_large'])} ({pct(t['in_front'])})" for t in s["thirds"]]
        ratio = f"{front_depth_ratio(r['signed_rel']):.2f}"
        lines.append(f"| {label} | {r['steps'] or '-'} | {s['num_points']} | {pct(s['median_abs'])} / {pct(s['p90_abs'])} | "
                     + " | ".join(sizes + [ratio] + thirds) + " |")
    lines += ["", f"Rendered at the near bound (below {NEAR_BOUND_FACTOR:g} x the view's near bound):", "",
              f"| run | of the errors in front beyond {FAR_ERROR:.0%} | of every point | true depths there |",
              "|---|---|---|---|"]
    for label, r in records.items():
        nb = r["near_bound"]
        lines.append(f"| {label} | {pct(nb['front_errors'])} | {pct(nb['rendered'])} | {pct(nb['true'])} |")
    lines += ["", "## 2. Occlusion edges", "",
              f"Delta: the range of the depths rendered on the point's ray and its 8 neighbours "
              f"{NEIGHBOUR_RADIUS_PX:g} pixels away.", "",
              "| run | errors > 15% with Delta >= half the error | other points with Delta > 15% of the depth "
              "| Spearman abs error vs Delta | vs the run's std |", "|---|---|---|---|---|"]
    for label, r in records.items():
        e = r["edges"]
        lines.append(f"| {label} | {pct(e['large_at_edge'])} | {pct(e['others_wide_range'])} | "
                     f"{e['spearman_delta']:.3f} | {e['spearman_std']:.3f} |")
    head = "| run | std | coverage 50 / 68 / 90 / 95 | median 95% half-width | IS95 / depth | CRPS / depth | Spearman |"
    lines += ["", "## 3. What an edge term would buy (level maps fitted out of fold on these points)", "", head,
              "|---|---|---|---|---|---|---|"]
    for label, r in records.items():
        for name, row in r["edge_term"].items():
            lines.append(f"| {label} | {name} | " + " | ".join(interval_cells(row)) + " |")
    lines += ["", "## 4. The product's intervals against the calibration's signed errors", "", head.replace("| std |", "| intervals |"),
              "|---|---|---|---|---|---|---|"]
    for label, r in records.items():
        for name, row in r["calibration"].items():
            if isinstance(row, dict):
                lines.append(f"| {label} | {name} | " + " | ".join(interval_cells(row)) + " |")
    lines += ["", "Signed standardised calibration errors (true - rendered) / s, quantiles 2.5 / 25 / 50 / 75 / 97.5%:", ""]
    for label, r in records.items():
        q = r["calibration"]["calibration_t_quantiles"]
        lines.append(f"- {label}: " + " / ".join(f"{v:+.2f}" for v in q)
                     + f" ({r['calibration']['calibration_points']} calibration points)")
    lines += ["", "![signed errors](signed_errors.png)", ""]
    return "\n".join(lines)


def plot(records: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    bins = np.linspace(-1.0, 0.5, 61)
    for label, r in records.items():
        rel = np.clip(np.asarray(r["signed_rel"]), bins[0], bins[-1])
        ax.hist(rel, bins=bins, histtype="step", density=True, label=label, linewidth=1.4)
    ax.set_yscale("log")
    ax.axvline(0.0, color="k", linewidth=0.8)
    ax.set_xlabel("(rendered - true) / true depth   (left: rendered in front of the truth; clipped at -100% / +50%)")
    ax.set_ylabel("density (log)")
    ax.set_title("Signed relative depth errors at capture points no training saw")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_run(text: str) -> tuple[str, Path]:
    label, sep, folder = text.partition("=")
    if not sep or not label or not folder:
        raise SystemExit(f"--run {text!r}: expected LABEL=FOLDER")
    if not re.fullmatch(r"[A-Za-z0-9_./-]+", label):
        raise SystemExit(f"--run {text!r}: a label of letters, digits and _ . / - only")
    if not (Path(folder) / "checkpoint.pt").is_file():
        raise SystemExit(f"--run {text!r}: {folder} holds no trained run (checkpoint.pt)")
    return label, Path(folder)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="LABEL=FOLDER")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--work", type=Path, default=None, help="Per-run records (large; default OUT/runs).")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    runs = [parse_run(text) for text in args.run]
    from stochastic_fields.io_utils import atomic_write_text

    work = args.work or args.out / "runs"
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/studies/depth_error_anatomy.py " + " ".join(
        f"--run {shlex.quote(f'{label}={folder}')}" for label, folder in runs) + f" --out {shlex.quote(str(args.out))}" \
        + (f" --work {shlex.quote(str(args.work))}" if args.work else "")
    records: dict[str, dict] = {}
    for label, folder in runs:
        record = work / (label.replace("/", "_") + ".json")
        if record.is_file() and json.loads(record.read_text()).get("folder") == str(folder):
            records[label] = json.loads(record.read_text())
        else:
            if not args.quiet:
                print(f"{label}: rendering {folder}", file=sys.stderr, flush=True)
            records[label] = anatomy_of_run(folder)
            atomic_write_text(record, json.dumps(records[label]))
        summary = {k: {**{kk: vv for kk, vv in r.items() if kk != "signed_rel"},
                       "front_depth_ratio": front_depth_ratio(r["signed_rel"])} for k, r in records.items()}
        atomic_write_text(args.out / "anatomy.json", json.dumps({"command": command, "runs": summary}, indent=1))
        atomic_write_text(args.out / "README.md", report(records, command))
        plot(records, args.out / "signed_errors.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
