"""Dual replay (DESIGN §2): a prioritized buffer B_p beside a FIFO uniform buffer B_u.

B_p keeps the `prioritized_capacity` fragments with the highest priority seen so far (a newcomer
enters only by beating the current lowest, which then moves to B_u); B_u keeps the most recent
fragments that are not in B_p, bounded in steps. A batch of B draws round(ζB) items from B_p,
∝ priority^α, and the rest uniformly from B_u.

The paper recomputes every normalised weight on each insert, O(N). Here B_p is indexed by
segment trees over its slots, so insert, sample (per item) and update are O(log N):
- `_mass` (sum): sampling mass of each slot — p^α, Σ_t p_t^α in step mode, 1 in "none" mode;
- `_rank` (min): what B_p membership compares — the priority, Σ_t p_t in step mode, or the
  insertion key in "none" mode (so the oldest item is the lowest and gets displaced). In
  trajectory mode its minimum also fixes the largest importance weight, as x ↦ x^α is monotone;
- `_min_step_mass` (min, step mode only): each fragment's smallest p_t^α, for the same purpose.

Priorities are clamped to ≥ `min_priority` as they arrive and everything downstream (membership,
sampling, weights, stats) sees the clamped value: then p^α > 0, and every item in B_p can be drawn.

ζ = 0 is a plain replay: B_p is bypassed and every item goes to B_u (else B_p would hold the
highest-priority items where no batch can reach them). `retention="fifo"` makes B_p a FIFO that
is still *sampled* by priority (PER over the newest items, the PPO+PER baseline): the oldest
item is displaced, whatever its priority.

In "step" mode the prioritized part of a batch is round(ζB) items' worth of transitions (T
draws per item, Schaul et al.'s PER over single steps), returned as the distinct fragments that
were drawn with a per-step weight matrix (Σ of the importance weights of the draws that hit each
step): the learner then trains on as many transitions as in trajectory mode.

Pure: numpy and the standard library only — no I/O, no clocks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from tpdeb.tpdeb_core.sumtree import MinTree, SumTree

PRIORITY_MODES = ("trajectory", "step", "none")
RETENTIONS = ("priority", "fifo")


@dataclass(frozen=True)
class ReplaySample:
    """One batch. Prioritized items come first, then uniform ones; arrays are aligned with items."""

    items: list[Any]
    keys: np.ndarray  # int64[B]
    from_prioritized: np.ndarray  # bool[B]
    weights: np.ndarray  # float32[B]: importance weights, exactly 1.0 for uniform items
    # "step" mode: float32[B, T] per-step loss weights (Σ of the importance weights of the
    # draws at each step; all 1.0 on uniform rows); None in the other modes
    step_weights: np.ndarray | None = None
    steps_drawn: int = 0  # transitions it stands for: 1 per step-mode draw, all steps of the rest


class _Leaf(NamedTuple):
    """What one B_p slot's trees hold, derived from a (validated, clamped) priority."""

    rank: float
    mass: float
    step_masses: np.ndarray | None = None  # p_t^α per step, "step" mode only


class _UniformEntry(NamedTuple):
    key: int
    item: Any
    num_steps: int


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_int(name: str, value: Any, minimum: int) -> int:
    if not _is_int(value) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _check_real(name: str, value: Any, low: float, high: float = math.inf) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not (math.isfinite(number) and low <= number <= high):
        bounds = f">= {low}" if high == math.inf else f"in [{low}, {high}]"
        raise ValueError(f"{name} must be finite and {bounds}, got {value!r}")
    return number


class DualReplay:
    """Prioritized buffer B_p (items) + uniform FIFO B_u (steps) storing opaque items.

    Args:
        prioritized_capacity: most items B_p holds (N_p).
        uniform_capacity_steps: most steps B_u holds (N_u); the oldest items are evicted past it.
        zeta: share of each batch drawn from B_p, round(zeta * batch_size).
        alpha: priority exponent; B_p samples ∝ priority^alpha (0 = uniform within B_p).
        seed: seeds the PCG64 generator used for all sampling.
        priority_mode: "trajectory" (one priority per item), "step" (one per step: PER over
            single transitions) or "none" (B_p holds the newest items, sampled uniformly).
        min_priority: floor applied to stored priorities so that priority^alpha > 0.
        retention: which item B_p gives up when full: "priority" (the lowest; TPDEB) or
            "fifo" (the oldest; sampling stays by priority).
    """

    def __init__(
        self,
        prioritized_capacity: int,
        uniform_capacity_steps: int,
        zeta: float = 0.2,
        alpha: float = 1.0,
        seed: int | None = None,
        priority_mode: str = "trajectory",
        min_priority: float = 1e-6,
        retention: str = "priority",
    ) -> None:
        self._capacity = _check_int("prioritized_capacity", prioritized_capacity, 1)
        self._uniform_capacity_steps = _check_int(
            "uniform_capacity_steps", uniform_capacity_steps, 1
        )
        self._zeta = _check_real("zeta", zeta, 0.0, 1.0)
        self._alpha = _check_real("alpha", alpha, 0.0)
        if priority_mode not in PRIORITY_MODES:
            raise ValueError(
                f"priority_mode must be one of {PRIORITY_MODES}, got {priority_mode!r}"
            )
        self._mode = priority_mode
        if retention not in RETENTIONS:
            raise ValueError(f"retention must be one of {RETENTIONS}, got {retention!r}")
        self._fifo = retention == "fifo"
        self._min_priority = _check_real("min_priority", min_priority, 0.0)
        if self._min_priority == 0.0:
            raise ValueError(
                f"min_priority must be > 0 so that priority^alpha > 0, got {min_priority!r}"
            )
        if seed is not None and not _is_int(seed):
            raise ValueError(f"seed must be an integer or None, got {seed!r}")
        self._rng = np.random.Generator(np.random.PCG64(seed))

        # B_p: slot-indexed storage; a slot is free when its key is -1.
        n = self._capacity
        self._items: list[Any] = [None] * n
        self._slot_keys = np.full(n, -1, dtype=np.int64)
        self._slot_steps = np.zeros(n, dtype=np.int64)
        self._step_masses: list[np.ndarray | None] = [None] * n
        self._slot_of_key: dict[int, int] = {}
        self._free_slots = list(range(n - 1, -1, -1))  # pop() hands out slot 0 first
        self._mass = SumTree(n)
        self._min_step_mass = MinTree(n) if priority_mode == "step" else None
        self._rank = MinTree(n)
        self._prioritized_steps = 0

        # B_u: a list read from `_uniform_head` (the oldest live entry): O(1) random access and
        # O(1) amortised eviction; the dead prefix is dropped once it is the larger half.
        self._uniform: list[_UniformEntry | None] = []
        self._uniform_head = 0
        self._uniform_steps = 0

        self._next_key = 0
        self._inserted = 0
        self._displaced = 0
        self._evicted = 0
        self._sampled = 0
        self._sampled_steps = 0

    # ----------------------------------------------------------------------------- insert

    def insert(self, item: Any, priority: float | np.ndarray, num_steps: int) -> int:
        """Store `item` (`num_steps` long) and return its key (0, 1, 2, ...).

        `priority` is a float in "trajectory" mode, an array of `num_steps` per-step priorities
        in "step" mode, and ignored in "none" mode. The item enters B_p if B_p has room or if
        its priority is strictly greater than the lowest in B_p (which moves to B_u); otherwise
        it goes to B_u. B_u then evicts its oldest items until it fits in its step budget.
        """
        if not _is_int(num_steps) or not 1 <= num_steps <= self._uniform_capacity_steps:
            raise ValueError(
                f"num_steps must be an integer in [1, uniform_capacity_steps="
                f"{self._uniform_capacity_steps}], got {num_steps!r}"
            )
        num_steps = int(num_steps)
        key = self._next_key
        leaf = self._leaf(priority, num_steps, key, "priority")
        self._next_key += 1
        self._inserted += 1

        if self._fifo:
            leaf = leaf._replace(rank=float(key))
        if self._zeta == 0.0:
            self._append_uniform(key, item, num_steps)
        elif self._free_slots:
            self._store_prioritized(self._free_slots.pop(), key, item, num_steps, leaf)
        elif leaf.rank > self._rank.min():
            slot = self._rank.argmin()
            old_key = int(self._slot_keys[slot])
            del self._slot_of_key[old_key]
            self._prioritized_steps -= int(self._slot_steps[slot])
            self._append_uniform(old_key, self._items[slot], int(self._slot_steps[slot]))
            self._displaced += 1
            self._store_prioritized(slot, key, item, num_steps, leaf)
        else:
            self._append_uniform(key, item, num_steps)
        self._evict_uniform()
        return key

    def _leaf(self, priority: Any, num_steps: int, key: int, name: str) -> _Leaf:
        """Validate a priority and turn it into tree values (the rank, masses)."""
        if self._mode == "none":
            return _Leaf(rank=float(key), mass=1.0)
        if self._mode == "trajectory":
            clamped = max(_check_real(name, priority, 0.0), self._min_priority)
            try:
                power = clamped**self._alpha
            except OverflowError:  # Python floats raise where numpy would give inf
                power = math.inf
            mass = self._checked_mass(power, name, priority)
            return _Leaf(rank=clamped, mass=mass)
        return self._step_leaf(priority, num_steps, name)

    def _step_leaf(self, priority: Any, num_steps: int | None, name: str) -> _Leaf:
        """Step mode: validate per-step priorities (`num_steps` long when known)."""
        try:
            steps = np.asarray(priority, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(
                f"{name} must be an array of per-step priorities, got {priority!r}"
            ) from None
        expected = steps.shape if num_steps is None else (num_steps,)
        if steps.ndim != 1 or steps.size == 0 or steps.shape != expected:
            raise ValueError(
                f"{name} must be a 1-D array of num_steps={num_steps} per-step priorities in "
                f"step mode, got shape {steps.shape}"
            )
        if not np.all(np.isfinite(steps)) or np.any(steps < 0):
            raise ValueError(f"{name} must be finite and >= 0 at every step, got {steps!r}")
        clamped_steps = np.maximum(steps, self._min_priority)
        step_masses = clamped_steps**self._alpha
        self._checked_mass(float(step_masses.min()), name, priority)
        mass = self._checked_mass(float(step_masses.sum()), name, priority)
        return _Leaf(rank=float(clamped_steps.sum()), mass=mass, step_masses=step_masses)

    def _checked_mass(self, mass: float, name: str, priority: Any) -> float:
        if not 0.0 < mass < math.inf:
            raise ValueError(
                f"{name}={priority!r} with alpha={self._alpha} gives a sampling mass of {mass}; "
                f"lower alpha, or rescale priorities / raise min_priority={self._min_priority}"
            )
        return mass

    def _store_prioritized(self, slot: int, key: int, item: Any, num_steps: int, leaf: _Leaf):
        self._items[slot] = item
        self._slot_keys[slot] = key
        self._slot_steps[slot] = num_steps
        self._step_masses[slot] = leaf.step_masses
        self._slot_of_key[key] = slot
        self._prioritized_steps += num_steps
        self._mass.set(slot, leaf.mass)
        self._rank.set(slot, leaf.rank)
        if self._min_step_mass is not None:
            self._min_step_mass.set(slot, float(leaf.step_masses.min()))

    def _append_uniform(self, key: int, item: Any, num_steps: int) -> None:
        self._uniform.append(_UniformEntry(key, item, num_steps))
        self._uniform_steps += num_steps

    def _evict_uniform(self) -> None:
        while self._uniform_steps > self._uniform_capacity_steps:
            oldest = self._uniform[self._uniform_head]
            self._uniform[self._uniform_head] = None  # release the item now, not at compaction
            self._uniform_head += 1
            self._uniform_steps -= oldest.num_steps
            self._evicted += 1
        if self._uniform_head * 2 > len(self._uniform):
            del self._uniform[: self._uniform_head]
            self._uniform_head = 0

    # ----------------------------------------------------------------------------- sample

    def sample(self, batch_size: int, beta: float = 1.0) -> ReplaySample:
        """Draw `batch_size` items with replacement: round(ζB) from B_p, the rest from B_u.

        When one buffer is empty the other fills the whole batch. Prioritized items carry
        importance weights w = (N·P)^(-β) / max_j (N·P_j)^(-β) = (P / P_min)^(-β): N and the
        total cancel, and P_min comes from a min tree, so no O(N) pass is needed. The sampling
        unit (for N, P) is the item, or the step in "step" mode.
        """
        batch_size = _check_int("batch_size", batch_size, 1)
        beta = _check_real("beta", beta, 0.0, 1.0)
        uniform_items = len(self._uniform) - self._uniform_head
        if not self._slot_of_key and uniform_items == 0:
            raise ValueError(
                "cannot sample from an empty DualReplay (both buffers hold 0 items): insert "
                "first, or gate sampling on a RateLimiter's min_size_to_sample"
            )
        if uniform_items == 0:
            num_prioritized = batch_size
        elif not self._slot_of_key:
            num_prioritized = 0
        else:
            num_prioritized = round(self._zeta * batch_size)

        if self._mode == "step":
            slots, step_weights, weights, drawn = self._sample_steps(num_prioritized, beta)
        else:
            slots, weights = self._sample_prioritized(num_prioritized, beta)
            step_weights, drawn = None, int(self._slot_steps[slots].sum())
        num_uniform = batch_size - num_prioritized
        positions = self._rng.integers(self._uniform_head, len(self._uniform), size=num_uniform)
        uniform_entries = [self._uniform[i] for i in positions.tolist()]

        items = [self._items[s] for s in slots.tolist()] + [e.item for e in uniform_entries]
        keys = np.concatenate(
            [self._slot_keys[slots], np.array([e.key for e in uniform_entries], dtype=np.int64)]
        )
        rows = len(items)
        from_prioritized = np.arange(rows) < slots.size
        all_weights = np.ones(rows, dtype=np.float32)
        all_weights[:slots.size] = weights
        uniform_steps = sum(e.num_steps for e in uniform_entries)
        if step_weights is not None:
            width = max([step_weights.shape[1], *(e.num_steps for e in uniform_entries)])
            matrix = np.zeros((rows, width), dtype=np.float32)
            matrix[:slots.size, :step_weights.shape[1]] = step_weights
            for row, entry in enumerate(uniform_entries, start=slots.size):
                matrix[row, :entry.num_steps] = 1.0
            step_weights = matrix

        self._sampled += batch_size
        self._sampled_steps += drawn + uniform_steps
        return ReplaySample(items, keys, from_prioritized, all_weights, step_weights,
                            drawn + uniform_steps)

    def _draw_slots(self, count: int) -> np.ndarray:
        """Stratified proportional draw (Schaul et al. 2016): one draw per equal segment of mass."""
        segment = self._mass.total() / count
        targets = (np.arange(count) + self._rng.random(count)) * segment
        return self._mass.find_prefix(targets)

    def _sample_prioritized(self, count: int, beta: float):
        """`count` items ∝ mass and their importance weights (trajectory and none modes)."""
        if count == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float64)
        slots = self._draw_slots(count)
        if self._mode == "none":
            return slots, np.ones(count)
        # (P / P_min)^(-β) = (p / p_min)^(-αβ), with P_min from the lowest priority: fifo
        # retention keeps keys in the rank tree, so the masses say it there.
        if self._fifo:
            return slots, (self._mass.get(slots) / self._min_mass()) ** (-beta)
        ratio = self._rank.get(slots) / self._rank.min()
        return slots, ratio ** (-self._alpha * beta)

    def _min_mass(self) -> float:
        live = np.flatnonzero(self._slot_keys >= 0)
        return float(np.min(self._mass.get(live)))

    def _sample_steps(self, count: int, beta: float):
        """Step mode: `count` items' worth of single transitions (`_draw_steps`), grouped by
        fragment: (distinct slots, [rows, T] Σ of the draws' weights per step, row weights 1,
        number of draws)."""
        if count == 0:
            return np.zeros(0, np.int64), np.zeros((0, 0), np.float32), np.zeros(0), 0
        draws = max(1, round(count * self._prioritized_steps / len(self._slot_of_key)))
        slots, steps, weights = self._draw_steps(draws, beta)
        distinct, rows = np.unique(slots, return_inverse=True)
        matrix = np.zeros((distinct.size, int(self._slot_steps[distinct].max())))
        np.add.at(matrix, (rows, steps), weights)
        return distinct, matrix.astype(np.float32), np.ones(distinct.size), draws

    def _draw_steps(self, count: int, beta: float):
        """`count` single transitions: the tree picks a fragment ∝ Σ_t p_t^α, then a step ∝
        p_t^α in it (O(T) each); returns (slots, steps, importance weights) per draw."""
        slots = self._draw_slots(count)
        step_index = np.empty(count, dtype=np.int64)
        step_mass = np.empty(count, dtype=np.float64)
        within = self._rng.random(count)
        for j, slot in enumerate(slots.tolist()):
            masses = self._step_masses[slot]
            cumulative = np.cumsum(masses)
            step = int(np.searchsorted(cumulative, within[j] * cumulative[-1], side="right"))
            step = min(step, masses.size - 1)  # rounding at the top end
            step_index[j] = step
            step_mass[j] = masses[step]
        return slots, step_index, (step_mass / self._min_step_mass.min()) ** (-beta)

    # ----------------------------------------------------------------------------- update

    def update_priorities(self, keys: Sequence[int] | np.ndarray, priorities: Any) -> int:
        """Set new priorities for keys that are in B_p; return how many (key, priority) pairs
        were applied. Keys evicted or living in B_u are ignored silently (the learner's batch
        may be stale). In "step" mode each priority is an array of that item's num_steps.
        In "none" mode priorities are ignored and 0 is returned. A repeated key: the last wins.

        Every priority is validated before anything changes, so a bad batch changes nothing.
        """
        key_array = np.asarray(keys)
        if key_array.ndim != 1 or (key_array.size and key_array.dtype.kind not in "iu"):
            raise ValueError(f"keys must be a 1-D sequence of integers, got {keys!r}")
        try:
            num_priorities = len(priorities)
        except TypeError:
            raise ValueError(f"priorities must be a sequence, got {priorities!r}") from None
        if num_priorities != key_array.size:
            raise ValueError(
                f"keys and priorities must have the same length, got {key_array.size} keys and "
                f"{num_priorities} priorities"
            )
        if self._mode == "none":
            return 0
        found = [
            (index, self._slot_of_key[key])
            for index, key in enumerate(key_array.tolist())
            if key in self._slot_of_key
        ]
        if self._mode == "trajectory":
            return self._update_trajectory(found, priorities)
        return self._update_steps(found, key_array, priorities)

    def _update_trajectory(self, found: list[tuple[int, int]], priorities: Any) -> int:
        values = np.asarray(priorities, dtype=np.float64)
        bad = ~np.isfinite(values) | (values < 0)
        if values.ndim != 1 or bad.any():
            first = int(np.flatnonzero(bad)[0]) if values.ndim == 1 else 0
            raise ValueError(
                f"priorities must be a 1-D sequence of finite numbers >= 0, got "
                f"priorities[{first}]={float(values.reshape(-1)[first])!r}"
            )
        if not found:
            return 0
        indices, slots = (np.array(column, dtype=np.int64) for column in zip(*found, strict=True))
        clamped = np.maximum(values[indices], self._min_priority)
        masses = clamped**self._alpha
        unusable = ~((masses > 0.0) & (masses < math.inf))
        if unusable.any():
            first = int(indices[np.flatnonzero(unusable)[0]])
            bad_mass = float(masses[unusable][0])
            self._checked_mass(bad_mass, f"priorities[{first}]", float(values[first]))
        self._mass.set_many(slots, masses)
        if not self._fifo:
            self._rank.set_many(slots, clamped)
        return len(found)

    def _update_steps(
        self, found: list[tuple[int, int]], key_array: np.ndarray, priorities: Any
    ) -> int:
        slot_of_index = dict(found)
        leaves: list[_Leaf] = []
        for index, key in enumerate(key_array.tolist()):
            slot = slot_of_index.get(index)
            # A stale key's value is still checked: a malformed batch is a caller bug.
            num_steps = None if slot is None else int(self._slot_steps[slot])
            leaf = self._step_leaf(priorities[index], num_steps, f"priorities[{index}] (key {key})")
            if slot is not None:
                leaves.append(leaf)
        if not found:
            return 0
        slots = np.array([slot for _, slot in found], dtype=np.int64)
        for slot, leaf in zip(slots.tolist(), leaves, strict=True):
            self._step_masses[slot] = leaf.step_masses
        self._mass.set_many(slots, np.array([leaf.mass for leaf in leaves]))
        if not self._fifo:
            self._rank.set_many(slots, np.array([leaf.rank for leaf in leaves]))
        self._min_step_mass.set_many(slots, [leaf.step_masses.min() for leaf in leaves])
        return len(found)

    # ----------------------------------------------------------------------------- introspection

    def __len__(self) -> int:
        return len(self._slot_of_key) + len(self._uniform) - self._uniform_head

    def stats(self) -> dict[str, float | int]:
        """Counters and sizes. The priority summary is over B_p (0.0 when empty or in "none"
        mode, where there are no priorities); it reads every occupied leaf, O(N) in numpy, so
        call it at reporting rate, not per operation."""
        priority_min = priority_max = priority_mean = 0.0
        if self._slot_of_key and self._mode != "none":
            live = np.flatnonzero(self._slot_keys >= 0)
            # fifo retention keeps keys in the rank tree: the priorities are in the masses
            ranks = (self._mass.get(live) ** (1.0 / self._alpha) if self._fifo and self._alpha
                     else self._rank.get(live))
            priority_min = float(ranks.min())
            priority_max = float(ranks.max())
            priority_mean = float(ranks.mean())
        return {
            "prioritized_items": len(self._slot_of_key),
            "prioritized_steps": self._prioritized_steps,
            "uniform_items": len(self._uniform) - self._uniform_head,
            "uniform_steps": self._uniform_steps,
            "inserted": self._inserted,
            "displaced": self._displaced,
            "evicted": self._evicted,
            "sampled": self._sampled,
            "sampled_steps": self._sampled_steps,
            "priority_min": priority_min,
            "priority_max": priority_max,
            "priority_mean": priority_mean,
        }

    # ----------------------------------------------------------------------------- state

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild this buffer exactly — the items, their tree values, the
        counters and the sampler's RNG state — as plain Python and numpy values (the items stay
        as they are: the caller decides how to store them). Arrays are copies and the lists
        are new, so the result stays valid while the buffer goes on changing."""
        live = np.flatnonzero(self._slot_keys >= 0)
        return {
            "config": {"prioritized_capacity": self._capacity,
                       "uniform_capacity_steps": self._uniform_capacity_steps,
                       "priority_mode": self._mode, "alpha": self._alpha,
                       "min_priority": self._min_priority,
                       "retention": "fifo" if self._fifo else "priority"},
            "slots": live.copy(),
            "slot_keys": self._slot_keys[live].copy(),
            "slot_steps": self._slot_steps[live].copy(),
            "slot_mass": np.asarray(self._mass.get(live), dtype=np.float64),
            "slot_rank": np.asarray(self._rank.get(live), dtype=np.float64),
            "step_masses": [self._step_masses[s] for s in live.tolist()],
            "slot_items": [self._items[s] for s in live.tolist()],
            "uniform": [tuple(e) for e in self._uniform[self._uniform_head:]],
            "counters": {"next_key": self._next_key, "inserted": self._inserted,
                         "displaced": self._displaced, "evicted": self._evicted,
                         "sampled": self._sampled, "sampled_steps": self._sampled_steps},
            "rng": self._rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned into this (empty) buffer, built with the same
        capacities and priority mode; a mismatch is refused with both values."""
        if self._next_key:
            raise ValueError("load_state_dict needs an empty buffer")
        config = state["config"]
        for name, mine in (("prioritized_capacity", self._capacity),
                           ("uniform_capacity_steps", self._uniform_capacity_steps),
                           ("priority_mode", self._mode),
                           ("retention", "fifo" if self._fifo else "priority")):
            if config.get(name, "priority") != mine:
                raise ValueError(f"saved buffer has {name}={config[name]!r}, this one {mine!r}")
        slots = np.asarray(state["slots"], dtype=np.int64)
        keys = np.asarray(state["slot_keys"], dtype=np.int64)
        steps = np.asarray(state["slot_steps"], dtype=np.int64)
        _check_saved_slots(state, slots, self._capacity)
        for i, slot in enumerate(slots.tolist()):
            self._items[slot] = state["slot_items"][i]
            self._step_masses[slot] = state["step_masses"][i]
            self._slot_of_key[int(keys[i])] = slot
        self._slot_keys[slots] = keys
        self._slot_steps[slots] = steps
        self._prioritized_steps = int(steps.sum())
        taken = set(slots.tolist())
        self._free_slots = [s for s in range(self._capacity - 1, -1, -1) if s not in taken]
        if len(slots):
            self._mass.set_many(slots, np.asarray(state["slot_mass"], dtype=np.float64))
            self._rank.set_many(slots, np.asarray(state["slot_rank"], dtype=np.float64))
            if self._min_step_mass is not None:
                self._min_step_mass.set_many(
                    slots, np.array([m.min() for m in state["step_masses"]], dtype=np.float64))
        self._uniform = [_UniformEntry(int(k), item, int(n)) for k, item, n in state["uniform"]]
        self._uniform_head = 0
        self._uniform_steps = sum(e.num_steps for e in self._uniform)
        counters = state["counters"]
        self._next_key = int(counters["next_key"])
        self._inserted = int(counters["inserted"])
        self._displaced = int(counters["displaced"])
        self._evicted = int(counters["evicted"])
        self._sampled = int(counters["sampled"])
        self._sampled_steps = int(counters["sampled_steps"])
        self._rng.bit_generator.state = state["rng"]

    def _prioritized_keys(self) -> set[int]:
        """Keys now in B_p (for tests and debugging)."""
        return set(self._slot_of_key)

    def _uniform_keys(self) -> list[int]:
        """Keys now in B_u, oldest first (for tests and debugging)."""
        return [entry.key for entry in self._uniform[self._uniform_head :]]


def _check_saved_slots(state: dict[str, Any], slots: np.ndarray, capacity: int) -> None:
    """A saved B_p must be self-consistent before any of it is used: one entry per slot in
    every per-slot field, distinct slots inside the capacity, positive step counts."""
    n = len(slots)
    if slots.ndim != 1 or len(set(slots.tolist())) != n or (n and not (
            slots.min() >= 0 and slots.max() < capacity)):
        raise ValueError(f"saved slots {slots.tolist()[:8]}… are not distinct slots below the "
                         f"capacity {capacity}")
    for name in ("slot_keys", "slot_steps", "slot_mass", "slot_rank", "step_masses",
                 "slot_items"):
        if len(state[name]) != n:
            raise ValueError(f"saved {name} has {len(state[name])} entries for {n} slots")
    if n and np.asarray(state["slot_steps"]).min() <= 0:
        raise ValueError("saved slot_steps must be > 0")
    for entry in state["uniform"]:
        if len(entry) != 3:
            raise ValueError(f"a saved uniform entry has {len(entry)} fields, not 3")
