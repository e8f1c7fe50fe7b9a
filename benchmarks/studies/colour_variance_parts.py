"""Which part of S-NeRF's colour variance ranks pixel errors (a one-view analysis, not a table).

With the Rao-Blackwellised estimator a trajectory's colour has a conditional mean E[C_k | w_k] and
variance Var[C_k | w_k]; the colour variance is their sum over trajectories (law of total
variance): the part BETWEEN trajectories, Var_k E[C_k | w_k] (where the drawn densities disagree:
geometry), plus the colour noise WITHIN them, mean_k Var[C_k | w_k] (the per-point colour-logit
scales). This script renders one test view of a trained run and prints Spearman's rank correlation
of per-pixel MSE (mean over RGB) with each part, their sum, and the between part's share.

    python benchmarks/studies/colour_variance_parts.py --run RUN [--data SCENE] [--view 1] [--raw-images]

``--data`` overrides the run's scene path (a run trained elsewhere); ``--raw-images`` reads LLFF
photos without undistortion (runs trained before the loader undistorted them).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, required=True, help="Trained S-NeRF run folder.")
    p.add_argument("--data", type=Path, default=None, help="Scene folder (default: the run's data.path).")
    p.add_argument("--view", type=int, default=1, help="Test view (default 1).")
    p.add_argument("--seed", type=int, default=0, help="Seed of the rendering noise (default 0).")
    p.add_argument("--raw-images", action="store_true", help="LLFF photos as they are (no undistortion).")
    args = p.parse_args(argv)

    import scipy.stats
    import torch

    from stochastic_fields.config import load_config
    from stochastic_fields.data import load_dataset
    from stochastic_fields.renderer import seeded_chunks
    from stochastic_fields.trainer import load_trained_model

    torch.set_num_threads(1)
    cfg = load_config(args.run / "config.json")
    path = args.data or Path(cfg.data.path)
    kwargs = {"images": cfg.data.images, "undistort": False} if (path / "poses_bounds.npy").is_file() else {}
    if not args.raw_images:
        kwargs.pop("undistort", None)
    dataset = load_dataset(path, split_every=cfg.data.split_every, **kwargs)
    _, model, dataset = load_trained_model(args.run, dataset=dataset, device="cpu")
    model.eval()
    if not hasattr(model, "render_chunk"):
        raise SystemExit(f"{args.run}: method {cfg.method!r} has no stochastic field (S-NeRF only)")
    options = model.render_options(colour_estimator="rao_blackwell")
    rays = dataset.rays(args.view).flatten()
    generators = seeded_chunks(args.seed, args.view)
    parts: dict[str, list] = {"between": [], "within": [], "mean": []}
    with torch.no_grad():
        for i, start in enumerate(range(0, len(rays), options.chunk_rays)):
            stats = model.render_chunk(rays[start:start + options.chunk_rays], options, generator=generators(i)).stats
            parts["between"].append(stats.colour_draws.var(dim=1, unbiased=False).mean(-1))
            parts["within"].append(stats.colour_noise_var_draws.mean(dim=1).mean(-1))
            parts["mean"].append(stats.colour_mean)
    between, within, mean = (torch.cat(parts[k]).double().numpy() for k in ("between", "within", "mean"))
    gt = dataset.images[args.view].reshape(-1, 3).double().numpy()
    mse = ((mean - gt) ** 2).mean(-1)
    rho = lambda x: scipy.stats.spearmanr(mse, x)[0]  # noqa: E731
    print(f"{dataset.name} view {args.view}: Spearman MSE vs between {rho(between):.3f}, within {rho(within):.3f}, "
          f"total {rho(between + within):.3f}; between share of the total {between.mean() / (between + within).mean():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
