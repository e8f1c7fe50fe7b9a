"""Free-path answers recalibrated on held-out capture points (``RUN/free_path_calibration.json``).

``free-path``'s P(free) is the share of K density trajectories whose transmittance along a segment
exceeds the level: the model's probability, which no depth map touches. Asked about segments whose
answer a held-out photo knows, it is overconfident at both ends where the model renders a surface
on the wrong side (benchmarks/results/free_path_reliability). The recalibration is the yes/no
analogue of the depth map (isotonic recalibration of probabilities, Zadrozny & Elkan 2002; Kuleshov
et al. 2018 for regression), fitted on the same held-out points as the depth map:

* events: each capture point of the CALIBRATE and SCORE roles that both views of a calibration
  view's pair observed (``calibration.calibration_view_points(points="held-out")``; at most
  ``FREE_PATH_CALIBRATION_POINTS``, drawn with a fixed seed), at camera depth y along the
  calibration view's pixel ray through it, and each margin m of ``FREE_PATH_CALIBRATION_MARGINS``:
  the segment from the ray's near point to camera depth (1 - m) y is free (outcome 1: the views
  that triangulated the point see it) and the one to (1 + m) y is blocked (outcome 0: it runs
  through the surface of the point);
* p_i: free-path's answer for event i (``free_path.segment_free_probability`` with the run's noise,
  the default draws and level, and the default step of ``free_path.default_step``);
* g: the isotonic (non-decreasing) regression of the outcomes on p, over the distinct values of p
  weighted by their counts (pool adjacent violators, ``scipy.optimize.isotonic_regression``),
  stored as knots (p_j, g(p_j)); between knots g is linear, outside them constant.

``free-path`` then reports ``probability_free = g(p)`` beside ``probability_free_model = p`` (the
Monte-Carlo ``stderr`` and ``bound_95`` stay those of p). The map was fitted for one transmittance
level; answers at another level stay the model's, and say so. What it can promise: on segments
like those it was fitted on (from a camera's near plane towards a surface the camera sees), the
stated probability matches the observed frequency on the calibration views; segments far from any
surface have no held-out truth to check against.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import isotonic_regression

from ..calibration import calibration_view_points
from ..capture_points import load_capture_points, rays_through_points, restrict_sparse_depth
from ..io_utils import atomic_write_text, read_json
from .free_path import (FREE_PATH_NUM_DRAWS, FREE_TRANSMITTANCE_LEVEL, FloatField, default_step,
                        segment_free_probability)
from .occupancy_map import require_stochastic_field

#: File the map is stored in, in the run folder.
FREE_PATH_CALIBRATION_FILE: str = "free_path_calibration.json"
#: Relative margins in front of and behind each held-out point.
FREE_PATH_CALIBRATION_MARGINS: tuple[float, ...] = (0.05, 0.1, 0.2)
#: Most held-out points the map is fitted on (each gives two events per margin).
FREE_PATH_CALIBRATION_POINTS: int = 1000
#: Fewest events a map is fitted on.
FREE_PATH_CALIBRATION_MIN_EVENTS: int = 50


@dataclass
class FreePathCalibration:
    """The map g of the module doc: knots ``knots_p`` [J] (increasing, in [0, 1]) and ``knots_g``
    [J] (non-decreasing, in [0, 1]); the ``level`` it was fitted at; ``events``, ``margins``,
    ``num_draws``, ``step`` and ``source`` say what it was fitted on."""

    knots_p: np.ndarray
    knots_g: np.ndarray
    level: float
    events: int
    margins: tuple[float, ...]
    num_draws: int
    step: float
    source: str = ""

    def __post_init__(self) -> None:
        self.knots_p = np.asarray(self.knots_p, dtype=np.float64).reshape(-1)
        self.knots_g = np.asarray(self.knots_g, dtype=np.float64).reshape(-1)
        p, g = self.knots_p, self.knots_g
        if p.size == 0 or p.size != g.size:
            raise ValueError(f"free-path calibration: needs as many knots p as g (>= 1), got {p.size} and {g.size}")
        if not (np.isfinite(p).all() and np.isfinite(g).all() and (p >= 0).all() and (p <= 1).all()
                and (g >= 0).all() and (g <= 1).all()):
            raise ValueError("free-path calibration: knots must be finite numbers in [0, 1]")
        if (np.diff(p) <= 0).any() or (np.diff(g) < 0).any():
            raise ValueError("free-path calibration: knots p must increase and g must not decrease")
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"free-path calibration: level must lie in (0, 1), got {self.level}")

    def __call__(self, p) -> np.ndarray:
        """g(p) for probabilities p [...] (linear between knots, constant outside)."""
        return np.interp(np.asarray(p, dtype=np.float64), self.knots_p, self.knots_g)

    @classmethod
    def fit(cls, prob: np.ndarray, outcome: np.ndarray, *, level: float, margins, num_draws: int, step: float,
            source: str = "") -> "FreePathCalibration":
        """The isotonic map of outcomes [N] in {0, 1} on model probabilities prob [N] (module doc)."""
        prob, outcome = np.asarray(prob, np.float64).reshape(-1), np.asarray(outcome, np.float64).reshape(-1)
        if prob.size != outcome.size or prob.size < FREE_PATH_CALIBRATION_MIN_EVENTS:
            raise ValueError(f"free-path calibration: needs >= {FREE_PATH_CALIBRATION_MIN_EVENTS} paired events, "
                             f"got {prob.size} probabilities and {outcome.size} outcomes")
        if not ((prob >= 0) & (prob <= 1)).all() or not np.isin(outcome, (0.0, 1.0)).all():
            raise ValueError("free-path calibration: probabilities must lie in [0, 1] and outcomes be 0 or 1")
        values, inverse, counts = np.unique(prob, return_inverse=True, return_counts=True)
        freq = np.bincount(inverse, weights=outcome) / counts
        g = isotonic_regression(freq, weights=counts.astype(np.float64), increasing=True).x
        return cls(values, np.clip(g, 0.0, 1.0), float(level), int(prob.size), tuple(float(m) for m in margins),
                   int(num_draws), float(step), source)

    def to_dict(self) -> dict:
        return {"knots_p": self.knots_p.tolist(), "knots_g": self.knots_g.tolist(), "level": self.level,
                "events": self.events, "margins": list(self.margins), "num_draws": self.num_draws,
                "step": self.step, "source": self.source}

    @classmethod
    def from_dict(cls, data: dict, *, where: str) -> "FreePathCalibration":
        try:
            return cls(data["knots_p"], data["knots_g"], float(data["level"]), int(data["events"]),
                       tuple(float(m) for m in data["margins"]), int(data["num_draws"]), float(data["step"]),
                       str(data.get("source", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a free-path calibration ({exc})") from exc


def calibration_events(model, dataset, *, step: float, margins=FREE_PATH_CALIBRATION_MARGINS,
                       max_points: int = FREE_PATH_CALIBRATION_POINTS, num_draws: int = FREE_PATH_NUM_DRAWS,
                       level: float = FREE_TRANSMITTANCE_LEVEL, seed: int = 0) -> tuple[np.ndarray, np.ndarray, str]:
    """(free-path's answers [N], outcomes [N], the data in words) of the module doc's events."""
    capture = load_capture_points(dataset)
    if capture is None:
        raise ValueError(f"{dataset.root}: no capture points to calibrate free-path answers on")
    cams, near, far, pairs, sparse = calibration_view_points(dataset, capture, points="held-out")
    sparse = subsample_points(sparse, max_points, seed)
    found = rays_through_points(cams, near, far, sparse)
    if found is None:
        raise ValueError(f"{dataset.root}: no held-out capture point is seen from the calibration views")
    rays, gt = found
    device = model.region.box.device
    seg = known_segments(rays.to(device), torch.from_numpy(gt).to(device), margins)
    with torch.no_grad():
        r = segment_free_probability(FloatField(model.field), seg["starts"], seg["ends"],
                                     num_draws=num_draws, level=level, step=step,
                                     shared_noise=model.render_settings.shared_noise,
                                     generator=torch.Generator(device=device).manual_seed(seed))
    source = (f"{len(gt)} held-out {capture.source} points seen from {len(pairs)} calibration views, margins "
              f"{', '.join(f'{m:g}' for m in margins)}: {int(seg['outcome'].numel())} segments")
    return r.probability.cpu().numpy(), seg["outcome"].cpu().numpy(), source


def known_segments(rays, depth: torch.Tensor, margins) -> dict[str, torch.Tensor]:
    """The segments whose answer a seen point knows (module doc): for rays [N] (a RayBundle) through
    points at camera depth ``depth`` [N] and each margin m, from the ray's near point to camera depth
    (1 - m) y ("outcome" 1) and to (1 + m) y (0); segments whose end lies before the near point are
    left out. Returns "starts", "ends" [E, 3], "outcome" [E] (float64), "ray" [E] (the ray's index)
    and "depth" [E] (the end's camera depth), float64 on the rays' device."""
    origins, dirs = rays.origins.double().reshape(-1, 3), rays.directions.double().reshape(-1, 3)
    z, near = rays.z_scale.double().reshape(-1), rays.near.double().reshape(-1)
    y = depth.double().reshape(-1).to(origins.device)
    ends, outcome, index, d = [], [], [], []
    for m in margins:
        for factor, free in ((1.0 - m, 1.0), (1.0 + m, 0.0)):
            t = factor * y / z
            ok = t > near
            ends.append(t[ok])
            index.append(torch.nonzero(ok).reshape(-1))
            d.append(factor * y[ok])
            outcome.append(torch.full((int(ok.sum()),), free, dtype=torch.float64, device=origins.device))
    i, t = torch.cat(index), torch.cat(ends)
    return {"starts": origins[i] + near[i, None] * dirs[i], "ends": origins[i] + t[:, None] * dirs[i],
            "outcome": torch.cat(outcome), "ray": i, "depth": torch.cat(d)}


def subsample_points(sparse: dict, limit: int, seed: int) -> dict:
    """At most ``limit`` of the points of {view: SparseDepth}, drawn uniformly without replacement."""
    sizes = {v: len(sd) for v, sd in sparse.items()}
    total = sum(sizes.values())
    if total <= limit:
        return sparse
    chosen = np.zeros(total, bool)
    chosen[np.random.default_rng(seed).choice(total, limit, replace=False)] = True
    out, at = {}, 0
    for v, sd in sparse.items():
        out[v] = restrict_sparse_depth(sd, chosen[at:at + sizes[v]])
        at += sizes[v]
    return out


def fit_free_path_calibration(run_dir: str | Path, model, dataset, *, seed: int = 0) -> FreePathCalibration:
    """Fit the map of a trained S-NeRF run (module doc) and write ``RUN/free_path_calibration.json``.
    ValueError for a run of another method (``occupancy_map.require_stochastic_field``)."""
    require_stochastic_field(model, run_dir, "free-path answers")
    step = default_step(model, dataset)  # the step free-path answers with
    prob, outcome, source = calibration_events(model, dataset, step=step, seed=seed)
    cal = FreePathCalibration.fit(prob, outcome, level=FREE_TRANSMITTANCE_LEVEL, margins=FREE_PATH_CALIBRATION_MARGINS,
                                  num_draws=FREE_PATH_NUM_DRAWS, step=step, source=source)
    atomic_write_text(Path(run_dir) / FREE_PATH_CALIBRATION_FILE, json.dumps(cal.to_dict(), indent=2))
    return cal


def recalibrate_free_path(run_dir: str | Path, model, dataset, *, seed: int = 0) -> FreePathCalibration | None:
    """``fit_free_path_calibration`` with one printed line either way: the map fitted, or why not
    (a baseline's run, too few held-out points). The map, or None."""
    try:
        cal = fit_free_path_calibration(run_dir, model, dataset, seed=seed)
    except ValueError as exc:
        print(f"free-path not recalibrated: {exc}")
        return None
    print(f"free-path recalibrated ({Path(run_dir) / FREE_PATH_CALIBRATION_FILE}): "
          f"{describe_free_path_calibration(cal)}")
    return cal


def load_free_path_calibration(run_dir: str | Path) -> FreePathCalibration | None:
    """The run's free-path map, or None when it has none. ValueError (naming the file) if malformed."""
    path = Path(run_dir) / FREE_PATH_CALIBRATION_FILE
    if not path.is_file():
        return None
    return FreePathCalibration.from_dict(read_json(path, "free-path calibration"), where=str(path))


def describe_free_path_calibration(cal: FreePathCalibration) -> str:
    """One line: what the map does at its ends and what it was fitted on."""
    return (f"P(free) 0 -> {cal(0.0):.3f}, 0.5 -> {cal(0.5):.3f}, 1 -> {cal(1.0):.3f} "
            f"(level {cal.level:g}; {cal.source})")


def applies(cal: FreePathCalibration | None, level: float) -> bool:
    """Whether ``cal`` recalibrates answers at transmittance ``level`` (the level it was fitted at)."""
    return cal is not None and math.isclose(cal.level, level, rel_tol=0.0, abs_tol=1e-12)
