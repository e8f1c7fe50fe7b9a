"""benchmarks/studies/render_plan_speed.py: the colour plan's changes timed chunk by chunk."""

from __future__ import annotations

import json

import pytest
from conftest import train_tiny_run

from stochastic_fields import renderer, row_kernels


def test_variants_switch_each_change_and_restore_it(load_script):
    script = load_script("benchmarks/studies/render_plan_speed.py")
    kept = renderer.reached_colour_moments
    with script.variant(compiled=False, kept_moments=False):
        assert renderer.reached_colour_moments is script._every_moment and row_kernels._disabled
    assert renderer.reached_colour_moments is kept and not row_kernels._disabled
    with pytest.raises(RuntimeError), script.variant(compiled=True, kept_moments=False):
        raise RuntimeError
    assert renderer.reached_colour_moments is kept


def test_summary_of_a_run_against_itself(tiny_scene, tmp_path, load_script):
    script = load_script("benchmarks/studies/render_plan_speed.py")
    run = train_tiny_run(tiny_scene, tmp_path / "run", iterations=5)
    out = tmp_path / "speed.json"
    script.main(["--snerf", str(run), "--deterministic", str(run), "--chunks", "2", "--out", str(out)])
    result = json.loads(out.read_text())
    names = {"before", "compiled draws", "kept moments", "both"}
    assert set(result["ms_per_chunk"]) == names | {"deterministic"} and min(result["ms_per_chunk"].values()) > 0
    assert result["relative_to_before"]["before"] == 1.0
    ms = result["ms_per_chunk"]
    assert result["over_deterministic"]["both"] == pytest.approx(ms["both"] / ms["deterministic"])
    assert result["chunks"] == 2 and result["command"].startswith("python benchmarks/studies/render_plan_speed.py")
    with pytest.raises(SystemExit):
        script.main(["--snerf", str(tmp_path), "--deterministic", str(run), "--out", str(out)])
    with pytest.raises(SystemExit):
        script.main(["--snerf", str(run), "--deterministic", str(run), "--chunks", "0", "--out", str(out)])

