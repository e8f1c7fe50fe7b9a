"""A density counted per finest cell (``field.density_per='cell'``) does not depend on the scene's
unit of length.

The field outputs k * (its own density parameters) with k = 1 / L, L the finest cell's side
(``SceneRegion.cell_length``), and the KL priors scale with k. The same photos with every length
times 10 then train the same grid values; with the density per unit of length they do not (the
analysis "the scene's unit of length" in docs/studies.md measured what that costs).
"""

from __future__ import annotations

import math

import pytest
import torch

from stochastic_fields.config import ExperimentConfig, preset
from stochastic_fields.fields.base import FieldParams
from stochastic_fields.fields.grid import GridField
from stochastic_fields.losses import Priors, field_kl
from stochastic_fields.scene_region import SceneRegion
from stochastic_fields.validation import ConfigError


def test_cell_length_of_a_box_is_the_geometric_mean_of_its_cell_edges():
    region = SceneRegion("aabb", torch.tensor([[-1.0, 0.0, 2.0], [3.0, 1.0, 4.0]]))
    assert region.cell_length((8, 5, 40)) == pytest.approx((0.5 * 0.2 * 0.05) ** (1 / 3), rel=1e-9)
    assert region.cell_length((4, 1, 2)) == pytest.approx(1.0, rel=1e-9)


def test_cell_length_in_ndc_is_the_cell_at_the_centre_of_the_box():
    """Reference camera at the origin looking along +z: at the box centre c (NDC), depth
    z = 2 near / (1 - c_z), and the world edges of a cell are
    dx = (hi - lo)_x / res_x * z tan_x, dy likewise, and a step in c_z moves the point along its ray
    (x, y, z) = z (c_x tan_x, c_y tan_y, 1): |dz| = (hi - lo)_z / res_z * 2 near / (1 - c_z)^2 *
    sqrt(1 + (c_x tan_x)^2 + (c_y tan_y)^2)."""
    tan_x, tan_y, near = 0.6, 0.4, 2.0
    box = torch.tensor([[-0.8, -0.9, -0.5], [1.0, 0.7, 0.9]])
    region = SceneRegion("ndc", box, ref_w2c=torch.eye(4), ndc_scale=torch.tensor([tan_x, tan_y, near]))
    res = (30, 20, 50)
    c = (box[0] + box[1]).double() / 2
    ext = (box[1] - box[0]).double()
    z = 2 * near / (1 - c[2])
    edges = [ext[0] / res[0] * z * tan_x, ext[1] / res[1] * z * tan_y, ext[2] / res[2] * 2 * near / (1 - c[2]) ** 2
             * math.sqrt(1 + (c[0] * tan_x) ** 2 + (c[1] * tan_y) ** 2)]
    expected = float(math.prod(float(e) for e in edges) ** (1 / 3))
    assert region.cell_length(res) == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match="three positive integers"):
        region.cell_length((4, 0, 4))


def _grid(unit: float) -> GridField:
    torch.manual_seed(0)
    region = SceneRegion("aabb", torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    field = GridField(region, (8, 8, 8), num_levels=2, density_unit=unit)
    with torch.no_grad():
        for table in field.levels:
            table.normal_()
    return field


def test_a_grid_field_scales_its_density_by_its_unit_and_keeps_outside_empty():
    points = torch.cat([torch.rand(50, 3) * 1.8 - 0.9, torch.tensor([[1.5, 0.0, 0.0]])])
    dirs = torch.nn.functional.normalize(torch.randn(51, 3), dim=-1)
    one, k = _grid(1.0), _grid(25.0)
    with torch.no_grad():
        a, b = one(points, dirs), k(points, dirs)
    torch.testing.assert_close(b.density_loc[:-1], 25.0 * a.density_loc[:-1])
    torch.testing.assert_close(b.density_scale, 25.0 * a.density_scale)
    torch.testing.assert_close(b.rgb_loc, a.rgb_loc)
    assert float(b.density_loc[-1]) == float(a.density_loc[-1]) < -1e3  # outside: empty in both
    loc, scale = k.density_params(points)
    torch.testing.assert_close(loc, b.density_loc)
    torch.testing.assert_close(scale, b.density_scale)
    assert float(k.density_unit_factor()) == 25.0 and float(one.density_unit_factor()) == 1.0
    with pytest.raises(ValueError, match="density_unit"):
        _grid(0.0)


def test_the_priors_follow_the_unit_so_the_kl_is_that_of_the_fields_own_parameters():
    torch.manual_seed(1)
    params = FieldParams(density_loc=torch.randn(40, dtype=torch.float64) * 2,
                         density_scale=torch.rand(40, dtype=torch.float64) + 0.1,
                         rgb_loc=torch.randn(40, 3, dtype=torch.float64), rgb_scale=torch.rand(40, 3, dtype=torch.float64) + 0.1)
    priors = Priors().double()
    with torch.no_grad():
        priors.random_density_loc.fill_(-0.7)
        priors.observed_density_loc.fill_(0.4)
    k = 37.0
    scaled = FieldParams(params.density_loc * k, params.density_scale * k, params.rgb_loc, params.rgb_scale)
    for name in ("random", "observed"):
        plain = field_kl(params, getattr(priors, name)())
        torch.testing.assert_close(field_kl(scaled, getattr(priors, name)(k)), plain, rtol=1e-6, atol=1e-9)
        assert float((field_kl(scaled, getattr(priors, name)()) - plain).abs().max()) > 1e-2  # the unit matters


def test_a_checkpoint_from_before_the_unit_loads_with_density_per_unit_of_length():
    field = _grid(25.0)
    state = {k: v for k, v in _grid(1.0).state_dict().items() if k != "density_unit"}
    field.load_state_dict(state)
    assert float(field.density_unit_factor()) == 1.0


def test_density_per_cell_needs_the_grid_backend():
    cfg = ExperimentConfig()
    cfg.field.backend, cfg.field.density_per = "mlp", "cell"
    with pytest.raises(ConfigError, match="density_per"):
        ExperimentConfig(field=cfg.field)


def _train(scene, run_dir, density_per: str):
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    cfg.field.density_per = density_per
    cfg.train.iterations = 15
    cfg.train.rays_per_batch = 128
    cfg.train.checkpoint_every = 0
    cfg.render.num_samples = 16
    cfg.train.train_draws = 2
    trainer = Trainer(cfg, run_dir, load_dataset(scene, split_every=4))
    trainer.train(progress=False)
    return trainer.model


def _learned(model) -> dict[str, torch.Tensor]:
    """The trained parameters (grid tables, decoder, priors): what the unit must not change."""
    return {name: p.detach() for name, p in model.named_parameters()}


@pytest.mark.parametrize("density_per", ["cell", "unit"])
def test_the_same_photos_in_another_unit_train_the_same_grid_only_with_density_per_cell(
        tiny_scene, tmp_path, load_script, monkeypatch, density_per):
    from stochastic_fields.models import field_builder

    # the cells per axis follow the views up to a ceil that float rounding may tip by one cell
    # between units (72 against 73 here): one shape for both, so the tables can be compared
    monkeypatch.setitem(field_builder.RESOLUTION_RULES, "parallax", lambda *a, **k: (24, 24, 8))
    scaled_scene = load_script("benchmarks/studies/scene_scale_study.py").scaled_scene
    metres = _train(tiny_scene, tmp_path / "x1", density_per)
    decimetres = _train(scaled_scene(tiny_scene, tmp_path / "scene_x10", 10.0), tmp_path / "x10", density_per)
    a, b = _learned(metres), _learned(decimetres)
    assert a.keys() == b.keys()
    # Adam turns a rounding-sized gradient into a full step, so a few cells part by up to a step
    # or two (about 0.1 after 15 steps); what the unit changes moves the bulk of the cells
    tables = [n for n in a if ".levels." in n]
    gap = torch.cat([(a[n] - b[n]).abs().flatten() for n in tables])
    q50, q99 = float(gap.quantile(0.5)), float(gap.quantile(0.99))
    if density_per == "cell":
        assert float(metres.field.density_unit_factor()) == pytest.approx(10.0 * float(decimetres.field.density_unit_factor()), rel=1e-5)
        assert q50 < 1e-4 and q99 < 1e-2, (q50, q99)  # measured 6e-6 and 2e-3
        others = [n for n in a if n not in tables]
        assert max(float((a[n] - b[n]).abs().max()) for n in others) < 1e-2
    else:
        assert q50 > 1e-2 and q99 > 0.1, (q50, q99)  # measured 0.024 and 0.33
