"""Experiment configuration: nested dataclasses, one docstring per field, named presets, and an
argparse bridge so that ``stochastic-fields train --help`` lists every knob with its explanation.

Options on the command line are dotted paths: ``--train.iterations 3000 --render.num_draws 32``.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import textwrap
import typing
from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any, Literal

from .losses import LossConfig
from .renderer import RenderSettings


@dataclass
class DataConfig:
    """Which scene to learn and how to split it."""

    path: str = ""
    """Scene folder: LLFF (poses_bounds.npy + images_N/), Blender/nerfstudio (transforms*.json). Empty: the embedded synthetic scene, generated into the run folder."""
    images: str = "images_8"
    """LLFF image folder to read (images_8 is 504x378 for fern)."""
    split_every: int = 5
    """Training views are those with index % split_every == 0 (SPEC 7); the rest are test views."""
    downscale: int = 1
    """Integer downscale of Blender images (lego: 8 gives 100x100)."""


@dataclass
class FieldConfig:
    """The stochastic field backend."""

    backend: Literal["grid", "mlp"] = "grid"
    """'grid': fast multi-resolution voxel grid (CPU default); 'mlp': the paper's 8x256 MLP."""
    init_std: float = 1.0
    """Initial standard deviation of density and colour logits."""
    mlp_depth: int = 8
    """MLP trunk layers."""
    mlp_width: int = 256
    """MLP trunk width."""
    dropout: float = 0.0
    """Dropout after odd MLP layers (MC-Dropout baseline)."""
    grid_levels: int = 3
    """Grid levels, each half the resolution of the next."""
    grid_pixels_per_voxel: float = 1.5
    """Finest voxel size in pixel footprints (resolution follows the images)."""
    grid_max_cells: int = 2_000_000
    """Cap on cells of the finest level."""
    grid_feature_dim: int = 8
    """Colour feature channels per cell."""
    grid_decoder_width: int = 32
    """Hidden width of the colour decoder (0: colours stored directly, view-independent)."""
    grid_init_density_loc: float = -1.0
    """Initial mean of the pre-ReLU density everywhere."""


@dataclass
class TrainConfig:
    """Optimisation."""

    iterations: int = 3000
    """Optimiser steps."""
    rays_per_batch: int = 1024
    """Training rays per step."""
    train_draws: int = 8
    """K during training (Monte-Carlo likelihood)."""
    lr: float = 5e-3
    """Adam learning rate (grid cells use 10x)."""
    lr_final_factor: float = 0.1
    """Learning rate at the end, as a fraction of lr (exponential decay)."""
    tv_weight: float = 1e-3
    """Total-variation weight on grid cells (grid backend)."""
    seed: int = 0
    """Seed for initialisation, ray batches and draws."""
    eval_every: int = 500
    """Steps between quick evaluations on one test view (0: never)."""
    checkpoint_every: int = 500
    """Steps between checkpoints (written atomically; training resumes from the last)."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""


@dataclass
class ExperimentConfig:
    """Everything a run needs; saved as config.json in the run folder."""

    method: str = "snerf"
    """Method: snerf (S-NeRF) or a baseline (see stochastic_fields.models.registry)."""
    data: DataConfig = dc_field(default_factory=DataConfig)
    field: FieldConfig = dc_field(default_factory=FieldConfig)
    render: RenderSettings = dc_field(default_factory=RenderSettings)
    loss: LossConfig = dc_field(default_factory=LossConfig)
    train: TrainConfig = dc_field(default_factory=TrainConfig)


def preset(name: str) -> ExperimentConfig:
    """Named presets. ``demo``: the embedded synthetic scene in a few minutes on 2 CPU cores.
    ``llff``: forward-facing LLFF scenes (disparity spacing). ``tiny``: seconds, for tests."""
    cfg = ExperimentConfig()
    if name == "demo":
        cfg.train.iterations = 2000
        cfg.render.background = (1.0, 1.0, 1.0)
        cfg.data.split_every = 4
    elif name == "llff":
        cfg.data.images = "images_8"
        cfg.render.spacing = "disparity"
        cfg.render.num_samples = 64
        cfg.train.iterations = 3000
    elif name == "tiny":
        cfg.train.iterations = 150
        cfg.train.rays_per_batch = 256
        cfg.train.eval_every = 0
        cfg.train.checkpoint_every = 100
        cfg.render.num_samples = 32
        cfg.render.num_draws = 8
        cfg.render.background = (1.0, 1.0, 1.0)
        cfg.data.split_every = 4
    elif name != "default":
        raise ValueError(f"unknown preset {name!r}; choose from default, demo, llff, tiny")
    return cfg


PRESETS = ("default", "demo", "llff", "tiny")


# --------------------------------------------------------------------------- serialisation
def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def from_dict(cls: type, data: dict) -> Any:
    """Build dataclass ``cls`` from a (possibly partial) dict; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} option(s): {sorted(unknown)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        if dataclasses.is_dataclass(hints[f.name]):
            value = from_dict(hints[f.name], value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


def save_config(cfg: ExperimentConfig, path: Path) -> None:
    from .io_utils import atomic_write_text

    atomic_write_text(path, json.dumps(to_dict(cfg), indent=2))


def load_config(path: Path) -> ExperimentConfig:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read config {path}: {exc}") from exc
    return from_dict(ExperimentConfig, data)


# --------------------------------------------------------------------------- argparse bridge
def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after each field) of a dataclass."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    docs: dict[str, str] = {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    for node, nxt in zip(body, body[1:]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def _parser_for(hint: Any):
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is Literal:
        return str, [str(a) for a in args]
    if hint is bool:
        return (lambda s: {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}[s.lower()]), None
    if hint in (int, float, str):
        return hint, None
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1 and typing.get_origin(inner[0]) is tuple:
            return (lambda s: None if s.lower() == "none" else tuple(float(v) for v in s.split(","))), None
        if len(inner) == 1:
            base, choices = _parser_for(inner[0])
            return (lambda s: None if s.lower() == "none" else base(s)), choices
    if origin is tuple:
        return (lambda s: tuple(float(v) for v in s.split(","))), None
    return str, None


def add_config_arguments(parser: argparse.ArgumentParser, cls: type = ExperimentConfig, prefix: str = "") -> None:
    """Add one ``--group.name`` option per leaf field, help text from the field docstrings."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(hint):
            group_doc = (inspect.getdoc(hint) or "").split("\n")[0]
            add_config_arguments(parser.add_argument_group(f"{name} options", group_doc), hint, prefix=f"{name}.")
            continue
        conv, choices = _parser_for(hint)
        parser.add_argument(f"--{name}", dest=name, type=conv, choices=choices, default=argparse.SUPPRESS,
                            help=docs.get(f.name, "").replace("%", "%%") + " (default: %s)" % (f.default if f.default is not dataclasses.MISSING else "see preset"))


def apply_overrides(cfg: ExperimentConfig, args: argparse.Namespace) -> ExperimentConfig:
    """Set every dotted option present in ``args`` on ``cfg`` (in place); returns cfg."""
    for key, value in vars(args).items():
        if "." not in key and key != "method":
            continue
        obj = cfg
        parts = key.split(".")
        for p in parts[:-1]:
            obj = getattr(obj, p)
        if not hasattr(obj, parts[-1]):
            continue
        setattr(obj, parts[-1], value)
    return cfg
