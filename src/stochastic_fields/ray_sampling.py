"""Error-guided choice of a training step's rays (``train.ray_sampling`` 'error').

Uniform sampling spends most of a step's rays on pixels the field already renders well. The
error map keeps, for every block of ``b x b`` pixels of the training views, the squared colour
error the last rays through it had (summed over the channels; a block no ray has visited keeps
its starting value, above any error, so every block is seen early). A step draws a block with
probability

    p_b = (1 - u) e_b n_b / sum_j e_j n_j + u n_b / P

(e_b its error, n_b its training pixels, P all of them, u = ``train.error_sampling_uniform_share``:
the uniform share that keeps every pixel reachable), then a pixel uniformly inside it: pixel i of
block b is drawn with q_i = p_b / n_b, against 1 / P under uniform sampling. Each ray's likelihood
is weighted by

    w_i = (1 / (P q_i))^alpha / mean over the batch of the same

(alpha = ``train.error_sampling_correction``): 1 makes the weighted likelihood an unbiased,
self-normalised estimate of the uniform one (importance sampling), 0 trains on the mined
distribution as it is (hard pixels count more), between is the "soft mining" of Kheradmand et
al. (CVPR 2024). After the step the blocks of the batch's rays take the mean error of their rays
(``ErrorMap.update``).

Off by default: on the captures it gained +0.06 / +0.03 dB (fern / flower) at equal steps, fern's
depth erred more, and at the paper split it lost 0.05-0.07 dB (docs/studies.md, study 50).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: A block's error before any ray has visited it: above any squared colour error of colours in
#: [0, 1] summed over three channels (at most 3), so unvisited blocks are drawn first.
UNVISITED_BLOCK_ERROR = 4.0


def pixel_blocks(views: int, height: int, width: int, block: int) -> Tensor:
    """[views * height * width] block index of every pixel (view-major, row-major, as the
    training rays are flattened): blocks of ``block`` x ``block`` pixels, each view its own."""
    if block < 1:
        raise ValueError(f"the error map's block side must be >= 1 pixel, got {block}")
    by, bx = -(-height // block), -(-width // block)
    rows = torch.arange(height) // block
    cols = torch.arange(width) // block
    within = (rows[:, None] * bx + cols[None, :]).reshape(-1)  # [H W]
    return (torch.arange(views)[:, None] * (by * bx) + within[None, :]).reshape(-1)


class ErrorMap:
    """The per-block error map of the training pixels and the sampler it drives (module doc).

    ``block_of_pixel`` [P]: each training pixel's block label (any integers; relabelled densely)."""

    def __init__(self, block_of_pixel: Tensor, *, uniform_share: float, correction: float):
        if not 0.0 <= uniform_share <= 1.0:
            raise ValueError(f"error_sampling_uniform_share must lie in [0, 1], got {uniform_share}")
        if not 0.0 <= correction <= 1.0:
            raise ValueError(f"error_sampling_correction must lie in [0, 1], got {correction}")
        if block_of_pixel.numel() == 0:
            raise ValueError("the error map needs at least one training pixel")
        labels, block = torch.unique(block_of_pixel, return_inverse=True)
        self.block = block  # [P] dense block label of each pixel
        self.order = torch.argsort(block, stable=True)  # [P] pixels grouped by block
        self.counts = torch.bincount(block, minlength=len(labels))  # [B] pixels per block
        self.starts = torch.cumsum(self.counts, 0) - self.counts  # [B] first slot of a block in `order`
        self.pixel_share = self.counts / self.counts.sum()  # [B] n_b / P: the uniform part of p_b
        self.error = torch.full((len(labels),), UNVISITED_BLOCK_ERROR)  # [B]
        self.uniform_share = float(uniform_share)
        self.correction = float(correction)

    @property
    def num_pixels(self) -> int:
        return int(self.block.numel())

    def to(self, device: torch.device) -> "ErrorMap":
        for name in ("block", "order", "counts", "starts", "pixel_share", "error"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    def block_probabilities(self) -> Tensor:
        """[B] p_b (module doc), summing to 1."""
        mined = self.error * self.pixel_share  # e_b n_b / P: the same shares as e_b n_b
        total = mined.sum()
        if not bool(total > 0):  # every block rendered exactly: nothing to mine
            return self.pixel_share
        return (1.0 - self.uniform_share) * mined / total + self.uniform_share * self.pixel_share

    def sample(self, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``n`` pixel indices [n] drawn from q (module doc) and their likelihood weights w [n]
        (mean 1). The draws use ``generator`` (on the CPU; indices follow the map's device)."""
        p = self.block_probabilities()
        cdf = torch.cumsum(p.double(), 0)
        u = torch.rand(n, generator=generator, dtype=torch.float64).to(cdf.device) * cdf[-1]
        b = torch.searchsorted(cdf, u, right=True).clamp_(max=len(p) - 1)
        v = torch.rand(n, generator=generator).to(cdf.device)
        count = self.counts[b]  # [n] pixels of each drawn block
        idx = self.order[self.starts[b] + torch.minimum((v * count).long(), count - 1)]
        if self.correction == 0.0:
            return idx, torch.ones(n, device=idx.device)
        q = p[b] / count.to(p.dtype)  # [n] probability of each drawn pixel
        w = (1.0 / (self.num_pixels * q)) ** self.correction
        return idx, (w / w.mean()).float()

    @torch.no_grad()
    def update(self, idx: Tensor, errors: Tensor) -> None:
        """Each block a ray of ``idx`` [n] went through takes the mean of those rays' ``errors`` [n]."""
        b = self.block[idx.to(self.block.device)]
        sums = torch.zeros_like(self.error).index_add_(0, b, errors.detach().to(self.error))
        hits = torch.zeros_like(self.error).index_add_(0, b, torch.ones_like(sums[b]))
        seen = hits > 0
        self.error[seen] = sums[seen] / hits[seen]

    def state_dict(self) -> dict:
        return {"error": self.error.cpu()}

    def load_state_dict(self, state: dict) -> None:
        error = state["error"]
        if error.shape != self.error.shape:
            raise ValueError(f"the checkpoint's error map has {error.shape[0]} blocks, this run's training "
                             f"pixels {self.error.shape[0]}")
        self.error.copy_(error)
