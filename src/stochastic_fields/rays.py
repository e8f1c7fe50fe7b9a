"""Ray and sample containers: small tensor dataclasses, indexable like tensors.

Axis names used everywhere in the package:
    R: rays, S: samples per ray (dense layout), N: packed samples (ragged layout),
    K: stochastic draws (trajectories), C: colour channels (3).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor


def _map_tensors(obj, fn):
    """Return a copy of dataclass ``obj`` with ``fn`` applied to every tensor field."""
    changes = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, Tensor):
            changes[f.name] = fn(value)
    return replace(obj, **changes)


@dataclass
class RayBundle:
    """A batch of rays in world coordinates (OpenCV cameras, metric units).

    Attributes:
        origins: [*B, 3] ray origins (camera centres).
        directions: [*B, 3] unit ray directions in world coordinates.
        near: [*B] distance along the ray where sampling starts.
        far: [*B] distance along the ray where sampling ends.
        z_scale: [*B] camera-z depth per unit ray distance (cosine between the ray and the
            optical axis): ``camera_z_depth = ray_distance * z_scale``.
    """

    origins: Tensor
    directions: Tensor
    near: Tensor
    far: Tensor
    z_scale: Tensor

    @property
    def shape(self) -> torch.Size:
        return self.origins.shape[:-1]

    def __len__(self) -> int:
        return self.origins.shape[0]

    def __getitem__(self, index) -> "RayBundle":
        return _map_tensors(self, lambda t: t[index])

    def reshape(self, *shape: int) -> "RayBundle":
        def fn(t: Tensor) -> Tensor:
            trailing = t.shape[len(self.shape):]
            return t.reshape(*shape, *trailing)

        return _map_tensors(self, fn)

    def flatten(self) -> "RayBundle":
        return self.reshape(-1)

    def to(self, device: torch.device | str) -> "RayBundle":
        return _map_tensors(self, lambda t: t.to(device))

    @staticmethod
    def cat(bundles: list["RayBundle"]) -> "RayBundle":
        first = bundles[0]
        changes = {f.name: torch.cat([getattr(b, f.name) for b in bundles]) for f in fields(first)}
        return replace(first, **changes)


@dataclass
class RaySamples:
    """Samples along rays, dense layout: every ray has S samples.

    Each sample i covers the interval [t_starts[i], t_ends[i]] of ray distance; the field is
    evaluated at the interval midpoint ``t_mids``.

    Attributes:
        rays: the RayBundle with shape [R].
        t_starts: [R, S] interval starts (ray distance), non-decreasing along S.
        t_ends: [R, S] interval ends, ``t_ends[..., i] <= t_starts[..., i + 1]``.
    """

    rays: RayBundle
    t_starts: Tensor
    t_ends: Tensor

    @property
    def t_mids(self) -> Tensor:
        """[R, S] interval midpoints, where the field is evaluated."""
        return 0.5 * (self.t_starts + self.t_ends)

    @property
    def deltas(self) -> Tensor:
        """[R, S] interval lengths."""
        return self.t_ends - self.t_starts

    @property
    def positions(self) -> Tensor:
        """[R, S, 3] world positions of the midpoints."""
        return self.rays.origins[..., None, :] + self.t_mids[..., None] * self.rays.directions[..., None, :]

    @property
    def directions(self) -> Tensor:
        """[R, S, 3] view directions broadcast to every sample."""
        return self.rays.directions[..., None, :].expand(*self.t_starts.shape, 3)


@dataclass
class PackedRaySamples:
    """Samples along rays, packed (ragged) layout after empty-space skipping.

    Samples of one ray are contiguous and sorted by distance. Reductions over rays use
    ``index_add_`` with ``ray_indices``.

    Attributes:
        rays: the RayBundle with shape [R].
        ray_indices: [N] int64, which ray each sample belongs to (sorted ascending).
        t_starts: [N] interval starts.
        t_ends: [N] interval ends.
    """

    rays: RayBundle
    ray_indices: Tensor
    t_starts: Tensor
    t_ends: Tensor

    @property
    def num_rays(self) -> int:
        return len(self.rays)

    @property
    def t_mids(self) -> Tensor:
        return 0.5 * (self.t_starts + self.t_ends)

    @property
    def deltas(self) -> Tensor:
        return self.t_ends - self.t_starts

    @property
    def positions(self) -> Tensor:
        """[N, 3] world positions of the midpoints."""
        return self.rays.origins[self.ray_indices] + self.t_mids[:, None] * self.rays.directions[self.ray_indices]

    @property
    def directions(self) -> Tensor:
        """[N, 3]"""
        return self.rays.directions[self.ray_indices]
