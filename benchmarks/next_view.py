"""Does S-NeRF's uncertainty choose views that teach the model more? (issue 37; docs/studies.md,
"Next-view selection").

Per scene (LLFF fern, flower): the paper split's training views start (every 5th photo); the
tables' scored test photos are a fixed test set kept apart; the candidates are the other photos.
One view at a time, up to ``--additions``, is added by each strategy:
- ``snerf``: ``next-view``'s score (``products.next_view``: expected information gain of the
  photo's pixels under the S-NeRF being trained);
- ``random0..2``: uniformly at random (three seeds);
- ``farthest``: the candidate camera farthest from its nearest training camera;
- ``ensemble``: the same score under a deep ensemble trained on the same views (its members'
  disagreement; the ensemble is trained, and warm-started after each addition, for the choice only).
After each addition the S-NeRF (the tables' default config) is fine-tuned for ``--finetune-steps``
steps from the previous round's weights (the same warm start and budget for every strategy), then
scored on the fixed test set: colour PSNR and depth abs-rel at the SCORE capture points
(``evaluation.evaluate``, as the tables). The selection cost is the wall time of the choice (for the
ensemble: its ranking plus the training of the ensemble, which exists only to choose).

Target (issue 37): S-NeRF's choice beats random (mean of the seeds) and farthest-camera by at least
0.5 dB averaged over the additions on each scene, and is at least the ensemble's choice at no more
than a third of its selection cost.

    OMP_NUM_THREADS=1 python benchmarks/next_view.py --scenes fern --work runs/next_view \\
        --out benchmarks/results/next_view

Resumes by stage: every (scene, strategy, round) keeps its checkpoint and ``result.json`` under
``--work``; a finished one is read, not recomputed. ``results.json``, ``README.md`` and the plot
are rewritten in ``--out`` after every stage.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stochastic_fields.cameras import camera_to_world
from stochastic_fields.defaults import NEXT_VIEW_MAX_PIXELS, NEXT_VIEW_NUM_DRAWS
from stochastic_fields.io_utils import atomic_write_text
from stochastic_fields.products.export import dataset_view_specs
from stochastic_fields.products.next_view import rank_candidates
from stochastic_fields.checkpoint import load_checkpoint
from stochastic_fields.trainer import CHECKPOINT_NAME, Trainer, load_trained_model, make_optimizer
from stochastic_fields_bench.budget import BenchmarkSettings, base_config
from stochastic_fields_bench.methods import METHOD_SPECS, method_config
from stochastic_fields_bench.runner import evaluate_run, scene_inputs

#: Where the shared LLFF scenes live, relative to the repository.
DATA_ROOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "nerf_llff_data"
STRATEGIES: tuple[str, ...] = ("snerf", "random0", "random1", "random2", "farthest", "ensemble")
#: Issue 37's target: dB over random and farthest; the ensemble's selection cost over S-NeRF's.
GAIN_TARGET_DB: float = 0.5
COST_RATIO_TARGET: float = 3.0


def views_config(method: str, settings: BenchmarkSettings, dataset, scene_path: Path, views: list[int],
                 iterations: int):
    cfg = method_config(METHOD_SPECS[method], base_config(settings, dataset), scene_path)
    cfg.data.split, cfg.data.train_list = "views", ",".join(str(v) for v in sorted(views))
    cfg.train.iterations, cfg.train.eval_every, cfg.train.checkpoint_every = int(iterations), 0, 0
    return cfg


def train_stage(method: str, settings, dataset, scene_path: Path, views: list[int], run_dir: Path, *,
                iterations: int, warm: tuple[torch.nn.Module, Path] | None):
    """Train ``method`` on ``views`` into ``run_dir`` (``iterations`` steps). ``warm``: (the start
    run's model, previous round's run): a copy of the start model (its scene region, so its grid)
    with the previous round's weights, then trained with a fresh optimiser and schedule. Returns
    (model, seconds); a finished stage is loaded, not retrained."""
    def built_from(template: torch.nn.Module, weights: Path) -> torch.nn.Module:
        model = copy.deepcopy(template)
        model.load_state_dict(load_checkpoint(weights / CHECKPOINT_NAME)["model"])
        return model

    done = run_dir / "done.json"
    if done.exists():
        model = built_from(warm[0], run_dir) if warm else load_trained_model(run_dir, device="cpu")[1]
        return model.eval(), json.loads(done.read_text())["train_s"]
    cfg = views_config(method, settings, dataset, scene_path, views, iterations)
    trainer = Trainer(cfg, run_dir, dataset.train_on(views))
    if warm is not None:
        trainer.model = built_from(*warm)
        trainer.optimizer = make_optimizer(trainer.model, cfg)
    t0 = time.perf_counter()
    model = trainer.train(progress=False)
    seconds = time.perf_counter() - t0
    atomic_write_text(done, json.dumps({"train_s": seconds, "views": sorted(views)}))
    return model, seconds


def camera_centres(dataset) -> np.ndarray:
    return camera_to_world(dataset.cameras)[:, :3, 3].double().numpy()


def choose(strategy: str, model, dataset, views: list[int], pool: list[int], round_index: int) -> int:
    """The strategy's next view among ``pool``."""
    if strategy.startswith("random"):
        rng = np.random.default_rng([int(strategy[len("random"):]), round_index])
        return int(rng.choice(pool))
    if strategy == "farthest":
        c = camera_centres(dataset)
        gaps = [np.linalg.norm(c[views] - c[p], axis=1).min() for p in pool]
        return int(pool[int(np.argmax(gaps))])
    specs = dataset_view_specs(dataset, pool)
    ranking, _ = rank_candidates(model, specs, count=1, num_draws=NEXT_VIEW_NUM_DRAWS, max_pixels=NEXT_VIEW_MAX_PIXELS,
                                 seed=round_index)
    return int(pool[ranking.batch[0][0]])


def scores(result: dict) -> dict:
    depth = (result.get("pooled") or {}).get("depth") or {}
    return {"psnr": result["summary"]["psnr"]["mean"],
            "depth_abs_rel": depth.get("abs_rel", result["summary"].get("depth/abs_rel", {}).get("mean"))}


def run_scene(scene: str, args) -> dict:
    settings = BenchmarkSettings(seed=0)
    scene_path, dataset, test_views, sparse = scene_inputs(scene, settings, args.data_root)
    start_views = [int(v) for v in dataset.train_indices]
    pool0 = [v for v in range(dataset.num_views) if v not in set(start_views) | set(test_views)]
    work = Path(args.work) / scene
    print(f"[{scene}] start {start_views}, fixed test {test_views}, candidates {pool0}", flush=True)
    start, _ = train_stage("snerf_default", settings, dataset, scene_path, start_views, work / "start",
                           iterations=args.start_steps, warm=None)

    def score_model(model, run_dir: Path) -> dict:
        path = run_dir / "scores.json"
        if path.exists():
            return json.loads(path.read_text())
        res = evaluate_run(model, dataset, run_dir / "eval", views=test_views, seed=0, sparse_depth=sparse,
                           product_views=0, progress=False)
        out = scores(res)
        atomic_write_text(path, json.dumps(out))
        return out

    out = {"start_views": start_views, "test_views": test_views, "candidates": pool0,
           "start": score_model(start, work / "start"), "strategies": {}}
    for strategy in args.strategies:
        views, pool, prev, rows = list(start_views), list(pool0), work / "start", []
        chooser, chooser_dir = start, work / "start"
        if strategy == "ensemble":
            ensemble_start, _ = train_stage("ensemble", settings, dataset, scene_path, start_views,
                                            work / "ensemble_start", iterations=args.start_steps, warm=None)
            chooser = ensemble_start
            chooser_dir = work / "ensemble_start"
        model = start
        for r in range(1, args.additions + 1):
            stage = work / strategy / f"round{r}"
            record = stage / "choice.json"
            if record.exists():
                choice = json.loads(record.read_text())
            else:
                t0 = time.perf_counter()
                pick = choose(strategy, chooser if strategy == "ensemble" else model, dataset, views, pool, r)
                choice = {"pick": pick, "select_s": time.perf_counter() - t0}
                stage.mkdir(parents=True, exist_ok=True)
                atomic_write_text(record, json.dumps(choice))
            views.append(choice["pick"])
            pool.remove(choice["pick"])
            model, train_s = train_stage("snerf_default", settings, dataset, scene_path, views, stage / "snerf",
                                         iterations=args.finetune_steps, warm=(start, prev))
            prev = stage / "snerf"
            row = {"round": r, "pick": choice["pick"], "select_s": choice["select_s"], "train_s": train_s,
                   **score_model(model, stage / "snerf")}
            if strategy == "ensemble" and r < args.additions:  # the chooser follows the views, for the next choice
                chooser, ens_s = train_stage("ensemble", settings, dataset, scene_path, views, stage / "ensemble",
                                             iterations=args.finetune_steps,
                                             warm=(ensemble_start, chooser_dir))
                chooser_dir = stage / "ensemble"
                row["chooser_train_s"] = ens_s
            rows.append(row)
            print(f"[{scene}/{strategy}] round {r}: +view {choice['pick']}, PSNR {row['psnr']:.2f} dB, "
                  f"abs-rel {row['depth_abs_rel']:.4f}, choice {choice['select_s']:.1f} s", flush=True)
            out["strategies"][strategy] = rows
            _RESULTS[scene] = out
            write_outputs(_RESULTS, args)
    return out


#: Every scene's rows so far (this process's and those read from --out), rewritten after each stage.
_RESULTS: dict = {}


def summarise(res: dict) -> dict:
    """Per strategy: mean PSNR / abs-rel over the additions, selection cost per choice."""
    s = {}
    for name, rows in res["strategies"].items():
        if not rows:
            continue
        cost = [r["select_s"] + r.get("chooser_train_s", 0.0) for r in rows]
        s[name] = {"rounds": len(rows), "psnr_mean": float(np.mean([r["psnr"] for r in rows])),
                   "abs_rel_mean": float(np.mean([r["depth_abs_rel"] for r in rows])),
                   "select_s_mean": float(np.mean(cost)), "picks": [r["pick"] for r in rows]}
    rnd = [s[k] for k in s if k.startswith("random")]
    if rnd:
        s["random (mean of seeds)"] = {"rounds": min(r["rounds"] for r in rnd),
                                       "psnr_mean": float(np.mean([r["psnr_mean"] for r in rnd])),
                                       "abs_rel_mean": float(np.mean([r["abs_rel_mean"] for r in rnd])),
                                       "select_s_mean": float(np.mean([r["select_s_mean"] for r in rnd])),
                                       "picks": []}
    return s


def verdict(summary: dict, additions: int) -> str:
    need = ("snerf", "random (mean of seeds)", "farthest", "ensemble")
    if any(k not in summary or summary[k]["rounds"] < additions for k in need):
        return "incomplete"
    sn = summary["snerf"]
    parts = [f"over random {sn['psnr_mean'] - summary['random (mean of seeds)']['psnr_mean']:+.2f} dB",
             f"over farthest {sn['psnr_mean'] - summary['farthest']['psnr_mean']:+.2f} dB",
             f"over the ensemble's choice {sn['psnr_mean'] - summary['ensemble']['psnr_mean']:+.2f} dB",
             f"selection cost ensemble / S-NeRF {summary['ensemble']['select_s_mean'] / sn['select_s_mean']:.1f}x"]
    met = (sn["psnr_mean"] - summary["random (mean of seeds)"]["psnr_mean"] >= GAIN_TARGET_DB
           and sn["psnr_mean"] - summary["farthest"]["psnr_mean"] >= GAIN_TARGET_DB
           and sn["psnr_mean"] >= summary["ensemble"]["psnr_mean"]
           and summary["ensemble"]["select_s_mean"] >= COST_RATIO_TARGET * sn["select_s_mean"])
    return ("met: " if met else "not met: ") + ", ".join(parts)


def write_outputs(results: dict, args) -> None:
    """results.json, README.md and the plot in ``--out``, with the scenes another process (one per
    scene, side by side) has written there since."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if (out / "results.json").exists():
        stored = json.loads((out / "results.json").read_text()).get("scenes", {})
        results.update({k: v for k, v in stored.items() if k not in args.scenes})
    full = {"command": " ".join(sys.argv), "additions": args.additions, "finetune_steps": args.finetune_steps,
            "start_steps": args.start_steps, "threads": torch.get_num_threads(), "scenes": results,
            "summary": {s: summarise(r) for s, r in results.items()}}
    atomic_write_text(out / "results.json", json.dumps(full, indent=1))
    lines = ["# Next-view selection (issue 37)", "",
             f"Command: `{full['command']}` ({full['threads']} torch thread(s), CPU)", "",
             f"Start: the paper split's training views, S-NeRF (default) trained {args.start_steps} steps; each "
             f"addition fine-tunes it {args.finetune_steps} steps from the previous round (every strategy alike). "
             "Scored on the tables' fixed test photos: PSNR, and depth abs-rel at their SCORE capture points.", ""]
    for scene, res in results.items():
        summ = full["summary"][scene]
        lines += [f"## {scene}", "", f"Start views {res['start_views']}, test views {res['test_views']}; before any "
                  f"addition: PSNR {res['start']['psnr']:.2f} dB, abs-rel {res['start']['depth_abs_rel']:.4f}.", "",
                  f"Target: **{verdict(summ, args.additions)}**", "",
                  "| strategy | picks | PSNR per round (dB) | mean PSNR | mean abs-rel | selection s / choice |",
                  "|---|---|---|---|---|---|"]
        for name, s in summ.items():
            rows = res["strategies"].get(name, [])
            per = " / ".join(f"{r['psnr']:.2f}" for r in rows) if rows else "-"
            lines.append(f"| {name} | {s['picks'] or '-'} | {per} | {s['psnr_mean']:.2f} | {s['abs_rel_mean']:.4f} | "
                         f"{s['select_s_mean']:.1f} |")
        lines.append("")
    atomic_write_text(out / "README.md", "\n".join(lines) + "\n")
    plot(results, out / "next_view.png")


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(results), figsize=(5.5 * len(results), 7), squeeze=False)
    for j, (scene, res) in enumerate(results.items()):
        for name, rows in res["strategies"].items():
            x = [0] + [r["round"] for r in rows]
            style = dict(lw=2.2) if name == "snerf" else dict(lw=1, alpha=0.8)
            axes[0][j].plot(x, [res["start"]["psnr"]] + [r["psnr"] for r in rows], marker="o", label=name, **style)
            axes[1][j].plot(x, [res["start"]["depth_abs_rel"]] + [r["depth_abs_rel"] for r in rows], marker="o",
                            label=name, **style)
        axes[0][j].set_title(f"{scene}: test PSNR after each added view")
        axes[1][j].set_title(f"{scene}: depth abs-rel (SfM points)")
        axes[1][j].set_xlabel("views added")
        axes[0][j].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["fern", "flower"])
    p.add_argument("--strategies", nargs="+", default=list(STRATEGIES), choices=STRATEGIES)
    p.add_argument("--additions", type=int, default=4)
    p.add_argument("--start-steps", type=int, default=1000, help="Steps of the starting S-NeRF (the tables' budget).")
    p.add_argument("--finetune-steps", type=int, default=200, help="Warm-started steps after each addition.")
    p.add_argument("--data-root", type=Path, default=DATA_ROOT, help="Folder of the LLFF scenes.")
    p.add_argument("--work", type=Path, default=Path("runs/next_view"))
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/next_view"))
    args = p.parse_args()
    results_path = Path(args.out) / "results.json"
    if results_path.exists():  # other scenes' finished rows stay in the tables
        _RESULTS.update(json.loads(results_path.read_text()).get("scenes", {}))
    for scene in args.scenes:
        _RESULTS[scene] = run_scene(scene, args)
        write_outputs(_RESULTS, args)


if __name__ == "__main__":
    main()
