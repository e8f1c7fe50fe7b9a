"""A rendered view beside its photo, depth and depth uncertainty, as one PNG (the README's picture).

    .venv/bin/stochastic-fields render --run RUN --views 8
    .venv/bin/python examples/view_panels.py --run RUN --view 8 --out docs/images/fern_view_panels.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from stochastic_fields.config import load_config
from stochastic_fields.plots import plot_view_panels
from stochastic_fields.scenes import load_run_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="A trained run whose view was rendered (render/eval).")
    ap.add_argument("--view", type=int, required=True)
    ap.add_argument("--renders", type=Path, default=None, help="Folder holding views/ (default RUN/renders).")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write.")
    args = ap.parse_args()
    renders = args.renders or args.run / "renders"
    npz = renders / "views" / f"view_{args.view:03d}.npz"
    if not npz.is_file():
        raise SystemExit(f"{npz}: missing; render it first: stochastic-fields render --run {args.run} --views {args.view}")
    maps = dict(np.load(npz))
    cfg = load_config(args.run / "config.json")
    dataset = load_run_dataset(cfg, args.run, generate=False)
    photo = dataset.images[args.view].numpy()
    role = "validation" if args.view in dataset.test_indices else "training"
    plot_view_panels(args.out, photo, maps, title=f"{dataset.name}, {role} photo {args.view}: "
                     f"{cfg.method}, K = {int(maps['num_draws'].max()) if 'num_draws' in maps else '?'}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
