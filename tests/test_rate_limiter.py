"""RateLimiter: deadlocking settings are refused, accepted ones never deadlock, the ratio holds."""

import numpy as np
import pytest

from tpdeb.tpdeb_core.rate_limiter import RateLimiter


def make(spi=4.0, min_size=256, error_buffer=None, insert_steps=64, sample_steps=512, **kw):
    if error_buffer is None:
        error_buffer = RateLimiter.min_error_buffer(spi, insert_steps, sample_steps)
    return RateLimiter(
        spi, min_size, error_buffer, insert_steps=insert_steps, sample_steps=sample_steps, **kw
    )


def test_min_error_buffer_is_the_larger_bound():
    # (64*4 + 512)/2 = 384 < 512: the first-sample bound wins.
    assert RateLimiter.min_error_buffer(4.0, 64, 512) == 512.0
    # (64*16 + 512)/2 = 768 > 512: the deadlock bound wins.
    assert RateLimiter.min_error_buffer(16.0, 64, 512) == 768.0


@pytest.mark.parametrize(
    ("kwargs", "fragments"),
    [
        ({"spi": 0.0}, ["samples_per_insert", "0.0"]),
        ({"spi": -2.0}, ["samples_per_insert", "-2.0"]),
        ({"spi": float("inf")}, ["samples_per_insert", "inf"]),
        ({"spi": float("nan")}, ["samples_per_insert", "nan"]),
        ({"min_size": 0}, ["min_size_to_sample", "0"]),
        ({"min_size": 2.5}, ["min_size_to_sample", "2.5"]),
        ({"insert_steps": 0}, ["insert_steps", "0"]),
        ({"sample_steps": -1}, ["sample_steps", "-1"]),
        ({"capacity_steps": 100}, ["capacity_steps=100", "min_size_to_sample=256"]),
        # Deadlock bound: (64*16 + 512)/2 = 768.
        (
            {"spi": 16.0, "error_buffer": 767.0},
            ["error_buffer=767.0", "samples_per_insert=16.0", "insert_steps=64", "768"],
        ),
        # First-sample bound: sample_steps = 512 > (64*4 + 512)/2.
        ({"error_buffer": 511.0}, ["error_buffer=511.0", "sample_steps=512", "512"]),
        ({"error_buffer": float("nan")}, ["error_buffer=nan"]),
    ],
)
def test_refuses_deadlocking_or_meaningless_settings(kwargs, fragments):
    with pytest.raises(ValueError) as error:
        make(**kwargs)
    for fragment in fragments:
        assert fragment in str(error.value)


def test_minimum_error_buffer_is_accepted():
    limiter = make(spi=16.0, error_buffer=768.0)
    assert limiter.stats()["diff"] == 0.0


def test_min_size_gates_sampling_not_inserting():
    limiter = make(spi=1.0, min_size=256, insert_steps=64, sample_steps=64)
    for _ in range(3):
        assert limiter.can_insert(64)
        assert not limiter.can_sample(64)
        limiter.on_insert(64)
    assert not limiter.can_sample(64)  # 192 < 256 steps
    limiter.on_insert(64)
    assert limiter.can_sample(64)  # first batch possible at once: error_buffer >= sample_steps


def test_requests_larger_than_declared_are_refused():
    limiter = make(insert_steps=64, sample_steps=512)
    with pytest.raises(ValueError, match="65"):
        limiter.can_insert(65)
    with pytest.raises(ValueError, match="513"):
        limiter.can_sample(513)
    with pytest.raises(ValueError, match="num_steps"):
        limiter.on_insert(0)


def race(limiter, rng, insert_bias, insert_steps, sample_steps, iterations=20_000,
         vary_sizes=False):
    """Actors and learner at random relative speeds, `insert_bias` how often the actors win
    when both may act; a refused side waits its turn. With `vary_sizes`, a fifth of the
    requests are smaller than the declared maxima (a short final fragment, a smaller batch)."""
    for _ in range(iterations):
        insert_size, sample_size = insert_steps, sample_steps
        if vary_sizes and rng.random() < 0.2:
            insert_size = int(rng.integers(1, insert_steps + 1))
        if vary_sizes and rng.random() < 0.2:
            sample_size = int(rng.integers(1, sample_steps + 1))
        may_insert = limiter.can_insert(insert_size)
        may_sample = limiter.can_sample(sample_size)
        assert may_insert or may_sample, f"deadlock at {limiter.stats()}"
        if may_insert and (not may_sample or rng.random() < insert_bias):
            limiter.on_insert(insert_size)
        else:
            limiter.on_sample(sample_size)
    return limiter.stats()


@pytest.mark.parametrize("insert_bias", [0.9, 0.1])
@pytest.mark.parametrize(
    ("spi", "insert_steps", "sample_steps", "min_size"),
    [
        (16.0, 64, 512, 512),  # the defaults: 8 fragments of 64, replay ratio 16
        (4.0, 64, 512, 256),
        (0.25, 64, 8, 64),  # more inserted than sampled
        (0.1, 7, 3, 10),  # a ratio that is not a binary fraction
        (3.0, 1, 1, 1),
    ],
)
def test_minimal_buffer_never_deadlocks_and_ratio_converges(
    spi, insert_steps, sample_steps, min_size, insert_bias
):
    """Actors and learner at random relative speeds; a side that is refused waits its turn.

    `insert_bias` is how often the actors win the race when both sides may act: one side is
    much faster than the other, yet the limiter holds the ratio.
    """
    rng = np.random.default_rng(0)
    limiter = make(spi, min_size, None, insert_steps, sample_steps)
    stats = race(limiter, rng, insert_bias, insert_steps, sample_steps, vary_sizes=True)
    assert stats["inserted_steps"] >= 10 * min_size
    # |diff - offset| <= error_buffer (+ one request), so the achieved ratio is within
    # (offset + error_buffer + one request) / inserted_steps of the target.
    bound = (
        spi * min_size
        + RateLimiter.min_error_buffer(spi, insert_steps, sample_steps)
        + spi * insert_steps
        + sample_steps
    ) / stats["inserted_steps"]
    assert abs(stats["samples_per_insert_achieved"] - spi) <= bound
    assert bound < 0.05 * spi


def test_stats_start_at_zero():
    stats = make().stats()
    assert stats["inserted_steps"] == 0
    assert stats["sampled_steps"] == 0
    assert stats["samples_per_insert_achieved"] == 0.0


def test_state_round_trip_and_bad_state():
    a = RateLimiter(2.0, 100, 1000, insert_steps=10, sample_steps=50)
    a.on_insert(10)
    a.on_insert(10)
    b = RateLimiter(2.0, 100, 1000, insert_steps=10, sample_steps=50)
    b.load_state_dict(a.state_dict())
    assert b.stats() == a.stats()
    with pytest.raises(ValueError, match="sampled_steps"):
        b.load_state_dict({"inserted_steps": 0, "sampled_steps": -1})


def test_inserts_restored_without_their_samples_leave_diff_where_it_stood():
    """A replay restart re-inserts what it logged after its snapshot; the samples taken against
    those went unrecorded. Counted as plain inserts they would put diff far above max_diff and
    hold every new insert back until the learner had sampled them all again (24-40 s of
    stalled actors after a replay kill 50 s past its snapshot)."""
    live = make(spi=16.0, insert_steps=64, sample_steps=512)
    for _ in range(200):  # the run until the kill: each side acts whenever it may
        if live.can_insert(64):
            live.on_insert(64)
        while live.can_sample(512):
            live.on_sample(512)
    saved = live.state_dict()
    for _ in range(50):  # after the snapshot: logged inserts, unlogged samples
        live.on_insert(64)
        while live.can_sample(512):
            live.on_sample(512)
    restored = make(spi=16.0, insert_steps=64, sample_steps=512)
    restored.load_state_dict(saved)
    for _ in range(50):
        restored.on_restored_insert(64)
    assert restored.stats()["inserted_steps"] == live.stats()["inserted_steps"]
    assert restored.stats()["diff"] == 16.0 * saved["inserted_steps"] - saved["sampled_steps"]
    assert restored.can_insert(64)
    counted_alone = make(spi=16.0, insert_steps=64, sample_steps=512)
    counted_alone.load_state_dict(saved)
    for _ in range(50):
        counted_alone.on_insert(64)
    assert not counted_alone.can_insert(64)  # what the restart did before


def test_inserts_restored_from_nothing_owe_no_samples_before_min_size():
    """A log replayed without any snapshot: the learner sampled nothing before min_size steps
    were in, and kept diff near spi · min_size after: both sides may act at once."""
    limiter = make(spi=4.0, min_size=256, insert_steps=64, sample_steps=512)
    for _ in range(20):
        limiter.on_restored_insert(64)
    assert limiter.stats()["diff"] == 4.0 * 256
    assert limiter.can_insert(64) and limiter.can_sample(512)


@pytest.mark.parametrize("upper", [2.0, float("nan"), float("inf"), "x"])
def test_band_refuses_an_upper_end_below_the_ratio_or_not_finite(upper):
    with pytest.raises(ValueError, match="max_samples_per_insert"):
        make(spi=4.0, max_samples_per_insert=upper)


@pytest.mark.parametrize(
    ("spi", "upper", "insert_steps", "sample_steps", "min_size"),
    [(16.0, 64.0, 64, 512, 512), (1.0, 4.0, 64, 64, 64), (0.25, 0.5, 7, 3, 10)],
)
def test_band_never_deadlocks_and_the_speeds_pick_the_ratio_inside_it(
    spi, upper, insert_steps, sample_steps, min_size
):
    """Fast actors hold the ratio at the band's lower end, scarce inserts let the learner rise
    to its upper end; the smallest deadlock-free error buffer of the lower ratio suffices."""
    rng = np.random.default_rng(1)
    achieved = {}
    for insert_bias in (0.95, 0.05):
        limiter = make(spi, min_size, None, insert_steps, sample_steps,
                       max_samples_per_insert=upper)
        stats = race(limiter, rng, insert_bias, insert_steps, sample_steps)
        achieved[insert_bias] = stats["samples_per_insert_achieved"]
        slack = (upper * min_size + RateLimiter.min_error_buffer(spi, insert_steps, sample_steps)
                 + upper * insert_steps + sample_steps) / stats["inserted_steps"]
        assert spi - slack <= achieved[insert_bias] <= upper + slack
    assert achieved[0.95] == pytest.approx(spi, rel=0.05)  # actors ahead: the learner's floor
    assert achieved[0.05] == pytest.approx(upper, rel=0.05)  # inserts scarce: the ceiling


def test_a_band_of_zero_width_is_the_fixed_ratio():
    rng_a, rng_b = np.random.default_rng(2), np.random.default_rng(2)
    fixed = race(make(spi=4.0), rng_a, 0.3, 64, 512, iterations=3_000)
    band = race(make(spi=4.0, max_samples_per_insert=4.0), rng_b, 0.3, 64, 512,
                    iterations=3_000)
    assert band == fixed
