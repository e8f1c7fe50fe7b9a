"""Cost of the depth map's parallax angle against the number of training views, compiled and numpy.

Every rendered view the parallax term is applied to (eval, render, export, the notebook) needs
theta_max at each opaque pixel: the widest angle between two training views that see the pixel's
rendered point (``parallax.parallax_angle``). The search over pairs grows with the square of the
views that see a point, and a user's capture may hold 30-200 photos. This times
``parallax_angle`` (the compiled pair search, ``parallax.widest_cosine``) and the numpy pair loop
it replaced (``parallax.widest_cosine_loop``, run up to ``--loop-max-views`` views: it holds every
point's rays, [T, N, 3] float64, in memory) on the same points, in one process on one thread (both
run serially; OMP_NUM_THREADS=1 keeps numpy's own threads out), and prints the largest difference
of their angles beside the seconds. The default depth map also checks free space, which projects the
same points into the same views: the free-space violation and the parallax angle are timed as two
passes (``free_space.free_space_violation`` then ``parallax_angle``) and as the one pass the product
runs (``parallax.training_view_terms``), whose values must equal the two passes' bit for bit.

The scene: T cameras on a 1 x 1 patch of the plane z = 0 looking along +z (504 x 378 pixels,
f = 400), each rendering a wall at z = 4; ``--points`` points in x, y in [-1.5, 1.5] and z in
[3, 4.1] (some behind the wall by more than the 5% tolerance: unseen).

    OMP_NUM_THREADS=1 python benchmarks/parallax_speed.py --out benchmarks/results/parallax_speed
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from stochastic_fields import parallax
from stochastic_fields.free_space import TrainingDepth, free_space_violation
from stochastic_fields.io_utils import atomic_write_text


def forward_facing_views(T: int, *, height: int = 378, width: int = 504, seed: int = 0) -> TrainingDepth:
    """T cameras at random on the patch [-0.5, 0.5]^2 of z = 0, identity rotation, each rendering a
    wall at camera z 4 with opacity 1 (module doc)."""
    K = np.array([[400.0, 0, width / 2], [0, 400.0, height / 2], [0, 0, 1]])
    w2c = np.repeat(np.eye(4)[None], T, 0)
    centres = np.random.default_rng(seed).uniform(-0.5, 0.5, (T, 2))
    w2c[:, 0, 3], w2c[:, 1, 3] = -centres[:, 0], -centres[:, 1]
    depth = np.full((T, height, width), 4.0, np.float32)
    return TrainingDepth(np.arange(T), np.stack([K] * T), w2c, depth, np.ones_like(depth))


def timed(fn, *args) -> tuple[np.ndarray, float]:
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--views", type=int, nargs="+", default=[4, 8, 29, 60, 120, 200])
    p.add_argument("--points", type=int, default=190_000, help="points per view (a 504 x 378 view's opaque pixels)")
    p.add_argument("--loop-max-views", type=int, default=60)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-1.5, 1.5, (args.points, 2)), rng.uniform(3.0, 4.1, args.points)]
    parallax.parallax_angle(X[:8], forward_facing_views(3))  # compiles (or loads) the pair search
    rows = []
    for T in args.views:
        ref = forward_facing_views(T)
        sees, sees_s = timed(parallax.views_seeing, X, ref)
        centres = ref.centres
        cos, pairs_s = timed(parallax.widest_cosine, X, centres, sees)
        row = {"views": T, "points": args.points, "mean_views_seeing": float(sees.sum(1).mean()),
               "compiled_s": sees_s + pairs_s, "loop_s": None, "max_diff_deg": None}
        if T <= args.loop_max_views:
            loop_cos, loop_pairs_s = timed(parallax.widest_cosine_loop, X, centres, sees)
            row["loop_s"] = sees_s + loop_pairs_s
            row["max_diff_deg"] = float(np.abs(parallax.angle_of_cosine(loop_cos) - parallax.angle_of_cosine(cos)).max())
        (violation, angle), one_s = timed(lambda: parallax.training_view_terms(X, ref, free_space=True, parallax=True))
        two_violation, violation_s = timed(free_space_violation, X, ref)
        two_angle, angle_s = timed(lambda: parallax.parallax_angle(X, ref)[0])
        row.update(two_pass_s=violation_s + angle_s, one_pass_s=one_s,
                   one_pass_equal=bool(np.array_equal(violation, two_violation) and np.array_equal(angle, two_angle)))
        rows.append(row)
        print(f"T={T:4d}: compiled {row['compiled_s']:6.2f} s" + (
              f", numpy loop {row['loop_s']:6.2f} s ({row['loop_s'] / row['compiled_s']:.1f}x), max angle "
              f"difference {row['max_diff_deg']:.1e} deg" if row["loop_s"] is not None else "")
              + f"; violation and parallax: two passes {row['two_pass_s']:.2f} s, one pass {one_s:.2f} s "
              f"({row['two_pass_s'] / one_s:.2f}x), equal: {row['one_pass_equal']}", flush=True)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "results.json", json.dumps({"rows": rows}, indent=1))
        lines = ["# The parallax angle's cost against the training views", "",
                 f"Command: `OMP_NUM_THREADS=1 python benchmarks/parallax_speed.py --out {args.out}` "
                 f"({args.points} points, one thread, this machine; scene in the script's docstring).", "",
                 "| training views | views seeing a point (mean) | compiled s | numpy loop s | ratio | max angle difference (deg) "
                 "| violation + parallax, two passes s | one pass s | ratio | one pass equal |",
                 "|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            loop = "-" if r["loop_s"] is None else f"{r['loop_s']:.2f}"
            ratio = "-" if r["loop_s"] is None else f"{r['loop_s'] / r['compiled_s']:.1f}x"
            diff = "-" if r["max_diff_deg"] is None else f"{r['max_diff_deg']:.1e}"
            lines.append(f"| {r['views']} | {r['mean_views_seeing']:.1f} | {r['compiled_s']:.2f} | {loop} | {ratio} | {diff} "
                         f"| {r['two_pass_s']:.2f} | {r['one_pass_s']:.2f} | {r['two_pass_s'] / r['one_pass_s']:.2f}x "
                         f"| {'yes' if r['one_pass_equal'] else 'NO'} |")
        lines += ["", "Both columns include finding the views that see each point (`parallax.views_seeing`, shared). "
                  "The numpy loop holds every view's rays, T x N x 3 float64 (0.9 GB at 200 views and 190k points); "
                  "the compiled search holds one flag per point and view. The angles agree to float rounding. The last "
                  "four columns: the free-space violation and the parallax angle (the default depth map's two "
                  "training-view terms) as two passes and as the one pass `apply_calibration` runs "
                  "(`parallax.training_view_terms`), with whether its values equal the two passes' bit for bit."]
        atomic_write_text(args.out / "README.md", "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
