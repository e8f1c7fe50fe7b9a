"""The core pipeline: renderer statistics against references, the scene region, the trainer
(resume, checkpoints), the CLI, and end-to-end runs on the synthetic scene and on fern."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from stochastic_fields.config import preset
from stochastic_fields.fields.base import FieldParams
from stochastic_fields.rays import RayBundle, RaySamples
from stochastic_fields.renderer import RenderSettings, render_samples
from stochastic_fields.scene_region import SceneRegion


def _samples(R: int, S: int, dtype=torch.float64) -> RaySamples:
    rays = RayBundle(origins=torch.zeros(R, 3, dtype=dtype), directions=torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype).expand(R, 3),
                     near=torch.full((R,), 2.0, dtype=dtype), far=torch.full((R,), 6.0, dtype=dtype), z_scale=torch.ones(R, dtype=dtype))
    edges = torch.linspace(2.0, 6.0, S + 1, dtype=dtype).expand(R, S + 1)
    return RaySamples(rays, edges[:, :-1].contiguous(), edges[:, 1:].contiguous())


def _params(R: int, S: int, scale: float, seed: int = 0, dtype=torch.float64) -> FieldParams:
    g = torch.Generator().manual_seed(seed)
    loc = torch.randn(R, S, generator=g, dtype=dtype) * 2.0 - 0.5
    return FieldParams(density_loc=loc, density_scale=torch.full((R, S), scale, dtype=dtype),
                       rgb_loc=torch.randn(R, S, 3, generator=g, dtype=dtype), rgb_scale=torch.full((R, S, 3), scale, dtype=dtype))


def _reference_draws(params: FieldParams, samples: RaySamples, K: int, seed: int):
    """float64 naive per-ray, per-draw loop: alpha compositing of independent draws."""
    rng = np.random.default_rng(seed)
    R, S = params.density_loc.shape
    colours = np.zeros((R, K, 3))
    depths = np.zeros((R, K))
    t0, t1 = samples.t_starts.numpy(), samples.t_ends.numpy()
    for r in range(R):
        mu_a, s_a = params.density_loc[r].numpy(), params.density_scale[r].numpy()
        mu_c, s_c = params.rgb_loc[r].numpy(), params.rgb_scale[r].numpy()
        for k in range(K):
            a = np.maximum(0.0, mu_a + s_a * rng.standard_normal(S))
            c = 1.0 / (1.0 + np.exp(-(mu_c + s_c * rng.standard_normal((S, 3)))))
            T, acc, num = 1.0, 0.0, 0.0
            for i in range(S):
                w = T * (1.0 - math.exp(-a[i] * (t1[r, i] - t0[r, i])))
                colours[r, k] += w * c[i]
                num += w * 0.5 * (t0[r, i] + t1[r, i])
                acc += w
                T *= math.exp(-a[i] * (t1[r, i] - t0[r, i]))
            depths[r, k] = num / acc if acc > 1e-6 else samples.rays.far[r].item()
    return colours, depths


def test_sigma_to_zero_gives_deterministic_depth_and_zero_variance():
    R, S = 6, 48
    samples = _samples(R, S)
    settings = RenderSettings(num_samples=S, num_draws=16)
    stochastic = render_samples(_params(R, S, 1e-9), samples, settings, num_draws=16,
                                generator=torch.Generator().manual_seed(1)).stats
    deterministic = render_samples(_params(R, S, 1e-9), samples, settings, num_draws=1, deterministic=True).stats
    torch.testing.assert_close(stochastic.depth_mean, deterministic.depth_mean, rtol=1e-7, atol=1e-7)
    assert float(stochastic.depth_var_epistemic.max()) < 1e-12
    assert float(stochastic.colour_var.max()) < 1e-12
    # spread is a property of one trajectory and survives sigma -> 0
    torch.testing.assert_close(stochastic.depth_var_spread, deterministic.depth_var_spread, rtol=1e-6, atol=1e-9)


def test_large_k_statistics_match_float64_reference():
    R, S, K = 3, 24, 4000
    samples = _samples(R, S)
    params = _params(R, S, 0.8, seed=3)
    stats = render_samples(params, samples, RenderSettings(num_samples=S), num_draws=K,
                           generator=torch.Generator().manual_seed(0)).stats
    ref_c, ref_d = _reference_draws(params, samples, 20000, seed=1)
    for r in range(R):
        se_mean = ref_d[r].std() / math.sqrt(K)
        assert abs(stats.depth_mean[r].item() - ref_d[r].mean()) < 5 * se_mean + 1e-9
        # variance of the sample variance ~ var^2 * 2 / K for near-Gaussian, use a generous 6 SE
        var_ref = ref_d[r].var()
        assert abs(stats.depth_var_epistemic[r].item() - var_ref) < 6 * var_ref * math.sqrt(2.0 / K) + 1e-9
        se_c = ref_c[r].std(0) / math.sqrt(K)
        assert np.all(np.abs(stats.colour_mean[r].numpy() - ref_c[r].mean(0)) < 5 * se_c + 1e-9)


def test_render_samples_gradcheck_float64():
    R, S, K = 2, 6, 3
    samples = _samples(R, S)
    base = _params(R, S, 0.5, seed=5)

    def fn(d_loc, d_scale, c_loc, c_scale):
        p = FieldParams(d_loc, d_scale, c_loc, c_scale)
        st = render_samples(p, samples, RenderSettings(num_samples=S), num_draws=K,
                            generator=torch.Generator().manual_seed(7)).stats
        return st.colour_mean, st.colour_var, st.depth_mean, st.depth_var_total

    inputs = tuple(t.clone().requires_grad_(True) for t in (base.density_loc.abs() + 0.5, base.density_scale,
                                                             base.rgb_loc, base.rgb_scale))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("kind", ["aabb", "ndc"])
def test_scene_region_round_trip_and_stratified_points(kind):
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.1, -0.2, 0.5])
    box = torch.tensor([[-1.0, -0.5, 0.0], [2.0, 1.5, 3.0]]) if kind == "aabb" else torch.tensor([[-1.0, -1.0, -0.9], [1.0, 1.0, 0.8]])
    region = SceneRegion(kind, box, w2c, torch.tensor([0.6, 0.45, 1.5]))
    unit = torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    world = region.from_unit(unit)
    torch.testing.assert_close(region.to_unit(world), unit, rtol=1e-4, atol=1e-4)
    pts = region.sample_stratified(6, generator=torch.Generator().manual_seed(1))
    assert pts.shape == (216, 3) and bool(region.contains(pts).all())
    # one point per stratum: the unit coordinates fall in distinct cells of the 6^3 partition
    cells = ((region.to_unit(pts) + 1) / 2 * 6).floor().clamp(0, 5).long()
    assert len({tuple(c) for c in cells.tolist()}) == 216


def test_scene_region_rejects_bad_box():
    with pytest.raises(ValueError, match="max > min"):
        SceneRegion("aabb", torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 1.0]]))


def _tiny_cfg(iterations: int):
    cfg = preset("tiny")
    cfg.train.iterations = iterations
    cfg.train.rays_per_batch = 128
    cfg.train.checkpoint_every = 5
    cfg.render.num_samples = 24
    cfg.train.train_draws = 4
    return cfg


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA"))])
def test_trainer_resume_continues_exactly(tiny_scene, tmp_path, device, monkeypatch):
    """A run interrupted and resumed ends where the uninterrupted run does: model, optimiser and
    both random streams come back from the checkpoint. On CUDA the checkpoint is read onto the
    GPU; the generators' states must still be restored (they take CPU byte tensors)."""

    def cfg():
        c = _tiny_cfg(12)
        c.train.device = device
        return c

    torch.set_num_threads(1)  # bitwise-reproducible reductions for the comparison
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    if device == "cuda":  # CUDA's scatter-adds sum in no fixed order unless asked to
        monkeypatch.setenv("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
    try:
        _interrupt_and_resume(tiny_scene, tmp_path, cfg)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _interrupt_and_resume(tiny_scene, tmp_path, cfg) -> None:
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    ds = load_dataset(tiny_scene, split_every=4)
    straight = Trainer(cfg(), tmp_path / "straight", ds)
    straight.train(progress=False)
    interrupted = Trainer(cfg(), tmp_path / "resumed", ds)
    interrupted.train(progress=False, max_steps=7)  # "interrupted" after 7 steps (checkpoint at 5 and 7)
    resumed = Trainer(cfg(), tmp_path / "resumed", ds)
    assert resumed.try_resume() and resumed.step == 7
    assert torch.equal(resumed.draw_generator.get_state(), interrupted.draw_generator.get_state())
    assert torch.equal(resumed.generator.get_state(), interrupted.generator.get_state())
    resumed.train(progress=False)
    assert resumed.step == 12
    for (name, a), (_, b) in zip(straight.model.state_dict().items(), resumed.model.state_dict().items()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    # the checkpoint loads without executing code
    state = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert state["step"] == 12


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    from stochastic_fields.checkpoint import save_checkpoint

    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"step": 1})

    def broken_save(obj, f, *a, **k):
        Path(f).write_bytes(b"partial")
        raise RuntimeError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(RuntimeError):
        save_checkpoint(path, {"step": 2})
    assert torch.load(path, weights_only=True)["step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


def test_atomic_writes_get_the_permissions_a_plain_write_gets(tmp_path):
    """A new file gets 0o666 less the umask, as open() would give it (not mkstemp's 0o600, which other
    users and services of the machine could not read); a file written over keeps its own mode."""
    from stochastic_fields.io_utils import atomic_write, atomic_write_text

    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "new.json", "{}")
        (tmp_path / "plain.json").write_text("{}")
        assert (tmp_path / "new.json").stat().st_mode & 0o777 == 0o640 == (tmp_path / "plain.json").stat().st_mode & 0o777
        os.umask(0o022)
        atomic_write(tmp_path / "cloud.ply", lambda tmp: Path(tmp).write_bytes(b"ply"))
        assert (tmp_path / "cloud.ply").stat().st_mode & 0o777 == 0o644
        os.chmod(tmp_path / "new.json", 0o600)  # the user's choice for an existing file stays
        atomic_write_text(tmp_path / "new.json", "[]")
        assert (tmp_path / "new.json").stat().st_mode & 0o777 == 0o600 and (tmp_path / "new.json").read_text() == "[]"
    finally:
        os.umask(old)


def test_cli_help_explains_every_option():
    out = subprocess.run([sys.executable, "-m", "stochastic_fields.cli", "train", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for option, words in [("--train.iterations", "Optimiser steps"), ("--render.quadrature", "compositing"),
                          ("--loss.kl", "Table 3"), ("--field.backend", "grid"), ("--data.split_every", "index")]:
        assert option in out and words in out, option


def test_cli_reports_missing_checkpoint(tmp_path):
    res = subprocess.run([sys.executable, "-m", "stochastic_fields.cli", "eval", "--run", str(tmp_path)],
                         capture_output=True, text=True)
    assert res.returncode == 2 and "checkpoint" in res.stderr and str(tmp_path) in res.stderr


@pytest.mark.slow
def test_end_to_end_tiny_synthetic_scene(tmp_path):
    """Train the tiny preset on the embedded scene, render held-out views, beat stated thresholds."""
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    ds = load_run_dataset(cfg, tmp_path)
    model = Trainer(cfg, tmp_path, ds).train(progress=False)
    views = list(ds.test_indices)[:6]
    result = evaluate(model, ds, tmp_path, views=views, progress=False)
    means = {k: v["mean"] for k, v in result["summary"].items()}
    assert means["psnr"] > 14.0, means  # measured 15.0 (seed 0, 150 steps)
    assert means["depth/abs_rel"] < 0.2, means  # measured 0.11
    assert (tmp_path / "metrics.json").exists() and (tmp_path / "views" / f"view_{views[0]:03d}_depth_std.png").exists()
    checked = json.loads((tmp_path / "metrics.json").read_text())["pose_check"]  # 6 validation photos: too few
    assert list(checked) == ["validation"] and len(checked["validation"]["psnr_db"]) == 6
    assert checked["validation"]["flagged"] == [] and checked["validation"]["threshold_db"] is None
    with np.load(tmp_path / "views" / f"view_{views[0]:03d}.npz") as z:
        assert z["depth_mean"].shape == ds.images.shape[1:3]
        assert np.all(z["depth_std"] >= 0) and np.all(np.isfinite(z["depth_std"]))


@pytest.mark.slow
def test_llff_smoke_fern_images_16(shared_data, tmp_path):
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer

    cfg = preset("llff")
    cfg.data.path = str(shared_data / "nerf_llff_data" / "fern")
    cfg.data.images = "images_16"
    cfg.data.split = "paper"  # the paper's protocol: every 5th view trains
    cfg.train.iterations = 15
    cfg.train.rays_per_batch = 256
    cfg.train.eval_every = 0
    cfg.render.num_samples = 24
    cfg.render.num_draws = 4
    cfg.field.grid_max_cells = 200_000
    ds = load_run_dataset(cfg, tmp_path)
    assert ds.train_indices == [0, 5, 10, 15]
    model = Trainer(cfg, tmp_path, ds).train(progress=False)
    result = evaluate(model, ds, tmp_path, views=[1], progress=False)
    assert math.isfinite(result["summary"]["nll"]["mean"]) and math.isfinite(result["summary"]["psnr"]["mean"])
    assert json.loads((tmp_path / "config.json").read_text())["data"]["images"] == "images_16"
