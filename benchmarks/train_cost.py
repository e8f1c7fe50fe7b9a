"""Training-step cost of the tables' methods on one scene, interleaved in one process.

The tables' own ``train s`` column is the wall time of each method's whole training; when several
methods train side by side on one machine (parallel processes on one GPU, say) those times are not
comparable. This measures the step time alone: every method's trainer is built with the tables'
configuration at the chosen budget, warmed up, then trained ``--rounds`` x ``--steps`` steps in
turn (method A, B, A, B, ...), so drifts of the machine hit every method alike. Medians of the
per-round step times, read from the trainer's loop clock (set-up, resume and checkpoint writes
excluded); ratios to ``--reference``. Beside them, the tensor operations per step (each at least
one kernel launch on a GPU, where small steps are launch-bound) and the functions issuing most.

    python benchmarks/train_cost.py --scene fern --budget full --methods deterministic snerf_default \\
        --out benchmarks/results/eval_tables_full/train_cost.json
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA_ROOT = REPO_ROOT / ".." / "shared" / "data" / "nerf_llff_data"


def count_step_ops(trainer, *, top: int = 8) -> tuple[float, list[tuple[str, float]]]:
    """Tensor operations (ATen calls, the backward pass's included) per training step, and the
    ``top`` functions of the package issuing the most (the backward's are counted where
    ``backward()`` was called). On a GPU each is at least one kernel launch, so when steps are
    launch-bound this count, not the arithmetic, sets the cost. Each ``train()`` call has set-up
    work of its own (training rays, a resume), so one step is the difference of 3 steps and 1."""
    import collections
    import sys as _sys

    from torch.utils._python_dispatch import TorchDispatchMode

    class _Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.by_function = collections.Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            frame, where = _sys._getframe(1), "(outside the package)"
            while frame is not None:
                name = frame.f_code.co_filename.replace("\\", "/")
                if "/stochastic_fields/" in name:
                    where = f"{name.rsplit('/stochastic_fields/', 1)[1]}:{frame.f_code.co_name}"
                    break
                frame = frame.f_back
            self.by_function[where] += 1
            return func(*args, **(kwargs or {}))

    counts = []
    for steps in (1, 3):
        with _Count() as c:
            trainer.train(progress=False, max_steps=steps)
        counts.append(c.by_function)
    per_step = collections.Counter({k: (counts[1][k] - counts[0][k]) / 2 for k in counts[1]})
    total = float(sum(per_step.values()))
    return total, [(k, v) for k, v in per_step.most_common(top) if v > 0]


def measure(scene: str, methods: list[str], *, budget: str, data_root: Path, device: str, rounds: int, steps: int,
            reference: str) -> dict:
    """{"scene", "device", "threads", "steps", "rounds", "step_s": {method: median s}, "ratio": {method: x}}."""
    import numpy as np
    import torch

    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer
    from stochastic_fields_bench.tables import METHOD_SPECS, BenchmarkSettings, base_config, method_config, resolve_scene

    if reference not in methods:
        raise ValueError(f"--reference {reference!r} is not among --methods {methods}")
    unknown = [m for m in methods if m not in METHOD_SPECS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(METHOD_SPECS)}")
    scene_path = resolve_scene(scene, data_root)
    from stochastic_fields.data import detect_format

    kwargs = {"images": "images_8"} if detect_format(scene_path) == "llff" else {}
    dataset = load_dataset(scene_path, split_every=5, **kwargs)
    settings = BenchmarkSettings(budget=budget, device=device)

    trainers, step_s = {}, {m: [] for m in methods}
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:
            cfg = method_config(METHOD_SPECS[m], base_config(settings, dataset), scene_path)
            cfg.train.checkpoint_every = 0
            cfg.train.eval_every = 0
            trainers[m] = Trainer(copy.deepcopy(cfg), Path(tmp) / m, dataset)
            trainers[m].train(progress=False, max_steps=5)  # warm-up: allocations, kernels, caches
        for _ in range(rounds):
            for m in methods:
                before = trainers[m].elapsed  # the training loop's own clock: no set-up, resume or checkpoint
                trainers[m].train(progress=False, max_steps=steps)
                step_s[m].append((trainers[m].elapsed - before) / steps)
        device_name = str(trainers[reference].device)
        ops = {m: count_step_ops(trainers[m]) for m in methods}
    med = {m: float(np.median(v)) for m, v in step_s.items()}
    return {"scene": dataset.name, "budget": budget, "device": device_name,
            "device_name": torch.cuda.get_device_name() if device_name.startswith("cuda") else "cpu",
            "threads": torch.get_num_threads(), "steps": steps, "rounds": rounds, "step_s": med,
            "ratio": {m: med[m] / med[reference] for m in methods}, "reference": reference,
            "ops_per_step": {m: ops[m][0] for m in methods}, "ops_by_function": {m: ops[m][1] for m in methods}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="fern", help="LLFF scene name under --data-root, or a scene folder (any format).")
    p.add_argument("--methods", nargs="+", default=["deterministic", "snerf_default"])
    p.add_argument("--reference", default="deterministic")
    p.add_argument("--budget", choices=("cpu", "full"), default="cpu")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda.")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--steps", type=int, default=25, help="Training steps per method and round.")
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--out", type=Path, default=None, help="Also write the result as JSON here.")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.steps < 1:
        p.error("--rounds and --steps must be positive")
    try:
        result = measure(args.scene, args.methods, budget=args.budget, data_root=args.data_root, device=args.device,
                         rounds=args.rounds, steps=args.steps, reference=args.reference)
    except (ValueError, FileNotFoundError) as exc:
        print(f"train_cost: error: {exc}", file=sys.stderr)
        return 2
    print(f"{result['scene']}, budget {result['budget']}, {result['device_name']}, {result['threads']} thread(s), "
          f"{result['rounds']} x {result['steps']} steps")
    print("| method | step ms | x " + args.reference + " | tensor ops / step | x " + args.reference + " |")
    print("|---|---|---|---|---|")
    ref_ops = result["ops_per_step"][args.reference]
    for m in args.methods:
        print(f"| {m} | {1e3 * result['step_s'][m]:.1f} | {result['ratio'][m]:.2f} | "
              f"{result['ops_per_step'][m]:.0f} | {result['ops_per_step'][m] / ref_ops:.2f} |")
    for m in args.methods:
        print(f"{m}: most tensor ops per step in " + ", ".join(f"{k} ({v:.0f})" for k, v in result["ops_by_function"][m]))
    if args.out is not None:
        from stochastic_fields.io_utils import atomic_write_text

        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
