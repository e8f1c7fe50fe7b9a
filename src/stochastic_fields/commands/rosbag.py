"""``stochastic-fields rosbag``: a ROS 2 bag of an export (``products.rosbag``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

from pathlib import Path

from ..defaults import ROSBAG_PERIOD_S


def add_arguments(p) -> None:
    p.add_argument("--export", required=True, type=Path, help="Export folder (from `stochastic-fields export`).")
    p.add_argument("--out", required=True, type=Path, help="Bag folder to create (must not exist).")
    p.add_argument("--metres-per-unit", type=float, default=None,
                   help="Metres per scene unit (default: the one the export recorded; required if it recorded none).")
    p.add_argument("--period", type=float, default=ROSBAG_PERIOD_S, help="Seconds between views (default 0.1).")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="rosbag2 storage plugin.")


def run(args) -> None:
    from ..products.rosbag import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
