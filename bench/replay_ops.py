"""Latency of each replay composition's operations as B_p grows, against the paper's O(N) scheme.

    python bench/replay_ops.py [--sizes 1e3,1e4,1e5,1e6] [--repeats 300] [--quick] [--json OUT]
        [--compositions tpdeb,fifo,ppo-per,uniform] [--no-reference]

(with the project installed, `pip install -e .`, so that `tpdeb_core` imports). `--quick` is a
smoke run (10³ and 10⁴ items, 30 calls, no reference), to check that the script works.

The compositions (DESIGN §2, `tpdeb_core/replay.py`), each with B_p filled to N items through the
public `insert` (the fill is timed and reported, not part of the result) and B_u holding a small
fixed population:
- tpdeb: trajectory sampler + lowest-priority remover, ζ = 0.2;
- fifo: trajectory sampler + oldest remover, ζ = 0.2 (its P_min was an O(N) pass per sample);
- ppo-per: step sampler + oldest remover, ζ = 1 (a batch is B·T single-step draws, O(T) each);
- uniform: uniform sampler + oldest remover (priority_mode "none"), ζ = 0.2.
Each public method is then timed call by call; the table shows the median (the best of 3
rounds):
- insert: one item into the full B_p that displaces an item into B_u (for tpdeb a priority above
  all of B_p's), so every timed insert takes the full path: the remover's choice, the move to
  B_u, B_u's eviction, the newcomer's store;
- sample: a batch of 32, β = 0.4;
- update: 32 keys that are in B_p (the uniform sampler has no priorities: not timed);
- stats: sizes and B_p's priority min / max / mean (the min is P_min's tree: the weights read it).
The O(N) reference does what the paper describes for tpdeb: priorities in a numpy array, every
insert and update recomputes all normalised sampling weights p/Σp, and sampling is
np.random.choice over them. It runs up to 10^5, and at 10^6 only when the 10^5 timings predict it
takes under a minute.

The goal is O(log N): each op's time at the largest size / at the smallest should stay <= 3.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import provenance

from tpdeb.tpdeb_core.replay import DualReplay, ppo_per, tpdeb

BATCH_SIZE = 32
ZETA = 0.2
BETA = 0.4
FRAGMENT_STEPS = 64
UNIFORM_ITEMS = 1_000
UNIFORM_STEPS = UNIFORM_ITEMS * FRAGMENT_STEPS
OPS = ("insert", "sample", "update", "stats")
REFERENCE_OPS = ("insert", "sample", "update")
REFERENCE_BUDGET_S = 60.0
ROUNDS = 3

# name -> (build for N items of B_p, per-step priorities?)
COMPOSITIONS: dict[str, tuple[Callable[[int], DualReplay], bool]] = {
    "tpdeb": (lambda n: tpdeb(n, UNIFORM_STEPS, zeta=ZETA, seed=0), False),
    "fifo": (lambda n: DualReplay(n, UNIFORM_STEPS, zeta=ZETA, seed=0, retention="fifo"), False),
    "ppo-per": (lambda n: ppo_per(n, UNIFORM_STEPS, seed=0), True),
    "uniform": (lambda n: DualReplay(n, UNIFORM_STEPS, zeta=ZETA, seed=0,
                                     priority_mode="none"), False),
}


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


def priority_source(per_step: bool, rng: np.random.Generator) -> Callable[[float], object]:
    """Priorities as the composition takes them: a float, or one per step around that value."""
    if not per_step:
        return lambda value: value
    return lambda value: value * rng.uniform(0.5, 1.5, FRAGMENT_STEPS)


def fill(name: str, size: int, rng: np.random.Generator, verbose: bool) -> DualReplay:
    """B_p full with `size` items, then UNIFORM_ITEMS more that end up in B_u."""
    build, per_step = COMPOSITIONS[name]
    replay = build(size)
    priority = priority_source(per_step, rng)
    values = rng.uniform(0.01, 1.0, size).tolist()
    step = max(size // 10, 1)
    start = time.perf_counter()
    for done in range(0, size, step):
        for value in values[done : done + step]:
            replay.insert(None, priority(value), FRAGMENT_STEPS)
        if verbose and size >= 100_000:
            print(f"  filling B_p: {min(done + step, size):>9,} / {size:,} "
                  f"({time.perf_counter() - start:.1f} s)", flush=True)
    # Priority 0 never beats tpdeb's lowest (>= 0.01): these go to B_u. The oldest remover
    # moves B_p's oldest there instead.
    for _ in range(UNIFORM_ITEMS):
        replay.insert(None, priority(0.0), FRAGMENT_STEPS)
    stats = replay.stats()
    assert stats["prioritized_items"] == size and stats["uniform_items"] == UNIFORM_ITEMS, stats
    if verbose:
        print(f"  filled {size:,} + {UNIFORM_ITEMS:,} items in "
              f"{time.perf_counter() - start:.1f} s", flush=True)
    return replay


def time_composition(name: str, size: int, repeats: int, verbose: bool = True
                     ) -> dict[str, float | None]:
    rng = np.random.default_rng(size)
    replay = fill(name, size, rng, verbose)
    per_step = COMPOSITIONS[name][1]
    priority = priority_source(per_step, rng)
    result: dict[str, float | None] = {
        "sample": median_s(lambda _: replay.sample(BATCH_SIZE, BETA), repeats),
        "stats": median_s(lambda _: replay.stats(), repeats),
        "update": None,
    }
    if replay.sampler.has_priorities:
        # Keys that are in B_p (no insert runs until the updates are done), 32 per update.
        pool: list[int] = []
        while len(pool) < BATCH_SIZE * 8:
            batch = replay.sample(BATCH_SIZE, BETA)
            pool.extend(batch.keys[batch.from_prioritized].tolist())
        key_sets = [rng.choice(pool, BATCH_SIZE) for _ in range(repeats)]
        new = [[priority(v) for v in rng.uniform(0.01, 1.0, BATCH_SIZE)] for _ in range(repeats)]
        result["update"] = median_s(lambda i: replay.update_priorities(key_sets[i], new[i]),
                                    repeats)
    fresh = [priority(value) for value in rising_priorities(repeats)]
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


def maybe_reference(size: int, repeats: int, reference: dict[int, dict[str, float]]) -> None:
    """Time the O(N) reference at `size` unless it is predicted to take over a minute."""
    if size > 100_000:
        measured = max(reference, default=None)
        if measured is None or (sum(reference[measured].values()) * repeats * size / measured
                                >= REFERENCE_BUDGET_S):
            print("  O(N) reference skipped: predicted over a minute")
            return
    reference[size] = time_reference(size, repeats)


def format_us(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1e6:,.1f}"


def print_tables(results, reference, sizes) -> dict[str, dict[str, float]]:
    """The per-composition tables and the growth ratios; returns the ratios."""
    print(f"\nMedian µs per op. insert: 1 item into a full B_p; sample: batch {BATCH_SIZE}, "
          f"β {BETA}; update: {BATCH_SIZE} keys; stats: sizes + priority min/max/mean.")
    header = ["composition", "B_p items", *OPS]
    if reference:
        header += [f"O(N) {op}" for op in REFERENCE_OPS]
    print(" | ".join(f"{name:>12}" for name in header))
    for name, by_size in results.items():
        for size in sizes:
            cells = [name, f"{size:,}"] + [format_us(by_size[size][op]) for op in OPS]
            if reference:
                cells += [format_us(reference.get(size, {}).get(op) if name == "tpdeb" else None)
                          for op in REFERENCE_OPS]
            print(" | ".join(f"{cell:>12}" for cell in cells))
    ratios: dict[str, dict[str, float]] = {}
    smallest, largest = sizes[0], sizes[-1]
    if largest > smallest:
        print(f"\nTime at {largest:,} / at {smallest:,} items (goal <= 3):")
        for name, by_size in results.items():
            growth = {op: by_size[largest][op] / by_size[smallest][op] for op in OPS
                      if by_size[smallest][op] is not None}
            ratios[f"{name}_{largest}_over_{smallest}"] = growth
            print(f"  {name:>8}: " + ", ".join(f"{op} x{v:.2f}" for op, v in growth.items()))
    if 100_000 in reference and "tpdeb" in results and 100_000 in results["tpdeb"]:
        speedup = {op: reference[100_000][op] / results["tpdeb"][100_000][op]
                   for op in REFERENCE_OPS}
        ratios["reference_over_tpdeb_at_100000"] = speedup
        print("O(N) reference / tpdeb at 100,000: "
              + ", ".join(f"{op} x{value:.1f}" for op, value in speedup.items()))
    return ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1e3,1e4,1e5,1e6",
                        help="B_p sizes (items), comma-separated")
    parser.add_argument("--repeats", type=int, default=300, help="timed calls per op and size")
    parser.add_argument("--compositions", default=",".join(COMPOSITIONS),
                        help=f"comma-separated, of {', '.join(COMPOSITIONS)}")
    parser.add_argument("--no-reference", action="store_true", help="skip the O(N) reference")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: sizes 1e3,1e4, 30 repeats, no reference")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    record = provenance.start()
    if args.quick:
        args.sizes, args.repeats, args.no_reference = "1e3,1e4", 30, True
    sizes = sorted(int(float(size)) for size in args.sizes.split(","))
    names = [name for name in args.compositions.split(",") if name]
    unknown = set(names) - set(COMPOSITIONS)
    if unknown:
        parser.error(f"--compositions: unknown {sorted(unknown)}; use {', '.join(COMPOSITIONS)}")

    # Untimed first round: numpy's first calls and the CPU's clock ramp-up would otherwise be
    # billed to the smallest size.
    for name in names:
        time_composition(name, 1_000, args.repeats, verbose=False)
    results: dict[str, dict[int, dict[str, float | None]]] = {name: {} for name in names}
    reference: dict[int, dict[str, float]] = {}
    for size in sizes:
        for name in names:
            print(f"{name}: B_p = {size:,} items", flush=True)
            results[name][size] = time_composition(name, size, args.repeats)
        if not args.no_reference:
            maybe_reference(size, args.repeats, reference)

    ratios = print_tables(results, reference, sizes)
    if args.json:
        output = {
            "unit": "seconds (median per op)", "batch_size": BATCH_SIZE, "zeta": ZETA,
            "repeats": args.repeats,
            "compositions": {name: {str(s): t for s, t in by_size.items()}
                             for name, by_size in results.items()},
            "reference": {str(size): times for size, times in reference.items()},
            "ratios": ratios,
        }
        provenance.stamp(output, record)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(output, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
