"""``stochastic-fields free-path``: P(collision-free) of segments or a path of a trained run.

Input JSON (world coordinates, scene units): ``{"segments": [[[x0, y0, z0], [x1, y1, z1]], ...]}``
and/or ``{"path": [[x, y, z], ...]}``. Output JSON (``--out``, else printed): per segment
``probability_free``, ``stderr``, ``bound_95``, ``transmittance_mean``, ``num_samples``; for
the path also the whole path's. Step along segments: ``--step`` or half the occupancy voxel
size from the images' footprint. Where the run has a free-path map (``free_path_calibration``,
fitted at the same level) ``probability_free`` is the recalibrated probability and
``probability_free_model`` the model's; ``recalibrated`` says which (``--raw-probability``: the
model's).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from ..io_utils import atomic_write_text, read_json
from .free_path import (FREE_PATH_NUM_DRAWS, FREE_TRANSMITTANCE_LEVEL, FloatField, default_step,
                        path_free_probability, segment_free_probability)
from .free_path_calibration import applies, describe_free_path_calibration, load_free_path_calibration
from .occupancy_map import require_stochastic_field
from ..trainer import load_trained_model


def _points(path: Path, key: str, value, shape_tail: tuple[int, ...]) -> torch.Tensor:
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {key!r} must be numbers, got {value!r}") from exc
    if t.ndim != len(shape_tail) + 1 or tuple(t.shape[1:]) != shape_tail or t.shape[0] == 0 \
            or not bool(torch.isfinite(t).all()):
        want = "[[[x0, y0, z0], [x1, y1, z1]], ...]" if key == "segments" else "[[x, y, z], ...] (2 or more)"
        raise ValueError(f"{path}: {key!r} must be {want} of finite numbers, got shape {tuple(t.shape)}")
    return t


def load_queries(path: str | Path) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(segments [B, 2, 3] or None, path [M, 3] or None) from the JSON file (module doc)."""
    path = Path(path)
    data = read_json(path, "free-path queries file")
    if not isinstance(data, dict) or not ({"segments", "path"} & set(data)):
        raise ValueError(f"{path}: expected an object with 'segments' and/or 'path'")
    segs = _points(path, "segments", data["segments"], (2, 3)) if "segments" in data else None
    way = _points(path, "path", data["path"], (3,)) if "path" in data else None
    if way is not None and way.shape[0] < 2:
        raise ValueError(f"{path}: 'path' needs at least 2 waypoints, got {way.shape[0]}")
    return segs, way


def run(args: argparse.Namespace) -> None:
    segs, way = load_queries(args.queries)
    if args.num_draws < 1:
        raise ValueError(f"--num-draws must be >= 1, got {args.num_draws}")
    _, model, dataset = load_trained_model(Path(args.run), device=args.device)
    require_stochastic_field(model, args.run, "free-path answers")
    device = model.region.box.device
    step = default_step(model, dataset) if args.step is None else args.step
    shared = model.render_settings.shared_noise if args.shared_noise == "run" else args.shared_noise == "true"
    gen = torch.Generator(device=device).manual_seed(args.seed)
    field = FloatField(model.field)
    cal = None if getattr(args, "raw_probability", False) else load_free_path_calibration(args.run)
    recalibrate = applies(cal, args.level)
    answer: dict = {"step": step, "shared_noise": shared, "units": "scene units", "recalibrated": recalibrate}
    if recalibrate:
        answer["recalibration"] = describe_free_path_calibration(cal)
    elif cal is not None:
        answer["recalibration"] = (f"none: the run's map was fitted at level {cal.level:g}, these answers are at "
                                   f"level {args.level:g} (the model's probabilities)")
    finish = (lambda d: recalibrated_answers(d, cal)) if recalibrate else (lambda d: d)
    if segs is not None:
        r = segment_free_probability(field, segs[:, 0].to(device), segs[:, 1].to(device), num_draws=args.num_draws,
                                     level=args.level, step=step, shared_noise=shared, generator=gen)
        answer["segments"] = finish(r.to_dict())
    if way is not None:
        whole, parts = path_free_probability(field, way.to(device), num_draws=args.num_draws, level=args.level,
                                             step=step, shared_noise=shared, generator=gen)
        answer["path"] = {"whole": finish(whole.to_dict()), "segments": finish(parts.to_dict())}
    text = json.dumps(answer, indent=2)
    if args.out is not None:
        atomic_write_text(args.out, text)
        print(f"free-path answers written to {args.out}")
    else:
        print(text)


def recalibrated_answers(answers: dict, cal) -> dict:
    """``FreePathResult.to_dict`` output with ``probability_free`` mapped by the run's free-path map
    ``cal`` (``free_path_calibration``) and the model's kept as ``probability_free_model``
    (``stderr`` and ``bound_95`` stay the model's Monte-Carlo errors; ``every_segment_free``, another
    event, stays the model's)."""
    out = dict(answers)
    out["probability_free_model"] = out["probability_free"]
    out["probability_free"] = cal(out["probability_free"]).tolist()
    return out
