"""Analysis: does a setting's std rank worse, or are its errors harder to rank? (decides nothing).

Two trained S-NeRF runs of the same scene and split, A and B, differing in one setting (study 51:
three grid levels against five), each evaluated on the same test views with their products
(``stochastic-fields eval --run RUN --out EVAL``: ``EVAL/views/view_NNN.npz``). On the points both
score (the SCORE capture points of the test views, or the synthetic scene's SCORE-block pixels, as
``eval`` scores them; opacity > 0.5 in both renders) this reports the depth ranking (Spearman of
|depth error| against the recalibrated depth std) four ways:

    std_A ranks err_A,  std_B ranks err_B   (each run's own ranking, what the tables report)
    std_A ranks err_B,  std_B ranks err_A   (the cross rankings)

If A's std ranks B's errors about as badly as B's std does, B's errors are what changed (harder to
rank); if B's std ranks A's errors worse than A's std does, B's std is what lost information. Beside
them: the share of errors over 5% of the depth, the ranking among them and among the other errors, where the large
ones sit in the std's order (their mean rank quantile, 0.5 = no better than chance), the ranking on a
subset with the other run's share of large errors (each group ranked as it is: how much of a change is
the mix of errors alone), and the median
signed relative error with the ranking after removing it (a bias every pixel shares is something
no std ranks).

    python benchmarks/studies/ranking_cross_analysis.py \\
        --pair demo=runs/demo_L3:runs/demo_L3/eval:runs/demo_L5/eval \\
        --pair flower=RUN_A:EVAL_A:EVAL_B --labels "3 levels" "5 levels" --out OUT

Each ``--pair`` is NAME=RUN:EVAL_A:EVAL_B; RUN (either run of the pair) gives the dataset and its
split. OUT/ranking_cross_analysis.md / .json hold the table.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

#: An error above this share of the depth counts as large (a wrong surface, not noise).
LARGE_RELATIVE_ERROR = 0.05
#: Seed of the subset ``_ranking_at_share`` draws.
SUBSET_SEED = 0


def parse_pair(text: str) -> tuple[str, Path, Path, Path]:
    name, sep, rest = text.partition("=")
    parts = rest.split(":")
    if not sep or not name or len(parts) != 3 or not all(parts):
        raise ValueError(f"--pair {text!r}: expected NAME=RUN:EVAL_A:EVAL_B")
    return name, Path(parts[0]), Path(parts[1]), Path(parts[2])


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    """``metrics.spearman`` (eval's ranking and its undefined cases) as a float; NaN for fewer than 3 points."""
    from stochastic_fields.metrics import spearman

    return float(spearman(x, y).value) if len(x) > 2 else float("nan")


def cross_scores(gt: np.ndarray, pred_a: np.ndarray, std_a: np.ndarray, pred_b: np.ndarray,
                 std_b: np.ndarray) -> dict[str, float]:
    """The four rankings and the error anatomy of two runs on the same points (all [N], float)."""
    err_a, err_b = np.abs(pred_a - gt), np.abs(pred_b - gt)
    out = {"points": int(len(gt)),
           "abs_rel_a": float(np.mean(err_a / gt)), "abs_rel_b": float(np.mean(err_b / gt)),
           "a_ranks_a": _spearman(err_a, std_a), "b_ranks_b": _spearman(err_b, std_b),
           "a_ranks_b": _spearman(err_b, std_a), "b_ranks_a": _spearman(err_a, std_b),
           "errors_agree": _spearman(err_a, err_b), "stds_agree": _spearman(std_a, std_b)}
    shares = {"a": float(np.mean(err_a / gt > LARGE_RELATIVE_ERROR)), "b": float(np.mean(err_b / gt > LARGE_RELATIVE_ERROR))}
    for tag, other, pred, err, std in (("a", "b", pred_a, err_a, std_a), ("b", "a", pred_b, err_b, std_b)):
        large = err / gt > LARGE_RELATIVE_ERROR
        rank_quantile = (np.argsort(np.argsort(std)) + 0.5) / len(std)
        signed = (pred - gt) / gt
        bias = float(np.median(signed))
        out.update({f"large_share_{tag}": float(large.mean()),
                    f"small_ranking_{tag}": _spearman(err[~large], std[~large]),
                    f"large_ranking_{tag}": _spearman(err[large], std[large]),
                    f"large_rank_quantile_{tag}": float(rank_quantile[large].mean()) if large.any() else float("nan"),
                    f"ranking_at_other_share_{tag}": _ranking_at_share(err, std, large, shares[other]),
                    f"median_signed_{tag}": bias,
                    f"unbiased_ranking_{tag}": _spearman(np.abs(pred - gt * (1.0 + bias)), std)})
    return out


def _ranking_at_share(err: np.ndarray, std: np.ndarray, large: np.ndarray, share: float) -> float:
    """Spearman |err| vs std on a subset whose share of large errors is ``share``: every point of the
    group that is under-represented, a fixed draw (seed ``SUBSET_SEED``) of the other group's. What the
    ranking would be with the other run's mix of large and small errors, each group ranked as it is."""
    n_large, n_small = int(large.sum()), int((~large).sum())
    if n_large == 0 or n_small == 0 or not 0.0 < share < 1.0:
        return float("nan")
    keep_large = min(n_large, int(round(n_small * share / (1.0 - share))))
    keep_small = min(n_small, int(round(keep_large * (1.0 - share) / share)))
    rng = np.random.default_rng(SUBSET_SEED)
    idx = np.concatenate([rng.choice(np.flatnonzero(large), keep_large, replace=False),
                          rng.choice(np.flatnonzero(~large), keep_small, replace=False)])
    return _spearman(err[idx], std[idx])


def pair_points(run: Path, eval_a: Path, eval_b: Path) -> tuple[np.ndarray, ...]:
    """(gt, pred_a, std_a, pred_b, std_b) pooled over the test views both evals rendered, at the
    points eval scores (SCORE capture points, or SCORE-block pixels of exact depth), opacity > 0.5
    in both."""
    from stochastic_fields.capture_points import dense_depth_score_mask, load_capture_points, score_sparse_depth
    from stochastic_fields.config import load_config
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.view_maps import OPACITY_MASK

    dataset = load_run_dataset(load_config(run / "config.json"), run)  # the run's split; no checkpoint needed
    views = [int(name.split("_")[1]) for name in json.loads((eval_a / "metrics.json").read_text())["views"]]
    sparse = score_sparse_depth(dataset, views)
    capture = load_capture_points(dataset) if sparse is None else None
    cols: list[list[np.ndarray]] = [[] for _ in range(5)]
    for v in views:
        a, b = (np.load(e / "views" / f"view_{v:03d}.npz") for e in (eval_a, eval_b))
        if sparse is not None:
            sd = sparse[v]
            keep = (sd.sample(a["opacity"]) > OPACITY_MASK) & (sd.sample(b["opacity"]) > OPACITY_MASK)
            values = [sd.depth] + [sd.sample(m[k]) for m in (a, b) for k in ("depth_mean", "depth_std")]
        else:
            gt = dataset.depths[v].numpy()
            scored = dense_depth_score_mask(dataset, capture, v) if capture is not None else gt > 0
            mask = scored & (gt > 0) & (a["opacity"] > OPACITY_MASK) & (b["opacity"] > OPACITY_MASK)
            keep = np.ones(int(mask.sum()), dtype=bool)
            values = [gt[mask]] + [m[k][mask] for m in (a, b) for k in ("depth_mean", "depth_std")]
        for col, x in zip(cols, values):
            col.append(np.asarray(x, dtype=np.float64)[keep])
    return tuple(np.concatenate(c) for c in cols)


ROWS: tuple[tuple[str, str, str], ...] = (
    ("points scored", "points", "{:d}"),
    ("depth abs-rel", "abs_rel_{}", "{:.4f}"),
    ("own std ranks own errors", "{0}_ranks_{0}", "{:.3f}"),
    ("other's std ranks these errors", "{1}_ranks_{0}", "{:.3f}"),
    ("share of errors > 5% of the depth", "large_share_{}", "{:.3f}"),
    ("own ranking of the errors <= 5%", "small_ranking_{}", "{:.3f}"),
    ("own ranking of the errors > 5%", "large_ranking_{}", "{:.3f}"),
    ("mean std-rank quantile of the errors > 5%", "large_rank_quantile_{}", "{:.3f}"),
    ("own ranking at the other's share of errors > 5%", "ranking_at_other_share_{}", "{:.3f}"),
    ("median signed error / depth", "median_signed_{}", "{:+.4f}"),
    ("own ranking with that bias removed", "unbiased_ranking_{}", "{:.3f}"),
)


def table(name: str, scores: dict, labels: tuple[str, str]) -> list[str]:
    lines = [f"### {name}", "", f"| | {labels[0]} (A) | {labels[1]} (B) |", "|---|---|---|"]
    for title, key, fmt in ROWS:
        if "{" not in key:
            cells = [fmt.format(scores[key])] * 2
        else:
            cells = [fmt.format(scores[key.format(t, o)]) for t, o in (("a", "b"), ("b", "a"))]
        lines.append(f"| {title} | {cells[0]} | {cells[1]} |")
    lines += ["", f"The two runs' errors agree at Spearman {scores['errors_agree']:.3f}, their stds at "
              f"{scores['stds_agree']:.3f}.", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pair", action="append", required=True, metavar="NAME=RUN:EVAL_A:EVAL_B")
    p.add_argument("--labels", nargs=2, default=("A", "B"))
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    try:
        pairs = [parse_pair(t) for t in args.pair]
    except ValueError as exc:
        p.error(str(exc))
    for _, run, eval_a, eval_b in pairs:
        for folder, what in ((run / "config.json", "a trained run"), (eval_a / "metrics.json", "an eval folder"),
                             (eval_b / "metrics.json", "an eval folder")):
            if not folder.is_file():
                p.error(f"{folder.parent}: not {what} (no {folder.name})")

    from stochastic_fields.io_utils import atomic_write_text

    command = "python benchmarks/studies/ranking_cross_analysis.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))
    rows, lines = [], ["# Does the std rank worse, or are the errors harder to rank?", "", f"Command: `{command}`", "",
                       "Spearman |depth error| against the recalibrated depth std, pooled over the test views, on "
                       "the points both runs score (opacity > 0.5 in both).", ""]
    for name, run, eval_a, eval_b in pairs:
        scores = cross_scores(*pair_points(run, eval_a, eval_b))
        rows.append({"name": name, "run": str(run), "eval_a": str(eval_a), "eval_b": str(eval_b), **scores})
        lines += table(name, scores, tuple(args.labels))
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "ranking_cross_analysis.md", "\n".join(lines))
    atomic_write_text(args.out / "ranking_cross_analysis.json",
                      json.dumps({"command": command, "labels": list(args.labels), "rows": rows}, indent=2))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
