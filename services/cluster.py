"""`tpdeb-cluster`: a compose-style launcher for the whole run on one machine (DESIGN §5).

Reads a cluster file (`deploy/local.toml`), resolves each service's whole configuration once
into the run dir (`config/{name}.toml`, what the service runs by), starts router → replay →
learner → actors as separate processes in dependency order (each waits for what it depends on
to answer), prefixes and saves their logs, shows a live progress line from the services' stats
and liveliness tokens, restarts crashed services by their restart policy (stopping the run on a
crash loop), and stops everything in reverse order at the end or on Ctrl-C. The learner ends
the run: when it exits 0 the others stop on its stop message.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import zenoh

from tpdeb.protocol import Control, DecodeError, Keys, decode
from tpdeb.services.budget import Budget
from tpdeb.services.config import (
    CONFIG_HELP,
    SET_HELP,
    ConfigError,
    Parser,
    add_setting_flags,
    resolve,
    to_toml,
)
from tpdeb.services.config.presets import shown
from tpdeb.services.config.service import SERVICE_CONFIGS
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.device import resolve_device
from tpdeb.services.launcher import PROG
from tpdeb.services.launcher.child import Child, RunEnded, resolve_command
from tpdeb.services.launcher.plan import (
    DEFAULT_FILE,
    LINK_KEYS,
    Plan,
    ServiceSpec,
    child_environment,
    make_plan,
    resolved_environment,
)
from tpdeb.services.launcher.restart import RestartTracker
from tpdeb.services.launcher.status import Display, Health
from tpdeb.services.net.session import fetch_spec, open_session
from tpdeb.services.preflight import preflight, run_dir_resume
from tpdeb.services.process import StopSignal

CONFIG_ERROR = 2  # the exit status of a service that refuses a setting (services/process.py)


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
        self.resume = False  # whether this start continues the run dir (prepare() says)

    def prepare(self) -> None:
        """The run's checks before anything exists: the env, the learner's device, the run
        dir (writable; this run's, when it exists)."""
        preflight(self.plan.train)
        self.resume = run_dir_resume(self.plan.train)

    def write_run_dir(self) -> None:
        """The run dir's logs, security files, train.toml and every child's configuration,
        resolved before any process starts. A bad setting of any service stops the launch,
        naming it, and a run dir this launch made is removed again."""
        made = not self.run_dir.exists()
        try:
            self._write_run_dir()
        except ConfigError:
            if made:
                shutil.rmtree(self.run_dir, ignore_errors=True)
            raise

    def _write_run_dir(self) -> None:
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        if self.plan.security.enabled:
            host = self.plan.endpoint.partition("/")[2].rpartition(":")[0].strip("[]")
            self.plan.security.prepare(self.run_dir / "security", self.users(),
                                       [host, "127.0.0.1", "localhost"])
        self.slots, configs = [], {}
        for spec in self.plan.services:
            for i in range(spec.replicas):
                child, configs[child.name] = self.slot(spec, i)
                self.slots.append(child)
        if "learner" in configs:  # its own device, where its `args` or `env` set one
            resolve_device(configs["learner"].device)
        (self.run_dir / "train.toml").write_text(to_toml(self.plan.train))
        (self.run_dir / "config").mkdir(exist_ok=True)
        for name, config in configs.items():
            (self.run_dir / "config" / f"{name}.toml").write_text(to_toml(config))
        (self.run_dir / "cluster.json").write_text(json.dumps({
            "source": self.plan.source, "run_id": self.plan.run_id,
            "endpoint": self.plan.endpoint, "link": self.plan.link,
            "link_endpoint": self.plan.link_endpoint,
            "services": [{**dataclasses.asdict(s), "restart": str(s.restart)}
                         for s in self.plan.services],
            "restarts": dataclasses.asdict(self.plan.restarts),
            "security": self.plan.security.summary(),
            "train": dataclasses.asdict(self.plan.train)}, indent=2))

    def slot(self, spec: ServiceSpec, index: int) -> tuple[Child, object]:
        """A service process and its configuration resolved whole: the training settings, the
        network flags the cluster gives it, its `args` and `env` and the shell's TPDEB_*
        variables, in the services' own precedence. It starts with that configuration's file
        alone (config/{name}.toml), so what the run dir records is what runs, and a restart runs
        the same."""
        name = spec.role if spec.replicas == 1 else f"{spec.role}-{index}"
        env = child_environment(os.environ, {k: str(v) for k, v in spec.env.items()},
                                self.plan.security.env(user_of(spec.role, index)))
        try:
            config = resolve(SERVICE_CONFIGS[spec.role], self.flags(spec, index),
                             f"{spec.command} ([services.{spec.role}] args)", "", environ=env,
                             base=dataclasses.asdict(self.plan.train))
        except SystemExit:  # argparse has said which flag it does not know
            raise ConfigError(f"[services.{spec.role}] args {spec.args}: not all are flags of "
                              f"{spec.command} ({spec.command} --help lists them)") from None
        path = self.run_dir / "config" / f"{name}.toml"
        child = Child(
            name, spec.role, [*resolve_command(spec.command), "--config", str(path)],
            resolved_environment(env), self.run_dir / "logs" / f"{name}.log",
            self.display.echo, RestartTracker(spec.restart, self.plan.restarts),
            ident=None if spec.role == "router" else str(index),
            has_token=spec.role != "router", stats_interval_s=config.stats_interval_s)
        return child, config

    def users(self) -> list[str]:
        """One user per process that opens a session (access control knows them by role)."""
        users = ["monitor"] + (["link"] if self.plan.link_endpoint else [])
        for spec in self.plan.services:
            users += [user_of(spec.role, i) for i in range(spec.replicas) if spec.role != "router"]
        return users

    def flags(self, spec: ServiceSpec, index: int) -> list[str]:
        """What the cluster sets for a service: the run id, its network and its security (the
        router), the actor's id; then the service's own `args`."""
        argv = ["--run-id", self.plan.run_id]
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
        if spec.role == "replay" and spec.replicas > 1:
            argv += ["--shard", str(index)]
        if spec.role == "learner" and spec.replicas > 1:
            argv += ["--rank", str(index), "--group-endpoint", self.plan.group_endpoint]
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
        say = self.display.echo
        try:
            self.write_run_dir()
        except ConfigError as exc:
            say(f"[{PROG}] error: {exc}")
            return 2
        except OSError as exc:
            say(f"[{PROG}] error: run dir {self.run_dir}: {exc.strerror or exc}")
            return 2
        train = self.plan.train
        limits = Budget(train.total_timesteps, train.train_for_seconds).describe()
        say(f"[{PROG}] run {self.plan.run_id}: {train.env_id}, {limits}, seed {train.seed}; "
            f"endpoint {self.plan.endpoint}; run dir {self.run_dir}")
        say(f"[{PROG}] algo {self.plan.train.algo}; preset: {shown(self.plan.train.preset)}")
        if self.resume:
            say(f"[{PROG}] continuing the run in {self.run_dir}: the learner resumes from its "
                "newest checkpoint, the replay from its snapshots and log")
        keys = Keys(self.plan.run_id)
        try:
            router, *others = self.plan.services
            self.start(self.slots[0])
            self.wait_until(lambda: self.connect(keys), "router")
            # The rest in dependency order without waiting in between: each service waits for
            # what it needs (the run spec, the first parameters), so their slow imports
            # overlap. The checks below then name the one that fails to come up.
            for spec in others:
                if spec.role == "actor" and self.plan.link_endpoint:
                    self.add_link(router)
                for slot in (c for c in self.slots if c.role == spec.role):
                    if not self.stopping.is_set():
                        self.start(slot)
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
        self.check_hangs(now)
        return self.check_actors()

    def check_hangs(self, now: float) -> None:
        """A service alive but silent (no stats for `hang_intervals` of its stats intervals, or
        since its start for at least start_timeout_s) is killed; its exit then goes to its
        restart policy like a crash, and counts toward a crash loop. When every service that
        publishes stats is silent at once, the network is: the router is the one killed."""
        if self.ending:
            return
        views = [c.view() for c in self.children]
        silent = self.health.silent(views, now, self.plan.hang_intervals,
                                    self.plan.start_timeout_s)
        watched = [v for v in views if v.running and v.ident is not None]
        if not silent:
            return
        children = {c.name: c for c in self.children}
        if len(silent) == len(watched) > 1:
            router = children.get("router")
            bound = max(b for _, _, b in silent)
            if router is None or not router.running or now - router.started_at <= bound:
                return  # restarting, or just restarted: its clients are reconnecting
            silent = [(router.view(), min(s for _, s, _ in silent), bound)]
        for view, silent_s, bound in silent:
            child = children[view.name]
            if not child.hung:
                what = "nobody's stats arrive" if child.role == "router" else "no stats"
                self.display.echo(f"[{PROG}] {child.name} is hung: {what} for {silent_s:.0f} s "
                                  f"(bound {bound:g} s); killing it")
                child.kill_hung()

    @property
    def ending(self) -> bool:
        """Ctrl-C, or the learner's stop message: nothing is restarted any more."""
        return self.stopping.is_set() or self.finishing.is_set()

    def on_exit(self, child: Child, code: int, now: float) -> int | None:
        say = self.display.echo
        if child.role == "learner" and code == 0 and child.ident == "0":  # it ends the run
            self.finishing.set()
            say(f"[{PROG}] {child.name} exited with code 0")
            return 130 if self.interrupted else 0
        if self.stopping.is_set():
            return None
        if child.role == "learner" and code == 0:
            return None  # a rank above 0 leaves with its group; rank 0 ends the run
        if child.role == "learner" and not self.finishing.is_set():
            self.restart_group(child)
        if code == 0 and child.role != "learner" and self.learner_finishing():
            return None  # it left on the learner's stop message; the learner exits next
        if self.finishing.is_set():
            if child.role != "learner":
                return None
            say(f"[{PROG}] learner exited with code {code} while finishing; see {child.log_path}")
            return 1
        if code == CONFIG_ERROR:  # a setting the service refuses: a restart refuses it again
            errors = [line for line in child.tail(20) if "error:" in line] or child.tail(1)
            say(f"[{PROG}] {child.name} refused its configuration (exit status 2), so the run "
                f"stops: {errors[-1].strip() if errors else f'see {child.log_path}'}")
            return CONFIG_ERROR
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

    def restart_group(self, failed: Child) -> None:
        """A learner rank died: the others wait in vain for it in their next exchange, so they
        are killed too and every rank restarts by its policy, the group from rank 0's last
        checkpoint."""
        others = [c for c in self.children if c.role == "learner" and c is not failed
                  and c.running]
        if others:
            self.display.echo(f"[{PROG}] {failed.name} failed: restarting the learner group "
                              f"({', '.join(c.name for c in others)} too) from its last "
                              "checkpoint")
        for other in others:
            other.kill_hung()

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

    def interrupt(self, name: str) -> None:
        """SIGINT/SIGTERM (from the signal thread, never in the handler: see StopSignal)."""
        self.interrupted = True
        self.stopping.set()
        self.display.echo(f"[{PROG}] {name}: stopping the services")


def user_of(role: str, index: int) -> str:
    """The user a service authenticates as: its role, with the actor's id ("" for the router,
    which authenticates the others)."""
    return {"actor": f"actor-{index}", "router": ""}.get(role, role)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def build_parser() -> Parser:
    """The cluster's own flags, and every training setting as tpdeb-train takes it (its flag,
    `--set`, `--config FILE`)."""
    p = Parser(prog=PROG, description=__doc__.split("\n\n")[0],
               formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--cluster-file", help=f"cluster file: the services, their restart policies, "
                   f"the [train] settings, [link], [security] (default: {DEFAULT_FILE})")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help=SET_HELP)
    p.add_argument("--actors", type=int, help="number of actor processes")
    p.add_argument("--run-id", help="Zenoh run id (default from the cluster file)")
    p.add_argument("--endpoint", help="router endpoint, e.g. tcp/127.0.0.1:7447")
    for key, text in (("tls", "TLS on every link (the endpoint becomes tls/…)"),
                      ("auth", "a generated user and password per service"),
                      ("acl", "access control: each service only its role's traffic")):
        p.add_argument(f"--{key}", action=argparse.BooleanOptionalAction, default=None,
                       help=f"{text} (overrides [security])")
    p.add_argument("--certs-dir", help="ca.pem, router.pem, router.key to use (tpdeb-certs "
                   "writes them; default: new ones in {run_dir}/security)")
    for key in LINK_KEYS:
        p.add_argument(f"--link-{key.replace('_', '-')}", type=float, metavar="X",
                       help=f"link shim {key} between actors and the rest (0 = off; overrides "
                       "[link])")
    add_setting_flags(p, TrainConfig)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        plan = make_plan(parse_args(argv))
        cluster = Cluster(plan)
        cluster.prepare()
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    StopSignal(on_signal=cluster.interrupt).install()
    code = cluster.run()
    print(f"{PROG}: {'finished' if code == 0 else 'stopped'}; run dir {cluster.run_dir}",
          flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
