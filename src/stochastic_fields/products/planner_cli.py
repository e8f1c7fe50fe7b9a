"""``stochastic-fields occupancy``: the occupancy map of a trained run (npz + OctoMap ``.ot``).

Registered by ``stochastic_fields.cli.EXTRA_COMMANDS``; bad input raises ValueError /
FileNotFoundError naming it. See ``occupancy_map`` for what the files hold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .occupancy_map import (BLOCKED_OPACITY, OCCUPANCY_MAX_CELLS, OCCUPANCY_PIXELS_PER_VOXEL, occupancy_from_run)


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


def run(args: argparse.Namespace) -> None:
    out = args.out if args.out is not None else Path(args.run) / "occupancy"
    if args.voxel_size is not None and not args.voxel_size > 0:
        raise ValueError(f"--voxel-size must be positive, got {args.voxel_size}")
    meta = occupancy_from_run(args.run, out, voxel_size=args.voxel_size, pixels_per_voxel=args.pixels_per_voxel,
                              max_cells=args.max_cells, blocked_opacity=args.blocked_opacity,
                              blocking_length=args.blocking_length, density_threshold=args.density_threshold,
                              metres_per_unit=args.metres_per_unit, octomap=not args.no_octomap,
                              device=args.device, progress=not args.quiet)
    print(f"occupancy of {args.run} into {out}: voxel {meta['voxel_size']:.4g} {meta['units']}, grid {meta['shape']}, "
          f"{meta['voxels_listed']} voxels with P >= {meta['min_probability']:g}, "
          f"{meta['voxels_p_above_0.5']} with P > 0.5; files {', '.join(meta['files'])}")
