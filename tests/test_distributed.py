"""Data-parallel training (stochastic_fields.distributed): 2 gloo ranks spawned from pytest.

The reference for a distributed step is one process taking one optimiser step on the union of
the ranks' batches: it draws each rank's share with that rank's generator state (recorded by the
ranks before the step) and back-propagates ``sum_r (n_r / B) loss_r`` (module doc of
``stochastic_fields.distributed``). Since Adam's step is nearly scale-free (eps 1e-15), the
parameters alone could not tell summed gradients from averaged ones: the reduced gradients
themselves are compared, dense and row-sparse.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import socket
import time
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from stochastic_fields.config import preset
from stochastic_fields.distributed import pack_bits, rank_seeds, shard_size, unpack_bits

WORLD = 2
#: seconds a test's ranks get to finish before the test fails (they take a few seconds each)
JOIN_TIMEOUT_S = 240.0

# ----------------------------------------------------------------------------- plain functions


def test_shard_sizes_cover_the_batch_and_differ_by_at_most_one():
    assert [shard_size(67, r, 2) for r in range(2)] == [34, 33]
    assert [shard_size(10, r, 4) for r in range(4)] == [3, 3, 2, 2]
    assert [shard_size(8, r, 4) for r in range(4)] == [2, 2, 2, 2]


def test_rank_seeds_keep_single_process_seeds_and_mix_rank_and_step():
    assert rank_seeds(7, 0, 1) == (7, 8)  # one process: training's historical seeds
    ref = np.random.SeedSequence(7, spawn_key=(1, 0)).generate_state(2, dtype=np.uint64)
    assert rank_seeds(7, 1, 2) == (int(ref[0]), int(ref[1]))
    seeds = {rank_seeds(7, r, 2, s) for r in range(2) for s in (0, 5)} | {rank_seeds(8, 0, 2)}
    assert len(seeds) == 5


@pytest.mark.parametrize("n", [1, 7, 8, 9, 1000])
def test_bitmap_packing_round_trips(n):
    mask = torch.rand(n, generator=torch.Generator().manual_seed(n)) < 0.3
    packed = pack_bits(mask)
    assert packed.dtype == torch.uint8 and packed.numel() == math.ceil(n / 8)
    assert torch.equal(unpack_bits(packed, n), mask)
    # bit j of byte i is mask[8 i + j]
    assert int(pack_bits(torch.tensor([True, False, True] + [False] * 5))[0]) == 0b101


def test_distributed_flag_without_torchrun_environment_is_refused(monkeypatch, tmp_path, capsys):
    from stochastic_fields.cli import main

    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    assert main(["train", "--out", str(tmp_path / "run"), "--preset", "tiny", "--distributed", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "RANK" in err and "torchrun" in err
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


# ----------------------------------------------------------------------------- spawned ranks


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _tiny_cfg(method: str = "snerf", backend: str = "grid", iterations: int = 4):
    cfg = preset("tiny")
    cfg.method = method
    cfg.field.backend = backend
    cfg.field.grid_max_cells = 20000
    cfg.field.mlp_depth, cfg.field.mlp_width = 2, 32
    cfg.train.iterations = iterations
    cfg.train.rays_per_batch = 67  # odd: rank 0 draws 34 rays, rank 1 draws 33
    cfg.train.checkpoint_every = 0
    cfg.train.train_draws = 4
    cfg.render.num_samples = 16
    cfg.loss.depth_rays_per_batch = 32
    cfg.loss.random_points_per_axis = 4
    return cfg


def _entry(rank: int, port: int, timeout_s: float, worker: str, args: tuple, out: str) -> None:
    """One rank: torchrun's environment, a gloo process group, ``worker(ctx, *args)``; its
    result (or its error) saved to ``out/rank<r>.pt``."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(WORLD), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    from stochastic_fields.distributed import process_group

    result: dict = {}
    try:
        with process_group("cpu", timeout_s=timeout_s) as ctx:
            result = {"value": globals()[worker](ctx, *args)}
    except BaseException as exc:  # reported to the test, which decides
        result = {"error": type(exc).__name__, "message": str(exc), "traceback": traceback.format_exc()}
    torch.save(result, Path(out) / f"rank{rank}.pt")


def _launch(worker: str, args: tuple, tmp_path: Path, *, timeout_s: float = 60.0,
            wait_for: tuple[int, ...] = tuple(range(WORLD))) -> list[dict]:
    """Run ``worker`` on WORLD spawned ranks; wait for the ranks in ``wait_for`` (then stop any
    other still running) and return every rank's result dict."""
    out = tmp_path / f"results_{worker}"
    out.mkdir()
    ctx = mp.get_context("spawn")
    port = _free_port()
    procs = [ctx.Process(target=_entry, args=(r, port, timeout_s, worker, args, str(out))) for r in range(WORLD)]
    for p in procs:
        p.start()
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    try:
        for r in wait_for:
            procs[r].join(max(0.0, deadline - time.monotonic()))
            assert not procs[r].is_alive(), f"rank {r} did not finish within {JOIN_TIMEOUT_S} s (hung)"
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
                p.join()
    results = []
    for r in range(WORLD):
        path = out / f"rank{r}.pt"
        results.append(torch.load(path, weights_only=False) if path.exists() else {"error": "no result"})
    return results


def _value(result: dict):
    assert "value" in result, f"{result.get('error')}: {result.get('message')}\n{result.get('traceback', '')}"
    return result["value"]


def _gradients(model) -> dict[str, torch.Tensor]:
    """Every gradient of ``model`` by parameter name: ``.grad``, or the grid tables' RowGradient as a dense table."""
    out = {}
    for name, p in model.named_parameters():
        acc = getattr(p, "row_gradient", None)
        if acc is not None:
            out[name] = acc.dense(p)
        elif p.grad is not None:
            out[name] = p.grad.detach().clone()
    return out


CASES = (("snerf", "grid"), ("snerf", "mlp"), ("deterministic", "grid"), ("deterministic", "mlp"))


def _one_step_worker(ctx, scene: str, run_root: str) -> dict:
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    ds = load_dataset(scene, split_every=4)
    results = {}
    for method, backend in CASES:
        trainer = Trainer(_tiny_cfg(method, backend, iterations=1), Path(run_root) / f"{method}_{backend}", ds,
                          distributed=ctx)
        rec = {"batch_rng": trainer.generator.get_state(), "draw_rng": trainer.draw_generator.get_state()}
        compute, step = trainer.compute_gradients, trainer.optimizer.step

        def recording_compute(*a, _compute=compute, _rec=rec):
            _rec["loss"], _rec["logs"] = _compute(*a)
            return _rec["loss"], _rec["logs"]

        def recording_step(_step=step, _rec=rec, _model=trainer.model):
            _rec["grads"] = _gradients(_model)
            _step()

        trainer.compute_gradients, trainer.optimizer.step = recording_compute, recording_step
        trainer.train(progress=False)
        rec["state"] = {k: v.clone() for k, v in trainer.model.state_dict().items()}
        results[(method, backend)] = rec
    return results


def _reference_step(method: str, backend: str, ds, rngs: list[dict], run_dir: Path):
    """One single-process step on the union of the ranks' batches: (loss, gradients after rank
    0's share alone, gradients, state after the step)."""
    from stochastic_fields.trainer import Trainer, TrainingDepth, TrainingRays

    cfg = _tiny_cfg(method, backend, iterations=1)
    trainer = Trainer(cfg, run_dir, ds)
    model = trainer.model
    data = TrainingRays.from_dataset(ds, trainer.device)
    depth = TrainingDepth.from_dataset(ds, trainer.device) if getattr(model, "accepts_depth", False) else None
    B, M = cfg.train.rays_per_batch, cfg.loss.depth_rays_per_batch
    shares, depth_shares = [34, 33], [16, 16]  # by hand: 67 = 34 + 33, 32 = 16 + 16
    model.train()
    trainer.optimizer.zero_grad(set_to_none=True)
    total, first = 0.0, None
    for r, rng in enumerate(rngs):
        trainer.generator.set_state(rng["batch_rng"])
        trainer.draw_generator.set_state(rng["draw_rng"])
        rays, target = data.batch(shares[r], trainer.generator)
        extra = {"depth": depth.batch(depth_shares[r], trainer.generator)} if depth is not None else {}
        loss, _ = model.training_loss(rays, target, step=0, generator=trainer.draw_generator, **extra)
        (loss * shares[r] / B).backward()
        total += loss.item() * shares[r] / B
        if first is None:
            first = _gradients(model)
    assert sum(shares) == B and sum(depth_shares) == M
    grads = _gradients(model)
    trainer.optimizer.set_step(0)
    trainer.optimizer.step()
    model.after_step(0)
    return total, first, grads, model.state_dict()


def _close(a: torch.Tensor, b: torch.Tensor) -> bool:
    scale = float(b.abs().max()) if b.numel() else 0.0
    return bool(torch.allclose(a, b, rtol=1e-4, atol=1e-6 * max(scale, 1e-12)))


@pytest.mark.slow
def test_one_distributed_step_equals_one_single_process_step_on_the_union_batch(tiny_scene, tmp_path):
    from stochastic_fields.data import load_dataset

    torch.set_num_threads(1)
    ranks = [_value(r) for r in _launch("_one_step_worker", (str(tiny_scene), str(tmp_path / "dist")), tmp_path)]
    ds = load_dataset(tiny_scene, split_every=4)
    for case in CASES:
        r0, r1 = ranks[0][case], ranks[1][case]
        # the ranks drew from different streams, and hold identical parameters after the step
        assert not torch.equal(r0["batch_rng"], r1["batch_rng"]) and not torch.equal(r0["draw_rng"], r1["draw_rng"])
        for name, t in r0["state"].items():
            assert torch.equal(t, r1["state"][name]), (case, name)
        assert r0["loss"] == r1["loss"]
        loss, first, grads, state = _reference_step(*case, ds, [r0, r1], tmp_path / f"ref_{case[0]}_{case[1]}")
        assert r0["loss"] == pytest.approx(loss, rel=1e-5), case
        assert set(grads) == set(r0["grads"]), case
        if case[1] == "grid":
            assert any(n.startswith("field.levels") or ".levels." in n for n in grads), "no row-sparse table in the case"
        for name, g in grads.items():
            d = r0["grads"][name]
            assert _close(d, g), (case, name, float((d - g).abs().max()), float(g.abs().max()))
            if float(g.abs().max()) > 0:
                # what summing instead of averaging, or ranks drawing the same rays, would give
                assert not _close(d, 2 * g), (case, name)
        assert any(not _close(grads[n], first[n] * 67 / 34) for n in grads if float(grads[n].abs().max()) > 0), case
        for name, t in state.items():
            if t.is_floating_point():
                torch.testing.assert_close(r0["state"][name], t, rtol=1e-4, atol=1e-5, msg=f"{case} {name}")
            else:
                assert torch.equal(r0["state"][name], t), (case, name)
        if case[0] == "snerf":  # the occupancy refresh after the step read the ranks' maximal interval scale
            assert torch.equal(r0["state"]["interval_scale"], state["interval_scale"])
            assert r0["state"]["occupancy.density_ema"].abs().max() > 0


def _steps_and_resume_worker(ctx, scene: str, root: str, single_run: str) -> dict:
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    ds = load_dataset(scene, split_every=4)
    root = Path(root)
    cfg = lambda: _tiny_cfg("snerf", "grid", iterations=4)  # noqa: E731
    straight = Trainer(cfg(), root / "straight", ds, distributed=ctx)
    straight.train(progress=False)
    interrupted = Trainer(cfg(), root / "interrupted", ds, distributed=ctx)
    interrupted.train(progress=False, max_steps=2)
    ctx.barrier("copy")
    if ctx.is_main:  # a distributed checkpoint at step 2, for a single-process resume in the test
        shutil.copytree(root / "interrupted", root / "for_single")
    ctx.barrier("copied")
    resumed = Trainer(cfg(), root / "interrupted", ds, distributed=ctx)
    resumed.train(progress=False)
    from_single = Trainer(cfg(), Path(single_run), ds, distributed=ctx)
    assert from_single.try_resume()
    at_resume = {"step": from_single.step, "state": {k: v.clone() for k, v in from_single.model.state_dict().items()}}
    from_single.train(progress=False)
    snapshot = lambda t: {k: v.clone() for k, v in t.model.state_dict().items()}  # noqa: E731
    return {"straight": snapshot(straight), "resumed": snapshot(resumed), "resumed_step": resumed.step,
            "from_single_at_resume": at_resume, "from_single": snapshot(from_single), "from_single_step": from_single.step}


@pytest.mark.slow
def test_ranks_agree_after_steps_and_resume_works_across_process_counts(tiny_scene, tmp_path):
    from stochastic_fields.checkpoint import load_checkpoint
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    torch.set_num_threads(1)
    ds = load_dataset(tiny_scene, split_every=4)
    single = Trainer(_tiny_cfg("snerf", "grid", iterations=4), tmp_path / "single", ds)
    single.train(progress=False, max_steps=2)  # a single-process checkpoint at step 2
    single_state = load_checkpoint(tmp_path / "single" / "checkpoint.pt")
    assert "rank_rngs" not in single_state  # single-process checkpoints keep their format
    ranks = [_value(r) for r in _launch("_steps_and_resume_worker",
                                        (str(tiny_scene), str(tmp_path / "dist"), str(tmp_path / "single")), tmp_path)]
    a, b = ranks
    for key in ("straight", "resumed", "from_single"):
        for name, t in a[key].items():
            assert torch.equal(t, b[key][name]), (key, name)  # bit-identical on both ranks
    # distributed -> distributed: the ranks' generator states are in the checkpoint, the run continues exactly
    assert a["resumed_step"] == 4
    for name, t in a["straight"].items():
        assert torch.equal(t, a["resumed"][name]), name
    ckpt = load_checkpoint(tmp_path / "dist" / "straight" / "checkpoint.pt")
    assert ckpt["step"] == 4 and ckpt["world_size"] == 2 and len(ckpt["rank_rngs"]) == 2
    for name, t in ckpt["model"].items():
        assert torch.equal(t, a["straight"][name]), name
    # single -> distributed: both ranks start from the single-process checkpoint
    assert a["from_single_at_resume"]["step"] == 2 and a["from_single_step"] == 4
    for name, t in single_state["model"].items():
        assert torch.equal(a["from_single_at_resume"]["state"][name], t), name
    assert load_checkpoint(tmp_path / "single" / "checkpoint.pt")["step"] == 4
    # distributed -> single: the model and optimiser of step 2 load; the streams restart (said)
    dist_ckpt = load_checkpoint(tmp_path / "dist" / "for_single" / "checkpoint.pt")
    solo = Trainer(_tiny_cfg("snerf", "grid", iterations=4), tmp_path / "dist" / "for_single", ds)
    with pytest.warns(UserWarning, match="written by 2 process"):
        assert solo.try_resume()
    assert solo.step == 2
    for name, t in dist_ckpt["model"].items():
        assert torch.equal(solo.model.state_dict()[name], t), name
    with pytest.warns(UserWarning, match="written by 2 process"):
        solo.train(progress=False)
    assert solo.step == 4 and load_checkpoint(tmp_path / "dist" / "for_single" / "checkpoint.pt")["step"] == 4


def _failing_worker(ctx, scene: str, run: str, mode: str) -> dict:
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    ds = load_dataset(scene, split_every=4)
    cfg = _tiny_cfg("deterministic", "grid", iterations=20)
    cfg.train.checkpoint_every = 1
    trainer = Trainer(cfg, Path(run), ds, distributed=ctx)
    compute = trainer.compute_gradients

    def failing_compute(*a):
        if ctx.rank == 1 and trainer.step == 3:
            if mode == "raises":
                raise RuntimeError("injected failure on rank 1")
            time.sleep(120)  # "hangs": stops answering; the test stops this process
        return compute(*a)

    trainer.compute_gradients = failing_compute
    trainer.train(progress=False)
    return {"step": trainer.step}


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["raises", "hangs"])
def test_a_failing_rank_stops_the_other_with_a_clear_error_and_no_partial_checkpoint(tiny_scene, tmp_path, mode):
    from stochastic_fields.checkpoint import load_checkpoint

    run = tmp_path / "run"
    r0, r1 = _launch("_failing_worker", (str(tiny_scene), str(run), mode), tmp_path, timeout_s=5.0,
                     wait_for=(0,) if mode == "hangs" else (0, 1))
    assert r0.get("error") == "DistributedError", r0
    assert "rank 0 of 2" in r0["message"] and "another rank stopped" in r0["message"]
    assert "all-reduce" in r0["message"]
    if mode == "raises":
        assert r1["error"] == "RuntimeError" and "injected failure" in r1["message"]
    else:
        assert "5 s" in r0["message"]  # the timeout is named
    # the last complete checkpoint is the step before the failure; no temporary file is left
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["step"] == 3 and state["world_size"] == 2
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "config.json", "train_log.jsonl"]


def test_row_gradient_replace_is_what_the_optimiser_takes():
    """``RowGradient.replace`` (the reduction's result) steps RowSparseAdam exactly as the same
    rows accumulated by ``add``; an ``add`` after it accumulates on top; ``zero`` drops it."""
    from stochastic_fields.fields.row_gather import row_gradient
    from stochastic_fields.optim import RowSparseAdam

    g = torch.Generator().manual_seed(0)
    rows = torch.tensor([1, 4, 6])
    values = torch.randn(3, 2, generator=g)
    tables = [torch.nn.Parameter(torch.randn(8, 2, generator=torch.Generator().manual_seed(1))) for _ in range(2)]
    opts = [RowSparseAdam([t], lr=0.1) for t in tables]
    row_gradient(tables[0]).add(tables[0], torch.tensor([6, 1, 4, 1]), torch.cat([values[[2, 0, 1]], torch.zeros(1, 2)]))
    row_gradient(tables[1]).add(tables[1], torch.tensor([0]), torch.ones(1, 2))  # dropped by replace
    row_gradient(tables[1]).replace(tables[1], rows, values)
    assert torch.equal(row_gradient(tables[1]).dense(tables[1]), row_gradient(tables[0]).dense(tables[0]))
    for opt in opts:
        opt.step()
    torch.testing.assert_close(tables[0].data, tables[1].data, rtol=0, atol=0)
    moved = (tables[1].data != torch.randn(8, 2, generator=torch.Generator().manual_seed(1))).any(dim=1)
    assert moved.nonzero().squeeze(1).tolist() == [1, 4, 6]
    acc = row_gradient(tables[1])
    acc.replace(tables[1], rows, values)
    acc.add(tables[1], torch.tensor([4]), torch.ones(1, 2))
    expected = torch.zeros(8, 2)
    expected[rows] = values
    expected[4] += 1
    assert torch.equal(acc.dense(tables[1]), expected)
    acc.replace(tables[1], rows, values)
    acc.zero()
    assert not acc.dense(tables[1]).any() and acc.take(tables[1])[0].numel() == 0


@pytest.mark.slow
def test_torchrun_cli_trains_two_ranks_and_one_process_resumes(tiny_scene, tmp_path):
    """``torchrun --nproc_per_node 2 -m stochastic_fields.cli train``: one run folder written by
    rank 0 (each log record once), then ``train`` in one process continues it."""
    import json
    import subprocess
    import sys

    from stochastic_fields.checkpoint import load_checkpoint

    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    options = ["--out", str(run), "--preset", "tiny", "--data.path", str(tiny_scene), "--train.checkpoint_every", "5",
               "--train.rays_per_batch", "128", "--render.num_samples", "16", "--quiet"]
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                           "--master_port", str(_free_port()), "-m", "stochastic_fields.cli", "train",
                           "--train.iterations", "20", *options],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("trained on 2 processes (gloo)") == 1
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["step"] == 20 and state["world_size"] == 2
    steps = [json.loads(line)["step"] for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert steps == [10, 20]
    done = subprocess.run([sys.executable, "-m", "stochastic_fields.cli", "train", "--train.iterations", "30", *options],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "written by 2 process(es) and resumes in 1" in done.stderr
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 30 and "world_size" not in load_checkpoint(run / "checkpoint.pt")
    steps = [json.loads(line)["step"] for line in (run / "train_log.jsonl").read_text().splitlines()]
    assert steps == [10, 20, 30]


# ----------------------------------------------------------------------------- sharded render / eval / export
#: views evaluated and exported: 5 (odd), so rank 0 renders positions 0, 2, 4 and rank 1 positions 1, 3
SHARDED_VIEWS = [1, 2, 3, 5, 6]
#: timing entries of metrics.json (wall clock, the only values allowed to differ between runs)
TIMING_KEYS = ("render_s", "render_s_per_view")


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory) -> Path:
    """A run folder trained for 3 single-process steps on the tiny scene (S-NeRF, grid)."""
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    torch.set_num_threads(1)
    run = tmp_path_factory.mktemp("tiny_run") / "run"
    Trainer(_tiny_cfg("snerf", "grid", iterations=3), run, load_dataset(tiny_scene, split_every=4)).train(progress=False)
    return run


def _load_run(scene: str, run: str):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import load_trained_model

    ds = load_dataset(scene, split_every=4)
    return ds, load_trained_model(Path(run), dataset=ds, device="cpu")[1]


def _recording(module, name: str, seen: list, fail_at=None):
    """Wrap ``module.name(model, dataset_or_spec, key, ...)``: record the keys it is called with, raise at ``fail_at``."""
    original = getattr(module, name)

    def wrapper(model, item, key, *a, **k):
        seen.append(key)
        if key == fail_at:
            raise RuntimeError(f"injected failure on rank 1 at {key}")
        return original(model, item, key, *a, **k)

    setattr(module, name, wrapper)


def _eval_worker(ctx, scene: str, run: str, out: str, fail_view) -> dict:
    from stochastic_fields import evaluation

    ds, model = _load_run(scene, run)
    rendered: list[int] = []
    _recording(evaluation, "_evaluate_view", rendered, fail_view if ctx.rank == 1 else None)
    result = evaluation.evaluate(model, ds, Path(out), views=SHARDED_VIEWS, product_views=4, seed=3, progress=False,
                                 distributed=ctx)
    return {"rendered": rendered, "nll": result["pooled"]["nll"],
            "all_gathered": ctx.all_gather_object({"rank": ctx.rank}, what="test") if fail_view is None else None}


def _without_timings(obj, drop: tuple[str, ...] = TIMING_KEYS):
    if isinstance(obj, dict):
        return {k: _without_timings(v, drop) for k, v in obj.items() if k not in drop}
    if isinstance(obj, list):
        return [_without_timings(v, drop) for v in obj]
    return obj


def _assert_same_npz(a: Path, b: Path) -> None:
    with np.load(a) as x, np.load(b) as y:
        assert sorted(x.files) == sorted(y.files), a.name
        for k in x.files:
            assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f"), (a.name, k)


def _assert_same_folders(single: Path, sharded: Path, json_without_timings: tuple[str, ...] = (),
                         drop: tuple[str, ...] = TIMING_KEYS) -> list[str]:
    """Every file of ``single`` equals ``sharded``'s (npz: arrays; json named: without the
    entries ``drop``; others: bytes) and neither has a file the other lacks. Returns the relative paths."""
    import json

    names = sorted(str(p.relative_to(single)) for p in single.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(sharded)) for p in sharded.rglob("*") if p.is_file())
    for name in names:
        a, b = single / name, sharded / name
        if name.endswith(".npz"):
            _assert_same_npz(a, b)
        elif name in json_without_timings:
            x, y = (_without_timings(json.loads(p.read_text()), drop) for p in (a, b))
            assert json.dumps(x, sort_keys=True) == json.dumps(y, sort_keys=True), name
        else:
            assert a.read_bytes() == b.read_bytes(), name
    return names


@pytest.mark.slow
def test_sharded_eval_equals_one_process_file_by_file(tiny_scene, tiny_run, tmp_path):
    import json

    from stochastic_fields.evaluation import evaluate

    torch.set_num_threads(1)
    r0, r1 = (_value(r) for r in _launch("_eval_worker", (str(tiny_scene), str(tiny_run), str(tmp_path / "sharded"),
                                                          None), tmp_path))
    assert r0["rendered"] == [1, 3, 6] and r1["rendered"] == [2, 5]  # views[r::2]
    assert r0["all_gathered"] == r1["all_gathered"] == [{"rank": 0}, {"rank": 1}]
    ds, model = _load_run(str(tiny_scene), str(tiny_run))
    single = evaluate(model, ds, tmp_path / "single", views=SHARDED_VIEWS, product_views=4, seed=3, progress=False)
    assert r0["nll"] == r1["nll"] == single["pooled"]["nll"]  # every rank returns rank 0's result
    names = _assert_same_folders(tmp_path / "single", tmp_path / "sharded", ("metrics.json",))
    # products of the first 4 views in the list, whichever rank rendered them (view 6 is 5th: none)
    assert {n.split("/")[1][:8] for n in names if n.startswith("views/")} == {"view_001", "view_002", "view_003",
                                                                               "view_005"}
    assert {"metrics.json", "curves.npz", "views/view_005.npz", "views/view_002_depth_std.png"} <= set(names)
    metrics = json.loads((tmp_path / "sharded" / "metrics.json").read_text())
    assert metrics["views"] == [f"view_{v:03d}" for v in SHARDED_VIEWS]  # the list's order
    assert metrics["pooled"]["num_pixels"] == len(SHARDED_VIEWS) * 64 * 48
    assert len(metrics["per_view"]["render_s"]) == 5 and min(metrics["per_view"]["render_s"]) > 0  # kept, not compared


@pytest.mark.slow
def test_a_failing_rank_during_eval_stops_the_other_and_no_metrics_are_written(tiny_scene, tiny_run, tmp_path):
    out = tmp_path / "sharded"
    r0, r1 = _launch("_eval_worker", (str(tiny_scene), str(tiny_run), str(out), 5), tmp_path, timeout_s=5.0)
    assert r1["error"] == "RuntimeError" and "injected failure on rank 1 at 5" in r1["message"], r1
    assert r0.get("error") == "DistributedError", r0
    assert "rank 0 of 2" in r0["message"] and "gather (evaluation's per-view results" in r0["message"]
    assert not (out / "metrics.json").exists() and not (out / "curves.npz").exists()
    assert not list(out.glob("*.tmp*")) and not list(out.glob(".*"))  # no temporary file left either


def _export_worker(ctx, scene: str, run: str, out: str, foreign: str, fail_position) -> dict:
    from stochastic_fields.products import export
    from stochastic_fields.products.export import ExportOptions, dataset_view_specs, export_views

    ds, model = _load_run(scene, run)
    specs = dataset_view_specs(ds, SHARDED_VIEWS)
    opts = ExportOptions(formats=("npz", "png16", "tiff"), fuse=True, covariance=True, num_draws=4, seed=1,
                         progress=False)
    try:  # a folder the export did not write: refused by rank 0, raised on every rank
        export_views(model, specs, Path(foreign), opts, distributed=ctx)
        refused = None
    except ValueError as exc:
        refused = str(exc)
    rendered: list[int] = []
    _recording(export, "_export_view", rendered, fail_position if ctx.rank == 1 else None)  # position 3: view 5
    summary = export_views(model, specs, Path(out), opts, mesh_path=Path(scene) / "scene.ply", distributed=ctx)
    return {"refused": refused, "rendered": [specs[i].name for i in rendered], "summary": summary}


@pytest.mark.slow
def test_sharded_export_equals_one_process_export(tiny_scene, tiny_run, tmp_path):
    from stochastic_fields.products.export import ExportOptions, dataset_view_specs, export_views

    torch.set_num_threads(1)
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    r0, r1 = (_value(r) for r in _launch("_export_worker", (str(tiny_scene), str(tiny_run), str(tmp_path / "sharded"),
                                                            str(foreign), None), tmp_path))
    assert r0["refused"] and r1["refused"] and "non-empty folder that this command did not write" in r1["refused"]
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    assert r0["rendered"] == ["view_001", "view_003", "view_006"] and r1["rendered"] == ["view_002", "view_005"]
    ds, model = _load_run(str(tiny_scene), str(tiny_run))
    opts = ExportOptions(formats=("npz", "png16", "tiff"), fuse=True, covariance=True, num_draws=4, seed=1,
                         progress=False)
    single = export_views(model, dataset_view_specs(ds, SHARDED_VIEWS), tmp_path / "single", opts,
                          mesh_path=Path(tiny_scene) / "scene.ply")
    assert r0["summary"] == r1["summary"] == single
    names = _assert_same_folders(tmp_path / "single", tmp_path / "sharded")
    assert {"fused.ply", "summary.json", "clouds/view_002.ply", "views/view_005.npz", "views/view_006.tiff"} <= set(names)
    assert single["counts"]["after_filters"] > 0 and "surface_distance" in single["ground_truth"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".sharded")]  # the temporary folder was swapped in


@pytest.mark.slow
def test_a_failing_rank_during_export_leaves_the_previous_export(tiny_scene, tiny_run, tmp_path):
    out = tmp_path / "sharded"
    out.mkdir()
    (out / "summary.json").write_text("{}")  # a previous export (replaceable), kept as it is
    r0, r1 = _launch("_export_worker", (str(tiny_scene), str(tiny_run), str(out), str(out / "summary.json"), 3),
                     tmp_path, timeout_s=5.0)
    assert r1.get("error") == "RuntimeError" and "injected failure" in r1["message"], (r0, r1)
    assert r0.get("error") == "DistributedError" and "gather (export's per-view" in r0["message"], r0
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"] and (out / "summary.json").read_text() == "{}"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".sharded.partial")]


def test_stage_assignment_covers_every_stage_once():
    from stochastic_fields_bench.tables import assign_stages

    scenes, methods = ["fern", "flower", "horns"], ["deterministic", "snerf", "mc_dropout", "ensemble"]
    every = [(s, m) for s in scenes for m in methods]
    for world in (1, 2, 3, 5, 12, 13):
        parts = assign_stages(scenes, methods, world)
        assert len(parts) == world
        flat = [st for part in parts for st in part]
        assert sorted(flat) == sorted(every) and len(set(flat)) == len(every), world
        assert max(map(len, parts)) - min(map(len, parts)) <= 1, world
    # by hand: round-robin over the scene-major list
    assert assign_stages(["a", "b"], ["x", "y", "z"], 2) == [[("a", "x"), ("a", "z"), ("b", "y")],
                                                            [("a", "y"), ("b", "x"), ("b", "z")]]
    with pytest.raises(ValueError, match="world size"):
        assign_stages(scenes, methods, 0)


def _tables_worker(ctx, scene: str, out: str) -> dict:
    from stochastic_fields_bench.tables import run_benchmark

    logs: list[str] = []
    tables = run_benchmark([scene], TABLE_METHODS, Path(out), _table_settings(), progress=False, log=logs.append,
                           distributed=ctx)
    return {"logs": logs, "tables": tables}


#: the 2-rank tables run: 3 stages on one scene (rank 0 runs 2, rank 1 one)
TABLE_METHODS = ("deterministic", "snerf", "mc_dropout")


def _table_settings():
    from stochastic_fields_bench.tables import BenchmarkSettings

    return BenchmarkSettings(iterations=2, max_views=1, timing=False, tiny=True, device="cpu", product_views=1,
                             overrides=(("render.num_samples", 8), ("render.num_draws", 4),
                                        ("field.grid_max_cells", 12 ** 3), ("train.rays_per_batch", 64),
                                        ("loss.random_points_per_axis", 4)))


def _tables_without_timings(tables: dict) -> dict:
    """The tables without wall-clock entries (training and invocation times and their ratios)."""
    drop = {"wall_s_this_invocation", "train_s", "train_ratio", "render_s", "render_ratio", "eval_s", "command"}

    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k not in drop}
        return [strip(v) for v in o] if isinstance(o, list) else o
    return strip(tables)


@pytest.mark.slow
def test_tables_stages_run_on_two_ranks_and_rank_0_writes_the_same_tables(tiny_scene, tmp_path):
    import json

    from stochastic_fields_bench.tables import run_benchmark

    torch.set_num_threads(1)
    r0, r1 = (_value(r) for r in _launch("_tables_worker", (str(tiny_scene), str(tmp_path / "sharded")), tmp_path))
    assert r1["tables"] is None and r0["tables"] is not None
    trained = lambda logs: [m.group(1) for m in map(re.compile(r"\[[^\]]+/([^\]/]+)\] train:").search, logs) if m]  # noqa: E731
    assert trained(r0["logs"]) == ["deterministic", "mc_dropout"] and trained(r1["logs"]) == ["snerf"]
    assert all(line.startswith("[rank 1/2] ") for line in r1["logs"])
    single = run_benchmark([str(tiny_scene)], TABLE_METHODS, tmp_path / "single", _table_settings(), progress=False,
                           log=lambda line: None)
    a, b = (_tables_without_timings(json.loads((tmp_path / d / "tables.json").read_text())) for d in ("single", "sharded"))
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert set(single["table2"]) == set(TABLE_METHODS)
    assert (tmp_path / "sharded" / "tables.md").is_file()
    assert sorted(p.name for p in (tmp_path / "sharded" / "plots").iterdir()) == \
        sorted(p.name for p in (tmp_path / "single" / "plots").iterdir())
    scene = Path(tiny_scene).name
    for m in TABLE_METHODS:
        x, y = (json.loads((tmp_path / d / scene / m / "metrics.json").read_text()) for d in ("single", "sharded"))
        assert json.dumps(_without_timings(x), sort_keys=True) == json.dumps(_without_timings(y), sort_keys=True), m


@pytest.mark.parametrize("command", [["calibrate", "--run", "RUN"], ["demo", "--out", "RUN"]])
def test_commands_that_cannot_shard_refuse_a_multi_rank_launch(monkeypatch, tmp_path, capsys, command):
    from stochastic_fields.cli import DISTRIBUTED_COMMANDS, main

    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main([a.replace("RUN", str(tmp_path / "run")) for a in command]) == 2
    err = capsys.readouterr().err
    assert f"'{command[0]}' does not run distributed: only train, render, eval, export do under torchrun" in err
    assert DISTRIBUTED_COMMANDS == ("train", "render", "eval", "export")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_torchrun_cli_eval_and_export_equal_one_process(tiny_scene, tmp_path):
    """``torchrun --nproc_per_node 2 -m stochastic_fields.cli eval`` / ``export`` on a CLI-trained
    run: the same files as the commands in one process (metrics.json but for timings)."""
    import subprocess
    import sys

    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    cli = [sys.executable, "-m", "stochastic_fields.cli"]
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
                str(_free_port()), "-m", "--", "stochastic_fields.cli"]  # "--": torchrun would take --run for --run-path
    done = subprocess.run(cli + ["train", "--out", str(run), "--preset", "tiny", "--data.path", str(tiny_scene),
                                 "--train.iterations", "10", "--render.num_samples", "16", "--quiet"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    for name, base in (("eval", ["eval", "--run", str(run), "--views", "1,2,3", "--num-draws", "4", "--quiet"]),
                       ("export", ["export", "--run", str(run), "--views", "1,2,3", "--num-draws", "4", "--fuse",
                                   "--quiet"])):
        outs = {}
        for how, launcher in (("single", cli), ("sharded", torchrun)):
            outs[how] = tmp_path / f"{name}_{how}"
            done = subprocess.run(launcher + base + ["--out", str(outs[how])], env=env, capture_output=True, text=True,
                                  timeout=300)
            assert done.returncode == 0, (name, how, done.stderr[-3000:])
            if how == "sharded" and name == "eval":
                assert done.stdout.count("(sharded over 2 processes, gloo)") == 1  # rank 0 prints, once
        # (the export's summary.json records its --out among the options: the one difference)
        _assert_same_folders(outs["single"], outs["sharded"], ("metrics.json", "summary.json"), TIMING_KEYS + ("out",))
