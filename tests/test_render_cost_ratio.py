"""benchmarks/studies/render_cost_ratio.py: two trained runs' validation renders timed in turn."""

from __future__ import annotations

import json

import pytest
from conftest import train_tiny_run


def test_a_run_against_itself(tiny_scene, tmp_path, load_script):
    script = load_script("benchmarks/studies/render_cost_ratio.py")
    run = train_tiny_run(tiny_scene, tmp_path / "run", iterations=5)
    times = script.render_seconds({"today": run, "candidate": run}, repeats=2)
    assert set(times) == {"today", "candidate"} and all(len(t) == 2 and min(t) > 0 for t in times.values())
    out = tmp_path / "cost.json"
    script.main([str(run), str(run), "--threads", "1", "--repeats", "1", "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["threads"] == 1 and result["ratio"] == pytest.approx(
        result["seconds"]["candidate"][0] / result["seconds"]["today"][0])
    with pytest.raises(SystemExit):
        script.main([str(run), str(run), "--repeats", "0"])
