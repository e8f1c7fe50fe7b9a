"""Data-parallel training on ``torch.distributed`` (launched by ``torchrun``), and the process
group of the commands that shard views over the ranks (``render``, ``eval``, ``export``: rank r
renders positions r, r + W, ... of the view list, ``shard_indices``; the per-view results are
gathered to rank 0 with ``DistContext.gather_object``; see ``evaluation.evaluate`` and
``products.export.export_views``) and of the benchmark tables (``stochastic_fields_bench.runner``).

Every rank holds the whole model and draws its own share of each step's ray batch; after the
backward pass the ranks' gradients are averaged, so every rank takes the same optimiser step and
holds the same parameters. One distributed step equals one single-process step on the union of
the ranks' batches (tested):

    loss = sum_r (n_r / B) loss_r          B = train.rays_per_batch, n_r = rank r's share
    grad = (1 / W) sum_r grad[(n_r W / B) loss_r]      W ranks

(each rank scales its loss by ``n_r W / B`` before ``backward``; with W dividing B that is 1 and
the reduction is the plain average of the ranks' gradients). The shares are ``B // W`` rays, the
first ``B % W`` ranks one more (``shard_size``); the capture-point depth rays of a step are split
the same way and weighted with the colour rays' share (exact when W divides both batch sizes).

Life cycle: ``init_process_group`` reads torchrun's environment (RANK, WORLD_SIZE, LOCAL_RANK,
MASTER_ADDR, MASTER_PORT), picks the backend from the run's device (gloo on CPU, NCCL on CUDA,
one GPU per rank: ``cuda:LOCAL_RANK``) and sets a timeout (``constants.DISTRIBUTED_TIMEOUT_S``)
so that a rank that stops answering makes the others fail with a :class:`DistributedError`
naming the collective, instead of waiting forever; a rank that dies closes its connections and
the others fail at once. ``destroy_process_group`` (or the ``process_group`` context manager)
ends it.

Gradient reduction (:class:`GradientReducer`), per step:

* dense parameters (MLPs, decoders, priors, the learned noise): one all-reduce (sum, then / W)
  of a flat float32 buffer holding every dense gradient, one has-gradient flag per parameter (a
  parameter no rank touched keeps ``grad = None``, as in one process) and the logged scalars:
  ``4 (D + P + L)`` bytes for D dense values, P parameters, L logged numbers;
* the grid's row-sparse tables (``fields.row_gather.RowGradient``, consumed by
  ``optim.RowSparseAdam``): first the touched-row bitmaps are united over the ranks (gloo: one
  bitwise-OR all-reduce of bits packed 8 to a byte, ``ceil(N / 8)`` bytes per table of N rows;
  NCCL, which has no OR: a max all-reduce of one byte per row, N bytes), then only the union's
  U rows are all-reduced (sum, then / W): ``4 U C`` bytes per table of C channels, instead of
  ``4 N C`` for the dense table. Rows that no rank touched stay untouched, as lazy Adam expects;
* buffers that training keeps as running maxima of the batch (``RadianceModel.running_max_buffers``,
  S-NeRF's ``interval_scale`` behind the occupancy grid): a max all-reduce of a few numbers, so
  the occupancy grid, refreshed from the parameters with a step-seeded generator, agrees too.

A ring all-reduce sends and receives about ``2 (W - 1) / W`` times each buffer per rank. At
W = 2 on fern's default grid this is 26 MB per step and rank (``benchmarks/distributed.py``
measures the share of a step spent in these calls).

Random streams: rank r of W draws its rays and trajectories from generators seeded by
``rank_seeds(seed, r, W)``, two 64-bit seeds from ``numpy.random.SeedSequence(seed,
spawn_key=(r, step))``; one process (W = 1) keeps the seeds ``(seed, seed + 1)`` of
single-process training. Everything else random in a step is drawn from these generators or
seeded by the step number (the occupancy refresh), and initialisation is seeded by ``seed`` on
every rank (and broadcast from rank 0 once at the start), so the ranks agree on all but their
batches.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import time
from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor
from tqdm.auto import tqdm

from .constants import DISTRIBUTED_TIMEOUT_S
from .fields.row_gather import row_gradient
from .launch import DistributedError, requested_by_environment  # noqa: F401  (re-exported)
from .models.registry import resolve_device
from .config import load_config

#: torchrun's environment variables that describe a rank.
ENV_VARS: tuple[str, ...] = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def rank() -> int:
    """This process's rank (0 when no process group is running)."""
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def world_size() -> int:
    """Number of ranks (1 when no process group is running)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def is_main_process() -> bool:
    """True on rank 0 or without a process group: the process that writes files and logs."""
    return rank() == 0


def rank_seeds(seed: int, rank: int, world_size: int, step: int = 0) -> tuple[int, int]:
    """(batch seed, draw seed) of rank ``rank`` of ``world_size`` starting at ``step``.

    One process starting at step 0 keeps single-process training's ``(seed, seed + 1)``.
    Otherwise both come from ``numpy.random.SeedSequence(seed, spawn_key=(rank, step))``: the
    ranks' streams are independent (SeedSequence mixes (seed, rank, step) through a hash), and a
    resume with another number of ranks restarts them from (seed, rank, step).
    """
    if world_size == 1 and step == 0:
        return int(seed), int(seed) + 1
    state = np.random.SeedSequence(int(seed), spawn_key=(int(rank), int(step))).generate_state(2, dtype=np.uint64)
    return int(state[0]), int(state[1])


def shard_indices(total: int, rank: int, world_size: int) -> list[int]:
    """Positions ``rank, rank + W, rank + 2 W, ...`` of ``total`` items: rank r renders views[r::W]
    (round-robin, so that the ranks' shares of a view list differ by at most one view)."""
    return list(range(int(rank), int(total), int(world_size)))


def map_sharded(fn, total: int, ctx: "DistContext | None", *, what: str, desc: str, progress: bool = True):
    """``[fn(i) for i in range(total)]`` in one process (``ctx`` None), or on the ranks of ``ctx``:
    each rank calls ``fn`` on its ``shard_indices`` and rank 0 receives every result, in position
    order (None on the other ranks). ``what`` names the gather in errors; ``desc`` the progress bar
    (rank 0's only)."""
    positions = range(total) if ctx is None else shard_indices(total, ctx.rank, ctx.world_size)
    quiet = not progress or (ctx is not None and not ctx.is_main)
    mine = [(i, fn(i)) for i in tqdm(positions, desc=desc, dynamic_ncols=True, disable=quiet)]
    if ctx is None:
        return [r for _, r in mine]
    parts = ctx.gather_object(mine, what=what)
    if not ctx.is_main:
        return None
    gathered = sorted((pair for part in parts for pair in part), key=lambda pair: pair[0])
    if [i for i, _ in gathered] != list(range(total)):
        raise DistributedError(f"{what}: the ranks' results do not cover positions 0..{total - 1}")
    return [r for _, r in gathered]


def shard_size(total: int, rank: int, world_size: int) -> int:
    """Rank ``rank``'s share of ``total`` items: ``total // W``, one more for the first ``total % W`` ranks."""
    return total // world_size + (1 if rank < total % world_size else 0)


def _env_int(name: str, minimum: int) -> int:
    text = os.environ.get(name)
    if text is None:
        raise ValueError(f"distributed training needs the environment variable {name} (set by torchrun); "
                         f"launch with 'torchrun --nproc_per_node N -m stochastic_fields.cli train ...'")
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"environment variable {name} must be an integer, got {text!r}") from None
    if value < minimum:
        raise ValueError(f"environment variable {name} must be >= {minimum}, got {value}")
    return value


@dataclass(frozen=True)
class DistContext:
    """One rank's view of a running process group."""

    rank: int
    world_size: int
    local_rank: int
    device: torch.device
    backend: str
    timeout_s: float

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def _fail(self, what: str, exc: BaseException) -> DistributedError:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return DistributedError(f"rank {self.rank} of {self.world_size}: {what} failed: another rank stopped, raised "
                                f"or did not answer within {self.timeout_s:g} s (the run's timeout); see that rank's "
                                f"error above. Nothing partial was written (training keeps its last complete checkpoint; "
                                f"render/eval do not write metrics.json, export leaves --out as it was). ({type(exc).__name__}: {first})")

    @contextlib.contextmanager
    def collective(self, what: str) -> Iterator[None]:
        """Turn a failed collective into a DistributedError naming ``what``."""
        try:
            yield
        except DistributedError:
            raise
        except (RuntimeError, OSError) as exc:  # dist.DistError derives from RuntimeError
            raise self._fail(what, exc) from exc

    def barrier(self, what: str) -> None:
        with self.collective(f"barrier ({what})"):
            dist.barrier()

    def all_reduce(self, tensor: Tensor, op=dist.ReduceOp.SUM, *, what: str) -> Tensor:
        with self.collective(f"all-reduce ({what})"):
            dist.all_reduce(tensor, op=op)
        return tensor

    def broadcast_object(self, obj: object, *, what: str) -> object:
        """Rank 0's ``obj`` on every rank (pickled; for the resume state and its errors)."""
        box = [obj if self.is_main else None]
        with self.collective(f"broadcast ({what})"):
            dist.broadcast_object_list(box, src=0, device=self.device if self.backend == "nccl" else None)
        return box[0]

    def broadcast_tensors(self, tensors: Sequence[Tensor], *, what: str) -> None:
        """Overwrite ``tensors`` (on this rank's device) with rank 0's values, in place."""
        with self.collective(f"broadcast ({what})"):
            for t in tensors:  # (gloo has no bool: flags travel as bytes)
                dist.broadcast(t.data.view(torch.uint8) if t.dtype == torch.bool else t.data, src=0)

    def all_gather_bytes(self, data: Tensor, *, what: str) -> list[Tensor]:
        """Every rank's uint8 tensor [n] (same n on every rank), in rank order, on the CPU."""
        local = data.to(self.device)
        out = [torch.empty_like(local) for _ in range(self.world_size)]
        with self.collective(f"all-gather ({what})"):
            dist.all_gather(out, local)
        return [t.cpu() for t in out]

    def gather_object(self, obj: object, *, what: str) -> list[object] | None:
        """Every rank's ``obj`` (pickled) in rank order on rank 0; None on the other ranks.
        For per-view results (scores, pooled arrays, point clouds): what a rank sends is held in
        memory on rank 0 (NCCL: staged through this rank's GPU)."""
        box = [None] * self.world_size if self.is_main else None
        with self.collective(f"gather ({what})"):
            dist.gather_object(obj, box, dst=0)
        return box

    def all_gather_object(self, obj: object, *, what: str) -> list[object]:
        """Every rank's ``obj`` (pickled) in rank order, on every rank."""
        box: list[object] = [None] * self.world_size
        with self.collective(f"all-gather ({what})"):
            dist.all_gather_object(box, obj)
        return box

    @contextlib.contextmanager
    def main_first(self, what: str) -> Iterator[None]:
        """Rank 0 runs the block first (e.g. generating a scene into the run folder), the others after it."""
        if not self.is_main:
            self.barrier(what)
        yield
        if self.is_main:
            self.barrier(what)


def init_process_group(device: str = "auto", *, timeout_s: float = DISTRIBUTED_TIMEOUT_S) -> DistContext:
    """Join the process group described by torchrun's environment (``ENV_VARS``).

    ``device``: the run's ``train.device``. CPU runs use gloo; CUDA runs use NCCL with one GPU per
    rank (``cuda:LOCAL_RANK``, whatever index the option names). ``timeout_s`` bounds every
    collective (and the rendezvous). ValueError names a missing or bad variable or option.
    """
    if not dist.is_available():
        raise ValueError("this torch build has no torch.distributed; distributed training is unavailable")
    if not (timeout_s > 0 and np.isfinite(timeout_s)):
        raise ValueError(f"--dist-timeout must be a positive number of seconds, got {timeout_s!r}")
    r, w = _env_int("RANK", 0), _env_int("WORLD_SIZE", 1)
    local = _env_int("LOCAL_RANK", 0) if "LOCAL_RANK" in os.environ else r
    if r >= w:
        raise ValueError(f"environment variable RANK={r} must be < WORLD_SIZE={w}")
    for name in ("MASTER_ADDR", "MASTER_PORT"):
        if not os.environ.get(name):
            raise ValueError(f"distributed training needs the environment variable {name} (set by torchrun)")
    dev = resolve_device(device)
    if dev.type == "cuda":
        if local >= torch.cuda.device_count():
            raise ValueError(f"LOCAL_RANK={local} but only {torch.cuda.device_count()} CUDA device(s) are visible: "
                             "start at most one process per GPU (--nproc_per_node)")
        dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
        backend = "nccl"
    else:
        backend = "gloo"
    if dist.is_initialized():
        raise ValueError("a torch.distributed process group is already running in this process")
    ctx = DistContext(rank=r, world_size=w, local_rank=local, device=dev, backend=backend, timeout_s=float(timeout_s))
    with ctx.collective("rendezvous (init_process_group)"):
        dist.init_process_group(backend, rank=r, world_size=w, timeout=datetime.timedelta(seconds=float(timeout_s)))
    return ctx


def destroy_process_group() -> None:
    """Leave the process group (nothing when none is running)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


@contextlib.contextmanager
def process_group(device: str = "auto", *, timeout_s: float = DISTRIBUTED_TIMEOUT_S) -> Iterator[DistContext]:
    """``init_process_group`` for the block, ``destroy_process_group`` after it (also on errors)."""
    ctx = init_process_group(device, timeout_s=timeout_s)
    try:
        yield ctx
    finally:
        destroy_process_group()


@contextlib.contextmanager
def sharding_from_environment(run_dir, device: str | None, *,
                              timeout_s: float = DISTRIBUTED_TIMEOUT_S) -> Iterator[DistContext | None]:
    """For render/eval/export: a process group (``process_group``) when torchrun started this
    process, else None (one process). ``device``: the command's ``--device``, by default the
    run's ``train.device`` (its config.json), which picks gloo or NCCL."""
    if not requested_by_environment():
        yield None
        return
    if device is None:
        saved = os.path.join(os.fspath(run_dir), "config.json")
        device = load_config(saved).train.device if os.path.isfile(saved) else "auto"
    with process_group(device, timeout_s=timeout_s) as ctx:
        yield ctx


# ----------------------------------------------------------------------------- gradients
def pack_bits(mask: Tensor) -> Tensor:
    """bool [N] -> uint8 [ceil(N / 8)], bit j of byte i = mask[8 i + j] (numpy's packbits: 40x
    faster than the same in torch ops on the CPU)."""
    packed = np.packbits(mask.detach().cpu().numpy(), bitorder="little")
    return torch.from_numpy(packed).to(mask.device)


def unpack_bits(packed: Tensor, n: int) -> Tensor:
    """uint8 [ceil(n / 8)] -> bool [n] (inverse of ``pack_bits``)."""
    bits = np.unpackbits(packed.detach().cpu().numpy(), count=n, bitorder="little")
    return torch.from_numpy(bits).to(packed.device, torch.bool)


class GradientReducer:
    """Averages a model's gradients over the ranks before the optimiser step (module doc).

    ``reduce(extras)`` after ``backward``: the dense gradients (``p.grad``) and the grid tables'
    ``RowGradient`` rows become the averages over the ranks, running-maximum buffers the maxima,
    and ``extras`` [L] (the logged scalars) is summed over the ranks and returned.
    ``comm_seconds`` accumulates the time spent inside the collectives (for the benchmark). With
    ``separate_wait`` set, a barrier first absorbs the time this rank waits for the slowest one
    (``wait_seconds``), so that ``comm_seconds`` is the transfers alone (one more collective per step).
    """

    def __init__(self, model: torch.nn.Module, param_groups: list[dict], ctx: DistContext):
        self.ctx = ctx
        sparse_ids = {id(p) for g in param_groups if g.get("sparse") for p in g["params"]}
        self.tables = [p for g in param_groups if g.get("sparse") for p in g["params"]]
        self.dense = [p for g in param_groups if not g.get("sparse") for p in g["params"] if id(p) not in sparse_ids]
        names = set(getattr(model, "running_max_buffers", ()))
        self.max_buffers = [b for n, b in model.named_buffers() if n in names]
        self.comm_seconds = 0.0
        self.wait_seconds = 0.0
        self.separate_wait = False
        self.bytes_last_step = 0

    def _timed(self, fn, *args, **kwargs):
        if self.ctx.device.type == "cuda":
            torch.cuda.synchronize(self.ctx.device)
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        if self.ctx.device.type == "cuda":
            torch.cuda.synchronize(self.ctx.device)
        self.comm_seconds += time.perf_counter() - t0
        return out

    @torch.no_grad()
    def reduce(self, extras: Tensor) -> Tensor:
        W = self.ctx.world_size
        dev = self.ctx.device
        nbytes = 0
        if self.separate_wait:
            before = self.comm_seconds
            self._timed(self.ctx.barrier, "waiting for the slowest rank")
            self.wait_seconds += self.comm_seconds - before
            self.comm_seconds = before
        # dense gradients, has-gradient flags and the logged scalars in one buffer
        parts, flags = [], []
        for p in self.dense:
            parts.append(p.grad.reshape(-1).float() if p.grad is not None else torch.zeros(p.numel(), device=dev))
            flags.append(1.0 if p.grad is not None else 0.0)
        flat = torch.cat(parts + [torch.tensor(flags, device=dev), extras.to(dev, torch.float32).reshape(-1)])
        self._timed(self.ctx.all_reduce, flat, what="dense gradients and logged values")
        nbytes += flat.numel() * 4
        offset = 0
        counts = flat[sum(p.numel() for p in self.dense):][:len(self.dense)]
        for i, p in enumerate(self.dense):
            n = p.numel()
            if counts[i] > 0:
                p.grad = (flat[offset:offset + n] / W).view_as(p).to(p.dtype)
            offset += n
        reduced_extras = flat[offset + len(self.dense):].clone()

        if self.tables:
            self._reduce_rows()
            nbytes += self._row_bytes
        if self.max_buffers:
            packed = torch.cat([b.reshape(-1).float() for b in self.max_buffers])
            self._timed(self.ctx.all_reduce, packed, dist.ReduceOp.MAX, what="running-maximum buffers")
            nbytes += packed.numel() * 4
            offset = 0
            for b in self.max_buffers:
                b.copy_(packed[offset:offset + b.numel()].view_as(b))
                offset += b.numel()
        self.bytes_last_step = nbytes
        return reduced_extras

    def _reduce_rows(self) -> None:
        W = self.ctx.world_size
        accs = [row_gradient(t) for t in self.tables]
        for t in self.tables:
            if t.grad is not None:
                raise ValueError("distributed training expects the grid tables' gradients in their RowGradient, "
                                 f"but a table of shape {tuple(t.shape)} has a .grad")
        masks = [acc.touched_rows(t) for acc, t in zip(accs, self.tables)]
        if self.ctx.backend == "gloo":
            packed = torch.cat([pack_bits(m) for m in masks])
            self._timed(self.ctx.all_reduce, packed, dist.ReduceOp.BOR, what="touched-row bitmaps")
            sizes = [(m.numel() + 7) // 8 for m in masks]
            union = [unpack_bits(b, m.numel()) for b, m in zip(packed.split(sizes), masks)]
            self._row_bytes = packed.numel()
        else:  # NCCL has no bitwise OR: one byte per row, max
            packed = torch.cat([m.to(torch.uint8) for m in masks])
            self._timed(self.ctx.all_reduce, packed, dist.ReduceOp.MAX, what="touched-row bitmaps")
            union = [b.bool() for b in packed.split([m.numel() for m in masks])]
            self._row_bytes = packed.numel()
        rows = [u.nonzero().squeeze(1) for u in union]
        values = torch.cat([acc.rows(t, r).float().reshape(-1) for acc, t, r in zip(accs, self.tables, rows)])
        self._timed(self.ctx.all_reduce, values, what="touched grid rows")
        self._row_bytes += values.numel() * 4
        offset = 0
        for acc, t, r in zip(accs, self.tables, rows):
            n = r.numel() * t.shape[1]
            acc.replace(t, r, (values[offset:offset + n] / W).view(r.numel(), t.shape[1]))
            offset += n
