"""The benchmarks of the grid's row loops: the replay of a run's scatter calls and the training checksum."""

from __future__ import annotations

import json

import pytest
from conftest import train_tiny_run

from stochastic_fields import row_kernels


def test_row_kernels_replay_of_a_run_against_another_copy(tiny_scene, tmp_path, load_script):
    """benchmarks/studies/row_kernels_replay.py: a trained run's scatter calls replayed every way, each
    checked bit for bit against today's loops, with a copy of today's module as the other checkout."""
    if row_kernels.numba is None:
        pytest.skip("numba not installed")
    script = load_script("benchmarks/studies/row_kernels_replay.py")
    run = train_tiny_run(tiny_scene, tmp_path / "run", iterations=5)
    out = tmp_path / "replay"
    script.main(["--run", str(run), "--work", str(tmp_path / "work"), "--against", row_kernels.__file__,
                 "--rounds", "1", "--out", str(out)])
    result = json.loads((out / "results.json").read_text())
    assert set(result["scatter_ms"]) == {"today", "serial", "zeros_added", "against", "against_serial"}
    assert result["calls"] > 0 and 0.0 <= result["share_without_gradient"] <= 1.0
    assert all(v["min"] > 0 for v in result["adam_ms"].values()) and "| against_serial |" in (out / "README.md").read_text()
    assert not (tmp_path / "work").exists() and (run / "checkpoint.pt").is_file()
    with pytest.raises(SystemExit):
        script.main(["--run", str(run), "--work", str(tmp_path / "work"), "--against", str(tmp_path / "none.py")])


def test_capture_steps_checksum_is_the_same_for_the_same_code(tiny_scene, tmp_path, load_script):
    """benchmarks/studies/capture_steps_checksum.py: two trainings of the same code and seed give one
    checksum; another seed another one; the run's folder is removed."""
    script = load_script("benchmarks/studies/capture_steps_checksum.py")
    root, name = tiny_scene.parent, tiny_scene.name
    common = ["--scene", name, "--llff-root", str(root), "--steps", "4"]
    first = script.main(common + ["--work", str(tmp_path / "a")])
    again = script.main(common + ["--work", str(tmp_path / "b")])
    other = script.main(common + ["--work", str(tmp_path / "c"), "--seed", "1"])
    assert first["model_sha256"] == again["model_sha256"] != other["model_sha256"]
    assert first["steps"] == 4 and first["second_half_ms_per_step"] > 0 and not (tmp_path / "a").exists()
    with pytest.raises(SystemExit):
        script.main(common[:-1] + ["1", "--work", str(tmp_path / "d")])
