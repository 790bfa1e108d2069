"""µs per `Learner.step`: the loss as written (autograd) against its closed-form fast path.

    python bench/loss_impl.py                     # 64×64 and 256×256, 5 rounds of 3 s each
    python bench/loss_impl.py --rounds 1 --seconds 1   # a quick look

The whole update as the learner service runs it (targets, loss and gradient, Adam, target
policy), on HalfCheetah-sized batches (obs 17, actions 6, T 64, B 8 fragments, a truncation in
each batch) with one torch thread. The implementations alternate round by round so that a
drift of the machine falls on both; the table gives each one's median over the rounds. Nothing
else should run meanwhile. Writes bench/out/loss_impl.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from pathlib import Path

import numpy as np
import provenance
import torch

from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.fragments import FragmentBatch
from tpdeb.tpdeb_core.learner import Learner
from tpdeb.tpdeb_core.loss_config import LOSS_IMPLS, LossConfig
from tpdeb.tpdeb_core.model import ActorCritic

ROOT = Path(__file__).resolve().parent.parent
OBS, ACT, T, B = 17, 6, 64, 8


def batch(rng: np.random.Generator) -> FragmentBatch:
    f32 = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    mean, log_std = 0.3 * f32(T, B, ACT), 0.1 * f32(T, B, ACT) - 1.0
    actions = (mean + np.exp(log_std) * f32(T, B, ACT)).astype(np.float32)
    terminated, truncated = np.zeros((T, B), bool), np.zeros((T, B), bool)
    truncated[T // 2, 0] = True
    return FragmentBatch(
        obs=f32(T + 1, B, OBS), actions=actions, rewards=f32(T, B), terminated=terminated,
        truncated=truncated, behaviour_mean=mean, behaviour_log_std=log_std,
        behaviour_logp=policy.log_prob(mean, log_std, actions, policy.NUMPY).astype(np.float32),
        trunc_t=np.array([T // 2], np.int32), trunc_b=np.array([0], np.int32),
        trunc_obs=f32(1, OBS), policy_version=np.zeros(B, np.int64))


def time_steps(learner: Learner, batches, seconds: float) -> float:
    """µs per step, after a warm-up."""
    keys, weights = np.arange(B), np.ones(B, np.float32)
    prioritized = np.arange(B) < 2
    cycle = itertools.cycle(batches)
    for _ in range(20):
        learner.step(next(cycle), keys, weights, prioritized)
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        learner.step(next(cycle), keys, weights, prioritized)
        calls += 1
    return 1e6 * (time.perf_counter() - start) / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=3.0, help="per round and implementation")
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "loss_impl.json"))
    args = parser.parse_args()
    record = provenance.start()
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    batches = [batch(rng) for _ in range(16)]
    results = {}
    for hidden in ((64, 64), (256, 256)):
        learners = {}
        for impl in LOSS_IMPLS:
            torch.manual_seed(0)
            learners[impl] = Learner(ActorCritic(OBS, ACT, hidden, init_log_std=-1.0),
                                     LossConfig(loss_impl=impl, ent_coef=0.01))
        rounds = {impl: [] for impl in LOSS_IMPLS}
        for r in range(args.rounds):
            for impl in LOSS_IMPLS if r % 2 == 0 else LOSS_IMPLS[::-1]:
                rounds[impl].append(time_steps(learners[impl], batches, args.seconds))
                print(f"  {hidden} {impl:11s} round {r + 1}: {rounds[impl][-1]:,.0f} µs",
                      flush=True)
        key = "x".join(map(str, hidden))
        results[key] = {impl: {"median_us": statistics.median(v), "rounds_us": v}
                        for impl, v in rounds.items()}
    print("\n| network | autograd µs | closed_form µs | autograd / closed_form |")
    print("|---|---|---|---|")
    for key, r in results.items():
        a, c = r["autograd"]["median_us"], r["closed_form"]["median_us"]
        print(f"| {key} | {a:,.0f} | {c:,.0f} | {a / c:.2f} |")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(provenance.stamp(results, record), indent=1) + "\n")


if __name__ == "__main__":
    main()
