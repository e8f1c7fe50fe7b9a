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
from .config import ExperimentConfig, save_config, to_dict
from .models.base import RadianceModel
from .models.registry import build_model, resolve_device
from .optim import FieldOptimizer
from .rays import RayBundle


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
        from .cameras import generate_rays_at
        from .capture_points import FIT, load_capture_points, sparse_depth_for_role

        points = load_capture_points(dataset)
        if points is None:
            return None
        per_view = sparse_depth_for_role(dataset, points, dataset.train_indices, FIT)
        views = torch.cat([torch.full((len(sd),), v, dtype=torch.long) for v, sd in per_view.items()])
        uv = torch.cat([torch.from_numpy(sd.uv) for sd in per_view.values()]).float()
        z = torch.cat([torch.from_numpy(sd.depth) for sd in per_view.values()]).float()
        if len(z) == 0:
            return None
        rays = generate_rays_at(dataset.cameras, views, uv, dataset.near, dataset.far)
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


def quick_eval(model: RadianceModel, dataset, view: int, device: torch.device) -> dict[str, float]:
    """PSNR of the mean colour on one test view (a cheap progress signal)."""
    from .cameras import generate_rays_for_view
    from .eval.metrics import psnr

    model.eval()
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far).to(device)
    maps = model.render_view(rays, num_draws=4)
    model.train()
    return {"eval_view": view, "eval_psnr": psnr(maps["colour_mean"].cpu(), dataset.images[view])}


class Trainer:
    def __init__(self, cfg: ExperimentConfig, run_dir: Path, dataset):
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
        self.model.load_state_dict(state["model"])
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

    # ------------------------------------------------------------------ loop
    def train(self, *, progress: bool = True, max_steps: int | None = None) -> RadianceModel:
        """Train to ``cfg.train.iterations`` (or stop after ``max_steps`` more steps, for tests)."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        save_config(self.cfg, self.run_dir / "config.json")
        resumed = self.try_resume()
        data = TrainingRays.from_dataset(self.dataset, self.device)
        depth_data = None
        if self.cfg.loss.lambda_depth > 0 and getattr(self.model, "accepts_depth", False):
            depth_data = TrainingDepth.from_dataset(self.dataset, self.device)
            if depth_data is None:
                warnings.warn(f"loss.lambda_depth = {self.cfg.loss.lambda_depth} but {self.dataset.root} has no "
                              "capture points in its training views: training without the depth term", stacklevel=2)
        total = self.cfg.train.iterations
        stop_at = total if max_steps is None else min(total, self.step + max_steps)
        log_path = self.run_dir / "train_log.jsonl"
        eval_view = self.dataset.test_indices[0] if len(self.dataset.test_indices) else None
        bar = tqdm(total=total, initial=self.step, desc="train" + (" (resumed)" if resumed else ""),
                   disable=not progress, dynamic_ncols=True)
        self.model.train()
        t_last = time.perf_counter()
        with log_path.open("a") as log:
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
    """(cfg, model, dataset) from a run folder; the model is in eval mode."""
    from .config import load_config
    from .scenes import load_run_dataset

    run_dir = Path(run_dir)
    ckpt = run_dir / CHECKPOINT_NAME
    if not ckpt.is_file():
        raise FileNotFoundError(f"run folder {run_dir} has no {CHECKPOINT_NAME}: train it first")
    cfg = load_config(run_dir / "config.json")
    if device is not None:
        cfg.train.device = device
    dataset = load_run_dataset(cfg, run_dir) if dataset is None else dataset
    dev = resolve_device(cfg.train.device)
    model = build_model(cfg, dataset).to(dev)
    state = load_checkpoint(ckpt, map_location=dev)
    model.load_state_dict(state["model"])
    model.eval()
    return cfg, model, dataset
