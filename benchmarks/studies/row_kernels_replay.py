"""The grid's compiled row loops replayed on a trained run's own inputs, alone, many times.

A training step's time moves by 10-20% from one block of steps to the next on a shared machine, more
than a change to one loop of the step can show. This times the two loops of ``row_kernels`` alone on
what a real step gives them: a trained run (e.g. ``make bench-capture``'s ten-minute S-NeRF run) is
copied to ``--work`` and resumed for three steps, and the last step's scatter calls (every grid level's
backward in each of the step's passes: rows, weights, gradient rows) are recorded. Then, ``--rounds``
times, alternating:

* the scatter calls into zeroed tables, and the lazy Adam update of the tables they touched (random
  moments, steps 1-3 in turn, one second-moment decay per channel as ``train.adam_beta2_colour`` sets);
* each way asked for: ``today`` (the loops split over the torch threads, as training runs them),
  ``serial`` (``row_kernels.serial_loops``), ``zeros_added`` (the scatter adding the zero products of
  samples without gradient, ``row_kernels.adding_zero_rows``), and with ``--against PATH`` the
  ``row_kernels.py`` of another checkout (e.g. a worktree of an earlier commit), split and serial.

Every way must give today's values bit for bit (checked on the first rounds; the run stops if not).
Reported: the minimum and the quartiles of each way's ms (the minimum is the least disturbed by the
machine), the share of samples without gradient, and the touched rows.

    git worktree add /tmp/before <commit>
    OMP_NUM_THREADS=2 python benchmarks/studies/row_kernels_replay.py --run RUN --threads 2 --work /tmp/replay \\
        --against /tmp/before/src/stochastic_fields/row_kernels.py --out benchmarks/results/row_kernels_replay/flower
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from stochastic_fields import row_kernels
from stochastic_fields.config import load_config
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.scenes import load_run_dataset
from stochastic_fields.trainer import Trainer

#: The second-moment decays of the replayed Adam update: 0.999, and 0.99 on the last 8 channels.
REPLAY_BETA2 = (0.999, 0.99)


def recorded_scatter_calls(run: Path, work: Path) -> list[tuple]:
    """The scatter calls (table shape, idx, weights, grad rows, first channel) of the third step after
    resuming a copy of ``run`` in ``work`` (removed after)."""
    shutil.rmtree(work, ignore_errors=True)
    shutil.copytree(run, work)
    try:
        cfg = json.loads((work / "config.json").read_text())
        # four more steps than the run made: a minute more of its budget (the schedule near its end, where
        # the run stopped) or four more iterations
        cfg["train"]["minutes"] = float(cfg["train"]["minutes"]) + 1.0 if float(cfg["train"]["minutes"]) > 0 else 0.0
        cfg["train"]["iterations"] = int(cfg["train"]["iterations"]) + 4
        (work / "config.json").write_text(json.dumps(cfg))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            config = load_config(work / "config.json")
            trainer = Trainer(config, work, load_run_dataset(config, work))
            trainer.train(progress=False, max_steps=1)  # resumes the checkpoint
        calls, original = [], row_kernels.scatter_weighted_rows

        def recording(acc, touched, idx, w, g, first_channel=0):
            calls.append((tuple(acc.shape), idx.clone(), w.clone(), g.clone(), first_channel))
            return original(acc, touched, idx, w, g, first_channel)

        row_kernels.scatter_weighted_rows = recording
        try:
            trainer.train(progress=False, max_steps=3)
        finally:
            row_kernels.scatter_weighted_rows = original
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return calls[len(calls) // 3 * 2:]


def module_from(path: Path):
    """``row_kernels`` of another checkout, imported under a name of its own from a copy in a temporary
    folder: numba caches the compiled loops beside their source under the importing module's name, so the
    copy keeps that cache away from the checkout's own (where a later import by its real name would
    find entries it cannot load)."""
    copy = Path(tempfile.mkdtemp(prefix="row_kernels_against_")) / "row_kernels_against.py"
    shutil.copyfile(path, copy)
    spec = importlib.util.spec_from_file_location("row_kernels_against", copy)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def replay(module, calls: list[tuple], moments: dict, step: int) -> tuple[float, float, dict]:
    """(scatter s, Adam s, {shape: (table, m1, m2, acc, touched)}) of one replay through ``module``."""
    tables = {shape: (x.clone(), m1.clone(), m2.clone(), torch.zeros(shape), torch.zeros(shape[0], dtype=torch.bool))
              for shape, (x, m1, m2) in moments.items()}
    start = time.perf_counter()
    for shape, idx, w, g, c0 in calls:
        _, _, _, acc, touched = tables[shape]
        module.scatter_weighted_rows(acc, touched, idx, w, g, c0)
    scattered = time.perf_counter()
    summed = {shape: (t[3].clone(), t[4].clone()) for shape, t in tables.items()}
    resumed = time.perf_counter()
    for shape, (x, m1, m2, acc, touched) in tables.items():
        beta2 = [REPLAY_BETA2[0]] * (shape[1] - 8) + [REPLAY_BETA2[1]] * 8
        module.adam_touched_rows(x, m1, m2, acc, touched, lr=0.05, betas=(0.9, beta2), eps=1e-8, step=step)
    done = time.perf_counter()
    return scattered - start, done - resumed, {s: (*tables[s][:3], *summed[s]) for s in tables}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="A trained run folder (checkpoint.pt, config.json).")
    p.add_argument("--work", type=Path, required=True, help="Scratch folder for the run's copy (removed after).")
    p.add_argument("--against", type=Path, help="Another checkout's row_kernels.py to replay beside today's.")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rounds", type=int, default=40)
    p.add_argument("--out", type=Path, help="Folder for results.json and README.md (else printed only).")
    args = p.parse_args(argv)
    if row_kernels.numba is None:
        raise SystemExit("numba is not installed: no compiled loops to time")
    if args.against is not None and not args.against.is_file():
        raise SystemExit(f"--against {args.against}: no such file")
    torch.set_num_threads(args.threads)
    calls = recorded_scatter_calls(args.run, args.work)
    if not calls:
        raise SystemExit(f"{args.run}: no compiled scatter ran in its steps (a CUDA or MLP run, or float16?)")
    gen = torch.Generator().manual_seed(0)
    moments = {shape: (torch.randn(shape, generator=gen), 0.01 * torch.randn(shape, generator=gen),
                       1e-4 * torch.rand(shape, generator=gen)) for shape, *_ in calls}
    other = module_from(args.against) if args.against else None
    ways = {"today": (row_kernels, contextlib.nullcontext), "serial": (row_kernels, row_kernels.serial_loops),
            "zeros_added": (row_kernels, row_kernels.adding_zero_rows)}
    if other is not None:
        ways |= {"against": (other, contextlib.nullcontext), "against_serial": (other, other.serial_loops)}
    times = {way: ([], []) for way in ways}
    for r in range(args.rounds + 1):  # round 0 compiles and warms the caches: dropped
        for way, (module, switch) in ways.items():
            with switch():
                scatter_s, adam_s, values = replay(module, calls, moments, 1 + r % 3)
            if r > 0:
                times[way][0].append(1e3 * scatter_s)
                times[way][1].append(1e3 * adam_s)
            if r < 3:
                if way == "today":
                    reference = values
                elif not all(torch.equal(a, b) for s in values for a, b in zip(values[s], reference[s])):
                    raise SystemExit(f"{way}: not today's values bit for bit (round {r})")
    samples = sum(g.shape[0] for *_, g, _ in calls)
    silent = sum(int((g == 0).all(dim=1).sum()) for *_, g, _ in calls)
    touched = {f"{s[0]}x{s[1]}": int(reference[s][4].sum()) for s in reference}

    def summary(ms: list[float]) -> dict:
        return {"min": round(float(np.min(ms)), 2), "q25": round(float(np.percentile(ms, 25)), 2),
                "median": round(float(np.median(ms)), 2), "q75": round(float(np.percentile(ms, 75)), 2)}

    result = {"run": str(args.run), "threads": args.threads, "rounds": args.rounds, "calls": len(calls),
              "samples": samples, "share_without_gradient": round(silent / samples, 3), "touched_rows": touched,
              "against": str(args.against) if args.against else None,
              "scatter_ms": {w: summary(t[0]) for w, t in times.items()},
              "adam_ms": {w: summary(t[1]) for w, t in times.items()}}
    print(json.dumps(result), flush=True)
    if args.out:
        command = "python benchmarks/studies/row_kernels_replay.py " + " ".join(sys.argv[1:] if argv is None else argv)
        lines = [f"# The row loops replayed on `{args.run}`'s inputs", "",
                 f"Command: `{command}` ({args.threads} torch thread{'s' if args.threads > 1 else ''}, {args.rounds} "
                 f"rounds, every way alternating; {samples} samples in {len(calls)} scatter calls, "
                 f"{100 * silent / samples:.1f}% without gradient; every way gave today's values bit for bit).", "",
                 "| way | scatter ms: min | q25 | median | q75 | Adam ms: min | q25 | median | q75 |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for w in ways:
            s, a = result["scatter_ms"][w], result["adam_ms"][w]
            lines.append(f"| {w} | {s['min']} | {s['q25']} | {s['median']} | {s['q75']} | {a['min']} | {a['q25']} | "
                         f"{a['median']} | {a['q75']} |")
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "results.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "README.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
