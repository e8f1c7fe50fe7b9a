"""Training loop: seeded, resumable, with progress bars, periodic evaluation and atomic checkpoints.

A run folder holds ``config.json``, ``checkpoint.pt`` (model, optimiser, step and
random-generator state) and ``train_log.jsonl``. Starting a run whose folder already has a
checkpoint resumes from it, so an interrupted run loses at most ``checkpoint_every`` steps and
nothing already on disk.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .cameras import generate_rays, generate_rays_for_view, select_cameras
from .checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from .config import (TRAIN_CHECKS, ExperimentConfig, flatten, load_config, save_config, saved_config,
                     set_dotted, to_dict, validate_experiment)
from .distributed import DistContext, GradientReducer, rank_seeds, shard_size
from .io_utils import atomic_write_text, open_append_no_follow, remove_stale_temporaries
from .fields.grid import GridField, coarse_to_fine_weights
from .models.base import RadianceModel
from .models.field_builder import trained_grid_resolution
from .models.registry import build_model, resolve_device
from .optim import FieldOptimizer
from .ray_sampling import ErrorMap, pixel_blocks
from .rays import RayBundle
from .capture_points import FIT, load_capture_points, rays_through_points, sparse_depth_for_role
from .holdout import holdout_masks
from .losses import bootstrap_head_weights
from .metrics import psnr
from .scenes import load_run_dataset
from .virtual_views import PatchSampler


#: Options a resumed run may change: how long and how often, where, and render chunking. Any
#: other difference (model shape, data, losses, learning rate, seed...) is refused on resume.
RESUMABLE_OPTIONS: tuple[str, ...] = ("train.iterations", "train.minutes", "train.eval_every", "train.checkpoint_every",
                                      "train.device", "render.chunk_rays", "render.num_draws",
                                      "render.colour_estimator", "render.depth_estimate")
LOG_NAME = "train_log.jsonl"
#: Added to the depth smoothness patches' seed so they draw apart from the batches of the same seed.
SMOOTHNESS_SEED_OFFSET = 0x5A17
#: Offset of the density heads' bootstrap table's seed from ``train.seed`` (``loss.head_bootstrap_keep``):
#: one table for the whole training, the same on every rank and after a resume.
HEAD_BOOTSTRAP_SEED_OFFSET = 0xB007


def _comparable_data_path(value: str) -> str:
    return str(Path(value).expanduser().resolve()) if value else ""


def config_differences(saved: ExperimentConfig, new: ExperimentConfig) -> list[tuple[str, object, object]]:
    """(dotted option, saved value, new value) for every option that differs and may not change
    on resume (everything outside ``RESUMABLE_OPTIONS``; data paths compared resolved)."""
    a, b = flatten(to_dict(saved)), flatten(to_dict(new))
    diffs = []
    for key in sorted(set(a) | set(b)):
        if key in RESUMABLE_OPTIONS:
            continue
        va, vb = a.get(key), b.get(key)
        if key == "data.path":
            va, vb = _comparable_data_path(va or ""), _comparable_data_path(vb or "")
        if va != vb:
            diffs.append((key, a.get(key), b.get(key)))
    return diffs


def saved_run_config(run_dir: Path, state: dict | None = None) -> ExperimentConfig | None:
    """The config the run's checkpoint was trained with (its ``config_json``; else config.json),
    or None when the folder has no checkpoint."""
    ckpt = Path(run_dir) / CHECKPOINT_NAME
    if not ckpt.exists():
        return None
    if state is None:
        state = load_checkpoint(ckpt)
    text = state.get("config_json")
    if isinstance(text, str):
        try:
            return saved_config(json.loads(text))
        except (ValueError, json.JSONDecodeError) as exc:
            raise ValueError(f"checkpoint {ckpt}: its stored config is unreadable ({exc})") from exc
    return load_config(Path(run_dir) / "config.json")


def resume_differences(run_dir: Path, cfg: ExperimentConfig, state: dict | None = None) -> list[tuple[str, object, object]]:
    """``config_differences`` of the run folder's checkpoint config and ``cfg`` ([] without a checkpoint)."""
    saved = saved_run_config(run_dir, state)
    return [] if saved is None else config_differences(saved, cfg)


def describe_differences(diffs: list[tuple[str, object, object]]) -> str:
    """'option: saved in the run, new now; ...' of ``config_differences``."""
    return "; ".join(f"{k}: {va!r} in the run, {vb!r} now" for k, va, vb in diffs)


def check_resume(run_dir: Path, cfg: ExperimentConfig, state: dict | None = None) -> None:
    """Refuse (ValueError naming each differing option, saved and new value) to resume a run
    folder's checkpoint with a config that changes anything but ``RESUMABLE_OPTIONS``. Reads only."""
    diffs = resume_differences(run_dir, cfg, state)
    if diffs:
        listed = describe_differences(diffs)
        raise ValueError(f"cannot resume {Path(run_dir) / CHECKPOINT_NAME} with different options ({listed}). "
                         f"Only {', '.join(RESUMABLE_OPTIONS)} may change when resuming; train into a new --out "
                         "folder for the rest. Nothing was changed on disk.")


@dataclass
class TrainingRays:
    """Every training pixel as a flat ray with its colour: rays [P], colours [P, 3]; without the
    pixels held out for the colour recalibration (``holdout.holdout_mask``) when ``holdout_fraction`` > 0."""

    rays: RayBundle
    colours: torch.Tensor
    #: Each ray's pixel block of ``train.error_sampling_block`` pixels (stochastic_fields.ray_sampling):
    #: [P] labels, or None where no error map is asked for.
    blocks: torch.Tensor | None = None

    @staticmethod
    def from_dataset(dataset, device: torch.device, *, holdout_fraction: float = 0.0,
                     holdout_block: int = 16, error_block: int | None = None) -> "TrainingRays":
        idx = list(dataset.train_indices)
        cams = select_cameras(dataset.cameras, idx)
        rays = generate_rays(cams, dataset.near[idx], dataset.far[idx]).flatten()
        images = dataset.images[idx]  # [V, H, W, 3]
        colours = images.reshape(-1, 3)
        blocks = None if error_block is None else pixel_blocks(*images.shape[:3], error_block)
        if holdout_fraction > 0:
            keep = torch.from_numpy(~holdout_masks(dataset, idx, fraction=holdout_fraction,
                                                   block=holdout_block).reshape(-1))
            rays, colours = rays[keep], colours[keep]
            blocks = None if blocks is None else blocks[keep]
        return TrainingRays(rays.to(device), colours.to(device), blocks)

    def batch(self, n: int, generator: torch.Generator) -> tuple[RayBundle, torch.Tensor]:
        """``n`` rays drawn uniformly with replacement, and their colours."""
        return self.at(self.draw(n, generator))

    def draw(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n] pixel indices drawn uniformly with replacement (what ``batch`` reads)."""
        return torch.randint(0, len(self.colours), (n,), generator=generator)

    def at(self, idx: torch.Tensor) -> tuple[RayBundle, torch.Tensor]:
        """The rays [n] and colours [n, 3] of the pixels ``idx`` [n]."""
        idx = idx.to(self.colours.device)
        return self.rays[idx], self.colours[idx]


@dataclass
class TrainingDepth:
    """The training views' capture points of the FIT role (stochastic_fields.capture_points) as rays
    through their pixels, with the surface's ray distance: rays [P], target_t [P]."""

    rays: RayBundle
    target_t: torch.Tensor

    @staticmethod
    def from_dataset(dataset, device: torch.device) -> "TrainingDepth | None":
        """None when the scene has no capture points or none of the FIT role lies inside a training view's bounds."""
        points = load_capture_points(dataset)
        if points is None:
            return None
        per_view = sparse_depth_for_role(dataset, points, dataset.train_indices, FIT)
        found = rays_through_points(dataset.cameras, dataset.near, dataset.far, per_view)
        if found is None:
            return None
        rays, depth = found
        z = torch.from_numpy(depth).float()
        t = z / rays.z_scale
        inside = (t > rays.near) & (t < rays.far)
        if not bool(inside.any()):
            return None
        return TrainingDepth(rays[inside].to(device), t[inside].to(device))

    def batch(self, n: int, generator: torch.Generator) -> tuple[RayBundle, torch.Tensor]:
        idx = torch.randint(0, len(self.target_t), (n,), generator=generator).to(self.target_t.device)
        return self.rays[idx], self.target_t[idx]


def make_optimizer(model: RadianceModel, cfg: ExperimentConfig) -> FieldOptimizer:
    return FieldOptimizer(model.param_groups(cfg.train.lr), total_steps=cfg.train.iterations,
                          final_factor=cfg.train.lr_final_factor, beta2=cfg.train.adam_beta2,
                          colour_beta2=cfg.train.adam_beta2_colour)


#: K of the progress signal's render (cheap; the report's own K comes from the run's settings).
QUICK_EVAL_DRAWS = 4


def quick_eval(model: RadianceModel, dataset, view: int, device: torch.device) -> dict[str, float]:
    """PSNR of the mean colour on one test view (a cheap progress signal)."""
    model.eval()
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far).to(device)
    maps = model.render_view(rays, model.default_render_options().with_changes(num_draws=QUICK_EVAL_DRAWS))
    model.train()
    return {"eval_view": view, "eval_psnr": psnr(maps["colour_mean"].cpu(), dataset.images[view])}


class Trainer:
    """Trains ``cfg``'s model on ``dataset`` into ``run_dir``.

    ``distributed``: this rank's process group (``distributed.init_process_group``) for
    data-parallel training (module doc of ``stochastic_fields.distributed``): each rank draws its
    share of ``train.rays_per_batch`` from its own generators, the gradients are averaged before
    every optimiser step, and rank 0 alone writes the run folder (config, log, checkpoints) while
    the others wait at a barrier after each checkpoint. None: one process, as before.
    """

    def __init__(self, cfg: ExperimentConfig, run_dir: Path, dataset, *, distributed: DistContext | None = None):
        validate_experiment(cfg)  # fields set by attribute after construction are checked here
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.dataset = dataset
        self.dist = distributed
        self.device = distributed.device if distributed is not None else resolve_device(cfg.train.device)
        rank, world = (distributed.rank, distributed.world_size) if distributed is not None else (0, 1)
        if distributed is not None and cfg.train.minutes > 0:
            raise ValueError(f"train.minutes = {cfg.train.minutes:g} with data-parallel training: each rank's clock "
                             "would stop it at another step; give train.iterations instead (train.minutes 0)")
        if cfg.train.rays_per_batch < world:
            raise ValueError(f"train.rays_per_batch = {cfg.train.rays_per_batch} is smaller than the {world} ranks: "
                             "every rank needs at least one ray per step")
        torch.manual_seed(cfg.train.seed)
        self.model = build_model(cfg, dataset).to(self.device)
        self.optimizer = make_optimizer(self.model, cfg)
        if (distributed is not None and cfg.loss.lambda_depth > 0 and getattr(self.model, "accepts_depth", False)
                and cfg.loss.depth_rays_per_batch < world):
            raise ValueError(f"loss.depth_rays_per_batch = {cfg.loss.depth_rays_per_batch} is smaller than the {world} "
                             "ranks: every rank needs at least one depth ray per step")
        batch_seed, draw_seed = rank_seeds(cfg.train.seed, rank, world)
        self.generator = torch.Generator().manual_seed(batch_seed)
        self.draw_generator = torch.Generator(device=self.device).manual_seed(draw_seed)
        self.reducer = (GradientReducer(self.model, self.model.param_groups(cfg.train.lr), distributed)
                        if distributed is not None else None)
        if cfg.train.ray_sampling == "error":
            if distributed is not None:
                raise ValueError("train.ray_sampling = 'error' with data-parallel training: each rank would keep its "
                                 "own error map; use 'uniform' or one process")
            if not self.model.accepts_ray_weights:
                raise ValueError(f"train.ray_sampling = 'error' needs a method whose likelihood takes ray weights "
                                 f"(snerf, deterministic); method {cfg.method!r} does not")
        if cfg.loss.head_bootstrap_keep < 1:
            heads = int(getattr(getattr(self.model, "field", None), "density_heads", 1))
            if not getattr(self.model, "accepts_head_weights", False) or heads < 2:
                raise ValueError(f"loss.head_bootstrap_keep = {cfg.loss.head_bootstrap_keep:g} needs density heads "
                                 f"(field.density_heads > 1, the grid S-NeRF's); method {cfg.method!r} here has "
                                 f"{heads} density field(s): leave it at 1")
        #: [N, M] each training pixel's weight per density head (``loss.head_bootstrap_keep`` < 1), built
        #: with the training rays.
        self._head_table: torch.Tensor | None = None
        #: The error-guided sampler's map (``train.ray_sampling`` 'error'), built with the training rays.
        self.error_map: ErrorMap | None = None
        self._error_map_state: dict | None = None  # a resumed checkpoint's map, loaded once it is built
        self.step = 0
        self.elapsed = 0.0

    @property
    def is_main(self) -> bool:
        """True in the process that writes the run folder (rank 0, or the only process)."""
        return self.dist is None or self.dist.is_main

    # ------------------------------------------------------------------ checkpoints
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / CHECKPOINT_NAME

    def state(self) -> dict:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step,
            "elapsed_s": self.elapsed,
            "batch_rng": self.generator.get_state(),
            "draw_rng": self.draw_generator.get_state().cpu(),
            "config_json": json.dumps(to_dict(self.cfg)),
            **grid_resolution_state(self.model),
            **({} if self.error_map is None else {"error_map": self.error_map.state_dict()}),
        }

    def save(self) -> None:
        """Write the checkpoint atomically. Distributed: every rank calls this (each rank's
        generator states are gathered into the checkpoint's ``rank_rngs``, with ``world_size``),
        rank 0 writes, and all wait at a barrier until the file is in place."""
        if self.dist is None:
            save_checkpoint(self.checkpoint_path, self.state())
            return
        rngs = self._gather_rng_states()
        if self.dist.is_main:
            save_checkpoint(self.checkpoint_path, {**self.state(), "world_size": self.dist.world_size,
                                                   "rank_rngs": rngs})
        self.dist.barrier("checkpoint written by rank 0")

    def _gather_rng_states(self) -> list[dict]:
        """[{batch_rng, draw_rng}] of every rank, in rank order (a collective)."""
        batch, draw = self.generator.get_state(), self.draw_generator.get_state().cpu()
        parts = self.dist.all_gather_bytes(torch.cat([batch, draw]), what="generator states for the checkpoint")
        return [{"batch_rng": p[:len(batch)].clone(), "draw_rng": p[len(batch):].clone()} for p in parts]

    def _resume_state(self) -> dict | None:
        """The run folder's checkpoint, validated against the config (``check_resume``), or None.
        Distributed: rank 0 reads it and broadcasts it, or its refusal, to every rank."""
        def read() -> dict | None:
            if not self.checkpoint_path.exists():
                return None
            state = load_checkpoint(self.checkpoint_path, map_location="cpu" if self.dist is not None else self.device)
            check_resume(self.run_dir, self.cfg, state)
            return state

        if self.dist is None:
            return read()
        payload = None
        if self.dist.is_main:
            try:
                payload = ("state", read())
            except (ValueError, FileNotFoundError) as exc:
                payload = ("error", str(exc))
        kind, value = self.dist.broadcast_object(payload, what="resume state from rank 0")
        if kind == "error":
            raise ValueError(value if self.dist.is_main else f"rank 0 refused to resume: {value}")
        return value

    def _restore_rngs(self, state: dict) -> None:
        """The generators as saved when the checkpoint was written by as many processes as run
        now; otherwise restarted from ``rank_seeds(seed, rank, world_size, step)`` (said in a warning)."""
        rank, world = (self.dist.rank, self.dist.world_size) if self.dist is not None else (0, 1)
        saved_world = int(state.get("world_size", 1))
        if saved_world == world:
            rng = state if world == 1 else state["rank_rngs"][rank]
            # Generator.set_state takes a CPU ByteTensor for every device's generator (a CUDA one
            # too), and a checkpoint read with map_location=cuda holds the states on the GPU.
            self.generator.set_state(rng["batch_rng"].cpu())
            self.draw_generator.set_state(rng["draw_rng"].cpu())
            return
        batch_seed, draw_seed = rank_seeds(self.cfg.train.seed, rank, world, self.step)
        self.generator.manual_seed(batch_seed)
        self.draw_generator.manual_seed(draw_seed)
        if self.is_main:
            warnings.warn(f"{self.checkpoint_path} was written by {saved_world} process(es) and resumes in {world}: "
                          "the model, optimiser and step continue; the ray and draw streams restart from "
                          "(seed, rank, step)", stacklevel=3)

    def try_resume(self) -> bool:
        state = self._resume_state()
        if state is None:
            return False
        stored, built = stored_grid_resolution(self.checkpoint_path, state), trained_grid_resolution(self.model)
        if stored is not None and stored != built:
            raise ValueError(f"checkpoint {self.checkpoint_path} was trained with a {' x '.join(map(str, stored))} grid "
                             f"and this config's training views size it {' x '.join(map(str, built))}: resume with "
                             "the run's own data and split, or train into another --out")
        try:
            self.model.load_state_dict(state["model"])
        except RuntimeError as exc:  # shapes or names differ from the config's model
            raise ValueError(f"checkpoint {self.checkpoint_path} does not fit the configured model: "
                             f"{str(exc).splitlines()[0]}") from exc
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except ValueError as exc:  # e.g. a checkpoint from before the row-sparse grid optimiser
            warnings.warn(f"{self.checkpoint_path}: optimiser state not restored ({exc}); the model and step are, "
                          "and Adam's moments restart from zero", stacklevel=2)
        self.step = int(state["step"])
        self.elapsed = float(state.get("elapsed_s", 0.0))
        self._error_map_state = state.get("error_map")
        self._restore_rngs(state)
        return True

    def _truncate_log(self) -> None:
        """Keep only the log records of steps up to the restored step: steps redone after a
        resume (or after a restart without checkpoint) are logged once, by the run that keeps them."""
        path = self.run_dir / LOG_NAME
        if path.is_symlink():
            raise ValueError(f"{path} is a symbolic link; refusing to write through it (remove the link)")
        if not path.exists():
            return
        kept = []
        for line in path.read_text().splitlines():
            try:
                if int(json.loads(line)["step"]) <= self.step:
                    kept.append(line)
            except (ValueError, KeyError, TypeError):
                continue  # a line cut by a kill: dropped
        atomic_write_text(path, "".join(k + "\n" for k in kept))

    # ------------------------------------------------------------------ loop
    def _set_level_weights(self, progress: float | None) -> None:
        """Coarse to fine (``field.grid_coarse_to_fine``): every grid's level weights at training
        ``progress`` (``grid.coarse_to_fine_weights``); None: all levels at 1 (a trained model)."""
        fraction = self.cfg.field.grid_coarse_to_fine
        if fraction <= 0:
            return
        for grid in (m for m in self.model.modules() if isinstance(m, GridField)):
            grid.set_level_weights(None if progress is None else
                                   coarse_to_fine_weights(len(grid.levels), progress, fraction))

    def schedule_progress(self) -> float:
        """Fraction of the schedule done: step / iterations, or with a ``train.minutes`` budget the
        larger of that and elapsed / budget (module doc of ``config.TrainConfig.minutes``)."""
        done = self.step / self.cfg.train.iterations
        budget_s = 60.0 * self.cfg.train.minutes
        if budget_s > 0:
            done = max(done, self.elapsed / budget_s)
        return min(done, 1.0)

    def train(self, *, progress: bool = True, max_steps: int | None = None,
              max_elapsed_s: float | None = None) -> RadianceModel:
        """Train to ``cfg.train.iterations`` or to the end of the ``train.minutes`` budget, whichever
        comes first (or stop after ``max_steps`` more steps, or once the loop's clock reaches
        ``max_elapsed_s`` seconds in all: for tests and for scoring along the way)."""
        if self.run_dir.exists() and not self.run_dir.is_dir():
            raise ValueError(f"--out {self.run_dir} exists and is not a folder")
        resumed = self.try_resume()  # validates the checkpoint against the config before any write
        main = self.is_main
        if main:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(self.run_dir)
            save_config(self.cfg, self.run_dir / "config.json")
            self._truncate_log()
        if self.dist is not None:  # identical starting point on every rank, whatever happened before
            self.dist.broadcast_tensors(list(self.model.state_dict().values()), what="parameters from rank 0")
        tc = self.cfg.train
        guided = tc.ray_sampling == "error"
        data = TrainingRays.from_dataset(self.dataset, self.device, holdout_fraction=tc.holdout_fraction,
                                         holdout_block=tc.holdout_block,
                                         error_block=tc.error_sampling_block if guided else None)
        if guided:
            self.error_map = ErrorMap(data.blocks, uniform_share=tc.error_sampling_uniform_share,
                                      correction=tc.error_sampling_correction).to(self.device)
            if self._error_map_state is not None:
                self.error_map.load_state_dict(self._error_map_state)
            elif resumed and main:
                warnings.warn(f"{self.checkpoint_path} holds no error map: the error-guided sampler starts afresh",
                              stacklevel=2)
        depth_data = None
        if self.cfg.loss.lambda_depth > 0 and getattr(self.model, "accepts_depth", False):
            depth_data = TrainingDepth.from_dataset(self.dataset, self.device)
            if depth_data is None and main:
                warnings.warn(f"loss.lambda_depth = {self.cfg.loss.lambda_depth} but {self.dataset.root} has no "
                              "capture points in its training views: training without the depth term", stacklevel=2)
        patch_sampler = None
        if self.cfg.loss.lambda_smoothness > 0:
            patch_sampler = PatchSampler.for_dataset(self.dataset, self.device)
            if patch_sampler is None and main:
                warnings.warn(f"loss.lambda_smoothness = {self.cfg.loss.lambda_smoothness} but {self.dataset.root} has "
                              "fewer than 2 training views to place virtual cameras between: training without the "
                              "depth smoothness term", stacklevel=2)
        total = self.cfg.train.iterations
        stop_at = total if max_steps is None else min(total, self.step + max_steps)
        if self.dist is not None and max_elapsed_s is not None:
            raise ValueError("max_elapsed_s with data-parallel training: each rank's clock would stop it at another step")
        budget_s = 60.0 * self.cfg.train.minutes
        clock_stop = min(budget_s if budget_s > 0 else math.inf,
                         math.inf if max_elapsed_s is None else float(max_elapsed_s))
        log_path = self.run_dir / LOG_NAME
        eval_view = self.dataset.test_indices[0] if len(self.dataset.test_indices) else None
        bar = tqdm(total=total, initial=self.step, desc="train" + (" (resumed)" if resumed else ""),
                   disable=not (progress and main), dynamic_ncols=True)
        self.model.train()
        t_last = time.perf_counter()
        try:
            with open_append_no_follow(log_path) if main else contextlib.nullcontext() as log:
                while self.step < stop_at and self.elapsed < clock_stop:
                    done = self.schedule_progress()
                    self._set_level_weights(done)
                    self.model.training_progress = done
                    loss, logs = self.compute_gradients(data, depth_data, patch_sampler)
                    self.optimizer.set_progress(done)
                    self.optimizer.step()
                    self.model.after_step(self.step)
                    self.step += 1
                    now = time.perf_counter()
                    self.elapsed += now - t_last
                    t_last = now
                    record = {"step": self.step, "loss": loss, "elapsed_s": round(self.elapsed, 3), **logs}
                    if main and self.cfg.train.eval_every and eval_view is not None \
                            and self.step % self.cfg.train.eval_every == 0:
                        record.update(quick_eval(self.model, self.dataset, eval_view, self.device))
                        t_last = time.perf_counter()
                    if main and (self.step % 10 == 0 or "eval_psnr" in record):
                        log.write(json.dumps(record) + "\n")
                        log.flush()
                        bar.set_postfix({k: f"{v:.4g}" for k, v in record.items() if k in ("loss", "mse", "eval_psnr")})
                    if self.cfg.train.checkpoint_every and self.step % self.cfg.train.checkpoint_every == 0:
                        self.save()
                        t_last = time.perf_counter()  # the clock counts training, not checkpoint writes
                    bar.update(1)
        finally:
            self._set_level_weights(None)  # the trained model reads every level
            self.model.training_progress = 0.0
        bar.close()
        self.save()
        self.model.eval()
        return self.model

    def smoothness_generators(self) -> tuple[torch.Generator, torch.Generator]:
        """(CPU, device) generators of this step's depth smoothness patches, both seeded from the
        run's seed, the rank and the step alone: the patches leave the ray batches and the draws
        as they are without the term, and a resumed run draws the same patches."""
        rank, world = (self.dist.rank, self.dist.world_size) if self.dist is not None else (0, 1)
        batch_seed, _ = rank_seeds(self.cfg.train.seed, rank, world)
        seed = (int(batch_seed) * 1_000_003 + self.step + SMOOTHNESS_SEED_OFFSET) % 2**63
        return torch.Generator().manual_seed(seed), torch.Generator(device=self.device).manual_seed(seed)

    def _add_smoothness(self, loss: torch.Tensor, logs: dict[str, float],
                        sampler: PatchSampler | None) -> torch.Tensor:
        """``loss`` plus the model's depth smoothness term of this step's patches (``sampler``
        None: unchanged)."""
        if sampler is None:
            return loss
        cpu, device = self.smoothness_generators()
        patches = sampler.sample(self.cfg.loss.smoothness_patches, self.cfg.loss.smoothness_patch_size, cpu)
        return self.model.add_smoothness(loss, logs, patches, generator=device)

    def _head_weights(self, data: TrainingRays, picked: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{"head_weights": [n, M]}`` of the pixels ``picked`` [n] (``loss.head_bootstrap_keep`` < 1),
        else ``{}``: the table of ``losses.bootstrap_head_weights``, drawn once from ``train.seed``."""
        keep = self.cfg.loss.head_bootstrap_keep
        if keep >= 1:
            return {}
        if self._head_table is None or len(self._head_table) != len(data.colours):
            heads = int(self.model.field.density_heads)
            generator = torch.Generator().manual_seed(self.cfg.train.seed + HEAD_BOOTSTRAP_SEED_OFFSET)
            self._head_table = bootstrap_head_weights(len(data.colours), heads, keep, generator).to(self.device)
        return {"head_weights": self._head_table[picked.to(self.device)]}

    def compute_gradients(self, data: TrainingRays, depth_data: TrainingDepth | None,
                          patch_sampler: PatchSampler | None = None) -> tuple[float, dict[str, float]]:
        """Draw this step's batch, compute the loss and leave its gradients in the parameters
        (``.grad`` and the grid tables' ``RowGradient``). Returns (loss, logged scalars).
        ``patch_sampler``: the depth smoothness patches' cameras (``loss.lambda_smoothness``).

        Distributed: this rank draws ``shard_size(rays_per_batch, rank, W)`` rays (and its share
        of the depth rays), back-propagates its loss scaled by ``n_r W / B``, and the gradients are
        averaged over the ranks (``distributed.GradientReducer``); the returned loss and logs are
        the weighted averages ``sum_r (n_r / B) x_r`` over the ranks, i.e. over the union batch.
        A non-finite loss on any rank raises FloatingPointError on every rank."""
        cfg = self.cfg
        if self.dist is None:
            weights = None
            if self.error_map is None:
                picked = data.draw(cfg.train.rays_per_batch, self.generator)
            else:
                picked, weights = self.error_map.sample(cfg.train.rays_per_batch, self.generator)
            rays, target = data.at(picked)
            extra = self._head_weights(data, picked)
            if depth_data is not None:
                extra["depth"] = depth_data.batch(cfg.loss.depth_rays_per_batch, self.generator)
            if weights is not None:
                extra["ray_weights"] = weights
            loss, logs = self.model.training_loss(rays, target, step=self.step, generator=self.draw_generator, **extra)
            loss = self._add_smoothness(loss, logs, patch_sampler)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"loss is {float(loss)} at step {self.step}: {logs}")
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if self.error_map is not None:
                self.error_map.update(picked, self.model.last_ray_errors)
            return loss.item(), logs
        rank, world, total = self.dist.rank, self.dist.world_size, cfg.train.rays_per_batch
        n = shard_size(total, rank, world)
        picked = data.draw(n, self.generator)
        rays, target = data.at(picked)
        extra = self._head_weights(data, picked)
        if depth_data is not None:
            extra["depth"] = depth_data.batch(shard_size(cfg.loss.depth_rays_per_batch, rank, world), self.generator)
        loss, logs = self.model.training_loss(rays, target, step=self.step, generator=self.draw_generator, **extra)
        loss = self._add_smoothness(loss, logs, patch_sampler)
        self.optimizer.zero_grad(set_to_none=True)
        (loss * (n * world / total)).backward()
        keys = sorted(logs)
        local = torch.tensor([loss.item()] + [float(logs[k]) for k in keys], dtype=torch.float64) * (n / total)
        reduced = self.reducer.reduce(local).tolist()
        loss_all, logs_all = reduced[0], dict(zip(keys, reduced[1:]))
        if not math.isfinite(loss_all):
            raise FloatingPointError(f"loss is {loss_all} at step {self.step} (averaged over {world} ranks; this "
                                     f"rank's: {loss.item()}): {logs_all}")
        return loss_all, logs_all


#: Checkpoint key of the finest grid level's cells per axis (absent for an MLP field and in
#: checkpoints from before it was stored, whose grid is sized again from the training views).
GRID_RESOLUTION_KEY = "grid_resolution"


def grid_resolution_state(model: RadianceModel) -> dict:
    """``{GRID_RESOLUTION_KEY: [X, Y, Z]}`` for a model with a grid field, else ``{}``."""
    res = trained_grid_resolution(model)
    return {} if res is None else {GRID_RESOLUTION_KEY: list(res)}


def stored_grid_resolution(path: Path, state: dict) -> tuple[int, int, int] | None:
    """The finest grid level a checkpoint was trained with (ValueError naming the file when
    the stored entry is not three positive integers), or None when it stores none."""
    res = state.get(GRID_RESOLUTION_KEY)
    if res is None:
        return None
    if (not isinstance(res, (list, tuple)) or len(res) != 3
            or not all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in res)):
        raise ValueError(f"checkpoint {path}: {GRID_RESOLUTION_KEY} must be three positive integers, got {res!r}")
    return tuple(res)


def load_trained_model(run_dir: Path, dataset=None, device: str | None = None):
    """(cfg, model, dataset) from a run folder; the model is in eval mode.

    The config is the run's config.json; when it differs from the config stored in the
    checkpoint in an option that shapes the model or its training (a run damaged by an earlier
    failed resume), the checkpoint's config is used, with a warning naming the options, but for
    ``RESUMABLE_OPTIONS`` (render options among them), which stay config.json's."""
    run_dir = Path(run_dir)
    ckpt = run_dir / CHECKPOINT_NAME
    if not ckpt.is_file():
        raise FileNotFoundError(f"run folder {run_dir} has no {CHECKPOINT_NAME}: train it first")
    dev_name = None
    if device is not None:
        try:
            dev_name = TRAIN_CHECKS["device"](device)
        except ValueError as exc:
            raise ValueError(f"--device must be {exc}, got {device!r}") from None
    state = load_checkpoint(ckpt, map_location="cpu")
    cfg = load_config(run_dir / "config.json")
    trained = saved_run_config(run_dir, state)
    if trained is not None and config_differences(trained, cfg):
        listed = ", ".join(k for k, _, _ in config_differences(trained, cfg))
        warnings.warn(f"{run_dir / 'config.json'} differs from the config stored in {ckpt} ({listed}); "
                      "using the checkpoint's", stacklevel=2)
        flat = flatten(to_dict(cfg))
        for key in RESUMABLE_OPTIONS:
            set_dotted(trained, key, flat[key])
        cfg = trained
    if dev_name is not None:
        cfg.train.device = dev_name
    dataset = load_run_dataset(cfg, run_dir) if dataset is None else dataset
    dev = resolve_device(cfg.train.device)
    model = build_model(cfg, dataset, grid_resolution=stored_grid_resolution(ckpt, state)).to(dev)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {ckpt} does not fit the model of {run_dir / 'config.json'}: "
                         f"{str(exc).splitlines()[0]}") from exc
    model.eval()
    return cfg, model, dataset
