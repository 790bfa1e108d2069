"""The replay server's delivery rules and the actor's outbox, in process on the in-memory
transport (no Zenoh network, no subprocess): de-duplication, acknowledgement after ingest,
not-ready replies, refusals, back-pressure and resends."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from tests.test_protocol import ACT_DIM, OBS_DIM, T, make_traj
from tpdeb.protocol import (
    Ack,
    JoinReply,
    JoinRequest,
    Keys,
    SampleReply,
    SampleRequest,
    decode,
    encode,
)
from tpdeb.services.actor import Outbox
from tpdeb.services.config.service import ReplayServiceConfig
from tpdeb.services.net.memory import MemoryBus, matches
from tpdeb.services.net.session import join_run
from tpdeb.services.net.wire import run_spec
from tpdeb.services.process import StopSignal
from tpdeb.services.replay import ReplayServer
from tpdeb.tpdeb_core.fragments import FragmentBatch
from tpdeb.tpdeb_core.schema import STACKED

RUN = "mem"


@pytest.fixture
def replay():
    config = ReplayServiceConfig(
        run_id=RUN, connect=("tcp/127.0.0.1:1",), env_id="Hopper-v5", fragment_len=T,
        batch_fragments=2, learning_starts_fragments=2, prioritized_capacity=4,
        uniform_capacity_steps=16 * T, replay_ratio=1.0, sample_wait_s=0.05, persist=False)
    spec = run_spec(config, OBS_DIM, ACT_DIM, -np.ones(ACT_DIM), np.ones(ACT_DIM))
    bus = MemoryBus()
    bus.heard = []  # every ack put, as an actor's subscriber receives it
    bus.session().declare_subscriber(Keys(RUN).ack_all, bus.heard.append)
    server = ReplayServer(config, spec, bus.session(), StopSignal())
    yield server, bus
    server.close()


def acks_for(bus: MemoryBus, actor_id: int) -> list[Ack]:
    key = Keys(RUN).ack(actor_id)
    return [decode(s.payload.to_bytes(), Ack) for s in bus.heard if s.key_expr == key]


def send(bus: MemoryBus, message, actor_id: int = 3) -> None:
    bus.session().put(Keys(RUN).traj(actor_id), encode(message))


def test_key_expressions_match_as_zenohs():
    assert matches("tpdeb/r/traj/*", "tpdeb/r/traj/3")
    assert not matches("tpdeb/r/traj/*", "tpdeb/r/traj/3/x")
    assert matches("tpdeb/r/stats/**", "tpdeb/r/stats/actor/1")
    assert matches("tpdeb/r/**", "tpdeb/r")
    assert not matches("tpdeb/r/ack/3", "tpdeb/r/ack/4")


def test_a_fragment_is_acknowledged_once_ingested_and_a_resent_one_stored_once(replay):
    server, bus = replay
    send(bus, make_traj(seed=0))
    send(bus, make_traj(seed=0))  # a copy while the first waits: one ack covers both
    send(bus, make_traj(seed=1))
    server.poll(0.0)
    assert len(server.replay) == 2
    assert sorted(int(s) for ack in acks_for(bus, 3) for s in ack.seqs) == [0, 1]
    send(bus, make_traj(seed=0))  # resent after its ack: that ack may have been lost
    server.poll(0.0)
    assert len(server.replay) == 2  # stored once, acknowledged again
    assert sorted(int(s) for ack in acks_for(bus, 3) for s in ack.seqs) == [0, 0, 1]
    assert server.ledgers[3].duplicates == 2 and server.ledgers[3].ingested == 2


def test_fragments_that_fail_their_checks_are_counted_and_never_acknowledged(replay):
    server, bus = replay
    bus.session().put(Keys(RUN).traj(5), b"\x93garbage")  # each from its own sender: a bad
    send(bus, make_traj(seed=2, obs_dim=OBS_DIM + 1))  # message puts its sender in a penalty
    send(bus, make_traj(seed=3), actor_id=4)  # carries actor 3's id on actor 4's key
    server.poll(0.0)
    assert len(server.replay) == 0 and not acks_for(bus, 3) and not acks_for(bus, 4)
    assert sum(server.bad.values()) == 3 and server.bad["sender"] == 1


def ask_for_a_batch(bus: MemoryBus, server: ReplayServer, size: int = 2) -> list[SampleReply]:
    """A learner's sample query, answered by the server's own loop."""
    replies: list[SampleReply] = []
    request = encode(SampleRequest(request_id=1, batch_size=size, beta=1.0))

    def learner() -> None:
        for reply in bus.session().get(Keys(RUN).sample, payload=request, timeout=5.0):
            replies.append(decode(reply.ok.payload.to_bytes(), SampleReply, server.spec))

    thread = threading.Thread(target=learner)
    thread.start()
    while thread.is_alive():
        server.poll(0.01)
    thread.join()
    return replies


def test_a_sample_request_before_enough_steps_gets_a_not_ready_reply(replay):
    server, bus = replay
    send(bus, make_traj(seed=0))  # one fragment; sampling starts at two
    (reply,) = ask_for_a_batch(bus, server)
    assert not reply.ready and "rate limiter" in reply.reason
    send(bus, make_traj(seed=1))
    (reply,) = ask_for_a_batch(bus, server)
    assert reply.ready and reply.batch.obs.shape == (T + 1, 2, OBS_DIM)
    assert set(reply.keys.tolist()) <= {0, 1} and reply.inserted_steps == 2 * T


def test_the_replay_stacks_the_fragments_it_decoded_and_the_learner_gets_them_as_sent(replay):
    server, bus = replay
    sent = [make_traj(seed=0), make_traj(seed=1)]
    for fragment in sent:
        send(bus, fragment)
    (reply,) = ask_for_a_batch(bus, server)
    assert reply.ready and type(reply.batch) is FragmentBatch
    for column, key in enumerate(reply.keys.tolist()):  # keys count up from 0 in arrival order
        for name in STACKED:
            np.testing.assert_array_equal(getattr(reply.batch, name)[:, column],
                                          getattr(sent[key], name))
    assert reply.batch.policy_version.tolist() == [7, 7]


def test_the_outbox_holds_back_pressure_and_resends_what_is_not_acknowledged():
    outbox = Outbox(capacity=2)
    outbox.add(0, b"a", now=0.0)
    outbox.add(1, b"b", now=0.5)
    assert not outbox.wait_for_room(0.0)  # full: the actor waits instead of dropping
    assert outbox.due(now=1.2, after_s=1.0) == [(0, b"a")]  # only what waited long enough
    assert outbox.due(now=1.3, after_s=1.0) == []  # its clock restarted on the resend
    outbox.ack([0, 7])  # an unknown seq (an ack of a duplicate) changes nothing
    assert outbox.wait_for_room(0.0) and len(outbox) == 1 and outbox.acked == 1
    outbox.make_all_due()  # the replay server came back: everything goes again
    assert outbox.due(now=1.4, after_s=1.0) == [(1, b"b")]


def test_auto_actor_ids_are_the_lowest_free_and_the_same_to_a_repeated_ask(replay):
    server, bus = replay
    bus.pump = lambda: server.poll(0.0)  # the replay answers while a query waits
    session, keys = bus.session(), Keys(RUN)
    assert [join_run(session, keys, 5.0, StopSignal()) for _ in range(2)] == [0, 1]
    send(bus, make_traj(seed=0), actor_id=3)
    server.poll(0.0)
    assert 3 in server.ledgers  # an actor that sent fragments holds its id
    ask = encode(JoinRequest(nonce=77))
    ids = [decode(next(session.get(keys.join, payload=ask, timeout=5.0)).ok.payload.to_bytes(),
                  JoinReply).actor_id for _ in range(2)]
    assert ids == [2, 2]  # the lowest free; asked again (a lost reply), the same
    assert join_run(session, keys, 5.0, StopSignal()) == 4  # 3 is taken by the sender
    assert not list(session.get(keys.join, payload=b"garbage", timeout=0.5))
    assert server.bad and sum(server.bad.values()) == 1


def test_an_actor_stopped_before_its_first_parameters_ends_cleanly():
    """A run that has already ended (a learner resumed past its last step stops at once): the
    actor hears the stop before any parameters and returns instead of failing."""
    from tpdeb.services.actor import ActorService
    from tpdeb.services.config.service import ActorServiceConfig
    from tpdeb.services.envs import make_vector_env, space_dims

    config = ActorServiceConfig(run_id=RUN, env_id="InvertedPendulum-v5", num_envs=1)
    envs = make_vector_env(config.env_id, 1)
    spec = run_spec(ReplayServiceConfig(env_id=config.env_id, persist=False),
                    *space_dims(envs))
    stop = StopSignal()
    actor = ActorService(config, spec, envs, MemoryBus().session(), stop)
    stop.set("stop message")
    try:
        actor.run()
        assert actor.collector is None and actor.sent == 0
    finally:
        actor.close()


def test_a_full_disk_stops_acks_and_intake_not_samples_and_nothing_acked_is_lost(
        replay, tmp_path, monkeypatch, caplog):
    import logging

    import tpdeb.services.replay as replay_module
    from tests.test_disk_full import refused_fsyncs
    from tpdeb.services.store.persistence import ReplayPersistence

    server, bus = replay
    server.enable_persistence(tmp_path / "replay")
    full = refused_fsyncs(monkeypatch, full=False)
    monkeypatch.setattr(replay_module, "DISK_RETRY_S", 0.0)
    send(bus, make_traj(seed=0))
    send(bus, make_traj(seed=1))
    server.poll(0.0)
    assert len(acks_for(bus, 3)) == 1
    full[0] = True
    with caplog.at_level(logging.INFO, "tpdeb-replay"):
        send(bus, make_traj(seed=2))  # ingested, its log write refused: never acknowledged
        server.poll(0.0)
        send(bus, make_traj(seed=3))  # waits: nothing is taken in while the disk is full
        server.poll(0.0)
        assert server.disk_full and len(server.replay) == 3 and len(server.pending) == 1
        assert sorted(int(s) for a in acks_for(bus, 3) for s in a.seqs) == [0, 1]
        (reply,) = ask_for_a_batch(bus, server)
        assert reply.ready  # samples go on
        full[0] = False
        server.poll(0.0)  # the log takes writes: the held fragment is acknowledged
        assert not server.disk_full
        server.poll(0.0)  # and the waiting one taken in
    assert len(server.replay) == 4
    assert sorted(int(s) for a in acks_for(bus, 3) for s in a.seqs) == [0, 1, 2, 3]
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "No space left on device" in warnings[0]
    server.close()
    monkeypatch.undo()
    state, records = ReplayPersistence(tmp_path / "replay").load(bytes)
    assert state["ledgers"][3]["ingested"] == 4 and list(records) == []  # a restart has all


def test_a_log_torn_by_a_power_cut_restores_what_came_before_with_one_line(
        replay, tmp_path, caplog):
    import logging

    from tpdeb.services.store.persistence import ReplayPersistence

    server, _ = replay
    log = ReplayPersistence(tmp_path / "replay")
    for seed in (0, 1):
        log.log(encode(make_traj(seed=seed)))
    log.close()
    segment = next((tmp_path / "replay").glob("wal-*.log"))
    segment.write_bytes(segment.read_bytes()[:-100])  # the power went mid-write
    with caplog.at_level(logging.INFO, "tpdeb-replay"):
        server.enable_persistence(tmp_path / "replay")
    assert len(server.replay) == 1
    lines = [r.getMessage() for r in caplog.records if "torn" in r.getMessage()]
    assert len(lines) == 1 and "restored the 1 logged fragments before it" in lines[0]


def test_a_flooding_sender_is_held_to_its_share_and_the_others_still_get_in(replay):
    server, bus = replay
    limit = server.config.max_queued_per_sender
    flooder = Keys(RUN).traj(9)
    for _ in range(20 * limit):  # garbage as fast as it can put it, before the loop runs once
        bus.session().put(flooder, b"\x93garbage")
    send(bus, make_traj(seed=0))
    send(bus, make_traj(seed=1))
    assert server.inbox.qsize() == limit + 2  # memory: its share, not its flood
    server.poll(0.0)
    assert len(server.replay) == 2  # the honest actor's fragments are in and acknowledged
    assert sorted(int(s) for a in acks_for(bus, 3) for s in a.seqs) == [0, 1]
    # its first bad message put it in the penalty box: the rest are not even decoded
    assert sum(server.bad.values()) == 1 and server.flooded == 20 * limit - 1
    assert server.stats()["bad/flood"] == 20 * limit - 1
    bus.session().put(flooder, b"\x93garbage")  # dropped on arrival while the penalty lasts
    assert server.inbox.qsize() == 0 and server.flooded == 20 * limit
    send(bus, make_traj(seed=2))  # the honest actor is not held back by it
    server.poll(0.0)
    assert len(server.replay) == 3


def test_a_resend_from_an_actor_restarted_many_times_ago_is_still_recognised(replay):
    server, bus = replay
    first = make_traj(seed=0)
    for incarnation in range(1, 11):  # the actor restarted nine times
        send(bus, dataclasses.replace(first, incarnation=incarnation))
        server.poll(0.0)
    send(bus, dataclasses.replace(first, incarnation=1))  # the first one's resend, late
    server.poll(0.0)
    ledger = server.ledgers[3]
    assert ledger.duplicates == 1  # stored once
    assert ledger.ingested + len(ledger.pending) == 10 and 0 in ledger.windows[1]


def test_a_replay_restored_from_an_old_snapshot_takes_in_and_acknowledges_at_once(tmp_path):
    """Killed long after its last snapshot, the replay re-inserts the fragments logged since,
    but the samples taken against them were never logged. Counted as plain inserts they held
    every new fragment back (unacknowledged, the actors stalled) until the learner had sampled
    them all again: 24 s in a chaos run, 36-42 s behind a replay kill 50 s after a snapshot."""
    config = ReplayServiceConfig(
        run_id=RUN, connect=("tcp/127.0.0.1:1",), env_id="Hopper-v5", fragment_len=T,
        batch_fragments=2, learning_starts_fragments=2, prioritized_capacity=4,
        uniform_capacity_steps=16 * T, replay_ratio=1.0, sample_wait_s=0.05, persist=False)
    spec = run_spec(config, OBS_DIM, ACT_DIM, -np.ones(ACT_DIM), np.ones(ACT_DIM))

    def start() -> tuple[ReplayServer, MemoryBus]:
        bus = MemoryBus()
        bus.heard = []
        bus.session().declare_subscriber(Keys(RUN).ack_all, bus.heard.append)
        server = ReplayServer(config, spec, bus.session(), StopSignal())
        server.enable_persistence(tmp_path / "replay")
        return server, bus

    server, bus = start()
    for seed in (0, 1):
        send(bus, make_traj(seed=seed))
    server.poll(0.0)
    server.snapshot(wait=True)
    for seed in range(2, 12, 2):  # logged after the snapshot, sampled at the ratio
        send(bus, make_traj(seed=seed))
        send(bus, make_traj(seed=seed + 1))
        server.poll(0.0)
        (reply,) = ask_for_a_batch(bus, server)
        assert reply.ready
    assert sorted(int(s) for a in acks_for(bus, 3) for s in a.seqs) == list(range(12))
    server.persistence.close()  # then killed: no snapshot at exit

    server, bus = start()
    try:
        assert len(server.replay) == 12
        send(bus, make_traj(seed=12))
        server.poll(0.0)
        assert len(server.pending) == 0, "a new fragment waits for samples already taken"
        assert [int(s) for a in acks_for(bus, 3) for s in a.seqs] == [12]
        (reply,) = ask_for_a_batch(bus, server)
        assert reply.ready  # and the learner samples on at the ratio
    finally:
        server.close()


def test_a_batch_up_to_the_growth_ceiling_is_served_and_a_larger_one_refused(replay):
    server, bus = replay
    grown = dataclasses.replace(server.config, max_batch_fragments=4, replay_ratio=4.0)
    server.config, server.limiter = grown, grown.rate_limiter()
    for seed in range(6):
        send(bus, make_traj(seed=seed))
    server.poll(0.0)
    (reply,) = ask_for_a_batch(bus, server, size=4)  # twice batch_fragments: growth's
    assert reply.ready and len(reply.keys) == 4
    (reply,) = ask_for_a_batch(bus, server, size=5)
    assert not reply.ready and "max_batch_fragments" in reply.reason and "(4" in reply.reason
