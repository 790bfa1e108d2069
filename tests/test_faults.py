"""Faults with real processes: `kill -9` of a service mid-run. The run goes on, nothing that was
acknowledged is lost, nothing is stored twice, and parameter versions never go back."""

from __future__ import annotations

import os
import signal
import statistics
import threading
import time

import pytest

from tests.procs import free_port, service_pid
from tests.test_services import next_stats, watch_stats
from tpdeb.protocol import Ack, Keys, Stats, Trajectory, decode
from tpdeb.services.net.session import open_session
from tpdeb.services.store.metrics import read_metrics
from tpdeb.services.store.persistence import ReplayPersistence

ENV = "InvertedPendulum-v5"


@pytest.fixture
def session(endpoint, procs):
    router = procs.spawn("router", "--listen", endpoint)
    procs.wait_for_line(router, "routing")
    s = open_session("client", [], [endpoint], connect_timeout_s=30)
    yield s
    s.close()


class AckLog:
    """Every acknowledgement on the wire: (actor, incarnation, seq) with the time it was seen."""

    def __init__(self, session, keys: Keys):
        self.lock = threading.Lock()
        self.seen: dict[tuple[int, int, int], float] = {}
        self.subscriber = session.declare_subscriber(keys.ack_all, self._on_ack)

    def _on_ack(self, sample) -> None:
        ack = decode(sample.payload.to_bytes(), Ack)
        now = time.monotonic()
        with self.lock:
            for seq in ack.seqs.tolist():
                self.seen.setdefault((ack.actor_id, ack.incarnation, seq), now)

    def snapshot(self) -> dict:
        with self.lock:
            return dict(self.seen)

    def first_after(self, t: float) -> float | None:
        with self.lock:
            later = [when for when in self.seen.values() if when > t]
        return min(later) if later else None

    def wait_after(self, t: float, what: str, timeout_s: float = 90) -> float:
        """When the first acknowledgement after `t` was seen (waiting for it)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.first_after(t) is None:
            time.sleep(0.2)
        first = self.first_after(t)
        assert first is not None, f"no acknowledgement after {what}"
        return first


def stored_state(run_dir, replay_dir="replay"):
    """The replay's final state as its next restart would load it."""
    state, records = ReplayPersistence(run_dir / replay_dir).load(
        lambda payload: decode(payload, Trajectory))
    assert state is not None, "no complete snapshot in the run dir"
    assert list(records) == [], "a clean stop leaves nothing to replay from the log"
    return state


def test_replay_killed_with_sigkill_loses_no_acknowledged_fragment(
        procs, endpoint, session, tmp_path, figures):
    run_dir = tmp_path / "run"
    keys = Keys("t")
    common = ["--run-id", "t", "--env-id", ENV, "--num-envs", "2", "--total-timesteps", "24000",
              "--run-dir", str(run_dir)]
    acks = AckLog(session, keys)
    stats = watch_stats(session, keys)
    replay_args = [*common, "--listen", "", "--connect", endpoint, "--snapshot-interval-s", "2"]
    replay = procs.spawn("replay", *replay_args)
    learner = procs.spawn("learner", *common, "--connect", endpoint)
    procs.spawn("actor", *common, "--connect", endpoint, "--actor-id", "0")
    next_stats(stats, "replay", lambda v: v.get("snapshots_written", 0) >= 1
               and v.get("inserted_steps", 0) >= 6000, timeout_s=120)
    time.sleep(0.5)  # fragments logged after the snapshot: restored from the log
    os.kill(replay.pid, signal.SIGKILL)
    replay.wait()
    killed_at = time.monotonic()
    acked_before = acks.snapshot()
    assert acked_before, "nothing was acknowledged before the kill"

    replay = procs.spawn("replay", *replay_args, name="replay-2")
    procs.wait_for_line(replay, "restored")
    assert learner.wait(timeout=180) == 0, procs.output(learner)
    recovered = acks.first_after(killed_at + 0.05)
    replay.send_signal(signal.SIGTERM)
    assert replay.wait(timeout=30) == 0, procs.output(replay)

    state = stored_state(run_dir)
    ledger = state["ledgers"][0]
    for (actor, incarnation, seq) in acked_before:
        assert actor == 0
        low, above = ledger["windows"][incarnation]
        assert seq < low or seq in above, f"acknowledged fragment {seq} was lost"
    # each fragment stored once: what the ledgers count equals what the buffer took in
    stored = sum(low + len(above) for low, above in ledger["windows"].values())
    assert ledger["ingested"] == stored == state["replay"]["counters"]["inserted"]
    assert recovered is not None
    # the learner's delivery counters: what the actor sent, what came back acknowledged
    last = [r for r in read_metrics(run_dir / "metrics.jsonl") if "delivery/sent" in r][-1]
    assert 0 < last["delivery/acked"] <= last["delivery/sent"]
    assert last["delivery/ingested"] > 0 and "delivery/duplicates" in last
    print(f"replay kill -9: {len(acked_before)} fragments acknowledged before, all present; "
          f"first ack {recovered - killed_at:.1f} s after the kill; "
          f"{ledger['duplicates']} resends recognised")
    figures.keep("replay-kill9", {"acknowledged_before": len(acked_before), "lost": 0,
                                  "first_ack_after_s": round(recovered - killed_at, 2),
                                  "resends_recognised": ledger["duplicates"]})


CLUSTER_FILE = """
[cluster]
run_id = "faults"
endpoint = "{endpoint}"
restart_backoff_s = 0.5

[train.run]
env_id = "{env}"
total_timesteps = {steps}
log_interval_s = 1

[train.actor]
num_envs = 2

[services.router]
command = "tpdeb-router"

[services.replay]
command = "tpdeb-replay"
depends_on = ["router"]
args = ["--snapshot-interval-s", "3"]

[services.learner]
command = "tpdeb-learner"
depends_on = ["replay"]
args = ["--checkpoint-interval-s", "2"]

[services.actor]
command = "tpdeb-actor"
replicas = 2
depends_on = ["learner"]
"""


class StatsLog:
    """Every stats message of the run, in arrival order, with its arrival time."""

    def __init__(self, session, keys: Keys):
        self.lock = threading.Lock()
        self.rows: list[tuple[float, str, str, dict]] = []
        self.subscriber = session.declare_subscriber(keys.stats_all, self._on_stats)

    def _on_stats(self, sample) -> None:
        stats = decode(sample.payload.to_bytes(), Stats)
        with self.lock:
            self.rows.append((time.monotonic(), stats.role, stats.ident, stats.values))

    def series(self, role: str, name: str, ident: str | None = None) -> list[tuple[float, float]]:
        with self.lock:
            return [(t, v[name]) for t, r, i, v in self.rows
                    if r == role and name in v and (ident is None or i == ident)]

    def wait(self, role: str, name: str, until, timeout_s: float = 120,
             since: float = 0.0, ident: str | None = None) -> float:
        """When the first stats after `since` satisfying `until` arrived."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            hits = [t for t, value in self.series(role, name, ident)
                    if t > since and until(value)]
            if hits:
                return hits[0]
            time.sleep(0.2)
        raise AssertionError(f"no {role} {name} satisfying the condition in {timeout_s} s")


def non_decreasing(values) -> bool:
    return all(a <= b for a, b in zip(values, values[1:], strict=False))


@pytest.mark.slow
def test_cluster_survives_kill9_of_an_actor_the_learner_the_replay_and_the_router(
        procs, tmp_path, figures):
    run_dir = tmp_path / "run"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cluster_file = tmp_path / "cluster.toml"
    # long enough that the run is still going after the four kills and recoveries (~30 s)
    cluster_file.write_text(CLUSTER_FILE.format(endpoint=endpoint, env=ENV, steps=300000))
    cluster = procs.spawn("cluster", "--cluster-file", str(cluster_file), "--run-dir", str(run_dir))
    procs.wait_for_line(cluster, "[learner] tpdeb-learner: run", timeout_s=120)
    session = open_session("client", [], [endpoint], connect_timeout_s=30)
    try:
        keys = Keys("faults")
        acks, stats = AckLog(session, keys), StatsLog(session, keys)
        recovery = {}

        # an actor: its replacement (a new incarnation) gets acknowledgements
        stats.wait("learner", "global_step", lambda v: v >= 4000)
        with acks.lock:
            old_incarnations = {inc for (a, inc, _) in acks.seen if a == 0}
        os.kill(service_pid(run_dir, "actor-0"), signal.SIGKILL)
        killed = time.monotonic()
        deadline = killed + 90
        while time.monotonic() < deadline:
            with acks.lock:
                new = [t for (a, inc, _), t in acks.seen.items()
                       if a == 0 and inc not in old_incarnations]
            if new:
                recovery["actor"] = min(new) - killed
                break
            time.sleep(0.2)
        assert "actor" in recovery, "the restarted actor-0 never delivered"

        # the learner: resumes from its checkpoint, versions go on above the old ones
        time.sleep(3)  # past a periodic checkpoint
        os.kill(service_pid(run_dir, "learner"), signal.SIGKILL)
        killed = time.monotonic()
        time.sleep(0.5)  # stats already on their way
        before = max(v for _, v in stats.series("learner", "param_version"))
        back = stats.wait("learner", "param_version", lambda v: v > before, since=killed)
        resumed_at = min(v for t, v in stats.series("learner", "param_version") if t >= back)
        # training again: a version past the one the restarted learner came back with
        recovery["learner"] = stats.wait("learner", "param_version",
                                         lambda v: v > resumed_at, since=back) - killed

        # the replay: restores everything it acknowledged, acks resume
        stats.wait("replay", "snapshots_written", lambda v: v >= 1)
        os.kill(service_pid(run_dir, "replay"), signal.SIGKILL)
        killed = time.monotonic()
        acked_before = acks.snapshot()
        recovery["replay"] = acks.wait_after(killed + 0.05, "the replay restarted") - killed

        # the router: every service reconnects to its replacement, acks flow again
        time.sleep(2)
        os.kill(service_pid(run_dir, "router"), signal.SIGKILL)
        killed = time.monotonic()
        recovery["router"] = acks.wait_after(killed + 0.05, "the router restarted") - killed

        # stopped here (the replay's last snapshot holds everything it acknowledged)
        time.sleep(2)
        cluster.send_signal(signal.SIGINT)
        assert cluster.wait(120) == 130, procs.output(cluster)[-3000:]
        learner_versions = [v for _, v in stats.series("learner", "param_version")]
        assert non_decreasing(learner_versions), "a parameter version went back"
        for ident in ("0", "1"):
            versions = [v for _, v in stats.series("actor", "param_version", ident)]
            assert non_decreasing(versions), f"actor {ident} took an older version"
    finally:
        session.close()
    out = procs.output(cluster)
    for name in ("actor-0", "learner", "replay", "router"):
        assert f"{name} exited with code -9; restarting" in out, out[-3000:]
    assert_all_present(stored_state(run_dir), acked_before)
    print("recovery after kill -9 (s): " + ", ".join(f"{k} {v:.1f}" for k, v in recovery.items())
          + f"; {len(acked_before)} acknowledged fragments before the replay kill, all present")
    figures.keep("cluster-kill9", {"recovery_s": {k: round(v, 2) for k, v in recovery.items()},
                                   "acknowledged_before_replay_kill": len(acked_before),
                                   "lost": 0, "versions_monotone": True})


def assert_all_present(state, acked) -> None:
    """Every acknowledged (actor, incarnation, seq) is in the replay's ledgers, and every
    fragment ingested once."""
    for (actor, incarnation, seq) in acked:
        low, above = state["ledgers"][actor]["windows"][incarnation]
        assert seq < low or seq in above, f"acknowledged fragment {actor}/{seq} was lost"
    inserted = state["replay"]["counters"]["inserted"]
    assert sum(ledger["ingested"] for ledger in state["ledgers"].values()) == inserted


@pytest.mark.slow
def test_two_shards_and_two_ranks_learn_through_kill9_of_a_shard_and_a_rank(procs, tmp_path):
    """Each actor writes to its own shard and each learner rank samples from both; a shard
    killed with SIGKILL comes back with everything it acknowledged, a killed rank takes the
    group back to rank 0's checkpoint, and the run still learns InvertedPendulum."""
    run_dir = tmp_path / "run"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cluster_file = tmp_path / "cluster.toml"
    cluster_file.write_text(CLUSTER_FILE.format(endpoint=endpoint, env=ENV, steps=100000)
                            .replace("[train.actor]", "[train.replay]\nreplay_shards = 2\n\n"
                                     "[train.learner]\nlearners = 2\n\n[train.actor]")
                            .replace("total_timesteps = 100000",
                                     "total_timesteps = 100000\nseed = 1"))
    cluster = procs.spawn("cluster", "--cluster-file", str(cluster_file), "--run-dir", str(run_dir))
    procs.wait_for_line(cluster, "[learner-0] tpdeb-learner: run", timeout_s=120)
    session = open_session("client", [], [endpoint], connect_timeout_s=30)
    try:
        keys = Keys("faults")
        acks = [AckLog(session, keys.of_shard(shard)) for shard in (0, 1)]
        stats = StatsLog(session, keys)
        # shard 1 (actor 1's): restores everything it acknowledged, its acks resume
        stats.wait("replay", "snapshots_written", lambda v: v >= 1, ident="1")
        os.kill(service_pid(run_dir, "replay-1"), signal.SIGKILL)
        killed = time.monotonic()
        acked_before = acks[1].snapshot()
        assert acked_before and all(actor == 1 for actor, _, _ in acked_before)
        acks[1].wait_after(killed + 0.05, "shard 1 restarted")
        # rank 1: the group restarts from rank 0's checkpoint and trains on
        time.sleep(3)  # past a periodic checkpoint
        before = max(v for _, v in stats.series("learner", "param_version", "0"))
        os.kill(service_pid(run_dir, "learner-1"), signal.SIGKILL)
        killed = time.monotonic()
        stats.wait("learner", "param_version", lambda v: v > before, since=killed + 0.5,
                   ident="0")
        assert cluster.wait(400) == 0, procs.output(cluster)[-3000:]
        versions = [v for _, v in stats.series("learner", "param_version", "0")]  # rank 0's
        assert non_decreasing(versions), "a parameter version went back"
        assert stats.series("learner", "param_version", "1")  # each rank's stats its own
    finally:
        session.close()
    out = procs.output(cluster)
    assert "replay-1 exited with code -9; restarting" in out, out[-3000:]
    assert "learner-1 exited with code -9" in out, out[-3000:]
    assert_all_present(stored_state(run_dir, "replay-1"), acked_before)
    for shard in (0, 1):  # each shard's own state, its ledgers its own actor's
        state = stored_state(run_dir, f"replay-{shard}")
        assert set(state["ledgers"]) == {shard}, state["ledgers"].keys()
        assert_all_present(state, acks[shard].snapshot())
    rows = read_metrics(run_dir / "metrics.jsonl")
    returns = [r["charts/episodic_return"] for r in rows if "charts/episodic_return" in r]
    assert statistics.mean(returns[-20:]) >= 800, returns[-20:]
    assert max(r["global_step"] for r in rows) >= 100000
    logs = {p.name for p in (run_dir / "logs").iterdir()}
    assert {"replay-0.log", "replay-1.log", "learner-0.log", "learner-1.log"} <= logs, logs
    assert list((run_dir / "checkpoints").glob("final_*.pt"))  # rank 0's
    assert not list((run_dir / "ranks" / "1").glob("checkpoints/*.pt"))
