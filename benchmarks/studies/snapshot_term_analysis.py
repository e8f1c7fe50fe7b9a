"""Analysis (decides nothing): how far a pixel's depth moved over the last part of training, as a depth std term.

S-NeRF's K trajectories agree where the photos see a surface (to 0.03-0.08% of the depth, study 34), so a
pixel rendered on the wrong surface often gets a small std; the deep ensemble ranks flower's depth errors
better (issue 36's open target 4) from what its independently trained members disagree on. A cheaper source
of disagreement is the run's own training trajectory: where the depth was still moving late in training,
the photos pinned it less. k = |d_final - d_snapshot|, d_snapshot the depth of the same run at an earlier
step of its schedule (``train-snapshot``: the run trained again to that step, ``train(max_steps=...)``; training
is deterministic, so it is the run's own state there, checked on the training log's losses). The arms are
``skew_term_analysis``'s with k in place of the skew: ``today`` (sigma), ``term`` (k as the map's extra term,
its weight fitted by the CRPS), ``sum`` (sqrt(sigma^2 + k^2), no weight); every map fitted on the same
calibration renders, scored on the validation photos' SCORE points as ``eval`` scores them (cross-fitted).
The snapshot renders with the same generator seeds as the final run's renders.

    OMP_NUM_THREADS=1 python benchmarks/eval_tables.py --scenes flower --methods snerf_default --seed 61 \\
        --no-timing --quiet --out runs/snap/tables
    OMP_NUM_THREADS=1 python benchmarks/studies/snapshot_term_analysis.py train-snapshot RUN runs/snap/snapshot \\
        --step 1225                                        # 70% of flower's 1750 steps (35%: 612 into snapshot35)
    stochastic-fields eval --run RUN --views VALIDATION --quiet --out runs/snap/evals
    OMP_NUM_THREADS=1 python benchmarks/studies/snapshot_term_analysis.py analyse \\
        --run paper_flower_s61 RUN runs/snap/evals runs/snap/snapshot \\
        --run paper_flower_s61_at35 RUN runs/snap/evals runs/snap/snapshot35 \\
        --run paper_fern_s61 ... --run paper_fern_s61_at35 ... --work runs/snap/analysis \\
        --out benchmarks/results/snapshot_term_analysis

RUN = runs/snap/tables/flower/snerf_default; VALIDATION the paper split's held-out photos the tables do not
score: flower 2,3,4,6,7,8,9,11,13,14,16,17,18,19,21,23,24,26,27,28,29,31,32, fern 2,3,4,6,8,9,11,12,14,16,17,18.
Fern the same way (``--scenes fern``, ``--out runs/snap/tables_fern``; snapshots at steps 700 and 350 of 1000).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from skew_term_analysis import ARMS, analyse, markdown  # noqa: E402
from study_helpers import cached, write_study  # noqa: E402

from stochastic_fields.calibration import render_at_points  # noqa: E402
from stochastic_fields.cameras import generate_rays_for_view  # noqa: E402
from stochastic_fields.config import load_config  # noqa: E402
from stochastic_fields.renderer import seeded_chunks  # noqa: E402
from stochastic_fields.scenes import load_run_dataset  # noqa: E402
from stochastic_fields.trainer import Trainer, load_trained_model  # noqa: E402


def snapshot_terms(snapshot: Path):
    """(term_at_points, term_map) of ``skew_term_analysis.analyse`` for |d_final - d_snapshot|."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, early, _ = load_trained_model(snapshot, device="cpu")

    def at_points(model, cams, near, far, sparse, depth, *, seed: int = 0, options=None) -> np.ndarray:
        r = render_at_points(early, cams, near, far, sparse, generator=torch.Generator().manual_seed(seed),
                             options=options)
        return np.abs(np.asarray(depth) - r["depth_mean"])

    def over_view(model, dataset, view: int, products: dict) -> np.ndarray:
        rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far)
        with torch.no_grad():
            maps = early.render_view(rays, generator=seeded_chunks(0, view))
        depth = maps["depth_mean"].double().numpy() * maps["z_scale"].double().numpy()
        return np.abs(products["depth_mean"] - depth)

    return at_points, over_view


def same_trajectory(run: Path, snapshot: Path) -> float:
    """The largest relative difference of the logged losses the two runs share (0: the same trajectory)."""
    def losses(d: Path) -> dict:
        return {r["step"]: r["loss"] for r in map(json.loads, (d / "train_log.jsonl").read_text().splitlines())}
    a, b = losses(run), losses(snapshot)
    shared = sorted(set(a) & set(b))
    if not shared:
        raise RuntimeError(f"{run} and {snapshot} log no common step")
    return max(abs(a[s] - b[s]) / max(abs(a[s]), 1e-12) for s in shared)


def train_snapshot(run: Path, out: Path, step: int) -> None:
    """Train ``run``'s configuration again into ``out``, stopping at ``step`` of its schedule (one thread)."""
    torch.set_num_threads(1)
    cfg = load_config(run / "config.json")
    out.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the capture's lens-distortion note
        dataset = load_run_dataset(cfg, out)
    Trainer(cfg, out, dataset).train(progress=False, max_steps=step)


def analyse_runs(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    results = {}
    for label, run, evals, snapshot in args.run:
        drift = same_trajectory(Path(run), Path(snapshot))
        if drift > 1e-4:
            raise RuntimeError(f"{snapshot} is not {run}'s trajectory: logged losses differ by {drift:.2g}")

        def compute(run=Path(run), evals=Path(evals), snapshot=Path(snapshot)) -> dict:
            at_points, over_view = snapshot_terms(snapshot)
            return analyse(run, evals, at_points, over_view)

        results[label] = cached(args.work / f"{label}.json", compute)
        print(label, {arm: (round(100 * a["halfwidth_median_95"], 1), round(a["interval_score_95"], 3),
                            round(a["spearman_per_view"], 3)) for arm, a in results[label]["arms"].items()}, flush=True)
    text = markdown(results, title="How far a pixel's depth moved late in training, as a depth std term",
                    script="snapshot_term_analysis.py", render="snapshot")
    write_study(args.out, {"results": results, "arms": list(ARMS)}, text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    snap = sub.add_parser("train-snapshot", help="train RUN's configuration again to --step into OUT")
    snap.add_argument("run", type=Path)
    snap.add_argument("out", type=Path)
    snap.add_argument("--step", type=int, required=True)
    an = sub.add_parser("analyse", help="score the arms of each run against its snapshot")
    an.add_argument("--run", nargs=4, action="append", required=True, metavar=("LABEL", "RUN", "EVALS", "SNAPSHOT"))
    an.add_argument("--work", type=Path, default=Path("runs/snapshot_term"), help="per-run results (resumable)")
    an.add_argument("--out", type=Path, default=Path("benchmarks/results/snapshot_term_analysis"))
    args = ap.parse_args()
    if args.command == "train-snapshot":
        train_snapshot(args.run, args.out, args.step)
    else:
        analyse_runs(args)


if __name__ == "__main__":
    main()
