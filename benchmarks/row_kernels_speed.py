"""Training step time with the grid's compiled row loops against the same steps as torch ops.

``row_kernels`` runs the backward of the grid's row gathers and the lazy Adam update as
compiled loops on the CPU; the torch ops they replace still run on CUDA and without numba. This
times both on the same trainer, in one process, alternating: each method trains ``--warmup``
steps on the capture split (``--preset llff``, the default split: every 8th photo validates; past
the empty-space occupancy warm-up), then ``--rounds`` times ``--steps`` steps with the compiled
loops and ``--steps`` steps with torch ops, so drifts of the machine hit both alike. The trainer's
loop clock; one torch thread, or ``--threads N``: then the compiled loops split over the N threads
are also timed against the same loops on one thread (``row_kernels.serial_loops``). With
``--prefetch`` the compiled loops are timed against themselves without their prefetch hints
(``row_kernels.without_prefetch``: the same values bit for bit), and torch ops are not timed.

Both paths give the same values up to float rounding (tests/test_grid_backend.py), so the training
itself is not compared here: ``benchmarks/capture_quality.py`` measures what the faster steps buy
in ten minutes.

    OMP_NUM_THREADS=1 python benchmarks/row_kernels_speed.py --out benchmarks/results/row_kernels
    OMP_NUM_THREADS=2 python benchmarks/row_kernels_speed.py --threads 2 --out benchmarks/results/row_kernels_threads
    OMP_NUM_THREADS=1 python benchmarks/row_kernels_speed.py --prefetch --out benchmarks/results/row_kernels_prefetch
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from stochastic_fields import row_kernels
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.scenes import load_run_dataset
from stochastic_fields.trainer import Trainer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from capture_quality import config_for  # noqa: E402  (the capture benchmark's configuration)


def time_steps(trainer: Trainer, steps: int) -> float:
    before = trainer.elapsed
    trainer.train(progress=False, max_steps=steps)
    return (trainer.elapsed - before) / steps


def measure(scene: str, method: str, *, warmup: int, steps: int, rounds: int, work: Path,
            threads: int = 1, prefetch: bool = False) -> dict:
    """One row: the paths' seconds per step (medians over the rounds) and their ratios (module doc)."""
    paths = 3 if threads > 1 and not prefetch else 2  # compiled, torch ops or no hints (and serial loops)
    cfg = config_for(scene, method, warmup + paths * rounds * steps, seed=0)
    run_dir = work / f"{scene}_{method}"
    dataset = load_run_dataset(cfg, run_dir)
    trainer = Trainer(cfg, run_dir, dataset)
    trainer.train(progress=False, max_steps=warmup)
    compiled, other, serial = [], [], []
    for _ in range(rounds):
        compiled.append(time_steps(trainer, steps))
        with row_kernels.without_prefetch() if prefetch else row_kernels.torch_ops_only():
            other.append(time_steps(trainer, steps))
        if threads > 1 and not prefetch:
            with row_kernels.serial_loops():
                serial.append(time_steps(trainer, steps))
    shutil.rmtree(run_dir, ignore_errors=True)
    c, t = float(np.median(compiled)), float(np.median(other))  # medians: robust to a disturbed block
    row = {"scene": scene, "method": method, "train_views": len(dataset.train_indices), "threads": threads,
           "compiled_s_per_step": c}
    if prefetch:
        return row | {"no_prefetch_s_per_step": t, "prefetch_speedup": t / c, "rounds_compiled": compiled,
                      "rounds_no_prefetch": other}
    row.update(torch_ops_s_per_step=t, speedup=t / c, rounds_compiled=compiled, rounds_torch_ops=other)
    if serial:
        row.update(serial_loops_s_per_step=float(np.median(serial)), split_speedup=float(np.median(serial)) / c,
                   rounds_serial_loops=serial)
    return row


def prefetch_report(rows: list[dict], command: str, threads: int = 1) -> str:
    lines = ["# Training step time: the compiled row loops with and without their prefetch hints", "",
             f"Command: `{command}` ({threads} torch thread{'s' if threads > 1 else ''}; the trainer's loop clock; both "
             "paths on the same trainer, alternating, after the warm-up; the median over the rounds; the two paths "
             "compute the same values bit for bit).", "",
             "| scene | method | training photos | s / step with hints | s / step without | speed-up |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | {r['train_views']} | {r['compiled_s_per_step']:.3f} "
                     f"| {r['no_prefetch_s_per_step']:.3f} | {r['prefetch_speedup']:.2f}x |")
    return "\n".join(lines) + "\n"


def report(rows: list[dict], command: str, threads: int = 1) -> str:
    split = threads > 1
    lines = ["# Training step time: compiled row loops against torch ops", "",
             f"Command: `{command}` ({threads} torch thread{'s' if split else ''}; the trainer's loop clock; every "
             "path on the same trainer, alternating, after the warm-up; the median over the rounds"
             + ("; 'compiled' splits the loops' rows over the threads, 'serial loops' runs them on one" if split else "")
             + ").", "",
             "| scene | method | training photos | s / step compiled | s / step torch ops | speed-up |"
             + (" s / step serial loops | split speed-up |" if split else ""),
             "|---|---|---|---|---|---|" + ("---|---|" if split else "")]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | {r['train_views']} | {r['compiled_s_per_step']:.3f} "
                     f"| {r['torch_ops_s_per_step']:.3f} | {r['speedup']:.2f}x |"
                     + (f" {r['serial_loops_s_per_step']:.3f} | {r['split_speedup']:.2f}x |" if split else ""))
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["fern", "flower"])
    p.add_argument("--methods", nargs="+", default=["snerf", "deterministic"])
    p.add_argument("--warmup", type=int, default=300, help="Steps before timing (past the occupancy warm-up).")
    p.add_argument("--steps", type=int, default=40, help="Steps per timed block.")
    p.add_argument("--rounds", type=int, default=2, help="Blocks per path, alternating.")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads; above 1 the loops split over them are also timed against serial loops.")
    p.add_argument("--prefetch", action="store_true",
                   help="Time the compiled loops against themselves without their prefetch hints (no torch ops).")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if args.threads < 1:
        raise SystemExit(f"--threads must be >= 1, got {args.threads}")
    if row_kernels.numba is None:
        raise SystemExit("numba is not installed: nothing to compare (pip install -r requirements-cpu.txt)")
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/row_kernels_speed.py " + " ".join(sys.argv[1:] if argv is None else argv)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for scene in args.scenes:
            for method in args.methods:
                rows.append(measure(scene, method, warmup=args.warmup, steps=args.steps, rounds=args.rounds,
                                    work=Path(work), threads=args.threads, prefetch=args.prefetch))
                print(json.dumps({k: v for k, v in rows[-1].items() if not k.startswith("rounds")}), flush=True)
                atomic_write_text(args.out / "results.json", json.dumps({"command": command, "rows": rows}, indent=2))
                atomic_write_text(args.out / "README.md",
                                  (prefetch_report if args.prefetch else report)(rows, command, args.threads))


if __name__ == "__main__":
    main()
