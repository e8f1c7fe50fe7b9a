"""Resumable stages of the tables (train -> calibrate -> eval -> timing per method and scene),
each skipped when the fingerprint of its inputs matches, and the whole run (``run_benchmark``)."""

from __future__ import annotations

import hashlib
import json
import platform
import resource
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from stochastic_fields.calibration import (CHECKED_SOURCE, CROSS_FIT_FOLDS, DEFAULT_CALIBRATION_POINTS, calibrate_run,
                                           describe, load_run_calibration)
from stochastic_fields.config import (LEGACY_VALUES, ExperimentConfig, fill_legacy_same_as, flatten, save_config,
                                     saved_config, set_dotted, to_dict)
from stochastic_fields.defaults import DEPTH_FREE_SPACE, DEPTH_PARALLAX_TERM
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.evaluation import evaluate, synchronize
from stochastic_fields.trainer import RESUMABLE_OPTIONS, load_trained_model, Trainer
from stochastic_fields.view_maps import draws_summary
from stochastic_fields.capture_points import score_sparse_depth
from stochastic_fields.data import detect_format, load_dataset
from stochastic_fields.scenes import apply_split
from tqdm import tqdm

from .methods import MethodSpec, METHOD_SPECS, method_config
from .budget import TABLE_CONVENTIONS, BenchmarkSettings, base_config, select_views
from .report import build_tables, format_markdown, write_plots


#: Which capture points score depth (capture_points: the SCORE role of the spatial split); part of
#: the eval fingerprint so that runs scored on every point are re-scored.
SCORED_POINTS = "score-role blocks"
#: Which pixels of an exact depth map score depth (evaluation.DENSE_DEPTH_SCORED); part of the eval
#: fingerprint of dense-depth scenes so that runs scored on every pixel are re-scored.
SCORED_PIXELS = "score-role blocks of the exact depth"


#: How the depth recalibration is fitted (part of the calibrate fingerprint: a new protocol refits).
#: (The free-space check joined it with study 22e, the parallax term with study 42; the text without them is the
#: protocol runs fitted before.)
CALIBRATION_PROTOCOL = (f"{DEFAULT_CALIBRATION_POINTS} (calibrate and score role) capture points from views halfway "
                        "between neighbouring training views, interval scores cross-fitted over "
                        f"{CROSS_FIT_FOLDS} folds of the score blocks"
                        + (f"{CHECKED_SOURCE} with a fitted weight" if DEPTH_FREE_SPACE else "")
                        + (", the training views' parallax term with a fitted weight" if DEPTH_PARALLAX_TERM else ""))


#: Config entries that do not change what a run computes (left out of fingerprints).
_NON_SEMANTIC = ("train.device", "train.eval_every", "train.checkpoint_every", "render.chunk_rays", "data.path")


#: Options of S-NeRF's noise head (docs/definitions.md §4.7).
_NOISE_HEAD_OPTIONS = ("loss.per_point_noise", "loss.noise_head_decoupled")

#: Options of S-NeRF's sparse-depth likelihood (the baselines take no depth term).
_DEPTH_OPTIONS = ("loss.lambda_depth", "loss.depth_rays_per_batch", "loss.depth_relative_std",
                  "loss.depth_likelihood", "loss.depth_draws", "loss.depth_outlier_share")

#: S-NeRF's training-likelihood estimator: the baselines' likelihoods draw no colours.
_LIKELIHOOD_OPTIONS = ("loss.likelihood_estimator",)

#: S-NeRF's KL terms (models/snerf.py only): the baselines have no prior.
_KL_OPTIONS = ("loss.kl", "loss.kl_estimator", "loss.kl_mc_samples", "loss.lambda_random", "loss.lambda_observed",
               "loss.random_points_per_axis", "loss.observed_kl_samples")

#: Options whose default changed after fingerprints were stored: the value the stored fingerprints
#: left out as "the default" (lambda_depth was 0.1 until study 4 made it 0.3, then study 6 1.0; lambda_observed
#: 5e-2 until study 16b; depth_relative_std 0.01 until study 35; the colour branch 8 features per cell and a
#: decoder 32 wide until study 43; three grid levels until study 51), so that a run at the new default gets a new fingerprint and one stored at
#: the old value keeps its own. A default changed without an entry here fails
#: tests/test_eval_tables.py (its snapshot tests/fingerprinted_defaults.json).
_FINGERPRINT_REFERENCE: dict[str, Any] = {"loss.lambda_depth": 0.1, "render.num_draws": 16,
                                          "render.colour_estimator": "draws", "loss.lambda_observed": 5e-2,
                                          "loss.depth_relative_std": 0.01, "field.grid_feature_dim": 8,
                                          "field.grid_decoder_width": 32, "field.grid_levels": 3}

#: Render-time options a trained run may change (``trainer.RESUMABLE_OPTIONS``): they are left out
#: of the training fingerprint (a new K or colour estimator re-calibrates and re-scores a stored run,
#: it does not retrain it) and a run folder saved with other values is updated to the new ones.
RENDER_ONLY_OPTIONS: tuple[str, ...] = tuple(k for k in RESUMABLE_OPTIONS if k.startswith("render."))


def semantic_options(flat: dict[str, Any]) -> dict[str, Any]:
    """Entries that change what a run computes, without those equal to the dataclass defaults:
    an option added later with a default that keeps the old behaviour changes no fingerprint.
    For an option whose default changed the model (``config.LEGACY_VALUES``) the legacy value is
    the one left out: runs saved before it existed computed with it; for one whose default changed
    after runs were fingerprinted (``_FINGERPRINT_REFERENCE``), the value those runs left out."""
    flat = fill_legacy_same_as(flat)  # a run saved before an option existed computed with its source's value
    reference = {**flatten(to_dict(ExperimentConfig())), **LEGACY_VALUES, **_FINGERPRINT_REFERENCE}
    ignored = set(_NON_SEMANTIC)
    if flat.get("method", "snerf") != "snerf":
        ignored.update(_NOISE_HEAD_OPTIONS)  # S-NeRF's field only: the baselines build none
        ignored.add("field.density_heads")  # nor density heads (deterministic_density_init: one field)
        ignored.update(_DEPTH_OPTIONS)  # nor do they take the depth likelihood
        ignored.update(_LIKELIHOOD_OPTIONS)
        ignored.update(_KL_OPTIONS)  # nor any KL term
        # nor draw S-NeRF's trajectories: they render their own K (1, the ensemble's members,
        # MC-Dropout's passes) from deterministic passes, whatever K or colour estimator is set
        ignored.update(RENDER_ONLY_OPTIONS)
    else:
        if not flat.get("loss.per_point_noise", LEGACY_VALUES["loss.per_point_noise"]):
            ignored.add("loss.noise_head_decoupled")  # changes nothing without the noise head
        if flat.get("loss.lambda_depth") == 0.0:  # the depth likelihood is off: its settings compute nothing
            ignored.update(o for o in _DEPTH_OPTIONS if o != "loss.lambda_depth")
    return {k: v for k, v in flat.items() if k not in ignored and not (k in reference and reference[k] == v)}


def config_fingerprint(cfg: ExperimentConfig, *extra: Any, leave_out: Sequence[str] = ()) -> str:
    """Hash of what ``cfg`` computes (``semantic_options``) with ``extra``, without the ``leave_out`` entries."""
    flat = {k: v for k, v in semantic_options(flatten(to_dict(cfg))).items() if k not in leave_out}
    text = json.dumps([flat, list(extra)], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_compatible(run_dir: Path, cfg: ExperimentConfig) -> list[str]:
    """A run folder may only be resumed with the same config (more iterations are allowed, and
    other ``RENDER_ONLY_OPTIONS``); returns the render-only options that differ. Options missing
    from the saved config count as their defaults."""
    saved = Path(run_dir) / "config.json"
    if not saved.exists():
        return []
    old = semantic_options(flatten(json.loads(saved.read_text())))
    new = semantic_options(flatten(to_dict(cfg)))
    differ = sorted(k for k in set(old) | set(new) if k != "train.iterations" and old.get(k) != new.get(k))
    trained = [k for k in differ if k not in RENDER_ONLY_OPTIONS]
    if trained:
        raise ValueError(f"run folder {run_dir} was trained with a different configuration "
                         f"(differs in {trained}); use another --out or remove the folder")
    return differ


def update_render_options(run_dir: Path, cfg: ExperimentConfig, keys: Sequence[str]) -> None:
    """Set the render-only options ``keys`` of ``run_dir``'s config.json to ``cfg``'s values,
    leaving every other entry as the run was trained (written atomically)."""
    saved = saved_config(_read_json(Path(run_dir) / "config.json"))
    flat = flatten(to_dict(cfg))
    for key in keys:
        if key not in RENDER_ONLY_OPTIONS:
            raise ValueError(f"{key} is not a render-only option ({', '.join(RENDER_ONLY_OPTIONS)})")
        set_dotted(saved, key, flat[key])
    save_config(saved, Path(run_dir) / "config.json")


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




def evaluate_run(model, dataset, out_dir: Path, *, views: Sequence[int] | None = None, seed: int = 0,
                 sparse_depth: dict | None = None, product_views: int = 1, progress: bool = True,
                 calibration=None) -> dict:
    """``evaluation.evaluate`` of one trained model with the tables' conventions (the model's own
    render options; products of the first ``product_views`` views)."""
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
        synchronize(device)
        t0 = time.perf_counter()
        maps = model.render_view(rays, options, generator=gen)
        synchronize(device)
        times.append(time.perf_counter() - t0)
    seconds = float(np.median(times))
    return {"view": int(view), "height": H, "width": W, "render_s": seconds, "render_s_min": min(times),
            "render_s_max": max(times), "repeats": repeats, "rays_per_s": H * W / seconds,
            **draws_summary(maps["num_draws"]), "device": str(device),
            "torch_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
            **_peak_memory()}


def time_renders_interleaved(variants: dict[str, tuple[Any, Any]], rays, repeats: int) -> dict[str, list[float]]:
    """Wall times of full renders of ``rays`` by each variant {name: (model, RenderOptions or None
    for the model's own)}, the variants in turn ``repeats`` times (A, B, A, B, ...) so that drifts of
    the machine hit every variant alike; each render draws from a generator seeded 0."""
    times: dict[str, list[float]] = {k: [] for k in variants}
    for _ in range(repeats):
        for name, (model, options) in variants.items():
            t0 = time.perf_counter()
            with torch.no_grad():
                model.render_view(rays, options, generator=torch.Generator().manual_seed(0))
            times[name].append(time.perf_counter() - t0)
    return times


def time_training_interleaved(trainers: dict[str, Any], steps: int, chunk: int, *,
                              progress: bool = False) -> dict[str, list[tuple[float, int]]]:
    """Train each of ``trainers`` {name: Trainer} ``steps`` more steps, ``chunk`` at a time in turn
    (A, B, A, B, ...) so that drifts of the machine hit every one alike; returns {name: [(loop
    seconds, steps) per chunk]} from the trainer's own loop clock (no set-up, resume or checkpoint)."""
    times: dict[str, list[tuple[float, int]]] = {k: [] for k in trainers}
    done, bar = 0, tqdm(total=steps, desc="train (interleaved)", unit="step", disable=not progress)
    while done < steps:
        n = min(chunk, steps - done)
        for name, trainer in trainers.items():
            before = trainer.elapsed
            trainer.train(progress=False, max_steps=n)
            times[name].append((trainer.elapsed - before, n))
        done += n
        bar.update(n)
    bar.close()
    return times


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
    run_dir = Path(run_dir)
    cfg = method_config(spec, base_config(settings, dataset), scene_path)
    render_changes = check_compatible(run_dir, cfg)
    if render_changes:  # renders of the stored run follow the new render options (stages below re-run)
        update_render_options(run_dir, cfg, render_changes)
        log(f"[{dataset.name}/{spec.name}] render options changed ({', '.join(render_changes)}): config.json updated")
    run_dir.mkdir(parents=True, exist_ok=True)
    stages = load_stages(run_dir)
    fp_train = config_fingerprint(cfg, leave_out=RENDER_ONLY_OPTIONS)
    fp_cal = config_fingerprint(cfg, "calibrate", settings.seed, CALIBRATION_PROTOCOL)
    fp_eval = config_fingerprint(cfg, "eval", list(views), settings.seed, sparse_depth is not None,
                                 SCORED_POINTS if sparse_depth is not None else SCORED_PIXELS,
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
        calibration = load_run_calibration(run_dir)
        if (stages.get("calibrate", {}).get("fingerprint") != fp_cal
                or (calibration is not None and not calibration.independent_depth_scores)):  # benchmarks score: refit
            t0 = time.perf_counter()
            try:
                calibration = calibrate_run(run_dir, model=loaded(), dataset=dataset, seed=settings.seed,
                                            progress=progress)
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


def scene_inputs(scene: str, settings: BenchmarkSettings, data_root: Path | None = None, *,
                 log: Callable[[str], None] = print) -> tuple[Path, Any, list[int], dict | None]:
    """What every method of a scene is scored on: (scene folder, dataset split by the settings'
    protocol (``budget.PROTOCOLS``; "paper": every 5th view trains), the scored test views, {view: SparseDepth} of the SCORE capture points or None
    where the scene has exact depth maps or no points)."""
    scene_path = resolve_scene(scene, data_root)
    if detect_format(scene_path) == "llff":
        dataset = load_dataset(scene_path, images=settings.images, split_every=5)
    else:
        dataset = load_dataset(scene_path, split_every=5)
    dataset = apply_split(dataset, base_config(settings, dataset))  # the protocol's split (paper: as loaded)
    views = select_views(list(dataset.test_indices), settings)
    sparse = score_sparse_depth(dataset, views)
    if sparse is None and getattr(dataset, "depths", None) is None:
        log(f"[{dataset.name}] no sparse depth ground truth: the scene has no COLMAP points")
    return scene_path, dataset, views, sparse


def run_scene(scene: str, methods: Sequence[str], out_root: Path, settings: BenchmarkSettings, *,
              data_root: Path | None = None, progress: bool = True,
              log: Callable[[str], None] = print) -> dict[str, dict]:
    """Every method on one scene: {method: load_method_result(...)}."""
    scene_path, dataset, views, sparse = scene_inputs(scene, settings, data_root, log=log)
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


#: Seconds a rank of a distributed benchmark waits at the final barrier for the others' stages
#: (``--dist-timeout`` of eval_tables.py): the slowest rank's training, evaluation and timing.
TABLES_DIST_TIMEOUT_S: float = 24 * 3600.0


def assign_stages(scenes: Sequence[str], methods: Sequence[str], world_size: int) -> list[list[tuple[str, str]]]:
    """The (scene, method) stages of each rank: the scene-major list of every stage dealt
    round-robin, rank r taking stages r, r + W, ... (each exactly once; counts differ by at most one)."""
    if world_size < 1:
        raise ValueError(f"world size must be >= 1, got {world_size}")
    stages = [(scene, m) for scene in scenes for m in methods]
    return [stages[r::world_size] for r in range(world_size)]


def run_benchmark(scenes: Sequence[str], methods: Sequence[str], out_root: Path, settings: BenchmarkSettings, *,
                  data_root: Path | None = None, progress: bool = True, command: str | None = None,
                  log: Callable[[str], None] = print, distributed=None) -> dict[str, Any] | None:
    """Run (or resume) every method on every scene, then write tables.json, tables.md and plots.

    ``distributed``: a ``stochastic_fields.distributed.DistContext`` (one rank of a torchrun
    launch): rank r runs its stages of ``assign_stages`` (each writes its own run folder, so
    ``out_root`` must be one folder for all ranks: a shared file system across hosts), waits at a
    barrier for the others, and rank 0 collects every run folder from disk and writes the tables,
    the same as one process's (but for the wall times). Returns the tables on rank 0, None on
    the others."""
    out_root = Path(out_root)
    t0 = time.perf_counter()
    ctx = distributed
    if ctx is None:
        for scene in scenes:
            run_scene(scene, methods, out_root, settings, data_root=data_root, progress=progress, log=log)
    else:
        mine = assign_stages(scenes, methods, ctx.world_size)[ctx.rank]
        rank_log = lambda line: log(f"[rank {ctx.rank}/{ctx.world_size}] {line}")  # noqa: E731
        for scene in dict.fromkeys(scenes):
            own = [m for s, m in mine if s == scene]
            if own:
                run_scene(scene, own, out_root, settings, data_root=data_root, progress=progress, log=rank_log)
        ctx.barrier("every rank's benchmark stages")
        if not ctx.is_main:
            return None
    results = collect_results(out_root, scenes, methods)
    tables = build_tables(results, methods=methods, settings=settings, command=command)
    tables["wall_s_this_invocation"] = time.perf_counter() - t0
    plots = write_plots(results, out_root / "plots")
    tables["plots"] = [str(p.relative_to(out_root)) for p in plots]
    atomic_write_text(out_root / "tables.json", json.dumps(tables, indent=2, default=json_default))
    atomic_write_text(out_root / "tables.md", format_markdown(tables))
    return tables


def json_default(o: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars and arrays (anything else as its string)."""
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
