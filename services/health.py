"""`tpdeb-health ROLE`: exit 0 once that service of the run is up, 1 with the reason otherwise —
a container healthcheck (DESIGN §5). It reads the service's own settings, from the same
`TPDEB_*` variables (or `--config` and flags) the service was started with: the router is up
once its endpoint takes connections (and completes TLS), the replay server, the learner and an
actor once the router holds their liveliness token (asked as the service's own user)."""

from __future__ import annotations

import logging
import sys

from tpdeb.protocol import Keys
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import SERVICE_CONFIGS
from tpdeb.services.net.security import security_of
from tpdeb.services.net.session import open_session, probe_endpoint
from tpdeb.services.process import actor_id_file, configure

PROG = "tpdeb-health"
log = logging.getLogger(PROG)
USAGE = (f"usage: {PROG} {{{','.join(SERVICE_CONFIGS)}}} [--timeout-s S] [the service's flags]"
         " (its TPDEB_* variables are read too)")


def local(endpoint: str) -> str:
    """An endpoint this host can dial: a wildcard listen address becomes loopback."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    host = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]", "": "127.0.0.1"}.get(host, host)
    return f"{proto}/{host}:{port}"


def actor_ident(config) -> str:
    if config.actor_id != "auto":
        return config.actor_id
    path = actor_id_file(config.run_id)
    if not path.is_file():
        raise ConfigError("the actor has not got its id from the replay server yet")
    return path.read_text().strip()


def problem(role: str, config, timeout_s: float) -> str | None:
    """Why `role` is not up (None when it is)."""
    security = security_of(config)
    if role == "router":
        endpoint = local(config.listen[0])
        state = probe_endpoint(endpoint, security, timeout_s)
        return None if state == "up" else f"the router at {endpoint} is {state}"
    ident = {"actor": lambda: actor_ident(config), "replay": lambda: str(config.shard),
             "learner": lambda: str(config.rank)}.get(role, lambda: "0")()  # a shard's, a rank's
    endpoints = list(config.connect) or [local(e) for e in config.listen]
    session = open_session("client", [], endpoints, timeout_s, 0, security)
    try:
        key = Keys(config.run_id).alive(role, ident)
        live = [r for r in session.liveliness().get(key, timeout=timeout_s) if r.ok is not None]
    finally:
        session.close()
    return None if live else f"the router at {', '.join(endpoints)} holds no token {key}"


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in SERVICE_CONFIGS:
        print(USAGE, file=sys.stderr)
        return 2
    role, rest, timeout_s = args[0], args[1:], 5.0
    if "--timeout-s" in rest:
        at = rest.index("--timeout-s")
        try:
            timeout_s = float(rest[at + 1])
        except (IndexError, ValueError):
            timeout_s = 0.0
        if not timeout_s > 0:
            print(f"{PROG}: --timeout-s takes a number of seconds > 0\n{USAGE}", file=sys.stderr)
            return 2
        rest = rest[:at] + rest[at + 2:]
    try:
        config = configure(SERVICE_CONFIGS[role], rest, f"{PROG} {role}", USAGE)
        why = problem(role, config, timeout_s)
    except ConfigError as exc:
        why = str(exc)
    if why:
        log.error(f"{role} is not healthy: {why}")
        return 1
    log.info(f"{role} is up")
    return 0


if __name__ == "__main__":
    sys.exit(main())
