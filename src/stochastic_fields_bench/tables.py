"""The paper's Tables 1-3 on real scenes, side by side, plus the stronger metrics (issue 4, SPEC 5-8).

Protocol (SPEC 7): every method is trained on the same scene, split (``index % 5 == 0`` trains),
budget (iterations, rays per batch, samples per ray, field backend and resolution) and seed,
then scored on every test view. One configuration per method for every scene: no per-scene
tuning.

Layout of an output folder::

    <out>/<scene>/<method>/        one run folder per method (Trainer: config.json, checkpoint.pt,
                                    train_log.jsonl) plus
        stages.json                 finished stages with the fingerprint of their inputs
        metrics.json                per-view and pooled scores, conventions
        curves.npz                  pooled sparsification / calibration curves (for the plots)
        timing.json                 render time of one full view (Table 2)
        views/                      products of the first ``product_views`` test views
    <out>/tables.json, tables.md    Tables 1-5 with conventions and the paper's figures
    <out>/plots/<scene>_*.png       sparsification and calibration plots

Stages (train -> eval -> timing) are resumable: a stage whose fingerprint matches is skipped, an
interrupted training resumes from its checkpoint, and a finished table can be rebuilt from the
files alone (``collect_results``).

Scores (per test view, then mean over views; undefined values are counted, not averaged):
``evaluate.score_view`` (PSNR, SSIM, NLL at the variance floor, Pearson/Spearman of per-pixel
MSE vs variance, AUSE-RMSE) plus AUSE-MAE, normalised AUSEs, colour AUCE, and depth scores
against COLMAP points (LLFF) or the dataset's depth maps (synthetic). Pooled values (every test
pixel of the scene at once) are kept beside them. A method whose uncertainty map is constant
(the deterministic NeRF) has undefined correlations and AUSE: ranking by a constant is
arbitrary.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import platform
import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from stochastic_fields.config import ExperimentConfig, flatten, preset, to_dict
from stochastic_fields.io_utils import atomic_path, atomic_write_text
from stochastic_fields import metrics as M
from stochastic_fields.view_maps import draws_summary

# --------------------------------------------------------------------------------------------
# methods and the paper's figures
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MethodSpec:
    """A column of the tables: a registry method plus config overrides (dotted paths)."""

    name: str
    method: str
    label: str
    overrides: tuple[tuple[str, Any], ...] = ()
    calibrate: bool = False
    """Fit the depth recalibration from the capture points (``stochastic_fields.calibration``) after
    training and score with it (raw scores kept as ``depth_raw/``)."""


#: The paper's S-NeRF objective and colour variance (SPEC 3, 4): fixed pixel noise, the variance over
#: the K trajectories, no depth likelihood (explicit, since the package defaults differ).
PAPER_SNERF: tuple[tuple[str, Any], ...] = (("loss.learn_likelihood_std", False),
                                            ("render.colour_variance", "epistemic"), ("loss.lambda_depth", 0.0))

METHOD_SPECS: dict[str, MethodSpec] = {
    "deterministic": MethodSpec("deterministic", "deterministic", "NeRF (deterministic)"),
    "mc_dropout": MethodSpec("mc_dropout", "mc_dropout", "MC-DO", (("field.dropout", 0.2),)),
    "ensemble": MethodSpec("ensemble", "ensemble", "D. Ens."),
    "nerfw": MethodSpec("nerfw", "nerfw", "NeRF-W"),
    "snerf_default": MethodSpec("snerf_default", "snerf", "S-NeRF (default)", (), calibrate=True),
    "snerf": MethodSpec("snerf", "snerf", "S-NeRF (paper)", (("loss.kl", "full"),) + PAPER_SNERF),
    "snerf_predictive": MethodSpec("snerf_predictive", "snerf", "S-NeRF + learned noise",
                                   (("loss.kl", "full"), ("loss.learn_likelihood_std", True),
                                    ("render.colour_variance", "predictive"), ("loss.lambda_depth", 0.0)),
                                   calibrate=True),
    "snerf_kl_none": MethodSpec("snerf_kl_none", "snerf", "S-NeRF w/o KL", (("loss.kl", "none"),) + PAPER_SNERF),
    "snerf_kl_fixed_prior": MethodSpec("snerf_kl_fixed_prior", "snerf", "S-NeRF w/ KL (fixed prior)",
                                       (("loss.kl", "fixed_prior"),) + PAPER_SNERF),
}
TABLE1_METHODS: tuple[str, ...] = ("mc_dropout", "ensemble", "nerfw", "snerf", "snerf_predictive", "snerf_default",
                                   "deterministic")
TABLE3_METHODS: tuple[str, ...] = ("snerf_kl_none", "snerf_kl_fixed_prior", "snerf")
DEFAULT_METHODS: tuple[str, ...] = ("deterministic", "mc_dropout", "ensemble", "nerfw", "snerf", "snerf_predictive",
                                    "snerf_default", "snerf_kl_none", "snerf_kl_fixed_prior")
DEFAULT_SCENES: tuple[str, ...] = ("fern", "flower")

#: Paper Table 1 (LLFF): scene -> method -> (NLL, Pearson correlation). NLL convention unstated.
PAPER_TABLE1: dict[str, dict[str, tuple[float, float]]] = {
    "fern": {"mc_dropout": (4.90, 0.50), "ensemble": (2.47, 0.65), "nerfw": (2.16, 0.59), "snerf": (2.01, 0.69)},
    "flower": {"mc_dropout": (4.63, 0.38), "ensemble": (1.63, 0.59), "nerfw": (1.71, 0.49), "snerf": (1.27, 0.63)},
    "horns": {"mc_dropout": (4.18, 0.43), "ensemble": (2.17, 0.50), "nerfw": (0.78, 0.50), "snerf": (0.60, 0.70)},
}
#: Paper Table 2: seconds to render one 500x400 view (their GPU; for context only).
PAPER_TABLE2: dict[str, float] = {"mc_dropout": 38.26, "ensemble": 34.77, "nerfw": 7.08, "snerf": 6.06}
#: Paper Table 3 (ablation): scene -> method -> (NLL, Pearson).
PAPER_TABLE3: dict[str, dict[str, tuple[float, float]]] = {
    "fern": {"snerf_kl_none": (2.46, 0.51), "snerf_kl_fixed_prior": (1.63, 0.66), "snerf": (2.01, 0.69)},
    "flower": {"snerf_kl_none": (1.41, 0.54), "snerf_kl_fixed_prior": (2.18, 0.51), "snerf": (1.27, 0.63)},
    "horns": {"snerf_kl_none": (3.08, 0.53), "snerf_kl_fixed_prior": (0.75, 0.64), "snerf": (0.60, 0.70)},
}


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------


#: The documented budget on a CPU (``budget="cpu"``, the default): every method trains 1000 steps
#: of 1024 rays on a grid capped at 250k cells and is scored on 4 test views spread over each
#: scene's test set (0.76M pixels per scene; MC-Dropout and the ensemble render each view 5
#: times). Fern and flower, all 8 methods: about 1.5 hours on 2 CPU cores. The grid's three
#: levels then hold 2.9M values (250k cells x 10 channels x 1.14), about as many as the
#: training pixels' colour values (fern: 4 views of 504x378 = 2.3M; flower: 7 views = 4.0M).
#: ``budget="full"`` is the llff preset (3000 steps, 2M cells, every test view): about 8x the
#: cost, for a GPU.
CPU_BUDGET_OVERRIDES: tuple[tuple[str, Any], ...] = (("train.iterations", 1000), ("field.grid_max_cells", 250_000))
CPU_BUDGET_VIEWS: int = 4


@dataclass
class BenchmarkSettings:
    """What a benchmark run does besides the per-method configs."""

    budget: str = "cpu"
    """'cpu': the documented CPU budget (CPU_BUDGET_OVERRIDES, CPU_BUDGET_VIEWS test views); 'full': the llff preset, every test view."""
    images: str = "images_8"
    """LLFF image folder (SPEC 7: images_8, 504x378)."""
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


def set_dotted(cfg: Any, key: str, value: Any) -> None:
    """``set_dotted(cfg, "loss.kl", "none")``; ValueError naming an unknown path."""
    obj = cfg
    parts = key.split(".")
    for p in parts[:-1]:
        if not hasattr(obj, p):
            raise ValueError(f"unknown config path {key!r} (no {p!r})")
        obj = getattr(obj, p)
    if not hasattr(obj, parts[-1]):
        raise ValueError(f"unknown config path {key!r} (no {parts[-1]!r})")
    setattr(obj, parts[-1], value)


def base_config(settings: BenchmarkSettings, dataset=None) -> ExperimentConfig:
    """The shared configuration: the ``llff`` preset (disparity spacing, 64 samples, K = 16) or,
    with ``tiny``, a configuration that runs in seconds. Scenes that are not forward-facing
    (``dataset.forward_facing`` False) sample linearly in distance and composite the dataset's
    background colour. ``settings.overrides`` apply last."""
    cfg = preset("llff")
    if dataset is not None and not getattr(dataset, "forward_facing", True):
        cfg.render.spacing = "linear"
        background = getattr(dataset, "background", None)
        cfg.render.background = None if background is None else tuple(float(c) for c in background)
    # Every method renders the same dense samples with a fixed K: empty-space skipping and adaptive
    # K exist for S-NeRF only, so they are off here unless an override turns them on.
    for key in ("skip_empty_space", "adaptive_draws"):
        if hasattr(cfg.render, key):
            setattr(cfg.render, key, False)
    cfg.data.images = settings.images
    cfg.data.split_every = 5
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


def method_config(spec: MethodSpec, base: ExperimentConfig, scene_path: Path) -> ExperimentConfig:
    cfg = copy.deepcopy(base)
    cfg.method = spec.method
    cfg.data.path = str(scene_path)
    for key, value in spec.overrides:
        set_dotted(cfg, key, value)
    return cfg


#: Which capture points score depth (capture_points: the SCORE role of the spatial split); part of
#: the eval fingerprint so that runs scored on every point are re-scored.
SCORED_POINTS = "score-role blocks"

#: How the depth recalibration is fitted (part of the calibrate fingerprint: a new protocol refits).
CALIBRATION_PROTOCOL = "calibrate-role capture points from views halfway between neighbouring training views"

#: Config entries that do not change what a run computes (left out of fingerprints).
_NON_SEMANTIC = ("train.device", "train.eval_every", "train.checkpoint_every", "render.chunk_rays", "data.path")


def _semantic(flat: dict[str, Any]) -> dict[str, Any]:
    """Entries that change what a run computes, without those equal to the dataclass defaults:
    an option added later with a default that keeps the old behaviour changes no fingerprint."""
    defaults = flatten(to_dict(ExperimentConfig()))
    return {k: v for k, v in flat.items() if k not in _NON_SEMANTIC and not (k in defaults and defaults[k] == v)}


def config_fingerprint(cfg: ExperimentConfig, *extra: Any) -> str:
    flat = _semantic(flatten(to_dict(cfg)))
    text = json.dumps([flat, list(extra)], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_compatible(run_dir: Path, cfg: ExperimentConfig) -> None:
    """A run folder may only be resumed with the same config (more iterations are allowed).
    Options missing from the saved config count as their defaults."""
    saved = Path(run_dir) / "config.json"
    if not saved.exists():
        return
    old = _semantic(flatten(json.loads(saved.read_text())))
    new = _semantic(flatten(to_dict(cfg)))
    differ = sorted(k for k in set(old) | set(new) if k != "train.iterations" and old.get(k) != new.get(k))
    if differ:
        raise ValueError(f"run folder {run_dir} was trained with a different configuration "
                         f"(differs in {differ}); use another --out or remove the folder")


# --------------------------------------------------------------------------------------------
# stages
# --------------------------------------------------------------------------------------------


def _read_json(path: Path) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read {path}: {exc}") from exc


def load_stages(run_dir: Path) -> dict:
    path = Path(run_dir) / "stages.json"
    return _read_json(path) if path.exists() else {}


def save_stages(run_dir: Path, stages: dict) -> None:
    atomic_write_text(Path(run_dir) / "stages.json", json.dumps(stages, indent=2, default=float))


def _peak_memory() -> dict[str, float]:
    """Process peak resident memory (MiB, since the process started) and CUDA peak allocation."""
    out = {"process_peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
    if torch.cuda.is_available():
        out["cuda_peak_allocated_mib"] = torch.cuda.max_memory_allocated() / 2 ** 20
    return out


def _reset_cuda_peak() -> None:
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# --------------------------------------------------------------------------------------------
# evaluation of one trained model
# --------------------------------------------------------------------------------------------


def _unpack(data, prefix: str, cls):
    kwargs = {}
    for f in dataclasses.fields(cls):
        v = data[f"{prefix}.{f.name}"]
        kwargs[f.name] = v if v.ndim else v.item()
    return cls(**kwargs)


#: What the tables' depth numbers mean, beside the conventions of ``evaluation.evaluate``.
TABLE_CONVENTIONS: dict[str, str] = {
    "scored_points": ("depth is scored only on the capture points of the SCORE role (capture_points: blocks of "
                      "space disjoint from the points that train the depth likelihood and fit the recalibration)"),
    "depth_calibration": ("methods marked calibrated report depth_std recalibrated on the CALIBRATE capture points "
                          "seen from training views, intervals at level p scaled by s(p)/s(0.683); raw scores under "
                          "depth_raw/"),
}


def evaluate_run(model, dataset, out_dir: Path, *, views: Sequence[int] | None = None, seed: int = 0,
                 sparse_depth: dict | None = None, product_views: int = 1, progress: bool = True,
                 calibration=None) -> dict:
    """``evaluation.evaluate`` of one trained model with the tables' conventions (the model's own
    render options; products of the first ``product_views`` views)."""
    from stochastic_fields.evaluation import evaluate

    return evaluate(model, dataset, out_dir, views=views, seed=seed, sparse_depth=sparse_depth,
                    product_views=product_views, calibration=calibration, conventions=TABLE_CONVENTIONS,
                    progress=progress)


def time_render(model, dataset, view: int, *, seed: int = 0, repeats: int = 3) -> dict[str, Any]:
    """Wall time of rendering one full view: median of ``repeats`` renders after an untimed
    warm-up chunk, with min/max, rays/s and memory."""
    if repeats < 1:
        raise ValueError(f"timing repeats must be >= 1, got {repeats}")
    device = next(model.parameters()).device
    rays = dataset.rays(view).to(device)
    gen = torch.Generator(device=device).manual_seed(seed)
    H, W = rays.shape
    options = model.default_render_options()
    warm = rays.flatten()[: options.chunk_rays].reshape(1, -1)
    model.render_view(warm, options, generator=gen)
    _reset_cuda_peak()
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        maps = model.render_view(rays, options, generator=gen)
        _sync(device)
        times.append(time.perf_counter() - t0)
    seconds = float(np.median(times))
    return {"view": int(view), "height": H, "width": W, "render_s": seconds, "render_s_min": min(times),
            "render_s_max": max(times), "repeats": repeats, "rays_per_s": H * W / seconds,
            **draws_summary(maps["num_draws"]), "device": str(device),
            "torch_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
            **_peak_memory()}


# --------------------------------------------------------------------------------------------
# running methods on scenes
# --------------------------------------------------------------------------------------------


def resolve_scene(scene: str, data_root: Path | None) -> Path:
    """A scene name under ``data_root`` or a path to a scene folder; FileNotFoundError if neither."""
    p = Path(scene)
    if p.is_dir():
        return p
    if data_root is not None and (Path(data_root) / scene).is_dir():
        return Path(data_root) / scene
    raise FileNotFoundError(f"scene {scene!r} is neither a folder nor under {data_root}")


def run_method(spec: MethodSpec, dataset, scene_path: Path, run_dir: Path, settings: BenchmarkSettings, *,
               views: Sequence[int], sparse_depth: dict | None, progress: bool = True,
               log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train (or resume), evaluate and time one method on one scene; skips finished stages."""
    from stochastic_fields.trainer import Trainer, load_trained_model

    run_dir = Path(run_dir)
    cfg = method_config(spec, base_config(settings, dataset), scene_path)
    check_compatible(run_dir, cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    stages = load_stages(run_dir)
    fp_train = config_fingerprint(cfg)
    fp_cal = config_fingerprint(cfg, "calibrate", settings.seed, CALIBRATION_PROTOCOL)
    fp_eval = config_fingerprint(cfg, "eval", list(views), settings.seed, sparse_depth is not None, SCORED_POINTS,
                                 spec.calibrate)
    fp_time = config_fingerprint(cfg, "timing", settings.seed, settings.timing_repeats)
    tag = f"{dataset.name}/{spec.name}"
    model = None
    if stages.get("train", {}).get("fingerprint") != fp_train:
        log(f"[{tag}] train: {cfg.train.iterations} iterations ({cfg.field.backend} backend)")
        _reset_cuda_peak()
        trainer = Trainer(cfg, run_dir, dataset)
        model = trainer.train(progress=progress)
        stages["train"] = {"fingerprint": fp_train, "steps": trainer.step, "train_s": trainer.elapsed,
                           "num_parameters": sum(p.numel() for p in model.parameters()), **_peak_memory()}
        stages.pop("eval", None)
        stages.pop("timing", None)
        save_stages(run_dir, stages)
    else:
        log(f"[{tag}] train: done ({stages['train']['steps']} steps), skipped")

    def loaded():
        nonlocal model
        if model is None:
            model = load_trained_model(run_dir, dataset=dataset, device=settings.device)[1]
        return model

    calibration = None
    if spec.calibrate:
        from stochastic_fields.calibration import calibrate_run, describe, load_run_calibration

        calibration = load_run_calibration(run_dir)
        if stages.get("calibrate", {}).get("fingerprint") != fp_cal:
            t0 = time.perf_counter()
            try:
                calibration = calibrate_run(run_dir, model=loaded(), dataset=dataset, seed=settings.seed)
                stages["calibrate"] = {"fingerprint": fp_cal, "calibrate_s": time.perf_counter() - t0}
                log(f"[{tag}] calibrate: {describe(calibration)}")
            except ValueError as exc:  # too few capture points: scored raw, and the reason kept
                (run_dir / "calibration.json").unlink(missing_ok=True)
                calibration = None
                stages["calibrate"] = {"fingerprint": fp_cal, "failed": str(exc)}
                log(f"[{tag}] calibrate: not fitted ({exc})")
            stages.pop("eval", None)
            save_stages(run_dir, stages)
        else:
            log(f"[{tag}] calibrate: done, skipped")
    if stages.get("eval", {}).get("fingerprint") != fp_eval or not (run_dir / "metrics.json").exists():
        log(f"[{tag}] eval: {len(views)} test views")
        t0 = time.perf_counter()
        evaluate_run(loaded(), dataset, run_dir, views=views, seed=settings.seed, sparse_depth=sparse_depth,
                     product_views=settings.product_views, progress=progress, calibration=calibration)
        stages["eval"] = {"fingerprint": fp_eval, "eval_s": time.perf_counter() - t0}
        save_stages(run_dir, stages)
    else:
        log(f"[{tag}] eval: done, skipped")
    if settings.timing:
        if stages.get("timing", {}).get("fingerprint") != fp_time or not (run_dir / "timing.json").exists():
            log(f"[{tag}] timing: one full view")
            timing = time_render(loaded(), dataset, views[0], seed=settings.seed, repeats=settings.timing_repeats)
            atomic_write_text(run_dir / "timing.json", json.dumps(timing, indent=2))
            stages["timing"] = {"fingerprint": fp_time}
            save_stages(run_dir, stages)
        else:
            log(f"[{tag}] timing: done, skipped")
    return load_method_result(run_dir)


def load_method_result(run_dir: Path) -> dict[str, Any]:
    """{"metrics", "stages", "timing" (or None), "config", "curves" (dict of arrays)} of a run folder."""
    run_dir = Path(run_dir)
    curves_path = run_dir / "curves.npz"
    curves = {}
    if curves_path.exists():
        with np.load(curves_path) as data:
            curves = {k: data[k] for k in data.files}
    timing_path = run_dir / "timing.json"
    return {"metrics": _read_json(run_dir / "metrics.json"), "stages": load_stages(run_dir),
            "timing": _read_json(timing_path) if timing_path.exists() else None,
            "config": _read_json(run_dir / "config.json"), "curves": curves}


def run_scene(scene: str, methods: Sequence[str], out_root: Path, settings: BenchmarkSettings, *,
              data_root: Path | None = None, progress: bool = True,
              log: Callable[[str], None] = print) -> dict[str, dict]:
    """Every method on one scene: {method: load_method_result(...)}."""
    from stochastic_fields.data import load_dataset
    from stochastic_fields.data import detect_format

    scene_path = resolve_scene(scene, data_root)
    kind = detect_format(scene_path)
    if kind == "llff":
        dataset = load_dataset(scene_path, images=settings.images, split_every=5)
    else:
        dataset = load_dataset(scene_path, split_every=5)
    views = select_views(list(dataset.test_indices), settings)
    sparse = None
    if getattr(dataset, "depths", None) is None:
        from stochastic_fields.capture_points import SCORE, load_capture_points, sparse_depth_for_role

        points = load_capture_points(dataset)
        if points is None:
            log(f"[{dataset.name}] no sparse depth ground truth: the scene has no COLMAP points")
        else:
            sparse = sparse_depth_for_role(dataset, points, views, SCORE)
    name = dataset.name
    results = {}
    for m in methods:
        if m not in METHOD_SPECS:
            raise ValueError(f"unknown method {m!r}; choose from {sorted(METHOD_SPECS)}")
        results[m] = run_method(METHOD_SPECS[m], dataset, scene_path, Path(out_root) / name / m, settings,
                                views=views, sparse_depth=sparse, progress=progress, log=log)
    return results


def collect_results(out_root: Path, scenes: Sequence[str], methods: Sequence[str]) -> dict[str, dict[str, dict]]:
    """Results of finished runs from disk: {scene: {method: load_method_result}} (missing ones skipped)."""
    out: dict[str, dict[str, dict]] = {}
    for scene in scenes:
        for m in methods:
            run_dir = Path(out_root) / Path(scene).name / m
            if (run_dir / "metrics.json").exists():
                out.setdefault(Path(scene).name, {})[m] = load_method_result(run_dir)
    return out


# --------------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------------


def _summary(result: dict, key: str) -> dict[str, Any]:
    """{"mean", "num_views", "num_undefined"} of a per-view metric (NaN mean when absent)."""
    s = result["metrics"]["summary"].get(key)
    if s is None:
        return {"mean": math.nan, "num_views": 0, "num_undefined": 0}
    return s


def _mean(values: Sequence[float]) -> float:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.mean(vals)) if vals else math.nan


def _scene_row(result: dict) -> dict[str, Any]:
    """The numbers of one method on one scene that the tables use."""
    metrics = result["metrics"]
    pooled = metrics.get("pooled", {})
    keys = ("nll", "pearson_mse_var", "spearman_mse_var", "psnr", "ssim", "ause_rmse", "ause_rmse_normalised",
            "ause_mae", "ause_mae_normalised", "auce_colour", "calibration_gap_colour", "render_s")
    row = {k: _summary(result, k)["mean"] for k in keys}
    row["correlation_undefined_views"] = _summary(result, "pearson_mse_var")["num_undefined"]
    row["num_views"] = _summary(result, "nll")["num_views"]
    row["pooled"] = {k: v for k, v in pooled.items() if k != "depth"}
    depth_keys = ("abs_rel", "rmse", "nll", "ause_rmse", "ause_rmse_normalised", "pearson", "spearman", "coverage_68",
                  "coverage_95", "auce", "num_used")
    if metrics.get("depth_source"):
        row["depth"] = {k: _summary(result, f"depth/{k}")["mean"] for k in depth_keys}
        row["depth"]["source"] = metrics["depth_source"]
        row["depth"]["pooled"] = pooled.get("depth", {})
    stages = result["stages"]
    train = stages.get("train", {})
    row["train_s"] = train.get("train_s", math.nan)
    row["steps"] = train.get("steps")
    row["num_parameters"] = train.get("num_parameters")
    row["num_draws"] = metrics.get("num_draws")
    timing = result.get("timing") or {}
    row["timing"] = timing
    return row


def build_tables(results: dict[str, dict[str, dict]], *, methods: Sequence[str] | None = None,
                 settings: BenchmarkSettings | None = None, command: str | None = None) -> dict[str, Any]:
    """All tables as one JSON-ready dict from {scene: {method: result}}."""
    scenes = list(results)
    present = [m for m in (methods or DEFAULT_METHODS) if any(m in results[s] for s in scenes)]
    rows = {s: {m: _scene_row(results[s][m]) for m in present if m in results[s]} for s in scenes}

    def per_scene(m: str, getter) -> dict[str, float]:
        vals = {s: getter(rows[s][m]) for s in scenes if m in rows[s]}
        vals["average"] = _mean(list(vals.values()))
        return vals

    table1 = {}
    for m in [m for m in TABLE1_METHODS if m in present]:
        table1[m] = {
            "label": METHOD_SPECS[m].label,
            "nll": per_scene(m, lambda r: r["nll"]),
            "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
            "spearman": per_scene(m, lambda r: r["spearman_mse_var"]),
            "pooled_pearson": per_scene(m, lambda r: r["pooled"].get("pearson_mse_var", math.nan)),
            "pooled_spearman": per_scene(m, lambda r: r["pooled"].get("spearman_mse_var", math.nan)),
            "correlation_undefined_views": {s: rows[s][m]["correlation_undefined_views"] for s in scenes if m in rows[s]},
            "paper": {s: PAPER_TABLE1.get(s, {}).get(m) for s in scenes},
        }
    ref = "deterministic" if "deterministic" in present else None
    table2 = {}
    for m in present:
        render = per_scene(m, lambda r: r["timing"].get("render_s", math.nan))
        train = per_scene(m, lambda r: r["train_s"])
        entry = {"label": METHOD_SPECS[m].label, "render_s": render, "train_s": train,
                 "rays_per_s": per_scene(m, lambda r: r["timing"].get("rays_per_s", math.nan)),
                 "num_draws": next((rows[s][m]["num_draws"] for s in scenes if m in rows[s]), None),
                 "peak_rss_mib": per_scene(m, lambda r: r["timing"].get("process_peak_rss_mib", math.nan)),
                 "psnr": per_scene(m, lambda r: r["psnr"]), "nll": per_scene(m, lambda r: r["nll"]),
                 "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
                 "depth_abs_rel": per_scene(m, lambda r: r.get("depth", {}).get("abs_rel", math.nan)),
                 "paper_render_s": PAPER_TABLE2.get(m)}
        if ref is not None:
            ref_render = per_scene(ref, lambda r: r["timing"].get("render_s", math.nan))
            ref_train = per_scene(ref, lambda r: r["train_s"])
            for key, num, den in (("render_ratio", render, ref_render), ("train_ratio", train, ref_train)):
                ratios = {s: num[s] / den[s] if den.get(s) else math.nan for s in scenes if s in num}
                ratios["average"] = _mean(list(ratios.values()))  # mean of the per-scene ratios
                entry[key] = ratios
        table2[m] = entry
    table3 = {}
    for m in [m for m in TABLE3_METHODS if m in present]:
        table3[m] = {"label": METHOD_SPECS[m].label, "nll": per_scene(m, lambda r: r["nll"]),
                     "pearson": per_scene(m, lambda r: r["pearson_mse_var"]),
                     "spearman": per_scene(m, lambda r: r["spearman_mse_var"]),
                     "psnr": per_scene(m, lambda r: r["psnr"]), "ause_rmse": per_scene(m, lambda r: r["ause_rmse"]),
                     "auce": per_scene(m, lambda r: r["auce_colour"]),
                     "paper": {s: PAPER_TABLE3.get(s, {}).get(m) for s in scenes}}
    quality = {m: {"label": METHOD_SPECS[m].label,
                   **{k: per_scene(m, lambda r, k=k: r[k]) for k in ("psnr", "ssim", "ause_rmse", "ause_rmse_normalised",
                                                                  "ause_mae", "ause_mae_normalised", "auce_colour",
                                                                  "calibration_gap_colour")}}
               for m in present}
    depth = {m: {"label": METHOD_SPECS[m].label,
                 **{k: per_scene(m, lambda r, k=k: r.get("depth", {}).get(k, math.nan))
                    for k in ("abs_rel", "rmse", "nll", "ause_rmse", "ause_rmse_normalised", "pearson", "spearman",
                              "coverage_68", "coverage_95", "auce", "num_used")}}
             for m in present}
    depth_sources = sorted({rows[s][m]["depth"]["source"] for s in scenes for m in rows[s] if "depth" in rows[s][m]})
    any_result = next(iter(next(iter(results.values())).values())) if results else None
    conventions = dict(any_result["metrics"]["conventions"]) if any_result else M.default_conventions()
    conventions.update({
        "view_means": "table entries are means over test views of per-view values; 'average' is the mean over scenes",
        "pooled": "pooled_* entries score every test pixel of a scene at once",
        "timing": "median wall time of repeated full renders of the first test view after an untimed warm-up "
                  "chunk, this machine, same run; ratios are to the deterministic NeRF",
        "paper_figures": "the paper's numbers are context only: their NLL convention and hardware are not ours",
        "same_pipeline": "every method renders the same dense samples (render.skip_empty_space and "
                         "render.adaptive_draws off unless overridden; the baselines never use them)",
    })
    budget = None
    if any_result:
        cfg = any_result["config"]
        budget = {"iterations": cfg["train"]["iterations"], "rays_per_batch": cfg["train"]["rays_per_batch"],
                  "backend": cfg["field"]["backend"], "num_samples": cfg["render"]["num_samples"],
                  "snerf_num_draws": cfg["render"]["num_draws"], "images": cfg["data"]["images"],
                  "split_every": cfg["data"]["split_every"], "seed": cfg["train"]["seed"],
                  "grid_max_cells": cfg["field"]["grid_max_cells"]}
    return {"scenes": scenes, "methods": present, "budget": budget, "command": command,
            "settings": dataclasses.asdict(settings) if settings else None, "table1": table1, "table2": table2,
            "table3": table3, "quality": quality, "depth": depth, "depth_sources": depth_sources,
            "per_scene": rows, "conventions": conventions}


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float) and math.isnan(v):
        return "undef."
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if abs(v) >= 1e4:
        return f"{v:.3g}"
    return f"{v:.{digits}f}"


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def format_markdown(tables: dict[str, Any]) -> str:
    """The tables as Markdown, with the budget, the command and the conventions."""
    scenes = tables["scenes"]
    cols = scenes + (["average"] if len(scenes) > 1 else [])
    L: list[str] = ["# Uncertainty benchmark: S-NeRF against the paper's baselines", ""]
    if tables.get("command"):
        L += ["Command: `" + tables["command"] + "`", ""]
    if tables.get("budget"):
        L += ["Budget (every method): " + ", ".join(f"{k}={v}" for k, v in tables["budget"].items()), ""]
    if tables["table1"]:
        L += ["## Table 1: NLL and MSE-uncertainty correlation (paper's figures in brackets)", ""]
        header = ["method"] + [f"NLL {s}" for s in cols] + [f"Pearson {s}" for s in cols] + [f"Spearman {s}" for s in cols]
        rows = []
        for m, e in tables["table1"].items():
            def cell(kind: str, s: str, idx: int) -> str:
                paper = e["paper"].get(s) if s != "average" else None
                text = _fmt(e[kind][s])
                return text + (f" [{paper[idx]:.2f}]" if paper else "")
            rows.append([e["label"]] + [cell("nll", s, 0) for s in cols] + [cell("pearson", s, 1) for s in cols]
                        + [_fmt(e["spearman"][s]) for s in cols])
        L += _md_table(header, rows) + [""]
        L += ["Pooled over all test pixels of a scene: " + "; ".join(
            f"{e['label']}: Pearson " + ", ".join(f"{s} {_fmt(e['pooled_pearson'][s])}" for s in scenes)
            + ", Spearman " + ", ".join(f"{s} {_fmt(e['pooled_spearman'][s])}" for s in scenes)
            for e in tables["table1"].values()), ""]
    if tables["table2"]:
        L += ["## Table 2: cost against what it buys (one full test view, this machine)", ""]
        header = ["method", "K"] + [f"render s {s}" for s in scenes] + ["render x NeRF", "rays/s", "train s",
                                                                         "train x NeRF", "peak RSS MiB", "PSNR",
                                                                         "NLL", "Pearson", "depth abs-rel",
                                                                         "paper render s"]
        rows = []
        for m, e in tables["table2"].items():
            avg = "average" if len(scenes) > 1 else scenes[0]
            rows.append([e["label"], _fmt(e["num_draws"])] + [_fmt(e["render_s"][s], 2) for s in scenes]
                        + [_fmt(e.get("render_ratio", {}).get(avg, math.nan), 2), _fmt(e["rays_per_s"][avg], 0),
                           _fmt(e["train_s"][avg], 0), _fmt(e.get("train_ratio", {}).get(avg, math.nan), 2),
                           _fmt(e["peak_rss_mib"][avg], 0), _fmt(e["psnr"][avg], 2), _fmt(e["nll"][avg]),
                           _fmt(e["pearson"][avg]), _fmt(e["depth_abs_rel"][avg]),
                           _fmt(e["paper_render_s"], 2)])
        L += _md_table(header, rows) + [""]
    if tables["table3"]:
        L += ["## Table 3: ablation of the KL terms (paper's figures in brackets)", ""]
        header = ["variant"] + [f"NLL {s}" for s in cols] + [f"Pearson {s}" for s in cols] + [
            f"Spearman {s}" for s in cols] + [f"PSNR {s}" for s in cols]
        rows = []
        for m, e in tables["table3"].items():
            def cell3(kind: str, s: str, idx: int) -> str:
                paper = e["paper"].get(s) if s != "average" else None
                return _fmt(e[kind][s]) + (f" [{paper[idx]:.2f}]" if paper else "")
            rows.append([e["label"]] + [cell3("nll", s, 0) for s in cols] + [cell3("pearson", s, 1) for s in cols]
                        + [_fmt(e["spearman"][s]) for s in cols] + [_fmt(e["psnr"][s], 2) for s in cols])
        L += _md_table(header, rows) + [""]
    L += ["## Table 4: image quality, sparsification and calibration (colour)", ""]
    header = ["method", "scene", "PSNR", "SSIM", "AUSE RMSE", "AUSE RMSE norm.", "AUSE MAE", "AUSE MAE norm.",
              "AUCE", "coverage gap"]
    rows = [[e["label"], s] + [_fmt(e[k][s], 2 if k == "psnr" else 4) for k in
                               ("psnr", "ssim", "ause_rmse", "ause_rmse_normalised", "ause_mae",
                                "ause_mae_normalised", "auce_colour", "calibration_gap_colour")]
            for e in tables["quality"].values() for s in cols]
    L += _md_table(header, rows) + [""]
    if tables["depth_sources"]:
        L += [f"## Table 5: depth against {', '.join(tables['depth_sources'])} ground truth (camera-z, scene units)", ""]
        header = ["method", "scene", "abs-rel", "RMSE", "depth NLL", "AUSE RMSE", "AUSE norm.", "Pearson |err|-std",
                  "Spearman |err|-std", "cov. 68%", "cov. 95%", "AUCE", "points"]
        rows = [[e["label"], s] + [_fmt(e[k][s], 4) for k in ("abs_rel", "rmse", "nll", "ause_rmse",
                                                             "ause_rmse_normalised", "pearson", "spearman",
                                                             "coverage_68", "coverage_95", "auce")]
                + [_fmt(e["num_used"][s], 0)] for e in tables["depth"].values() for s in cols]
        L += _md_table(header, rows) + [""]
    L += ["## Conventions", ""] + [f"- **{k}**: {v}" for k, v in tables["conventions"].items()] + [""]
    return "\n".join(L)


# --------------------------------------------------------------------------------------------
# plots
# --------------------------------------------------------------------------------------------


def write_plots(results: dict[str, dict[str, dict]], plot_dir: Path) -> list[Path]:
    """Per scene: colour sparsification (RMSE, normalised) and calibration plots for the Table-1
    methods and for the ablation, plus depth plots where depth ground truth exists."""
    from stochastic_fields.plots import plot_calibration, plot_sparsification

    written = []
    groups = {"": TABLE1_METHODS, "ablation_": TABLE3_METHODS}
    for scene, by_method in results.items():
        for prefix, group in groups.items():
            members = [m for m in group if m in by_method]
            if not members:
                continue
            label = lambda m: METHOD_SPECS[m].label  # noqa: E731
            for kind, stem, cls, plot in (
                ("colour_sparsification_rmse", "sparsification_rmse", M.SparsificationResult, plot_sparsification),
                ("colour_calibration", "calibration_colour", M.CalibrationResult, plot_calibration),
                ("depth_sparsification_rmse", "sparsification_depth", M.SparsificationResult, plot_sparsification),
                ("depth_calibration", "calibration_depth", M.CalibrationResult, plot_calibration),
            ):
                curves = {label(m): _unpack(by_method[m]["curves"], kind, cls) for m in members
                          if f"{kind}.auce" in by_method[m]["curves"] or f"{kind}.ause" in by_method[m]["curves"]}
                if not curves:
                    continue
                path = Path(plot_dir) / f"{scene}_{prefix}{stem}.png"
                title = f"{scene}: {stem.replace('_', ' ')} ({'ablation' if prefix else 'methods'})"
                written.append(plot(curves, path, title=title))
    return written


# --------------------------------------------------------------------------------------------
# the whole benchmark
# --------------------------------------------------------------------------------------------


def run_benchmark(scenes: Sequence[str], methods: Sequence[str], out_root: Path, settings: BenchmarkSettings, *,
                  data_root: Path | None = None, progress: bool = True, command: str | None = None,
                  log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run (or resume) every method on every scene, then write tables.json, tables.md and plots."""
    out_root = Path(out_root)
    t0 = time.perf_counter()
    for scene in scenes:
        run_scene(scene, methods, out_root, settings, data_root=data_root, progress=progress, log=log)
    results = collect_results(out_root, scenes, methods)
    tables = build_tables(results, methods=methods, settings=settings, command=command)
    tables["wall_s_this_invocation"] = time.perf_counter() - t0
    plots = write_plots(results, out_root / "plots")
    tables["plots"] = [str(p.relative_to(out_root)) for p in plots]
    atomic_write_text(out_root / "tables.json", json.dumps(tables, indent=2, default=_json_default))
    atomic_write_text(out_root / "tables.md", format_markdown(tables))
    return tables


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
