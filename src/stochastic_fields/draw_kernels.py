"""Compiled CPU loops for the draws of a render's colour plan (numba).

Before its field decodes any colour, a render draws its K trajectories' densities over the dense
samples [R, S] to find the samples some trajectory reaches (``renderer.colour_plan``), and then
composites the same draws (``ColourPlan.drawn``). For draw k of head h = k mod M, with
``c_hi = mu_a,i + o_h,i`` (``FieldParams.density_offsets``; M = 1: mu_a):

    a_ik = relu(c_hi + s_a,i eps_ik),   T_ik = exp(-sum_{j<i} a_jk delta_j)
    reached_i = some k with a_ik > 0 and T_ik >= tau

In torch that is about ten passes over [R, K, S] (a million elements a 2048-ray chunk at K = 8):
the heads' broadcast, the product and sum, the ReLU, the optical depths, the cumulative sum and its
shift, the exponential, two comparisons and the reduction over k. ``draw_reach`` makes the densities
and the exclusive sums of optical depth in one loop per ray and draw, adding in float64 as torch's
``cumsum`` does, takes torch's vectorised exponential of them, and finds the reached samples in a
second loop: the same densities, transmittances and reached samples bit for bit (tested), on a
flower chunk 4.6 -> 2.5 ms (two threads, the loops on one).

The loops run on one thread. Split over two (numba's ``prange``) they were as fast alone but slower
inside a render: numba's pool, woken between torch's operations, competes with torch's OpenMP
threads that are still spinning (a moment-summing loop so split made a flower render 7% slower,
the same loop serial 5% faster; that loop, 0.7 ms a chunk in use, was not kept). Written with
``exp`` inside the loop they were slower than torch (a scalar exponential per element against
torch's vectorised one), hence the split at the exponential.

``available(*tensors)``: no autograd (the plan's draws never need it, in training as in a render),
numba imported, not inside ``row_kernels.torch_ops_only()`` (which switches these loops off as
well as the row loops: the torch ops then run, as on CUDA and without numba), every tensor on the
CPU and of one float dtype of ``row_kernels.KERNEL_DTYPES``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import row_kernels

numba = row_kernels.numba

if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _draw_optical_depths(centre, scale, eps, deltas, density, optical):  # pragma: no cover - compiled
        # a_ik = relu(c_hi + s_i eps_ik) and the exclusive sum of a_jk delta_j, added in float64 as
        # torch's cumsum adds (then rounded to the arrays' dtype): T = exp(-optical) is torch's bit for bit
        R, M, S = centre.shape
        K = eps.shape[1]
        shared = eps.shape[2] == 1
        zero = deltas.dtype.type(0.0)
        for r in range(R):
            for k in range(K):
                h = k % M
                total = 0.0
                for i in range(S):
                    e = eps[r, k, 0] if shared else eps[r, k, i]
                    a = centre[r, h, i] + scale[r, i] * e
                    if a < zero:  # relu (a NaN stays NaN, as torch.relu keeps it)
                        a = zero
                    density[r, k, i] = a
                    optical[r, k, i] = total
                    total += a * deltas[r, i]

    @numba.njit(cache=True, nogil=True)
    def _reached(density, transmittance, min_transmittance, reached):  # pragma: no cover - compiled
        R, K, S = density.shape
        zero = density.dtype.type(0.0)
        tau = transmittance.dtype.type(min_transmittance)  # compared in the arrays' dtype, as torch compares
        for r in range(R):
            for i in range(S):
                reached[r, i] = False
            for k in range(K):
                for i in range(S):
                    if density[r, k, i] > zero and transmittance[r, k, i] >= tau:
                        reached[r, i] = True


def available(*tensors: Tensor) -> bool:
    """Whether the compiled loops can run on ``tensors`` (module doc): without autograd, and where the row
    loops can (``row_kernels.available``), a strided input being copied."""
    return not torch.is_grad_enabled() and row_kernels.available(*tensors, contiguous=False)


def draw_reach(centre: Tensor, scale: Tensor, eps: Tensor, deltas: Tensor, min_transmittance: float
               ) -> tuple[Tensor, Tensor, Tensor]:
    """(reached [R, S] bool, densities [R, K, S], transmittances [R, K, S]) of K draws (module doc):
    the same values as the torch ops bit for bit (tested). centre [R, M, S] the M heads' locs ``mu_a + o_h``
    (M = 1: mu_a), scale [R, S], eps [R, K, S'] (S' = S, or 1 for noise shared along the ray), deltas
    [R, S]; draw k reads head k mod M."""
    R, M, S = centre.shape
    K = eps.shape[1]
    if scale.shape != (R, S) or deltas.shape != (R, S) or eps.shape[0] != R or eps.shape[2] not in (1, S):
        raise ValueError(f"draw_reach: centre {tuple(centre.shape)}, scale {tuple(scale.shape)}, eps "
                         f"{tuple(eps.shape)}, deltas {tuple(deltas.shape)} do not fit")
    centre, scale, eps, deltas = (x.contiguous() for x in (centre, scale, eps, deltas))
    density = torch.empty(R, K, S, dtype=centre.dtype)
    optical = torch.empty_like(density)
    _draw_optical_depths(centre.numpy(), scale.numpy(), eps.numpy(), deltas.numpy(), density.numpy(), optical.numpy())
    transmittance = optical.neg_().exp_()
    reached = torch.empty(R, S, dtype=torch.bool)
    _reached(density.numpy(), transmittance.numpy(), float(min_transmittance), reached.numpy())
    return reached, density, transmittance
