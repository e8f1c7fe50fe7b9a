"""The two S-NeRF distributions and their KL divergences (docs/definitions.md §4; paper appendix "Distributions"
and "The posterior-prior KL divergence").

    density   X = max(0, Y),  Y ~ N(loc, scale^2)      rectified normal, support {0} U (0, inf)
    radiance  R = sigmoid(Y), Y ~ N(loc, scale^2)      logistic normal,  support (0, 1)

Everything is batched and broadcasts like torch elementwise ops; results carry the inputs'
device and dtype and are differentiable in ``loc`` and ``scale``. Throughout, ``z = loc / scale``
is the standardised location, ``phi``/``Phi`` the standard normal pdf/cdf.

Conventions others must know:

* ``RectifiedNormal.log_prob`` is the density with respect to ``delta_0 + Lebesgue(0, inf)``:
  ``log Phi(-z)`` (the log point mass) at ``x == 0``, the Gaussian log-density at ``x > 0`` and
  ``-inf`` at ``x < 0``. This is the density whose log-ratio defines the KL, so Monte-Carlo KLs
  use it as is.
* Scales must be positive. The classes check this (``validate=True``); the ``kl_*`` functions
  do not (they run every training step); pass positive scales (``fields.base.positive_scale``).
* The KL functions reduce nothing: they return the broadcast batch shape of their arguments.
* Gradients are finite for loc in [-50, 50] and scale in [1e-4, 1e3] in float32 and float64
  (tested): ``log_ndtr`` here switches to an ``erfcx`` form in the far left tail (torch's own
  ``log_ndtr`` gradient is 0 at z = -5e5 instead of 5e5), truncated-normal moments use a
  continued fraction there, and point masses use ``exp(log_ndtr)`` so that ``0 * log 0`` terms
  are exact zeros with zero gradients.
* ``ndtr`` here is accurate in the left tail; ``torch.special.ndtr`` is not (see ``ndtr``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .constants import (LOGISTIC_QUADRATURE_SCALE_SWITCH, LOGISTIC_TAIL_CUTOFF, MILLS_CF_DEPTH,
                        MILLS_CF_SWITCH)

#: Gauss-Hermite nodes for logistic-normal moments at logit std <= 1 (see
#: ``LOGISTIC_QUADRATURE_SCALE_SWITCH``). With 64 nodes the rule is at float64 round-off for
#: std <= 1 (worst measured: 3e-15 relative, against mpmath).
LOGISTIC_NORMAL_HERMITE_NODES: int = 64

#: Gauss-Legendre nodes on [0, LOGISTIC_TAIL_CUTOFF] for logistic-normal moments at logit
#: std > 1 (worst measured absolute error 5e-15 in float64, against mpmath).
LOGISTIC_NORMAL_LEGENDRE_NODES: int = 64

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_LOG2 = math.log(2.0)

__all__ = [
    "LOGISTIC_NORMAL_HERMITE_NODES", "LOGISTIC_NORMAL_LEGENDRE_NODES", "LogisticNormal",
    "RectifiedNormal", "draw_standard_normal", "kl_logistic_normal", "kl_logistic_normal_mc",
    "kl_normal", "kl_rectified_normal", "kl_rectified_normal_mc", "log_ndtr", "ndtr",
    "normal_log_prob", "truncated_normal_stats",
]


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------

def _as_tensors(*values: Tensor | float) -> tuple[Tensor, ...]:
    """Convert Python numbers to tensors on the device/dtype of the first tensor argument."""
    ref = next((v for v in values if isinstance(v, Tensor)), None)
    device = ref.device if ref is not None else None
    dtype = ref.dtype if ref is not None and ref.is_floating_point() else torch.get_default_dtype()
    return tuple(v if isinstance(v, Tensor) and v.is_floating_point()
                 else torch.as_tensor(v, device=device, dtype=dtype) for v in values)


def _check_scale(name: str, scale: Tensor) -> None:
    """Raise ValueError naming the offending value if any scale is not finite and positive."""
    bad = ~(torch.isfinite(scale) & (scale > 0))
    if bool(bad.any()):
        raise ValueError(f"{name} must be finite and > 0; got {scale[bad].flatten()[0].item()!r} "
                         f"({int(bad.sum())} bad of {scale.numel()})")


def draw_standard_normal(shape: Sequence[int], generator: torch.Generator | None = None,
                         device: torch.device | str | None = None,
                         dtype: torch.dtype | None = None) -> Tensor:
    """``eps ~ N(0, 1)`` of the given shape (the noise of the reparameterisation trick)."""
    return torch.randn(tuple(shape), generator=generator, device=device, dtype=dtype)


def normal_log_prob(y: Tensor, loc: Tensor, scale: Tensor) -> Tensor:
    """``log N(y; loc, scale^2) = -((y - loc) / scale)^2 / 2 - log(scale) - log(sqrt(2 pi))``."""
    u = (y - loc) / scale
    return -0.5 * u * u - torch.log(scale) - _LOG_SQRT_2PI


def ndtr(x: Tensor) -> Tensor:
    """Standard normal cdf ``Phi(x) = erfc(-x/sqrt2) / 2``, accurate to round-off in the left tail.

    ``torch.special.ndtr`` is not (relative error 6e-6 at x = -6.9 and 0 below x ~ -8.3 in
    float64, where the true value is still ~1e-17).
    """
    return 0.5 * torch.special.erfc(-x / math.sqrt(2.0))


def _log_phi(z: Tensor) -> Tensor:
    """log of the standard normal pdf."""
    return -0.5 * z * z - _LOG_SQRT_2PI


def _laplace_tails(a: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """First three tails ``t1, t2, t3`` of Laplace's continued fraction, for ``a >= MILLS_CF_SWITCH``.

        t_j = j / (a + t_{j+1}),   j = D, ..., 1,   D = MILLS_CF_DEPTH,

    started from the fixed point of ``t = (D + 1) / (a + t)`` (the fraction's asymptotic tail),
    so that ``Phi(-a) / phi(a) = 1 / (a + t1)``. For ``Y ~ N(-a, 1)`` given ``Y > 0``:
    ``E[Y | Y > 0] = t1`` and ``Var[Y | Y > 0] = t1 * (t2 - t1)``; neither subtracts nearly
    equal numbers, unlike ``z + phi/Phi`` at very negative ``z``.
    """
    t = 0.5 * (torch.sqrt(a * a + 4.0 * (MILLS_CF_DEPTH + 1)) - a)
    t3 = t
    for j in range(MILLS_CF_DEPTH, 1, -1):
        t3, t = t, j / (a + t)
    return 1.0 / (a + t), t, t3


class _GaussianTailMoments(torch.autograd.Function):
    """``(lam, kappa, var)`` of ``Y ~ N(-a, 1)`` given ``Y > 0`` for ``a >= MILLS_CF_SWITCH``, with
    a closed-form backward (``truncated_normal_stats``' far-tail branch).

    Forward: ``kappa = t1``, ``var = t1 (t2 - t1)``, ``lam = a + t1`` from Laplace's continued
    fraction, evaluated without building an autograd graph (its 40-term loop would otherwise add
    some 160 tensor operations to every backward pass). Backward, with ``mu = -a`` and the
    truncated normal's identities ``d kappa/d mu = var``, ``d lam/d mu = -lam kappa``,
    ``d var/d mu = lam (kappa^2 - var)``, written in the fraction's tails so that nothing cancels
    (``2 t1 - t2 = t1 t2 (t3 - t2)``, from ``t1 = 1/(a + t2)`` and ``t2 = 2/(a + t3)``):

        d lam/da   = 1 - var
        d kappa/da = -var
        d var/da   = -lam t1^2 t2 (t3 - t2)

    Differentiable once (the KLs need first derivatives only)."""

    @staticmethod
    def forward(ctx, a: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        t1, t2, t3 = _laplace_tails(a)
        lam, var = a + t1, t1 * (t2 - t1)
        ctx.save_for_backward(t1, t2, t3, lam, var)
        return lam, t1, var

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_lam: Tensor, g_kappa: Tensor, g_var: Tensor) -> Tensor:
        t1, t2, t3, lam, var = ctx.saved_tensors
        return g_lam * (1.0 - var) - g_kappa * var - g_var * (lam * t1 * t1 * t2 * (t3 - t2))


def truncated_normal_stats(z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Moments of ``Y ~ N(z, 1)`` conditioned on ``Y > 0``, stable for every finite ``z``.

    Returns ``(lam, kappa, var)``, each shaped like ``z``:

        lam   = phi(z) / Phi(z)            inverse Mills ratio (= d/dz log Phi(z))
        kappa = E[Y | Y > 0]  = z + lam
        var   = Var[Y | Y > 0] = 1 - lam * kappa

    For ``z >= -MILLS_CF_SWITCH`` these formulas are used directly, with
    ``lam = sqrt(2/pi) / erfcx(-z/sqrt2)`` for ``z < 0`` (accurate to round-off); below, Laplace's
    continued fraction gives ``kappa`` and ``var`` without cancellation (``kappa ~ 1/|z|``,
    ``var ~ 1/z^2`` as ``z -> -inf``). Relative accuracy (vs mpmath): float64 ~1e-14,
    float32 ~4e-5 (worst: var near z = -3).
    """
    use_cf = z < -MILLS_CF_SWITCH
    z_d = z.clamp_min(-MILLS_CF_SWITCH)
    lam_neg = math.sqrt(2.0 / math.pi) / torch.special.erfcx((-z_d).clamp_min(0.0) / math.sqrt(2.0))
    z_pos = z_d.clamp_min(0.0)
    lam_pos = torch.exp(_log_phi(z_pos) - torch.special.log_ndtr(z_pos))
    lam_d = torch.where(z_d < 0, lam_neg, lam_pos)
    kappa_d = z_d + lam_d
    var_d = 1.0 - lam_d * kappa_d
    lam_cf, kappa_cf, var_cf = _GaussianTailMoments.apply((-z).clamp_min(MILLS_CF_SWITCH))
    lam = torch.where(use_cf, lam_cf, lam_d)
    kappa = torch.where(use_cf, kappa_cf, kappa_d)
    var = torch.where(use_cf, var_cf, var_d)
    return lam, kappa, var


def log_ndtr(x: Tensor) -> Tensor:
    """``log Phi(x)`` with a gradient (``phi(x)/Phi(x)``) that stays accurate in the far left tail.

    ``torch.special.log_ndtr`` returns the right value but its gradient collapses to 0 (or
    inf) once ``x^2/2`` exceeds the float's resolution (float32: x ~ -1e3). Below
    ``-MILLS_CF_SWITCH`` this evaluates ``log Phi(x) = log(erfcx(-x/sqrt2) / 2) - x^2/2``, whose
    autograd derivative ``-x + (x + sqrt(2/pi)/erfcx(-x/sqrt2))`` is accurate to a few eps
    relative (the rounding of the cancelling ``x`` terms is ~eps*|x| against a result ~|x|).
    """
    use_tail = x < -MILLS_CF_SWITCH
    x_t = x.clamp_max(-MILLS_CF_SWITCH)
    tail = torch.log(torch.special.erfcx(-x_t / math.sqrt(2.0))) - _LOG2 - 0.5 * x_t * x_t
    return torch.where(use_tail, tail, torch.special.log_ndtr(x.clamp_min(-MILLS_CF_SWITCH)))


def _log_abs_sinh(v: Tensor) -> Tensor:
    """``log|sinh(v)|`` for ``v != 0``, without overflow: ``|v| + log(1 - exp(-2|v|)) - log 2``."""
    av = v.abs()
    return av + torch.log(-torch.expm1(-2.0 * av)) - _LOG2


def _log_cosh(u: Tensor) -> Tensor:
    """``log cosh(u) = |u| + log(1 + exp(-2|u|)) - log 2`` without overflow."""
    au = u.abs()
    return au + F.softplus(-2.0 * au) - _LOG2


@lru_cache(maxsize=None)
def _quadrature_numpy(kind: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    if kind == "hermite":  # nodes/weights for E over N(0, 1/2) scaled to E_{x~N(0,1)} f(sqrt2 x)
        x, w = np.polynomial.hermite.hermgauss(n)
        return x * math.sqrt(2.0), w / math.sqrt(math.pi)
    x, w = np.polynomial.legendre.leggauss(n)  # mapped to [0, LOGISTIC_TAIL_CUTOFF]
    half = 0.5 * LOGISTIC_TAIL_CUTOFF
    return half * (x + 1.0), half * w


def _quadrature(kind: str, n: int, like: Tensor) -> tuple[Tensor, Tensor]:
    x, w = _quadrature_numpy(kind, n)
    return (torch.as_tensor(x, device=like.device, dtype=like.dtype),
            torch.as_tensor(w, device=like.device, dtype=like.dtype))


# ----------------------------------------------------------------------------------------------
# Rectified normal
# ----------------------------------------------------------------------------------------------

class RectifiedNormal:
    """``X = max(0, Y)``, ``Y ~ N(loc, scale^2)``: the density distribution (paper Eq. den_sampling).

    Shapes: ``loc``, ``scale`` broadcast to the batch shape ``[*B]``; draws are
    ``[*S, *B]``. ``P(X = 0) = Phi(-z)``; on ``x > 0`` X has the Gaussian density.
    """

    def __init__(self, loc: Tensor | float, scale: Tensor | float, validate: bool = True):
        loc, scale = torch.broadcast_tensors(*_as_tensors(loc, scale))
        if validate:
            _check_scale("RectifiedNormal scale", scale)
        self.loc, self.scale = loc, scale

    @property
    def batch_shape(self) -> torch.Size:
        return self.loc.shape

    def rsample(self, eps: Tensor) -> Tensor:
        """Reparameterised draw ``relu(loc + scale * eps)``; ``eps`` [*S, *B] from the caller."""
        return torch.relu(self.loc + self.scale * eps)

    def sample(self, sample_shape: Sequence[int] = (), generator: torch.Generator | None = None) -> Tensor:
        """[*sample_shape, *B] draws, detached from the parameters."""
        with torch.no_grad():
            eps = draw_standard_normal((*sample_shape, *self.batch_shape), generator,
                                       self.loc.device, self.loc.dtype)
            return self.rsample(eps)

    def prob_zero(self) -> Tensor:
        """[*B] point mass ``P(X = 0) = Phi(-loc/scale)``."""
        return ndtr(-self.loc / self.scale)

    def log_prob_zero(self) -> Tensor:
        """[*B] ``log P(X = 0) = log Phi(-loc/scale)`` (stable ``log_ndtr``)."""
        return log_ndtr(-self.loc / self.scale)

    def log_prob(self, x: Tensor) -> Tensor:
        """Log density w.r.t. ``delta_0 + Lebesgue(0, inf)`` (mixed convention, see module doc).

            log p(x) = log Phi(-z)                   if x == 0   (log point mass)
                     = log N(x; loc, scale^2)        if x > 0
                     = -inf                          if x < 0

        Shapes: x [*S, *B] -> [*S, *B].
        """
        gauss = normal_log_prob(x, self.loc, self.scale)
        at_zero = torch.where(x == 0, self.log_prob_zero(), torch.full_like(gauss, -math.inf))
        return torch.where(x > 0, gauss, at_zero)

    def cdf(self, x: Tensor) -> Tensor:
        """``P(X <= x)``: 0 for ``x < 0``, ``Phi((x - loc)/scale)`` for ``x >= 0`` (jump at 0)."""
        c = ndtr((x - self.loc) / self.scale)
        return torch.where(x < 0, torch.zeros_like(c), c)

    @property
    def mean(self) -> Tensor:
        """[*B] ``E[X] = loc Phi(z) + scale phi(z) = scale * Phi(z) * kappa(z)``.

        Computed as ``exp(log scale + log Phi(z) + log kappa)`` with ``kappa = E[Y/scale | Y > 0]``
        from ``truncated_normal_stats`` (no cancellation at very negative z).
        """
        z = self.loc / self.scale
        _, kappa, _ = truncated_normal_stats(z)
        return torch.exp(torch.log(self.scale) + log_ndtr(z) + torch.log(kappa))

    @property
    def variance(self) -> Tensor:
        """[*B] ``Var[X]``. By the law of total variance over {X = 0} and {X > 0}:

            Var[X] / scale^2 = Phi(z) * (v_t + Phi(-z) * kappa^2)

        with ``kappa``, ``v_t`` the mean and variance of ``Y/scale`` given ``Y > 0``. Every term
        is positive (equals ``(z^2+1)Phi(z) + z phi(z) - (z Phi(z) + phi(z))^2`` without its
        catastrophic cancellation at large |z|).
        """
        z = self.loc / self.scale
        _, kappa, var_t = truncated_normal_stats(z)
        inner = var_t + ndtr(-z) * kappa * kappa
        return torch.exp(2.0 * torch.log(self.scale) + log_ndtr(z) + torch.log(inner))

    @property
    def stddev(self) -> Tensor:
        return self.variance.sqrt()


# ----------------------------------------------------------------------------------------------
# Logistic normal
# ----------------------------------------------------------------------------------------------

def _logistic_normal_moments(loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
    """``E[sigmoid(Y)]`` and ``Var[sigmoid(Y)]`` for ``Y ~ N(loc, scale^2)`` (no closed form).

    scale <= LOGISTIC_QUADRATURE_SCALE_SWITCH: Gauss-Hermite with
    ``LOGISTIC_NORMAL_HERMITE_NODES`` nodes on the centred differences
    ``d_i = sigmoid(y_i) - sigmoid(loc) = sinh((y_i - loc)/2) / (2 cosh(y_i/2) cosh(loc/2))``
    (evaluated in log space), ``mean = sigmoid(loc) + E d``, ``var = E d^2 - (E d)^2``: keeps
    relative accuracy for tiny scales (var ~ sigmoid'(loc)^2 scale^2) and for |loc| ~ 50.

    scale > switch: with loc folded to ``m = -|loc| <= 0`` (mean -> 1 - mean, var unchanged),
    ``E[sigmoid(Y)] = Phi(m/s) + int_0^L u(t) [N(-t) - N(t)] dt`` and
    ``E[sigmoid(Y)^2] = Phi(m/s) + int_0^L [u^2 N(-t) - u (2 - u) N(t)] dt`` where
    ``u(t) = sigmoid(-t)``, ``N(t) = N(t; m, s^2)``, ``L = LOGISTIC_TAIL_CUTOFF``: the unit step is
    exact and the smooth, localised remainder is integrated by Gauss-Legendre.

    Accuracy (float64, against mpmath quadrature and the lognormal limit at loc = -50):
    absolute error <= 1e-14 for loc in [-50, 50] and scale in [1e-4, 1e3]; relative error
    <= 1e-12 where scale <= 1, even for values ~1e-52. Where scale > 1, values below ~1e-17
    (e.g. the mean at loc = -50, scale = 3) are only accurate in absolute terms.
    """
    small = scale <= LOGISTIC_QUADRATURE_SCALE_SWITCH

    # Gauss-Hermite branch (scale clamped so the unused branch stays finite).
    xh, wh = _quadrature("hermite", LOGISTIC_NORMAL_HERMITE_NODES, loc)  # [G]
    s_g = scale.clamp_max(LOGISTIC_QUADRATURE_SCALE_SWITCH)
    h = s_g[..., None] * xh  # [*B, G], y_i - loc
    y = loc[..., None] + h
    log_d = _log_abs_sinh(0.5 * h) - _log_cosh(0.5 * y) - _log_cosh(0.5 * loc)[..., None] - _LOG2
    d = torch.sign(xh) * torch.exp(log_d)
    e_d = (d * wh).sum(-1)
    e_d2 = (torch.exp(2.0 * log_d) * wh).sum(-1)
    mean_g = torch.sigmoid(loc) + e_d
    var_g = e_d2 - e_d * e_d

    # Step + Gauss-Legendre branch.
    t, wt = _quadrature("legendre", LOGISTIC_NORMAL_LEGENDRE_NODES, loc)  # [G2]
    s_b = scale.clamp_min(LOGISTIC_QUADRATURE_SCALE_SWITCH)[..., None]
    positive = loc > 0
    m = torch.where(positive, -loc, loc)[..., None]
    u = torch.sigmoid(-t)
    n_minus = torch.exp(normal_log_prob(-t, m, s_b))
    n_plus = torch.exp(normal_log_prob(t, m, s_b))
    step = ndtr(m[..., 0] / s_b[..., 0])
    e1 = step + (wt * u * (n_minus - n_plus)).sum(-1)
    e2 = step + (wt * (u * u * n_minus - u * (2.0 - u) * n_plus)).sum(-1)
    mean_b = torch.where(positive, 1.0 - e1, e1)
    var_b = e2 - e1 * e1

    return torch.where(small, mean_g, mean_b), torch.where(small, var_g, var_b)


class LogisticNormal:
    """``R = sigmoid(Y)``, ``Y ~ N(loc, scale^2)``: the radiance distribution per channel
    (paper Eq. rad_sampling / radiance_pdf).

    Shapes: ``loc``, ``scale`` broadcast to ``[*B]`` (for colours ``[*B, 3]``); draws ``[*S, *B]``.
    """

    def __init__(self, loc: Tensor | float, scale: Tensor | float, validate: bool = True):
        loc, scale = torch.broadcast_tensors(*_as_tensors(loc, scale))
        if validate:
            _check_scale("LogisticNormal scale", scale)
        self.loc, self.scale = loc, scale

    @property
    def batch_shape(self) -> torch.Size:
        return self.loc.shape

    def rsample(self, eps: Tensor) -> Tensor:
        """Reparameterised draw ``sigmoid(loc + scale * eps)``; ``eps`` [*S, *B]."""
        return torch.sigmoid(self.loc + self.scale * eps)

    def sample(self, sample_shape: Sequence[int] = (), generator: torch.Generator | None = None) -> Tensor:
        """[*sample_shape, *B] draws, detached from the parameters."""
        with torch.no_grad():
            eps = draw_standard_normal((*sample_shape, *self.batch_shape), generator,
                                       self.loc.device, self.loc.dtype)
            return self.rsample(eps)

    def log_prob(self, r: Tensor) -> Tensor:
        """Paper Eq. radiance_pdf, in log space; ``-inf`` outside (0, 1). Shapes: [*S, *B].

            log f(r) = log N(logit r; loc, scale^2) - log r - log(1 - r)

        with ``log r = logsigmoid(logit r)`` and ``log(1 - r) = log1p(-r)`` taken directly.
        """
        inside = (r > 0) & (r < 1)
        r_safe = torch.where(inside, r, torch.full_like(r, 0.5))
        log_r = torch.log(r_safe)
        log_1mr = torch.log1p(-r_safe)
        lp = normal_log_prob(log_r - log_1mr, self.loc, self.scale) - log_r - log_1mr
        return torch.where(inside, lp, torch.full_like(lp, -math.inf))

    def log_prob_logit(self, y: Tensor) -> Tensor:
        """``log f(sigmoid(y))`` from the logit ``y`` (finite even where sigmoid(y) rounds to 0 or 1):

            log N(y; loc, scale^2) - logsigmoid(y) - logsigmoid(-y)
        """
        return normal_log_prob(y, self.loc, self.scale) - F.logsigmoid(y) - F.logsigmoid(-y)

    def cdf(self, r: Tensor) -> Tensor:
        """``P(R <= r) = Phi((logit r - loc) / scale)``; 0 for r <= 0, 1 for r >= 1."""
        inside = (r > 0) & (r < 1)
        r_safe = torch.where(inside, r, torch.full_like(r, 0.5))
        c = ndtr((torch.log(r_safe) - torch.log1p(-r_safe) - self.loc) / self.scale)
        return torch.where(inside, c, (r >= 1).to(c.dtype))

    @property
    def mean(self) -> Tensor:
        """[*B] ``E[R]`` by quadrature (see ``_logistic_normal_moments`` for rules and accuracy)."""
        return _logistic_normal_moments(self.loc, self.scale)[0]

    @property
    def variance(self) -> Tensor:
        """[*B] ``Var[R]`` by quadrature (see ``_logistic_normal_moments``)."""
        return _logistic_normal_moments(self.loc, self.scale)[1]

    @property
    def stddev(self) -> Tensor:
        return self.variance.sqrt()


# ----------------------------------------------------------------------------------------------
# KL divergences (closed form)
# ----------------------------------------------------------------------------------------------

def kl_normal(loc_q: Tensor, scale_q: Tensor, loc_p: Tensor | float, scale_p: Tensor | float) -> Tensor:
    """``KL(N(mq, sq^2) || N(mp, sp^2))``, broadcast over the batch, nothing summed:

        log(sp/sq) + (sq^2 + (mq - mp)^2) / (2 sp^2) - 1/2 = (expm1(w) - w)/2 + delta^2/2

    with ``w = 2 log(sq/sp)`` and ``delta = (mq - mp)/sp`` (no cancellation as sq -> sp).
    """
    loc_q, scale_q, loc_p, scale_p = _as_tensors(loc_q, scale_q, loc_p, scale_p)
    w = 2.0 * (torch.log(scale_q) - torch.log(scale_p))
    delta = (loc_q - loc_p) / scale_p
    return 0.5 * (torch.expm1(w) - w) + 0.5 * delta * delta


def kl_logistic_normal(loc_q: Tensor, scale_q: Tensor, loc_p: Tensor | float,
                       scale_p: Tensor | float) -> Tensor:
    """KL between logistic normals = ``kl_normal`` of the logits.

    KL is invariant under the bijection ``sigmoid``: the Jacobian ``r(1-r)`` appears in both
    densities and cancels in the log-ratio.
    """
    return kl_normal(loc_q, scale_q, loc_p, scale_p)


def kl_rectified_normal(loc_q: Tensor, scale_q: Tensor, loc_p: Tensor | float,
                        scale_p: Tensor | float) -> Tensor:
    """Closed-form ``KL(RN(mq, sq) || RN(mp, sp))``, broadcast over the batch, nothing summed.

    Both distributions live on ``{0} U (0, inf)`` so the KL is finite for any positive scales:

        KL = Q_q (log Q_q - log Q_p)  +  P_q * C                           (paper appendix)
        Q = Phi(-z) (point mass at 0),  P_q = Phi(z_q),  z = loc/scale
        C = E[log N(X; q) - log N(X; p) | X > 0], X ~ N(mq, sq^2)
          = -w/2 + (E[(rho u + delta)^2] - E[u^2]) / 2

    where ``u = (X - mq)/sq`` given ``u > -z_q`` has ``E[u] = lam``, ``E[u^2] = 1 - z_q lam``
    (``lam``, ``kappa``, ``v_t`` from ``truncated_normal_stats(z_q)``), ``rho = sq/sp``,
    ``w = 2 log rho``, ``delta = (mq - mp)/sp``. Two algebraically equal forms of the bracket,

        A: expm1(w) E[u^2] + 2 rho delta lam + delta^2            (exactly 0 when q == p)
        B: rho^2 v_t + (rho kappa - z_p)^2 - E[u^2]               (no cancellation when the
                                                                  truncated mean sits far from mp)

    are both computed and, per element, the one with the smaller rounding bound is used. Masses
    are ``exp(log_ndtr)`` so ``Q_q -> 0`` gives ``0 * log 0 = 0`` with zero (finite) gradients.
    """
    loc_q, scale_q, loc_p, scale_p = _as_tensors(loc_q, scale_q, loc_p, scale_p)
    z_q = loc_q / scale_q
    z_p = loc_p / scale_p

    log_q0 = log_ndtr(-z_q)
    log_p0 = log_ndtr(-z_p)
    point = torch.exp(log_q0) * (log_q0 - log_p0)

    lam, kappa, var_t = truncated_normal_stats(z_q)
    m2 = 1.0 - z_q * lam  # E[u^2 | u > -z_q] >= 0, no cancellation (z lam < 0 for z < 0)
    w = 2.0 * (torch.log(scale_q) - torch.log(scale_p))
    rho = scale_q / scale_p
    delta = (loc_q - loc_p) / scale_p
    em1 = torch.expm1(w)  # rho^2 - 1
    cross = 2.0 * rho * delta * lam
    form_a = em1 * m2 + cross + delta * delta
    shift = rho * kappa - z_p  # (E[X | X > 0] - mp) / sp
    spread = rho * rho * var_t
    form_b = spread + shift * shift - m2
    with torch.no_grad():
        err_a = (em1 * m2).abs() + cross.abs() + delta * delta
        err_b = spread + shift * shift + m2
    bracket = torch.where(err_a <= err_b, form_a, form_b)
    continuous = torch.exp(log_ndtr(z_q)) * (0.5 * (bracket - w))
    return point + continuous


# ----------------------------------------------------------------------------------------------
# KL divergences (Monte-Carlo, the paper's estimator)
# ----------------------------------------------------------------------------------------------

def _mc_noise(params: tuple[Tensor, ...], num_samples: int, generator: torch.Generator | None,
              eps: Tensor | None) -> Tensor:
    if eps is not None:
        return eps
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    batch = torch.broadcast_shapes(*(p.shape for p in params))
    return draw_standard_normal((num_samples, *batch), generator, params[0].device, params[0].dtype)


def kl_rectified_normal_mc(loc_q: Tensor, scale_q: Tensor, loc_p: Tensor | float,
                           scale_p: Tensor | float, num_samples: int,
                           generator: torch.Generator | None = None,
                           eps: Tensor | None = None, boundary_gradient: bool = True) -> Tensor:
    """Monte-Carlo ``KL(q || p)`` for rectified normals (the paper's estimator), [*B]:

        1/K sum_k g(eps_k),   g(eps) = log q(x) - log p(x),   x = relu(mq + sq eps)

    with the mixed ``log_prob`` convention: a draw at exactly 0 contributes
    ``log Q_q - log Q_p``. ``eps`` [K, *B] overrides the draws.

    The value is unbiased. Its reparameterised gradient with respect to ``loc_q``/``scale_q`` is
    not: ``g`` jumps at ``eps0 = -mq/sq`` from the mass ratio ``g_0 = log Q_q - log Q_p`` to the
    density ratio ``g_+ = log N(0; q) - log N(0; p)``, and the jump moves with the parameters, so
    ``d/dtheta E[g] = E[dg/dtheta] + phi(eps0) (g_0 - g_+) d eps0/dtheta`` (Leibniz rule).
    ``boundary_gradient=True`` (default) adds that exact term (zero in value,
    ``eps0 * c - stopgrad(eps0 * c)``); ``False`` gives the plain reparameterised estimator
    (the paper's), whose q-gradients are biased by hundreds of standard errors at large K.
    Gradients with respect to the prior parameters are unbiased either way.
    """
    params = _as_tensors(loc_q, scale_q, loc_p, scale_p)
    loc_q, scale_q, loc_p, scale_p = params
    eps = _mc_noise(params, num_samples, generator, eps)  # [K, *B]
    q = RectifiedNormal(loc_q, scale_q, validate=False)
    p = RectifiedNormal(loc_p, scale_p, validate=False)
    x = q.rsample(eps)
    estimate = (q.log_prob(x) - p.log_prob(x)).mean(0)
    if boundary_gradient:
        eps0 = -loc_q / scale_q
        with torch.no_grad():
            zero = torch.zeros_like(eps0)
            jump = (q.log_prob_zero() - p.log_prob_zero()
                    - normal_log_prob(zero, loc_q, scale_q) + normal_log_prob(zero, loc_p, scale_p))
            coef = torch.exp(_log_phi(eps0)) * jump
        surrogate = eps0 * coef
        estimate = estimate + (surrogate - surrogate.detach())
    return estimate


def kl_logistic_normal_mc(loc_q: Tensor, scale_q: Tensor, loc_p: Tensor | float,
                          scale_p: Tensor | float, num_samples: int,
                          generator: torch.Generator | None = None,
                          eps: Tensor | None = None) -> Tensor:
    """Monte-Carlo ``KL(q || p)`` for logistic normals, [*B]:

        1/K sum_k [log q(r_k) - log p(r_k)],   r_k = sigmoid(y_k),  y_k = mq + sq eps_k.

    The log-densities are evaluated from the logit ``y_k``; their common Jacobian term
    ``-log r(1 - r)`` cancels exactly, leaving ``log N(y_k; q) - log N(y_k; p)`` (finite even
    where ``r_k`` rounds to 0 or 1). ``eps`` [K, *B] overrides the draws.
    """
    params = _as_tensors(loc_q, scale_q, loc_p, scale_p)
    loc_q, scale_q, loc_p, scale_p = params
    eps = _mc_noise(params, num_samples, generator, eps)
    y = loc_q + scale_q * eps
    return (normal_log_prob(y, loc_q, scale_q) - normal_log_prob(y, loc_p, scale_p)).mean(0)
