"""Batch growth: the rule that doubles the learner's batch while its device has headroom, and
the settings that carry it to the replay's rate limiter."""

from __future__ import annotations

import pytest

from tests.test_checkpoint import close, service_for
from tpdeb.services.config import ConfigError
from tpdeb.services.config.train import TrainConfig
from tpdeb.tpdeb_core.batch_growth import BatchGrowth


def feed(growth: BatchGrowth, cost_of, wait_share: float = 0.0, updates: int = 1000) -> list:
    """Updates timed by `cost_of(size)` seconds; the sizes it moved to, in order."""
    moves = []
    for _ in range(updates):
        busy = cost_of(growth.size)
        moved = growth.observe(busy, busy * wait_share / (1 - wait_share))
        if moved is not None:
            moves.append(moved)
    return moves


def test_a_batch_that_costs_little_more_is_doubled_up_to_the_ceiling():
    growth = BatchGrowth(8, 64, settle=2, window=5)
    moves = feed(growth, lambda size: 1e-3 * (1 + size / 64))  # mostly fixed overhead
    assert moves == [16, 32, 64] and growth.settled and growth.size == 64
    assert [size for size, _ in growth.history] == [8, 16, 32, 64]


def test_a_doubled_batch_that_costs_too_much_is_given_back_and_kept_there():
    growth = BatchGrowth(8, 64, settle=2, window=5)
    moves = feed(growth, lambda size: 1e-3 * (1 if size <= 16 else size / 8))  # 32 costs 2×
    assert moves == [16, 32, 16] and growth.settled and growth.size == 16
    assert growth.last[0] == 32 and growth.last[1] == pytest.approx(4e-3)
    assert feed(growth, lambda size: 1e-6) == []  # settled: it does not move again


def test_a_learner_that_waits_for_its_batches_is_not_the_limit_and_keeps_its_batch():
    growth = BatchGrowth(8, 64, settle=2, window=5)
    assert feed(growth, lambda size: 1e-3, wait_share=0.5, updates=70) == []  # 10 windows
    assert growth.size == 8 and not growth.settled and growth.history == [(8, 1e-3)]
    assert feed(growth, lambda size: 1e-3, updates=7) == [16]  # the actors caught up


def test_a_doubling_measured_again_is_judged_again():
    growth = BatchGrowth(8, 64, settle=0, window=2)
    assert [growth.observe(1.0, 0.0) for _ in range(2)] == [None, 16]
    # at 16 the first window is cheap but the learner waited: it stays at 16 and measures again
    assert [growth.observe(1.2, 1.0) for _ in range(2)] == [None, None]
    assert growth.size == 16 and not growth.settled
    # measured again, an update on 16 costs 2.5× one on 8: 8 is taken back
    assert [growth.observe(2.5, 0.0) for _ in range(2)] == [None, 8]
    assert growth.settled and growth.size == 8 and growth.last == (16, 2.5)


def test_the_rule_is_timed_only_after_each_change_has_settled():
    growth = BatchGrowth(8, 16, settle=3, window=2)
    # the first three updates of a size are not timed: a slow start does not count
    assert [growth.observe(s, 0.0) for s in (9.0, 9.0, 9.0, 1.0, 1.0)] == [None] * 4 + [16]
    assert [growth.observe(s, 0.0) for s in (9.0, 9.0, 9.0, 1.2, 1.2)] == [None] * 5
    assert growth.settled and growth.size == 16  # kept: 1.2× the smaller one's cost


def test_bad_growth_settings_are_refused():
    with pytest.raises(ValueError, match="largest"):
        BatchGrowth(8, 4)
    with pytest.raises(ValueError, match="cost"):
        BatchGrowth(8, 16, cost=0.5)
    assert BatchGrowth(8, 8).settled  # no room to grow: nothing to decide


def test_the_growth_ceiling_is_checked_and_builds_the_replays_rate_limiter():
    with pytest.raises(ConfigError, match="max_batch_fragments=4: must be 0"):
        TrainConfig(batch_fragments=8, max_batch_fragments=4)
    with pytest.raises(ConfigError, match="max_batch_fragments=8192"):
        TrainConfig(max_batch_fragments=8192)
    with pytest.raises(ConfigError, match="learners=2"):
        TrainConfig(batch_fragments=8, max_batch_fragments=32, learners=2)
    plain, grown = TrainConfig(), TrainConfig(max_batch_fragments=32)
    assert plain.largest_batch == 8 and grown.largest_batch == 32
    steps = grown.fragment_len
    with pytest.raises(ValueError, match="at most"):
        plain.rate_limiter().can_sample(16 * steps)
    limiter = grown.rate_limiter()
    assert limiter.can_sample(32 * steps) is False  # asked of (nothing inserted yet), not refused
    with pytest.raises(ValueError, match="at most"):
        limiter.can_sample(33 * steps)

    def width(config):  # the limiter's error buffer: wide enough for the largest batch
        stats = config.rate_limiter().stats()
        return stats["max_diff"] - stats["min_diff"]

    assert width(grown) > width(plain)


def test_the_learner_asks_for_the_size_its_growth_picks(tmp_path):
    service, _ = service_for(tmp_path, compile="off", batch_fragments=4, max_batch_fragments=8)
    asked = []
    service._ask = lambda key, request: asked.append(request) or []  # no replay: no answer
    try:
        service.fetch(1)
        for _ in range(60):  # cheap updates while the learner never waits: doubled
            service.grow(busy_s=1e-3, waited_s=0.0)
        service.fetch(2)
        for _ in range(60):  # an update on 8 costs 3× one on 4: 4 is taken back
            service.grow(busy_s=3e-3, waited_s=0.0)
        service.fetch(3)
    finally:
        close(service)
    assert [request.batch_size for request in asked] == [4, 8, 4]
    assert service.growth.settled
