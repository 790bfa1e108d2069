"""How much a snapshot stalls the replay server's loop, and how long a restore takes.

    python bench/replay_snapshot.py [--uniform-steps 8192,262144,1048576] [--seconds 3]
    python bench/replay_snapshot.py --out docs/data/replay-snapshot.json   # the figures kept

For each uniform-buffer size, a replay server (its real code, with a stand-in for the Zenoh
session) is filled with HalfCheetah-sized fragments (T 64, obs 17, act 6) through its own
ingest path — insert, append to the write-ahead log. Then the loop's work is timed op by op for
`--seconds`: ingest one fragment + fsync the log (what precedes an ack), and sample a batch of
16 fragments. First with nothing else going on, then while a snapshot is written in the
background. Reported: the capture (the only part of a snapshot on the loop thread), the
background write time and size, the ops' p50 / p99 / max latency idle vs during a snapshot, and
how long a new server takes to restore everything (snapshot + log).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import provenance

from tpdeb.protocol import Trajectory, decode, encode
from tpdeb.services.config.service import ReplayServiceConfig
from tpdeb.services.net.wire import run_spec
from tpdeb.services.process import StopSignal
from tpdeb.services.replay import ReplayServer

T, OBS, ACT = 64, 17, 6


class _Handle:
    def put(self, *_args, **_kwargs) -> None:
        pass

    def undeclare(self) -> None:
        pass


class _Liveliness:
    def declare_token(self, *_args, **_kwargs) -> _Handle:
        return _Handle()


class StandInSession:
    """What ReplayServer declares, doing nothing: the bench times the server's own work."""

    def declare_subscriber(self, *_args, **_kwargs) -> _Handle:
        return _Handle()

    declare_queryable = declare_publisher = declare_subscriber

    def liveliness(self) -> _Liveliness:
        return _Liveliness()


def fragment(rng: np.random.Generator, seq: int) -> bytes:
    f4 = np.float32
    return encode(Trajectory(
        actor_id=0, seq=seq, env_index=0, policy_version=0, reward_scale=1.0,
        obs=rng.standard_normal((T + 1, OBS)).astype(f4),
        actions=rng.standard_normal((T, ACT)).astype(f4), rewards=rng.standard_normal(T).astype(f4),
        terminated=np.zeros(T, bool), truncated=np.zeros(T, bool),
        behaviour_mean=np.zeros((T, ACT), f4), behaviour_log_std=np.zeros((T, ACT), f4),
        behaviour_logp=rng.standard_normal(T).astype(f4),
        trunc_index=np.zeros(0, np.int32), trunc_obs=np.zeros((0, OBS), f4),
        disc_returns=rng.standard_normal(T).astype(f4),
        td_abs=np.abs(rng.standard_normal(T)).astype(f4), incarnation=1))


def make_server(run_dir: Path, uniform_steps: int) -> ReplayServer:
    config = ReplayServiceConfig(env_id="HalfCheetah-v5", run_dir=str(run_dir),
                                 uniform_capacity_steps=uniform_steps, snapshot_interval_s=0)
    spec = run_spec(config, OBS, ACT, -np.ones(ACT), np.ones(ACT))
    server = ReplayServer(config, spec, StandInSession(), StopSignal())
    server.enable_persistence(run_dir / "replay")
    return server


def ingest(server: ReplayServer, payload: bytes) -> None:
    server._insert(decode(payload, Trajectory, server.spec))
    server.persistence.log(payload)


def time_ops(server: ReplayServer, payloads: list[bytes], seconds: float, until=None):
    """Latencies (ms) of alternating ingest+fsync and sample ops for `seconds` (or while
    `until()` holds)."""
    ingest_ms, sample_ms = [], []
    deadline = time.perf_counter() + seconds
    i = 0
    while time.perf_counter() < deadline if until is None else until():
        started = time.perf_counter()
        ingest(server, payloads[i % len(payloads)])
        server.persistence.sync()
        ingest_ms.append(1e3 * (time.perf_counter() - started))
        started = time.perf_counter()
        server.replay.sample(16)
        sample_ms.append(1e3 * (time.perf_counter() - started))
        i += 1
    return ingest_ms, sample_ms


def percentiles(values: list[float]) -> dict | None:
    """p50, p99 and max (ms) of one op's latencies, with their count."""
    if not values:
        return None
    ordered = sorted(values)
    return {"p50": statistics.median(ordered),
            "p99": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))],
            "max": ordered[-1], "n": len(ordered)}


def summary(values: list[float]) -> str:
    p = percentiles(values)
    return "-" if p is None else f"{p['p50']:.2f} / {p['p99']:.2f} / {p['max']:.1f}"


def run(uniform_steps: int, seconds: float) -> dict:
    rng = np.random.default_rng(0)
    payloads = [fragment(rng, i) for i in range(256)]
    with tempfile.TemporaryDirectory() as tmp:
        server = make_server(Path(tmp), uniform_steps)
        fill = (uniform_steps // T) + 64
        for i in range(fill):
            ingest(server, payloads[i % len(payloads)])
            if i % 2000 == 0:
                print(f"  filling {uniform_steps:,} steps: {i:,}/{fill:,} fragments", end="\r",
                      flush=True)
        server.persistence.sync()
        idle = time_ops(server, payloads, seconds)
        server.snapshot(wait=True)  # the first one also compacts the fill's log
        started = time.perf_counter()
        server.snapshot()
        capture_ms = server.persistence.last_capture_ms
        during = time_ops(server, payloads, 0, until=lambda: server.persistence.writing)
        write_s = time.perf_counter() - started
        snapshot_dir = sorted((Path(tmp) / "replay").glob("snapshot-*"))[-1]
        size_mb = sum(f.stat().st_size for f in snapshot_dir.iterdir()) / 2**20
        server.persistence.close()
        started = time.perf_counter()
        restored = make_server(Path(tmp), uniform_steps)
        restore_s = time.perf_counter() - started
        assert len(restored.replay) == len(server.replay), "restore lost fragments"
        restored.persistence.close()
    return {"uniform_steps": uniform_steps, "fragments": len(server.replay),
            "capture_ms": capture_ms, "write_s": write_s, "size_mb": size_mb,
            "ingest_idle": idle[0], "ingest_during": during[0],
            "sample_idle": idle[1], "sample_during": during[1], "restore_s": restore_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uniform-steps", default="8192,262144,1048576",
                        help="uniform buffer sizes in steps, comma-separated")
    parser.add_argument("--seconds", type=float, default=3.0, help="idle timing per size")
    parser.add_argument("--out", type=Path, help="keep the figures here (JSON)")
    args = parser.parse_args()
    record = provenance.start()
    rows = []
    for steps in (int(float(s)) for s in args.uniform_steps.split(",")):
        print(f"uniform buffer {steps:,} steps …", flush=True)
        rows.append(run(steps, args.seconds))
    print("\nop latency in ms: p50 / p99 / max\n")
    print("| uniform steps | fragments | capture on loop (ms) | write (s) | size (MB) | "
          "ingest+fsync idle | ingest+fsync during | sample idle | sample during | restore (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['uniform_steps']:,} | {r['fragments']:,} | {r['capture_ms']:.1f} | "
              f"{r['write_s']:.2f} | {r['size_mb']:.0f} | {summary(r['ingest_idle'])} | "
              f"{summary(r['ingest_during'])} | {summary(r['sample_idle'])} | "
              f"{summary(r['sample_during'])} | {r['restore_s']:.1f} |")
    if args.out is not None:
        ops = ("ingest_idle", "ingest_during", "sample_idle", "sample_during")
        kept = [{k: (percentiles(v) if k in ops else v) for k, v in r.items()} for r in rows]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(provenance.stamp(
            {"seconds": args.seconds, "latency_unit": "ms", "sizes": kept}, record), indent=1))
        provenance.written(args.out)
        print(f"\nfigures in {args.out}")


if __name__ == "__main__":
    main()
