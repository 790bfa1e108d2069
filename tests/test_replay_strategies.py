"""The replay's strategies one by one — samplers, removers, the two buffers, the priority index —
against brute force and exact probabilities, then their compositions (DESIGN §2)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats as scipy_stats

from tpdeb.services.config import resolve
from tpdeb.services.config.train import ALGOS, TrainConfig
from tpdeb.tpdeb_core.replay import (
    COMPOSITIONS,
    PRIORITY_MODES,
    RETENTIONS,
    DualReplay,
    ReplaySample,
    impact,
    ppo_per,
    tpdeb,
)
from tpdeb.tpdeb_core.replay_buffers import Entry, PrioritizedBuffer, UniformFifo
from tpdeb.tpdeb_core.replay_removers import LowestPriorityRemover, OldestRemover
from tpdeb.tpdeb_core.replay_samplers import StepSampler, TrajectorySampler, UniformSampler
from tpdeb.tpdeb_core.sumtree import PriorityIndex

P_VALUE_FLOOR = 1e-4  # by chance once in 10^4 runs; the seeds are fixed anyway


def assert_frequencies(counts, probabilities):
    """Chi-square goodness of fit of `counts` (cell -> n) to exact `probabilities`."""
    assert set(counts) <= set(probabilities), "drew something with probability 0"
    cells = sorted(probabilities)
    observed = np.array([counts.get(cell, 0) for cell in cells], dtype=np.float64)
    expected = np.array([probabilities[cell] for cell in cells]) * observed.sum()
    assert scipy_stats.chisquare(observed, expected)[1] > P_VALUE_FLOOR, (observed, expected)


def filled(sampler, priorities, num_steps=1):
    """`sampler` with one slot per priority, and the index a buffer would keep beside it."""
    index = PriorityIndex(sampler.capacity)
    for slot, priority in enumerate(priorities):
        leaf = sampler.leaf(priority, num_steps)
        sampler.set(slot, leaf)
        index.set(slot, leaf.priority)
    return sampler, index


# ------------------------------------------------------------------------ the priority index


@settings(max_examples=60, deadline=None)
@given(writes=st.lists(st.tuples(st.integers(0, 9), st.floats(0.0, 50.0), st.booleans(),
                                 st.booleans()), min_size=1, max_size=40),
       flush_slots=st.sampled_from([1, 3, PriorityIndex.FLUSH_SLOTS]))
def test_priority_index_matches_brute_force(writes, flush_slots):
    """Min, max and sum as over a plain dict, whenever they are read (the max and sum trees
    catch up on reads and every `flush_slots` written slots)."""
    index, values = PriorityIndex(10), {}
    index.FLUSH_SLOTS = flush_slots
    for slot, value, batched, read in writes:
        if batched:
            index.set_many(np.array([slot, slot]), np.array([value + 1.0, value]))  # last wins
        else:
            index.set(slot, value)
        values[slot] = value
        if read:
            assert index.min() == min(values.values()) == values[index.argmin()]
            assert index.max() == max(values.values())
            assert index.total() == pytest.approx(sum(values.values()), rel=1e-12, abs=1e-300)
    assert index.min() == min(values.values()) == values[index.argmin()]
    assert index.max() == max(values.values())
    assert index.total() == pytest.approx(sum(values.values()), rel=1e-12, abs=1e-300)
    assert index.get(np.array(sorted(values))).tolist() == [values[s] for s in sorted(values)]


# ------------------------------------------------------------------------ samplers


@pytest.mark.parametrize("alpha", [1.0, 0.5])
def test_trajectory_sampler_draws_proportional_to_priority_power_alpha(alpha):
    priorities = np.array([0.1, 0.5, 1.0, 3.0, 6.0])
    sampler, index = filled(TrajectorySampler(5, alpha), priorities)
    rng = np.random.default_rng(0)
    counts = {}
    for _ in range(400):
        for slot in sampler.sample(50, 1.0, rng, index).slots.tolist():
            counts[slot] = counts.get(slot, 0) + 1
    mass = priorities**alpha
    assert_frequencies(counts, dict(enumerate(mass / mass.sum())))


def test_trajectory_sampler_weights_are_p_over_p_min_to_minus_alpha_beta():
    alpha, beta = 0.7, 0.6
    priorities = np.array([0.25, 1.0, 4.0])
    sampler, index = filled(TrajectorySampler(3, alpha), priorities)
    draw = sampler.sample(300, beta, np.random.default_rng(1), index)
    probabilities = priorities**alpha / np.sum(priorities**alpha)
    expected = (3 * probabilities) ** (-beta) / (3 * probabilities.min()) ** (-beta)
    np.testing.assert_allclose(draw.weights, expected[draw.slots], rtol=1e-12)
    assert draw.step_weights is None and draw.steps_drawn is None


def test_trajectory_sampler_validates_a_whole_update_before_returning():
    sampler = TrajectorySampler(4, alpha=2.0)
    with pytest.raises(ValueError, match=r"priorities\[2\]=-1.0"):
        sampler.update_leaves([0, 1, 2], [1.0, 2.0, -1.0], [1, None, 1])
    with pytest.raises(ValueError, match=r"priorities\[1\]=1e\+300 with alpha=2.0"):
        sampler.update_leaves([0, 1], [1.0, 1e300], [1, 1])
    leaves = sampler.update_leaves([5, 6, 7], [0.0, 3.0, 2.0], [1, None, 1])  # 6 is stale
    np.testing.assert_array_equal(leaves.priority, [1e-6, 2.0])
    np.testing.assert_array_equal(leaves.mass, [1e-12, 4.0])


def test_step_sampler_draws_fragment_then_step_and_weighs_each_draw():
    alpha, beta = 0.8, 0.5
    per_step = [np.array([1.0, 2.0, 0.0]), np.array([3.0, 0.5, 1.5])]
    sampler, _ = filled(StepSampler(2, alpha), per_step, num_steps=3)
    slots, steps, weights = sampler.draw_steps(60_000, beta, np.random.default_rng(2))
    masses = np.maximum(np.concatenate(per_step), 1e-6) ** alpha
    counts = {}
    for cell in (slots * 3 + steps).tolist():
        counts[cell] = counts.get(cell, 0) + 1
    assert_frequencies(counts, dict(enumerate(masses / masses.sum())))
    np.testing.assert_allclose(weights, (masses[slots * 3 + steps] / masses.min()) ** (-beta))


def test_step_sampler_groups_t_draws_per_item_by_fragment():
    sampler, _ = filled(StepSampler(3), [[1.0] * 4, [2.0] * 4, [4.0] * 4], num_steps=4)
    draw = sampler.sample(2, 0.0, np.random.default_rng(3))
    assert draw.steps_drawn == 8 and draw.step_weights.sum() == 8  # β = 0: counts
    assert len(set(draw.slots.tolist())) == draw.slots.size
    np.testing.assert_array_equal(draw.weights, 1.0)


def test_step_sampler_refuses_arrays_of_the_wrong_length():
    sampler, _ = filled(StepSampler(2), [[1.0, 1.0]], num_steps=2)
    with pytest.raises(ValueError, match=r"priorities\[0\] \(key 7\).*num_steps=2"):
        sampler.update_leaves([7], [[1.0, 1.0, 1.0]], [2])
    # a stale key's array may be any length, but must still be priorities
    assert sampler.update_leaves([8], [[1.0, 1.0, 1.0]], [None]).mass.size == 0
    with pytest.raises(ValueError, match="finite"):
        sampler.update_leaves([8], [[1.0, np.nan]], [None])


def test_uniform_sampler_ignores_priorities_and_draws_every_item_alike():
    sampler = UniformSampler(4)
    for slot in (2, 0, 3):
        sampler.set(slot, sampler.leaf("anything", 1))
    counts = {}
    rng = np.random.default_rng(4)
    for _ in range(300):
        draw = sampler.sample(20, 1.0, rng)
        assert np.all(draw.weights == 1.0)
        for slot in draw.slots.tolist():
            counts[slot] = counts.get(slot, 0) + 1
    assert_frequencies(counts, {0: 1 / 3, 2: 1 / 3, 3: 1 / 3})


# ------------------------------------------------------------------------ removers


def test_lowest_priority_remover_admits_only_a_higher_priority():
    index = PriorityIndex(3)
    index.set_many(np.arange(3), np.array([2.0, 0.5, 0.5]))
    remover = LowestPriorityRemover()
    assert remover.victim(0.5, index) is None  # a tie keeps the incumbent
    assert remover.victim(0.4, index) is None
    assert remover.victim(0.6, index) == 1  # the leftmost lowest


def test_oldest_remover_follows_insertion_order_whatever_the_priorities():
    remover = OldestRemover()
    for slot in (0, 1, 2):
        remover.inserted(slot)
    assert remover.victim(100.0, None) == 0 and remover.victim(0.0, None) == 0
    remover.removed(0)
    remover.inserted(0)  # the newcomer takes the freed slot and is the newest
    assert remover.victim(1.0, None) == 1
    with pytest.raises(ValueError, match="not the oldest"):
        remover.removed(2)
    remover.load(np.array([5, 3, 4]), np.array([20, 10, 30]))  # smallest key: oldest
    assert remover.victim(1.0, None) == 3


# ------------------------------------------------------------------------ the buffers


def test_uniform_fifo_keeps_the_newest_within_its_step_budget():
    fifo = UniformFifo(10)
    evicted = 0
    for key, steps in enumerate([4, 4, 4, 1, 5]):
        fifo.append(Entry(key, f"item{key}", steps))
        evicted += fifo.evict()
    assert [entry.key for entry in fifo.entries()] == [2, 3, 4]
    assert fifo.steps == 10 and evicted == 2 and len(fifo) == 3
    drawn = [entry.key for entry in fifo.sample(3000, np.random.default_rng(5))]
    assert_frequencies({k: drawn.count(k) for k in set(drawn)}, {2: 1 / 3, 3: 1 / 3, 4: 1 / 3})


def test_prioritized_buffer_hands_back_what_goes_to_the_uniform_buffer():
    buffer = PrioritizedBuffer(TrajectorySampler(2), LowestPriorityRemover())
    offer = lambda key, p: buffer.offer(Entry(key, key, 1), buffer.sampler.leaf(p, 1))  # noqa: E731
    assert offer(0, 1.0) is None and offer(1, 3.0) is None  # room
    assert offer(2, 0.5).key == 2  # refused: the newcomer itself
    assert offer(3, 2.0).key == 0  # displaced: the lowest
    assert buffer.keys() == {1, 3} and buffer.priority_summary() == (2.0, 3.0, 2.5)


def test_a_remover_that_needs_priorities_is_refused_without_them():
    with pytest.raises(ValueError, match="UniformSampler has none: use OldestRemover"):
        PrioritizedBuffer(UniformSampler(2), LowestPriorityRemover())


# ------------------------------------------------------------------------ fixed defects


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_fifo_retention_reports_priorities_not_keys(alpha):
    replay = DualReplay(3, 100, zeta=1.0, alpha=alpha, retention="fifo", seed=0)
    for priority in [7.0, 1.0, 2.0, 4.0]:  # the 7.0 gives way: it is the oldest
        replay.insert(None, priority, 1)
    stats = replay.stats()
    assert (stats["priority_min"], stats["priority_max"]) == (1.0, 4.0)
    assert stats["priority_mean"] == pytest.approx(7.0 / 3)
    step = DualReplay(2, 100, zeta=1.0, alpha=alpha, retention="fifo", priority_mode="step")
    step.insert(None, [1.0, 2.0], 2)
    step.insert(None, [0.5, 0.5], 2)
    assert (step.stats()["priority_min"], step.stats()["priority_max"]) == (1.0, 3.0)


def test_fifo_p_min_follows_the_items_that_stay():
    """P_min is the index's minimum: when the lowest item leaves by age the weights move."""
    replay = DualReplay(2, 100, zeta=1.0, alpha=1.0, retention="fifo", seed=1)
    low = replay.insert("low", 0.5, 1)
    replay.insert("mid", 1.0, 1)
    batch = replay.sample(50, beta=1.0)
    np.testing.assert_allclose(batch.weights, np.where(batch.keys == low, 1.0, 0.5))
    replay.insert("high", 4.0, 1)  # "low", the oldest, leaves
    batch = replay.sample(50, beta=1.0)
    np.testing.assert_allclose(batch.weights, np.where(batch.items == np.array("mid"),
                                                       1.0, 0.25))


# ------------------------------------------------------------------------ compositions


def insert_and_sample(replay, seed=0, mode="trajectory"):
    rng = np.random.default_rng(seed)
    for key in range(12):
        priority = rng.uniform(0.1, 3.0, 4) if mode == "step" else float(rng.uniform(0.1, 3))
        replay.insert(key, priority, 4)
    batches = [replay.sample(6, beta=0.5) for _ in range(4)]
    return replay, batches


def same_batches(first: list[ReplaySample], second: list[ReplaySample]) -> bool:
    return all(a.items == b.items and np.array_equal(a.weights, b.weights)
               for a, b in zip(first, second, strict=True))


@pytest.mark.parametrize("mode", PRIORITY_MODES)
@pytest.mark.parametrize("retention", RETENTIONS)
def test_compose_from_objects_is_the_constructor(mode, retention):
    kind = {"trajectory": TrajectorySampler, "step": StepSampler}.get(mode)
    sampler = UniformSampler(3) if kind is None else kind(3, alpha=0.7)
    remover = OldestRemover() if retention == "fifo" or kind is None else LowestPriorityRemover()
    built = DualReplay(3, 24, zeta=0.5, alpha=0.7, seed=4, priority_mode=mode,
                       retention=retention)
    composed = DualReplay.compose(sampler, remover, 24, zeta=0.5, seed=4)
    assert (built.sampler.name, built.remover.name) == (sampler.name, remover.name)
    _, expected = insert_and_sample(built, mode=mode)
    _, got = insert_and_sample(composed, mode=mode)
    assert same_batches(expected, got)


def test_the_named_compositions():
    replay, _ = insert_and_sample(tpdeb(4, 64, zeta=0.5, seed=0))
    assert (replay.sampler.name, replay.remover.name, replay.zeta) == (
        "trajectory", "lowest_priority", 0.5)
    replay, _ = insert_and_sample(impact(32, seed=0))
    assert replay._prioritized_keys() == set() and replay._uniform_keys() == list(range(4, 12))
    replay, batches = insert_and_sample(ppo_per(3, 4, seed=0), mode="step")
    assert replay._prioritized_keys() == {9, 10, 11}  # the newest three, whatever their priority
    assert all(batch.from_prioritized.all() and batch.step_weights is not None
               for batch in batches)


@pytest.mark.parametrize("algo", ALGOS)
def test_each_algorithms_settings_build_its_composition(algo):
    """presets.ALGORITHMS sets the constructor's settings; they give the same replay as the
    algorithm's named composition (IMPACT's B_p is bypassed, whatever it would sample by)."""
    config = resolve(TrainConfig, ["--algo", algo, "--env-id", "InvertedPendulum-v5",
                                   "--preset", "none"], "test", "test")
    built = config.make_replay()
    named = {"tpdeb": lambda: tpdeb(config.prioritized_capacity, config.uniform_capacity_steps,
                                    config.zeta, config.alpha, config.seed),
             "impact": lambda: impact(config.uniform_capacity_steps, config.seed),
             "ppo-per": lambda: ppo_per(config.prioritized_capacity,
                                        config.uniform_capacity_steps, config.alpha,
                                        config.seed)}[algo]()
    assert set(COMPOSITIONS) == set(ALGOS)
    assert built.zeta == named.zeta
    if algo != "impact":
        assert (built.sampler.name, built.remover.name) == (named.sampler.name,
                                                            named.remover.name)
    mode = "step" if algo == "ppo-per" else "trajectory"
    _, expected = insert_and_sample(built, mode=mode)
    _, got = insert_and_sample(named, mode=mode)
    assert same_batches(expected, got)


# ------------------------------------------------------------------------ saved state


@pytest.mark.parametrize("mode", ["trajectory", "step"])
def test_fifo_state_round_trip_continues_identically(mode):
    original, _ = insert_and_sample(
        DualReplay(3, 24, zeta=0.5, seed=6, priority_mode=mode, retention="fifo"), mode=mode)
    restored = DualReplay(3, 24, zeta=0.5, seed=0, priority_mode=mode, retention="fifo")
    restored.load_state_dict(original.state_dict())
    assert restored.stats() == original.stats()
    _, expected = insert_and_sample(original, seed=1, mode=mode)
    _, got = insert_and_sample(restored, seed=1, mode=mode)
    assert same_batches(expected, got) and restored.stats() == original.stats()


def format_1_state(replay, retention):
    """What the replay before the strategies saved: no format, a "rank" per slot."""
    state = replay.state_dict()
    del state["format"]
    config = state["config"]
    config.update(priority_mode=config.pop("sampler"), retention=retention)
    del config["remover"]
    rank = state.pop("slot_priority")
    state["slot_rank"] = state["slot_keys"].astype(float) if retention == "fifo" else rank
    return state


def test_a_format_1_state_loads_where_its_priorities_survive():
    original, _ = insert_and_sample(DualReplay(3, 24, zeta=0.5, seed=7))
    restored = DualReplay(3, 24, zeta=0.5, seed=0)
    restored.load_state_dict(format_1_state(original, "priority"))
    assert restored.stats() == original.stats()
    assert same_batches([original.sample(5)], [restored.sample(5)])


def test_a_format_1_fifo_state_or_an_unknown_format_is_refused_with_the_reason():
    original, _ = insert_and_sample(DualReplay(3, 24, retention="fifo"))
    with pytest.raises(ValueError, match="format 1 with retention='fifo'.*priorities are lost"):
        DualReplay(3, 24, retention="fifo").load_state_dict(format_1_state(original, "fifo"))
    state = original.state_dict() | {"format": 9}
    with pytest.raises(ValueError, match="format 9, this version reads 2"):
        DualReplay(3, 24, retention="fifo").load_state_dict(state)


def test_a_state_of_another_composition_is_refused():
    state = DualReplay(3, 24, retention="fifo").state_dict()
    with pytest.raises(ValueError, match="remover='oldest', this one 'lowest_priority'"):
        DualReplay(3, 24).load_state_dict(state)
