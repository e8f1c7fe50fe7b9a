"""Shared fixtures: the read-only reference data and a tiny generated synthetic scene."""

from __future__ import annotations

import sys

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Reference data lives beside the clone (``<repo>/../shared/data``), never inside it.
SHARED_DATA = (REPO_ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``<repo>/../shared/data`` (LLFF fern/flower, Blender lego); skips when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"reference data not found at {SHARED_DATA} (expected ../shared/data beside the repository)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """A small synthetic scene (20 views of 64x48, depth maps, scene.ply) in a session tmp dir.

    Load it with ``stochastic_fields.data.load_dataset(tiny_scene)``; split: every 5th view trains.
    """
    from stochastic_fields.data.synthetic import make_synthetic_scene

    return make_synthetic_scene(tmp_path_factory.mktemp("tiny_scene"), num_views=20, width=64, height=48, seed=0)


@pytest.fixture(scope="session")
def load_script():
    """``load_script("benchmarks/studies/train_cost.py")``: a script of the repository (not a package
    module) imported by path, as its command line would run it."""
    import importlib.util

    def load(relative: str):
        path = REPO_ROOT / relative
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # a dataclass of the script looks its module up there
        spec.loader.exec_module(module)
        return module

    return load


def tiny_cpu_config(iterations: int):
    """The tiny preset for a few CPU steps on ``tiny_scene``: 32 rays a step, an 8^3-cell grid."""
    from stochastic_fields.config import preset

    cfg = preset("tiny")
    cfg.train.iterations = iterations
    cfg.train.rays_per_batch = 32
    cfg.train.device = "cpu"
    cfg.field.grid_max_cells = 8 ** 3
    return cfg


def train_tiny_run(scene: Path, run_dir: Path, iterations: int = 30) -> Path:
    """The tiny preset trained ``iterations`` steps on ``scene`` (every 5th view trains) into
    ``run_dir``, one CPU thread, no checkpoints or evaluations on the way: a run for the scripts that
    re-score trained runs. Returns ``run_dir``."""
    import torch

    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.trainer import Trainer

    torch.set_num_threads(1)
    cfg = preset("tiny")
    cfg.train.iterations = iterations
    cfg.train.checkpoint_every = 0
    cfg.train.eval_every = 0
    cfg.data.path = str(scene)
    cfg.data.split, cfg.data.split_every = "paper", 5  # the config says what trained: every 5th view
    Trainer(cfg, run_dir, load_dataset(scene, split_every=5)).train(progress=False)
    return run_dir


def train_tiny_synthetic_run(run_dir: Path):
    """A tiny preset trained 200 steps in ``run_dir`` on a 20-view synthetic scene (every 5th view
    trains): (model, dataset). The slow calibration tests' shared run."""
    from stochastic_fields.config import preset
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data.synthetic import make_synthetic_scene
    from stochastic_fields.trainer import Trainer

    cfg = preset("tiny")
    cfg.train.iterations = 200
    cfg.train.rays_per_batch = 512
    cfg.render.num_samples = 24
    ds = load_dataset(make_synthetic_scene(run_dir / "scene", num_views=20, width=192, height=144, seed=0),
                      split_every=5)
    return Trainer(cfg, run_dir, ds).train(progress=False), ds


def rays_along_z(near, far):
    """RayBundle [R] (float64) from the origin along +z, with the given near and far distances [R]."""
    import torch

    from stochastic_fields.rays import RayBundle

    near = torch.as_tensor(near, dtype=torch.float64)
    far = torch.as_tensor(far, dtype=torch.float64)
    R = len(near)
    dirs = torch.zeros(R, 3, dtype=torch.float64)
    dirs[:, 2] = 1.0
    return RayBundle(origins=torch.zeros(R, 3, dtype=torch.float64), directions=dirs, near=near, far=far,
                     z_scale=torch.ones(R, dtype=torch.float64))


def grid_sample_read(table, shape: tuple[int, int, int], unit):
    """A grid level's trilinear values by torch's ``grid_sample`` (the reference of the gather): table
    [X Y Z, C] with cell (x, y, z) at row (z Y + y) X + x, unit points [P, 3] -> [P, C], border cells outside."""
    import torch.nn.functional as F

    X, Y, Z = shape
    vol = table.T.reshape(1, -1, Z, Y, X)
    out = F.grid_sample(vol, unit.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(table.shape[1], -1).T
