"""The services' transport in memory: the part of a Zenoh session they use (publishers,
subscribers, queryables, queries, liveliness tokens), delivered inside one process.

The replay server, the learner service and the actor take a session; a `MemoryBus` session
stands in for Zenoh's wherever the wire is not the point — fast in-process tests of de-dup,
acknowledgements and not-ready replies, and running the services' own objects together in one
process. Delivery is synchronous: a put calls every matching subscriber's callback before it
returns, as Zenoh's callbacks would (the services' callbacks only enqueue). Query replies are
collected until every queryable has answered or dropped its query, or the timeout passes.
Payloads are bytes in both directions, exactly what crosses the wire.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import zenoh


def matches(pattern: str, key: str) -> bool:
    """Zenoh's key-expression match of `pattern` against a concrete `key`: `*` is one chunk,
    `**` any number of chunks (also none)."""
    return _match(pattern.split("/"), key.split("/"))


def _match(pattern: list[str], key: list[str]) -> bool:
    if not pattern:
        return not key
    head, rest = pattern[0], pattern[1:]
    if head == "**":
        return any(_match(rest, key[i:]) for i in range(len(key) + 1))
    return bool(key) and (head == "*" or head == key[0]) and _match(rest, key[1:])


class _Bytes:
    """What `sample.payload` is to the services: something with `to_bytes()` (and `as_shm()`,
    None: nothing in one process goes through shared memory)."""

    def __init__(self, data: bytes):
        self._data = bytes(data)

    def to_bytes(self) -> bytes:
        return self._data

    def as_shm(self) -> None:
        return None


class MemorySample:
    def __init__(self, key_expr: str, payload: _Bytes, kind=zenoh.SampleKind.PUT):
        self.key_expr, self.payload, self.kind = key_expr, payload, kind


@dataclass
class MemoryReply:
    ok: MemorySample | None
    err: object = None


class MemoryQuery:
    """A query as a queryable sees it: answered with `reply` (any number of times), finished
    with `drop` (a queryable must do one or the other, as with Zenoh)."""

    def __init__(self, selector: str, payload: bytes | None, replies: queue.Queue):
        key, _, params = selector.partition("?")
        self.key_expr = key
        self.selector = selector
        self.payload = _Bytes(payload) if payload is not None else None
        self.parameters = dict(p.split("=", 1) for p in params.split(";") if "=" in p)
        self._replies = replies
        self._done = False

    def reply(self, key: str, data: bytes) -> None:
        if self._done:
            raise zenoh.ZError("the query is finished")
        self._replies.put(MemoryReply(MemorySample(str(key), _Bytes(data))))

    def drop(self) -> None:
        if not self._done:
            self._done = True
            self._replies.put(None)

    def __del__(self) -> None:  # as with Zenoh, a query no one holds any more is finished
        self.drop()


@dataclass
class _Handle:
    undeclare: Callable[[], None]


@dataclass
class _Matching:
    matching: bool


class MemoryPublisher:
    def __init__(self, bus: MemoryBus, key: str, options: dict):
        self.bus, self.key, self.options = bus, key, options

    def put(self, data: bytes) -> None:
        self.bus.put(self.key, data)

    @property
    def matching_status(self) -> _Matching:
        return _Matching(any(matches(p, self.key) for p, _ in self.bus.subscribers()))

    def undeclare(self) -> None:
        pass


@dataclass
class MemoryBus:
    """One in-memory network. `session()` gives each participant its own handle; they all share
    the bus, as Zenoh clients share a router."""

    _subscribers: list = field(default_factory=list)  # (pattern, callback)
    _queryables: list = field(default_factory=list)  # (key expression, callback)
    _tokens: dict = field(default_factory=dict)  # key -> count
    _watchers: list = field(default_factory=list)  # (pattern, callback)
    _lock: threading.RLock = field(default_factory=threading.RLock)
    # Run while a query waits for its replies: in one thread (tpdeb-train) the answering
    # services' loops must get their turn, or the query would wait for itself.
    pump: Callable[[], None] | None = None

    def session(self) -> MemorySession:
        return MemorySession(self)

    def subscribers(self) -> list:
        with self._lock:
            return list(self._subscribers)

    def put(self, key: str, data: bytes) -> None:
        with self._lock:
            targets = [cb for pattern, cb in self._subscribers if matches(pattern, key)]
        for callback in targets:
            callback(MemorySample(key, _Bytes(data)))

    def _add(self, where: list, item) -> _Handle:
        with self._lock:
            where.append(item)

        def undeclare() -> None:
            with self._lock:
                if item in where:
                    where.remove(item)

        return _Handle(undeclare)

    def _token(self, key: str) -> _Handle:
        self._token_change(key, +1)
        done = []

        def undeclare() -> None:
            if not done:
                done.append(True)
                self._token_change(key, -1)

        return _Handle(undeclare)

    def _token_change(self, key: str, delta: int) -> None:
        with self._lock:
            before = self._tokens.get(key, 0)
            self._tokens[key] = before + delta
            edge = (before == 0) if delta > 0 else (before + delta == 0)
            watchers = [cb for pattern, cb in self._watchers if matches(pattern, key)]
        if edge:
            kind = zenoh.SampleKind.PUT if delta > 0 else zenoh.SampleKind.DELETE
            for callback in watchers:
                callback(MemorySample(key, _Bytes(b""), kind))

    def _watch(self, pattern: str, callback, history: bool) -> _Handle:
        handle = self._add(self._watchers, (pattern, callback))
        if history:
            with self._lock:
                live = [k for k, n in self._tokens.items() if n > 0 and matches(pattern, k)]
            for key in live:
                callback(MemorySample(key, _Bytes(b""), zenoh.SampleKind.PUT))
        return handle


class _Liveliness:
    def __init__(self, bus: MemoryBus):
        self.bus = bus

    def declare_token(self, key: str) -> _Handle:
        return self.bus._token(str(key))

    def declare_subscriber(self, keyexpr: str, callback, history: bool = False) -> _Handle:
        return self.bus._watch(str(keyexpr), callback, history)


class MemorySession:
    """The subset of `zenoh.Session` the services use, on a `MemoryBus`."""

    def __init__(self, bus: MemoryBus):
        self.bus = bus

    def declare_publisher(self, key: str, **options) -> MemoryPublisher:
        return MemoryPublisher(self.bus, str(key), options)

    def declare_subscriber(self, keyexpr: str, callback) -> _Handle:
        return self.bus._add(self.bus._subscribers, (str(keyexpr), callback))

    def declare_queryable(self, keyexpr: str, callback) -> _Handle:
        return self.bus._add(self.bus._queryables, (str(keyexpr), callback))

    def liveliness(self) -> _Liveliness:
        return _Liveliness(self.bus)

    def put(self, key: str, data: bytes) -> None:
        self.bus.put(str(key), data)

    def get(self, selector: str, handler=None, payload: bytes | None = None,
            timeout: float = 10.0, cancellation_token=None) -> Iterator[MemoryReply] | None:
        """The replies of every matching queryable, as they come, until each has finished its
        query or `timeout` seconds pass; given a callback `handler` (a `zenoh.handlers.Callback`:
        its callback per reply, its drop when the query ends), they go to it from a thread of
        their own, as Zenoh's would, and nothing is returned."""
        replies = self._replies(selector, payload, timeout)
        if handler is None:
            return replies

        def deliver() -> None:
            for reply in replies:
                handler.callback(reply)
            if handler.drop is not None:
                handler.drop()

        threading.Thread(target=deliver, name="memory-query", daemon=True).start()
        return None

    def _replies(self, selector: str, payload: bytes | None,
                 timeout: float) -> Iterator[MemoryReply]:
        key = str(selector).partition("?")[0]
        with self.bus._lock:
            answerers = [cb for pattern, cb in self.bus._queryables if matches(pattern, key)]
        replies: queue.Queue = queue.Queue()
        for callback in answerers:
            callback(MemoryQuery(str(selector), payload, replies))
        open_queries, deadline = len(answerers), time.monotonic() + timeout
        while open_queries:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            try:
                if self.bus.pump is not None and replies.empty():
                    self.bus.pump()
                    reply = replies.get_nowait()
                else:
                    reply = replies.get(timeout=min(left, 0.05))
            except queue.Empty:
                continue
            if reply is None:
                open_queries -= 1
            else:
                yield reply

    def close(self) -> None:
        """Nothing to release: the bus lives as long as its participants."""
