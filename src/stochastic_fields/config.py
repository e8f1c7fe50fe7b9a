"""Experiment configuration: nested dataclasses, one docstring per field, named presets, and an
argparse bridge so that ``stochastic-fields train --help`` lists every knob with its explanation.

Options on the command line are dotted paths: ``--train.iterations 3000 --render.num_draws 32``.
"""

from __future__ import annotations

import argparse
import ast
import copy
import dataclasses
import inspect
import json
import textwrap
import typing
from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any, Literal

from . import validation as V
from .io_utils import atomic_write_text, read_json
from .settings import LOSS_CHECKS, RENDER_CHECKS, LossConfig, RenderSettings


@dataclass
class DataConfig:
    """Which scene to learn and how to split it."""

    path: str = ""
    """Scene folder: LLFF (poses_bounds.npy + images_N/), Blender/nerfstudio (transforms*.json). Empty: the embedded synthetic scene, generated into the run folder. Stored resolved (absolute) in the run's config.json."""
    images: str = "images_8"
    """LLFF image folder to read (images_8 is 504x378 for fern): a folder name inside the scene, no path separators. Range: a folder name (no '/', not '.' or '..')."""
    split: Literal["capture", "paper", "fewview", "views"] = "capture"
    """Which photos train. 'capture': every photo trains except every holdout_every-th (index % holdout_every == 0: photos 0, 8, 16, ... as LLFF's convention), which validate. 'paper': the paper's protocol (docs/definitions.md §7), about 20% train (index % split_every == 0) and the rest are test views; the benchmark tables use it (--preset paper). 'fewview': the few-view protocol of the literature (RegNeRF, FreeNeRF, FSGS...): every holdout_every-th photo tests and train_views of the others, spread evenly, train. 'views': the photos listed in train_list train, the rest are test views (a next-view loop adds the chosen photos to the list). Scenes whose files give the split (Blender's transforms_train/test.json) keep it."""
    holdout_every: int = 8
    """Capture split: views with index % holdout_every == 0 validate, the rest train. Range: an integer >= 2 and <= 1000000."""
    train_views: int = 3
    """Few-view split: how many of the photos that are not held out train (3, 6 or 9 in the literature). Range: an integer >= 1 and <= 1000000."""
    train_list: str = ""
    """'views' split: the training photos' indices, comma-separated (e.g. 0,5,10). Range: empty or comma-separated integers >= 0."""
    split_every: int = 5
    """Paper split: training views are those with index % split_every == 0 (docs/definitions.md §7); the rest are test views. Range: an integer >= 1 and <= 1000000."""
    downscale: int = 1
    """Integer downscale of Blender images (lego: 8 gives 100x100). LLFF scenes refuse values other than 1: choose data.images instead. Range: an integer >= 1 and <= 1024."""
    undistort: bool = True
    """LLFF scenes whose COLMAP model (sparse/0/cameras.bin) has lens distortion (fern, flower): resample the images to the pinhole camera of poses_bounds.npy (docs/capture.md). false leaves them distorted, as LLFF, NeRF and this package before it did (to reproduce those numbers). COLMAP and transforms.json captures are always undistorted and refuse false. Range: true or false."""

    def __post_init__(self) -> None:
        V.check_fields(self, DATA_CHECKS)


@dataclass
class FieldConfig:
    """The stochastic field backend."""

    backend: Literal["grid", "mlp"] = "grid"
    """'grid': fast multi-resolution voxel grid (CPU default); 'mlp': the paper's 8x256 MLP."""
    init_std: float = 1.0
    """Initial standard deviation of density and colour logits. Range: a finite number > 0."""
    mlp_depth: int = 8
    """MLP trunk layers. Range: an integer >= 1 and <= 64."""
    mlp_width: int = 256
    """MLP trunk width. Range: an integer >= 1 and <= 8192."""
    dropout: float = 0.0
    """Dropout after odd MLP layers (MC-Dropout baseline). Range: a finite number >= 0 and < 1."""
    grid_levels: int = 5
    """Grid levels, each half the resolution of the next (5 since study 51: two coarser levels under the same finest learn a capture faster; 3 before). Range: an integer >= 1 and <= 16."""
    grid_pixels_per_voxel: float = 1.5
    """Finest voxel size in pixels: the pixels a voxel spans along each axis in the view that sees that axis best (field.grid_resolution_rule 'parallax'), or in pixel footprints ('footprint'). Range: a finite number > 0."""
    grid_resolution_rule: Literal["footprint", "parallax"] = "parallax"
    """How the finest level's cells per axis follow the training views (before the grid_max_cells cap): 'parallax' (default since study 24): along each axis, grid_pixels_per_voxel pixels of motion in the view that sees a step along that axis move most (on a forward-facing capture the depth axis gets the cells its baselines resolve, the image axes the rest; docs/design.md); 'footprint' (before): a voxel spans grid_pixels_per_voxel pixel footprints along every axis."""
    grid_max_cells: int = 2_000_000
    """Cap on cells of the finest level. Range: an integer >= 8 and <= 2147483648."""
    grid_feature_dim: int = 16
    """Colour feature channels per cell (16 since study 43; 8 before). Range: an integer >= 1 and <= 1024."""
    grid_colour_levels: Literal["sum", "concat"] = "sum"
    """How the colour decoder reads the levels' colour features: 'sum' (the trilinear values of every level summed, grid_feature_dim inputs) or 'concat' (each level's own, grid_levels x grid_feature_dim inputs, as instant-NGP concatenates its levels; needs grid_decoder_width > 0)."""
    grid_decoder_width: int = 64
    """Hidden width of the colour decoder (0: colours stored directly, view-independent; 64 since study 43, 32 before). Range: an integer >= 0 and <= 8192."""
    grid_init_density_loc: float = -1.0
    """Initial mean of the pre-ReLU density everywhere. Range: a finite number."""
    density_per: Literal["unit", "cell"] = "unit"
    """What the grid's density is counted per: 'unit' (per unit of the capture's length: the same photos in other units train differently, docs/design.md) or 'cell' (optical depth per finest cell: the field outputs relu(g) / L with L the finest cell's side, SceneRegion.cell_length, and the KL priors scale with it, so training does not depend on the unit; grid backend only)."""
    density_heads: int = 2
    """Density heads of the grid: M alternative density fields around one centre, trajectory k drawing its density from head k mod M, each head starting from its own noise (2 since study 54: the paper split reconstructs better and the intervals narrow; 1 before, one density field). The grid backend's S-NeRF only: the MLP backend and the baselines (which draw no trajectories) build one density field. Range: an integer >= 1 and <= 16."""
    grid_coarse_to_fine: float = 0.0
    """Share of training over which the finer grid levels fade in, coarsest first (0: all from the start; a few-view regulariser). Range: a finite number >= 0 and <= 1."""

    def __post_init__(self) -> None:
        V.check_fields(self, FIELD_CHECKS)


@dataclass
class TrainConfig:
    """Optimisation."""

    iterations: int = 3000
    """Optimiser steps. Range: an integer >= 1 and <= 1000000000."""
    minutes: float = 0.0
    """Training budget in minutes of the training loop's wall clock (0: none, the steps decide). With a budget the schedule (learning-rate decay, coarse to fine) follows the larger of step / iterations and elapsed / budget, and training stops at whichever end comes first: N minutes end with the schedule complete on any machine, and the machine's speed sets the steps (a resumed run continues its clock; not with data-parallel training). Range: a finite number >= 0."""
    rays_per_batch: int = 1024
    """Training rays per step. Range: an integer >= 1 and <= 16777216."""
    train_draws: int = 8
    """K during training (Monte-Carlo likelihood). Range: an integer >= 1 and <= 4096."""
    lr: float = 5e-3
    """Adam learning rate (grid cells use 10x). Range: a finite number > 0."""
    lr_final_factor: float = 0.1
    """Learning rate at the end, as a fraction of lr (exponential decay). Range: a finite number > 0 and <= 1."""
    adam_beta2: float = 0.999
    """Adam's second-moment decay for every parameter but the colour's (the grid's lazy Adam too): 0.999 is Adam's own; 0.99 is Instant-NGP's for hash grids, its step size adapting within about a hundred steps. Range: a finite number > 0 and < 1."""
    adam_beta2_colour: float = 0.999
    """Adam's second-moment decay for the colour's parameters: a grid's colour channels and its colour decoder (a field without a grid has none apart; its parameters all take adam_beta2). Range: a finite number > 0 and < 1."""
    tv_weight: float = 1e-3
    """Total-variation weight on grid cells (grid backend). Range: a finite number >= 0."""
    holdout_fraction: float = 0.0
    """Share of each training view's pixel blocks held out from training; the colour std is recalibrated on them after training (stochastic_fields.holdout; 0: none). Range: a finite number >= 0 and <= 0.5."""
    holdout_block: int = 16
    """Side of the held-out pixel blocks, in pixels. Range: an integer >= 1 and <= 4096."""
    ray_sampling: Literal["uniform", "error"] = "uniform"
    """How a step chooses its training rays: 'uniform' (every training pixel alike) or 'error' (blocks of error_sampling_block pixels drawn by the squared colour error their last rays had, mixed with a uniform share; stochastic_fields.ray_sampling; S-NeRF and the deterministic NeRF, one process). Study 50 measured no gain on the captures at equal steps (+0.06 / +0.03 dB on fern / flower, fern's depth abs-rel +0.0025), so 'uniform' stays the default."""
    error_sampling_block: int = 4
    """Side in pixels of the error map's blocks (train.ray_sampling 'error'). Range: an integer >= 1 and <= 4096."""
    error_sampling_uniform_share: float = 0.25
    """Share of the error-guided draws spread uniformly over the training pixels, so every pixel stays reachable. Range: a finite number >= 0 and <= 1."""
    error_sampling_correction: float = 0.5
    """Power alpha of the likelihood weights (1 / (P q))^alpha of error-guided rays: 1 unbiased (importance sampling), 0 none (hard pixels count more). Range: a finite number >= 0 and <= 1."""
    seed: int = 0
    """Seed for initialisation, ray batches and draws. Range: an integer >= 0 and <= 9223372036854775807."""
    eval_every: int = 500
    """Steps between quick evaluations on one test view (0: never). Range: an integer >= 0 and <= 1000000000."""
    checkpoint_every: int = 500
    """Steps between checkpoints (written atomically; training resumes from the last). Range: an integer >= 0 and <= 1000000000."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:N'. Range: 'auto', 'cpu', 'cuda' or 'cuda:N'."""

    def __post_init__(self) -> None:
        V.check_fields(self, TRAIN_CHECKS)


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

    def __post_init__(self) -> None:
        validate_experiment(self)


def _folder_name(s: str) -> bool:
    return bool(s) and s not in (".", "..") and "/" not in s and "\\" not in s and "\0" not in s


def _device_name(s: str) -> bool:
    if s in ("auto", "cpu", "cuda"):
        return True
    return s.startswith("cuda:") and s[5:].isdigit()


def _index_list(s: str) -> bool:
    return s == "" or all(part.strip().isdigit() for part in s.split(","))


# Declared ranges: the one place each field is checked (on construction, on load, after CLI
# overrides); --help shows them as "[range: ...]".
DATA_CHECKS: dict[str, V.Checker] = {
    "path": V.text(),
    "images": V.text(pattern_rule="a folder name (no '/', not '.' or '..')", accept=_folder_name),
    "split": V.choice("capture", "paper", "fewview", "views"),
    "train_list": V.text(pattern_rule="empty or comma-separated integers >= 0", accept=_index_list),
    "train_views": V.integer(1, 10**6),
    "holdout_every": V.integer(2, 10**6),
    "split_every": V.integer(1, 10**6),
    "downscale": V.integer(1, 1024),
    "undistort": V.boolean(),
}
FIELD_CHECKS: dict[str, V.Checker] = {
    "backend": V.choice("grid", "mlp"),
    "grid_resolution_rule": V.choice("footprint", "parallax"),
    "init_std": V.real(0.0, lo_open=True),
    "mlp_depth": V.integer(1, 64),
    "mlp_width": V.integer(1, 8192),
    "dropout": V.real(0.0, 1.0, hi_open=True),
    "grid_levels": V.integer(1, 16),
    "grid_pixels_per_voxel": V.real(0.0, lo_open=True),
    "grid_max_cells": V.integer(8, 2**31),
    "grid_feature_dim": V.integer(1, 1024),
    "grid_decoder_width": V.integer(0, 8192),
    "grid_colour_levels": V.choice("sum", "concat"),
    "grid_init_density_loc": V.real(),
    "density_per": V.choice("unit", "cell"),
    "grid_coarse_to_fine": V.real(0.0, 1.0),
    "density_heads": V.integer(1, 16),
}
TRAIN_CHECKS: dict[str, V.Checker] = {
    "iterations": V.integer(1, 10**9),
    "minutes": V.real(0.0),
    "rays_per_batch": V.integer(1, 2**24),
    "train_draws": V.integer(1, 4096),
    "lr": V.real(0.0, lo_open=True),
    "lr_final_factor": V.real(0.0, 1.0, lo_open=True),
    "adam_beta2": V.real(0.0, 1.0, lo_open=True, hi_open=True),
    "adam_beta2_colour": V.real(0.0, 1.0, lo_open=True, hi_open=True),
    "tv_weight": V.real(0.0),
    "holdout_fraction": V.real(0.0, 0.5),
    "holdout_block": V.integer(1, 4096),
    "ray_sampling": V.choice("uniform", "error"),
    "error_sampling_block": V.integer(1, 4096),
    "error_sampling_uniform_share": V.real(0.0, 1.0),
    "error_sampling_correction": V.real(0.0, 1.0),
    "seed": V.integer(0, 2**63 - 1),
    "eval_every": V.integer(0, 10**9),
    "checkpoint_every": V.integer(0, 10**9),
    "device": V.text(pattern_rule="'auto', 'cpu', 'cuda' or 'cuda:N'", accept=_device_name),
}

#: Every method's name (``models.registry.METHODS`` builds each): S-NeRF and the baselines (docs/definitions.md §5).
METHOD_NAMES: tuple[str, ...] = ("snerf", "deterministic", "mc_dropout", "ensemble", "nerfw")

#: Methods whose renders report a variance over K trajectories: they need render.num_draws >= 2.
STOCHASTIC_METHODS: tuple[str, ...] = ("snerf",)


def validate_experiment(cfg: "ExperimentConfig") -> None:
    """Check every field of ``cfg`` against its declared range (ConfigError naming the dotted
    option and the value), and the rules that join fields."""
    if not isinstance(cfg.method, str) or cfg.method not in METHOD_NAMES:
        raise V.ConfigError("method", "one of " + ", ".join(sorted(METHOD_NAMES)), cfg.method)
    for f in dataclasses.fields(cfg):
        group = getattr(cfg, f.name)
        if dataclasses.is_dataclass(group):
            try:
                group.__post_init__()
            except V.ConfigError as exc:
                raise exc.prefixed(f"{f.name}.") from None
    if cfg.method in STOCHASTIC_METHODS and cfg.render.num_draws < 2:
        raise V.ConfigError("render.num_draws", f"an integer >= 2 for method {cfg.method!r} (the variance over K "
                            "draws is its uncertainty)", cfg.render.num_draws)
    if cfg.method == "snerf" and cfg.render.quadrature == "trapezoid" and cfg.render.skip_empty_space:
        raise V.ConfigError("render.skip_empty_space", "false with render.quadrature='trapezoid' (empty-space "
                            "skipping needs alpha compositing)", cfg.render.skip_empty_space)
    if cfg.render.depth_estimate == "median" and cfg.render.adaptive_draws:
        raise V.ConfigError("render.depth_estimate", "'mean' with render.adaptive_draws (the median reads every "
                            "trajectory's weights; adaptive K renders its draws in batches)", cfg.render.depth_estimate)
    if cfg.field.density_per == "cell" and cfg.field.backend != "grid":
        raise V.ConfigError("field.density_per", "'unit' with field.backend='mlp' (an MLP has no cells)",
                            cfg.field.density_per)
    if cfg.field.grid_coarse_to_fine > 0 and cfg.field.backend != "grid":
        raise V.ConfigError("field.grid_coarse_to_fine", "0 with field.backend='mlp' (it fades in grid levels)",
                            cfg.field.grid_coarse_to_fine)
    if cfg.field.grid_colour_levels == "concat" and (cfg.field.backend != "grid" or cfg.field.grid_decoder_width == 0):
        raise V.ConfigError("field.grid_colour_levels", "'sum' without a grid colour decoder (field.backend='grid' "
                            "and field.grid_decoder_width > 0)", cfg.field.grid_colour_levels)


#: Named presets as data: dotted option -> value, applied on top of the defaults (``--help``
#: lists them). ``demo``: the embedded synthetic scene in a few minutes on 2 CPU cores; ``llff``:
#: forward-facing LLFF scenes (disparity spacing); ``paper``: the paper's split (about 20% of the
#: views train, the benchmark tables' protocol); ``tiny``: seconds, for tests.
PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    "default": {},
    "demo": {"train.iterations": 2000, "render.background": (1.0, 1.0, 1.0), "data.split": "paper",
             "data.split_every": 4},
    "llff": {"data.images": "images_8", "render.spacing": "disparity", "render.num_samples": 64,
             "train.iterations": 3000, "loss.lambda_occlusion": 0.1},
    "tiny": {"train.iterations": 150, "train.rays_per_batch": 256, "train.eval_every": 0,
             "train.checkpoint_every": 100, "render.num_samples": 32, "render.num_draws": 8,
             "render.background": (1.0, 1.0, 1.0), "data.split": "paper", "data.split_every": 4},
    "paper": {"data.split": "paper", "data.split_every": 5},
}
PRESETS = tuple(PRESET_OVERRIDES)


def preset(name: str) -> ExperimentConfig:
    """The defaults with ``PRESET_OVERRIDES[name]`` applied (validated)."""
    if name not in PRESET_OVERRIDES:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    cfg = ExperimentConfig()
    for key, value in PRESET_OVERRIDES[name].items():
        set_dotted(cfg, key, value)
    validate_experiment(cfg)
    return cfg


def presets_help() -> str:
    """One line per preset with the options it sets (for ``--help``)."""
    lines = []
    for name, overrides in PRESET_OVERRIDES.items():
        items = ", ".join(f"{k}={','.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in overrides.items())
        lines.append(f"{name}: {items or 'the defaults'}")
    return "; ".join(lines)


def set_dotted(cfg: Any, key: str, value: Any) -> None:
    """Set ``cfg.<a>.<b> = value`` for ``key = "a.b"`` (no validation; ValueError for unknown keys)."""
    obj = cfg
    parts = key.split(".")
    for p in parts[:-1]:
        if not dataclasses.is_dataclass(obj) or p not in {f.name for f in dataclasses.fields(obj)}:
            raise ValueError(f"unknown option {key!r}")
        obj = getattr(obj, p)
    if not dataclasses.is_dataclass(obj) or parts[-1] not in {f.name for f in dataclasses.fields(obj)} \
            or dataclasses.is_dataclass(getattr(obj, parts[-1])):
        raise ValueError(f"unknown option {key!r}")
    setattr(obj, parts[-1], value)


# --------------------------------------------------------------------------- serialisation
def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    """Build dataclass ``cls`` from a (possibly partial) dict; unknown keys and values outside
    their declared ranges are a ValueError naming the dotted option."""
    if not isinstance(data, dict):
        raise ValueError(f"option group {prefix.rstrip('.') or cls.__name__}: expected a JSON object, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {cls.__name__} option(s): {sorted(prefix + str(u) for u in unknown)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        if dataclasses.is_dataclass(hints[f.name]):
            value = from_dict(hints[f.name], value, prefix=f"{prefix}{f.name}.")
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = value
    try:
        return cls(**kwargs)
    except V.ConfigError as exc:
        raise exc.prefixed(prefix) from None


def merge_dict(cfg: ExperimentConfig, data: Any, source: str) -> ExperimentConfig:
    """Apply a (partial) nested dict like config.json onto ``cfg`` (in place) and validate;
    errors name ``source`` and the dotted key."""
    def walk(obj: Any, d: Any, prefix: str) -> None:
        if not isinstance(d, dict):
            raise ValueError(f"{source}: {prefix.rstrip('.') or 'the top level'} must be a JSON object, got {d!r}")
        names = {f.name for f in dataclasses.fields(obj)}
        for key, value in d.items():
            if key not in names:
                raise ValueError(f"{source}: unknown option {prefix + str(key)!r}")
            if dataclasses.is_dataclass(getattr(obj, key)):
                walk(getattr(obj, key), value, f"{prefix}{key}.")
            else:
                setattr(obj, key, tuple(value) if isinstance(value, list) else value)
    walk(cfg, data, "")
    try:
        validate_experiment(cfg)
    except V.ConfigError as exc:
        raise ValueError(f"{source}: {exc}") from None
    return cfg


def read_config_file(path: str | Path) -> dict:
    """The JSON object in ``path`` (ValueError/FileNotFoundError naming the file)."""
    path = Path(path)
    data = read_json(path, "config file")
    if not isinstance(data, dict):
        raise ValueError(f"config {path}: expected a JSON object, got {type(data).__name__}")
    return data


def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """A nested config dict -> {"group.name": value}, sequences as tuples, so that a config read
    back from JSON (lists) compares equal to one from ``to_dict`` (tuples)."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = tuple(v) if isinstance(v, list) else v
    return out


def save_config(cfg: ExperimentConfig, path: Path) -> None:
    atomic_write_text(path, json.dumps(to_dict(cfg), indent=2))


#: Options whose default changed what a model is: a run's saved config without the key was
#: trained before the option existed and computed with this value (read by ``saved_config``;
#: the benchmark fingerprints count these values, not the defaults, as "unchanged", except where
#: ``stochastic_fields_bench.runner._FINGERPRINT_REFERENCE`` names the value stored runs left out).
LEGACY_VALUES: dict[str, Any] = {"loss.per_point_noise": False, "loss.noise_head_decoupled": False,
                                 "loss.lambda_depth": 0.0, "data.split": "paper",
                                 "field.grid_resolution_rule": "footprint", "render.colour_min_transmittance": 0.0,
                                 "field.density_heads": 1}


#: Options that a run saved before they existed computed with another option's value: the colour's
#: second-moment decay was ``train.adam_beta2`` (every parameter's) until ``train.adam_beta2_colour``.
LEGACY_SAME_AS: dict[str, str] = {"train.adam_beta2_colour": "train.adam_beta2"}


def legacy_same_as_values(flat: dict[str, Any]) -> dict[str, Any]:
    """Each ``LEGACY_SAME_AS`` key a flat saved config (dotted keys) lacks, with its source's value."""
    return {k: flat[src] for k, src in LEGACY_SAME_AS.items() if k not in flat and src in flat}


def fill_legacy_same_as(flat: dict[str, Any]) -> dict[str, Any]:
    """A flat saved config with each ``LEGACY_SAME_AS`` key it lacks set to its source's value."""
    return {**flat, **legacy_same_as_values(flat)}


def saved_config(data: dict) -> ExperimentConfig:
    """The config of a saved run (config.json, a checkpoint's copy): ``from_dict`` with each
    ``LEGACY_VALUES`` key the run's file lacks set to its legacy value, each ``LEGACY_SAME_AS`` key
    to its source's value."""
    data = copy.deepcopy(data)
    for dotted, value in {**LEGACY_VALUES, **legacy_same_as_values(flatten(data))}.items():
        *groups, name = dotted.split(".")
        node = data
        for g in groups:
            node = node.setdefault(g, {}) if isinstance(node, dict) else node
        if isinstance(node, dict) and name not in node:
            node[name] = value
    return from_dict(ExperimentConfig, data)


def load_config(path: Path) -> ExperimentConfig:
    """A saved run's config.json (``saved_config``); errors name the file."""
    data = read_config_file(path)
    try:
        return saved_config(data)
    except ValueError as exc:
        raise ValueError(f"config {path}: {exc}") from None


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


BOOL_WORDS: dict[str, bool] = {"true": True, "on": True, "yes": True, "1": True,
                               "false": False, "off": False, "no": False, "0": False}


def parse_bool(text: str) -> bool:
    """on/off, true/false, yes/no, 1/0 (any case) -> bool; argparse error otherwise."""
    try:
        return BOOL_WORDS[text.strip().lower()]
    except KeyError:
        raise argparse.ArgumentTypeError(f"expected one of on/off, true/false, yes/no, 1/0, got {text!r}") from None


def _parse_float_tuple(text: str) -> tuple[float, ...] | None:
    if text.strip().lower() == "none":
        return None
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers like 1,1,1 (or none), got {text!r}") from None


def _typed(base: type):
    def parse(text: str):
        try:
            return base(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if base is int else 'a number'}, "
                                             f"got {text!r}") from None
    return parse


def _parser_for(hint: Any):
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is Literal:
        return str, [str(a) for a in args]
    if hint is bool:
        return parse_bool, None
    if hint in (int, float):
        return _typed(hint), None
    if hint is str:
        return str, None
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1 and typing.get_origin(inner[0]) is tuple:
            return _parse_float_tuple, None
        if len(inner) == 1:
            base, choices = _parser_for(inner[0])
            return (lambda s: None if s.lower() == "none" else base(s)), choices
    if origin is tuple:
        return _parse_float_tuple, None
    return str, None


def _checks_of(cls: type) -> dict:
    return {DataConfig: DATA_CHECKS, FieldConfig: FIELD_CHECKS, TrainConfig: TRAIN_CHECKS,
            RenderSettings: RENDER_CHECKS, LossConfig: LOSS_CHECKS}.get(cls, {})


def add_config_arguments(parser: argparse.ArgumentParser, cls: type = ExperimentConfig, prefix: str = "") -> None:
    """Add one ``--group.name`` option per leaf field (also spelled ``--group.na-me``), help
    text from the field docstrings plus the declared range."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    checks = _checks_of(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(hint):
            group_doc = (inspect.getdoc(hint) or "").split("\n")[0]
            add_config_arguments(parser.add_argument_group(f"{name} options", group_doc), hint, prefix=f"{name}.")
            continue
        conv, choices = _parser_for(hint)
        spellings = [f"--{name}"] + ([f"--{name.replace('_', '-')}"] if "_" in name else [])
        default = f.default if f.default is not dataclasses.MISSING else "see preset"
        doc = docs.get(f.name, "")
        rule = (f" [range: {checks[f.name].rule}]" if f.name in checks and choices is None
                and checks[f.name].rule != "a string" and "Range:" not in doc else "")
        parser.add_argument(*spellings, dest=name, type=conv, choices=choices, default=argparse.SUPPRESS,
                            help=(doc + rule).replace("%", "%%") + " (default: %s)" % (default,))


def apply_overrides(cfg: ExperimentConfig, args: argparse.Namespace) -> ExperimentConfig:
    """Set every dotted option present in ``args`` on ``cfg`` (in place) and validate the
    result (ValueError naming the option and value); returns cfg."""
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
    validate_experiment(cfg)
    return cfg
