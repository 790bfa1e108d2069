"""Throughput benchmark: how close the distributed pieces come to their in-process limits.

    python bench/throughput.py                  # HalfCheetah-v5, 10 s parts, 60k-step runs
    python bench/throughput.py --seconds 3 --total-timesteps 15000     # a quick look

Everything is measured in one run on one machine (figures, not pass/fail):

1. env limit: one process steps `make_vector_env(env_id, num_envs)` with precomputed random
   actions, no policy; env steps/s = vector steps × num_envs.
2. actor: the same env inside `tpdeb_core.fragments.Collector` with an ActorCritic (torch 1
   thread, as tpdeb-actor), every fragment also encoded to wire bytes; steps/s and its ratio to 1.
3. learner in memory: `Learner.step` on batches of `batch_fragments` real fragments (collected once)
   for `--seconds`, with torch at 1 thread and at its default thread count.
4. clusters: `python -m services.cluster` with 1 and then 2 actors (`--num-envs` each). The
   cluster's stdout is read line by line and every line is time-stamped on arrival; the learner's
   progress lines (every `--log-interval-s`) carry env steps and update counts, so rates over the
   steady part come from wall-clock differences between those lines. The first learner update is
   timed by a Zenoh client of this script subscribed to the learner's parameter broadcasts (the
   learner publishes version n right after update n). RSS of the cluster process and all its
   descendants is sampled every 0.2 s from /proc.

Writes `bench/out/throughput/results.json` (and the clusters' logs and run dirs beside it) and
prints a markdown table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from procfs import cmdline, descendants, proc_table, rss_kib, service_name

from protocol import DecodeError, Keys, Params, decode, encode
from services.envs import make_vector_env, space_dims
from services.train_config import TrainConfig
from services.wire import fragment_to_message, load_params, model_for, params_message, run_spec
from services.zsession import open_session
from tpdeb_core.fragments import Collector
from tpdeb_core.learner import Learner

ROOT = Path(__file__).resolve().parents[1]
GOAL = 0.9

PROGRESS = re.compile(r"^\[learner\] tpdeb-learner: \[\s*([\d,]+)/[\d,]+\] SPS\s+(\S+) \|"
                      r".*\| updates ([\d,]+) \|")
ACTOR_UP = re.compile(r"^\[actor(?:-\d+)?\] tpdeb-actor: actor (\d+): ")
ACTOR_END = re.compile(r"actor (\d+) stopped \(([^)]*)\): ([\d,]+) steps, (\d+) fragments sent, "
                       r"(\d+) acknowledged, (\d+) resent")
REPLAY_END = re.compile(r"tpdeb-replay: stopped \(([^)]*)\); ([\d,]+) steps ingested, (\d+) bad")
PROBLEM = re.compile(r"traceback|error|exception|exited with code|ended with code|dropped|"
                     r"warning|no actor|did not come up", re.IGNORECASE)
# Not problems: MuJoCo's deprecation notice on loading HalfCheetah's XML (every env prints it),
# a clean replay stop, the learner's normal exit.
BENIGN = re.compile(r"settotalmass|, 0 bad messages dropped|learner exited with code 0$")


def say(text: str) -> None:
    print(f"[bench] {text}", flush=True)


def num(text: str) -> int:
    return int(text.replace(",", ""))


# ----------------------------------------------------------------------------- in process

def bench_env(env_id: str, num_envs: int, seconds: float, seed: int) -> dict:
    envs = make_vector_env(env_id, num_envs)
    try:
        envs.reset(seed=[seed + i for i in range(num_envs)])
        envs.action_space.seed(seed)
        actions = [envs.action_space.sample() for _ in range(1024)]
        for i in range(200):  # warm-up
            envs.step(actions[i % len(actions)])
        steps, start = 0, time.perf_counter()
        while (elapsed := time.perf_counter() - start) < seconds:
            for i in range(100):
                envs.step(actions[(steps + i) % len(actions)])
            steps += 100
    finally:
        envs.close()
    return {"env_steps_per_s": steps * num_envs / elapsed, "vector_steps": steps,
            "seconds": elapsed}


def make_collector(env_id: str, num_envs: int, seed: int):
    config = TrainConfig(env_id=env_id, num_envs=num_envs, seed=seed)
    envs = make_vector_env(env_id, num_envs)
    spec = run_spec(config, *space_dims(envs))
    model = model_for(spec)
    collector = Collector(envs, model, spec.fragment_len, spec.gamma, spec.action_low,
                          spec.action_high, seed=seed)
    return config, spec, envs, model, collector


def bench_actor(env_id: str, num_envs: int, seconds: float, seed: int) -> dict:
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    _, _, envs, model, collector = make_collector(env_id, num_envs, seed)
    try:
        def run(duration: float) -> tuple[int, int, int, float]:
            steps0, frags, nbytes = collector.env_steps, 0, 0
            start = time.perf_counter()
            while (elapsed := time.perf_counter() - start) < duration:
                for fragment in collector.step():
                    nbytes += len(encode(fragment_to_message(fragment, model.reward_scale())))
                    frags += 1
            return collector.env_steps - steps0, frags, nbytes, elapsed

        run(1.0)  # warm-up
        steps, frags, nbytes, elapsed = run(seconds)
        # What one parameter load costs the actor (decode + load_state_dict), measured apart:
        # the real actor does it between env steps whenever new parameters arrived.
        payload = encode(params_message(model, 1))
        loads, start = 0, time.perf_counter()
        while time.perf_counter() - start < min(2.0, seconds / 2) or loads < 20:
            load_params(model, decode(payload, Params))
            loads += 1
        load_ms = 1e3 * (time.perf_counter() - start) / loads
    finally:
        envs.close()
    return {"env_steps_per_s": steps / elapsed, "env_steps": steps, "fragments": frags,
            "fragment_bytes_mean": nbytes / max(frags, 1), "seconds": elapsed,
            "torch_threads": 1, "param_load_ms": load_ms, "params_bytes": len(payload)}


def collect_fragments(env_id: str, num_envs: int, count: int, seed: int):
    config, spec, envs, model, collector = make_collector(env_id, num_envs, seed)
    fragments = []
    try:
        while len(fragments) < count:
            fragments.extend(collector.step())
    finally:
        envs.close()
    return config, spec, fragments[:count]


def bench_learner(config: TrainConfig, spec, fragments, seconds: float, threads: int,
                  seed: int) -> dict:
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    model = model_for(spec)
    learner = Learner(model, config.loss_config())
    for fragment in fragments:  # realistic normaliser statistics
        learner.observe(fragment)
    rng = np.random.default_rng(seed)
    b = config.batch_fragments
    keys = np.arange(b, dtype=np.int64)
    weights = np.ones(b, np.float32)
    from_prioritized = np.arange(b) < int(round(config.zeta * b))

    def batch():
        return [fragments[i] for i in rng.choice(len(fragments), b, replace=False)]

    for _ in range(10):  # warm-up
        learner.step(batch(), keys, weights, from_prioritized)
    updates, busy, start = 0, 0.0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        picked = batch()
        t = time.perf_counter()
        learner.step(picked, keys, weights, from_prioritized)
        busy += time.perf_counter() - t
        updates += 1
    elapsed = time.perf_counter() - start
    return {"updates_per_s": updates / elapsed, "updates": updates, "seconds": elapsed,
            "update_ms": 1e3 * busy / updates, "torch_threads": threads,
            "batch_fragments": b, "fragment_len": config.fragment_len}


# ----------------------------------------------------------------------------- processes

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def role_of(pid: int, root: int) -> str:
    """The service a process of the measured cluster is ("cluster" for the launcher)."""
    return "cluster" if pid == root else service_name(cmdline(pid)) or "other"


class RssSampler(threading.Thread):
    """Every `interval_s`: VmRSS of `root` and its descendants (the tree is rescanned each 1 s).
    Keeps the peak of the sum and each service's peak."""

    def __init__(self, root: int, interval_s: float = 0.2):
        super().__init__(daemon=True, name="rss")
        self.root, self.interval_s = root, interval_s
        self.done = threading.Event()
        self.names: dict[int, str] = {}
        self.peak_total_kib = 0
        self.peak_total_at_s = 0.0
        self.peak_by_service: dict[str, int] = {}
        self.samples = 0
        self.start_time = time.perf_counter()

    def run(self) -> None:
        last_scan = -1e9
        while not self.done.is_set():
            now = time.perf_counter()
            if now - last_scan >= 1.0:
                for pid in [self.root, *descendants(self.root)]:
                    if pid not in self.names:
                        self.names[pid] = role_of(pid, self.root)
                last_scan = now
            total, by_service = 0, {}
            for pid, name in list(self.names.items()):
                kib = rss_kib(pid)
                if kib is None:
                    continue
                total += kib
                by_service[name] = by_service.get(name, 0) + kib
            if total:
                self.samples += 1
                if total > self.peak_total_kib:
                    self.peak_total_kib, self.peak_total_at_s = total, now - self.start_time
                for name, kib in by_service.items():
                    self.peak_by_service[name] = max(self.peak_by_service.get(name, 0), kib)
            self.done.wait(self.interval_s)


class FirstUpdateWatcher:
    """A Zenoh client of the run that notes when the learner's parameters first carry
    version ≥ 1, i.e. when its first update is done (it publishes after every update)."""

    def __init__(self, endpoint: str, run_id: str, t0: float):
        self.endpoint, self.keys, self.t0 = endpoint, Keys(run_id), t0
        self.first_update_s: float | None = None
        self.version: int | None = None
        self.error: str | None = None
        self.got = threading.Event()
        self.session = None
        self.subscriber = None
        self.lock = threading.Lock()
        self.closed = False
        self.thread = threading.Thread(target=self._open, daemon=True, name="zenoh-watch")
        self.thread.start()

    def _open(self) -> None:
        try:
            session = open_session("client", [], [self.endpoint], 120.0)
        except Exception as exc:  # noqa: BLE001 - reported, the benchmark goes on without it
            self.error = f"{type(exc).__name__}: {exc}"
            return
        with self.lock:
            if self.closed:
                session.close()
                return
            self.session = session
            self.subscriber = session.declare_subscriber(self.keys.params, self._on_params)

    def _on_params(self, sample) -> None:
        if self.got.is_set():
            return
        now = time.perf_counter()
        try:
            version = decode(sample.payload.to_bytes(), Params).version
        except DecodeError:
            return
        if version >= 1:
            self.first_update_s, self.version = now - self.t0, version
            self.got.set()

    def stop_listening(self) -> None:
        with self.lock:
            if self.subscriber is not None:
                with contextlib.suppress(Exception):
                    self.subscriber.undeclare()
                self.subscriber = None

    def close(self) -> None:
        self.stop_listening()
        with self.lock:
            self.closed = True
            if self.session is not None:
                with contextlib.suppress(Exception):
                    self.session.close()
                self.session = None


def kill_leftovers(marker: str) -> list[str]:
    """SIGTERM, then SIGKILL, live processes whose command line contains `marker`."""
    def find() -> list[int]:
        me = os.getpid()
        return [pid for pid in proc_table() if pid != me and marker in " ".join(cmdline(pid))
                and rss_kib(pid) is not None]

    found = find()
    described = [f"{pid}: {' '.join(cmdline(pid))[:120]}" for pid in found]
    for pid in found:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + 10
    while found and time.monotonic() < deadline:
        time.sleep(0.2)
        found = [pid for pid in find() if pid in found]
    for pid in found:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return described


def run_cluster(args, actors: int, out_dir: Path) -> dict:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dir = (out_dir / "runs" / f"{args.env_id}__{actors}actors__{stamp}").resolve()
    log_path = out_dir / f"cluster_{actors}actors.log"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_id = f"bench{os.getpid()}a{actors}"
    argv = [sys.executable, "-m", "services.cluster", "--env-id", args.env_id,
            "--total-timesteps", str(args.total_timesteps), "--run-dir", str(run_dir),
            "--actors", str(actors), "--num-envs", str(args.num_envs), "--seed", str(args.seed),
            "--endpoint", endpoint, "--run-id", run_id,
            "--set", f"log_interval_s={args.log_interval_s:g}"]
    events: dict[str, float] = {}
    progress: list[tuple[float, int, int]] = []  # (s since launch, env steps, updates)
    actors_up: set[int] = set()
    actor_ends, replay_end, problems = [], None, []
    lines = 0
    log = log_path.open("w")
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, text=True, bufsize=1,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
    sampler = RssSampler(proc.pid)
    sampler.start()
    watcher = FirstUpdateWatcher(endpoint, run_id, t0)
    exit_code, timed_out, leftovers = None, False, []
    load_before = os.getloadavg()

    def read_output() -> None:
        nonlocal replay_end, lines
        for line in proc.stdout:
            t = time.perf_counter() - t0
            lines += 1
            log.write(f"{t:9.3f} {line}")
            line = line.rstrip("\n")
            if (m := PROGRESS.search(line)) is not None:
                progress.append((t, num(m.group(1)), num(m.group(3))))
                if num(m.group(3)) > 0:
                    events.setdefault("first_progress_line_with_updates", t)
                print(f"    {line}", flush=True)
            elif "[replay] tpdeb-replay: run" in line:
                events.setdefault("replay_serving", t)
            elif "[learner] tpdeb-learner: run" in line:
                events.setdefault("learner_training", t)
            elif (m := ACTOR_UP.search(line)) is not None:
                actors_up.add(int(m.group(1)))
                events.setdefault("first_actor_stepping", t)
                if len(actors_up) == actors:
                    events.setdefault("all_actors_stepping", t)
            elif "[learner] tpdeb-learner: done at" in line:
                events.setdefault("learner_done", t)
            if (m := ACTOR_END.search(line)) is not None:
                actor_ends.append({"actor": int(m.group(1)), "reason": m.group(2),
                                   "steps": num(m.group(3)), "sent": int(m.group(4)),
                                   "acked": int(m.group(5)), "resent": int(m.group(6))})
            if (m := REPLAY_END.search(line)) is not None:
                replay_end = {"reason": m.group(1), "ingested": num(m.group(2)),
                              "bad_messages": int(m.group(3))}
            if PROBLEM.search(line) and not PROGRESS.search(line) and not BENIGN.search(line):
                problems.append(f"{t:.1f}s {line}")
                print(f"    ! {line}", flush=True)

    reader = threading.Thread(target=read_output, daemon=True, name="cluster-stdout")
    reader.start()
    try:
        try:
            exit_code = proc.wait(args.cluster_timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            say(f"the cluster ran past {args.cluster_timeout_s:g} s: stopping it")
        events["cluster_exit"] = time.perf_counter() - t0
    finally:
        watcher.close()
        if proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)  # the cluster stops its services in order
            try:
                exit_code = proc.wait(120)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)  # children die with it (PDEATHSIG)
                exit_code = proc.wait()
        sampler.done.set()
        sampler.join(5)
        reader.join(10)
        log.close()
        leftovers = kill_leftovers(str(run_dir))
    wall = events.get("cluster_exit", time.perf_counter() - t0)
    result = {"actors": actors, "num_envs": args.num_envs, "total_timesteps":
              args.total_timesteps, "run_dir": str(run_dir), "log": str(log_path),
              "exit_code": exit_code, "timed_out": timed_out, "wall_s": wall,
              "loadavg_before": load_before, "events_s": events,
              "first_update_s": watcher.first_update_s,
              "first_update_version_seen": watcher.version, "watcher_error": watcher.error,
              "progress": progress, "actor_ends": actor_ends, "replay_end": replay_end,
              "problems": problems[:40], "problem_lines": len(problems), "stdout_lines": lines,
              "leftover_processes": leftovers,
              "rss_peak_total_mib": sampler.peak_total_kib / 1024,
              "rss_peak_total_at_s": sampler.peak_total_at_s,
              "rss_peak_by_service_mib": {k: v / 1024 for k, v in
                                          sorted(sampler.peak_by_service.items())},
              "rss_samples": sampler.samples}
    result.update(steady_rates(progress))
    result.update(learner_metrics(run_dir / "metrics.jsonl", result.get("steady_from_step")))
    if "learner_done" in events:
        result["e2e_env_steps_per_s_whole_run"] = progress[-1][1] / events["learner_done"] \
            if progress else None
    return result


def steady_rates(progress: list[tuple[float, int, int]]) -> dict:
    """Rates between the first progress line with updates > 0 and the last progress line,
    timed by when the lines arrived on the cluster's stdout."""
    rows = [row for row in progress if row[2] > 0]
    if len(rows) < 2 or rows[-1][0] - rows[0][0] <= 0:
        return {"steady_s": None, "steady_env_steps_per_s": None, "steady_updates_per_s": None}
    (t_a, s_a, u_a), (t_b, s_b, u_b) = rows[0], rows[-1]
    dt = t_b - t_a
    return {"steady_s": dt, "steady_from_step": s_a, "steady_to_step": s_b,
            "steady_env_steps_per_s": (s_b - s_a) / dt, "steady_updates_per_s": (u_b - u_a) / dt,
            "steady_rows": len(rows)}


def learner_metrics(path: Path, from_step: int | None) -> dict:
    """The learner's own view over the same rows: mean update time and waiting share."""
    if not path.exists():
        return {}
    rows = [json.loads(line) for line in path.open() if line.strip()]
    rows = [r for r in rows if "perf/updates" in r and r["perf/updates"] > 0
            and (from_step is None or r["global_step"] > from_step)]
    out = {}
    for key, name in (("perf/update_ms", "learner_update_ms"),
                      ("perf/batch_wait_fraction", "learner_batch_wait_fraction"),
                      ("actor/param_version_lag", "param_version_lag"),
                      ("replay/sample_age_updates", "sample_age_updates")):
        values = [r[key] for r in rows if key in r]
        if values:
            out[name] = float(np.mean(values))
    return out


# ----------------------------------------------------------------------------- output

def fmt(value, digits: int = 0, unit: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:,.{digits}f}{unit}"


def ratio_text(value, goal: float | None = None) -> str:
    if value is None:
        return "n/a"
    mark = "" if goal is None else (" ✓" if value >= goal else " ✗")
    return f"{value:.2f}{mark}"


def per_update(c: dict) -> str:
    """A cluster update's wall time split into Learner.step, waiting for a batch, and the rest
    (decoding the batch, publishing priorities and parameters, stats)."""
    ups, step_ms = c.get("steady_updates_per_s"), c.get("learner_update_ms")
    wait = c.get("learner_batch_wait_fraction")
    if not ups or step_ms is None or wait is None or wait >= 1:
        return "n/a"
    wall_ms = 1e3 / ups
    wait_ms = step_ms * wait / (1 - wait)
    return (f"{wall_ms:.1f}: {step_ms:.1f} / {wait_ms:.1f} / "
            f"{wall_ms - step_ms - wait_ms:.1f}")


def render(results: dict) -> str:
    env, actor = results["env_limit"], results["actor"]
    mem = results["learner_in_memory"]
    best_mem = max(mem.values(), key=lambda r: r["updates_per_s"])
    clusters = results["clusters"]
    rows = [("env steps/s, raw (limit)", fmt(env["env_steps_per_s"]), "")]
    ratio = actor["env_steps_per_s"] / env["env_steps_per_s"]
    rows.append(("actor steps/s (policy + encode), ratio to limit",
                 f"{fmt(actor['env_steps_per_s'])} ({ratio_text(ratio, GOAL)})", f"≥ {GOAL}"))
    for name, r in mem.items():
        rows.append((f"learner updates/s in memory ({name})",
                     f"{fmt(r['updates_per_s'], 1)} ({fmt(r['update_ms'], 1)} ms/update)", ""))
    for actors, c in clusters.items():
        ups = c.get("steady_updates_per_s")
        ratio = ups / best_mem["updates_per_s"] if ups is not None else None
        rows.append((f"learner updates/s through the cluster ({actors} actor{'s' * (actors != '1')}"
                     "), ratio", f"{fmt(ups, 1)} ({ratio_text(ratio, GOAL)})", f"≥ {GOAL}"))
    for actors, c in clusters.items():
        rows.append((f"end-to-end env steps/s, {actors} actor{'s' * (actors != '1')}",
                     f"{fmt(c.get('steady_env_steps_per_s'))} (whole run "
                     f"{fmt(c.get('e2e_env_steps_per_s_whole_run'))})", ""))
    for actors, c in clusters.items():
        rows.append((f"launch → first update, {actors} actor{'s' * (actors != '1')}",
                     fmt(c.get("first_update_s"), 1, " s"), ""))
    for actors, c in clusters.items():
        rows.append((f"peak RSS of the cluster (sum), {actors} actor{'s' * (actors != '1')}",
                     fmt(c.get("rss_peak_total_mib"), 0, " MiB"), ""))
    lines = ["| measure | value | goal |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]

    services = sorted({s for c in clusters.values() for s in c["rss_peak_by_service_mib"]})
    lines += ["", "Peak RSS per service (MiB):", "",
              "| service | " + " | ".join(f"{a} actor{'s' * (a != '1')}" for a in clusters) + " |",
              "|---|" + "---|" * len(clusters)]
    for s in services:
        lines.append(f"| {s} | " + " | ".join(fmt(c["rss_peak_by_service_mib"].get(s))
                                              for c in clusters.values()) + " |")

    lines += ["", "Cluster details:", "",
              "| | " + " | ".join(f"{a} actor{'s' * (a != '1')}" for a in clusters) + " |",
              "|---|" + "---|" * len(clusters)]

    def detail(label: str, get) -> None:
        lines.append(f"| {label} | " + " | ".join(get(c) for c in clusters.values()) + " |")

    ev = "events_s"
    detail("exit code / wall s", lambda c: f"{c['exit_code']} / {fmt(c['wall_s'], 1)}")
    detail("replay serving (s)", lambda c: fmt(c[ev].get("replay_serving"), 1))
    detail("learner training (s)", lambda c: fmt(c[ev].get("learner_training"), 1))
    detail("all actors stepping (s)", lambda c: fmt(c[ev].get("all_actors_stepping"), 1))
    detail("first update, Zenoh params v≥1 (s)", lambda c: fmt(c.get("first_update_s"), 2))
    detail("first progress line with updates > 0 (s)",
           lambda c: fmt(c[ev].get("first_progress_line_with_updates"), 1))
    detail("steady window (s, rows)",
           lambda c: f"{fmt(c.get('steady_s'), 1)}, {c.get('steady_rows', 0)}")
    detail("learner ms/update (in cluster)", lambda c: fmt(c.get("learner_update_ms"), 1))
    detail("learner batch-wait fraction", lambda c: fmt(c.get("learner_batch_wait_fraction"), 2))
    detail("wall ms per update: Learner.step / waiting / rest", per_update)
    detail("rate-limiter ceiling, updates/s", lambda c: fmt(c.get("rate_limit_updates_per_s"), 1))
    detail("param version lag (updates)", lambda c: fmt(c.get("param_version_lag"), 1))
    detail("fragments resent / bad messages",
           lambda c: f"{sum(a['resent'] for a in c['actor_ends'])} / "
                     f"{(c['replay_end'] or {}).get('bad_messages', 'n/a')}")
    detail("problem lines in the log", lambda c: str(c["problem_lines"]))
    detail("leftover processes killed", lambda c: str(len(c["leftover_processes"])))
    meta = results["meta"]
    lines += ["", f"Machine: {meta['cpu_count']} CPUs (os.cpu_count()), load average at start "
              f"{meta['loadavg_start'][0]:.2f}, at end {meta['loadavg_end'][0]:.2f}; torch "
              f"{meta['torch']}, default torch threads {meta['torch_default_threads']}; "
              f"{meta['env_id']}, {meta['num_envs']} envs per actor/limit. Other processes on "
              "the machine share the CPUs and lower every figure."]
    lines += ["", "Notes: env steps/s count single-env steps (vector steps × envs). The actor "
              "figure includes the policy forward pass, fragment building and msgpack encoding, "
              f"not the network; loading parameters costs {fmt(actor['param_load_ms'], 2)} ms "
              "each (the real actor loads at most one per env step, when new ones arrived). "
              "Cluster rates are taken between the first learner progress line with updates > 0 "
              "and the last one, timed by their arrival on the cluster's stdout "
              f"(every {meta['log_interval_s']:g} s), so start-up and shutdown are excluded; the "
              "ratio is against the best in-memory figure. With replay_ratio r the replay lets "
              "the learner do at most r × env steps/s ÷ (B·T) updates/s (the ceiling row): "
              "through the cluster the learner cannot beat it, whatever its own speed. "
              "'launch → first update' is from Popen of the cluster to the arrival of parameters "
              "with version ≥ 1 at a Zenoh client of this script (the learner publishes after "
              "every update). RSS: VmRSS of the cluster and all descendants every 0.2 s; shared "
              "pages count once per process, so the sum overstates physical memory."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--num-envs", type=int, default=4, help="envs per actor (and the limit)")
    parser.add_argument("--seconds", type=float, default=10.0,
                        help="duration of each in-process measurement")
    parser.add_argument("--total-timesteps", type=int, default=60_000, help="per cluster run")
    parser.add_argument("--actors", type=int, nargs="*", default=[1, 2],
                        help="cluster runs to make, by actor count (none: skip the clusters)")
    parser.add_argument("--log-interval-s", type=float, default=2.0,
                        help="the learner's progress interval in the cluster runs")
    parser.add_argument("--cluster-timeout-s", type=float, default=900.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "throughput"))
    args = parser.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    default_threads = torch.get_num_threads()
    meta = {"cpu_count": os.cpu_count(), "loadavg_start": os.getloadavg(),
            "python": platform.python_version(), "torch": torch.__version__,
            "torch_default_threads": default_threads, "env_id": args.env_id,
            "num_envs": args.num_envs, "seconds": args.seconds,
            "total_timesteps": args.total_timesteps, "log_interval_s": args.log_interval_s,
            "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    say(f"{os.cpu_count()} CPUs, load average {meta['loadavg_start'][0]:.2f}; "
        f"{args.env_id}, {args.num_envs} envs")

    say(f"env limit: raw stepping for {args.seconds:g} s…")
    env = bench_env(args.env_id, args.num_envs, args.seconds, args.seed)
    say(f"  {env['env_steps_per_s']:,.0f} env steps/s")

    say(f"actor: Collector + ActorCritic + encode for {args.seconds:g} s…")
    actor = bench_actor(args.env_id, args.num_envs, args.seconds, args.seed)
    say(f"  {actor['env_steps_per_s']:,.0f} env steps/s "
        f"({actor['env_steps_per_s'] / env['env_steps_per_s']:.2f} of the limit)")

    config, spec, fragments = collect_fragments(args.env_id, args.num_envs, 64, args.seed)
    mem = {}
    for threads in sorted({1, default_threads}):
        say(f"learner in memory, {threads} torch thread(s), for {args.seconds:g} s…")
        r = bench_learner(config, spec, fragments, args.seconds, threads, args.seed)
        mem[f"{threads} thread{'s' * (threads != 1)}"] = r
        say(f"  {r['updates_per_s']:,.1f} updates/s ({r['update_ms']:.1f} ms/update)")
    torch.set_num_threads(default_threads)

    clusters = {}
    for actors in args.actors:
        say(f"running cluster with {actors} actor{'s' * (actors != 1)}: "
            f"{args.total_timesteps:,} steps…")
        c = run_cluster(args, actors, out_dir)
        if c.get("steady_env_steps_per_s") is not None:
            c["rate_limit_updates_per_s"] = (config.replay_ratio * c["steady_env_steps_per_s"]
                                             / config.batch_steps)
        clusters[str(actors)] = c
        say(f"  exit {c['exit_code']} after {c['wall_s']:.1f} s; steady "
            f"{fmt(c.get('steady_env_steps_per_s'))} env steps/s, "
            f"{fmt(c.get('steady_updates_per_s'), 1)} updates/s; first update at "
            f"{fmt(c.get('first_update_s'), 1, ' s')}; peak RSS "
            f"{c['rss_peak_total_mib']:,.0f} MiB")
        if c["leftover_processes"]:
            say(f"  killed {len(c['leftover_processes'])} leftover process(es): "
                f"{c['leftover_processes']}")

    meta["loadavg_end"] = os.getloadavg()
    results = {"meta": meta, "env_limit": env, "actor": actor, "learner_in_memory": mem,
               "clusters": clusters}
    results["actor"]["ratio_to_limit"] = actor["env_steps_per_s"] / env["env_steps_per_s"]
    best = max(r["updates_per_s"] for r in mem.values())
    for c in clusters.values():
        ups = c.get("steady_updates_per_s")
        c["updates_ratio_to_in_memory"] = ups / best if ups is not None else None
    table = render(results)
    results["table_markdown"] = table
    path = out_dir / "results.json"
    path.write_text(json.dumps(results, indent=2))
    print()
    print(table)
    print()
    say(f"results in {path}")


if __name__ == "__main__":
    main()
