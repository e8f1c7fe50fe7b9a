"""Bad input, table-driven: every case must end with a non-zero exit (or the documented exception
type) and a message that names the option or file and the bad value; nothing is written for a
refused command. Cases: CLI options of train/render/eval/export, ``--config`` files, scene
loaders (transforms.json, poses_bounds.npy) and config construction/loading."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from stochastic_fields import config as C
from stochastic_fields.cli import main
from stochastic_fields.data import load_dataset
from stochastic_fields.data.errors import DatasetError
from stochastic_fields.losses import LossConfig
from stochastic_fields.renderer import RenderSettings
from stochastic_fields.validation import ConfigError


def run_cli(argv, capsys) -> tuple[int, str]:
    """(exit code, stderr) of ``stochastic-fields argv`` run in-process."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse errors
        rc = exc.code
    captured = capsys.readouterr()
    return rc, captured.err


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory, tiny_scene) -> Path:
    """A 2-step tiny run on the tiny scene (seconds)."""
    run = tmp_path_factory.mktemp("bad_input") / "run"
    assert main(["train", "--preset", "tiny", "--data.path", str(tiny_scene), "--train.iterations", "2",
                 "--out", str(run), "--quiet"]) == 0
    return run


# --------------------------------------------------------------------------- train options
# (extra argv, substrings the message must contain: the option and the value)
TRAIN_CASES = [
    (["--train.lr", "-1"], ["train.lr", "-1"]),
    (["--train.lr", "0"], ["train.lr", "0"]),
    (["--train.lr", "nan"], ["train.lr", "nan"]),
    (["--train.lr", "fast"], ["--train.lr", "'fast'"]),
    (["--train.iterations", "-5"], ["train.iterations", "-5"]),
    (["--train.iterations", "0"], ["train.iterations", "0"]),
    (["--train.rays_per_batch", "0"], ["train.rays_per_batch", "0"]),
    (["--train.rays-per-batch", "-3"], ["train.rays_per_batch", "-3"]),
    (["--train.rays_per_batch", "1.5"], ["--train.rays_per_batch", "'1.5'"]),
    (["--train.train_draws", "0"], ["train.train_draws", "0"]),
    (["--train.checkpoint_every", "-1"], ["train.checkpoint_every", "-1"]),
    (["--train.eval_every", "-1"], ["train.eval_every", "-1"]),
    (["--train.lr_final_factor", "2"], ["train.lr_final_factor", "2"]),
    (["--train.seed", "-1"], ["train.seed", "-1"]),
    (["--train.device", "tpu"], ["train.device", "tpu"]),
    (["--field.grid_levels", "0"], ["field.grid_levels", "0"]),
    (["--field.grid_levels", "-2"], ["field.grid_levels", "-2"]),
    (["--field.backend", "cnn"], ["--field.backend", "cnn"]),
    (["--field.dropout", "1.5"], ["field.dropout", "1.5"]),
    (["--field.init_std", "0"], ["field.init_std", "0"]),
    (["--field.mlp_width", "0"], ["field.mlp_width", "0"]),
    (["--render.num_draws", "0"], ["render.num_draws", "0"]),
    (["--render.num_draws", "1"], ["render.num_draws", "1"]),
    (["--render.num_samples", "0"], ["render.num_samples", "0"]),
    (["--render.background", "2,0,0"], ["render.background", "2"]),
    (["--render.background=-0.1,0,0"], ["render.background", "-0.1"]),
    (["--render.background", "1,1"], ["render.background", "(1.0, 1.0)"]),
    (["--render.background", "nan,0,0"], ["render.background", "nan"]),
    (["--render.background", "wide"], ["--render.background", "'wide'"]),
    (["--render.skip_empty_space", "maybe"], ["--render.skip_empty_space", "'maybe'"]),
    (["--render.chunk_rays", "0"], ["render.chunk_rays", "0"]),
    (["--render.occupancy_alpha_threshold", "1.5"], ["render.occupancy_alpha_threshold", "1.5"]),
    (["--render.adaptive_rtol", "0"], ["render.adaptive_rtol", "0"]),
    (["--render.quadrature", "trapezoid"], ["render.skip_empty_space", "trapezoid"]),
    (["--loss.likelihood_std", "0"], ["loss.likelihood_std", "0"]),
    (["--loss.likelihood_std", "-0.1"], ["loss.likelihood_std", "-0.1"]),
    (["--loss.likelihood_std", "inf"], ["loss.likelihood_std", "inf"]),
    (["--loss.random_points_per_axis", "0"], ["loss.random_points_per_axis", "0"]),
    (["--loss.lambda_random", "-1"], ["loss.lambda_random", "-1"]),
    (["--loss.kl_mc_samples", "0"], ["loss.kl_mc_samples", "0"]),
    (["--loss.kl", "half"], ["--loss.kl", "half"]),
    (["--data.split_every", "0"], ["data.split_every", "0"]),
    (["--data.downscale", "0"], ["data.downscale", "0"]),
    (["--data.images", "../images"], ["data.images", "../images"]),
    (["--method", "nope"], ["method", "nope"]),
    (["--data.path", "/nonexistent/scene"], ["/nonexistent/scene"]),
    (["--train.iterations", "99999999999999999999"], ["train.iterations", "99999999999999999999"]),
    (["--render.num_draws", "100000"], ["render.num_draws", "100000"]),
    (["--loss.random_points_per_axis", "5000"], ["loss.random_points_per_axis", "5000"]),
]


@pytest.mark.parametrize("extra,expected", TRAIN_CASES, ids=[" ".join(c[0]) for c in TRAIN_CASES])
def test_train_refuses_bad_option(extra, expected, tmp_path, tiny_scene, capsys):
    out = tmp_path / "run"
    argv = ["train", "--out", out, "--quiet", "--data.path", tiny_scene, *extra]
    rc, err = run_cli(argv, capsys)
    assert rc != 0
    for s in expected:
        assert s in err, (s, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 3
    assert not out.exists()  # refused before anything was written


# --------------------------------------------------------------------------- --config files
CONFIG_FILE_CASES = [
    ("missing", None, ["missing.json", "does not exist"]),
    ("not json", "{train: 1", ["config.json", "cannot read config"]),
    ("list", "[1, 2]", ["config.json", "JSON object"]),
    ("unknown key", {"train": {"learning_rate": 1}}, ["config.json", "train.learning_rate"]),
    ("unknown group", {"trian": {}}, ["config.json", "trian"]),
    ("wrong type", {"train": {"lr": "fast"}}, ["config.json", "train.lr", "'fast'"]),
    ("out of range", {"render": {"num_draws": 0}}, ["config.json", "render.num_draws", "0"]),
    ("group not object", {"render": 3}, ["config.json", "render", "3"]),
    ("bool as string", {"render": {"skip_empty_space": "on"}}, ["config.json", "render.skip_empty_space", "'on'"]),
]


@pytest.mark.parametrize("name,content,expected", CONFIG_FILE_CASES, ids=[c[0] for c in CONFIG_FILE_CASES])
def test_config_file_errors_name_file_and_key(name, content, expected, tmp_path, tiny_scene, capsys):
    path = tmp_path / ("missing.json" if content is None else "config.json")
    if content is not None:
        path.write_text(content if isinstance(content, str) else json.dumps(content))
    out = tmp_path / "run"
    rc, err = run_cli(["train", "--out", out, "--quiet", "--data.path", tiny_scene, "--config", path], capsys)
    assert rc != 0
    for s in expected:
        assert s in err, (s, err)
    assert not out.exists()


def test_out_is_empty(tmp_path, tiny_scene, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, err = run_cli(["train", "--out", "", "--quiet", "--data.path", tiny_scene], capsys)
    assert rc == 2 and "--out must name a folder, got ''" in err and list(tmp_path.iterdir()) == []


def test_out_is_a_file(tmp_path, tiny_scene, capsys):
    f = tmp_path / "file.txt"
    f.write_text("x")
    rc, err = run_cli(["train", "--out", f, "--quiet", "--data.path", tiny_scene], capsys)
    assert rc == 2 and str(f) in err and "not a folder" in err
    assert f.read_text() == "x"


def test_llff_refuses_downscale(shared_data, tmp_path, capsys):
    fern = shared_data / "nerf_llff_data" / "fern"
    rc, err = run_cli(["train", "--out", tmp_path / "run", "--quiet", "--preset", "llff", "--data.path", fern,
                       "--data.downscale", "2"], capsys)
    assert rc == 2 and "data.downscale=2" in err and str(fern) in err


# --------------------------------------------------------------------------- render / eval / export on a run
def _cameras_file(tmp_path: Path, **changes) -> Path:
    cam = {"K": [[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]],
           "world_to_camera": np.eye(4).tolist(), "width": 32, "height": 24, "near": 1.0, "far": 5.0}
    cam.update(changes)
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([cam]))
    return path


RUN_CASES = [
    ("render views comma", lambda run, tmp: ["render", "--run", run, "--views", ","], ["--views", "','"]),
    ("render views range", lambda run, tmp: ["render", "--run", run, "--views", "99"], ["--views", "99"]),
    ("render views text", lambda run, tmp: ["render", "--run", run, "--views", "one"], ["--views", "'one'"]),
    ("render K=1", lambda run, tmp: ["render", "--run", run, "--num-draws", "1"], ["--num-draws", "1"]),
    ("render K=0", lambda run, tmp: ["render", "--run", run, "--num-draws", "0"], ["--num-draws", "0"]),
    ("render K text", lambda run, tmp: ["render", "--run", run, "--num-draws", "x"], ["--num-draws", "'x'"]),
    ("render device", lambda run, tmp: ["render", "--run", run, "--device", "tpu"], ["--device", "'tpu'"]),
    ("eval views", lambda run, tmp: ["eval", "--run", run, "--views", "-1"], ["--views", "-1"]),
    ("render missing run", lambda run, tmp: ["render", "--run", tmp / "nope"], [str(Path("nope"))]),
    ("render out file", lambda run, tmp: ["render", "--run", run, "--out", tmp / "f.txt"], ["--out", "f.txt"]),
    ("export voxel tiny", lambda run, tmp: ["export", "--run", run, "--views", "1", "--formats", "npz", "--fuse",
                                            "--voxel-size", "1e-30", "--out", tmp / "e"], ["voxel_size", "1e-30"]),
    ("export voxel neg", lambda run, tmp: ["export", "--run", run, "--fuse", "--voxel-size", "-1",
                                           "--out", tmp / "e"], ["voxel_size", "-1"]),
    ("export K=1", lambda run, tmp: ["export", "--run", run, "--num-draws", "1", "--out", tmp / "e"],
     ["num_draws", "1"]),
    ("export quantiles", lambda run, tmp: ["export", "--run", run, "--quantiles", "0,2", "--out", tmp / "e"],
     ["quantile", "2"]),
    ("export min opacity", lambda run, tmp: ["export", "--run", run, "--min-opacity", "2", "--out", tmp / "e"],
     ["min_opacity", "2"]),
    ("export formats", lambda run, tmp: ["export", "--run", run, "--formats", "xyz", "--out", tmp / "e"],
     ["--formats", "'xyz'"]),
    ("export cameras missing", lambda run, tmp: ["export", "--run", run, "--cameras", tmp / "none.json",
                                                 "--out", tmp / "e"], ["none.json"]),
    ("export camera name traversal", lambda run, tmp: ["export", "--run", run, "--cameras",
                                                       _cameras_file(tmp, name="../../escaped"), "--out", tmp / "e"],
     ["cams.json", "'name'", "'../../escaped'"]),
    ("export camera name absolute", lambda run, tmp: ["export", "--run", run, "--cameras",
                                                      _cameras_file(tmp, name="/tmp/abs"), "--out", tmp / "e"],
     ["cams.json", "'/tmp/abs'"]),
    ("export camera name type", lambda run, tmp: ["export", "--run", run, "--cameras",
                                                  _cameras_file(tmp, name=7), "--out", tmp / "e"], ["cams.json", "7"]),
    ("export camera far text", lambda run, tmp: ["export", "--run", run, "--cameras",
                                                 _cameras_file(tmp, far="far"), "--out", tmp / "e"],
     ["cams.json", "'far'"]),
    ("export camera not rigid", lambda run, tmp: ["export", "--run", run, "--cameras",
                                                  _cameras_file(tmp, world_to_camera=(2 * np.eye(4)).tolist()),
                                                  "--out", tmp / "e"], ["cams.json", "rigid", "2.0"]),
    ("render views twice", lambda run, tmp: ["render", "--run", run, "--views", "1,1"], ["--views", "'1,1'"]),
    ("eval K huge", lambda run, tmp: ["eval", "--run", run, "--num-draws", "99999999999"],
     ["--num-draws", "99999999999"]),
    ("export units newline", lambda run, tmp: ["export", "--run", run, "--units", "m\nelement vertex 0",
                                               "--out", tmp / "e"], ["units", "'m\\nelement vertex 0'"]),
    ("export seed", lambda run, tmp: ["export", "--run", run, "--seed", "-1", "--out", tmp / "e"], ["seed", "-1"]),
    ("export views twice", lambda run, tmp: ["export", "--run", run, "--views", "2,2", "--out", tmp / "e"],
     ["--views", "'2,2'"]),
    ("export out run folder", lambda run, tmp: ["export", "--run", run, "--views", "1", "--out", run],
     ["--out", "did not write"]),
    ("export out file", lambda run, tmp: ["export", "--run", run, "--out", tmp / "f.txt"], ["--out", "f.txt"]),
    ("export out foreign folder", lambda run, tmp: ["export", "--run", run, "--views", "1", "--formats", "npz",
                                                    "--out", tmp / "mine"], ["--out", "mine", "did not write"]),
]


@pytest.mark.parametrize("name,argv,expected", RUN_CASES, ids=[c[0] for c in RUN_CASES])
def test_run_commands_refuse_bad_input(name, argv, expected, trained_run, tmp_path, capsys):
    (tmp_path / "f.txt").write_text("x")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    before = sorted(p.name for p in trained_run.iterdir())
    rc, err = run_cli(argv(trained_run, tmp_path), capsys)
    assert rc != 0
    for s in expected:
        assert s in err, (s, err)
    assert "Traceback" not in err
    assert sorted(p.name for p in trained_run.iterdir()) == before
    assert (tmp_path / "f.txt").read_text() == "x" and (tmp_path / "mine" / "notes.txt").read_text() == "keep"
    assert not (tmp_path / "e").exists()


# --------------------------------------------------------------------------- scene loaders
def _edit(meta: dict, key: str, value) -> None:
    meta[key] = value
    for f in meta["frames"]:
        f.pop(key, None)


def _frame0(meta: dict, key: str, value) -> None:
    meta["frames"][0][key] = value


LOADER_CASES = [
    ("aabb string", lambda m: _edit(m, "aabb", "big"), ["aabb", "big"]),
    ("aabb inverted", lambda m: _edit(m, "aabb", [[1, 1, 1], [0, 0, 0]]), ["aabb", "[[1, 1, 1]"]),
    ("fl_x list", lambda m: _edit(m, "fl_x", [1, 2]), ["'fl_x'", "[1, 2]"]),
    ("fl_x text", lambda m: _edit(m, "fl_x", "wide"), ["'fl_x'", "'wide'"]),
    ("fl_x zero", lambda m: _edit(m, "fl_x", 0), ["fl_x=0"]),
    ("cx nan", lambda m: _edit(m, "cx", float("nan")), ["'cx'", "nan"]),
    ("camera_angle_x zero", lambda m: (m.pop("fl_x"), m.pop("fl_y"), _edit(m, "camera_angle_x", 0.0)),
     ["'camera_angle_x'", "0.0"]),
    ("camera_angle_x 180 deg", lambda m: (m.pop("fl_x"), m.pop("fl_y"), _edit(m, "camera_angle_x", math.pi)),
     ["'camera_angle_x'", "3.14159"]),
    ("camera_angle_x text", lambda m: (m.pop("fl_x"), m.pop("fl_y"), _edit(m, "camera_angle_x", "wide")),
     ["'camera_angle_x'", "'wide'"]),
    ("w text", lambda m: _edit(m, "w", "96px"), ["'w'", "'96px'"]),
    ("frame is a number", lambda m: m["frames"].__setitem__(1, 7), ["frame 1", "7"]),
    ("pose singular", lambda m: _frame0(m, "transform_matrix", np.diag([1.0, 1.0, 0.0, 1.0]).tolist()),
     ["frame 0", "transform_matrix", "rigid"]),
    ("pose scaled", lambda m: _frame0(m, "transform_matrix", np.diag([2.0, 2.0, 2.0, 1.0]).tolist()),
     ["frame 0", "transform_matrix", "2.0"]),
    ("pose mirrored", lambda m: _frame0(m, "transform_matrix", np.diag([-1.0, 1.0, 1.0, 1.0]).tolist()),
     ["frame 0", "transform_matrix", "-1.0"]),
    ("near text", lambda m: _edit(m, "near", "close"), ["'near'", "'close'"]),
    ("far below near", lambda m: _edit(m, "far", 0.5), ["near", "far=0.5"]),
    ("depth scale negative", lambda m: _edit(m, "depth_unit_scale_factor", -1), ["depth_unit_scale_factor", "-1"]),
    ("background text", lambda m: _edit(m, "background", "wide"), ["background", "wide"]),
    ("split_every zero", lambda m: _edit(m, "split_every", 0), ["split_every", "0"]),
    ("frames empty", lambda m: m.__setitem__("frames", []), ["frames"]),
]


@pytest.fixture
def scene_copy(tiny_scene, tmp_path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(tiny_scene, dst)
    return dst


@pytest.mark.parametrize("name,edit,expected", LOADER_CASES, ids=[c[0] for c in LOADER_CASES])
def test_transforms_json_bad_values(name, edit, expected, scene_copy):
    path = scene_copy / "transforms.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as info:
        load_dataset(scene_copy)
    msg = str(info.value)
    assert "transforms.json" in msg
    for s in expected:
        assert s in msg, (s, msg)


def test_poses_bounds_non_rigid(tmp_path):
    from stochastic_fields.data.llff import read_poses_bounds

    arr = np.zeros((2, 17))
    pose = np.concatenate([np.eye(3), np.zeros((3, 1)), [[48.0], [64.0], [50.0]]], axis=1)
    arr[:, :15] = pose.reshape(-1)
    arr[:, 15:] = [1.0, 5.0]
    arr[1, :15] = np.concatenate([3 * np.eye(3), np.zeros((3, 1)), [[48.0], [64.0], [50.0]]], axis=1).reshape(-1)
    np.save(tmp_path / "poses_bounds.npy", arr)
    with pytest.raises(DatasetError, match=r"poses_bounds.npy: row 1: .*rotation.*3\.0"):
        read_poses_bounds(tmp_path / "poses_bounds.npy")


# --------------------------------------------------------------------------- config objects
CONSTRUCT_CASES = [
    (lambda: RenderSettings(num_draws=0), "num_draws", "0"),
    (lambda: RenderSettings(background=(1.0, 2.0, 0.0)), "background", "2.0"),
    (lambda: RenderSettings(quadrature="simpson"), "quadrature", "simpson"),
    (lambda: RenderSettings(shared_noise="yes"), "shared_noise", "'yes'"),
    (lambda: LossConfig(likelihood_std=-1.0), "likelihood_std", "-1.0"),
    (lambda: LossConfig(random_points_per_axis=0), "random_points_per_axis", "0"),
    (lambda: C.TrainConfig(lr=float("nan")), "lr", "nan"),
    (lambda: C.TrainConfig(iterations=True), "iterations", "True"),
    (lambda: C.FieldConfig(grid_levels=2.5), "grid_levels", "2.5"),
    (lambda: C.DataConfig(split_every=0), "split_every", "0"),
    (lambda: C.from_dict(C.ExperimentConfig, {"render": {"num_draws": 1}}), "render.num_draws", "1"),
    (lambda: C.from_dict(C.ExperimentConfig, {"train": {"lr": "1e-3"}}), "train.lr", "'1e-3'"),
    (lambda: C.from_dict(C.ExperimentConfig, {"loss": {"kl": None}}), "loss.kl", "None"),
]


@pytest.mark.parametrize("make,option,value", CONSTRUCT_CASES, ids=[f"{c[1]}={c[2]}" for c in CONSTRUCT_CASES])
def test_config_construction_refuses(make, option, value):
    with pytest.raises(ConfigError) as info:
        make()
    msg = str(info.value)
    assert f"option {option}:" in msg and value in msg


def test_load_config_names_file_and_key(tmp_path):
    data = C.to_dict(C.preset("tiny"))
    data["render"]["num_draws"] = 0
    path = tmp_path / "config.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"config.json: option render.num_draws: must be an integer >= 1 and <= 4096, got 0"):
        C.load_config(path)


def test_every_numeric_field_has_a_declared_range():
    """Every int/float field of the config dataclasses has an explicit range (not just a type)."""
    import dataclasses
    import typing

    from stochastic_fields.losses import LOSS_CHECKS
    from stochastic_fields.renderer import RENDER_CHECKS

    for cls, checks in ((C.DataConfig, C.DATA_CHECKS), (C.FieldConfig, C.FIELD_CHECKS),
                        (C.TrainConfig, C.TRAIN_CHECKS), (RenderSettings, RENDER_CHECKS), (LossConfig, LOSS_CHECKS)):
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] in (int, float):
                assert f.name in checks, f"{cls.__name__}.{f.name} has no declared range"
        # the defaults themselves are inside the declared ranges
        cls()
    for name in C.PRESETS:
        C.preset(name)


def test_docstrings_state_the_declared_ranges():
    """config.py's groups, RenderSettings and LossConfig state each numeric field's checked range in its
    docstring, word for word (so the text cannot drift from the check)."""
    import dataclasses
    import typing

    from stochastic_fields.losses import LOSS_CHECKS, LossConfig
    from stochastic_fields.renderer import RENDER_CHECKS

    for cls, checks in ((C.DataConfig, C.DATA_CHECKS), (C.FieldConfig, C.FIELD_CHECKS),
                        (C.TrainConfig, C.TRAIN_CHECKS), (RenderSettings, RENDER_CHECKS),
                        (LossConfig, LOSS_CHECKS)):
        docs = C.field_docs(cls)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] in (int, float):
                assert f"Range: {checks[f.name].rule}." in docs[f.name], (cls.__name__, f.name, docs[f.name])


def test_checkers_normalise_values():
    r = RenderSettings(background=[1, 0, 0.5], num_draws=4)
    assert r.background == (1.0, 0.0, 0.5) and isinstance(r.background[0], float)
    assert isinstance(C.TrainConfig(lr=1).lr, float) and C.TrainConfig(lr=1).lr == 1.0
    assert torch.isfinite(torch.tensor(C.TrainConfig().lr))
