"""Removers of the prioritized buffer B_p (DESIGN §2): which item gives way when a newcomer
arrives at a full B_p. The `remover=` of a `DualReplay`, as in Reverb's Table(remover=…).

- `LowestPriorityRemover` (TPDEB): the newcomer enters only if its priority beats B_p's lowest,
  which then moves to B_u; otherwise the newcomer goes to B_u. B_p holds a top-N by priority.
- `OldestRemover` (the PPO + PER baseline, and B_p without priorities): the oldest item gives way,
  whatever its priority; B_p is a FIFO (still sampled by its sampler).

A remover answers `victim(priority, priorities)` in O(log N) or better and is told of every
insert and removal. The lowest-priority remover reads the buffer's `PriorityIndex` (a min tree
of priorities, never of masses or keys); the oldest keeps its own insertion order (a deque of
slots), so a priority update never changes who is oldest.

Pure: the standard library only.
"""

from __future__ import annotations

from collections import deque
from typing import Protocol

import numpy as np

from tpdeb.tpdeb_core.sumtree import PriorityIndex


class Remover(Protocol):
    """What `PrioritizedBuffer` asks of a remover (one instance per buffer)."""

    name: str  # recorded in a saved state, which only a replay of the same remover loads
    needs_priorities: bool  # refused beside a sampler without priorities

    def victim(self, priority: float, priorities: PriorityIndex | None) -> int | None: ...

    def inserted(self, slot: int) -> None: ...

    def removed(self, slot: int) -> None: ...

    def load(self, slots: np.ndarray, keys: np.ndarray) -> None: ...


class LowestPriorityRemover:
    """The item with the lowest priority gives way, and only to a newcomer with a strictly
    higher one (ties keep the incumbent: the leftmost lowest slot, as the min tree finds it)."""

    name = "lowest_priority"
    needs_priorities = True

    def victim(self, priority: float, priorities: PriorityIndex | None) -> int | None:
        """The slot to empty for a newcomer of `priority`, or None: it goes to B_u instead."""
        return priorities.argmin() if priority > priorities.min() else None

    def inserted(self, slot: int) -> None:
        """Nothing to track: the priorities live in the buffer's index."""

    def removed(self, slot: int) -> None:
        """Nothing to track: the priorities live in the buffer's index."""

    def load(self, slots: np.ndarray, keys: np.ndarray) -> None:
        """Nothing to restore: the priorities live in the buffer's index."""


class OldestRemover:
    """The item inserted longest ago gives way, to every newcomer. Insertion order is a deque of
    slots: the oldest is at the left, a newcomer joins at the right, both O(1)."""

    name = "oldest"
    needs_priorities = False

    def __init__(self) -> None:
        self._order: deque[int] = deque()

    def victim(self, priority: float, priorities: PriorityIndex | None) -> int:
        return self._order[0]

    def inserted(self, slot: int) -> None:
        self._order.append(slot)

    def removed(self, slot: int) -> None:
        if slot != self._order[0]:
            raise ValueError(f"OldestRemover: slot {slot} is not the oldest ({self._order[0]})")
        self._order.popleft()

    def load(self, slots: np.ndarray, keys: np.ndarray) -> None:
        """Rebuild the order from the saved keys: keys grow with every insert, so the smallest
        key is the oldest item."""
        self._order = deque(np.asarray(slots)[np.argsort(keys, kind="stable")].tolist())
