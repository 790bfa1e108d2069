"""Who may do what on a run's router: Zenoh access-control rules per user, and the password
dictionary the router authenticates them with.

Default deny. Each user name is a role of the run — `replay`, `learner`, `actor-{i}`, `actor`
(a pool: any actor id, for launchers that hand ids out — `--actor-id auto`, a StatefulSet),
`monitor` (a watching session such as the cluster's), `link` (the link shim's stats) — or
`{role}@{run_id}` for a role of another run sharing the router. A user gets exactly the traffic
its role needs, all under tpdeb/{run_id}/: an actor can only publish its own fragments and
stats and hear its own acks (a pool's members, any actor's); nobody but the learner can answer
for the parameters.

The router applies the rules per remote session: `ingress` is what that session sends (puts,
declarations, queries, replies, tokens), `egress` what the router hands it (samples for its
subscribers, queries for its queryables, replies to its queries, others' tokens).
"""

from __future__ import annotations

import os
import re
import secrets
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from tpdeb.protocol import Keys
from tpdeb.protocol.topics import ANY, grants
from tpdeb.services.config import ConfigError


@dataclass(frozen=True)
class Security:
    """The security settings of one Zenoh session (empty strings: not used)."""

    tls_ca: str = ""  # CA certificate a client trusts for tls/ endpoints
    tls_cert: str = ""  # certificate and key a listener presents on tls/ endpoints
    tls_key: str = ""
    user: str = ""  # credentials this session authenticates with
    password: str = ""
    auth_file: str = ""  # a listener's user:password dictionary
    access_control: dict | None = None  # a listener's rules (access_control() below)

    def __repr__(self) -> str:  # never print the password
        shown = {k: ("***" if k == "password" and v else v) for k, v in vars(self).items()}
        return f"Security({', '.join(f'{k}={v!r}' for k, v in shown.items() if v)})"


ROLES = ("replay", "learner", "actor-{i}", "actor", "monitor", "link")
_ACTOR = re.compile(r"actor-(0|[1-9][0-9]{0,9})")
_USER_TEXT = re.compile(r"[A-Za-z0-9_.@-]{1,128}")


def _grants(keys: Keys, role: str) -> list[tuple[str, str, str]]:
    """(message, flow, key expression) triples of one user role, derived from the topic table
    (`tpdeb.protocol.topics`): what it may send into the router (ingress) and what the router
    may hand it (egress)."""
    actor = _ACTOR.fullmatch(role)
    if actor:
        return grants(keys, "actor", int(actor.group(1)))
    if role == "actor":  # the pool: what any actor may do, under one user
        return grants(keys, "actor", ANY)
    if role in ("replay", "learner"):  # a pool too: every replay shard, every learner rank
        return grants(keys, role, ANY)
    if role in ("monitor", "link", "evaluator"):
        return grants(keys, role, 0)
    raise ConfigError(f"user {role!r} is not a TPDEB role: users are {', '.join(ROLES)} "
                      "(or ROLE@RUN_ID for another run on this router)")


def role_of(user: str, run_id: str) -> tuple[str, str]:
    """(role, run id) a user name stands for: `role`, or `role@run_id` for another run."""
    role, sep, other_run = user.partition("@")
    return role, (other_run if sep else run_id)


def access_control(run_id: str, users: Iterable[str]) -> dict:
    """The router's `access_control` config for these users (see the module's docstring):
    default deny, one subject per user name, one policy tying it to its role's rules."""
    rules, subjects, policies = [], [], []
    seen = set()
    for user in users:
        if user in seen:
            raise ConfigError(f"user {user!r} is listed twice")
        seen.add(user)
        role, run = role_of(user, run_id)
        try:
            keys = Keys(run)
        except ValueError as exc:
            raise ConfigError(f"user {user!r}: {exc}") from None
        rule_ids = []
        by_kind: dict[tuple[str, str], list[str]] = {}
        for message, flow, key in _grants(keys, role):
            by_kind.setdefault((message, flow), []).append(key)
        for (message, flow), keyexprs in by_kind.items():
            rule_id = f"{user} {flow} {message}"
            rules.append({"id": rule_id, "permission": "allow", "flows": [flow],
                          "messages": [message], "key_exprs": keyexprs})
            rule_ids.append(rule_id)
        subjects.append({"id": f"user {user}", "usernames": [user]})
        policies.append({"id": f"policy {user}", "rules": rule_ids, "subjects": [f"user {user}"]})
    if not subjects:
        raise ConfigError("access control needs at least one user (the --auth-file is empty)")
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def check_user(user: str, where: str) -> str:
    if not _USER_TEXT.fullmatch(user):
        raise ConfigError(f"{where}: user {user!r} must be 1-128 letters, digits, '_', '.', "
                          "'-', '@'")
    return user


def read_auth_file(path: str | Path) -> dict[str, str]:
    """The router's user:password dictionary, one pair a line; one clear line on a bad one."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"--auth-file {path}: cannot read it ({exc.strerror})") from None
    users: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        where = f"--auth-file {path} line {number}"
        if not sep or not password:
            raise ConfigError(f"{where}: expected USER:PASSWORD")
        check_user(user, where)
        if user in users:
            raise ConfigError(f"{where}: user {user!r} appears twice")
        users[user] = password
    if not users:
        raise ConfigError(f"--auth-file {path}: no USER:PASSWORD line in it")
    return users


def new_passwords(users: Iterable[str]) -> dict[str, str]:
    """A fresh random password per user (URL-safe text: no ':' to confuse the dictionary)."""
    return {check_user(user, "users"): secrets.token_urlsafe(24) for user in users}


def write_auth_file(path: str | Path, passwords: dict[str, str]) -> Path:
    """Write the dictionary readable by its owner only (it holds every password)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write("".join(f"{user}:{password}\n" for user, password in passwords.items()))
    return path


def check_settings(listen, connect, tls_ca: str = "", tls_cert: str = "", tls_key: str = "",
                   user: str = "", password: str = "") -> None:
    """Refuse contradictory or incomplete security settings with one line naming the fix."""
    for name, path in (("tls_ca", tls_ca), ("tls_cert", tls_cert), ("tls_key", tls_key)):
        if path and not Path(path).is_file():
            raise ConfigError(f"{name}={path!r}: no such file (tpdeb-certs DIR writes ca.pem, "
                              "router.pem and router.key)")
    if bool(tls_cert) != bool(tls_key):
        raise ConfigError("--tls-cert and --tls-key go together: give both (the certificate "
                          "and its private key) or neither")
    tls_listen = [e for e in listen if e.startswith("tls/")]
    if tls_listen and not (tls_cert and tls_key):
        raise ConfigError(f"listening on {tls_listen[0]} needs --tls-cert and --tls-key (the "
                          "router's certificate and key, e.g. from tpdeb-certs)")
    if tls_cert and not tls_listen:
        raise ConfigError(f"--tls-cert {tls_cert} is set but no --listen endpoint is tls/… "
                          f"(listen: {', '.join(listen) or 'none'}): listen on tls/HOST:PORT")
    if tls_ca and not any(e.startswith("tls/") for e in (*connect, *listen)):
        raise ConfigError(f"--tls-ca {tls_ca} is set but no endpoint is tls/… (connect: "
                          f"{', '.join(connect) or 'none'}): connect to tls/HOST:PORT")
    if password and not user:
        raise ConfigError("a password is set but no user: set TPDEB_USER too")
    if user and not password:
        raise ConfigError(f"user {user!r} has no password: set TPDEB_PASSWORD (an environment "
                          "variable keeps it out of the process list)")
    if user:
        check_user(user, "TPDEB_USER")


def security_of(config) -> Security:
    """A service config's security settings (fields absent from a config are off); the router's
    rules are built from the users in its --auth-file."""
    auth_file = getattr(config, "auth_file", "")
    rules = None
    if getattr(config, "acl", False):
        rules = access_control(config.run_id, read_auth_file(auth_file))
    return Security(tls_ca=getattr(config, "tls_ca", ""), tls_cert=getattr(config, "tls_cert", ""),
                    tls_key=getattr(config, "tls_key", ""), user=getattr(config, "user", ""),
                    password=getattr(config, "secret_password", "")
                    or getattr(config, "password", ""), auth_file=auth_file,
                    access_control=rules)


SECURITY_KEYS = ("tls", "auth", "acl", "certs_dir")


@dataclass
class ClusterSecurity:
    """A cluster file's [security] section (flags on top) and what it makes: certificates, a
    password per user in a dictionary only the router reads, and each service's share of it.
    Secrets reach services through their environment, never their command line."""

    tls: bool = False
    auth: bool = False
    acl: bool = False
    certs_dir: str = ""  # ca.pem, router.pem, router.key; empty: made in {run_dir}/security
    passwords: dict[str, str] | None = field(default=None, repr=False)  # by user, once prepared
    auth_file: Path | None = None
    certs: dict[str, Path] | None = None

    @classmethod
    def from_section(cls, section: dict, flags: dict, where: str) -> ClusterSecurity:
        unknown = set(section) - set(SECURITY_KEYS)
        if unknown:
            raise ConfigError(f"{where} [security]: unknown key(s) {sorted(unknown)}; known: "
                              f"{list(SECURITY_KEYS)}")
        values = {**section, **{k: v for k, v in flags.items() if v is not None}}
        for key in ("tls", "auth", "acl"):
            if not isinstance(values.get(key, False), bool):
                raise ConfigError(f"{where} [security] {key}={values[key]!r}: expected true or "
                                  "false")
        if not isinstance(values.get("certs_dir", ""), str):
            raise ConfigError(f"{where} [security] certs_dir={values['certs_dir']!r}: expected "
                              "a directory path (\"\": generate certificates in the run dir)")
        security = cls(**values)
        if security.acl and not security.auth:
            raise ConfigError("[security] acl = true needs auth = true (--auth): access rules "
                              "are per authenticated user")
        if security.certs_dir:
            if not security.tls:
                raise ConfigError(f"[security] certs_dir={security.certs_dir!r} is set but tls "
                                  "= false: set tls = true (--tls) or leave certs_dir empty")
            missing = [n for n in ("ca.pem", "router.pem", "router.key")
                       if not (Path(security.certs_dir) / n).is_file()]
            if missing:
                raise ConfigError(f"[security] certs_dir={security.certs_dir!r} lacks "
                                  f"{', '.join(missing)}: run tpdeb-certs {security.certs_dir} "
                                  "(or leave certs_dir empty to generate them per run)")
        return security

    @property
    def enabled(self) -> bool:
        return self.tls or self.auth

    def endpoint(self, endpoint: str) -> str:
        """The cluster's endpoint under this setting: tls/… when TLS is on."""
        proto, _, address = endpoint.partition("/")
        if not self.tls or proto == "tls":
            return endpoint
        if proto != "tcp":
            raise ConfigError(f"endpoint {endpoint!r}: TLS runs over tcp; use tls/{address}")
        if not self.certs_dir:  # the certificate made for the run names this host
            from tpdeb.services.net.certs import parse_hosts

            parse_hosts([address.rpartition(":")[0].strip("[]")], f"endpoint {endpoint}")
        return f"tls/{address}"

    def prepare(self, directory: Path, users: Iterable[str], hosts: Iterable[str]) -> None:
        """Certificates (unless certs_dir names them) and the password dictionary, in
        `directory` (the run dir's security/, readable by its owner only)."""
        from tpdeb.services.net.certs import FILES, write_certs

        directory.mkdir(parents=True, exist_ok=True)
        directory.chmod(0o700)
        if self.tls:
            source = Path(self.certs_dir) if self.certs_dir else directory
            if not self.certs_dir and not all((directory / n).is_file() for n in FILES):
                write_certs(directory, list(dict.fromkeys(hosts)), force=True)
            self.certs = {n: source / n for n in ("ca.pem", "router.pem", "router.key")}
        if self.auth:
            self.passwords = new_passwords(users)
            self.auth_file = write_auth_file(directory / "users.txt", self.passwords)

    def router_args(self) -> list[str]:
        args = []
        if self.certs:
            args += ["--tls-cert", str(self.certs["router.pem"]),
                     "--tls-key", str(self.certs["router.key"])]
        if self.auth_file:
            args += ["--auth-file", str(self.auth_file)]
        if self.acl:
            args += ["--acl", "true"]
        return args

    def env(self, user: str) -> dict[str, str]:
        """A service's TPDEB_* variables: its credentials and the CA it trusts. The router
        (user "") needs neither: it checks the others."""
        env = {}
        if not user:
            return env
        if self.certs:
            env["TPDEB_TLS_CA"] = str(self.certs["ca.pem"])
        if self.passwords:
            env["TPDEB_USER"], env["TPDEB_PASSWORD"] = user, self.passwords[user]
        return env

    def session(self, user: str) -> Security:
        """Settings of a session the cluster opens itself (as `monitor`)."""
        env = self.env(user)
        return Security(tls_ca=env.get("TPDEB_TLS_CA", ""), user=env.get("TPDEB_USER", ""),
                        password=env.get("TPDEB_PASSWORD", ""))

    def summary(self) -> dict:
        return {"tls": self.tls, "auth": self.auth, "acl": self.acl,
                "certs_dir": str(self.certs["ca.pem"].parent) if self.certs else ""}
