"""A real network partition between an actor and the rest of the run.

Two network namespaces joined by a veth pair: `core` runs the replay server (its Zenoh router
listens on the core address) and the learner, `edge` runs one actor connected across the veth.
Once the learner trains, the link is cut for PARTITION_S (longer than the 10 s Zenoh lease, so
both sides close the transport), then restored, in two ways:

- blackhole: every packet leaving either end is dropped and nobody is told, as across a cable
  cut between two switches (a tbf qdisc smaller than any packet; needs `tc`);
- link-down: the edge end of the veth goes down, so the actor's kernel fails its sends at once
  (network unreachable) while the core side just loses carrier.

Nothing may die, the actor must reconnect, its fragments must be acknowledged again, the
learner's global step must advance again and the run must finish. A Zenoh client in `core`
(tests/watch.py) timestamps the services' stats and liveliness tokens; the recovery times are
printed. Needs root and `ip`.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from tests.netns import Namespaces, run, unavailable
from tests.procs import ROOT

ENV = "InvertedPendulum-v5"
RUN_ID = "partition"
PORT = 7447  # the namespaces are private: no other listener can hold it
PARTITION_S = 15.0
TOTAL_STEPS = 30_000
START_STEPS = 3_000  # the learner's global step that counts as "training"
FRAGMENT_STEPS = 64
RECOVERY_TIMEOUT_S = 30.0  # reconnect (≤ 4 s of Zenoh retry backoff) + resend (10 s) + margin
WATCH = str(ROOT / "tests" / "watch.py")
# Connects to a port nobody listens on: "refused" means the packet crossed and came back.
PROBE = """
import socket, sys
try:
    socket.create_connection((sys.argv[1], 9), timeout=float(sys.argv[2]))
except ConnectionRefusedError:
    print("reachable")
except OSError as e:
    print(f"unreachable ({type(e).__name__}: {e})")
"""


def probe(ns: str, host: str, timeout_s: float = 1.0) -> str:
    done = run("ip", "netns", "exec", ns, sys.executable, "-c", PROBE, host, str(timeout_s))
    return done.stdout.strip() or f"probe failed: {done.stderr.strip()}"


class Watch:
    """The events tests/watch.py printed so far."""

    def __init__(self, spaces: Namespaces, proc: subprocess.Popen):
        self.spaces, self.proc = spaces, proc

    def events(self) -> list[dict]:
        lines = self.spaces.output(self.proc).splitlines()
        return [json.loads(line) for line in lines if line.startswith("{") and line.endswith("}")]

    def stats(self, role: str, since: float = 0.0) -> list[dict]:
        return [e for e in self.events() if e.get("stats") == role and e["t"] >= since]

    def latest(self, role: str) -> dict:
        found = self.stats(role)
        return found[-1]["values"] if found else {}

    def first(self, role: str, since: float, until) -> dict | None:
        return next((e for e in self.stats(role, since) if until(e["values"])), None)


def wait_for(what: str, check, procs: dict[str, subprocess.Popen], spaces: Namespaces,
             timeout_s: float):
    """Poll `check()` until it returns something; fail at once if a service exits."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        for name, proc in procs.items():
            if proc.poll() is not None:
                raise AssertionError(f"{name} exited with {proc.returncode} while waiting for "
                                     f"{what}:\n{spaces.output(proc)[-3000:]}")
        time.sleep(0.2)
    logs = "\n".join(f"--- {name}\n{spaces.output(p)[-1500:]}" for name, p in procs.items())
    raise AssertionError(f"no {what} within {timeout_s:g} s\n{logs}")


@pytest.fixture
def spaces(tmp_path):
    if reason := unavailable():
        pytest.skip(reason)
    spaces = Namespaces(tmp_path, tag="part", net="10.232")
    try:
        try:
            spaces.create()
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"cannot set up network namespaces: {exc}")
        yield spaces
    finally:
        problems = spaces.close()  # stops every process by pid, deletes namespaces and veths
        assert not problems, "cleanup left things behind: " + "; ".join(problems)


CUTS = {
    "blackhole": (lambda s: s.set_blackhole(True), lambda s: s.set_blackhole(False)),
    "link-down": (lambda s: s.set_link(s.b, up=False), lambda s: s.set_link(s.b, up=True)),
}


@pytest.mark.parametrize("cut", CUTS)
def test_training_recovers_from_a_network_partition(spaces, tmp_path, cut, figures):
    core, edge = spaces.a, spaces.b
    cut_link, restore_link = CUTS[cut]
    if cut == "blackhole":
        try:  # sch_tbf may be missing from the kernel
            cut_link(spaces)
            restore_link(spaces)
        except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"cannot drop packets with a tbf qdisc: {exc}")
    endpoint = f"tcp/{spaces.addr_a}:{PORT}"
    common = ["--run-id", RUN_ID, "--env-id", ENV, "--num-envs", "2", "--seed", "1",
              "--total-timesteps", str(TOTAL_STEPS), "--fragment-len", str(FRAGMENT_STEPS),
              "--run-dir", str(tmp_path / "run")]
    replay = spaces.spawn(core, "replay", "-m", "tpdeb.services.replay", *common,
                          "--listen", endpoint)
    learner = spaces.spawn(core, "learner", "-m", "tpdeb.services.learner", *common,
                           "--connect", endpoint)
    actor = spaces.spawn(edge, "actor", "-m", "tpdeb.services.actor", *common,
                         "--connect", endpoint, "--actor-id", "0")
    watcher = spaces.spawn(core, "watch", WATCH, endpoint, RUN_ID)
    procs = {"replay": replay, "learner": learner, "actor": actor, "watch": watcher}
    watch = Watch(spaces, watcher)
    assert probe(edge, spaces.addr_a) == "reachable"

    wait_for(
        "training", lambda: watch.first("learner", 0, lambda v: v.get("updates", 0) > 0
                                        and v.get("global_step", 0) >= START_STEPS),
        procs, spaces, timeout_s=90)

    # -- the partition
    cut_at = time.time()
    cut_link(spaces)
    # Neither direction gets through (not even a refusal), checked from both ends.
    to_core, to_edge = probe(edge, spaces.addr_a), probe(core, spaces.addr_b)
    assert to_core.startswith("unreachable") and to_edge.startswith("unreachable"), (
        f"the cut link still passes traffic: edge→core {to_core}, core→edge {to_edge}")
    time.sleep(2.0)  # what was in flight at the cut has landed

    def received_steps(values: dict) -> int:
        # Inserted or held back by the rate limiter: what reached the replay. (Its inserted
        # steps alone may still grow while the learner drains what is held back.)
        return values["inserted_steps"] + FRAGMENT_STEPS * values["pending_fragments"]

    received = received_steps(watch.latest("replay"))
    wait_for("the partition's end", lambda: time.time() >= cut_at + PARTITION_S or None, procs,
             spaces, PARTITION_S + 5)
    before = {role: watch.latest(role) for role in ("learner", "replay")}
    restored_at = time.time()
    restore_link(spaces)
    partition_s = restored_at - cut_at
    # Nothing crossed: from 2 s after the cut the replay received nothing.
    during = [received_steps(e["values"]) for e in watch.stats("replay", cut_at + 2.0)
              if e["t"] < restored_at]
    assert during, "the replay published no stats during the partition"
    assert set(during) == {received}, f"steps reached the replay during the partition: {during}"
    assert probe(edge, spaces.addr_a, timeout_s=3.0) == "reachable"
    frozen_step = before["learner"]["global_step"]
    frozen_inserted = before["replay"]["inserted_steps"]

    # -- recovery: the actor reconnects, its fragments are acknowledged, the learner trains on
    arrival = wait_for("a fragment reaching the replay after the partition", lambda: watch.first(
        "replay", restored_at, lambda v: received_steps(v) > received),
        procs, spaces, RECOVERY_TIMEOUT_S)
    # The replay acknowledges a fragment once inserted; the actor counts each acknowledged
    # fragment once. At the link's return at most the fragments inserted by then were
    # acknowledged: a higher count means acks sent after the partition.
    ack = wait_for("a new acknowledgement at the actor", lambda: watch.first(
        "actor", restored_at, lambda v: v["acked"] > frozen_inserted // FRAGMENT_STEPS),
        procs, spaces, RECOVERY_TIMEOUT_S)
    progress = wait_for("learner progress after the partition", lambda: watch.first(
        "learner", restored_at, lambda v: v["global_step"] > frozen_step),
        procs, spaces, RECOVERY_TIMEOUT_S)
    reconnect = next((e for e in watch.events() if e.get("alive", "").endswith("/actor/0")
                      and e["up"] and e["t"] >= restored_at), None)
    lost = next((e for e in watch.events() if e.get("alive", "").endswith("/actor/0")
                 and not e["up"] and cut_at <= e["t"] <= restored_at), None)

    def after(event, start: float) -> str:
        return f"{event['t'] - start:+.1f} s" if event else "not seen"

    print(f"\npartition ({cut}): link cut for {partition_s:.1f} s at step {frozen_step:,}; the "
          f"actor's liveliness token dropped {after(lost, cut_at)} after the cut (lease). From the "
          f"link's return: actor's token back {after(reconnect, restored_at)}, first fragment "
          f"at the replay {after(arrival, restored_at)}, new acks counted by the actor "
          f"{after(ack, restored_at)}, learner's step advancing {after(progress, restored_at)} "
          "(stats every 1 s)")

    # -- the run finishes; nothing died on the way
    for name in ("learner", "actor", "replay"):  # each exits 0 (finish asserts it)
        spaces.finish(procs[name], 120 if name == "learner" else 30)
    assert watcher.poll() is None, spaces.output(watcher)
    done = [line for line in spaces.output(learner).splitlines() if "done at" in line]
    assert done, f"the learner did not reach its total:\n{spaces.output(learner)[-2000:]}"

    def since(event, start: float) -> float | None:
        return round(event["t"] - start, 2) if event else None

    figures.keep(f"partition-{cut}", {
        "cut": cut, "partition_s": round(partition_s, 2), "frozen_step": frozen_step,
        "token_dropped_after_cut_s": since(lost, cut_at),
        "from_link_return_s": {"actor_token_back": since(reconnect, restored_at),
                               "first_fragment_at_replay": since(arrival, restored_at),
                               "new_acks_at_actor": since(ack, restored_at),
                               "learner_advancing": since(progress, restored_at)},
        "stats_interval_s": 1.0})
