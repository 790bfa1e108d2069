"""Data-parallel learners (DESIGN §3 "Learner ranks"): `learners = N` processes as one
torch.distributed group, each sampling its own batches, their updates kept identical.

Rank r of N meets the others at `group_endpoint` (rank 0's TCP store; NCCL where each rank has
a GPU of its own, rank r on cuda:r, with a gloo group beside it for the host-side exchanges;
gloo through the host on CPUs and where ranks share a GPU). Per update:

- `average` (the update's hook, between the gradients and Adam): the gradients and the
  metrics, summed in one flat all-reduce and divided by N — every rank then clips the same
  global norm and steps Adam on the same numbers, so the parameters stay bit for bit equal.
  A compiled update is two graphs with the all-reduce run eagerly between them;
- `agree` (before the update, on the host): every rank's share of the normalisers' moments
  (each replay reply carries its steps' moments once) gathered and merged in rank order on
  every rank; rank 0's env steps and training seconds, from which every rank computes the same
  schedules (learning rate, log-std ceiling, β); and whether to stop — any rank's signal or
  rank 0's budget ends the group at the same update;
- `broadcast_state` (at the start): rank 0's learner — parameters, target policy, Adam's
  moments and steps, KL coefficient, normalisers, counters — copied to every rank, so a group
  restarted from rank 0's checkpoint starts equal wherever the other ranks' disks are.

Nothing here pickles: every exchange is a tensor of numbers.
"""

from __future__ import annotations

import datetime
import threading
from typing import NamedTuple

import numpy as np
import torch
import torch.distributed as dist

from tpdeb.protocol.messages import Moments
from tpdeb.services.compiled import COMPILE_THREAD


class Agreement(NamedTuple):
    """What every rank takes from an exchange: all ranks' moments, rank 0's progress."""

    obs: list[Moments]  # in rank order, the ranks' that had any
    ret: list[Moments]
    global_step: int
    elapsed_s: float
    stop: bool
    compiled: int  # the ranks' compiled updates: 1 all ready, 0 one still compiling, −1 one failed


class Group:
    """One learner's place in the group of `size` learners."""

    def __init__(self, rank: int, size: int, endpoint: str, device: torch.device,
                 timeout_s: float):
        self.rank, self.size, self.device = rank, size, device
        timeout = datetime.timedelta(seconds=timeout_s)
        # NCCL wants one GPU per rank; ranks sharing a GPU (or on CPUs) go through gloo
        shared = device.type == "cuda" and size > torch.cuda.device_count()
        backend = self.backend = "nccl" if device.type == "cuda" and not shared else "gloo"
        dist.init_process_group(backend, init_method=f"tcp://{endpoint}", rank=rank,
                                world_size=size, timeout=timeout)
        # host-side numbers (moments, progress) never go through NCCL
        self.host = dist.new_group(backend="gloo", timeout=timeout) if backend == "nccl" \
            else dist.group.WORLD

    def close(self) -> None:
        if dist.is_initialized():
            dist.destroy_process_group()

    # -- per update
    def reducer(self):
        """The update's hook: `average`, run eagerly between the compiled update's two graphs
        (the gradients', and Adam's with the rest), and skipped in the background compile's
        trial updates on a copy of the learner, which no other rank makes."""
        @torch.compiler.disable
        def reduce(grads: list[torch.Tensor], metrics: torch.Tensor) -> None:
            if threading.current_thread().name != COMPILE_THREAD:
                self.average(grads, metrics)
        return reduce

    def average(self, grads: list[torch.Tensor], metrics: torch.Tensor) -> None:
        """The gradients and the metrics averaged over the ranks, in place (one all-reduce)."""
        flat = torch.cat([g.reshape(-1) for g in grads] + [metrics.reshape(-1)])
        if flat.is_cuda and self.backend == "gloo":  # ranks sharing a GPU: through the host
            host = flat.cpu()
            dist.all_reduce(host)
            flat.copy_(host)
        else:
            dist.all_reduce(flat)
        flat /= self.size
        offset = 0
        for tensor in (*grads, metrics):
            n = tensor.numel()
            tensor.copy_(flat[offset:offset + n].view_as(tensor))
            offset += n

    def agree(self, obs: Moments | None, ret: Moments | None, obs_dim: int, global_step: int,
              elapsed_s: float, stop: bool, compiled: int = 0) -> Agreement:
        """Every rank's moments, rank 0's progress, anyone's stop and the least ready compiled
        update (`compiled` as in Agreement: the group switches to it together), in one
        all-gather."""
        row = np.concatenate([_packed(obs, obs_dim), _packed(ret, 1),
                              [compiled, global_step, elapsed_s, float(stop)]])
        mine = torch.as_tensor(row, dtype=torch.float64)
        rows = [torch.empty_like(mine) for _ in range(self.size)]
        dist.all_gather(rows, mine, group=self.host)
        table = torch.stack(rows).numpy()
        width = 1 + 2 * obs_dim
        obs_parts = [m for m in (_unpacked(r[:width], (obs_dim,)) for r in table) if m]
        ret_parts = [m for m in (_unpacked(r[width:width + 3], ()) for r in table) if m]
        return Agreement(obs_parts, ret_parts, int(table[0, -3]), float(table[0, -2]),
                         bool(table[:, -1].max()), int(table[:, -4].min()))

    # -- at the start
    def broadcast_state(self, tensors: list[torch.Tensor], numbers: list[float]) -> list[float]:
        """Rank 0's `tensors` copied into every rank's (in place), and its `numbers` returned."""
        for tensor in tensors:
            on_host = self.backend == "gloo"  # gloo: every tensor through the host
            if tensor.is_cuda == on_host:
                staged = tensor.cpu() if on_host else tensor.to(self.device)
                dist.broadcast(staged, src=0)
                tensor.copy_(staged)
            else:
                dist.broadcast(tensor, src=0)
        values = torch.tensor(numbers, dtype=torch.float64)
        dist.broadcast(values, src=0, group=self.host)
        return values.tolist()


def _packed(moments: Moments | None, dim: int) -> np.ndarray:
    """(count, mean, M2) as 1 + 2·dim numbers; a count of 0 when there are none."""
    if moments is None:
        return np.zeros(1 + 2 * dim)
    return np.concatenate([[moments.count], np.ravel(moments.mean), np.ravel(moments.m2)])


def _unpacked(row: np.ndarray, shape: tuple) -> Moments | None:
    dim = (row.size - 1) // 2
    if row[0] <= 0:
        return None
    return Moments(float(row[0]), row[1:1 + dim].reshape(shape).copy(),
                   row[1 + dim:].reshape(shape).copy())


def learner_tensors(learner, model) -> list[torch.Tensor]:
    """Every tensor that makes a learner's state, in a fixed order: the model's parameters and
    buffers (the normalisers' moments among them), the target policy's, Adam's moments and
    step counts, the KL coefficient."""
    state = learner.state
    return [*model.state_dict().values(), *learner.target_policy.state_dict().values(),
            *state.exp_avgs, *state.exp_avg_sqs, *state.steps, state.kl_coef]


def rank_device(setting: str, rank: int) -> str:
    """A rank's device: with GPUs (`auto` or `cuda`), one each while there are enough —
    rank r on cuda:(r mod the GPUs); an explicit cuda:N or cpu stays."""
    if setting in ("auto", "cuda") and torch.cuda.is_available():
        return f"cuda:{rank % torch.cuda.device_count()}"
    return setting
