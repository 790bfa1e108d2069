"""Dual replay (DESIGN §2): a prioritized buffer B_p beside a FIFO uniform buffer B_u.

A replay is a composition, as Reverb's Table(sampler=…, remover=…, rate_limiter=…):
- the sampler (`replay_samplers`) draws B_p's share of a batch and weighs it: trajectory
  priorities (TPDEB), step priorities (PER over single transitions) or uniform (no priorities);
- the remover (`replay_removers`) says which B_p item gives way when B_p is full: the lowest
  priority, and only to a higher one (TPDEB), or the oldest (a FIFO);
- B_p (`PrioritizedBuffer`) and B_u (`UniformFifo`, bounded in steps) are pieces of their own
  (`replay_buffers`); an item leaving B_p moves to B_u, and B_u evicts its oldest;
- the rate limiter (`rate_limiter.RateLimiter`) stays outside: it gates the caller, in steps, not
  the buffers. The replay server asks `can_insert(T)` / `can_sample(B·T)` before calling `insert`
  / `sample` and reports the steps moved (`num_steps`, `ReplaySample.steps_drawn`) to
  `on_insert` / `on_sample`, as Reverb's Table consults its limiter around each operation.

A batch of B draws round(ζB) items from B_p and the rest uniformly from B_u (when one buffer is
empty the other fills the batch). ζ = 0 is a plain replay: B_p is bypassed and every item goes to
B_u (else B_p would hold items no batch can reach).

The three algorithms are compositions (`COMPOSITIONS`): `tpdeb` (trajectory sampler, lowest-
priority remover, ζ from the settings), `impact` (ζ = 0: B_u only) and `ppo_per` (step sampler,
oldest remover, ζ = 1). The constructor keeps its string settings (priority_mode × retention)
and picks the strategies from them; `DualReplay.compose` takes strategy objects.

Pure: numpy and the standard library only — no I/O, no clocks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpdeb.tpdeb_core.replay_buffers import Entry, PrioritizedBuffer, UniformFifo
from tpdeb.tpdeb_core.replay_removers import LowestPriorityRemover, OldestRemover, Remover
from tpdeb.tpdeb_core.replay_samplers import (
    Draw,
    Sampler,
    StepSampler,
    TrajectorySampler,
    UniformSampler,
    check_int,
    check_priority_settings,
    check_real,
    is_int,
)
from tpdeb.tpdeb_core.replay_state import (
    PRIORITY_MODES,
    RETENTIONS,
    STATE_FORMAT,
    check_saved_slots,
    strategy_names,
    upgraded,
)
from tpdeb.tpdeb_core.shards import ShardView

# One import for a composition: the replay, its strategies and the algorithms' compositions.
__all__ = ["COMPOSITIONS", "PRIORITY_MODES", "RETENTIONS", "DualReplay", "LowestPriorityRemover",
           "OldestRemover", "ReplaySample", "StepSampler", "TrajectorySampler", "UniformSampler",
           "impact", "ppo_per", "tpdeb"]


@dataclass(frozen=True)
class ReplaySample:
    """One batch. Prioritized items come first, then uniform ones; arrays are aligned with items."""

    items: list[Any]
    keys: np.ndarray  # int64[B]
    from_prioritized: np.ndarray  # bool[B]
    weights: np.ndarray  # float32[B]: importance weights, exactly 1.0 for uniform items
    # step sampler: float32[B, T] per-step loss weights (Σ of the importance weights of the
    # draws at each step; all 1.0 on uniform rows); None with the other samplers
    step_weights: np.ndarray | None = None
    steps_drawn: int = 0  # transitions it stands for: 1 per step draw, all steps of the rest


class DualReplay:
    """Prioritized buffer B_p (items) + uniform FIFO B_u (steps) storing opaque items.

    Args:
        prioritized_capacity: most items B_p holds (N_p).
        uniform_capacity_steps: most steps B_u holds (N_u); the oldest items are evicted past it.
        zeta: share of each batch drawn from B_p, round(zeta * batch_size).
        alpha: priority exponent; B_p samples ∝ priority^alpha (0 = uniform within B_p).
        seed: seeds the PCG64 generator used for all sampling.
        priority_mode: the sampler: "trajectory" (one priority per item), "step" (one per step:
            PER over single transitions) or "none" (uniform; B_p then keeps the newest items).
        min_priority: floor applied to stored priorities so that priority^alpha > 0.
        retention: the remover: "priority" (the lowest gives way, to a higher one; TPDEB) or
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
        capacity = check_int("prioritized_capacity", prioritized_capacity, 1)
        check_int("uniform_capacity_steps", uniform_capacity_steps, 1)
        check_real("zeta", zeta, 0.0, 1.0)
        check_priority_settings(alpha, min_priority)
        if priority_mode not in PRIORITY_MODES:
            raise ValueError(
                f"priority_mode must be one of {PRIORITY_MODES}, got {priority_mode!r}"
            )
        if retention not in RETENTIONS:
            raise ValueError(f"retention must be one of {RETENTIONS}, got {retention!r}")
        sampler_name, remover_name = strategy_names(priority_mode, retention)
        if sampler_name == "uniform":
            sampler: Sampler = UniformSampler(capacity)
        else:
            kind = TrajectorySampler if sampler_name == "trajectory" else StepSampler
            sampler = kind(capacity, alpha, min_priority)
        remover = OldestRemover() if remover_name == "oldest" else LowestPriorityRemover()
        self._assemble(sampler, remover, uniform_capacity_steps, zeta, seed)

    @classmethod
    def compose(cls, sampler: Sampler, remover: Remover, uniform_capacity_steps: int,
                zeta: float = 0.2, seed: int | None = None) -> DualReplay:
        """A replay made of strategy objects: B_p holds `sampler.capacity` items, drawn by
        `sampler`, giving way by `remover` (see the module docstring). The strategies index
        B_p's slots: give each replay its own."""
        replay = cls.__new__(cls)
        replay._assemble(sampler, remover, uniform_capacity_steps, zeta, seed)
        return replay

    def _assemble(self, sampler: Sampler, remover: Remover, uniform_capacity_steps: int,
                  zeta: float, seed: int | None) -> None:
        self._zeta = check_real("zeta", zeta, 0.0, 1.0)
        if seed is not None and not is_int(seed):
            raise ValueError(f"seed must be an integer or None, got {seed!r}")
        self._rng = np.random.Generator(np.random.PCG64(seed))
        self._prioritized = PrioritizedBuffer(sampler, remover)
        self._uniform = UniformFifo(uniform_capacity_steps)
        self._next_key = 0
        self._inserted = 0
        self._displaced = 0
        self._evicted = 0
        self._sampled = 0
        self._sampled_steps = 0

    @property
    def sampler(self) -> Sampler:
        return self._prioritized.sampler

    @property
    def remover(self) -> Remover:
        return self._prioritized.remover

    @property
    def zeta(self) -> float:
        return self._zeta

    # ----------------------------------------------------------------------------- insert

    def insert(self, item: Any, priority: float | np.ndarray, num_steps: int) -> int:
        """Store `item` (`num_steps` long) and return its key (0, 1, 2, ...).

        `priority` is a float for the trajectory sampler, an array of `num_steps` per-step
        priorities for the step sampler, and ignored by the uniform one. It is validated even
        when ζ = 0. The item enters B_p if B_p has room or the remover makes room (the item that
        gives way moves to B_u); otherwise it goes to B_u. B_u then evicts its oldest items
        until it fits in its step budget.
        """
        capacity_steps = self._uniform.capacity_steps
        if not is_int(num_steps) or not 1 <= num_steps <= capacity_steps:
            raise ValueError(
                f"num_steps must be an integer in [1, uniform_capacity_steps="
                f"{capacity_steps}], got {num_steps!r}"
            )
        key = self._next_key
        leaf = self.sampler.leaf(priority, int(num_steps))
        self._next_key += 1
        self._inserted += 1
        entry = Entry(key, item, int(num_steps))
        to_uniform = entry if self._zeta == 0.0 else self._prioritized.offer(entry, leaf)
        if to_uniform is not None:
            self._displaced += int(to_uniform.key != key)
            self._uniform.append(to_uniform)
        self._evicted += self._uniform.evict()
        return key

    # ----------------------------------------------------------------------------- sample

    def sample(self, batch_size: int, beta: float = 1.0,
               num_prioritized: int | None = None) -> ReplaySample:
        """Draw `batch_size` items with replacement: round(ζB) from B_p, the rest from B_u.

        When one buffer is empty the other fills the whole batch. B_p's items carry the
        sampler's importance weights (P / P_min)^(-β); B_u's weigh 1. `num_prioritized`: B_p's
        rows as the caller splits the batch (a shard's share, `shards.split_batch`) in place of
        round(ζB), with the same fallback when one buffer is empty.
        """
        batch_size = check_int("batch_size", batch_size, 1)
        beta = check_real("beta", beta, 0.0, 1.0)
        if num_prioritized is not None:
            num_prioritized = check_int("num_prioritized", num_prioritized, 0)
            if num_prioritized > batch_size:
                raise ValueError(f"num_prioritized={num_prioritized} is more than the batch "
                                 f"({batch_size})")
        if not self._prioritized and not self._uniform:
            raise ValueError(
                "cannot sample from an empty DualReplay (both buffers hold 0 items): insert "
                "first, or gate sampling on a RateLimiter's min_size_to_sample"
            )
        if not self._uniform:
            num_prioritized = batch_size
        elif not self._prioritized:
            num_prioritized = 0
        elif num_prioritized is None:
            num_prioritized = round(self._zeta * batch_size)
        draw = self._prioritized.sample(num_prioritized, beta, self._rng)
        uniform_entries = self._uniform.sample(batch_size - num_prioritized, self._rng)
        batch = self._batch(draw, uniform_entries)
        self._sampled += batch_size
        self._sampled_steps += batch.steps_drawn
        return batch

    def _batch(self, draw: Draw, uniform_entries: list[Entry]) -> ReplaySample:
        """B_p's rows, then B_u's, as one `ReplaySample`."""
        slots = draw.slots
        items = self._prioritized.items(slots) + [entry.item for entry in uniform_entries]
        keys = np.concatenate([self._prioritized.slot_keys[slots],
                               np.array([entry.key for entry in uniform_entries], np.int64)])
        rows = len(items)
        from_prioritized = np.arange(rows) < slots.size
        weights = np.ones(rows, dtype=np.float32)
        weights[:slots.size] = draw.weights
        uniform_steps = sum(entry.num_steps for entry in uniform_entries)
        step_weights = draw.step_weights
        if step_weights is not None:
            width = max([step_weights.shape[1], *(e.num_steps for e in uniform_entries)])
            matrix = np.zeros((rows, width), dtype=np.float32)
            matrix[:slots.size, :step_weights.shape[1]] = step_weights
            for row, entry in enumerate(uniform_entries, start=slots.size):
                matrix[row, :entry.num_steps] = 1.0
            step_weights = matrix
        return ReplaySample(items, keys, from_prioritized, weights, step_weights,
                            draw.steps_drawn + uniform_steps)

    # ----------------------------------------------------------------------------- update

    def update_priorities(self, keys: Sequence[int] | np.ndarray, priorities: Any) -> int:
        """Set new priorities for keys that are in B_p; return how many (key, priority) pairs
        were applied. Keys evicted or living in B_u are ignored silently (the learner's batch
        may be stale). With the step sampler each priority is an array of that item's
        num_steps; the uniform sampler ignores priorities and 0 is returned. A repeated key: the
        last wins.

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
        if not self.sampler.has_priorities:
            return 0
        return self._prioritized.update(key_array.tolist(), priorities)

    # ----------------------------------------------------------------------------- introspection

    def __len__(self) -> int:
        return len(self._prioritized) + len(self._uniform)

    def stats(self) -> dict[str, float | int]:
        """Counters and sizes, O(1). The priority summary is over B_p's items' (clamped)
        priorities — Σ_t p_t per item with the step sampler — and 0.0 when B_p is empty or the
        sampler has no priorities."""
        priority_min, priority_max, priority_mean = self._prioritized.priority_summary()
        return {
            "prioritized_items": len(self._prioritized),
            "prioritized_steps": self._prioritized.steps,
            "uniform_items": len(self._uniform),
            "uniform_steps": self._uniform.steps,
            "inserted": self._inserted,
            "displaced": self._displaced,
            "evicted": self._evicted,
            "sampled": self._sampled,
            "sampled_steps": self._sampled_steps,
            "priority_min": priority_min,
            "priority_max": priority_max,
            "priority_mean": priority_mean,
        }

    def view(self) -> ShardView:
        """What this replay holds as a shard of a larger one (`shards.ShardView`): B_p's and
        B_u's item counts, B_p's sampling mass and its P_min's mass."""
        sampler, items = self.sampler, len(self._prioritized)
        if not items:
            mass = min_mass = 0.0
        elif sampler.has_priorities:
            mass, min_mass = sampler.total_mass(), sampler.min_mass(self._prioritized.priorities)
        else:
            mass, min_mass = float(items), 1.0
        return ShardView(items, len(self._uniform), mass, min_mass)

    def _prioritized_keys(self) -> set[int]:
        """Keys now in B_p (for tests and debugging)."""
        return self._prioritized.keys()

    def _uniform_keys(self) -> list[int]:
        """Keys now in B_u, oldest first (for tests and debugging)."""
        return [entry.key for entry in self._uniform.entries()]

    @property
    def _slot_keys(self) -> np.ndarray:
        """B_p's key per slot, -1 where free (for tests: maps `_draw_steps`' slots to keys)."""
        return self._prioritized.slot_keys

    def _draw_steps(self, count: int, beta: float):
        """Step sampler: `count` single transitions as (slots, steps, weights) (for tests)."""
        return self.sampler.draw_steps(count, beta, self._rng)

    # ----------------------------------------------------------------------------- state

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to rebuild this buffer exactly — the items, their tree values, the
        counters and the sampler's RNG state — as plain Python and numpy values (the items stay
        as they are: the caller decides how to store them). Arrays are copies and the lists
        are new, so the result stays valid while the buffer goes on changing."""
        return {
            "format": STATE_FORMAT,
            "config": {"prioritized_capacity": self._prioritized.capacity,
                       "uniform_capacity_steps": self._uniform.capacity_steps,
                       "sampler": self.sampler.name, "remover": self.remover.name,
                       "alpha": getattr(self.sampler, "alpha", None),
                       "min_priority": getattr(self.sampler, "min_priority", None)},
            **self._prioritized.state(),
            "uniform": [tuple(entry) for entry in self._uniform.entries()],
            "counters": {"next_key": self._next_key, "inserted": self._inserted,
                         "displaced": self._displaced, "evicted": self._evicted,
                         "sampled": self._sampled, "sampled_steps": self._sampled_steps},
            "rng": self._rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned into this (empty) buffer, built with the same
        capacities and strategies; a mismatch is refused with both values. A format-1 state
        (before the strategies) is read where that is lossless, and refused where it is not."""
        if self._next_key:
            raise ValueError("load_state_dict needs an empty buffer")
        state = upgraded(state)
        config = state["config"]
        for name, mine in (("prioritized_capacity", self._prioritized.capacity),
                           ("uniform_capacity_steps", self._uniform.capacity_steps),
                           ("sampler", self.sampler.name), ("remover", self.remover.name)):
            if config.get(name) != mine:
                raise ValueError(f"saved buffer has {name}={config.get(name)!r}, this one "
                                 f"{mine!r}")
        check_saved_slots(state, self._prioritized.capacity)
        self._prioritized.load(state)
        self._uniform.load(state["uniform"])
        counters = state["counters"]
        self._next_key = int(counters["next_key"])
        self._inserted = int(counters["inserted"])
        self._displaced = int(counters["displaced"])
        self._evicted = int(counters["evicted"])
        self._sampled = int(counters["sampled"])
        self._sampled_steps = int(counters["sampled_steps"])
        self._rng.bit_generator.state = state["rng"]


# ----------------------------------------------------------------------------- the algorithms


def tpdeb(prioritized_capacity: int, uniform_capacity_steps: int, zeta: float = 0.2,
          alpha: float = 1.0, seed: int | None = None, min_priority: float = 1e-6) -> DualReplay:
    """TPDEB: B_p keeps the highest-priority fragments (the lowest gives way, only to a higher
    one) and is sampled ∝ p^α per fragment; ζ from the settings."""
    return DualReplay.compose(TrajectorySampler(prioritized_capacity, alpha, min_priority),
                              LowestPriorityRemover(), uniform_capacity_steps, zeta, seed)


def impact(uniform_capacity_steps: int, seed: int | None = None) -> DualReplay:
    """IMPACT: one uniform FIFO bounded in steps (ζ = 0 bypasses B_p; no priorities)."""
    return DualReplay.compose(UniformSampler(1), OldestRemover(), uniform_capacity_steps,
                              zeta=0.0, seed=seed)


def ppo_per(prioritized_capacity: int, uniform_capacity_steps: int, alpha: float = 1.0,
            seed: int | None = None, min_priority: float = 1e-6) -> DualReplay:
    """PPO + PER: B_p a FIFO of the newest fragments (the oldest gives way), sampled by PER over
    single steps; every batch from B_p (ζ = 1)."""
    return DualReplay.compose(StepSampler(prioritized_capacity, alpha, min_priority),
                              OldestRemover(), uniform_capacity_steps, zeta=1.0, seed=seed)


# What each algorithm's replay is made of (services/config/presets.py's ALGORITHMS sets the same
# through the constructor's settings; tests/test_replay_strategies.py checks they agree).
COMPOSITIONS = {"tpdeb": tpdeb, "impact": impact, "ppo-per": ppo_per}
