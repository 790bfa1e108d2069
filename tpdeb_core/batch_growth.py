"""Batch growth (DESIGN §2 "Batch growth"): the learner's batch doubled while its device has
headroom, so that a fast device turns into env steps rather than idle time.

At a fixed replay ratio the learner makes one update per `ratio` inserted steps per batch step:
an update on 2B fragments stands for as many env steps as two on B. When the learner is the
limit of the run (it seldom waits for a batch) and an update on 2B costs less than two on B —
what a GPU, or a CPU whose update is mostly fixed overhead, gives — a doubled batch lets the
actors insert faster at the same ratio. `BatchGrowth` decides it from the learner's own timings:

- at each size it lets `settle` updates pass (a new shape's first calls are slow) and then
  times `window` of them, taking the median seconds per update (the loop's busy time: the
  update and what the loop does around it, not the waits for a batch);
- it asks for the doubled size only if the learner waited for batches at most `max_wait` of
  the window's time (otherwise the actors are the limit and a larger batch buys nothing: it
  measures again); every window at a doubled size is a trial: the size is kept while its
  update costs at most `cost` times the half size's (`cost` < 2: more fragments learned per
  second), and the next doubling is tried, up to `largest`; otherwise the half size is taken
  back and kept.
- Once settled it does not move again.

Pure: the standard library only; the caller feeds it the times.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tpdeb.tpdeb_core.replay_samplers import check_int, check_real


@dataclass
class BatchGrowth:
    """The learner's batch size (fragments), grown by doubling from `size` up to `largest`."""

    size: int
    largest: int
    cost: float = 1.5  # a doubled batch is kept while its update costs ≤ this × the smaller's
    settle: int = 10  # untimed updates after each change
    window: int = 50  # timed updates per size
    max_wait: float = 0.1  # the learner is the limit: it waited ≤ this share of the window
    settled: bool = False
    costs: dict[int, float] = field(default_factory=dict)  # size → its latest median s/update
    last: tuple[int, float] | None = None  # the latest window's (size, median s/update)
    _busy: list[float] = field(default_factory=list, repr=False)
    _waited: float = field(default=0.0, repr=False)
    _seen: int = field(default=0, repr=False)

    def __post_init__(self):
        check_int("size", self.size, 1)
        check_int("largest", self.largest, self.size)
        check_real("cost", self.cost, 1.0)
        check_int("settle", self.settle, 0)
        check_int("window", self.window, 1)
        check_real("max_wait", self.max_wait, 0.0)
        self.settled = self.settled or self.largest == self.size

    def observe(self, busy_s: float, waited_s: float) -> int | None:
        """One update at the current size took `busy_s` (the learner waited `waited_s` for
        its batch before it). Returns the new size when it changes, else None."""
        if self.settled:
            return None
        self._seen += 1
        if self._seen <= self.settle:
            return None
        self._busy.append(busy_s)
        self._waited += waited_s
        if len(self._busy) < self.window:
            return None
        median, waited = _median(self._busy), self._waited / (self._waited + sum(self._busy))
        self._busy, self._waited, self._seen = [], 0.0, 0
        self.last = (self.size, median)
        smaller = self.costs.get(self.size // 2)
        if smaller is not None and median > self.cost * smaller:  # every window of a doubling
            self.settled = True  # is a trial: the larger batch costs too much, its half stays
            self.size //= 2
            return self.size
        self.costs[self.size] = median
        if self.size * 2 > self.largest:
            self.settled = True
            return None
        if waited > self.max_wait:  # the actors are the limit: measure again
            return None
        self.size *= 2
        return self.size

    @property
    def history(self) -> list[tuple[int, float]]:
        """(size, its latest median seconds per update), in the order the sizes were tried."""
        return list(self.costs.items())

def _median(values: list[float]) -> float:
    ordered, mid = sorted(values), len(values) // 2
    return ordered[mid] if len(ordered) % 2 else 0.5 * (ordered[mid - 1] + ordered[mid])
