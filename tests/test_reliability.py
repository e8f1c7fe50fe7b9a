"""Crash, integrity and security behaviour: a refused resume changes nothing on disk; a resumed
run logs each step once and continues bit-identically; interrupted re-exports never look
finished; damaged checkpoints are refused; nothing is written outside the output folder;
environment errors are one line; half-precision renders equal float32 renders."""

from __future__ import annotations

import errno
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from stochastic_fields.checkpoint import load_checkpoint, save_checkpoint, state_checksum
from stochastic_fields.cli import main


def run_cli(argv, capsys) -> tuple[int, str]:
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def tree_digest(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``folder`` (symlinks by target text)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        if p.is_symlink():
            out[rel] = "link:" + str(p.readlink())
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


TRAIN = ["--preset", "tiny", "--train.iterations", "8", "--train.checkpoint_every", "4", "--quiet"]


@pytest.fixture(scope="module")
def run(tmp_path_factory, tiny_scene) -> Path:
    run = tmp_path_factory.mktemp("reliability") / "run"
    assert main(["train", "--data.path", str(tiny_scene), "--out", str(run), *TRAIN]) == 0
    return run


# --------------------------------------------------------------------------- resume
@pytest.mark.parametrize("extra,named", [
    (["--field.grid_levels", "2"], "field.grid_levels: 5 in the run, 2 now"),
    (["--preset", "demo"], "train.rays_per_batch: 256 in the run, 1024 now"),
    (["--preset", "default"], "render.num_samples: 32 in the run, 64 now"),
    (["--train.lr", "0.01"], "train.lr: 0.005 in the run, 0.01 now"),
    (["--loss.kl", "none"], "loss.kl: 'full' in the run, 'none' now"),
])
def test_refused_resume_changes_nothing(run, extra, named, capsys, tiny_scene):
    before = tree_digest(run)
    rc, err = run_cli(["train", "--out", run, "--quiet", *extra], capsys)
    assert rc == 2 and named in err and "Nothing was changed on disk" in err
    assert tree_digest(run) == before
    # the run still evaluates
    rc, err = run_cli(["eval", "--run", run, "--views", "1", "--no-products", "--quiet", "--out", run.parent / "ev"],
                      capsys)
    assert rc == 0, err


def test_run_damaged_by_an_old_failed_resume_still_loads(run, tmp_path):
    """Before the resume check, a failed resume rewrote config.json (grid_levels 2 for a
    5-level checkpoint): the checkpoint's own config repairs it, with a warning."""
    import shutil

    from stochastic_fields.config import load_config, save_config
    from stochastic_fields.trainer import load_trained_model

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    cfg = load_config(copy / "config.json")
    cfg.field.grid_levels = 2
    cfg.render.num_draws, cfg.render.colour_estimator = 5, "draws"  # render options: free to change
    save_config(cfg, copy / "config.json")
    with pytest.warns(UserWarning, match="field.grid_levels"):
        cfg, model, _ = load_trained_model(copy)
    assert cfg.field.grid_levels == 5
    assert (cfg.render.num_draws, cfg.render.colour_estimator) == (5, "draws")  # config.json's, not the checkpoint's
    assert model.default_render_options().num_draws == 5


def test_resume_may_extend_iterations(tmp_path, tiny_scene, capsys):
    out = tmp_path / "run"
    assert main(["train", "--data.path", str(tiny_scene), "--out", str(out), *TRAIN]) == 0
    rc, err = run_cli(["train", "--out", out, "--quiet", "--train.iterations", "10", "--train.eval_every", "5"], capsys)
    assert rc == 0, err
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 10


def test_killed_run_resumes_identically_and_logs_each_step_once(tmp_path, tiny_scene):
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    def cfg():
        c = preset("tiny")
        c.data.path = str(tiny_scene)
        c.train.iterations, c.train.checkpoint_every = 20, 4
        return c

    ds = load_dataset(tiny_scene, split_every=4)
    Trainer(cfg(), tmp_path / "straight", ds).train(progress=False)

    killed = Trainer(cfg(), tmp_path / "killed", ds)
    real_after_step = killed.model.after_step

    def after_step(step):  # "kill -9" after step 11: checkpoint at 8, log record at 10
        real_after_step(step)
        if step + 1 == 11:
            raise KeyboardInterrupt
    killed.model.after_step = after_step
    with pytest.raises(KeyboardInterrupt):
        killed.train(progress=False)
    # a killed save leaves a temporary file: the resumed run removes it
    stale = tmp_path / "killed" / ".checkpoint.pt.ab12cd34.tmp.pt"
    stale.write_bytes(b"\0" * 100)
    assert load_checkpoint(tmp_path / "killed" / "checkpoint.pt")["step"] == 8
    Trainer(cfg(), tmp_path / "killed", ds).train(progress=False)
    assert not stale.exists()

    def log(folder):
        return [json.loads(line) for line in (folder / "train_log.jsonl").read_text().splitlines()]
    straight, resumed = log(tmp_path / "straight"), log(tmp_path / "killed")
    assert [r["step"] for r in resumed] == [10, 20]
    assert [r["loss"] for r in resumed] == [r["loss"] for r in straight]  # bit-identical


# --------------------------------------------------------------------------- checkpoints
def test_nan_weights_refused(run, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(run, bad)
    state = load_checkpoint(bad / "checkpoint.pt")
    name = next(k for k, v in state["model"].items() if v.is_floating_point() and v.numel() > 1)
    state["model"][name].view(-1)[0] = float("nan")
    save_checkpoint(bad / "checkpoint.pt", state)  # a valid checksum over NaN weights
    rc, err = run_cli(["eval", "--run", bad, "--quiet"], capsys)
    assert rc == 2 and "checkpoint.pt" in err and repr(name) in err and "non-finite" in err


def test_edited_weights_fail_the_checksum(run, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(run, bad)
    state = load_checkpoint(bad / "checkpoint.pt")
    stored = state["checksum"]
    assert stored == state_checksum(state)
    name = next(k for k, v in state["model"].items() if v.is_floating_point() and v.numel() > 1)
    state["model"][name].view(-1)[0] += 1e-3
    torch.save(state, bad / "checkpoint.pt")  # old checksum, changed tensor
    rc, err = run_cli(["render", "--run", bad, "--quiet"], capsys)
    assert rc == 2 and "checkpoint.pt is corrupted" in err and stored[:16] in err


def test_flipped_bytes_refused(run, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(run, bad)
    data = bytearray((bad / "checkpoint.pt").read_bytes())
    rng = np.random.default_rng(0)
    for i in rng.choice(np.arange(len(data) // 4, len(data) * 3 // 4), 200, replace=False):
        data[i] ^= 0xFF
    (bad / "checkpoint.pt").write_bytes(bytes(data))
    rc, err = run_cli(["eval", "--run", bad, "--quiet"], capsys)
    assert rc == 2 and str(bad / "checkpoint.pt") in err
    assert "corrupted" in err or "cannot read checkpoint" in err or "non-finite" in err


# --------------------------------------------------------------------------- security
def test_camera_names_cannot_escape_out(run, tmp_path, capsys):
    escape_dir = tmp_path / "some" / "dir"
    escape_dir.mkdir(parents=True)
    for name in ["../../../../" + str(escape_dir).lstrip("/") + "/escaped", str(escape_dir / "abs"), "..", ".hidden",
                 "a/b", "-rf"]:
        cams = tmp_path / "cams.json"
        cams.write_text(json.dumps([{"K": [[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]], "world_to_camera": np.eye(4).tolist(),
                                     "width": 32, "height": 24, "near": 1.0, "far": 5.0, "name": name}]))
        before = tree_digest(tmp_path)
        rc, err = run_cli(["export", "--run", run, "--cameras", cams, "--out", tmp_path / "out" / "e", "--quiet"],
                          capsys)
        assert rc == 2 and repr(name) in err, err
        assert tree_digest(tmp_path) == before and not (tmp_path / "out").exists()


def test_log_symlink_is_not_followed(tmp_path, tiny_scene, capsys):
    target = tmp_path / "outside.txt"
    target.write_text("precious\n")
    out = tmp_path / "run"
    out.mkdir()
    (out / "train_log.jsonl").symlink_to(target)
    rc, err = run_cli(["train", "--data.path", tiny_scene, "--out", out, *TRAIN], capsys)
    assert rc == 2 and "train_log.jsonl is a symbolic link" in err
    assert target.read_text() == "precious\n"


def test_planted_folder_links_are_refused(run, tmp_path, capsys):
    import shutil

    outside = tmp_path / "outside"
    outside.mkdir()
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    (copy / "views").symlink_to(outside, target_is_directory=True)
    rc, err = run_cli(["eval", "--run", copy, "--views", "1", "--quiet"], capsys)
    assert rc == 2 and "views is a symbolic link" in err and list(outside.iterdir()) == []
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / "scene").symlink_to(outside, target_is_directory=True)
    rc, err = run_cli(["train", "--out", fresh, *TRAIN], capsys)
    assert rc == 2 and "scene is a symbolic link" in err and list(outside.iterdir()) == []


# --------------------------------------------------------------------------- export folder
def test_interrupted_reexport_keeps_the_finished_one(run, tmp_path, monkeypatch, capsys):
    from stochastic_fields.products import export as E

    out = tmp_path / "e"
    assert main(["export", "--run", str(run), "--views", "1", "--formats", "npz,tiff", "--out", str(out),
                 "--quiet"]) == 0
    first = tree_digest(out)
    calls = {"n": 0}
    real = E.write_view_files

    def killed_after_one(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(E, "write_view_files", killed_after_one)
    rc, err = run_cli(["export", "--run", run, "--views", "2,3", "--formats", "npz", "--out", out, "--quiet"], capsys)
    assert rc == 130 and "interrupted" in err
    assert tree_digest(out) == first  # the finished export, untouched; no view of the new settings
    assert json.loads((out / "summary.json").read_text())["views"] == ["view_001"]
    # a kill -9 leaves the partial folder: the next export removes it and replaces the folder whole
    (tmp_path / ".e.partial-zzzz").mkdir()
    (tmp_path / ".e.partial-zzzz" / "x.npz").write_bytes(b"partial")
    monkeypatch.setattr(E, "write_view_files", real)
    assert main(["export", "--run", str(run), "--views", "2", "--formats", "npz", "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e"]
    assert sorted(p.name for p in (out / "views").iterdir()) == ["view_002.npz"]
    assert json.loads((out / "summary.json").read_text())["views"] == ["view_002"]


# --------------------------------------------------------------------------- environment errors
@pytest.mark.parametrize("code,words", [(errno.ENOSPC, "No space left on device"),
                                        (errno.EACCES, "Permission denied"),
                                        (errno.EROFS, "Read-only file system")])
def test_environment_errors_are_one_line(tmp_path, tiny_scene, monkeypatch, capsys, code, words):
    import os
    import tempfile

    out = tmp_path / "run"
    assert main(["train", "--data.path", str(tiny_scene), "--out", str(out), *TRAIN]) == 0
    before = tree_digest(out)
    real = tempfile.mkstemp

    def failing(*a, **k):
        if k.get("prefix", "").startswith(".checkpoint.pt"):
            raise OSError(code, os.strerror(code), str(out / "checkpoint.pt"))
        return real(*a, **k)
    monkeypatch.setattr(tempfile, "mkstemp", failing)
    rc, err = run_cli(["train", "--out", out, "--quiet", "--train.iterations", "12"], capsys)
    assert rc == 2 and words in err and "checkpoint.pt" in err and len(err.strip().splitlines()) == 1
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 8  # the previous checkpoint is intact
    assert tree_digest(out)["checkpoint.pt"] == before["checkpoint.pt"]


def test_out_under_a_file(tmp_path, tiny_scene, capsys):
    (tmp_path / "f").write_text("x")
    rc, err = run_cli(["train", "--data.path", tiny_scene, "--out", tmp_path / "f" / "run", *TRAIN], capsys)
    assert rc == 2 and "f/run" in err and len(err.strip().splitlines()) == 1


# --------------------------------------------------------------------------- half precision
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_logistic_normal_table_half_inputs(dtype):
    from stochastic_fields.distributions import _logistic_normal_moments
    from stochastic_fields.logistic_normal_table import logistic_normal_moments_tabulated

    loc = torch.tensor([0.0, 1.0, -2.0, 4.0])
    scale = torch.tensor([2.0, 0.5, 1.0, 3.0])
    mean, var = logistic_normal_moments_tabulated(loc.to(dtype), scale.to(dtype))
    assert mean.dtype == dtype and var.dtype == dtype and bool(torch.isfinite(mean).all())
    ref_m, ref_v = _logistic_normal_moments(loc.to(dtype).double(), scale.to(dtype).double())
    tol = 2 ** -8 if dtype == torch.bfloat16 else 2 ** -10  # one rounding of the result
    torch.testing.assert_close(mean.double(), ref_m, rtol=tol, atol=1e-4)
    torch.testing.assert_close(var.double(), ref_v, rtol=2 * tol, atol=1e-5)
    assert float(mean[0]) == 0.5


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("estimator", ["draws", "rao_blackwell"])
def test_half_precision_render_equals_float32(dtype, estimator):
    from stochastic_fields.fields.base import FieldParams
    from stochastic_fields.rays import RayBundle, RaySamples
    from stochastic_fields.renderer import RenderSettings, render_samples, upcast_half

    R, S = 5, 48
    g = torch.Generator().manual_seed(0)
    rays = RayBundle(origins=torch.zeros(R, 3), directions=torch.tensor([[0.0, 0.0, 1.0]]).expand(R, 3),
                     near=torch.full((R,), 2.0), far=torch.full((R,), 30.0), z_scale=torch.ones(R))
    edges = torch.linspace(2.0, 30.0, S + 1).expand(R, S + 1)
    samples = RaySamples(rays, edges[:, :-1].contiguous(), edges[:, 1:].contiguous())
    params = FieldParams(torch.randn(R, S, generator=g) - 1.0, torch.full((R, S), 0.7),
                         torch.randn(R, S, 3, generator=g), torch.full((R, S, 3), 0.8))
    half_params = params.map(lambda t: t.to(dtype))
    half_samples = RaySamples(rays.__class__(**{k: getattr(rays, k).to(dtype) for k in
                                                ("origins", "directions", "near", "far", "z_scale")}),
                              samples.t_starts.to(dtype), samples.t_ends.to(dtype))
    st = RenderSettings(num_samples=S, colour_estimator=estimator, skip_empty_space=False)
    half = render_samples(half_params, half_samples, st, num_draws=16, generator=torch.Generator().manual_seed(1)).stats
    ref = render_samples(upcast_half(half_params), upcast_half(half_samples), st, num_draws=16,
                         generator=torch.Generator().manual_seed(1)).stats
    assert half.colour_mean.dtype == torch.float32
    for name in ("colour_mean", "colour_var", "depth_mean", "depth_var_epistemic", "depth_var_spread"):
        torch.testing.assert_close(getattr(half, name), getattr(ref, name), rtol=0, atol=0)
    assert bool(torch.isfinite(half.colour_mean).all()) and float(half.colour_mean.max()) <= 1.0


def test_set_aside_run_keeps_everything_under_a_free_name(tmp_path):
    from stochastic_fields.cli import set_aside_run

    run = tmp_path / "demo"
    for n in range(2):
        run.mkdir()
        (run / "metrics.json").write_text(f'{{"n": {n}}}')
        kept = set_aside_run(run)
        assert not run.exists() and (kept / "metrics.json").read_text() == f'{{"n": {n}}}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.previous", "demo.previous-2"]


@pytest.mark.slow
def test_demo_over_a_run_of_other_options_sets_it_aside_and_trains(run, tmp_path, capsys):
    """After an upgrade changes a default, `make demo` must still run: the old run is kept beside."""
    import shutil

    out = tmp_path / "demo"
    shutil.copytree(run, out)
    before = tree_digest(out)
    rc = main([str(a) for a in ["demo", "--out", out, "--preset", "tiny", "--train.iterations", "2",
                                "--train.lr", "0.01", "--quiet"]])
    printed = capsys.readouterr().out
    assert rc == 0
    assert f"moved it to {tmp_path / 'demo.previous'}" in printed and "train.lr: 0.005 in the run, 0.01 now" in printed
    assert tree_digest(tmp_path / "demo.previous") == before
    assert (out / "metrics.json").is_file() and (out / "checkpoint.pt").is_file()
