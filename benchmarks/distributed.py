"""Data-parallel training speed (issue 16): steps/s for 1 and 2 processes, and the
communication share of a step.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/distributed.py \\
        --data ../shared/data/nerf_llff_data/fern --preset llff --out benchmarks/results/distributed

With ``--eval N``, views/s of ``evaluation.evaluate`` instead (``stochastic-fields eval``'s loop,
views sharded over the ranks): a model is first trained in one process for ``--train-steps``
steps (not timed), then N test views are evaluated by 1 and by 2 processes, timed on rank 0 from
a barrier before the loop to the return of ``evaluate`` (rendering, scoring, per-view files,
the gather and rank 0's pooled scores and metrics.json). The two runs' metrics are checked
equal (but for timings) before the row is written:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/distributed.py --eval 4 --train-steps 50 \\
        --data ../shared/data/nerf_llff_data/fern --preset llff --out benchmarks/results/distributed/fern_eval

Each configuration runs in freshly spawned processes (gloo on CPU, one thread per process):
``1`` is plain single-process training (no process group), ``2`` two ranks, each drawing half
of ``train.rays_per_batch``, so both take steps of the same global batch. After ``--warmup``
steps, ``--steps`` steps are timed on rank 0 from the start of one step to the start of the
next (a step: batch, loss, backward, gradient reduction, optimiser, occupancy refresh). The
reducer runs with ``separate_wait``: a barrier before its all-reduces absorbs the time rank 0
waits for the slower rank (reported apart), so the communication share is the time inside the
all-reduces themselves over the step time. Writes ``distributed.json`` and ``README.md`` (the
table and the command) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.multiprocessing as mp


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(args: argparse.Namespace):
    from stochastic_fields import config as C

    cfg = C.preset(args.preset)
    cfg.data.path = str(Path(args.data).resolve()) if args.data else ""
    cfg.method = args.method
    cfg.field.backend = args.backend
    cfg.train.rays_per_batch = args.rays_per_batch
    cfg.train.iterations = args.warmup + args.steps + 1
    cfg.train.eval_every = 0
    cfg.train.checkpoint_every = 0
    cfg.train.device = "cpu"
    return cfg


def _measure_on_ranks(measure, rank: int, world: int, path: Path) -> None:
    """``measure(ctx)`` in one process (ctx None) or inside this rank's process group; rank 0
    writes the result to ``path``."""
    from stochastic_fields.distributed import process_group

    if world == 1:
        result = measure(None)
    else:
        with process_group("cpu") as ctx:
            result = measure(ctx)
    if rank == 0:
        path.write_text(json.dumps(result))


def _rank(rank: int, world: int, port: int, args: argparse.Namespace, out: str) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    torch.set_num_threads(1)
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer

    cfg = _config(args)
    run_dir = Path(out) / f"run_{world}"

    def measure(ctx) -> dict:
        dataset = load_run_dataset(cfg, run_dir)
        trainer = Trainer(cfg, run_dir, dataset, distributed=ctx)
        marks: list[tuple[float, float, float]] = []  # (time, transfer s, wait s so far) at each step's start
        compute = trainer.compute_gradients
        if trainer.reducer is not None:
            trainer.reducer.separate_wait = True

        def timed(*a):
            r = trainer.reducer
            marks.append((time.perf_counter(), r.comm_seconds if r else 0.0, r.wait_seconds if r else 0.0))
            return compute(*a)

        trainer.compute_gradients = timed
        trainer.train(progress=False, max_steps=args.warmup + args.steps + 1)
        (t0, c0, w0), (t1, c1, w1) = marks[args.warmup], marks[args.warmup + args.steps]
        return {"processes": world, "steps": args.steps, "seconds": t1 - t0, "steps_per_s": args.steps / (t1 - t0),
                "rays_per_s": args.steps * cfg.train.rays_per_batch / (t1 - t0),
                "comm_seconds": c1 - c0, "comm_share": (c1 - c0) / (t1 - t0),
                "wait_seconds": w1 - w0, "wait_share": (w1 - w0) / (t1 - t0),
                "comm_bytes_per_step": trainer.reducer.bytes_last_step if trainer.reducer else 0,
                "dense_values": sum(p.numel() for p in trainer.reducer.dense) if trainer.reducer else None,
                "table_rows": [int(t.shape[0]) for t in trainer.reducer.tables] if trainer.reducer else None}

    _measure_on_ranks(measure, rank, world, Path(out) / f"result_{world}.json")


def _eval_rank(rank: int, world: int, port: int, args: argparse.Namespace, out: str) -> None:
    """One rank of the eval benchmark: ``evaluate`` of the trained run's first ``args.eval`` test views."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    torch.set_num_threads(1)
    from stochastic_fields.evaluation import evaluate
    from stochastic_fields.trainer import load_trained_model

    run_dir = Path(out) / "run"

    def measure(ctx) -> dict:
        _, model, dataset = load_trained_model(run_dir, device="cpu")
        views = list(dataset.test_indices)[: args.eval]
        if ctx is not None:
            ctx.barrier("start of the timed evaluation")
        t0 = time.perf_counter()
        result = evaluate(model, dataset, Path(out) / f"eval_{world}", views=views, progress=False, distributed=ctx)
        seconds = time.perf_counter() - t0
        return {"processes": world, "views": len(views), "seconds": seconds, "views_per_s": len(views) / seconds,
                "pixels_per_view": int(dataset.height * dataset.width), "num_draws": result["num_draws"],
                "pooled_nll": result["pooled"]["nll"], "psnr": result["summary"]["psnr"]["mean"]}

    _measure_on_ranks(measure, rank, world, Path(out) / f"eval_result_{world}.json")


def _same_metrics(work: str, worlds: list[int]) -> bool:
    """metrics.json of every process count equal but for the timings (render_s)."""
    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k not in ("render_s", "render_s_per_view")}
        return [strip(v) for v in o] if isinstance(o, list) else o
    texts = {json.dumps(strip(json.loads((Path(work) / f"eval_{w}" / "metrics.json").read_text())), sort_keys=True)
             for w in worlds}
    return len(texts) == 1


def eval_benchmark(args: argparse.Namespace, worlds: list[int], work: str) -> list[dict]:
    """Train once (one process, not timed), then time ``evaluate`` on each process count."""
    from stochastic_fields.scenes import load_run_dataset
    from stochastic_fields.trainer import Trainer

    torch.set_num_threads(1)
    cfg = _config(args)
    cfg.train.iterations = args.train_steps
    run_dir = Path(work) / "run"
    Trainer(cfg, run_dir, load_run_dataset(cfg, run_dir)).train(progress=False)
    results = []
    for world in worlds:
        mp.start_processes(_eval_rank, args=(world, _free_port(), args, work), nprocs=world, start_method="spawn",
                           join=True)
        results.append(json.loads((Path(work) / f"eval_result_{world}.json").read_text()))
    if not _same_metrics(work, worlds):
        raise SystemExit("the sharded evaluation's metrics.json differs from one process's")
    return results


def _eval_table(results: list[dict]) -> str:
    base = results[0]["views_per_s"]
    lines = ["| processes (1 thread each) | views | views/s | s per view | speed-up |", "| --- | --- | --- | --- | --- |"]
    for r in results:
        lines.append(f"| {r['processes']} | {r['views']} | {r['views_per_s']:.4f} | {r['seconds'] / r['views']:.2f} | "
                     f"{r['views_per_s'] / base:.2f}x |")
    return "\n".join(lines)


def _matmul_rank(rank: int, world: int, out: str) -> None:
    """ms per float32 matmul [16384, 256] x [256, 256] on one thread, ``world`` processes at once."""
    torch.set_num_threads(1)
    a, b = torch.randn(16384, 256), torch.randn(256, 256)
    for _ in range(3):
        a @ b
    t0 = time.perf_counter()
    for _ in range(MATMUL_REPEATS):
        a @ b
    (Path(out) / f"matmul_{world}_{rank}.json").write_text(json.dumps((time.perf_counter() - t0) / MATMUL_REPEATS * 1e3))


#: matmuls timed per process by the machine's scaling check
MATMUL_REPEATS = 50


def machine_scaling(out: str) -> dict:
    """How much compute 2 concurrent single-thread processes get here, relative to one alone:
    ``2 t_1 / t_2`` for the same matmul (2.0 on two free cores)."""
    times = {}
    for world in (1, 2):
        mp.start_processes(_matmul_rank, args=(world, out), nprocs=world, start_method="spawn", join=True)
        times[world] = max(json.loads((Path(out) / f"matmul_{world}_{r}.json").read_text()) for r in range(world))
    return {"matmul_ms_1_process": times[1], "matmul_ms_2_processes": times[2],
            "throughput_2_vs_1": 2 * times[1] / times[2]}


def run_world(world: int, args: argparse.Namespace, out: str) -> dict:
    port = _free_port()
    mp.start_processes(_rank, args=(world, port, args, out), nprocs=world, start_method="spawn", join=True)
    return json.loads((Path(out) / f"result_{world}.json").read_text())


def _table(results: list[dict]) -> str:
    base = results[0]["steps_per_s"]
    lines = ["| processes (1 thread each) | steps/s | rays/s | speed-up | step | all-reduces (share of the step) | "
             "waiting for the slower rank (share) | bytes all-reduced per step and rank |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in results:
        comm, wait, sent = "-", "-", "-"
        if r["processes"] > 1:
            comm = f"{r['comm_seconds'] / r['steps'] * 1e3:.1f} ms ({100 * r['comm_share']:.1f}%)"
            wait = f"{r['wait_seconds'] / r['steps'] * 1e3:.1f} ms ({100 * r['wait_share']:.1f}%)"
            sent = f"{r['comm_bytes_per_step'] / 1e6:.2f} MB"
        lines.append(f"| {r['processes']} | {r['steps_per_s']:.3f} | {r['rays_per_s']:.0f} | "
                     f"{r['steps_per_s'] / base:.2f}x | {r['seconds'] / r['steps'] * 1e3:.0f} ms | {comm} | {wait} | "
                     f"{sent} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="", help="Scene folder (default: the embedded synthetic scene).")
    parser.add_argument("--preset", default="default", help="Config preset (default: default).")
    parser.add_argument("--method", default="snerf")
    parser.add_argument("--backend", default="grid", choices=("grid", "mlp"))
    parser.add_argument("--rays-per-batch", type=int, default=1024, help="Global batch (split over the ranks).")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--processes", default="1,2", help="Comma-separated process counts.")
    parser.add_argument("--eval", type=int, default=0, metavar="N",
                        help="Time the evaluation of N test views (views/s) instead of training steps.")
    parser.add_argument("--train-steps", type=int, default=50,
                        help="--eval: training steps of the evaluated model (one process, not timed).")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/distributed"))
    args = parser.parse_args()
    worlds = [int(w) for w in args.processes.split(",")]
    load_at_start = os.getloadavg()
    with tempfile.TemporaryDirectory() as work:
        scaling = machine_scaling(work)
        if args.eval:
            results = eval_benchmark(args, worlds, work)
        else:
            results = [run_world(w, args, work) for w in worlds]
    info = {"command": "OMP_NUM_THREADS=1 python " + " ".join(sys.argv), "torch": torch.__version__,
            "cpu_count": os.cpu_count(), "threads_per_process": 1, "machine": platform.processor() or platform.machine(),
            "load_average_at_start": load_at_start,
            "load_average_at_end": os.getloadavg(), "data": args.data or "embedded synthetic scene",
            "method": args.method, "eval_views": args.eval, "train_steps": args.train_steps if args.eval else None, "backend": args.backend, "rays_per_batch": args.rays_per_batch,
            "warmup_steps": args.warmup, "timed_steps": args.steps, "machine_scaling": scaling, "results": results}
    args.out.mkdir(parents=True, exist_ok=True)
    from stochastic_fields.io_utils import atomic_write_text

    atomic_write_text(args.out / "distributed.json", json.dumps(info, indent=2))
    table = _eval_table(results) if args.eval else _table(results)
    print(table)
    if args.eval:
        r = results[0]
        what = (f"`evaluate` of {r['views']} test views ({r['pixels_per_view']} pixels, K={r['num_draws']}) of "
                f"{args.method} / {args.backend} on {info['data']} trained {args.train_steps} steps; metrics.json of "
                f"every process count equal but for timings:")
    else:
        what = (f"{args.method} / {args.backend} on {info['data']}, {args.rays_per_batch} rays per step in total, "
                f"{args.steps} timed steps after {args.warmup} warm-up steps:")
    atomic_write_text(args.out / "README.md", "\n".join([
        "# Distributed evaluation speed (issue 16)" if args.eval else "# Data-parallel training speed (issue 16)", "",
        f"`benchmarks/distributed.py` on this machine ({info['cpu_count']} cores, torch {info['torch']}, gloo, "
        f"1 thread per process), " + what, "",
        "    " + info["command"], "", table, "",
        f"This machine's compute for two processes: the same float32 matmul takes {scaling['matmul_ms_1_process']:.1f} ms "
        f"in one process alone and {scaling['matmul_ms_2_processes']:.1f} ms in each of two running at once, so two "
        f"single-thread processes get {scaling['throughput_2_vs_1']:.2f}x the compute of one (2.00x on two free cores).",
        "",
        "Load average (1, 5, 15 min) at the start: " + ", ".join(f"{x:.2f}" for x in load_at_start)
        + "; at the end: " + ", ".join(f"{x:.2f}" for x in info["load_average_at_end"])
        + " (the machine is shared: other work running beside the benchmark slows both rows).", ""]))


if __name__ == "__main__":
    main()
