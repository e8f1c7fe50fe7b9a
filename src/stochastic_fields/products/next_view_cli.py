"""``stochastic-fields next-view``: rank candidates (``products.next_view``) and write

    OUT/next_views.json   the candidates ranked alone and the greedy batch of --count views: name,
                          pose (world_to_camera and camera_to_world, OpenCV, the run's world frame
                          and units), K, size, score and its parts
    OUT/next_views.png    contact sheet of the top candidates: colour, depth, depth std / depth and
                          the information map

both atomically. The frame and conventions are written into the JSON (``FRAME``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..calibration import load_run_calibration
from ..io_utils import atomic_path, atomic_write_text
from ..trainer import load_trained_model
from .export import load_cameras_json
from .next_view import CandidateMaps, Ranking, rank_candidates, untrained_view_specs

#: What next_views.json states about its numbers.
FRAME: str = (
    "poses in the run's world frame and scene units (the frame of the scene's cameras, of export and of "
    "cameras.json); world_to_camera maps world points to OpenCV camera points (x right, y down, z forward), "
    "x_cam = R x_world + t; camera_to_world is its inverse (its last column is the camera centre); K is "
    "the full-size 3x3 intrinsics with pixel centres at (j + 0.5, i + 0.5); score = expected information "
    "gain of the candidate's photo about the field, nats per pixel (docs/guide.md, 'Choosing the next view')"
)


def candidate_specs(args: argparse.Namespace, dataset, run_scene: Path):
    """The candidates: ``--candidates FILE`` or the run's photos that did not train."""
    if args.candidates is not None:
        return load_cameras_json(args.candidates, default_near=float(dataset.near.min()),
                                 default_far=float(dataset.far.max()))
    scene = Path(args.candidates_from).expanduser().resolve()
    if scene != Path(run_scene).resolve():
        raise ValueError(f"--candidates-from {args.candidates_from}: the run {args.run} was trained on {run_scene}; "
                         "candidates must be in its frame (pass the run's scene, or poses with --candidates FILE)")
    specs = untrained_view_specs(dataset)
    if not specs:
        raise ValueError(f"--candidates-from {args.candidates_from}: every one of its {dataset.num_views} photos "
                         "trained the run; there is no candidate left")
    return specs


def pose_entry(c: CandidateMaps) -> dict:
    s = c.spec
    return {"name": s.name, "index": int(s.index), "width": s.width, "height": s.height,
            "K": np.asarray(s.intrinsics).tolist(), "world_to_camera": np.asarray(s.world_to_camera).tolist(),
            "camera_to_world": np.linalg.inv(s.world_to_camera).tolist(), "near": s.near, "far": s.far}


def ranking_json(ranking: Ranking, rendered: list[CandidateMaps], meta: dict) -> dict:
    return {
        **meta, "frame": FRAME,
        "ranked": [{"rank": r + 1, **pose_entry(rendered[i]), "score": p["information_nats_per_pixel"], "parts": p}
                   for r, (i, p) in enumerate(ranking.order)],
        "batch": [{"pick": r + 1, **pose_entry(rendered[i]), "score": p["information_nats_per_pixel"], "parts": p}
                  for r, (i, p) in enumerate(ranking.batch)],
    }


def write_contact_sheet(path: Path, ranking: Ranking, rendered: list[CandidateMaps], rows: int) -> None:
    """PNG: one row per top candidate (ranked alone): colour, depth, depth std / depth, information."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    top = ranking.order[:max(1, rows)]
    info_max = max(float(rendered[i].information.max()) for i, _ in top) or 1.0
    fig, axes = plt.subplots(len(top), 4, figsize=(13, 2.6 * len(top)), squeeze=False)
    for r, (i, p) in enumerate(top):
        c = rendered[i]
        rel = np.where(c.valid, c.depth_std / np.maximum(c.depth_mean, 1e-12), np.nan)
        depth = np.where(c.valid, c.depth_mean, np.nan)
        panels = [(np.clip(c.colour_mean, 0, 1), None, "colour"), (depth, "viridis", "depth"),
                  (rel, "magma", "depth std / depth"), (c.information, "inferno", "information (nats / pixel)")]
        for ax, (img, cmap, title) in zip(axes[r], panels):
            kw = {"vmin": 0.0, "vmax": info_max} if title.startswith("information") else {}
            im = ax.imshow(img, cmap=cmap, **kw)
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"#{r + 1} {c.spec.name}: {title}" if cmap is None else title, fontsize=9)
            if cmap is not None:
                fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        axes[r][0].set_ylabel(f"score {p['information_nats_per_pixel']:.3g}", fontsize=9)
    fig.suptitle("Next view: candidates ranked by expected information (blank in the depth maps: no surface)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)


def run(args: argparse.Namespace) -> None:
    for name, value, lo in (("--count", args.count, 1), ("--num-draws", args.num_draws, 2),
                            ("--max-pixels", args.max_pixels, 1), ("--sheet-rows", args.sheet_rows, 1)):
        if value < lo:
            raise ValueError(f"{name} must be >= {lo}, got {value}")
    cfg, model, dataset = load_trained_model(Path(args.run), device=args.device)
    from ..scenes import scene_path  # deferred: loads only when this command runs (keeps --help fast)

    specs = candidate_specs(args, dataset, scene_path(cfg, Path(args.run)))
    if args.count > len(specs):
        source = args.candidates if args.candidates is not None else f"the photos of {args.candidates_from} that did not train"
        raise ValueError(f"--count {args.count}: only {len(specs)} candidates to choose from in {source}")
    progress = None if args.quiet else (lambda s: tqdm(s, desc="candidates", unit="view"))
    ranking, rendered = rank_candidates(model, specs, count=args.count, num_draws=args.num_draws,
                                        max_pixels=args.max_pixels, seed=args.seed,
                                        calibration=load_run_calibration(args.run), progress=progress)
    out = Path(args.out) if args.out else Path(args.run) / "next_view"
    meta = {"run": str(args.run), "num_candidates": len(specs), "count": args.count, "num_draws": args.num_draws,
            "max_pixels": args.max_pixels, "seed": args.seed}
    atomic_write_text(out / "next_views.json", json.dumps(ranking_json(ranking, rendered, meta), indent=1))
    write_contact_sheet(out / "next_views.png", ranking, rendered, args.sheet_rows)
    print(f"ranked {len(specs)} candidates of {args.run} (K={args.num_draws}, <= {args.max_pixels} pixels each):")
    for r, (i, p) in enumerate(ranking.batch):
        c = rendered[i].spec
        centre = np.linalg.inv(c.world_to_camera)[:3, 3]
        print(f"  pick {r + 1}: {c.name}  {p['information_nats_per_pixel']:.4g} nats/pixel "
              f"({p['fraction_new_pixels']:.0%} new pixels), centre {np.round(centre, 4).tolist()}")
    print(f"  {out / 'next_views.json'}, {out / 'next_views.png'}")
