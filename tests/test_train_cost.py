"""benchmarks/studies/train_cost.py: the interleaved step cost and the tensor operations per step."""

from __future__ import annotations


import pytest




def test_operations_per_step_are_those_of_one_step(tiny_scene, tmp_path, load_script):
    """The count is per step (set-up excluded): a trainer's 2-step difference equals its
    1-step count on the next call, and S-NeRF issues more operations than its deterministic baseline."""
    import torch

    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    torch.set_num_threads(1)
    ds = load_dataset(tiny_scene, split_every=5)
    script = load_script("benchmarks/studies/train_cost.py")
    counts = {}
    for method in ("snerf", "deterministic"):
        cfg = preset("tiny")
        cfg.method = method
        cfg.train.iterations = 50
        cfg.train.checkpoint_every = 0
        cfg.train.eval_every = 0
        trainer = Trainer(cfg, tmp_path / method, ds)
        trainer.train(progress=False, max_steps=2)
        total, top = script.count_step_ops(trainer, top=3)
        assert trainer.step == 2 + 1 + 3
        assert total > 0 and len(top) == 3 and all(v > 0 for _, v in top)
        assert total == pytest.approx(script.count_step_ops(trainer)[0], rel=0.02)  # steady from step to step
        counts[method] = total
    assert counts["snerf"] > counts["deterministic"]


def test_command_refuses_a_reference_it_does_not_measure(tiny_scene, capsys, load_script):
    script = load_script("benchmarks/studies/train_cost.py")
    assert script.main(["--scene", str(tiny_scene), "--methods", "snerf_default", "--reference", "deterministic"]) == 2
    assert "--reference" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main(["--scene", str(tiny_scene), "--chunk", "0"])


def test_variant_is_parsed_into_typed_overrides(load_script):
    script = load_script("benchmarks/studies/train_cost.py")
    assert script.parse_variant("k4=snerf_default:train.train_draws=4,loss.kl=none,loss.lambda_depth=0.5") == (
        "k4", "snerf_default", (("train.train_draws", 4), ("loss.kl", "none"), ("loss.lambda_depth", 0.5)))
    assert script.parse_variant("s=snerf:render.shared_noise=true")[2] == (("render.shared_noise", True),)
    for bad in ("k4", "k4=snerf_default", "=snerf:a=1", "k4=snerf_default:", "k4=snerf_default:train.train_draws"):
        with pytest.raises(ValueError, match="--variant"):
            script.parse_variant(bad)


def test_command_refuses_a_variant_outside_its_range(tiny_scene, capsys, load_script):
    script = load_script("benchmarks/studies/train_cost.py")
    assert script.main(["--scene", str(tiny_scene), "--variant", "k0=snerf_default:train.train_draws=0"]) == 2
    assert "train.train_draws" in capsys.readouterr().err
    assert script.main(["--scene", str(tiny_scene), "--variant", "k4=snerf_default:train.no_such=1"]) == 2
    assert "train.no_such" in capsys.readouterr().err
    assert script.main(["--scene", str(tiny_scene), "--variant", "deterministic=snerf_default:train.train_draws=4"]) == 2
    assert "distinct" in capsys.readouterr().err


@pytest.mark.slow
def test_whole_training_is_timed_in_interleaved_chunks(tiny_scene, tmp_path, monkeypatch, load_script):
    """Every method trains the same steps in chunks of --chunk (the last one shorter); the loop
    times add up to each method's total, the ratio is of totals, and the JSON and the plot are
    written. A --variant trains beside them with its overrides."""
    import json

    import torch

    from stochastic_fields_bench import budget, runner

    torch.set_num_threads(1)
    script = load_script("benchmarks/studies/train_cost.py")
    monkeypatch.setattr(budget, "CPU_BUDGET_OVERRIDES", (("train.iterations", 7), ("field.grid_max_cells", 4096)))
    timed = runner.time_training_interleaved
    draws = {}

    def record(trainers, *args, **kwargs):
        draws.update({m: t.cfg.train.train_draws for m, t in trainers.items()})
        return timed(trainers, *args, **kwargs)

    monkeypatch.setattr(runner, "time_training_interleaved", record)
    out = tmp_path / "cost.json"
    assert script.main(["--scene", str(tiny_scene), "--chunk", "3", "--quiet", "--out", str(out),
                        "--variant", "k3=snerf_default:train.train_draws=3"]) == 0
    r = json.loads(out.read_text())
    assert r["steps"] == 7 and r["chunk_end_step"] == [3, 6, 7]
    assert draws["k3"] == 3 and draws["snerf_default"] != 3
    assert r["ratio"]["k3"] == pytest.approx(r["train_s"]["k3"] / r["train_s"]["deterministic"])
    for m in ("deterministic", "snerf_default", "k3"):
        assert len(r["chunk_step_s"][m]) == 3 and all(t > 0 for t in r["chunk_step_s"][m])
        total = sum(t * n for t, n in zip(r["chunk_step_s"][m], (3, 3, 1)))
        assert total == pytest.approx(r["train_s"][m], rel=1e-9)
        assert r["step_s"][m] == pytest.approx(r["train_s"][m] / 7, rel=1e-12)
    assert r["ratio"]["snerf_default"] == pytest.approx(r["train_s"]["snerf_default"] / r["train_s"]["deterministic"])
    assert r["ratio"]["deterministic"] == 1.0
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
