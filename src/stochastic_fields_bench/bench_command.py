"""``stochastic-fields bench``: speed against error (``stochastic_fields_bench.speed``), added to the
command line through the ``stochastic_fields.commands`` entry point.

The options live here, without the benchmark, so that ``--help`` answers at once; ``run`` loads the
benchmark when the command runs.
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="benchmarks/results", help="Output folder for bench.json and plots.")
    parser.add_argument("--data", default="../shared/data", help="Reference data folder (fern is skipped if absent).")
    parser.add_argument("--quick", action="store_true", help="Small budget (about 10 minutes on 2 CPU cores).")
    parser.add_argument("--iterations", type=int, default=None, help="Training steps per backend (default 100 quick, 3000).")
    parser.add_argument("--mlp-iterations", type=int, default=None, help="Training steps of the MLP (default: --iterations).")
    parser.add_argument("--mlp-width", type=int, default=None, help="MLP trunk width (paper: 256; default 64 quick, 256).")
    parser.add_argument("--rays-per-batch", type=int, default=None, help="Training rays per step (default 512 quick, 1024).")
    parser.add_argument("--eval-pixels", type=int, default=None, help="Test pixels for the training curves (default 1024 quick, 8192).")
    parser.add_argument("--curve-points", type=int, default=8,
                        help="Evaluations along each training curve, spaced geometrically in steps (early quality is where backends differ).")
    parser.add_argument("--view-stride", type=int, default=None, help="Pixel stride of the rendered view (default 4 quick on fern, 1).")
    parser.add_argument("--scenes", default="synthetic,fern", help="Comma-separated scenes: synthetic, fern.")


def run(args: argparse.Namespace) -> None:
    from .speed import run as run_bench  # deferred: loads only when this command runs (keeps --help fast)

    run_bench(args)
