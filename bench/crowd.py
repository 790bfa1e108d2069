"""A crowd against one replay server: many synthetic actors joining at once and sending as fast as
they are acknowledged, one of them (optionally) flooding garbage, while a learner asks for
batches.

    python bench/crowd.py                          # 64 actors + a flooder, 60 s, ~2 minutes
    python bench/crowd.py --actors 8 --seconds 10 --no-flood   # a quick look

A router and a replay server (real processes; the write-ahead log on, the rate limiter opened
wide), one crowd process: one Zenoh session with a publisher per actor key, each actor sending
real fragments of the task (collected once, re-stamped) with an actor's window (8 in flight) and
its resend of what stays unacknowledged; the actors take turns, so an unfairness that shows is
the replay server's or the network's, not this process's. And a flooder process of its own (as
a misbehaving actor's host would be), publishing garbage on its own actor key as fast as it
can. This process plays the learner: sample requests one after another, each reply's latency
timed. Every second the replay's RSS and every process's CPU time are read.

Prints and writes (bench/out/crowd/results.json; `--save` also to docs/data/crowd/): fragments/s
acknowledged in all and per actor (min, median, max: whether anyone is starved), the fragments
resent (acks lost or late) and the duplicates the replay saw, the flooder's messages and how
many the replay dropped on arrival, the learner's reply latency (median, p99) and ready
fraction, the replay's RSS at start and at most (bounded by back-pressure, not growing with the
flood) and each process's CPU in cores. These are timings: nothing else may run meanwhile.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "crowd"
DATA = ROOT / "docs" / "data" / "crowd"
sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance  # noqa: E402


def crowd(args) -> None:
    """The crowd process (`--crowd`): prints one JSON line when its time is up. Each actor keeps
    what it sent in the actor's own outbox (the window) and, like a real actor, resends what is
    unacknowledged after `--resend-after-s` (an ack may be lost: acks are not resent)."""
    import numpy as np
    from capacity import RUN_ID, fragments_of

    from tpdeb.protocol import Ack, Keys, decode, encode
    from tpdeb.services.actor import Outbox
    from tpdeb.services.net.session import declare_publisher, open_session

    fragments = fragments_of(args.env_id, 16, args.seed)
    keys = Keys(RUN_ID)
    session = open_session("client", [], [args.endpoint])
    incarnation = int(np.random.default_rng(args.seed).integers(1, 2**62))
    outboxes = [Outbox(args.window) for _ in range(args.actors)]
    resent = [0] * args.actors
    acked = threading.Event()  # some window has room again

    def on_ack(sample) -> None:
        ack = decode(sample.payload.to_bytes(), Ack)
        if ack.incarnation == incarnation and ack.actor_id < args.actors:
            outboxes[ack.actor_id].ack(ack.seqs)
            acked.set()

    subscriber = session.declare_subscriber(keys.ack_all, on_ack)
    publishers = [declare_publisher(session, "traj", keys.traj(i)) for i in range(args.actors)]
    seqs = [0] * args.actors
    end = last_check = time.monotonic()
    end += args.seconds
    while (now := time.monotonic()) < end:
        # One round: every actor with room in its window sends one fragment. The actors take
        # turns, so whatever unfairness shows is the replay server's, not this process's.
        if now - last_check >= 0.5:
            for i, outbox in enumerate(outboxes):
                for _, payload in outbox.due(now, args.resend_after_s):
                    publishers[i].put(payload)
                    resent[i] += 1
            last_check = now
        ready = [i for i, outbox in enumerate(outboxes) if len(outbox) < args.window]
        if not ready:
            acked.wait(0.05)
            acked.clear()
        for i in ready:
            payload = encode(dataclasses.replace(fragments[seqs[i] % len(fragments)], actor_id=i,
                                                 incarnation=incarnation, seq=seqs[i]))
            outboxes[i].add(seqs[i], payload, time.monotonic())
            publishers[i].put(payload)
            seqs[i] += 1
    time.sleep(1.0)  # the last acks
    print(json.dumps({"acked": [o.acked for o in outboxes], "resent": resent,
                      "steps_per_fragment": int(fragments[0].num_steps)}), flush=True)
    subscriber.undeclare()
    session.close()


def flooder(args) -> None:
    """The flooder process (`--flooder`): garbage on actor key `args.actors`, as fast as it can,
    through a session of its own; prints how many it sent."""
    from capacity import RUN_ID

    from tpdeb.protocol import Keys
    from tpdeb.services.net.session import declare_publisher, open_session

    session = open_session("client", [], [args.endpoint])
    publisher = declare_publisher(session, "traj", Keys(RUN_ID).traj(args.actors))
    end, sent = time.monotonic() + args.seconds, 0
    while time.monotonic() < end:
        publisher.put(b"\x93garbage")
        sent += 1
    print(json.dumps({"flood_sent": sent}), flush=True)
    session.close()


def learner(endpoint: str, stop: threading.Event, out: dict) -> None:
    """Sample requests one after another: each reply's latency and whether it held a batch."""
    from capacity import RUN_ID

    from tpdeb.protocol import Keys, SampleReply, SampleRequest, Stats, decode, encode
    from tpdeb.services.net.session import open_session

    session = open_session("client", [], [endpoint])
    keys, request_id = Keys(RUN_ID), 0

    def on_stats(sample) -> None:
        out["replay_stats"] = decode(sample.payload.to_bytes(), Stats).values

    subscriber = session.declare_subscriber(keys.stats("replay", 0), on_stats)
    while not stop.is_set():
        request_id += 1
        started = time.perf_counter()
        ready = False
        for reply in session.get(keys.sample, payload=encode(SampleRequest(
                request_id=request_id, batch_size=8, beta=1.0)), timeout=10.0):
            if reply.ok is not None:
                ready = decode(reply.ok.payload.to_bytes(), SampleReply).ready
        out["latency_ms"].append(1e3 * (time.perf_counter() - started))
        out["ready"].append(ready)
    subscriber.undeclare()
    session.close()


def main() -> None:
    from tpdeb.services.config.service import ActorServiceConfig

    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--actors", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--resend-after-s", type=float, default=ActorServiceConfig.resend_after_s,
                        help="an unacknowledged fragment is sent again after this long "
                             "(default: the actor's, %(default)s)")
    parser.add_argument("--no-flood", dest="flood", action="store_false")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--save", action="store_true", help="also to docs/data/crowd/")
    parser.add_argument("--out", type=Path, default=OUT, help="results.json goes here")
    parser.add_argument("--crowd", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--flooder", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help="the router's (default: a free port on loopback)")
    args = parser.parse_args()
    args.record = provenance.start()
    if args.actors < 1 or args.window < 1 or args.seconds <= 0 or args.resend_after_s <= 0:
        parser.error("--actors and --window must be ≥ 1, --seconds and --resend-after-s > 0")
    if args.crowd:
        return crowd(args)
    if args.flooder:
        return flooder(args)
    import psutil
    from capacity import services, stop

    from tpdeb.services.launcher.plan import free_port

    args.out.mkdir(parents=True, exist_ok=True)
    endpoint = args.endpoint or f"tcp/127.0.0.1:{free_port()}"
    rss, cpu, probe = [], [], {"latency_ms": [], "ready": [], "replay_stats": {}}
    with tempfile.TemporaryDirectory(prefix="crowd-") as tmp:
        args.startup_s = 4.0
        procs = services(args, endpoint, Path(tmp), persist=True, max_pending=1024)
        done = threading.Event()
        sampler = threading.Thread(target=learner, args=(endpoint, done, probe), daemon=True)
        try:
            replay = psutil.Process(procs[1].pid)
            rss.append(replay.memory_info().rss)
            sampler.start()
            cmd = [sys.executable, str(Path(__file__).resolve()), "--endpoint", endpoint,
                   "--env-id", args.env_id, "--actors", str(args.actors), "--seconds",
                   str(args.seconds), "--window", str(args.window), "--seed", str(args.seed),
                   "--resend-after-s", str(args.resend_after_s)]
            children = {role: subprocess.Popen([*cmd, f"--{role}"], cwd=ROOT, text=True,
                                               stdout=subprocess.PIPE, start_new_session=True)
                        for role in ("crowd", "flooder")[:1 + args.flood]}
            procs.extend(children.values())  # stopped with the services, also on failure
            watched = {"router": psutil.Process(procs[0].pid), "replay": replay,
                       "learner": psutil.Process(),
                       **{role: psutil.Process(c.pid) for role, c in children.items()}}
            while all(c.poll() is None for c in children.values()):
                rss.append(replay.memory_info().rss)
                with contextlib.suppress(psutil.NoSuchProcess):  # a child just ended
                    cpu.append((time.monotonic(), {role: sum(p.cpu_times()[:2])
                                                   for role, p in watched.items()}))
                time.sleep(1.0)
            for c in children.values():
                c.wait()
            child = {"flood_sent": 0}
            for role, c in children.items():
                lines = c.stdout.read().strip().splitlines()
                if c.returncode != 0 or not lines:
                    raise SystemExit(f"[crowd] the {role} process failed (exit {c.returncode}); "
                                     "its error is above")
                child.update(json.loads(lines[-1]))
        finally:
            done.set()
            sampler.join(15)
            stop(procs)
    report(args, child, probe, rss, cores_used(cpu))


def _actor_sum(stats: dict, name: str, actors: int) -> float:
    """A replay ledger figure summed over the crowd's actors (NaN without the replay's stats)."""
    values = [stats[f"actor{i}/{name}"] for i in range(actors) if f"actor{i}/{name}" in stats]
    return sum(values) if values else float("nan")


def cores_used(cpu: list) -> dict[str, float]:
    """Each process's CPU in cores from 5 s after the start (imports, the fragments collected)
    to the last sample before the crowd's time was up."""
    if len(cpu) < 7:
        return {}
    (t0, start), (t1, end) = cpu[5], cpu[-1]
    return {role: (end[role] - start[role]) / (t1 - t0) for role in start}


def report(args, child: dict, probe: dict, rss: list[int], cores: dict[str, float]) -> None:
    acked = child["acked"]
    per_s = [a / args.seconds for a in acked]
    latency = sorted(probe["latency_ms"]) or [float("nan")]
    result = {
        "env_id": args.env_id, "actors": args.actors, "seconds": args.seconds,
        "flood": args.flood, "fragments_per_s": sum(per_s),
        "env_steps_per_s": sum(per_s) * child["steps_per_fragment"],
        "per_actor_fragments_per_s": {"min": min(per_s), "median": statistics.median(per_s),
                                      "max": max(per_s)},
        "acked_per_actor": acked,
        "resent": sum(child["resent"]),
        "actors_that_resent": sum(1 for r in child["resent"] if r),
        "replay_duplicates": _actor_sum(probe["replay_stats"], "duplicates", args.actors),
        "replay_dropped_busy": _actor_sum(probe["replay_stats"], "dropped_busy", args.actors),
        "flood_sent": child["flood_sent"],
        "flood_dropped_on_arrival": probe["replay_stats"].get("bad/flood", float("nan")),
        "bad_messages": probe["replay_stats"].get("bad_messages", float("nan")),
        "learner_latency_ms": {"median": statistics.median(latency),
                               "p99": latency[int(0.99 * (len(latency) - 1))]},
        "learner_requests": len(probe["ready"]),
        "learner_ready_fraction": (sum(probe["ready"]) / len(probe["ready"])
                                   if probe["ready"] else float("nan")),
        "replay_rss_mib": {"start": rss[0] / 2**20, "max": max(rss) / 2**20},
        "cores_used": cores}
    text = json.dumps(provenance.stamp(result, args.record), indent=1)
    (args.out / "results.json").write_text(text)
    if args.save:
        kept = DATA / f"{args.env_id}__{args.actors}actors{'__flood' if args.flood else ''}.json"
        kept.parent.mkdir(parents=True, exist_ok=True)
        kept.write_text(text)
        provenance.written(kept)
    a = result["per_actor_fragments_per_s"]
    print(f"[crowd] {args.actors} actors{' + a flooder' if args.flood else ''}, "
          f"{args.seconds:g} s: {result['fragments_per_s']:,.0f} fragments/s acknowledged "
          f"({result['env_steps_per_s']:,.0f} env steps/s); per actor min {a['min']:.1f}, "
          f"median {a['median']:.1f}, max {a['max']:.1f}")
    print(f"[crowd] {result['resent']:,} fragments resent by {result['actors_that_resent']} "
          f"actors (acks lost or late); the replay saw {result['replay_duplicates']:,.0f} "
          f"duplicates and turned {result['replay_dropped_busy']:,.0f} away while busy")
    print(f"[crowd] flooder: {result['flood_sent']:,} garbage messages sent, "
          f"{result['flood_dropped_on_arrival']:,.0f} dropped on arrival by the replay "
          f"({result['bad_messages']:,.0f} bad messages in all)")
    lat = result["learner_latency_ms"]
    print(f"[crowd] learner: {result['learner_requests']:,} requests, median "
          f"{lat['median']:.1f} ms, p99 {lat['p99']:.1f} ms, "
          f"{100 * result['learner_ready_fraction']:.0f} % with a batch")
    print("[crowd] CPU in cores: " + ", ".join(f"{role} {c:.2f}" for role, c in cores.items()))
    r = result["replay_rss_mib"]
    print(f"[crowd] replay RSS: {r['start']:.0f} MiB at start, {r['max']:.0f} MiB at most")


if __name__ == "__main__":
    main()
