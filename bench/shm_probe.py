"""Sample replies through Zenoh's shared memory or through TCP: which is faster on one host?

    python bench/shm_probe.py                 # 80 KB (a batch of 8 HalfCheetah fragments), 320
                                              # KB and 1.3 MB replies, 500 queries each way
    python bench/shm_probe.py --out docs/data/capacity/shm-probe.json
    python bench/shm_probe.py --cluster --out docs/data/capacity/shm-cluster.json
                                              # the default cluster with shared memory on and
                                              # off, alternated (~6 minutes)

Where a replay shard and a learner share a host, every sample reply (~79 KB for 8 × 64 steps)
crosses the router over TCP loopback: the replay's session copies it into a batch, the kernel
twice, the router once more, the learner's session into its buffer. Zenoh 1.x can instead hand
a reference to a shared-memory buffer between processes of one host (`zenoh.shm`). The probe
runs the path as the cluster does — a router, a replier process answering queries with a reply
of the size asked, the asking process — once with shared memory off (today's configuration:
`transport/shared_memory/enabled = false`, so that every byte crosses the link shim's path) and
once with it on, where the replier copies each encoded reply into a buffer from a provider (the
encoder writes bytes; there is no zero-copy encode), and reports the median round trip and the
replies per second one asker gets. Each reply is checked on arrival (its size, its first and
last byte, and whether it came as shared memory).

The replier's allocations collect the buffers the asker has dropped when the pool (64 of the
largest replies, 83 MB) runs out (`GarbageCollect`); blocking on a full pool instead
(`BlockOn` inside it) hung the replier once the pool was spent.

With `--cluster` it measures what the cluster gets of it: `tpdeb-cluster` on `--env-id` (its
preset, 2 actors × 4 envs, the learner on the CPU) trained for `--cluster-seconds`, with the
replay's, the learner's and the router's `shared_memory` on (the default) and off
(`TPDEB_SHARED_MEMORY=false`), `--pairs` times each, the order alternated: env steps/s, updates/s,
the CPU of each role per second, and the share of the learner's batches that came through shared
memory (its `perf/sample_replies_shared_memory`).

The machine must be otherwise idle: these are timings.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import provenance
import zenoh
from runs import alternation_arguments, save_result

from tpdeb.services.launcher.plan import free_port
from tpdeb.services.net.session import zenoh_config

ROOT = Path(__file__).resolve().parents[1]
KEY = "probe/sample"
SIZES = (80_000, 320_000, 1_300_000)


def config(mode: str, listen: list[str], connect: list[str], shm: bool):
    conf = zenoh_config(mode, listen, connect, connect_timeout_s=30)
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
    return conf


def serve(endpoint: str, shm: bool) -> None:
    """The replier: answers each query with a reply of the size its payload names."""
    session = zenoh.open(config("client", [], [endpoint], shm))
    provider = zenoh.shm.ShmProvider.default_backend(64 * max(SIZES)) if shm else None
    cache: dict[int, bytes] = {}

    def answer(query) -> None:
        size = int(query.payload.to_bytes())
        data = cache.setdefault(size, bytes([7]) + os.urandom(size - 2) + bytes([9]))
        if provider is not None:
            buf = provider.alloc(size, zenoh.shm.GarbageCollect())
            buf[0:size] = data  # the encoded reply copied into the shared buffer
            payload = zenoh.ZBytes(buf)
        else:
            payload = data
        query.reply(KEY, payload)
        query.drop()

    queryable = session.declare_queryable(KEY, answer)
    print("serving", flush=True)
    sys.stdin.read()  # until the asker closes our stdin
    queryable.undeclare()
    session.close()


def ask(session, size: int, queries: int) -> dict:
    times, shm_replies = [], 0
    for _ in range(queries):
        started = time.perf_counter()
        got = None
        for reply in session.get(KEY, payload=str(size).encode(), timeout=10.0):
            if reply.ok is None:
                raise RuntimeError(f"the replier failed: {reply.err.payload.to_string()}")
            got = reply.ok.payload
        data = got.to_bytes()  # the learner decodes from bytes
        times.append(time.perf_counter() - started)
        if got.as_shm() is not None:
            shm_replies += 1
        assert len(data) == size and data[0] == 7 and data[-1] == 9, "a damaged reply"
    median = statistics.median(times)
    return {"bytes": size, "queries": queries, "median_round_trip_us": round(1e6 * median, 1),
            "p90_round_trip_us": round(1e6 * sorted(times)[int(0.9 * queries)], 1),
            "replies_per_s": round(queries / sum(times), 1),
            "mb_per_s": round(size * queries / sum(times) / 1e6, 1),
            "replies_as_shared_memory": shm_replies}


def run_mode(shm: bool, queries: int) -> list[dict]:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    me = [sys.executable, __file__]
    router = subprocess.Popen([*me, "--role", "router", "--endpoint", endpoint, *(
        ["--shm"] if shm else [])], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    server = None
    try:
        assert router.stdout.readline().strip() == "routing"
        server = subprocess.Popen([*me, "--role", "serve", "--endpoint", endpoint, *(
            ["--shm"] if shm else [])], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert server.stdout.readline().strip() == "serving"
        session = zenoh.open(config("client", [], [endpoint], shm))
        try:
            time.sleep(0.5)  # the queryable's declaration reaches the router
            ask(session, SIZES[0], 200)  # warm-up
            return [ask(session, size, queries) for size in SIZES]
        finally:
            session.close()
    finally:
        for proc in (server, router):
            if proc is not None:
                proc.stdin.close()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def route(endpoint: str, shm: bool) -> None:
    session = zenoh.open(config("router", [endpoint], [], shm))
    print("routing", flush=True)
    sys.stdin.read()
    session.close()


def round_trips(args) -> dict:
    """One asker's round trips through the router, TCP and shared memory alternated."""
    result = {"modes": {}}
    for shm in (False, True, False, True):  # alternated: the second pair checks the first
        name = "shared_memory" if shm else "tcp"
        rows = run_mode(shm, args.queries)
        result["modes"].setdefault(name, []).append(rows)
        for row in rows:
            print(f"{name:>13} {row['bytes']:>9,} B: round trip "
                  f"{row['median_round_trip_us']:>8,.1f} µs median, "
                  f"{row['replies_per_s']:>7,.1f} replies/s, {row['mb_per_s']:>7,.1f} MB/s "
                  f"({row['replies_as_shared_memory']} as shared memory)", flush=True)
    for i, size in enumerate(SIZES):
        tcp = statistics.median(r[i]["median_round_trip_us"] for r in result["modes"]["tcp"])
        shm = statistics.median(r[i]["median_round_trip_us"]
                                for r in result["modes"]["shared_memory"])
        result.setdefault("ratio_tcp_over_shm", {})[str(size)] = round(tcp / shm, 3)
        print(f"{size:>9,} B: TCP {tcp:,.1f} µs, shared memory {shm:,.1f} µs: "
              f"{tcp / shm:.2f}× faster with shared memory")
    return result


def cluster_pairs(args) -> dict:
    """The default cluster with shared memory on and off, alternated."""
    from gpu import alternated

    return alternated(args, {
        "shared_memory": {"environ": {"TPDEB_SHARED_MEMORY": "true"}},
        "tcp": {"environ": {"TPDEB_SHARED_MEMORY": "false"}}},
        args.pairs, 2, ROOT / "bench" / "out" / "shm")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--queries", type=int, default=500, help="queries per size and mode")
    parser.add_argument("--out", type=Path, help="write the figures here as JSON")
    parser.add_argument("--cluster", action="store_true",
                        help="the default cluster with shared memory on and off, alternated")
    alternation_arguments(parser, 60.0)
    parser.add_argument("--role", choices=("router", "serve"), help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--shm", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role == "router":
        route(args.endpoint, args.shm)
        return 0
    if args.role == "serve":
        serve(args.endpoint, args.shm)
        return 0
    record = provenance.start()
    result = cluster_pairs(args) if args.cluster else round_trips(args)
    save_result(args.out, result, record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
