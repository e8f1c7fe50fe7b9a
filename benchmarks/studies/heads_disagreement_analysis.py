"""Analysis: do the density heads hold alternative surfaces where the depth is wrong? (decides nothing).

With M density heads (``field.density_heads``) draw k of a render draws its density around head
k mod M, so a pixel's K expected depths D_k fall into M groups. The law of total variance splits the
depth variance into three parts (docs/definitions.md §3.4, the epistemic part split once more):

    Var = Var_h(mean_{k in h} D_k)            BETWEEN: the heads' means disagree
        + mean_h Var_{k in h}(D_k)             WITHIN: draws around one head disagree
        + mean_k V_k                           SPREAD: each trajectory's termination along the ray

(heads weighted by their share of the draws, population variances). A deep ensemble's members put a
surface the photos leave open in different places; if the heads did the same, BETWEEN would be large
where the depth error is, and one head's mean would be near the truth where the mixture's is not.

For each trained S-NeRF run this renders the test views exactly as the tables score them (the same
views, SCORE capture points or the synthetic scene's SCORE-block pixels, opacity > 0.5, render seed
0, the run's stored recalibration) with the per-draw depths kept, and reports on the pooled points:
Spearman |error| against the recalibrated total std (the tables' ranking, a check) and against each
part's std alone, per-view mean and pooled; each part's median share of the raw variance; among the
large errors (> 5% of the depth) the mean rank quantile of BETWEEN (0.5: no better than chance) and
the share of points where the nearest head's mean is within 5% of the truth (a head held the right
surface) against the share where every head's is beyond it.

    python benchmarks/studies/heads_disagreement_analysis.py --run flower=RUN --out OUT

``--run`` SCENE=FOLDER as ``depth_variance_parts.py``. OUT/heads_disagreement.md / .json hold the table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import parse_runs, study_command, write_study  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"
#: An error above this share of the depth counts as large (a wrong surface, not noise).
LARGE_RELATIVE_ERROR = 0.05
#: The parts, in the table's order, after the total.
PARTS: tuple[str, ...] = ("between", "within", "spread")


def head_parts(depth_draws: np.ndarray, heads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(head means [P, M], between-head variance [P], within-head variance [P]) of the per-draw
    expected depths [P, K] (NaN where a pixel got fewer draws); draw k belongs to head k mod M, and
    each head is weighted by its share of the pixel's draws. between + within is the population
    variance of the draws (the epistemic part)."""
    P, K = depth_draws.shape
    valid = np.isfinite(depth_draws)
    head_of = np.arange(K) % heads
    counts = np.stack([valid[:, head_of == h].sum(1) for h in range(heads)], 1).astype(np.float64)  # [P, M]
    d = np.where(valid, depth_draws, 0.0)
    sums = np.stack([d[:, head_of == h].sum(1) for h in range(heads)], 1)
    means = sums / np.maximum(counts, 1)
    share = counts / counts.sum(1, keepdims=True)
    centre = (share * means).sum(1)
    between = (share * (means - centre[:, None]) ** 2).sum(1)
    sq = np.where(valid, (depth_draws - means[:, head_of]) ** 2, 0.0)
    within = sum(share[:, h] * sq[:, head_of == h].sum(1) / np.maximum(counts[:, h], 1) for h in range(heads))
    return means, between, within


def rank_quantile(values: np.ndarray, subset: np.ndarray) -> float:
    """Mean rank quantile in [0, 1] of ``values[subset]`` among all ``values`` (0.5: chance)."""
    if not subset.any():
        return float("nan")
    ranks = np.argsort(np.argsort(values, kind="stable"), kind="stable") / max(len(values) - 1, 1)
    return float(ranks[subset].mean())


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    from stochastic_fields.metrics import spearman

    return float(spearman(x, y).value) if len(x) > 2 else float("nan")


def view_points(products: dict[str, np.ndarray], gt_depth: np.ndarray | None, sparse, heads: int) -> dict | None:
    """The scored points of one view: gt, pred, the recalibrated total std and the parts' variances."""
    from stochastic_fields.view_maps import OPACITY_MASK

    draws = products["depth_draws"]
    maps = {"pred": products["depth_mean"], "std": products["depth_std"],
            "spread": products["depth_std_spread"].astype(np.float64) ** 2,
            "opacity": products["opacity"]}
    if sparse is not None:
        keep = sparse.sample(maps["opacity"]) > OPACITY_MASK
        gt = np.asarray(sparse.depth, np.float64)[keep]
        at = {k: np.asarray(sparse.sample(v), np.float64)[keep] for k, v in maps.items()}
        d = np.stack([np.asarray(sparse.sample(draws[..., k]), np.float64) for k in range(draws.shape[-1])], 1)[keep]
    elif gt_depth is not None:
        keep = (gt_depth > 0) & (maps["opacity"] > OPACITY_MASK)
        gt = gt_depth[keep].astype(np.float64)
        at = {k: v[keep].astype(np.float64) for k, v in maps.items()}
        d = draws[keep].astype(np.float64)
    else:
        return None
    means, between, within = head_parts(d, heads)
    return {"gt": gt, "pred": at["pred"], "std": at["std"], "between": between, "within": within,
            "spread": at["spread"], "head_means": means}


def scores(points: list[dict]) -> dict[str, float]:
    """The table's numbers from the per-view points."""
    per_view: dict[str, list[float]] = {name: [] for name in ("total", *PARTS)}
    for p in points:
        err = np.abs(p["pred"] - p["gt"])
        if len(err) < 3:
            continue
        per_view["total"].append(_spearman(err, p["std"]))
        for name in PARTS:
            per_view[name].append(_spearman(err, np.sqrt(p[name])))
    pool = {k: np.concatenate([p[k] for p in points]) for k in points[0]}
    gt = pool["gt"]
    err = np.abs(pool["pred"] - gt)
    rel = err / gt
    large = rel > LARGE_RELATIVE_ERROR
    total_var = pool["between"] + pool["within"] + pool["spread"]
    head_off = pool["head_means"] - gt[:, None]  # [P, M] each head's signed error
    out: dict[str, float] = {"points": int(len(gt)), "abs_rel": float(rel.mean()), "large_share": float(large.mean())}
    out.update({f"ranking_views_{k}": float(np.nanmean(v)) for k, v in per_view.items()})
    out["ranking_pooled_total"] = _spearman(err, pool["std"])
    for name in PARTS:
        out[f"ranking_pooled_{name}"] = _spearman(err, np.sqrt(pool[name]))
        out[f"variance_share_{name}"] = float(np.median(pool[name] / np.maximum(total_var, 1e-30)))
    out["between_std_over_depth"] = float(np.median(np.sqrt(pool["between"]) / gt))
    out["large_rank_quantile_between"] = rank_quantile(pool["between"], large)
    out["large_rank_quantile_total"] = rank_quantile(pool["std"], large)
    if large.any():
        out["large_some_head_right"] = float((np.abs(head_off[large]).min(1) <= LARGE_RELATIVE_ERROR * gt[large]).mean())
        out["large_heads_straddle"] = float(((head_off[large].min(1) < 0) & (head_off[large].max(1) > 0)).mean())
    else:
        out["large_some_head_right"] = out["large_heads_straddle"] = float("nan")
    return out


ROWS: tuple[tuple[str, str, str], ...] = (
    ("points scored", "points", "{:d}"),
    ("depth abs-rel, pooled over the points", "abs_rel", "{:.4f}"),
    ("share of errors > 5% of the depth", "large_share", "{:.3f}"),
    ("ranking by the total std (the tables'), views / pooled", "total", "rank"),
    ("ranking by BETWEEN heads alone", "between", "rank"),
    ("ranking by WITHIN a head alone", "within", "rank"),
    ("ranking by the SPREAD alone", "spread", "rank"),
    ("median share of the variance: BETWEEN", "variance_share_between", "{:.3f}"),
    ("median share of the variance: WITHIN", "variance_share_within", "{:.3f}"),
    ("median share of the variance: SPREAD", "variance_share_spread", "{:.3f}"),
    ("median BETWEEN std / depth", "between_std_over_depth", "{:.4f}"),
    ("errors > 5%: mean rank quantile in BETWEEN", "large_rank_quantile_between", "{:.3f}"),
    ("errors > 5%: mean rank quantile in the total std", "large_rank_quantile_total", "{:.3f}"),
    ("errors > 5%: share where some head's mean is within 5%", "large_some_head_right", "{:.3f}"),
    ("errors > 5%: share where the heads' means straddle the truth", "large_heads_straddle", "{:.3f}"),
)


def table(rows: list[dict]) -> list[str]:
    lines = ["| | " + " | ".join(f"{r['scene']} (`{r['run']}`)" for r in rows) + " |",
             "|---|" + "---|" * len(rows)]
    for label, key, fmt in ROWS:
        if fmt == "rank":
            cells = [f"{r[f'ranking_views_{key}']:.3f} / {r[f'ranking_pooled_{key}']:.3f}" for r in rows]
        else:
            cells = [fmt.format(r[key]) for r in rows]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="SCENE=FOLDER")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--seed", type=int, default=0, help="render seed (the tables': 0)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    runs = parse_runs(p, args.run, required="config.json").items()

    import torch
    from tqdm import tqdm

    from stochastic_fields.calibration import apply_calibration, load_run_calibration
    from stochastic_fields.capture_points import dense_depth_score_mask, load_capture_points
    from stochastic_fields.renderer import seeded_chunks
    from stochastic_fields.trainer import load_trained_model
    from stochastic_fields.view_maps import camera_z_maps, view_camera_arrays
    from stochastic_fields_bench.budget import BenchmarkSettings
    from stochastic_fields_bench.runner import scene_inputs

    torch.set_num_threads(args.threads)
    rows: list[dict] = []
    for scene, folder in runs:
        _, dataset, views, sparse = scene_inputs(scene, BenchmarkSettings(), args.data_root, log=lambda _m: None)
        cfg, model, _ = load_trained_model(folder, dataset=dataset)
        heads = int(getattr(getattr(model, "field", None), "density_heads", 1))
        if heads < 2:
            p.error(f"{folder}: the field has one density head; nothing to split")
        calibration = load_run_calibration(folder)
        options = model.default_render_options().with_changes(keep_draws=True)
        device = next(model.parameters()).device
        gt_depths = getattr(dataset, "depths", None)
        # exact depth maps score the SCORE blocks' pixels only where the scene has capture points (as eval)
        capture = load_capture_points(dataset) if sparse is None and gt_depths is not None else None
        points = []
        for v in tqdm(views, desc=f"{scene}: views", disable=args.quiet):
            maps = model.render_view(dataset.rays(v).to(device), options, generator=seeded_chunks(args.seed, v, device))
            camera = view_camera_arrays(dataset, v)
            products = apply_calibration(camera_z_maps(maps), calibration,
                                         camera=(camera["intrinsics"], camera["world_to_camera"]))
            gt_depth = None if gt_depths is None else gt_depths[v].numpy()
            if gt_depth is not None and capture is not None:
                gt_depth = np.where(dense_depth_score_mask(dataset, capture, v), gt_depth, 0.0)
            got = view_points(products, gt_depth, None if sparse is None else sparse[v], heads)
            if got is not None and len(got["gt"]):
                points.append(got)
        if not points:
            p.error(f"{folder}: no scored depth points on the test views")
        rows.append({"scene": dataset.name, "run": str(folder), "heads": heads, **scores(points)})

    command = study_command("heads_disagreement_analysis.py", argv)
    lines = ["# Do the density heads hold alternative surfaces where the depth is wrong?", "",
             f"Command: `{command}`", "",
             "Spearman |depth error| against each std: per-view mean / pooled over the scored test views. "
             "BETWEEN: the variance of the heads' mean depths; WITHIN: the draws' variance around their head; "
             "SPREAD: the mean termination variance along the ray (raw, before the recalibration).", ""]
    lines += table(rows)
    write_study(args.out, {"command": command, "rows": rows}, "\n".join(lines) + "\n", name="heads_disagreement")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
