"""Replay shards (DESIGN §2 "Replay shards"): K replay servers, one global buffer to the learner.

Each actor writes to one shard (`shard_of`, by its id); the learner draws each batch from all of
them. For the batch to be the one a single replay holding every shard's items would give, it is
split as that replay would draw it (`split_batch`):

- B_p's share, round(ζB), among the shards in proportion to their B_p sampling mass (Σ p^α),
  B_u's share in proportion to their B_u item counts — as one multinomial draw each, so every
  row of the batch is an independent draw from the union: P(i) = m_i / Σ_k M_k exactly;
- a shard that is down, or whose state is not yet known, takes no share: the batch comes from
  the live shards in proportion among them;
- importance weights (m_i / m_min)^(−β) are each shard's, against its own P_min; `global_weights`
  rescales them to the union's P_min (the smallest over the live shards), so that they are the
  union's weights.

What is not global: B_p's remover acts per shard (a shard's lowest-priority item gives way to a
higher one arriving at that shard, not at another), and B_u's FIFO evicts per shard. With actors
spread evenly over the shards (`shard_of` is the id modulo K) both are close to the union's.

Pure: numpy and the standard library only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from tpdeb.tpdeb_core.replay_samplers import check_int, check_real


class ShardView(NamedTuple):
    """What a shard holds, as its last sample reply said: B_p's and B_u's item counts, B_p's
    sampling mass (Σ p^α; the item count where B_p has no priorities) and its P_min's mass
    (the mass its importance weights are taken against; 1.0 without priorities)."""

    prioritized: int
    uniform: int
    mass: float
    min_mass: float

    @property
    def empty(self) -> bool:
        return self.prioritized + self.uniform == 0


def shard_of(actor_id: int, shards: int) -> int:
    """The shard an actor writes to: its id modulo K (ids 0, 1, 2, … spread evenly)."""
    check_int("shards", shards, 1)
    return check_int("actor_id", actor_id, 0) % shards


def split_batch(batch_size: int, zeta: float, views: Sequence[ShardView | None],
                rng: np.random.Generator) -> np.ndarray:
    """Each shard's share of a batch, as an int array [K, 2] of (from B_p, from B_u).

    `views[k]` is None for a shard that is down or not yet heard from. One buffer empty on every
    live shard: the other fills the batch (as one replay does). No live shard holds anything:
    all zeros (the caller waits)."""
    batch_size = check_int("batch_size", batch_size, 1)
    zeta = check_real("zeta", zeta, 0.0, 1.0)
    counts = np.zeros((len(views), 2), dtype=np.int64)
    live = [(k, v) for k, v in enumerate(views) if v is not None and not v.empty]
    if not live:
        return counts
    p_mass = np.array([v.mass if v.prioritized else 0.0 for _, v in live], dtype=np.float64)
    u_items = np.array([v.uniform for _, v in live], dtype=np.float64)
    has_p, has_u = p_mass.sum() > 0.0, u_items.sum() > 0.0
    num_p = batch_size if not has_u else 0 if not has_p else round(zeta * batch_size)
    rows = [k for k, _ in live]
    if num_p:
        counts[rows, 0] = rng.multinomial(num_p, p_mass / p_mass.sum())
    if batch_size - num_p:
        counts[rows, 1] = rng.multinomial(batch_size - num_p, u_items / u_items.sum())
    return counts


def global_min_mass(min_masses: Sequence[float]) -> float:
    """The union's P_min mass: the smallest of the live shards' (those with B_p items)."""
    masses = [m for m in min_masses if m > 0.0]
    if not masses:
        raise ValueError("no shard with prioritized items: there is no P_min to weigh against")
    return min(masses)


def global_weights(weights: np.ndarray, shard_min_mass: float, union_min_mass: float,
                   beta: float) -> np.ndarray:
    """A shard's B_p importance weights (m / m_min,k)^(−β) as the union's (m / m_min)^(−β):
    times (m_min,k / m_min)^(−β), ≤ 1 since the union's P_min is at most the shard's."""
    check_real("beta", beta, 0.0, 1.0)
    if not 0.0 < union_min_mass <= shard_min_mass:
        raise ValueError(f"the union's P_min mass ({union_min_mass!r}) must be in "
                         f"(0, the shard's {shard_min_mass!r}]")
    factor = (shard_min_mass / union_min_mass) ** (-beta)
    return (np.asarray(weights) * factor).astype(np.asarray(weights).dtype, copy=False)
