"""benchmarks/studies/render_profile.py: the side-by-side table of a render's operations."""

from __future__ import annotations

import pytest


def test_report_orders_by_the_first_runs_excess(load_script):
    script = load_script("benchmarks/studies/render_profile.py")
    rows = {"snerf": ({"aten::add": (900.0, 50), "aten::normal_": (400.0, 9), "aten::mul": (300.0, 40)}, 1600.0),
            "deterministic": ({"aten::add": (600.0, 40), "aten::mul": (310.0, 30), "aten::sigmoid": (50.0, 9)}, 960.0)}
    text = script.report(rows, "python benchmarks/studies/render_profile.py ...", 2, limit=3)
    lines = [line for line in text.splitlines() if line.startswith("| `")]
    assert [line.split("`")[1] for line in lines] == ["aten::normal_", "aten::add", "aten::mul"]  # +400, +300, -10
    assert lines[0] == "| `aten::normal_` | 400 (9) | 0 (0) | +400 |"
    assert lines[2].endswith("| -10 |")
    assert "| snerf | 1600 |" in text and "| deterministic | 960 |" in text


def test_run_arguments_are_checked(load_script, tmp_path, capsys):
    script = load_script("benchmarks/studies/render_profile.py")
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    out = ["--out", str(tmp_path / "profile.md")]
    with pytest.raises(SystemExit):
        script.main(["--run", str(tmp_path), "--run", f"b={tmp_path}", *out])
    assert "expects SCENE=RUN_DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--run", f"a={tmp_path / 'missing'}", "--run", f"b={tmp_path}", *out])
    assert "has no checkpoint.pt" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--run", f"a={tmp_path}", *out])
    assert "at least two --run" in capsys.readouterr().err
