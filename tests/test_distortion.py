"""Distortion regulariser: O(S) prefix-sum form against the float64 double loop of its definition,
packed = dense (skipped samples carry no weight), gradcheck, hand values, and the S-NeRF loss term."""

from __future__ import annotations

import pytest
import torch

from stochastic_fields.distortion import distortion_loss, distortion_loss_packed, normalised_coordinate
from stochastic_fields.losses import LossConfig
from stochastic_fields.samplers import bin_edges


def naive(w, s0, s1):
    """sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s1_i - s0_i), one ray, by loops."""
    m = 0.5 * (s0 + s1)
    total = 0.0
    for i in range(len(w)):
        for j in range(len(w)):
            total += float(w[i] * w[j] * abs(m[i] - m[j]))
        total += float(w[i] ** 2 * (s1[i] - s0[i])) / 3.0
    return total


def random_rays(R=5, S=17, K=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    edges = torch.sort(torch.rand(R, S + 1, generator=g, dtype=torch.float64), dim=-1).values
    w = torch.rand(R, K, S, generator=g, dtype=torch.float64) ** 4
    w = w / w.sum(-1, keepdim=True) * torch.rand(R, K, 1, generator=g, dtype=torch.float64)  # opacity <= 1
    return w, edges[:, :-1], edges[:, 1:]


def test_matches_double_loop():
    w, s0, s1 = random_rays()
    got = distortion_loss(w, s0[:, None], s1[:, None])
    for r in range(w.shape[0]):
        for k in range(w.shape[1]):
            assert got[r, k].item() == pytest.approx(naive(w[r, k], s0[r], s1[r]), rel=1e-12, abs=1e-15)


def test_hand_values():
    s0, s1 = torch.tensor([0.0, 0.5], dtype=torch.float64), torch.tensor([0.5, 1.0], dtype=torch.float64)
    # all weight in one interval of width 0.5: only the own-interval term, 1/3 * 1 * 0.5
    assert distortion_loss(torch.tensor([1.0, 0.0], dtype=torch.float64), s0, s1).item() == pytest.approx(1 / 6)
    # half and half, midpoints 0.5 apart: 2 * 0.25 * 0.5 + 1/3 * 2 * 0.25 * 0.5
    assert distortion_loss(torch.tensor([0.5, 0.5], dtype=torch.float64), s0, s1).item() == pytest.approx(
        0.25 + 1 / 12)
    assert distortion_loss(torch.zeros(2, dtype=torch.float64), s0, s1).item() == 0.0  # empty ray


def test_packed_equals_dense_when_skipped_samples_have_no_weight():
    w, s0, s1 = random_rays(R=4, S=9, K=2, seed=1)
    keep = torch.rand(4, 9, generator=torch.Generator().manual_seed(2)) > 0.4
    keep[2] = False  # one ray with nothing kept
    w = w * keep[:, None, :]
    ri, si = torch.nonzero(keep, as_tuple=True)
    packed = distortion_loss_packed(w[ri, :, si].T, s0[ri, si], s1[ri, si], ri, 4)  # [K, R]
    torch.testing.assert_close(packed, distortion_loss(w, s0[:, None], s1[:, None]).T, rtol=1e-12, atol=1e-15)
    assert torch.all(packed[:, 2] == 0)


def test_gradcheck():
    w, s0, s1 = random_rays(R=2, S=6, K=2, seed=3)
    w.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: distortion_loss(x, s0[:, None], s1[:, None]), (w,))
    ri = torch.arange(2).repeat_interleave(6)
    wp = w.detach().permute(1, 0, 2).reshape(2, -1).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: distortion_loss_packed(x, s0.reshape(-1), s1.reshape(-1), ri, 2), (wp,))


@pytest.mark.parametrize("spacing", ["linear", "disparity"])
def test_normalised_coordinate_is_uniform_in_the_sampling_coordinate(spacing):
    near, far = torch.tensor([2.0, 0.5], dtype=torch.float64), torch.tensor([6.0, 100.0], dtype=torch.float64)
    edges = bin_edges(near, far, 8, spacing)
    s = normalised_coordinate(edges, near[:, None], far[:, None], spacing)
    torch.testing.assert_close(s, torch.linspace(0, 1, 9, dtype=torch.float64).expand(2, 9))
    with pytest.raises(ValueError, match="spacing"):
        normalised_coordinate(edges, near[:, None], far[:, None], "log")


def test_snerf_loss_adds_the_weighted_term_dense_and_packed(monkeypatch):
    from test_packed_render import box_rays, make_models

    from stochastic_fields import renderer

    monkeypatch.setattr(renderer, "PACK_MIN_SKIPPED_FRACTION", 0.0)  # pack whatever the grid skips

    lam = 0.3
    dense, skip, field = make_models(LossConfig(kl="none"))
    dense_d, skip_d, _ = make_models(LossConfig(kl="none", lambda_distortion=lam))
    for m in (dense_d, skip_d):
        m.field = field
    rays = box_rays()
    target = torch.rand(len(rays), 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    skip.training_loss(rays, target, step=0)
    skip.after_step(0)  # occupancy update: the skipping model packs
    skip_d.occupancy.load_state_dict(skip.occupancy.state_dict())
    skip_d.interval_scale.copy_(skip.interval_scale)
    for base, reg in ((dense, dense_d), (skip, skip_d)):
        l0, _ = base.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(7))
        l1, logs = reg.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(7))
        assert logs["distortion"] > 0
        torch.testing.assert_close(l1, l0 + lam * logs["distortion"], rtol=1e-12, atol=1e-12)
    _, logs_dense = dense_d.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(7))
    _, logs_skip = skip_d.training_loss(rays, target, step=0, generator=torch.Generator().manual_seed(7))
    assert logs_skip["field_evals_per_ray"] < logs_dense["field_evals_per_ray"]
    # shared noise along rays: packed and dense draws coincide, and skipped samples carry no weight
    assert logs_skip["distortion"] == pytest.approx(logs_dense["distortion"], rel=1e-9)
