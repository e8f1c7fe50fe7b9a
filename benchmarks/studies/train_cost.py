"""Training cost of the tables' methods on one scene: the whole training, interleaved in one process.

The tables' own ``train s`` column is the wall time of each method's whole training; when several
methods train side by side on one machine (parallel processes, other sessions) those times are not
comparable. This trains every method with the tables' configuration at the chosen budget from
scratch to its last step (or ``--max-steps``), in turn, ``--chunk`` steps at a time (method A, B,
A, B, ...), so drifts of the machine hit every method alike and every phase of training is in the
sum (step times change over training, S-NeRF's more than the deterministic NeRF's: see the plot;
and with ``--variant ...:render.skip_empty_space=true``, which the tables leave off, S-NeRF skips
empty space only after its occupancy warm-up).
Times are the trainer's loop clock (set-up, resume and checkpoint writes excluded); the ratio is
of whole-training loop times to ``--reference``. Beside them: the step time of each chunk (a plot
with ``--out``), and the tensor operations per step at the end (each at least one kernel launch on
a GPU, where small steps are launch-bound) with the functions issuing most.

    python benchmarks/studies/train_cost.py --scene fern --methods deterministic snerf_default \\
        --out benchmarks/results/eval_tables/train_cost.json

A study row's configuration is timed as a variant of a method, ``LABEL=METHOD:KEY=VALUE,...``
(values read as JSON, else as text; the result is checked like any configuration):

    python benchmarks/studies/train_cost.py --methods deterministic snerf_default \\
        --variant draws4=snerf_default:train.train_draws=4
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
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


def parse_variant(text: str) -> tuple[str, str, tuple[tuple[str, object], ...]]:
    """``"LABEL=METHOD:KEY=VALUE,KEY=VALUE"`` -> (label, method, ((key, value), ...)); each value
    is read as JSON (``4``, ``true``, ``0.5``) and kept as text when it is not JSON."""
    label, sep, rest = text.partition("=")
    method, sep2, pairs = rest.partition(":")
    if not sep or not sep2 or not label or not method or not pairs:
        raise ValueError(f"--variant {text!r}: expected LABEL=METHOD:KEY=VALUE[,KEY=VALUE...]")
    overrides = []
    for pair in pairs.split(","):
        key, sep3, raw = pair.partition("=")
        if not sep3 or not key:
            raise ValueError(f"--variant {text!r}: {pair!r} is not KEY=VALUE")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        overrides.append((key, value))
    return label, method, tuple(overrides)


def _started_trainer(cfg, run_dir: Path, dataset):
    """A fresh trainer past its first call (which starts from scratch while every later call
    resumes): what ``count_step_ops`` needs once the timed trainers have finished training."""
    from stochastic_fields.trainer import Trainer

    trainer = Trainer(copy.deepcopy(cfg), run_dir, dataset)
    trainer.train(progress=False, max_steps=2)
    return trainer


def measure(scene: str, methods: list[str], *, budget: str, data_root: Path, device: str, chunk: int,
            reference: str, max_steps: int | None = None, progress: bool = True,
            variants: tuple[tuple[str, str, tuple[tuple[str, object], ...]], ...] = ()) -> dict:
    """{"scene", "device", "threads", "steps", "chunk", "train_s": {method: loop s},
    "step_s": {method: mean s}, "ratio": {method: x}, "chunk_step_s": {method: [s per step]}, ...}.
    ``variants`` (label, method, overrides) are timed beside ``methods`` under their labels."""
    import numpy as np
    import torch

    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer
    from stochastic_fields_bench.runner import time_training_interleaved
    from stochastic_fields_bench.tables import METHOD_SPECS, BenchmarkSettings, base_config, method_config, resolve_scene

    from stochastic_fields.config import ExperimentConfig, from_dict, set_dotted, to_dict

    if reference not in methods:
        raise ValueError(f"--reference {reference!r} is not among --methods {methods}")
    unknown = [m for m in methods + [v[1] for v in variants] if m not in METHOD_SPECS]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; choose from {sorted(METHOD_SPECS)}")
    labels = [v[0] for v in variants]
    if len(set(methods + labels)) != len(methods) + len(labels):
        raise ValueError(f"every method and variant label must be distinct, got {methods + labels}")
    scene_path = resolve_scene(scene, data_root)
    from stochastic_fields.data import detect_format

    kwargs = {"images": "images_8"} if detect_format(scene_path) == "llff" else {}
    dataset = load_dataset(scene_path, split_every=5, **kwargs)
    settings = BenchmarkSettings(budget=budget, device=device)

    configs = {}
    for label, method, overrides in [(m, m, ()) for m in methods] + list(variants):
        cfg = method_config(METHOD_SPECS[method], base_config(settings, dataset), scene_path)
        for key, value in overrides + (("train.checkpoint_every", 0), ("train.eval_every", 0)):
            set_dotted(cfg, key, value)
        configs[label] = from_dict(ExperimentConfig, to_dict(cfg))  # checks every value's range
    methods = methods + labels
    trainers = {}
    with tempfile.TemporaryDirectory() as tmp:
        for m in methods:
            trainers[m] = Trainer(copy.deepcopy(configs[m]), Path(tmp) / m, dataset)
        iterations = {m: t.cfg.train.iterations for m, t in trainers.items()}
        if len(set(iterations.values())) != 1:
            raise ValueError(f"the methods train for different numbers of steps at this budget: {iterations}")
        total = next(iter(iterations.values())) if max_steps is None else min(max_steps, *iterations.values())
        chunk_s = time_training_interleaved(trainers, total, chunk, progress=progress)
        device_name = str(trainers[reference].device)
        ops = {m: count_step_ops(_started_trainer(configs[m], Path(tmp) / f"ops_{m}", dataset)) for m in methods}
    train_s = {m: float(sum(t for t, _ in v)) for m, v in chunk_s.items()}
    return {"scene": dataset.name, "budget": budget, "device": device_name,
            "device_name": torch.cuda.get_device_name() if device_name.startswith("cuda") else "cpu",
            "threads": torch.get_num_threads(), "steps": total, "chunk": chunk, "train_s": train_s,
            "step_s": {m: train_s[m] / total for m in methods},
            "ratio": {m: train_s[m] / train_s[reference] for m in methods}, "reference": reference,
            "chunk_step_s": {m: [t / n for t, n in v] for m, v in chunk_s.items()},
            "chunk_end_step": np.cumsum([n for _, n in chunk_s[reference]]).tolist(),
            "ops_per_step": {m: ops[m][0] for m in methods}, "ops_by_function": {m: ops[m][1] for m in methods}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="fern", help="LLFF scene name under --data-root, or a scene folder (any format).")
    p.add_argument("--methods", nargs="+", default=["deterministic", "snerf_default"])
    p.add_argument("--variant", action="append", default=[], metavar="LABEL=METHOD:KEY=VALUE[,KEY=VALUE]",
                   help="Also time METHOD with these config overrides under LABEL (repeatable), e.g. "
                        "draws4=snerf_default:train.train_draws=4.")
    p.add_argument("--reference", default="deterministic")
    p.add_argument("--budget", choices=("cpu", "full"), default="cpu")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda.")
    p.add_argument("--chunk", type=int, default=50, help="Training steps per method between switches.")
    p.add_argument("--max-steps", type=int, default=None,
                   help="Stop every method after this many steps (default: the budget's whole training).")
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    p.add_argument("--out", type=Path, default=None,
                   help="Also write the result as JSON here, and the step-time plot beside it (.png).")
    p.add_argument("--quiet", action="store_true", help="No progress bar.")
    args = p.parse_args(argv)
    if args.chunk < 1 or (args.max_steps is not None and args.max_steps < 1):
        p.error("--chunk and --max-steps must be positive")
    try:
        variants = tuple(parse_variant(v) for v in args.variant)
        result = measure(args.scene, args.methods, budget=args.budget, data_root=args.data_root, device=args.device,
                         chunk=args.chunk, reference=args.reference, max_steps=args.max_steps,
                         progress=not args.quiet, variants=variants)
    except (ValueError, FileNotFoundError) as exc:
        print(f"train_cost: error: {exc}", file=sys.stderr)
        return 2
    print(f"{result['scene']}, budget {result['budget']}, {result['device_name']}, {result['threads']} thread(s), "
          f"{result['steps']} steps each, interleaved every {result['chunk']}")
    print("| method | training loop s | ms / step | x " + args.reference + " | tensor ops / step | x "
          + args.reference + " |")
    print("|---|---|---|---|---|---|")
    ref_ops = result["ops_per_step"][args.reference]
    for m in result["train_s"]:
        print(f"| {m} | {result['train_s'][m]:.1f} | {1e3 * result['step_s'][m]:.1f} | {result['ratio'][m]:.2f} | "
              f"{result['ops_per_step'][m]:.0f} | {result['ops_per_step'][m] / ref_ops:.2f} |")
    for m in result["train_s"]:
        print(f"{m}: most tensor ops per step in " + ", ".join(f"{k} ({v:.0f})" for k, v in result["ops_by_function"][m]))
    if args.out is not None:
        from stochastic_fields.io_utils import atomic_write_text

        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, json.dumps(result, indent=2))
        from stochastic_fields.plots import plot_step_times

        plot = plot_step_times(
            result["chunk_end_step"], result["chunk_step_s"],
            {m: f"{m}: {result['ratio'][m]:.2f}x {args.reference} over the whole training" for m in result["train_s"]},
            args.out.with_suffix(".png"),
            title=f"{result['scene']}, budget {result['budget']}, {result['device_name']}, {result['threads']} "
                  f"thread(s), interleaved every {result['chunk']} steps")
        print(f"wrote {args.out} and {plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
