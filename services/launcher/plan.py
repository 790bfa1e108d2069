"""The launch plan: the cluster file, flags and TPDEB_* variables resolved once into what to
start, in which order, with which training configuration (DESIGN §5)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

from tpdeb.services.config import (
    ENV_PREFIX,
    ConfigError,
    check_environment,
    coerce,
    is_cluster_file,
    known_settings,
    load_toml,
    parse_sets,
    read_sections,
    read_settings_file,
    refuse_retired,
)
from tpdeb.services.config.presets import layer
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.launcher.restart import RESTART_KEYS, RestartPolicy, RestartSettings
from tpdeb.services.net.security import SECURITY_KEYS, ClusterSecurity

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_FILE = ROOT / "deploy" / "local.toml"
ROLES = ("router", "replay", "learner", "actor", "evaluator")
OPTIONAL = ("evaluator",)  # a cluster file without its section runs without it
SERVICE_KEYS = {"command", "replicas", "depends_on", "args", "env", "restart"}
CLUSTER_KEYS = {"run_id", "endpoint", "stop_timeout_s", "start_timeout_s", "hang_intervals",
                *RESTART_KEYS}
PASSWORD_VARIABLE = ENV_PREFIX + "PASSWORD"  # the one setting no file carries
LINK_KEYS = ("up_bytes_per_s", "down_bytes_per_s", "latency_ms", "jitter_ms", "queue_ms")


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
    hang_intervals: float = 30.0  # stats silent this many of a service's intervals: hung
    group_endpoint: str = ""  # where data-parallel learners meet (learners > 1)


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
    """The cluster file with the flags and the shell's variables on top, checked whole."""
    path = Path(args.cluster_file) if args.cluster_file else DEFAULT_FILE
    data = load_toml(path, "--cluster-file")
    if not is_cluster_file(data) and data:
        raise ConfigError(f"--cluster-file {path} is a settings file (it has "
                          f"{', '.join(f'[{t}]' for t in sorted(data))}): pass it as --config, "
                          "on top of a cluster file")
    unknown = set(data) - {"cluster", "train", "services", "link", "security"}
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {sorted(unknown)}; expected cluster, "
                          "train, services, link, security")
    cluster = data.get("cluster", {})
    if set(cluster) - CLUSTER_KEYS:
        raise ConfigError(f"{path} [cluster]: unknown key(s) {sorted(set(cluster) - CLUSTER_KEYS)}"
                          f"; known: {sorted(CLUSTER_KEYS)}")
    services = service_specs(data.get("services", {}), path, args.actors)
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
    train = train_settings(data.get("train", {}), args, f"{path} [train]")
    if train.eval_every() == (0, 0.0):  # eval_interval = 0: no evaluation, no evaluator
        services.pop("evaluator", None)
    services["replay"].replicas = train.replay_shards  # one replay server per shard
    services["learner"].replicas = train.learners  # one process per rank
    if train.replay_shards > services["actor"].replicas:
        raise ConfigError(f"replay_shards={train.replay_shards} with {services['actor'].replicas} "
                          "actor(s): actor a writes to shard a mod replay_shards, so a shard "
                          "beyond the actors would stay empty; use at most one per actor")
    return Plan(run_id=args.run_id or cluster.get("run_id", "local"), endpoint=endpoint,
                stop_timeout_s=float(cluster.get("stop_timeout_s", 20)),
                start_timeout_s=float(cluster.get("start_timeout_s", 120)),
                train=train, services=start_order(services), source=str(path), link=link,
                link_endpoint=link_endpoint,
                restarts=RestartSettings.from_section(cluster, path), security=security,
                hang_intervals=hang_intervals(cluster, path),
                group_endpoint=f"127.0.0.1:{free_port()}" if train.learners > 1 else "")


def hang_intervals(cluster: dict, path) -> float:
    value = cluster.get("hang_intervals", 30)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise ConfigError(f"{path} [cluster]: hang_intervals={value!r} must be a number >= 0 "
                          "(a service whose stats stay silent for that many of its stats "
                          "intervals is restarted; 0: never)")
    return float(value)


def service_specs(sections: dict, path: Path, actors: int | None) -> dict[str, ServiceSpec]:
    """The [services.*] sections as specs, every role present once, `--actors` applied."""
    services = {}
    for role, body in sections.items():
        if role not in ROLES:
            raise ConfigError(f"{path}: unknown service {role!r}; services are {ROLES}")
        if set(body) - SERVICE_KEYS:
            raise ConfigError(f"{path} [services.{role}]: unknown key(s) "
                              f"{sorted(set(body) - SERVICE_KEYS)}; known: {sorted(SERVICE_KEYS)}")
        body = dict(body)
        restart = RestartPolicy.parse(body.pop("restart", "on-failure"),
                                      f"{path} [services.{role}]")
        services[role] = ServiceSpec(role=role, restart=restart, **body)
    missing = set(ROLES) - set(OPTIONAL) - set(services)
    if missing:
        raise ConfigError(f"{path}: services {sorted(missing)} are missing (see "
                          f"{DEFAULT_FILE} for their sections)")
    if services["router"].depends_on:
        raise ConfigError(f"{path} [services.router]: depends_on="
                          f"{services['router'].depends_on}: the router starts first; remove it")
    if actors is not None:
        services["actor"].replicas = actors
    for spec in services.values():
        if spec.replicas < (1 if spec.role == "actor" else 0) or (
                spec.role != "actor" and spec.replicas != 1):
            raise ConfigError(f"services.{spec.role}.replicas={spec.replicas}: the router, the "
                              "replay, the learner and the evaluator run once, actors at least "
                              "once (replay_shards and learners set how many replays and "
                              "learners)")
    return services


def train_settings(section: dict, args: argparse.Namespace, source: str) -> TrainConfig:
    """[train] (its tables [train.run], [train.loss], …) < `--config FILE` < the shell's
    TPDEB_* training variables < the flags and --set, as every service takes them."""
    check_environment(os.environ)
    refuse_retired(vars(args))
    train = read_sections(TrainConfig, section, source)
    if args.config:
        train.update(read_settings_file(TrainConfig, args.config))
    # The variables are resolved here once, so that train.toml is the whole training
    # configuration and no child applies them again on top of a flag (see child_environment).
    train.update({name: coerce(TrainConfig, name, value, ENV_PREFIX + name.upper())
                  for name, value in train_variables(os.environ).items()})
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    train.update({k: coerce(TrainConfig, k, v, "--" + k.replace("_", "-"))
                  for k, v in vars(args).items() if k in names})
    for key, value in parse_sets(args.set).items():
        if key not in names:
            raise ConfigError(f"--set {key}: {key} is a service setting, not a training one; "
                              "give it in the service's `args` in the cluster file")
        train[key] = coerce(TrainConfig, key, value, f"--set {key}")
    config = coerce_train(train)
    if not config.run_dir:
        config.run_dir = str(config.default_run_dir())
    return config


def train_variables(environ) -> dict[str, str]:
    """The training settings set in an environment: {field: value} of its TPDEB_<FIELD>."""
    return {f.name: environ[ENV_PREFIX + f.name.upper()] for f in dataclasses.fields(TrainConfig)
            if ENV_PREFIX + f.name.upper() in environ}


def child_environment(environ, *extra: dict) -> dict[str, str]:
    """The environment a child's configuration is resolved in: the launcher's without the
    training variables it has already resolved into train.toml (they would outrank the file,
    and a flag the file carries), then `extra` (the service's own `env`, its credentials)."""
    trained = {ENV_PREFIX + name.upper() for name in train_variables(environ)}
    env = {k: v for k, v in environ.items() if k not in trained}
    for more in extra:
        env.update(more)
    return env


def resolved_environment(env: dict[str, str]) -> dict[str, str]:
    """A child's environment once its configuration is resolved into its file: no TPDEB_*
    setting is left to act twice, except the password, which no file carries."""
    settings = {ENV_PREFIX + name.upper() for name in known_settings()} - {PASSWORD_VARIABLE}
    return {k: v for k, v in env.items() if k not in settings}


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
