"""The narrow field interface every backend implements.

A stochastic field maps points and view directions to the parameters of two distributions
(docs/definitions.md §2):

    density  alpha = relu(density_loc + density_scale * eps)          (rectified normal)
    radiance r_c   = sigmoid(rgb_loc_c + rgb_scale_c * eps_c)          (logistic normal)

Scales are positive: ``softplus(raw) + FIELD_STD_FLOOR``. A field built with an observation-noise
head also returns ``noise_scale`` beta(x) >= 0, the standard deviation (colour units) of the pixel
noise a point contributes (``loss.per_point_noise``, docs/definitions.md §4.7): a learned point
value, not a random variable.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, fields, replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..constants import FIELD_STD_FLOOR


def positive_scale(raw: Tensor) -> Tensor:
    """Map an unconstrained tensor to a standard deviation: softplus(raw) + FIELD_STD_FLOOR."""
    return F.softplus(raw) + FIELD_STD_FLOOR


def inverse_positive_scale(std: float) -> float:
    """Raw value whose ``positive_scale`` is ``std`` (for initialisation)."""
    y = std - FIELD_STD_FLOOR
    if y <= 0:
        raise ValueError(f"std must exceed FIELD_STD_FLOOR={FIELD_STD_FLOOR}, got {std}")
    return inverse_softplus(y)


def inverse_softplus(y: float) -> float:
    """x with softplus(x) = y > 0 (initial raw value of a softplus-positive output)."""
    if not y > 0:
        raise ValueError(f"inverse_softplus needs y > 0, got {y}")
    return float(y + torch.log(-torch.expm1(torch.tensor(-y, dtype=torch.float64))))


@dataclass
class FieldParams:
    """Distribution parameters at a batch of points.

    Attributes:
        density_loc: [*B] mean of the Gaussian before the ReLU (mu_a).
        density_scale: [*B] its standard deviation (s_a > 0).
        rgb_loc: [*B, 3] mean of the colour logits (mu_c).
        rgb_scale: [*B, 3] standard deviation of the colour logits (s_c > 0).
        noise_scale: None, or [*B] the observation-noise std beta(x) >= 0 of a field with a noise head.
        density_offsets: None, or [*B, M] the density heads' offsets o_h of a field with M density
            heads (``field.density_heads``): trajectory k draws its density around
            density_loc + o_{k mod M}; the offsets sum to 0 over the heads, so density_loc is their centre.
    """

    density_loc: Tensor
    density_scale: Tensor
    rgb_loc: Tensor
    rgb_scale: Tensor
    noise_scale: Tensor | None = None
    density_offsets: Tensor | None = None

    @property
    def shape(self) -> torch.Size:
        return self.density_loc.shape

    def map(self, fn) -> "FieldParams":
        """``fn`` applied to every tensor (an absent ``noise_scale`` or ``density_offsets`` stays None)."""
        return replace(self, **{f.name: fn(getattr(self, f.name)) for f in fields(self)
                                if getattr(self, f.name) is not None})

    def reshape(self, *shape: int) -> "FieldParams":
        return FieldParams(
            density_loc=self.density_loc.reshape(*shape),
            density_scale=self.density_scale.reshape(*shape),
            rgb_loc=self.rgb_loc.reshape(*shape, 3),
            rgb_scale=self.rgb_scale.reshape(*shape, 3),
            noise_scale=None if self.noise_scale is None else self.noise_scale.reshape(*shape),
            density_offsets=None if self.density_offsets is None
            else self.density_offsets.reshape(*shape, self.density_offsets.shape[-1]),
        )

    @staticmethod
    def cat(parts: list["FieldParams"], dim: int = 0) -> "FieldParams":
        for name in ("noise_scale", "density_offsets"):
            if len({getattr(p, name) is None for p in parts}) > 1:
                raise ValueError(f"cannot concatenate field parameters with and without {name}")
        return FieldParams(**{f.name: torch.cat([getattr(p, f.name) for p in parts], dim) for f in fields(parts[0])
                              if getattr(parts[0], f.name) is not None})


def density_reader(source):
    """``points [N, 3] -> (loc [N], scale [N], offsets [N, M] or None)`` of ``source``: its
    ``density_head_params`` (a field with density heads gives their offsets), else its
    ``density_params`` (no heads), else ``source`` itself (a callable returning either)."""
    if hasattr(source, "density_head_params"):
        return source.density_head_params
    fn = getattr(source, "density_params", source)

    def read(points: Tensor):
        loc, scale, *heads = fn(points)
        return loc, scale, heads[0] if heads else None

    return read


class StochasticField(nn.Module, abc.ABC):
    """Base class: ``forward(positions [*B, 3], directions [*B, 3]) -> FieldParams [*B]``.

    ``directions`` are unit vectors in world coordinates. Backends that ignore the view
    direction still take it. ``aabb`` ([2, 3] buffer: min and max corners) is the region the
    field models; outside it the field returns empty space (density_loc very negative).
    """

    aabb: Tensor

    @abc.abstractmethod
    def forward(self, positions: Tensor, directions: Tensor) -> FieldParams:  # pragma: no cover
        ...

    def density_unit_factor(self) -> float | Tensor:
        """k: the world density per unit of the field's own density parameter (1 unless a grid
        counts density per cell, ``GridField``: its 0-d buffer, so a training step reads it
        without a device sync); priors on the density scale with it."""
        return 1.0

    def forward_colour_where(self, positions: Tensor, directions: Tensor, colour_where) -> FieldParams:
        """``forward``, with the colour parameters needed only where ``colour_where(density_loc [P],
        density_scale [P]) -> [P] bool`` (flat over the batch, detached) is True; elsewhere they may
        be placeholders (``renderer.colour_plan``: colours no trajectory reaches). Backends whose
        colour costs more than their density override it; by default every colour is computed."""
        return self.forward(positions, directions)

    def density_params(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """(density_loc, density_scale) at ``positions`` [*B, 3]; used by occupancy updates.

        Backends may override with a cheaper path that skips colour.
        """
        directions = torch.zeros_like(positions)
        directions[..., 2] = 1.0
        out = self.forward(positions, directions)
        return out.density_loc, out.density_scale

    def density_head_params(self, positions: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """``density_params`` and the density heads' offsets ([*B, M], ``FieldParams.density_offsets``;
        None for a field of one head, as every backend but a grid with ``density_heads`` > 1)."""
        loc, scale = self.density_params(positions)
        return loc, scale, None
