"""Reproduce the paper's Tables 1-3 (and the depth / calibration tables) on LLFF scenes.

Trains every method on every scene with the protocol of docs/definitions.md §7 (LLFF images_8, every 5th view
trains, same budget and seed for all; ``--protocol fewview|dense`` for the literature's splits), scores the test views, times one full-view render per
method, and writes ``tables.json``, ``tables.md`` and ``plots/*.png`` into ``--out``. Every stage
is resumable: run the same command again after an interruption and finished stages are skipped.

Examples::

    # the documented CPU budget (about 1.5 hours on 2 CPU cores; a GPU is used when present)
    python benchmarks/eval_tables.py --scenes fern flower --out benchmarks/results/eval_tables

    # the few-view protocol of the literature (every 8th view tests, 3 of the others train), S-NeRF alone
    python benchmarks/eval_tables.py --protocol fewview --views 3 --methods snerf_default \
        --out benchmarks/results/eval_tables_fewview3

    # the paper-scale budget (llff preset, every test view: for a GPU)
    python benchmarks/eval_tables.py --budget full --scenes fern flower --out results/eval_tables_full

    # the CI configuration: images_16 fern, 20 iterations, 2 methods, 2 test views (about a minute)
    python benchmarks/eval_tables.py --tiny --scenes fern --methods deterministic snerf --max-views 2 \\
        --out /tmp/eval_tables_tiny

    # the stages (method x scene) dealt over 2 processes (or hosts: --nnodes, --rdzv-endpoint, and
    # --out on a file system every host shares); rank 0 writes the tables once all are done
    torchrun --nproc_per_node 2 benchmarks/eval_tables.py --scenes fern flower --out results/eval_tables
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"


def build_parser() -> argparse.ArgumentParser:
    from stochastic_fields_bench.tables import (DEFAULT_METHODS, DEFAULT_SCENES, METHOD_SPECS, PROTOCOLS,
                                                TABLES_DIST_TIMEOUT_S)

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES),
                   help="Scene names under --data-root, or scene folders (default: fern flower).")
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT,
                   help="Folder holding the LLFF scenes (default: ../shared/data/nerf_llff_data).")
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=sorted(METHOD_SPECS),
                   help="Methods and ablations to run (default: all).")
    p.add_argument("--images", default=None, help="LLFF image folder (default images_8; images_16 with --tiny).")
    p.add_argument("--iterations", type=int, default=None,
                   help="Training steps of every method (default: the budget's; 20 with --tiny).")
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/eval_tables"), help="Output folder (resumable).")
    p.add_argument("--seed", type=int, default=0, help="Seed of every method (default 0).")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda.")
    p.add_argument("--budget", choices=("cpu", "full"), default="cpu",
                   help="'cpu' (default, the documented budget): 1000 steps per 762k training pixels (fern 1000, flower 1750; "
                   "at most 2000), grid <= 250k cells, 4 test views per scene; "
                   "'full': the llff preset (3000 steps, 2M cells, every test view; for a GPU).")
    p.add_argument("--protocol", choices=PROTOCOLS, default="paper",
                   help="The split: 'paper' (default; every 5th view trains, the others test), 'fewview' (every 8th "
                        "view tests, --views of the others train, spread evenly: RegNeRF's protocol of the few-view "
                        "literature) or 'dense' (every 8th view tests, all others train). Use one --out per protocol.")
    p.add_argument("--views", type=int, default=3, help="Training views of --protocol fewview (3, 6 or 9; default 3).")
    p.add_argument("--max-views", type=int, default=None,
                   help="Score N test views spread evenly over the test set (default: the budget's).")
    p.add_argument("--product-views", type=int, default=1,
                   help="Write npz/PNG products of the first N test views per method (default 1).")
    p.add_argument("--no-timing", action="store_true", help="Skip the full-view render timing (Table 2).")
    p.add_argument("--timing-repeats", type=int, default=None,
                   help="Timed renders of the view per method; the median is reported (default 3; 1 with --tiny).")
    p.add_argument("--tiny", action="store_true",
                   help="CI configuration: images_16, small grid, few samples and iterations.")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="Config override for every method, e.g. --set render.num_samples=32 (JSON values; repeatable). "
                   "A method's own settings (loss.kl of the ablations, field.dropout of mc_dropout) take precedence.")
    p.add_argument("--quiet", action="store_true", help="No progress bars.")
    p.add_argument("--distributed", action="store_true",
                   help="Run as one rank of a torchrun launch (implied when torchrun's RANK and WORLD_SIZE are set): "
                        "the (scene, method) stages are dealt round-robin over the ranks; rank 0 writes the tables.")
    p.add_argument("--dist-timeout", type=float, default=TABLES_DIST_TIMEOUT_S, metavar="SECONDS",
                   help="Distributed: seconds a rank waits at the final barrier for the others' stages "
                        "(default %(default)g).")
    return p


def parse_override(text: str) -> tuple[str, object]:
    """'render.num_samples=32' -> ('render.num_samples', 32); values are JSON, else strings."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"--set expects PATH=VALUE, got {text!r}")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.strip(), value


def main(argv: list[str] | None = None) -> int:
    from stochastic_fields_bench.tables import BenchmarkSettings, format_markdown, run_benchmark

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        overrides = tuple(parse_override(t) for t in args.overrides)
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    images = args.images or ("images_16" if args.tiny else "images_8")
    settings = BenchmarkSettings(budget=args.budget, images=images, iterations=args.iterations, seed=args.seed, device=args.device,
                                 max_views=args.max_views, product_views=args.product_views,
                                 timing=not args.no_timing, timing_repeats=args.timing_repeats or (1 if args.tiny else 3),
                                 tiny=args.tiny, overrides=overrides, protocol=args.protocol, train_views=args.views)
    command = "python benchmarks/eval_tables.py " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    from stochastic_fields.distributed import DistributedError, process_group, requested_by_environment

    try:
        if args.distributed or requested_by_environment():
            with process_group(args.device, timeout_s=args.dist_timeout) as ctx:
                if ctx.device.type == "cuda":  # one GPU per rank
                    settings = dataclasses.replace(settings, device=str(ctx.device))
                tables = run_benchmark(args.scenes, args.methods, args.out, settings, data_root=args.data_root,
                                       progress=not args.quiet, command=command, distributed=ctx)
            if not ctx.is_main:
                return 0
        else:
            tables = run_benchmark(args.scenes, args.methods, args.out, settings, data_root=args.data_root,
                                   progress=not args.quiet, command=command)
    except (ValueError, FileNotFoundError, DistributedError) as exc:
        print(f"eval_tables: error: {exc}", file=sys.stderr)
        return 2
    print(format_markdown(tables))
    print(f"wrote {args.out / 'tables.md'}, {args.out / 'tables.json'} and {len(tables['plots'])} plots "
          f"({tables['wall_s_this_invocation']:.0f} s this invocation)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
