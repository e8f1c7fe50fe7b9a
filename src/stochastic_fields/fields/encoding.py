"""Input encodings for the MLP field."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class PositionalEncoding(nn.Module):
    """NeRF's frequency encoding: x -> [x, sin(2^l pi x), cos(2^l pi x)] for l < num_frequencies.

    Shapes: [*B, D] -> [*B, D * (1 + 2 L)] (``include_input=True``).
    """

    def __init__(self, num_frequencies: int, include_input: bool = True):
        super().__init__()
        self.num_frequencies = num_frequencies
        self.include_input = include_input
        self.register_buffer("freqs", (2.0 ** torch.arange(num_frequencies)) * torch.pi, persistent=False)

    def output_dim(self, input_dim: int) -> int:
        return input_dim * (2 * self.num_frequencies + int(self.include_input))

    def forward(self, x: Tensor) -> Tensor:
        scaled = (x[..., None, :] * self.freqs.to(x)[:, None]).flatten(-2)  # [*B, L * D]
        parts = [torch.sin(scaled), torch.cos(scaled)]
        if self.include_input:
            parts.insert(0, x)
        return torch.cat(parts, dim=-1)
