"""The services' configurations, each composed of the groups it uses (DESIGN §5):

    router   NetConfig + its own (auth file, access control)
    replay   NetConfig + SamplingConfig (run, model, replay, priorities) + its own
    learner  NetConfig + LearningConfig (SamplingConfig, learner, loss) + its own
    actor    NetConfig + RunSettings + ActingSettings + its own
    evaluator  NetConfig + RunSettings + EvalSettings

`NetConfig` is what every process on the network needs (run id, endpoints, security, stats,
logging). Each group is a table of the TOML file, so one file (train.toml) configures every
service of a run, each taking its groups and passing over the others'."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from tpdeb.services.config import ConfigError
from tpdeb.services.config.train import (
    ActingSettings,
    EvalSettings,
    LearningConfig,
    RunSettings,
    SamplingConfig,
    chain_post_init,
    check,
)
from tpdeb.services.logs import LEVELS
from tpdeb.services.net.security import access_control, check_settings, read_auth_file

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_RUN_ID = re.compile(r"[A-Za-z0-9_.-]{1,64}")


@dataclass
class NetConfig:
    """How a process joins the run's network."""

    SECTION = "net"

    run_id: str = "default"
    """run identifier: every key expression lives under tpdeb/{run_id}/, so runs sharing a
    router never exchange data"""
    listen: tuple[str, ...] = ()
    """Zenoh endpoints this process listens on, e.g. tcp/127.0.0.1:7447"""
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints (the replay server's router) this process connects to"""
    connect_timeout_s: float = 60.0
    """how long to wait for the router (and for the run spec) before giving up"""
    stats_interval_s: float = 1.0
    """seconds between stats publications"""
    log_level: str = "info"
    """debug, info, warning or error: what the service prints"""
    tcp_buffer_bytes: int = 0
    """socket buffers of this process's Zenoh TCP links (0: the OS's autotuning); small values
    keep a throttled link from queueing seconds of data ahead of acks and keep-alives"""
    max_message_bytes: int = 16 * 2**20
    """incoming messages larger than this are dropped unread (and counted)"""
    tls_ca: str = ""
    """CA certificate (PEM) trusted on tls/ endpoints; the router's certificate must be signed
    by it (tpdeb-certs DIR writes DIR/ca.pem). Empty: the system's CAs"""
    tls_cert: str = ""
    """certificate (PEM) this process presents on its tls/ --listen endpoints, i.e. the
    router's (tpdeb-certs DIR writes DIR/router.pem)"""
    tls_key: str = ""
    """private key of --tls-cert (tpdeb-certs DIR writes DIR/router.key, readable by its owner
    only)"""
    user: str = ""
    """user name this process authenticates to its router with; under access control it is
    the role: replay, learner, actor-{actor_id}, monitor or link"""
    password: str = ""
    """password of --user: set it as TPDEB_PASSWORD, not as a flag (every user of the machine
    sees a process's arguments in ps). It is kept out of every copy of the config (run dir,
    checkpoints, TensorBoard)"""
    password_file: str = ""
    """file whose first line is the password of --user (a Docker or Kubernetes secret, e.g.
    /run/secrets/actor_password), instead of TPDEB_PASSWORD"""

    def __post_init__(self):
        chain_post_init(NetConfig, self)  # the training groups', in a ServiceConfig
        check(self, [
            (_RUN_ID.fullmatch(self.run_id), "run_id", "use 1-64 letters, digits, '_', '.', '-'"),
            (self.log_level in LEVELS, "log_level", f"expected one of {', '.join(LEVELS)}"),
            (self.connect_timeout_s > 0, "connect_timeout_s", "must be > 0"),
        ])
        if self.password_file:
            if self.password:
                raise ConfigError("password and password_file are both set: keep one")
            self.password = read_password_file(self.password_file)
        check_settings(self.listen, self.connect, self.tls_ca, self.tls_cert, self.tls_key,
                       self.user, self.password)
        # Services write their config into the run dir and their checkpoints; the password
        # moves to an attribute that is not a field, so none of those copies carries it.
        if self.password:
            self.secret_password, self.password = self.password, ""


@dataclass
class SharedMemoryConfig:
    """Shared memory between the processes of one host that may use it."""

    SECTION = "net"

    shared_memory: bool = False
    """carry large messages (sample replies, parameters) between this process and the replay,
    learner or router on the same host through Zenoh's shared memory instead of TCP, where both
    ends set it; each link negotiates it, so processes on other hosts, or in containers that do
    not share /dev/shm, get TCP. Off by default: on two cores the default cluster made 0.90×
    the env steps/s with it. Actors never use it: their data crosses the network path (and the
    link shim) as it would between hosts"""


@dataclass
class RouterConfig(SharedMemoryConfig, NetConfig):
    """The router's settings: the network's and who may use it."""

    SECTION = "router"

    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints the router listens on (every service connects here)"""
    connect: tuple[str, ...] = ()
    """other routers to connect to (multi-host setups)"""
    auth_file: str = ""
    """user:password dictionary, one pair a line, readable by its owner only: with it, only
    sessions presenting a listed user and its password may connect"""
    acl: bool = False
    """access control (needs --auth-file): default deny, and each user gets only its role's
    traffic under tpdeb/{run_id}/. Users are roles: replay, learner, actor-{i}, monitor, link
    (ROLE@RUN_ID for a role of another run sharing this router)"""

    def __post_init__(self):
        super().__post_init__()
        if not self.listen:
            raise ConfigError("the router needs at least one --listen endpoint")
        if self.acl and not self.auth_file:
            raise ConfigError("--acl needs --auth-file: access rules are per authenticated user")
        if self.auth_file:
            users = read_auth_file(self.auth_file)
            if Path(self.auth_file).stat().st_mode & 0o077:
                raise ConfigError(f"--auth-file {self.auth_file} holds passwords but others may "
                                  f"read it: chmod 600 {self.auth_file}")
            if self.acl:
                access_control(self.run_id, users)  # every user must be a role


@dataclass
class ReplayServiceConfig(SharedMemoryConfig, NetConfig, SamplingConfig):
    """The replay server's settings: the network's, the replay's and its durability."""

    SECTION = "replay"

    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints the replay server's router listens on (the others connect here)"""
    connect: tuple[str, ...] = ()
    """other routers to connect to (multi-host setups with a separate zenohd)"""
    max_pending_fragments: int = 1024
    """fragments received but held back by the rate limiter; beyond this, new ones are dropped
    unacknowledged (their actors resend them)"""
    max_queued_per_sender: int = 64
    """messages of one sender (an actor's trajectory key) waiting to be decoded; beyond this
    its new ones are dropped on arrival (an honest actor has at most its outbox in flight), so
    one that floods cannot fill memory or crowd the others out"""
    sample_wait_s: float = 1.0
    """how long a sample request may wait for the rate limiter before a 'not ready' reply"""
    persist: bool = True
    """keep a write-ahead log and snapshots in {run_dir}/replay, and acknowledge a fragment only
    once it is on disk, so acknowledged fragments survive a crash; off: nothing survives"""
    snapshot_interval_s: float = 60.0
    """seconds between background snapshots of the whole replay (0: only at shutdown); they
    bound how much log a restart replays"""
    keep_snapshots: int = 2
    """complete snapshots kept (the newest that reads back is restored)"""
    restore: str = "auto"
    """auto: start from the newest complete snapshot in {run_dir}/replay plus the log after it
    (empty when there is none); never: start empty, moving earlier state aside"""
    shard: int = 0
    """which replay shard this server is, 0 to replay_shards - 1 (its state in
    {run_dir}/replay-{shard} when there are several)"""

    def __post_init__(self):
        super().__post_init__()
        if not self.listen and not self.connect:
            raise ConfigError("the replay server needs --listen (or --connect to a router)")
        check(self, [
            (0 <= self.shard < self.replay_shards, "shard",
             f"must be in [0, replay_shards={self.replay_shards})"),
            (self.restore in ("auto", "never"), "restore", "expected auto or never"),
            (self.snapshot_interval_s >= 0, "snapshot_interval_s", "must be ≥ 0"),
            (self.keep_snapshots >= 1, "keep_snapshots", "must be ≥ 1"),
        ])


@dataclass
class LearnerServiceConfig(SharedMemoryConfig, NetConfig, LearningConfig):
    """The learner's settings: the network's, the training's and its checkpoints."""

    SECTION = "learner"

    requests_in_flight: int = 3
    """sample requests kept outstanding at the replay server so the learner never waits"""
    request_timeout_s: float = 30.0
    """a sample request unanswered this long is abandoned and asked again"""
    rank: int = 0
    """this learner's rank among `learners` (0 publishes, checkpoints and writes metrics)"""
    group_endpoint: str = "127.0.0.1:29500"
    """host:port where the learners meet (rank 0 listens: torch.distributed's TCP store, with
    no TLS or password — keep it on a trusted network)"""
    group_timeout_s: float = 120.0
    """seconds a learner waits for the others in an exchange before it fails (and the cluster
    restarts the group from its last checkpoint)"""

    def __post_init__(self):
        super().__post_init__()
        host, _, port = self.group_endpoint.rpartition(":")
        check(self, [
            (self.requests_in_flight >= 1, "requests_in_flight", "must be ≥ 1"),
            (0 <= self.rank < self.learners, "rank", f"must be in [0, learners={self.learners})"),
            (bool(host) and port.isdecimal() and 0 < int(port) < 65536, "group_endpoint",
             "expected host:port"),
            (self.group_timeout_s > 0, "group_timeout_s", "must be > 0"),
        ])


@dataclass
class ActorServiceConfig(NetConfig, RunSettings, ActingSettings):
    """An actor's settings: the network's, the run's and how it collects; no replay, loss or
    optimiser setting (what it needs of those comes in the run spec)."""

    SECTION = "actor"

    actor_id: str = "0"
    """this actor's id, unique in the run (its key is traj/{actor_id}, its envs' seeds
    seed + 1000·actor_id + i) | auto: the replay server hands out the lowest id no actor of
    the run holds, for identical replicas (docker compose --scale); do not mix with fixed ids"""
    outbox_fragments: int = 0
    """fragments sent but not yet acknowledged; at this bound the actor waits (back-pressure).
    0 means 2 × num_envs: one round of fragments in flight while the next is collected"""
    resend_after_s: float = 10.0
    """resend a fragment not acknowledged within this time"""

    def __post_init__(self):
        super().__post_init__()
        self.actor_id = str(self.actor_id).strip()
        if self.actor_id != "auto" and not (
                self.actor_id.isdigit() and 0 <= int(self.actor_id) < 2**31):
            raise ConfigError(f"actor_id={self.actor_id!r}: must be auto or an integer in "
                              "[0, 2^31)")
        check(self, [
            (self.outbox_fragments >= 0, "outbox_fragments", "must be ≥ 0"),
            (self.resend_after_s > 0, "resend_after_s", "must be > 0"),
        ])
        self.outbox_fragments = self.outbox_fragments or 2 * self.num_envs


@dataclass
class EvaluatorServiceConfig(NetConfig, RunSettings, EvalSettings):
    """The evaluator's settings: the network's, the run's and the evaluation's."""

    SECTION = "eval"


def read_password_file(path: str) -> str:
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise ConfigError(f"password_file={path!r}: cannot read it ({exc.strerror})") from None
    if not lines or not lines[0].strip():
        raise ConfigError(f"password_file={path!r}: its first line is empty")
    return lines[0].strip()


SERVICE_CONFIGS = {"router": RouterConfig, "replay": ReplayServiceConfig,
                   "learner": LearnerServiceConfig, "actor": ActorServiceConfig,
                   "evaluator": EvaluatorServiceConfig}
