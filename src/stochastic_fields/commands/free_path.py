"""``stochastic-fields free-path``: P(collision-free) of segments or a path (``products.free_path``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..defaults import FREE_PATH_NUM_DRAWS, FREE_TRANSMITTANCE_LEVEL


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, help="Trained S-NeRF run folder.")
    p.add_argument("--queries", required=True, type=Path, help='JSON with "segments" and/or "path" (world, scene units).')
    p.add_argument("--out", type=Path, default=None, help="Write the answers to this JSON file (default: print).")
    p.add_argument("--num-draws", type=int, default=FREE_PATH_NUM_DRAWS, help="K density trajectories (default 256).")
    p.add_argument("--level", type=float, default=FREE_TRANSMITTANCE_LEVEL,
                   help="Free = transmittance along the segment above this (default 0.5).")
    p.add_argument("--step", type=float, default=None, help="Sample spacing along segments (default: from footprint).")
    p.add_argument("--shared-noise", choices=("run", "true", "false"), default="run",
                   help="Share eps along a segment per draw (default: as the run renders).")
    p.add_argument("--seed", type=int, default=0, help="Seed of the draws.")
    p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
    p.add_argument("--raw-probability", action="store_true",
                   help="Report the model's P(free) as probability_free even where the run has a free-path "
                        "recalibration (RUN/free_path_calibration.json; docs/uncertainty.md).")


def run(args) -> None:
    from ..products.free_path_cli import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
