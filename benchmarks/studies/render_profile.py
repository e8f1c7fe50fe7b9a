"""Where a full view's render spends its time, by operation, for finished runs side by side.

The tables' Table 2 times one full test view per method; this says which torch operations make
the difference between two methods' renders (issue 36's cost target compares S-NeRF's render with
the deterministic NeRF's). Each run renders its first test view once untimed (a warm-up chunk), then
once under the torch profiler, with the run's own render options; the table lists each operation's
self time per run, sorted by the first run's excess over the last.

    OMP_NUM_THREADS=2 python benchmarks/studies/render_profile.py \\
        --run snerf=runs/tables/flower/snerf_default --run deterministic=runs/tables/flower/deterministic \\
        --out benchmarks/results/render_profile/flower.md
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from stochastic_fields.cameras import generate_rays_for_view
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.trainer import load_trained_model

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import parse_runs, study_command  # noqa: E402


def self_ms(run: Path) -> tuple[dict[str, tuple[float, int]], float]:
    """({operation: (self ms, calls)}, total self ms) of one full render of the run's first test view."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    view = int(dataset.test_indices[0])
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far)
    options = model.default_render_options()
    with torch.no_grad():
        model.render_view(rays.flatten()[: options.chunk_rays].reshape(1, -1), options,
                          generator=torch.Generator().manual_seed(0))
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            model.render_view(rays, options, generator=torch.Generator().manual_seed(0))
    ops = {e.key: (e.self_cpu_time_total / 1e3, e.count) for e in prof.key_averages()}
    return ops, sum(ms for ms, _ in ops.values())


def report(rows: dict[str, tuple[dict[str, tuple[float, int]], float]], command: str, threads: int,
           limit: int) -> str:
    labels = list(rows)
    first, last = labels[0], labels[-1]
    names = set().union(*(ops for ops, _ in rows.values()))

    def ms(label: str, name: str) -> float:
        return rows[label][0].get(name, (0.0, 0))[0]

    order = sorted(names, key=lambda n: ms(first, n) - ms(last, n), reverse=True)[:limit]
    lines = ["# A full view's render by operation", "",
             f"Command: `{command}` ({threads} torch threads; one full render of each run's first test view after a "
             "warm-up chunk, the run's own render options; self time by the torch profiler).", "",
             "| run | total self ms |", "|---|---|"]
    lines += [f"| {label} | {rows[label][1]:.0f} |" for label in labels]
    lines += ["", f"Operations by {first}'s excess over {last} (self ms, calls):", "",
              "| operation | " + " | ".join(labels) + f" | {first} - {last} |",
              "|---|" + "---|" * (len(labels) + 1)]
    for name in order:
        cells = [f"{ms(label, name):.0f} ({rows[label][0].get(name, (0.0, 0))[1]})" for label in labels]
        lines.append(f"| `{name}` | " + " | ".join(cells) + f" | {ms(first, name) - ms(last, name):+.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", required=True, metavar="LABEL=RUN_DIR",
                   help="A trained run (repeatable; the first is compared with the last).")
    p.add_argument("--rows", type=int, default=20, help="Operations listed.")
    p.add_argument("--out", type=Path, required=True, help="Markdown table.")
    args = p.parse_args(argv)
    runs = parse_runs(p, args.run, required="checkpoint.pt")
    if len(runs) < 2:
        p.error("give at least two --run with different labels to compare")
    rows = {label: self_ms(path) for label, path in runs.items()}
    command = study_command("render_profile.py", argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, report(rows, command, torch.get_num_threads(), args.rows))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
