"""Latency of DualReplay's insert / sample / update as B_p grows, against the paper's O(N) scheme.

    python bench/replay_ops.py [--sizes 1e3,1e4,1e5,1e6] [--repeats 300] [--json OUT]

(with the project installed, `pip install -e .`, so that `tpdeb_core` imports).

For each size N the prioritized buffer is filled to N items through the public `insert` (the
fill is timed and reported, not part of the result), B_u gets a small fixed population, and then
each public method is timed call by call; the table shows the median (the best of 3 rounds):
- insert: one item whose priority beats all of B_p's (B_p is full), so every timed insert takes
  the full path: find B_p's lowest item, move it to B_u, evict B_u's oldest, store the newcomer;
- sample: a batch of 32 with ζ = 0.2 (6 items from B_p, 26 from B_u), β = 0.4;
- update: 32 keys that are in B_p.
The O(N) reference does what the paper describes: priorities in a numpy array, every insert and
update recomputes all normalised sampling weights p/Σp, and sampling is np.random.choice over them
(its B_u half is the same cheap uniform draw). It runs up to 10^5, and at 10^6 only when the 10^5
timings predict it takes under a minute.

The goal (DESIGN §2) is O(log N): the 10^6 / 10^3 time ratio of each op should stay <= 3.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from tpdeb.tpdeb_core.replay import DualReplay

BATCH_SIZE = 32
ZETA = 0.2
BETA = 0.4
FRAGMENT_STEPS = 64
UNIFORM_ITEMS = 1_000
OPS = ("insert", "sample", "update")
REFERENCE_BUDGET_S = 60.0
ROUNDS = 3


class PaperReplay:
    """The O(N) reference: dense priorities, weights p/Σp recomputed on every insert/update."""

    def __init__(self, capacity: int, seed: int) -> None:
        self.priorities = np.zeros(capacity)
        self.size = 0
        self.weights = np.zeros(0)
        self.uniform_keys = np.zeros(UNIFORM_ITEMS, dtype=np.int64)  # a ring, newest overwrites
        self.uniform_next = 0
        self.rng = np.random.default_rng(seed)

    def _to_uniform(self, key: int) -> None:
        self.uniform_keys[self.uniform_next % UNIFORM_ITEMS] = key
        self.uniform_next += 1

    def _renormalise(self) -> None:
        live = self.priorities[: self.size]
        self.weights = live / live.sum()

    def insert(self, priority: float) -> None:
        if self.size < self.priorities.size:
            slot = self.size
            self.size += 1
        else:
            slot = int(np.argmin(self.priorities))
            if priority <= self.priorities[slot]:
                self._to_uniform(-1)
                return
            self._to_uniform(slot)
        self.priorities[slot] = priority
        self._renormalise()

    def sample(self, batch_size: int) -> np.ndarray:
        count = round(ZETA * batch_size)
        slots = self.rng.choice(self.size, size=count, p=self.weights)
        weights = (self.size * self.weights[slots]) ** -BETA
        weights /= (self.size * self.weights.min()) ** -BETA
        filled = min(self.uniform_next, UNIFORM_ITEMS)
        uniform = self.uniform_keys[self.rng.integers(0, filled, size=batch_size - count)]
        return np.concatenate([slots, uniform])

    def update(self, slots: np.ndarray, priorities: np.ndarray) -> None:
        self.priorities[slots] = priorities
        self._renormalise()


def rising_priorities(count: int) -> list[float]:
    """Priorities above every filled one (those are < 1), so each insert displaces B_p's lowest."""
    return (1.0 + np.arange(count) / count).tolist()


def median_s(call: Callable[[int], object], repeats: int) -> float:
    """Time `call(i)` for i in range(repeats), each call on its own, in ROUNDS consecutive
    rounds; return the smallest round median, so that a round disturbed by another process on
    this (shared, 2-core) machine does not set the result."""
    times_ns = []
    for i in range(repeats):
        start = time.perf_counter_ns()
        call(i)
        times_ns.append(time.perf_counter_ns() - start)
    per_round = max(repeats // ROUNDS, 1)
    medians = [
        statistics.median(times_ns[first : first + per_round])
        for first in range(0, repeats, per_round)
    ]
    return min(medians) * 1e-9


def fill_dual(size: int, rng: np.random.Generator, verbose: bool) -> DualReplay:
    replay = DualReplay(
        prioritized_capacity=size,
        uniform_capacity_steps=UNIFORM_ITEMS * FRAGMENT_STEPS,
        zeta=ZETA,
        alpha=1.0,
        seed=0,
    )
    priorities = rng.uniform(0.01, 1.0, size).tolist()
    step = max(size // 10, 1)
    start = time.perf_counter()
    for done in range(0, size, step):
        for priority in priorities[done : done + step]:
            replay.insert(None, priority, FRAGMENT_STEPS)
        if verbose and size >= 100_000:
            progress = min(done + step, size)
            elapsed_s = time.perf_counter() - start
            print(f"  filling B_p: {progress:>9,} / {size:,} ({elapsed_s:.1f} s)", flush=True)
    # Priority 0 never beats B_p's lowest (>= 0.01): these go to B_u.
    for _ in range(UNIFORM_ITEMS):
        replay.insert(None, 0.0, FRAGMENT_STEPS)
    stats = replay.stats()
    assert stats["prioritized_items"] == size and stats["uniform_items"] == UNIFORM_ITEMS
    if verbose:
        elapsed_s = time.perf_counter() - start
        print(f"  filled {size:,} + {UNIFORM_ITEMS:,} items in {elapsed_s:.1f} s")
    return replay


def time_dual(size: int, repeats: int, verbose: bool = True) -> dict[str, float]:
    rng = np.random.default_rng(size)
    replay = fill_dual(size, rng, verbose)
    result = {"sample": median_s(lambda _: replay.sample(BATCH_SIZE, BETA), repeats)}
    # Keys that are in B_p (no insert runs until the updates are done), 32 per update.
    pool = []
    while len(pool) < BATCH_SIZE * 8:
        batch = replay.sample(BATCH_SIZE, BETA)
        pool.extend(batch.keys[batch.from_prioritized].tolist())
    key_sets = [rng.choice(pool, BATCH_SIZE) for _ in range(repeats)]
    new_priorities = rng.uniform(0.01, 1.0, (repeats, BATCH_SIZE))
    result["update"] = median_s(
        lambda i: replay.update_priorities(key_sets[i], new_priorities[i]), repeats
    )
    fresh = rising_priorities(repeats)
    result["insert"] = median_s(lambda i: replay.insert(None, fresh[i], FRAGMENT_STEPS), repeats)
    return result


def time_reference(size: int, repeats: int) -> dict[str, float]:
    rng = np.random.default_rng(size)
    reference = PaperReplay(size, seed=0)
    # Fill without renormalising each time (that would be O(N^2)): the state is the same.
    reference.priorities[:] = rng.uniform(0.01, 1.0, size)
    reference.size = size
    reference._renormalise()
    for _ in range(UNIFORM_ITEMS):
        reference._to_uniform(-1)
    slot_sets = rng.integers(0, size, (repeats, BATCH_SIZE))
    new_priorities = rng.uniform(0.01, 1.0, (repeats, BATCH_SIZE))
    fresh = rising_priorities(repeats)
    return {
        "sample": median_s(lambda _: reference.sample(BATCH_SIZE), repeats),
        "update": median_s(lambda i: reference.update(slot_sets[i], new_priorities[i]), repeats),
        "insert": median_s(lambda i: reference.insert(fresh[i]), repeats),
    }


def format_us(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1e6:,.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes", default="1e3,1e4,1e5,1e6", help="B_p sizes (items), comma-separated"
    )
    parser.add_argument("--repeats", type=int, default=300, help="timed calls per op and size")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    sizes = sorted(int(float(size)) for size in args.sizes.split(","))

    # Untimed first round: numpy's first calls and the CPU's clock ramp-up would otherwise be
    # billed to the smallest size.
    time_dual(1_000, args.repeats, verbose=False)
    time_reference(1_000, args.repeats)

    dual: dict[int, dict[str, float]] = {}
    reference: dict[int, dict[str, float]] = {}
    for size in sizes:
        print(f"B_p = {size:,} items", flush=True)
        dual[size] = time_dual(size, args.repeats)
        if size <= 100_000:
            reference[size] = time_reference(size, args.repeats)
        else:
            # O(N): predict from the largest size measured so far.
            measured = max(reference, default=None)
            predicted_s = (
                None
                if measured is None
                else sum(reference[measured].values()) * args.repeats * size / measured
            )
            if predicted_s is not None and predicted_s < REFERENCE_BUDGET_S:
                reference[size] = time_reference(size, args.repeats)
            else:
                print("  O(N) reference skipped: predicted over a minute")

    print()
    print(
        f"Median µs per op. insert: 1 item; sample: batch {BATCH_SIZE}, zeta {ZETA}; "
        f"update: {BATCH_SIZE} keys. O(N) = the paper's scheme."
    )
    header = ["B_p items", *OPS, *(f"O(N) {op}" for op in OPS)]
    print(" | ".join(f"{name:>12}" for name in header))
    for size in sizes:
        cells = [f"{size:,}"] + [format_us(dual[size][op]) for op in OPS]
        cells += [format_us(reference.get(size, {}).get(op)) for op in OPS]
        print(" | ".join(f"{cell:>12}" for cell in cells))

    ratios: dict[str, dict[str, float]] = {}
    smallest, largest = sizes[0], sizes[-1]
    if largest > smallest:
        growth = {op: dual[largest][op] / dual[smallest][op] for op in OPS}
        ratios[f"dual_{largest}_over_{smallest}"] = growth
        print(
            f"\nDualReplay time at {largest:,} / at {smallest:,} (goal <= 3): "
            + ", ".join(f"{op} x{value:.2f}" for op, value in growth.items())
        )
    if 100_000 in reference:
        speedup = {op: reference[100_000][op] / dual[100_000][op] for op in OPS}
        ratios["reference_over_dual_at_100000"] = speedup
        print(
            "O(N) reference / DualReplay at 100,000: "
            + ", ".join(f"{op} x{value:.1f}" for op, value in speedup.items())
        )
    if args.json:
        results = {
            "unit": "seconds (median per op)",
            "batch_size": BATCH_SIZE,
            "zeta": ZETA,
            "repeats": args.repeats,
            "dual": {str(size): dual[size] for size in sizes},
            "reference": {str(size): times for size, times in reference.items()},
            "ratios": ratios,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
