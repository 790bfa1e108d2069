"""Segment trees over a fixed number of leaf slots: the index behind `DualReplay`.

Prioritized replay needs a few things in O(log N): the total sampling mass (to normalise), a
prefix-sum search (to draw a slot with probability ∝ its mass), the minimum (the largest
importance weight, and which item to displace) and, for reporting, the maximum and the sum of
the priorities (`PriorityIndex`). A binary tree stored in one numpy float64 array
answers all of them. Layout: the implicit heap — node 1 is the root, node i has children 2i and
2i+1, and leaf `slot` lives at node `size + slot` with `size` a power of two ≥ capacity, so every
leaf sits at the same depth and a batch of leaves can be walked up (or a batch of queries walked
down) one level per numpy call.

Interior nodes are always recomputed from their children, never adjusted by a delta, so float
rounding cannot accumulate over millions of updates. The trees do not validate leaf values: the
caller (the replay) checks priorities once, where the bad value can be named in the error.
"""

from __future__ import annotations

import numpy as np


def _last_writes(slots: np.ndarray, values: np.ndarray | float, capacity: int):
    """(distinct slots, their values) of a batch of writes, the last one winning for a repeated
    slot (numpy's fancy assignment does not promise an order for duplicates); slots checked."""
    slots = np.asarray(slots, dtype=np.int64).reshape(-1)
    values = np.broadcast_to(np.asarray(values, dtype=np.float64), slots.shape)
    if slots.size == 0:
        return slots, values
    if slots.min() < 0 or slots.max() >= capacity:
        bad = slots[(slots < 0) | (slots >= capacity)][0]
        raise IndexError(f"slot {bad} out of range [0, {capacity})")
    if len(set(slots.tolist())) == slots.size:
        return slots, values
    # np.unique on the reversed array keeps the first hit there, i.e. the last one here.
    _, first_in_reversed = np.unique(slots[::-1], return_index=True)
    last = slots.size - 1 - first_in_reversed
    return slots[last], values[last]


class _SegmentTree:
    """A complete binary tree whose interior nodes hold `op` of their children."""

    def __init__(self, capacity: int, op: np.ufunc, neutral: float) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)):
            raise ValueError(f"capacity must be an integer >= 1, got {capacity!r}")
        if capacity < 1:
            raise ValueError(f"capacity must be an integer >= 1, got {capacity!r}")
        self.capacity = int(capacity)
        self._depth = (self.capacity - 1).bit_length()
        self._size = 1 << self._depth
        self._op = op
        self._level_shifts = np.arange(self._depth + 1, dtype=np.int64)
        # Unused leaves hold the neutral element so they never change a query's answer.
        self._nodes = np.full(2 * self._size, neutral, dtype=np.float64)
        # Row i of this view is (node 2i, node 2i+1): both children of node i in one gather.
        self._children = self._nodes.reshape(self._size, 2)

    def set(self, slot: int, value: float) -> None:
        """Set one leaf and recompute its ancestors in a handful of numpy calls.

        Walking up, ancestor k becomes op(ancestor k-1, sibling k-1): that is a running
        `op.accumulate` over the leaf value followed by the siblings along the path, which gives
        the same floats as a level-by-level recomputation (op is commutative) without a Python
        loop over the depth.
        """
        if not 0 <= slot < self.capacity:
            raise IndexError(f"slot {slot} out of range [0, {self.capacity})")
        path = (int(slot) + self._size) >> self._level_shifts  # leaf, parent, ..., root
        running = np.empty(self._depth + 1, dtype=np.float64)
        running[0] = value
        running[1:] = self._nodes[path[:-1] ^ 1]
        self._op.accumulate(running, out=running)
        self._nodes[path] = running

    def set_many(self, slots: np.ndarray, values: np.ndarray | float) -> None:
        """Set a batch of leaves, then recompute their ancestors one level at a time (batched).

        Repeated slots behave like repeated `set` calls: the last value wins.
        """
        slots, values = _last_writes(slots, values, self.capacity)
        if slots.size == 0:
            return
        node = slots + self._size
        self._nodes[node] = values
        for _ in range(self._depth):
            node >>= 1
            self._recompute(node)

    def _recompute(self, node: np.ndarray) -> None:
        """Nodes from their children (siblings share a parent: duplicates write twice alike)."""
        children = self._children[node]
        self._nodes[node] = self._op(children[:, 0], children[:, 1])

    def get(self, slots: np.ndarray | int) -> np.ndarray | float:
        """Leaf values for one slot (a float) or an array of slots."""
        slots = np.asarray(slots, dtype=np.int64)
        if slots.size and (slots.min() < 0 or slots.max() >= self.capacity):
            raise IndexError(f"slots must lie in [0, {self.capacity}), got {slots!r}")
        leaves = self._nodes[self._size + slots]
        return float(leaves) if leaves.ndim == 0 else leaves


class SumTree(_SegmentTree):
    """Sum over non-negative leaves, with prefix-sum search for proportional sampling."""

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity, np.add, 0.0)

    def total(self) -> float:
        return float(self._nodes[1])

    def find_prefix(self, values: np.ndarray) -> np.ndarray:
        """For each prefix sum v, the slot i with cumsum[i-1] <= v < cumsum[i].

        A batch descends together, one numpy step per level (log2 N steps in all). The descent
        only enters subtrees with positive mass, so the answer is always a slot with a positive
        leaf, even when float rounding puts v at or past `total()` (then the last positive slot)
        or v is negative (then the first positive slot). Requires total() > 0.
        """
        if not self._nodes[1] > 0.0:
            raise ValueError(f"find_prefix needs a positive total, the tree sums to {self.total()}")
        # Clipping at 0 keeps `remaining` >= 0 all the way down, so a zero left subtree is
        # always passed on the right.
        remaining = np.maximum(np.asarray(values, dtype=np.float64).reshape(-1), 0.0)
        node = np.ones(remaining.shape, dtype=np.int64)
        for _ in range(self._depth):
            children = self._children[node]
            left_sum = children[:, 0]
            # A zero right subtree (reachable only through rounding) forces left: the descent
            # stays on positive mass.
            go_right = (remaining >= left_sum) & (children[:, 1] > 0.0)
            remaining -= left_sum * go_right
            node += node + go_right
        return node - self._size


class MinTree(_SegmentTree):
    """Minimum over leaves (+inf where unused), with the slot that holds it."""

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity, np.minimum, np.inf)

    def min(self) -> float:
        return float(self._nodes[1])

    def argmin(self) -> int:
        """A slot holding the minimum (the leftmost one on ties), by one root-to-leaf walk."""
        nodes = self._nodes
        node = 1
        while node < self._size:
            left = 2 * node
            node = left if nodes[left] <= nodes[left + 1] else left + 1
        return node - self._size


class MaxTree(_SegmentTree):
    """Maximum over leaves (-inf where unused)."""

    def __init__(self, capacity: int) -> None:
        super().__init__(capacity, np.maximum, -np.inf)

    def max(self) -> float:
        return float(self._nodes[1])


class PriorityIndex:
    """Per-slot priorities with their minimum (and its slot), maximum and sum: what P_min, the
    lowest-priority remover and `stats()` read. It holds priorities only, never sampling masses
    or keys, so whatever reads it gets a priority. Slots never written do not count.

    The minimum is read on every sample and insert, so its tree is kept current (O(log N) per
    write). The maximum and the sum are for reporting: writes only note their slots, and the
    two trees catch up in one batched pass when read (or when the notes reach `FLUSH_SLOTS`),
    which keeps a priority update as cheap as the minimum alone: amortised O(log N) per write,
    O(1) per read when nothing changed.
    """

    FLUSH_SLOTS = 1 << 16

    def __init__(self, capacity: int) -> None:
        self._min = MinTree(capacity)
        self._max = MaxTree(capacity)
        self._sum = SumTree(capacity)
        self._values = np.zeros(self._min.capacity, dtype=np.float64)
        self._stale: list[int] = []  # slots written since the max and sum trees last caught up

    def set(self, slot: int, priority: float) -> None:
        self._min.set(slot, priority)
        self._values[slot] = priority
        self._note([int(slot)])

    def set_many(self, slots: np.ndarray, priorities: np.ndarray) -> None:
        """A batch of writes; a repeated slot keeps its last value."""
        slots, priorities = _last_writes(slots, priorities, self._min.capacity)
        self._min.set_many(slots, priorities)
        self._values[slots] = priorities
        self._note(slots.tolist())

    def _note(self, slots: list[int]) -> None:
        self._stale.extend(slots)
        if len(self._stale) >= self.FLUSH_SLOTS:
            self._catch_up()

    def _catch_up(self) -> None:
        if self._stale:
            slots = np.unique(np.array(self._stale, dtype=np.int64))
            self._max.set_many(slots, self._values[slots])
            self._sum.set_many(slots, self._values[slots])
            self._stale = []

    def get(self, slots: np.ndarray | int) -> np.ndarray | float:
        return self._min.get(slots)

    def min(self) -> float:
        return self._min.min()

    def argmin(self) -> int:
        return self._min.argmin()

    def max(self) -> float:
        self._catch_up()
        return self._max.max()

    def total(self) -> float:
        self._catch_up()
        return self._sum.total()
