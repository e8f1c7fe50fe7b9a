"""``stochastic-fields export``: command-line options mapped onto :class:`.export.ExportOptions`.

Registered by ``stochastic_fields.cli.EXTRA_COMMANDS``; bad input raises ValueError or
FileNotFoundError, which ``cli.main`` turns into a one-line message and exit code 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .export_options import FORMATS, ExportOptions


def _floats(name: str):
    def parse(text: str) -> tuple[float, ...]:
        try:
            return tuple(float(t) for t in text.split(",") if t.strip())
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{name} must be comma-separated numbers, got {text!r}") from exc
    return parse


def _formats(text: str) -> tuple[str, ...]:
    items = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [t for t in items if t not in FORMATS]
    if bad or not items:
        raise argparse.ArgumentTypeError(
            f"--formats takes a comma-separated subset of {','.join(FORMATS)}, got {text!r}")
    return items


def _known_distance(values) -> tuple[float, float, float] | None:
    if values is None:
        return None
    if len(values) != 3:
        raise ValueError(f"--known-distance takes I,J,METRES (two camera indices and a distance), got {list(values)}")
    return tuple(values)


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = ExportOptions()
    p.add_argument("--run", required=True, help="Trained run folder (with checkpoint.pt and config.json).")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--views", default=d.views,
                     help="'test' (default), 'train', 'all' or dataset view indices like 1,2,3.")
    src.add_argument("--cameras", type=Path, default=None,
                     help='JSON list of {"K": 3x3, "world_to_camera": 4x4, "width", "height"} (OpenCV; optional '
                          '"near", "far" camera-z and "name").')
    p.add_argument("--out", type=Path, default=None, help="Output folder (default: RUN/export).")
    p.add_argument("--render.num_draws", "--render.num-draws", "--num-draws", dest="num_draws", type=int, default=None,
                   help="K depth trajectories per pixel (default: the run's render.num_draws).")
    p.add_argument("--formats", type=_formats, default=d.formats,
                   help=f"Per-view map formats, comma-separated subset of {','.join(FORMATS)} (default: "
                        f"{','.join(d.formats)}; 'ros' = REP 118 metres/millimetres + CameraInfo, needs a scale).")
    p.add_argument("--quantiles", type=_floats("--quantiles"), default=d.quantiles,
                   help="Depth quantile levels from the K draws (default 0.05,0.95).")
    p.add_argument("--min-opacity", type=float, default=d.min_opacity,
                   help="Pixels with lower accumulated opacity get no depth and no point (default 0.5).")
    p.add_argument("--max-std", type=float, default=None,
                   help="Drop points whose total depth std exceeds this (scene units).")
    p.add_argument("--max-rel-std", type=float, default=None, help="Drop points whose depth_std / depth exceeds this.")
    p.add_argument("--keep-fraction", type=float, default=None,
                   help="Keep only this fraction of each view's most confident points (0..1].")
    p.add_argument("--colour-by", choices=("rgb", "uncertainty"), default=d.colour_by,
                   help="PLY colours: rendered RGB or depth std through a perceptual colour map (range recorded).")
    p.add_argument("--fuse", action="store_true",
                   help="Also fuse all views into fused.ply (inverse-variance per voxel).")
    p.add_argument("--voxel-size", type=float, default=None,
                   help="Fusion voxel size (default: median pixel footprint).")
    p.add_argument("--free-space-thresholds", type=_floats("--free-space-thresholds"), default=(),
                   help="Camera-z distances d: write P(depth > d) volumes [T, H, W] per view.")
    p.add_argument("--covariance", action="store_true",
                   help="Add per-point 3x3 covariances (cov_xx..cov_zz) to the PLYs.")
    p.add_argument("--save-draws", action="store_true", help="Keep the per-draw depths [H, W, K] in each npz.")
    p.add_argument("--units", default=d.units, help="Name of the length unit written into the files.")
    p.add_argument("--metres-per-unit", type=float, default=None,
                   help="Metres per scene unit (needed by --formats ros; recorded in every npz). LLFF/SfM scenes "
                        "have no metric scale of their own.")
    p.add_argument("--known-distance", type=_floats("--known-distance"), default=None,
                   help="I,J,METRES: dataset cameras I and J are METRES apart (sets the metric scale instead of "
                        "--metres-per-unit).")
    p.add_argument("--seed", type=int, default=d.seed, help="Seed of the K draws.")
    p.add_argument("--raw-uncertainty", action="store_true",
                   help="Ignore the run's calibration.json: depth_std and the bands use the raw total std.")
    p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    from ..cli import add_dist_timeout_argument  # deferred: loads only when this command runs (keeps --help fast)

    add_dist_timeout_argument(p)


def options_from_args(args: argparse.Namespace) -> ExportOptions:
    return ExportOptions(
        views=args.views, cameras=args.cameras, out=args.out, num_draws=args.num_draws, formats=tuple(args.formats),
        quantiles=tuple(args.quantiles), min_opacity=args.min_opacity, max_std=args.max_std,
        max_rel_std=args.max_rel_std, keep_fraction=args.keep_fraction, colour_by=args.colour_by, fuse=args.fuse,
        voxel_size=args.voxel_size, free_space_thresholds=tuple(args.free_space_thresholds),
        covariance=args.covariance, save_draws=args.save_draws, units=args.units,
        metres_per_unit=args.metres_per_unit, known_distance=_known_distance(args.known_distance), seed=args.seed,
        raw_uncertainty=args.raw_uncertainty, device=args.device, progress=not args.quiet)


def run(args: argparse.Namespace) -> None:
    from ..distributed import sharding_from_environment  # deferred: loads only when this command runs (keeps --help fast)
    from .export import export_run  # deferred: loads only when this command runs (keeps --help fast)

    opts = options_from_args(args)
    with sharding_from_environment(args.run, args.device, timeout_s=args.dist_timeout) as ctx:
        summary = export_run(args.run, opts, distributed=ctx)
    if ctx is not None and not ctx.is_main:
        return
    out = Path(args.out) if args.out else Path(args.run) / "export"
    c = summary["counts"]
    line = f"exported {len(summary['views'])} views (K={summary['num_draws']}) into {out}: " \
           f"{c['after_opacity']} valid pixels -> {c['after_filters']} points"
    if "after_fusion" in c:
        line += f" -> {c['after_fusion']} fused"
    print(line)
    gt = summary.get("ground_truth", {})
    if "surface_distance" in gt:
        s = gt["surface_distance"]
        print(f"  distance to the true surface: mean {s['mean']:.4g}, "
              f"50% most confident {s['most_confident_50_mean']:.4g} [{s['units']}]")
    if "calibration" in gt:
        cal = gt["calibration"]
        print(f"  GT depth inside mean +- z std: 68% -> {cal['gaussian_total_std']['68']:.3f}, "
              f"95% -> {cal['gaussian_total_std']['95']:.3f}; draw-quantile intervals: "
              f"68% -> {cal['draw_quantiles']['68']:.3f}, 95% -> {cal['draw_quantiles']['95']:.3f}")
    print(f"  summary: {out / 'summary.json'}")
