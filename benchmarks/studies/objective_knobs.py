"""Which knob of the objective lets S-NeRF's density stay uncertain at the surfaces?

Study 34 found the K trajectories agree at the capture points (their expected depths 0.03-0.08% of
the depth apart) and that without the sparse-depth likelihood they disagree three times more and
the depth errors rank better (Spearman 0.48 -> 0.66) at a cost of 0.8 dB and a quarter more depth
error. This measurement asks whether a change of the objective short of dropping that likelihood
keeps the accuracy and buys the ranking. One factor per run, everything else the default of the day
(each capture point's depth noise 1% of its depth, ``PINNED``, since changed by study 35):

* ``depth_decay``: the depth likelihood's weight falls linearly to 0 over training
  (``loss.depth_final_factor 0``): the points place the surfaces early, the pixels alone shape
  the density late;
* ``depth_no_scale``: the depth likelihood's trajectories drawn with stopgrad(scale)
  (``loss.depth_trains_scale false``): the points move the density's location only;
* ``depth_rho_3x``: each point's depth noise 3% of its depth instead of 1%
  (``loss.depth_relative_std 0.03``): the likelihood asks less of each trajectory;
* ``kl_20x``: both KL weights 20 times larger (``loss.lambda_random 0.2 --loss.lambda_observed 0.25``):
  the priors hold the variance up against the pixels;
* ``observed_kl_20x``: the observed-ray KL alone 20 times larger.

The scene is the embedded scene generated with seed 4, fresh (no study has used it; the studies'
validation scenes are seeds 1-3 and stay unread here), S-NeRF with the demo preset, training seed
4, one thread, two runs at a time, scored on its 30 test views by ``stochastic-fields eval``; the
trajectories measured as ``trajectory_spread.py`` measures them. One seed: decides nothing::

    python benchmarks/studies/objective_knobs.py --work runs/likelihood_probe \\
        --out benchmarks/results/predictive_depth_study/objective_knobs

Resumable: a run whose ``eval/metrics.json`` exists is read, not re-run.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers
from study_helpers import pooled_scores, study_command, train_and_eval, write_study  # noqa: E402
from trajectory_spread import spread_of  # noqa: E402

#: The fresh validation scene's seed (scene generation and training).
SEED = 4
#: (run name, command-line options) of each row; the first is the default.
ROWS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("today", ()),
    ("depth_decay", ("--loss.depth_final_factor", "0")),
    ("depth_no_scale", ("--loss.depth_trains_scale", "false")),
    ("depth_rho_3x", ("--loss.depth_relative_std", "0.03")),
    ("kl_20x", ("--loss.lambda_random", "0.2", "--loss.lambda_observed", "0.25")),
    ("observed_kl_20x", ("--loss.lambda_observed", "0.25")),
)
LEVELS = (0.5, 0.683, 0.9, 0.95)
#: The default of the day these rows ran that study 35 changed (each point's depth noise 1% of its
#: depth), before each row's own options.
PINNED = ("--loss.depth_relative_std", "0.01")


def row_line(name: str, options: tuple[str, ...], s: dict, t: dict) -> str:
    cov = "/".join(f"{100 * s[f'coverage_{round(100 * p)}']:.1f}" for p in LEVELS)
    return (f"| {name} | {' '.join(options) or '(default)'} | {s['psnr']:.2f} | {s['abs_rel']:.4f} | {cov} | "
            f"{100 * s['halfwidth_median_95']:.1f}% | {s['interval_score_95']:.3f} | {s['crps']:.4f} | "
            f"**{s['spearman']:.3f}** | {t['peak_scale_over_loc_median']:.3f} | {100 * t['epistemic_rel_median']:.3f}% | "
            f"{100 * t['termination_rel_median']:.2f}% |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("runs/likelihood_probe"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/predictive_depth_study/objective_knobs"))
    ap.add_argument("--jobs", type=int, default=2, help="Runs trained at once (one thread each).")
    args = ap.parse_args(argv)
    from stochastic_fields.data.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(args.work / f"scene_s{SEED}", seed=SEED)
    with ThreadPoolExecutor(args.jobs) as pool:
        metrics = list(pool.map(lambda row: train_and_eval(scene, args.work / row[0], SEED, options=PINNED + row[1]),
                                ROWS))
    scores = [pooled_scores(m, LEVELS) for m in metrics]
    spreads = [spread_of(args.work / name, SEED) for name, _ in ROWS]
    results = {"command": study_command("objective_knobs.py", argv), "seed": SEED,
               "rows": [{"name": name, "options": list(opts), "scores": s, "trajectories": t}
                        for (name, opts), s, t in zip(ROWS, scores, spreads)]}
    lines = ["# Which knob of the objective lets the density stay uncertain (one fresh seed; decides nothing)", "",
             f"Command: `{results['command']}`. Embedded scene generated with seed {SEED} (fresh), S-NeRF, demo "
             "preset, training seed 4, scored by `stochastic-fields eval` on the 30 test views; the trajectory "
             "columns as `trajectory_spread.py` (4096 FIT capture-point rays, the training draws): the density's "
             "scale over its location at the sample holding most of the weight, and the medians of the std over K of "
             "the trajectories' expected depths and of the termination spread, relative to the depth.", "",
             "| run | options | PSNR dB | depth abs-rel | cov 50 / 68 / 90 / 95 | median 95% half-width | IS95 / depth | "
             "CRPS / depth | depth Spearman | scale / loc at the surface | std over K of d_k / depth | "
             "termination spread / depth |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [row_line(name, opts, s, t) for (name, opts), s, t in zip(ROWS, scores, spreads)]
    write_study(args.out, results, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
