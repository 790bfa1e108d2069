"""`tpdeb-router`: a Zenoh router and nothing else.

The cluster runs it as its own process so that the network outlives every other service: a
replay server or a learner that crashes and restarts finds the router, the actors and their
subscriptions where it left them (Zenoh clients reconnect to a router that comes back, too).
It is also where TLS, authentication and access-control rules are enforced.
"""

from __future__ import annotations

import logging
import sys

from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import RouterConfig
from tpdeb.services.net.session import close_session, open_for
from tpdeb.services.process import StopSignal, configure, fail

PROG = "tpdeb-router"
log = logging.getLogger(PROG)


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(RouterConfig, argv, PROG, "TPDEB router: the Zenoh router of a run.")
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
