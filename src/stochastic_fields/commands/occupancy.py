"""``stochastic-fields occupancy``: the occupancy map of a trained run (``products.occupancy_map``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..defaults import BLOCKED_OPACITY, OCCUPANCY_MAX_CELLS, OCCUPANCY_PIXELS_PER_VOXEL


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, help="Trained S-NeRF run folder.")
    p.add_argument("--out", type=Path, default=None, help="Output folder (default: RUN/occupancy).")
    p.add_argument("--voxel-size", type=float, default=None,
                   help="Voxel edge (scene units; default: from the images' pixel footprint).")
    p.add_argument("--pixels-per-voxel", type=float, default=OCCUPANCY_PIXELS_PER_VOXEL,
                   help="Pixels a voxel spans where the cameras see it (default 2).")
    p.add_argument("--max-cells", type=int, default=OCCUPANCY_MAX_CELLS, help="Most voxels (coarser beyond).")
    p.add_argument("--blocked-opacity", type=float, default=BLOCKED_OPACITY,
                   help="Occupied = a straight crossing of --blocking-length has at least this opacity (default 0.5).")
    p.add_argument("--blocking-length", type=float, default=None,
                   help="Length of that crossing (scene units; default: the voxel size). Use the robot's size or "
                        "clearance when the model's surfaces are diffuse.")
    p.add_argument("--density-threshold", type=float, default=None,
                   help="Occupied = density above this (overrides --blocked-opacity/--blocking-length).")
    p.add_argument("--metres-per-unit", type=float, default=None,
                   help="Metres per scene unit (the .ot file is then in metres; recorded in the npz).")
    p.add_argument("--no-octomap", action="store_true", help="Skip the OctoMap .ot file.")
    p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")


def run(args) -> None:
    from ..products.planner_cli import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
