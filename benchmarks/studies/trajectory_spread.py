"""How far apart are S-NeRF's K trajectories where the capture points are?

At the training views' FIT capture-point rays (the depth likelihood's rays, ``TrainingDepth``), with
the trajectories the depth likelihood draws in training (``SNeRF.depth_trajectories``: stratified
samples, the run's render settings, its K), it reports per run:

* the two forms of the depth likelihood on the same draws (``losses.termination_depth_nll``):
  'expected' -1/(R K) sum log p_rk and 'predictive' -1/R sum log 1/K sum_k p_rk, and their gap
  (Jensen's: 0 when the trajectories give each point the same likelihood);
* the median over rays of the std over k of the trajectories' expected depths d_k = sum_i w_ki t_i /
  sum_i w_ki (the depth std's epistemic part), and of the termination spread
  sqrt(1/K sum_k sum_i w_ki (t_i - mean_k d_k)^2 / sum_i w_ki), both relative to the point's depth;
* at the sample holding most of the mean weight (the surface), the median of the density's scale over
  its location s_a / mu_a (how much a draw may move the density there) and of mu_a delta.

Renders only; decides nothing (study 34's evidence, docs/studies.md)::

    python benchmarks/studies/trajectory_spread.py --run synthetic/1=RUN fern/capture=RUN ... \\
        --out benchmarks/results/predictive_depth_study/trajectory_spread
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import parse_runs, study_command, study_parser, write_study  # noqa: E402

#: Capture-point rays per run (each with the run's training trajectories, ``SNeRF.depth_trajectories``).
RAYS = 4096


def spread_of(run_dir: Path, seed: int) -> dict:
    from stochastic_fields.losses import termination_depth_nll
    from stochastic_fields.trainer import TrainingDepth, load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    depth = TrainingDepth.from_dataset(dataset, torch.device("cpu"))
    rays, target = depth.batch(RAYS, torch.Generator().manual_seed(seed))
    with torch.no_grad():  # the depth likelihood's own samples and trajectories
        s, loc, scale, w = model.depth_trajectories(rays, generator=torch.Generator().manual_seed(seed + 1))
        rho = model.loss_config.depth_relative_std
        nll = {form: float(termination_depth_nll(w, s.t_mids, s.deltas, target, rho, form))
               for form in ("expected", "predictive")}
        mass = w.sum(-1).clamp_min(1e-12)  # [R, K]
        d_k = (w * s.t_mids[:, None]).sum(-1) / mass
        mean = d_k.mean(-1, keepdim=True)
        spread = ((w * (s.t_mids[:, None] - mean[..., None]) ** 2).sum(-1) / mass).mean(-1).sqrt()
        peak = w.mean(dim=1).argmax(dim=-1)  # [R] the sample holding most of the mean weight
        rows = torch.arange(len(peak))
        peak_loc, peak_scale = loc[rows, peak], scale[rows, peak]
    return {"run": str(run_dir), "rays": RAYS, "draws": int(w.shape[1]), "nll": nll, "gap": nll["expected"] - nll["predictive"],
            "epistemic_rel_median": float((d_k.std(-1) / target).median()),
            "termination_rel_median": float((spread / target).median()),
            "peak_scale_over_loc_median": float((peak_scale / peak_loc.clamp_min(1e-12)).median()),
            "peak_optical_depth_median": float((peak_loc * s.deltas[rows, peak]).median())}


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "trajectory_spread", "Trained S-NeRF runs on scenes with capture points.",
                     metavar="LABEL=RUN_DIR")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    runs = parse_runs(p, args.run, required="checkpoint.pt")  # a trained run is enough (no eval needed)
    results = {"command": study_command("trajectory_spread.py", argv), "torch_threads": 1}
    results["runs"] = {label: spread_of(run, args.seed) for label, run in runs.items()}
    draws = ", ".join(sorted({str(r["draws"]) for r in results["runs"].values()}))
    lines = ["# How far apart S-NeRF's trajectories are at the capture points", "", f"Command: `{results['command']}`",
             "", f"{RAYS} FIT capture-point rays of the training views per run, the trajectories the depth likelihood "
             f"draws in training (`SNeRF.depth_trajectories`, K = {draws}). Depth likelihood per form on the same "
             "draws (nats per ray) and the median over rays of the "
             "trajectories' expected-depth std and of the termination spread, relative to the point's depth.", "",
             "| run | expected | predictive | gap | std over K of d_k / depth | termination spread / depth | "
             "scale / loc at the peak sample | mu delta at the peak sample |",
             "|---|---|---|---|---|---|---|---|"]
    for label, r in results["runs"].items():
        lines.append(f"| {label} | {r['nll']['expected']:.4f} | {r['nll']['predictive']:.4f} | {r['gap']:.5f} | "
                     f"{100 * r['epistemic_rel_median']:.3f}% | {100 * r['termination_rel_median']:.2f}% | "
                     f"{r['peak_scale_over_loc_median']:.3f} | {r['peak_optical_depth_median']:.2f} |")
    text = "\n".join(lines) + "\n"
    write_study(args.out, results, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
