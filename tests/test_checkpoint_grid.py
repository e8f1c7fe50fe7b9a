"""A saved run rebuilds the grid it was trained with, whatever sizes a grid today.

The finest level's cells per axis follow the training views (``field.grid_resolution_rule``), so a
change of the rule's code, of its constants or of the views handed to the loader would otherwise
give another table shape and a checkpoint that no longer loads. The trainer stores the shape
(``trainer.GRID_RESOLUTION_KEY``) and ``load_trained_model`` builds the model with it.
"""

from __future__ import annotations

import pytest
import torch

from stochastic_fields.checkpoint import load_checkpoint, save_checkpoint
from stochastic_fields.config import preset
from stochastic_fields.models import field_builder
from stochastic_fields.models.field_builder import trained_grid_resolution


def _trained_run(tiny_scene, run_dir, method: str = "snerf"):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    cfg.method = method
    cfg.train.iterations = 2
    cfg.train.rays_per_batch = 64
    cfg.render.num_samples = 16
    cfg.train.train_draws = 2
    ds = load_dataset(tiny_scene, split_every=4)
    trainer = Trainer(cfg, run_dir, ds)
    trainer.train(progress=False)
    return trainer, ds


def _rule_that_sizes_otherwise(monkeypatch):
    """Today's rule replaced by one that gives every axis two more cells."""
    rule = field_builder.RESOLUTION_RULES["parallax"]
    monkeypatch.setitem(field_builder.RESOLUTION_RULES, "parallax",
                        lambda *a, **k: tuple(r + 2 for r in rule(*a, **k)))


@pytest.mark.parametrize("method", ["snerf", "ensemble"])
def test_checkpoint_stores_the_grid_and_loads_it_when_the_rule_changes(tiny_scene, tmp_path, monkeypatch, method):
    from stochastic_fields.trainer import GRID_RESOLUTION_KEY, load_trained_model

    trainer, ds = _trained_run(tiny_scene, tmp_path / "run", method)
    trained = trained_grid_resolution(trainer.model)
    state = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert state[GRID_RESOLUTION_KEY] == list(trained)

    _rule_that_sizes_otherwise(monkeypatch)
    cfg = trainer.cfg
    assert field_builder.finest_grid_resolution(cfg, field_builder.fit_scene_region(ds, cfg), ds) != trained
    _, model, _ = load_trained_model(tmp_path / "run", dataset=ds)
    assert trained_grid_resolution(model) == trained
    for (name, a), (_, b) in zip(trainer.model.state_dict().items(), model.state_dict().items()):
        torch.testing.assert_close(a, b, msg=name)


def test_checkpoint_without_the_shape_sizes_the_grid_from_the_views(tiny_scene, tmp_path):
    """Checkpoints from before the shape was stored still load (sized again, as they were)."""
    from stochastic_fields.trainer import GRID_RESOLUTION_KEY, load_trained_model

    trainer, ds = _trained_run(tiny_scene, tmp_path / "run")
    path = tmp_path / "run" / "checkpoint.pt"
    state = load_checkpoint(path)
    state.pop(GRID_RESOLUTION_KEY)
    state.pop("checksum")
    save_checkpoint(path, state)
    _, model, _ = load_trained_model(tmp_path / "run", dataset=ds)
    assert trained_grid_resolution(model) == trained_grid_resolution(trainer.model)


@pytest.mark.parametrize("bad", [[4, 4], [4, 0, 4], [4.0, 4, 4], "4x4x4", [True, 4, 4]])
def test_a_damaged_stored_shape_is_refused_naming_the_file(tiny_scene, tmp_path, bad):
    from stochastic_fields.trainer import GRID_RESOLUTION_KEY, load_trained_model

    _, ds = _trained_run(tiny_scene, tmp_path / "run")
    path = tmp_path / "run" / "checkpoint.pt"
    state = load_checkpoint(path)
    state[GRID_RESOLUTION_KEY] = bad
    state.pop("checksum")
    save_checkpoint(path, state)
    with pytest.raises(ValueError, match=rf"checkpoint .*checkpoint\.pt: grid_resolution must be three positive"):
        load_trained_model(tmp_path / "run", dataset=ds)


def test_resume_names_both_grids_when_the_views_size_another(tiny_scene, tmp_path, monkeypatch):
    from stochastic_fields.trainer import Trainer

    trainer, ds = _trained_run(tiny_scene, tmp_path / "run")
    trained = trained_grid_resolution(trainer.model)
    _rule_that_sizes_otherwise(monkeypatch)
    again = Trainer(trainer.cfg, tmp_path / "run", ds)
    shape = " x ".join(map(str, trained))
    with pytest.raises(ValueError, match=rf"trained with a {shape} grid and this config's training views size it"):
        again.try_resume()
