"""Where a capture's training step spends its time: the torch profiler's operations, by their own time.

``capture_step_cost.py`` times whole steps against each other; this breaks one configuration's step into
the operations it runs. S-NeRF (or ``--method``) trains on the capture split as the capture bench
configures it (``capture_quality.config_for``: ``--preset llff``) to ``--warmup`` steps, then the profiler
records ``--steps`` more and the table lists the operations by their self time per step (the grid's
compiled row loops appear as their autograd node ``_WeightedRowGatherBackward`` and the optimiser's
``RowSparseAdam.step``). Profiling adds its own overhead; compare shares, and time steps with
``capture_step_cost.py``.

    OMP_NUM_THREADS=2 python benchmarks/studies/capture_step_profile.py --scene fern --threads 2 \\
        --out benchmarks/results/capture_step_profile/capture_fern.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # capture_quality, beside this folder

from capture_quality import LLFF_ROOT, config_for, parse_setting  # noqa: E402

from stochastic_fields.io_utils import atomic_write_text  # noqa: E402
from stochastic_fields.scenes import load_run_dataset  # noqa: E402
from stochastic_fields.trainer import Trainer  # noqa: E402


def _self_ms(prof) -> dict[str, tuple[float, int]]:
    """{operation: (self ms, calls)} of a profile."""
    return {e.key: (e.self_cpu_time_total / 1000, e.count) for e in prof.key_averages()}


def profile_steps(scene: str, method: str, *, warmup: int, steps: int, seed: int = 0,
                  settings: tuple[tuple[str, object], ...] = (), llff_root: Path = LLFF_ROOT) -> tuple[float, list[tuple[str, float, float]]]:
    """(ms per step over ``steps`` steps after ``warmup``, by the trainer's loop clock, unprofiled;
    [(operation, self ms per step, calls per step)] of the next ``steps`` profiled steps, largest first).
    Each ``train`` call first builds its ray batches' source; the profile of a call with no step is
    subtracted, so the table holds the steps alone."""
    # a schedule far past the profiled steps: the learning rate is where the capture bench has it
    cfg = config_for(scene, method, 10 * (warmup + 2 * steps), seed, settings, llff_root)
    cfg.train.minutes = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the capture's lens-distortion note
            dataset = load_run_dataset(cfg, Path(tmp))
        trainer = Trainer(cfg, Path(tmp), dataset)
        trainer.save = lambda: None  # no checkpoint writes between the parts
        trainer.train(progress=False, max_steps=warmup)
        before = trainer.elapsed
        trainer.train(progress=False, max_steps=steps)
        ms_per_step = 1000 * (trainer.elapsed - before) / steps
        with profile(activities=[ProfilerActivity.CPU]) as setup:
            trainer.train(progress=False, max_steps=0)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            trainer.train(progress=False, max_steps=steps)
    base = _self_ms(setup)
    rows = [(key, (ms - base.get(key, (0.0, 0))[0]) / steps, (n - base.get(key, (0.0, 0))[1]) / steps)
            for key, (ms, n) in _self_ms(prof).items()]
    return ms_per_step, sorted(rows, key=lambda r: -r[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="fern")
    ap.add_argument("--method", default="snerf")
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (stated in the table)")
    ap.add_argument("--rows", type=int, default=25)
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="Config overrides on top of the capture bench's configuration (repeatable).")
    ap.add_argument("--out", type=Path, required=True, help="markdown table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ms, rows = profile_steps(args.scene, args.method, warmup=args.warmup, steps=args.steps,
                             settings=tuple(args.set))
    total = sum(r[1] for r in rows)
    lines = [f"# A capture training step's operations: {args.scene}, {args.method}", "",
             f"Command: `python benchmarks/studies/capture_step_profile.py --scene {args.scene} --method {args.method} "
             f"--warmup {args.warmup} --steps {args.steps} --threads {args.threads}"
             + "".join(f" --set {k}={v}" for k, v in args.set) + f"` ({args.threads} torch threads; "
             f"steps {args.warmup + args.steps + 1}-{args.warmup + 2 * args.steps} profiled, the training call's set-up "
             f"subtracted). Unprofiled, by the trainer's loop clock: {ms:.0f} ms a step; profiled self time "
             f"{total:.0f} ms a step.", "",
             "| operation | self ms / step | share | calls / step |", "|---|---|---|---|"]
    lines += [f"| `{name}` | {t:.1f} | {100 * t / total:.1f}% | {n:.0f} |" for name, t, n in rows[:args.rows]]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
