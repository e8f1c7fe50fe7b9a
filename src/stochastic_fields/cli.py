"""``stochastic-fields``: train | render | eval | demo (and the commands other modules add).

Every option of the experiment config is available as ``--group.name``; ``--help`` on each
command lists them with their explanations.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from . import config as C
from .renderer import COLOUR_ESTIMATORS


def _add_experiment_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default=None, choices=C.PRESETS,
                   help="Start from a named preset (default: 'default', or the run's saved config when resuming).")
    C.add_config_arguments(p)


def experiment_from_args(args: argparse.Namespace, run_dir: Path) -> C.ExperimentConfig:
    """The run's saved config when resuming, else the preset; explicit options apply on top."""
    saved = run_dir / "config.json"
    if saved.exists() and args.preset is None:
        cfg = C.load_config(saved)
    else:
        cfg = C.preset(args.preset or "default")
    return C.apply_overrides(cfg, args)


def _parse_views(spec: str | None, dataset) -> list[int]:
    if spec is None or spec == "test":
        return list(dataset.test_indices)
    if spec == "train":
        return list(dataset.train_indices)
    if spec == "all":
        return list(range(dataset.num_views))
    try:
        views = [int(v) for v in spec.split(",") if v.strip()]
    except ValueError as exc:
        raise SystemExit(f"--views must be 'test', 'train', 'all' or comma-separated indices, got {spec!r}") from exc
    bad = [v for v in views if not 0 <= v < dataset.num_views]
    if bad:
        raise SystemExit(f"--views {bad} out of range: the scene has {dataset.num_views} views (0..{dataset.num_views - 1})")
    return views


def cmd_train(args: argparse.Namespace) -> None:
    from .scenes import load_run_dataset
    from .trainer import Trainer

    run_dir = Path(args.out)
    cfg = experiment_from_args(args, run_dir)
    dataset = load_run_dataset(cfg, run_dir)
    Trainer(cfg, run_dir, dataset).train(progress=not args.quiet)
    print(f"trained: {run_dir / 'checkpoint.pt'}")


def _apply_render_overrides(model, args: argparse.Namespace) -> None:
    """Render options a trained run can change without retraining (``--colour-estimator``)."""
    settings = getattr(model, "render_settings", None)
    if args.colour_estimator is not None and settings is not None:
        settings.colour_estimator = args.colour_estimator


def cmd_render(args: argparse.Namespace) -> None:
    from .evaluate import evaluate
    from .trainer import load_trained_model

    cfg, model, dataset = load_trained_model(Path(args.run), device=args.device)
    _apply_render_overrides(model, args)
    views = _parse_views(args.views, dataset)
    out = Path(args.out) if args.out else Path(args.run) / "renders"
    evaluate(model, dataset, out, views=views, num_draws=args.num_draws, progress=not args.quiet)
    print(f"rendered {len(views)} views into {out / 'views'}")


def cmd_eval(args: argparse.Namespace) -> None:
    from .eval.metrics import MetricReport
    from .evaluate import evaluate
    from .trainer import load_trained_model

    cfg, model, dataset = load_trained_model(Path(args.run), device=args.device)
    _apply_render_overrides(model, args)
    views = _parse_views(args.views, dataset)
    out = Path(args.out) if args.out else Path(args.run)
    result = evaluate(model, dataset, out, views=views, num_draws=args.num_draws, progress=not args.quiet,
                      write_products=not args.no_products)
    _print_summary(result, f"{cfg.method} on {dataset.name}: {len(views)} views, K={result['num_draws']}")
    print(f"metrics: {out / 'metrics.json'}")


def _print_summary(result: dict, title: str) -> None:
    print(title)
    for name, s in result["summary"].items():
        print(f"  {name:<26s} {s['mean']:>10.4f}" + (f"  ({s['num_undefined']} undefined)" if s["num_undefined"] else ""))
    if "pooled_depth" in result:
        p = result["pooled_depth"]
        print(f"  pooled depth |err| vs std: Pearson {p['err_std_pearson']:.3f}, Spearman {p['err_std_spearman']:.3f} over {p['num_pixels']} px")


def cmd_demo(args: argparse.Namespace) -> None:
    """Generate the embedded scene, train S-NeRF, render and score the held-out views."""
    from .evaluate import evaluate
    from .scenes import load_run_dataset
    from .trainer import Trainer

    run_dir = Path(args.out)
    cfg = experiment_from_args(argparse.Namespace(**{**vars(args), "preset": args.preset or "demo"}), run_dir)
    t0 = time.perf_counter()
    dataset = load_run_dataset(cfg, run_dir)
    model = Trainer(cfg, run_dir, dataset).train(progress=not args.quiet)
    t_train = time.perf_counter() - t0
    result = evaluate(model, dataset, run_dir, progress=not args.quiet)
    wall = time.perf_counter() - t0
    result["wall_time_s"] = {"train_and_data": round(t_train, 1), "total": round(wall, 1)}
    from .io_utils import atomic_write_text

    atomic_write_text(run_dir / "metrics.json", json.dumps(result, indent=2, default=float))
    _print_summary(result, f"demo: S-NeRF on the embedded scene, {len(dataset.test_indices)} test views")
    print(f"  wall time: {wall:.0f} s (training incl. data {t_train:.0f} s)")
    print(f"run folder: {run_dir} (checkpoint.pt, metrics.json, views/)")


#: extra commands registered by other modules: name -> (module, help)
EXTRA_COMMANDS = {
    "export": ("stochastic_fields.products.cli", "Export depth maps, uncertainty maps and point clouds of a trained run."),
    "bench": ("stochastic_fields.bench", "Speed-against-error benchmark (see benchmarks/)."),
    "prepare": ("stochastic_fields.data.prepare", "Photos or a video -> camera poses with pycolmap (SfM) -> a scene folder to train on."),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="stochastic-fields", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="Train a method on a scene (resumes from the run folder's checkpoint).")
    p.add_argument("--out", required=True, help="Run folder (created; an existing checkpoint is resumed).")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    _add_experiment_options(p)
    p.set_defaults(func=cmd_train)

    for name, func, helptext in (("render", cmd_render, "Render views of a trained run with colour/depth uncertainty maps."),
                                 ("eval", cmd_eval, "Render and score views of a trained run; writes metrics.json.")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--run", required=True, help="Trained run folder.")
        p.add_argument("--views", default=None, help="'test' (default), 'train', 'all' or indices like 1,2,3.")
        p.add_argument("--num-draws", type=int, default=None, help="K trajectories per ray (default: the run's render.num_draws).")
        p.add_argument("--out", default=None, help="Output folder (default: inside the run folder).")
        p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
        p.add_argument("--colour-estimator", choices=COLOUR_ESTIMATORS, default=None,
                       help="S-NeRF colour statistics: 'draws' (SPEC 3) or 'rao_blackwell' (density draws "
                            "only, colour noise integrated exactly; default: the run's render.colour_estimator).")
        p.add_argument("--quiet", action="store_true", help="No progress bars.")
        if name == "eval":
            p.add_argument("--no-products", action="store_true", help="Only metrics, no per-view files.")
        p.set_defaults(func=func)

    p = sub.add_parser("demo", help="Embedded synthetic scene end to end: generate, train, render, score.")
    p.add_argument("--out", default="runs/demo", help="Run folder.")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    _add_experiment_options(p)
    p.set_defaults(func=cmd_demo)

    import importlib

    for name, (module, helptext) in EXTRA_COMMANDS.items():
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("stochastic_fields"):
                continue
            raise
        p = sub.add_parser(name, help=helptext)
        mod.add_arguments(p)
        p.set_defaults(func=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"stochastic-fields {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
