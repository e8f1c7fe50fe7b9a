"""A capture's training steps on one thread: their time and a checksum of the trained model
(``checkpoint.state_checksum``, the checkpoints' own, of its parameters and buffers).

For a change that must keep every value (a compiled loop rewritten, a pass skipped that adds only zeros):
run this with the code before and the code after side by side, one thread each, the code before from a
worktree first on ``PYTHONPATH``. Equal checksums say the two trainings made the same model bit for bit;
the second half's ms a step (after the occupancy warm-up and the first steps' fog) say what the change
saves in training. The configuration is ``make bench-capture``'s (``capture_quality.config_for``).

    git worktree add /tmp/before <commit>
    PYTHONPATH=/tmp/before/src OMP_NUM_THREADS=1 python benchmarks/studies/capture_steps_checksum.py \\
        --scene flower --steps 600 --work /tmp/steps_before &
    OMP_NUM_THREADS=1 python benchmarks/studies/capture_steps_checksum.py --scene flower --steps 600 \\
        --work /tmp/steps_after
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # capture_quality, beside this folder

import stochastic_fields  # noqa: E402
from capture_quality import LLFF_ROOT, config_for  # noqa: E402
from stochastic_fields.checkpoint import state_checksum  # noqa: E402
from stochastic_fields.scenes import load_run_dataset  # noqa: E402
from stochastic_fields.trainer import Trainer  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True, help="A scene folder's name under --llff-root.")
    p.add_argument("--llff-root", type=Path, default=LLFF_ROOT)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", type=Path, required=True, help="The run's folder (replaced; removed after).")
    args = p.parse_args(argv)
    if args.steps < 2:
        raise SystemExit(f"--steps must be >= 2, got {args.steps}")
    torch.set_num_threads(1)
    cfg = config_for(args.scene, "snerf", args.steps, args.seed, llff_root=args.llff_root)
    shutil.rmtree(args.work, ignore_errors=True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            trainer = Trainer(cfg, args.work, load_run_dataset(cfg, args.work))
            trainer.train(progress=False, max_steps=args.steps // 2)
            half = trainer.elapsed
            trainer.train(progress=False)
        result = {"code": str(Path(stochastic_fields.__file__).parent), "scene": args.scene, "steps": trainer.step,
                  "first_half_s": round(half, 2),
                  "second_half_ms_per_step": round(1e3 * (trainer.elapsed - half) / (args.steps - args.steps // 2), 1),
                  "model_sha256": state_checksum(dict(trainer.model.state_dict()))[:16]}
    finally:
        shutil.rmtree(args.work, ignore_errors=True)
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
