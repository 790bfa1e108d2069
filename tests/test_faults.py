"""Faults with real processes: `kill -9` of a service mid-run. The run goes on, nothing that was
acknowledged is lost, nothing is stored twice, and parameter versions never go back."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from protocol import Ack, Keys, Trajectory, decode
from services.metrics import read_metrics
from services.persistence import ReplayPersistence
from services.zsession import open_session
from tests.test_services import next_stats, watch_stats

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


def stored_state(run_dir, spec_env=ENV):
    """The replay's final state as its next restart would load it."""
    state, records = ReplayPersistence(run_dir / "replay").load(
        lambda payload: decode(payload, Trajectory))
    assert state is not None, "no complete snapshot in the run dir"
    assert list(records) == [], "a clean stop leaves nothing to replay from the log"
    return state


def test_replay_killed_with_sigkill_loses_no_acknowledged_fragment(
        procs, endpoint, session, tmp_path):
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
