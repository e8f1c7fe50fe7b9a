"""Tests for distributions: the rectified normal, the logistic normal and their KL divergences.

References are independent of the implementation: scipy.stats / scipy.special in float64,
scipy.integrate.quad of the defining integrals, torch.distributions' Gaussian KL, mpmath at
50+ digits for extreme parameters (mpmath ships with torch through sympy), large Monte-Carlo
samples with tolerances from their standard error, and gradcheck in float64.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy import integrate, special, stats

from stochastic_fields.distributions import (LogisticNormal, RectifiedNormal, draw_standard_normal,
                                             kl_logistic_normal, kl_logistic_normal_mc, kl_normal,
                                             kl_rectified_normal, kl_rectified_normal_mc, log_ndtr, ndtr,
                                             truncated_normal_stats)

try:  # mpmath ships with torch (torch -> sympy -> mpmath); only the 60-digit references need it.
    import mpmath as mp
except ImportError:  # pragma: no cover
    mp = None
needs_mpmath = pytest.mark.skipif(mp is None, reason="mpmath is not installed")

EXTREME_LOCS = [-50.0, -5.0, 0.0, 5.0, 50.0]
EXTREME_SCALES = [1e-4, 1e-2, 1.0, 10.0, 1e3]
DTYPES = [torch.float32, torch.float64]


def t64(values) -> torch.Tensor:
    return torch.as_tensor(np.asarray(values, dtype=np.float64))


def extreme_kl_grid(dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """All 625 (loc_q, scale_q, loc_p, scale_p) combinations of the extreme values, as leaves."""
    combos = np.array(list(itertools.product(EXTREME_LOCS, EXTREME_SCALES, EXTREME_LOCS, EXTREME_SCALES)))
    return tuple(torch.tensor(combos[:, i], dtype=dtype, requires_grad=True) for i in range(4))


# ----------------------------------------------------------------------------- references


def mp_rectified_moments(loc: float, scale: float) -> tuple[float, float]:
    """Raw-moment formulas at 60 digits: E X = s(z Phi + phi), E X^2 = s^2((z^2+1) Phi + z phi)."""
    with mp.workdps(60):
        s = mp.mpf(scale)
        z = mp.mpf(loc) / s
        big_phi, small_phi = mp.ncdf(z), mp.npdf(z)
        mean = s * (z * big_phi + small_phi)
        second = s * s * ((z * z + 1) * big_phi + z * small_phi)
        return float(mean), float(second - mean * mean)


def mp_rectified_kl(mq: float, sq: float, mp_: float, sp: float) -> float:
    """KL of rectified normals at 60 digits from the textbook expansion of the x > 0 integral:
    int_{u > -z} phi(u) [log(sp/sq) - u^2/2 + ((mq + sq u - mp)/sp)^2 / 2] du with
    int phi = Phi(z), int u phi = phi(z), int u^2 phi = Phi(z) - z phi(z); plus the point mass term.
    """
    with mp.workdps(60):
        mq, sq, mp_, sp = (mp.mpf(v) for v in (mq, sq, mp_, sp))
        zq, zp = mq / sq, mp_ / sp
        q0, p0 = mp.ncdf(-zq), mp.ncdf(-zp)
        point = q0 * (mp.log(q0) - mp.log(p0)) if q0 > 0 else mp.mpf(0)
        i0, i1 = mp.ncdf(zq), mp.npdf(zq)
        i2 = i0 - zq * i1
        d = mq - mp_
        cont = mp.log(sp / sq) * i0 - i2 / 2 + (d * d * i0 + 2 * d * sq * i1 + sq * sq * i2) / (2 * sp * sp)
        return float(point + cont)


def _breakpoints(lo: float, hi: float, centre: float, width: float, extra=()) -> list[float]:
    pts = [centre + k * width for k in (-10, -3, -1, 0, 1, 3, 10)] + list(extra)
    return sorted({p for p in pts if lo < p < hi})


def quad_rectified_kl(mq: float, sq: float, mp_: float, sp: float) -> float:
    """Point-mass term (scipy log_ndtr) + quad over x > 0 of N(x; q) log(N(x; q) / N(x; p))."""
    lq0, lp0 = special.log_ndtr(-mq / sq), special.log_ndtr(-mp_ / sp)
    point = math.exp(lq0) * (lq0 - lp0)

    def integrand(x: float) -> float:
        lq = stats.norm.logpdf(x, mq, sq)
        return math.exp(lq) * (lq - stats.norm.logpdf(x, mp_, sp))

    # Mass of q on x > 0 sits within 40 sq of max(mq, 0); near 0 it decays at rate |mq|/sq^2.
    hi = max(mq, 0.0) + 40.0 * sq
    decay = sq * sq / abs(mq) if mq < 0 else sq
    pts = _breakpoints(0.0, hi, max(mq, 0.0), sq, extra=[decay, 3 * decay, 10 * decay])
    cont, _ = integrate.quad(integrand, 0.0, hi, points=pts, limit=400, epsabs=1e-13, epsrel=1e-11)
    return point + cont


def quad_logistic_density_kl(mq: float, sq: float, mp_: float, sp: float) -> float:
    """int_0^1 f_q(r) log(f_q(r)/f_p(r)) dr with f from the change of variables r = sigmoid(y)
    (does not use the invariance of KL under the bijection). Split at r = 1/2 and written in
    terms of log r, log(1 - r) to resolve the endpoints."""

    def log_f(r: float, m: float, s: float) -> float:
        return stats.norm.logpdf(special.logit(r), m, s) - math.log(r) - math.log1p(-r)

    def integrand(r: float) -> float:
        lq = log_f(r, mq, sq)
        return math.exp(lq) * (lq - log_f(r, mp_, sp))

    # Put breakpoints where q's mass is (in r units) so quad does not miss a narrow peak.
    pts = sorted({float(special.expit(mq + k * sq)) for k in (-6, -3, -1, 0, 1, 3, 6)} - {0.0, 1.0})
    total = 0.0
    edges = [0.0] + pts + [1.0]
    for a, b in zip(edges[:-1], edges[1:]):
        if b > a:
            total += integrate.quad(integrand, a, b, limit=200, epsabs=1e-13, epsrel=1e-11)[0]
    return total


def quad_logistic_moments(loc: float, scale: float) -> tuple[float, float]:
    """E[sigmoid(Y)] and Var[sigmoid(Y)] by quad in float64 (plain expit, no centring), over the
    standardised variable u = (y - loc)/scale in [-40, 40], with breakpoints where y crosses the
    sigmoid's transition."""
    pts = sorted({k for k in (-10.0, -3.0, -1.0, 0.0, 1.0, 3.0, 10.0)}
                 | {(y - loc) / scale for y in (-40.0, -5.0, 0.0, 5.0, 40.0) if abs(y - loc) < 40 * scale})

    def expect(fn) -> float:
        return integrate.quad(lambda u: fn(loc + scale * u) * stats.norm.pdf(u), -40.0, 40.0,
                              points=pts, limit=400, epsabs=1e-15, epsrel=1e-13)[0]

    mean = expect(special.expit)
    var = expect(lambda y: (special.expit(y) - mean) ** 2)
    return mean, var


# ----------------------------------------------------------------------------- special functions


@pytest.mark.parametrize("dtype", DTYPES)
def test_log_ndtr_value_and_gradient_in_far_tail(dtype):
    x_np = np.array([-5e5, -3e4, -1e3, -100.0, -30.0, -10.0, -3.5, -3.0, -2.9, -1.0, 0.0, 2.0, 10.0, 40.0])
    x = torch.tensor(x_np, dtype=dtype, requires_grad=True)
    value = log_ndtr(x)
    (grad,) = torch.autograd.grad(value.sum(), x)
    ref_value = special.log_ndtr(x_np)
    # phi / Phi; for x < 0 via scipy's erfcx (the log-space ratio loses ~eps * x^2 / 2 there).
    ref_grad = np.where(x_np < 0, math.sqrt(2 / math.pi) / special.erfcx(-x_np / math.sqrt(2)),
                        np.exp(stats.norm.logpdf(x_np) - ref_value))
    rtol = 2e-6 if dtype == torch.float32 else 1e-13
    np.testing.assert_allclose(value.detach().double().numpy(), ref_value, rtol=rtol, atol=1e-30)
    np.testing.assert_allclose(grad.double().numpy(), ref_grad, rtol=rtol, atol=1e-30)


@pytest.mark.parametrize("dtype", DTYPES)
def test_ndtr_relative_accuracy_in_left_tail(dtype):
    x_np = np.array([-37.0, -12.0, -8.5, -6.9, -3.0, 0.0, 1.0, 9.0])
    got = ndtr(torch.tensor(x_np, dtype=dtype)).double().numpy()
    ref = special.ndtr(x_np)
    keep = ref > 1e3 * torch.finfo(dtype).tiny
    # Phi's condition number at x is ~x^2: rounding the argument alone costs eps * x^2.
    bound = 4 * torch.finfo(dtype).eps * (1 + x_np**2) * ref
    assert (np.abs(got - ref)[keep] <= bound[keep]).all(), (got, ref)


@needs_mpmath
@pytest.mark.parametrize("dtype", DTYPES)
def test_truncated_normal_stats_against_mpmath(dtype):
    zs = [-5e5, -1e3, -50.0, -10.0, -3.0001, -3.0, -2.9999, -1.0, 0.0, 0.5, 3.0, 10.0, 50.0, 5e5]
    lam, kappa, var = truncated_normal_stats(torch.tensor(zs, dtype=dtype))
    rtol = 1e-4 if dtype == torch.float32 else 1e-12
    for i, z in enumerate(zs):
        with mp.workdps(50):
            zm = mp.mpf(z)
            lam_ref = mp.npdf(zm) / mp.ncdf(zm)
            kappa_ref = zm + lam_ref
            var_ref = 1 - lam_ref * kappa_ref
        for got, ref in ((lam[i], lam_ref), (kappa[i], kappa_ref), (var[i], var_ref)):
            assert float(got) == pytest.approx(float(ref), rel=rtol, abs=1e-300), (z, float(got), float(ref))


@pytest.mark.parametrize("dtype", DTYPES)
def test_truncated_normal_tail_gradients_match_the_fraction_differentiated_step_by_step(dtype):
    """The far-tail branch's closed-form backward against autograd through every step of
    Laplace's continued fraction (the implementation it replaced), a in [3, 1e6]."""
    from stochastic_fields.distributions import _laplace_tails

    z = -torch.logspace(math.log10(3.0001), 6, 200, dtype=dtype)
    z_new, z_ref = z.clone().requires_grad_(True), z.clone().requires_grad_(True)
    new = truncated_normal_stats(z_new)
    a = -z_ref
    t1, t2, _ = _laplace_tails(a)  # differentiated by autograd through every step of the loop
    ref = (a + t1, t1, t1 * (t2 - t1))
    rtol = 2e-6 if dtype == torch.float32 else 1e-12
    for got, want in zip(new, ref):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
        g_new, = torch.autograd.grad(got.sum(), z_new, retain_graph=True)
        g_ref, = torch.autograd.grad(want.sum(), z_ref, retain_graph=True)
        torch.testing.assert_close(g_new, g_ref, rtol=rtol, atol=0)


def test_truncated_normal_stats_gradcheck_across_the_branches():
    z = t64([-400.0, -30.0, -3.5, -3.0001, -2.5, -0.3, 0.0, 1.2, 8.0]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: truncated_normal_stats(x), (z,), eps=1e-7, atol=1e-8, rtol=1e-6)


@needs_mpmath
def test_truncated_normal_variance_derivative_against_mpmath():
    """d var/dz in the far tail, where it is ~1/|z|^3 and a naive formula loses every digit."""
    zs = [-3.5, -20.0, -1e3, -1e5]
    z = t64(zs).requires_grad_(True)
    g, = torch.autograd.grad(truncated_normal_stats(z)[2].sum(), z)
    for i, zv in enumerate(zs):
        with mp.workdps(60):
            def var(x):
                lam = mp.npdf(x) / mp.ncdf(x)
                return 1 - lam * (x + lam)
            ref = mp.diff(var, mp.mpf(zv))
        assert float(g[i]) == pytest.approx(float(ref), rel=1e-9), (zv, float(g[i]), float(ref))


# ----------------------------------------------------------------------------- rectified normal


def test_rectified_log_prob_cdf_point_mass_vs_scipy():
    loc = t64([0.7, -1.3, 2.0, -4.0])[:, None]
    scale = t64([1.0, 0.5, 3.0, 0.2])[:, None]
    x = t64([-1.0, -1e-9, 0.0, 1e-6, 0.3, 2.5, 10.0])[None, :]
    d = RectifiedNormal(loc, scale)
    lp = d.log_prob(x).numpy()
    cdf = d.cdf(x).numpy()
    L, S, X = np.broadcast_arrays(loc.numpy(), scale.numpy(), x.numpy())
    ref_lp = np.where(X > 0, stats.norm.logpdf(X, L, S), np.where(X == 0, stats.norm.logcdf(0.0, L, S), -np.inf))
    ref_cdf = np.where(X < 0, 0.0, stats.norm.cdf(X, L, S))
    np.testing.assert_allclose(lp, ref_lp, rtol=1e-13)
    assert np.all(np.isneginf(lp[X < 0]))
    np.testing.assert_allclose(cdf, ref_cdf, rtol=1e-13, atol=1e-300)
    np.testing.assert_allclose(d.prob_zero().numpy()[:, 0], stats.norm.cdf(0.0, loc[:, 0], scale[:, 0]), rtol=1e-13)
    # The cdf jumps at 0 by exactly the point mass.
    np.testing.assert_allclose(d.cdf(torch.zeros(4, 1, dtype=torch.float64)).numpy(), d.prob_zero().numpy(), rtol=1e-15)


@pytest.mark.parametrize("dtype", DTYPES)
def test_rectified_log_point_mass_extreme(dtype):
    loc = torch.tensor(EXTREME_LOCS, dtype=dtype)[:, None]
    scale = torch.tensor(EXTREME_SCALES, dtype=dtype)[None, :]
    got = RectifiedNormal(loc, scale).log_prob_zero().double().numpy()
    ref = special.log_ndtr(-(np.array(EXTREME_LOCS)[:, None] / np.array(EXTREME_SCALES)[None, :]))
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, ref, rtol=2e-6 if dtype == torch.float32 else 1e-13, atol=1e-30)


@pytest.mark.parametrize("loc,scale", [(0.7, 1.0), (-1.5, 0.8), (-3.0, 0.4)])
def test_rectified_mass_integrates_to_one(loc, scale):
    """P(X = 0) + int_0^inf exp(log_prob(x)) dx = 1 under the mixed log_prob convention."""
    d = RectifiedNormal(torch.tensor(loc, dtype=torch.float64), torch.tensor(scale, dtype=torch.float64))
    dens = lambda x: float(torch.exp(d.log_prob(torch.tensor(x, dtype=torch.float64))))  # noqa: E731
    cont, _ = integrate.quad(dens, 0.0, max(loc, 0.0) + 40 * scale, limit=200, epsabs=1e-14)
    assert float(d.prob_zero()) + cont == pytest.approx(1.0, abs=1e-10)


def test_rectified_mean_variance_vs_quad():
    for loc, scale in itertools.product([-2.0, -0.4, 0.0, 0.9, 3.0], [0.3, 1.0, 2.5]):
        hi = max(loc, 0.0) + 40 * scale
        pdf = lambda x: stats.norm.pdf(x, loc, scale)  # noqa: E731
        pts = _breakpoints(0.0, hi, max(loc, 0.0), scale)
        mean_ref = integrate.quad(lambda x: x * pdf(x), 0.0, hi, points=pts, limit=200, epsabs=1e-14)[0]
        var_ref = integrate.quad(lambda x: (x - mean_ref) ** 2 * pdf(x), 0.0, hi, points=pts, limit=200,
                                 epsabs=1e-14)[0] + stats.norm.cdf(0.0, loc, scale) * mean_ref**2
        d = RectifiedNormal(torch.tensor(loc, dtype=torch.float64), torch.tensor(scale, dtype=torch.float64))
        assert float(d.mean) == pytest.approx(mean_ref, rel=1e-10, abs=1e-13), (loc, scale)
        assert float(d.variance) == pytest.approx(var_ref, rel=1e-9, abs=1e-13), (loc, scale)


@needs_mpmath
@pytest.mark.parametrize("dtype", DTYPES)
def test_rectified_mean_variance_extreme_vs_mpmath(dtype):
    loc = torch.tensor(EXTREME_LOCS + [-40.0, -3.0], dtype=dtype)[:, None]
    scale = torch.tensor(EXTREME_SCALES, dtype=dtype)[None, :]
    loc, scale = torch.broadcast_tensors(loc, scale)
    loc, scale = loc.clone().requires_grad_(), scale.clone().requires_grad_()
    d = RectifiedNormal(loc, scale)
    mean, var = d.mean, d.variance
    grads = torch.autograd.grad((mean + var).sum(), (loc, scale))
    assert all(torch.isfinite(g).all() for g in grads)
    tiny = torch.finfo(dtype).tiny
    rtol = 2e-5 if dtype == torch.float32 else 1e-12
    for i, j in itertools.product(range(loc.shape[0]), range(loc.shape[1])):
        ref_mean, ref_var = mp_rectified_moments(float(loc.detach()[i, j]), float(scale.detach()[i, j]))
        for got, ref in ((mean[i, j], ref_mean), (var[i, j], ref_var)):
            got = float(got)
            assert math.isfinite(got) and got >= 0.0
            if ref > 1e3 * tiny:  # values in the normal range: relative accuracy
                assert got == pytest.approx(ref, rel=rtol), (i, j, got, ref)
            else:  # below the float's range: underflow to (near) zero is the right answer
                assert got <= 1e4 * tiny


def test_rectified_moments_and_cdf_vs_monte_carlo():
    gen = torch.Generator().manual_seed(0)
    loc, scale = t64([0.5, -1.0, 2.0]), t64([1.0, 0.7, 0.3])
    d = RectifiedNormal(loc, scale)
    x = d.sample((400_000,), generator=gen)
    assert x.shape == (400_000, 3) and (x >= 0).all()
    n = x.shape[0]
    se_mean = x.std(0) / math.sqrt(n)
    se_var = ((x - x.mean(0)) ** 2).std(0) / math.sqrt(n)
    assert ((x.mean(0) - d.mean).abs() < 5 * se_mean).all()
    assert ((x.var(0) - d.variance).abs() < 5 * se_var).all()
    p0 = d.prob_zero()
    assert (((x == 0).double().mean(0) - p0).abs() < 5 * torch.sqrt(p0 * (1 - p0) / n)).all()


def test_rectified_rsample_is_reparameterised_and_validates_scale():
    loc = torch.tensor([0.5, -0.5], dtype=torch.float64, requires_grad=True)
    scale = torch.tensor([2.0, 1.0], dtype=torch.float64, requires_grad=True)
    eps = torch.tensor([[0.3, 0.2], [-1.0, 1.0]], dtype=torch.float64)
    x = RectifiedNormal(loc, scale).rsample(eps)  # [[1.1, 0], [0, 0.5]]
    torch.testing.assert_close(x, t64([[1.1, 0.0], [0.0, 0.5]]))
    x.sum().backward()
    torch.testing.assert_close(loc.grad, t64([1.0, 1.0]))  # one positive draw per column
    torch.testing.assert_close(scale.grad, t64([0.3, 1.0]))
    with pytest.raises(ValueError, match="-1.0"):
        RectifiedNormal(0.0, torch.tensor([1.0, -1.0]))
    with pytest.raises(ValueError, match="scale"):
        LogisticNormal(0.0, torch.tensor([0.0]))


# ----------------------------------------------------------------------------- logistic normal


def test_logistic_log_prob_and_cdf_vs_change_of_variables():
    loc = t64([0.0, 1.5, -3.0])[:, None]
    scale = t64([1.0, 0.3, 2.0])[:, None]
    r = t64([1e-12, 1e-3, 0.2, 0.5, 0.9, 1 - 1e-9])[None, :]
    d = LogisticNormal(loc, scale)
    L, S, R = np.broadcast_arrays(loc.numpy(), scale.numpy(), r.numpy())
    y = special.logit(R)
    ref_lp = stats.norm.logpdf(y, L, S) - np.log(R) - np.log1p(-R)
    np.testing.assert_allclose(d.log_prob(r).numpy(), ref_lp, rtol=1e-12)
    np.testing.assert_allclose(d.cdf(r).numpy(), stats.norm.cdf(y, L, S), rtol=1e-12, atol=1e-300)
    outside = t64([-0.1, 0.0, 1.0, 1.5])
    assert torch.isneginf(LogisticNormal(0.0, 1.0).log_prob(outside)).all()
    torch.testing.assert_close(LogisticNormal(t64(0.0), t64(1.0)).cdf(outside), t64([0.0, 0.0, 1.0, 1.0]))
    # From the logit: same values where sigmoid(y) is representable, finite where it rounds to 0/1.
    y_mid = t64([-40.0, -2.0, 0.0, 3.0, 40.0])[None, :]
    L, S, Y = np.broadcast_arrays(loc.numpy(), scale.numpy(), y_mid.numpy())
    ref_logit = stats.norm.logpdf(Y, L, S) - special.log_expit(Y) - special.log_expit(-Y)
    np.testing.assert_allclose(d.log_prob_logit(y_mid).numpy(), ref_logit, rtol=1e-13)
    far = LogisticNormal(torch.tensor(0.0), torch.tensor(50.0)).log_prob_logit(torch.tensor([-200.0, 200.0]))
    assert torch.isfinite(far).all()


def test_logistic_density_integrates_to_one():
    for loc, scale in [(0.0, 1.0), (2.0, 0.5), (-1.0, 2.5)]:
        d = LogisticNormal(torch.tensor(loc, dtype=torch.float64), torch.tensor(scale, dtype=torch.float64))
        total = sum(integrate.quad(lambda r: float(torch.exp(d.log_prob(torch.tensor(r, dtype=torch.float64)))),
                                   a, b, limit=200, epsabs=1e-13)[0] for a, b in [(0.0, 0.5), (0.5, 1.0)])
        assert total == pytest.approx(1.0, abs=1e-9)


def test_logistic_mean_variance_vs_quad():
    for loc, scale in itertools.product([-5.0, -1.0, 0.0, 0.7, 5.0], [1e-2, 0.5, 1.0, 1.5, 3.0, 10.0]):
        mean_ref, var_ref = quad_logistic_moments(loc, scale)
        d = LogisticNormal(torch.tensor(loc, dtype=torch.float64), torch.tensor(scale, dtype=torch.float64))
        assert float(d.mean) == pytest.approx(mean_ref, rel=1e-9, abs=1e-12), (loc, scale)
        assert float(d.variance) == pytest.approx(var_ref, rel=1e-8, abs=1e-12), (loc, scale)


@pytest.mark.parametrize("dtype", DTYPES)
def test_logistic_mean_variance_extreme(dtype):
    """Extreme grid: float64 vs float64 quad (absolute), float32 vs float64; finite gradients."""
    loc = torch.tensor(EXTREME_LOCS, dtype=dtype)[:, None].expand(5, 5).clone().requires_grad_()
    scale = torch.tensor(EXTREME_SCALES, dtype=dtype)[None, :].expand(5, 5).clone().requires_grad_()
    d = LogisticNormal(loc, scale)
    mean, var = d.mean, d.variance
    grads = torch.autograd.grad((mean + var).sum(), (loc, scale))
    assert all(torch.isfinite(g).all() for g in grads)
    assert ((mean >= 0) & (mean <= 1)).all() and (var >= 0).all() and (var <= mean * (1 - mean) + 1e-7).all()
    atol = 1e-6 if dtype == torch.float32 else 1e-12
    for i, j in itertools.product(range(5), range(5)):
        mean_ref, var_ref = quad_logistic_moments(EXTREME_LOCS[i], EXTREME_SCALES[j])
        assert float(mean[i, j]) == pytest.approx(mean_ref, abs=atol), (i, j)
        assert float(var[i, j]) == pytest.approx(var_ref, abs=atol), (i, j)
    if dtype == torch.float32:  # relative accuracy of the tiny variances at small scales
        ref64 = LogisticNormal(loc.detach().double(), scale.detach().double()).variance
        small = (scale <= 1).detach() & (ref64 > 1e-30)
        torch.testing.assert_close(var.detach().double()[small], ref64[small], rtol=1e-3, atol=0)


def test_logistic_tiny_scale_variance_is_delta_method():
    """scale -> 0: Var[sigmoid(Y)] = sigmoid'(loc)^2 scale^2 (1 + O(scale^2)); no cancellation."""
    loc = t64([-8.0, 0.0, 2.0])
    for dtype in DTYPES:
        d = LogisticNormal(loc.to(dtype), torch.full((3,), 1e-4, dtype=dtype))
        s = torch.sigmoid(loc)
        torch.testing.assert_close(d.variance.double(), (s * (1 - s) * 1e-4) ** 2, rtol=1e-4, atol=0)


def test_logistic_far_left_tail_is_lognormal():
    """loc = -50: sigmoid(y) = e^y (1 + O(e^-45)) on the mass, so R is lognormal to ~1e-19:
    E R = exp(m + s^2/2), Var R = exp(2m + s^2) expm1(s^2); values ~1e-52 keep relative accuracy."""
    scale = t64([1e-4, 0.3, 1.0])
    d = LogisticNormal(torch.full((3,), -50.0, dtype=torch.float64), scale)
    torch.testing.assert_close(d.mean, torch.exp(-50.0 + scale**2 / 2), rtol=1e-12, atol=0)
    torch.testing.assert_close(d.variance, torch.exp(-100.0 + scale**2) * torch.expm1(scale**2), rtol=1e-10, atol=0)


def test_logistic_moments_vs_monte_carlo():
    gen = torch.Generator().manual_seed(1)
    d = LogisticNormal(t64([0.3, -2.0, 1.0]), t64([0.8, 2.0, 6.0]))
    r = d.sample((400_000,), generator=gen)
    n = r.shape[0]
    assert ((r.mean(0) - d.mean).abs() < 5 * r.std(0) / math.sqrt(n)).all()
    assert ((r.var(0) - d.variance).abs() < 5 * ((r - r.mean(0)) ** 2).std(0) / math.sqrt(n)).all()


# ----------------------------------------------------------------------------- KL: references


def test_kl_normal_vs_torch_distributions():
    gen = torch.Generator().manual_seed(2)
    mq, mp_ = torch.randn(2, 50, generator=gen, dtype=torch.float64) * 3
    sq, sp = torch.exp(torch.randn(2, 50, generator=gen, dtype=torch.float64))
    ref = torch.distributions.kl_divergence(torch.distributions.Normal(mq, sq), torch.distributions.Normal(mp_, sp))
    torch.testing.assert_close(kl_normal(mq, sq, mp_, sp), ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(kl_logistic_normal(mq, sq, mp_, sp), ref, rtol=1e-12, atol=1e-14)
    # Nearly equal scales in float32: KL ~ (sq/sp - 1)^2 = 1e-8, not rounding noise.
    sq32 = torch.tensor(1.0001, dtype=torch.float32)
    k = kl_normal(torch.tensor(0.0), sq32, torch.tensor(0.0), torch.tensor(1.0))
    rho = float(sq32)  # the float32 value, exactly, in float64
    assert float(k) == pytest.approx(-math.log(rho) + (rho**2 - 1) / 2, rel=1e-3)


def test_kl_logistic_normal_vs_quadrature_of_densities():
    """Gaussian KL of the logits equals the integral of the logistic-normal densities over (0, 1)."""
    for mq, sq, mp_, sp in itertools.product([-1.5, 0.4], [0.3, 1.2], [0.0, 2.0], [0.5, 2.0]):
        ref = quad_logistic_density_kl(mq, sq, mp_, sp)
        got = float(kl_logistic_normal(*(torch.tensor(v, dtype=torch.float64) for v in (mq, sq, mp_, sp))))
        assert got == pytest.approx(ref, rel=1e-8, abs=1e-10), (mq, sq, mp_, sp)


def test_kl_rectified_vs_quadrature():
    cases = list(itertools.product([-2.0, 0.3, 1.5], [0.3, 1.0, 3.0], [-1.0, 0.5, 2.0], [0.5, 2.0, 4.0]))
    cases += [(-8.0, 1.0, 0.0, 1.0), (-3.0, 0.1, 0.5, 5.0), (5.0, 0.01, 5.001, 0.02), (-20.0, 2.0, 0.0, 10.0),
              (-6.0, 1.0, -6.0, 1.2), (0.0, 1e-3, 0.0, 10.0)]
    arr = np.array(cases)
    got = kl_rectified_normal(*(t64(arr[:, i]) for i in range(4))).numpy()
    ref = np.array([quad_rectified_kl(*c) for c in cases])
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-10)


@needs_mpmath
@pytest.mark.parametrize("dtype", DTYPES)
def test_kl_rectified_extreme_grid_vs_mpmath(dtype):
    """625 combinations of loc in {-50..50}, scale in {1e-4..1e3}: values against 60-digit
    mpmath; finite values and gradients; KL >= 0; float32 within its precision."""
    params = extreme_kl_grid(dtype)
    kl = kl_rectified_normal(*params)
    grads = torch.autograd.grad(kl.sum(), params)
    assert torch.isfinite(kl).all()
    assert all(torch.isfinite(g).all() for g in grads)
    ref = np.array([mp_rectified_kl(*(float(p[i]) for p in params)) for i in range(kl.shape[0])])
    rtol = 1e-4 if dtype == torch.float32 else 1e-10
    np.testing.assert_allclose(kl.detach().double().numpy(), ref, rtol=rtol, atol=rtol * 1e-2)
    assert (kl >= 0).all()  # holds exactly here
    assert (ref >= -1e-50).all()  # and in the reference, up to its 60-digit rounding


@pytest.mark.parametrize("dtype", DTYPES)
def test_kl_self_is_exactly_zero_with_finite_gradients(dtype):
    loc = torch.tensor(EXTREME_LOCS, dtype=dtype)[:, None].expand(5, 5).reshape(-1).clone().requires_grad_()
    scale = torch.tensor(EXTREME_SCALES, dtype=dtype)[None, :].expand(5, 5).reshape(-1).clone().requires_grad_()
    for kl_fn in (kl_rectified_normal, kl_logistic_normal):
        kl = kl_fn(loc, scale, loc, scale)
        assert (kl == 0).all(), kl_fn.__name__
        grads = torch.autograd.grad(kl.sum(), (loc, scale))
        assert all(torch.isfinite(g).all() for g in grads)
        # KL(q || q) is a minimum: its gradient vanishes (up to rounding of 0 * large numbers).
        assert all(g.abs().max() < 1e-3 for g in grads), kl_fn.__name__


@pytest.mark.parametrize("dtype", DTYPES)
def test_kl_logistic_and_mc_estimators_finite_on_extreme_grid(dtype):
    params = extreme_kl_grid(dtype)
    kl = kl_logistic_normal(*params)
    assert torch.isfinite(kl).all() and (kl >= 0).all()
    assert all(torch.isfinite(g).all() for g in torch.autograd.grad(kl.sum(), params))
    gen = torch.Generator().manual_seed(3)
    for mc in (kl_rectified_normal_mc, kl_logistic_normal_mc):
        est = mc(*params, num_samples=4, generator=gen)
        assert est.shape == kl.shape and torch.isfinite(est).all()
        assert all(torch.isfinite(g).all() for g in torch.autograd.grad(est.sum(), params))


# ----------------------------------------------------------------------------- KL: Monte-Carlo


MC_CASES = t64([[-0.5, 1.0, 0.3, 2.0],   # q has a big point mass
                [0.8, 0.6, -1.0, 1.5],
                [-2.0, 1.5, 1.0, 3.0],
                [1.0, 0.5, 1.0, 10.0]])  # prior-like wide p


def _per_sample(mc_fn, n: int, seed: int, **kwargs):
    """Per-draw values and per-draw parameter gradients (params expanded per draw)."""
    eps = draw_standard_normal((1, n, MC_CASES.shape[0]), torch.Generator().manual_seed(seed), dtype=torch.float64)
    params = MC_CASES.T[:, None, :].expand(4, n, MC_CASES.shape[0]).clone().requires_grad_()
    values = mc_fn(*params, num_samples=1, eps=eps, **kwargs)  # [n, B]
    values.sum().backward()
    return values.detach(), params.grad  # [n, B], [4, n, B]


@pytest.mark.parametrize("closed,mc", [(kl_rectified_normal, kl_rectified_normal_mc),
                                       (kl_logistic_normal, kl_logistic_normal_mc)])
def test_kl_closed_form_vs_monte_carlo_values_and_gradients(closed, mc):
    n = 200_000
    values, grads = _per_sample(mc, n, seed=4)
    q = MC_CASES.T.clone().requires_grad_()
    exact = closed(*q)
    exact.sum().backward()
    se = values.std(0) / math.sqrt(n)
    assert ((values.mean(0) - exact.detach()).abs() < 5 * se + 1e-12).all()
    g_se = grads.std(1) / math.sqrt(n)
    assert ((grads.mean(1) - q.grad).abs() < 5 * g_se + 1e-12).all()


def test_plain_reparameterised_rectified_kl_gradient_misses_the_boundary_term():
    """Without the boundary term, d/d(loc_q, scale_q) of the MC KL is biased; adding the Leibniz
    term phi(eps0) (g_0 - g_+) d eps0/dtheta by hand recovers the closed-form gradient."""
    n = 200_000
    _, plain = _per_sample(kl_rectified_normal_mc, n, seed=5, boundary_gradient=False)
    q = MC_CASES.T.clone().requires_grad_()
    kl_rectified_normal(*q).sum().backward()
    mq, sq, mp_, sp = MC_CASES.T
    eps0 = -mq / sq
    g0 = special.log_ndtr(-(mq / sq).numpy()) - special.log_ndtr(-(mp_ / sp).numpy())
    g_plus = stats.norm.logpdf(0.0, mq.numpy(), sq.numpy()) - stats.norm.logpdf(0.0, mp_.numpy(), sp.numpy())
    jump = torch.from_numpy(stats.norm.pdf(eps0.numpy()) * (g0 - g_plus))
    boundary = torch.stack([jump * (-1 / sq), jump * (mq / sq**2)])  # d eps0/d loc_q, d eps0/d scale_q
    mean, se = plain.mean(1), plain.std(1) / math.sqrt(n)
    assert ((mean[:2] - q.grad[:2]).abs() > 20 * se[:2]).any()  # the bias is real and large
    assert ((mean[:2] + boundary - q.grad[:2]).abs() < 5 * se[:2] + 1e-12).all()
    assert ((mean[2:] - q.grad[2:]).abs() < 5 * se[2:] + 1e-12).all()  # prior grads are unbiased


def test_mc_kl_draws_shape_generator_and_broadcasting():
    loc_q = torch.zeros(4, 6)
    scale_q = torch.ones(4, 6)
    prior_loc, prior_scale = torch.tensor(0.5), 10.0
    for mc in (kl_rectified_normal_mc, kl_logistic_normal_mc):
        a = mc(loc_q, scale_q, prior_loc, prior_scale, num_samples=8, generator=torch.Generator().manual_seed(0))
        b = mc(loc_q, scale_q, prior_loc, prior_scale, num_samples=8, generator=torch.Generator().manual_seed(0))
        assert a.shape == (4, 6) and a.dtype == torch.float32
        torch.testing.assert_close(a, b)
    for closed in (kl_rectified_normal, kl_logistic_normal, kl_normal):
        out = closed(loc_q, scale_q, prior_loc, prior_scale)
        assert out.shape == (4, 6) and out.dtype == torch.float32
    with pytest.raises(ValueError, match="num_samples"):
        kl_rectified_normal_mc(loc_q, scale_q, 0.0, 1.0, num_samples=0)


# ----------------------------------------------------------------------------- gradcheck


GRADCHECK_POINTS = [
    (0.7, 1.3, -0.4, 2.0),
    (-6.0, 1.0, 1.0, 3.0),      # continued-fraction regime for z_q
    (3.0, 0.5, 2.0, 0.4),
    (-1.0, 0.2, 0.1, 0.05),     # truncated mean far from loc_p (second bracket form)
    (-20.0, 2.0, 5.0, 10.0),
    (0.4, 1.0, 0.4, 1.0),       # q == p
]


@pytest.mark.parametrize("point", GRADCHECK_POINTS)
def test_gradcheck_kls(point):
    args = tuple(torch.tensor([v], dtype=torch.float64, requires_grad=True) for v in point)
    assert torch.autograd.gradcheck(kl_rectified_normal, args)
    assert torch.autograd.gradcheck(kl_logistic_normal, args)


@pytest.mark.parametrize("loc,scale", [(0.7, 1.3), (-10.0, 1.0), (-3.0, 1.0), (3.0, 0.5), (-40.0, 2.0)])
def test_gradcheck_moments(loc, scale):
    args = (torch.tensor([loc], dtype=torch.float64, requires_grad=True),
            torch.tensor([scale], dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(lambda m, s: RectifiedNormal(m, s).mean, args)
    assert torch.autograd.gradcheck(lambda m, s: RectifiedNormal(m, s).variance, args)
    assert torch.autograd.gradcheck(lambda m, s: LogisticNormal(m, s).mean, args)
    assert torch.autograd.gradcheck(lambda m, s: LogisticNormal(m, s).variance, args)
    assert torch.autograd.gradcheck(log_ndtr, (args[0],))


def test_field_kl_means_of_parts_equal_separate_kls_values_and_gradients():
    """The KL terms evaluated as one batch (each part with its own prior, as the random-point and
    observed-sample KLs of a training step) equal each part's own ``field_kl`` mean, in value and
    in the gradients of the points' parameters and of both priors (float64)."""
    from stochastic_fields.fields.base import FieldParams
    from stochastic_fields.losses import field_kl, field_kl_means

    gen = torch.Generator().manual_seed(3)

    def params(n):
        return FieldParams(torch.randn(n, generator=gen, dtype=torch.float64) * 3,
                           torch.rand(n, generator=gen, dtype=torch.float64) + 0.05,
                           torch.randn(n, 3, generator=gen, dtype=torch.float64) * 2,
                           torch.rand(n, 3, generator=gen, dtype=torch.float64) + 0.05).map(lambda t: t.requires_grad_(True))

    def prior(loc, scale):  # (density loc, scale, colour loc [3], scale [3]) as Priors gives them, float64 leaves
        return tuple(torch.tensor(v, dtype=torch.float64, requires_grad=True)
                     for v in (loc, scale, [loc, -loc, 0.5], [scale, 2 * scale, 1.0]))

    priors = [prior(0.0, 3.0), prior(-0.7, 0.9)]
    parts = [(params(7), priors[0]), (params(5), priors[1])]
    joined = field_kl_means(parts)
    separate = [field_kl(p, prior).mean() for p, prior in parts]
    leaves = [t for p, _ in parts for t in (p.density_loc, p.density_scale, p.rgb_loc, p.rgb_scale)] + [t for pr in priors for t in pr]
    g_joined = torch.autograd.grad(joined[0] + 0.3 * joined[1], leaves, allow_unused=True, retain_graph=True)
    g_separate = torch.autograd.grad(separate[0] + 0.3 * separate[1], leaves, allow_unused=True)
    for a, b in zip(joined, separate):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    for a, b in zip(g_joined, g_separate):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    assert field_kl_means([]) == []
    torch.testing.assert_close(field_kl_means(parts[:1])[0], separate[0])
