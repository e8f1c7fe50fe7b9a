"""``stochastic-fields occupancy``: the occupancy map of a trained run (npz + OctoMap ``.ot``).

Registered by ``stochastic_fields.cli.EXTRA_COMMANDS``; bad input raises ValueError /
FileNotFoundError naming it. See ``occupancy_map`` for what the files hold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .occupancy_map import (BLOCKED_OPACITY, OCCUPANCY_MAX_CELLS, OCCUPANCY_PIXELS_PER_VOXEL, occupancy_from_run)


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
