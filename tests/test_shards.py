"""Replay shards: a batch split over K replays is the batch one replay of their union would draw."""

import contextlib
import dataclasses
import threading
import time

import numpy as np
import pytest
import torch

from tests.test_protocol import ACT_DIM, OBS_DIM, T, make_traj
from tpdeb.protocol import DecodeError, Keys, Moments, SampleReply, SampleRequest, decode, encode
from tpdeb.protocol.keys import ANY_SHARD
from tpdeb.services.cluster import Cluster, parse_args
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import LearnerServiceConfig, ReplayServiceConfig
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.launcher.plan import make_plan
from tpdeb.services.learner import LearnerService
from tpdeb.services.net.memory import MemoryBus
from tpdeb.services.net.wire import run_spec
from tpdeb.services.process import StopSignal
from tpdeb.services.replay import ReplayServer
from tpdeb.services.serial import SerialRunner
from tpdeb.services.shards import Gathered, ShardSet
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.replay import DualReplay, ppo_per
from tpdeb.tpdeb_core.shards import (
    ShardView,
    global_min_mass,
    global_weights,
    shard_of,
    split_batch,
)

ALPHA, BETA, ZETA = 0.7, 0.4, 0.5


def sharded(shards: int, priorities: list[float], uniform_items: int = 0):
    """K TPDEB replays holding `priorities` round-robin in their B_p (shard k the k-th, K+k-th,
    …), each with `uniform_items` more in B_u (lower than every B_p priority, so B_p, sized to
    its items, keeps them out)."""
    per_shard = [priorities[k::shards] for k in range(shards)]
    replays = []
    for k, prios in enumerate(per_shard):
        replay = DualReplay(prioritized_capacity=max(len(prios), 1), uniform_capacity_steps=10**6,
                            zeta=ZETA, alpha=ALPHA, seed=100 + k)
        for j, p in enumerate(prios):
            replay.insert(("p", k, j), p, num_steps=4)
        for j in range(uniform_items):  # lower than every B_p priority: straight to B_u
            replay.insert(("u", k, j), 1e-9, num_steps=4)
        replays.append(replay)
    return replays


def test_shard_of_spreads_ids_evenly_and_refuses_bad_input():
    assert [shard_of(i, 3) for i in range(7)] == [0, 1, 2, 0, 1, 2, 0]
    assert shard_of(5, 1) == 0
    with pytest.raises(ValueError, match="shards"):
        shard_of(1, 0)
    with pytest.raises(ValueError, match="actor_id"):
        shard_of(-1, 2)


def test_split_follows_the_union_rules():
    rng = np.random.default_rng(0)
    views = [ShardView(3, 5, 2.0, 0.1), None, ShardView(0, 0, 0.0, 0.0), ShardView(1, 5, 6.0, 1.0)]
    counts = split_batch(64, 0.25, views, rng)
    assert counts.shape == (4, 2) and counts.sum() == 64
    assert counts[:, 0].sum() == 16  # round(ζB) from the B_p's
    assert not counts[1].any() and not counts[2].any()  # down, and empty: no share
    # B_p empty on every live shard: B_u gives the whole batch; and the other way round
    only_u = split_batch(8, 0.5, [ShardView(0, 4, 0.0, 0.0), ShardView(0, 2, 0.0, 0.0)], rng)
    assert only_u[:, 0].sum() == 0 and only_u.sum() == 8
    only_p = split_batch(8, 0.5, [ShardView(2, 0, 1.0, 0.5), None], rng)
    assert only_p.tolist() == [[8, 0], [0, 0]]
    assert not split_batch(8, 0.5, [None, ShardView(0, 0, 0.0, 0.0)], rng).any()
    with pytest.raises(ValueError, match="zeta"):
        split_batch(8, 1.5, views, rng)


def test_split_shares_go_by_mass_and_by_item_count():
    rng = np.random.default_rng(1)
    views = [ShardView(10, 30, 1.0, 0.1), ShardView(10, 10, 3.0, 0.1)]
    totals = sum(split_batch(100, 0.5, views, rng) for _ in range(2000))
    p_share = totals[:, 0] / totals[:, 0].sum()
    u_share = totals[:, 1] / totals[:, 1].sum()
    assert p_share == pytest.approx([0.25, 0.75], abs=0.01)  # by B_p mass
    assert u_share == pytest.approx([0.75, 0.25], abs=0.01)  # by B_u items


def draw_union(replays, batch_size, rng, views=None):
    """One batch from the shards as a learner draws it: (shard, item, weight, from B_p) rows,
    the weights rescaled to the union's P_min."""
    views = views if views is not None else [r.view() for r in replays]
    counts = split_batch(batch_size, ZETA, views, rng)
    union_min = global_min_mass([v.min_mass for v in views if v is not None])
    rows = []
    for k, (num_p, num_u) in enumerate(counts):
        if num_p + num_u == 0:
            continue
        batch = replays[k].sample(int(num_p + num_u), BETA, num_prioritized=int(num_p))
        weights = np.where(batch.from_prioritized,
                           global_weights(batch.weights, views[k].min_mass, union_min, BETA),
                           batch.weights)
        rows += [(k, item, float(w), bool(fp)) for item, w, fp in
                 zip(batch.items, weights, batch.from_prioritized, strict=True)]
    return rows


def test_sharded_draws_are_the_union_replays_draws():
    """Each B_p item is drawn with probability p^α / Σ_union p^α, and weighs (p / p_min)^(−αβ)
    with the union's p_min — exactly what one replay holding every item gives."""
    rng = np.random.default_rng(7)
    priorities = list(np.random.default_rng(3).uniform(0.05, 3.0, size=12))
    replays = sharded(3, priorities, uniform_items=5)
    masses = np.array(priorities) ** ALPHA
    expected = masses / masses.sum()
    p_min = min(priorities)
    hits = np.zeros(len(priorities))
    uniform_hits = 0
    for _ in range(3000):
        for k, item, weight, from_p in draw_union(replays, 32, rng):
            if not from_p:
                assert item[0] == "u" and weight == 1.0
                uniform_hits += 1
                continue
            index = item[2] * 3 + k  # round-robin: shard k holds priorities[k::3]
            hits[index] += 1
            assert weight == pytest.approx((priorities[index] / p_min) ** (-ALPHA * BETA),
                                           rel=1e-5)
    assert hits.sum() == 3000 * 16 and uniform_hits == 3000 * 16
    assert hits / hits.sum() == pytest.approx(expected, abs=0.005)
    # the one replay of the union, for comparison: the same probabilities
    union = DualReplay(prioritized_capacity=12, uniform_capacity_steps=10**6, zeta=ZETA,
                       alpha=ALPHA, seed=5)
    for i, p in enumerate(priorities):
        union.insert(i, p, num_steps=4)
    union_hits = np.zeros(12)
    for _ in range(1500):
        batch = union.sample(32, BETA)
        np.add.at(union_hits, np.array(batch.items), 1)
    assert union_hits / union_hits.sum() == pytest.approx(expected, abs=0.005)


def test_a_down_shard_leaves_the_live_ones_in_proportion_among_them():
    rng = np.random.default_rng(11)
    priorities = [0.5, 1.0, 2.0, 0.25, 4.0, 1.5]
    replays = sharded(2, priorities)
    views = [replays[0].view(), None]  # shard 1 down: its items are not drawn
    live = np.array(priorities[0::2]) ** ALPHA
    hits = np.zeros(3)
    for _ in range(3000):
        for k, item, _, _ in draw_union(replays, 16, rng, views):
            assert k == 0
            hits[item[2]] += 1
    assert hits / hits.sum() == pytest.approx(live / live.sum(), abs=0.01)


def test_view_says_what_the_replay_holds():
    replay = DualReplay(prioritized_capacity=2, uniform_capacity_steps=100, zeta=0.5, alpha=0.5)
    assert replay.view() == ShardView(0, 0, 0.0, 0.0)
    for p in (4.0, 1.0, 9.0):  # the third displaces 1.0 into B_u
        replay.insert(object(), p, num_steps=3)
    view = replay.view()
    assert (view.prioritized, view.uniform) == (2, 1)
    assert view.mass == pytest.approx(4.0**0.5 + 9.0**0.5)
    assert view.min_mass == pytest.approx(2.0)
    steps = ppo_per(prioritized_capacity=4, uniform_capacity_steps=100, alpha=1.0)
    steps.insert(object(), np.array([0.5, 2.0]), num_steps=2)
    steps.insert(object(), np.array([1.0, 0.25]), num_steps=2)
    assert steps.view() == ShardView(2, 0, pytest.approx(3.75), pytest.approx(0.25))
    plain = DualReplay(prioritized_capacity=4, uniform_capacity_steps=100, zeta=0.5,
                       priority_mode="none", retention="fifo")
    plain.insert(object(), 1.0, num_steps=2)
    assert plain.view() == ShardView(1, 0, 1.0, 1.0)


def test_sample_takes_the_callers_split_and_falls_back_like_round_zeta():
    replay = DualReplay(prioritized_capacity=4, uniform_capacity_steps=100, zeta=0.5, seed=1)
    for p in (1.0, 2.0, 3.0, 4.0):
        replay.insert(object(), p, num_steps=2)
    assert replay.sample(6, num_prioritized=6).from_prioritized.all()  # B_u empty: all from B_p
    for p in (0.1, 0.2):  # two low ones: straight to B_u
        replay.insert(object(), p, num_steps=2)
    batch = replay.sample(6, num_prioritized=1)
    assert batch.from_prioritized.tolist() == [True] + [False] * 5
    assert not replay.sample(3, num_prioritized=0).from_prioritized.any()
    with pytest.raises(ValueError, match="more than the batch"):
        replay.sample(3, num_prioritized=4)
    with pytest.raises(ValueError, match="num_prioritized"):
        replay.sample(3, num_prioritized=-1)


def test_weights_rescale_refuses_an_impossible_pmin():
    with pytest.raises(ValueError, match="P_min"):
        global_weights(np.ones(2), 0.5, 0.6, 0.4)
    with pytest.raises(ValueError, match="no shard"):
        global_min_mass([0.0, 0.0])
    assert global_weights(np.ones(2, np.float32), 0.5, 0.5, 0.4).dtype == np.float32


# --- the learner's side: ShardSet (services/shards.py) --------------------------------------------

def shard_reply(replay: DualReplay, shard_items: dict, num_p: int, num_u: int, inserted: int,
                moments: Moments | None = None) -> SampleReply:
    """What a replay shard answers (as services/replay.py builds it): its draw, stacked."""
    sample = replay.sample(num_p + num_u, BETA, num_prioritized=num_p)
    view = replay.view()
    return SampleReply(
        request_id=1, ready=True, keys=sample.keys.astype(np.int64),
        weights=sample.weights.astype(np.float32),
        from_prioritized=sample.from_prioritized.astype(bool), step_weights=None,
        batch=stack_fragments([shard_items[key] for key in sample.keys.tolist()]),
        inserted_steps=inserted, obs_moments=moments, ret_moments=None, reason="",
        prioritized_items=view.prioritized, uniform_items=view.uniform, mass=view.mass,
        min_mass=view.min_mass)


def test_a_shard_set_probes_splits_and_leaves_out_what_is_down():
    now = [0.0]
    shards = ShardSet(3, ZETA, seed=0, retry_s=5.0, clock=lambda: now[0])
    first = shards.plan(8)  # nothing known: every shard probed, the batch shared evenly
    assert first[:, 0].sum() == 0 and sorted(first[:, 1].tolist()) == [2, 3, 3]
    empty = SampleReply.not_ready(1, "rate limiter", 0, (0, 0, 0.0, 0.0))
    shards.heard(0, SampleReply.not_ready(1, "rate limiter", 40, (4, 2, 2.0, 0.5)))
    shards.heard(1, empty)
    shards.missed(2, waited_s=30.0)  # its query timed out: left out for retry_s
    plan = shards.plan(8)
    assert plan[0].sum() == 8 and not plan[1:].any()  # 1 empty, 2 down
    assert shards.down() == [2] and shards.inserted_steps == 40
    now[0] = 6.0  # shard 2's retry, and shard 1 (empty) asked again: one B_u row each
    plan = shards.plan(8)
    assert plan[1].tolist() == plan[2].tolist() == [0, 1] and plan[0].sum() == 6
    assert shards.plan(4, among=[1]).sum() == 0  # probed just now: not again at once
    shards.gone(0)  # its token went: left out until it is back
    assert shards.plan(4).sum() == 0 and 0 in shards.down()
    shards.back(0)
    now[0] = 7.5  # every shard unknown or empty, probed: the batch shared among them
    plan = shards.plan(4)
    assert plan[:, 0].sum() == 0 and plan.sum() == 4 and (plan[:, 1] >= 1).all()
    with pytest.raises(ValueError, match="2 or more"):
        ShardSet(1, ZETA, seed=0)


def test_a_shard_that_answered_nothing_at_once_is_asked_again_soon():
    """No reply at once (the routes to it being remade after the router came back) is not a
    shard that hangs: left out for probe_s, not for the request timeout."""
    now = [0.0]
    shards = ShardSet(2, ZETA, seed=0, retry_s=30.0, probe_s=1.0, clock=lambda: now[0])
    assert shards.missed(0, waited_s=0.004) == 1.0
    assert shards.missed(1, waited_s=12.0) == 12.0
    assert shards.missed(1, waited_s=0.01) is None  # already out (for longer): news to no one
    assert shards.down() == [0, 1] and shards.plan(8).sum() == 0
    now[0] = 1.5
    assert shards.down() == [1] and shards.plan(8)[0].tolist() == [0, 8]
    shards.back(1)  # its token came back (the router's lease renewed): asked again at once
    assert shards.down() == []


def test_a_query_is_timed_by_its_own_end_not_by_the_replies_read_before_it():
    """Shard 1's query ended at once with nothing; shard 0's, read first, timed out later. Read
    in that order, shard 1 is charged its own (short) wait, not shard 0's."""
    now = [0.0]
    first, second = Gathered(clock=lambda: now[0]), Gathered(clock=lambda: now[0])
    second.end()  # nothing at once: its handler dropped at 0.0
    now[0] = 12.0
    first.add("late")
    first.end()
    assert first.wait(10.0) == ["late"] and first.ended_at == 12.0
    assert second.wait(10.0) == [] and second.ended_at == 0.0
    hung = Gathered(clock=lambda: now[0])  # never ended: counts as ended when the wait gives up
    assert hung.wait(0.0) == [] and hung.ended_at == 12.0


def test_joined_replies_are_one_batch_with_global_keys_weights_and_moments():
    priorities = [0.5, 2.0, 1.0, 4.0, 0.25, 3.0]
    replays = sharded(2, priorities, uniform_items=2)
    items = [{}, {}]  # each shard's key → its fragment
    for k, replay in enumerate(replays):
        for key in range(len(replay)):
            items[k][key] = make_traj(seed=10 * k + key)
    shards = ShardSet(2, ZETA, seed=0)
    obs = [Moments(4.0, np.ones(OBS_DIM), np.full(OBS_DIM, 2.0)),
           Moments(2.0, np.zeros(OBS_DIM), np.ones(OBS_DIM))]
    replies = [(k, shard_reply(replays[k], items[k], 2, 1, 100 * (k + 1), obs[k]))
               for k in (0, 1)]
    for k, reply in replies:
        shards.heard(k, reply)
    joined = shards.join(replies, BETA)
    assert joined.batch.obs.shape == (T + 1, 6, OBS_DIM) and joined.inserted_steps == 300
    routes = shards.route(joined.keys)
    for k, (positions, own_keys) in routes.items():
        np.testing.assert_array_equal(own_keys, replies[k][1].keys)
        for column, key in zip(positions.tolist(), own_keys.tolist(), strict=True):
            np.testing.assert_array_equal(joined.batch.obs[:, column], items[k][key].obs)
    trunc_columns = joined.batch.trunc_b.tolist()  # each fragment's truncation, shifted along
    assert trunc_columns == list(range(6))
    p_min = min(priorities)
    for column in np.flatnonzero(joined.from_prioritized).tolist():
        k = int(joined.keys[column] % 2)
        key = int(joined.keys[column] // 2)
        p = priorities[key * 2 + k]
        assert joined.weights[column] == pytest.approx((p / p_min) ** (-ALPHA * BETA), rel=1e-5)
    assert (joined.weights[~joined.from_prioritized] == 1.0).all()
    assert joined.obs_moments.count == 6.0
    np.testing.assert_allclose(joined.obs_moments.mean, np.full(OBS_DIM, 4.0 / 6.0))


def test_shard_keys_keep_an_unsharded_run_as_it_was():
    plain, shard = Keys("run"), Keys("run", 2)
    assert plain.traj(5) == "tpdeb/run/traj/5" and plain.sample == "tpdeb/run/sample"
    assert shard.traj(5) == "tpdeb/run/shard/2/traj/5"
    assert shard.ack_all == "tpdeb/run/shard/2/ack/*"
    assert (shard.sample, shard.priorities) == ("tpdeb/run/shard/2/sample",
                                                "tpdeb/run/shard/2/priorities")
    for name in ("params", "params_latest", "spec", "control", "join", "stats_all"):
        assert getattr(shard, name) == getattr(plain, name)  # the run's, not the shard's
    assert shard.actor_id_of("tpdeb/run/shard/2/traj/5") == 5
    assert shard.actor_id_of("tpdeb/run/shard/1/traj/5") is None
    assert Keys("run", ANY_SHARD).traj_all == "tpdeb/run/shard/*/traj/*"
    assert plain.of_shard(3).sample == "tpdeb/run/shard/3/sample"
    for bad in (-1, True, "x", 1.5):
        with pytest.raises(ValueError, match="shard"):
            Keys("run", bad)


def test_a_request_cannot_ask_more_rows_from_bp_than_its_batch():
    data = encode(SampleRequest(request_id=1, batch_size=4, beta=0.5, num_prioritized=3))
    assert decode(data, SampleRequest).num_prioritized == 3
    assert decode(encode(SampleRequest(1, 4, 0.5)), SampleRequest).num_prioritized is None
    with pytest.raises(DecodeError, match="more than the batch"):
        decode(encode(SampleRequest(1, 4, 0.5, num_prioritized=5)), SampleRequest)


# --- in process: two replay shards and a learner on the in-memory transport -------------------

@pytest.fixture
def two_shards(tmp_path):
    with shards_and_learner(tmp_path) as started:
        yield started


@contextlib.contextmanager
def shards_and_learner(tmp_path, **learner_settings):
    """Two replay servers as shards 0 and 1 and a learner, on one in-memory bus."""
    bus = MemoryBus()
    settings = dict(run_id="t", env_id="Hopper-v5", fragment_len=T, batch_fragments=4,
                    learning_starts_fragments=2, prioritized_capacity=4,
                    uniform_capacity_steps=16 * T, replay_ratio=1.0, replay_shards=2)
    configs = [ReplayServiceConfig(connect=("tcp/127.0.0.1:1",), shard=k, sample_wait_s=0.05,
                                   persist=False, **settings) for k in (0, 1)]
    spec = run_spec(configs[0], OBS_DIM, ACT_DIM, -np.ones(ACT_DIM), np.ones(ACT_DIM))
    assert spec.replay_shards == 2
    servers = [ReplayServer(config, spec, bus.session(), StopSignal()) for config in configs]
    learner = LearnerService(LearnerServiceConfig(run_dir=str(tmp_path), compile="off",
                                                  **settings, **learner_settings),
                             spec, bus.session(), StopSignal())
    try:
        yield servers, learner, bus
    finally:
        learner.metrics.close()
        for server in servers:
            server.close()


def fetch_while_serving(learner, servers):
    """The learner's fetch in its own thread, the shards' loops answering meanwhile."""
    out = []
    thread = threading.Thread(target=lambda: out.append(learner.fetch(1)))
    thread.start()
    while thread.is_alive():
        for server in servers:
            server.poll(0.005)
    thread.join()
    return out[0]


def test_a_learner_samples_both_shards_and_sends_each_its_priorities(two_shards):
    servers, learner, bus = two_shards
    sent = {}
    for actor_id in (0, 1):  # actor a writes to shard a mod 2
        for seq in range(4):
            fragment = dataclasses.replace(make_traj(seed=10 * actor_id + seq), actor_id=actor_id)
            bus.session().put(Keys("t", actor_id).traj(actor_id), encode(fragment))
            sent[(actor_id, seq)] = fragment
    for server in servers:
        server.poll(0.01)
    assert [server.inserted_steps for server in servers] == [4 * T, 4 * T]
    batch = None
    for _ in range(10):  # the first asks probe the shards; then a full batch
        batch = batch or fetch_while_serving(learner, servers)
    assert batch is not None and batch.batch.obs.shape == (T + 1, 4, OBS_DIM)
    assert learner.global_step == 8 * T
    for column, key in enumerate(batch.keys.tolist()):
        shard, own = key % 2, key // 2  # each shard's keys count its own arrivals
        np.testing.assert_array_equal(batch.batch.obs[:, column], sent[(shard, own)].obs)
    # new priorities, one per row: each B_p row's goes to its own shard, under its own key
    values = 1000.0 + np.arange(4)
    learner.send_priorities((batch.keys, batch.from_prioritized, torch.tensor(values)))
    for server in servers:
        server.poll(0.01)
    for shard, server in enumerate(servers):
        rows = [c for c in range(4) if batch.from_prioritized[c] and batch.keys[c] % 2 == shard]
        if rows:
            assert server.replay.stats()["priority_max"] == max(values[rows])


def test_a_shard_that_goes_leaves_the_batch_to_the_live_one(two_shards):
    servers, learner, bus = two_shards
    for actor_id in (0, 1):
        for seq in range(4):
            fragment = dataclasses.replace(make_traj(seed=seq), actor_id=actor_id)
            bus.session().put(Keys("t", actor_id).traj(actor_id), encode(fragment))
    for server in servers:
        server.poll(0.01)
    servers[1].token.undeclare()  # shard 1 gone (its liveliness token with it): not served
    batch = None
    for _ in range(10):
        batch = batch or fetch_while_serving(learner, servers[:1])
    assert batch is not None and {key % 2 for key in batch.keys.tolist()} == {0}


def test_the_learner_charges_each_shard_its_own_query_wait(tmp_path):
    """Shard 0 is asked first and answers nothing until its query times out (2 s); shard 1,
    whose sample queryable is gone (its token still there), answers nothing at once. Shard 1 is
    left out for the 1 s probe interval, not for the 2 s that shard 0's reading took."""
    with shards_and_learner(tmp_path, request_timeout_s=2.0) as (servers, learner, _):
        servers[1].queryables[0].undeclare()
        assert learner.fetch_sharded(1) is None  # neither shard polled: no batch
        left_out = [until - time.monotonic() for until in learner.shard_set.down_until]
        assert 1.0 < left_out[0] <= 2.0 and 0.0 < left_out[1] < 1.0


def test_the_cluster_starts_one_replay_per_shard_each_told_its_own(tmp_path):
    plan = make_plan(parse_args(["--set", "replay_shards=2", "--run-dir", str(tmp_path / "run")]))
    (replay,) = [s for s in plan.services if s.role == "replay"]
    assert replay.replicas == 2
    Cluster(plan).write_run_dir()
    for shard in (0, 1):
        text = (tmp_path / "run" / "config" / f"replay-{shard}.toml").read_text()
        assert f"shard = {shard}" in text and "replay_shards = 2" in text
    with pytest.raises(ConfigError, match="replay_shards=3 with 2 actor"):
        make_plan(parse_args(["--set", "replay_shards=3", "--run-dir", str(tmp_path / "r3")]))
    with pytest.raises(ConfigError, match="shard"):
        ReplayServiceConfig(replay_shards=2, shard=2)
    with pytest.raises(ConfigError, match="one process has one replay"):
        SerialRunner(TrainConfig(replay_shards=2))
