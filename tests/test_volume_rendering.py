"""Tests for volume_rendering: analytic integrals, golden values, float64 loops, gradcheck, packed == dense."""

from __future__ import annotations

import doctest
import math
import statistics

import numpy as np
import pytest
import torch
from scipy import integrate

from stochastic_fields import volume_rendering as vr
from stochastic_fields.constants import OPACITY_EPS

NEAR, FAR = 2.0, 6.0
R0, R1 = 0.2, 0.1  # radiance along the ray: r(t) = R0 + R1 t (linear, so its integral has a closed form)
TOL = {torch.float32: dict(rtol=2e-5, atol=2e-6), torch.float64: dict(rtol=1e-10, atol=1e-12)}


# ----------------------------------------------------------------------------- references


def slab_reference(a: float, b: float, sigma: float) -> dict[str, float]:
    """Closed forms for constant density ``sigma`` on [a, b] (zero elsewhere), radiance R0 + R1 t.

    Termination distance given a hit is an exponential truncated to [a, b]:
        opacity = 1 - exp(-sigma L), D = a + 1/sigma - L e^{-sigma L} / (1 - e^{-sigma L}),
        spread = 1/sigma^2 - L^2 e^{-sigma L} / (1 - e^{-sigma L})^2,
        colour = int T sigma (R0 + R1 t) dt = R0 opacity + R1 D opacity.
    """
    length = b - a
    e = math.exp(-sigma * length)
    acc = -math.expm1(-sigma * length)
    depth = a + 1.0 / sigma - length * e / acc
    spread = 1.0 / sigma**2 - length**2 * e / acc**2
    return dict(opacity=acc, colour=R0 * acc + R1 * depth * acc, depth=depth, spread=spread)


def bump(amp: float, mu: float, sd: float):
    """Gaussian density bump: (density fn on tensors, optical depth from t0 fn on floats)."""

    def density(t: torch.Tensor) -> torch.Tensor:
        return amp * torch.exp(-((t - mu) ** 2) / (2 * sd * sd))

    def optical_depth(t0: float, t: float) -> float:
        c = sd * math.sqrt(2.0)
        return amp * sd * math.sqrt(math.pi / 2) * (math.erf((t - mu) / c) - math.erf((t0 - mu) / c))

    return density, optical_depth


def bump_reference(amp: float, mu: float, sd: float, t0: float = NEAR, t1: float = FAR) -> dict[str, float]:
    """scipy.quad of int_{t0}^{t1} T(t) a(t) g(t) dt with the exact (erf) transmittance."""
    _, optical_depth = bump(amp, mu, sd)

    def a(t: float) -> float:
        return amp * math.exp(-((t - mu) ** 2) / (2 * sd * sd))

    def quad(g) -> float:
        f = lambda t: math.exp(-optical_depth(t0, t)) * a(t) * g(t)  # noqa: E731
        return integrate.quad(f, t0, t1, points=[mu], epsabs=1e-14, epsrel=1e-13, limit=200)[0]

    acc = quad(lambda t: 1.0)
    first = quad(lambda t: t)
    return dict(opacity=acc, colour=R0 * acc + R1 * first, depth=first / acc)


def uniform_grid(num: int, near: float = NEAR, far: float = FAR, dtype=torch.float64):
    edges = torch.linspace(near, far, num + 1, dtype=dtype)
    t_starts, t_ends = edges[:-1], edges[1:]
    return t_starts, t_ends, 0.5 * (t_starts + t_ends)


def render_1d(density_fn, num: int, quadrature: str, near=NEAR, far=FAR, dtype=torch.float64):
    t_starts, t_ends, t_mids = uniform_grid(num, near, far, dtype)
    w = vr.render_weights(density_fn(t_mids).to(dtype), t_starts, t_ends, quadrature)
    depth = vr.expected_depth(w, t_mids, far)
    return dict(
        opacity=vr.opacity(w).item(),
        colour=vr.accumulate(w, R0 + R1 * t_mids).item(),
        depth=depth.item(),
        spread=vr.termination_spread(w, t_mids, depth).item(),
        weights=w,
    )


def slab_density(a: float, b: float, sigma: float):
    return lambda t: sigma * ((t >= a) & (t <= b)).to(t.dtype)


# Hard cases for the quadrature comparison: (density, analytic reference).
HARD_CASES = {
    "step_1e4": (slab_density(3.3, FAR, 1e4), slab_reference(3.3, FAR, 1e4)),
    "step_1e6": (slab_density(3.3, FAR, 1e6), slab_reference(3.3, FAR, 1e6)),
    "opaque_from_near_1e4": (slab_density(NEAR, FAR, 1e4), slab_reference(NEAR, FAR, 1e4)),
    "narrow_bump_200": (bump(200.0, 4.0, 0.02)[0], bump_reference(200.0, 4.0, 0.02)),
}


# ----------------------------------------------------------------------------- golden values


def test_docstring_examples_hold():
    result = doctest.testmod(vr, raise_on_error=False)
    assert result.attempted >= 10
    assert result.failed == 0


def test_golden_nerfacc_transmittance_and_weights():
    alpha = torch.tensor([[0.3, 0.8, 0.8, 0.5]], dtype=torch.float64)
    density = -torch.log1p(-alpha)  # unit intervals: 1 - exp(-density) = alpha
    t_starts = torch.arange(4.0, dtype=torch.float64)
    transmittance = vr.transmittance_alpha(density, torch.ones(4, dtype=torch.float64))
    torch.testing.assert_close(transmittance, torch.tensor([[1.0, 0.7, 0.14, 0.028]], dtype=torch.float64))
    w = vr.weights_alpha(density, t_starts, t_starts + 1)
    torch.testing.assert_close(w, torch.tensor([[0.3, 0.56, 0.112, 0.014]], dtype=torch.float64))
    assert vr.opacity(w).item() == pytest.approx(1 - 0.7 * 0.2 * 0.2 * 0.5, abs=1e-14)


def test_golden_trapezoid_by_hand():
    # nodes 0.5, 1.5, 3.5 (delta 1, 2); densities 1, 3, 0
    # T = 1, exp(-(1+3)/2 * 1) = e^-2, e^-2 * exp(-(3+0)/2 * 2) = e^-5
    # w = T a (left + right)/2 = [1*1*0.5, e^-2*3*1.5, 0]
    density = torch.tensor([1.0, 3.0, 0.0], dtype=torch.float64)
    t_starts = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)
    t_ends = torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64)
    transmittance = vr.transmittance_trapezoid(density, 0.5 * (t_starts + t_ends))
    torch.testing.assert_close(transmittance, torch.exp(-torch.tensor([0.0, 2.0, 5.0], dtype=torch.float64)))
    w = vr.weights_trapezoid(density, t_starts, t_ends)
    torch.testing.assert_close(w, torch.tensor([0.5, 4.5 * math.exp(-2.0), 0.0], dtype=torch.float64))


def test_small_optical_depth_keeps_precision_in_float32():
    # 1 - exp(-1e-8) is exactly 0 in float32; -expm1(-x) keeps it.
    density = torch.full((1, 3), 1e-8, dtype=torch.float32)
    t_starts = torch.arange(3.0)
    w = vr.weights_alpha(density, t_starts, t_starts + 1)
    torch.testing.assert_close(w, torch.full((1, 3), 1e-8), rtol=1e-6, atol=0.0)


# ----------------------------------------------------------------------------- the paper's rule


def paper_eq_tp(a, r, t, lagged: bool) -> float:
    """Eq. "tp" literally, float64 loop over python floats.

    ``lagged=True`` takes the transmittance sum up to j = i - 1 as printed in the paper;
    ``lagged=False`` up to j = i (the trapezoidal rule for exp(-int_{t_0}^{t_i} a)).
    """
    n = len(t)
    transmittance = []
    for i in range(n):
        upper = i - 1 if lagged else i
        tau = sum(0.5 * (a[j - 1] + a[j]) * (t[j] - t[j - 1]) for j in range(1, upper + 1))
        transmittance.append(math.exp(-tau))
    return sum(
        0.5 * (transmittance[i - 1] * r[i - 1] * a[i - 1] + transmittance[i] * r[i] * a[i]) * (t[i] - t[i - 1])
        for i in range(1, n)
    )


def test_trapezoid_weights_equal_paper_sum():
    gen = torch.Generator().manual_seed(0)
    edges = torch.sort(torch.rand(9, generator=gen, dtype=torch.float64) * 4).values
    t_starts, t_ends = edges[:-1], edges[1:]
    density = torch.rand(8, generator=gen, dtype=torch.float64) * 3
    radiance = torch.rand(8, generator=gen, dtype=torch.float64)
    w = vr.weights_trapezoid(density, t_starts, t_ends)
    t_mids = 0.5 * (t_starts + t_ends)
    expected = paper_eq_tp(density.tolist(), radiance.tolist(), t_mids.tolist(), lagged=False)
    assert vr.accumulate(w, radiance).item() == pytest.approx(expected, rel=1e-13)


def test_trapezoid_is_second_order_for_integral_between_first_and_last_node():
    """sum_i w_i r_i -> int_{t_0}^{t_{S-1}} T a r dt at O(h^2); the paper's printed index is O(h)."""
    density_fn, _ = bump(5.0, 4.0, 0.3)
    errors, errors_lagged = [], []
    for num in (32, 64, 128):
        t_starts, t_ends, t_mids = uniform_grid(num)
        density = density_fn(t_mids)
        radiance = R0 + R1 * t_mids
        ref = bump_reference(5.0, 4.0, 0.3, t0=t_mids[0].item(), t1=t_mids[-1].item())["colour"]
        colour = vr.accumulate(vr.weights_trapezoid(density, t_starts, t_ends), radiance).item()
        errors.append(abs(colour - ref))
        lagged = paper_eq_tp(density.tolist(), radiance.tolist(), t_mids.tolist(), lagged=True)
        errors_lagged.append(abs(lagged - ref))
    for coarse, fine in zip(errors[:-1], errors[1:]):
        assert 3.5 < coarse / fine < 4.5  # halving h divides the error by 4
    for coarse, fine in zip(errors_lagged[:-1], errors_lagged[1:]):
        assert 1.7 < coarse / fine < 2.3  # first order
    assert errors[-1] < errors_lagged[-1] / 50


# ----------------------------------------------------------------------------- analytic integrals


SMOOTH_CASES = {
    "uniform_slab": (slab_density(NEAR, FAR, 1.0), slab_reference(NEAR, FAR, 1.0)),
    "unaligned_slab": (slab_density(3.1, 4.7, 2.0), slab_reference(3.1, 4.7, 2.0)),
    "gaussian_bump": (bump(5.0, 4.0, 0.3)[0], bump_reference(5.0, 4.0, 0.3)),
}


@pytest.mark.parametrize("case", sorted(SMOOTH_CASES))
def test_both_rules_converge_to_analytic_and_to_each_other(case):
    density_fn, ref = SMOOTH_CASES[case]
    nums = (16, 64, 256, 1024)
    results = {q: [render_1d(density_fn, n, q) for n in nums] for q in vr.QUADRATURES}
    for quadrature, runs in results.items():
        for key in ("opacity", "colour", "depth"):
            errors = [abs(run[key] - ref[key]) for run in runs]
            assert errors[-1] < 3e-3, (quadrature, key, errors)
            if max(errors) < 1e-10:  # alpha's opacity is exact when the density is constant
                continue
            if case == "gaussian_bump":  # smooth: every refinement by 4 divides the error by >= 8
                steps = zip(errors[:-1], errors[1:])
                assert all(fine < coarse / 8 for coarse, fine in steps), (quadrature, key, errors)
            else:  # steps and end truncation: errors oscillate with grid alignment, their envelope falls as h
                assert errors[-1] < max(errors[:-1]) / 4, (quadrature, key, errors)
                assert all(err <= 2.0 * (FAR - NEAR) / n for err, n in zip(errors, nums)), (quadrature, key, errors)
    gaps = [abs(a["colour"] - t["colour"]) for a, t in zip(results["alpha"], results["trapezoid"])]
    assert all(fine < coarse for coarse, fine in zip(gaps[:-1], gaps[1:])), gaps


def test_constant_slab_alpha_is_exact_in_transmittance():
    sigma = 1.3
    t_starts, t_ends, t_mids = uniform_grid(50)
    density = torch.full((50,), sigma, dtype=torch.float64)
    transmittance = vr.transmittance_alpha(density, t_ends - t_starts)
    torch.testing.assert_close(transmittance, torch.exp(-sigma * (t_starts - NEAR)), rtol=1e-13, atol=0.0)
    # constant colour c: C = c (1 - exp(-sigma L)) exactly
    w = vr.weights_alpha(density, t_starts, t_ends)
    colour = vr.accumulate(w, torch.full((50, 3), 0.7, dtype=torch.float64))
    torch.testing.assert_close(colour, torch.full((3,), 0.7 * -math.expm1(-sigma * (FAR - NEAR)), dtype=torch.float64))


def test_slab_depth_and_spread_match_closed_form():
    ref = slab_reference(NEAR, FAR, 0.7)
    run = render_1d(slab_density(NEAR, FAR, 0.7), 4096, "alpha")
    assert run["depth"] == pytest.approx(ref["depth"], abs=1e-6)
    # midpoint sampling adds the within-interval variance h^2/12 at most
    assert run["spread"] == pytest.approx(ref["spread"], abs=1e-6)


def test_opaque_step_alpha_is_bounded_by_one_interval():
    for sigma in (1e4, 1e6):
        ref = slab_reference(3.3, FAR, sigma)
        for num in (16, 64, 256):
            h = (FAR - NEAR) / num
            run = render_1d(slab_density(3.3, FAR, sigma), num, "alpha")
            assert run["opacity"] == pytest.approx(1.0, abs=1e-12)
            assert abs(run["depth"] - ref["depth"]) <= h
            assert abs(run["colour"] - ref["colour"]) <= R1 * h + 1e-12
            assert run["spread"] <= h**2


def test_trapezoid_converges_on_opaque_step_only_when_h_resolves_one_over_sigma():
    """In a 2e-3 window around a wall of density 1e4, trapezoid converges once sigma h < 1."""
    near, far, wall, sigma = 3.299, 3.301, 3.2997, 1e4
    ref = slab_reference(wall, far, sigma)
    density_fn = slab_density(wall, far, sigma)
    for quadrature in vr.QUADRATURES:
        colours = [render_1d(density_fn, n, quadrature, near, far)["colour"] for n in (16, 128, 1024)]
        errors = [abs(colour - ref["colour"]) for colour in colours]
        assert errors[2] < errors[0] / 10, (quadrature, errors)
        assert errors[2] < 2e-3, (quadrature, errors)


@pytest.mark.parametrize("case", sorted(HARD_CASES))
def test_alpha_beats_trapezoid_on_hard_cases(case):
    density_fn, ref = HARD_CASES[case]
    for num in (64, 256, 1024):
        alpha = render_1d(density_fn, num, "alpha")
        trapezoid = render_1d(density_fn, num, "trapezoid")
        for key in ("colour", "opacity"):
            err_alpha, err_trap = abs(alpha[key] - ref[key]), abs(trapezoid[key] - ref[key])
            assert err_alpha < err_trap, (case, num, key, err_alpha, err_trap)
        assert alpha["opacity"] <= 1.0 + 1e-12


def test_trapezoid_weights_exceed_one_when_opaque_at_first_node():
    run = render_1d(slab_density(NEAR, FAR, 1e4), 64, "trapezoid")
    h = (FAR - NEAR) / 64
    assert run["weights"][0].item() == pytest.approx(1e4 * h / 2)  # T_0 = 1, w_0 = a_0 delta_1 / 2
    assert run["opacity"] > 100


def test_trapezoid_misses_opaque_wall_between_nodes():
    # a_{i-1} = 0, a_i = 1e4: T_i = exp(-a_i delta / 2) = 0 at the first node inside the wall
    run = render_1d(slab_density(3.3, FAR, 1e4), 64, "trapezoid")
    assert run["opacity"] < 1e-100


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_alpha_weights_sum_at_most_one(dtype):
    gen = torch.Generator().manual_seed(1)
    scale = torch.tensor([0.0, 1e-3, 1.0, 1e2, 1e4, 1e6], dtype=dtype)[:, None, None]
    density = torch.rand(6, 50, 32, generator=gen, dtype=dtype) * scale
    edges = torch.sort(torch.rand(50, 33, generator=gen, dtype=dtype) * 10, dim=-1).values
    w = vr.weights_alpha(density, edges[..., :-1], edges[..., 1:])
    assert bool((w >= 0).all())
    assert vr.opacity(w).max().item() <= 1.0 + 4 * torch.finfo(dtype).eps


# ----------------------------------------------------------------------------- degenerate inputs


@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_space_ray(quadrature, dtype):
    t_starts, t_ends, t_mids = uniform_grid(16, dtype=dtype)
    density = torch.zeros(2, 16, dtype=dtype, requires_grad=True)
    w = vr.render_weights(density, t_starts, t_ends, quadrature)
    depth = vr.expected_depth(w, t_mids, FAR)
    spread = vr.termination_spread(w, t_mids, depth)
    assert torch.equal(vr.opacity(w), torch.zeros(2, dtype=dtype))
    assert torch.equal(depth, torch.full((2,), FAR, dtype=dtype))
    assert torch.equal(spread, torch.zeros(2, dtype=dtype))
    colour = vr.composite_background(vr.accumulate(w, torch.rand(2, 16, 3, dtype=dtype)), vr.opacity(w), 0.25)
    assert torch.equal(colour, torch.full((2, 3), 0.25, dtype=dtype))
    (colour.sum() + depth.sum() + spread.sum()).backward()
    assert torch.isfinite(density.grad).all()


@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
def test_zero_length_intervals_contribute_nothing(quadrature):
    gen = torch.Generator().manual_seed(2)
    t_starts, t_ends, _ = uniform_grid(8)
    density = torch.rand(8, generator=gen, dtype=torch.float64) * 2
    base = vr.render_weights(density, t_starts, t_ends, quadrature)
    # duplicate sample 3 as a zero-length interval at its midpoint, with an arbitrary density
    mid = 0.5 * (t_starts[3] + t_ends[3])
    t_starts2 = torch.cat([t_starts[:4], mid[None], t_starts[4:]])
    t_ends2 = torch.cat([t_ends[:4], mid[None], t_ends[4:]])
    if quadrature == "alpha":
        density2 = torch.cat([density[:4], torch.tensor([1e6], dtype=torch.float64), density[4:]])
    else:  # trapezoid: a zero-length node at an existing node must carry the same density
        density2 = torch.cat([density[:4], density[3:4], density[4:]])
    w2 = vr.render_weights(density2, t_starts2, t_ends2, quadrature)
    if quadrature == "alpha":
        assert w2[4].item() == 0.0
        torch.testing.assert_close(torch.cat([w2[:4], w2[5:]]), base, rtol=1e-13, atol=1e-15)
    else:  # the duplicated node splits its weight: left half-interval on one, right on the other
        torch.testing.assert_close(w2[3] + w2[4], base[3], rtol=1e-13, atol=1e-15)
        torch.testing.assert_close(torch.cat([w2[:3], w2[5:]]), torch.cat([base[:3], base[4:]]), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
def test_trailing_zero_length_padding_is_inert(quadrature):
    gen = torch.Generator().manual_seed(2)
    t_starts, t_ends, t_mids = uniform_grid(8)
    density = torch.rand(8, generator=gen, dtype=torch.float64) * 2
    base = vr.render_weights(density, t_starts, t_ends, quadrature)
    pad = t_mids[-1].expand(3)  # padding: zero-length intervals at the last midpoint, any density
    padded = vr.render_weights(
        torch.cat([density, torch.tensor([5.0, 0.0, 1e6], dtype=torch.float64)]),
        torch.cat([t_starts, pad]),
        torch.cat([t_ends, pad]),
        quadrature,
    )
    torch.testing.assert_close(padded[:8], base, rtol=1e-14, atol=0.0)
    assert torch.equal(padded[8:], torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.0, 1e4, 1e6])
def test_gradients_finite_on_hard_cases(quadrature, dtype, sigma):
    t_starts, t_ends, t_mids = uniform_grid(32, dtype=dtype)
    density = (slab_density(3.3, FAR, sigma)(t_mids) + torch.zeros(3, 32, dtype=dtype)).requires_grad_(True)
    rgb = torch.rand(3, 32, 3, dtype=dtype, requires_grad=True)
    w = vr.render_weights(density, t_starts, t_ends, quadrature)
    depth = vr.expected_depth(w, t_mids, FAR)
    loss = vr.accumulate(w, rgb).sum() + depth.sum() + vr.termination_spread(w, t_mids, depth).sum()
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.isfinite(density.grad).all() and torch.isfinite(rgb.grad).all()


def test_zero_samples_dense():
    empty = torch.zeros(4, 0)
    for quadrature in vr.QUADRATURES:
        w = vr.render_weights(empty, empty, empty, quadrature)
        assert w.shape == (4, 0)
        assert torch.equal(vr.expected_depth(w, empty, 3.0), torch.full((4,), 3.0))


def test_bad_arguments_raise():
    x = torch.ones(2, 3)
    with pytest.raises(ValueError, match="quadrature 'simpson'"):
        vr.render_weights(x, x, x, "simpson")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"values must have shape"):
        vr.accumulate(x, torch.ones(2, 3, 4, 5))
    with pytest.raises(ValueError, match="sorted"):
        vr.exclusive_cumsum_packed(torch.ones(3), torch.tensor([0, 2, 1]), 3)
    with pytest.raises(ValueError, match="num_rays=2"):
        vr.exclusive_cumsum_packed(torch.ones(3), torch.tensor([0, 1, 2]), 2)
    with pytest.raises(ValueError, match="N = 3"):
        vr.weights_alpha_packed(torch.ones(3), torch.zeros(3), torch.ones(3), torch.tensor([0, 1]), 2)


# ----------------------------------------------------------------------------- batch shapes


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
def test_leading_batch_dims_match_row_by_row(batch, quadrature):
    gen = torch.Generator().manual_seed(3)
    density = torch.rand(*batch, 7, generator=gen, dtype=torch.float64) * 3
    edges = torch.sort(torch.rand(8, generator=gen, dtype=torch.float64), dim=-1).values
    w = vr.render_weights(density, edges[:-1], edges[1:], quadrature)
    flat = density.reshape(-1, 7)
    rows = torch.stack([vr.render_weights(row, edges[:-1], edges[1:], quadrature) for row in flat])
    torch.testing.assert_close(w.reshape(-1, 7), rows, rtol=0, atol=0)


# ----------------------------------------------------------------------------- trajectory statistics


def naive_statistics(density, rgb, t_starts, t_ends, far, background):
    """float64 per-ray, per-draw python loop (alpha compositing), moments via the statistics module."""
    num_rays, num_draws, num_samples = density.shape
    keys = ("colour_mean", "colour_var", "depth_mean", "depth_var_epistemic", "depth_var_spread", "opacity")
    out = {k: [] for k in keys}
    for r in range(num_rays):
        colours, depths, spreads, accs = [], [], [], []
        for k in range(num_draws):
            transmittance, weights = 1.0, []
            for i in range(num_samples):
                delta = float(t_ends[r, i] - t_starts[r, i])
                alpha = 1.0 - math.exp(-float(density[r, k, i]) * delta)
                weights.append(transmittance * alpha)
                transmittance *= 1.0 - alpha
            t = [0.5 * float(t_starts[r, i] + t_ends[r, i]) for i in range(num_samples)]
            acc = sum(weights)
            colour = [
                sum(w * float(rgb[r, k, i, c]) for i, w in enumerate(weights)) + (1 - acc) * background[c]
                for c in range(3)
            ]
            if acc < OPACITY_EPS:
                depth, spread = float(far[r]), 0.0
            else:
                depth = sum(w * ti for w, ti in zip(weights, t)) / acc
                spread = sum(w * (ti - depth) ** 2 for w, ti in zip(weights, t)) / acc
            colours.append(colour)
            depths.append(depth)
            spreads.append(spread)
            accs.append(acc)
        out["colour_mean"].append([statistics.fmean(c[ch] for c in colours) for ch in range(3)])
        out["colour_var"].append([statistics.pvariance([c[ch] for c in colours]) for ch in range(3)])
        out["depth_mean"].append(statistics.fmean(depths))
        out["depth_var_epistemic"].append(statistics.pvariance(depths))
        out["depth_var_spread"].append(statistics.fmean(spreads))
        out["opacity"].append(statistics.fmean(accs))
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in out.items()}


def random_rays(num_rays=5, num_draws=4, num_samples=6, seed=4, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    density = torch.rand(num_rays, num_draws, num_samples, generator=gen, dtype=dtype) * 2
    density[0] = 0.0  # a ray through empty space: every draw hits nothing
    density[1, :2] = 0.0  # a ray where half the draws hit nothing
    rgb = torch.rand(num_rays, num_draws, num_samples, 3, generator=gen, dtype=dtype)
    unit = torch.sort(torch.rand(num_rays, num_samples + 1, generator=gen, dtype=dtype), dim=-1).values
    edges = NEAR + unit * (FAR - NEAR)
    far = torch.full((num_rays,), FAR, dtype=dtype)
    return density, rgb, edges[:, :-1], edges[:, 1:], far


def test_trajectory_statistics_match_naive_loop():
    density, rgb, t_starts, t_ends, far = random_rays()
    background = [0.1, 0.5, 0.9]
    weights = vr.weights_alpha(density, t_starts[:, None], t_ends[:, None])
    t_mids = 0.5 * (t_starts + t_ends)
    stats = vr.trajectory_statistics(weights, rgb, t_mids, far, torch.tensor(background, dtype=torch.float64))
    ref = naive_statistics(density, rgb, t_starts, t_ends, far, background)
    for key, value in ref.items():
        torch.testing.assert_close(getattr(stats, key), value, rtol=1e-10, atol=1e-12, msg=key)
    torch.testing.assert_close(stats.depth_var_total, ref["depth_var_epistemic"] + ref["depth_var_spread"])
    # conventions: the empty ray sits at far with no variance; the half-empty ray mixes far and hits
    assert torch.equal(stats.depth_draws[0], far[0].expand(4))
    assert stats.depth_var_epistemic[0] == 0 and stats.depth_var_spread[0] == 0
    assert torch.equal(stats.depth_draws[1, :2], far[1].expand(2))
    assert stats.depth_var_epistemic[1] > 0
    # t_mids given as [R, 1, S] is the same
    again = vr.trajectory_statistics(weights, rgb, t_mids[:, None], far, torch.tensor(background, dtype=torch.float64))
    torch.testing.assert_close(again.colour_var, stats.colour_var, rtol=0, atol=0)


def test_trajectory_statistics_shapes_and_background_per_ray():
    density, rgb, t_starts, t_ends, far = random_rays(num_rays=3, num_draws=5, num_samples=4)
    weights = vr.weights_alpha(density, t_starts[:, None], t_ends[:, None])
    t_mids = 0.5 * (t_starts + t_ends)
    background = torch.rand(3, 3, dtype=torch.float64)
    stats = vr.trajectory_statistics(weights, rgb, t_mids, far, background)
    assert stats.colour_draws.shape == (3, 5, 3) and stats.depth_draws.shape == (3, 5)
    assert stats.colour_mean.shape == (3, 3) and stats.depth_var_total.shape == (3,)
    torch.testing.assert_close(stats.colour_draws[0], background[0].expand(5, 3))  # empty ray shows the background


def test_variance_is_stable_for_large_offsets():
    # draws at 1e4 +/- 1e-3: a one-pass E[x^2] - E[x]^2 in float32 would return noise or negatives
    depth = 1e4 + torch.tensor([[-1e-3, 1e-3, -1e-3, 1e-3]], dtype=torch.float64)
    stats = vr.statistics_from_draws(torch.zeros(1, 4, 3), depth.float(), torch.zeros(1, 4), torch.ones(1, 4))
    # float32 spacing at 1e4 is ~1e-3, so the draws are +/- one ulp: the variance is that ulp^2
    ulp = torch.finfo(torch.float32).eps * 8192
    assert 0.2 * ulp**2 < stats.depth_var_epistemic.item() < 2 * ulp**2


# ----------------------------------------------------------------------------- gradcheck


def _positive(shape, seed, scale=1.0):
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(*shape, generator=gen, dtype=torch.float64) * scale + 0.05).requires_grad_(True)


def test_gradcheck_weights():
    density = _positive((2, 5), 5, 2.0)
    edges = torch.cumsum(_positive((6,), 6).detach(), 0)
    t_starts = edges[:-1].clone().requires_grad_(True)
    t_ends = edges[1:].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(vr.weights_alpha, (density, t_starts, t_ends))
    assert torch.autograd.gradcheck(vr.weights_trapezoid, (density, t_starts, t_ends))


def test_gradcheck_depth_and_spread():
    weights = _positive((3, 5), 7, 0.3)
    t_mids = torch.cumsum(_positive((5,), 8).detach(), 0).requires_grad_(True)

    def depth_and_spread(w, t):
        depth = vr.expected_depth(w, t, 10.0)
        return depth, vr.termination_spread(w, t, depth)

    assert torch.autograd.gradcheck(depth_and_spread, (weights, t_mids))


def test_gradcheck_trajectory_statistics():
    weights = _positive((2, 3, 4), 9, 0.3)
    rgb = _positive((2, 3, 4, 3), 10)
    t_mids = torch.cumsum(_positive((2, 1, 4), 11).detach(), -1).requires_grad_(True)
    far = torch.tensor([8.0, 9.0], dtype=torch.float64)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)

    def all_outputs(w, c, t):
        s = vr.trajectory_statistics(w, c, t, far, background)
        return (s.colour_mean, s.colour_var, s.depth_mean, s.depth_var_epistemic, s.depth_var_spread,
                s.depth_var_total, s.opacity)

    assert torch.autograd.gradcheck(all_outputs, (weights, rgb, t_mids))


@pytest.mark.parametrize("shared", [False, True])
def test_logit_normal_colour_draws_match_drawn_colours_and_gradcheck(shared):
    """The fused composite of colours given by their logits equals ``accumulate`` of the drawn
    colours (float64 loop over rays, draws and samples), with its own backward checked by
    gradcheck; saturated logits (|mu| ~ 40) give finite gradients, as the sigmoid's."""
    gen = torch.Generator().manual_seed(12)
    R, K, S = 3, 4, 5
    weights = _positive((R, K, S), 13, 0.3)
    loc = torch.randn(R, S, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    scale = _positive((R, S, 3), 14)
    eps = torch.randn(R, K, 1 if shared else S, 3, generator=gen, dtype=torch.float64)

    def fused(w, mu, s):
        return vr.composite_logit_normal_draws(w, vr.LogitNormalColourDraws(mu, s, eps))

    expected = torch.zeros(R, K, 3, dtype=torch.float64)
    for r in range(R):
        for k in range(K):
            for i in range(S):
                e = eps[r, k, 0 if shared else i]
                expected[r, k] += weights[r, k, i] * torch.sigmoid(loc[r, i] + scale[r, i] * e)
    torch.testing.assert_close(fused(weights, loc, scale), expected.detach(), rtol=1e-12, atol=1e-14)
    assert torch.autograd.gradcheck(fused, (weights, loc, scale))
    # the same statistics as drawn colours through trajectory_statistics, and without autograd
    t_mids = torch.cumsum(_positive((R, 1, S), 15).detach(), -1)
    far = torch.full((R,), 9.0, dtype=torch.float64)
    drawn = torch.sigmoid(loc[:, None] + scale[:, None] * eps)
    by_logits = vr.trajectory_statistics(weights, vr.LogitNormalColourDraws(loc, scale, eps), t_mids, far, 0.5)
    torch.testing.assert_close(by_logits.colour_var, vr.trajectory_statistics(weights, drawn, t_mids, far, 0.5).colour_var)
    with torch.no_grad():
        torch.testing.assert_close(fused(weights, loc, scale), expected.detach(), rtol=1e-12, atol=1e-14)
    saturated = (40.0 * torch.sign(loc.detach())).requires_grad_(True)
    fused(weights, saturated, scale).sum().backward()
    assert torch.isfinite(saturated.grad).all() and torch.isfinite(scale.grad).all()


def test_gradcheck_packed_cumsum():
    x = _positive((2, 7), 12)
    ray_indices = torch.tensor([0, 0, 0, 2, 2, 2, 2])
    assert torch.autograd.gradcheck(lambda v: vr.exclusive_cumsum_packed(v, ray_indices, 3), (x,))


# ----------------------------------------------------------------------------- packed layout


def test_packed_cumsum_long_concatenation_float32():
    """1e5 samples over ~1000 rays, with an early ray of huge optical depth.

    A global cumsum minus per-ray offsets in float32 loses every digit after that ray (the
    offset is ~1e6, its ulp ~0.06); the segmented scan stays at float32 precision per ray.
    """
    rng = np.random.default_rng(13)
    lengths = rng.integers(0, 200, size=1000)
    lengths[3] = 50
    ray_indices_np = np.repeat(np.arange(1000), lengths)
    x_np = rng.random(ray_indices_np.size)
    x_np[np.flatnonzero(ray_indices_np == 3)] = 1e4 * rng.random(50) + 2e4  # ~1e6 optical depth in total
    assert x_np.size > 90_000
    reference = np.zeros_like(x_np)
    starts = np.concatenate([[0], np.cumsum(lengths)])
    for r in range(1000):
        seg = slice(starts[r], starts[r + 1])
        reference[seg] = np.cumsum(x_np[seg]) - x_np[seg]
        reference[starts[r]] = 0.0
    x = torch.from_numpy(x_np).float()
    ray_indices = torch.from_numpy(ray_indices_np)
    ours = vr.exclusive_cumsum_packed(x, ray_indices, 1000).double().numpy()
    relative = np.abs(ours - reference) / np.maximum(np.abs(reference), 1.0)
    assert relative.max() < 2e-6
    # the naive global-offset formulation fails on the same data (so this test can tell them apart)
    glob = torch.cumsum(x, 0) - x  # global exclusive cumsum
    first = torch.from_numpy(starts[:-1])[ray_indices]  # index of each sample's first sample in its ray
    naive = (glob - glob[first]).double().numpy()
    naive_relative = np.abs(naive - reference) / np.maximum(np.abs(reference), 1.0)
    assert naive_relative.max() > 100 * relative.max()


def ragged_layout(num_rays, num_draws, seed, dtype, max_len=7):
    """Random ragged samples (some rays empty, one ray of zero density) plus the equivalent dense layout.

    Dense padding uses zero-length intervals at the last midpoint (which neither rule weights).
    Returns (packed dict, dense interval dict [R, 1, S], function mapping packed per-sample
    [K, N, *C] tensors to dense [R, K, S, *C]).
    """
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.randint(0, max_len + 1, (num_rays,), generator=gen)
    lengths[0] = 0
    lengths[1] = max(int(lengths[1]), 3)
    num_samples = int(lengths.max())
    ray_indices = torch.repeat_interleave(torch.arange(num_rays), lengths)
    n = int(lengths.sum())
    starts = torch.cumsum(lengths, 0) - lengths
    position = torch.arange(n) - starts[ray_indices]
    unit = torch.sort(torch.rand(num_rays, num_samples + 1, generator=gen, dtype=dtype), -1).values
    edges = NEAR + unit * (FAR - NEAR)
    t_starts, t_ends = edges[ray_indices, position], edges[ray_indices, position + 1]
    density = torch.rand(num_draws, n, generator=gen, dtype=dtype) * 3
    density[:, ray_indices == 1] = 0.0  # ray 1: samples through empty space
    rgb = torch.rand(num_draws, n, 3, generator=gen, dtype=dtype)
    rays = torch.arange(num_rays)
    last_mid = 0.5 * (edges[rays, lengths] + edges[rays, (lengths - 1).clamp_min(0)])
    pad_t = torch.where(lengths > 0, last_mid, torch.full_like(last_mid, NEAR))

    def to_dense(values, fill):
        """[K, N, *C] -> [R, K, S, *C] with ``fill`` in the padding, differentiable w.r.t. values."""
        dense = torch.full((num_rays, num_draws, num_samples, *values.shape[2:]), fill, dtype=dtype)
        draws = torch.arange(num_draws)[None, :]  # [1, K]
        return dense.index_put((ray_indices[:, None], draws, position[:, None]), values.movedim(0, 1))

    dense_t_starts = pad_t[:, None].expand(num_rays, num_samples).clone()
    dense_t_ends = dense_t_starts.clone()
    dense_t_starts[ray_indices, position] = t_starts
    dense_t_ends[ray_indices, position] = t_ends
    packed = dict(ray_indices=ray_indices, t_starts=t_starts, t_ends=t_ends, density=density, rgb=rgb)
    dense = dict(t_starts=dense_t_starts[:, None], t_ends=dense_t_ends[:, None])
    return packed, dense, to_dense


@pytest.mark.parametrize("quadrature", vr.QUADRATURES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_packed_equals_dense_values_and_gradients(quadrature, dtype, seed):
    num_rays, num_draws = 9, 3
    packed, dense, to_dense = ragged_layout(num_rays, num_draws, seed, dtype)
    gen = torch.Generator().manual_seed(100 + seed)
    far = FAR + torch.rand(num_rays, generator=gen, dtype=dtype)
    background = torch.rand(3, generator=gen, dtype=dtype)
    ray_indices = packed["ray_indices"]

    def run(layout):
        density = packed["density"].clone().requires_grad_(True)
        rgb = packed["rgb"].clone().requires_grad_(True)
        if layout == "packed":
            w = vr.render_weights_packed(
                density, packed["t_starts"], packed["t_ends"], ray_indices, num_rays, quadrature
            )
            t_mids = 0.5 * (packed["t_starts"] + packed["t_ends"])
            stats = vr.trajectory_statistics_packed(w, rgb, t_mids, ray_indices, num_rays, far, background)
        else:
            w = vr.render_weights(to_dense(density, 7.0), dense["t_starts"], dense["t_ends"], quadrature)
            t_mids = 0.5 * (dense["t_starts"] + dense["t_ends"])
            stats = vr.trajectory_statistics(w, to_dense(rgb, 0.5), t_mids, far, background)
        outputs = [stats.colour_draws, stats.depth_draws, stats.spread_draws, stats.opacity_draws, stats.colour_var,
                   stats.depth_var_total]
        probe = torch.Generator().manual_seed(7)
        loss = sum((o * torch.rand(o.shape, generator=probe, dtype=dtype)).sum() for o in outputs)
        loss.backward()
        return outputs, density.grad, rgb.grad

    out_p, grad_density_p, grad_rgb_p = run("packed")
    out_d, grad_density_d, grad_rgb_d = run("dense")
    for a, b in zip(out_p, out_d):
        torch.testing.assert_close(a, b, **TOL[dtype])
    torch.testing.assert_close(grad_density_p, grad_density_d, **TOL[dtype])
    torch.testing.assert_close(grad_rgb_p, grad_rgb_d, **TOL[dtype])
    # conventions for empty rays hold in the packed layout
    assert torch.equal(out_p[1][0], far[0].expand(num_draws))  # ray 0 has no samples
    assert torch.equal(out_p[1][1], far[1].expand(num_draws))  # ray 1 crosses empty space
    torch.testing.assert_close(out_p[0][0], background.expand(num_draws, 3))


def test_packed_functions_on_zero_samples():
    ray_indices = torch.zeros(0, dtype=torch.long)
    density = torch.zeros(2, 0, requires_grad=True)
    for quadrature in vr.QUADRATURES:
        w = vr.render_weights_packed(density, torch.zeros(0), torch.zeros(0), ray_indices, 4, quadrature)
        assert w.shape == (2, 0)
        depth = vr.expected_depth_packed(w, torch.zeros(0), ray_indices, 4, FAR)
        assert torch.equal(depth, torch.full((2, 4), FAR))
        assert torch.equal(vr.termination_spread_packed(w, torch.zeros(0), depth, ray_indices, 4), torch.zeros(2, 4))
        assert torch.equal(vr.accumulate_packed(w, torch.zeros(2, 0, 3), ray_indices, 4), torch.zeros(2, 4, 3))
