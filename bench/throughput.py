"""Throughput benchmark: every process against the limit the machine sets it.

    python bench/throughput.py                          # HalfCheetah-v5, its preset, 3 runs
    python bench/throughput.py --repeat 1 --seconds 3 --total-timesteps 40000   # a quick look

Each run measures, on this machine and one after another (nothing else should run meanwhile):

1. the update floor: forward of the policy on a batch's T·B observations and of the value net on
   its (T+1)·B, backward and the learner's Adam (torch's, fused), eager, nothing else; and the
   learner's whole update, compiled as the service runs it, on batches stacked as the replay
   server ships them and placed as its fetch threads place them (1 torch thread, as the
   learner);
2. the acting limit: a plain loop of the vector env and the same policy in numpy, one core, no
   fragments, learning or messaging; and the actor's own work (the Collector with its initial
   priorities, every fragment encoded);
3. the learner limit: in-memory updates/s × batch steps ÷ replay ratio (the env steps/s the
   learner could absorb);
4. the cluster (`python -m tpdeb.services.cluster`, the default config with the task's preset): its
   stdout is time-stamped line by line; steady env steps/s and updates/s come from the learner's
   progress lines, launch → first update from a Zenoh client of this script that sees the
   learner's first parameters with version ≥ 1, peak RSS of every process from /proc (0.2 s);
5. start-up parts: each service module's import in a fresh interpreter, the env's
   construction, and the cluster's timeline (router up, replay serving, learner training,
   actors stepping, first update).

Prints medians over `--repeat` runs with each run's figure; writes
`bench/out/throughput/results.json`.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import platform
import re
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import provenance
import torch
from procfs import cmdline, descendants, proc_table, rss_kib, service_name

from tpdeb.protocol import DecodeError, Keys, Params, decode, encode
from tpdeb.services.compiled import BackgroundCompile
from tpdeb.services.config import resolve
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.envs import make_vector_env, space_dims
from tpdeb.services.launcher.plan import free_port
from tpdeb.services.net.model_wire import model_for, params_message
from tpdeb.services.net.session import open_session
from tpdeb.services.net.wire import policy_from_params, run_spec
from tpdeb.tpdeb_core.fragments import Collector, stack_fragments
from tpdeb.tpdeb_core.learner import Learner, place

ROOT = Path(__file__).resolve().parents[1]

PROGRESS = re.compile(r"^\[learner\] tpdeb-learner: \[\s*([\d,]+)/[\d,]+\] SPS\s+(\S+) \|"
                      r".*\| updates ([\d,]+) \|")
ACTOR_UP = re.compile(r"^\[actor(?:-\d+)?\] tpdeb-actor: actor (\d+): ")
ACTOR_END = re.compile(r"actor (\d+) stopped \(([^)]*)\): ([\d,]+) steps, (\d+) fragments sent, "
                       r"(\d+) acknowledged, (\d+) resent")
REPLAY_END = re.compile(r"tpdeb-replay: stopped \(([^)]*)\); ([\d,]+) steps ingested, (\d+) bad")
PROBLEM = re.compile(r"traceback|error|exception|exited with code|ended with code|dropped|"
                     r"warning|no actor|did not come up", re.IGNORECASE)
# Not problems: a clean replay stop, the learner's normal exit.
BENIGN = re.compile(r", 0 bad messages dropped|learner exited with code 0$")


def say(text: str) -> None:
    print(f"[bench] {text}", flush=True)


def num(text: str) -> int:
    return int(text.replace(",", ""))


# ----------------------------------------------------------------------------- in process

def timed_loop(step, seconds: float, warmup: int = 20) -> tuple[int, float]:
    """(calls, seconds) of `step()` called repeatedly for `seconds` after `warmup` calls."""
    for _ in range(warmup):
        step()
    calls, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        step()
        calls += 1
    return calls, elapsed


def bench_env(env_id: str, num_envs: int, seconds: float, seed: int) -> dict:
    """Raw stepping with precomputed random actions: what the simulator alone costs."""
    envs = make_vector_env(env_id, num_envs)
    try:
        envs.reset(seed=[seed + i for i in range(num_envs)])
        envs.action_space.seed(seed)
        actions = [envs.action_space.sample() for _ in range(1024)]
        cycle = itertools.cycle(actions)
        calls, elapsed = timed_loop(lambda: envs.step(next(cycle)), seconds)
    finally:
        envs.close()
    return {"env_steps_per_s": calls * num_envs / elapsed, "seconds": elapsed}


def preset_config(env_id: str, num_envs: int, seed: int) -> TrainConfig:
    """The task's configuration as the cluster resolves it (its preset included)."""
    return resolve(TrainConfig, ["--env-id", env_id, "--num-envs", str(num_envs), "--seed",
                                 str(seed)], "bench", "")


def make_policy(config: TrainConfig, envs):
    spec = run_spec(config, *space_dims(envs))
    model = model_for(spec)
    return spec, model, model.numpy_policy()


def bench_acting_limit(config: TrainConfig, seconds: float) -> dict:
    """The plain acting loop on one core: the vector env and the same policy in numpy, actions
    clipped to the bounds; no fragments, no learning, no messaging."""
    envs = make_vector_env(config.env_id, config.num_envs)
    try:
        spec, _, policy = make_policy(config, envs)
        obs, _ = envs.reset(seed=[config.seed + i for i in range(config.num_envs)])
        rng = np.random.default_rng(config.seed)
        state = {"obs": obs}

        def step():
            action = policy.act(state["obs"], rng)["action"]
            state["obs"] = envs.step(np.clip(action, spec.action_low, spec.action_high))[0]

        calls, elapsed = timed_loop(step, seconds)
    finally:
        envs.close()
    return {"env_steps_per_s": calls * config.num_envs / elapsed, "seconds": elapsed}


def bench_actor(config: TrainConfig, seconds: float) -> dict:
    """What tpdeb-actor does between network calls: the Collector (fragments, initial
    priorities) and every fragment encoded; plus the cost of loading new parameters."""
    envs = make_vector_env(config.env_id, config.num_envs)
    try:
        spec, model, policy = make_policy(config, envs)
        collector = Collector(envs, policy, spec.fragment_len, spec.gamma, spec.action_low,
                              spec.action_high, seed=config.seed)
        sent = {"fragments": 0, "bytes": 0}

        def step():
            for fragment in collector.step():
                sent["bytes"] += len(encode(fragment))
                sent["fragments"] += 1

        timed_loop(step, 0.5)  # warm-up
        steps0 = collector.env_steps
        _, elapsed = timed_loop(step, seconds, warmup=0)
        steps = collector.env_steps - steps0
        payload = encode(params_message(model.arrays(), 1))
        loads, load_s = timed_loop(lambda: policy_from_params(decode(payload, Params), spec),
                                   min(2.0, seconds / 2))
    finally:
        envs.close()
    return {"env_steps_per_s": steps / elapsed, "seconds": elapsed,
            "fragment_bytes_mean": sent["bytes"] / max(sent["fragments"], 1),
            "param_load_ms": 1e3 * load_s / loads, "params_bytes": len(payload)}


def sample_batches(config: TrainConfig, count: int = 32) -> tuple:
    """Real fragments of the task (a fresh policy), stacked into `count` batches as the replay
    server ships them."""
    envs = make_vector_env(config.env_id, config.num_envs)
    try:
        spec, model, policy = make_policy(config, envs)
        collector = Collector(envs, policy, spec.fragment_len, spec.gamma, spec.action_low,
                              spec.action_high, seed=config.seed)
        fragments = []
        while len(fragments) < 64:
            fragments.extend(collector.step())
    finally:
        envs.close()
    rng = np.random.default_rng(config.seed)
    b = config.batch_fragments
    batches = [stack_fragments([fragments[i] for i in rng.choice(len(fragments), b,
                                                                 replace=False)])
               for _ in range(count)]
    return spec, fragments, batches


def bench_floor(config: TrainConfig, spec, batches, seconds: float) -> dict:
    """The math floor of one update: forward of the policy on the batch's T·B observations and
    of the value net on its (T+1)·B, backward and the learner's Adam, nothing else."""
    torch.set_num_threads(config.torch_threads)
    torch.manual_seed(config.seed)
    model = model_for(spec)
    optimizer = Learner(model, config.loss_config()).optimizer  # the learner's own settings
    obs = [torch.tensor(b.obs) for b in batches]
    cycle = itertools.cycle(obs)

    def step():
        x = next(cycle)
        mean, log_std = model.policy(x[:-1])
        loss = mean.square().mean() + log_std.sum() + model.value(x).square().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    calls, elapsed = timed_loop(step, seconds)
    return {"update_ms": 1e3 * elapsed / calls, "updates_per_s": calls / elapsed}


def prepared_learner(config: TrainConfig, spec, fragments, batches, device: str = "cpu",
                     threads: int | None = None, reduce=None) -> tuple:
    """(step, compile seconds, the learner's device): the learner service's work per update as
    `step()`, compiled as the service runs it once its compile is ready. `reduce`: a learner rank's
    all-reduce hook (services.ranks.Group.reducer())."""
    torch.set_num_threads(threads or config.torch_threads)
    torch.manual_seed(config.seed)
    learner = Learner(model_for(spec), config.loss_config(), device)
    if reduce is not None:
        learner.rules.reduce = reduce
    for fragment in fragments:  # realistic normaliser statistics
        learner.observe(fragment)
    b = config.batch_fragments
    pin = learner.device.type != "cpu"
    placed = [place(batch, np.ones(b, np.float32), None, learner.device, pin)
              for batch in batches]
    compiler = BackgroundCompile(learner)
    started = time.perf_counter()
    compiler.start(placed[0], learner.normaliser())
    compiler.done.wait()
    compile_s = time.perf_counter() - started
    if not compiler.install():
        raise SystemExit(f"the update did not compile: {compiler.error}")
    cycle = itertools.cycle(placed)

    def step():  # the priorities reach the host a step later, as in the service
        learner.update(next(cycle), learner.normaliser()).to("cpu", non_blocking=pin)

    return step, compile_s, learner.device


def bench_learner(config: TrainConfig, spec, fragments, batches, seconds: float,
                  device: str = "cpu", threads: int | None = None) -> dict:
    """The learner service's work per update, without the network: the normaliser's map, the
    update (compiled, as the service runs it once its compile is ready) and the new
    priorities copied out, on batches placed as the fetch threads place them; at the learner's
    thread count unless `threads` says otherwise."""
    step, compile_s, on = prepared_learner(config, spec, fragments, batches, device, threads)
    calls, elapsed = timed_loop(step, seconds)
    if on.type != "cpu":
        torch.cuda.synchronize(on)
        elapsed = max(elapsed, 1e-9)
    return {"update_ms": 1e3 * elapsed / calls, "updates_per_s": calls / elapsed,
            "batch_steps": config.batch_steps, "replay_ratio": config.replay_ratio,
            "torch_threads": threads or config.torch_threads, "compile_s": compile_s}


def bench_imports() -> dict:
    """Seconds to import each entry point's module in a fresh interpreter (what a process pays
    before its first line of work)."""
    out = {}
    for name, module in (("router", "tpdeb.services.router"), ("replay", "tpdeb.services.replay"),
                         ("learner", "tpdeb.services.learner"), ("actor", "tpdeb.services.actor"),
                         ("cluster", "tpdeb.services.cluster")):
        code = f"import time; t = time.perf_counter(); import {module}; " \
               "print(time.perf_counter() - t)"
        runs = [float(subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True,
                                     capture_output=True, text=True).stdout) for _ in range(3)]
        out[name] = statistics.median(runs)
    return out


def bench_env_construction(env_id: str, num_envs: int) -> float:
    """Seconds to build the vector env in a fresh interpreter, imports excluded."""
    code = ("import time; from tpdeb.services.envs import make_vector_env; "
            "t = time.perf_counter(); "
            f"make_vector_env({env_id!r}, {num_envs}).close(); print(time.perf_counter() - t)")
    return statistics.median(float(subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, check=True, capture_output=True,
        text=True).stdout) for _ in range(3))


# ----------------------------------------------------------------------------- processes

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
    argv = [sys.executable, "-m", "tpdeb.services.cluster", "--env-id", args.env_id,
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
            elif "[router] tpdeb-router: routing" in line:
                events.setdefault("router_up", t)
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
            elif "[learner] tpdeb-learner: update compiled in" in line:
                events.setdefault("update_compiled", t)
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


def derive(r: dict) -> dict:
    """The issue's ratios from one run's measurements."""
    learner, acting = r["learner_in_memory"], r["acting_limit"]
    learner_limit = learner["updates_per_s"] * learner["batch_steps"] / learner["replay_ratio"]
    c = r["cluster"]
    e2e, ups = c.get("steady_env_steps_per_s"), c.get("steady_updates_per_s")
    lesser = min(acting["env_steps_per_s"], learner_limit)
    wait = c.get("learner_batch_wait_fraction")
    # The learner's own wall time per update in the cluster with its waits for a batch (the
    # rate limiter, the actors) taken out: what its plumbing costs per update.
    busy_ups = ups / (1 - wait) if ups and wait is not None and wait < 1 else None
    return {
        "floor_ms": r["floor"]["update_ms"], "learner_ms": learner["update_ms"],
        "learner_over_floor": learner["update_ms"] / r["floor"]["update_ms"],
        "learner_updates_per_s": learner["updates_per_s"],
        "cluster_updates_per_s": ups,
        "cluster_over_memory_updates": ups / learner["updates_per_s"] if ups else None,
        "cluster_busy_over_memory_updates": busy_ups / learner["updates_per_s"]
        if busy_ups else None,
        "acting_limit": acting["env_steps_per_s"], "learner_limit": learner_limit,
        "actor_steps_per_s": r["actor"]["env_steps_per_s"],
        "actor_over_acting": r["actor"]["env_steps_per_s"] / acting["env_steps_per_s"],
        "e2e_steps_per_s": e2e,
        "e2e_over_lesser": e2e / lesser if e2e else None,
        "e2e_over_acting": e2e / acting["env_steps_per_s"] if e2e else None,
        "startup_s": c.get("first_update_s"),
        "rss_total_mib": c.get("rss_peak_total_mib"),
        **{f"rss_{k}_mib": v for k, v in c.get("rss_peak_by_service_mib", {}).items()},
        **{f"import_{k}_s": v for k, v in r["imports_s"].items()},
        "env_build_s": r["env_build_s"],
        **{f"event_{k}_s": v for k, v in c.get("events_s", {}).items()},
    }


ROWS = [  # (label, key, digits, unit, goal)
    ("update floor: forward + backward + Adam", "floor_ms", 2, " ms", ""),
    ("the learner's update in memory (compiled)", "learner_ms", 2, " ms", ""),
    ("update ÷ floor", "learner_over_floor", 2, "", "≤ 1.0"),
    ("updates/s in memory", "learner_updates_per_s", 0, "", ""),
    ("updates/s through the cluster", "cluster_updates_per_s", 0, "", ""),
    ("through the cluster ÷ in memory", "cluster_over_memory_updates", 2, "", "≥ 0.8"),
    ("… with the learner's waits for a batch taken out", "cluster_busy_over_memory_updates", 2,
     "", ""),
    ("acting limit: plain loop, one core (env steps/s)", "acting_limit", 0, "", ""),
    ("learner limit: updates/s × B·T ÷ replay ratio", "learner_limit", 0, "", ""),
    ("actor alone (Collector + encode), env steps/s", "actor_steps_per_s", 0, "", ""),
    ("actor ÷ acting limit", "actor_over_acting", 2, "", ""),
    ("end-to-end env steps/s (cluster, steady)", "e2e_steps_per_s", 0, "", ""),
    ("end-to-end ÷ the lesser limit", "e2e_over_lesser", 2, "", "≥ 0.8"),
    ("end-to-end ÷ the plain loop", "e2e_over_acting", 2, "", ""),
    ("launch → first learner update", "startup_s", 2, " s", "≤ 4"),
    ("peak RSS of the cluster (sum)", "rss_total_mib", 0, " MiB", "≤ 1,000"),
]


def render(runs: list[dict], meta: dict) -> str:
    figures = [derive(r) for r in runs]

    def median(key):
        values = [f[key] for f in figures if f.get(key) is not None]
        return statistics.median(values) if values else None

    def each(key, digits):
        return ", ".join(fmt(f.get(key), digits) for f in figures)

    lines = [f"Medians of {len(runs)} run(s) (each run's figures in brackets).", "",
             "| measure | median | runs | goal |", "|---|---|---|---|"]
    lines += [f"| {label} | {fmt(median(key), digits, unit)} | {each(key, digits)} | {goal} |"
              for label, key, digits, unit, goal in ROWS]
    services = sorted({k[4:-4] for f in figures for k in f if k.startswith("rss_")
                       and k != "rss_total_mib"})
    lines += ["", "Peak RSS per service (MiB, medians):", "", "| service | MiB |", "|---|---|"]
    lines += [f"| {s} | {fmt(median(f'rss_{s}_mib'))} |" for s in services]
    lines += ["", "Start-up (seconds, medians): imports in a fresh interpreter, env construction, "
              "and the cluster's timeline from launch:", "", "| part | s |", "|---|---|"]
    lines += [f"| import {name} | {fmt(median(f'import_{name}_s'), 2)} |"
              for name in ("cluster", "router", "replay", "actor", "learner")]
    lines.append(f"| build {meta['num_envs']} × {meta['env_id']} | "
                 f"{fmt(median('env_build_s'), 2)} |")
    for event in ("router_up", "replay_serving", "learner_training", "first_actor_stepping",
                  "all_actors_stepping", "first_update", "update_compiled"):
        key = "startup_s" if event == "first_update" else f"event_{event}_s"
        lines.append(f"| {event.replace('_', ' ')} | {fmt(median(key), 2)} |")
    lines += ["", f"Machine: {meta['cpu_count']} CPUs, load average {meta['loadavg_start'][0]:.2f}"
              f" at start; torch {meta['torch']}; {meta['env_id']} with its preset "
              f"({meta['hidden_sizes']} networks, batch {meta['batch_steps']} steps, replay ratio "
              f"{meta['replay_ratio']:g}), {meta['actors']} actors × {meta['num_envs']} envs."]
    return "\n".join(lines)


def measure(args, config: TrainConfig, out_dir: Path, index: int) -> dict:
    r = {}
    say(f"run {index}: raw env stepping, {args.seconds:g} s…")
    r["env"] = bench_env(config.env_id, config.num_envs, args.seconds, config.seed)
    say(f"run {index}: acting limit (plain loop), {args.seconds:g} s…")
    r["acting_limit"] = bench_acting_limit(config, args.seconds)
    say(f"run {index}: actor (Collector + encode), {args.seconds:g} s…")
    r["actor"] = bench_actor(config, args.seconds)
    spec, fragments, batches = sample_batches(config)
    say(f"run {index}: update floor and Learner.step, {args.seconds:g} s each…")
    r["floor"] = bench_floor(config, spec, batches, args.seconds)
    r["learner_in_memory"] = bench_learner(config, spec, fragments, batches, args.seconds)
    say(f"run {index}: imports and env construction…")
    r["imports_s"] = bench_imports()
    r["env_build_s"] = bench_env_construction(config.env_id, config.num_envs)
    say(f"run {index}: the cluster, {args.actors} actors, {args.total_timesteps:,} steps…")
    r["cluster"] = run_cluster(args, args.actors, out_dir)
    f = derive(r)
    say(f"run {index}: floor {fmt(f['floor_ms'], 2)} ms, learner {fmt(f['learner_ms'], 2)} ms, "
        f"end-to-end {fmt(f['e2e_steps_per_s'])} env steps/s, first update at "
        f"{fmt(f['startup_s'], 2)} s, peak RSS {fmt(f['rss_total_mib'])} MiB")
    return r


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env-id", default="HalfCheetah-v5")
    parser.add_argument("--num-envs", type=int, default=4, help="envs per actor")
    parser.add_argument("--actors", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=10.0,
                        help="duration of each in-process measurement")
    parser.add_argument("--total-timesteps", type=int, default=150_000, help="per cluster run")
    parser.add_argument("--repeat", type=int, default=3, help="runs; the table shows medians")
    parser.add_argument("--log-interval-s", type=float, default=2.0,
                        help="the learner's progress interval in the cluster runs")
    parser.add_argument("--cluster-timeout-s", type=float, default=900.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out" / "throughput"))
    args = parser.parse_args()
    record = provenance.start()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    config = preset_config(args.env_id, args.num_envs, args.seed)
    meta = {"cpu_count": os.cpu_count(), "loadavg_start": os.getloadavg(),
            "python": platform.python_version(), "torch": torch.__version__,
            "env_id": args.env_id, "num_envs": args.num_envs, "actors": args.actors,
            "hidden_sizes": "×".join(map(str, config.hidden_sizes)),
            "batch_steps": config.batch_steps, "replay_ratio": config.replay_ratio,
            "seconds": args.seconds, "total_timesteps": args.total_timesteps,
            "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    say(f"{os.cpu_count()} CPUs, load average {meta['loadavg_start'][0]:.2f}; {args.env_id}, "
        f"{args.actors} actors × {args.num_envs} envs, {args.repeat} run(s)")
    runs = []
    for index in range(1, args.repeat + 1):
        runs.append(measure(args, config, out_dir, index))
        (out_dir / "results.json").write_text(json.dumps(provenance.stamp(
            {"meta": meta, "runs": runs, "figures": [derive(r) for r in runs]}, record), indent=2))
    meta["loadavg_end"] = os.getloadavg()
    table = render(runs, meta)
    (out_dir / "results.json").write_text(json.dumps(provenance.stamp(
        {"meta": meta, "runs": runs, "figures": [derive(r) for r in runs],
         "table_markdown": table}, record), indent=2))
    print()
    print(table)
    print()
    say(f"results in {out_dir / 'results.json'}")


if __name__ == "__main__":
    main()
