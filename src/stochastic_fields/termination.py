"""A pixel's depth distribution as the model defines it: the mixture over K trajectories of each
trajectory's termination distribution along the ray (docs/definitions.md §3.8).

Trajectory k of a ray has, on its sample intervals [t_i, t_i + delta_i] (ray distance), a constant
density a_ik; its compositing weights are w_ik = T_ik alpha_ik with alpha_ik = 1 - exp(-a_ik delta_i)
and T_ik = 1 - sum_{j<i} w_jk. Its termination distance has, inside interval i at the fraction
u = (t - t_i) / delta_i, the exact CDF of a constant density,

    G_k(t) = sum_{j<i} w_jk + T_ik (1 - (1 - alpha_ik)^u),

flat between intervals (skipped samples carry no mass). As the depth map (``volume_rendering.
expected_depth``: D_k = sum_i w_ik t_i / sum_i w_ik, ``far`` where the opacity A_k = sum_i w_ik is
below ``OPACITY_EPS``), a trajectory's depth is its termination distance *given that the ray
terminates*: F_k(t) = G_k(t) / A_k, or all mass at ``far`` for a trajectory that hits nothing. The
pixel's predictive distribution is the mixture F(t) = (1 / K) sum_k F_k(t): its mean is the depth
mean (up to the exact position inside each interval instead of the midpoint) and its variance the
total depth variance (epistemic + spread, the law of total variance).

Unlike one Gaussian (depth mean, total std), the mixture has mass only where some trajectory
terminates: a pixel whose rays split their mass between two surfaces gets two modes, so a band
can cover the far surface where there is one instead of widening every pixel's band.

Depths are camera z: ray distance times the ray's ``z_scale``. Everything is float64 torch on the
render's device. ``quantiles`` is exact up to a bisection on u inside one interval
(``TERMINATION_BISECTION_STEPS``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from .constants import OPACITY_EPS
from .rays import PackedRaySamples, RayBundle

#: Bisection steps on the fraction u in [0, 1] of the interval holding a quantile: 2^-52 of the
#: interval, float64's resolution.
TERMINATION_BISECTION_STEPS: int = 52


def _log_clear(alpha: Tensor) -> Tensor:
    """log(1 - alpha), finite for an opaque interval (alpha clamped below 1; ``_mass_inside`` treats alpha = 1)."""
    return torch.log1p(-alpha.clamp(max=1.0 - 1e-16))


def _mass_inside(T: Tensor, alpha: Tensor, log_clear: Tensor, u: Tensor) -> Tensor:
    """T (1 - (1 - alpha)^u): the mass a constant-density interval stops in its first fraction u
    (module doc), for transmittance T at its start, opacity alpha and ``_log_clear(alpha)``; an
    opaque interval (alpha = 1) stops all of T at its front."""
    inside = T * -torch.expm1(u * log_clear)
    return torch.where(alpha >= 1.0, torch.where(u > 0, T, torch.zeros_like(T)), inside)


@dataclass
class TerminationMixture:
    """Per ray r: sample intervals ``t_starts``, ``t_ends`` [R, S] (ray distance, sorted, not
    overlapping; padding intervals have zero length and weight), compositing weights ``weights``
    [R, K, S] of K trajectories, ``far`` [R] (where the passing mass sits) and ``z_scale`` [R]
    (camera z per unit ray distance). float64."""

    t_starts: Tensor
    t_ends: Tensor
    weights: Tensor
    far: Tensor
    z_scale: Tensor

    def __post_init__(self) -> None:
        R, S = self.t_starts.shape
        if self.t_ends.shape != (R, S) or self.weights.ndim != 3 or self.weights.shape[0] != R \
                or self.weights.shape[2] != S or self.far.shape != (R,) or self.z_scale.shape != (R,):
            raise ValueError(f"termination mixture: t_starts, t_ends [R, S], weights [R, K, S], far and z_scale [R] "
                             f"expected, got {tuple(self.t_starts.shape)}, {tuple(self.t_ends.shape)}, "
                             f"{tuple(self.weights.shape)}, {tuple(self.far.shape)}, {tuple(self.z_scale.shape)}")

    @property
    def num_rays(self) -> int:
        return self.t_starts.shape[0]

    def _parts(self) -> tuple[Tensor, Tensor, Tensor]:
        """(w [R, K, S]: the weights, negative ones as 0; C [R, K, S + 1]: each trajectory's mass before
        each interval and after the last; scale [R, K]: 1 / A_k for a trajectory that hits something,
        else 0, so a trajectory that hits nothing keeps all its mass at far)."""
        w = self.weights.clamp_min(0.0)
        C = torch.cat([torch.zeros_like(w[..., :1]), w.cumsum(-1)], dim=-1).clamp(max=1.0)
        acc = C[..., -1]
        scale = torch.where(acc >= OPACITY_EPS, 1.0 / acc.clamp_min(OPACITY_EPS), torch.zeros_like(acc))
        return w, C, scale

    @staticmethod
    def _alpha_at(w: Tensor, T_at: Tensor, index: Tensor) -> Tensor:
        """alpha [R, K, Q] of the intervals ``index`` [R, K, Q] (< S), given ``T_at`` = 1 - C there (the
        mass left before each): w_i / T_i, 0 where nothing is left to stop, clamped to [0, 1]. Only the
        intervals asked for: the CDF and the quantiles read one interval per value, so the [R, K, S]
        opacities are never formed."""
        T = T_at.clamp_min(0.0)
        wi = w.gather(2, index)
        return torch.where(T > 0, wi / T.clamp_min(torch.finfo(w.dtype).tiny), torch.zeros_like(wi)).clamp(0.0, 1.0)

    def select(self, index: Tensor) -> "TerminationMixture":
        """The mixtures of rays ``index`` (indices or a mask over R)."""
        return TerminationMixture(*(getattr(self, f.name)[index] for f in fields(self)))

    @classmethod
    def concatenate(cls, parts: list["TerminationMixture"]) -> "TerminationMixture":
        """The rays of ``parts`` in order, each padded to the most intervals with zero-length,
        zero-weight intervals at its ``far``."""
        S = max(m.t_starts.shape[1] for m in parts)

        def pad(m: TerminationMixture) -> TerminationMixture:
            edge = m.far[:, None].expand(-1, S - m.t_starts.shape[1])
            return cls(torch.cat([m.t_starts, edge], 1), torch.cat([m.t_ends, edge], 1),
                       torch.nn.functional.pad(m.weights, (0, edge.shape[1])), m.far, m.z_scale)

        padded = [pad(m) for m in parts]
        return cls(*(torch.cat([getattr(m, f.name) for m in padded]) for f in fields(cls)))

    def cdf(self, depth: Tensor) -> Tensor:
        """F(d) at camera-z depths ``depth`` [R, Q] (or [R]) -> [R, Q] (or [R]): the mixture's
        probability that the depth is at most d (module doc); 1 at and beyond ``far``."""
        flat = depth.ndim == 1
        d = (depth[:, None] if flat else depth).to(self.t_starts)
        t = d / self.z_scale[:, None]  # ray distance [R, Q]
        w, C, scale = self._parts()
        i = torch.searchsorted(self.t_ends.contiguous(), t.contiguous(), right=True)  # intervals ended by t [R, Q]
        S = self.t_starts.shape[1]
        ic = i.clamp(max=S - 1)
        ts, te = self.t_starts.gather(1, ic), self.t_ends.gather(1, ic)
        u = torch.where((i < S) & (t > ts), (t - ts) / (te - ts).clamp_min(torch.finfo(t.dtype).tiny),
                        torch.zeros_like(t)).clamp(0.0, 1.0)  # [R, Q]
        K = C.shape[1]
        before = C.gather(2, i[:, None, :].expand(-1, K, -1))  # [R, K, Q]
        at = ic[:, None, :].expand(-1, K, -1)
        T = 1.0 - C.gather(2, at)
        a = self._alpha_at(w, T, at)
        inside = _mass_inside(T, a, _log_clear(a), u[:, None, :])
        G = before + torch.where((i < S)[:, None, :], inside, torch.zeros_like(inside))
        F = (scale[..., None] * G).mean(1)
        F = torch.where(t >= self.far[:, None], torch.ones_like(F), F.clamp(0.0, 1.0))
        return F[:, 0] if flat else F

    def survival(self, depth: Tensor) -> Tensor:
        """P(depth > d) = 1 - F(d) at camera z ``depth`` (given that the ray terminates, as the depth map)."""
        return 1.0 - self.cdf(depth)

    def quantiles(self, levels: Tensor) -> Tensor:
        """F^-1(p) at ``levels`` [Q] (shared) or [R, Q] in (0, 1) -> camera-z depths [R, Q]: the
        smallest d with F(d) >= p; ``far`` where p exceeds the mass of the trajectories that hit something."""
        w, C, scale = self._parts()
        R, K, _ = C.shape
        S = self.t_starts.shape[1]
        p = levels.to(self.t_starts)
        p = p.expand(R, -1) if p.ndim == 1 else p
        if not bool(((p > 0) & (p < 1)).all()):
            raise ValueError("termination quantiles: levels must lie strictly between 0 and 1")
        F_edges = (scale[..., None] * C).mean(1)  # [R, S + 1]: F at the first start (0) and each interval's end
        i = torch.searchsorted(F_edges[:, 1:].contiguous(), p.contiguous())  # first interval reaching p [R, Q]
        beyond = i >= S
        ic = i.clamp(max=S - 1)
        at = ic[:, None, :].expand(-1, K, -1)
        Cb = C.gather(2, at)  # [R, K, Q]
        T = 1.0 - Cb
        a = self._alpha_at(w, T, at)
        log_clear = _log_clear(a)
        lo, hi = torch.zeros_like(p), torch.ones_like(p)
        for _ in range(TERMINATION_BISECTION_STEPS):
            mid = 0.5 * (lo + hi)  # > 0
            F = (scale[..., None] * (Cb + _mass_inside(T, a, log_clear, mid[:, None, :]))).mean(1)
            below = F < p
            lo, hi = torch.where(below, mid, lo), torch.where(below, hi, mid)
        ts, te = self.t_starts.gather(1, ic), self.t_ends.gather(1, ic)
        t = torch.where(beyond, self.far[:, None].expand_as(p), ts + hi * (te - ts))
        return t * self.z_scale[:, None]


def termination_mixture(samples, weights: Tensor, rays: RayBundle) -> TerminationMixture:
    """The ``TerminationMixture`` of a render's samples (``RaySamples`` [R, S] with weights
    [R, K, S], or ``PackedRaySamples`` [N] with weights [K, N], padded to the most samples of a
    ray with zero-length, zero-weight intervals at ``far``)."""
    far = rays.far.reshape(-1).double()
    z = rays.z_scale.reshape(-1).double()
    if not isinstance(samples, PackedRaySamples):
        return TerminationMixture(samples.t_starts.double(), samples.t_ends.double(), weights.double(), far, z)
    R = far.shape[0]
    ray = samples.ray_indices
    counts = torch.bincount(ray, minlength=R)
    S = max(1, int(counts.max())) if ray.numel() else 1
    first = torch.cumsum(counts, 0) - counts
    slot = torch.arange(ray.numel(), device=ray.device) - first[ray]
    ts = far[:, None].repeat(1, S)
    te = ts.clone()
    ts[ray, slot], te[ray, slot] = samples.t_starts.double(), samples.t_ends.double()
    K = weights.shape[0]
    w = torch.zeros(R, K, S, dtype=torch.float64, device=weights.device)
    w[ray, :, slot] = weights.double().T
    return TerminationMixture(ts, te, w, far, z)


#: The level of the median depth estimate (``RenderSettings.depth_estimate`` "median").
MEDIAN_LEVEL: float = 0.5


def median_depth(samples, weights: Tensor, rays: RayBundle) -> Tensor:
    """[R] ray distance: each ray's median termination distance F^-1(1/2) of the mixture of its K
    trajectories (``termination_mixture`` of a render's samples and weights; ``far`` where at least
    half the trajectories hit nothing, as the mean depth puts them), float64."""
    mixture = termination_mixture(samples, weights, rays)
    half = torch.full((mixture.num_rays, 1), MEDIAN_LEVEL, dtype=torch.float64, device=mixture.t_starts.device)
    return mixture.quantiles(half)[:, 0] / mixture.z_scale


def with_depth_estimate(out, rays: RayBundle, estimate: str):
    """The render ``out`` (``renderer.RayRender``) with its depth map the point estimate ``estimate``
    (``RenderSettings.depth_estimate``): "mean" leaves it as rendered; "median" replaces
    ``stats.depth_mean`` by ``median_depth`` of the same draws (the variances stay about the mean)."""
    if estimate == "mean":
        return out
    if estimate != "median":
        raise ValueError(f"depth estimate must be 'mean' or 'median', got {estimate!r}")
    median = median_depth(out.samples, out.extras["weights"], rays).to(out.stats.depth_mean)
    return replace(out, stats=replace(out.stats, depth_mean=median.reshape(out.stats.depth_mean.shape)))


@torch.no_grad()
def render_termination(model, rays: RayBundle, options=None, *, generator: torch.Generator | None = None
                       ) -> tuple[dict[str, Tensor], TerminationMixture]:
    """Render rays [N] as ``model.render_chunk`` does (chunks of ``options.chunk_rays``, the same
    samples, skipping and noise) and return ({"depth_mean", "depth_std", "opacity"} [N], camera z,
    float64; the K trajectories' ``TerminationMixture``) of the same draws."""
    options = options or model.default_render_options()
    stats: dict[str, list[Tensor]] = {"depth_mean": [], "depth_std": [], "opacity": []}
    parts: list[TerminationMixture] = []
    for c0 in range(0, len(rays), options.chunk_rays):
        chunk = rays[c0:c0 + options.chunk_rays]
        out = model.render_chunk(chunk, options, generator=generator)
        z = chunk.z_scale.reshape(-1).double()
        stats["depth_mean"].append(out.stats.depth_mean.double() * z)
        stats["depth_std"].append(out.stats.depth_var_total.double().clamp_min(0).sqrt() * z)
        stats["opacity"].append(out.stats.opacity.double())
        parts.append(termination_mixture(out.samples, out.extras["weights"], chunk))
    return {k: torch.cat(v) for k, v in stats.items()}, TerminationMixture.concatenate(parts)
