"""`tpdeb-cluster`: a compose-style launcher for the whole run on one machine (SPEC §5).

Reads a cluster file (`deploy/local.toml`), writes the resolved training config into the run
dir, starts replay → learner → actors as separate processes in dependency order (each waits
for what it depends on to answer), prefixes and saves their logs, shows a live progress line
from the services' stats, and stops everything in reverse order at the end or on Ctrl-C.
The learner ends the run: when it exits 0 the others stop on its stop message.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from protocol import DecodeError, Keys, Stats, decode
from services.config import ConfigError, coerce, load_toml, to_toml
from services.envs import make_vector_env
from services.service_config import ServiceConfig
from services.train_config import TrainConfig
from services.zsession import fetch_spec, open_session

PROG = "tpdeb-cluster"
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FILE = ROOT / "deploy" / "local.toml"
ROLES = ("replay", "learner", "actor")
SERVICE_KEYS = {"command", "replicas", "depends_on", "args", "env"}
CLUSTER_KEYS = {"run_id", "endpoint", "stop_timeout_s", "start_timeout_s"}
LINK_KEYS = ("up_bytes_per_s", "down_bytes_per_s", "latency_ms", "jitter_ms", "queue_ms")


@dataclass
class ServiceSpec:
    role: str
    command: str
    replicas: int = 1
    depends_on: list[str] = field(default_factory=list)
    args: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)


@dataclass
class Plan:
    run_id: str
    endpoint: str
    stop_timeout_s: float
    start_timeout_s: float
    train: TrainConfig
    services: list[ServiceSpec]  # in start order
    source: str
    link: dict = field(default_factory=dict)  # [link] settings; empty: actors connect directly
    link_endpoint: str = ""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_order(services: dict[str, ServiceSpec]) -> list[ServiceSpec]:
    ordered: list[ServiceSpec] = []
    visiting: set[str] = set()

    def visit(name: str) -> None:
        if any(s.role == name for s in ordered):
            return
        if name in visiting:
            raise ConfigError(f"services: depends_on forms a cycle through {name!r}")
        visiting.add(name)
        for dep in services[name].depends_on:
            if dep not in services:
                raise ConfigError(f"services.{name}.depends_on: unknown service {dep!r}")
            visit(dep)
        ordered.append(services[name])

    for name in services:
        visit(name)
    return ordered


def make_plan(args: argparse.Namespace) -> Plan:
    path = Path(args.config) if args.config else DEFAULT_FILE
    data = load_toml(path)
    unknown = set(data) - {"cluster", "train", "services", "link"}
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {sorted(unknown)}; expected cluster, "
                          "train, services, link")
    cluster = data.get("cluster", {})
    if set(cluster) - CLUSTER_KEYS:
        raise ConfigError(f"{path} [cluster]: unknown key(s) {sorted(set(cluster) - CLUSTER_KEYS)}"
                          f"; known: {sorted(CLUSTER_KEYS)}")
    services = {}
    for role, body in data.get("services", {}).items():
        if role not in ROLES:
            raise ConfigError(f"{path}: unknown service {role!r}; services are {ROLES}")
        if set(body) - SERVICE_KEYS:
            raise ConfigError(f"{path} [services.{role}]: unknown key(s) "
                              f"{sorted(set(body) - SERVICE_KEYS)}; known: {sorted(SERVICE_KEYS)}")
        services[role] = ServiceSpec(role=role, **body)
    missing = set(ROLES) - set(services)
    if missing:
        raise ConfigError(f"{path}: services {sorted(missing)} are missing")
    if args.actors is not None:
        services["actor"].replicas = args.actors
    for spec in services.values():
        if spec.replicas < (1 if spec.role == "actor" else 0) or (
                spec.role != "actor" and spec.replicas != 1):
            raise ConfigError(f"services.{spec.role}.replicas={spec.replicas}: the replay and "
                              "the learner run once, actors at least once")
    train = dict(data.get("train", {}))
    overrides = {"env_id": args.env_id, "total_timesteps": args.total_timesteps,
                 "seed": args.seed, "run_dir": args.run_dir, "num_envs": args.num_envs}
    train.update({k: v for k, v in overrides.items() if v is not None})
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        train[key.strip().replace("-", "_")] = value.strip()
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    if set(train) - names:
        raise ConfigError(f"train setting(s) {sorted(set(train) - names)} do not exist "
                          "(tpdeb-train --help lists them)")
    train_config = coerce_train(train)
    if not train_config.run_dir:
        train_config.run_dir = str(train_config.default_run_dir())
    endpoint = args.endpoint or cluster.get("endpoint", "tcp/127.0.0.1:auto")
    if endpoint.endswith(":auto"):
        endpoint = f"{endpoint[:-len('auto')]}{free_port()}"
    link = link_settings(data.get("link", {}), args, path)
    link_endpoint = ""
    if any(link.get(k, 0) for k in LINK_KEYS[:4]):
        link_endpoint = f"tcp/127.0.0.1:{free_port()}"
    return Plan(run_id=args.run_id or cluster.get("run_id", "local"), endpoint=endpoint,
                stop_timeout_s=float(cluster.get("stop_timeout_s", 20)),
                start_timeout_s=float(cluster.get("start_timeout_s", 120)),
                train=train_config, services=start_order(services), source=str(path),
                link=link, link_endpoint=link_endpoint)


def link_settings(section: dict, args: argparse.Namespace, path: Path) -> dict:
    """The [link] section with --link-* flags on top; every value a number ≥ 0."""
    unknown = set(section) - set(LINK_KEYS)
    if unknown:
        raise ConfigError(f"{path} [link]: unknown key(s) {sorted(unknown)}; known: "
                          f"{list(LINK_KEYS)}")
    link = dict(section)
    for key in LINK_KEYS:
        flag = getattr(args, f"link_{key}", None)
        if flag is not None:
            link[key] = flag
    for key, value in link.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise ConfigError(f"[link] {key}={value!r}: expected a number ≥ 0 (0 = off)")
    return link


def coerce_train(values: dict) -> TrainConfig:
    """Values from TOML/flags (strings allowed) → a validated TrainConfig."""
    return TrainConfig(**{k: coerce(TrainConfig, k, v, "train") for k, v in values.items()})


def resolve_command(command: str) -> list[str]:
    """`tpdeb-x` next to this interpreter first (a venv needs no activation), then PATH."""
    local = Path(sys.executable).parent / command
    if local.exists():
        return [str(local)]
    found = shutil.which(command)
    if found is None:
        raise ConfigError(f"command {command!r} not found (is the package installed?)")
    return [found]


def _die_with_parent() -> None:
    # Children must not outlive a cluster that is killed with SIGKILL.
    with contextlib.suppress(Exception):
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Child:
    """One service process, its log file and the thread that prefixes its output."""

    def __init__(self, name: str, argv: list[str], env: dict, log_dir: Path, echo):
        self.name, self.argv = name, argv
        self.log = (log_dir / f"{name}.log").open("a", buffering=1)
        self.proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=env, start_new_session=True, preexec_fn=_die_with_parent, text=True,
            bufsize=1)
        self.reader = threading.Thread(target=self._pump, args=(echo,), daemon=True)
        self.reader.start()

    def _pump(self, echo) -> None:
        for line in self.proc.stdout:
            self.log.write(line)
            echo(f"[{self.name}] {line.rstrip()}")
        self.log.close()

    def stop(self, timeout_s: float) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(timeout=5)
        return self.proc.returncode


class Display:
    """Latest stats per service, rendered as one status line (redrawn in place on a TTY)."""

    def __init__(self, out=sys.stdout):
        self.out = out
        self.tty = out.isatty()
        self.latest: dict[tuple[str, str], dict] = {}
        self.lock = threading.Lock()
        self.last_plain = 0.0
        self.status = ""

    def on_stats(self, sample) -> None:
        try:
            stats = decode(sample.payload.to_bytes(), Stats)
        except DecodeError:
            return
        with self.lock:
            self.latest[(stats.role, stats.ident)] = stats.values

    def line(self, alive_actors: int, total_actors: int) -> str:
        with self.lock:
            learner = self.latest.get(("learner", "0"), {})
            replay = self.latest.get(("replay", "0"), {})
            link = self.latest.get(("link", "0"))
        if not learner:
            return f"starting… actors {alive_actors}/{total_actors}"
        link_text = (f" | link ↑{link.get('up_bytes_per_s', 0) / 1e3:,.0f} "
                     f"↓{link.get('down_bytes_per_s', 0) / 1e3:,.0f} kB/s") if link else ""
        step, total = int(learner.get("global_step", 0)), int(learner.get("total_timesteps", 0))
        pct = f" ({100 * step / total:.0f}%)" if total else ""
        ret = learner.get("mean_return", math.nan)
        fill = replay.get("prioritized_items", 0), replay.get("uniform_steps", 0)
        return (f"{step:,}/{total:,} steps{pct} | {learner.get('sps', 0):,.0f} SPS | return "
                f"{ret:,.1f} | replay {fill[0]} fragments + {fill[1]:,} steps | lag "
                f"{learner.get('param_version_lag', math.nan):.1f} versions | "
                f"{int(learner.get('updates', 0)):,} updates | actors {alive_actors}/"
                f"{total_actors}{link_text}")

    def echo(self, text: str) -> None:
        with self.lock:
            if self.tty and self.status:
                self.out.write("\r\033[K")
            self.out.write(text + "\n")
            if self.tty and self.status:
                self.out.write(self.status)
            self.out.flush()

    def show(self, status: str, plain_interval_s: float = 10.0) -> None:
        if self.tty:
            with self.lock:
                self.status = f"[{PROG}] {status}"
                self.out.write("\r\033[K" + self.status)
                self.out.flush()
        elif time.monotonic() - self.last_plain >= plain_interval_s:
            self.last_plain = time.monotonic()
            self.echo(f"[{PROG}] {status}")


class Cluster:
    def __init__(self, plan: Plan, out=sys.stdout):
        self.plan = plan
        self.run_dir = Path(plan.train.run_dir)
        self.display = Display(out)
        self.children: list[Child] = []
        self.stopping = threading.Event()
        self.session = None
        self.interrupted = False

    def write_run_dir(self) -> Path:
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        service_config = ServiceConfig(**dataclasses.asdict(self.plan.train),
                                       run_id=self.plan.run_id, connect=(self.plan.endpoint,))
        path = self.run_dir / "train.toml"
        path.write_text(to_toml(self.plan.train))
        (self.run_dir / "cluster.json").write_text(json.dumps({
            "source": self.plan.source, "run_id": self.plan.run_id,
            "endpoint": self.plan.endpoint, "link": self.plan.link,
            "link_endpoint": self.plan.link_endpoint,
            "services": [dataclasses.asdict(s) for s in self.plan.services],
            "train": dataclasses.asdict(service_config)}, indent=2))
        return path

    def argv(self, spec: ServiceSpec, train_file: Path, index: int) -> list[str]:
        argv = [*resolve_command(spec.command), "--config", str(train_file),
                "--run-id", self.plan.run_id]
        if spec.role == "replay":
            argv += ["--listen", self.plan.endpoint]
        elif spec.role == "actor" and self.plan.link_endpoint:
            argv += ["--connect", self.plan.link_endpoint]  # actors sit behind the link
        else:
            argv += ["--connect", self.plan.endpoint]
        if spec.role == "actor":
            argv += ["--actor-id", str(index)]
        if self.plan.link_endpoint and spec.role in ("replay", "actor"):
            argv += ["--tcp-buffer-bytes", str(self.link_tcp_buffer())]
        return argv + [str(a) for a in spec.args]

    def link_tcp_buffer(self) -> int:
        """A quarter second at the link's slowest throttled rate (the kernel doubles it)."""
        rates = [self.plan.link.get(k, 0) for k in ("up_bytes_per_s", "down_bytes_per_s")]
        slowest = min((r for r in rates if r > 0), default=0)
        return max(16384, int(slowest * 0.25)) if slowest else 0

    def link_argv(self) -> list[str]:
        argv = [*resolve_command("tpdeb-link"), "--listen", self.plan.link_endpoint,
                "--connect", self.plan.endpoint, "--run-id", self.plan.run_id]
        for key, value in self.plan.link.items():
            argv += [f"--{key.replace('_', '-')}", str(value)]
        return argv

    def run(self) -> int:
        train_file = self.write_run_dir()
        say = self.display.echo
        say(f"[{PROG}] run {self.plan.run_id}: {self.plan.train.env_id}, "
            f"{self.plan.train.total_timesteps:,} steps, seed {self.plan.train.seed}; "
            f"endpoint {self.plan.endpoint}; run dir {self.run_dir}")
        keys = Keys(self.plan.run_id)
        try:
            # Started in dependency order without waiting in between: each service waits for
            # what it needs (the router, the run spec, the first parameters), so their slow
            # imports overlap. The checks below then name the one that fails to come up.
            for spec in self.plan.services:
                if spec.role == "actor" and self.plan.link_endpoint:
                    self.children.append(Child("link", self.link_argv(), dict(os.environ),
                                               self.run_dir / "logs", say))
                for i in range(spec.replicas):
                    name = spec.role if spec.replicas == 1 else f"{spec.role}-{i}"
                    env = {**os.environ, **{k: str(v) for k, v in spec.env.items()}}
                    self.children.append(Child(name, self.argv(spec, train_file, i), env,
                                               self.run_dir / "logs", say))
            self.connect(keys)
            self.wait_until(lambda: fetch_spec(self.session, keys, 1.0) is not None, "replay")
            self.wait_until(lambda: self._answers(self.session, keys.params_latest), "learner")
            return self.supervise()
        except ConfigError as exc:
            say(f"[{PROG}] error: {exc}")
            return 1
        finally:
            self.shutdown()
            if self.session is not None:
                self.session.close()

    def connect(self, keys: Keys) -> None:
        """The cluster's own client session: readiness checks and the stats it displays."""
        self.session = open_session("client", [], [self.plan.endpoint], self.plan.start_timeout_s)
        self.subscriber = self.session.declare_subscriber(keys.stats_all, self.display.on_stats)

    @staticmethod
    def _answers(session, key: str) -> bool:
        return any(r.ok is not None for r in session.get(key, timeout=1.0))

    def wait_until(self, ready, what: str) -> None:
        deadline = time.monotonic() + self.plan.start_timeout_s
        while time.monotonic() < deadline and not self.stopping.is_set():
            crashed = self.exited()
            if crashed:
                raise ConfigError(f"{crashed.name} exited with code {crashed.proc.returncode} "
                                  f"while starting; see {self.run_dir}/logs/{crashed.name}.log")
            with contextlib.suppress(ConfigError):
                if ready():
                    return
            time.sleep(0.2)
        if not self.stopping.is_set():
            raise ConfigError(f"{what} did not come up within {self.plan.start_timeout_s:g} s")

    def exited(self) -> Child | None:
        return next((c for c in self.children if c.proc.poll() is not None), None)

    def supervise(self) -> int:
        actors = [c for c in self.children if c.name.startswith("actor")]
        learner = next(c for c in self.children if c.name == "learner")
        replay = next(c for c in self.children if c.name == "replay")
        link = next((c for c in self.children if c.name == "link"), None)
        reported: set[str] = set()
        while not self.stopping.is_set():
            if learner.proc.poll() is not None:
                code = learner.proc.returncode
                self.display.echo(f"[{PROG}] learner exited with code {code}")
                return 0 if code == 0 and not self.interrupted else (130 if self.interrupted
                                                                    else 1)
            if link is not None and link.proc.poll() is not None and learner.proc.poll() is None:
                self.display.echo(f"[{PROG}] link exited with code {link.proc.returncode}: "
                                  f"stopping the run (see {self.run_dir}/logs/link.log)")
                return 1
            if replay.proc.poll() is not None and not (
                    replay.proc.returncode == 0 and self.learner_finishing(learner)):
                self.display.echo(f"[{PROG}] replay exited with code {replay.proc.returncode}: "
                                  f"stopping the run (see {self.run_dir}/logs/replay.log)")
                return 1
            for actor in actors:
                if actor.proc.poll() is not None and actor.name not in reported:
                    reported.add(actor.name)
                    if actor.proc.returncode == 0:
                        continue  # left on the learner's stop message
                    self.display.echo(f"[{PROG}] {actor.name} exited with code "
                                      f"{actor.proc.returncode}; the other actors go on")
            alive = sum(a.proc.poll() is None for a in actors)
            if not alive and all(a.proc.returncode == 0 for a in actors) and \
                    self.learner_finishing(learner):
                continue  # the actors left on the learner's stop message; it exits next
            if not alive:
                self.display.echo(f"[{PROG}] no actor is left: stopping the run")
                return 1
            self.display.show(self.display.line(alive, len(actors)))
            time.sleep(0.5)
        return 130

    def learner_finishing(self, learner: Child) -> bool:
        """The replay left on the learner's stop message: give the learner time to finish."""
        try:
            learner.proc.wait(self.plan.stop_timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return True

    def shutdown(self) -> None:
        """Reverse start order: actors, then the learner (final checkpoint), then the replay.
        Processes already told to stop by the learner get time to finish on their own."""
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(c.proc.poll() is None for c in self.children):
            if self.interrupted:
                break
            time.sleep(0.1)
        for child in reversed(self.children):
            code = child.stop(self.plan.stop_timeout_s)
            if code not in (0, None) and code != -signal.SIGTERM:
                self.display.echo(f"[{PROG}] {child.name} ended with code {code}")
        if self.display.tty:
            self.display.out.write("\n")

    def interrupt(self, signum, _frame) -> None:
        self.interrupted = True
        self.stopping.set()
        self.display.echo(f"[{PROG}] {signal.Signals(signum).name}: stopping the services")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", help=f"cluster file (default: {DEFAULT_FILE})")
    p.add_argument("--env-id", help="gymnasium environment id (overrides [train])")
    p.add_argument("--total-timesteps", type=int, help="env steps to train for")
    p.add_argument("--seed", type=int, help="seed of every service, actor and env")
    p.add_argument("--num-envs", type=int, help="envs per actor")
    p.add_argument("--actors", type=int, help="number of actor processes")
    p.add_argument("--run-dir", help="run directory (default runs/{env}__{exp}__{seed}__{time})")
    p.add_argument("--run-id", help="Zenoh run id (default from the file)")
    p.add_argument("--endpoint", help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="any training setting, e.g. --set learning_rate=3e-4 (repeatable)")
    for key in LINK_KEYS:
        p.add_argument(f"--link-{key.replace('_', '-')}", type=float, metavar="X",
                       help=f"link shim {key} between actors and the rest (0 = off; overrides "
                       "[link])")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    try:
        plan = make_plan(parse_args(argv))
        make_vector_env(plan.train.env_id, 1).close()  # one clear line for a wrong env id
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    cluster = Cluster(plan)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, cluster.interrupt)
    code = cluster.run()
    print(f"{PROG}: {'finished' if code == 0 else 'stopped'}; run dir {cluster.run_dir}",
          flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
