"""Compiled CPU loops for the grid tables' row gradients and their lazy Adam update (numba).

A training step reads a few hundred thousand rows of each grid level (8 trilinear corners per
sample) and updates the rows it read. torch runs each of the two row loops below as several
passes over the touched rows, each pass a random access into a table of millions of rows:

* **scatter** (the backward of ``row_gather.gather_rows``), for samples m, corners j, channels c:

      acc[idx[m, j], c0 + c] += w[m, j] g[m, c],     touched[idx[m, j]] = True

  torch forms the [M J, C] products (an einsum) and ``index_add_``s them (one pass each). The loop adds
  nothing for a sample whose gradient row g[m] is all 0 (it still marks its rows, so the same rows step
  and every value is the same as adding its zeros): late in a capture's training most samples are empty
  space in every draw (52-60% of a step's), and adding zeros into their rows was a random access into
  the table for each of their corners. The bitmap, a byte a row, is what is left of their cost;
* **Adam** (``optim.RowSparseAdam``'s lazy update), for every touched row r and channel c, with
  ``step_size = lr / (1 - b1^t)`` and ``bias2_c = 1 - b2_c^t`` of the table's step t (the second
  moment's decay b2_c may differ per channel: ``train.adam_beta2_colour`` on the colour channels):

      m_rc <- b1 m_rc + (1 - b1) acc_rc,   v_rc <- b2_c v_rc + (1 - b2_c) acc_rc^2
      x_rc <- x_rc - step_size m_rc / (sqrt(v_rc / bias2_c) + eps),   acc_r <- 0,   touched_r <- False

  torch gathers the rows of the gradient, both moments and the table, and copies three back.

Here each is one loop over the rows, in the order torch adds them (samples, then corners), in the
tables' own dtype (the scalars are cast to it). With more than one torch thread the rows are split
into as many contiguous blocks, one per thread (numba's ``prange``): every block reads all the
samples and adds only into its own rows, so each row sums the same terms in the same order and
the result is the serial loop's bit for bit. On two threads a capture's training step is then
1.35-1.42x faster for the deterministic NeRF and 1.25-1.27x for S-NeRF, whose step the loops are a
smaller part of (with the prefetch hints below; before them 1.31-1.34x and 1.04-1.06x:
``benchmarks/results/row_kernels_threads/`` and its history). Profiled on one thread (an S-NeRF step on the flower
capture), the two torch versions were 58% of the step; with the loops a training step on a capture
is 1.6-2.0x faster (S-NeRF and the deterministic NeRF, fern and flower, ``benchmarks/results/row_kernels/``).

Both loops are bound by memory: each touched row is a random access into a table of millions of rows
(tens of MB), and a loop that waits for one row before it asks for the next leaves the CPU idle. So each
loop asks for its rows a little ahead (LLVM's prefetch hint, ``_prefetch``): the scatter for the corner
rows of the sample ``PREFETCH_SAMPLES`` ahead, the Adam update for the next ``PREFETCH_ROWS`` touched
rows (of the table, both moments and the gradient). A hint changes no value, only when the cache line
arrives: the loops add and update in the same order as without it, bit for bit. A capture's training
step is 1.09x faster for S-NeRF and 1.13-1.21x for the deterministic NeRF than without the hints on one
thread, 1.08x and 1.16-1.21x on two (``benchmarks/results/row_kernels_prefetch/``, ``..._threads/``;
``benchmarks/row_kernels_speed.py --prefetch``). Where the hint cannot be compiled it is left out.

They are not bound by memory alone: replayed on a trained capture's real inputs, the scatter into the
coarsest level (816 rows, in the L1 cache) took as long as into the finest (2M rows). So each loop is
written for LLVM to vectorise its channel loop: the scatter copies the sample's gradient row into a local
buffer and adds it to each corner row through a view of its channels; the Adam update reads and writes
each row through views when it runs on one thread, takes the square root as LLVM's ``llvm.sqrt``
(``_sqrt``; numba's ``np.sqrt`` calls libm's, which no loop vectorises; both are IEEE's correctly rounded
root) and divides under numpy's error model (no Python ``ZeroDivisionError`` check per element, which
also stops vectorisation; the divisors here are never 0). Split over threads the Adam update keeps the
element-by-element loop: there it waits on memory, and the vectorised loop's checks that a row's views do
not overlap made it 1-2 ms slower a step (medians of 40 replays, two threads). Every value is the same
bit for bit: each channel's operations (``_adam_element``, one formula for both loops) and their order are
unchanged, and LLVM fuses no multiply-add without fast-math. Replayed on fern and flower's
ten-minute captures (``benchmarks/studies/row_kernels_replay.py``, medians of 40 replays,
``benchmarks/results/row_kernels_replay/``): on one thread the Adam update is 1.6x as fast as before
(47-55 -> 29-34 ms a step) and the scatter 1.3-1.6x (46-56 -> 35-36 ms), the scatter's gain nearly all the
skip of samples without gradient (50-57% of a step's; the vectorised loop adding their zeros takes 46-50 ms).
On two threads both stay within the machine's noise of before: the minima agree within 1 ms, and the
medians move by several ms from one replay to the next.

``available(*tensors)`` says when they apply: numba imported (a dependency; without it the torch
ops run), and every tensor on the CPU and contiguous. CUDA tensors always take the torch ops. The
two paths give the same values up to float rounding (tests/test_grid_backend.py).
"""

from __future__ import annotations

import contextlib
import os
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

try:  # a declared dependency; the torch ops stand in where it is missing
    import numba
except ImportError:  # pragma: no cover - exercised only on machines without numba
    numba = None

if numba is not None and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # The split loops' threads: OpenMP first (what torch's CPU ops use), then numba's own pool; TBB,
    # numba's first choice, last: an older TBB on the machine costs a warning at the first step.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

#: Table dtypes the loops are compiled for.
KERNEL_DTYPES: tuple[torch.dtype, ...] = (torch.float32, torch.float64)
#: Set by ``torch_ops_only``: every caller runs the torch ops.
_disabled: bool = False
#: Set by ``serial_loops``: the compiled loops run on one thread whatever torch's thread count.
_serial: bool = False
#: How many samples ahead the scatter asks for the rows of a sample's corners (module doc).
PREFETCH_SAMPLES: int = 8
#: How many touched rows ahead of the one it updates the Adam loop asks for (module doc).
PREFETCH_ROWS: int = 8
#: Set by ``without_prefetch``: the loops ask for no row ahead (to time the hints).
_no_prefetch: bool = False
#: Set by ``adding_zero_rows``: the scatter adds the products of samples whose gradient is all 0 too.
_add_zero_rows: bool = False

if numba is not None:
    from llvmlite import ir as _ir
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def _prefetch(typingctx, flat, index):
        """Ask for the cache line of ``flat[index]`` (a 1-d array, an integer index) ahead of its use:
        LLVM's ``llvm.prefetch`` (for a write, kept in every cache level). Changes no value; where the
        hint cannot be emitted nothing is."""
        def codegen(context, builder, signature, args):
            try:
                data = context.make_array(signature.args[0])(context, builder, args[0]).data
                i8p, i32 = _ir.IntType(8).as_pointer(), _ir.IntType(32)
                address = builder.bitcast(builder.gep(data, [args[1]]), i8p)
                fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p],
                                                      _ir.FunctionType(_ir.VoidType(), [i8p, i32, i32, i32]))
                builder.call(fn, [address, i32(1), i32(3), i32(1)])  # write, highest locality, data
            except Exception:  # pragma: no cover - an llvmlite without the intrinsic: no hint, same loops
                pass
            return context.get_dummy_value()

        if isinstance(flat, numba.types.Array) and flat.ndim == 1 and isinstance(index, numba.types.Integer):
            return numba.types.void(flat, index), codegen
        return None

    @_intrinsic
    def _sqrt(typingctx, value):
        """IEEE square root as LLVM's ``llvm.sqrt`` (correctly rounded, as libm's ``sqrt`` that numba's
        ``np.sqrt`` calls, so the same bits): unlike the call, the intrinsic lets LLVM vectorise a loop."""
        def codegen(context, builder, signature, args):
            fn = builder.module.declare_intrinsic("llvm.sqrt", [context.get_value_type(signature.args[0])])
            return builder.call(fn, [args[0]])

        if isinstance(value, numba.types.Float):
            return value(value), codegen
        return None

    @numba.njit(cache=True, nogil=True, inline="always")
    def _prefetch_row(flat, row, width, first, count):  # pragma: no cover - compiled
        # the first and last element of row ``row``'s ``count`` channels from ``first`` (a row of a
        # [N, width] table spans at most two cache lines at these widths: both are asked for)
        e = row * width + first
        _prefetch(flat, e)
        _prefetch(flat, e + count - 1)

    # Each loop is written once, over the rows [lo, hi): the serial kernels run it on every row (no
    # thread pool is started on one thread), the split kernels on one contiguous block per thread.
    @numba.njit(cache=True, nogil=True, inline="always")
    def _in_block(r, lo, span):  # pragma: no cover - compiled
        # lo <= r < lo + span, as one unsigned comparison
        return np.uint64(r - lo) < np.uint64(span)

    @numba.njit(cache=True, nogil=True, inline="always")
    def _scatter_rows_in(acc, touched, idx, w, g, c0, lo, hi, ahead, add_zero_rows):  # pragma: no cover - compiled; tested through the wrappers
        # every sample is read, only rows in [lo, hi) are added to, in the samples' then corners' order;
        # a sample whose gradient row is all 0 marks its rows and adds nothing (module doc: ``adds``, one
        # pass over g first; a NaN counts as carried); the rows of sample m + ahead are asked for while
        # sample m is added (ahead 0: none): the gradient rows of a sample that adds, the bitmap's entries
        # of one that only marks. An adding sample's gradient row is copied into ``carried`` and each
        # corner row is added to through a view of its channels: LLVM then vectorises the channel loop
        M, J = idx.shape
        C = g.shape[1]
        width = acc.shape[1]
        flat = acc.reshape(-1)
        span = hi - lo
        adds = np.empty(M, dtype=np.bool_)
        for m in range(M):
            adds[m] = add_zero_rows
            for c in range(C):
                adds[m] = adds[m] or g[m, c] != 0.0
        carried = np.empty(C, dtype=acc.dtype)
        for m in range(M):
            if ahead > 0 and m + ahead < M:
                for j in range(J):
                    q = idx[m + ahead, j]
                    if _in_block(q, lo, span):
                        if adds[m + ahead]:
                            _prefetch_row(flat, q, width, c0, C)
                        else:
                            _prefetch(touched, q)
            if adds[m]:
                for c in range(C):
                    carried[c] = g[m, c]
            for j in range(J):
                r = idx[m, j]
                if _in_block(r, lo, span):
                    touched[r] = True
                    if adds[m]:
                        wj = w[m, j]
                        row = acc[r, c0:c0 + C]
                        for c in range(C):
                            row[c] += wj * carried[c]

    @numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
    def _adam_element(g, m1, m2, x, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2, eps):  # pragma: no cover - compiled
        # one channel's update (module doc): the new (m1, m2, x)
        a = b1 * m1 + one_minus_b1 * g
        b = b2 * m2 + one_minus_b2 * g * g
        return a, b, x - step_size * (a / (_sqrt(b / bias2) + eps))

    @numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
    def _adam_rows_in(x, m1, m2, acc, touched, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2, eps,
                      lo, hi, ahead, vectorised):  # pragma: no cover - compiled; tested through the wrappers
        # the next ``ahead`` touched rows after r are asked for (in all four tables) while r is updated:
        # ``seek`` scans the bitmap ahead of r, ``pending`` counts the touched rows in (r, seek), asked for
        C = x.shape[1]
        fx, f1, f2, fa = x.reshape(-1), m1.reshape(-1), m2.reshape(-1), acc.reshape(-1)
        seek, pending = lo, 0
        for r in range(lo, hi):
            if seek <= r:
                seek, pending = r + 1, 0
            elif touched[r]:
                pending -= 1  # r was asked for: it leaves the window
            while pending < ahead and seek < hi:
                if touched[seek]:
                    _prefetch_row(fx, seek, C, 0, C)
                    _prefetch_row(f1, seek, C, 0, C)
                    _prefetch_row(f2, seek, C, 0, C)
                    _prefetch_row(fa, seek, C, 0, C)
                    pending += 1
                seek += 1
            if not touched[r]:
                continue
            touched[r] = False
            if vectorised:  # the row's views: a loop LLVM vectorises
                xr, m1r, m2r, gr = x[r], m1[r], m2[r], acc[r]
                for c in range(C):
                    m1r[c], m2r[c], xr[c] = _adam_element(gr[c], m1r[c], m2r[c], xr[c], step_size, b1, one_minus_b1,
                                                          b2[c], one_minus_b2[c], bias2[c], eps)
                for c in range(C):
                    gr[c] = 0.0
            else:  # element by element (module doc: the split loops)
                for c in range(C):
                    g = acc[r, c]
                    acc[r, c] = 0.0
                    m1[r, c], m2[r, c], x[r, c] = _adam_element(g, m1[r, c], m2[r, c], x[r, c], step_size, b1,
                                                                one_minus_b1, b2[c], one_minus_b2[c], bias2[c], eps)

    @numba.njit(cache=True, nogil=True)
    def _scatter_weighted(acc, touched, idx, w, g, c0, ahead, add_zero_rows):  # pragma: no cover - compiled; tested through the wrappers
        _scatter_rows_in(acc, touched, idx, w, g, c0, 0, acc.shape[0], ahead, add_zero_rows)

    @numba.njit(cache=True, nogil=True, error_model="numpy")
    def _adam_touched(x, m1, m2, acc, touched, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2,
                      eps, ahead):  # pragma: no cover - compiled; tested through the wrappers
        _adam_rows_in(x, m1, m2, acc, touched, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2, eps, 0, x.shape[0],
                      ahead, True)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _scatter_weighted_blocks(acc, touched, idx, w, g, c0, blocks, ahead, add_zero_rows):  # pragma: no cover - compiled
        N = acc.shape[0]
        for b in numba.prange(blocks):
            _scatter_rows_in(acc, touched, idx, w, g, c0, N * b // blocks, N * (b + 1) // blocks, ahead, add_zero_rows)

    @numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
    def _adam_touched_blocks(x, m1, m2, acc, touched, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2,
                             eps, blocks, ahead):  # pragma: no cover - compiled
        N = x.shape[0]
        for b in numba.prange(blocks):
            _adam_rows_in(x, m1, m2, acc, touched, step_size, b1, one_minus_b1, b2, one_minus_b2, bias2, eps,
                          N * b // blocks, N * (b + 1) // blocks, ahead, False)


def row_blocks() -> int:
    """How many threads share a row loop: torch's intra-op thread count (the rows split into that
    many contiguous blocks, one per thread), at most numba's; 1 inside ``serial_loops``."""
    if numba is None or _serial:
        return 1
    return max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))


@contextlib.contextmanager
def _switched_on(flag: str):
    """Within it the module's switch ``flag`` (``_serial``, ``_no_prefetch``, ``_add_zero_rows``,
    ``_disabled``) is True."""
    before = globals()[flag]
    globals()[flag] = True
    try:
        yield
    finally:
        globals()[flag] = before


def serial_loops():
    """Within it the compiled loops run on one thread (the loops before they were split over
    threads): to time the split (``benchmarks/row_kernels_speed.py --threads``)."""
    return _switched_on("_serial")


def without_prefetch():
    """Within it the compiled loops ask for no row ahead (the same values): to time the hints
    (``benchmarks/row_kernels_speed.py --prefetch``)."""
    return _switched_on("_no_prefetch")


def adding_zero_rows():
    """Within it the compiled scatter adds the (zero) products of samples whose gradient row is all 0
    as well, as it did before it skipped them (the same values): to time the skip
    (``benchmarks/studies/row_kernels_replay.py``)."""
    return _switched_on("_add_zero_rows")


def available(*tensors: Tensor, contiguous: bool = True) -> bool:
    """Whether the compiled loops can run on ``tensors``: numba imported, not inside
    ``torch_ops_only``, all on the CPU, contiguous (unless ``contiguous`` is False: a caller that copies
    strided inputs), and the float ones of one dtype of ``KERNEL_DTYPES``."""
    if numba is None or _disabled:
        return False
    floats = {t.dtype for t in tensors if t.is_floating_point()}
    return (all(t.device.type == "cpu" and (t.is_contiguous() or not contiguous) for t in tensors)
            and len(floats) == 1 and floats <= set(KERNEL_DTYPES))


def torch_ops_only():
    """Within it every row loop runs as torch ops (what CUDA tensors and a machine without numba
    get): to compare the two paths (tests, ``benchmarks/row_kernels_speed.py``)."""
    return _switched_on("_disabled")


def scatter_weighted_rows(acc: Tensor, touched: Tensor, idx: Tensor, weights: Tensor, grad: Tensor,
                          first_channel: int = 0) -> None:
    """In place: ``acc[idx[m, j], first_channel + c] += weights[m, j] grad[m, c]`` and
    ``touched[idx[m, j]] = True`` (module doc). acc [N, C], touched [N] bool, idx [M, J] int64,
    weights [M, J], grad [M, c] with ``first_channel + c <= C``; float tensors of acc's dtype."""
    if not (idx.shape == weights.shape and grad.shape[0] == idx.shape[0]
            and first_channel + grad.shape[1] <= acc.shape[1] and touched.shape == acc.shape[:1]):
        raise ValueError(f"scatter_weighted_rows: acc {tuple(acc.shape)}, touched {tuple(touched.shape)}, idx "
                         f"{tuple(idx.shape)}, weights {tuple(weights.shape)}, grad {tuple(grad.shape)} at channel "
                         f"{first_channel} do not fit")
    blocks = row_blocks()
    ahead = 0 if _no_prefetch else PREFETCH_SAMPLES
    if blocks > 1:
        _scatter_weighted_blocks(acc.numpy(), touched.numpy(), idx.numpy(), weights.numpy(), grad.numpy(),
                                 int(first_channel), blocks, ahead, _add_zero_rows)
    else:
        _scatter_weighted(acc.numpy(), touched.numpy(), idx.numpy(), weights.numpy(), grad.numpy(), int(first_channel),
                          ahead, _add_zero_rows)


def adam_touched_rows(table: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor, acc: Tensor, touched: Tensor, *,
                      lr: float, betas: tuple[float, float | Sequence[float]], eps: float, step: int) -> None:
    """The lazy Adam update (module doc) of every row of ``table`` [N, C] marked in ``touched`` [N],
    with the summed gradient ``acc`` [N, C], the moments ``exp_avg``, ``exp_avg_sq`` [N, C] and the
    table's step count ``step`` (>= 1, this update included); zeroes ``acc`` and ``touched`` there.
    ``betas[1]`` is one second-moment decay or C of them, one per channel."""
    b1, b2 = betas
    x = table.numpy()
    channels = x.shape[1]
    b2 = np.broadcast_to(np.asarray(b2, dtype=np.float64), (channels,))  # [C]
    cast = x.dtype.type  # the scalars in the table's dtype, as torch's ops compute
    scalars = (cast(lr / (1.0 - b1 ** step)), cast(b1), cast(1.0 - b1), b2.astype(x.dtype), (1.0 - b2).astype(x.dtype),
               (1.0 - b2 ** step).astype(x.dtype), cast(eps))
    blocks, ahead = row_blocks(), 0 if _no_prefetch else PREFETCH_ROWS
    if blocks > 1:
        _adam_touched_blocks(x, exp_avg.numpy(), exp_avg_sq.numpy(), acc.numpy(), touched.numpy(), *scalars, blocks, ahead)
    else:
        _adam_touched(x, exp_avg.numpy(), exp_avg_sq.numpy(), acc.numpy(), touched.numpy(), *scalars, ahead)
