"""What the colour plan's compiled draws and its colour moments buy a render, chunk by chunk.

An S-NeRF render's colour plan draws every trajectory's density to find the samples some trajectory
reaches (``renderer.colour_plan``). Two changes make that cheaper on the CPU: the draws as compiled
loops (``draw_kernels.draw_reach``; switched off by ``row_kernels.torch_ops_only``) and the colour
moments read only at the samples the plan keeps (``renderer.reached_colour_moments``; "before" reads
every sample's, as ``colour_moments`` does). Full-view timings on this machine drift by about 10%
between renders, more than either change, so the variants render the same chunk one after the other,
in a rotating order, chunk after chunk, next to the deterministic NeRF's render of the chunk:

    OMP_NUM_THREADS=2 python benchmarks/studies/render_plan_speed.py --snerf runs/tables/flower/snerf_default \\
        --deterministic runs/tables/flower/deterministic --chunks 93 --out benchmarks/results/render_plan_speed/flower.json

Prints and writes ms per chunk per variant, each variant relative to "before", and each S-NeRF
variant's time over the deterministic NeRF's (issue 36's cost target compares full renders the same way).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
import warnings
from pathlib import Path

import torch

from stochastic_fields import renderer, row_kernels
from stochastic_fields.cameras import generate_rays_for_view
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.logistic_normal_table import logistic_normal_moments_tabulated
from stochastic_fields.models.baselines import render_mean_field
from stochastic_fields.trainer import load_trained_model

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import study_command  # noqa: E402

#: (variant, compiled draws, moments only where kept); "deterministic" renders the other run
VARIANTS: tuple[tuple[str, bool, bool], ...] = (
    ("before", False, False), ("compiled draws", True, False), ("kept moments", False, True), ("both", True, True))


def _every_moment(params, reached):
    return logistic_normal_moments_tabulated(params.rgb_loc, params.rgb_scale)


@contextlib.contextmanager
def variant(compiled: bool, kept_moments: bool):
    """Within it the render has (or lacks) each change."""
    kept = renderer.reached_colour_moments
    if not kept_moments:
        renderer.reached_colour_moments = _every_moment
    try:
        with row_kernels.torch_ops_only() if not compiled else contextlib.nullcontext():
            yield
    finally:
        renderer.reached_colour_moments = kept


def time_chunks(snerf, deterministic, rays, chunk_rays: int, chunks: int) -> dict[str, float]:
    """Seconds per variant (and "deterministic") summed over ``chunks`` chunks of ``rays`` [N], each
    chunk rendered by every variant in a rotating order, after one untimed chunk each."""
    names = [v[0] for v in VARIANTS] + ["deterministic"]
    flags = {name: (compiled, kept) for name, compiled, kept in VARIANTS}
    starts = list(range(0, len(rays), chunk_rays))

    def render(name: str, chunk, seed: int) -> None:
        gen = torch.Generator().manual_seed(seed)
        if name == "deterministic":
            render_mean_field(deterministic.field, chunk, deterministic.render_settings, generator=gen)
            return
        with variant(*flags[name]):
            snerf.render_chunk(chunk, snerf.default_render_options(), generator=gen)

    totals = dict.fromkeys(names, 0.0)
    with torch.no_grad():
        for name in names:
            render(name, rays[:chunk_rays], 0)
        for n in range(chunks):
            start = starts[(7 * n) % len(starts)]  # spread over the view
            chunk = rays[start:start + chunk_rays]
            for name in names[n % len(names):] + names[:n % len(names)]:
                t0 = time.perf_counter()
                render(name, chunk, n)
                totals[name] += time.perf_counter() - t0
    return totals


def summary(totals: dict[str, float], chunks: int) -> dict:
    return {"ms_per_chunk": {k: 1e3 * v / chunks for k, v in totals.items()},
            "relative_to_before": {k: v / totals["before"] for k, v in totals.items() if k != "deterministic"},
            "over_deterministic": {k: v / totals["deterministic"] for k, v in totals.items() if k != "deterministic"}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--snerf", type=Path, required=True, help="A trained S-NeRF run.")
    p.add_argument("--deterministic", type=Path, required=True, help="The deterministic NeRF's run of the same scene.")
    p.add_argument("--chunks", type=int, default=93, help="Chunks timed (each by every variant).")
    p.add_argument("--out", type=Path, required=True, help="JSON results.")
    args = p.parse_args(argv)
    for run in (args.snerf, args.deterministic):
        if not (run / "checkpoint.pt").is_file():
            p.error(f"{run} has no checkpoint.pt")
    if args.chunks < 1:
        p.error(f"--chunks must be >= 1, got {args.chunks}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, snerf, dataset = load_trained_model(args.snerf, device="cpu")
        _, deterministic, _ = load_trained_model(args.deterministic, device="cpu", dataset=dataset)
    view = int(dataset.test_indices[0])
    rays = generate_rays_for_view(dataset.cameras, view, dataset.near, dataset.far).flatten()
    chunk_rays = snerf.default_render_options().chunk_rays
    totals = time_chunks(snerf, deterministic, rays, chunk_rays, args.chunks)
    result = {"command": study_command("render_plan_speed.py", argv), "threads": torch.get_num_threads(),
              "view": view, "chunk_rays": chunk_rays, "chunks": args.chunks, **summary(totals, args.chunks)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
