"""Data-parallel learners: two ranks on gloo, each on its own batches, stay bit for bit equal,
eager and then compiled (the group switching together once every rank's compile is ready)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from tests.test_learner import fragments_and_model
from tpdeb.protocol import Moments
from tpdeb.services.compiled import BackgroundCompile
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import LearnerServiceConfig
from tpdeb.services.launcher.plan import free_port
from tpdeb.services.ranks import Group, learner_tensors
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.learner import Learner, place
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.moments import batch_moments

UPDATES = 3


def rank_worker(rank: int, endpoint: str, out_dir: str) -> None:
    """One rank: its own initial networks and data; the group's start, moments and updates."""
    torch.set_num_threads(1)
    fragments, model = fragments_and_model(n=4, seed=rank)  # different on each rank
    learner = Learner(model, LossConfig(kl_target=0.01))  # the KL coefficient adapts: state
    group = Group(rank, 2, endpoint, torch.device("cpu"), timeout_s=60)
    learner.rules.reduce = group.reducer()
    numbers = group.broadcast_state(learner_tensors(learner, model), [7.0 + rank, 1.5])
    before = [p.detach().clone() for p in learner.params]
    n = len(fragments)
    batch = stack_fragments(fragments)
    compiler, compiled, states = BackgroundCompile(learner), 0, []

    def update(ready: int):
        obs = Moments(*batch_moments(np.concatenate([f.obs[:-1] for f in fragments])))
        ret = Moments(*batch_moments(np.concatenate([f.disc_returns for f in fragments])))
        agreed = group.agree(obs, ret, 3, 100 * (rank + 1), 2.0 + rank, stop=False,
                             compiled=ready)
        for rms, parts in ((model.obs_rms, agreed.obs), (model.ret_rms, agreed.ret)):
            for part in parts:
                rms.merge(part.count, part.mean, part.m2)
        learner.step(batch, np.arange(n), np.ones(n, np.float32), np.ones(n, bool))
        return agreed

    for _ in range(UPDATES):
        agreed = update(0)
    # rank 0 starts compiling an update before rank 1: the group switches when both are ready
    if rank == 0:
        compiler.start(place(batch, np.ones(n, np.float32), None, learner.device),
                       learner.normaliser())
    while not compiled:
        if rank == 1 and compiler.thread is None:
            compiler.start(place(batch, np.ones(n, np.float32), None, learner.device),
                           learner.normaliser())
        compiler.done.wait(0.05)
        mine = int(compiler.ready() and compiler.error is None)
        agreed = update(mine)  # eager, every rank, until the agreement says all are ready
        states.append((mine, agreed.compiled))
        if agreed.compiled:
            compiled = agreed.compiled
            assert compiler.install()
    for _ in range(UPDATES):
        agreed = update(0)  # compiled: the all-reduce between its two graphs
    stop = group.agree(None, None, 3, 0, 0.0, stop=rank == 1)
    state = torch.cat([t.detach().reshape(-1).double() for t in learner_tensors(learner, model)])
    moved = sum(float((p - b).abs().sum()) for p, b in zip(learner.params, before, strict=True))
    np.savez(f"{out_dir}/rank{rank}.npz", state=state.numpy(), numbers=np.array(numbers),
             progress=np.array([agreed.global_step, agreed.elapsed_s, stop.stop, moved]),
             kl_coef=learner.kl_coef, compiled=compiled, states=np.array(states),
             updates=learner.updates, runs_compiled=learner.run_update is compiler.update)
    group.close()


def test_two_learner_ranks_stay_bit_for_bit_equal(tmp_path):
    endpoint = f"127.0.0.1:{free_port()}"
    mp.start_processes(rank_worker, args=(endpoint, str(tmp_path)), nprocs=2, join=True,
                       start_method="spawn")
    ranks = [np.load(tmp_path / f"rank{r}.npz") for r in (0, 1)]
    # every tensor of the learner's state equal after updates on different batches
    np.testing.assert_array_equal(ranks[0]["state"], ranks[1]["state"])
    assert float(ranks[0]["kl_coef"]) == float(ranks[1]["kl_coef"])
    for rank in ranks:
        assert rank["numbers"].tolist() == [7.0, 1.5]  # rank 0's numbers, everywhere
        step, elapsed, stop, moved = rank["progress"].tolist()
        assert (step, elapsed) == (100, 2.0)  # rank 0's progress
        assert stop == 1.0 and moved > 0  # rank 1's stop is the group's
        assert int(rank["compiled"]) == 1 and bool(rank["runs_compiled"])
    # the group switched at the first update where both were ready, not before
    mine = [[ready for ready, _ in rank["states"].tolist()] for rank in ranks]
    agreed = [[a for _, a in rank["states"].tolist()] for rank in ranks]
    assert agreed[0] == agreed[1] == [0] * (len(agreed[0]) - 1) + [1], agreed
    assert [min(pair) for pair in zip(*mine, strict=True)] == agreed[0], mine
    assert int(ranks[0]["updates"]) == int(ranks[1]["updates"])


def test_learner_rank_settings_are_checked():
    with pytest.raises(ConfigError, match="rank"):
        LearnerServiceConfig(learners=2, rank=2)
    with pytest.raises(ConfigError, match="group_endpoint"):
        LearnerServiceConfig(learners=2, group_endpoint="nohost")
