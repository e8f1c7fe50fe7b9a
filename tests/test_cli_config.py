"""CLI/config usability: on/off booleans, hyphenated option names, ``--config FILE`` with CLI
precedence, resolved data paths (and old relative ones still loading), presets as data in --help."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pytest

from stochastic_fields import config as C
from stochastic_fields.cli import build_parser, experiment_from_args, main


def parse(*argv: str) -> argparse.Namespace:
    return build_parser().parse_args(["train", "--out", "unused", *argv])


@pytest.mark.parametrize("word,value", [("on", True), ("off", False), ("true", True), ("False", False),
                                        ("yes", True), ("NO", False), ("1", True), ("0", False)])
def test_boolean_words(word, value, tmp_path):
    cfg = experiment_from_args(parse("--render.skip_empty_space", word), tmp_path)
    assert cfg.render.skip_empty_space is value


def test_boolean_error_names_option_and_value(capsys):
    with pytest.raises(SystemExit) as info:
        parse("--render.skip_empty_space", "maybe")
    err = capsys.readouterr().err
    assert info.value.code == 2 and "--render.skip_empty_space" in err and "'maybe'" in err and "on/off" in err


def test_hyphen_and_underscore_spellings(tmp_path):
    a = experiment_from_args(parse("--train.rays-per-batch", "77", "--loss.learn-likelihood-std", "on"), tmp_path)
    b = experiment_from_args(parse("--train.rays_per_batch", "77", "--loss.learn_likelihood_std", "on"), tmp_path)
    assert a.train.rays_per_batch == b.train.rays_per_batch == 77
    assert a.loss.learn_likelihood_std is b.loss.learn_likelihood_std is True
    assert C.to_dict(a) == C.to_dict(b)


def test_config_file_partial_and_cli_precedence(tmp_path):
    f = tmp_path / "opts.json"
    f.write_text(json.dumps({"train": {"lr": 0.02, "iterations": 40}, "render": {"background": [0, 0.5, 1]}}))
    cfg = experiment_from_args(parse("--preset", "tiny", "--config", str(f), "--train.iterations", "7"), tmp_path)
    assert cfg.train.lr == 0.02  # from the file
    assert cfg.train.iterations == 7  # the explicit option wins over the file
    assert cfg.render.background == (0.0, 0.5, 1.0)
    assert cfg.render.num_samples == 32  # the rest from the preset
    assert cfg.train.rays_per_batch == 256


def test_config_file_round_trips_a_run_config(tmp_path):
    cfg = C.preset("llff")
    cfg.train.lr = 0.003
    f = tmp_path / "config.json"
    C.save_config(cfg, f)
    again = experiment_from_args(parse("--config", str(f)), tmp_path / "new")
    assert C.to_dict(again) == C.to_dict(cfg)


def test_data_path_stored_absolute_and_renders_from_elsewhere(tmp_path, tiny_scene, monkeypatch, capsys):
    monkeypatch.chdir(tiny_scene.parent)
    rel = os.path.relpath(tiny_scene, tiny_scene.parent)
    run = tmp_path / "run"
    assert main(["train", "--preset", "tiny", "--data.path", rel, "--train.iterations", "2", "--out", str(run),
                 "--quiet"]) == 0
    saved = json.loads((run / "config.json").read_text())["data"]["path"]
    assert Path(saved).is_absolute() and Path(saved) == tiny_scene.resolve()
    monkeypatch.chdir(tmp_path)
    assert main(["render", "--run", str(run), "--views", "1", "--quiet"]) == 0
    assert (run / "renders" / "views" / "view_001.npz").is_file()
    # resuming with the relative spelling is the same data path, not a changed option
    monkeypatch.chdir(tiny_scene.parent)
    assert main(["train", "--data.path", rel, "--train.iterations", "3", "--out", str(run), "--quiet"]) == 0


def test_old_config_with_relative_path_still_loads(tmp_path, monkeypatch):
    data = C.to_dict(C.preset("tiny"))
    data["data"]["path"] = "some/relative/scene"
    (tmp_path / "config.json").write_text(json.dumps(data))
    cfg = C.load_config(tmp_path / "config.json")
    assert cfg.data.path == "some/relative/scene"


def test_presets_are_data_and_listed_in_help(capsys):
    assert C.preset("tiny").train.rays_per_batch == C.PRESET_OVERRIDES["tiny"]["train.rays_per_batch"] == 256
    for name, overrides in C.PRESET_OVERRIDES.items():
        cfg = C.preset(name)
        for key, value in overrides.items():
            group, field = key.split(".")
            assert getattr(getattr(cfg, group), field) == value
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "tiny: train.iterations=150, train.rays_per_batch=256" in text
    assert "llff: data.images=images_8, render.spacing=disparity" in text
    assert "Adam learning rate (grid cells use 10x). Range: a finite number > 0." in text  # declared ranges too
    assert "likelihood (colour units, [0, 1]); the starting value when learned. Range: a finite number > 0." in text
    assert "[range: true or false]" in text  # fields whose docstring has no range get it appended
    with pytest.raises(ValueError, match="unknown preset 'fast'"):
        C.preset("fast")


def test_a_command_imports_only_its_own_module():
    """Building any command's parser (what --help does) loads neither torch nor a command's
    implementation (export's trimesh/Open3D, prepare's pycolmap): each loads when its command runs."""
    import subprocess
    import sys

    from stochastic_fields.cli import EXTRA_COMMANDS

    heavy = ("torch", "stochastic_fields.products.export", "stochastic_fields.data.prepare",
             "stochastic_fields.calibration", "stochastic_fields.products.rosbag", "stochastic_fields.products.rerun_log")
    code = ("import sys; from stochastic_fields.cli import build_parser; build_parser({!r}); "
            f"print(' '.join(m for m in {heavy!r} if m in sys.modules))")
    commands = ("train", "eval", "render", "demo", *EXTRA_COMMANDS, "bench")
    loaded = {cmd: subprocess.run([sys.executable, "-c", code.format(cmd)], capture_output=True, text=True,
                                  check=True).stdout.split() for cmd in commands}
    assert loaded == {cmd: [] for cmd in commands}
    # and each --help answers with its usage
    for cmd in commands:
        out = subprocess.run([sys.executable, "-m", "stochastic_fields.cli", cmd, "--help"], capture_output=True,
                             text=True, check=True).stdout
        assert out.startswith(f"usage: stochastic-fields {cmd}"), (cmd, out[:80])


@pytest.mark.parametrize("command", ["render", "eval", "export"])
def test_render_time_options_have_the_config_spelling_and_the_old_one(command):
    """K (and the colour estimator) are spelled as in the run's config, --render.num_draws, as on
    train; the short spellings of earlier versions keep working."""
    base = [command, "--run", "r"]
    for spelling in ("--render.num_draws", "--render.num-draws", "--num-draws"):
        assert build_parser(command).parse_args([*base, spelling, "8"]).num_draws == 8
    if command != "export":
        for spelling in ("--render.colour_estimator", "--colour-estimator"):
            args = build_parser(command).parse_args([*base, spelling, "rao_blackwell"])
            assert args.colour_estimator == "rao_blackwell"
