"""`tpdeb-router`: a Zenoh router and nothing else.

The cluster runs it as its own process so that the network outlives every other service: a
replay server or a learner that crashes and restarts finds the router, the actors and their
subscriptions where it left them (Zenoh clients reconnect to a router that comes back, too).
It is also where TLS, authentication and access-control rules are enforced.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path

from tpdeb.services.config import ConfigError, resolve
from tpdeb.services.config.service import DEFAULT_ENDPOINT, NetConfig
from tpdeb.services.logs import setup_logging
from tpdeb.services.net.security import access_control, read_auth_file
from tpdeb.services.net.session import StopSignal, close_session, fail, open_for

PROG = "tpdeb-router"
log = logging.getLogger(PROG)


@dataclass
class RouterConfig(NetConfig):
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


def main(argv: list[str] | None = None) -> int:
    setup_logging()
    try:
        config = resolve(RouterConfig, argv, PROG, "TPDEB router: the Zenoh router of a run.")
        setup_logging(config.log_level)
        session = open_for(config, "router")
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    guards = [name for name, on in (("TLS", config.tls_cert), ("user/password", config.auth_file),
                                    ("access control", config.acl)) if on]
    log.info(f"routing on {', '.join(config.listen)}"
              f"{' with ' + ', '.join(guards) if guards else ''}")
    try:
        while not stop.wait(1.0):
            pass
    finally:
        close_session(session, PROG)
    log.info(f"stopped ({stop.reason})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
