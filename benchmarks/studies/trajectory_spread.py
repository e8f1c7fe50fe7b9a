"""How far apart are S-NeRF's K trajectories where the capture points are?

At the training views' FIT capture-point rays (the depth likelihood's rays, ``TrainingDepth``), with
the run's field and K = 8 trajectories drawn as in training (stratified samples, the run's render
settings), it reports per run:

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

import shlex
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the studies' shared helpers (study_helpers.py)
from study_helpers import study_parser, write_study  # noqa: E402

#: Capture-point rays per run, and the trajectories drawn on each.
RAYS, DRAWS = 4096, 8


def spread_of(run_dir: Path, seed: int) -> dict:
    from stochastic_fields.losses import termination_depth_nll
    from stochastic_fields.renderer import trajectory_weights
    from stochastic_fields.samplers import sample_along_rays
    from stochastic_fields.trainer import TrainingDepth, load_trained_model

    _, model, dataset = load_trained_model(run_dir)
    depth = TrainingDepth.from_dataset(dataset, torch.device("cpu"))
    rays, target = depth.batch(RAYS, torch.Generator().manual_seed(seed))
    st = model.render_settings
    with torch.no_grad():
        s = sample_along_rays(rays, st.num_samples, spacing=st.spacing, stratified=True,
                              generator=torch.Generator().manual_seed(seed + 1))
        loc, scale = model.field.density_params(s.positions)
        w = trajectory_weights(loc, scale, s, st, num_draws=DRAWS, generator=torch.Generator().manual_seed(seed + 2))
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
    return {"run": str(run_dir), "rays": RAYS, "draws": DRAWS, "nll": nll, "gap": nll["expected"] - nll["predictive"],
            "epistemic_rel_median": float((d_k.std(-1) / target).median()),
            "termination_rel_median": float((spread / target).median()),
            "peak_scale_over_loc_median": float((peak_scale / peak_loc.clamp_min(1e-12)).median()),
            "peak_optical_depth_median": float((peak_loc * s.deltas[rows, peak]).median())}


def main(argv: list[str] | None = None) -> int:
    p = study_parser(__doc__, "trajectory_spread", "Trained S-NeRF runs on scenes with capture points.",
                     metavar="LABEL=RUN_DIR")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    runs = {}
    for item in args.run:  # a trained run is enough (no eval needed): its checkpoint
        label, sep, path = item.partition("=")
        if not sep or not (Path(path) / "checkpoint.pt").is_file():
            p.error(f"--run expects LABEL=RUN_DIR of a trained run (with checkpoint.pt), got {item!r}")
        runs[label] = Path(path)
    results = {"command": "python benchmarks/studies/trajectory_spread.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:])),
               "torch_threads": 1}
    results["runs"] = {label: spread_of(run, args.seed) for label, run in runs.items()}
    lines = ["# How far apart S-NeRF's trajectories are at the capture points", "", f"Command: `{results['command']}`",
             "", f"{RAYS} FIT capture-point rays of the training views per run, K = {DRAWS} trajectories drawn as in "
             "training. Depth likelihood per form on the same draws (nats per ray) and the median over rays of the "
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
