"""The optimiser of every method: Adam, with SparseAdam for parameters that get sparse gradients.

Grid cells (``fields.grid``) receive sparse gradients (only the cells a batch touches), which
``torch.optim.Adam`` rejects. :class:`RowSparseAdam` updates their moments and values only in the
rows where a gradient arrived (lazy Adam, as ``torch.optim.SparseAdam`` and instant-NGP), and
finds those rows with a bitmap instead of sorting the gradient's indices: ``SparseAdam``'s
coalesce (a sort of every corner index of the batch) was half of a training step at 2M cells. On the CPU the
update of a table is one compiled loop over its touched rows (``row_kernels``).
Everything else (decoders, MLPs, priors) uses Adam. One object steps, zeroes, schedules and
checkpoints both.

Second-moment decay: ``beta2`` (``train.adam_beta2``) for every parameter but the colour's, which
get ``colour_beta2`` (``train.adam_beta2_colour``): a grid's colour channels (its table's columns
``colour_channels``) and its colour decoder, as ``RadianceModel.param_groups`` marks them. Where the
two are equal the groups are the model's own (so older checkpoints load).

Learning rate: exponential decay from ``lr`` to ``lr * final_factor`` over ``total_steps``,
``lr(step) = lr * final_factor ** (step / total_steps)``, set from the step number (so a
resumed run has the same schedule without a scheduler state).
"""

from __future__ import annotations

import torch

from .constants import ADAM_EPS
from . import row_kernels


class FieldOptimizer:
    """Adam for dense groups, SparseAdam for groups marked ``{"sparse": True}``."""

    def __init__(self, param_groups: list[dict], *, total_steps: int, final_factor: float, beta2: float = 0.999,
                 colour_beta2: float | None = None):
        colour_beta2 = beta2 if colour_beta2 is None else float(colour_beta2)
        dense, sparse = [], []
        for group in param_groups:
            g = dict(group)
            colour_ids = {id(p) for p in g.pop("colour_params", ())}
            colour_channels = g.pop("colour_channels", None)
            if g.pop("sparse", False):
                if colour_channels is not None and colour_beta2 != beta2:
                    g["colour_channels"], g["colour_beta2"] = tuple(colour_channels), colour_beta2
                sparse.append(g)
            elif colour_ids and colour_beta2 != beta2:
                dense.append({**g, "params": [p for p in g["params"] if id(p) not in colour_ids]})
                dense.append({**g, "params": [p for p in g["params"] if id(p) in colour_ids],
                              "betas": (0.9, colour_beta2)})
            else:
                dense.append(g)
        dense = [g for g in dense if g["params"]]
        sparse = [g for g in sparse if g["params"]]
        for g in dense + sparse:
            g["initial_lr"] = g["lr"]
        self.optimizers: list[torch.optim.Optimizer] = []
        betas = (0.9, beta2)  # train.adam_beta2; the first moment's decay is Adam's own
        if dense:
            self.optimizers.append(torch.optim.Adam(dense, betas=betas, eps=ADAM_EPS))
        if sparse:
            self.optimizers.append(RowSparseAdam(sparse, betas=betas, eps=ADAM_EPS))
        self.total_steps = max(1, int(total_steps))
        self.final_factor = float(final_factor)

    @property
    def param_groups(self) -> list[dict]:
        return [g for opt in self.optimizers for g in opt.param_groups]

    def set_step(self, step: int) -> None:
        """Learning rates for optimiser step ``step`` (0-based) of the decay schedule."""
        self.set_progress(step / self.total_steps)

    def set_progress(self, fraction: float) -> None:
        """Learning rates at ``fraction`` of the schedule (clipped to [0, 1]):
        ``lr = initial_lr * final_factor ** fraction`` (exponential decay)."""
        factor = self.final_factor ** min(max(float(fraction), 0.0), 1.0)
        for g in self.param_groups:
            g["lr"] = g["initial_lr"] * factor

    def zero_grad(self, set_to_none: bool = True) -> None:
        for opt in self.optimizers:
            opt.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        for opt in self.optimizers:
            opt.step()

    def state_dict(self) -> dict:
        return {"optimizers": [opt.state_dict() for opt in self.optimizers]}

    def load_state_dict(self, state: dict) -> None:
        saved = state.get("optimizers")
        if saved is None or len(saved) != len(self.optimizers):
            raise ValueError("checkpoint optimiser state does not match this model's parameter groups "
                             f"({0 if saved is None else len(saved)} saved, {len(self.optimizers)} expected)")
        for opt, s in zip(self.optimizers, saved):
            opt.load_state_dict(s)


class RowSparseAdam(torch.optim.Optimizer):
    """Lazy Adam for tables [N, C] whose gradient arrives as rows (``fields.row_gather``).

    For the rows r that received gradient g_r this step (duplicates summed), with the step
    count t of the table:

        m_r <- b1 m_r + (1 - b1) g_r,   v_r <- b2 v_r + (1 - b2) g_r^2
        x_r <- x_r - lr * (m_r / (1 - b1^t)) / (sqrt(v_r / (1 - b2^t)) + eps)

    A group with ``colour_channels`` (start, stop) and ``colour_beta2`` uses that second-moment
    decay in those columns (b2 is then one per channel, elementwise above).

    Rows without gradient keep their values and moments (as ``torch.optim.SparseAdam``, whose
    updates this reproduces; tested). A table's gradient is read from its ``RowGradient``; a
    parameter with an ordinary ``.grad`` (dense or sparse) works too.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = ADAM_EPS):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps))

    @staticmethod
    def channel_beta2(p: torch.Tensor, group: dict) -> float | tuple[float, ...]:
        """The second-moment decay of table p [N, C]: the group's b2, or C of them where the group
        gives its colour channels their own (``colour_channels``, ``colour_beta2``)."""
        b2 = group["betas"][1]
        channels = group.get("colour_channels")  # absent from checkpoints saved before the option
        if channels is None:
            return b2
        start, stop = channels
        return tuple(group["colour_beta2"] if start <= c < stop else b2 for c in range(p.shape[1]))

    @staticmethod
    def _gradient_rows(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(rows [U] unique, summed gradient [U, C]) of p [N, C], or None without gradient."""
        parts = []
        acc = getattr(p, "row_gradient", None)
        if acc is not None:
            parts.append(acc.take(p))  # rows already unique and summed: the grid's fast path
        if p.grad is not None:
            g = p.grad.coalesce() if p.grad.is_sparse else p.grad
            parts.append((g.indices()[0], g.values()) if g.is_sparse else
                         (torch.arange(p.shape[0], device=p.device), g))
        parts = [(r, v) for r, v in parts if r.numel() > 0]
        if not parts:
            return None
        if len(parts) == 1:
            return parts[0]
        rows, inverse = torch.unique(torch.cat([r for r, _ in parts]), return_inverse=True)
        values = torch.cat([v.reshape(len(r), -1) for r, v in parts])
        summed = torch.zeros(len(rows), values.shape[1], dtype=p.dtype, device=p.device)
        return rows, summed.index_add_(0, inverse, values)

    def _state(self, p: torch.Tensor) -> dict:
        state = self.state[p]
        if not state:
            state["step"] = torch.zeros((), dtype=torch.float64)
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
        return state

    def _step_in_place(self, p: torch.Tensor, group: dict) -> bool:
        """The update of a table whose whole gradient waits in its ``RowGradient`` (no ``.grad``), as
        one compiled loop over the touched rows (``row_kernels``; CPU). False where it does not
        apply (then ``step`` takes the rows and updates them with torch ops: same values)."""
        acc = getattr(p, "row_gradient", None)
        buffers = None if acc is None or p.grad is not None else acc.pending(p)
        if buffers is None or not bool(buffers[1].any()):
            return False
        state = self._state(p)
        if not row_kernels.available(p, state["exp_avg"], state["exp_avg_sq"], *buffers):
            return False
        state["step"] += 1
        row_kernels.adam_touched_rows(p.data, state["exp_avg"], state["exp_avg_sq"], *buffers, lr=group["lr"],
                                      betas=(group["betas"][0], self.channel_beta2(p, group)), eps=group["eps"],
                                      step=int(state["step"]))
        acc.mark_reset()
        return True

    def zero_grad(self, set_to_none: bool = True) -> None:
        super().zero_grad(set_to_none=set_to_none)
        for group in self.param_groups:
            for p in group["params"]:
                acc = getattr(p, "row_gradient", None)
                if acc is not None:
                    acc.zero()

    @torch.no_grad()
    def step(self, closure=None):
        loss = closure() if closure is not None else None
        for group in self.param_groups:
            b1 = group["betas"][0]
            for p in group["params"]:
                if self._step_in_place(p, group):
                    continue
                taken = self._gradient_rows(p)
                if taken is None:
                    continue
                rows, g = taken
                state = self._state(p)
                state["step"] += 1
                t = float(state["step"])
                b2 = self.channel_beta2(p, group)
                m = state["exp_avg"][rows].mul_(b1).add_(g, alpha=1 - b1)
                if isinstance(b2, tuple):  # one decay per channel [C]
                    b2 = torch.tensor(b2, dtype=torch.float64).to(device=p.device, dtype=p.dtype)
                    v = state["exp_avg_sq"][rows].mul_(b2).addcmul_(g, g * (1 - b2))
                    denom = (v / (1 - b2.double() ** t).to(p.dtype)).sqrt_().add_(group["eps"])
                else:
                    v = state["exp_avg_sq"][rows].mul_(b2).addcmul_(g, g, value=1 - b2)
                    denom = (v / (1 - b2 ** t)).sqrt_().add_(group["eps"])
                state["exp_avg"].index_copy_(0, rows, m)
                state["exp_avg_sq"].index_copy_(0, rows, v)
                # rows are unique: a gather and an indexed copy (index_add_ is 2x slower on CPU)
                p.index_copy_(0, rows, p[rows].sub_(m.div_(denom), alpha=group["lr"] / (1 - b1 ** t)))
        return loss
