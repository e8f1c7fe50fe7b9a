"""Checkpoints that load without executing code, and refuse damaged weights.

One file, ``checkpoint.pt``, written with ``torch.save`` to a temporary file and moved into
place with ``os.replace`` (an interrupted save keeps the previous checkpoint). It holds only
tensors, numbers, strings and containers of them, and is read with
``torch.load(weights_only=True)``, so a run folder from someone else is safe to open.

Integrity: every save stores ``checksum``, the SHA-256 of the state (keys, dtypes, shapes and
tensor bytes, in key order; :func:`state_checksum`); loading recomputes it and refuses a file
whose tensors changed (flipped bytes, edited weights). Loading also refuses a model tensor with
NaN or inf values. Checkpoints from before the checksum load with the finiteness check only.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import torch

from .io_utils import atomic_path

CHECKPOINT_NAME = "checkpoint.pt"
CHECKSUM_KEY = "checksum"


def _feed(h: "hashlib._Hash", obj: Any) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(obj, dict):
        h.update(b"D%d" % len(obj))
        for key in sorted(obj, key=repr):
            h.update(repr(key).encode())
            _feed(h, obj[key])
    elif isinstance(obj, (list, tuple)):
        h.update(b"L%d" % len(obj))
        for item in obj:
            _feed(h, item)
    else:
        h.update(repr(obj).encode())


def state_checksum(state: dict[str, Any]) -> str:
    """SHA-256 hex digest of a checkpoint state without its ``checksum`` entry."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in state.items() if k != CHECKSUM_KEY})
    return h.hexdigest()


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    state = {**state, CHECKSUM_KEY: state_checksum(state)}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def check_finite_model(path: Path, model_state: Any) -> None:
    """ValueError naming the file and the first model tensor with NaN/inf values."""
    if not isinstance(model_state, dict):
        return
    for name, t in model_state.items():
        if isinstance(t, torch.Tensor) and (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise ValueError(f"checkpoint {path}: model tensor {name!r} has {bad} non-finite (NaN/inf) value(s) of "
                             f"{t.numel()}: the weights are damaged; retrain or restore the file")


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The state in ``path`` after the integrity checks of the module doc (ValueError naming
    the file when the file is unreadable, its checksum differs or a weight is not finite)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupted or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {exc}") from exc
    if not isinstance(state, dict) or "model" not in state:
        raise ValueError(f"checkpoint {path}: not a stochastic-fields checkpoint (no 'model' state)")
    stored = state.get(CHECKSUM_KEY)
    if stored is not None:
        actual = state_checksum(state)
        if actual != stored:
            raise ValueError(f"checkpoint {path} is corrupted: checksum {actual[:16]}... differs from the stored "
                             f"{str(stored)[:16]}...; restore the file or retrain")
    check_finite_model(path, state["model"])
    return state
