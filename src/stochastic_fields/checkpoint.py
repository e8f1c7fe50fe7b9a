"""Checkpoints that load without executing code.

One file, ``checkpoint.pt``, written with ``torch.save`` to a temporary file and moved into
place with ``os.replace`` (an interrupted save keeps the previous checkpoint). It holds only
tensors, numbers, strings and containers of them, and is read with
``torch.load(weights_only=True)``, so a run folder from someone else is safe to open.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from .io_utils import atomic_path

CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupted or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {exc}") from exc
