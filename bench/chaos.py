"""Chaos, audited: a cluster run under a seeded schedule of faults, then a fragment-by-fragment
audit of what the replay holds against every acknowledgement that crossed the wire.

    python bench/chaos.py --minutes 30 --out docs/data/chaos-30.json   # half an hour
    python bench/chaos.py --minutes 3                                  # a quick check
    python bench/chaos.py --plan --seed 2                              # the schedule alone
    python bench/chaos.py --minutes 10 --shards 2 --learners 2         # replay shards, ranks
    python bench/chaos.py --minutes 3.2 --warmup-s 45 --calm-s 20 --shards 2 --learners 2 \
        --repeat hang:router:12       # one fault six times over (20 s calm between), judged alike

The run is the default cluster (deploy/local.toml: router, replay, learner, 2 actors × 4 envs)
on HalfCheetah-v5 with its preset, the actors behind `tpdeb-link` at an unlimited rate (so a
link exists to cut), trained for the chaos window plus `--calm-s` by the learner's clock
(`--train-for-seconds`): the run ends on its own and must exit 0. From `--warmup-s` on, every
10-30 s (after the previous fault ended) one fault, drawn with `--seed`:

- kill: SIGKILL of a service (router, replay, learner, actor-N; with `--shards K` and
  `--learners N` replay-k and learner-r, every shard and rank a target): the cluster restarts
  it (a learner rank with its whole group);
- hang: SIGSTOP of a service for 5-20 s, then SIGCONT: alive but silent, past Zenoh's 10 s
  lease for the longer ones (transports close; the service must reconnect);
- partition: SIGSTOP of the link for 5-20 s: the actors' side and the learner's side stay up,
  no byte crosses between them.

A Zenoh client on the router timestamps every acknowledgement and every stats message. Per
fault, the recovery time runs from the fault's end (the kill, the SIGCONT) to the first moment
both fragments are acknowledged again (the target actor's, or anyone's) and the learner has
published a parameter version newer than any before. At the end, from the replay's final state
(its snapshot, plus any log records after it): every (actor, incarnation, seq) acknowledged on
the wire must be stored, and stored once (the ledgers' count = distinct fragments = the
buffers' insert counter); parameter versions must never go back at the learner or at any actor
process (actors report their incarnation); the return must rise. The schedule, the faults as
injected, the recoveries and the audit go to `--out` (JSON) and a summary is printed. Exit
status 1 where anything was lost or duplicated, a version went back, or the run failed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import provenance  # noqa: E402
from bandwidth import UNLIMITED  # noqa: E402  the link is there, but never the bottleneck
from paper_report import compare  # noqa: E402
from procfs import cmdline, descendants, proc_table, service_name  # noqa: E402

from tpdeb.protocol import Ack, Keys, Stats, Trajectory, decode  # noqa: E402
from tpdeb.protocol.keys import ANY_SHARD  # noqa: E402
from tpdeb.services.net.session import open_session  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("kill", "hang", "partition")
GAP_S = (10.0, 30.0)
HOLD_S = (5.0, 20.0)
RECOVERY_LIMIT_S = 10.0  # a fault not recovered from within this long fails the run
RULE_VERSION = 2  # of `judge`; 1: no loss, no duplicate, versions monotone, last > first


def say(text: str) -> None:
    print(f"[chaos] {time.strftime('%H:%M:%S')} {text}", flush=True)


@dataclasses.dataclass
class Fault:
    at_s: float  # seconds after the run started
    kind: str  # kill | hang | partition
    target: str  # service name (the link for a partition)
    hold_s: float = 0.0  # how long a hang or partition lasts

    @property
    def end_s(self) -> float:
        return self.at_s + self.hold_s


def schedule(seed: int, start_s: float, end_s: float, services: list[str]) -> list[Fault]:
    """The faults between `start_s` and `end_s`: one every GAP_S after the previous one ended,
    kind and target drawn uniformly, hangs and partitions held for HOLD_S."""
    rng = random.Random(seed)
    faults, t = [], start_s
    while True:
        kind = rng.choice(KINDS)
        target = "link" if kind == "partition" else rng.choice(services)
        hold = 0.0 if kind == "kill" else round(rng.uniform(*HOLD_S), 1)
        if t + hold > end_s:
            return faults
        faults.append(Fault(round(t, 1), kind, target, hold))
        t += hold + rng.uniform(*GAP_S)


def repeated(spec: str, start_s: float, end_s: float, services: list[str]) -> list[Fault]:
    """One fault again and again between `start_s` and `end_s` (`kind:target[:hold_s]`, e.g.
    hang:router:12), the schedule's mean calm between them: to measure one recovery many times
    in one run."""
    parts = spec.split(":")
    kind, target = (parts + ["", ""])[:2]
    try:
        hold_s = 0.0 if kind == "kill" else float(parts[2]) if len(parts) == 3 else HOLD_S[0]
    except ValueError:
        hold_s = -1.0
    if len(parts) not in (2, 3) or kind not in KINDS or hold_s < 0 \
            or not (target == "link" if kind == "partition" else target in services):
        raise SystemExit(f"[chaos] --repeat {spec}: expected kind:target[:hold_s] with kind in "
                         f"{', '.join(KINDS)}, target one of {', '.join(services)} (link for a "
                         f"partition)")
    faults, t = [], start_s
    while t + hold_s <= end_s:
        faults.append(Fault(round(t, 1), kind, target, hold_s))
        t += hold_s + sum(GAP_S) / 2
    return faults


class Wire:
    """What crossed the router: every acknowledgement (first time seen) and every stats
    message, with arrival times (seconds since `t0`)."""

    def __init__(self, endpoint: str, run_id: str, t0: float, shards: int = 1):
        self.t0, self.lock = t0, threading.Lock()
        self.acks: dict[tuple[int, int, int], float] = {}
        self.stats: list[tuple[float, str, str, dict]] = []
        self.session = open_session("client", [], [endpoint], connect_timeout_s=60)
        keys = Keys(run_id)
        acks = (keys if shards == 1 else keys.of_shard(ANY_SHARD)).ack_all  # every shard's
        self.subscribers = [self.session.declare_subscriber(acks, self._on_ack),
                            self.session.declare_subscriber(keys.stats_all, self._on_stats)]

    def now(self) -> float:
        return time.monotonic() - self.t0

    def _on_ack(self, sample) -> None:
        ack, now = decode(sample.payload.to_bytes(), Ack), self.now()
        with self.lock:
            for seq in ack.seqs.tolist():
                self.acks.setdefault((ack.actor_id, ack.incarnation, seq), now)

    def _on_stats(self, sample) -> None:
        stats, now = decode(sample.payload.to_bytes(), Stats), self.now()
        with self.lock:
            self.stats.append((now, stats.role, stats.ident, dict(stats.values)))

    def copy(self) -> tuple[dict, list]:
        with self.lock:
            return dict(self.acks), list(self.stats)

    def close(self) -> None:
        self.session.close()


IN_FLIGHT_S = 0.05  # what a killed process sent just before it died may still arrive this late


def recovery_s(fault: Fault, acks: dict, stats: list) -> float | None:
    """Seconds from the fault's end until fragments are acknowledged again and the learner
    published a version newer than any before. After a kill the acknowledgement must be one the
    dead process could not have sent: after an actor's kill, one of its new incarnation; after
    another service's, one arriving more than IN_FLIGHT_S after the kill (no restarted process
    acknowledges sooner). After a hang or a partition, any acknowledgement after its end."""
    end = fault.end_s
    actor = int(fault.target.split("-")[1]) if fault.target.startswith("actor-") else None
    since = end + (IN_FLIGHT_S if fault.kind == "kill" and actor is None else 0.0)
    old = ({inc for (a, inc, _), t in acks.items() if a == actor and t <= end}
           if fault.kind == "kill" and actor is not None else set())
    ack = min((t for (a, inc, _), t in acks.items() if t > since
               and (actor is None or (a == actor and inc not in old))), default=None)
    before = max((v["param_version"] for t, r, i, v in stats
                  if (r, i) == ("learner", "0") and t <= end and "param_version" in v),
                 default=-1)  # rank 0's: the version the actors get
    newer = min((t for t, r, i, v in stats if (r, i) == ("learner", "0") and t > end
                 and v.get("param_version", -1) > before), default=None)
    if ack is None or newer is None:
        return None
    return round(max(ack, newer) - end, 2)


def versions_monotone(stats: list) -> dict[str, bool]:
    """Per process (the learner, rank 0 of a group; each actor incarnation): did its parameter
    version ever go back, in arrival order?"""
    series: dict[str, list[float]] = {}
    for _, role, ident, values in stats:
        if "param_version" not in values or (role, ident) != ("learner", "0") and role != "actor":
            continue
        key = role if role == "learner" else f"actor-{ident}/{values.get('incarnation', '?')}"
        series.setdefault(key, []).append(values["param_version"])
    return {k: all(a <= b for a, b in zip(v, v[1:], strict=False)) for k, v in series.items()}


def audit(acked: set[tuple[int, int, int]], ledgers: dict, inserted: int,
          logged: list[tuple[int, int, int]]) -> dict:
    """The replay's final state against the acknowledgements. `ledgers` as its snapshot keeps
    them (per actor: `windows` {incarnation: (low, above)}, every seq < low and those in
    `above` stored; `ingested`; `duplicates`, resends recognised), `inserted` its buffers'
    insert counter, `logged` the keys of log records after the snapshot (a restore inserts
    each). Lost: acknowledged, stored nowhere. Duplicated: insertions beyond the distinct
    fragments, a logged record the snapshot already holds among them."""
    def in_ledger(key) -> bool:
        actor, incarnation, seq = key
        window = ledgers.get(actor, {}).get("windows", {}).get(incarnation)
        return window is not None and (seq < window[0] or seq in window[1])

    distinct = sum(low + len(above) for ledger in ledgers.values()
                   for low, above in ledger["windows"].values())
    ingested = sum(ledger["ingested"] for ledger in ledgers.values())
    restored = set(logged)
    again = sum(map(in_ledger, restored)) + len(logged) - len(restored)
    lost = sorted(key for key in acked if key not in restored and not in_ledger(key))
    return {"acknowledged": len(acked), "stored": distinct + len(restored) - again,
            "ingested": ingested, "inserted": inserted, "lost": len(lost),
            "lost_examples": [list(k) for k in lost[:10]],
            "duplicated": max(ingested, inserted) - distinct + again,
            "resends_recognised": sum(ledger.get("duplicates", 0) for ledger in ledgers.values())}


def pid_of(cluster_pid: int, name: str, wait_s: float = 15.0) -> int | None:
    """The pid of the cluster's service `name` (waiting while it is being restarted)."""
    deadline = time.monotonic() + wait_s
    while True:
        table = proc_table()
        for pid in descendants(cluster_pid, table):
            if service_name(cmdline(pid)) == name:
                return pid
        if time.monotonic() > deadline:
            return None
        time.sleep(0.5)


def signal_pid(pid: int, sig: int) -> bool:
    try:
        os.kill(pid, sig)
        return True
    except ProcessLookupError:
        return False


class Chaos:
    """The cluster run with its faults injected, and the wire watched."""

    def __init__(self, args, run_dir: Path):
        self.args, self.run_dir = args, run_dir
        named = {"replay": args.shards, "learner": args.learners}
        self.services = ["router", *(role if n == 1 else f"{role}-{i}"
                                     for role, n in named.items() for i in range(n)),
                         *(f"actor-{i}" for i in range(2))]
        self.window = (args.warmup_s, args.warmup_s + 60.0 * args.minutes)
        self.faults = (repeated(args.repeat, *self.window, self.services) if args.repeat
                       else schedule(args.seed, *self.window, self.services))
        self.injected: list[dict] = []
        self.stopped: int | None = None  # a pid held with SIGSTOP right now
        self.cluster: subprocess.Popen | None = None
        self.wire: Wire | None = None
        self.shown = 0.0  # when the last progress line was printed

    def start(self) -> None:
        budget = self.window[1] + self.args.calm_s
        cmd = [sys.executable, "-m", "tpdeb.services.cluster", "--cluster-file",
               str(ROOT / "deploy" / "local.toml"), "--env-id", self.args.env_id,
               "--seed", str(self.args.seed), "--run-dir", str(self.run_dir),
               "--total-timesteps", str(10**9), "--train-for-seconds", str(budget),
               "--link-up-bytes-per-s", str(UNLIMITED), "--link-down-bytes-per-s", str(UNLIMITED),
               "--set", "log_interval_s=10", "--set", f"replay_shards={self.args.shards}",
               "--set", f"learners={self.args.learners}"]
        self.log = (self.run_dir.parent / "cluster.log").open("w")
        self.t0 = time.monotonic()
        self.cluster = subprocess.Popen(cmd, cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT,
                                        start_new_session=True)
        say(f"cluster pid {self.cluster.pid}, run dir {self.run_dir}, log {self.log.name}; "
            f"{len(self.faults)} faults from {self.window[0]:.0f} s to {self.window[1]:.0f} s, "
            f"training {budget:.0f} s by the learner's clock")
        spec = self.run_dir / "cluster.json"
        while not spec.is_file():
            if self.cluster.poll() is not None:
                raise SystemExit(f"[chaos] the cluster exited with {self.cluster.returncode} "
                                 f"before it started; see {self.log.name}")
            time.sleep(0.2)
        spec = json.loads(spec.read_text())
        self.wire = Wire(spec["endpoint"], spec["run_id"], self.t0, self.args.shards)

    def inject(self, fault: Fault) -> None:
        pid = pid_of(self.cluster.pid, fault.target)
        row = {**dataclasses.asdict(fault), "pid": pid, "at_s": round(self.wire.now(), 1)}
        if pid is None:
            row["skipped"] = "not running"
        elif fault.kind == "kill":
            signal_pid(pid, signal.SIGKILL)
        else:
            self.stopped = pid if signal_pid(pid, signal.SIGSTOP) else None
            self.sleep_until(row["at_s"] + fault.hold_s)
            if self.stopped is not None:
                row["resumed"] = signal_pid(pid, signal.SIGCONT)
                self.stopped = None
        row["end_s"] = round(self.wire.now(), 1)
        self.injected.append(row)
        what = {"kill": "kill -9", "hang": "SIGSTOP", "partition": "partition (link SIGSTOP)"}
        say(f"{row['at_s']:7.1f} s  {what[fault.kind]} {fault.target}"
            + (f" for {fault.hold_s:g} s" if fault.hold_s else "")
            + (f" (skipped: {row['skipped']})" if "skipped" in row else f" (pid {pid})"))

    def sleep_until(self, t: float) -> None:
        while (now := self.wire.now()) < t:
            if self.cluster.poll() is not None:
                raise SystemExit(f"[chaos] the cluster exited with {self.cluster.returncode} "
                                 f"at {now:.0f} s; see {self.log.name}")
            if now - self.shown >= 60:
                self.progress()
                self.shown = now
            time.sleep(min(0.5, t - now))

    def progress(self) -> None:
        acks, stats = self.wire.copy()
        learner = next((v for _, r, _, v in reversed(stats) if r == "learner"), {})
        say(f"{self.wire.now():7.0f} s  {len(self.injected)}/{len(self.faults)} faults, "
            f"{len(acks):,} fragments acknowledged, learner at {learner.get('global_step', 0):,}"
            f" steps, return {learner.get('mean_return', float('nan')):,.0f}")

    def run(self) -> int:
        for fault in self.faults:
            self.sleep_until(fault.at_s)
            self.inject(fault)
        say("chaos over; waiting for the run to end")
        deadline = time.monotonic() + self.args.calm_s + 900
        while self.cluster.poll() is None and time.monotonic() < deadline:
            time.sleep(1)
        if self.cluster.poll() is None:
            say("the run did not end in time: stopping it")
            self.stop()
        return self.cluster.returncode

    def stop(self) -> None:
        if self.stopped is not None:
            signal_pid(self.stopped, signal.SIGCONT)
        if self.cluster is not None and self.cluster.poll() is None:
            os.killpg(self.cluster.pid, signal.SIGINT)
            try:
                self.cluster.wait(120)
            except subprocess.TimeoutExpired:
                os.killpg(self.cluster.pid, signal.SIGKILL)
                self.cluster.wait()


def replay_keys(run_dir: Path, shards: int = 1) -> tuple[dict, int, list[tuple[int, int, int]]]:
    """The replay's final state: its ledgers, its insert counter and the keys of the log
    records after its snapshot — with shards, all of theirs (an actor writes to one shard, so
    their ledgers never share an actor)."""
    from tpdeb.services.store.persistence import ReplayPersistence

    ledgers, inserted, logged = {}, 0, []
    for name in ["replay"] if shards == 1 else [f"replay-{k}" for k in range(shards)]:
        state, records = ReplayPersistence(run_dir / name).load(
            lambda payload: decode(payload, Trajectory))
        if state is None:
            raise SystemExit(f"[chaos] no complete replay snapshot in {run_dir / name}")
        ledgers.update(state["ledgers"])
        inserted += state["replay"]["counters"]["inserted"]
        for payload in records:
            item = decode(payload, Trajectory)
            logged.append((item.actor_id, item.incarnation, item.seq))
    return ledgers, inserted, logged


def returns(run_dir: Path) -> dict:
    """Mean training return of the episodes in the first and the last 10 % of the steps."""
    from tpdeb.services.store.metrics import read_metrics

    return returns_of([(r["global_step"], r["charts/episodic_return"])
                       for r in read_metrics(run_dir / "metrics.jsonl")
                       if "charts/episodic_return" in r])


def returns_of(rows: list[tuple[int, float]]) -> dict:
    """(step, episodic return) pairs to the first and last 10 %'s means, stds and whether the
    last is above the first beyond the larger of the two stds."""
    if not rows:
        return {"first": None, "last": None, "learned": False}
    top = max(step for step, _ in rows)
    first = [r for s, r in rows if s <= 0.1 * top]
    last = [r for s, r in rows if s >= 0.9 * top]
    return {"first": round(statistics.fmean(first), 1), "last": round(statistics.fmean(last), 1),
            "first_std": round(statistics.stdev(first), 1) if len(first) > 1 else None,
            "last_std": round(statistics.stdev(last), 1) if len(last) > 1 else None,
            "first_episodes": len(first),
            "last_episodes": len(last), "steps": top,
            "learned": compare(last, first) == 1}


def summarise(chaos: Chaos, code: int) -> dict:
    acks, stats = chaos.wire.copy()
    for row in chaos.injected:
        if "skipped" not in row:
            fault = Fault(row["at_s"], row["kind"], row["target"], row["end_s"] - row["at_s"])
            row["recovery_s"] = recovery_s(fault, acks, stats)
    ledgers, inserted, logged = replay_keys(chaos.run_dir, chaos.args.shards)
    monotone = versions_monotone(stats)
    by_kind = {}
    for kind in KINDS:
        rows = [r for r in chaos.injected if r["kind"] == kind and "skipped" not in r]
        times = [r["recovery_s"] for r in rows if r["recovery_s"] is not None]
        by_kind[kind] = {"injected": len(rows), "recovered": len(times),
                         "skipped": sum(r["kind"] == kind and "skipped" in r
                                        for r in chaos.injected),
                         "within_limit": sum(t <= RECOVERY_LIMIT_S for t in times),
                         "median_s": round(statistics.median(times), 1) if times else None,
                         "max_s": round(max(times), 1) if times else None}
    return {"seed": chaos.args.seed, "minutes": chaos.args.minutes, "env_id": chaos.args.env_id,
            "replay_shards": chaos.args.shards, "learners": chaos.args.learners,
            "exit_code": code, "faults": chaos.injected, "by_kind": by_kind,
            "audit": audit(set(acks), ledgers, inserted, logged),
            "versions_monotone": all(monotone.values()),
            "version_series": {k: v for k, v in sorted(monotone.items())},
            "return": returns(chaos.run_dir)}


def report(result: dict) -> str:
    a, r = result["audit"], result["return"]
    lines = [f"| fault | injected | skipped | recovered | within {RECOVERY_LIMIT_S:g} s | "
             "median recovery (s) | max (s) |", "|---|---|---|---|---|---|---|"]
    for kind, k in result["by_kind"].items():
        lines.append(f"| {kind} | {k['injected']} | {k.get('skipped', '—')} | {k['recovered']} | "
                     f"{k.get('within_limit', '—')} | "
                     f"{k['median_s'] if k['median_s'] is not None else '—'} | "
                     f"{k['max_s'] if k['max_s'] is not None else '—'} |")
    lines += ["", f"fragments acknowledged {a['acknowledged']:,}, stored {a['stored']:,}: "
              f"{a['lost']} lost, {a['duplicated']} duplicated "
              f"({a['resends_recognised']:,} resends recognised)",
              f"parameter versions monotone at the learner and at all "
              f"{len(result['version_series']) - 1} actor processes: "
              f"{'yes' if result['versions_monotone'] else 'NO'}",
              f"return {r['first']} (± {r.get('first_std')}) in the first 10 % of steps → "
              f"{r['last']} (± {r.get('last_std')}) in the last "
              f"({r.get('steps', 0):,} steps); exit code {result['exit_code']}"]
    return "\n".join(lines)


def judge(result: dict) -> list[str]:
    """Why a chaos run fails (an empty list: it passes), by the rule fixed before the run
    (version RULE_VERSION): the run exits 0; no acknowledged fragment lost, none stored twice;
    parameter versions never go back; every scheduled fault was injected (a target not running
    when its fault came had not come back from the previous one, at least 10 s earlier) and
    recovered from within RECOVERY_LIMIT_S; and the return in the last 10 % of the steps is
    above the first 10 %'s by more than the larger std of their episodes."""
    a, r, why = result["audit"], result["return"], []
    if result["exit_code"] != 0:
        why.append(f"the run exited with {result['exit_code']}")
    if a["lost"] or a["duplicated"]:
        why.append(f"{a['lost']} acknowledged fragments lost, {a['duplicated']} duplicated")
    if not result["versions_monotone"]:
        why.append("a parameter version went back")
    for row in result["faults"]:
        name = f"{row['kind']} {row['target']} at {row['at_s']:.0f} s"
        if "skipped" in row:
            why.append(f"{name}: not injected ({row['skipped']})")
        elif row.get("recovery_s") is None:
            why.append(f"{name}: never recovered")
        elif row["recovery_s"] > RECOVERY_LIMIT_S:
            why.append(f"{name}: recovered in {row['recovery_s']:.1f} s > "
                       f"{RECOVERY_LIMIT_S:g} s")
    if not r["learned"]:
        why.append(f"the return did not rise beyond its episodes' spread: {r['first']} "
                   f"(± {r.get('first_std')}) in the first 10 % → {r['last']} "
                   f"(± {r.get('last_std')}) in the last")
    return why


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=30.0, help="the chaos window")
    p.add_argument("--seed", type=int, default=1, help="the run's seed and the schedule's")
    p.add_argument("--env-id", default="HalfCheetah-v5")
    p.add_argument("--warmup-s", type=float, default=60.0, help="calm before the first fault")
    p.add_argument("--calm-s", type=float, default=120.0, help="calm after the last fault")
    p.add_argument("--shards", type=int, default=1, help="replay shards (replay_shards)")
    p.add_argument("--learners", type=int, default=1, help="data-parallel learner ranks")
    p.add_argument("--out", type=Path, help="the result as JSON")
    p.add_argument("--repeat", metavar="KIND:TARGET[:HOLD_S]",
                   help="one fault over and over instead of the seeded schedule (e.g. "
                        "hang:router:12)")
    p.add_argument("--plan", action="store_true", help="print the schedule and exit")
    args = p.parse_args(argv)
    if args.minutes <= 0 or args.warmup_s < 0 or args.calm_s < 0:
        p.error("--minutes must be > 0, --warmup-s and --calm-s ≥ 0")
    if not 1 <= args.shards <= 2 or args.learners < 1:
        p.error("--shards must be 1 or 2 (one per actor of the default cluster), --learners ≥ 1")
    out = ROOT / "bench" / "out" / "chaos"
    chaos = Chaos(args, out / "run")
    if args.plan:
        for f in chaos.faults:
            print(f"{f.at_s:7.1f} s  {f.kind:9s} {f.target}"
                  + (f" for {f.hold_s:g} s" if f.hold_s else ""))
        return 0
    record = provenance.start()
    out.mkdir(parents=True, exist_ok=True)
    chaos.run_dir = Path(tempfile.mkdtemp(prefix="chaos-", dir=out)) / "run"
    try:
        chaos.start()
        code = chaos.run()
    finally:
        chaos.stop()
    result = provenance.stamp(summarise(chaos, code), record)
    chaos.wire.close()
    why = judge(result)
    provenance.add_verdict(result, "bench/chaos.py:judge", RULE_VERSION, not why, why)
    text = json.dumps(result, indent=1)
    (chaos.run_dir.parent / "result.json").write_text(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        provenance.written(args.out)
    print(report(result))
    for line in why:
        say(f"  {line}")
    say("FAIL" if why else "PASS")
    return 1 if why else 0


if __name__ == "__main__":
    sys.exit(main())
