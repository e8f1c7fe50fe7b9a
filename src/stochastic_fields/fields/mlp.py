"""The paper's field: NeRF's MLP (8 x 256, skip at layer 4, positional encoding) with the last
layers doubled to output distribution parameters (Sec. 4.1: "we double the number of outputs").

    trunk(PE(x))             -> features, (mu_a, raw_s_a)
    head(features, PE(d))    -> (mu_c [3], raw_s_c [3])
    with ``noise_head``: the trunk also gives raw_beta, beta = softplus(raw_beta) (observation noise)
    s = softplus(raw) + FIELD_STD_FLOOR

Positions are first mapped to the unit cube of the scene region (NDC for forward-facing
scenes, as NeRF does). ``dropout`` (> 0) inserts dropout after the odd trunk layers, which is
the MC-Dropout baseline's backbone.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..constants import NOISE_HEAD_INIT_STD, OUTSIDE_DENSITY_LOC
from ..scene_region import SceneRegion
from .base import FieldParams, StochasticField, inverse_positive_scale, inverse_softplus, positive_scale
from .encoding import PositionalEncoding


class MLPField(StochasticField):
    def __init__(self, region: SceneRegion, *, depth: int = 8, width: int = 256, skip_layer: int = 4,
                 position_frequencies: int = 10, direction_frequencies: int = 4, head_width: int = 128,
                 dropout: float = 0.0, init_std: float = 1.0, noise_head: bool = False):
        super().__init__()
        self.region = region
        self.noise_head = bool(noise_head)
        self.pos_enc = PositionalEncoding(position_frequencies)
        self.dir_enc = PositionalEncoding(direction_frequencies)
        in_pos = self.pos_enc.output_dim(3)
        in_dir = self.dir_enc.output_dim(3)
        self.skip_layer = skip_layer
        layers = []
        for i in range(depth):
            fan_in = in_pos if i == 0 else width
            if i == skip_layer and i > 0:
                fan_in += in_pos
            layers.append(nn.Linear(fan_in, width))
        self.trunk = nn.ModuleList(layers)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else None
        self.density_head = nn.Linear(width, 3 if self.noise_head else 2)
        self.feature = nn.Linear(width, width)
        self.colour_hidden = nn.Linear(width + in_dir, head_width)
        self.colour_head = nn.Linear(head_width, 6)
        with torch.no_grad():
            raw = inverse_positive_scale(init_std)
            self.density_head.bias[1] = raw
            self.colour_head.bias[3:] = raw
            if self.noise_head:
                self.density_head.bias[2] = inverse_softplus(NOISE_HEAD_INIT_STD)

    def forward(self, positions: Tensor, directions: Tensor) -> FieldParams:
        batch = positions.shape[:-1]
        unit = self.region.to_unit(positions.reshape(-1, 3))
        x_enc = self.pos_enc(unit)
        h = x_enc
        for i, layer in enumerate(self.trunk):
            if i == self.skip_layer and i > 0:
                h = torch.cat([h, x_enc], dim=-1)
            h = torch.relu(layer(h))
            if self.dropout is not None and i % 2 == 1:
                h = self.dropout(h)
        dens = self.density_head(h)
        d_enc = self.dir_enc(directions.reshape(-1, 3))
        c = torch.relu(self.colour_hidden(torch.cat([self.feature(h), d_enc], dim=-1)))
        col = self.colour_head(c)
        outside = ~(unit.abs() <= 1.0).all(-1)
        density_loc = torch.where(outside, torch.full_like(dens[:, 0], OUTSIDE_DENSITY_LOC), dens[:, 0])
        return FieldParams(
            density_loc=density_loc.reshape(batch),
            density_scale=positive_scale(dens[:, 1]).reshape(batch),
            rgb_loc=col[:, :3].reshape(*batch, 3),
            rgb_scale=positive_scale(col[:, 3:]).reshape(*batch, 3),
            noise_scale=F.softplus(dens[:, 2]).reshape(batch) if self.noise_head else None,
        )
