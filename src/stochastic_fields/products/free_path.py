"""The planner's question: is this straight segment (or this path) free, and how sure are we?

For a segment from a to b (length L), n midpoints ``x_i = a + (i + 1/2) / n (b - a)`` (spacing
``delta = L / n <= step``) and K density trajectories drawn from the field's rectified normals,

    tau_k = sum_i relu(mu(x_i) + s(x_i) eps_ik) delta,     T_k = exp(-tau_k)     (transmittance)
    free_k = [T_k > level]                                  (the segment lets through more than ``level``)
    P(free) ~= p = (1 / K) sum_k free_k,    Monte-Carlo standard error sqrt(p (1 - p) / K)

(at p = 0 or 1 the standard error is 0; the "rule of three" bound 3 / K is then the honest
95% limit on the other outcome, returned as ``bound_95``). ``eps_ik`` is independent per point
and draw (the paper's default) or shared along the segment per draw (``shared_noise=True``,
one consistent field realisation per trajectory), as the run renders. With independent noise
the spread of tau over draws shrinks as the spacing does (tau averages n independent values);
shared noise does not average out, and is the conservative choice for a planner.

A path (waypoints w_0..w_m) is free in draw k when its whole transmittance ``prod_s T_sk``
exceeds ``level``; the draws are the same trajectories for every segment. A long path through
faint density (a model's residual "fog") accumulates optical depth, so its whole transmittance can
fall below the level while every segment passes; ``every_segment_free`` (the fraction of draws in
which every segment's own transmittance exceeds the level) answers the segment-wise question.

Everything is batched torch on the field's device (CPU or CUDA).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor
from ..defaults import (FREE_PATH_NUM_DRAWS, FREE_TRANSMITTANCE_LEVEL)  # noqa: F401  (defaults the command line shows)
from ..fields.base import density_reader
from ..renderer import draw_locs
from .occupancy_map import run_voxel_size

#: Points per chunk (segments x samples) of field evaluations.
FREE_PATH_CHUNK_POINTS: int = 262_144


@dataclass
class FreePathResult:
    """Per segment (or path) b: ``probability`` [B] of being free, ``stderr`` [B] (Monte Carlo),
    ``bound_95`` [B] (3 / K where p is 0 or 1, else 1.96 stderr), ``transmittance_mean`` [B],
    ``transmittance`` [B, K] per draw, ``num_samples`` [B] points along each, ``level``."""

    probability: Tensor
    stderr: Tensor
    bound_95: Tensor
    transmittance_mean: Tensor
    transmittance: Tensor
    num_samples: Tensor
    level: float
    every_segment_free: Tensor | None = None

    def to_dict(self) -> dict:
        return {"probability_free": self.probability.tolist(), "stderr": self.stderr.tolist(),
                "bound_95": self.bound_95.tolist(), "transmittance_mean": self.transmittance_mean.tolist(),
                "num_samples": self.num_samples.tolist(), "level": self.level,
                "num_draws": int(self.transmittance.shape[-1]),
                **({"every_segment_free": self.every_segment_free.tolist()}
                   if self.every_segment_free is not None else {})}


def free_probability(transmittance: Tensor, level: float) -> tuple[Tensor, Tensor, Tensor]:
    """(p, stderr, bound_95) from per-draw transmittances [..., K] (module doc)."""
    K = transmittance.shape[-1]
    p = (transmittance > level).to(transmittance.dtype).mean(-1)
    se = (p * (1 - p) / K).sqrt()
    bound = torch.where((p == 0) | (p == 1), torch.full_like(p, 3.0 / K), 1.959963985 * se)
    return p, se, bound


def segment_optical_depths(density_params, starts: Tensor, ends: Tensor, *, num_draws: int, step: float,
                           shared_noise: bool = False, generator: torch.Generator | None = None,
                           chunk_points: int = FREE_PATH_CHUNK_POINTS) -> tuple[Tensor, Tensor]:
    """Per-draw optical depth tau [B, K] of segments starts/ends [B, 3] and samples per segment [B].

    ``density_params(points [N, 3]) -> (loc [N], scale [N])``, or (loc, scale, offsets [N, M] or None)
    of a field with density heads (``density_head_params``): draw k then draws around loc + o_{k mod M},
    as the renderer's trajectories (``renderer.draw_locs``). Every segment gets
    ``n = max(1, ceil(L / step))`` midpoint samples; segments are padded to the longest n
    (padding has delta 0). Noise eps [B, K, n] (or [B, K, 1] shared) from ``generator``.
    """
    if starts.shape != ends.shape or starts.shape[-1] != 3 or starts.ndim != 2:
        raise ValueError(f"segments: starts and ends must both be [B, 3], got {tuple(starts.shape)} "
                         f"and {tuple(ends.shape)}")
    if not (step > 0 and math.isfinite(step)):
        raise ValueError(f"free-path step must be a positive length, got {step}")
    if num_draws < 1:
        raise ValueError(f"num_draws must be >= 1, got {num_draws}")
    device = starts.device
    B = starts.shape[0]
    seg = ends - starts
    length = seg.norm(dim=-1)  # [B]
    n = torch.clamp(torch.ceil(length / step), min=1).long()  # [B]
    n_max = int(n.max()) if B else 1
    i = torch.arange(n_max, device=device)
    frac = (i[None, :] + 0.5) / n[:, None]  # [B, n_max]
    real = i[None, :] < n[:, None]
    delta = torch.where(real, (length / n)[:, None], torch.zeros((), device=device, dtype=length.dtype))
    points = starts[:, None, :] + frac.clamp(max=1.0)[..., None] * seg[:, None, :]  # [B, n_max, 3]
    tau = torch.zeros(B, num_draws, dtype=torch.float64, device=device)
    read = density_reader(density_params)
    rows = max(1, chunk_points // n_max)
    for b0 in range(0, B, rows):
        b1 = min(B, b0 + rows)
        loc, scale, offsets = read(points[b0:b1].reshape(-1, 3))
        if offsets is not None:  # [b, K, n_max]: each draw its head's loc
            loc = draw_locs(loc.reshape(b1 - b0, n_max), offsets.reshape(b1 - b0, n_max, -1), 0, num_draws, packed=False)
        loc = loc.reshape(b1 - b0, -1, n_max).double()
        scale = scale.reshape(b1 - b0, 1, n_max).double()
        eps = torch.randn(b1 - b0, num_draws, 1 if shared_noise else n_max, generator=generator, device=device,
                          dtype=torch.float64)
        alpha = torch.relu(loc + scale * eps)  # [b, K, n_max]
        tau[b0:b1] = (alpha * delta[b0:b1, None, :].double()).sum(-1)
    return tau, n


class FloatField:
    """A float32 field evaluated at float64 query points (``density_params`` as free-path calls it)."""

    def __init__(self, field) -> None:
        self.field = field

    def density_params(self, points: Tensor):
        return self.field.density_params(points.float())

    def density_head_params(self, points: Tensor):
        return self.field.density_head_params(points.float())


def default_step(model, dataset) -> float:
    """The step along segments when none is given: half the occupancy map's voxel size from the
    images' footprint (``occupancy_map.run_voxel_size``)."""
    return 0.5 * run_voxel_size(model, dataset)


def _result(tau: Tensor, n: Tensor, level: float) -> FreePathResult:
    T = torch.exp(-tau)
    p, se, bound = free_probability(T, level)
    return FreePathResult(p, se, bound, T.mean(-1), T, n, level)


@torch.no_grad()
def segment_free_probability(field, starts: Tensor, ends: Tensor, *, num_draws: int = FREE_PATH_NUM_DRAWS,
                             level: float = FREE_TRANSMITTANCE_LEVEL, step: float, shared_noise: bool = False,
                             generator: torch.Generator | None = None) -> FreePathResult:
    """P(each segment is free) for a batch of segments starts/ends [B, 3] (module doc).

    ``field``: a StochasticField (``density_head_params``: its heads' draws too) or any callable
    points -> (loc, scale) (or (loc, scale, offsets), ``segment_optical_depths``).
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"transmittance level must lie in (0, 1), got {level}")
    fn = density_reader(field)
    tau, n = segment_optical_depths(fn, starts, ends, num_draws=num_draws, step=step, shared_noise=shared_noise,
                                    generator=generator)
    return _result(tau, n, level)


@torch.no_grad()
def path_free_probability(field, waypoints: Tensor, *, num_draws: int = FREE_PATH_NUM_DRAWS,
                          level: float = FREE_TRANSMITTANCE_LEVEL, step: float, shared_noise: bool = False,
                          generator: torch.Generator | None = None) -> tuple[FreePathResult, FreePathResult]:
    """(whole path [1], each segment [m]) for waypoints [m + 1, 3]: the path's transmittance per
    draw is the product of its segments' (the same K trajectories). With ``shared_noise`` every
    segment of a draw shares its eps (one consistent realisation along the whole path)."""
    if waypoints.ndim != 2 or waypoints.shape[-1] != 3 or waypoints.shape[0] < 2:
        raise ValueError(f"a path needs waypoints [M >= 2, 3], got {tuple(waypoints.shape)}")
    fn = density_reader(field)
    starts, ends = waypoints[:-1], waypoints[1:]
    if shared_noise and generator is None:
        generator = torch.Generator(device=waypoints.device)
        generator.manual_seed(int(torch.randint(2**62, (1,))))
    if shared_noise:
        # one eps per draw for the whole path: evaluate each segment with the same generator state
        state = generator.get_state() if generator is not None else None
        taus = []
        for s in range(starts.shape[0]):
            if generator is not None:
                generator.set_state(state)
            t, n_s = segment_optical_depths(fn, starts[s:s + 1], ends[s:s + 1], num_draws=num_draws, step=step,
                                            shared_noise=True, generator=generator)
            taus.append((t, n_s))
        tau = torch.cat([t for t, _ in taus])
        n = torch.cat([n_s for _, n_s in taus])
    else:
        tau, n = segment_optical_depths(fn, starts, ends, num_draws=num_draws, step=step, generator=generator)
    whole = _result(tau.sum(0, keepdim=True), n.sum(0, keepdim=True), level)
    whole.every_segment_free = (torch.exp(-tau) > level).all(0).to(tau.dtype).mean()[None]
    return whole, _result(tau, n, level)
