"""`tpdeb-cluster`: a compose-style launcher for the whole run on one machine (DESIGN §5).

Reads a cluster file (`deploy/local.toml`), writes the resolved training config into the run
dir, starts router → replay → learner → actors as separate processes in dependency order (each
waits for what it depends on to answer), prefixes and saves their logs, shows a live progress
line from the services' stats and liveliness tokens, restarts crashed services by their restart
policy (stopping the run on a crash loop), and stops everything in reverse order at the end or
on Ctrl-C. The learner ends the run: when it exits 0 the others stop on its stop message.
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
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from tpdeb.protocol import Control, DecodeError, Keys, Stats, decode
from tpdeb.services.config import ENV_PREFIX, ConfigError, coerce, load_toml, to_toml
from tpdeb.services.envs import make_vector_env
from tpdeb.services.presets import layer, shown
from tpdeb.services.security import SECURITY_KEYS, ClusterSecurity
from tpdeb.services.service_config import ServiceConfig
from tpdeb.services.train_config import TrainConfig
from tpdeb.services.zsession import fetch_spec, open_session

PROG = "tpdeb-cluster"
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FILE = ROOT / "deploy" / "local.toml"
ROLES = ("router", "replay", "learner", "actor")
SERVICE_KEYS = {"command", "replicas", "depends_on", "args", "env", "restart"}
RESTART_KEYS = ("restart_backoff_s", "restart_reset_s", "max_restarts", "crash_loop_window_s")
CLUSTER_KEYS = {"run_id", "endpoint", "stop_timeout_s", "start_timeout_s", *RESTART_KEYS}
RESTART_MODES = ("no", "on-failure", "always")
MAX_BACKOFF_S = 30.0
STALE_INTERVALS = 3  # stats older than this many intervals mark a service stale
LINK_KEYS = ("up_bytes_per_s", "down_bytes_per_s", "latency_ms", "jitter_ms", "queue_ms")


@dataclass(frozen=True)
class RestartPolicy:
    """Compose's vocabulary: "no", "on-failure" (a non-zero exit), "on-failure:N" (at most N
    restarts), "always" (any exit, unless the run is ending)."""

    mode: str = "on-failure"
    limit: int | None = None

    @classmethod
    def parse(cls, value, where: str) -> RestartPolicy:
        mode, sep, count = value.partition(":") if isinstance(value, str) else ("", "", "")
        if mode in RESTART_MODES and not sep:
            return cls(mode)
        if mode == "on-failure" and count.isdigit():
            return cls(mode, int(count))
        raise ConfigError(f"{where}: restart={value!r} is not a restart policy; use \"no\", "
                          "\"on-failure\", \"on-failure:N\" (at most N restarts) or \"always\"")

    def restarts_after(self, code: int) -> bool:
        return self.mode == "always" or (self.mode == "on-failure" and code != 0)

    def __str__(self) -> str:
        return self.mode if self.limit is None else f"{self.mode}:{self.limit}"


@dataclass(frozen=True)
class RestartSettings:
    """[cluster] back-off and crash-loop limits, shared by every service."""

    backoff_s: float = 1.0  # first delay; doubles per consecutive failure up to MAX_BACKOFF_S
    reset_after_s: float = 60.0  # a process up this long starts again from `backoff_s`
    max_restarts: int = 5  # more restarts of one process within `window_s` is a crash loop
    window_s: float = 120.0
    max_backoff_s: float = MAX_BACKOFF_S

    @classmethod
    def from_section(cls, cluster: dict, path) -> RestartSettings:
        values = {}
        for key, name in zip(RESTART_KEYS, ("backoff_s", "reset_after_s", "max_restarts",
                                            "window_s"), strict=True):
            if key not in cluster:
                continue
            value, integral = cluster[key], name == "max_restarts"
            number = not isinstance(value, bool) and isinstance(value, (int, float))
            if not number or (integral and not (value >= 0 and float(value).is_integer())) or (
                    not integral and not 0 < value < math.inf):
                raise ConfigError(f"{path} [cluster] {key}={value!r}: expected "
                                  f"{'an integer ≥ 0' if integral else 'a number of seconds > 0'}")
            values[name] = int(value) if integral else float(value)
        return cls(**values)


@dataclass
class Verdict:
    """What to do about one exit: "restart" after `delay_s`, "stay_down", or "crash_loop"."""

    action: str
    restarts: int  # restarts so far, this one included
    delay_s: float = 0.0
    reason: str = ""


class RestartTracker:
    """When one service process starts again after it exits. Pure: the clock is passed in.

    Back-off doubles per consecutive failure from `backoff_s` up to `max_backoff_s`, and starts
    over once the process has stayed up `reset_after_s`. More than `max_restarts` restarts within
    `window_s`, or an on-failure:N limit reached, is a crash loop: restarting again would only
    hide a fault that needs a person."""

    def __init__(self, policy: RestartPolicy, settings: RestartSettings):
        self.policy, self.settings = policy, settings
        self.restarts = 0
        self.consecutive = 0
        self.recent: deque[float] = deque()  # times of restarts within the window
        self.started_at: float | None = None

    def started(self, now: float) -> None:
        self.started_at = now

    def exited(self, code: int, now: float) -> Verdict:
        s = self.settings
        if not self.policy.restarts_after(code):
            return Verdict("stay_down", self.restarts)
        if self.started_at is not None and now - self.started_at >= s.reset_after_s:
            self.consecutive = 0
        while self.recent and now - self.recent[0] > s.window_s:
            self.recent.popleft()
        if self.policy.limit is not None and self.restarts >= self.policy.limit:
            return Verdict("crash_loop", self.restarts, reason=f'restart = "{self.policy}"')
        if len(self.recent) >= s.max_restarts:
            return Verdict("crash_loop", self.restarts,
                           reason=f"max_restarts = {s.max_restarts} within crash_loop_window_s "
                                  f"= {s.window_s:g} s")
        delay_s = min(s.backoff_s * 2 ** self.consecutive, s.max_backoff_s)
        self.consecutive += 1
        self.restarts += 1
        self.recent.append(now)
        return Verdict("restart", self.restarts, delay_s)


@dataclass
class ServiceSpec:
    role: str
    command: str
    replicas: int = 1
    depends_on: list[str] = field(default_factory=list)
    args: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    restart: RestartPolicy = field(default_factory=RestartPolicy)


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
    restarts: RestartSettings = field(default_factory=RestartSettings)
    security: ClusterSecurity = field(default_factory=ClusterSecurity)


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

    for name in sorted(services, key=lambda n: n != "router"):  # the network comes up first
        visit(name)
    return ordered


def make_plan(args: argparse.Namespace) -> Plan:
    path = Path(args.config) if args.config else DEFAULT_FILE
    data = load_toml(path)
    unknown = set(data) - {"cluster", "train", "services", "link", "security"}
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {sorted(unknown)}; expected cluster, "
                          "train, services, link, security")
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
        body = dict(body)
        restart = RestartPolicy.parse(body.pop("restart", "on-failure"),
                                      f"{path} [services.{role}]")
        services[role] = ServiceSpec(role=role, restart=restart, **body)
    missing = set(ROLES) - set(services)
    if missing:
        raise ConfigError(f"{path}: services {sorted(missing)} are missing (see "
                          f"{DEFAULT_FILE} for their sections)")
    if services["router"].depends_on:
        raise ConfigError(f"{path} [services.router]: depends_on="
                          f"{services['router'].depends_on}: the router starts first; remove it")
    if args.actors is not None:
        services["actor"].replicas = args.actors
    for spec in services.values():
        if spec.replicas < (1 if spec.role == "actor" else 0) or (
                spec.role != "actor" and spec.replicas != 1):
            raise ConfigError(f"services.{spec.role}.replicas={spec.replicas}: the router, the "
                              "replay and the learner run once, actors at least once")
    train = dict(data.get("train", {}))
    # The shell's TPDEB_* training variables rank between the file and the flags, as for any
    # service; resolved here once, so that train.toml is the whole training configuration and
    # no child applies them again on top of a flag (see child_environment).
    train.update({name: coerce(TrainConfig, name, value, ENV_PREFIX + name.upper())
                  for name, value in train_variables(os.environ).items()})
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
    security = ClusterSecurity.from_section(
        data.get("security", {}), {k: getattr(args, k, None) for k in SECURITY_KEYS}, str(path))
    endpoint = security.endpoint(endpoint)
    link = link_settings(data.get("link", {}), args, path)
    link_endpoint = ""
    if any(link.get(k, 0) for k in LINK_KEYS[:4]):  # the link forwards TLS bytes unchanged
        link_endpoint = security.endpoint(f"tcp/127.0.0.1:{free_port()}")
    return Plan(run_id=args.run_id or cluster.get("run_id", "local"), endpoint=endpoint,
                stop_timeout_s=float(cluster.get("stop_timeout_s", 20)),
                start_timeout_s=float(cluster.get("start_timeout_s", 120)),
                train=train_config, services=start_order(services), source=str(path),
                link=link, link_endpoint=link_endpoint,
                restarts=RestartSettings.from_section(cluster, path), security=security)


def train_variables(environ) -> dict[str, str]:
    """The training settings set in an environment: {field: value} of its TPDEB_<FIELD>."""
    return {f.name: environ[ENV_PREFIX + f.name.upper()] for f in dataclasses.fields(TrainConfig)
            if ENV_PREFIX + f.name.upper() in environ}


def child_environment(environ, *extra: dict) -> dict[str, str]:
    """A child's environment: the launcher's without the training variables it has already
    resolved into train.toml (they would outrank the file, and a flag the file carries), then
    `extra` (the service's own `env`, its credentials) on top."""
    trained = {ENV_PREFIX + name.upper() for name in train_variables(environ)}
    env = {k: v for k, v in environ.items() if k not in trained}
    for more in extra:
        env.update(more)
    return env


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
    """Values from TOML/flags (strings allowed) over the task's preset and the algorithm's
    settings → a validated TrainConfig."""
    return TrainConfig(**layer(TrainConfig, {k: coerce(TrainConfig, k, v, "train")
                                             for k, v in values.items()}))


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


class RunEnded(Exception):
    """The run must end with this exit status (the reason has been shown already)."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


class Child:
    """One service process slot: its command, log file and restart book-keeping, the current
    process, and the thread that prefixes its output. A restart starts a new process with the
    same argv that appends to the same log."""

    def __init__(self, name: str, role: str, argv: list[str], env: dict, log_path: Path, echo,
                 tracker: RestartTracker, ident: str | None = None, has_token: bool = True,
                 stats_interval_s: float = 1.0):
        self.name, self.role, self.argv, self.env = name, role, argv, env
        self.log_path, self.echo, self.tracker = log_path, echo, tracker
        self.ident = ident  # its stats (and liveliness token) are {role}/{ident}; None: none
        self.has_token = has_token
        self.stats_interval_s = stats_interval_s
        self.proc: subprocess.Popen | None = None
        self.reader: threading.Thread | None = None
        self.restart_at: float | None = None  # monotonic time a scheduled restart is due
        self.last_code: int | None = None
        self.reported = False  # the current process's exit was handed to the supervisor

    def start(self, now: float) -> None:
        log = self.log_path.open("a", buffering=1)
        if self.tracker.restarts:
            log.write(f"--- restart #{self.tracker.restarts} (exit code {self.last_code}) ---\n")
        self.proc = subprocess.Popen(
            self.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=self.env, start_new_session=True,
            preexec_fn=_die_with_parent, text=True, bufsize=1)
        self.reader = threading.Thread(target=self._pump, args=(self.proc, log), daemon=True)
        self.reader.start()
        self.tracker.started(now)
        self.restart_at, self.reported = None, False

    def _pump(self, proc: subprocess.Popen, log) -> None:
        for line in proc.stdout:
            log.write(line)
            self.echo(f"[{self.name}] {line.rstrip()}")
        log.close()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def poll_exit(self) -> int | None:
        """The current process's exit code, returned once, when it has ended."""
        if self.proc is None or self.reported or self.proc.poll() is None:
            return None
        self.reported, self.last_code = True, self.proc.returncode
        self.reader.join(timeout=5)  # its last words are in the log before anyone reads it
        return self.last_code

    def tail(self, lines: int = 3) -> list[str]:
        """The last lines of the log (read from its end: logs of long runs are large)."""
        try:
            with self.log_path.open("rb") as f:
                f.seek(max(0, f.seek(0, os.SEEK_END) - 16384))
                return f.read().decode(errors="replace").splitlines()[-lines:]
        except OSError:
            return []

    def view(self) -> ServiceView:
        return ServiceView(self.name, self.role, self.ident, self.has_token, self.running,
                           self.tracker.restarts, self.stats_interval_s)

    def stop(self, timeout_s: float) -> int | None:
        self.restart_at = None
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(timeout=5)
        return self.proc.returncode


@dataclass
class ServiceView:
    """What the cluster knows of one process, for the status line."""

    name: str
    role: str
    ident: str | None  # stats/liveliness ident; None: publishes neither (the router)
    has_token: bool
    running: bool
    restarts: int = 0
    stats_interval_s: float = 1.0


class Health:
    """Which services are alive, from their liveliness tokens (DESIGN §3) and the age of their
    stats; rendered as the `up: …` part of the status line. Thread-safe: Zenoh callbacks feed
    it, the supervisor reads it."""

    def __init__(self):
        self.alive: set[tuple[str, str]] = set()
        self.seen: set[tuple[str, str]] = set()  # had a token since its last (re)start
        self.stats_at: dict[tuple[str, str], float] = {}
        self.lock = threading.Lock()

    def on_token(self, sample) -> None:
        """Liveliness subscriber callback: …/alive/{role}/{ident} appears (PUT) or goes."""
        role, _, ident = str(sample.key_expr).rpartition("/alive/")[2].partition("/")
        self.token(role, ident, sample.kind == zenoh.SampleKind.PUT)

    def token(self, role: str, ident: str, alive: bool) -> None:
        with self.lock:
            (self.alive.add if alive else self.alive.discard)((role, ident))
            if alive:
                self.seen.add((role, ident))

    def saw_stats(self, role: str, ident: str, now: float) -> None:
        with self.lock:
            self.stats_at[(role, ident)] = now

    def restarted(self, role: str, ident: str | None) -> None:
        """A restarted process starts fresh: its predecessor's stats do not make it stale."""
        with self.lock:
            self.stats_at.pop((role, ident), None)
            self.seen.discard((role, ident))

    def summary(self, views: list[ServiceView], now: float) -> str:
        up, starting, unreachable, down, stale = [], [], [], [], []
        actors = actors_up = 0
        with self.lock:
            for v in views:
                key = (v.role, v.ident)
                # A token gone while the process runs: the network lost it, or it is stopping.
                state = ("down" if not v.running else "up" if not v.has_token or
                         key in self.alive else "unreachable" if key in self.seen else "starting")
                seen = self.stats_at.get(key)
                if state == "up" and seen is not None and \
                        now - seen > STALE_INTERVALS * v.stats_interval_s:
                    stale.append(f"{v.name} {now - seen:.0f} s")
                if v.role == "actor":
                    actors, actors_up = actors + 1, actors_up + (state == "up")
                else:
                    {"up": up, "starting": starting, "unreachable": unreachable,
                     "down": down}[state].append(v.name)
        if actors:
            up.append(f"actors {actors_up}/{actors}")
        parts = [f"up: {' '.join(up) or 'none'}"]
        parts += [f"{label}: {' '.join(names)}" for label, names in
                  (("starting", starting), ("unreachable", unreachable), ("down", down)) if names]
        if stale:
            parts.append(f"stale: {', '.join(stale)}")
        restarts = [f"{v.name} {v.restarts}" for v in views if v.restarts]
        if restarts:
            parts.append(f"restarts: {', '.join(restarts)}")
        return " | ".join(parts)


class Display:
    """Latest stats per service, rendered as one status line (redrawn in place on a TTY)."""

    def __init__(self, out=sys.stdout):
        self.out = out
        self.tty = out.isatty()
        self.latest: dict[tuple[str, str], dict] = {}
        self.lock = threading.Lock()
        self.last_plain = 0.0
        self.status = ""

    def on_stats(self, sample) -> Stats | None:
        try:
            stats = decode(sample.payload.to_bytes(), Stats)
        except DecodeError:
            return None
        with self.lock:
            self.latest[(stats.role, stats.ident)] = stats.values
        return stats

    def parts(self, health: str) -> list[tuple[str, int]]:
        """The status line's parts, training progress from the latest stats, then `health`
        (Health.summary), each with its rank: where the line is wider than the terminal the
        highest ranks go first (see `fit`)."""
        with self.lock:
            learner = self.latest.get(("learner", "0"), {})
            replay = self.latest.get(("replay", "0"), {})
            link = self.latest.get(("link", "0"))
        if not learner:
            return [("starting…", 0), (health, 1)]
        step, total = int(learner.get("global_step", 0)), int(learner.get("total_timesteps", 0))
        pct = f" ({100 * step / total:.0f}%)" if total else ""
        fill = replay.get("prioritized_items", 0), replay.get("uniform_steps", 0)
        parts = [(f"{step:,}/{total:,} steps{pct}", 0),
                 (f"{learner.get('sps', 0):,.0f} SPS", 2),
                 (f"return {learner.get('mean_return', math.nan):,.1f}", 1),
                 (f"replay {fill[0]} fragments + {fill[1]:,} steps", 7),
                 (f"lag {learner.get('param_version_lag', math.nan):.1f} versions", 6),
                 (f"{int(learner.get('updates', 0)):,} updates", 5)]
        if link:
            parts.append((f"link ↑{link.get('up_bytes_per_s', 0) / 1e3:,.0f} "
                          f"↓{link.get('down_bytes_per_s', 0) / 1e3:,.0f} kB/s", 4))
        return [*parts, (health, 3)]

    def echo(self, text: str) -> None:
        with self.lock:
            if self.tty and self.status:
                self.out.write("\r\033[K")
            self.out.write(text + "\n")
            if self.tty and self.status:
                self.out.write(self.status)
            self.out.flush()

    def show(self, parts: list[tuple[str, int]], plain_interval_s: float = 10.0) -> None:
        """On a terminal: redraw the line in place, fitted to the terminal's width now (a line
        that wraps cannot be redrawn: each redraw would add rows). Elsewhere (a log file): the
        whole line every `plain_interval_s`."""
        if self.tty:
            # One column spare: writing the last one moves some terminals to the next row.
            width = shutil.get_terminal_size((100, 24)).columns - 1
            with self.lock:
                self.status = fit([(f"[{PROG}]", -1), *parts], width, " ")
                self.out.write("\r\033[K" + self.status)
                self.out.flush()
        elif time.monotonic() - self.last_plain >= plain_interval_s:
            self.last_plain = time.monotonic()
            self.echo(f"[{PROG}] " + " | ".join(text for text, _ in parts))


def fit(parts: list[tuple[str, int]], width: int, first_sep: str = " | ") -> str:
    """Join (text, rank) parts with " | " (`first_sep` after the first), dropping the highest
    ranks until the line fits in `width` columns, then cutting it with "…"."""
    def join(kept):
        return (kept[0][0] + first_sep + " | ".join(t for t, _ in kept[1:])) if len(kept) > 1 \
            else kept[0][0]

    kept = list(parts)
    while len(kept) > 2 and len(join(kept)) > width:
        kept.remove(max(kept, key=lambda part: part[1]))
    line = join(kept)
    return line if len(line) <= width else line[:max(width - 1, 0)] + "…"


class Cluster:
    def __init__(self, plan: Plan, out=sys.stdout):
        self.plan = plan
        self.run_dir = Path(plan.train.run_dir)
        self.display = Display(out)
        self.children: list[Child] = []  # in start order
        self.health = Health()
        self.stopping = threading.Event()
        self.finishing = threading.Event()  # the learner broadcast its stop
        self.session = None
        self.interrupted = False

    def write_run_dir(self) -> Path:
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        if self.plan.security.enabled:
            host = self.plan.endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
            self.plan.security.prepare(self.run_dir / "security", self.users(),
                                       [host, "127.0.0.1", "localhost"])
        service_config = ServiceConfig(**dataclasses.asdict(self.plan.train),
                                       run_id=self.plan.run_id, connect=(self.plan.endpoint,))
        path = self.run_dir / "train.toml"
        path.write_text(to_toml(self.plan.train))
        (self.run_dir / "cluster.json").write_text(json.dumps({
            "source": self.plan.source, "run_id": self.plan.run_id,
            "endpoint": self.plan.endpoint, "link": self.plan.link,
            "link_endpoint": self.plan.link_endpoint,
            "services": [{**dataclasses.asdict(s), "restart": str(s.restart)}
                         for s in self.plan.services],
            "restarts": dataclasses.asdict(self.plan.restarts),
            "security": self.plan.security.summary(),
            "train": dataclasses.asdict(service_config)}, indent=2))
        return path

    def users(self) -> list[str]:
        """One user per process that opens a session (access control knows them by role)."""
        users = ["monitor"] + (["link"] if self.plan.link_endpoint else [])
        for spec in self.plan.services:
            users += [user_of(spec.role, i) for i in range(spec.replicas) if spec.role != "router"]
        return users

    def argv(self, spec: ServiceSpec, train_file: Path, index: int) -> list[str]:
        argv = [*resolve_command(spec.command), "--config", str(train_file),
                "--run-id", self.plan.run_id]
        if spec.role == "router":
            argv += ["--listen", self.plan.endpoint, *self.plan.security.router_args()]
        elif spec.role == "replay":
            # A client of the router (no listen endpoint of its own): the network lives in
            # the router process and outlives a replay restart.
            argv += ["--listen", "", "--connect", self.plan.endpoint]
        elif spec.role == "actor" and self.plan.link_endpoint:
            argv += ["--connect", self.plan.link_endpoint]  # actors sit behind the link
        else:
            argv += ["--connect", self.plan.endpoint]
        if spec.role == "actor":
            argv += ["--actor-id", str(index)]
        if self.plan.link_endpoint and spec.role in ("router", "actor"):  # the link's ends
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
        say(f"[{PROG}] algo {self.plan.train.algo}; preset: {shown(self.plan.train.preset)}")
        keys = Keys(self.plan.run_id)
        try:
            router, *others = self.plan.services
            self.add(router, train_file, 0)
            self.wait_until(lambda: self.connect(keys), "router")
            # The rest in dependency order without waiting in between: each service waits for
            # what it needs (the run spec, the first parameters), so their slow imports
            # overlap. The checks below then name the one that fails to come up.
            for spec in others:
                if spec.role == "actor" and self.plan.link_endpoint:
                    self.add_link(router)
                for i in range(spec.replicas):
                    if not self.stopping.is_set():
                        self.add(spec, train_file, i)
            self.wait_until(lambda: fetch_spec(self.session, keys, 1.0) is not None, "replay")
            self.wait_until(lambda: self._answers(self.session, keys.params_latest), "learner")
            return self.supervise()
        except ConfigError as exc:
            say(f"[{PROG}] error: {exc}")
            return 1
        except RunEnded as end:
            return end.code
        finally:
            self.shutdown()
            if self.session is not None:
                self.session.close()

    def add(self, spec: ServiceSpec, train_file: Path, index: int) -> None:
        name = spec.role if spec.replicas == 1 else f"{spec.role}-{index}"
        env = child_environment(os.environ, {k: str(v) for k, v in spec.env.items()},
                                self.plan.security.env(user_of(spec.role, index)))
        self.start(Child(
            name, spec.role, self.argv(spec, train_file, index), env,
            self.run_dir / "logs" / f"{name}.log", self.display.echo,
            RestartTracker(spec.restart, self.plan.restarts),
            ident=None if spec.role == "router" else str(index),
            has_token=spec.role != "router",
            stats_interval_s=stats_interval_s(spec.args, env)))

    def add_link(self, router: ServiceSpec) -> None:
        # The link is part of the network between the actors and the router: restarted like it.
        self.start(Child("link", "link", self.link_argv(),
                         child_environment(os.environ, self.plan.security.env("link")),
                         self.run_dir / "logs" / "link.log", self.display.echo,
                         RestartTracker(router.restart, self.plan.restarts), ident="0",
                         has_token=False))

    def start(self, child: Child) -> None:
        child.start(time.monotonic())
        self.children.append(child)

    def connect(self, keys: Keys) -> bool:
        """The cluster's own client session: readiness checks, the stats and liveliness tokens
        it displays, and the learner's stop message (after which nothing is restarted)."""
        # Short attempts: a router that crashes while starting is noticed (and restarted).
        self.session = open_session("client", [], [self.plan.endpoint], 1.0,
                                    security=self.plan.security.session("monitor"))
        self.subscribers = [
            self.session.declare_subscriber(keys.stats_all, self._on_stats),
            self.session.declare_subscriber(keys.control, self._on_control),
            self.session.liveliness().declare_subscriber(keys.alive_all, self.health.on_token,
                                                         history=True)]
        return True

    def _on_stats(self, sample) -> None:
        stats = self.display.on_stats(sample)
        if stats is not None:
            self.health.saw_stats(stats.role, stats.ident, time.monotonic())

    def _on_control(self, sample) -> None:
        with contextlib.suppress(DecodeError):
            if decode(sample.payload.to_bytes(), Control).command == "stop":
                self.finishing.set()

    @staticmethod
    def _answers(session, key: str) -> bool:
        return any(r.ok is not None for r in session.get(key, timeout=1.0))

    def wait_until(self, ready, what: str) -> None:
        deadline = time.monotonic() + self.plan.start_timeout_s
        while time.monotonic() < deadline and not self.stopping.is_set():
            end = self.tend()
            if end is not None:
                raise RunEnded(end)
            with contextlib.suppress(ConfigError, zenoh.ZError):  # not yet: ask again
                if ready():
                    return
            self.display.show(self.status_line())
            time.sleep(0.2)
        if not self.stopping.is_set():
            raise ConfigError(f"{what} did not come up within {self.plan.start_timeout_s:g} s "
                              f"(start_timeout_s); see {self.run_dir}/logs/{what}.log")

    def supervise(self) -> int:
        while not self.stopping.is_set():
            end = self.tend()
            if end is not None:
                return end
            self.display.show(self.status_line())
            time.sleep(0.5)
        return 130

    def status_line(self) -> list[tuple[str, int]]:
        return self.display.parts(self.health.summary([c.view() for c in self.children],
                                                      time.monotonic()))

    def tend(self) -> int | None:
        """One supervision step: notice exits, apply the restart policies, start the restarts
        that are due. Returns the run's exit status once the run must end."""
        now = time.monotonic()
        for child in self.children:
            code = child.poll_exit()
            if code is not None:
                end = self.on_exit(child, code, now)
                if end is not None:
                    return end
            elif child.restart_at is not None and now >= child.restart_at and not self.ending:
                self.health.restarted(child.role, child.ident)
                child.start(now)
        return self.check_actors()

    @property
    def ending(self) -> bool:
        """Ctrl-C, or the learner's stop message: nothing is restarted any more."""
        return self.stopping.is_set() or self.finishing.is_set()

    def on_exit(self, child: Child, code: int, now: float) -> int | None:
        say = self.display.echo
        if child.role == "learner" and code == 0:  # the learner ends the run
            self.finishing.set()
            say(f"[{PROG}] learner exited with code 0")
            return 130 if self.interrupted else 0
        if self.stopping.is_set():
            return None
        if code == 0 and child.role != "learner" and self.learner_finishing():
            return None  # it left on the learner's stop message; the learner exits next
        if self.finishing.is_set():
            if child.role != "learner":
                return None
            say(f"[{PROG}] learner exited with code {code} while finishing; see {child.log_path}")
            return 1
        verdict = child.tracker.exited(code, now)
        if verdict.action == "restart":
            child.restart_at = now + verdict.delay_s
            say(f"[{PROG}] {child.name} exited with code {code}; restarting in "
                f"{verdict.delay_s:g} s (restart {verdict.restarts})")
            return None
        if verdict.action == "crash_loop":
            tail = "".join(f"\n    {line}" for line in child.tail(3))
            say(f"[{PROG}] {child.name} is crash looping: exited with code {code} after "
                f"{verdict.restarts} restart{'' if verdict.restarts == 1 else 's'} "
                f"({verdict.reason}); stopping the run. Its log {child.log_path} ends:{tail}")
            return 1
        policy = f'restart = "{child.tracker.policy}"'
        if child.role == "actor":  # stays down by its policy; the others go on
            say(f"[{PROG}] {child.name} exited with code {code}; the other actors go on "
                f"({policy})")
            return None
        say(f"[{PROG}] {child.name} exited with code {code}: stopping the run ({policy}; see "
            f"{child.log_path})")
        return 1

    def check_actors(self) -> int | None:
        actors = [c for c in self.children if c.role == "actor"]
        if not actors or self.finishing.is_set() or any(
                a.running or a.restart_at is not None for a in actors):
            return None
        if all(a.last_code == 0 for a in actors) and self.learner_finishing():
            return None  # the actors left on the learner's stop message; it exits next
        self.display.echo(f"[{PROG}] no actor is left: stopping the run")
        return 1

    def learner_finishing(self) -> bool:
        """Whether the run is ending on the learner's stop message. A service may see the
        message before this cluster does: wait up to stop_timeout_s for it (or the learner's
        exit 0)."""
        learner = next((c for c in self.children if c.role == "learner"), None)
        deadline = time.monotonic() + self.plan.stop_timeout_s
        while not self.stopping.is_set():
            if self.finishing.is_set() or (learner is not None and learner.proc.poll() == 0):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.1)
        return True

    def shutdown(self) -> None:
        """Reverse start order: actors, then the learner (final checkpoint), then the replay,
        then the router. Processes already told to stop by the learner get time to finish on
        their own; nothing is restarted from here on."""
        finishing = self.finishing.is_set() and not self.interrupted
        self.stopping.set()
        deadline = time.monotonic() + 5.0
        while finishing and time.monotonic() < deadline and any(
                c.running for c in self.children if c.role not in ("router", "link")):
            time.sleep(0.1)
        for child in reversed(self.children):
            reported = child.reported
            code = child.stop(self.plan.stop_timeout_s)
            if not reported and code not in (0, None, -signal.SIGTERM):
                self.display.echo(f"[{PROG}] {child.name} ended with code {code}")
        if self.display.tty:
            self.display.out.write("\n")

    def interrupt(self, signum, _frame) -> None:
        self.interrupted = True
        self.stopping.set()
        self.display.echo(f"[{PROG}] {signal.Signals(signum).name}: stopping the services")


def user_of(role: str, index: int) -> str:
    """The user a service authenticates as: its role, with the actor's id ("" for the router,
    which authenticates the others)."""
    return {"actor": f"actor-{index}", "router": ""}.get(role, role)


def stats_interval_s(args: list, env: dict) -> float:
    """The stats interval a service was given (flag, else TPDEB_ variable, else the default),
    against which the display judges its stats stale."""
    args = [str(a) for a in args]
    value = env.get("TPDEB_STATS_INTERVAL_S")
    for i, arg in enumerate(args):
        if arg == "--stats-interval-s" and i + 1 < len(args):
            value = args[i + 1]
        elif arg.startswith("--stats-interval-s="):
            value = arg.partition("=")[2]
    try:
        return float(value) if value else ServiceConfig.stats_interval_s
    except ValueError:
        return ServiceConfig.stats_interval_s  # the service itself refuses it, with the reason


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
    for key, text in (("tls", "TLS on every link (the endpoint becomes tls/…)"),
                      ("auth", "a generated user and password per service"),
                      ("acl", "access control: each service only its role's traffic")):
        p.add_argument(f"--{key}", action=argparse.BooleanOptionalAction, default=None,
                       help=f"{text} (overrides [security])")
    p.add_argument("--certs-dir", help="ca.pem, router.pem, router.key to use (tpdeb-certs "
                   "writes them; default: new ones in {run_dir}/security)")
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
