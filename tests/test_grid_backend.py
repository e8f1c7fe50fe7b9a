"""The grid backend's gather-based interpolation and its row-sparse optimiser, against torch's
own grid_sample, dense autograd and torch.optim.SparseAdam."""

from __future__ import annotations

import contextlib

import pytest
import torch
import torch.nn.functional as F
from conftest import grid_sample_read

from stochastic_fields.fields.grid import GridField, trilinear_corners
from stochastic_fields import row_kernels
from stochastic_fields.fields.row_gather import gather_rows, row_gradient
from stochastic_fields.optim import FieldOptimizer, RowSparseAdam
from stochastic_fields.scene_region import SceneRegion

SHAPE = (5, 4, 6)  # X, Y, Z: anisotropic so that a swapped axis fails


def _cube_region() -> SceneRegion:
    return SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def _unit_points(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=dtype) * 2.4 - 1.2  # some outside: border padding
    u[:4] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0]], dtype=dtype)
    return u


def _grid_sample_reference(table: torch.Tensor, unit: torch.Tensor) -> torch.Tensor:
    return grid_sample_read(table, SHAPE, unit)


def test_trilinear_corners_match_grid_sample_values():
    X, Y, Z = SHAPE
    table = torch.randn(X * Y * Z, 3, dtype=torch.float64)
    unit = _unit_points(200)
    idx, w = trilinear_corners(unit, SHAPE)
    assert idx.min() >= 0 and idx.max() < X * Y * Z
    torch.testing.assert_close(w.sum(-1), torch.ones(200, dtype=torch.float64))
    torch.testing.assert_close(gather_rows(table, idx, w), _grid_sample_reference(table, unit), rtol=1e-12, atol=1e-12)


def test_trilinear_corner_cell_is_exact():
    X, Y, Z = SHAPE
    table = torch.arange(X * Y * Z, dtype=torch.float64)[:, None]
    # cell (x, y, z) = (4, 0, 5) sits at unit (1, -1, 1): row (5 * Y + 0) * X + 4
    out = gather_rows(table, *trilinear_corners(torch.tensor([[1.0, -1.0, 1.0]], dtype=torch.float64), SHAPE))
    assert out.item() == (5 * Y + 0) * X + 4


def test_row_gradient_equals_dense_autograd_gradient():
    X, Y, Z = SHAPE
    table = torch.randn(X * Y * Z, 4, dtype=torch.float64, requires_grad=True)
    unit = _unit_points(300, seed=1)
    coeff = torch.randn(300, 4, dtype=torch.float64)
    idx, w = trilinear_corners(unit, SHAPE)
    extra = torch.randint(0, X * Y * Z, (50,))
    loss = (gather_rows(table, idx, w) * coeff).sum() + (gather_rows(table, extra) ** 2).sum()  # two uses, duplicates
    loss.backward()
    assert table.grad is None
    dense = table.detach().clone().requires_grad_(True)
    ref = (_grid_sample_reference(dense, unit) * coeff).sum() + (dense[extra] ** 2).sum()
    ref.backward()
    torch.testing.assert_close(row_gradient(table).dense(table), dense.grad, rtol=1e-12, atol=1e-12)
    rows, grad = row_gradient(table).take(table)
    torch.testing.assert_close(grad, dense.grad[rows])
    assert set(rows.tolist()) >= set(dense.grad.abs().sum(-1).nonzero().squeeze(1).tolist())
    assert row_gradient(table).dense(table).abs().max() == 0  # take() resets


def test_channel_slice_gathers_and_back_propagates_only_those_channels():
    """A channel-sliced gather (the depth likelihood's density-only read) equals the full gather's
    slice, and its gradient equals dense autograd's on the slice, zero elsewhere, on the same
    touched rows (so the row-sparse optimiser steps the same rows either way)."""
    X, Y, Z = SHAPE
    table = torch.randn(X * Y * Z, 5, dtype=torch.float64, requires_grad=True)
    unit = _unit_points(200, seed=4)
    idx, w = trilinear_corners(unit, SHAPE)
    coeff = torch.randn(200, 2, dtype=torch.float64)
    out = gather_rows(table, idx, w, channels=slice(1, 3))
    torch.testing.assert_close(out, gather_rows(table, idx, w)[:, 1:3], rtol=1e-12, atol=1e-12)
    (out * coeff).sum().backward()
    dense = table.detach().clone().requires_grad_(True)
    (_grid_sample_reference(dense, unit)[:, 1:3] * coeff).sum().backward()
    got = row_gradient(table).dense(table)
    torch.testing.assert_close(got, dense.grad, rtol=1e-12, atol=1e-12)
    assert got[:, [0, 3, 4]].abs().max() == 0
    assert torch.equal(row_gradient(table).touched_rows(table).nonzero().squeeze(1), idx.unique())
    w_req = w.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda ww: gather_rows(table.detach(), idx[:20], ww, channels=slice(1, 3)),
                                    (w_req[:20],))
    grad_table = table.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda ww: gather_rows(grad_table, idx[:20], ww, channels=slice(1, 3)),
                                    (w_req[:20],))


def test_gather_rows_weight_gradient_gradcheck():
    table = torch.randn(7, 2, dtype=torch.float64)
    idx = torch.randint(0, 7, (5, 3))
    w = torch.rand(5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda ww: gather_rows(table, idx, ww), (w,))


@pytest.mark.parametrize("beta2", [0.999, 0.99])
@pytest.mark.parametrize("steps", [1, 5])
def test_row_sparse_adam_matches_torch_sparse_adam(steps, beta2):
    torch.manual_seed(0)
    N, C = 30, 3
    ours = torch.nn.Parameter(torch.randn(N, C, dtype=torch.float64))
    ref = torch.nn.Parameter(ours.detach().clone())
    opt = RowSparseAdam([ours], lr=0.05, betas=(0.9, beta2), eps=1e-15)
    ref_opt = torch.optim.SparseAdam([ref], lr=0.05, betas=(0.9, beta2), eps=1e-15)
    for s in range(steps):
        idx = torch.randint(0, N // 2, (20,)) + s  # duplicates; untouched rows exist
        coeff = torch.randn(20, C, dtype=torch.float64)
        opt.zero_grad()
        (gather_rows(ours, idx) * coeff).sum().backward()
        opt.step()
        ref_opt.zero_grad()
        (F.embedding(idx, ref, sparse=True) * coeff).sum().backward()
        ref_opt.step()
    torch.testing.assert_close(ours.detach(), ref.detach(), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(opt.state[ours]["exp_avg_sq"], ref_opt.state[ref]["exp_avg_sq"], rtol=1e-12, atol=1e-15)


def test_field_optimizer_schedule_and_state_round_trip():
    field = GridField(_cube_region(), (8, 8, 8), num_levels=2, decoder_width=8)
    groups = [{"params": list(field.levels.parameters()), "lr": 0.1, "sparse": True},
              {"params": list(field.decoder.parameters()), "lr": 0.01}]
    assert [g["betas"] for g in FieldOptimizer(groups, total_steps=10, final_factor=0.1, beta2=0.99).param_groups] \
        == [(0.9, 0.99)] * 2  # train.adam_beta2 reaches the dense Adam and the grid's lazy Adam
    opt = FieldOptimizer(groups, total_steps=10, final_factor=0.1)
    assert [g["betas"] for g in opt.param_groups] == [(0.9, 0.999)] * 2
    opt.set_step(5)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([0.01 * 0.1 ** 0.5, 0.1 * 0.1 ** 0.5])
    pts = torch.rand(64, 3) * 2 - 1
    dirs = F.normalize(torch.randn(64, 3), dim=-1)
    p = field(pts, dirs)
    (p.density_loc.sum() + p.rgb_loc.sum()).backward()
    before = field.levels[1].detach().clone()
    opt.step()
    changed = (field.levels[1].detach() != before).any(-1)
    assert 0 < int(changed.sum()) < before.shape[0]  # only the touched cells move
    state = opt.state_dict()
    opt2 = FieldOptimizer(groups, total_steps=10, final_factor=0.1)
    opt2.load_state_dict(state)
    with pytest.raises(ValueError, match="parameter groups"):
        FieldOptimizer(groups[1:], total_steps=10, final_factor=0.1).load_state_dict(state)


def test_grid_field_loads_channels_first_checkpoints():
    field = GridField(_cube_region(), (6, 5, 4), num_levels=2)
    old_state = {k: v.clone() for k, v in field.state_dict().items()}
    for i, (X, Y, Z) in enumerate(field.level_shapes):
        t = old_state[f"levels.{i}"]
        old_state[f"levels.{i}"] = t.T.reshape(1, -1, Z, Y, X).contiguous()  # the layout grid_sample used
    other = GridField(_cube_region(), (6, 5, 4), num_levels=2)
    other.load_state_dict(old_state)
    for a, b in zip(field.levels, other.levels):
        torch.testing.assert_close(a, b)


def test_trainer_resumes_a_checkpoint_with_an_old_optimiser_state(tiny_scene, tmp_path):
    from conftest import tiny_cpu_config
    from stochastic_fields.checkpoint import load_checkpoint, save_checkpoint
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    cfg = tiny_cpu_config(iterations=4)
    dataset = load_dataset(tiny_scene)
    Trainer(cfg, tmp_path, dataset).train(progress=False, max_steps=2)
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    state["optimizer"] = {"state": {}, "param_groups": []}  # torch.optim.Adam's layout, as older runs saved it
    save_checkpoint(tmp_path / "checkpoint.pt", state)
    trainer = Trainer(cfg, tmp_path, dataset)
    with pytest.warns(UserWarning, match="optimiser state not restored"):
        trainer.train(progress=False)
    assert trainer.step == 4


def test_density_params_with_and_without_gradients_agree():
    field = GridField(_cube_region(), (7, 6, 5), num_levels=2)
    with torch.no_grad():
        for level in field.levels:
            level.normal_()
    pts = torch.rand(50, 3) * 2 - 1
    with torch.no_grad():
        loc0, scale0 = field.density_params(pts)
    loc1, scale1 = field.density_params(pts)
    torch.testing.assert_close(loc0, loc1)
    torch.testing.assert_close(scale0, scale1)
    full = field(pts, torch.nn.functional.normalize(torch.randn(50, 3), dim=-1))
    torch.testing.assert_close(loc1, full.density_loc)


def test_row_sparse_adam_accepts_ordinary_sparse_and_dense_gradients():
    torch.manual_seed(1)
    N, C = 12, 2
    for sparse in (True, False):
        ours = torch.nn.Parameter(torch.randn(N, C, dtype=torch.float64))
        ref = torch.nn.Parameter(ours.detach().clone())
        opt = RowSparseAdam([ours], lr=0.1)
        ref_opt = torch.optim.SparseAdam([ref], lr=0.1, eps=1e-15) if sparse else torch.optim.Adam([ref], lr=0.1, eps=1e-15)
        idx = torch.tensor([0, 3, 3, 7])
        coeff = torch.randn(4, C, dtype=torch.float64)
        for p, o in ((ours, opt), (ref, ref_opt)):
            o.zero_grad()
            (F.embedding(idx, p, sparse=sparse) * coeff).sum().backward()
            o.step()
        torch.testing.assert_close(ours.detach(), ref.detach(), rtol=1e-12, atol=1e-12)


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [None, slice(1, 3)])
def test_compiled_row_scatter_matches_torch_ops(dtype, channels):
    g = torch.Generator().manual_seed(3)
    N, C, M, J = 40, 4, 300, 8
    table = torch.zeros(N, C, dtype=dtype, requires_grad=True)
    idx = torch.randint(0, N // 2, (M, J), generator=g)  # many duplicates; rows N/2.. never touched
    w = torch.rand(M, J, generator=g, dtype=dtype)
    width = C if channels is None else channels.stop - channels.start
    coeff = torch.randn(M, width, generator=g, dtype=dtype)

    def accumulated():
        row_gradient(table).zero()
        (gather_rows(table, idx, w, channels=channels) * coeff).sum().backward()
        return row_gradient(table).dense(table), row_gradient(table).touched_rows(table)

    compiled, touched = accumulated()
    with row_kernels.torch_ops_only():
        reference, touched_ref = accumulated()
    exact = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(compiled, reference, **exact)
    assert torch.equal(touched, touched_ref) and touched[N // 2:].sum() == 0 and touched[: N // 2].any()
    if channels is not None:
        assert compiled[:, : channels.start].abs().sum() == 0 and compiled[:, channels.stop:].abs().sum() == 0


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("blocks", [2, 3, 7])
def test_row_blocks_equal_the_serial_loops_bit_for_bit(monkeypatch, dtype, blocks):
    """The loops split over threads (rows in contiguous blocks, one per thread) add the same terms in
    the same order per row as the serial loops: scatter and Adam agree exactly, with duplicate rows,
    rows on the block edges, untouched rows and a channel offset."""
    g = torch.Generator().manual_seed(11)
    N, C, M, J = 23, 5, 400, 8
    idx = torch.randint(0, N, (M, J), generator=g)
    idx[:4] = torch.tensor([N * b // blocks for b in range(blocks)] * J)[:J]  # first rows of blocks
    idx[idx == 5] = 6  # row 5 untouched
    w = torch.rand(M, J, generator=g, dtype=dtype)
    grad = torch.randn(M, 3, generator=g, dtype=dtype)
    x0 = torch.randn(N, C, generator=g, dtype=dtype)
    m1_0, m2_0 = torch.randn(N, C, generator=g, dtype=dtype), torch.rand(N, C, generator=g, dtype=dtype)

    def run(threads: int):
        monkeypatch.setattr(row_kernels, "row_blocks", lambda: threads)
        acc, touched = torch.zeros(N, C, dtype=dtype), torch.zeros(N, dtype=torch.bool)
        x, m1, m2 = x0.clone(), m1_0.clone(), m2_0.clone()
        for step in (1, 2):
            row_kernels.scatter_weighted_rows(acc, touched, idx, w, grad, first_channel=2)
            summed, marked = acc.clone(), touched.clone()
            row_kernels.adam_touched_rows(x, m1, m2, acc, touched, lr=0.03, betas=(0.9, 0.99), eps=1e-8, step=step)
        assert not touched.any() and not acc.any()
        return summed, marked, x, m1, m2

    serial, split = run(1), run(blocks)
    for a, b in zip(serial, split):
        assert torch.equal(a, b)
    assert not serial[1][5] and torch.equal(serial[2][5], x0[5])


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("blocks", [1, 3])
@pytest.mark.parametrize("pattern", ["first", "last", "ends", "sparse", "dense", "block_edges"])
def test_prefetch_hints_change_no_value(monkeypatch, blocks, pattern):
    """The loops with their prefetch hints (rows asked for ahead: module doc of row_kernels) give the
    loops' values without them bit for bit, and update exactly the touched rows, whatever the touched
    rows' layout: only the first or the last row, both ends, isolated rows far apart, long runs, and
    rows around the blocks' edges (the Adam loop's look-ahead stops at its block's end)."""
    monkeypatch.setattr(row_kernels, "row_blocks", lambda: blocks)
    N, C = 300, 5
    g = torch.Generator().manual_seed(5)
    rows = {"first": [0], "last": [N - 1], "ends": [0, 1, N - 2, N - 1], "sparse": list(range(7, N, 37)),
            "dense": list(range(40, 260)),
            "block_edges": [r + d for b in range(1, 3) for r in [N * b // 3] for d in (-2, -1, 0, 1)]}[pattern]
    rows = torch.tensor(rows)
    idx = rows[torch.randint(0, len(rows), (200, 8), generator=g)]
    w = torch.rand(200, 8, generator=g)
    grad = torch.randn(200, 3, generator=g)
    x0, m1_0, m2_0 = torch.randn(N, C, generator=g), torch.randn(N, C, generator=g), torch.rand(N, C, generator=g)

    def run():
        acc, touched = torch.zeros(N, C), torch.zeros(N, dtype=torch.bool)
        x, m1, m2 = x0.clone(), m1_0.clone(), m2_0.clone()
        row_kernels.scatter_weighted_rows(acc, touched, idx, w, grad, first_channel=1)
        summed, marked = acc.clone(), touched.clone()
        row_kernels.adam_touched_rows(x, m1, m2, acc, touched, lr=0.03, betas=(0.9, 0.99), eps=1e-8, step=1)
        assert not touched.any() and not acc.any()
        return summed, marked, x, m1, m2

    hinted = run()
    with row_kernels.without_prefetch():
        plain = run()
    for a, b in zip(hinted, plain):
        assert torch.equal(a, b)
    marked, x = hinted[1], hinted[2]
    assert torch.equal(marked.nonzero().squeeze(1), torch.unique(rows))
    assert torch.equal(x[~marked], x0[~marked]) and (x[marked] != x0[marked]).any(dim=1).all()


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("blocks", [1, 3])
def test_zero_gradient_samples_mark_their_rows_and_change_no_value(monkeypatch, dtype, blocks):
    """A sample whose gradient row is all 0 (+0 or -0) adds nothing but still marks its rows: the
    scatter and two Adam steps give the values of the loop that adds its zeros bit for bit, the rows
    only such samples read are stepped (their momentum), and a NaN row is carried like any other."""
    monkeypatch.setattr(row_kernels, "row_blocks", lambda: blocks)
    g = torch.Generator().manual_seed(13)
    N, C, M, J = 60, 4, 300, 8
    idx = torch.randint(0, N, (M, J), generator=g)
    w = torch.rand(M, J, generator=g, dtype=dtype)
    grad = torch.randn(M, C, generator=g, dtype=dtype)
    silent = torch.rand(M, generator=g) < 0.6
    grad[silent] = 0.0
    grad[silent.nonzero()[::2, 0]] = -0.0
    idx[silent] = idx[silent] % 20  # rows 0..19 read mostly by silent samples
    idx[~silent] = 20 + idx[~silent] % (N - 20)
    idx[silent.nonzero()[0, 0]] = torch.arange(J)  # rows 0..7 read by a silent sample at least
    x0, m1_0, m2_0 = torch.randn(N, C, generator=g, dtype=dtype), torch.randn(N, C, generator=g, dtype=dtype), \
        torch.rand(N, C, generator=g, dtype=dtype)

    def run(coeff):
        acc, touched = torch.zeros(N, C, dtype=dtype), torch.zeros(N, dtype=torch.bool)
        x, m1, m2 = x0.clone(), m1_0.clone(), m2_0.clone()
        for step in (1, 2):
            row_kernels.scatter_weighted_rows(acc, touched, idx, w, coeff)
            summed, marked = acc.clone(), touched.clone()
            row_kernels.adam_touched_rows(x, m1, m2, acc, touched, lr=0.03, betas=(0.9, 0.99), eps=1e-8, step=step)
        return summed, marked, x, m1, m2

    skipped = run(grad)
    with row_kernels.adding_zero_rows():
        added = run(grad)
    for a, b in zip(skipped, added):
        assert torch.equal(a, b)
    summed, marked, x = skipped[:3]
    assert marked[:8].all() and torch.equal(marked.nonzero().squeeze(1), torch.unique(idx))
    reference = torch.zeros(N, C, dtype=torch.float64)  # float64 loop over the samples that carry a gradient
    for m in (~silent).nonzero().squeeze(1).tolist():
        for j in range(J):
            reference[idx[m, j]] += float(w[m, j]) * grad[m].double()
    torch.testing.assert_close(summed.double(), reference, rtol=1e-5, atol=1e-5)
    assert (x[:8] != x0[:8]).any(dim=1).all()  # stepped by their momentum although no gradient arrived
    nan_grad = grad.clone()
    nan_grad[silent.nonzero()[1, 0], 0] = float("nan")
    assert run(nan_grad)[0].isnan().any()


@pytest.mark.skipif(row_kernels.numba is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_adam_matches_torch_ops_and_is_used(monkeypatch, dtype):
    """Five steps of RowSparseAdam with the compiled loop against the same steps as torch ops: same
    table and moments (float rounding), untouched rows unchanged, and the loop really ran."""
    calls = []
    compiled_adam = row_kernels.adam_touched_rows
    monkeypatch.setattr(row_kernels, "adam_touched_rows", lambda *a, **k: calls.append(1) or compiled_adam(*a, **k))

    def train(torch_ops: bool):
        g = torch.Generator().manual_seed(0)
        table = torch.nn.Parameter(torch.randn(30, 3, generator=g, dtype=dtype))
        opt = RowSparseAdam([table], lr=0.05, eps=1e-8)
        with row_kernels.torch_ops_only() if torch_ops else contextlib.nullcontext():
            for s in range(5):
                idx = torch.randint(0, 15, (20, 8), generator=g) + s
                w = torch.rand(20, 8, generator=g, dtype=dtype)
                opt.zero_grad()
                (gather_rows(table, idx, w) * torch.randn(20, 3, generator=g, dtype=dtype)).sum().backward()
                opt.step()
        return table.detach(), opt.state[table]

    ours, state = train(torch_ops=False)
    assert len(calls) == 5
    ref, ref_state = train(torch_ops=True)
    assert len(calls) == 5  # the torch ops ran the second time
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=2e-6, atol=2e-6)
    torch.testing.assert_close(ours, ref, **tol)
    for key in ("exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(state[key], ref_state[key], **tol)
    assert float(state["step"]) == float(ref_state["step"]) == 5.0
    start = torch.randn(30, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    assert torch.equal(ours[20:], start[20:])  # rows 20.. were never read: untouched


@pytest.mark.parametrize("torch_ops", [False, True])
def test_zero_grad_clears_only_what_no_step_took(torch_ops):
    """A gradient accumulated and then dropped by zero_grad (a step that did not run) never reaches
    a later step: the table equals the one trained without those backward passes. After a step the
    buffers are clear, so zero_grad has nothing to write."""
    def train(skipped_backward: bool):
        g = torch.Generator().manual_seed(3)
        table = torch.nn.Parameter(torch.randn(40, 3, generator=g, dtype=torch.float64))
        opt, acc = RowSparseAdam([table], lr=0.05, eps=1e-8), row_gradient(table)
        with row_kernels.torch_ops_only() if torch_ops else contextlib.nullcontext():
            for s in range(6):
                idx = torch.randint(0, 40, (25, 8), generator=g)
                w, up = torch.rand(25, 8, generator=g, dtype=torch.float64), torch.randn(25, 3, generator=g, dtype=torch.float64)
                opt.zero_grad()
                runs = s % 3 != 1
                if runs or skipped_backward:
                    (gather_rows(table, idx, w) * up).sum().backward()
                if not runs:
                    assert acc._dirty == skipped_backward
                    continue
                opt.step()
                assert not acc._dirty and acc.dense(table).abs().max() == 0 and not acc.touched_rows(table).any()
        return table.detach()

    assert torch.equal(train(skipped_backward=True), train(skipped_backward=False))


def test_row_kernels_refuse_what_they_cannot_run():
    a = torch.zeros(4, 3)
    assert not row_kernels.available(a, a.double())  # mixed float dtypes
    assert not row_kernels.available(a.T)  # not contiguous
    assert not row_kernels.available(a.half())
    if row_kernels.numba is not None:
        assert row_kernels.available(a, torch.zeros(4, dtype=torch.bool), torch.zeros(2, 8, dtype=torch.int64))
        with pytest.raises(ValueError, match="do not fit"):
            row_kernels.scatter_weighted_rows(a, torch.zeros(4, dtype=torch.bool), torch.zeros(2, 8, dtype=torch.int64),
                                              torch.zeros(2, 8), torch.zeros(2, 3), first_channel=1)
