"""What every method of the tables is trained and scored with: the shared configuration, the
CPU and full budgets, the test views."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from stochastic_fields.config import ExperimentConfig, preset, set_dotted
from stochastic_fields.models.registry import scene_render_settings


#: The documented budget on a CPU (``budget="cpu"``, the default): every method trains 1000 steps
#: of 1024 rays per 762k training pixels (``cpu_budget_steps``: fern 1000, flower 1750 at the
#: paper split) on a grid capped at 250k cells and is scored on 4 test views spread over each
#: scene's test set (0.76M pixels per scene; MC-Dropout and the ensemble render each view 5
#: times). Fern and flower, all 9 methods: about 2 hours on 2 CPU cores. The grid's three
#: levels then hold 2.9M values (250k cells x 10 channels x 1.14), about as many as the
#: training pixels' colour values (fern: 4 views of 504x378 = 2.3M; flower: 7 views = 4.0M).
#: ``budget="full"`` is the llff preset (3000 steps, 2M cells, every test view): about 8x the
#: cost, for a GPU.
CPU_BUDGET_OVERRIDES: tuple[tuple[str, Any], ...] = (("train.iterations", 1000), ("field.grid_max_cells", 250_000))
#: The CPU budget's steps follow the training photos' pixels (docs/studies.md, study 28): the
#: overrides' 1000 steps are for the paper split's smallest training set, fern's four photos at
#: images_8 (762k pixels, which 1000 steps of 1024 rays pass over 1.34 times); a scene with more
#: training pixels gets as many passes, up to twice the steps (issue 40's bound): ``cpu_budget_steps``.
CPU_BUDGET_REFERENCE_PIXELS: int = 4 * 504 * 378
CPU_BUDGET_MAX_STEP_FACTOR: int = 2

#: The split protocols of the tables (``BenchmarkSettings.protocol``):
#: "paper": the S-NeRF paper's (every 5th view trains, the others test; docs/definitions.md §7);
#: "fewview": the few-view literature's (every 8th view tests, ``train_views`` of the others train,
#: spread evenly: RegNeRF's protocol, used by FreeNeRF, SparseNeRF, FSGS, CoR-GS);
#: "dense": every 8th view tests, all others train (the literature's dense LLFF protocol, and
#: ``train``'s capture split).
PROTOCOLS: tuple[str, ...] = ("paper", "fewview", "dense")
#: Every how-many-th view tests under the "fewview" and "dense" protocols.
LITERATURE_HOLDOUT_EVERY: int = 8


CPU_BUDGET_VIEWS: int = 4


@dataclass
class BenchmarkSettings:
    """What a benchmark run does besides the per-method configs."""

    budget: str = "cpu"
    """'cpu': the documented CPU budget (CPU_BUDGET_OVERRIDES, CPU_BUDGET_VIEWS test views); 'full': the llff preset, every test view."""
    images: str = "images_8"
    """LLFF image folder (docs/definitions.md §7: images_8, 504x378)."""
    iterations: int | None = None
    """Training steps for every method (None: the llff preset's)."""
    seed: int = 0
    """Seed of initialisation, batches, draws and evaluation renders."""
    device: str = "auto"
    """'auto', 'cpu' or 'cuda'."""
    max_views: int | None = None
    """Score N test views spread evenly over the test set (first and last included; None: the budget's)."""
    product_views: int = 1
    """Write view products (npz + PNG) for the first N test views."""
    timing: bool = True
    """Time one full-view render per method (Table 2)."""
    timing_repeats: int = 3
    """Timed renders of the view; the median is reported (shared machines are noisy), min and max kept."""
    tiny: bool = False
    """CI configuration: small grid, few samples and iterations (checks the pipeline, not the numbers)."""
    overrides: tuple[tuple[str, Any], ...] = ()
    """Extra (dotted config path, value) pairs applied to every method, after ``tiny``."""
    protocol: str = "paper"
    """The split (``PROTOCOLS``): "paper", "fewview" or "dense"."""
    train_views: int = 3
    """Training views of the "fewview" protocol (3, 6 or 9 in the literature)."""

    def describe_protocol(self) -> str:
        """One line for the tables' header."""
        if self.protocol == "fewview":
            return (f"few-view protocol: every {LITERATURE_HOLDOUT_EVERY}th view tests, {self.train_views} of the others "
                    "train, spread evenly (RegNeRF's)")
        if self.protocol == "dense":
            return f"dense protocol: every {LITERATURE_HOLDOUT_EVERY}th view tests, all others train"
        return "the S-NeRF paper's protocol: every 5th view trains, the others test"


def cpu_budget_steps(base_steps: int, training_pixels: int) -> int:
    """The CPU budget's training steps for ``training_pixels`` (the training photos' pixels summed):

        steps = min(F base, max(base, ceil(base P / P_ref)))      F = CPU_BUDGET_MAX_STEP_FACTOR

    (P_ref = ``CPU_BUDGET_REFERENCE_PIXELS``): as many passes over the training pixels as ``base_steps``
    give the reference set, never fewer steps than ``base_steps`` nor more than F times them. Paper
    split at images_8: fern (4 photos) 1000, flower (7) 1750; the dense protocol's 17 and 29 photos 2000."""
    if base_steps < 1 or training_pixels < 0:
        raise ValueError(f"need base_steps >= 1 and training_pixels >= 0, got {base_steps} and {training_pixels}")
    passes_steps = -(-base_steps * int(training_pixels) // CPU_BUDGET_REFERENCE_PIXELS)  # ceil, in integers
    return min(CPU_BUDGET_MAX_STEP_FACTOR * base_steps, max(base_steps, passes_steps))


def training_pixels(dataset) -> int:
    """The pixels of a dataset's training photos (every photo of a scene has one size)."""
    return len(dataset.train_indices) * int(dataset.height) * int(dataset.width)


def base_config(settings: BenchmarkSettings, dataset=None) -> ExperimentConfig:
    """The shared configuration: the ``llff`` preset (disparity spacing, 64 samples; S-NeRF renders K = 8 with Rao-Blackwellised colours) or,
    with ``tiny``, a configuration that runs in seconds. At the CPU budget the steps follow ``dataset``'s
    training pixels (``cpu_budget_steps``; the overrides' steps without a dataset). Scenes that are not forward-facing
    (``dataset.forward_facing`` False) sample linearly in distance and composite the dataset's
    background colour. ``settings.overrides`` apply last."""
    cfg = preset("llff")
    if dataset is not None and not getattr(dataset, "forward_facing", True):
        cfg.render.spacing = "linear"
        cfg.render = scene_render_settings(cfg.render, dataset)  # recorded as the colour the model composites
    # Every method renders the same dense samples with a fixed K: empty-space skipping and adaptive
    # K exist for S-NeRF only, so they are off here unless an override turns them on.
    for key in ("skip_empty_space", "adaptive_draws"):
        if hasattr(cfg.render, key):
            setattr(cfg.render, key, False)
    cfg.data.images = settings.images
    if settings.protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {settings.protocol!r}")
    if settings.protocol == "paper":
        cfg.data.split = "paper"  # the paper's protocol, explicitly (not the capture default)
        cfg.data.split_every = 5
    else:
        cfg.data.split = "fewview" if settings.protocol == "fewview" else "capture"
        cfg.data.holdout_every = LITERATURE_HOLDOUT_EVERY
        if settings.protocol == "fewview":
            if settings.train_views < 1:
                raise ValueError(f"the few-view protocol needs at least 1 training view, got {settings.train_views}")
            cfg.data.train_views = int(settings.train_views)
    cfg.train.seed = settings.seed
    cfg.train.device = settings.device
    if settings.tiny:
        cfg.train.iterations = 20
        cfg.train.rays_per_batch = 256
        cfg.train.eval_every = 0
        cfg.train.checkpoint_every = 0
        cfg.render.num_samples = 24
        cfg.render.num_draws = 8
        cfg.field.grid_max_cells = 24 ** 3
        cfg.field.grid_levels = 2
    if settings.budget not in ("cpu", "full"):
        raise ValueError(f"budget must be 'cpu' or 'full', got {settings.budget!r}")
    if settings.budget == "cpu" and not settings.tiny:
        for key, value in CPU_BUDGET_OVERRIDES:
            set_dotted(cfg, key, value)
        if dataset is not None:  # the steps follow the training pixels (study 28)
            cfg.train.iterations = cpu_budget_steps(cfg.train.iterations, training_pixels(dataset))
    if settings.iterations is not None:
        cfg.train.iterations = int(settings.iterations)
    for key, value in settings.overrides:
        set_dotted(cfg, key, value)
    return cfg


def select_views(test_views: list[int], settings: BenchmarkSettings) -> list[int]:
    """The scored test views: ``max_views`` (or the budget's count) spread evenly, ends included."""
    n = settings.max_views
    if n is None and settings.budget == "cpu" and not settings.tiny:
        n = CPU_BUDGET_VIEWS
    if n is None or n >= len(test_views):
        return list(test_views)
    if n <= 0:
        raise ValueError(f"max_views must be positive, got {n}")
    picks = np.unique(np.linspace(0, len(test_views) - 1, n).round().astype(int))
    return [test_views[i] for i in picks]


#: What the tables' depth numbers mean, beside the conventions of ``evaluation.evaluate``.
TABLE_CONVENTIONS: dict[str, str] = {
    "scored_points": ("depth is scored only on the capture points of the SCORE role (capture_points: blocks of "
                      "space disjoint from the points that train the depth likelihood)"),
    "depth_calibration": ("methods marked calibrated report depth_std recalibrated on every held-out (CALIBRATE and "
                          "SCORE) capture point seen from views halfway between neighbouring training views, intervals "
                          "at level p scaled by s(p)/s(0.683); their coverage, AUCE and depth NLL are cross-fitted "
                          "(each scored point judged by a fold map fitted without its SCORE block's fold); raw scores "
                          "under depth_raw/"),
}
