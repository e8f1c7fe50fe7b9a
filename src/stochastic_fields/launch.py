"""How a process was launched, without torch: whether torchrun started it, and the error a failed
collective raises. ``distributed`` (which needs torch) and the command line (which must not, to
answer ``--help`` at once) both use them."""

from __future__ import annotations

import os


class DistributedError(RuntimeError):
    """A collective failed: another rank stopped, raised, or did not answer within the timeout."""


def requested_by_environment() -> bool:
    """True when the process was started by torchrun (``RANK`` and ``WORLD_SIZE`` are set)."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ
