"""``stochastic-fields``: train | render | eval | demo (and the commands other modules add).

Every option of the experiment config is available as ``--group.name``; ``--help`` on each
command lists them with their explanations.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from . import config as C
from .constants import DISTRIBUTED_TIMEOUT_S
from .defaults import FREE_PATH_RECALIBRATION
from .launch import DistributedError, requested_by_environment
from .settings import COLOUR_ESTIMATORS


def _add_experiment_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default=None, choices=C.PRESETS,
                   help="Start from a named preset (default: 'default', or the run's saved config when resuming). "
                        "What each sets: " + C.presets_help().replace("%", "%%") + ".")
    p.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="JSON file of options with the nested structure of a run's config.json (may be partial), "
                        "applied on top of the preset or saved config; explicit --group.name options override it.")
    C.add_config_arguments(p)


def experiment_from_args(args: argparse.Namespace, run_dir: Path) -> C.ExperimentConfig:
    """The run's saved config when resuming, else the preset; then ``--config FILE``; then
    explicit options. The data path is stored resolved (absolute). Validated."""
    saved = run_dir / "config.json"
    if saved.is_file() and args.preset is None:
        cfg = C.load_config(saved)
    else:
        cfg = C.preset(args.preset or "default")
    if getattr(args, "config", None) is not None:
        C.merge_dict(cfg, C.read_config_file(args.config), str(args.config))
    C.apply_overrides(cfg, args)
    if cfg.data.path:
        cfg.data.path = str(Path(cfg.data.path).expanduser().resolve())
    return cfg


def _parse_views(spec: str | None, dataset) -> list[int]:
    from .data.dataset import parse_views  # deferred: loads only when this command runs (keeps --help fast)

    return parse_views(spec, dataset.num_views, dataset.train_indices, dataset.test_indices)


#: Upper bound of --num-draws (and of render.num_draws): K draws cost K times one render.
MAX_CLI_DRAWS: int = 4096


def _num_draws(text: str) -> int:
    """--num-draws: an integer >= 2 (a variance needs two draws)."""
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2, got {text!r}") from None
    if not 2 <= k <= MAX_CLI_DRAWS:
        raise argparse.ArgumentTypeError(f"must be in [2, {MAX_CLI_DRAWS}] (the uncertainty is a variance over K "
                                         f"draws), got {k}")
    return k


def add_dist_timeout_argument(p: argparse.ArgumentParser) -> None:
    """--dist-timeout of the commands that run under torchrun (train, render, eval, export)."""
    p.add_argument("--dist-timeout", type=float, default=DISTRIBUTED_TIMEOUT_S, metavar="SECONDS",
                   help="Distributed (under torchrun): seconds a rank waits for the others in a collective before it "
                        "stops with an error (default %(default)g).")


def cmd_train(args: argparse.Namespace) -> None:
    from .models.registry import resolve_device  # deferred: loads only when this command runs (keeps --help fast)
    from .scenes import describe_split, load_run_dataset  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import Trainer  # deferred: loads only when this command runs (keeps --help fast)
    from .models.field_builder import grid_field  # deferred: loads only when this command runs (keeps --help fast)

    from .io_utils import check_output_folder  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import check_resume  # deferred: loads only when this command runs (keeps --help fast)

    run_dir = check_output_folder(args.out, "--out")
    cfg = experiment_from_args(args, run_dir)
    if args.distributed or requested_by_environment():
        _train_distributed(args, run_dir, cfg)
        return
    check_resume(run_dir, cfg)  # before anything is written or generated
    resolve_device(cfg.train.device)  # an absent CUDA device is refused before the scene is generated
    dataset = load_run_dataset(cfg, run_dir)
    print(describe_split(dataset, cfg))
    trainer = Trainer(cfg, run_dir, dataset)
    grid = grid_field(trainer.model)
    if grid is not None:
        print(f"grid: {grid.describe()}, sized by the {cfg.field.grid_resolution_rule} rule "
              f"(field.grid_resolution_rule) under the {cfg.field.grid_max_cells:,}-cell cap")
    model = trainer.train(progress=not args.quiet)
    print(f"trained: {run_dir / 'checkpoint.pt'} ({trainer.step} steps, {trainer.elapsed / 60:.1f} training minutes)")
    _calibrate_after_training(run_dir, model, dataset, progress=not args.quiet)


def _train_distributed(args: argparse.Namespace, run_dir: Path, cfg: C.ExperimentConfig) -> None:
    """``train`` as one rank of a data-parallel run (torchrun's environment; see
    stochastic_fields.distributed). Rank 0 writes the run folder and fits the calibration."""
    from .distributed import process_group  # deferred: loads only when this command runs (keeps --help fast)
    from .scenes import load_run_dataset  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import Trainer, check_resume  # deferred: loads only when this command runs (keeps --help fast)

    with process_group(cfg.train.device, timeout_s=args.dist_timeout) as ctx:
        # rank 0's config everywhere (on another host the run folder's config.json may be absent)
        cfg = C.from_dict(C.ExperimentConfig, ctx.broadcast_object(C.to_dict(cfg), what="the run's config from rank 0"))
        check_resume(run_dir, cfg)  # every rank, before anything is written or generated
        with ctx.main_first("rank 0 loads or generates the scene"):
            dataset = load_run_dataset(cfg, run_dir)
        model = Trainer(cfg, run_dir, dataset, distributed=ctx).train(progress=not args.quiet)
    if ctx.is_main:  # the other ranks are done; the calibration is rank 0's alone
        print(f"trained on {ctx.world_size} processes ({ctx.backend}): {run_dir / 'checkpoint.pt'}")
        _calibrate_after_training(run_dir, model, dataset, progress=not args.quiet)


def _calibrate_after_training(run_dir: Path, model, dataset, *, progress: bool = True):
    """Fit the recalibration of an S-NeRF run (calibration.json): depth from its capture points,
    colour from the pixels it held out of training (``train.holdout_fraction``); a run with neither
    keeps the raw stds (said, not an error); ``progress``: a bar over the training views the
    free-space check renders, which also check the training photos' poses (``pose_check``, said).
    Returns the calibration or None."""
    from .calibration import calibrate_run, describe  # deferred: loads only when this command runs (keeps --help fast)
    from .pose_check import load_training_fit  # deferred: loads only when this command runs (keeps --help fast)

    if not getattr(model, "accepts_depth", False):
        return None
    try:
        calibration = calibrate_run(run_dir, model=model, dataset=dataset, progress=progress)
    except ValueError as exc:
        print(f"uncertainty not recalibrated: {exc}")
        calibration = None
    else:
        print(f"uncertainty recalibrated ({run_dir / 'calibration.json'}): {describe(calibration)}")
    fit = load_training_fit(run_dir)
    if fit is not None:
        print(fit.summary())
    if calibration is None:
        return None
    if FREE_PATH_RECALIBRATION and calibration.depth is not None:
        from .products.free_path_calibration import recalibrate_free_path  # deferred: loads only when used

        recalibrate_free_path(run_dir, model, dataset)
    return calibration


def _run_calibration(args: argparse.Namespace):
    """The run's calibration.json unless --raw-uncertainty."""
    from .calibration import load_run_calibration  # deferred: loads only when this command runs (keeps --help fast)

    return None if args.raw_uncertainty else load_run_calibration(Path(args.run))


def _render_options(model, args: argparse.Namespace):
    """This command's render options: the run's, with ``--num-draws`` and ``--colour-estimator``."""
    return model.render_options(num_draws=args.num_draws, colour_estimator=args.colour_estimator)


def _render_and_score(args: argparse.Namespace, default_out: Path, product_views: int | None):
    """What ``render`` and ``eval`` share: the run loaded, its views rendered and scored by
    ``evaluation.evaluate`` into ``--out`` (default ``default_out``), sharded over the ranks of a
    torchrun launch. Returns (config, dataset, views, metrics, out folder, DistContext or None)."""
    from .capture_points import score_sparse_depth  # deferred: loads only when this command runs (keeps --help fast)
    from .evaluation import evaluate  # deferred: loads only when this command runs (keeps --help fast)
    from .io_utils import check_no_symlinks, check_output_folder  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import load_trained_model  # deferred: loads only when this command runs (keeps --help fast)

    from .distributed import sharding_from_environment  # deferred: loads only when this command runs (keeps --help fast)

    out = check_output_folder(args.out if args.out is not None else default_out, "--out")
    check_no_symlinks(out, "views", "metrics.json")
    with sharding_from_environment(args.run, args.device, timeout_s=args.dist_timeout) as ctx:
        device = args.device if ctx is None else str(ctx.device)
        cfg, model, dataset = load_trained_model(Path(args.run), device=device)
        views = _parse_views(args.views, dataset)
        result = evaluate(model, dataset, out, views=views, options=_render_options(model, args),
                          progress=not args.quiet, product_views=product_views,
                          calibration=_run_calibration(args), distributed=ctx,
                          sparse_depth=score_sparse_depth(dataset, views))
    return cfg, dataset, views, result, out, ctx


def cmd_render(args: argparse.Namespace) -> None:
    _, _, views, _, out, ctx = _render_and_score(args, Path(args.run) / "renders", None)
    if ctx is None or ctx.is_main:
        print(f"rendered {len(views)} views into {out / 'views'}" + _on_ranks(ctx))


def cmd_eval(args: argparse.Namespace) -> None:
    cfg, dataset, views, result, out, ctx = _render_and_score(args, Path(args.run),
                                                              0 if args.no_products else None)
    if ctx is None or ctx.is_main:
        _print_summary(result, f"{cfg.method} on {dataset.name}: {len(views)} views, K={result['num_draws']}"
                       + _on_ranks(ctx))
        _print_pose_check(result)
        print(f"metrics: {out / 'metrics.json'}")


def _print_pose_check(result: dict) -> None:
    """The pose check ``evaluate`` recorded (``pose_check``): one line per group of photos scored."""
    from .pose_check import fit_from_dict  # deferred: loads only when this command runs (keeps --help fast)

    for stored in result.get("pose_check", {}).values():
        print("  " + fit_from_dict(stored).summary())


def _on_ranks(ctx) -> str:
    return "" if ctx is None else f" (sharded over {ctx.world_size} processes, {ctx.backend})"


def _print_summary(result: dict, title: str) -> None:
    print(title)
    for name, s in result["summary"].items():
        print(f"  {name:<26s} {s['mean']:>10.4f}" + (f"  ({s['num_undefined']} undefined)" if s["num_undefined"] else ""))
    depth = result.get("pooled", {}).get("depth")
    if depth:
        scored = "SfM points (SCORE role)" if result.get("depth_source") == "sparse" else "px"
        print(f"  pooled depth: abs-rel {depth['abs_rel']:.4f}; |err| vs std: Pearson {depth['pearson']:.3f}, Spearman "
              f"{depth['spearman']:.3f} over {depth['num_used']} {scored}; coverage 68% {depth['coverage_68']:.3f}, "
              f"95% {depth['coverage_95']:.3f}")
    iv = result.get("pooled", {}).get("depth_intervals")
    if iv and math.isfinite(iv.get("coverage_95", math.nan)):
        from .evaluation import INTERVAL_PLOT  # deferred: loads only when this command runs (keeps --help fast)
        from .metrics import INTERVAL_LEVELS, level_name  # deferred: loads only when this command runs (keeps --help fast)

        names = [level_name(p) for p in INTERVAL_LEVELS]
        print("  depth intervals " + "/".join(names) + "%: coverage "
              + "/".join(f"{100 * iv[f'coverage_{n}']:.1f}" for n in names)
              + f"; 95% half-width / depth: median {100 * iv['halfwidth_median_95']:.1f}%, "
              f"90th percentile {100 * iv['halfwidth_p90_95']:.1f}%; interval score / depth 68% "
              f"{iv['interval_score_68']:.3f}, 95% {iv['interval_score_95']:.3f}; CRPS / depth {iv['crps']:.4f} "
              f"(plot: {INTERVAL_PLOT})")
        if math.isfinite(iv.get("coverage_95_narrowest_third", math.nan)):
            print(f"  where the 95% band is narrowest (a third of the depths, half-width at most "
                  f"{100 * iv['halfwidth_95_narrowest_third_max']:.1f}% of the depth): coverage 68% "
                  f"{100 * iv['coverage_68_narrowest_third']:.1f}, 95% {100 * iv['coverage_95_narrowest_third']:.1f}; "
                  f"widest third: 68% {100 * iv['coverage_68_widest_third']:.1f}, "
                  f"95% {100 * iv['coverage_95_widest_third']:.1f}")


def set_aside_run(run_dir: Path) -> Path:
    """Rename ``run_dir`` to the first free ``<run_dir>.previous``, ``.previous-2``, ... and return
    the new path: nothing in it is lost, and ``run_dir`` is free for a new run."""
    run_dir = Path(run_dir)
    for n in range(1, 10_000):
        target = run_dir.with_name(run_dir.name + (".previous" if n == 1 else f".previous-{n}"))
        if not target.exists():
            run_dir.rename(target)
            return target
    raise ValueError(f"{run_dir}: no free name to set the old run aside (.previous ... .previous-9999 exist)")


def cmd_demo(args: argparse.Namespace) -> None:
    """Generate the embedded scene, train S-NeRF, render and score the held-out views."""
    from .evaluation import evaluate  # deferred: loads only when this command runs (keeps --help fast)
    from .models.registry import resolve_device  # deferred: loads only when this command runs (keeps --help fast)
    from .scenes import load_run_dataset  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import Trainer  # deferred: loads only when this command runs (keeps --help fast)

    from .io_utils import check_output_folder  # deferred: loads only when this command runs (keeps --help fast)
    from .trainer import describe_differences, resume_differences  # deferred: loads only when this command runs (keeps --help fast)

    run_dir = check_output_folder(args.out, "--out")
    cfg = experiment_from_args(argparse.Namespace(**{**vars(args), "preset": args.preset or "demo"}), run_dir)
    diffs = resume_differences(run_dir, cfg)
    if diffs:  # a run of other options (an older version's defaults): kept, not resumed
        kept = set_aside_run(run_dir)
        print(f"demo: {run_dir} holds a run made with other options; moved it to {kept} and training afresh "
              f"({describe_differences(diffs)})")
    resolve_device(cfg.train.device)
    t0 = time.perf_counter()
    dataset = load_run_dataset(cfg, run_dir)
    model = Trainer(cfg, run_dir, dataset).train(progress=not args.quiet)
    calibration = _calibrate_after_training(run_dir, model, dataset, progress=not args.quiet)
    t_train = time.perf_counter() - t0
    result = evaluate(model, dataset, run_dir, progress=not args.quiet, calibration=calibration)
    wall = time.perf_counter() - t0
    result["wall_time_s"] = {"train_and_data": round(t_train, 1), "total": round(wall, 1)}
    from .io_utils import atomic_write_text  # deferred: loads only when this command runs (keeps --help fast)

    atomic_write_text(run_dir / "metrics.json", json.dumps(result, indent=2, default=float))
    _print_summary(result, f"demo: S-NeRF on the embedded scene, {len(dataset.test_indices)} test views")
    print(f"  wall time: {wall:.0f} s (training incl. data {t_train:.0f} s)")
    print(f"run folder: {run_dir} (checkpoint.pt, metrics.json, views/)")


#: Commands that run as ranks of a torchrun launch: train (data-parallel), render/eval/export
#: (views sharded over the ranks). The others refuse a multi-rank launch: demo (train with
#: torchrun, then eval), calibrate (one fit over every capture point), occupancy and free-path
#: (one volume or path), rosbag/rerun (one stream written in order), prepare (one SfM solve).
DISTRIBUTED_COMMANDS: tuple[str, ...] = ("train", "render", "eval", "export")

#: extra commands of the library's own modules: name -> (module, help). Packages above the library
#: (the benchmarks' ``bench``) add theirs through the ``stochastic_fields.commands`` entry-point group
#: (pyproject.toml), so that the library never imports them.
EXTRA_COMMANDS = {
    "export": ("stochastic_fields.products.cli", "Export depth maps, uncertainty maps and point clouds of a trained run."),
    "calibrate": ("stochastic_fields.commands.calibrate",
                  "Fit a run's uncertainty recalibration (calibration.json): depth from its capture points, "
                  "colour from the pixels it held out of training."),
    "occupancy": ("stochastic_fields.commands.occupancy", "Occupancy probabilities of a run (npz + OctoMap .ot)."),
    "free-path": ("stochastic_fields.commands.free_path", "P(collision-free) of segments or a path, with its error."),
    "rosbag": ("stochastic_fields.commands.rosbag", "ROS 2 bag (depth, std, CameraInfo, colour, PointCloud2) of an export."),
    "rerun": ("stochastic_fields.commands.rerun", "rerun recording (.rrd) of an export."),
    "next-view": ("stochastic_fields.commands.next_view",
                  "Rank candidate cameras by the information a photo from each would give the run."),
    "prepare": ("stochastic_fields.commands.prepare", "Photos or a video -> camera poses with pycolmap (SfM) -> a scene folder to train on."),
}


#: entry-point group through which installed packages add commands (module with add_arguments and run)
COMMAND_ENTRY_POINTS = "stochastic_fields.commands"


class _Parser(argparse.ArgumentParser):
    """argparse with a short error: the bad option and value on one line, and where the help is
    (the full usage of the config options runs to dozens of lines)."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n(see '{self.prog} --help')\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The CLI's parser. The modules of the extra commands (export, prepare, ... and those of
    installed packages) are imported only for ``command`` (None: all of them; "": none), so that a command
    does not pay for the imports of the others (trimesh, Open3D, pycolmap)."""
    parser = _Parser(prog="stochastic-fields", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="Train a method on a scene (resumes from the run folder's checkpoint).")
    p.add_argument("--out", required=True, help="Run folder (created; an existing checkpoint is resumed).")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    p.add_argument("--distributed", action="store_true",
                   help="Data-parallel training as one rank of a torchrun launch (implied when torchrun's RANK and "
                        "WORLD_SIZE are set): 'torchrun --nproc_per_node N -m stochastic_fields.cli train ...'. "
                        "Each rank draws train.rays_per_batch / N rays per step; gradients are averaged.")
    add_dist_timeout_argument(p)
    _add_experiment_options(p)
    p.set_defaults(func=cmd_train)

    for name, func, helptext in (("render", cmd_render, "Render views of a trained run with colour/depth uncertainty maps."),
                                 ("eval", cmd_eval, "Render and score views of a trained run; writes metrics.json.")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--run", required=True, help="Trained run folder.")
        p.add_argument("--views", default=None, help="'test' (default), 'train', 'all' or indices like 1,2,3.")
        p.add_argument("--render.num_draws", "--render.num-draws", "--num-draws", dest="num_draws", type=_num_draws,
                       default=None, help="K trajectories per ray, >= 2: a fixed K for this render (default: the "
                                          "run's render.num_draws, or its adaptive K).")
        p.add_argument("--out", default=None, help="Output folder (default: inside the run folder).")
        p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
        p.add_argument("--render.colour_estimator", "--render.colour-estimator", "--colour-estimator",
                       dest="colour_estimator", choices=COLOUR_ESTIMATORS, default=None,
                       help="S-NeRF colour statistics: 'draws' (docs/definitions.md §3) or 'rao_blackwell' (density "
                            "draws only, colour noise integrated exactly; default: the run's render.colour_estimator).")
        p.add_argument("--raw-uncertainty", action="store_true",
                       help="Ignore the run's calibration.json: depth_std is the raw rendered std (by default the "
                            "recalibrated std, with the raw one kept as depth_std_raw).")
        p.add_argument("--quiet", action="store_true", help="No progress bars.")
        add_dist_timeout_argument(p)
        if name == "eval":
            p.add_argument("--no-products", action="store_true", help="Only metrics, no per-view files.")
        p.set_defaults(func=func)

    p = sub.add_parser("demo", help="Embedded synthetic scene end to end: generate, train, render, score.")
    p.add_argument("--out", default="runs/demo", help="Run folder.")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    _add_experiment_options(p)
    p.set_defaults(func=cmd_demo)

    import importlib  # deferred: loads only when this command runs (keeps --help fast)
    from importlib.metadata import entry_points  # deferred: loads only when this command runs (keeps --help fast)

    commands = {name: (lambda module=module: importlib.import_module(module), helptext)
                for name, (module, helptext) in EXTRA_COMMANDS.items()}
    for ep in entry_points(group=COMMAND_ENTRY_POINTS):
        commands.setdefault(ep.name, (ep.load, None))
    for name, (load, helptext) in commands.items():
        if command is not None and name != command:
            sub.add_parser(name, help=helptext or f"(see 'stochastic-fields {name} --help')")
            continue
        try:
            mod = load()
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("stochastic_fields"):
                continue
            raise
        p = sub.add_parser(name, help=helptext or (mod.__doc__ or "").strip().split("\n")[0])
        mod.add_arguments(p)
        p.set_defaults(func=mod.run)
    return parser


def _describe_os_error(exc: OSError) -> str:
    """One line for an environment error: what failed, on which file, and why."""
    import errno  # deferred: loads only when this command runs (keeps --help fast)

    where = f" {exc.filename}" if exc.filename else ""
    reason = exc.strerror or str(exc)
    hints = {errno.ENOSPC: "free some space or choose another --out",
             errno.EACCES: "check the folder's permissions or choose another --out",
             errno.EROFS: "the file system is read-only; choose another --out",
             errno.EEXIST: "a file is in the way of a folder",
             errno.ENOTDIR: "a file is in the way of a folder",
             errno.EISDIR: "a folder is where a file was expected"}
    hint = hints.get(exc.errno or -1)
    return f"cannot access{where}: {reason}" + (f" ({hint})" if hint else "")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), "")  # "": no command yet (top-level help)
    args = build_parser(command).parse_args(argv)
    try:
        if (args.command not in DISTRIBUTED_COMMANDS and requested_by_environment()
                and int(os.environ.get("WORLD_SIZE", "1")) > 1):
            raise ValueError(f"'{args.command}' does not run distributed: only {', '.join(DISTRIBUTED_COMMANDS)} do "
                             "under torchrun; run it in one process (without torchrun)")
        args.func(args)
    except (ValueError, FileNotFoundError, FloatingPointError, DistributedError) as exc:
        print(f"stochastic-fields {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # permissions, full disk, a file where a folder should be
        print(f"stochastic-fields {args.command}: error: {_describe_os_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stochastic-fields {args.command}: interrupted (complete files only were written; training "
              "resumes from its last checkpoint)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
