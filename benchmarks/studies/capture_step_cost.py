"""A training step's cost on a capture: today's configuration against one with ``--set`` options.

``train_cost.py`` times the tables' configuration (the paper split); this times the capture bench's
(``capture_quality.config_for``: ``--preset llff``, the capture split), where a study whose rows
compare at equal steps (``capture_quality.py --steps``) must still rule on what a step costs: in
the ten-minute budget a dearer step is fewer steps. Both trainings start from scratch, train
``--warmup`` steps each, then ``--steps`` more interleaved ``--chunk`` at a time (today, candidate,
today, ...) so that the machine's drifts hit both alike; times are the trainer's loop clock.

    OMP_NUM_THREADS=1 python benchmarks/studies/capture_step_cost.py --scene flower \\
        --set field.grid_colour_levels=concat --out benchmarks/results/colour_levels_study/step_cost_flower.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # capture_quality, beside this folder


def measure(scene: str, settings: tuple[tuple[str, object], ...], *, method: str = "snerf", warmup: int = 100,
            steps: int = 300, chunk: int = 50, seed: int = 0, llff_root: Path | None = None) -> dict:
    """{"scene", "method", "settings", "threads", "warmup", "steps", "chunk", "train_s": {label: s},
    "ms_per_step": {label: ms}, "ratio": candidate / today} over the ``steps`` after the warm-up."""
    import torch

    from capture_quality import LLFF_ROOT, config_for
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer
    from stochastic_fields_bench.runner import time_training_interleaved

    trainers = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, extra in (("today", ()), ("candidate", settings)):
            cfg = config_for(scene, method, warmup + steps, seed, extra, llff_root or LLFF_ROOT)
            cfg.train.minutes = 0.0
            run_dir = Path(tmp) / label
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the capture's lens-distortion note
                dataset = load_run_dataset(cfg, run_dir)
            trainer = Trainer(cfg, run_dir, dataset)
            trainer.save = lambda: None  # no checkpoint writes between chunks
            trainer.train(progress=False, max_steps=warmup)
            trainers[label] = trainer
        chunks = time_training_interleaved(trainers, steps, chunk)
    train_s = {k: float(sum(t for t, _ in v)) for k, v in chunks.items()}
    return {"scene": scene, "method": method, "settings": [[k, v] for k, v in settings],
            "threads": torch.get_num_threads(), "warmup": warmup, "steps": steps, "chunk": chunk,
            "train_s": train_s, "ms_per_step": {k: 1e3 * s / steps for k, s in train_s.items()},
            "ratio": train_s["candidate"] / train_s["today"]}


def main(argv: list[str] | None = None) -> int:
    from capture_quality import parse_setting, positive_int

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="flower", help="LLFF scene under the shared data (fern, flower).")
    p.add_argument("--method", default="snerf", choices=("snerf", "deterministic"))
    p.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE", required=True,
                   help="The candidate's option (dotted, value as JSON; repeatable).")
    p.add_argument("--warmup", type=positive_int, default=100, help="Steps each trains before the clock runs.")
    p.add_argument("--steps", type=positive_int, default=300, help="Timed steps each.")
    p.add_argument("--chunk", type=positive_int, default=50, help="Steps each trains between switches.")
    p.add_argument("--out", type=Path, default=None, help="Also write the result as JSON here.")
    args = p.parse_args(argv)
    result = measure(args.scene, tuple(args.set), method=args.method, warmup=args.warmup, steps=args.steps,
                     chunk=args.chunk)
    print(f"{result['scene']}, {result['method']}, {result['threads']} thread(s), {result['steps']} steps each after "
          f"{result['warmup']}, interleaved every {result['chunk']}: today {result['ms_per_step']['today']:.1f} ms a "
          f"step, candidate {result['ms_per_step']['candidate']:.1f} ms ({result['ratio']:.3f}x)")
    if args.out is not None:
        from stochastic_fields.io_utils import atomic_write_text

        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, json.dumps(result, indent=2))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
