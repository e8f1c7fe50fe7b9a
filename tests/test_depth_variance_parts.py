"""benchmarks/studies/depth_variance_parts.py: a trained run re-scored, the total's and each part's ranking."""

from __future__ import annotations

import json

import pytest
from conftest import train_tiny_run


def test_parts_of_a_trained_run_are_scored_as_the_tables_score(tiny_scene, tmp_path, load_script):
    run = train_tiny_run(tiny_scene, tmp_path / "run")
    out = tmp_path / "parts"
    script = load_script("benchmarks/studies/depth_variance_parts.py")
    assert script.main(["--run", f"{tiny_scene}={run}", "--out", str(out), "--quiet"]) == 0
    row = json.loads((out / "depth_variance_parts.json").read_text())["rows"][0]
    metrics = json.loads(next(out.glob("*/0/metrics.json")).read_text())
    assert row["view_mean"]["total"] == metrics["summary"]["depth/spearman"]["mean"]
    assert row["pooled"]["total"] == metrics["pooled"]["depth"]["spearman"]
    for part in ("epistemic", "spread"):
        assert -1.0 <= row["view_mean"][part] <= 1.0 and -1.0 <= row["pooled"][part] <= 1.0
        assert row["view_mean"][part] == metrics["summary"][f"depth_parts/spearman_{part}"]["mean"]
    assert "| total (views / pooled) |" in (out / "depth_variance_parts.md").read_text()
    # resumable: a second call reads the finished scores back
    stamp = (next(out.glob("*/0/metrics.json"))).stat().st_mtime_ns
    assert script.main(["--run", f"{tiny_scene}={run}", "--out", str(out), "--quiet"]) == 0
    assert next(out.glob("*/0/metrics.json")).stat().st_mtime_ns == stamp


def test_refuses_what_is_not_a_run(tmp_path, load_script):
    script = load_script("benchmarks/studies/depth_variance_parts.py")
    with pytest.raises(SystemExit):
        script.main(["--run", "fern", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        script.main(["--run", f"fern={tmp_path / 'nothing'}", "--out", str(tmp_path)])
