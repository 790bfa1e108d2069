"""Samplers of the prioritized buffer B_p (DESIGN §2): which B_p items a batch draws, with what
importance weights. The `sampler=` of a `DualReplay`, as in Reverb's Table(sampler=…).

- `TrajectorySampler` (TPDEB): one priority p per item, P(i) ∝ p_i^α, w_i = (P(i) / P_min)^(−β);
- `StepSampler` (PPO + PER): one priority per step, Schaul et al.'s PER over single transitions:
  a fragment ∝ Σ_t p_t^α, then a step in it ∝ p_t^α; per-step weights;
- `UniformSampler`: no priorities at all, every item equally likely, weights 1.

A sampler keeps per B_p slot only what its draws need (sampling masses in a sum tree; the step
sampler also each step's mass and a min tree of them, for its P_min) and turns a caller's
priority into those values (`leaf`, `update_leaves`): priorities are validated here, once, where
the bad value can be named, and clamped to ≥ min_priority so that p^α > 0 and every item can be
drawn. A sampler never sees items or keys: the buffer (`replay_buffers.PrioritizedBuffer`) owns
the slots and a `PriorityIndex` of each item's priority (what P_min, the lowest-priority remover
and the stats read), and hands the index to `sample`.

(P / P_min)^(−β) is (N·P)^(−β) / max_j (N·P_j)^(−β): N and the total mass cancel, and P_min is a
tree's minimum, so weights cost O(log N) per draw, never an O(N) pass.

Pure: numpy and the standard library only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple, Protocol

import numpy as np

from tpdeb.tpdeb_core.sumtree import MinTree, PriorityIndex, SumTree


def is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_int(name: str, value: Any, minimum: int) -> int:
    if not is_int(value) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_real(name: str, value: Any, low: float, high: float = math.inf) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not (math.isfinite(number) and low <= number <= high):
        bounds = f">= {low}" if high == math.inf else f"in [{low}, {high}]"
        raise ValueError(f"{name} must be finite and {bounds}, got {value!r}")
    return number


def check_priority_settings(alpha: Any, min_priority: Any) -> tuple[float, float]:
    """The priority exponent and floor, validated: p^α > 0 needs a positive floor."""
    alpha = check_real("alpha", alpha, 0.0)
    floor = check_real("min_priority", min_priority, 0.0)
    if floor == 0.0:
        raise ValueError(
            f"min_priority must be > 0 so that priority^alpha > 0, got {min_priority!r}"
        )
    return alpha, floor


class Leaf(NamedTuple):
    """What one B_p slot holds, from a validated and clamped priority."""

    priority: float  # the clamped priority (Σ_t p_t for the step sampler); 0.0 without priorities
    mass: float  # sampling mass: p^α, Σ_t p_t^α, or 1
    step_masses: np.ndarray | None = None  # p_t^α per step (step sampler only)


class Leaves(NamedTuple):
    """`Leaf` values for a batch of slots (a priority update), as aligned arrays."""

    priority: np.ndarray
    mass: np.ndarray
    step_masses: list[np.ndarray] | None = None


class Draw(NamedTuple):
    """B_p's rows of a batch."""

    slots: np.ndarray  # int64[R]
    weights: np.ndarray  # float64[R]: importance weights (1 for step rows: see step_weights)
    step_weights: np.ndarray | None = None  # float32[R, T], step sampler: Σ of its draws' weights
    steps_drawn: int | None = None  # transitions drawn; None: every step of every row


class Sampler(Protocol):
    """What `PrioritizedBuffer` asks of a sampler (one instance per buffer: it indexes slots).
    With `has_priorities` it also takes updates (`update_leaves` then `set_many`) and says its
    `total_mass()` and `min_mass(priorities)` (a shard's view, `shards.ShardView`)."""

    name: str  # recorded in a saved state, which only a replay of the same sampler loads
    capacity: int  # B_p's slots
    has_priorities: bool

    def leaf(self, priority: Any, num_steps: int, name: str = "priority") -> Leaf: ...

    def set(self, slot: int, leaf: Leaf) -> None: ...

    def sample(self, count: int, beta: float, rng: np.random.Generator,
               priorities: PriorityIndex | None) -> Draw: ...

    def state(self, slots: np.ndarray) -> dict[str, Any]: ...

    def load(self, slots: np.ndarray, state: dict[str, Any]) -> None: ...


def _empty_draw(per_step: bool) -> Draw:
    slots, weights = np.zeros(0, np.int64), np.zeros(0, np.float64)
    if per_step:
        return Draw(slots, weights, np.zeros((0, 0), np.float32), 0)
    return Draw(slots, weights)


class _ProportionalSampler:
    """Draws slots ∝ a per-slot mass kept in a sum tree, stratified over the batch."""

    has_priorities = True

    def __init__(self, capacity: int, alpha: float = 1.0, min_priority: float = 1e-6) -> None:
        self.capacity = check_int("prioritized_capacity", capacity, 1)
        self.alpha, self.min_priority = check_priority_settings(alpha, min_priority)
        self._mass = SumTree(self.capacity)

    def _stratified(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Stratified proportional draw (Schaul et al. 2016): one draw per equal segment of mass."""
        segment = self._mass.total() / count
        return self._mass.find_prefix((np.arange(count) + rng.random(count)) * segment)

    def total_mass(self) -> float:
        """Σ of the slots' sampling masses (what a batch's B_p rows are drawn in proportion to)."""
        return self._mass.total()

    def _checked_mass(self, mass: float, name: str, priority: Any) -> float:
        if not 0.0 < mass < math.inf:
            raise ValueError(
                f"{name}={priority!r} with alpha={self.alpha} gives a sampling mass of {mass}; "
                f"lower alpha, or rescale priorities / raise min_priority={self.min_priority}"
            )
        return mass

    def state(self, slots: np.ndarray) -> dict[str, Any]:
        """Per-slot values for a snapshot (the masses as computed, so a restore is bit-exact)."""
        return {"slot_mass": np.asarray(self._mass.get(slots), dtype=np.float64)}


class TrajectorySampler(_ProportionalSampler):
    """One priority per item (TPDEB): P(i) ∝ p_i^α, w_i = (p_i / p_min)^(−αβ) = (P(i)/P_min)^(−β)
    with p_min read from the buffer's `PriorityIndex` (x ↦ x^α is monotone)."""

    name = "trajectory"

    def leaf(self, priority: Any, num_steps: int, name: str = "priority") -> Leaf:
        clamped = max(check_real(name, priority, 0.0), self.min_priority)
        try:
            power = clamped**self.alpha
        except OverflowError:  # Python floats raise where numpy would give inf
            power = math.inf
        return Leaf(clamped, self._checked_mass(power, name, priority))

    def update_leaves(
        self, keys: Sequence[int], priorities: Any, num_steps: Sequence[int | None]
    ) -> Leaves:
        """Validate every priority (also those of keys no longer in B_p: a malformed batch is a
        caller bug), then the leaves of the keys in B_p (`num_steps` not None), in order."""
        values = np.asarray(priorities, dtype=np.float64)
        bad = ~np.isfinite(values) | (values < 0)
        if values.ndim != 1 or bad.any():
            first = int(np.flatnonzero(bad)[0]) if values.ndim == 1 else 0
            raise ValueError(
                f"priorities must be a 1-D sequence of finite numbers >= 0, got "
                f"priorities[{first}]={float(values.reshape(-1)[first])!r}"
            )
        known = np.array([i for i, n in enumerate(num_steps) if n is not None], dtype=np.int64)
        clamped = np.maximum(values[known], self.min_priority)
        with np.errstate(over="ignore"):  # an overflow is refused just below, by name
            masses = clamped**self.alpha
        unusable = ~((masses > 0.0) & (masses < math.inf))
        if unusable.any():
            first = int(known[np.flatnonzero(unusable)[0]])
            self._checked_mass(float(masses[unusable][0]), f"priorities[{first}]",
                               float(values[first]))
        return Leaves(clamped, masses)

    def set(self, slot: int, leaf: Leaf) -> None:
        self._mass.set(slot, leaf.mass)

    def set_many(self, slots: np.ndarray, leaves: Leaves) -> None:
        self._mass.set_many(slots, leaves.mass)

    def sample(self, count: int, beta: float, rng: np.random.Generator,
               priorities: PriorityIndex) -> Draw:
        if count == 0:
            return _empty_draw(per_step=False)
        slots = self._stratified(count, rng)
        ratio = priorities.get(slots) / priorities.min()
        return Draw(slots, ratio ** (-self.alpha * beta))

    def min_mass(self, priorities: PriorityIndex) -> float:
        """P_min's mass, p_min^α: the weights' reference (B_p not empty)."""
        return priorities.min() ** self.alpha

    def load(self, slots: np.ndarray, state: dict[str, Any]) -> None:
        self._mass.set_many(slots, np.asarray(state["slot_mass"], dtype=np.float64))


class StepSampler(_ProportionalSampler):
    """One priority per step (PER over single transitions, the PPO + PER baseline).

    A batch's B_p share is round(ζB) items' worth of transitions (T draws per item on average),
    returned as the distinct fragments drawn with a per-step weight matrix (Σ of the importance
    weights of the draws that hit each step), so the learner trains on as many transitions as
    with trajectory priorities. The sampling unit is the step: P = p_t^α / Σ, and P_min is the
    smallest step mass in B_p, kept in a min tree of each fragment's smallest step mass. An
    item's priority (for the remover and the stats) is Σ_t p_t.
    """

    name = "step"

    def __init__(self, capacity: int, alpha: float = 1.0, min_priority: float = 1e-6) -> None:
        super().__init__(capacity, alpha, min_priority)
        self._step_masses: list[np.ndarray | None] = [None] * self.capacity
        self._sizes = np.zeros(self.capacity, dtype=np.int64)  # steps of each slot's item
        self._min_step_mass = MinTree(self.capacity)
        self._items = 0
        self._steps = 0

    def leaf(self, priority: Any, num_steps: int | None, name: str = "priority") -> Leaf:
        """Validate per-step priorities (`num_steps` long when known)."""
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
        clamped = np.maximum(steps, self.min_priority)
        step_masses = clamped**self.alpha
        self._checked_mass(float(step_masses.min()), name, priority)
        mass = self._checked_mass(float(step_masses.sum()), name, priority)
        return Leaf(float(clamped.sum()), mass, step_masses)

    def update_leaves(
        self, keys: Sequence[int], priorities: Any, num_steps: Sequence[int | None]
    ) -> Leaves:
        """Validate every item's array (a stale key's of any length), then the leaves of the keys
        in B_p (`num_steps` not None), in order."""
        leaves = []
        for index, (key, steps) in enumerate(zip(keys, num_steps, strict=True)):
            leaf = self.leaf(priorities[index], steps, f"priorities[{index}] (key {key})")
            if steps is not None:
                leaves.append(leaf)
        return Leaves(np.array([leaf.priority for leaf in leaves], dtype=np.float64),
                      np.array([leaf.mass for leaf in leaves], dtype=np.float64),
                      [leaf.step_masses for leaf in leaves])

    def set(self, slot: int, leaf: Leaf) -> None:
        old = self._step_masses[slot]
        self._items += old is None
        self._steps += leaf.step_masses.size - (0 if old is None else old.size)
        self._step_masses[slot] = leaf.step_masses
        self._sizes[slot] = leaf.step_masses.size
        self._mass.set(slot, leaf.mass)
        self._min_step_mass.set(slot, float(leaf.step_masses.min()))

    def set_many(self, slots: np.ndarray, leaves: Leaves) -> None:
        """Update slots in place (the same number of steps each: `update_leaves` checked it)."""
        for slot, step_masses in zip(slots.tolist(), leaves.step_masses, strict=True):
            self._step_masses[slot] = step_masses
        self._mass.set_many(slots, leaves.mass)
        self._min_step_mass.set_many(slots, [m.min() for m in leaves.step_masses])

    def sample(self, count: int, beta: float, rng: np.random.Generator,
               priorities: PriorityIndex | None = None) -> Draw:
        """`count` items' worth of single transitions (`draw_steps`), grouped by fragment."""
        if count == 0:
            return _empty_draw(per_step=True)
        draws = max(1, round(count * self._steps / self._items))
        slots, steps, weights = self.draw_steps(draws, beta, rng)
        distinct, rows = np.unique(slots, return_inverse=True)
        matrix = np.zeros((distinct.size, int(self._sizes[distinct].max())))
        np.add.at(matrix, (rows, steps), weights)
        return Draw(distinct, np.ones(distinct.size), matrix.astype(np.float32), draws)

    def draw_steps(self, count: int, beta: float, rng: np.random.Generator):
        """`count` single transitions: the tree picks a fragment ∝ Σ_t p_t^α, then a step ∝
        p_t^α in it (O(T) each, for all draws at once: the drawn fragments' step masses side by
        side, zero-padded, and one cumulative sum); returns (slots, steps, importance weights)
        per draw."""
        slots = self._stratified(count, rng)
        within = rng.random(count)
        distinct, rows = np.unique(slots, return_inverse=True)
        sizes = self._sizes[distinct]
        arrays = [self._step_masses[slot] for slot in distinct.tolist()]
        if (sizes == sizes[0]).all():  # the usual case: every fragment T steps long
            masses = np.concatenate(arrays).reshape(distinct.size, -1)  # np.stack: 10× the cost
        else:
            masses = np.zeros((distinct.size, int(sizes.max())))
            for row, array in enumerate(arrays):
                masses[row, :array.size] = array
        cumulative = np.cumsum(masses, axis=1)[rows]  # [count, width]; padding adds nothing
        targets = within * cumulative[:, -1]
        # the first step whose cumulative mass passes the target (searchsorted, side "right")
        steps = np.minimum((cumulative <= targets[:, None]).sum(axis=1), sizes[rows] - 1)
        step_mass = masses[rows, steps]
        return slots, steps.astype(np.int64), (step_mass / self._min_step_mass.min()) ** (-beta)

    def min_mass(self, priorities: PriorityIndex | None = None) -> float:
        """P_min's mass: the smallest step mass in B_p (not empty)."""
        return self._min_step_mass.min()

    def state(self, slots: np.ndarray) -> dict[str, Any]:
        return {**super().state(slots),
                "step_masses": [self._step_masses[s] for s in slots.tolist()]}

    def load(self, slots: np.ndarray, state: dict[str, Any]) -> None:
        for slot, masses in zip(slots.tolist(), state["step_masses"], strict=True):
            masses = np.asarray(masses, dtype=np.float64)
            if masses.ndim != 1 or masses.size == 0:
                raise ValueError(f"saved step_masses of slot {slot} has shape {masses.shape}")
            self.set(slot, Leaf(0.0, 0.0, masses))  # counts the steps; the mass comes next
        self._mass.set_many(slots, np.asarray(state["slot_mass"], dtype=np.float64))


class UniformSampler:
    """No priorities (priorities passed in are ignored): every B_p item equally likely, weights
    exactly 1. Its B_p can only give way by age (`OldestRemover`): there is no priority to rank.

    B_p never frees a slot (an item leaves only for a newcomer that takes its slot), so the
    occupied slots are a list that only grows, and a draw is an index into it: O(1).
    """

    name = "uniform"
    has_priorities = False

    def __init__(self, capacity: int) -> None:
        self.capacity = check_int("prioritized_capacity", capacity, 1)
        self._slots = np.zeros(self.capacity, dtype=np.int64)
        self._occupied = np.zeros(self.capacity, dtype=bool)
        self._count = 0

    def leaf(self, priority: Any, num_steps: int | None, name: str = "priority") -> Leaf:
        return Leaf(0.0, 1.0)

    def set(self, slot: int, leaf: Leaf) -> None:
        if not self._occupied[slot]:
            self._occupied[slot] = True
            self._slots[self._count] = slot
            self._count += 1

    def sample(self, count: int, beta: float, rng: np.random.Generator,
               priorities: PriorityIndex | None = None) -> Draw:
        """Stratified like the proportional samplers: one draw per equal share of the items."""
        if count == 0:
            return _empty_draw(per_step=False)
        positions = ((np.arange(count) + rng.random(count)) * (self._count / count)).astype(
            np.int64)
        slots = self._slots[np.minimum(positions, self._count - 1)]
        return Draw(slots, np.ones(count))

    def state(self, slots: np.ndarray) -> dict[str, Any]:
        return {"slot_mass": np.ones(len(slots))}

    def load(self, slots: np.ndarray, state: dict[str, Any]) -> None:
        for slot in slots.tolist():
            self.set(slot, Leaf(0.0, 1.0))
