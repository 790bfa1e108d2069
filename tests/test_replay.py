"""DualReplay and its segment trees against brute-force references and exact probabilities."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats as scipy_stats

from tpdeb.tpdeb_core.replay import DualReplay
from tpdeb.tpdeb_core.sumtree import MinTree, SumTree

MIN_PRIORITY = 1e-6
# A p-value this small happens by chance once in 10^4 runs; every seed below is fixed anyway.
P_VALUE_FLOOR = 1e-4

# ------------------------------------------------------------------------ segment trees


leaf_values = st.one_of(st.just(0.0), st.floats(0.0, 100.0), st.floats(1e-12, 1e-6))


@settings(max_examples=60, deadline=None)
@given(
    capacity=st.integers(1, 40),
    writes=st.lists(st.tuples(st.integers(0, 39), leaf_values, st.booleans()), max_size=60),
    queries=st.lists(st.floats(0.0, 1.0, exclude_max=True), min_size=1, max_size=20),
)
def test_trees_match_brute_force(capacity, writes, queries):
    sums, mins = SumTree(capacity), MinTree(capacity)
    leaves = np.zeros(capacity)
    pending_slots, pending_values = [], []
    for slot, value, batched in writes:
        slot %= capacity
        leaves[slot] = value
        if batched:  # exercise set_many, duplicates included: the last write wins
            pending_slots.append(slot)
            pending_values.append(value)
        else:
            sums.set_many(pending_slots, pending_values)
            mins.set_many(pending_slots, pending_values)
            pending_slots, pending_values = [], []
            sums.set(slot, value)
            mins.set(slot, value)
    sums.set_many(pending_slots, pending_values)
    mins.set_many(pending_slots, pending_values)
    # MinTree leaves never written hold +inf.
    written = np.zeros(capacity, bool)
    written[[slot % capacity for slot, _, _ in writes]] = True
    min_leaves = np.where(written, leaves, np.inf)

    np.testing.assert_array_equal(sums.get(np.arange(capacity)), leaves)
    assert sums.total() == pytest.approx(leaves.sum(), rel=1e-12, abs=1e-300)
    assert mins.min() == min_leaves.min()
    assert min_leaves[mins.argmin()] == min_leaves.min()
    if sums.total() == 0.0:
        with pytest.raises(ValueError, match="positive total"):
            sums.find_prefix(np.array([0.0]))
        return
    # Each answer is a positive leaf whose [cumsum before, cumsum after] interval holds the
    # query (up to rounding), including queries outside [0, total).
    targets = np.array(queries + [-1.0, 1.0, 2.0]) * sums.total()
    slots = sums.find_prefix(targets)
    before = np.concatenate([[0.0], np.cumsum(leaves)])[slots]
    tolerance = 1e-9 * leaves.sum()
    assert np.all(leaves[slots] > 0.0)
    inside = np.clip(targets, 0.0, leaves.sum())
    assert np.all(before - tolerance <= inside)
    assert np.all(inside <= before + leaves[slots] + tolerance)


def test_tree_capacity_and_slot_checks():
    with pytest.raises(ValueError, match="capacity"):
        SumTree(0)
    tree = SumTree(5)
    with pytest.raises(IndexError, match="slot 5"):
        tree.set(5, 1.0)
    with pytest.raises(IndexError, match="slot -1"):
        tree.set_many(np.array([0, -1]), 1.0)


# ------------------------------------------------------------------------ sampling frequencies


def sample_counts(replay, num_batches, batch_size, beta=1.0):
    """Counts of (key, -1) over many batches (a row per drawn item)."""
    counts = {}
    for _ in range(num_batches):
        batch = replay.sample(batch_size, beta)
        assert batch.step_weights is None
        for key in batch.keys.tolist():
            counts[key, -1] = counts.get((key, -1), 0) + 1
    return counts


def draw_counts(replay, num_draws):
    """Step mode: counts of (key, step) over `num_draws` single-transition draws."""
    slots, steps, _ = replay._draw_steps(num_draws, 1.0)
    counts = {}
    for key, step in zip(replay._slot_keys[slots].tolist(), steps.tolist(), strict=True):
        counts[key, step] = counts.get((key, step), 0) + 1
    return counts


def assert_frequencies(counts, probabilities):
    """Chi-square goodness of fit of `counts` to the exact `probabilities` (same keys)."""
    assert set(counts) <= set(probabilities), "sampled something with probability 0"
    cells = sorted(probabilities)
    observed = np.array([counts.get(cell, 0) for cell in cells], dtype=np.float64)
    expected = np.array([probabilities[cell] for cell in cells]) * observed.sum()
    _, p_value = scipy_stats.chisquare(observed, expected)
    assert p_value > P_VALUE_FLOOR, (observed, expected)


@pytest.mark.parametrize("alpha", [1.0, 0.6])
def test_prioritized_frequencies_are_priority_power_alpha(alpha):
    priorities = np.array([0.05, 0.3, 1.0, 1.0, 2.5, 4.0, 7.0, 12.0])
    # zeta = 1 and room in B_p for everything: every draw is a prioritized draw.
    replay = DualReplay(len(priorities), 64, zeta=1.0, alpha=alpha, seed=11)
    for priority in priorities:
        replay.insert(None, priority, 1)
    mass = priorities**alpha
    probabilities = {(key, -1): m / mass.sum() for key, m in enumerate(mass)}
    assert_frequencies(sample_counts(replay, 1500, 64), probabilities)


def test_step_mode_frequencies_are_per_step_priority_power_alpha():
    rng = np.random.default_rng(5)
    alpha, num_steps = 0.6, 5
    step_priorities = [rng.uniform(0.0, 3.0, num_steps) for _ in range(4)]
    step_priorities[1][2] = 0.0  # clamped to MIN_PRIORITY: rarely drawn, never impossible
    replay = DualReplay(4, 64, zeta=1.0, alpha=alpha, seed=12, priority_mode="step")
    for priorities in step_priorities:
        replay.insert(None, priorities, num_steps)
    mass = {
        (key, step): max(p, MIN_PRIORITY) ** alpha
        for key, priorities in enumerate(step_priorities)
        for step, p in enumerate(priorities)
    }
    total = sum(mass.values())
    probabilities = {cell: m / total for cell, m in mass.items()}
    assert_frequencies(draw_counts(replay, 96_000), probabilities)


def test_updates_change_frequencies_and_unknown_keys_are_ignored():
    replay = DualReplay(2, 4, zeta=1.0, seed=13)
    a = replay.insert("a", 1.0, 1)
    b = replay.insert("b", 1.0, 1)
    in_uniform = replay.insert("c", 0.5, 1)  # not above the lowest (1.0): goes to B_u
    assert replay._uniform_keys() == [in_uniform]
    applied = replay.update_priorities([a, 1000, in_uniform, b], [9.0, 5.0, 50.0, 1.0])
    assert applied == 2
    assert replay._uniform_keys() == [in_uniform]
    assert replay.stats()["priority_max"] == 9.0
    assert_frequencies(sample_counts(replay, 500, 20), {(a, -1): 0.9, (b, -1): 0.1})

    # An evicted key is ignored too: 4 more steps push "c" out of B_u.
    for _ in range(4):
        replay.insert(None, 0.1, 1)
    assert in_uniform not in replay._uniform_keys()
    assert replay.update_priorities(np.array([in_uniform]), np.array([3.0])) == 0


def test_a_bad_update_batch_changes_nothing():
    replay = DualReplay(2, 4, zeta=1.0, seed=14)
    a = replay.insert(None, 1.0, 1)
    b = replay.insert(None, 2.0, 1)
    before = replay.stats()
    with pytest.raises(ValueError, match=r"priorities\[1\]"):
        replay.update_priorities([a, b], [5.0, float("nan")])
    assert replay.stats() == before


# ------------------------------------------------------------------------ importance weights


def direct_weights(unit_priorities, alpha, beta):
    """w_i = (N·P(i))^-β / max_j w_j over the sampling units, computed the O(N) way."""
    unit_priorities = np.maximum(np.asarray(unit_priorities, np.float64), MIN_PRIORITY)
    probabilities = unit_priorities**alpha / np.sum(unit_priorities**alpha)
    weights = (len(unit_priorities) * probabilities) ** (-beta)
    return weights / weights.max()


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0])
def test_trajectory_weights_match_direct_formula(beta):
    alpha = 0.6
    priorities = [0.5, 1.0, 2.0, 4.0, 0.25]
    replay = DualReplay(5, 16, zeta=1.0, alpha=alpha, seed=15)
    keys = [replay.insert(None, p, 1) for p in priorities]
    batch = replay.sample(500, beta)
    expected = direct_weights(priorities, alpha, beta)
    np.testing.assert_allclose(batch.weights, expected[batch.keys], rtol=1e-6)
    assert batch.weights.dtype == np.float32
    assert batch.weights.max() == 1.0  # the lowest priority item (key 4) is drawn

    # Raising the lowest priority moves the maximum weight to the next lowest item.
    replay.update_priorities([keys[4]], [3.0])
    priorities[4] = 3.0
    batch = replay.sample(500, beta)
    expected = direct_weights(priorities, alpha, beta)
    np.testing.assert_allclose(batch.weights, expected[batch.keys], rtol=1e-6)
    assert batch.weights.max() == 1.0


@pytest.mark.parametrize("beta", [0.0, 0.5, 1.0])
def test_step_weights_match_direct_formula(beta):
    alpha = 0.8
    step_priorities = [np.array([1.0, 2.0, 0.25]), np.array([3.0, 0.5, 1.5])]
    replay = DualReplay(2, 16, zeta=1.0, alpha=alpha, seed=16, priority_mode="step")
    for priorities in step_priorities:
        replay.insert(None, priorities, 3)
    flat = np.concatenate(step_priorities)  # unit = step: N = 6 steps held in B_p
    slots, steps, weights = replay._draw_steps(500, beta)
    expected = direct_weights(flat, alpha, beta)[replay._slot_keys[slots] * 3 + steps]
    np.testing.assert_allclose(weights, expected, rtol=1e-6)
    assert weights.max() == 1.0


def test_step_mode_batch_is_t_draws_per_prioritized_item_grouped_by_fragment():
    replay = DualReplay(3, 64, zeta=0.5, alpha=1.0, seed=21, priority_mode="step")
    for key, priorities in enumerate([[1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 5.0],
                                      [3.0, 3.0, 3.0, 3.0], [0.1] * 4, [0.1] * 4]):
        replay.insert(key, np.array(priorities), 4)  # the last two go to B_u
    batch = replay.sample(4, beta=0.0)  # β = 0: every draw weighs 1, the matrix counts draws
    prioritized = batch.from_prioritized
    assert prioritized.sum() <= 3 and (~prioritized).sum() == 2
    assert len(set(batch.keys[prioritized].tolist())) == prioritized.sum()  # distinct rows
    counts = batch.step_weights[prioritized]
    assert counts.sum() == 2 * 4  # round(ζB) = 2 items' worth of steps = 8 transitions
    assert np.all(batch.step_weights[~prioritized] == 1.0)  # uniform rows: every step once
    assert batch.steps_drawn == 8 + 2 * 4
    # Steps whose priority is (clamped) zero are (all but) never drawn.
    row_of = {key: row for row, key in enumerate(batch.keys[prioritized].tolist())}
    if 0 in row_of:
        assert counts[row_of[0], 1:].sum() == 0


def test_zeta_zero_bypasses_the_prioritized_buffer():
    replay = DualReplay(2, 100, zeta=0.0, seed=22)
    for priority in [5.0, 6.0, 1.0]:
        replay.insert(None, priority, 4)
    assert replay._prioritized_keys() == set() and replay._uniform_keys() == [0, 1, 2]
    assert set(sample_counts(replay, 50, 6)) == {(0, -1), (1, -1), (2, -1)}


def test_fifo_retention_displaces_the_oldest_and_samples_by_priority():
    replay = DualReplay(2, 100, zeta=1.0, seed=23, retention="fifo")
    a = replay.insert("a", 9.0, 1)
    b = replay.insert("b", 1.0, 1)
    c = replay.insert("c", 0.5, 1)  # lower than both, still enters: "a", the oldest, leaves
    assert replay._prioritized_keys() == {b, c} and replay._uniform_keys() == [a]
    assert_frequencies(sample_counts(replay, 500, 20), {(b, -1): 2 / 3, (c, -1): 1 / 3})
    batch = replay.sample(50, beta=1.0)
    np.testing.assert_allclose(batch.weights, np.where(batch.keys == c, 1.0, 0.5), rtol=1e-6)
    replay.update_priorities([b], [0.1])  # a priority update does not change who is oldest
    replay.insert("d", 0.2, 1)
    assert replay._prioritized_keys() == {c, 3}


# ------------------------------------------------------------------------ batch composition


def replay_with_both_buffers(zeta, seed=17):
    replay = DualReplay(2, 100, zeta=zeta, seed=seed)
    for priority in [5.0, 6.0, 1.0, 1.0, 1.0]:  # the last three go to B_u
        replay.insert(None, priority, 4)
    assert len(replay._prioritized_keys()) == 2 and len(replay._uniform_keys()) == 3
    return replay


@pytest.mark.parametrize(
    ("zeta", "batch_size"), [(0.2, 32), (0.2, 8), (0.25, 10), (0.5, 7), (1.0, 16)]
)
def test_batch_takes_round_zeta_b_from_prioritized(zeta, batch_size):
    replay = replay_with_both_buffers(zeta)
    batch = replay.sample(batch_size)
    assert batch.from_prioritized.sum() == round(zeta * batch_size)
    prioritized = replay._prioritized_keys()
    flags = batch.from_prioritized.tolist()
    assert [key in prioritized for key in batch.keys.tolist()] == flags
    assert np.all(batch.weights[~batch.from_prioritized] == 1.0)
    assert len(batch.items) == batch_size == batch.keys.size
    assert batch.step_weights is None and batch.steps_drawn == 4 * batch_size


def test_prioritized_fills_the_batch_when_uniform_is_empty():
    # B_p fills before anything reaches B_u, so "B_p empty, B_u not" happens only with ζ = 0
    # (then B_p is never used): B_u being empty is the other one-sided case.
    replay = DualReplay(4, 100, zeta=0.1, seed=18)
    replay.insert("x", 1.0, 4)
    batch = replay.sample(8)
    assert batch.from_prioritized.all()
    assert batch.items == ["x"] * 8


def test_empty_replay_refuses_to_sample():
    with pytest.raises(ValueError, match="empty"):
        DualReplay(4, 100).sample(8)


def test_same_seed_same_batches():
    def batches(seed):
        replay = replay_with_both_buffers(0.5, seed)
        return [replay.sample(8).keys.tolist() for _ in range(5)]

    assert batches(3) == batches(3)
    assert batches(3) != batches(4)


def test_none_mode_keeps_the_newest_and_samples_uniformly():
    replay = DualReplay(3, 100, zeta=1.0, seed=19, priority_mode="none")
    keys = [replay.insert(None, priority, 2) for priority in [50.0, 40.0, 30.0, 20.0, 10.0]]
    assert replay._prioritized_keys() == set(keys[2:])  # priorities ignored: newest stay
    assert replay._uniform_keys() == keys[:2]  # oldest first
    assert replay.stats()["displaced"] == 2
    assert np.all(replay.sample(30, beta=1.0).weights == 1.0)
    assert_frequencies(sample_counts(replay, 500, 30), {(key, -1): 1 / 3 for key in keys[2:]})
    assert replay.update_priorities(keys, [1.0] * 5) == 0
    assert replay.stats()["priority_mean"] == 0.0


# ------------------------------------------------------------------------ invariants vs a model


class ReferenceReplay:
    """The dual-buffer rules applied by brute force (lists and min() over everything).

    When B_p is full and several items share the lowest priority, either may be displaced:
    the model checks that the one the replay chose is a lowest one, then follows that choice.
    """

    def __init__(self, capacity, uniform_capacity_steps, mode, zeta=0.2):
        self.capacity = capacity
        self.zeta = zeta
        self.uniform_capacity_steps = uniform_capacity_steps
        self.mode = mode
        self.rank = {}  # B_p: key -> what membership compares
        self.unit_priorities = {}  # B_p: key -> clamped priority per sampling unit
        self.steps = {}  # every key -> num_steps
        self.uniform = []  # B_u keys, oldest first
        self.displaced = self.evicted = 0

    def clamp(self, priority):
        return np.maximum(np.asarray(priority, np.float64), MIN_PRIORITY)

    def rank_of(self, key, priority):
        if self.mode == "none":
            return float(key)
        return float(self.clamp(priority).sum())

    def insert(self, key, priority, num_steps, prioritized_after):
        self.steps[key] = num_steps
        rank = self.rank_of(key, priority)
        if self.zeta == 0.0:  # a plain replay: B_p is bypassed
            self.uniform.append(key)
        elif len(self.rank) < self.capacity:
            self.enter(key, priority, rank)
        elif rank > min(self.rank.values()):
            (gone,) = set(self.rank) - (prioritized_after - {key})
            assert self.rank[gone] == min(self.rank.values()), "displaced a non-lowest item"
            del self.rank[gone], self.unit_priorities[gone]
            self.uniform.append(gone)
            self.displaced += 1
            self.enter(key, priority, rank)
        else:
            self.uniform.append(key)
        while sum(self.steps[k] for k in self.uniform) > self.uniform_capacity_steps:
            self.uniform.pop(0)
            self.evicted += 1

    def enter(self, key, priority, rank):
        self.rank[key] = rank
        self.unit_priorities[key] = np.atleast_1d(self.clamp(priority))

    def update(self, keys, priorities):
        applied = 0
        for key, priority in zip(keys, priorities, strict=True):
            if key in self.rank and self.mode != "none":
                self.enter(key, priority, self.rank_of(key, priority))
                applied += 1
        return applied


def check_against(replay, model):
    prioritized, uniform = replay._prioritized_keys(), replay._uniform_keys()
    assert prioritized == set(model.rank)
    assert uniform == model.uniform
    assert not prioritized & set(uniform)
    assert len(replay) == len(prioritized) + len(uniform)
    stats = replay.stats()
    assert stats["prioritized_items"] == len(prioritized)
    assert stats["prioritized_steps"] == sum(model.steps[k] for k in prioritized)
    assert stats["uniform_items"] == len(uniform)
    assert stats["uniform_steps"] == sum(model.steps[k] for k in uniform)
    assert stats["uniform_steps"] <= model.uniform_capacity_steps
    assert stats["inserted"] == len(model.steps)
    assert stats["displaced"] == model.displaced
    assert stats["evicted"] == model.evicted
    if model.mode == "none" or not model.rank:
        assert stats["priority_min"] == stats["priority_max"] == stats["priority_mean"] == 0.0
    else:
        ranks = list(model.rank.values())
        assert stats["priority_min"] == min(ranks)
        assert stats["priority_max"] == max(ranks)
        assert stats["priority_mean"] == pytest.approx(np.mean(ranks), rel=1e-12)


def check_batch(batch, batch_size, beta, alpha, zeta, model):
    # B_p fills first, so B_u empty is the only one-sided case: B_p then fills the batch.
    expected_prioritized = round(zeta * batch_size) if model.uniform else batch_size
    if not model.rank:
        expected_prioritized = 0
    flags = batch.from_prioritized
    assert (~flags).sum() == batch_size - expected_prioritized
    assert all(key in model.rank for key in batch.keys[flags].tolist())
    assert all(key in model.uniform for key in batch.keys[~flags].tolist())
    assert np.all(batch.weights[~flags] == 1.0)
    assert batch.items == batch.keys.tolist()  # the tests store each item's key as the item
    if model.mode == "none":
        assert flags.sum() == expected_prioritized
        assert np.all(batch.weights == 1.0)
        return
    if not model.rank:
        return
    # The direct formula over every sampling unit in B_p: (P / P_min)^-β.
    smallest = min(p.min() for p in model.unit_priorities.values()) ** alpha
    if model.mode == "trajectory":
        assert flags.sum() == expected_prioritized and batch.step_weights is None
        for key, weight in zip(batch.keys[flags].tolist(), batch.weights[flags].tolist(),
                               strict=True):
            unit = model.unit_priorities[key][0]
            assert weight == pytest.approx((unit**alpha / smallest) ** (-beta), rel=1e-5)
            assert 0.0 < weight <= 1.0
        return
    # Step mode: distinct fragments, each step's entry a whole number of draws times that
    # step's weight; the draws add up to round(ζB) items' worth of steps.
    assert len(set(batch.keys[flags].tolist())) == flags.sum()
    uniform_rows = batch.step_weights[~flags]
    for row, key in zip(uniform_rows, batch.keys[~flags].tolist(), strict=True):
        assert np.all(row[:model.steps[key]] == 1.0) and np.all(row[model.steps[key]:] == 0.0)
    draws = 0
    for row, key in zip(batch.step_weights[flags], batch.keys[flags].tolist(), strict=True):
        assert np.all(row[model.steps[key]:] == 0.0)
        units = model.unit_priorities[key]
        for step, value in enumerate(row[:model.steps[key]].tolist()):
            weight = (units[step] ** alpha / smallest) ** (-beta)
            count = value / weight
            assert count == pytest.approx(round(count), abs=1e-3)
            draws += round(count)
    if expected_prioritized:
        mean_steps = sum(model.steps[k] for k in model.rank) / len(model.rank)
        assert draws == max(1, round(expected_prioritized * mean_steps))
    assert batch.steps_drawn == draws + sum(model.steps[k] for k in batch.keys[~flags].tolist())


priorities = st.one_of(
    st.sampled_from([0.0, 1e-7, 0.5, 1.0, 2.0]),  # ties, and values under the clamp
    st.floats(0.0, 10.0),
)
operations = st.lists(
    st.one_of(
        st.tuples(
            st.just("insert"), st.lists(priorities, min_size=6, max_size=6), st.integers(1, 6)
        ),
        st.tuples(st.just("sample"), st.integers(1, 9), st.sampled_from([0.0, 0.4, 1.0])),
        st.tuples(
            st.just("update"),
            st.lists(st.integers(0, 60), max_size=5),
            st.lists(st.lists(priorities, min_size=6, max_size=6), min_size=5, max_size=5),
        ),
    ),
    max_size=40,
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    mode=st.sampled_from(["trajectory", "step", "none"]),
    capacity=st.integers(1, 5),
    uniform_capacity_steps=st.integers(1, 16),
    zeta=st.sampled_from([0.0, 0.2, 0.5, 1.0]),
    alpha=st.sampled_from([0.0, 0.6, 1.0]),
    operations=operations,
)
def test_membership_displacement_and_fifo_follow_the_rules(
    mode, capacity, uniform_capacity_steps, zeta, alpha, operations
):
    replay = DualReplay(
        capacity, uniform_capacity_steps, zeta=zeta, alpha=alpha, seed=0, priority_mode=mode
    )
    model = ReferenceReplay(capacity, uniform_capacity_steps, mode, zeta)
    num_steps_of = {}  # key -> num_steps, the length a step-mode update for it must have
    for operation in operations:
        if operation[0] == "insert":
            _, drawn, num_steps = operation
            num_steps = min(num_steps, uniform_capacity_steps)
            priority = np.array(drawn[:num_steps]) if mode == "step" else drawn[0]
            key = len(model.steps)  # keys are 0, 1, 2, ...; each item is its own key
            assert replay.insert(key, priority, num_steps) == key
            num_steps_of[key] = num_steps
            model.insert(key, priority, num_steps, replay._prioritized_keys())
        elif operation[0] == "sample":
            _, batch_size, beta = operation
            if not model.steps:
                with pytest.raises(ValueError):
                    replay.sample(batch_size, beta)
                continue
            batch = replay.sample(batch_size, beta)
            check_batch(batch, batch_size, beta, alpha, zeta, model)
        else:
            _, keys, drawn = operation
            drawn = drawn[: len(keys)]
            if mode == "step":
                # Known keys get arrays of their own length; unknown keys any length.
                values = [
                    np.array(d[: num_steps_of.get(k, 3)]) for k, d in zip(keys, drawn, strict=True)
                ]
            else:
                values = [d[0] for d in drawn]
            assert replay.update_priorities(keys, values) == model.update(keys, values)
        check_against(replay, model)


@settings(max_examples=100, deadline=None)
@given(capacity=st.integers(1, 8), drawn=st.lists(priorities, min_size=1, max_size=40))
def test_prioritized_buffer_holds_a_top_n_of_everything_inserted(capacity, drawn):
    """Without updates, B_p is the top-N by priority; among equal priorities any choice is fine,
    so the check is that nothing outside B_p beats anything inside."""
    replay = DualReplay(capacity, 1000, seed=0)
    for priority in drawn:
        replay.insert(None, priority, 1)
    clamped = np.maximum(drawn, MIN_PRIORITY)
    inside = sorted(replay._prioritized_keys())
    outside = sorted(set(range(len(drawn))) - set(inside))
    assert len(inside) == min(capacity, len(drawn))
    if outside:
        assert clamped[inside].min() >= clamped[outside].max()


# ------------------------------------------------------------------------ argument errors


@pytest.mark.parametrize(
    ("kwargs", "fragments"),
    [
        ({"prioritized_capacity": 0}, ["prioritized_capacity", "0"]),
        ({"prioritized_capacity": 2.0}, ["prioritized_capacity", "2.0"]),
        ({"uniform_capacity_steps": -5}, ["uniform_capacity_steps", "-5"]),
        ({"zeta": 1.5}, ["zeta", "1.5"]),
        ({"zeta": float("nan")}, ["zeta", "nan"]),
        ({"alpha": -0.1}, ["alpha", "-0.1"]),
        ({"priority_mode": "episode"}, ["priority_mode", "'episode'"]),
        ({"min_priority": 0.0}, ["min_priority", "0.0"]),
        ({"seed": 1.5}, ["seed", "1.5"]),
    ],
)
def test_constructor_names_the_bad_argument(kwargs, fragments):
    arguments = {"prioritized_capacity": 4, "uniform_capacity_steps": 64} | kwargs
    with pytest.raises(ValueError) as error:
        DualReplay(**arguments)
    for fragment in fragments:
        assert fragment in str(error.value)


@pytest.mark.parametrize(
    ("mode", "priority", "num_steps", "fragments"),
    [
        ("trajectory", -1.0, 4, ["priority", "-1.0"]),
        ("trajectory", float("nan"), 4, ["priority", "nan"]),
        ("trajectory", float("inf"), 4, ["priority", "inf"]),
        ("trajectory", "high", 4, ["priority", "'high'"]),
        ("trajectory", 1.0, 0, ["num_steps", "0"]),
        ("trajectory", 1.0, 65, ["num_steps", "65", "64"]),
        ("trajectory", 1.0, 2.0, ["num_steps", "2.0"]),
        ("trajectory", 1.0, True, ["num_steps", "True"]),
        ("step", [1.0, 2.0], 3, ["priority", "num_steps=3", "(2,)"]),
        ("step", 1.0, 1, ["priority", "()"]),
        ("step", [1.0, -2.0], 2, ["priority", "-2."]),
    ],
)
def test_insert_names_the_bad_argument(mode, priority, num_steps, fragments):
    replay = DualReplay(4, 64, priority_mode=mode)
    with pytest.raises(ValueError) as error:
        replay.insert(None, priority, num_steps)
    for fragment in fragments:
        assert fragment in str(error.value)
    assert len(replay) == 0 and replay.stats()["inserted"] == 0


def test_priority_whose_power_overflows_is_refused():
    replay = DualReplay(4, 64, alpha=3.0)
    with pytest.raises(ValueError, match="alpha=3.0"):
        replay.insert(None, 1e200, 1)


def test_sample_and_update_name_the_bad_argument():
    replay = DualReplay(4, 64)
    replay.insert(None, 1.0, 1)
    with pytest.raises(ValueError, match="batch_size must be an integer >= 1, got 0"):
        replay.sample(0)
    with pytest.raises(ValueError, match=r"beta must be finite and in \[0.0, 1.0\], got 1.5"):
        replay.sample(4, beta=1.5)
    with pytest.raises(ValueError, match="beta.*-0.1"):
        replay.sample(4, beta=-0.1)
    with pytest.raises(ValueError, match="2 keys and 1 priorities"):
        replay.update_priorities([0, 1], [1.0])
    with pytest.raises(ValueError, match="keys"):
        replay.update_priorities([0.5], [1.0])
    with pytest.raises(ValueError, match=r"priorities\[0\]=-3.0"):
        replay.update_priorities([0], [-3.0])
    step_replay = DualReplay(4, 64, priority_mode="step")
    key = step_replay.insert(None, [1.0, 1.0], 2)
    with pytest.raises(ValueError, match=r"priorities\[0\] \(key 0\).*num_steps=2"):
        step_replay.update_priorities([key], [[1.0, 1.0, 1.0]])


@pytest.mark.parametrize("mode", ["trajectory", "step", "none"])
def test_state_dict_round_trip_continues_identically(mode):
    """A buffer rebuilt from its state samples, updates and evicts exactly like the original."""
    rng = np.random.default_rng(3)

    def priority(n):
        return rng.uniform(0.1, 5.0, n) if mode == "step" else float(rng.uniform(0.1, 5.0))

    original = DualReplay(8, 60, zeta=0.5, alpha=0.7, seed=11, priority_mode=mode)
    for i in range(30):
        original.insert(f"item{i}", priority(4), 4)
    original.sample(6, beta=0.5)
    original.update_priorities([25, 28, 3], [priority(4) for _ in range(3)]
                               if mode == "step" else [0.2, 9.0, 1.0])
    restored = DualReplay(8, 60, zeta=0.5, alpha=0.7, seed=999, priority_mode=mode)
    restored.load_state_dict(original.state_dict())
    assert restored.stats() == original.stats()
    for i in range(30, 45):
        p = priority(4)
        assert restored.insert(f"item{i}", p, 4) == original.insert(f"item{i}", p, 4)
        a, b = original.sample(5, beta=0.6), restored.sample(5, beta=0.6)
        assert a.items == b.items
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_allclose(a.weights, b.weights)
    assert restored.stats() == original.stats()
    assert restored._uniform_keys() == original._uniform_keys()


def test_load_state_dict_refuses_another_shape():
    state = DualReplay(8, 60).state_dict()
    with pytest.raises(ValueError, match="prioritized_capacity=8"):
        DualReplay(16, 60).load_state_dict(state)
    used = DualReplay(8, 60)
    used.insert("x", 1.0, 4)
    with pytest.raises(ValueError, match="empty"):
        used.load_state_dict(state)


@pytest.mark.parametrize("damage, match", [
    (lambda s: s.update(slots=np.array([0, 0])), "distinct slots"),
    (lambda s: s.update(slots=np.array([0, 99])), "below the capacity 8"),
    (lambda s: s.update(slot_mass=s["slot_mass"][:1]), "slot_mass has 1 entries for 2"),
    (lambda s: s.update(slot_steps=np.array([4, 0])), "slot_steps must be > 0"),
    (lambda s: s["uniform"].append((1, "y")), "2 fields, not 3"),
])
def test_load_state_dict_refuses_an_inconsistent_state(damage, match):
    """A saved state read from a run dir is checked before any of it lands in the buffer."""
    original = DualReplay(8, 60)
    for i in range(2):
        original.insert(f"item{i}", 1.0 + i, 4)
    state = original.state_dict()
    damage(state)
    with pytest.raises(ValueError, match=match):
        DualReplay(8, 60).load_state_dict(state)
