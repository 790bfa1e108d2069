"""The learner's side of replay shards (DESIGN §2 "Replay shards"): one batch from K replays.

`ShardSet` keeps what each shard last said it holds (the view in its replies) and which shards
are down, plans each batch's split (`tpdeb_core.shards.split_batch`: B_p's rows by sampling
mass, B_u's by item count) and joins the shards' replies into the one reply a learner trains on
(`join`):

- fragments side by side (`fragments.join_batches`);
- keys made global, key·K + shard, so that each priority finds its shard again (`route`);
- B_p's importance weights rescaled to the union's P_min (`shards.global_weights`);
- inserted steps summed over the shards (each shard's latest count), normaliser moments merged.

A shard never heard from, back from being left out, or empty when last heard from is probed (at
most once per `probe_s`) with one B_u row of the batch: its reply (ready or not) says what it
holds, and it takes its share from the next batch on.

A shard that did not answer is left out for as long as the unanswered query waited (at least
`probe_s`, at most `retry_s`): one that let a query time out would cost every batch that asks it
the whole timeout, one that answered nothing at once (its routes being remade) costs nothing to
ask again. Each shard's wait is its own query's (`Gathered`: from the asking to the query's
end), whatever order the replies are read in. A shard whose liveliness token goes is left out
until it comes back, and asked again as soon as it does — also when it was left out for a miss:
after the router hangs past its lease, the queries sent meanwhile end unanswered as the tokens
go, and the tokens' return is the newer news.

With one shard the learner does not use this: its requests and replies are today's.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
import zenoh

from tpdeb.protocol.messages import Moments, SampleReply
from tpdeb.tpdeb_core.fragments import join_batches
from tpdeb.tpdeb_core.moments import merge_moments
from tpdeb.tpdeb_core.shards import ShardView, global_min_mass, global_weights, split_batch


class Gathered:
    """One shard's sample query: its replies as they come (a zenoh callback's thread) and when
    the query ended (the handler dropped: all replies in, the timeout or a cancellation), so
    that a shard's wait is timed by its own query, whatever the order the replies are read in."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.clock, self.replies, self.ended_at = clock, [], None
        self.ended = threading.Event()

    def handler(self) -> zenoh.handlers.Callback:
        """What the query is sent with: each reply added, the query's end recorded."""
        return zenoh.handlers.Callback(self.add, self.end)

    def add(self, reply) -> None:
        self.replies.append(reply)

    def end(self) -> None:
        self.ended_at = self.clock()
        self.ended.set()

    def wait(self, timeout_s: float) -> list:
        """The replies once the query ended (at most `timeout_s` and a second: zenoh ends it
        at its timeout; past that it counts as ended now)."""
        if not self.ended.wait(timeout_s + 1.0):
            self.ended_at = self.clock()
        return list(self.replies)


class ShardSet:
    """K replay shards as the learner sees them."""

    def __init__(self, shards: int, zeta: float, seed: int, retry_s: float = 5.0,
                 probe_s: float = 1.0, clock: Callable[[], float] = time.monotonic):
        if shards < 2:
            raise ValueError(f"replay_shards={shards}: a ShardSet is for 2 or more shards")
        self.shards, self.zeta, self.clock = shards, zeta, clock
        self.retry_s, self.probe_s = retry_s, probe_s
        self.rng = np.random.default_rng(seed)
        self.lock = threading.Lock()  # the fetch threads and the liveliness callback share it
        self.views: list[ShardView | None] = [None] * shards  # None: not heard from yet
        self.inserted = [0] * shards
        self.down_until = [0.0] * shards
        self.probed_at = [-math.inf] * shards
        # the normalisers' moments of replies whose batch was not filled: with the next one
        self.aside: list[tuple[Moments | None, Moments | None]] = []

    # -- which shard holds what
    def heard(self, shard: int, reply: SampleReply) -> None:
        """A reply from `shard` (ready or not): what it holds now, and that it is up."""
        with self.lock:
            self.views[shard] = ShardView(reply.prioritized_items, reply.uniform_items,
                                          reply.mass, reply.min_mass)
            self.inserted[shard] = max(self.inserted[shard], reply.inserted_steps)
            self.down_until[shard] = 0.0

    def missed(self, shard: int, waited_s: float) -> float | None:
        """No answer from `shard` to a query that waited `waited_s`: down, left out for as
        long (within [probe_s, retry_s]). Returns those seconds where it was up until now (for
        the log: the other fetchers' misses of the same outage say nothing new)."""
        out_s = min(max(waited_s, self.probe_s), self.retry_s)
        with self.lock:
            now = self.clock()
            was_up = self.down_until[shard] <= now
            self.views[shard] = None
            self.down_until[shard] = max(self.down_until[shard], now + out_s)
        return out_s if was_up else None

    def gone(self, shard: int) -> None:
        """`shard`'s liveliness token went: left out until it is back."""
        with self.lock:
            self.views[shard] = None
            self.down_until[shard] = math.inf

    def back(self, shard: int) -> None:
        """`shard`'s token is there (again): probed from the next batch on — also when it was
        left out for a miss, which the token's return is newer news than (the queries sent
        while the router hung end unanswered when the lease runs out, as the tokens go)."""
        with self.lock:
            self.down_until[shard] = 0.0

    def down(self) -> list[int]:
        with self.lock:
            now = self.clock()
            return [k for k in range(self.shards) if self.down_until[k] > now]

    @property
    def inserted_steps(self) -> int:
        return sum(self.inserted)

    # -- one batch
    def plan(self, batch_size: int, among: Sequence[int] | None = None) -> np.ndarray:
        """Each shard's rows of the next batch, [K, 2] (from B_p, from B_u). `among`: only these
        shards (a second round, for the rows of shards that were not ready)."""
        with self.lock:
            return self._plan(batch_size, among)

    def _plan(self, batch_size: int, among: Sequence[int] | None) -> np.ndarray:
        allowed = set(range(self.shards) if among is None else among)
        now = self.clock()
        down = {k for k in range(self.shards) if self.down_until[k] > now}
        probes = [k for k in sorted(allowed - down) if now - self.probed_at[k] >= self.probe_s
                  and (self.views[k] is None or self.views[k].empty)][:batch_size]
        for k in probes:
            self.probed_at[k] = now
        counts = np.zeros((self.shards, 2), dtype=np.int64)
        counts[probes, 1] = 1
        views = [self.views[k] if k in allowed and k not in down else None
                 for k in range(self.shards)]
        rest = batch_size - len(probes)
        if rest and any(v is not None and not v.empty for v in views):
            counts += split_batch(rest, self.zeta, views, self.rng)
        elif rest and probes:  # nothing known yet: the probes share the batch evenly
            for i in range(rest):
                counts[probes[i % len(probes)], 1] += 1
        return counts

    def join(self, replies: Sequence[tuple[int, SampleReply]], beta: float) -> SampleReply:
        """The shards' ready replies as one: what the learner trains on (their views heard)."""
        with self.lock:  # the union's P_min: the shards' as last heard, and these replies'
            union_min = global_min_mass(
                [v.min_mass for v in self.views if v is not None]
                + [r.min_mass for _, r in replies]) \
                if any(r.from_prioritized.any() for _, r in replies) else None
            moments = self.aside + [(r.obs_moments, r.ret_moments) for _, r in replies]
            self.aside, inserted = [], self.inserted_steps
        keys, weights, step_weights = [], [], []
        for shard, reply in replies:
            keys.append(reply.keys * self.shards + shard)
            w = reply.weights
            sw = reply.step_weights
            chosen = reply.from_prioritized
            if chosen.any():
                if sw is None:
                    w = np.where(chosen, global_weights(w, reply.min_mass, union_min, beta), w)
                else:
                    sw = np.where(chosen[:, None],
                                  global_weights(sw, reply.min_mass, union_min, beta), sw)
            weights.append(w.astype(np.float32))
            step_weights.append(sw)
        if any(sw is not None for sw in step_weights):
            width = max(sw.shape[1] for sw in step_weights if sw is not None)
            step_weights = [np.pad(sw, ((0, 0), (0, width - sw.shape[1])))
                            for sw in step_weights]
        first = replies[0][1]
        return SampleReply(
            request_id=first.request_id, ready=True, keys=np.concatenate(keys),
            weights=np.concatenate(weights),
            from_prioritized=np.concatenate([r.from_prioritized for _, r in replies]),
            step_weights=(np.concatenate(step_weights).astype(np.float32)
                          if step_weights[0] is not None else None),
            batch=join_batches([r.batch for _, r in replies]),
            inserted_steps=inserted,
            obs_moments=_merged([obs for obs, _ in moments]),
            ret_moments=_merged([ret for _, ret in moments]))

    def set_aside(self, replies: Sequence[SampleReply]) -> None:
        """Replies of a batch that could not be filled: the normalisers' moments they carry
        (each replay ships its moments once) go with the next batch."""
        with self.lock:
            self.aside += [(r.obs_moments, r.ret_moments) for r in replies]

    def route(self, keys: np.ndarray) -> dict[int, np.ndarray]:
        """Global keys → {shard: (positions in `keys`, the shard's own keys)} (priorities)."""
        keys = np.asarray(keys, np.int64)
        out = {}
        for shard in range(self.shards):
            where = np.flatnonzero(keys % self.shards == shard)
            if where.size:
                out[shard] = (where, keys[where] // self.shards)
        return out


def _merged(parts: Sequence[Moments | None]) -> Moments | None:
    """Moments (count, mean, M2) of the union of the parts' samples; None if none has any."""
    moments = [(m.count, m.mean, m.m2) for m in parts if m is not None]
    if not moments:
        return None
    total = moments[0]
    for part in moments[1:]:
        total = merge_moments(total, part)
    return Moments(*total)
