"""A crowd against one replay server: many synthetic actors joining at once and sending as fast as
they are acknowledged, one of them (optionally) flooding garbage, while a learner asks for
batches.

    python bench/crowd.py                          # 64 actors + a flooder, 60 s, ~2 minutes
    python bench/crowd.py --actors 8 --seconds 10 --no-flood   # a quick look

A router and a replay server (real processes; the write-ahead log on, the rate limiter opened
wide), one crowd process: one Zenoh session with a publisher per actor key, each actor sending
real fragments of the task (collected once, re-stamped) with an actor's window (8 in flight),
and a flooder process of its own (as a misbehaving actor's host would be), publishing garbage on
its own actor key as fast as it can. This process plays the learner: sample requests one after
another, each reply's latency timed. Every second the replay's RSS is read.

Prints and writes (bench/out/crowd/results.json; `--save` also to docs/data/crowd/): fragments/s
acknowledged in all and per actor (min, median, max: whether anyone is starved), the
flooder's messages and how many the replay dropped on arrival, the learner's reply latency
(median, p99) and ready fraction, and the replay's RSS at start and at most (bounded by
back-pressure, not growing with the flood). These are timings: nothing else may run meanwhile.
"""

from __future__ import annotations

import argparse
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


def crowd(args) -> None:
    """The crowd process (`--crowd`): prints one JSON line when its time is up."""
    import numpy as np
    from capacity import RUN_ID, fragments_of

    from tpdeb.protocol import Ack, Keys, decode, encode
    from tpdeb.services.net.session import declare_publisher, open_session

    fragments = fragments_of(args.env_id, 16, args.seed)
    keys = Keys(RUN_ID)
    session = open_session("client", [], [args.endpoint])
    incarnation = int(np.random.default_rng(args.seed).integers(1, 2**62))
    windows = [threading.Semaphore(args.window) for _ in range(args.actors)]
    acked = [0] * args.actors

    def on_ack(sample) -> None:
        ack = decode(sample.payload.to_bytes(), Ack)
        if ack.incarnation == incarnation and ack.actor_id < args.actors:
            acked[ack.actor_id] += len(ack.seqs)
            for _ in range(len(ack.seqs)):
                windows[ack.actor_id].release()

    subscriber = session.declare_subscriber(keys.ack_all, on_ack)
    end = time.monotonic() + args.seconds

    def actor(i: int) -> None:
        publisher = declare_publisher(session, "traj", keys.traj(i))
        seq = 0
        while time.monotonic() < end:
            if not windows[i].acquire(timeout=0.5):
                continue
            publisher.put(encode(dataclasses.replace(fragments[seq % len(fragments)],
                                                     actor_id=i, incarnation=incarnation,
                                                     seq=seq)))
            seq += 1

    threads = [threading.Thread(target=actor, args=(i,)) for i in range(args.actors)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    time.sleep(1.0)  # the last acks
    print(json.dumps({"acked": acked, "steps_per_fragment": int(fragments[0].num_steps)}),
          flush=True)
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
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--actors", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--no-flood", dest="flood", action="store_false")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--save", action="store_true", help="also to docs/data/crowd/")
    parser.add_argument("--crowd", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--flooder", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.crowd:
        return crowd(args)
    if args.flooder:
        return flooder(args)
    import psutil
    from capacity import services, stop

    from tpdeb.services.launcher.plan import free_port

    OUT.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rss, probe = [], {"latency_ms": [], "ready": [], "replay_stats": {}}
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
                   str(args.seconds), "--window", str(args.window), "--seed", str(args.seed)]
            children = {role: subprocess.Popen([*cmd, f"--{role}"], cwd=ROOT, text=True,
                                               stdout=subprocess.PIPE, start_new_session=True)
                        for role in ("crowd", "flooder")[:1 + args.flood]}
            procs.extend(children.values())  # stopped with the services, also on failure
            while any(c.poll() is None for c in children.values()):
                rss.append(replay.memory_info().rss)
                time.sleep(1.0)
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
    report(args, child, probe, rss)


def report(args, child: dict, probe: dict, rss: list[int]) -> None:
    acked = child["acked"]
    per_s = [a / args.seconds for a in acked]
    latency = sorted(probe["latency_ms"]) or [float("nan")]
    result = {
        "env_id": args.env_id, "actors": args.actors, "seconds": args.seconds,
        "flood": args.flood, "fragments_per_s": sum(per_s),
        "env_steps_per_s": sum(per_s) * child["steps_per_fragment"],
        "per_actor_fragments_per_s": {"min": min(per_s), "median": statistics.median(per_s),
                                      "max": max(per_s)},
        "flood_sent": child["flood_sent"],
        "flood_dropped_on_arrival": probe["replay_stats"].get("bad/flood", float("nan")),
        "bad_messages": probe["replay_stats"].get("bad_messages", float("nan")),
        "learner_latency_ms": {"median": statistics.median(latency),
                               "p99": latency[int(0.99 * (len(latency) - 1))]},
        "learner_requests": len(probe["ready"]),
        "learner_ready_fraction": (sum(probe["ready"]) / len(probe["ready"])
                                   if probe["ready"] else float("nan")),
        "replay_rss_mib": {"start": rss[0] / 2**20, "max": max(rss) / 2**20}}
    text = json.dumps(result, indent=1)
    (OUT / "results.json").write_text(text)
    if args.save:
        DATA.mkdir(parents=True, exist_ok=True)
        (DATA / f"{args.env_id}__{args.actors}actors{'__flood' if args.flood else ''}.json"
         ).write_text(text)
    a = result["per_actor_fragments_per_s"]
    print(f"[crowd] {args.actors} actors{' + a flooder' if args.flood else ''}, "
          f"{args.seconds:g} s: {result['fragments_per_s']:,.0f} fragments/s acknowledged "
          f"({result['env_steps_per_s']:,.0f} env steps/s); per actor min {a['min']:.1f}, "
          f"median {a['median']:.1f}, max {a['max']:.1f}")
    print(f"[crowd] flooder: {result['flood_sent']:,} garbage messages sent, "
          f"{result['flood_dropped_on_arrival']:,.0f} dropped on arrival by the replay "
          f"({result['bad_messages']:,.0f} bad messages in all)")
    lat = result["learner_latency_ms"]
    print(f"[crowd] learner: {result['learner_requests']:,} requests, median "
          f"{lat['median']:.1f} ms, p99 {lat['p99']:.1f} ms, "
          f"{100 * result['learner_ready_fraction']:.0f} % with a batch")
    r = result["replay_rss_mib"]
    print(f"[crowd] replay RSS: {r['start']:.0f} MiB at start, {r['max']:.0f} MiB at most")


if __name__ == "__main__":
    main()
