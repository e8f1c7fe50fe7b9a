"""Training loop: seeded, resumable, with progress bars, periodic evaluation and atomic checkpoints.

A run folder holds ``config.json``, ``checkpoint.pt`` (model, optimiser, step and
random-generator state) and ``train_log.jsonl``. Starting a run whose folder already has a
checkpoint resumes from it, so an interrupted run loses at most ``checkpoint_every`` steps and
nothing already on disk.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .cameras import generate_rays
from .checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from .config import ExperimentConfig, flatten, from_dict, save_config, to_dict, validate_experiment
from .io_utils import atomic_write_text, open_append_no_follow, remove_stale_temporaries
from .models.base import RadianceModel
from .models.registry import build_model, resolve_device
from .optim import FieldOptimizer
from .rays import RayBundle


#: Options a resumed run may change: how long and how often, where, and render chunking. Any
#: other difference (model shape, data, losses, learning rate, seed...) is refused on resume.
RESUMABLE_OPTIONS: tuple[str, ...] = ("train.iterations", "train.eval_every", "train.checkpoint_every",
                                      "train.device", "render.chunk_rays", "render.num_draws",
                                      "render.colour_estimator")
LOG_NAME = "train_log.jsonl"


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
            return from_dict(ExperimentConfig, json.loads(text))
        except (ValueError, json.JSONDecodeError) as exc:
            raise ValueError(f"checkpoint {ckpt}: its stored config is unreadable ({exc})") from exc
    from .config import load_config

    return load_config(Path(run_dir) / "config.json")


def check_resume(run_dir: Path, cfg: ExperimentConfig, state: dict | None = None) -> None:
    """Refuse (ValueError naming each differing option, saved and new value) to resume a run
    folder's checkpoint with a config that changes anything but ``RESUMABLE_OPTIONS``. Reads only."""
    saved = saved_run_config(run_dir, state)
    if saved is None:
        return
    diffs = config_differences(saved, cfg)
    if diffs:
        listed = "; ".join(f"{k}: {va!r} in the run, {vb!r} now" for k, va, vb in diffs)
        raise ValueError(f"cannot resume {Path(run_dir) / CHECKPOINT_NAME} with different options ({listed}). "
                         f"Only {', '.join(RESUMABLE_OPTIONS)} may change when resuming; train into a new --out "
                         "folder for the rest. Nothing was changed on disk.")


@dataclass
class TrainingRays:
    """Every training pixel as a flat ray with its colour: rays [P], colours [P, 3]."""

    rays: RayBundle
    colours: torch.Tensor

    @staticmethod
    def from_dataset(dataset, device: torch.device) -> "TrainingRays":
        from .cameras import select_cameras

        idx = list(dataset.train_indices)
        cams = select_cameras(dataset.cameras, idx)
        rays = generate_rays(cams, dataset.near[idx], dataset.far[idx]).flatten().to(device)
        colours = dataset.images[idx].reshape(-1, 3).to(device)
        return TrainingRays(rays, colours)

    def batch(self, n: int, generator: torch.Generator) -> tuple[RayBundle, torch.Tensor]:
        idx = torch.randint(0, len(self.colours), (n,), generator=generator).to(self.colours.device)
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
        from .capture_points import FIT, load_capture_points, rays_through_points, sparse_depth_for_role

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
                          final_factor=cfg.train.lr_final_factor)


#: K of the progress signal's render (cheap; the report's own K comes from the run's settings).
QUICK_EVAL_DRAWS = 4


def quick_eval(model: RadianceModel, dataset, view: int, device: torch.device) -> dict[str, float]:
    """PSNR of the mean colour on one test view (a cheap progress signal)."""
    from .cameras import generate_rays_for_view
    from .metrics import psnr

    model.eval()
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far).to(device)
    maps = model.render_view(rays, model.default_render_options().with_changes(num_draws=QUICK_EVAL_DRAWS))
    model.train()
    return {"eval_view": view, "eval_psnr": psnr(maps["colour_mean"].cpu(), dataset.images[view])}


class Trainer:
    def __init__(self, cfg: ExperimentConfig, run_dir: Path, dataset):
        validate_experiment(cfg)  # fields set by attribute after construction are checked here
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.dataset = dataset
        self.device = resolve_device(cfg.train.device)
        torch.manual_seed(cfg.train.seed)
        self.model = build_model(cfg, dataset).to(self.device)
        self.optimizer = make_optimizer(self.model, cfg)
        self.generator = torch.Generator().manual_seed(cfg.train.seed)
        self.draw_generator = torch.Generator(device=self.device).manual_seed(cfg.train.seed + 1)
        self.step = 0
        self.elapsed = 0.0

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
        }

    def save(self) -> None:
        save_checkpoint(self.checkpoint_path, self.state())

    def try_resume(self) -> bool:
        if not self.checkpoint_path.exists():
            return False
        state = load_checkpoint(self.checkpoint_path, map_location=self.device)
        check_resume(self.run_dir, self.cfg, state)
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
        self.generator.set_state(state["batch_rng"])
        self.draw_generator.set_state(state["draw_rng"].to(self.draw_generator.device) if self.device.type == "cuda" else state["draw_rng"])
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
    def train(self, *, progress: bool = True, max_steps: int | None = None) -> RadianceModel:
        """Train to ``cfg.train.iterations`` (or stop after ``max_steps`` more steps, for tests)."""
        if self.run_dir.exists() and not self.run_dir.is_dir():
            raise ValueError(f"--out {self.run_dir} exists and is not a folder")
        resumed = self.try_resume()  # validates the checkpoint against the config before any write
        self.run_dir.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(self.run_dir)
        save_config(self.cfg, self.run_dir / "config.json")
        self._truncate_log()
        data = TrainingRays.from_dataset(self.dataset, self.device)
        depth_data = None
        if self.cfg.loss.lambda_depth > 0 and getattr(self.model, "accepts_depth", False):
            depth_data = TrainingDepth.from_dataset(self.dataset, self.device)
            if depth_data is None:
                warnings.warn(f"loss.lambda_depth = {self.cfg.loss.lambda_depth} but {self.dataset.root} has no "
                              "capture points in its training views: training without the depth term", stacklevel=2)
        total = self.cfg.train.iterations
        stop_at = total if max_steps is None else min(total, self.step + max_steps)
        log_path = self.run_dir / LOG_NAME
        eval_view = self.dataset.test_indices[0] if len(self.dataset.test_indices) else None
        bar = tqdm(total=total, initial=self.step, desc="train" + (" (resumed)" if resumed else ""),
                   disable=not progress, dynamic_ncols=True)
        self.model.train()
        t_last = time.perf_counter()
        with open_append_no_follow(log_path) as log:
            while self.step < stop_at:
                rays, target = data.batch(self.cfg.train.rays_per_batch, self.generator)
                extra = {}
                if depth_data is not None:
                    extra["depth"] = depth_data.batch(self.cfg.loss.depth_rays_per_batch, self.generator)
                loss, logs = self.model.training_loss(rays, target, step=self.step, generator=self.draw_generator,
                                                      **extra)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"loss is {float(loss)} at step {self.step}: {logs}")
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                self.optimizer.set_step(self.step)
                self.optimizer.step()
                self.model.after_step(self.step)
                self.step += 1
                now = time.perf_counter()
                self.elapsed += now - t_last
                t_last = now
                record = {"step": self.step, "loss": loss.item(), "elapsed_s": round(self.elapsed, 3), **logs}
                if self.cfg.train.eval_every and eval_view is not None and self.step % self.cfg.train.eval_every == 0:
                    record.update(quick_eval(self.model, self.dataset, eval_view, self.device))
                    t_last = time.perf_counter()
                if self.step % 10 == 0 or "eval_psnr" in record:
                    log.write(json.dumps(record) + "\n")
                    log.flush()
                    bar.set_postfix({k: f"{v:.4g}" for k, v in record.items() if k in ("loss", "mse", "eval_psnr")})
                if self.cfg.train.checkpoint_every and self.step % self.cfg.train.checkpoint_every == 0:
                    self.save()
                bar.update(1)
        bar.close()
        self.save()
        self.model.eval()
        return self.model


def load_trained_model(run_dir: Path, dataset=None, device: str | None = None):
    """(cfg, model, dataset) from a run folder; the model is in eval mode.

    The config is the run's config.json; when it differs from the config stored in the
    checkpoint in an option that shapes the model or its training (a run damaged by an earlier
    failed resume), the checkpoint's config is used, with a warning naming the options."""
    from .config import load_config
    from .scenes import load_run_dataset

    run_dir = Path(run_dir)
    ckpt = run_dir / CHECKPOINT_NAME
    if not ckpt.is_file():
        raise FileNotFoundError(f"run folder {run_dir} has no {CHECKPOINT_NAME}: train it first")
    dev_name = None
    if device is not None:
        from .config import TRAIN_CHECKS

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
        cfg = trained
    if dev_name is not None:
        cfg.train.device = dev_name
    dataset = load_run_dataset(cfg, run_dir) if dataset is None else dataset
    dev = resolve_device(cfg.train.device)
    model = build_model(cfg, dataset).to(dev)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ValueError(f"checkpoint {ckpt} does not fit the model of {run_dir / 'config.json'}: "
                         f"{str(exc).splitlines()[0]}") from exc
    model.eval()
    return cfg, model, dataset
