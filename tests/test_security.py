"""Zenoh security against a real tpdeb-router: TLS, user/password authentication, access-control
rules per role, run isolation, the cluster with all three on; and, without processes, the rule
builder, tpdeb-certs and the refusals of bad settings."""

from __future__ import annotations

import contextlib
import os
import stat
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zenoh
from cryptography import x509

from tests.procs import ROOT, free_port, pids_with
from tpdeb.protocol import Keys
from tpdeb.protocol.keys import ANY_SHARD
from tpdeb.services.cluster import parse_args
from tpdeb.services.config import ConfigError, resolve, to_toml
from tpdeb.services.config.service import ActorServiceConfig, NetConfig, RouterConfig
from tpdeb.services.launcher.plan import make_plan
from tpdeb.services.link import LinkConfig
from tpdeb.services.net import certs as certs_cli
from tpdeb.services.net.security import (
    Security,
    access_control,
    new_passwords,
    read_auth_file,
    security_of,
    write_auth_file,
)
from tpdeb.services.net.session import open_for, open_session, zenoh_config
from tpdeb.services.store.metrics import read_metrics

ENV = "InvertedPendulum-v5"
ROLES = ["replay", "learner", "actor-0", "actor-1", "monitor", "link"]
SETTLE_S = 1.0  # declarations reach the router and its other sessions
GRACE_S = 0.7  # after a later message arrived, an earlier one that was let through would have


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return certs_cli.write_certs(tmp_path_factory.mktemp("certs"), ["127.0.0.1", "localhost"])


@pytest.fixture
def sessions():
    """Opens Zenoh sessions for the test and closes every one of them afterwards, newest first
    (a router opened here outlives its clients)."""
    opened: list[zenoh.Session] = []

    def keep(session: zenoh.Session) -> zenoh.Session:
        opened.append(session)
        return session

    yield keep
    for session in reversed(opened):
        session.close()


class Inbox:
    """Payloads received by subscribers, by tag, from Zenoh's callback threads."""

    def __init__(self):
        self.items: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def callback(self, tag: str):
        def on_sample(sample) -> None:
            with self.lock:
                self.items.append((tag, sample.payload.to_bytes()))
        return on_sample

    def got(self, tag: str) -> list[bytes]:
        with self.lock:
            return [payload for t, payload in self.items if t == tag]

    def wait(self, tag: str, payload: bytes, timeout_s: float = 15) -> None:
        deadline = time.monotonic() + timeout_s
        while payload not in self.got(tag):
            if time.monotonic() > deadline:
                raise AssertionError(f"{tag} never received {payload!r}; got {self.got(tag)}")
            time.sleep(0.05)


def start_router(procs, tmp_path, *, certs=None, users=(), acl=False, run_id="r",
                 name="router", wait=True) -> tuple[str, dict[str, str]]:
    endpoint = f"{'tls' if certs else 'tcp'}/127.0.0.1:{free_port()}"
    args = ["--listen", endpoint, "--run-id", run_id]
    if certs:
        args += ["--tls-cert", str(certs["router.pem"]), "--tls-key", str(certs["router.key"])]
    passwords = new_passwords(users)
    if users:
        args += ["--auth-file", str(write_auth_file(tmp_path / f"{name}-users.txt", passwords))]
    if acl:
        args += ["--acl"]
    router = procs.spawn("router", *args, name=name)
    if wait:
        procs.wait_for_line(router, "routing on")
    return endpoint, passwords


def security(certs=None, user="", passwords=None, password=None) -> Security:
    return Security(tls_ca=str(certs["ca.pem"]) if certs else "", user=user,
                    password=password if password is not None else (passwords or {}).get(user, ""))


def zenoh_refuses(endpoint: str, settings: Security) -> bool:
    """Zenoh itself, without this project's checks in front, fails to open the session."""
    try:
        zenoh.open(zenoh_config("client", [], [endpoint], 2.0, security=settings)).close()
    except zenoh.ZError:
        return True
    return False


# -- processes: authentication and TLS


def test_sessions_without_the_right_credentials_are_refused(procs, tmp_path, certs, sessions):
    endpoint, passwords = start_router(procs, tmp_path, certs=certs, users=["actor-0"])
    # A service with a wrong password stops with one line, not a traceback or a hang.
    actor = procs.spawn("actor", "--env-id", ENV, "--run-id", "r", "--connect", endpoint,
                        env={"TPDEB_USER": "actor-0", "TPDEB_PASSWORD": "not-it",
                             "TPDEB_TLS_CA": str(certs["ca.pem"])})
    sessions(open_session("client", [], [endpoint], 20, security=security(
        certs, "actor-0", passwords)))

    def refused(settings: Security) -> tuple[str, float, bool]:
        started = time.monotonic()
        try:
            sessions(open_session("client", [], [endpoint], 60, security=settings))
        except ConfigError as exc:
            return str(exc), time.monotonic() - started, zenoh_refuses(endpoint, settings)
        return "", time.monotonic() - started, False

    cases = {"refused user 'actor-0'": security(certs, "actor-0", password="not-it"),
             "refused user 'actor-9'": security(certs, "actor-9", password="x"),
             "requires a user and password": security(certs)}
    with ThreadPoolExecutor(len(cases)) as pool:  # each waits out a refused handshake
        results = dict(zip(cases, pool.map(refused, cases.values()), strict=True))
    for expected, (message, elapsed_s, zenoh_too) in results.items():
        assert expected in message, message
        assert elapsed_s < 30, f"a refusal must not wait out the connect timeout: {elapsed_s}"
        assert zenoh_too, "Zenoh itself let the session in"
    assert actor.wait(90) == 2
    lines = procs.output(actor).strip().splitlines()
    assert len(lines) == 1 and "refused user 'actor-0'" in lines[0], lines


def test_tls_endpoint_refuses_plain_tcp_untrusted_cas_and_wrong_names(
        procs, tmp_path, certs, sessions):
    other = certs_cli.write_certs(tmp_path / "other", ["localhost"])  # another CA; no IP name
    by_name, _ = start_router(procs, tmp_path, certs=other, name="router-localhost", wait=False)
    endpoint, _ = start_router(procs, tmp_path, certs=certs)
    procs.wait_for_line(procs.started[0], "routing on")  # the localhost-only one, too
    port = endpoint.rpartition(":")[2]
    for good in (endpoint, f"tls/localhost:{port}"):  # the certificate names both
        sessions(open_session("client", [], [good], 20, security=security(certs)))

    def plain_tcp() -> str:
        try:
            sessions(open_session("client", [], [f"tcp/127.0.0.1:{port}"], 60))
        except ConfigError as exc:
            return str(exc)
        return "connected"

    pool = ThreadPoolExecutor(1)  # it waits out a failing handshake while the rest goes on
    plain = pool.submit(plain_tcp)
    assert zenoh_refuses(f"tcp/127.0.0.1:{port}", Security())
    for settings in (security(other), Security()):  # a foreign CA; the system's CAs
        with pytest.raises(ConfigError, match="does not trust"):
            sessions(open_session("client", [], [endpoint], 60, security=settings))
        assert zenoh_refuses(endpoint, settings)

    other_port = by_name.rpartition(":")[2]
    sessions(open_session("client", [], [f"tls/localhost:{other_port}"], 20,
                          security=security(other)))
    with pytest.raises(ConfigError, match="does not name 127.0.0.1"):
        sessions(open_session("client", [], [by_name], 60, security=security(other)))
    assert zenoh_refuses(by_name, security(other))
    assert "expects TLS: connect to tls/127.0.0.1" in plain.result(timeout=60)
    pool.shutdown()


# -- processes: access control


def test_each_role_gets_its_traffic_and_nothing_else(procs, tmp_path, certs, sessions):
    endpoint, passwords = start_router(procs, tmp_path, certs=certs, users=ROLES, acl=True)
    s = {user: sessions(open_session("client", [], [endpoint], 20,
                                     security=security(certs, user, passwords)))
         for user in ROLES}
    k, inbox = Keys("r"), Inbox()
    for user, key in (("replay", k.traj_all), ("replay", k.priorities), ("replay", k.control),
                      ("learner", k.stats_all), ("monitor", k.stats_all), ("monitor", k.control),
                      ("actor-0", k.ack(0)), ("actor-0", k.control), ("actor-0", k.ack(1)),
                      ("actor-1", k.params), ("actor-1", k.ack(1)), ("monitor", k.traj_all)):
        s[user].declare_subscriber(key, inbox.callback(f"{user}<{key}"))
    s["replay"].declare_queryable(k.spec, lambda q: q.reply(k.spec, b"spec"))
    s["replay"].declare_queryable(k.sample, lambda q: q.reply(k.sample, b"batch"))
    s["learner"].declare_queryable(k.params_latest, lambda q: q.reply(k.params_latest, b"real"))
    s["actor-0"].declare_queryable(k.params_latest,
                                   lambda q: q.reply(k.params_latest, b"forged"))
    tokens = [s["replay"].liveliness().declare_token(k.alive("replay", 0)),
              s["actor-0"].liveliness().declare_token(k.alive("actor", 0)),
              s["actor-1"].liveliness().declare_token(k.alive("learner", 0))]  # not its own
    alive = Inbox()
    s["monitor"].liveliness().declare_subscriber(k.alive_all, alive.callback("alive"))
    time.sleep(SETTLE_S)

    traj = s["actor-0"].declare_publisher(k.traj(0),
                                          congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(SETTLE_S)
    # refused first, then what is allowed: once that arrives, a refused one would have, too
    for user, key, payload in (
            ("actor-0", k.traj(1), b"forged traj/1"), ("actor-0", k.params, b"forged params"),
            ("actor-0", k.stats("actor", 1), b"forged stats"), ("actor-0", k.control, b"stop!"),
            ("link", k.traj(0), b"link traj"), ("replay", k.params, b"replay params")):
        s[user].put(key, payload)
    traj.put(b"traj/0")
    for user, key, payload in (
            ("actor-0", k.stats("actor", 0), b"a0 stats"), ("actor-1", k.traj(1), b"traj/1"),
            ("replay", k.ack(0), b"ack 0"), ("replay", k.ack(1), b"ack 1"),
            ("learner", k.priorities, b"priorities"), ("learner", k.control, b"control"),
            ("replay", k.stats("replay", 0), b"replay stats"),
            ("link", k.stats("link", 0), b"link stats")):
        s[user].put(key, payload)
    inbox.wait(f"replay<{k.traj_all}", b"traj/0")
    inbox.wait(f"replay<{k.traj_all}", b"traj/1")
    for tag, payload in ((f"replay<{k.priorities}", b"priorities"),
                         (f"replay<{k.control}", b"control"), (f"actor-0<{k.control}", b"control"),
                         (f"monitor<{k.control}", b"control"), (f"actor-0<{k.ack(0)}", b"ack 0"),
                         (f"actor-1<{k.ack(1)}", b"ack 1"),
                         (f"learner<{k.stats_all}", b"a0 stats"),
                         (f"learner<{k.stats_all}", b"link stats"),
                         (f"monitor<{k.stats_all}", b"replay stats")):
        inbox.wait(tag, payload)
    time.sleep(GRACE_S)
    assert sorted(inbox.got(f"replay<{k.traj_all}")) == [b"traj/0", b"traj/1"]
    assert b"forged stats" not in inbox.got(f"learner<{k.stats_all}")
    assert b"stop!" not in inbox.got(f"replay<{k.control}")
    assert not inbox.got(f"actor-0<{k.ack(1)}")  # another actor's acks
    assert not inbox.got(f"actor-1<{k.params}") and not inbox.got(f"monitor<{k.traj_all}")

    def answers(user: str, selector: str) -> list[bytes]:
        return sorted(r.ok.payload.to_bytes() for r in s[user].get(selector, timeout=3)
                      if r.ok is not None)

    assert answers("actor-1", f"{k.params_latest}?after=0") == [b"real"]  # never "forged"
    assert answers("monitor", k.params_latest) == [b"real"]
    assert answers("actor-0", k.spec) == answers("learner", k.spec) == [b"spec"]
    assert answers("learner", k.sample) == [b"batch"]
    assert answers("actor-0", k.sample) == []  # only the learner samples
    assert answers("link", k.spec) == []
    keys_alive = {str(r.ok.key_expr) for r in s["monitor"].liveliness().get(k.alive_all,
                                                                            timeout=3) if r.ok}
    assert keys_alive == {k.alive("replay", 0), k.alive("actor", 0)}
    for token in tokens:
        token.undeclare()


def test_router_drops_what_a_user_may_not_send_before_routing_it(tmp_path, sessions):
    # The router's own session sees every message that passes its ingress rules, whoever it
    # is for; a message that never shows up there was dropped at the door.
    users = ["replay", "actor-0"]
    passwords = new_passwords(users)
    config = RouterConfig(listen=(f"tcp/127.0.0.1:{free_port()}",), run_id="r", acl=True,
                          auth_file=str(write_auth_file(tmp_path / "users.txt", passwords)))
    router = sessions(open_for(config, "router"))
    seen = Inbox()
    k, other = Keys("r"), Keys("other")
    for prefix in (k.prefix, other.prefix):
        router.declare_subscriber(f"{prefix}/**", seen.callback("router"))
    actor = sessions(open_session("client", [], list(config.listen), 20,
                                  security=security(None, "actor-0", passwords)))
    # a subscriber the rules allow, so the router passes the actor's publisher its interest
    sessions(open_session("client", [], list(config.listen), 20, security=security(
        None, "replay", passwords))).declare_subscriber(k.traj_all, lambda _: None)
    time.sleep(SETTLE_S)
    for key in (k.params, k.traj(1), k.control, k.ack(0), k.stats("learner", 0), other.traj(0)):
        actor.put(key, key.encode())
    actor.put(k.traj(0), b"allowed")
    seen.wait("router", b"allowed")
    time.sleep(GRACE_S)
    assert seen.got("router") == [b"allowed"]


def test_runs_sharing_a_router_never_exchange_data(procs, tmp_path, certs, sessions):
    run_users = {"a": ["replay", "actor-0", "monitor"],
                 "b": ["replay@b", "actor-0@b", "monitor@b"]}
    for acl in (False, True):
        users = run_users["a"] + run_users["b"] if acl else []
        endpoint, passwords = start_router(procs, tmp_path, users=users, acl=acl, run_id="a",
                                           name=f"router-acl-{acl}")
        inbox = Inbox()
        s = {}
        for run in ("a", "b"):
            k = Keys(run)
            for role in ("replay", "actor", "monitor"):
                user = next(u for u in run_users[run] if u.startswith(role)) if acl else ""
                s[run, role] = sessions(open_session(
                    "client", [], [endpoint], 20, security=security(None, user, passwords)))
            s[run, "replay"].declare_subscriber(k.traj_all, inbox.callback(f"{run} replay"))
            s[run, "replay"].declare_queryable(
                k.spec, lambda q, run=run: q.reply(Keys(run).spec, f"spec {run}".encode()))
            s[run, "actor"].declare_subscriber(k.ack(0), inbox.callback(f"{run} actor"))
            s[run, "monitor"].declare_subscriber(k.stats_all, inbox.callback(f"{run} monitor"))
        # run a's actor reaches for run b's keys: only an access-control router stops that
        s["a", "actor"].declare_subscriber(Keys("b").ack(0), inbox.callback("a actor in b"))
        time.sleep(SETTLE_S)
        for run in ("a", "b"):
            k = Keys(run)
            s[run, "actor"].put(k.traj(0), run.encode())
            s[run, "actor"].put(k.stats("actor", 0), run.encode())
            s[run, "replay"].put(k.ack(0), run.encode())
        for run in ("a", "b"):
            for role in ("replay", "actor", "monitor"):
                inbox.wait(f"{run} {role}", run.encode())
        time.sleep(GRACE_S)
        for run in ("a", "b"):
            for role in ("replay", "actor", "monitor"):
                assert inbox.got(f"{run} {role}") == [run.encode()], (acl, run, role)
            spec = [r.ok.payload.to_bytes() for r in s[run, "actor"].get(Keys(run).spec,
                                                                          timeout=3) if r.ok]
            assert spec == [f"spec {run}".encode()]
        if acl:
            assert not inbox.got("a actor in b")
            assert not [r for r in s["a", "actor"].get(Keys("b").spec, timeout=2) if r.ok]


# -- processes: the cluster


def test_cluster_trains_with_tls_auth_and_access_control(procs, tmp_path):
    run_dir = tmp_path / "run"
    cluster = procs.spawn("cluster", "--env-id", ENV, "--total-timesteps", "3000",
                          "--num-envs", "2", "--run-dir", str(run_dir), "--tls", "--auth",
                          "--acl")
    argv_seen: set[str] = set()  # every service's command line, read while the run goes on
    deadline = time.monotonic() + 300
    while cluster.poll() is None and time.monotonic() < deadline:
        for pid in pids_with(str(run_dir)):
            with contextlib.suppress(OSError):
                argv_seen.add(Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace"))
        time.sleep(0.5)
    assert cluster.wait(10) == 0, procs.output(cluster)[-3000:]
    out = procs.output(cluster)
    assert "routing on tls/127.0.0.1:" in out and "with TLS, user/password, access control" in out
    assert max(r["global_step"] for r in read_metrics(run_dir / "metrics.jsonl")) >= 3000
    secrets_dir = run_dir / "security"
    for name in ("users.txt", "ca.key", "router.key"):
        assert stat.S_IMODE((secrets_dir / name).stat().st_mode) == 0o600, name
    users = read_auth_file(secrets_dir / "users.txt")
    assert set(users) == {"monitor", "replay", "learner", "actor-0", "actor-1", "evaluator"}
    for path in run_dir.rglob("*"):  # no password anywhere else: configs, logs, checkpoints
        if path.is_file() and path.name != "users.txt":
            data = path.read_bytes()
            assert not any(p.encode() in data for p in users.values()), path
    assert not any(p in out for p in users.values())
    assert any("tpdeb-router" in a for a in argv_seen) and any("tpdeb-actor" in a
                                                               for a in argv_seen)
    assert not any(p in a for p in users.values() for a in argv_seen), "a password in argv"


# -- no processes: rules, certificates, settings


def test_a_pool_of_actors_under_one_user_acts_as_any_actor_and_nothing_more():
    acl = access_control("r", ["actor", "actor-0"])
    rules = {r["id"]: r for r in acl["rules"]}

    def keys(user: str, message: str, flow: str) -> set[str]:
        return {key for r in rules.values() if r["id"].startswith(f"{user} ")
                and r["messages"] == [message] and r["flows"] == [flow] for key in r["key_exprs"]}

    r = Keys("r")
    s = r.of_shard(ANY_SHARD)  # with replay shards: every shard's fragments and acks
    assert keys("actor", "put", "ingress") == {r.traj_all, s.traj_all,
                                               r.of_role("stats", "actor")}
    assert keys("actor", "declare_subscriber", "ingress") == {r.ack_all, s.ack_all, r.control}
    assert keys("actor", "liveliness_token", "ingress") == {r.of_role("alive", "actor")}
    assert keys("actor", "query", "ingress") == keys("actor-0", "query", "ingress")  # spec, join…
    assert not keys("actor", "declare_queryable", "ingress")  # never answers for anyone
    assert not any(r.sample in k or r.priorities in k for k in keys("actor", "put", "ingress"))


def test_access_control_is_default_deny_with_one_policy_per_user():
    acl = access_control("r", ROLES + ["actor-0@b"])
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert [s["usernames"] for s in acl["subjects"]] == [[u] for u in ROLES + ["actor-0@b"]]
    rules = {r["id"]: r for r in acl["rules"]}
    assert all(r["permission"] == "allow" and len(r["flows"]) == 1 for r in rules.values())

    def keys(user: str, message: str, flow: str) -> set[str]:
        policy = next(p for p in acl["policies"] if p["subjects"] == [f"user {user}"])
        return {key for rid in policy["rules"] for key in rules[rid]["key_exprs"]
                if rules[rid]["messages"] == [message] and rules[rid]["flows"] == [flow]}

    r, b = Keys("r"), Keys("b")
    rs, bs = r.of_shard(ANY_SHARD), b.of_shard(ANY_SHARD)  # the same, on any replay shard
    assert keys("actor-0", "put", "ingress") == {r.traj(0), rs.traj(0), r.stats("actor", 0)}
    assert keys("actor-0@b", "put", "ingress") == {b.traj(0), bs.traj(0), b.stats("actor", 0)}
    assert keys("actor-1", "declare_subscriber", "ingress") == {r.ack(1), rs.ack(1), r.control}
    assert not keys("actor-0", "declare_queryable", "ingress")
    assert keys("learner", "declare_queryable", "ingress") == {r.params_latest}
    assert keys("replay", "declare_queryable", "ingress") == {r.sample, rs.sample, r.spec,
                                                               r.join}
    # every shard and every learner rank under one user each: their stats and tokens any ident
    assert keys("replay", "put", "ingress") == {r.ack_all, rs.ack_all,
                                                r.of_role("stats", "replay")}
    assert keys("learner", "liveliness_token", "ingress") == {r.of_role("alive", "learner")}
    assert keys("link", "put", "ingress") == {r.stats("link", 0)}
    assert keys("monitor", "put", "ingress") == set()
    assert all(key.startswith((r.prefix + "/", b.prefix + "/"))
               for rule in acl["rules"] for key in rule["key_exprs"])


@pytest.mark.parametrize("users, message", [
    (["replay", "bob"], "'bob' is not a TPDEB role"),
    (["actor-x"], "'actor-x' is not a TPDEB role"),
    (["actor-01"], "'actor-01' is not a TPDEB role"),
    (["replay", "replay"], "listed twice"),
    (["replay@bad/run"], "invalid"),
    ([], "at least one user"),
])
def test_access_control_refuses_users_that_are_not_roles(users, message):
    with pytest.raises(ConfigError, match=message):
        access_control("r", users)


def test_certs_command_writes_a_ca_and_a_router_certificate(tmp_path, capsys):
    target = tmp_path / "certs"
    assert certs_cli.main([str(target), "--hosts", "127.0.0.1,localhost,learner.example",
                           "--days", "30"]) == 0
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in target.iterdir()}
    assert modes == {"ca.pem": 0o644, "ca.key": 0o600, "router.pem": 0o644, "router.key": 0o600}
    ca = x509.load_pem_x509_certificate((target / "ca.pem").read_bytes())
    router = x509.load_pem_x509_certificate((target / "router.pem").read_bytes())
    router.verify_directly_issued_by(ca)
    names = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    assert names.get_values_for_type(x509.DNSName) == ["localhost", "learner.example"]
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    capsys.readouterr()

    before = (target / "ca.pem").read_bytes()
    assert certs_cli.main([str(target)]) == 2  # never replaces without --force
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already exist" in err[0] and "--force" in err[0], err
    assert (target / "ca.pem").read_bytes() == before
    assert certs_cli.main([str(target), "--force"]) == 0
    assert (target / "ca.pem").read_bytes() != before
    assert stat.S_IMODE((target / "router.key").stat().st_mode) == 0o600


def test_certs_command_writes_passwords_the_router_and_each_service_read(tmp_path, capsys):
    target = tmp_path / "secrets"
    argv = [str(target), "--users", "replay,learner,actor"]
    assert certs_cli.main(argv) == 0
    users = read_auth_file(target / "users.txt")
    assert sorted(users) == ["actor", "learner", "replay"] and len(set(users.values())) == 3
    for user, password in users.items():
        path = target / f"{user}.password"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        config = NetConfig(user=user, password_file=str(path), connect=("tls/router:7447",),
                           tls_ca=str(target / "ca.pem"))
        assert config.secret_password == password
    assert stat.S_IMODE((target / "users.txt").stat().st_mode) == 0o600
    RouterConfig(auth_file=str(target / "users.txt"))  # the router accepts it as it is
    capsys.readouterr()
    assert certs_cli.main([*argv, "--if-missing"]) == 0  # an init step at every start
    assert "nothing written" in capsys.readouterr().out
    assert read_auth_file(target / "users.txt") == users
    assert certs_cli.main([*argv, "--users", "replay,learner,actor,monitor", "--if-missing"]) == 0
    assert "monitor" in read_auth_file(target / "users.txt")  # incomplete: all written anew
    assert certs_cli.main(argv) == 2 and "--force" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--hosts", "127.0.0.1,exa_mple.org"], "'exa_mple.org' is neither an IP address nor a "
     "DNS name"),
    (["--hosts", ","], "--hosts is empty"),
    (["--days", "0"], "--days 0"),
    (["--days", "soon"], "--days 'soon'"),
])
def test_certs_command_refuses_bad_input_with_one_line(tmp_path, capsys, argv, message):
    assert certs_cli.main([str(tmp_path / "certs"), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "certs").exists()


def test_security_settings_are_validated_with_one_clear_line(tmp_path, certs):
    ca, cert, key = (str(certs[n]) for n in ("ca.pem", "router.pem", "router.key"))
    tls = (f"tls/127.0.0.1:{free_port()}",)
    cases = [
        (dict(listen=tls), "needs --tls-cert and --tls-key"),
        (dict(listen=tls, tls_cert=cert), "go together"),
        (dict(listen=tls, tls_cert=cert, tls_key=str(tmp_path / "nokey")), "no such file"),
        (dict(listen=("tcp/127.0.0.1:7447",), tls_cert=cert, tls_key=key), "no --listen "
         "endpoint is tls/"),
        (dict(tls_ca=ca), "no endpoint is tls/"),
        (dict(password="secret"), "no user"),
        (dict(user="actor-0"), "has no password"),
        (dict(user="actor 0", password="x"), "must be 1-128 letters"),
    ]
    for fields, message in cases:
        with pytest.raises(ConfigError, match=message):
            NetConfig(**fields)
    NetConfig(listen=tls, tls_cert=cert, tls_key=key, connect=tls, tls_ca=ca)

    users = tmp_path / "users.txt"
    with pytest.raises(ConfigError, match="--acl needs --auth-file"):
        RouterConfig(acl=True)
    write_auth_file(users, {"replay": "x", "eve": "y"})
    with pytest.raises(ConfigError, match="'eve' is not a TPDEB role"):
        RouterConfig(auth_file=str(users), acl=True)
    RouterConfig(auth_file=str(users))  # without rules, any listed user may connect
    os.chmod(users, 0o644)
    with pytest.raises(ConfigError, match="chmod 600"):
        RouterConfig(auth_file=str(users))
    users.write_text("replay\n")
    os.chmod(users, 0o600)
    with pytest.raises(ConfigError, match="line 1: expected USER:PASSWORD"):
        RouterConfig(auth_file=str(users))
    with pytest.raises(ConfigError, match="same protocol"):
        LinkConfig(listen="tcp/127.0.0.1:7448", connect="tls/127.0.0.1:7447")


def test_the_password_comes_from_the_environment_and_is_never_written_out(monkeypatch):
    monkeypatch.setenv("TPDEB_USER", "actor-3")
    monkeypatch.setenv("TPDEB_PASSWORD", "hunter2-secret")
    config = resolve(ActorServiceConfig, ["--actor-id", "3"], "tpdeb-actor", "")
    assert config.user == "actor-3" and config.password == ""
    assert "hunter2-secret" not in to_toml(config) + repr(config)
    settings = security_of(config)
    assert settings.password == "hunter2-secret" and "hunter2" not in repr(settings)


def test_cluster_security_section_and_flags(tmp_path):
    base = (ROOT / "deploy" / "local.toml").read_text()

    def plan(security_lines: str = "", *flags: str):
        path = tmp_path / "cluster.toml"
        path.write_text(base.replace('certs_dir = ""\n', f'certs_dir = ""\n{security_lines}'))
        return make_plan(parse_args(["--cluster-file", str(path), "--run-dir",
                                     str(tmp_path / "run"), *flags]))

    default = plan()
    assert default.endpoint.startswith("tcp/") and not default.security.enabled
    on = plan("", "--tls", "--auth", "--acl")
    assert on.endpoint.startswith("tls/127.0.0.1:") and on.security.acl
    assert plan("", "--tls", "--link-latency-ms", "5").link_endpoint.startswith("tls/")
    assert not plan("", "--tls", "--no-tls").security.tls
    for lines, flags, message in (
            ("", ["--acl"], "acl = true needs auth = true"),
            ("", ["--tls", "--certs-dir", str(tmp_path)], "lacks ca.pem, router.pem, router.key"),
            ("", ["--certs-dir", str(tmp_path)], "is set but tls = false"),
            ("mtls = true\n", [], r"unknown key\(s\) \['mtls'\]"),
            ("", ["--tls", "--endpoint", "udp/127.0.0.1:7447"], "TLS runs over tcp")):
        with pytest.raises(ConfigError, match=message):
            plan(lines, *flags)
