"""Measurement (decides nothing): what the Laplace depth std costs inside S-NeRF's render.

The Laplace analyses computed l in a second pass over 64 dense samples in float64 (0.5-0.8 of a
photo's render). ``LaplaceDensity.depth_std_of_samples`` computes it from the render's own samples and
the density parameters the render already evaluated (no field evaluation). This renders the same
validation photos of trained runs, interleaved, with today's ``render_view`` and with a render that also
computes l chunk by chunk in that pass, on one thread, and reports the time of each and their ratio, and
how far the in-render l is from the separate dense pass's (empty-space skipping leaves out samples whose
density the occupancy grid calls empty)::

    OMP_NUM_THREADS=1 python benchmarks/studies/laplace_render_cost.py \
        --run flower=runs/lap44/s18/today/flower/snerf_default --run fern=runs/lap44/s18/today/fern/snerf_default \
        --views 2 --repeats 3 --out benchmarks/results/laplace_term_analysis/render_cost
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_helpers import write_study  # noqa: E402

from stochastic_fields.cameras import generate_rays_for_view  # noqa: E402
from stochastic_fields.laplace import fit_laplace_density  # noqa: E402
from stochastic_fields.renderer import ChunkRender, render_chunked, seeded_chunks  # noqa: E402
from stochastic_fields.trainer import TrainingRays, load_trained_model  # noqa: E402
from tables_cap_study import validation_views  # noqa: E402


def render_with_laplace(model, laplace, rays, options, generator):
    """``render_view``'s maps (fixed K) and l [H, W] computed in the same pass, chunk by chunk."""
    ls = []

    def chunk(r, gen):
        out = model.render_chunk(r, options, generator=gen)
        ls.append(laplace.depth_std_of_samples(out.samples, out.params.density_loc, out.params.density_scale,
                                               model.field.region))
        return ChunkRender(out.stats, options.num_draws, out.extras["field_evals"])

    maps = render_chunked(chunk, rays, options.chunk_rays, generator=generator)
    return maps, torch.cat(ls).reshape(rays.shape)


def measure(run: Path, scene: str, views: int, repeats: int) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, model, dataset = load_trained_model(run, device="cpu")
    laplace = fit_laplace_density(model, TrainingRays.from_dataset(dataset, torch.device("cpu")).rays)
    options = model.default_render_options()
    rows = []
    for v in validation_views(scene)[:views]:
        rays = generate_rays_for_view(dataset.cameras, v, dataset.near, dataset.far)
        plain, with_l = [], []
        for _ in range(repeats):  # interleaved, so drifts of the machine fall on both
            t0 = time.perf_counter()
            with torch.no_grad():
                model.render_view(rays, options, generator=seeded_chunks(0, v))
            plain.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            with torch.no_grad():
                _, l_in = render_with_laplace(model, laplace, rays, options, seeded_chunks(0, v))
            with_l.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        l_dense = laplace.depth_std(model, rays.flatten()).reshape(rays.shape)
        dense_s = time.perf_counter() - t0
        diff = (l_in - l_dense).abs()
        rows.append({"view": v, "render_s": float(np.median(plain)), "render_with_l_s": float(np.median(with_l)),
                     "dense_pass_s": dense_s, "ratio": float(np.median(with_l) / np.median(plain)),
                     "l_median": float(l_dense.median()),
                     "abs_diff_median": float(diff.median()), "abs_diff_p99": float(diff.quantile(0.99)),
                     "rel_diff_median": float((diff / l_dense.clamp_min(1e-12)).median())})
    return {"run": str(run), "views": rows, "repeats": repeats}


def markdown(results: dict) -> str:
    lines = ["# The Laplace depth std inside S-NeRF's render: cost", "",
             "One thread; each time the median of the repeats, the two renders interleaved. `dense pass`: l by "
             "`LaplaceDensity.depth_std` (64 dense samples, a second pass) for comparison. Decides nothing.", "",
             "| scene | view | render s | render with l s | ratio | dense pass s | median l (camera z) | median abs "
             "diff in-render - dense | 99th pct abs diff | median rel diff |", "|---|---|---|---|---|---|---|---|---|---|"]
    for scene, res in results.items():
        for r in res["views"]:
            lines.append(f"| {scene} | {r['view']} | {r['render_s']:.2f} | {r['render_with_l_s']:.2f} | {r['ratio']:.3f} | "
                         f"{r['dense_pass_s']:.2f} | {r['l_median']:.3g} | {r['abs_diff_median']:.2g} | "
                         f"{r['abs_diff_p99']:.2g} | {r['rel_diff_median']:.2g} |")
    return "\n".join(lines) + "\n\nCommand: the module docstring of `benchmarks/studies/laplace_render_cost.py`.\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", action="append", required=True, metavar="SCENE=RUN", help="a trained S-NeRF run")
    ap.add_argument("--views", type=int, default=2, help="validation photos rendered per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/laplace_term_analysis/render_cost"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = {}
    for item in args.run:
        scene, run = item.split("=", 1)
        results[scene] = measure(Path(run), scene, args.views, args.repeats)
    write_study(args.out, results, markdown(results))


if __name__ == "__main__":
    main()
