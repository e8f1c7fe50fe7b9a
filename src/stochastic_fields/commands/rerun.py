"""``stochastic-fields rerun``: a rerun recording of an export (``products.rerun_log``).

The options live here, without the implementation, so that ``--help`` answers at once; ``run``
loads the implementation when the command runs.
"""

from __future__ import annotations

from pathlib import Path



def add_arguments(p) -> None:
    p.add_argument("--export", required=True, type=Path, help="Export folder (from `stochastic-fields export`).")
    p.add_argument("--out", required=True, type=Path, help="Recording file to write (.rrd).")


def run(args) -> None:
    from ..products.rerun_log import run as run_command  # deferred: loads only when this command runs (keeps --help fast)

    run_command(args)
