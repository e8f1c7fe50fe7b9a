"""Weighted row gathers from a cell table whose gradient is kept as summed rows.

A grid level is a table ``[N, C]``; a batch reads a few hundred thousand of its rows (8 trilinear
corners per sample). Autograd's own options for the table's gradient are both slow on CPU: a
dense ``[N, C]`` gradient costs O(N) to zero, accumulate and optimise at every step, and a
sparse COO gradient costs a copy or a sort each time two of them are added (measured: ~40 ms
per add for 550k rows at N = 2M, more than the whole forward pass).

Here the backward pass adds each row's gradient straight into a :class:`RowGradient` attached
to the table (a scratch table plus a bitmap of touched rows), and returns no gradient for the
table itself. The optimiser (``optim.RowSparseAdam``) updates the touched rows from it and resets
them, so zeroing costs O(touched rows): ``zero`` clears the whole table only when something was
accumulated that no optimiser step took (an O(N) clear at every step cost 7 ms at N = 2M and 54 ms
at 16M). On the CPU both loops are compiled (``row_kernels``: a capture's
training step 1.6-2.0x faster than with the ``index_add_`` and gathers); on CUDA they are torch ops.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .. import row_kernels


class RowGradient:
    """Summed gradient rows of a table [N, C]: a scratch table and a touched-row bitmap.

    ``replace`` sets the whole gradient to given (rows, values) at once (the distributed
    reduction's result), kept as they are until ``take`` hands them to the optimiser.
    """

    def __init__(self) -> None:
        self._acc: Tensor | None = None
        self._touched: Tensor | None = None
        self._replaced: tuple[Tensor, Tensor] | None = None
        #: Whether the buffers may hold rows no ``take`` or in-place step has reset since they were
        #: last all zero.
        self._dirty = False

    def _buffers(self, like: Tensor) -> tuple[Tensor, Tensor]:
        if self._acc is None or self._acc.shape != like.shape or self._acc.device != like.device \
                or self._acc.dtype != like.dtype:
            self._acc = torch.zeros_like(like)
            self._touched = torch.zeros(like.shape[0], dtype=torch.bool, device=like.device)
        return self._acc, self._touched

    def _unreplace(self, table: Tensor) -> tuple[Tensor, Tensor]:
        """The buffers, with a pending ``replace`` written into them."""
        acc, touched = self._buffers(table)
        if self._replaced is not None:
            rows, values = self._replaced
            self._replaced = None
            acc.index_add_(0, rows, values.to(acc.dtype))
            touched[rows] = True
            self._dirty = True
        return acc, touched

    def add(self, table: Tensor, rows: Tensor, values: Tensor, channels: slice | None = None) -> None:
        """Accumulate values [M, C] into rows [M] (duplicates summed); with ``channels``, values
        [M, c] into those channels only (the others' gradient is zero for these rows)."""
        acc, touched = self._unreplace(table)
        self._dirty = True
        (acc if channels is None else acc[:, channels]).index_add_(0, rows, values.to(acc.dtype))
        touched[rows] = True

    def add_weighted(self, table: Tensor, idx: Tensor, weights: Tensor, grad: Tensor,
                     channels: slice | None = None) -> None:
        """Accumulate ``weights[m, j] grad[m, c]`` into rows ``idx[m, j]`` (idx, weights [M, J], grad
        [M, c]; the channels of ``channels``, all by default): the backward of a weighted gather.
        On the CPU one compiled loop (``row_kernels``), else the products and ``add``."""
        acc, touched = self._unreplace(table)
        start, _, stride = (0, acc.shape[1], 1) if channels is None else channels.indices(acc.shape[1])
        grad, weights, idx = grad.to(acc.dtype).contiguous(), weights.to(acc.dtype).contiguous(), idx.contiguous()
        if stride == 1 and row_kernels.available(acc, touched, idx, weights, grad):
            self._dirty = True
            row_kernels.scatter_weighted_rows(acc, touched, idx, weights, grad, start)
            return
        # w_mj g_mc as one einsum: the broadcast product took ~3x as long on CPU in isolation (same values)
        rows = torch.einsum("mj,mc->mjc", weights, grad).reshape(-1, grad.shape[-1])
        self.add(table, idx.reshape(-1), rows, channels)

    def pending(self, table: Tensor) -> tuple[Tensor, Tensor] | None:
        """(accumulated gradient [N, C], touched rows [N] bool), the buffers themselves, when they hold
        the whole gradient since the last reset; None when a ``replace``d gradient waits or nothing was
        ever accumulated. For an optimiser that updates the touched rows in place, resets both and
        then calls ``mark_reset``
        (``optim.RowSparseAdam``)."""
        if self._replaced is not None or self._acc is None:
            return None
        return self._buffers(table)

    def take(self, table: Tensor) -> tuple[Tensor, Tensor]:
        """(rows [U] ascending, gradient [U, C]) accumulated since the last take; resets to zero."""
        if self._replaced is not None and self._acc is not None and self._acc.shape == table.shape:
            rows, grad = self._replaced
            self._replaced = None
            return rows, grad.to(table.dtype)
        acc, touched = self._unreplace(table)
        rows = touched.nonzero().squeeze(1)
        grad = acc[rows]
        acc[rows] = 0.0
        touched[rows] = False
        self._dirty = False
        return rows, grad

    def mark_reset(self) -> None:
        """Say that the caller of ``pending`` has zeroed every touched row and cleared the bitmap."""
        self._dirty = False

    def touched_rows(self, table: Tensor) -> Tensor:
        """[N] bool: the rows accumulated into since the last take (a copy)."""
        return self._unreplace(table)[1].clone()

    def rows(self, table: Tensor, rows: Tensor) -> Tensor:
        """[U, C] the accumulated gradient of ``rows`` [U] (zero where untouched); nothing is reset."""
        return self._unreplace(table)[0].index_select(0, rows)

    def replace(self, table: Tensor, rows: Tensor, values: Tensor) -> None:
        """Make rows [U] (ascending, unique) with gradient values [U, C] the whole accumulated
        gradient (the distributed reduction's average over the ranks); what was accumulated is
        dropped. ``take`` returns them as given (no second gather)."""
        self.zero()
        self._buffers(table)
        self._replaced = (rows, values)

    def zero(self) -> None:
        """Drop everything accumulated (O(N) only when rows wait that no step took)."""
        self._replaced = None
        if self._acc is not None and self._dirty:
            self._acc.zero_()
            self._touched.zero_()
        self._dirty = False

    def dense(self, table: Tensor) -> Tensor:
        """[N, C] the accumulated gradient as a dense table (for tests and inspection)."""
        out = self._buffers(table)[0].clone()
        if self._replaced is not None:
            out.index_add_(0, self._replaced[0], self._replaced[1].to(out.dtype))
        return out


def row_gradient(table: Tensor) -> RowGradient:
    """The :class:`RowGradient` of ``table`` (attached on first use)."""
    acc = getattr(table, "row_gradient", None)
    if acc is None:
        acc = RowGradient()
        table.row_gradient = acc
    return acc


def _weighted_sum_of_rows(table: Tensor, idx: Tensor, weights: Tensor, channels: slice | None = None) -> Tensor:
    """``sum_j weights[m, j] table[idx[m, j], channels]`` [M, C] (or [M, c]) as one fused gather-and-sum
    (``embedding_bag``, bags of J rows): it never forms the [M, J, C] corner tensor, which made
    the gather 10-14x slower on CPU at 32k-131k points (measured, float32, 2M-row table).

    A ``channels`` slice is taken of the sums, not of the table: ``embedding_bag`` reads a strided
    table slice only after copying it whole (a [2M, 2] copy each call, 18 ms on CPU, against 3 ms for
    the sums of every channel at a depth likelihood's 16k points; measured, 1 thread)."""
    out = F.embedding_bag(idx, table, per_sample_weights=weights.to(table.dtype), mode="sum")
    return out if channels is None else out[:, channels]


class _WeightedRowGather(torch.autograd.Function):
    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, weights: Tensor, channels: slice | None) -> Tensor:
        ctx.save_for_backward(table, idx, weights)
        ctx.channels = channels
        return _weighted_sum_of_rows(table, idx, weights, channels)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        table, idx, weights = ctx.saved_tensors
        channels = ctx.channels
        grad_w = None
        if ctx.needs_input_grad[0]:
            row_gradient(table).add_weighted(table, idx, weights, grad_out, channels)
        if ctx.needs_input_grad[2]:
            M, J = idx.shape
            read = table if channels is None else table[:, channels]
            corners = read.index_select(0, idx.reshape(-1)).view(M, J, grad_out.shape[-1])
            grad_w = torch.bmm(corners, grad_out[:, :, None].to(corners.dtype))[..., 0]
        return None, None, grad_w, None


def gather_rows(table: Tensor, idx: Tensor, weights: Tensor | None = None, *,
                channels: slice | None = None) -> Tensor:
    """``out[m] = sum_j weights[m, j] * table[idx[m, j], channels]``: table [N, C], idx [M, J]
    -> [M, C] (or [M, c] for the ``channels`` slice: the gradient rows then carry only those
    channels, a fraction of the backward's cost when few are read).

    Without weights, idx [M] -> table[idx] [M, C]. The table's gradient goes to its
    :class:`RowGradient` (see module doc), never to ``table.grad``.
    """
    if weights is None:
        idx = idx[:, None]
        weights = torch.ones(idx.shape, dtype=table.dtype, device=table.device)
    if not (torch.is_grad_enabled() and table.requires_grad):
        return _weighted_sum_of_rows(table, idx, weights, channels)
    return _WeightedRowGather.apply(table, idx, weights, channels)
