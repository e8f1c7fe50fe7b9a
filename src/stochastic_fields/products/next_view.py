"""Where to look next: rank candidate cameras by the information a photo from each would give.

The score (docs/guide.md, "Choosing the next view"; docs/definitions.md §9) is the expected
information gain of the candidate's photo about the field, in nats per pixel: for each pixel and
colour channel c the model predicts the observed value as the trajectory's colour C_k (random over
the posterior: the K draws, colours drawn too) plus observation noise of variance n_c
(sigma_n^2 + the noise head's mean_k v_k). For a Gaussian that mutual information is

    I_c = 1/2 log(1 + e_c / n_c),   e_c = var_k C_kc (epistemic),   n_c = predictive var - e_c

(BALD: the entropy of the prediction minus the expected entropy of the noise). A pixel the
training views pinned down has e << n and gives almost nothing; a pixel whose trajectories
disagree beyond the noise teaches the model about the field. The candidate's score is the mean
of sum_c I_c over its pixels, rendered at no more than ``max_pixels`` rays (the intrinsics scaled).
Pixels are treated as independent: an upper bound where neighbouring pixels see the same points.

A batch of N (``greedy_batch``) is chosen greedily: after a candidate is picked, the pixels of
every other candidate whose expected surface point the picked view will see (it projects into the
picked image, in front of the camera, and the picked view's rendered depth there is not nearer than
the point by more than ``COVERED_DEPTH_RTOL``) give nothing any more. A near-identical view then
scores about zero and is not picked twice.

Reported beside the score (its parts): the mean epistemic colour std, the median calibrated depth
std / depth over valid pixels, the mean opacity and the fraction of pixels a picked view covers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import torch

from ..cameras import generate_rays_for_view, in_image, intrinsics_3x3, make_cameras, project_points, rescale_cameras
from ..renderer import seeded_chunks
from .depth_maps import compute_depth_products
from .export import ViewSpec, dataset_view_specs
from .pointcloud import backproject_map

#: Observation-noise variance floor (colour units^2) under n_c: the predictive variance minus the
#: epistemic part is at least sigma_n^2 > 0 in exact arithmetic; the floor keeps float32
#: cancellation from dividing by zero (sigma_n is 1e-2 or more in every trained run).
NOISE_VARIANCE_FLOOR: float = 1e-8
#: A pixel's surface point counts as seen by a picked view when that view's depth at its pixel is
#: at least (1 - rtol) times the point's camera depth (nothing nearer occludes it).
COVERED_DEPTH_RTOL: float = 0.05


@dataclass
class CandidateMaps:
    """One rendered candidate: its (possibly downscaled) camera and per-pixel maps [h, w]."""

    spec: ViewSpec
    render_intrinsics: np.ndarray
    render_size: tuple[int, int]
    information: np.ndarray
    colour_mean: np.ndarray
    colour_std_epistemic: np.ndarray
    depth_mean: np.ndarray
    depth_std: np.ndarray
    opacity: np.ndarray
    valid: np.ndarray
    points: np.ndarray = field(repr=False)
    """[h * w, 3] world points at each pixel's mean depth (rays that hit nothing: at their far depth)."""

    def parts(self, uncovered: np.ndarray | None = None) -> dict[str, float]:
        """The score and its parts; ``uncovered`` [h, w] bool: the pixels no picked view sees."""
        keep = np.ones_like(self.valid) if uncovered is None else uncovered
        rel = self.depth_std[self.valid] / np.maximum(self.depth_mean[self.valid], 1e-12)
        return {
            "information_nats_per_pixel": float((self.information * keep).mean()),
            "information_nats_per_pixel_alone": float(self.information.mean()),
            "colour_std_epistemic_mean": float(self.colour_std_epistemic.mean()),
            "depth_rel_std_median": float(np.median(rel)) if rel.size else float("nan"),
            "opacity_mean": float(self.opacity.mean()),
            "fraction_new_pixels": float(keep.mean()),
        }


def render_scale(height: int, width: int, max_pixels: int) -> float:
    """The factor (<= 1) that brings an image of ``height x width`` to at most ``max_pixels``."""
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be >= 1, got {max_pixels}")
    return min(1.0, math.sqrt(max_pixels / float(height * width)))


def scaled_camera(spec: ViewSpec, scale: float) -> tuple[np.ndarray, int, int]:
    """(K [3, 3], h, w) of ``spec`` resampled by ``scale`` (``cameras.rescale_cameras``)."""
    cam = rescale_cameras(_camera(spec.intrinsics, spec.world_to_camera, spec.height, spec.width), scale)
    return intrinsics_3x3(cam)[0].numpy(), int(cam.height[0]), int(cam.width[0])


def _camera(K: np.ndarray, world_to_camera: np.ndarray, height: int, width: int):
    """A one-view float64 kornia camera."""
    return make_cameras(torch.as_tensor(K, dtype=torch.float64)[None],
                        torch.as_tensor(world_to_camera, dtype=torch.float64)[None], height, width)


def information_gain(colour_draws: torch.Tensor, colour_var: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel expected information gain (nats) and epistemic colour variance.

    colour_draws [..., K, 3] (each trajectory's colour), colour_var [..., 3] (the predictive
    variance: epistemic + noise) -> (sum_c 1/2 log(1 + e_c / n_c) [...], e [..., 3]), with
    e_c = var_k C_kc (population) and n_c = max(colour_var - e, NOISE_VARIANCE_FLOOR)."""
    draws = colour_draws.double()
    e = ((draws - draws.mean(dim=-2, keepdim=True)) ** 2).mean(dim=-2)
    n = (colour_var.double() - e).clamp_min(NOISE_VARIANCE_FLOOR)
    return 0.5 * torch.log1p(e / n).sum(dim=-1), e


def render_candidate(model, spec: ViewSpec, *, num_draws: int, max_pixels: int, seed: int = 0,
                     calibration=None, min_opacity: float = 0.5) -> CandidateMaps:
    """Render ``spec`` at no more than ``max_pixels`` rays with K = ``num_draws`` trajectories
    (colours drawn, so the K colours carry the whole epistemic colour variance) and its maps."""
    num_draws = getattr(model, "trajectories", None) or num_draws  # a deep ensemble renders its M members
    if num_draws < 2:
        raise ValueError(f"num_draws must be >= 2 (the score is a variance over the draws), got {num_draws}")
    K, h, w = scaled_camera(spec, render_scale(spec.height, spec.width, max_pixels))
    device = next(model.parameters()).device
    cams = make_cameras(torch.from_numpy(K).float()[None], torch.from_numpy(spec.world_to_camera).float()[None], h, w)
    rays = generate_rays_for_view(cams, 0, spec.near, spec.far).to(device)
    options = model.render_options(num_draws=num_draws, keep_draws=True, colour_estimator="draws")
    with torch.no_grad():
        maps = model.render_view(rays, options, generator=seeded_chunks(seed, spec.index, device))
    info, e = information_gain(maps["colour_draws"].cpu(), maps["colour_var"].cpu())
    products = compute_depth_products(maps, K, spec.world_to_camera, near=spec.near, far=spec.far,
                                      min_opacity=min_opacity, calibration=calibration)
    depth = np.where(products.valid, products.depth_mean, np.float32(spec.far))
    return CandidateMaps(spec=spec, render_intrinsics=K, render_size=(h, w), information=info.numpy(),
                         colour_mean=products.colour_mean, colour_std_epistemic=e.sqrt().mean(dim=-1).numpy(),
                         depth_mean=products.depth_mean, depth_std=products.depth_std, opacity=products.opacity,
                         valid=products.valid,
                         points=backproject_map(depth, K, spec.world_to_camera).reshape(-1, 3).numpy())


def seen_by(points: np.ndarray, picked: CandidateMaps, rtol: float = COVERED_DEPTH_RTOL) -> np.ndarray:
    """[P] bool: which world ``points`` [P, 3] the picked view sees (module doc): in its image, in
    front of it, and not behind its rendered surface by more than ``rtol`` of the point's depth."""
    h, w = picked.render_size
    cam = _camera(picked.render_intrinsics, picked.spec.world_to_camera, h, w)
    uv, z = project_points(cam, torch.as_tensor(points, dtype=torch.float64))
    inside = in_image(cam, uv, z)[0].numpy()
    uv, z = uv[0].numpy(), z[0].numpy()
    rows = np.clip(np.nan_to_num(np.floor(uv[:, 1])), 0, h - 1).astype(int)
    cols = np.clip(np.nan_to_num(np.floor(uv[:, 0])), 0, w - 1).astype(int)
    surface = np.where(picked.valid, picked.depth_mean, np.float32(picked.spec.far))[rows, cols]
    return inside & (surface >= (1.0 - rtol) * z)


@dataclass
class Ranking:
    """Candidates ranked alone (``order``: best first, with each one's parts) and the greedy
    batch (``batch``: picked in order, each with its parts given the views picked before it)."""

    order: list[tuple[int, dict]]
    batch: list[tuple[int, dict]]


def greedy_batch(candidates: Sequence[CandidateMaps], count: int) -> list[tuple[int, dict]]:
    """Pick ``count`` candidates one at a time, each the best given the pixels the ones picked
    before it will see (module doc). Returns [(candidate index, parts)]."""
    if not 1 <= count <= len(candidates):
        raise ValueError(f"--count must be between 1 and the {len(candidates)} candidates, got {count}")
    uncovered = [np.ones(c.render_size, dtype=bool) for c in candidates]
    left = list(range(len(candidates)))
    picked: list[tuple[int, dict]] = []
    for _ in range(count):
        scores = {i: candidates[i].parts(uncovered[i]) for i in left}
        best = max(left, key=lambda i: (scores[i]["information_nats_per_pixel"], -i))
        picked.append((best, scores[best]))
        left.remove(best)
        for i in left:
            uncovered[i] &= ~seen_by(candidates[i].points, candidates[best]).reshape(candidates[i].render_size)
    return picked


def untrained_view_specs(dataset) -> list[ViewSpec]:
    """The dataset's photos that did not train, as candidates (no ground truth attached)."""
    train = set(int(i) for i in dataset.train_indices)
    specs = dataset_view_specs(dataset, [v for v in range(dataset.num_views) if v not in train])
    for s in specs:
        s.gt_depth = None
    return specs


def rank_candidates(model, specs: Sequence[ViewSpec], *, count: int = 1, num_draws: int, max_pixels: int,
                    seed: int = 0, calibration=None, progress: Callable | None = None
                    ) -> tuple[Ranking, list[CandidateMaps]]:
    """Render every candidate (``progress``: an iterable wrapper such as tqdm) and rank them."""
    if not specs:
        raise ValueError("no candidate cameras to rank")
    it = progress(specs) if progress is not None else specs
    rendered = [render_candidate(model, s, num_draws=num_draws, max_pixels=max_pixels, seed=seed,
                                 calibration=calibration) for s in it]
    alone = sorted(((i, c.parts()) for i, c in enumerate(rendered)),
                   key=lambda item: (-item[1]["information_nats_per_pixel"], item[0]))
    return Ranking(order=alone, batch=greedy_batch(rendered, count)), rendered
