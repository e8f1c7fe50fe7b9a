"""Plan a path on a run's occupancy map and print the free-path probability of each segment.

    PYTHONPATH=src python examples/plan_path.py --run runs/demo --start=-1.6,0,0.3 --goal=1.6,0,0.3 --blocking-length 0.2

1. occupancy map of the run (``stochastic-fields occupancy`` computes the same; P(voxel blocked),
   closed form from the field's rectified normals, resolution from the images' footprint);
2. cheapest 6-connected voxel path with cost length * (1 + w * -log(1 - P)) (products/plan.py),
   shortened into straight segments through voxels with P <= 0.01;
3. P(each segment is free) and P(the whole path is free) from K density trajectories
   (products/free_path.py), with Monte-Carlo errors;
4. a picture (``--png``): the occupancy map at the path's height (max over those layers) with the path.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    from stochastic_fields.products.free_path import path_free_probability
    from stochastic_fields.products.free_path_calibration import applies, load_free_path_calibration
    from stochastic_fields.products.occupancy_map import occupancy_map, run_voxel_size
    from stochastic_fields.products.plan import plan_voxel_path, simplify_voxel_path
    from stochastic_fields.trainer import load_trained_model

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True)
    ap.add_argument("--start", required=True, help="x,y,z (world, scene units)")
    ap.add_argument("--goal", required=True, help="x,y,z")
    ap.add_argument("--num-draws", type=int, default=256)
    ap.add_argument("--blocking-length", type=float, default=None,
                    help="Occupied = a crossing of this length is blocked with opacity >= 0.5 (default: the voxel).")
    ap.add_argument("--png", type=Path, default=None, help="Write a top-down picture of the map and the path.")
    args = ap.parse_args()
    torch.set_num_threads(1)
    start = np.array([float(v) for v in args.start.split(",")])
    goal = np.array([float(v) for v in args.goal.split(",")])

    _, model, ds = load_trained_model(Path(args.run), device="cpu")
    voxel = run_voxel_size(model, ds, max_cells=500_000)
    occ = occupancy_map(model.field, model.region, voxel, blocking_length=args.blocking_length, progress=True)
    print(f"occupancy: voxel {voxel:.4f}, grid {occ.shape}, {int((occ.probability > 0.5).sum())} voxels with P > 0.5")
    vox, risk = plan_voxel_path(occ, start, goal)
    way = simplify_voxel_path(occ, vox)
    print(f"voxel path: {len(vox)} voxels, sum -log(1 - P) = {risk:.3f}; {len(way) - 1} straight segments")
    with torch.no_grad():
        whole, parts = path_free_probability(lambda x: model.field.density_params(x.float()),
                                             torch.from_numpy(way), num_draws=args.num_draws, step=0.5 * voxel,
                                             shared_noise=model.render_settings.shared_noise,
                                             generator=torch.Generator().manual_seed(0))
    cal = load_free_path_calibration(args.run)  # the run's free-path map, as `free-path` applies it
    stated = (lambda p: float(cal(p))) if applies(cal, 0.5) else float
    if cal is None:
        print("P(free) below is the model's (the run has no free_path_calibration.json: `stochastic-fields "
              "calibrate --run RUN --free-path` fits one)")
    for s in range(len(way) - 1):
        print(f"  segment {s}: {np.round(way[s], 3)} -> {np.round(way[s + 1], 3)}  "
              f"P(free) = {stated(parts.probability[s]):.3f} (model {parts.probability[s]:.3f} +- {parts.stderr[s]:.3f}; "
              f"mean transmittance {parts.transmittance_mean[s]:.3f})")
    print(f"whole path: P(transmittance > 0.5) = {stated(whole.probability[0]):.3f} (model {whole.probability[0]:.3f} "
          f"+- {whole.stderr[0]:.3f}, mean {whole.transmittance_mean[0]:.3f}); P(every segment free) = "
          f"{whole.every_segment_free[0]:.3f} (the model's; K = {args.num_draws})")
    if args.png is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        zc = occ.origin[2] + (np.arange(occ.shape[2]) + 0.5) * voxel
        band = (zc >= way[:, 2].min() - voxel) & (zc <= way[:, 2].max() + voxel)  # the path's height
        top = np.fmax.reduce(occ.dense(unknown=np.nan)[:, :, band], axis=2)  # NaN (unknown) only where all are
        ext = [occ.origin[0], occ.origin[0] + occ.shape[0] * voxel, occ.origin[1], occ.origin[1] + occ.shape[1] * voxel]
        fig, ax = plt.subplots(figsize=(5, 4.5), dpi=110)
        im = ax.imshow(top.T, origin="lower", extent=ext, cmap="magma", vmin=0, vmax=1)
        ax.plot(way[:, 0], way[:, 1], "c-o", ms=3, lw=1.5, label=f"path, P(every segment free) = {whole.every_segment_free[0]:.2f}")
        ax.legend(loc="upper left", fontsize=8)
        fig.colorbar(im, ax=ax, label=f"P(occupied), max over z in [{zc[band].min():.2f}, {zc[band].max():.2f}]")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        fig.savefig(args.png, bbox_inches="tight")
        print(f"picture: {args.png}")


if __name__ == "__main__":
    main()
