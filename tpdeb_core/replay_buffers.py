"""The two buffers of the dual replay (DESIGN §2), each a piece of its own.

- `PrioritizedBuffer` (B_p): at most N_p items in fixed slots, drawn by a sampler
  (`replay_samplers`), giving way by a remover (`replay_removers`). It owns the slots (items,
  keys, step counts, key → slot so that updates for evicted keys are ignored) and a
  `PriorityIndex` of each item's clamped priority (min with its slot, max, sum): what P_min, the
  lowest-priority remover and the stats read. Each structure serves one purpose: the sampler's
  sum tree holds sampling masses, the index priorities, the oldest remover insertion order.
- `UniformFifo` (B_u): the most recent items not in B_p, bounded in steps, drawn uniformly.

Every operation is O(log N) (B_u's, amortised O(1)). Pure: numpy and the standard library only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from tpdeb.tpdeb_core.replay_removers import Remover
from tpdeb.tpdeb_core.replay_samplers import Draw, Leaf, Sampler, check_int
from tpdeb.tpdeb_core.sumtree import PriorityIndex


class Entry(NamedTuple):
    """An item with its key and length, as it moves between the buffers."""

    key: int
    item: Any
    num_steps: int


class UniformFifo:
    """B_u: items oldest first, at most `capacity_steps` steps in all, drawn uniformly.

    A list read from `_head` (the oldest live entry): O(1) random access and O(1) amortised
    eviction; the dead prefix is dropped once it is the larger half.
    """

    def __init__(self, capacity_steps: int) -> None:
        self.capacity_steps = check_int("uniform_capacity_steps", capacity_steps, 1)
        self._entries: list[Entry | None] = []
        self._head = 0
        self.steps = 0

    def __len__(self) -> int:
        return len(self._entries) - self._head

    def append(self, entry: Entry) -> None:
        self._entries.append(entry)
        self.steps += entry.num_steps

    def evict(self) -> int:
        """Drop the oldest items until the rest fit in the step budget; return how many."""
        evicted = 0
        while self.steps > self.capacity_steps:
            oldest = self._entries[self._head]
            self._entries[self._head] = None  # release the item now, not at compaction
            self._head += 1
            self.steps -= oldest.num_steps
            evicted += 1
        if self._head * 2 > len(self._entries):
            del self._entries[: self._head]
            self._head = 0
        return evicted

    def sample(self, count: int, rng: np.random.Generator) -> list[Entry]:
        """`count` entries, uniformly with replacement."""
        positions = rng.integers(self._head, len(self._entries), size=count)
        return [self._entries[i] for i in positions.tolist()]

    def entries(self) -> list[Entry]:
        """The live entries, oldest first (a new list)."""
        return self._entries[self._head :]

    def load(self, entries: Sequence[Sequence[Any]]) -> None:
        self._entries = [Entry(int(key), item, int(steps)) for key, item, steps in entries]
        self._head = 0
        self.steps = sum(entry.num_steps for entry in self._entries)


class PrioritizedBuffer:
    """B_p: `sampler.capacity` slots, filled from slot 0 up, then renewed only through the
    remover (an item leaves B_p only to make room for a newcomer, which takes its slot)."""

    def __init__(self, sampler: Sampler, remover: Remover) -> None:
        if remover.needs_priorities and not sampler.has_priorities:
            raise ValueError(
                f"remover {type(remover).__name__} ranks items by priority, but sampler "
                f"{type(sampler).__name__} has none: use OldestRemover"
            )
        self.sampler, self.remover = sampler, remover
        self.capacity = n = sampler.capacity
        self.priorities = PriorityIndex(n) if sampler.has_priorities else None
        self._items: list[Any] = [None] * n
        self.slot_keys = np.full(n, -1, dtype=np.int64)  # -1: a free slot
        self._slot_steps = np.zeros(n, dtype=np.int64)
        self._slot_of_key: dict[int, int] = {}
        self._free = list(range(n - 1, -1, -1))  # pop() hands out slot 0 first
        self.steps = 0

    def __len__(self) -> int:
        return len(self._slot_of_key)

    def keys(self) -> set[int]:
        return set(self._slot_of_key)

    def offer(self, entry: Entry, leaf: Leaf) -> Entry | None:
        """Store `entry` if B_p has room or the remover makes room for it. Returns what goes to
        B_u instead: the item that gave way, the newcomer itself if refused, or None."""
        if self._free:
            self._store(self._free.pop(), entry, leaf)
            return None
        slot = self.remover.victim(leaf.priority, self.priorities)
        if slot is None:
            return entry
        leaving = self._take(slot)
        self._store(slot, entry, leaf)
        return leaving

    def _take(self, slot: int) -> Entry:
        key, steps = int(self.slot_keys[slot]), int(self._slot_steps[slot])
        leaving = Entry(key, self._items[slot], steps)
        del self._slot_of_key[key]
        self.steps -= steps
        self.remover.removed(slot)
        return leaving

    def _store(self, slot: int, entry: Entry, leaf: Leaf) -> None:
        self._items[slot] = entry.item
        self.slot_keys[slot] = entry.key
        self._slot_steps[slot] = entry.num_steps
        self._slot_of_key[entry.key] = slot
        self.steps += entry.num_steps
        self.sampler.set(slot, leaf)
        if self.priorities is not None:
            self.priorities.set(slot, leaf.priority)
        self.remover.inserted(slot)

    def sample(self, count: int, beta: float, rng: np.random.Generator) -> Draw:
        """`count` items' worth of draws from the sampler, with the steps they stand for."""
        draw = self.sampler.sample(count, beta, rng, self.priorities)
        if draw.steps_drawn is None:
            draw = draw._replace(steps_drawn=int(self._slot_steps[draw.slots].sum()))
        return draw

    def items(self, slots: np.ndarray) -> list[Any]:
        return [self._items[slot] for slot in slots.tolist()]

    def update(self, keys: list[int], priorities: Any) -> int:
        """New priorities for the keys in B_p (the others are ignored); every priority is
        validated by the sampler before anything changes. Returns how many were applied."""
        slots = [self._slot_of_key.get(key) for key in keys]
        num_steps = [None if slot is None else int(self._slot_steps[slot]) for slot in slots]
        leaves = self.sampler.update_leaves(keys, priorities, num_steps)
        found = np.array([slot for slot in slots if slot is not None], dtype=np.int64)
        if found.size:
            self.sampler.set_many(found, leaves)
            self.priorities.set_many(found, leaves.priority)
        return int(found.size)

    def priority_summary(self) -> tuple[float, float, float]:
        """(min, max, mean) of the items' priorities, O(1); zeros when empty or unprioritized."""
        if not self._slot_of_key or self.priorities is None:
            return 0.0, 0.0, 0.0
        return (self.priorities.min(), self.priorities.max(),
                self.priorities.total() / len(self._slot_of_key))

    def state(self) -> dict[str, Any]:
        """The occupied slots and what each holds, as copies."""
        live = np.flatnonzero(self.slot_keys >= 0)
        priority = (np.zeros(live.size) if self.priorities is None
                    else np.asarray(self.priorities.get(live), dtype=np.float64))
        return {"slots": live, "slot_keys": self.slot_keys[live], "slot_steps":
                self._slot_steps[live], "slot_priority": priority,
                "step_masses": [None] * live.size, **self.sampler.state(live),
                "slot_items": [self._items[slot] for slot in live.tolist()]}

    def load(self, state: dict[str, Any]) -> None:
        """Fill this empty buffer from `state` (checked by the caller)."""
        slots = np.asarray(state["slots"], dtype=np.int64)
        keys = np.asarray(state["slot_keys"], dtype=np.int64)
        steps = np.asarray(state["slot_steps"], dtype=np.int64)
        for i, slot in enumerate(slots.tolist()):
            self._items[slot] = state["slot_items"][i]
            self._slot_of_key[int(keys[i])] = slot
        self.slot_keys[slots] = keys
        self._slot_steps[slots] = steps
        self.steps = int(steps.sum())
        taken = set(slots.tolist())
        self._free = [slot for slot in range(self.capacity - 1, -1, -1) if slot not in taken]
        if slots.size:
            self.sampler.load(slots, state)
            if self.priorities is not None:
                self.priorities.set_many(
                    slots, np.asarray(state["slot_priority"], dtype=np.float64))
        self.remover.load(slots, keys)
