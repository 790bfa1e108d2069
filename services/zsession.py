"""Zenoh session setup and the process plumbing every service shares (SPEC §3, "Zenoh facts").

Topology of the embedded default: the replay server opens a `router`-mode session listening on
`--listen`; the learner and the actors open `client` sessions connected to it, so everything
crosses one TCP connection per process (which is also what the link shim needs to throttle).
Multicast scouting is off; nothing is discovered that was not named.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time

import zenoh

from protocol import DecodeError, Keys, RunSpec, decode
from services.config import ConfigError

# A put blocked longer than this closes the transport and loses the data (SPEC §3). Actors
# already bound their outbox, so waiting long here only delays them, it never loses anything.
BLOCK_WAIT_BEFORE_CLOSE_MS = 60_000


def zenoh_config(mode: str, listen: list[str], connect: list[str], connect_timeout_s: float = 60.0,
                 lease_ms: int = 10_000, tcp_buffer_bytes: int = 0):
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                      json.dumps(BLOCK_WAIT_BEFORE_CLOSE_MS * 1000))  # microseconds
    conf.insert_json5("transport/link/tx/lease", json.dumps(lease_ms))
    # Shared memory would carry payloads between processes of one host around the TCP link,
    # past the link shim: every byte must cross the network path it would cross between hosts.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    if tcp_buffer_bytes:
        # On a throttled link the kernel's autotuned send buffer (MBs on loopback) would queue
        # seconds of data ahead of acks and keep-alives; a small one keeps the queue in Zenoh,
        # where priorities apply.
        for option in ("so_sndbuf", "so_rcvbuf"):
            conf.insert_json5(f"transport/link/tcp/{option}", json.dumps(tcp_buffer_bytes))
    if mode == "client":
        # Keep retrying the router for a while: services may start in any order.
        timeout_ms = int(connect_timeout_s * 1e3)
        conf.insert_json5("connect/timeout_ms", json.dumps({"client": timeout_ms}))
        conf.insert_json5("connect/exit_on_failure", json.dumps({"client": True}))
    return conf


def check_endpoints(name: str, endpoints: list[str]) -> None:
    for endpoint in endpoints:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.rpartition(":")
        if proto not in ("tcp", "udp", "tls", "quic") or not host or not port.isdigit():
            raise ConfigError(f"{name}={endpoint!r}: expected PROTO/HOST:PORT, e.g. "
                              "tcp/127.0.0.1:7447")


def open_session(mode: str, listen: list[str], connect: list[str],
                 connect_timeout_s: float = 60.0, tcp_buffer_bytes: int = 0) -> zenoh.Session:
    """Open a session, turning Zenoh's errors into one line a user can act on. A client waits
    up to `connect_timeout_s` for its router (install signal handlers after this returns)."""
    check_endpoints("listen", listen)
    check_endpoints("connect", connect)
    try:
        return zenoh.open(zenoh_config(mode, listen, connect, connect_timeout_s,
                                       tcp_buffer_bytes=tcp_buffer_bytes))
    except zenoh.ZError as exc:
        text = str(exc)
        if listen and ("in use" in text.lower() or "bind" in text.lower()):
            raise ConfigError(f"cannot listen on {', '.join(listen)}: the address is in use or "
                              "not available; pick a free port (--listen)") from None
        if mode == "client":
            raise ConfigError(f"no Zenoh router answered at {', '.join(connect)} within "
                              f"{connect_timeout_s:g} s: start tpdeb-replay (it listens there) or "
                              "fix --connect") from None
        raise ConfigError(f"cannot open a Zenoh session (mode {mode}, listen {listen}, "
                          f"connect {connect}): {text}") from None


def open_for(config, mode: str = "client") -> zenoh.Session:
    """A service's session from its config's listen/connect endpoints."""
    return open_session(mode, list(config.listen), list(config.connect), config.connect_timeout_s,
                        config.tcp_buffer_bytes)


def fail(prog: str, exc: Exception) -> int:
    """One line on stderr, exit status 2: how every service refuses bad settings."""
    print(f"{prog}: error: {exc}", file=sys.stderr, flush=True)
    return 2


class StopSignal:
    """Set by SIGINT/SIGTERM (or by a stop message); services poll or wait on it."""

    def __init__(self):
        self.event = threading.Event()
        self.reason = ""

    def install(self) -> StopSignal:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum, _frame) -> None:
        self.set(signal.Signals(signum).name)

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout_s: float) -> bool:
        return self.event.wait(timeout_s)


class RateLimitedLog:
    """Logs at most one line per `interval_s` per kind, with a count of what was suppressed."""

    def __init__(self, prog: str, interval_s: float = 5.0):
        self.prog, self.interval_s = prog, interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, kind: str, line: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(kind, -1e9) < self.interval_s:
                self._suppressed[kind] = self._suppressed.get(kind, 0) + 1
                return
            self._last[kind] = now
            extra = self._suppressed.pop(kind, 0)
        more = f" (+{extra} more since the last report)" if extra else ""
        print(f"{self.prog}: {line}{more}", file=sys.stderr, flush=True)


def say(prog: str, line: str) -> None:
    print(f"{prog}: {line}", flush=True)


def fetch_spec(session, keys: Keys, timeout_s: float, stop=None) -> RunSpec:
    """Ask the replay server for the run spec until it answers (or `timeout_s` passes)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop:
        for reply in session.get(keys.spec, timeout=2.0):
            if reply.ok is not None:
                try:
                    return decode(reply.ok.payload.to_bytes(), RunSpec)
                except DecodeError as exc:
                    if exc.kind == "version":
                        raise ConfigError(f"the replay server speaks another wire schema: "
                                          f"{exc.detail}; run the same TPDEB version") from None
                    raise ConfigError(f"bad run spec from the replay server: {exc}") from None
        time.sleep(0.2)
    raise ConfigError(f"no replay server answered for run {keys.run_id!r} within {timeout_s:g} s"
                      " (wrong --run-id or --connect?)")
