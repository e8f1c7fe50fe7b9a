"""Capture points (spatial split), the sparse-depth likelihood and the depth recalibration,
against float64 loops, gradcheck, Monte-Carlo samples with known miscalibration and geometry."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import stats

from stochastic_fields.renderer import RenderOptions
from stochastic_fields.calibration import (CALIBRATION_LEVELS, ONE_SIGMA_LEVEL, QuantileCalibration, RunCalibration,
                                           apply_calibration, standardised_errors)
from stochastic_fields.capture_points import (CALIBRATE, FIT, SCORE, SPLIT_BLOCKS_PER_AXIS, split_points_by_blocks)
from stochastic_fields.constants import DEPTH_MIXTURE_WEIGHT_FLOOR
from stochastic_fields import metrics as M
from stochastic_fields.losses import termination_depth_nll


# ----------------------------------------------------------------------------- depth likelihood
def _mixture_loop(weights, t_mids, deltas, target, rho, r, k) -> float:
    """float64 loop of sum_i max(w_rki, floor) N(t*_r | t_ri, s_ri^2), s_ri^2 = delta_ri^2 / 12 + (rho t*_r)^2."""
    mix = 0.0
    for i in range(weights.shape[2]):
        var = deltas[r, i] ** 2 / 12 + (rho * target[r]) ** 2
        dens = math.exp(-0.5 * (target[r] - t_mids[r, i]) ** 2 / var) / math.sqrt(2 * math.pi * var)
        mix += max(weights[r, k, i], DEPTH_MIXTURE_WEIGHT_FLOOR) * dens
    return mix


def _nll_loop(weights, t_mids, deltas, target, rho) -> float:
    """float64 triple loop of -1/(R K) sum_{r,k} log sum_i max(w, floor) N(t* | t_i, s_i^2)."""
    R, K, _ = weights.shape
    return -sum(math.log(_mixture_loop(weights, t_mids, deltas, target, rho, r, k))
                for r in range(R) for k in range(K)) / (R * K)


def _random_rays(seed: int, R: int, K: int, S: int):
    """float64 rays of S random bins in [1, 11] (edges [R, S+1], t_mids and deltas [R, S]) and K random
    trajectories' weights [R, K, S] of opacity 0.9 each."""
    g = torch.Generator().manual_seed(seed)
    edges = torch.sort(torch.rand(R, S + 1, generator=g, dtype=torch.float64) * 10 + 1, dim=-1).values
    t_mids, deltas = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    w = torch.rand(R, K, S, generator=g, dtype=torch.float64)
    return edges, t_mids, deltas, w / w.sum(-1, keepdim=True) * 0.9


def test_termination_depth_nll_matches_float64_loop():
    R, K, S = 5, 3, 7
    edges, t_mids, deltas, w = _random_rays(0, R, K, S)
    w[0, 0] = 0.0  # an empty trajectory: only the floor remains
    target = t_mids[:, 3] + 0.3
    got = termination_depth_nll(w, t_mids, deltas, target, 0.01).item()
    ref = _nll_loop(w.numpy(), t_mids.numpy(), deltas.numpy(), target.numpy(), 0.01)
    assert got == pytest.approx(ref, rel=1e-10)


def test_termination_depth_nll_gradcheck_and_direction():
    g = torch.Generator().manual_seed(1)
    R, K, S = 3, 2, 6
    t_mids = torch.linspace(1, 6, S, dtype=torch.float64).expand(R, S).clone()
    deltas = torch.ones(R, S, dtype=torch.float64)
    w = (torch.rand(R, K, S, generator=g, dtype=torch.float64) * 0.15 + 0.01).requires_grad_()
    target = torch.tensor([2.1, 3.4, 5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda w: termination_depth_nll(w, t_mids, deltas, target, 0.02), (w,))
    # the gradient moves mass towards the sample nearest the surface: most negative there
    termination_depth_nll(w, t_mids, deltas, target, 0.02).backward()
    nearest = (t_mids - target[:, None]).abs().argmin(-1)
    assert torch.equal(w.grad.argmin(-1), nearest[:, None].expand(R, K))


def test_termination_depth_nll_hard_cases_finite():
    S = 64
    t_mids = torch.linspace(1, 100, S).expand(4, S).clone()
    deltas = torch.full((4, S), 99 / S)
    w = torch.zeros(4, 2, S)
    w[1, :, 10] = 1.0  # opaque wall far from the target
    w[2, :, :] = 1e-30  # denormal weights
    w[3, :, 20] = 1.0  # wall at the target
    w.requires_grad_()
    target = torch.tensor([50.0, 80.0, 1e-3, float(t_mids[0, 20])])
    loss = termination_depth_nll(w, t_mids, deltas, target, 0.01)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(w.grad).all()
    per_ray = [termination_depth_nll(w[r:r + 1].detach(), t_mids[r:r + 1], deltas[r:r + 1], target[r:r + 1], 0.01)
               for r in range(4)]
    assert per_ray[3] < per_ray[0]  # the wall at the surface explains it better than no mass at all


def _predictive_nll_loop(weights, t_mids, deltas, target, rho) -> float:
    """float64 loop of -1/R sum_r log (1/K sum_k sum_i max(w, floor) N(t* | t_i, s_i^2))."""
    R, K, _ = weights.shape
    return -sum(math.log(sum(_mixture_loop(weights, t_mids, deltas, target, rho, r, k) for k in range(K)) / K)
                for r in range(R)) / R


def test_predictive_depth_nll_matches_float64_loop_and_jensen():
    R, K, S = 5, 4, 7
    edges, t_mids, deltas, w = _random_rays(3, R, K, S)
    w[0, 0] = 0.0  # an empty trajectory: the others still explain the point
    target = t_mids[:, 3] + 0.3
    got = termination_depth_nll(w, t_mids, deltas, target, 0.01, "predictive").item()
    ref = _predictive_nll_loop(w.numpy(), t_mids.numpy(), deltas.numpy(), target.numpy(), 0.01)
    assert got == pytest.approx(ref, rel=1e-10)
    expected = termination_depth_nll(w, t_mids, deltas, target, 0.01, "expected").item()
    assert got < expected  # Jensen: log of the mean >= mean of the logs, strictly for unequal trajectories
    # equal for K = 1 and for trajectories that agree
    one = w[:, :1]
    assert termination_depth_nll(one, t_mids, deltas, target, 0.01, "predictive").item() == pytest.approx(
        termination_depth_nll(one, t_mids, deltas, target, 0.01, "expected").item(), rel=1e-12)
    same = w[:, :1].expand(R, K, S)
    assert termination_depth_nll(same, t_mids, deltas, target, 0.01, "predictive").item() == pytest.approx(
        expected_one := termination_depth_nll(one, t_mids, deltas, target, 0.01).item(), rel=1e-12)
    assert np.isfinite(expected_one)


def _robust_nll_loop(weights, t_mids, deltas, target, rho, eps, form) -> float:
    """float64 loop of the outlier-share likelihood: p'_rk = (1 - eps) p_rk + eps / L_r,
    L_r = sum_i delta_ri; 'expected' -1/(R K) sum log p'_rk, 'predictive' -1/R sum log mean_k p'_rk."""
    R, K, _ = weights.shape
    total = 0.0
    for r in range(R):
        span = float(sum(deltas[r]))
        per_k = [(1 - eps) * _mixture_loop(weights, t_mids, deltas, target, rho, r, k) + eps / span for k in range(K)]
        if form == "predictive":
            total -= math.log(sum(per_k) / K)
        else:
            total -= sum(math.log(p) for p in per_k) / K
    return total / R


@pytest.mark.parametrize("form", ["expected", "predictive"])
def test_depth_nll_outlier_share_matches_float64_loop(form):
    """loss.depth_outlier_share: the Gaussian mixture mixed with a uniform density over the ray's sampled
    range, against a float64 loop; 0 gives today's value bit for bit."""
    R, K, S = 6, 3, 9
    edges, t_mids, deltas, w = _random_rays(5, R, K, S)
    w[0, 0] = 0.0  # an empty trajectory
    target = t_mids[:, 4] + 0.2
    target[1] = edges[1, -1] + 40.0  # a point far behind every sample: an outlier
    for eps in (0.01, 0.2):
        got = termination_depth_nll(w, t_mids, deltas, target, 0.03, form, eps).item()
        ref = _robust_nll_loop(w.numpy(), t_mids.numpy(), deltas.numpy(), target.numpy(), 0.03, eps, form)
        assert got == pytest.approx(ref, rel=1e-10)
    assert torch.equal(termination_depth_nll(w, t_mids, deltas, target, 0.03, form, 0.0),
                       termination_depth_nll(w, t_mids, deltas, target, 0.03, form))


def test_depth_nll_outlier_share_bounds_an_outliers_pull():
    """A point far from the rendered surface: with eps > 0 its loss is at most -log(eps / L) and its
    gradient on the weights is far smaller than the Gaussian's; a point at the surface keeps almost
    all of its pull."""
    S = 32
    t_mids = torch.linspace(1, 10, S, dtype=torch.float64).expand(2, S).clone()
    deltas = torch.full((2, S), 9 / (S - 1), dtype=torch.float64)
    base = torch.full((2, 1, S), 1e-4, dtype=torch.float64)
    base[:, 0, 5] = 0.9  # an opaque surface near t = 2.3
    target = torch.tensor([float(t_mids[0, 5]), 9.5], dtype=torch.float64)  # at the surface; far behind it

    def pull(eps: float):
        w = base.clone().requires_grad_()
        per_ray = [termination_depth_nll(w[r:r + 1], t_mids[r:r + 1], deltas[r:r + 1], target[r:r + 1], 0.03,
                                         "expected", eps) for r in range(2)]
        grads = [torch.autograd.grad(loss, w, retain_graph=True)[0][r].abs().sum().item()
                 for r, loss in enumerate(per_ray)]
        return [loss.item() for loss in per_ray], grads

    (near0, far0), (gnear0, gfar0) = pull(0.0)
    (near1, far1), (gnear1, gfar1) = pull(0.05)
    span = float(deltas[1].sum())
    assert far1 <= -math.log(0.05 / span) + 1e-12 < far0
    # d(-log p')/dw_i = (1 - eps) N_i / p' = [(1 - eps) p / p'] d(-log p)/dw_i: the pull scales by the
    # share of the point's likelihood the surface still explains
    share_far, share_near = (0.95 * math.exp(-x0) / math.exp(-x1) for x0, x1 in ((far0, far1), (near0, near1)))
    assert gfar1 == pytest.approx(share_far * gfar0, rel=1e-9) and share_far < 0.1
    assert gnear1 == pytest.approx(share_near * gnear0, rel=1e-9) and share_near > 0.94
    with pytest.raises(ValueError, match="outlier share"):
        termination_depth_nll(base, t_mids, deltas, target, 0.03, "expected", 1.0)


def test_depth_outlier_share_option_range():
    from stochastic_fields.config import ExperimentConfig, set_dotted, validate_experiment

    cfg = ExperimentConfig()
    assert cfg.loss.depth_outlier_share == 0.0
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="depth_outlier_share"):
            set_dotted(cfg, "loss.depth_outlier_share", bad)
            validate_experiment(cfg)


def test_predictive_depth_nll_hand_value_two_trajectories():
    """One ray, two samples, K = 2: trajectory 0 puts all its mass on the sample at the point, 1 on
    the far one. With bins of width sqrt(12) (s^2 = 1 + (rho t*)^2, rho tiny) and N(0) = 1/sqrt(2 pi),
    N(5) = e^-12.5 / sqrt(2 pi): predictive = -log((N(0) + N(5)) / 2), expected = -(log N(0) + log N(5)) / 2."""
    t_mids = torch.tensor([[10.0, 15.0]], dtype=torch.float64)
    deltas = torch.full((1, 2), math.sqrt(12.0), dtype=torch.float64)
    w = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]], dtype=torch.float64)
    target = torch.tensor([10.0], dtype=torch.float64)
    rho = 1e-9
    n0 = 1.0 / math.sqrt(2 * math.pi)
    n5 = math.exp(-12.5) / math.sqrt(2 * math.pi)
    floor = DEPTH_MIXTURE_WEIGHT_FLOOR
    p0, p1 = n0 + floor * n5, n5 + floor * n0
    assert termination_depth_nll(w, t_mids, deltas, target, rho, "predictive").item() == pytest.approx(
        -math.log((p0 + p1) / 2), rel=1e-9)
    assert termination_depth_nll(w, t_mids, deltas, target, rho, "expected").item() == pytest.approx(
        -(math.log(p0) + math.log(p1)) / 2, rel=1e-9)


def test_predictive_depth_nll_gradcheck_and_credit():
    """Gradients flow (gradcheck), and the predictive form credits the trajectory that explains the
    point: the far trajectory's pull towards the surface is weaker than under the expected form."""
    g = torch.Generator().manual_seed(4)
    R, K, S = 3, 3, 6
    t_mids = torch.linspace(1, 6, S, dtype=torch.float64).expand(R, S).clone()
    deltas = torch.ones(R, S, dtype=torch.float64)
    w = (torch.rand(R, K, S, generator=g, dtype=torch.float64) * 0.15 + 0.01).requires_grad_()
    target = torch.tensor([2.1, 3.4, 5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda w: termination_depth_nll(w, t_mids, deltas, target, 0.02, "predictive"), (w,))
    good = torch.zeros(1, 2, S, dtype=torch.float64)
    good[0, 0, 1], good[0, 1, 5], good[0, 1, 1] = 0.9, 0.85, 0.05  # trajectory 0 at the point (t = 2), 1 mostly far
    grads = {}
    for form in ("expected", "predictive"):
        x = good.clone().requires_grad_()
        termination_depth_nll(x, t_mids[:1], deltas[:1], torch.tensor([2.0], dtype=torch.float64), 0.02, form).backward()
        grads[form] = x.grad[0, 1, 1].item()  # the far trajectory's gradient at the surface sample
    # by hand (the far sample's density at t* = 2 is e^-8 of the near one's, below the tolerance):
    # expected -1/(R K) / w_1 = -1 / (2 x 0.05); predictive -(1/K) / ((0.9 + 0.05) / K) = -1 / 0.95
    assert grads["expected"] == pytest.approx(-10.0, rel=1e-6)
    assert grads["predictive"] == pytest.approx(-1.0 / 0.95, rel=1e-6)


def test_depth_nll_unknown_form_refused():
    w = torch.full((1, 1, 2), 0.5)
    with pytest.raises(ValueError, match="'mode'"):
        termination_depth_nll(w, torch.tensor([[1.0, 2.0]]), torch.ones(1, 2), torch.tensor([1.5]), 0.01, "mode")


# ----------------------------------------------------------------------------- spatial split
def test_split_points_by_blocks_roles_blocks_and_shares():
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(20000, 3)) * [3.0, 1.0, 10.0] + [0, 0, 40]
    roles = split_points_by_blocks(xyz)
    assert roles.dtype == np.int8 and set(np.unique(roles)) == {FIT, CALIBRATE, SCORE}
    shares = np.bincount(roles, minlength=3) / len(roles)
    assert shares == pytest.approx([0.4, 0.2, 0.4], abs=0.08)  # whole blocks: close to, not exactly, the shares
    # every block belongs wholly to one role (recompute the block of each point)
    n = SPLIT_BLOCKS_PER_AXIS
    lo, hi = np.percentile(xyz, (1, 99), axis=0)
    cell = np.clip(np.floor((xyz - lo) / (hi - lo) * n), 0, n - 1).astype(int)
    key = (cell[:, 0] * n + cell[:, 1]) * n + cell[:, 2]
    for k in np.unique(key):
        assert len(np.unique(roles[key == k])) == 1
    assert np.array_equal(roles, split_points_by_blocks(xyz))  # deterministic
    assert not np.array_equal(roles, split_points_by_blocks(xyz, seed=1))


@pytest.mark.parametrize("xyz, kwargs, message", [
    (np.zeros((0, 3)), {}, "P > 0"),
    (np.zeros((5, 2)), {}, "shape"),
    (np.array([[0.0, 0.0, np.nan]]), {}, "NaN"),
    (np.zeros((5, 3)), {"fractions": (0.5, 0.5, 0.5)}, "summing to 1"),
    (np.zeros((5, 3)), {"fractions": (1.2, -0.2, 0.0)}, "non-negative"),
    (np.zeros((5, 3)), {"blocks_per_axis": 0}, "blocks_per_axis"),
])
def test_split_points_by_blocks_rejects_bad_input(xyz, kwargs, message):
    with pytest.raises(ValueError, match=message):
        split_points_by_blocks(xyz, **kwargs)


def _hand_block_key(xyz: np.ndarray, reference: np.ndarray) -> list[tuple[int, int, int]]:
    """The split's block of each point, by hand: the 1st-99th percentile box of ``reference`` cut
    into SPLIT_BLOCKS_PER_AXIS^3 cells, points outside clamped into the border cells."""
    n = SPLIT_BLOCKS_PER_AXIS
    lo, hi = np.percentile(reference, (1, 99), axis=0)
    out = []
    for p in xyz:
        out.append(tuple(min(max(int(math.floor((p[a] - lo[a]) / (hi[a] - lo[a]) * n)), 0), n - 1) for a in range(3)))
    return out


def test_block_roles_by_hand_and_for_blocks_without_points():
    from stochastic_fields.capture_points import NO_ROLE, CapturePoints, block_roles

    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 10, size=(3000, 3))
    xyz = xyz[(xyz[:, 0] < 4) | (xyz[:, 0] > 7)]  # a slab of space with no capture point
    cap = CapturePoints(xyz, split_points_by_blocks(xyz), "sfm")
    assert np.array_equal(block_roles(xyz, cap), cap.roles)
    query = np.concatenate([rng.uniform(-5, 15, size=(400, 3)), [[5.5, 5.0, 5.0], [1e6, -1e6, 0.0]]])
    role_of = dict(zip(_hand_block_key(xyz, xyz), cap.roles.tolist()))
    expected = np.array([role_of.get(k, NO_ROLE) for k in _hand_block_key(query, xyz)])
    got = block_roles(query, cap)
    assert got.dtype == np.int8 and np.array_equal(got, expected)
    assert got[-2] == NO_ROLE  # inside the empty slab
    assert (got == NO_ROLE).any() and set(np.unique(got)) - {NO_ROLE} == {FIT, CALIBRATE, SCORE}


def test_dense_depth_score_mask_keeps_the_score_blocks_surfaces(tiny_scene):
    """Dense scoring mirrors the sparse one: a pixel of the exact depth map scores only when its
    surface point (back-projected by hand, float64) lies in a block of the SCORE role; the stand-in
    points a training view gave fall on pixels the mask agrees with."""
    from stochastic_fields.cameras import camera_to_world, intrinsics_3x3
    from stochastic_fields.capture_points import dense_depth_score_mask, load_capture_points
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene, split_every=5)
    cap = load_capture_points(ds)
    role_of = dict(zip(_hand_block_key(cap.xyz, cap.xyz), cap.roles.tolist()))
    for v in (ds.test_indices[0], ds.train_indices[0]):
        depth = ds.depths[v].double().numpy()
        mask = dense_depth_score_mask(ds, cap, v)
        assert mask.shape == depth.shape and 0 < mask.sum() < (depth > 0).sum()
        K = intrinsics_3x3(ds.cameras)[v].double().numpy()
        c2w = camera_to_world(ds.cameras)[v].double().numpy()
        rows, cols = np.nonzero(depth > 0)
        cam = np.linalg.solve(K, np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))])) * depth[rows, cols]
        world = (c2w[:3, :3] @ cam).T + c2w[:3, 3]
        expected = np.zeros_like(mask)
        expected[rows, cols] = [role_of.get(k) == SCORE for k in _hand_block_key(world, cap.xyz)]
        assert np.array_equal(mask, expected)


# ----------------------------------------------------------------------------- recalibration
def _coverage(err, std, levels, scale=None):
    return M.calibration_curve(err, np.zeros_like(err), std, levels=levels, interval_scale=scale).coverage


def test_quantile_calibration_recovers_a_known_scale():
    """Errors twice as large as the predicted std: s(p) = 2 at every level, and the recalibrated
    intervals hold their level on fresh samples (within 3 binomial standard errors)."""
    rng = np.random.default_rng(0)
    std = rng.uniform(0.5, 3.0, size=40000)
    err = rng.normal(size=std.size) * 2.0 * std
    cal = QuantileCalibration.fit(standardised_errors(err, np.zeros_like(err), std), quantity="depth_std")
    assert cal.std_scale == pytest.approx(2.0, rel=0.03)
    assert cal.scales[5:-5] == pytest.approx(np.full(cal.scales[5:-5].shape, 2.0), rel=0.05)
    std2 = rng.uniform(0.5, 3.0, size=40000)
    err2 = rng.normal(size=std2.size) * 2.0 * std2
    levels = np.array([ONE_SIGMA_LEVEL, 0.9, 0.95])
    raw = _coverage(err2, std2, levels)
    fixed = _coverage(err2, std2 * cal.std_scale, levels, cal.relative_scale)
    tol = 3 * np.sqrt(levels * (1 - levels) / err2.size) + 0.005
    assert (raw < levels - 0.2).all()  # overconfident before
    assert np.abs(fixed - levels) == pytest.approx(np.zeros(3), abs=tol.max())


def test_quantile_calibration_fixes_heavy_tails_level_by_level():
    """Laplace errors with a Gaussian-looking std: one scale cannot fit 68% and 95% at once, the
    level-dependent map does (the synthetic scene's 42% / 97% pattern)."""
    rng = np.random.default_rng(1)
    std = np.ones(60000)
    err = rng.laplace(scale=1.0, size=std.size)
    cal = QuantileCalibration.fit(np.abs(err), quantity="depth_std")
    # exact: Q_p(|Laplace|) = -ln(1 - p)
    for p in (0.5, ONE_SIGMA_LEVEL, 0.95):
        assert float(cal.scale_at(p)) == pytest.approx(-math.log(1 - p) / stats.norm.ppf((1 + p) / 2), rel=0.03)
    err2 = rng.laplace(scale=1.0, size=std.size)
    levels = np.array([ONE_SIGMA_LEVEL, 0.95])
    single = _coverage(err2, std * cal.std_scale, levels)
    mapped = _coverage(err2, std * cal.std_scale, levels, cal.relative_scale)
    assert abs(single[1] - 0.95) > 0.015  # a single scale misses the 95% level
    assert mapped == pytest.approx(levels, abs=0.01)


def test_quantile_calibration_round_trip_and_validation():
    cal = QuantileCalibration.fit(np.linspace(0.01, 3.0, 500), quantity="depth_std", source="test")
    back = QuantileCalibration.from_dict(cal.to_dict())
    assert np.array_equal(back.scales, cal.scales) and back.num_samples == 500 and back.source == "test"
    assert np.array_equal(back.levels, CALIBRATION_LEVELS)
    with pytest.raises(ValueError, match="at least"):
        QuantileCalibration.fit(np.ones(10), quantity="depth_std")
    with pytest.raises(ValueError, match="finite"):
        QuantileCalibration.fit(np.r_[np.ones(60), np.nan], quantity="depth_std")
    bad = cal.to_dict()
    bad["scales"] = [-1.0] * len(bad["levels"])
    with pytest.raises(ValueError, match="calibration.json: depth"):
        RunCalibration.from_dict({"depth": bad}, where="calibration.json")
    with pytest.raises(ValueError, match="malformed"):
        QuantileCalibration.from_dict({"levels": [0.5]}, where="x")


def test_apply_calibration_keeps_the_raw_std():
    cal = RunCalibration(depth=QuantileCalibration("depth_std", CALIBRATION_LEVELS,
                                                   np.full(CALIBRATION_LEVELS.shape, 2.5), 1000))
    products = {"depth_std": np.array([[1.0, 2.0]], np.float32), "depth_mean": np.ones((1, 2), np.float32)}
    out = apply_calibration(products, cal)
    assert np.array_equal(out["depth_std_raw"], products["depth_std"])
    assert out["depth_std"] == pytest.approx(np.array([[2.5, 5.0]]))
    assert apply_calibration(products, None) == products


# ----------------------------------------------------------------------------- capture-point rays
def test_training_depth_rays_hit_the_stand_in_points(tiny_scene):
    """The synthetic scene's stand-in capture points: the FIT rays at t* land on the points'
    world positions (pixel-centre back-projection), and every ray comes from a training view."""
    from stochastic_fields.capture_points import load_capture_points, sparse_depth_for_role
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import TrainingDepth

    ds = load_dataset(tiny_scene, split_every=5)
    pts = load_capture_points(ds)
    assert pts.source == "synthetic" and pts.counts()["fit"] > 0
    per_view = sparse_depth_for_role(ds, pts, ds.train_indices, FIT)
    xyz = np.concatenate([pts.xyz[sd.point_index] for sd in per_view.values()])
    td = TrainingDepth.from_dataset(ds, torch.device("cpu"))
    hit = (td.rays.origins + td.target_t[:, None] * td.rays.directions).double().numpy()
    assert len(hit) == len(xyz)
    np.testing.assert_allclose(hit, xyz, atol=2e-4 * np.abs(xyz).max())
    assert all(v in ds.train_indices for v in per_view)


def test_calibration_views_lie_halfway_between_training_neighbours(tiny_scene):
    """Each virtual camera: centre halfway along the arc around the scene centre (direction of the
    chord's midpoint, the pair's mean distance), rotation halfway (equal geodesic angle to both),
    the pair's intrinsics and widest bounds; pairs are nearest training neighbours."""
    from scipy.spatial.transform import Rotation

    from stochastic_fields.calibration import calibration_views
    from stochastic_fields.cameras import camera_centres, intrinsics_3x3
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene, split_every=5)
    cams, near, far, pairs = calibration_views(ds)
    centres = camera_centres(ds.cameras).double()
    R_all = ds.cameras.extrinsics.double()[:, :3, :3].numpy()
    for p, (i, j) in enumerate(pairs):
        assert i in ds.train_indices and j in ds.train_indices and i != j
        others = [v for v in ds.train_indices if v != i]
        dist = {v: float((centres[v] - centres[i]).norm()) for v in others}
        dist_j = {v: float((centres[v] - centres[j]).norm()) for v in ds.train_indices if v != j}
        assert min(dist, key=dist.get) == j or min(dist_j, key=dist_j.get) == i
        c = camera_centres(cams).double()[p]
        o = ds.aabb.double().mean(0)
        mid = 0.5 * (centres[i] + centres[j]) - o
        radius = 0.5 * ((centres[i] - o).norm() + (centres[j] - o).norm())
        torch.testing.assert_close(c, o + mid / mid.norm() * radius, atol=1e-4, rtol=0)
        R = cams.extrinsics.double()[p, :3, :3].numpy()
        a_i = (Rotation.from_matrix(R) * Rotation.from_matrix(R_all[i]).inv()).magnitude()
        a_j = (Rotation.from_matrix(R) * Rotation.from_matrix(R_all[j]).inv()).magnitude()
        a_ij = (Rotation.from_matrix(R_all[j]) * Rotation.from_matrix(R_all[i]).inv()).magnitude()
        assert a_i == pytest.approx(a_ij / 2, abs=1e-5) and a_j == pytest.approx(a_ij / 2, abs=1e-5)
        torch.testing.assert_close(intrinsics_3x3(cams)[p], intrinsics_3x3(ds.cameras)[i])
        assert float(near[p]) == pytest.approx(min(float(ds.near[i]), float(ds.near[j])))
        assert float(far[p]) == pytest.approx(max(float(ds.far[i]), float(ds.far[j])))


def test_calibration_view_bounds_widest_or_interpolated(tiny_scene):
    """Bounds of each virtual camera from its pair's, by hand: the nearer near and farther far
    ("widest"), or both at the view's fraction ("interpolated"); an unknown choice is refused."""
    from stochastic_fields.calibration import calibration_views
    from stochastic_fields.data import load_dataset

    ds = load_dataset(tiny_scene, split_every=5)
    ds.near = torch.linspace(1.0, 2.0, ds.num_views)
    ds.far = torch.linspace(9.0, 5.0, ds.num_views)
    _, near, far, pairs = calibration_views(ds, fractions=(0.25, 0.5), bounds="widest")
    _, near_i, far_i, pairs_i = calibration_views(ds, fractions=(0.25, 0.5), bounds="interpolated")
    assert pairs_i == pairs and len(pairs) == 2 * len(set(pairs))
    for p, (i, j) in enumerate(pairs):
        f = (0.25, 0.5)[p % 2]
        ni, nj, fi, fj = (float(x) for x in (ds.near[i], ds.near[j], ds.far[i], ds.far[j]))
        assert float(near[p]) == pytest.approx(min(ni, nj)) and float(far[p]) == pytest.approx(max(fi, fj))
        assert float(near_i[p]) == pytest.approx((1 - f) * ni + f * nj)
        assert float(far_i[p]) == pytest.approx((1 - f) * fi + f * fj)
    with pytest.raises(ValueError, match="bounds must be one of"):
        calibration_views(ds, bounds="narrow")


class _MeshDepthModel(torch.nn.Module):
    """Renders the exact mesh depth plus an error ``error_factor`` times larger than the std it reports,
    and (``abs_std`` > 0) an independent error of std ``abs_std`` that the reported std leaves out; the
    reported std is ``rel_std`` times the depth, times exp(U(-std_spread, std_spread)) per ray."""

    def __init__(self, mesh_path, error_factor: float, rel_std: float = 0.02, abs_std: float = 0.0,
                 std_spread: float = 0.0):
        super().__init__()
        import open3d as o3d
        import trimesh

        self.anchor = torch.nn.Parameter(torch.zeros(1))
        mesh = trimesh.load(str(mesh_path), force="mesh", process=False)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        self.error_factor, self.rel_std, self.abs_std, self.std_spread = error_factor, rel_std, abs_std, std_spread

    def default_render_options(self):
        return RenderOptions(num_draws=1)

    def render_options(self, **changes):
        return self.default_render_options().with_changes(**changes)

    def render_view(self, rays, options=None, *, generator=None):
        import open3d as o3d

        o, d = rays.origins.reshape(-1, 3).numpy(), rays.directions.reshape(-1, 3).numpy()
        t = self.scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], -1).astype(np.float32)))["t_hit"].numpy()
        hit = np.isfinite(t)
        t = np.where(hit, t, 1.0).astype(np.float64)
        rng = np.random.default_rng(0)
        normal = rng.normal(size=t.shape)
        s = self.rel_std * t * np.exp(rng.uniform(-self.std_spread, self.std_spread, size=t.shape))
        err = normal * np.hypot(s * self.error_factor, self.abs_std)
        f = lambda a: torch.from_numpy(np.asarray(a, np.float32)).reshape(rays.shape)  # noqa: E731
        return {"depth_mean": f(t + err), "depth_var_total": f(s ** 2), "opacity": f(hit.astype(np.float64)),
                "z_scale": rays.z_scale, "num_draws": torch.ones(rays.shape)}


def test_fit_depth_calibration_recovers_the_error_factor(tmp_path):
    """End to end (capture points, calibration views, projection, rendering at their pixels, camera-z):
    a model whose errors are 3x its reported std gets s(p) ~ 3 at the central levels."""
    from stochastic_fields.calibration import fit_depth_calibration
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "scene", num_views=20, width=192, height=144, seed=0)
    ds = load_dataset(scene, split_every=5)
    cal = fit_depth_calibration(_MeshDepthModel(scene / "scene.ply", 3.0), ds)
    assert cal.num_samples >= 150
    for p in (0.3, 0.5, ONE_SIGMA_LEVEL):
        assert float(cal.scale_at(p)) == pytest.approx(3.0, rel=0.2)
    exact = fit_depth_calibration(_MeshDepthModel(scene / "scene.ply", 1.0), ds)
    assert exact.std_scale == pytest.approx(1.0, rel=0.2)


def test_held_out_calibration_fits_on_calibrate_and_score_points_and_eval_says_so(tmp_path):
    """--points held-out fits on the CALIBRATE and SCORE roles (more samples, the factor kept), is
    stored in calibration.json, and makes eval warn and note that its depth scores saw the map's
    data; old files without "points" read as "calibrate"; unknown values are refused."""
    from stochastic_fields.calibration import (fit_depth_calibration, load_run_calibration, save_run_calibration)
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene
    from stochastic_fields.evaluation import SCORE_POINTS_SEEN, _conventions

    scene = make_synthetic_scene(tmp_path / "scene", num_views=20, width=192, height=144, seed=0)
    ds = load_dataset(scene, split_every=5)
    model = _MeshDepthModel(scene / "scene.ply", 3.0)
    only = fit_depth_calibration(model, ds)
    held = fit_depth_calibration(model, ds, points="held-out")
    assert held.num_samples > 2 * only.num_samples
    # a few points render on another surface (occluded from the virtual view) with a large |z|
    # whatever the factor; below them the quantiles scale with the error factor exactly
    exact = fit_depth_calibration(_MeshDepthModel(scene / "scene.ply", 1.0), ds, points="held-out")
    assert held.std_scale / exact.std_scale == pytest.approx(3.0, rel=0.05)
    assert "calibrate and score roles" in held.source and "calibrate role" in only.source
    with pytest.raises(ValueError, match="calibration points"):
        fit_depth_calibration(model, ds, points="score")

    save_run_calibration(tmp_path, RunCalibration(depth=held, points="held-out"))
    loaded = load_run_calibration(tmp_path)
    assert loaded.points == "held-out" and loaded.saw_score_points
    assert _conventions("sparse", loaded)["depth_calibration_independence"] == SCORE_POINTS_SEEN
    assert "depth_calibration_independence" not in _conventions("sparse", RunCalibration(depth=only))
    old = RunCalibration.from_dict({"depth": only.to_dict()}, where="old")
    assert old.points == "calibrate" and not old.saw_score_points
    with pytest.raises(ValueError, match="points must be one of"):
        RunCalibration.from_dict({"depth": None, "points": "all"}, where="bad")


def test_export_applies_the_run_calibration(tmp_path, tiny_scene):
    """Export with a recalibration: depth_std = s(0.683) x raw (raw kept), the 90% band uses
    s(0.9) / s(0.683) on top, and the summary records the map."""
    from stochastic_fields.data import load_dataset
    from stochastic_fields.products.export import ExportOptions, dataset_view_specs, export_views

    scales = np.linspace(1.5, 4.0, CALIBRATION_LEVELS.size)
    cal = RunCalibration(depth=QuantileCalibration("depth_std", CALIBRATION_LEVELS, scales, 500))
    ds = load_dataset(tiny_scene)
    model = _MeshDepthModel(tiny_scene / "scene.ply", 1.0)
    model.render_view = _with_draws(model.render_view)
    opts = ExportOptions(formats=("npz",), progress=False)
    summary = export_views(model, dataset_view_specs(ds, [1]), tmp_path / "cal", opts, calibration=cal)
    assert summary["depth_calibration"]["depth"]["std_scale"] == pytest.approx(cal.depth.std_scale)
    with np.load(next((tmp_path / "cal" / "views").glob("*.npz"))) as f:
        raw, std, mean = f["depth_std_raw"], f["depth_std"], f["depth_mean"]
        valid = f["valid"] & (raw > 0)
        np.testing.assert_allclose(std[valid], raw[valid] * cal.depth.std_scale, rtol=1e-5)
        half = (f["depth_band90_upper"] - mean)[valid]
        expected = stats.norm.ppf(0.95) * std[valid] * cal.depth.relative_scale(0.9)
        np.testing.assert_allclose(half, expected, rtol=1e-4, atol=1e-6)


def _with_draws(render):
    """Add the per-draw depths and colour maps that export reads (draws: mean +- std, K = 4)."""
    def wrapped(rays, options=None, *, generator=None):
        maps = render(rays, options, generator=generator)
        s = maps["depth_var_total"].sqrt()
        signs = torch.tensor([-1.0, 1.0, -1.0, 1.0])
        maps["depth_draws"] = maps["depth_mean"][..., None] + s[..., None] * signs
        maps["depth_var_epistemic"] = maps["depth_var_total"]
        maps["depth_var_spread"] = torch.zeros_like(maps["depth_var_total"])
        maps["colour_mean"] = torch.full((*rays.shape, 3), 0.5)
        maps["colour_var"] = torch.zeros((*rays.shape, 3))
        return maps
    return wrapped


@pytest.mark.parametrize("shared_noise, quadrature", [(False, "alpha"), (True, "alpha"), (False, "trapezoid")])
def test_trajectory_weights_are_the_renders_weights_without_colours(shared_noise, quadrature):
    """The depth likelihood's weights-only draws: for the same density noise they equal the full
    render's weights exactly (colour noise drawn or not), and from a generator they draw [R, K, S]
    (shared: constant along the ray) normals, so the depth term needs no colour draws."""
    from stochastic_fields.fields.base import FieldParams
    from stochastic_fields.rays import RayBundle
    from stochastic_fields.renderer import RenderSettings, render_samples, trajectory_weights
    from stochastic_fields.samplers import sample_along_rays

    R, S, K = 5, 12, 4
    g = torch.Generator().manual_seed(0)
    rays = RayBundle(torch.zeros(R, 3), torch.nn.functional.normalize(torch.randn(R, 3, generator=g), dim=-1),
                     torch.full((R,), 0.5), torch.full((R,), 4.0), torch.ones(R))
    samples = sample_along_rays(rays, S)
    params = FieldParams(torch.randn(R, S, generator=g), torch.rand(R, S, generator=g) + 0.1,
                         torch.randn(R, S, 3, generator=g), torch.rand(R, S, 3, generator=g) + 0.1)
    st = RenderSettings(num_samples=S, shared_noise=shared_noise, quadrature=quadrature)
    eps_a = torch.randn(R, K, 1 if shared_noise else S, generator=g)
    eps_c = torch.randn(R, K, 1 if shared_noise else S, 3, generator=g)
    full = render_samples(params, samples, st, num_draws=K, noise=(eps_a, eps_c), colour_estimator="draws")
    w = trajectory_weights(params.density_loc, params.density_scale, samples, st, num_draws=K, noise=eps_a)
    assert torch.equal(w, full.extras["weights"])
    drawn = trajectory_weights(params.density_loc, params.density_scale, samples, st, num_draws=K,
                               generator=torch.Generator().manual_seed(3))
    again = trajectory_weights(params.density_loc, params.density_scale, samples, st, num_draws=K,
                               noise=torch.randn(R, K, 1 if shared_noise else S, generator=torch.Generator().manual_seed(3)))
    assert drawn.shape == (R, K, S) and torch.equal(drawn, again)


@pytest.mark.parametrize("depth_draws,form,trains_scale", [(0, "expected", True), (3, "expected", True),
                                                         (3, "predictive", True), (3, "expected", False)])
def test_depth_term_reads_density_only_and_matches_the_full_field_pass(tiny_scene, depth_draws, form, trains_scale):
    """The model's depth term evaluates only the density (``field.density_params``: no colour
    decoder, a 2-channel backward on the grid) and gives the loss and grid gradients of the full
    field evaluation with the same draws, float64; it draws ``loss.depth_draws`` trajectories
    (0: ``train.train_draws``). Without ``loss.depth_trains_scale`` the gradients are those of
    draws made with stopgrad(scale): the same loss, other gradients."""
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.fields.row_gather import row_gradient
    from stochastic_fields.losses import termination_depth_nll
    from stochastic_fields.models.registry import build_model
    from stochastic_fields.renderer import trajectory_weights
    from stochastic_fields.samplers import sample_along_rays
    from stochastic_fields.rays import RayBundle
    from stochastic_fields.trainer import TrainingDepth

    dataset = load_dataset(tiny_scene, split_every=5)
    cfg = preset("tiny")
    cfg.loss.depth_draws = depth_draws
    cfg.loss.depth_likelihood = form
    cfg.loss.depth_trains_scale = trains_scale
    model = build_model(cfg, dataset).double()
    assert model.train_draws != 3
    with torch.no_grad():  # a field with structure, not the uniform initial fog
        for table in model.field.levels:
            table.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    depth = TrainingDepth.from_dataset(dataset, torch.device("cpu"))
    rays, target = depth.batch(16, torch.Generator().manual_seed(0))
    rays = RayBundle(*(t.double() for t in dataclasses.astuple(rays)))
    target = target.double()

    def grads():
        out = [row_gradient(t).dense(t).clone() for t in model.field.levels]
        for t in model.field.levels:
            row_gradient(t).zero()
        return out

    got = model._depth_nll(rays, target, generator=torch.Generator().manual_seed(5))
    got.backward()
    got_grads = grads()

    g = torch.Generator().manual_seed(5)
    st = model.render_settings
    samples = sample_along_rays(rays, st.num_samples, spacing=st.spacing, stratified=True, generator=g)
    params = model.field(samples.positions.reshape(-1, 3), samples.directions.reshape(-1, 3))
    params = params.reshape(*samples.t_starts.shape)
    noise = torch.randn(len(rays), depth_draws or model.train_draws, st.num_samples, generator=g, dtype=torch.float64)

    def reference(scale):
        w = trajectory_weights(params.density_loc, scale, samples, st, num_draws=noise.shape[1], noise=noise,
                               density_offsets=params.density_offsets)  # the default's heads, each draw its own
        return termination_depth_nll(w, samples.t_mids, samples.deltas, target, model.loss_config.depth_relative_std, form)

    assert noise.shape[1] == (depth_draws or cfg.train.train_draws)
    ref = reference(params.density_scale if trains_scale else params.density_scale.detach())
    ref.backward(retain_graph=True)
    ref_grads = grads()
    assert torch.isfinite(got) and got.item() == pytest.approx(ref.item(), rel=1e-12)
    for a, b in zip(got_grads, ref_grads):
        assert b.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-14)
    reference(params.density_scale if not trains_scale else params.density_scale.detach()).backward()
    assert any((a - b).abs().max() > 1e-8 for a, b in zip(got_grads, grads()))  # the scale's share differs
    assert model.field.decoder[0].weight.grad is None  # the colour decoder never ran


def test_depth_weight_falls_linearly_to_its_final_factor():
    """loss.depth_final_factor: lambda (1 - (1 - f) p), p clamped to [0, 1]; by hand."""
    from stochastic_fields.losses import depth_weight
    assert depth_weight(2.0, 0.25, 0.0) == 2.0
    assert depth_weight(2.0, 0.25, 0.5) == pytest.approx(2.0 * (1 - 0.75 * 0.5))
    assert depth_weight(2.0, 0.25, 1.0) == pytest.approx(0.5)
    assert depth_weight(2.0, 0.25, 3.0) == pytest.approx(0.5) and depth_weight(2.0, 0.25, -1.0) == 2.0
    assert depth_weight(1.0, 1.0, 0.7) == 1.0


def test_depth_term_weight_follows_the_training_progress(tiny_scene):
    """The model's loss adds depth_weight(lambda, f, model.training_progress) times the depth NLL:
    two losses on the same draws at progress 0 and 0.5 differ by exactly (w(0.5) - w(0)) * nll."""
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.losses import depth_weight
    from stochastic_fields.models.registry import build_model
    from stochastic_fields.rays import RayBundle
    from stochastic_fields.trainer import TrainingDepth

    dataset = load_dataset(tiny_scene, split_every=5)
    cfg = preset("tiny")
    cfg.loss.lambda_depth, cfg.loss.depth_final_factor = 2.0, 0.2
    model = build_model(cfg, dataset).double()
    depth = TrainingDepth.from_dataset(dataset, torch.device("cpu"))
    d_rays, d_t = depth.batch(16, torch.Generator().manual_seed(0))
    d_rays = RayBundle(*(t.double() for t in dataclasses.astuple(d_rays)))
    rays, colours = d_rays, torch.full((len(d_rays), 3), 0.5, dtype=torch.float64)

    def loss_at(progress):
        model.training_progress = progress
        loss, logs = model.training_loss(rays, colours, step=0, generator=torch.Generator().manual_seed(3),
                                         depth=(d_rays, d_t.double()))
        return loss.item(), logs

    l0, logs0 = loss_at(0.0)
    l5, logs5 = loss_at(0.5)
    assert logs0["depth_weight"] == 2.0 and logs5["depth_weight"] == pytest.approx(depth_weight(2.0, 0.2, 0.5))
    assert logs0["depth_nll"] == logs5["depth_nll"]
    assert l5 - l0 == pytest.approx((logs5["depth_weight"] - 2.0) * logs0["depth_nll"], rel=1e-9)


def test_trainer_sets_the_progress_the_depth_weight_follows(tiny_scene, tmp_path):
    """The trainer sets the model's progress (step / iterations) before each step: with
    loss.depth_final_factor 0 the logged weight at steps 10 and 20 of 20 is 1 - 9/20 and 1 - 19/20
    (the record after step s holds step s - 1's loss), and a trained model reads progress 0."""
    import json

    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import LOG_NAME, Trainer

    cfg = preset("tiny")
    cfg.train.iterations, cfg.loss.lambda_depth, cfg.loss.depth_final_factor = 20, 1.0, 0.0
    model = Trainer(cfg, tmp_path, load_dataset(tiny_scene, split_every=5)).train(progress=False)
    records = {r["step"]: r for r in map(json.loads, (tmp_path / LOG_NAME).read_text().splitlines())}
    assert records[10]["depth_weight"] == pytest.approx(1 - 9 / 20)
    assert records[20]["depth_weight"] == pytest.approx(1 - 19 / 20)
    assert model.training_progress == 0.0
