"""`tpdeb-link`: a constrained actor ↔ learner-side link (DESIGN §4), as a TCP bridge.

Actors connect to the link's `--listen` endpoint instead of the router; the link connects each
of them on to the router (`--connect`). Zenoh runs over TCP, so the services need no change to
run behind it, and everything that crosses (trajectories up; parameters, acks and keep-alives
down) is shaped. Per direction, one token bucket shared by all connections sets the rate, and
each chunk is held for the one-way latency (± jitter, never reordered). Nothing is dropped:
when a direction's queue is full the link stops reading, TCP's window closes, and the sender
feels back-pressure. Buffers are bounded in time (`queue_ms` at the configured rate) so Zenoh's
keep-alives are never queued behind more than that.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import signal
import socket
import sys
import time
from dataclasses import dataclass

from tpdeb.services.config import ConfigError
from tpdeb.services.net.security import Security, check_settings
from tpdeb.services.net.session import check_endpoints, declare_publisher
from tpdeb.services.process import configure, fail

PROG = "tpdeb-link"
log = logging.getLogger(PROG)
UNLIMITED_CHUNK = 64 * 1024


@dataclass
class LinkConfig:
    """The link's settings (its own: it bridges bytes and opens no service session)."""

    SECTION = "link"

    listen: str = "tcp/127.0.0.1:7448"
    """actor-side endpoint this link listens on (actors --connect here)"""
    connect: str = "tcp/127.0.0.1:7447"
    """learner-side endpoint (the replay server's router) every connection is bridged to"""
    up_bytes_per_s: float = 0.0
    """actor → learner rate in bytes/s (0: unlimited)"""
    down_bytes_per_s: float = 0.0
    """learner → actor rate in bytes/s (0: unlimited)"""
    latency_ms: float = 0.0
    """one-way delay added in each direction"""
    jitter_ms: float = 0.0
    """random extra delay in [0, jitter_ms] per chunk (order is kept, as on a TCP path)"""
    queue_ms: float = 500.0
    """most data held per direction, as time at the configured rate (bounds added delay)"""
    burst_bytes: int = 0
    """token-bucket depth; 0 picks 10 ms of the rate (at least 1,500 bytes)"""
    run_id: str = "default"
    """run whose stats key (stats/link/0) the link reports on"""
    publish_stats: bool = True
    """publish achieved rates over Zenoh to the learner-side router (the learner logs link/*)"""
    stats_interval_s: float = 1.0
    """seconds between stats reports"""
    tls_ca: str = ""
    """CA certificate the stats session trusts when --connect is tls/… (the bridged bytes
    pass through untouched: TLS runs end to end between actors and the router)"""
    user: str = ""
    """user the stats session authenticates with (under access control: link)"""
    password: str = ""
    """password of --user: set it as TPDEB_PASSWORD, not as a flag (argv shows in ps)"""

    def __post_init__(self):
        check_endpoints("listen", [self.listen])
        check_endpoints("connect", [self.connect])
        if self.listen.partition("/")[0] != self.connect.partition("/")[0]:
            raise ConfigError(f"listen={self.listen} and connect={self.connect}: the link "
                              "forwards bytes unchanged, so both must use the same protocol")
        check_settings([], [self.connect], self.tls_ca, user=self.user, password=self.password)
        for name in ("up_bytes_per_s", "down_bytes_per_s", "latency_ms", "jitter_ms"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name}={getattr(self, name)}: must be ≥ 0 (0 = off)")
        if self.queue_ms <= 0:
            raise ConfigError(f"queue_ms={self.queue_ms}: must be > 0")


def host_port(endpoint: str) -> tuple[str, int]:
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    return host.strip("[]"), int(port)


class TokenBucket:
    """Rate limiter with debt: taking n bytes may overdraw, and the caller then waits until the
    debt is paid, so the long-run rate is exact whatever the chunk sizes."""

    def __init__(self, rate: float, burst: float):
        self.rate, self.burst = rate, burst
        self.tokens = burst
        self.stamp = time.monotonic()

    def take(self, n: int) -> float:
        now = time.monotonic()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        self.tokens -= n
        return max(0.0, -self.tokens / self.rate)


class Direction:
    """One way of the link: its rate, delay, bounds and counters, shared by all connections."""

    def __init__(self, name: str, rate: float, config: LinkConfig):
        self.name, self.rate = name, rate
        burst = config.burst_bytes or max(1500.0, rate * 0.01)
        self.bucket = TokenBucket(rate, burst) if rate > 0 else None
        self.latency_s, self.jitter_s = config.latency_ms / 1e3, config.jitter_ms / 1e3
        self.chunk = int(min(UNLIMITED_CHUNK, max(1024, rate * 0.01))) if rate else UNLIMITED_CHUNK
        self.max_queue = int(max(4 * self.chunk, rate * config.queue_ms / 1e3)) if rate \
            else 4 * 2**20
        self.delivered = 0
        self.queued = 0
        self.delay_sum_s = 0.0
        self.chunks = 0

    def due(self, previous: float) -> float:
        extra = random.uniform(0.0, self.jitter_s) if self.jitter_s else 0.0
        return max(previous, time.monotonic() + self.latency_s + extra)

    async def pace(self, n: int) -> None:
        if self.bucket is not None:
            wait = self.bucket.take(n)
            if wait > 0:
                await asyncio.sleep(wait)


async def pump(reader, writer, direction: Direction) -> None:
    """Copy one TCP stream to another through `direction`, with a bounded queue in between."""
    queue: asyncio.Queue = asyncio.Queue()
    room = asyncio.Event()
    room.set()
    own = {"queued": 0}

    async def read_side() -> None:
        last_due = 0.0
        while True:
            await room.wait()
            data = await reader.read(direction.chunk)
            if not data:
                await queue.put(None)
                return
            last_due = direction.due(last_due)
            await queue.put((last_due, time.monotonic(), data))
            own["queued"] += len(data)
            direction.queued += len(data)
            if own["queued"] >= direction.max_queue:
                room.clear()  # stop reading: TCP's window closes, the sender waits

    async def write_side() -> None:
        while True:
            item = await queue.get()
            if item is None:
                with contextlib.suppress(OSError):
                    writer.write_eof()
                return
            due, read_at, data = item
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            await direction.pace(len(data))
            writer.write(data)
            await writer.drain()
            own["queued"] -= len(data)
            direction.queued -= len(data)
            direction.delivered += len(data)
            direction.delay_sum_s += time.monotonic() - read_at
            direction.chunks += 1
            if own["queued"] < direction.max_queue:
                room.set()

    tasks = [asyncio.create_task(read_side()), asyncio.create_task(write_side())]
    try:
        await asyncio.gather(*tasks)
    finally:  # one side failed or the connection is being closed: end the other, and wait
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


def receive_buffer(direction: Direction) -> int | None:
    """SO_RCVBUF for sockets the link reads `direction` from: small for a throttled direction,
    so data waits in the sender (which then feels back-pressure) rather than in our kernel."""
    return max(16384, direction.chunk * 4) if direction.rate else None


def bound_socket(family: int, rcvbuf: int | None) -> socket.socket:
    # Set before listen/connect: the TCP window scale is agreed in the handshake.
    sock = socket.socket(family, socket.SOCK_STREAM)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    return sock


async def connect(endpoint: str, rcvbuf: int | None):
    """A stream pair to `endpoint` whose socket has `rcvbuf` set before connecting; on failure
    or cancellation the socket is closed here, not left to the garbage collector."""
    host, port = host_port(endpoint)
    info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    sock = bound_socket(info[0], rcvbuf)
    try:
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, info[4])
        return await asyncio.open_connection(sock=sock)
    except BaseException:
        sock.close()
        raise


class Link:
    def __init__(self, config: LinkConfig):
        self.config = config
        self.up = Direction("up", config.up_bytes_per_s, config)
        self.down = Direction("down", config.down_bytes_per_s, config)
        self.connections = 0
        # Each connection's task, held here: the event loop holds tasks weakly, and a
        # connection whose sockets all wait could otherwise be collected mid-flight.
        self.tasks: set[asyncio.Task] = set()

    def accept(self, actor_reader, actor_writer) -> None:
        """The server's callback for a new actor connection: bridge it in a task of our own."""
        task = asyncio.get_running_loop().create_task(self.handle(actor_reader, actor_writer))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def close(self) -> None:
        """End every connection (both sockets closed) and wait until each has."""
        for task in list(self.tasks):
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)

    async def handle(self, actor_reader, actor_writer) -> None:
        try:
            router_reader, router_writer = await connect(self.config.connect,
                                                         receive_buffer(self.down))
        except OSError as exc:
            log.info(f"cannot reach the router at {self.config.connect} ({exc.strerror}): is "
                      "tpdeb-replay running there? (normal while a run is shutting down)")
            actor_writer.close()
            return
        except asyncio.CancelledError:  # the link stops while this one is still connecting
            actor_writer.close()
            raise
        self.connections += 1
        try:
            await asyncio.gather(pump(actor_reader, router_writer, self.up),
                                 pump(router_reader, actor_writer, self.down),
                                 return_exceptions=True)
        finally:
            self.connections -= 1
            for w in (actor_writer, router_writer):
                w.close()

    def stats(self, previous: dict, interval_s: float) -> dict:
        values = {"connections": self.connections,
                  "queue_bytes": self.up.queued + self.down.queued,
                  "up_bytes_total": self.up.delivered, "down_bytes_total": self.down.delivered}
        for d in (self.up, self.down):
            values[f"{d.name}_bytes_per_s"] = (
                d.delivered - previous.get(f"{d.name}_bytes_total", 0)) / interval_s
        chunks = self.up.chunks + self.down.chunks - previous.get("_chunks", 0)
        delay = self.up.delay_sum_s + self.down.delay_sum_s - previous.get("_delay_s", 0.0)
        if chunks:
            values["latency_ms"] = 1e3 * delay / chunks
        values["_chunks"] = self.up.chunks + self.down.chunks
        values["_delay_s"] = self.up.delay_sum_s + self.down.delay_sum_s
        return values


async def serve(config: LinkConfig, stop: asyncio.Event, report) -> None:
    link = Link(config)
    host, port = host_port(config.listen)
    try:
        info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = bound_socket(info[0], receive_buffer(link.up))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(info[4])
        server = await asyncio.start_server(link.accept, sock=sock)
    except OSError as exc:
        raise ConfigError(f"cannot listen on {config.listen}: {exc.strerror}; pick a free port "
                          "(--listen)") from None
    rates = " ".join(f"{d.name} {d.rate:,.0f} B/s" if d.rate else f"{d.name} unlimited"
                     for d in (link.up, link.down))
    log.info(f"{config.listen} ⇄ {config.connect}: {rates}, latency {config.latency_ms:g} ms "
              f"± {config.jitter_ms:g} ms")
    previous: dict = {}
    last = time.monotonic()
    async with server:
        while not stop.is_set():
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), config.stats_interval_s)
            now = time.monotonic()
            previous = link.stats(previous, now - last)
            last = now
            report({k: v for k, v in previous.items() if not k.startswith("_")})
        server.close()  # no new connections, then end the open ones
        await link.close()


def stats_reporter(config: LinkConfig):
    """Publish the link's figures as Stats(role="link") through the learner-side router."""
    if not config.publish_stats:
        return (lambda values: None), (lambda: None)
    import numpy as np

    from tpdeb.protocol import Keys, Stats, encode
    from tpdeb.services.net.session import open_session

    session = open_session("client", [], [config.connect], 60.0, security=Security(
        tls_ca=config.tls_ca, user=config.user, password=config.password))
    publisher = declare_publisher(session, "stats", Keys(config.run_id).stats("link", 0))

    def report(values: dict) -> None:
        publisher.put(encode(Stats(role="link", ident="0", values=values,
                                   episode_returns=np.zeros(0),
                                   episode_lengths=np.zeros(0, np.int64))))

    return report, session.close


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(LinkConfig, argv, PROG,
                           "Throttled TCP bridge between actors and the learner-side router.")
        report, close = stats_reporter(config)
    except ConfigError as exc:
        return fail(PROG, exc)
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        loop.run_until_complete(serve(config, stop, report))
    except ConfigError as exc:
        return fail(PROG, exc)
    finally:
        close()
        loop.close()
    log.info("stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
