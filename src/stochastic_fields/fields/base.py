"""The narrow field interface every backend implements.

A stochastic field maps points and view directions to the parameters of two distributions
(docs/definitions.md §2):

    density  alpha = relu(density_loc + density_scale * eps)          (rectified normal)
    radiance r_c   = sigmoid(rgb_loc_c + rgb_scale_c * eps_c)          (logistic normal)

Scales are positive: ``softplus(raw) + FIELD_STD_FLOOR``.
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
    return float(y + torch.log(-torch.expm1(torch.tensor(-y, dtype=torch.float64))))


@dataclass
class FieldParams:
    """Distribution parameters at a batch of points.

    Attributes:
        density_loc: [*B] mean of the Gaussian before the ReLU (mu_a).
        density_scale: [*B] its standard deviation (s_a > 0).
        rgb_loc: [*B, 3] mean of the colour logits (mu_c).
        rgb_scale: [*B, 3] standard deviation of the colour logits (s_c > 0).
    """

    density_loc: Tensor
    density_scale: Tensor
    rgb_loc: Tensor
    rgb_scale: Tensor

    @property
    def shape(self) -> torch.Size:
        return self.density_loc.shape

    def map(self, fn) -> "FieldParams":
        return replace(self, **{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    def reshape(self, *shape: int) -> "FieldParams":
        return FieldParams(
            density_loc=self.density_loc.reshape(*shape),
            density_scale=self.density_scale.reshape(*shape),
            rgb_loc=self.rgb_loc.reshape(*shape, 3),
            rgb_scale=self.rgb_scale.reshape(*shape, 3),
        )

    @staticmethod
    def cat(parts: list["FieldParams"], dim: int = 0) -> "FieldParams":
        return FieldParams(**{f.name: torch.cat([getattr(p, f.name) for p in parts], dim) for f in fields(parts[0])})


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

    def density_params(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """(density_loc, density_scale) at ``positions`` [*B, 3]; used by occupancy updates.

        Backends may override with a cheaper path that skips colour.
        """
        directions = torch.zeros_like(positions)
        directions[..., 2] = 1.0
        out = self.forward(positions, directions)
        return out.density_loc, out.density_scale
