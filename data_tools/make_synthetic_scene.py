"""Generate the embedded synthetic scene (coloured solids on a checkered ground) into a folder.

Example:
    python data_tools/make_synthetic_scene.py runs/synthetic --num-views 40 --width 96 --height 72
"""

from __future__ import annotations

import argparse
from pathlib import Path

from stochastic_fields.data.synthetic import make_synthetic_scene


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="folder to write transforms.json, images/, depth/, scene.ply into")
    parser.add_argument("--num-views", type=int, default=40, help="cameras on the ring (default 40)")
    parser.add_argument("--width", type=int, default=96, help="image width in pixels (default 96)")
    parser.add_argument("--height", type=int, default=72, help="image height in pixels (default 72)")
    parser.add_argument("--seed", type=int, default=0, help="seed for the camera phase and colours (default 0)")
    args = parser.parse_args(argv)
    out = make_synthetic_scene(args.out_dir, num_views=args.num_views, width=args.width, height=args.height,
                               seed=args.seed)
    print(f"wrote {out / 'transforms.json'}")
    return out


if __name__ == "__main__":
    main()
