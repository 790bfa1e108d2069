"""`tpdeb-router`: a Zenoh router and nothing else.

The cluster runs it as its own process so that the network outlives every other service: a
replay server or a learner that crashes and restarts finds the router, the actors and their
subscriptions where it left them (Zenoh clients reconnect to a router that comes back, too).
It is also where TLS, authentication and access-control rules are enforced.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from services.config import ConfigError, resolve
from services.service_config import DEFAULT_ENDPOINT, ServiceConfig
from services.zsession import StopSignal, fail, open_for, say

PROG = "tpdeb-router"


@dataclass
class RouterConfig(ServiceConfig):
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints the router listens on (every service connects here)"""
    connect: tuple[str, ...] = ()
    """other routers to connect to (multi-host setups)"""

    def __post_init__(self):
        super().__post_init__()
        if not self.listen:
            raise ConfigError("the router needs at least one --listen endpoint")


def main(argv: list[str] | None = None) -> int:
    try:
        config = resolve(RouterConfig, argv, PROG, "TPDEB router: the Zenoh router of a run.")
        session = open_for(config, "router")
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    say(PROG, f"routing on {', '.join(config.listen)}")
    try:
        while not stop.wait(1.0):
            pass
    finally:
        session.close()
    say(PROG, f"stopped ({stop.reason})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
