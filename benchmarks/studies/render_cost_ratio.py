"""The render cost of one trained run against another's: a validation photo of each, rendered in turn.

A study whose candidate changes what a render computes (density heads: a draw per head's loc) rules on the
render's cost (issue 36's target 6: at most 1.5x the deterministic NeRF's). Each run renders its first
validation view with its own settings, today's run first, then the candidate's, ``--repeats`` times in
turn, so that the machine's drifts hit both alike; the ratio is of the medians. Run it on an otherwise idle
machine (the threads are stated in the output).

    OMP_NUM_THREADS=2 python benchmarks/studies/render_cost_ratio.py runs/s79/today/seed_44/flower/snerf/run \\
        runs/s79/heads_2/seed_44/flower/snerf/run --threads 2 --out benchmarks/results/density_heads_study/render_cost_flower.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import warnings
from pathlib import Path

import torch

from stochastic_fields.cameras import generate_rays_for_view
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.renderer import seeded_chunks
from stochastic_fields.trainer import load_trained_model


def render_seconds(runs: dict[str, Path], repeats: int) -> dict[str, list[float]]:
    """{label: the seconds of each of ``repeats`` renders of the run's first validation view}, in turn."""
    loaded = {}
    for label, run in runs.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the capture's lens-distortion note
            _, model, ds = load_trained_model(run, device="cpu")
        if not len(ds.test_indices):
            raise SystemExit(f"{run}: the run's dataset holds no validation view to render")
        view = int(ds.test_indices[0])
        loaded[label] = (model, generate_rays_for_view(ds.cameras, view, ds.near, ds.far), view)
    times: dict[str, list[float]] = {label: [] for label in runs}
    for _ in range(repeats):
        for label, (model, rays, view) in loaded.items():
            start = time.perf_counter()
            with torch.no_grad():
                model.render_view(rays, generator=seeded_chunks(0, view))
            times[label].append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("today", type=Path, help="today's trained run (a folder with its checkpoint)")
    ap.add_argument("candidate", type=Path, help="the candidate's trained run")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--repeats", type=int, default=3, help="renders of each, in turn")
    ap.add_argument("--out", type=Path, default=None, help="also write the result as JSON here")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.threads < 1:
        ap.error(f"--repeats and --threads must be >= 1, got {args.repeats} and {args.threads}")
    torch.set_num_threads(args.threads)
    times = render_seconds({"today": args.today, "candidate": args.candidate}, args.repeats)
    result = {"today": str(args.today), "candidate": str(args.candidate), "threads": args.threads,
              "repeats": args.repeats, "seconds": times,
              "ratio": statistics.median(times["candidate"]) / statistics.median(times["today"])}
    print(json.dumps(result, indent=2))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
