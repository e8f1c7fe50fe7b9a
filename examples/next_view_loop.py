"""The planner's loop of looking next: rank where to look, print the pose, take the photo, retrain.

    PYTHONPATH=src python examples/next_view_loop.py --run runs/demo --candidates-from runs/demo/scene --rounds 2

Each round (``products.next_view``, the code behind ``stochastic-fields next-view``):
1. every candidate camera (``--candidates FILE`` as ``export --cameras`` reads, or the run's
   photos that did not train) is rendered at no more than 4096 pixels with K = 16 trajectories;
2. each is scored by the expected information gain of its photo about the field (nats per pixel);
3. the best pose is printed as a robot takes it: camera centre and camera-to-world rotation
   (OpenCV axes, x right, y down, z forward; the run's world frame and scene units, as in
   ``next_views.json``);
4. with ``--retrain-steps N`` and ``--candidates-from``, the chosen photo joins the training views
   (the 'views' split, ``data.train_list``) and a fresh run with the run's config trains N steps
   on them into ``RUN_next<k>``, which the next round ranks with; without it each round ranks the
   same run with the chosen views removed, as a planner that cannot retrain between views would.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    from stochastic_fields.defaults import NEXT_VIEW_MAX_PIXELS, NEXT_VIEW_NUM_DRAWS
    from stochastic_fields.products.export import load_cameras_json
    from stochastic_fields.products.next_view import rank_candidates, untrained_view_specs
    from stochastic_fields.trainer import load_trained_model

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, type=Path)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--candidates", type=Path, help="cameras JSON (export --cameras format)")
    src.add_argument("--candidates-from", type=Path, help="the run's scene: its photos that did not train")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--retrain-steps", type=int, default=0, help="train this many steps after each choice (0: no)")
    args = ap.parse_args()
    torch.set_num_threads(1)

    run = args.run
    cfg, model, ds = load_trained_model(run, device="cpu")
    if args.candidates is not None:
        specs = load_cameras_json(args.candidates, default_near=float(ds.near.min()), default_far=float(ds.far.max()))
    else:
        specs = untrained_view_specs(ds)
    chosen: list[int] = []
    for r in range(1, args.rounds + 1):
        left = [s for s in specs if s.index not in chosen]
        if not left:
            print("no candidate left")
            break
        ranking, rendered = rank_candidates(model, left, count=1, num_draws=NEXT_VIEW_NUM_DRAWS,
                                            max_pixels=NEXT_VIEW_MAX_PIXELS, seed=r)
        best, parts = ranking.batch[0]
        spec = rendered[best].spec
        c2w = np.linalg.inv(spec.world_to_camera)
        print(f"round {r}: look from {spec.name}: centre {np.round(c2w[:3, 3], 4).tolist()}, "
              f"camera-to-world rotation {np.round(c2w[:3, :3], 4).tolist()}; "
              f"{parts['information_nats_per_pixel']:.3f} nats per pixel expected")
        chosen.append(spec.index)
        if args.retrain_steps and args.candidates_from is not None:
            from stochastic_fields.cli import main as cli

            views = sorted(set(ds.train_indices) | set(chosen))
            out = Path(f"{args.run}_next{r}")
            cli(["train", "--config", str(run / "config.json"), "--data.split", "views",
                 "--data.train_list", ",".join(map(str, views)),
                 "--train.iterations", str(args.retrain_steps), "--out", str(out), "--quiet"])
            run = out
            cfg, model, ds = load_trained_model(run, device="cpu")


if __name__ == "__main__":
    main()
