"""The capacity plan: how many actors one replay server, one router and one learner can feed,
measured on this machine with synthetic actors instead of environments.

    python bench/capacity.py                          # HalfCheetah-v5 fragments, ~6 minutes
    python bench/capacity.py --seconds 5 --actors 1   # a quick look
    python bench/capacity.py --report docs/data/capacity/*.json   # medians over kept runs

1. Replay ingest ceiling: a router and a replay server (real processes, the replay a client of
   the router as in a cluster) and 1, 2, 4 synthetic actors, each a process that sends real
   fragments of the task (collected once, re-stamped with new sequence numbers) as fast as they
   are acknowledged, its outbox as an actor's (2 × 4 envs in flight). The replay's rate limiter
   is opened wide (no learner samples), so what is measured is receiving, decoding, checking,
   inserting, logging and acknowledging: fragments/s and env steps/s, with the write-ahead log
   (`persist`, acknowledged once on disk) and without. CPU per second of the replay and router.
2. Router forwarding ceiling: the same synthetic senders publishing to a counting subscriber
   through the router alone (no replay, no acks): fragments/s forwarded.
3. Learner update ceiling per network size (64×64, 256×256) and batch (8, 16, 32 fragments):
   the compiled update's updates/s at one torch thread, the env steps/s that feeds at the
   preset's replay ratio, and the batch growth would keep (`max_batch_fragments`).
4. Learner ranks (`--ranks 2`: data-parallel learners, `learners = N`): N processes, one torch
   thread each, the compiled update with its gradients all-reduced over gloo as a cluster's
   ranks run it, for each network size at the presets' batch: updates/s per rank and what the
   group feeds (N × updates/s × batch steps ÷ the replay ratio) against N × one learner's.
5. One actor's acting rate per task (4 envs, its policy in numpy, one core).

Prints the figures and the plan (actors of each task one replay and one learner can feed, and
K replay shards and N learner ranks, each shard a replay's ceiling on its own core);
writes bench/out/capacity/results.json.
These are timings: nothing else may run meanwhile.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "out" / "capacity"
RUN_ID = "capacity"
SIZES = ((64, 64), (256, 256))


def fragments_of(env_id: str, count: int, seed: int) -> list:
    """`count` real fragments of the task from a fresh policy (the preset's length)."""
    from throughput import make_policy, preset_config

    from tpdeb.services.envs import make_vector_env
    from tpdeb.tpdeb_core.fragments import Collector

    config = preset_config(env_id, 4, seed)
    envs = make_vector_env(config.env_id, config.num_envs)
    try:
        spec, _, policy = make_policy(config, envs)
        collector = Collector(envs, policy, spec.fragment_len, spec.gamma, spec.action_low,
                              spec.action_high, seed=seed)
        fragments = []
        while len(fragments) < count:
            fragments.extend(collector.step())
    finally:
        envs.close()
    return fragments[:count]


# -- one synthetic actor (a process of its own: `--synthetic-actor`) -----------------------------


def synthetic_actor(args) -> None:
    """Send re-stamped fragments as fast as acknowledged (or, `--no-acks`, as fast as the
    publisher takes them) for `--seconds` after a 2 s warm-up; print one JSON line."""
    import numpy as np

    from tpdeb.protocol import Ack, Keys, decode, encode
    from tpdeb.services.net.session import declare_publisher, open_session

    fragments = fragments_of(args.env_id, 16, args.seed + args.actor_id)
    keys = Keys(RUN_ID)
    session = open_session("client", [], [args.endpoint])
    publisher = declare_publisher(session, "traj", keys.traj(args.actor_id))
    window = threading.Semaphore(args.window)
    acked = {"n": 0}
    incarnation = int(np.random.default_rng(args.actor_id).integers(1, 2**62))

    def on_ack(sample) -> None:
        ack = decode(sample.payload.to_bytes(), Ack)
        if ack.incarnation == incarnation:
            for _ in range(len(ack.seqs)):
                acked["n"] += 1
                window.release()

    subscriber = session.declare_subscriber(keys.ack(args.actor_id), on_ack)
    seq, start, counted_from = 0, time.perf_counter(), None
    warmup, end = start + 2.0, start + 2.0 + args.seconds
    while True:
        now = time.perf_counter()
        if counted_from is None and now >= warmup:
            counted_from = (acked["n"], seq, now, time.time())
        if now >= end:
            break
        if not args.no_acks and not window.acquire(timeout=1.0):
            continue
        fragment = dataclasses.replace(fragments[seq % len(fragments)], actor_id=args.actor_id,
                                       incarnation=incarnation, seq=seq)
        publisher.put(encode(fragment))
        seq += 1
    acked0, sent0, t0, wall0 = counted_from
    elapsed = time.perf_counter() - t0
    print(json.dumps({"actor": args.actor_id, "acked_per_s": (acked["n"] - acked0) / elapsed,
                      "sent_per_s": (seq - sent0) / elapsed, "window": [wall0, time.time()],
                      "steps_per_fragment": int(fragments[0].num_steps)}), flush=True)
    subscriber.undeclare()
    session.close()


def counting_subscriber(args) -> None:
    """Count the fragments the router forwards: from 1 s after the first to the last, once
    none has come for 2 s (or after --seconds + 60 s); one JSON line."""
    from tpdeb.protocol import Keys
    from tpdeb.services.net.session import open_session

    session = open_session("client", [], [args.endpoint])
    arrivals: list[float] = []
    subscriber = session.declare_subscriber(Keys(RUN_ID).traj_all,
                                            lambda sample: arrivals.append(time.perf_counter()))
    deadline = time.perf_counter() + args.seconds + 60.0
    while time.perf_counter() < deadline and not (
            arrivals and time.perf_counter() - arrivals[-1] > 2.0):
        time.sleep(0.2)
    subscriber.undeclare()
    session.close()
    counted = [t for t in arrivals if t >= arrivals[0] + 1.0] if arrivals else []
    rate = ((len(counted) - 1) / (counted[-1] - counted[0]) if len(counted) > 1
            else float("nan"))
    print(json.dumps({"forwarded_per_s": rate, "received": len(arrivals)}), flush=True)


# -- the parent: services, senders, CPU ----------------------------------------------------------


def spawn(argv: list[str], log: Path) -> subprocess.Popen:
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as out:
        return subprocess.Popen(argv, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)


def stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def services(args, endpoint: str, run_dir: Path, persist: bool | None,
             max_pending: int = 100000) -> list:
    """A router, and (persist not None) a replay server with its limiter opened wide."""
    py = sys.executable
    procs = [spawn([py, "-m", "tpdeb.services.router", "--listen", endpoint, "--run-id", RUN_ID],
                   OUT / "router.log")]
    if persist is not None:
        procs.append(spawn(
            [py, "-m", "tpdeb.services.replay", "--listen", "", "--connect", endpoint,
             "--run-id", RUN_ID, "--env-id", args.env_id, "--run-dir", str(run_dir),
             "--persist", str(persist).lower(), "--replay-ratio", "1",
             "--rate-error-buffer-steps", "1e15", "--max-pending-fragments", str(max_pending)],
            OUT / "replay.log"))
    time.sleep(args.startup_s)
    return procs


def senders(args, endpoint: str, n: int, no_acks: bool) -> list[dict]:
    py = sys.executable
    cmd = [py, str(Path(__file__).resolve()), "--env-id", args.env_id, "--endpoint", endpoint,
           "--seconds", str(args.seconds), "--seed", str(args.seed), "--window",
           str(args.window)]
    procs = [subprocess.Popen([*cmd, "--synthetic-actor", "--actor-id", str(i),
                               *(["--no-acks"] if no_acks else [])], cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              start_new_session=True) for i in range(n)]
    out = []
    for proc in procs:
        stdout, _ = proc.communicate(timeout=args.seconds + 120)
        lines = stdout.strip().splitlines()
        out.append(json.loads(lines[-1]) if lines else {"error": proc.returncode})
    return out


def ingest(args, persist: bool, n: int) -> dict:
    from procfs import CpuSampler

    from tpdeb.services.launcher.plan import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="capacity-") as tmp:
        procs = services(args, endpoint, Path(tmp), persist)
        sampler = CpuSampler(lambda: {i: p.pid for i, p in enumerate(procs)}, 0.2)
        sampler.start()
        try:
            sent = senders(args, endpoint, n, no_acks=False)
        finally:
            sampler.stop()
            stop(procs)
    windows = [s["window"] for s in sent if "window" in s]
    rates = sampler.per_second(max(w[0] for w in windows), min(w[1] for w in windows)) \
        if windows else {}
    cpu = [rates.get(i, float("nan")) for i in range(2)]
    fragments = sum(s.get("acked_per_s", 0.0) for s in sent)
    steps = fragments * max((s.get("steps_per_fragment", 0) for s in sent), default=0)
    row = {"persist": persist, "actors": n, "fragments_per_s": fragments,
           "env_steps_per_s": steps, "router_cpu": cpu[0], "replay_cpu": cpu[1],
           "senders": sent}
    print(f"[capacity] replay ingest, WAL {'on ' if persist else 'off'}, {n} sender(s): "
          f"{fragments:,.0f} fragments/s = {steps:,.0f} env steps/s; CPU/s replay "
          f"{cpu[1]:.2f}, router {cpu[0]:.2f}", flush=True)
    return row


def forwarding(args, n: int) -> dict:
    from tpdeb.services.launcher.plan import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs = services(args, endpoint, Path("."), None)
    try:
        counter = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--counting-subscriber",
             "--endpoint", endpoint, "--seconds", str(args.seconds)], cwd=ROOT,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
            start_new_session=True)
        senders(args, endpoint, n, no_acks=True)
        stdout, _ = counter.communicate(timeout=args.seconds + 120)
    finally:
        stop(procs)
    lines = stdout.strip().splitlines()
    forwarded = json.loads(lines[-1])["forwarded_per_s"] if lines else float("nan")
    print(f"[capacity] router forwarding, {n} sender(s): {forwarded:,.0f} fragments/s",
          flush=True)
    return {"senders": n, "forwarded_per_s": forwarded}


def learner_ceilings(args) -> list[dict]:
    from gpu import updates_per_s
    from throughput import preset_config, sample_batches

    rows = []
    for hidden in SIZES:
        for batch in args.batches:
            config = preset_config(args.env_id, 4, args.seed)
            config.hidden_sizes, config.batch_fragments = hidden, batch
            spec, fragments, batches = sample_batches(config, count=16)
            rate = updates_per_s(spec, config, fragments, batches, "cpu", 1, args.seconds)
            feeds = rate * config.batch_steps / config.replay_ratio
            print(f"[capacity] learner {'×'.join(map(str, hidden))}, batch {batch}: {rate:,.0f} "
                  f"updates/s, feeds {feeds:,.0f} env steps/s at replay ratio "
                  f"{config.replay_ratio:g}", flush=True)
            rows.append({"hidden": "×".join(map(str, hidden)), "batch_fragments": batch,
                         "updates_per_s": rate, "batch_steps": config.batch_steps,
                         "replay_ratio": config.replay_ratio, "feeds_env_steps_per_s": feeds})
    return rows


def learner_rank(args) -> None:
    """One learner rank (a child): the compiled update with the group's all-reduce, run for an
    agreed count of updates (every rank makes the same number, or one would wait on the others'
    all-reduce), timed; prints its updates/s."""
    import torch
    import torch.distributed as dist
    from throughput import prepared_learner, preset_config, sample_batches

    from tpdeb.services.ranks import Group

    config = preset_config(args.env_id, 4, args.seed)
    config.hidden_sizes = tuple(int(x) for x in args.hidden.split("x"))
    spec, fragments, batches = sample_batches(config, count=16)
    group = Group(args.rank, args.ranks, args.endpoint, torch.device("cpu"), 300.0)
    try:
        step, _, _ = prepared_learner(config, spec, fragments, batches, "cpu", 1,
                                      group.reducer())
        for _ in range(20):  # warm-up, and how fast the slowest rank goes
            step()
        started = time.perf_counter()
        for _ in range(20):
            step()
        count = torch.tensor([int(args.seconds * 20 / (time.perf_counter() - started))])
        dist.all_reduce(count, op=dist.ReduceOp.MIN)
        started = time.perf_counter()
        for _ in range(int(count)):
            step()
        elapsed = time.perf_counter() - started
        print(json.dumps({"rank": args.rank, "updates": int(count),
                          "updates_per_s": int(count) / elapsed}), flush=True)
    finally:
        group.close()


def rank_ceilings(args) -> list[dict]:
    """Per network size: `args.ranks` learner ranks as processes, their updates/s each and
    what the group feeds at the preset's replay ratio."""
    from throughput import preset_config

    from tpdeb.services.launcher.plan import free_port

    config = preset_config(args.env_id, 4, args.seed)
    rows = []
    for hidden in SIZES:
        name, label = "x".join(map(str, hidden)), "×".join(map(str, hidden))
        endpoint = f"127.0.0.1:{free_port()}"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--learner-rank", "--env-id",
               args.env_id, "--seconds", str(args.seconds), "--seed", str(args.seed),
               "--endpoint", endpoint, "--ranks", str(args.ranks), "--hidden", name]
        procs = [subprocess.Popen([*cmd, "--rank", str(r)], cwd=ROOT, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True, start_new_session=True)
                 for r in range(args.ranks)]
        got = []
        try:
            for proc in procs:
                stdout, _ = proc.communicate(timeout=args.seconds + 600)
                lines = stdout.strip().splitlines()
                if proc.returncode or not lines:
                    raise SystemExit(f"[capacity] learner rank {len(got)} of {args.ranks} "
                                     f"({name}) exited with {proc.returncode} and no figure")
                got.append(json.loads(lines[-1]))
        finally:
            stop(procs)
        rate = min(g["updates_per_s"] for g in got)
        feeds = args.ranks * rate * config.batch_steps / config.replay_ratio
        print(f"[capacity] {args.ranks} learner ranks {label}: {rate:,.0f} "
              f"updates/s each, feed {feeds:,.0f} env steps/s at replay ratio "
              f"{config.replay_ratio:g}", flush=True)
        rows.append({"hidden": label, "ranks": args.ranks,
                     "batch_fragments": config.batch_fragments, "updates_per_s": rate,
                     "per_rank": [g["updates_per_s"] for g in got],
                     "batch_steps": config.batch_steps, "replay_ratio": config.replay_ratio,
                     "feeds_env_steps_per_s": feeds})
    return rows


def grown(rows: list[dict], hidden: str) -> dict:
    """The learner row batch growth would settle on for a network: its rule
    (tpdeb_core.batch_growth) fed each batch size's measured seconds per update."""
    from tpdeb.tpdeb_core.batch_growth import BatchGrowth

    by_size = {r["batch_fragments"]: r for r in rows if r["hidden"] == hidden}
    growth = BatchGrowth(min(by_size), max(by_size), settle=0, window=1)
    while not growth.settled and growth.size in by_size:
        growth.observe(1.0 / by_size[growth.size]["updates_per_s"], 0.0)
    return by_size[growth.size if growth.size in by_size else growth.last[0]]


def acting_rates(args) -> dict[str, dict]:
    """Per task: env steps/s of one actor (4 envs, the policy in numpy, one core), and the
    preset's network and replay ratio."""
    from paper import TASKS
    from throughput import bench_acting_limit, preset_config

    rates = {}
    for env_id in TASKS:
        config = preset_config(env_id, 4, args.seed)
        rate = bench_acting_limit(config, args.seconds / 3)["env_steps_per_s"]
        rates[env_id] = {"env_steps_per_s": rate, "replay_ratio": config.replay_ratio,
                         "hidden": "×".join(map(str, config.hidden_sizes))}
        print(f"[capacity] one actor of {env_id}: {rate:,.0f} env steps/s", flush=True)
    return rates


def plan_table(result: dict) -> str:
    """Actors of each task that one replay (WAL on, the best sender count) and one learner
    (the task's network size) can feed; and, where learner ranks were timed, K replay shards
    and N ranks (K = N: each shard one replay's ceiling, each rank its measured rate)."""
    replay = max((r["env_steps_per_s"] for r in result["ingest"] if r["persist"]), default=0)
    rows = [dict(r, batch_fragments=r.get("batch_fragments", 8)) for r in result["learner"]]
    steps = {r["hidden"]: r["updates_per_s"] * r["batch_steps"] for r in rows
             if r["batch_fragments"] == 8}  # the presets' batch
    ranks = {r["hidden"]: r for r in result.get("ranks", [])}
    n = next(iter(ranks.values()))["ranks"] if ranks else 0
    out = ["| task | one actor (env steps/s) | actors one replay can feed | actors one learner "
           "can feed (its network, its replay ratio) | with batch growth (the batch it keeps) |"
           + (f" {n} replay shards | {n} learner ranks (each rank's updates/s ÷ one "
              "learner's) |" if n else ""),
           "|---|---|---|---|---|" + ("---|---|" if n else "")]
    for env_id, task in result["acting"].items():
        rate, ratio = task["env_steps_per_s"], task["replay_ratio"]
        feeds = steps.get(task["hidden"], float("nan")) / ratio
        kept = grown(rows, task["hidden"]) if any(r["hidden"] == task["hidden"] for r in rows) \
            else None
        growth = (f"{kept['updates_per_s'] * kept['batch_steps'] / ratio / rate:,.1f} "
                  f"({kept['batch_fragments']})" if kept else "—")
        line = (f"| {env_id} | {rate:,.0f} | {replay / rate:,.1f} | {feeds / rate:,.1f} "
                f"({task['hidden']}, {ratio:g}) | {growth} |")
        if n:
            group = ranks.get(task["hidden"])
            one = steps.get(task["hidden"])
            line += f" {n * replay / rate:,.1f} |" + (
                f" {n * group['updates_per_s'] * group['batch_steps'] / ratio / rate:,.1f} "
                f"({group['updates_per_s'] * group['batch_steps'] / one:.2f}) |"
                if group and one else " — |")
        out.append(line)
    return "\n".join(out)


def combine(results: list[dict]) -> dict:
    """One result of medians over runs: each run's best sender count for the replay (WAL on and
    off) and the router, the learner's updates/s per size, each task's acting rate."""
    from statistics import median

    def best(run: dict, part: str, key: str, **match) -> float:
        return max(r[key] for r in run[part] if all(r[k] == v for k, v in match.items()))

    ingest = [{"persist": persist, "env_steps_per_s": median(
        best(r, "ingest", "env_steps_per_s", persist=persist) for r in results),
        "runs": [best(r, "ingest", "env_steps_per_s", persist=persist) for r in results]}
        for persist in (True, False)]
    forwarding = [best(r, "forwarding", "forwarded_per_s") for r in results]
    def size(row: dict) -> tuple:
        return row["hidden"], row.get("batch_fragments", 8)

    learner = [dict(row, batch_fragments=size(row)[1], updates_per_s=median(
        x["updates_per_s"] for r in results for x in r["learner"] if size(x) == size(row)))
        for row in results[0]["learner"]]
    timed = [r for r in results if r.get("ranks")]  # runs that timed learner ranks
    ranks = []
    for row in timed[0]["ranks"] if timed else []:
        runs = [x["updates_per_s"] for r in timed for x in r["ranks"]
                if x["hidden"] == row["hidden"]]
        ranks.append(dict(row, updates_per_s=median(runs), runs=runs))
    acting = {env_id: dict(task, env_steps_per_s=median(
        r["acting"][env_id]["env_steps_per_s"] for r in results))
        for env_id, task in results[0]["acting"].items()}
    return {"runs": len(results), "ingest": ingest, "learner": learner, "ranks": ranks,
            "acting": acting,
            "forwarding": {"per_s": median(forwarding), "runs": forwarding}}


def report(paths: list[str]) -> None:
    combined = combine([json.loads(Path(p).read_text()) for p in paths])
    for row in combined["ingest"]:
        print(f"replay ingest, WAL {'on' if row['persist'] else 'off'}: median "
              f"{row['env_steps_per_s']:,.0f} env steps/s (runs: "
              f"{', '.join(f'{x:,.0f}' for x in row['runs'])})")
    fwd = combined["forwarding"]
    print(f"router forwarding: median {fwd['per_s']:,.0f} fragments/s (runs: "
          f"{', '.join(f'{x:,.0f}' for x in fwd['runs'])})")
    for row in combined["learner"]:
        print(f"learner {row['hidden']}, batch {row['batch_fragments']}: median "
              f"{row['updates_per_s']:,.0f} updates/s")
    for row in combined["ranks"]:
        print(f"{row['ranks']} learner ranks {row['hidden']}: median "
              f"{row['updates_per_s']:,.0f} updates/s each (runs: "
              f"{', '.join(f'{x:,.0f}' for x in row['runs'])})")
    print()
    print(plan_table(combined))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--seconds", type=float, default=15.0, help="each measurement")
    parser.add_argument("--window", type=int, default=8,
                        help="fragments in flight per synthetic actor (an actor's 2 × 4 envs)")
    parser.add_argument("--startup-s", type=float, default=4.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--batches", type=int, nargs="+", default=[8, 16, 32],
                        help="learner batch sizes (fragments) timed per network: what batch "
                        "growth (max_batch_fragments) would pick from")
    parser.add_argument("--ranks", type=int, default=2,
                        help="learner ranks timed together (0: none); 2 up to the cores")
    parser.add_argument("--report", nargs="+", metavar="RESULTS",
                        help="no runs: medians over these results.json files and the plan")
    # the children's roles
    parser.add_argument("--synthetic-actor", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--counting-subscriber", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--no-acks", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--actor-id", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--learner-rank", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--rank", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--hidden", default="64x64", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.ranks not in (0, *range(2, (os.cpu_count() or 1) + 1)):
        parser.error(f"--ranks {args.ranks}: 0 (no ranks timed) or from 2 to the machine's "
                     f"{os.cpu_count()} cores")
    if args.learner_rank:
        return learner_rank(args)
    if args.synthetic_actor:
        return synthetic_actor(args)
    if args.counting_subscriber:
        return counting_subscriber(args)
    if args.report:
        return report(args.report)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import provenance

    record = provenance.start()
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"cores": os.cpu_count(), "env_id": args.env_id, "args": vars(args),
              "ingest": [ingest(args, persist, n) for persist in (True, False)
                         for n in args.actors],
              "forwarding": [forwarding(args, n) for n in args.actors],
              "learner": learner_ceilings(args),
              "ranks": rank_ceilings(args) if args.ranks > 1 else [],
              "acting": acting_rates(args)}
    result["plan_markdown"] = plan_table(result)
    provenance.stamp(result, record)
    (OUT / "results.json").write_text(json.dumps(result, indent=1))
    print()
    print(result["plan_markdown"])
    print(f"[capacity] results in {OUT / 'results.json'}")


if __name__ == "__main__":
    main()
