"""The distributed services as real processes on loopback Zenoh: the replay server alone and
under a flood of bad messages, clear refusals, a killed actor, and the cluster learning."""

from __future__ import annotations

import os
import queue
import signal
import statistics
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
import zenoh

from tests.procs import ROOT, maps_torch, pids_with
from tpdeb.protocol import SCHEMA_VERSION, Keys, SampleReply, SampleRequest, Stats, decode, encode
from tpdeb.services.net.session import fetch_spec, open_session
from tpdeb.services.store.metrics import read_metrics

ENV = "InvertedPendulum-v5"


@pytest.fixture
def client(endpoint):
    sessions = []

    def connect():
        session = open_session("client", [], [endpoint], connect_timeout_s=30)
        sessions.append(session)
        return session

    yield connect
    for session in sessions:
        session.close()


def start_replay(procs, endpoint, tmp_path, *extra, run_id="t"):
    proc = procs.spawn("replay", "--run-id", run_id, "--listen", endpoint, "--env-id", ENV,
                       "--run-dir", str(tmp_path / "run"), *extra)
    procs.wait_for_line(proc, "serving")
    return proc


def watch_stats(session, keys: Keys) -> queue.Queue:
    inbox: queue.Queue = queue.Queue()
    session.declare_subscriber(keys.stats_all, lambda s: inbox.put(
        decode(s.payload.to_bytes(), Stats)))
    return inbox


def next_stats(inbox: queue.Queue, role: str, until, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            stats = inbox.get(timeout=1)
        except queue.Empty:
            continue
        if stats.role == role and until(stats.values):
            return stats.values
    raise AssertionError(f"no {role} stats satisfying the condition within {timeout_s} s")


def test_replay_alone_serves_spec_and_survives_a_flood_of_bad_messages(
        procs, endpoint, client, tmp_path):
    replay = start_replay(procs, endpoint, tmp_path, "--max-message-bytes", "1000000")
    session = client()
    keys = Keys("t")
    spec = fetch_spec(session, keys, 30)
    assert (spec.env_id, spec.obs_dim, spec.act_dim) == (ENV, 4, 1)
    inbox = watch_stats(session, keys)

    rng = np.random.default_rng(0)
    good = {"v": SCHEMA_VERSION, "type": "Trajectory", "body": {"actor_id": 3}}
    garbage = [rng.bytes(int(n)) for n in rng.integers(1, 2000, 100)]
    garbage += [msgpack.packb({**good, "v": 99}), msgpack.packb(good), msgpack.packb([1, 2]),
                b"\x00" * (2 * 2**20)]  # wrong version, missing fields, not a map, oversize
    # Each from a sender of its own (a bad message puts its sender in a penalty, during which
    # its next ones are dropped undecoded). BLOCK: on a loaded machine a DROP publisher may
    # shed part of the flood before it leaves.
    for i, payload in enumerate(garbage):
        session.declare_publisher(keys.traj(10 + i),
                                  congestion_control=zenoh.CongestionControl.BLOCK).put(payload)
    stats = next_stats(inbox, "replay", lambda v: v.get("bad_messages", 0) >= len(garbage))
    assert stats["bad_messages"] == len(garbage)
    assert stats.get("bad/msgpack", 0) > 0 and stats.get("bad/version") == 1
    assert stats.get("bad/size") == 1 and stats.get("bad/field", 0) >= 1
    assert stats["inserted_steps"] == 0  # nothing half-inserted

    # still serving: the spec again, and an honest "not ready" to a sample request
    assert fetch_spec(session, keys, 10).env_id == ENV
    replies = list(session.get(keys.sample, payload=encode(SampleRequest(
        request_id=1, batch_size=8, beta=0.4)), timeout=10))
    reply = decode(replies[0].ok.payload.to_bytes(), SampleReply)
    assert not reply.ready and reply.reason
    assert replay.poll() is None
    assert "dropped a bad message" in procs.output(replay)
    started = time.monotonic()
    replay.send_signal(signal.SIGTERM)  # closes its session and exits promptly
    assert replay.wait(10) == 0 and time.monotonic() - started < 5


def test_unknown_env_id_is_refused_with_one_line(procs, endpoint, tmp_path):
    actor = procs.spawn("actor", "--env-id", "InvertedPendulum-v9", "--connect", endpoint)
    assert actor.wait(60) == 2
    lines = procs.output(actor).strip().splitlines()
    assert len(lines) == 1 and "InvertedPendulum-v9" in lines[0], lines
    cluster = procs.spawn("cluster", "--env-id", "HalfCheeta-v5", "--run-dir",
                          str(tmp_path / "c"))
    assert cluster.wait(60) == 2
    out = procs.output(cluster)
    assert "HalfCheeta-v5" in out and "HalfCheetah-v5" in out  # names the likely fix


def test_actor_refuses_a_run_spec_mismatch(procs, endpoint, tmp_path):
    start_replay(procs, endpoint, tmp_path)
    actor = procs.spawn("actor", "--run-id", "t", "--env-id", "Hopper-v5", "--connect", endpoint)
    assert actor.wait(60) == 2
    lines = procs.output(actor).strip().splitlines()
    assert len(lines) == 1 and "run spec mismatch" in lines[0] and ENV in lines[0], lines


def test_actor_refuses_another_schema_version(procs, endpoint):
    # A replay server from another release: its run spec carries schema version 99.
    router = open_session("router", [endpoint], [])
    try:
        keys = Keys("t")
        old = msgpack.packb({"v": 99, "type": "RunSpec", "body": {}})
        queryable = router.declare_queryable(keys.spec, lambda q: q.reply(keys.spec, old))
        actor = procs.spawn("actor", "--run-id", "t", "--env-id", ENV, "--connect", endpoint)
        assert actor.wait(60) == 2
        out = procs.output(actor)
        assert "schema" in out and "99" in out, out
        queryable.undeclare()
    finally:
        router.close()


def test_killed_actor_does_not_stop_the_run(procs, endpoint, client, tmp_path):
    common = ["--run-id", "t", "--env-id", ENV, "--num-envs", "2", "--total-timesteps", "20000",
              "--run-dir", str(tmp_path / "run")]
    replay = start_replay(procs, endpoint, tmp_path, *common[4:])
    learner = procs.spawn("learner", *common, "--connect", endpoint)
    actors = [procs.spawn("actor", *common, "--connect", endpoint, "--actor-id", str(i),
                          name=f"actor-{i}") for i in range(2)]
    inbox = watch_stats(client(), Keys("t"))
    next_stats(inbox, "learner", lambda v: v.get("global_step", 0) >= 4000, timeout_s=120)
    # while they run: actors and the replay act, prioritise and sample without torch
    assert [maps_torch(p.pid) for p in (replay, *actors)] == [False, False, False]
    assert maps_torch(learner.pid)
    # each actor process names its run in its stats (what tells a restarted actor's versions
    # apart from its predecessor's): two processes, two names
    names, deadline = set(), time.monotonic() + 60
    while len(names) < 2 and time.monotonic() < deadline:
        names.add(next_stats(inbox, "actor", lambda v: "incarnation" in v)["incarnation"])
    assert len(names) == 2, f"actor stats named {names}"
    os.kill(actors[0].pid, signal.SIGKILL)
    assert learner.wait(240) == 0, procs.output(learner)
    assert actors[1].wait(30) == 0, procs.output(actors[1])
    assert actors[0].wait(5) == -signal.SIGKILL
    steps = [r["global_step"] for r in read_metrics(tmp_path / "run" / "metrics.jsonl")]
    assert max(steps) >= 20000


@pytest.mark.slow
def test_cluster_learns_inverted_pendulum(procs, tmp_path):
    run_dir = tmp_path / "run"
    cluster = procs.spawn("cluster", "--env-id", ENV, "--total-timesteps", "100000",
                          "--seed", "1", "--run-dir", str(run_dir))
    assert cluster.wait(540) == 0, procs.output(cluster)[-3000:]
    rows = read_metrics(run_dir / "metrics.jsonl")
    returns = [r["charts/episodic_return"] for r in rows if "charts/episodic_return" in r]
    assert statistics.mean(returns[-20:]) >= 800, returns[-20:]
    keys = set().union(*rows)
    for key in ("charts/SPS", "losses/policy_loss", "replay/prioritized_items",
                "actor/param_version_lag", "perf/update_ms"):
        assert key in keys, key
    assert max(r["global_step"] for r in rows) >= 100000
    shared = [r["perf/sample_replies_shared_memory"] for r in rows
              if "perf/sample_replies_shared_memory" in r]
    assert shared and max(shared) == 0.0, shared  # shared memory is off unless asked for
    assert list(run_dir.glob("events.out.tfevents.*"))
    assert 'env_id = "InvertedPendulum-v5"' in (run_dir / "config.toml").read_text()
    assert list((run_dir / "checkpoints").glob("final_*.pt"))
    assert {"replay.log", "learner.log", "actor-0.log", "actor-1.log"} <= {
        p.name for p in (run_dir / "logs").iterdir()}


def test_ctrl_c_stops_the_cluster_in_order_with_a_checkpoint(procs, tmp_path):
    run_dir = tmp_path / "run"
    cluster = procs.spawn("cluster", "--env-id", ENV, "--total-timesteps", "1000000",
                          "--num-envs", "2", "--run-dir", str(run_dir))
    procs.wait_for_line(cluster, "[learner] tpdeb-learner: [", timeout_s=120)  # training
    cluster.send_signal(signal.SIGINT)
    assert cluster.wait(60) == 130, procs.output(cluster)[-3000:]
    out = procs.output(cluster)
    assert "SIGINT: stopping the services" in out
    # stopped before its end: a periodic checkpoint, which the next start resumes from
    names = [p.name for p in (run_dir / "checkpoints").glob("*.pt")]
    assert any(n.startswith("ckpt_") for n in names), out[-3000:]
    assert not any(n.startswith("final_") for n in names)
    assert not pids_with(str(run_dir))  # every service is gone


def test_cluster_behind_a_throttled_link_reports_what_crossed_it(procs, tmp_path):
    run_dir = tmp_path / "run"
    # shared memory on for the replay, the learner and the router: never past the link
    cluster = procs.spawn(
        "cluster", "--env-id", ENV, "--total-timesteps", "6000", "--num-envs", "2",
        "--run-dir", str(run_dir), "--link-up-bytes-per-s", "32768",
        "--link-down-bytes-per-s", "131072", "--link-latency-ms", "20",
        "--set", "log_interval_s=1", "--set", "trajectory_compression=zstd",
        "--set", "params_dtype=float16", env={"TPDEB_SHARED_MEMORY": "true"})
    assert cluster.wait(300) == 0, procs.output(cluster)[-3000:]
    rows = read_metrics(run_dir / "metrics.jsonl")
    link = [r for r in rows if "link/up_bytes_per_s" in r]
    assert link, "no link/* metrics"
    for key in ("link/down_bytes_per_s", "link/queue_bytes", "link/latency_ms",
                "link/up_bytes_per_env_step"):
        assert key in link[-1], key
    # the setting bounds what went up (per-second readings jitter a little around it)
    assert max(r["link/up_bytes_per_s"] for r in link) <= 1.2 * 32768
    assert min(r["link/latency_ms"] for r in link) >= 20
    # every fragment crossed the link: the bytes per env step are the fragments' size, not a
    # shared-memory side channel (an InvertedPendulum step is ~40 bytes compressed)
    assert link[-1]["link/up_bytes_per_env_step"] > 20
    shared = [r["perf/sample_replies_shared_memory"] for r in rows
              if "perf/sample_replies_shared_memory" in r]
    # while the batches came through it (the first ones may cross before the link's shared
    # memory is set up: lazily, at its first large message)
    assert shared and statistics.median(shared) == 1.0 and shared[-1] == 1.0, shared
    assert "⇄" in (run_dir / "logs" / "link.log").read_text()


def test_a_session_close_that_times_out_does_not_fail_a_finished_process(capsys):
    import zenoh

    from tpdeb.services.net.session import close_session

    class Stuck:
        def close(self):
            raise zenoh.ZError("close operation timed out! at zenoh/src/api/close.rs:135.")

    close_session(Stuck(), "tpdeb-learner")  # no exception: the process exits as it would
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "close operation timed out!" in out[0] and "close.rs" not in out[0]


def test_health_follows_each_services_token_and_auto_ids_are_unique(procs, endpoint, tmp_path):
    """`tpdeb-health ROLE` (a container's healthcheck) from the service's own variables:
    1 before the replay serves, 0 once it holds its token; identical actors started with
    `--actor-id auto` get distinct ids from the replay and each holds its own token."""
    env = {"TPDEB_RUN_ID": "t", "TPDEB_CONNECT": endpoint}

    def health(role: str, *flags: str) -> tuple[int, str]:
        proc = procs.spawn("health", role, "--timeout-s", "2", *flags, env=env,
                           name=f"health-{role}-{len(procs.started)}")
        return proc.wait(60), procs.output(proc)

    code, out = health("replay")
    assert code == 1 and "no Zenoh router answered" in out, out
    start_replay(procs, endpoint, tmp_path)
    assert health("replay")[0] == 0
    assert health("router", "--listen", endpoint)[0] == 0  # the replay's router takes connections
    code, out = health("learner")
    assert code == 1 and "holds no token tpdeb/t/alive/learner/0" in out, out
    actors = [procs.spawn("actor", "--actor-id", "auto", "--num-envs", "1", "--env-id", ENV,
                          env=env, name=f"actor-auto-{i}") for i in range(2)]
    for actor in actors:
        procs.wait_for_line(actor, "from the replay server (--actor-id auto)")
    ids = sorted(int(procs.output(a).split("actor id ")[1].split()[0]) for a in actors)
    assert ids == [0, 1]
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and [health("actor", "--actor-id", str(i))[0]
                                           for i in ids] != [0, 0]:
        time.sleep(0.5)
    assert [health("actor", "--actor-id", str(i))[0] for i in ids] == [0, 0]
    assert health("actor", "--actor-id", "7")[0] == 1


@pytest.mark.parametrize("argv", [[], ["replayer"], ["replay", "--timeout-s"],
                                  ["replay", "--timeout-s", "0"]])
def test_health_refuses_bad_usage_with_status_2(argv, capsys):
    from tpdeb.services import health

    assert health.main(argv) == 2
    assert "usage: tpdeb-health {router,replay,learner,actor,evaluator}" in capsys.readouterr().err


def test_a_signal_arriving_while_the_stop_lock_is_held_cannot_deadlock():
    """The handler runs on the main thread between two bytecodes — here while that thread holds
    the lock of the stop event, as inside a wait or a first signal's handling. It must not take
    that lock (it used to: a second SIGTERM hung a service for good)."""
    code = ("import signal; from tpdeb.services.process import StopSignal\n"
            "stop = StopSignal().install()\n"
            "with stop.event._cond:\n"
            "    signal.raise_signal(signal.SIGTERM)\n"
            "    signal.raise_signal(signal.SIGINT)\n"
            "    assert stop and stop.reason == 'SIGTERM'\n"
            "assert stop.wait(5) and stop.event.is_set()\n"
            "print('stopped', stop.reason)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 0 and done.stdout.strip() == "stopped SIGTERM", done.stderr


def test_a_storm_of_sigterms_stops_a_service_cleanly(procs, endpoint, tmp_path):
    replay = start_replay(procs, endpoint, tmp_path)
    for _ in range(50):
        os.kill(replay.pid, signal.SIGTERM)
    assert replay.wait(30) == 0, procs.output(replay)
    assert "stopped (SIGTERM)" in procs.output(replay)
