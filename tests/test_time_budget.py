"""``train.minutes``: a training budget in minutes. The schedule follows the larger of step /
iterations and elapsed / budget, training stops at whichever end comes first, a resumed run
continues its clock, and data-parallel training refuses it. The trainer's clock is replaced by
one that advances one second a step, so every number here is exact."""

from __future__ import annotations

import types

import pytest
import torch

from stochastic_fields.config import preset
from stochastic_fields.data import load_dataset
from stochastic_fields.fields.grid import GridField
from stochastic_fields.optim import FieldOptimizer
from stochastic_fields.scene_region import SceneRegion
from stochastic_fields.trainer import Trainer
from stochastic_fields.validation import ConfigError


class StepClock:
    """``time.perf_counter`` that returns 0, 1, 2, ... seconds: one second between two reads."""

    def __init__(self) -> None:
        self.now = -1.0

    def perf_counter(self) -> float:
        self.now += 1.0
        return self.now


@pytest.fixture
def step_clock(monkeypatch):
    import stochastic_fields.trainer as trainer_module

    clock = StepClock()
    monkeypatch.setattr(trainer_module, "time", types.SimpleNamespace(perf_counter=clock.perf_counter))
    return clock


def tiny_config(iterations: int, minutes: float):
    cfg = preset("tiny")
    cfg.train.iterations = iterations
    cfg.train.minutes = minutes
    cfg.train.rays_per_batch = 32
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    cfg.field.grid_max_cells = 8 ** 3
    return cfg


def lrs(trainer: Trainer) -> list[float]:
    return [g["lr"] for g in trainer.optimizer.param_groups]


def test_set_progress_is_the_exponential_decay_and_clips():
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (8, 8, 8), num_levels=1, decoder_width=0)
    opt = FieldOptimizer([{"params": list(field.parameters()), "lr": 0.2}], total_steps=10, final_factor=0.1)
    for fraction, factor in ((0.0, 1.0), (0.5, 0.1 ** 0.5), (1.0, 0.1), (-0.3, 1.0), (7.0, 0.1)):
        opt.set_progress(fraction)
        assert [g["lr"] for g in opt.param_groups] == pytest.approx([0.2 * factor], rel=1e-12)
    opt.set_step(4)
    assert opt.param_groups[0]["lr"] == pytest.approx(0.2 * 0.1 ** 0.4, rel=1e-12)


def test_budget_stops_the_training_and_sets_the_schedule(tiny_scene, tmp_path, step_clock):
    dataset = load_dataset(tiny_scene)
    cfg = tiny_config(iterations=1000, minutes=0.1)  # 6 s: six steps of the one-second clock
    trainer = Trainer(cfg, tmp_path / "run", dataset)
    initial = lrs(trainer)
    trainer.train(progress=False)
    assert trainer.step == 6 and trainer.elapsed == pytest.approx(6.0)
    # the last step ran at 5 s of 6: its learning rates are lr * final ** (5 / 6), not ** (5 / 1000)
    factor = cfg.train.lr_final_factor ** (5 / 6)
    assert lrs(trainer) == pytest.approx([lr * factor for lr in initial], rel=1e-9)
    assert trainer.schedule_progress() == 1.0
    # resumed with a longer budget: the clock goes on from the checkpoint's 6 s
    cfg2 = tiny_config(iterations=1000, minutes=0.2)
    resumed = Trainer(cfg2, tmp_path / "run", dataset)
    resumed.train(progress=False)
    assert resumed.step == 12 and resumed.elapsed == pytest.approx(12.0)
    assert lrs(resumed) == pytest.approx([lr * cfg.train.lr_final_factor ** (11 / 12) for lr in initial], rel=1e-9)


def test_steps_end_first_when_the_budget_is_long(tiny_scene, tmp_path, step_clock):
    dataset = load_dataset(tiny_scene)
    trainer = Trainer(tiny_config(iterations=4, minutes=1.0), tmp_path / "run", dataset)
    initial = lrs(trainer)
    trainer.train(progress=False)
    assert trainer.step == 4 and trainer.elapsed == pytest.approx(4.0)
    # progress before the last step: max(3 / 4, 3 / 60)
    assert lrs(trainer) == pytest.approx([lr * 0.1 ** 0.75 for lr in initial], rel=1e-9)


def test_max_elapsed_stops_along_the_way(tiny_scene, tmp_path, step_clock):
    dataset = load_dataset(tiny_scene)
    trainer = Trainer(tiny_config(iterations=1000, minutes=0.1), tmp_path / "run", dataset)
    trainer.train(progress=False, max_elapsed_s=2.0)
    assert trainer.step == 2
    trainer.train(progress=False, max_elapsed_s=4.0)
    assert trainer.step == 4
    trainer.train(progress=False)
    assert trainer.step == 6


def test_budget_is_validated_and_refused_with_data_parallel_training(tiny_scene, tmp_path):
    cfg = tiny_config(iterations=10, minutes=0.0)
    cfg.train.minutes = -1.0
    with pytest.raises(ConfigError, match="train.minutes"):
        Trainer(cfg, tmp_path / "a", load_dataset(tiny_scene))
    cfg.train.minutes = 0.5
    ranks = types.SimpleNamespace(device=torch.device("cpu"), rank=0, world_size=2, is_main=True)
    with pytest.raises(ValueError, match="train.minutes = 0.5 with data-parallel training"):
        Trainer(cfg, tmp_path / "b", load_dataset(tiny_scene), distributed=ranks)


def test_checkpoint_writes_are_not_counted(tiny_scene, tmp_path, step_clock, monkeypatch):
    dataset = load_dataset(tiny_scene)
    cfg = tiny_config(iterations=1000, minutes=0.1)
    cfg.train.checkpoint_every = 2
    trainer = Trainer(cfg, tmp_path / "run", dataset)
    save = trainer.save

    def slow_save():  # a checkpoint write that takes 100 s of the clock
        save()
        step_clock.now += 100.0

    monkeypatch.setattr(trainer, "save", slow_save)
    trainer.train(progress=False)
    assert trainer.step == 6 and trainer.elapsed == pytest.approx(6.0)
