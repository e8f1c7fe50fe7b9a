"""``stochastic-fields next-view``: rank candidate cameras by the information a photo from each
would give the run (``products.next_view``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..defaults import NEXT_VIEW_MAX_PIXELS, NEXT_VIEW_NUM_DRAWS, NEXT_VIEW_SHEET_ROWS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, type=Path, help="Trained run folder (S-NeRF, or a baseline with draws).")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--candidates", type=Path, default=None, metavar="FILE",
                     help='Candidate cameras: the JSON export --cameras reads (list of {"K", "world_to_camera", '
                          '"width", "height"}, OpenCV, the run\'s world frame and units; optional near, far, name).')
    src.add_argument("--candidates-from", type=Path, default=None, metavar="SCENE",
                     help="The run's scene folder: its photos that did not train are the candidates.")
    p.add_argument("--count", type=int, default=1,
                   help="How many views to choose, greedily: each after the ones before it, counting only the "
                        "pixels they will not already see (default 1).")
    p.add_argument("--out", type=Path, default=None, help="Output folder (default: RUN/next_view).")
    p.add_argument("--num-draws", type=int, default=NEXT_VIEW_NUM_DRAWS,
                   help="K trajectories per pixel for the score (default %(default)s).")
    p.add_argument("--max-pixels", type=int, default=NEXT_VIEW_MAX_PIXELS,
                   help="Render each candidate at no more than this many pixels (default %(default)s).")
    p.add_argument("--sheet-rows", type=int, default=NEXT_VIEW_SHEET_ROWS,
                   help="Candidates shown in the contact sheet next_views.png (default %(default)s).")
    p.add_argument("--seed", type=int, default=0, help="Seed of the draws.")
    p.add_argument("--device", default=None, help="auto, cpu or cuda (default: the run's).")
    p.add_argument("--quiet", action="store_true", help="No progress bar.")


def run(args: argparse.Namespace) -> None:
    from ..products.next_view_cli import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
